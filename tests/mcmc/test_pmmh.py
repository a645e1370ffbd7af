"""PmMH kernel ([C21] Alg. 1): exactness on a target with a known answer, adaptation, seeding,
Pyro integration, checkpoint/resume; the priors; and the pieces of the PmMH package each alone
(the step-size and covariance adapters, the proposals and their mixture, the kernel's checkpoint
state, format 1).

The known-answer target: a fake likelihood whose estimate is
    log p̂(θ) = ℓ(θ) + s(θ) ε − s(θ)²/2,   ε ~ N(0, 1),
so p̂ is an unbiased estimator of exp ℓ(θ) (log-normal noise, mean-corrected), ℓ a Gaussian
log-likelihood.  With the Gaussian prior the exact posterior is Gaussian in closed form.  A
pseudo-marginal chain must reproduce it whatever the noise; a chain that re-estimates the current
state every step (Monte Carlo within Metropolis) targets something else and is measurably too wide.

Run-until-converged PmMH (:func:`run_pmmh_until`, issue #15 item 1): the chains are extended
block by block from each chain's saved kernel state, so a run that stops at D draws per chain holds
exactly the draws of one fixed run of D draws with the same seed; checkpoints resume bit-exactly
in the middle of a block and between blocks; budgets stop the run and are recorded (their target:
``_NoisyGaussian`` below).
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import scipy.stats
import torch

from accel_bayes.diagnostics import stats as dg_stats
from accel_bayes.errors import UserError
from accel_bayes.inference.mcmc import PMMHKernel, regularized_cov, run_pmmh, run_pmmh_until, warmup_windows
from accel_bayes.inference.mcmc.priors import BoxPrior, GaussianPrior
from accel_bayes.inference.mcmc.adaptation import INIT_BUFFER, RM_DECAY, RM_GAIN, CovarianceAdapter, StepSizeAdapter
from accel_bayes.inference.mcmc.proposals import (MOVE_IND, MOVE_RW, IndependenceProposal, ProposalMixture,
                                                  RandomWalkProposal)
from tests.paths import STORED

D = 6  # 3(A − 1) with A = 3 triads
SIG_PRIOR = 3e-3
F64 = torch.float64


class FakeLikelihood:
    """Unbiased noisy estimator of a Gaussian likelihood in θ (A = 3, reference 0)."""

    A = 3
    reference = 0

    def __init__(self, mu, prec, noise=1.0, noise_slope=0.0):
        self.mu, self.prec, self.noise, self.noise_slope = mu, prec, noise, noise_slope
        self.calls = 0

    def exact(self, theta):
        x = (theta - self.mu).reshape(*theta.shape[:-2], -1)
        return -0.5 * ((x @ self.prec) * x).sum(-1)

    def log_phat(self, positions, generator=None):
        self.calls += 1
        th = positions[..., 1:, :] - positions[..., :1, :]
        s = self.noise + self.noise_slope * torch.tanh(th[..., 0, 0] / 1e-3)
        e = torch.randn(th.shape[:-2], generator=generator, dtype=th.dtype)
        return self.exact(th) + s * e - 0.5 * s * s


def _problem(noise=1.0, noise_slope=0.0, seed=0):
    g = torch.Generator().manual_seed(seed)
    B = torch.randn(D, D, generator=g, dtype=torch.float64)
    lik_cov = (B @ B.T / D + 0.5 * torch.eye(D, dtype=torch.float64)) * 1e-6  # ~1 mm scale
    prec = torch.linalg.inv(lik_cov)
    mu = torch.full((2, 3), 1e-3, dtype=torch.float64)
    prior = GaussianPrior(torch.zeros(3, 3, dtype=torch.float64), std=SIG_PRIOR)
    post_prec = prec + torch.eye(D, dtype=torch.float64) / SIG_PRIOR**2
    post_cov = torch.linalg.inv(post_prec)
    post_mean = post_cov @ (prec @ mu.reshape(-1))
    return FakeLikelihood(mu, prec, noise, noise_slope), prior, post_mean, post_cov


class ReestimatingKernel(PMMHKernel):
    """The classic mistake: re-estimate the current state's likelihood at every step (MCWM)."""

    def _current_log_phat(self):
        return self._estimate(self._theta)


def _moments(run):
    x = run.theta.reshape(-1, D)
    return x.mean(0), x.std(0)


# ---------------------------------------------------------------------------- exactness

def _ess(run):
    import arviz as az

    x = run.theta.reshape(run.num_chains, run.num_samples, D).numpy()
    return torch.as_tensor(np.array([az.ess(x[..., j]) for j in range(D)]))


def _check_exact(run, mean, cov, z_max=4.0, sd_tol=None):
    """Posterior mean within z_max Monte Carlo standard errors (ESS-based) in every coordinate,
    and the average sd ratio within 4 of its standard errors (≈ 1/√(2·ESS) each) of 1."""
    sd = cov.diagonal().sqrt()
    m, s = _moments(run)
    ess = _ess(run)
    z = (m - mean) / (sd / ess.sqrt())
    assert bool((z.abs() < z_max).all()), (z, ess)
    ratio = float((s / sd).mean())
    tol = sd_tol if sd_tol is not None else 4.0 * float((1.0 / (2.0 * ess)).sqrt().mean()) / math.sqrt(D)
    assert abs(ratio - 1.0) < tol, (ratio, tol, ess)
    return ratio


def test_pseudo_marginal_exact_and_reestimation_biased():
    # θ-dependent estimator noise (Var[log p̂] from 0.5 to 1.7) makes exactness non-trivial.
    lik, prior, mean, cov = _problem(noise=1.0, noise_slope=0.3)
    run = run_pmmh(PMMHKernel(lik, prior, seed=11), num_samples=3000, warmup_steps=500, num_chains=3,
                   progress=False)
    ratio = _check_exact(run, mean, cov)
    assert 0.9 < ratio < 1.1
    # re-estimating the current state (MCWM) is not exact: visibly too wide (≈ 1.24 here)
    wrong = run_pmmh(ReestimatingKernel(lik, prior, seed=11), num_samples=2500, warmup_steps=300, num_chains=1,
                     progress=False)
    _, s_w = _moments(wrong)
    assert float((s_w / cov.diagonal().sqrt()).mean()) > 1.12


def test_independence_mixture_exact_with_misspecified_proposal():
    # the independence proposal is centred off the posterior and too narrow in some directions:
    # the MH correction q(θ)/q(θ') must still give the exact posterior
    lik, prior, mean, cov = _problem(noise=0.8)
    sd = cov.diagonal().sqrt()
    bad_mean = (mean + 0.5 * sd).reshape(2, 3)
    bad_cov = torch.diag(cov.diagonal() * torch.tensor([0.7, 1.5, 1.0, 2.0, 0.8, 1.2], dtype=torch.float64))
    k = PMMHKernel(lik, prior, seed=5, independence_prob=0.7, independence_mean=bad_mean, independence_cov=bad_cov,
                   proposal_cov=cov)
    run = run_pmmh(k, num_samples=2000, warmup_steps=300, num_chains=2, progress=False)
    _check_exact(run, mean, cov)
    d = run.diagnostics[0]
    assert 0.0 < d["independence acceptance rate"] < 1.0
    assert bool((run.move == 1).any()) and bool((run.move == 0).any())


def test_cached_estimate_is_kept():
    # exactly one likelihood estimate per proposal (plus one at the start of each chain):
    # the accepted state's log p̂ is never re-estimated
    lik, prior, _, _ = _problem()
    k = PMMHKernel(lik, prior, seed=0)
    run = run_pmmh(k, num_samples=50, warmup_steps=30, num_chains=2, progress=False)
    assert lik.calls == 2 * (1 + 80)
    # a rejected move repeats the state and its cached estimate bit for bit
    same = ~run.accepted[:, 1:]
    assert torch.equal(run.log_phat[:, 1:][same], run.log_phat[:, :-1][same])
    assert torch.equal(run.theta[:, 1:][same], run.theta[:, :-1][same])


# ---------------------------------------------------------------------------- adaptation

@pytest.mark.parametrize("step0", [20.0, 1e-3])
def test_step_size_adaptation_lands_in_paper_range(step0):
    lik, prior, _, cov = _problem(noise=0.7)
    k = PMMHKernel(lik, prior, seed=2, step_size=step0)  # far too large / far too small
    run = run_pmmh(k, num_samples=1500, warmup_steps=1000, num_chains=2, progress=False)
    acc = run.acceptance_rate
    assert torch.all((acc > 0.07) & (acc < 0.23)), acc  # [C21] §III-C: 7–23 %
    # adaptation is frozen after warm-up: one step size for all kept draws
    assert k.step_size == pytest.approx(float(run.step_size[-1]))


def test_warmup_windows_and_regularized_cov():
    assert warmup_windows(100) == []
    w = warmup_windows(1000)
    assert w[0] == 150 + 25 and w[-1] == 800 and w == sorted(set(w))
    g = torch.Generator().manual_seed(0)
    x = torch.randn(500, 4, generator=g, dtype=torch.float64) @ torch.tensor(
        [[1.0, 0.5, 0, 0], [0, 1.0, 0, 0], [0, 0, 2.0, 0], [0, 0, 0, 0.1]], dtype=torch.float64)
    S = regularized_cov(500, x.sum(0), x.T @ x)
    ref = np.cov(x.numpy().T)
    lam = max(0.05, 4 / 500)
    np.testing.assert_allclose(S.numpy(), (1 - lam) * ref + lam * np.diag(np.diag(ref)), rtol=1e-10, atol=1e-14)
    one = x[:1].expand(10, 4)
    assert regularized_cov(10, one.sum(0), one.T @ one) is None  # a stuck chain carries no scale


# ---------------------------------------------------------------------------- seeding

def test_same_seed_same_chain_other_seed_other_chain():
    lik, prior, _, _ = _problem()
    a = run_pmmh(PMMHKernel(lik, prior, seed=7), 100, 100, 2, progress=False)
    b = run_pmmh(PMMHKernel(lik, prior, seed=7), 100, 100, 2, progress=False)
    c = run_pmmh(PMMHKernel(lik, prior, seed=8), 100, 100, 2, progress=False)
    assert torch.equal(a.theta, b.theta) and torch.equal(a.log_phat, b.log_phat)
    assert not torch.equal(a.theta, c.theta)
    assert not torch.equal(a.theta[0], a.theta[1])  # chains have their own streams


def test_runs_under_pyro_mcmc_with_two_chains(capsys, monkeypatch):
    import pyro.infer.mcmc.api as mcmc_api
    from pyro.infer import MCMC

    # With more chains than spare cores (2 cores here) Pyro runs them one after another on one
    # kernel object; pin that behaviour on machines with more cores too.
    monkeypatch.setattr(mcmc_api.mp, "cpu_count", lambda: 2)
    # Pyro hides its progress bar whenever a CI variable is set; this test is about the bar.
    monkeypatch.delenv("CI", raising=False)
    monkeypatch.delenv("PYTEST_XDIST_WORKER", raising=False)
    lik, prior, _, _ = _problem()
    init = prior.sample((2,), generator=torch.Generator().manual_seed(3))
    kernel = PMMHKernel(lik, prior, seed=4)
    with pytest.warns(UserWarning, match="sequentially"):
        mcmc = MCMC(kernel, num_samples=60, warmup_steps=40, num_chains=2, initial_params={"r": init},
                    disable_progbar=False)
    mcmc.run()
    err = capsys.readouterr().err
    assert "acc. rate" in err  # kernel.logging() feeds the progress bar
    r = mcmc.get_samples(group_by_chain=True)["r"]
    assert r.shape == (2, 60, 2, 3)
    diag = mcmc.diagnostics()
    assert "divergences" in diag and "acceptance rate" in diag
    # the driver runs the very same transitions
    ref = run_pmmh(PMMHKernel(lik, prior, seed=4), 60, 40, 2, init, progress=False)
    assert torch.equal(r, ref.theta)


def test_pyro_mcmc_from_prior_draws():
    from pyro.infer import MCMC

    lik, prior, _, _ = _problem()
    mcmc = MCMC(PMMHKernel(lik, prior, seed=4), num_samples=20, warmup_steps=10, disable_progbar=True)
    mcmc.run()
    assert mcmc.get_samples()["r"].shape == (20, 2, 3)


# ---------------------------------------------------------------------------- checkpoints

class _Kill(Exception):
    pass


def test_checkpoint_resume_is_bit_exact(tmp_path):
    lik, prior, _, _ = _problem()
    mk = lambda: PMMHKernel(lik, prior, seed=21, independence_prob=0.3)  # noqa: E731
    W, S, C = 300, 120, 2  # W ≥ 150: covariance windows and independence moments adapt in warm-up
    full = run_pmmh(mk(), S, W, C, progress=False)
    ck = tmp_path / "run.ckpt"
    for stop in [(0, 187), (1, 377)]:  # inside chain 0's warm-up windows; inside chain 1's sampling

        def cb(chain, i, kernel, stop=stop):
            if (chain, i) == stop:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            run_pmmh(mk(), S, W, C, progress=False, checkpoint=ck, checkpoint_every=50, callback=cb,
                     resume=True)
        assert ck.exists()
    resumed = run_pmmh(mk(), S, W, C, progress=False, checkpoint=ck, checkpoint_every=50, resume=True)
    assert resumed.resumed
    for name in ("theta", "log_phat", "log_prior", "accepted", "accept_prob", "move", "step_size", "proposal_cov",
                 "initial"):
        assert torch.equal(getattr(resumed, name), getattr(full, name)), name
    assert resumed.diagnostics == full.diagnostics


def test_resume_refuses_other_settings(tmp_path):
    lik, prior, _, _ = _problem()
    ck = tmp_path / "c.ckpt"
    run_pmmh(PMMHKernel(lik, prior, seed=1), 20, 10, 1, progress=False, checkpoint=ck, checkpoint_every=5)
    with pytest.raises(UserError, match="different settings.*num_samples"):
        run_pmmh(PMMHKernel(lik, prior, seed=1), 30, 10, 1, progress=False, checkpoint=ck, resume=True)
    with pytest.raises(UserError, match="checkpoint_every: needs"):
        run_pmmh(PMMHKernel(lik, prior, seed=1), 30, 10, 1, progress=False, checkpoint_every=5)


# ---------------------------------------------------------------------------- validation

def test_kernel_refuses_bad_settings():
    lik, prior, _, _ = _problem()
    with pytest.raises(ValueError, match="target_accept_prob"):
        PMMHKernel(lik, prior, target_accept_prob=1.5)
    with pytest.raises(ValueError, match="step_size"):
        PMMHKernel(lik, prior, step_size=-1.0)
    with pytest.raises(ValueError, match="proposal_cov"):
        PMMHKernel(lik, prior, proposal_cov=torch.eye(3, dtype=torch.float64))
    with pytest.raises(ValueError, match="independence_prob"):
        PMMHKernel(lik, prior, independence_prob=1.0)
    with pytest.raises(ValueError, match="num_samples"):
        run_pmmh(PMMHKernel(lik, prior), 0, 10, 1, progress=False)


def test_nonfinite_estimate_is_rejected_and_reported():
    lik, prior, _, _ = _problem()

    class Flaky(FakeLikelihood):
        def log_phat(self, positions, generator=None):
            v = super().log_phat(positions, generator)
            return v if self.calls % 5 else torch.tensor(float("nan"), dtype=torch.float64)

    fl = Flaky(lik.mu, lik.prec)
    run = run_pmmh(PMMHKernel(fl, prior, seed=0), 40, 0, 1, progress=False)
    assert len(run.diagnostics[0]["divergences"]) == 8
    assert bool(torch.isfinite(run.log_phat).all())


# ---------------------------------------------------------------------------- priors

def test_gaussian_prior_against_scipy():
    pos = torch.tensor([[1e-3, 2e-3, 0.0], [5e-3, -1e-3, 1e-3], [0.0, 4e-3, -2e-3]], dtype=torch.float64)
    pr = GaussianPrior(pos, std=2e-3, reference=1)
    assert torch.allclose(pr.mean, torch.stack((pos[0] - pos[1], pos[2] - pos[1])))
    th = torch.randn(5, 2, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64) * 1e-3
    ref = scipy.stats.norm(pr.mean.numpy(), 2e-3).logpdf(th.numpy()).sum((-1, -2))
    np.testing.assert_allclose(pr.log_prob(th).numpy(), ref, rtol=1e-12)
    x = pr.sample((20000,), generator=torch.Generator().manual_seed(1))
    assert torch.allclose(x.mean(0), pr.mean, atol=4 * 2e-3 / math.sqrt(20000))
    assert torch.allclose(x.std(0), torch.full((2, 3), 2e-3, dtype=torch.float64), rtol=0.03)
    with pytest.raises(ValueError, match="prior_std"):
        GaussianPrior(pos, std=0.0)


def test_box_prior():
    pos = torch.zeros(3, 3, dtype=torch.float64)
    pos[1, 0] = 0.01
    pr = BoxPrior.with_std(pos, std=1e-3)
    hw = math.sqrt(3) * 1e-3
    inside = pr.mean.clone()
    outside = pr.mean.clone()
    outside[0, 1] += 1.01 * hw
    lp = pr.log_prob(torch.stack((inside, outside)))
    assert float(lp[0]) == pytest.approx(-6 * math.log(2 * hw), rel=1e-12)
    assert float(lp[1]) == float("-inf")
    x = pr.sample((20000,), generator=torch.Generator().manual_seed(2))
    assert bool(torch.isfinite(pr.log_prob(x)).all())
    assert torch.allclose(x.std(0), torch.full((2, 3), 1e-3, dtype=torch.float64), rtol=0.03)
    with pytest.raises(ValueError, match="high > low"):
        BoxPrior(torch.zeros(2, 3), torch.zeros(2, 3))


def test_box_prior_chain_stays_inside():
    lik, _, _, _ = _problem()
    pr = BoxPrior.with_std(torch.zeros(3, 3, dtype=torch.float64), std=1e-3)
    run = run_pmmh(PMMHKernel(lik, pr, seed=3), 300, 200, 1, progress=False)
    assert bool(torch.isfinite(pr.log_prob(run.theta)).all())


def test_step_size_adapter_robbins_monro_and_polyak_average():
    a = StepSizeAdapter(0.2)
    a.setup(10)  # averaging from step 6 (W // 2 = 5, strictly after)
    ls, seen = 0.0, []
    for t, alpha in enumerate([0.0, 1.0, 0.5, 0.2, 0.1, 0.3, 0.0, 0.9, 0.2, 0.4], start=1):
        new = a.update(ls, alpha, t)
        assert new == ls + RM_GAIN / (t ** RM_DECAY) * (alpha - 0.2)
        ls = new
        if t > 5:
            seen.append(ls)
    assert a.final(ls) == sum(seen) / len(seen)
    off = StepSizeAdapter(0.2, enabled=False)
    off.setup(10)
    assert off.update(-1.0, 0.9, 1) == -1.0 and off.final(-1.0) == -1.0


def test_step_size_adapter_restart_resets_gain_and_average():
    a = StepSizeAdapter(0.25)
    a.setup(100)
    for t in range(1, 61):
        a.update(0.0, 0.5, t)
    a.restart(60)  # new phase: gain from k = 1, averaging from 60 + 20
    assert a.update(0.0, 0.75, 61) == RM_GAIN / 2
    assert a.final(7.0) == 7.0  # nothing averaged yet in this phase
    assert a.state_dict()["avg_from"] == 80


def test_covariance_adapter_windows_and_moments():
    W = 200
    ends = warmup_windows(W)
    cov = CovarianceAdapter(2, F64)
    cov.setup(W)
    g = torch.Generator().manual_seed(0)
    draws = torch.randn(W, 2, generator=g, dtype=F64) * torch.tensor([1.0, 3.0], dtype=F64)
    start, got = int(INIT_BUFFER * W), []
    for t in range(1, W + 1):
        if cov.observe(t, draws[t - 1]):
            got.append((t, cov.take()))
    assert [t for t, _ in got] == ends
    # the first window holds the draws after the initial buffer up to its end
    x = draws[start:ends[0]]
    c0, m0 = got[0][1]
    assert torch.allclose(m0, x.mean(0))
    assert torch.allclose(c0, regularized_cov(len(x), x.sum(0), x.T @ x))
    assert cov.state_dict()["win_n"] == 0  # cleared


def test_independence_log_q_is_the_gaussian_log_density_up_to_a_constant():
    g = torch.Generator().manual_seed(1)
    B = torch.randn(6, 6, generator=g, dtype=F64)
    S = B @ B.T + torch.eye(6, dtype=F64)
    mean = torch.randn(2, 3, generator=g, dtype=F64)
    q = IndependenceProposal((2, 3), scale=1.3)
    assert not q.available
    q.set(mean, S)
    ref = torch.distributions.MultivariateNormal(mean.reshape(-1), covariance_matrix=1.3**2 * S)
    a, b = torch.randn(2, 2, 3, generator=g, dtype=F64)
    assert torch.allclose(q.log_q(a) - q.log_q(b), ref.log_prob(a.reshape(-1)) - ref.log_prob(b.reshape(-1)))


def test_mixture_draw_order_and_move_types():
    rw = RandomWalkProposal(torch.eye(6, dtype=F64) * 1e-6, math.log(0.5))
    ind = IndependenceProposal((2, 3), scale=1.0)
    mix = ProposalMixture(rw, ind, independence_prob=0.9)
    theta = torch.zeros(2, 3, dtype=F64)
    # no independence proposal yet: no uniform drawn, only ε
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    prop, lq, mv = mix.propose(theta, g1, warming_up=False)
    eps = torch.randn(6, generator=g2, dtype=F64)
    assert mv == MOVE_RW and lq == 0.0 and torch.equal(prop, rw.propose(theta, eps))
    ind.set(torch.ones(2, 3, dtype=F64), torch.eye(6, dtype=F64))
    moves = [mix.propose(theta, g1, warming_up=w)[2] for w in [True] * 400 + [False] * 400]
    share_warm = sum(m == MOVE_IND for m in moves[:400]) / 400
    share_after = sum(m == MOVE_IND for m in moves[400:]) / 400
    assert 0.4 < share_warm < 0.6 and share_after > 0.83  # capped at 1/2 during warm-up


def test_kernel_state_keys_are_those_of_checkpoint_format_1():
    from tests.mcmc.test_pmmh_reference import _kernels

    old = torch.load(STORED / "pmmh_checkpoint_v1.ckpt", weights_only=True)
    k = _kernels()["adapted"]()
    k.setup(200)
    assert set(k.state_dict()) == set(old["kernel"])


FIELDS = ("theta", "log_phat", "log_prior", "accepted", "accept_prob", "move", "step_size", "proposal_cov",
          "initial")


class _NoisyGaussian:
    """log p̂ = ℓ(θ) + s ε − s²/2, ε ~ N(0, 1) from the kernel's generator (A = 3, reference 0)."""

    A, reference = 3, 0

    def __init__(self, noise=0.8):
        self.noise = noise
        g = torch.Generator().manual_seed(0)
        B = torch.randn(6, 6, generator=g, dtype=torch.float64)
        self.prec = torch.linalg.inv((B @ B.T / 6 + 0.5 * torch.eye(6, dtype=torch.float64)) * 1e-6)
        self.mu = torch.full((2, 3), 1e-3, dtype=torch.float64)

    def log_phat(self, positions, generator=None):
        th = positions[..., 1:, :] - positions[..., :1, :]
        x = (th - self.mu).reshape(*th.shape[:-2], -1)
        e = torch.randn(th.shape[:-2], generator=generator, dtype=th.dtype)
        return -0.5 * ((x @ self.prec) * x).sum(-1) + self.noise * e - 0.5 * self.noise ** 2


def _kernel(seed=3, noise=0.8):
    prior = GaussianPrior(torch.zeros(3, 3, dtype=torch.float64), std=3e-3)
    return PMMHKernel(_NoisyGaussian(noise), prior, seed=seed, independence_prob=0.3)


def _converges_at(n):
    """A check that passes once the chains have n draws (records what it saw)."""
    seen = []

    def check(theta):
        seen.append(int(theta.shape[1]))
        return SimpleNamespace(converged=theta.shape[1] >= n)

    check.seen = seen
    return check


W, C = 160, 2  # W ≥ 150: covariance windows and independence moments adapt in warm-up


def _same(a, b):
    for f in FIELDS:
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_continuation_equals_one_long_run():
    """Stopping after 3 blocks of 70 draws gives exactly the fixed run of 210 draws, and the
    shorter prefixes are those of the fixed runs of 70 and 140 draws."""
    check = _converges_at(210)
    run = run_pmmh_until(_kernel(), check, W, C, check_every=70, max_samples=1000, progress=False)
    assert check.seen == [70, 140, 210] and run.stopped == "converged" and run.num_samples == 210
    assert [c["draws"] for c in run.checks] == [70, 140, 210]
    fixed = run_pmmh(_kernel(), 210, W, C, progress=False)
    _same(run, fixed)
    assert run.diagnostics == fixed.diagnostics
    short = run_pmmh(_kernel(), 70, W, C, progress=False)
    assert torch.equal(short.theta, run.theta[:, :70]) and torch.equal(short.log_phat, run.log_phat[:, :70])


def test_budget_stops_and_last_block_is_shortened():
    check = _converges_at(10 ** 9)
    run = run_pmmh_until(_kernel(), check, W, C, check_every=40, max_samples=100, progress=False)
    assert check.seen == [40, 80, 100] and run.stopped == "max_samples" and run.num_samples == 100
    _same(run, run_pmmh(_kernel(), 100, W, C, progress=False))
    # the wall-clock safety stop is tested after a check (here the first one)
    run = run_pmmh_until(_kernel(), _converges_at(10 ** 9), W, C, check_every=40, max_samples=1000,
                         max_seconds=1e-9, progress=False)
    assert run.stopped == "max_seconds" and run.num_samples == 40 and len(run.checks) == 1


@pytest.mark.parametrize("stop", [(0, 100), (1, 185), (0, 230), (1, 265)],
                         ids=["chain0-warmup", "chain1-block0", "chain0-block1", "chain1-block2"])
def test_resume_is_bit_exact_inside_and_between_blocks(tmp_path, stop):
    ck = tmp_path / "until.ckpt"
    full = run_pmmh_until(_kernel(), _converges_at(150), W, C, check_every=50, max_samples=400, progress=False)
    assert full.num_samples == 150

    def kill(chain, i, kernel):
        if (chain, i) == stop:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_pmmh_until(_kernel(), _converges_at(150), W, C, check_every=50, max_samples=400, progress=False,
                       checkpoint=ck, checkpoint_every=20, callback=kill)
    check = _converges_at(150)
    resumed = run_pmmh_until(_kernel(), check, W, C, check_every=50, max_samples=400, progress=False,
                             checkpoint=ck, checkpoint_every=20, resume=True)
    assert resumed.resumed and resumed.stopped == "converged"
    _same(resumed, full)
    assert resumed.diagnostics == full.diagnostics
    assert [c["draws"] for c in resumed.checks] == [50, 100, 150]
    # a finished run resumes to itself without sampling
    again = run_pmmh_until(_kernel(), check, W, C, check_every=50, max_samples=400, progress=False,
                           checkpoint=ck, resume=True)
    _same(again, full)


def test_resume_with_a_larger_budget_continues_as_one_run(tmp_path):
    ck = tmp_path / "until.ckpt"
    kw = dict(check_every=50, progress=False, checkpoint=ck)
    first = run_pmmh_until(_kernel(), _converges_at(200), W, C, max_samples=120, **kw)
    assert first.stopped == "max_samples" and first.num_samples == 120
    more = run_pmmh_until(_kernel(), _converges_at(200), W, C, max_samples=1000, resume=True, **kw)
    assert more.stopped == "converged" and more.num_samples == 200
    _same(more, run_pmmh_until(_kernel(), _converges_at(200), W, C, check_every=50, max_samples=1000,
                               progress=False))
    # other settings (here: the check interval) are refused
    with pytest.raises(UserError, match="different settings.*check_every"):
        run_pmmh_until(_kernel(), _converges_at(200), W, C, check_every=60, max_samples=1000, progress=False,
                       checkpoint=ck, resume=True)
    # a fixed-length run does not resume a run-until-converged checkpoint, nor the reverse
    with pytest.raises(UserError, match="different settings"):
        run_pmmh(_kernel(), 200, W, C, progress=False, checkpoint=ck, resume=True)


def test_with_the_real_convergence_check():
    """dg_stats.convergence_check as the check (what calibrate uses); the checks are recorded."""
    check = lambda th: dg_stats.convergence_check(th, rhat_max=1.05, ess_min=100)  # noqa: E731
    g = torch.Generator().manual_seed(0)
    init = 1e-3 + 1e-3 * torch.randn(C, 2, 3, generator=g, dtype=torch.float64)  # around the posterior
    run = run_pmmh_until(_kernel(noise=0.1), check, 400, C, init, check_every=200, max_samples=4000,
                         progress=False)
    assert run.stopped == "converged" and run.checks[-1]["converged"] and len(run.checks) >= 2
    assert all(not c["converged"] and c["failed"] for c in run.checks[:-1])
    last = dg_stats.convergence_check(run.theta, rhat_max=1.05, ess_min=100)
    assert last.converged and last.as_dict()["rhat_max"] == run.checks[-1]["rhat_max"]
    # the noisier chains do not get there within a small budget: stopped, with the reasons recorded
    run = run_pmmh_until(_kernel(), check, W, C, check_every=100, max_samples=300, progress=False)
    assert run.stopped == "max_samples" and not run.checks[-1]["converged"]
    assert any("ESS" in f for f in run.checks[-1]["failed"])


def test_progress_reports_each_check(capsys):
    run_pmmh_until(_kernel(), _converges_at(60), W, 1, check_every=30, max_samples=100, progress=True)
    err = capsys.readouterr().err
    assert "check 1:" in err and "continuing" in err and "check 2:" in err and "stopped (converged)" in err


def test_refuses_bad_settings():
    for kw, name in ((dict(check_every=0), "check_every"), (dict(max_samples=0), "max_samples"),
                     (dict(max_seconds=0.0), "max_seconds"), (dict(max_seconds=float("nan")), "max_seconds"),
                     (dict(checkpoint_every=5), "checkpoint_every")):
        with pytest.raises(UserError, match=name):
            run_pmmh_until(_kernel(), _converges_at(1), W, C, progress=False, **kw)
    with pytest.raises(UserError, match="check"):
        run_pmmh_until(_kernel(), None, W, C, progress=False)

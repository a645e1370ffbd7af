"""Correlated pseudo-marginal PmMH (``PMMHKernel(correlation=ρ)``, Deligiannidis, Doucet & Pitt 2018).

The known-answer target is the random-effects model of that paper, one per coordinate of θ
(A = 2 triads, θ (1, 3) m):

    y_tk = θ_k + x_tk + e_tk,   x_tk ~ N(0, s²),  e_tk ~ N(0, σ²),   t = 1..T, k = 1..3,

whose likelihood p(y|θ) = Π N(y_tk; θ_k, s² + σ²) is known in closed form, while the estimator
the chain uses, p̂(y|θ, z) = Π_tk (1/N) Σ_n N(y_tk; θ_k + s z_tkn, σ²), z ~ N(0, I) (T, N, 3), is
unbiased and very noisy at N = 1 (Var[log p̂] ≈ 19 here).  With the Gaussian prior the posterior
of θ is Gaussian in closed form; a CPM chain must reproduce it (mean within 4 Monte Carlo standard
errors from the ESS, sd ratio within 4 of its standard errors), and ρ = 0 must be the fresh-draw
kernel of [C21] bit for bit.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.inference.mcmc import PMMHKernel, run_pmmh, run_pmmh_until
from accel_bayes.inference.mcmc.priors import GaussianPrior
from accel_bayes.model.draw_tuning import choose_correlation

T, S_RE, SIG = 60, 0.3e-3, 1.0e-3  # samples; random-effect and noise std (m)
SIG_PRIOR = 3e-3


class RandomEffects:
    """Unbiased importance-sampling estimator of the random-effects likelihood (module docstring)."""

    A, reference = 2, 0
    dtype, device = torch.float64, torch.device("cpu")

    def __init__(self, num_draws=1, seed=12345):  # a data seed no chain or test uses
        g = torch.Generator().manual_seed(seed)
        self.truth = torch.tensor([1e-3, -5e-4, 2e-4], dtype=torch.float64)
        self.y = (self.truth + math.sqrt(S_RE**2 + SIG**2) * torch.randn(T, 3, generator=g, dtype=torch.float64))
        self.T, self.num_draws = T, int(num_draws)

    def sample_z(self, batch_shape=(), num_draws=None, generator=None):
        N = self.num_draws if num_draws is None else int(num_draws)
        return torch.randn(*tuple(batch_shape), T, N, 3, generator=generator, dtype=torch.float64)

    def log_phat(self, positions, generator=None, z=None):
        th = positions[..., 1, :] - positions[..., 0, :]  # (..., 3)
        if z is None:
            z = self.sample_z((), None, generator)
        r = (self.y[:, None, :] - th[..., None, None, :] - S_RE * z) / SIG  # (..., T, N, 3)
        lw = -0.5 * r * r - math.log(SIG) - 0.5 * math.log(2 * math.pi)
        N = z.shape[-2]
        return (torch.logsumexp(lw, dim=-2) - math.log(N)).sum((-1, -2))

    def posterior(self):
        """Exact posterior mean and sd of θ (3,), m."""
        prec = T / (S_RE**2 + SIG**2) + 1.0 / SIG_PRIOR**2
        mean = (self.y.sum(0) / (S_RE**2 + SIG**2)) / prec
        return mean, torch.full((3,), 1.0 / math.sqrt(prec), dtype=torch.float64)


def _prior():
    return GaussianPrior(torch.zeros(2, 3, dtype=torch.float64), std=SIG_PRIOR)


def _post_cov(lik):
    _, sd = lik.posterior()
    return torch.diag(sd * sd)


def _ess(x):
    import arviz as az

    return np.array([float(az.ess(x[..., j])) for j in range(x.shape[-1])])


def test_cpm_chain_targets_the_exact_posterior():
    lik = RandomEffects(num_draws=1)
    mean, sd = lik.posterior()
    pos = torch.zeros(2, 3, dtype=torch.float64)
    pos[1] = mean
    rho, table = choose_correlation(lik, pos, 1, target=1.0, seed=0)
    assert 0.9 < rho < 1.0 and 0.4 < table[-1]["var"] < 2.5, table
    # fresh draws at N = 1 would be hopeless here: Var[log p̂] at the posterior mean
    v = float(torch.stack([lik.log_phat(pos, generator=torch.Generator().manual_seed(i)) for i in range(40)]).var())
    assert v > 10, v
    cov = _post_cov(lik)
    k = PMMHKernel(lik, _prior(), seed=3, correlation=rho, proposal_cov=cov, independence_prob=0.5,
                   independence_mean=mean.reshape(1, 3), independence_cov=cov)
    run = run_pmmh(k, num_samples=3000, warmup_steps=300, num_chains=2, progress=False)
    x = run.theta.reshape(2, 3000, 3).numpy()
    ess = _ess(x)
    assert (ess > 150).all(), ess
    m = torch.as_tensor(x.reshape(-1, 3).mean(0))
    s = torch.as_tensor(x.reshape(-1, 3).std(0))
    z = (m - mean) / (sd / torch.as_tensor(ess).sqrt())
    assert bool((z.abs() < 4.0).all()), (z, ess)
    ratio = float((s / sd).mean())
    tol = 4.0 * float(np.sqrt(1.0 / (2.0 * ess)).mean()) / math.sqrt(3)
    assert abs(ratio - 1.0) < tol, (ratio, tol, ess)
    # the z moves are part of the kernel: far more accepted than fresh draws at the same N
    fresh = run_pmmh(PMMHKernel(lik, _prior(), seed=3, proposal_cov=cov, independence_prob=0.5,
                                independence_mean=mean.reshape(1, 3), independence_cov=cov),
                     num_samples=500, warmup_steps=100, num_chains=1, progress=False)
    assert float(run.accepted.double().mean()) > 3 * float(fresh.accepted.double().mean())


def test_rho_zero_is_the_fresh_draw_kernel_bit_for_bit():
    lik = RandomEffects(num_draws=3)
    cov = _post_cov(lik)
    a = run_pmmh(PMMHKernel(lik, _prior(), seed=7, proposal_cov=cov, independence_prob=0.3), 80, 160, 2,
                 progress=False)
    b = run_pmmh(PMMHKernel(lik, _prior(), seed=7, proposal_cov=cov, independence_prob=0.3, correlation=0.0), 80,
                 160, 2, progress=False)
    for f in ("theta", "log_phat", "accepted", "accept_prob", "move", "step_size", "proposal_cov"):
        assert torch.equal(getattr(a, f), getattr(b, f)), f
    # ρ > 0 starts from the same numbers (z drawn as log_phat would draw it) and then differs
    c = PMMHKernel(lik, _prior(), seed=7, correlation=0.5)
    d = PMMHKernel(lik, _prior(), seed=7)
    c.setup(10)
    d.setup(10)
    assert torch.equal(c.last.log_phat, d.last.log_phat)
    assert c.state_dict()["z"].shape == (T, 3, 3) and "z" not in d.state_dict()


def test_cpm_checkpoint_resume_is_bit_exact(tmp_path):
    lik = RandomEffects(num_draws=2)
    cov = _post_cov(lik)
    mk = lambda: PMMHKernel(lik, _prior(), seed=21, correlation=0.97, proposal_cov=cov,  # noqa: E731
                            independence_prob=0.3)
    W, S, C = 200, 100, 2
    full = run_pmmh(mk(), S, W, C, progress=False)
    ck = tmp_path / "run.ckpt"
    for stop in [(0, 170), (1, 250)]:

        def cb(chain, i, kernel, stop=stop):
            if (chain, i) == stop:
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            run_pmmh(mk(), S, W, C, progress=False, checkpoint=ck, checkpoint_every=40, callback=cb, resume=True)
    resumed = run_pmmh(mk(), S, W, C, progress=False, checkpoint=ck, checkpoint_every=40, resume=True)
    assert resumed.resumed
    for f in ("theta", "log_phat", "log_prior", "accepted", "accept_prob", "move", "step_size", "proposal_cov"):
        assert torch.equal(getattr(resumed, f), getattr(full, f)), f
    # the until-converged runner keeps each chain's state (z included) between blocks
    never = lambda th: SimpleNamespace(converged=False)  # noqa: E731
    a = run_pmmh_until(mk(), never, 100, 2, check_every=50, max_samples=100, progress=False)
    b = run_pmmh(mk(), 100, 100, 2, progress=False)
    assert torch.equal(a.theta, b.theta) and torch.equal(a.log_phat, b.log_phat)


def test_correlation_refused_when_out_of_range_or_unsupported():
    lik = RandomEffects()
    for bad in (-0.1, 1.0, 1.5, float("nan"), "0.5", True):
        with pytest.raises(UserError, match="correlation"):
            PMMHKernel(lik, _prior(), correlation=bad)

    class NoZ:
        A, reference = 2, 0

        def log_phat(self, positions, generator=None):
            return torch.zeros(positions.shape[:-2], dtype=torch.float64)

    with pytest.raises(UserError, match="correlation"):
        PMMHKernel(NoZ(), _prior(), correlation=0.5)
    # a state saved by a fresh-draw kernel cannot continue as a correlated one
    k0 = PMMHKernel(lik, _prior(), seed=1)
    k0.setup(5)
    k1 = PMMHKernel(lik, _prior(), seed=1, correlation=0.5)
    with pytest.raises(UserError, match="correlation"):
        k1.load_state_dict(k0.state_dict())


def test_choose_correlation_is_seeded_and_hits_its_target():
    lik = RandomEffects(num_draws=1)
    mean, _ = lik.posterior()
    pos = torch.zeros(2, 3, dtype=torch.float64)
    pos[1] = mean
    r1, t1 = choose_correlation(lik, pos, 1, target=2.0, seed=4)
    r2, t2 = choose_correlation(lik, pos, 1, target=2.0, seed=4)
    assert r1 == r2 and t1 == t2
    # 32 pairs: the variance's relative standard error is ≈ 0.25; the linear law is approximate
    assert 0.8 < t1[-1]["var"] < 5.0, t1
    r_small, _ = choose_correlation(lik, pos, 1, target=0.5, seed=4)
    assert r_small > r1  # less noise wanted → more correlation
    with pytest.raises(UserError, match="target"):
        choose_correlation(lik, pos, 1, target=0.0)

"""The per-sample-covariance likelihood (accel_bayes.model.likelihood_percov, issue #30 item 1).

The references are independent of the estimator's algebra: per sample a dense 3A × 3A Gaussian
built from the kinematics (models.specific_force columns for H, no Woodbury identity, no
determinant lemma, no shared factor) — with a proper φ prior the full N(y; Gu, Q + s²DDᵀ + HFHᵀ)
of scipy, with the flat prior the dense weighted projection; the heavy tails against numerical
quadrature over the mixture's scale; the gradient against central finite differences.
"""
import math

import numpy as np
import pytest
import torch
from scipy import integrate, stats

from accel_bayes.errors import UserError
from accel_bayes.model.gyro_posterior import gyro_posterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import (PerSampleCovLikelihood, ages_from_clocks, band_scale,
                                                 with_unresolved_motion)
from accel_bayes.physics.models import specific_force

DT = torch.float64
POS5 = torch.tensor([[0.0, 0.0, 0.0], [0.10, 0.01, 0.0], [0.02, 0.09, 0.01], [0.01, -0.02, 0.08],
                     [0.07, 0.06, -0.03]], dtype=DT)
SIG = 0.3  # m/s²


def _case(T=7, seed=3, jerk=2000.0, age_scale=1e-3, pos=POS5):
    """acc (T, A, 3) with an age-loaded jerk in it, gyro posterior, ages (T, A) s, s (T,) m/s³."""
    g = torch.Generator().manual_seed(seed)
    A = pos.shape[0]
    w = 4 * torch.randn(T, 3, generator=g, dtype=DT)
    wd = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    s = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    age = age_scale * torch.rand(T, A, generator=g, dtype=DT)
    m = jerk * torch.randn(T, 3, generator=g, dtype=DT)
    acc = (specific_force(pos, w, wd, s) - age[..., None] * m[:, None, :]
           + SIG * torch.randn(T, A, 3, generator=g, dtype=DT))
    gyro = w[:, None, :] + 0.05 * torch.randn(T, 4, 3, generator=g, dtype=DT)
    omega = gyro_posterior(gyro, torch.full((4,), 0.05, dtype=DT), "calibrated")
    jerk_std = jerk * (0.5 + torch.rand(T, generator=g, dtype=DT))
    return acc, omega, age, jerk_std


def _kinematic_H(pos):
    """(3A, 6): the specific force of unit ω̇ (ω = 0) and unit s, from models.specific_force."""
    cols = []
    zero = torch.zeros(1, 3, dtype=DT)
    for j in range(6):
        e = torch.zeros(1, 6, dtype=DT)
        e[0, j] = 1
        cols.append(specific_force(pos, zero, e[:, :3], e[:, 3:]).reshape(-1))
    return torch.stack(cols, -1).numpy()


def _dense_sample_logpdfs(pos, acc, omega, age, jerk_std, F=None, lam_scale=1.0):
    """Per sample log p(y_t | ω_t, θ) (T,), all constants included, by dense 3A × 3A algebra.

    F None: flat unit-density prior on φ (the dense projection); else N(0, F) (a plain Gaussian).
    ``lam_scale`` divides every covariance (the scale mixture's λ)."""
    A = pos.shape[0]
    n = 3 * A
    H = _kinematic_H(pos)
    out = []
    for t in range(acc.shape[0]):
        mean = specific_force(pos, omega[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
        r = (acc[t] - mean[0]).reshape(-1).numpy()
        d = (age[t] - age[t].mean()).numpy()
        D = np.kron(d[:, None], np.eye(3))
        Sig = (SIG ** 2 * np.eye(n) + float(jerk_std[t]) ** 2 * D @ D.T) / lam_scale
        out.append(_dense_marginal(r, Sig, H, None if F is None else F / lam_scale))
    return np.array(out)


def _dense_marginal(r, Sig, H, F=None) -> float:
    """log p(r) of r = H φ + ε, ε ~ N(0, Sig), φ integrated out by dense algebra: N(0, F) (a plain
    Gaussian), or F None a flat unit-density prior (the 6 directions of H projected out)."""
    n = r.shape[0]
    if F is not None:
        return float(stats.multivariate_normal(np.zeros(n), Sig + H @ F @ H.T).logpdf(r))
    Si = np.linalg.inv(Sig)
    M = H.T @ Si @ H
    P = Si - Si @ H @ np.linalg.solve(M, H.T @ Si)
    return float(-(n - 6) / 2 * math.log(2 * math.pi) - 0.5 * np.linalg.slogdet(Sig)[1]
                 - 0.5 * np.linalg.slogdet(M)[1] - 0.5 * r @ P @ r)


def _ours(acc, omega, age, jerk_std, nu=None, phi_prior=None, num_draws=3):
    return PerSampleCovLikelihood(acc, omega, SIG, num_draws, age, jerk_std, nu=nu, phi_prior=phi_prior)


@pytest.mark.parametrize("prior", [None, "proper"])
def test_given_omega_equals_the_dense_gaussian_at_two_geometries(prior):
    acc, omega, age, s = _case()
    F = None if prior is None else np.diag([30.0, 20.0, 25.0, 9.0, 16.0, 4.0])
    lik = _ours(acc, omega, age, s, phi_prior=None if F is None else torch.as_tensor(F))
    w = omega.mean + 0.1
    const = lik.T * (-(3 * 5 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG))
    if F is not None:  # the base class omits −½ log|F| and −3 log 2π of the proper prior too
        const += lik.T * (-0.5 * np.linalg.slogdet(F)[1] - 3 * math.log(2 * math.pi))
    for pos in (POS5, POS5 * 1.3):  # row 0 stays the origin (a proper φ prior is not translation invariant)
        want = _dense_sample_logpdfs(pos, acc, w, age, s, F=F).sum()
        got = float(lik.log_lik_given_omega(pos, w)) + const
        assert got == pytest.approx(want, rel=1e-10, abs=1e-8)


@pytest.mark.parametrize("A", [5, 3])
def test_log_phat_equals_the_dense_monte_carlo_average_on_the_same_draws(A):
    """A = 3: C = GᵀSG is singular (rank 3A − 6 = 3), the eigendecomposition factor is used."""
    pos = POS5[:A]
    acc, omega, age, s = _case(T=6, pos=pos)
    s[::3] = 0.0  # samples without the term: the per-sample terms are scattered among the others
    for N in (1, 5, 40):
        lik = _ours(acc, omega, age, s, num_draws=N)
        z = lik.sample_z((), N, torch.Generator().manual_seed(N))
        om = lik.omega_draws(z)  # (T, N, 3)
        per = np.stack([_dense_sample_logpdfs(pos, acc, om[:, n], age, s) for n in range(N)], -1)
        const = lik.T * (-(3 * A - 6) / 2 * math.log(2 * math.pi) - 3 * A * math.log(SIG))
        want = (torch.logsumexp(torch.as_tensor(per), -1) - math.log(N)).sum().item()
        got = float(lik.log_phat(pos, z=z)) + const
        assert got == pytest.approx(want, rel=1e-9, abs=1e-8)
        # a batch of two geometries with one z per geometry agrees with them one by one
        pos2 = torch.stack((pos, pos * 1.1))
        zb = lik.sample_z((2,), N, torch.Generator().manual_seed(7))
        both = lik.log_phat(pos2, z=zb)
        one = torch.stack([lik.log_phat(pos2[i], z=zb[i]) for i in range(2)])
        assert torch.allclose(both, one, rtol=1e-12, atol=1e-9)


@pytest.mark.parametrize("prior", [None, "proper"])
def test_scale_mixture_equals_quadrature_over_the_scale(prior):
    acc, omega, age, s = _case(T=3)
    nu = 4.5
    F = None if prior is None else np.diag([30.0, 20.0, 25.0, 9.0, 16.0, 4.0])
    lik = _ours(acc, omega, age, s, nu=nu, phi_prior=None if F is None else torch.as_tensor(F))
    w = omega.mean - 0.2
    got = float(lik.log_lik_given_omega(POS5, w))
    lik_g = _ours(acc, omega, age, s, phi_prior=None if F is None else torch.as_tensor(F))
    gauss = float(lik_g.log_lik_given_omega(POS5, w))
    dense_g = _dense_sample_logpdfs(POS5, acc, w, age, s, F=F)
    a = nu / 2
    want = 0.0
    for t in range(lik.T):
        def f(lam, t=t):
            return math.exp(_dense_sample_logpdfs(POS5, acc[t:t + 1], w[t:t + 1], age[t:t + 1], s[t:t + 1], F=F,
                                                  lam_scale=lam)[0] - dense_g[t]) * stats.gamma(a, scale=1 / a).pdf(lam)
        val, err = integrate.quad(f, 0, np.inf, limit=200, epsabs=0, epsrel=1e-11)
        want += math.log(val) + dense_g[t]
    # both sides carry the Gaussian's constants: compare against the Gaussian's offset
    assert got - gauss == pytest.approx(want - dense_g.sum(), rel=1e-8, abs=1e-8)
    assert abs(got - gauss) > 0.5  # the tails change the value: the check can fail


def test_zero_scale_equals_the_flat_likelihood_to_1e_10():
    acc, omega, age, s = _case(T=40, seed=8)
    for N in (1, 4, 64):
        flat = RaoBlackwellLikelihood(acc, omega, SIG, N)
        z = flat.sample_z((), N, torch.Generator().manual_seed(1))
        pos = torch.stack((POS5, POS5 * 0.9))
        want = flat.log_phat(pos, z=z)
        zero = with_unresolved_motion(flat, age, 0.0)
        assert len(zero.active) == 0
        assert torch.allclose(zero.log_phat(pos, z=z), want, rtol=0, atol=1e-10)
        # a vanishing but non-zero scale goes through the per-sample path and converges to it
        tiny = with_unresolved_motion(flat, age, s * 1e-9)
        assert len(tiny.active) == 40
        assert torch.allclose(tiny.log_phat(pos, z=z), want, rtol=0, atol=1e-10)
    w = omega.mean + 0.05
    assert float(tiny.log_lik_given_omega(POS5, w)) == pytest.approx(float(flat.log_lik_given_omega(POS5, w)),
                                                                    abs=1e-10)
    # and the term matters at its real size (the check above is not vacuous)
    full = with_unresolved_motion(flat, age, s)
    assert abs(float(full.log_lik_given_omega(POS5, w)) - float(flat.log_lik_given_omega(POS5, w))) > 1.0


def test_gradient_matches_finite_differences():
    acc, omega, age, s = _case(T=10, seed=4)
    for nu in (None, 6.0):
        lik = _ours(acc, omega, age, s, nu=nu, num_draws=5)
        z = lik.sample_z((), 5, torch.Generator().manual_seed(2))
        pos = POS5.clone().requires_grad_(True)
        val = lik.log_phat(pos, z=z)
        (grad,) = torch.autograd.grad(val, pos)
        h = 1e-6
        with torch.no_grad():
            for k, i in ((1, 0), (2, 1), (3, 2), (4, 0)):
                e = torch.zeros_like(POS5)
                e[k, i] = h
                fd = (lik.log_phat(POS5 + e, z=z) - lik.log_phat(POS5 - e, z=z)) / (2 * h)
                assert float(grad[k, i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)
        # the exact given-ω value (what a MAP would climb), in positions and in ω
        w = (omega.mean + 0.1).requires_grad_(True)
        gp, gw = torch.autograd.grad(lik.log_lik_given_omega(pos, w), (pos, w))
        with torch.no_grad():
            e = torch.zeros_like(POS5)
            e[3, 1] = h
            fd = (lik.log_lik_given_omega(POS5 + e, w) - lik.log_lik_given_omega(POS5 - e, w)) / (2 * h)
            assert float(gp[3, 1]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)
            ew = torch.zeros_like(w)
            ew[4, 2] = h
            fd = (lik.log_lik_given_omega(POS5, w + ew) - lik.log_lik_given_omega(POS5, w - ew)) / (2 * h)
            assert float(gw[4, 2]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)


def test_a_moved_copy_keeps_the_terms_and_the_value():
    acc, omega, age, s = _case(T=8, seed=6)
    lik = _ours(acc, omega, age, s, nu=3.0, num_draws=4)
    z = lik.sample_z((), 4, torch.Generator().manual_seed(3))
    want = lik.log_phat(POS5, z=z)
    moved = lik.to("cpu")
    assert isinstance(moved, PerSampleCovLikelihood) and moved.nu == 3.0
    assert not hasattr(moved, "_tf_cache") or moved._tf_cache is None
    assert torch.equal(moved.log_phat(POS5, z=z), want)


def test_inputs_are_checked_and_helpers_map_bands_and_clocks():
    acc, omega, age, s = _case(T=5)
    with pytest.raises(UserError, match="^age: expected shape"):
        _ours(acc, omega, age[:, :3], s)
    with pytest.raises(UserError, match="^jerk_std"):
        _ours(acc, omega, age, -s)
    with pytest.raises(UserError, match="^nu"):
        _ours(acc, omega, age, s, nu=0.0)
    from accel_bayes.model.tempering import TemperedLikelihood
    with pytest.raises(UserError, match="^lik: expected an untempered"):
        with_unresolved_motion(TemperedLikelihood(acc, omega, SIG, 1, 2.0), age, s)
    got = band_scale([0.1, 1.0, 2.5, 9.0], [1.0, 3.0], [10.0, 20.0, 30.0])
    assert got.tolist() == [10.0, 20.0, 20.0, 30.0]
    with pytest.raises(UserError, match="^jerk_rms"):
        band_scale([0.1], [1.0], [1.0])
    from accel_bayes.physics.effects import make_effect
    clock = make_effect("sampling_clock", imu=2, axis=None, parameters={
        "internal_rate_hz": 1000.0, "beat_hz": 0.5, "phase": 0.25, "drift_hz_per_s": 0.0,
        "age_rms_s": 1e-3 / math.sqrt(12), "filter_delay_acc_minus_gyro_s": 2e-4})
    t = torch.tensor([0.0, 0.5, 1.0])
    ages = ages_from_clocks(t, {2: clock}, [0, 2], sensor="acc")
    assert ages[:, 0].tolist() == [0.0, 0.0, 0.0]
    assert ages[:, 1].numpy() == pytest.approx([0.25e-3 + 2e-4, 0.5e-3 + 2e-4, 0.75e-3 + 2e-4], abs=1e-15)


def test_timing_gyro_posterior_is_the_dense_generalised_least_squares():
    from accel_bayes.model.gyro_posterior import gyro_posterior_timing

    g = np.random.default_rng(4)
    T, G = 6, 5
    y = g.normal(size=(T, G, 3))
    std = g.uniform(0.01, 0.05, size=G)
    age = g.uniform(0, 1e-3, size=(T, G))
    s = g.uniform(0, 200.0, size=T)
    got = gyro_posterior_timing(torch.as_tensor(y), torch.as_tensor(std), torch.as_tensor(age), torch.as_tensor(s))
    one = np.kron(np.ones((G, 1)), np.eye(3))
    for t in range(T):
        d = age[t] - age[t].mean()
        cov = np.kron(np.diag(std ** 2) + s[t] ** 2 * np.outer(d, d), np.eye(3))
        P = one.T @ np.linalg.solve(cov, one)
        mean = np.linalg.solve(P, one.T @ np.linalg.solve(cov, y[t].ravel()))
        assert got.mean[t].numpy() == pytest.approx(mean, rel=1e-10, abs=1e-12)
        assert got.cov[t].numpy() == pytest.approx(np.linalg.inv(P), rel=1e-10, abs=1e-16)
    # equal noise: the centred loading is orthogonal to the mean, the calibrated posterior exactly
    eq = gyro_posterior_timing(torch.as_tensor(y), 0.02, torch.as_tensor(age), torch.as_tensor(s))
    cal = gyro_posterior(torch.as_tensor(y), torch.full((G,), 0.02, dtype=DT), "calibrated")
    assert torch.allclose(eq.mean, cal.mean, rtol=1e-12) and torch.allclose(eq.cov, cal.cov, rtol=1e-12)
    assert not torch.allclose(got.cov, gyro_posterior(torch.as_tensor(y), torch.as_tensor(std), "calibrated").cov,
                              rtol=1e-6)


def _clock_report(findings):
    from experiments._reports import minimal_report

    return minimal_report(findings, explanation="test finding")


def test_report_terms_read_clock_ages_and_band_scales(monkeypatch):
    from accel_bayes.data import mismatch_report
    from accel_bayes.model.report_terms import unresolved_terms
    from accel_bayes.physics.effects.clock import clock_age

    if "unresolved_motion" not in mismatch_report.VOCABULARY + mismatch_report.EXTENSIONS:
        # DESIGN §7.2 vocabulary 1.2 names it; the effects library registers it on the detect branch
        monkeypatch.setattr(mismatch_report, "EXTENSIONS", mismatch_report.EXTENSIONS + ("unresolved_motion",))

    clock = {"internal_rate_hz": 1002.5, "beat_hz": -2.5, "phase": 0.3, "drift_hz_per_s": 1e-4,
             "age_rms_s": 0.9e-3 / math.sqrt(12), "filter_delay_acc_minus_gyro_s": 1e-4}
    um = {"omega_edges": [1.0, 2.0], "jerk_rms": [100.0, 200.0, 300.0], "angular_acc_rms": [1.0, 2.0, 3.0]}
    t = torch.linspace(0, 3, 7, dtype=DT)
    wn = torch.tensor([0.5, 1.5, 2.5, 0.1, 1.0, 2.0, 9.0], dtype=DT)
    rep = _clock_report([("sampling_clock", 1, clock), ("unresolved_motion", None, um)])
    got = unresolved_terms(rep, t, [0, 1, 2], [1, 2], wn)
    # the hold's own sawtooth (width 1/f_k), not the fitted 0.9 ms: the loading the report's scales were fitted on
    want1 = clock_age(t, -2.5, 0.3, 1e-4, 1 / 1002.5)
    # IMUs 0 and 2 have no clock: the clocked IMU's mean age (+ its filter delay on acc), not 0
    # (tests/model/test_unclocked.py checks the age prior itself)
    assert torch.allclose(got.age_gyro[:, 0], want1, atol=1e-18) and torch.allclose(got.age_gyro[:, 1], want1.mean())
    assert torch.allclose(got.age_acc[:, 1], want1 + 1e-4, atol=1e-18)
    assert torch.allclose(got.age_acc[:, [0, 2]], want1.mean() + 1e-4)
    assert got.jerk_std.tolist() == [100.0, 200.0, 300.0, 100.0, 200.0, 300.0, 300.0]
    assert got.angular_acc_std.tolist() == [1.0, 2.0, 3.0, 1.0, 2.0, 3.0, 3.0]
    assert [u["effect"] for u in got.used] == ["sampling_clock", "unresolved_motion", "sampling_clock"]
    assert unresolved_terms(_clock_report([("sampling_clock", 1, clock)]), t, [0, 1], [1], wn) is None
    bad = _clock_report([("unresolved_motion", None, {**um, "jerk_rms": [1.0, 2.0]})])
    with pytest.raises(UserError, match=r"^model: findings\[0\]\.parameters\.jerk_rms: expected 3 values"):
        unresolved_terms(bad, t, [0], [0], wn)
    bad = _clock_report([("unresolved_motion", None, {k: v for k, v in um.items() if k != "angular_acc_rms"})])
    with pytest.raises(UserError, match=r"^model: findings\[0\]\.parameters\.angular_acc_rms: missing"):
        unresolved_terms(bad, t, [0], [0], wn)


def test_the_maximum_is_consistent_and_pmmh_runs_on_it():
    """On data drawn from the model (jerk ~5× the noise in the loaded channels), the maximum of the
    exact given-ω likelihood lies within 4 Laplace std of the true geometry on every coordinate; and
    the sampler, which needs only A, reference, sample_z and log_phat(…, z=), runs on it."""
    from accel_bayes.inference.mcmc import PMMHKernel, run_pmmh
    from accel_bayes.inference.mcmc.priors import GaussianPrior

    acc, omega, age, s = _case(T=300, seed=12, jerk=1500.0)
    lik = _ours(acc, omega, age, s, num_draws=2)
    truth = POS5[1:]
    w = omega.mean

    def nll(th):
        return -lik.log_lik_given_omega(torch.cat((POS5[:1], th.reshape(4, 3))), w)

    th = truth.reshape(-1).clone().requires_grad_(True)
    opt = torch.optim.LBFGS([th], max_iter=200, line_search_fn="strong_wolfe", tolerance_grad=1e-9)

    def closure():
        opt.zero_grad()
        loss = nll(th)
        loss.backward()
        return loss

    opt.step(closure)
    H = torch.autograd.functional.hessian(nll, th.detach())
    sd = torch.linalg.inv(H).diagonal().sqrt()
    z = (th.detach() - truth.reshape(-1)) / sd
    assert bool((z.abs() < 4).all()) and float(z.abs().max()) > 0.05, z  # (not stuck at the start)
    k = PMMHKernel(lik, GaussianPrior(POS5 * 0, std=1.0), seed=1, proposal_cov=torch.diag(sd * sd))
    run = run_pmmh(k, num_samples=60, warmup_steps=40, num_chains=1, initial_params=th.detach().reshape(1, 4, 3),
                   progress=False)
    assert bool(torch.isfinite(run.log_phat).all()) and float(run.accepted.double().mean()) > 0.05


def test_flat_value_is_the_beta_limit_of_one_dense_gaussian_over_all_stacked_samples():
    """All T samples' 3A-vectors stacked into one Gaussian (block-diagonal covariance, φ_t with the
    prior N(0, β I₆) integrated out by the dense covariance Σ_t + β H Hᵀ): log N + 3T log(2πβ)
    converges to the flat-prior value as β grows (DESIGN §4's brute-force limit)."""
    from scipy.linalg import block_diag

    acc, omega, age, s = _case(T=5, seed=9)
    lik = _ours(acc, omega, age, s)
    w = omega.mean - 0.1
    got = float(lik.log_lik_given_omega(POS5, w)) + lik.log_constant
    H = _kinematic_H(POS5)
    n = 15
    r, covs = [], []
    for t in range(lik.T):
        mean = specific_force(POS5, w[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
        r.append((acc[t] - mean[0]).reshape(-1).numpy())
        d = (age[t] - age[t].mean()).numpy()
        D = np.kron(d[:, None], np.eye(3))
        covs.append(SIG ** 2 * np.eye(n) + float(s[t]) ** 2 * D @ D.T)
    r = np.concatenate(r)
    errs = []
    for beta in (1e2, 1e5, 1e8):  # the error falls like 1/β
        big = block_diag(*[c + beta * H @ H.T for c in covs])
        Lc = np.linalg.cholesky(big)  # scipy's own check refuses the conditioning at large β
        u = np.linalg.solve(Lc, r)
        logpdf = -0.5 * (len(r) * math.log(2 * math.pi) + 2 * np.log(np.diag(Lc)).sum() + u @ u)
        val = logpdf + 3 * lik.T * math.log(2 * math.pi * beta)
        errs.append(abs(val - got))
    assert errs[-1] < 1e-4 and errs[0] > 10 * errs[-1], errs  # converging to ours, not by accident

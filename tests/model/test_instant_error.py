"""The triads' own sampling-instant error in the per-sample likelihood (issue #30, percov4):
y_kt = … + d_kt m_t + ε_kt ρ_kt + e_kt, ε_kt ~ N(0, e_k²) independent per triad and sample, ρ_kt
the rate of triad k's output (accel_bayes.model.unresolved_cov.instant_error_loadings,
accel_bayes.model.likelihood_percov's general path).

References independent of the estimator's algebra: per sample a dense 3A × 3A covariance
σ²I + s²DDᵀ + blockdiag(e_k² ρ_kt ρ_ktᵀ) built naively and the dense weighted projection (flat φ
prior) or scipy's Gaussian (proper prior); the gradient against central finite differences; the
instant error's scale recovered from data simulated with it (type-II ML).
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood, with_unresolved_motion
from accel_bayes.model.unresolved_cov import instant_error_loadings, loadings, lowrank_terms
from accel_bayes.model.unresolved_fit import fit_unresolved_scales
from accel_bayes.physics.models import specific_force
from tests.model.test_likelihood_percov import POS5, SIG, _case, _dense_marginal, _kinematic_H

DT = torch.float64


def _rate(T, A, seed=11, size=3000.0):
    g = torch.Generator().manual_seed(seed)
    return size * torch.randn(T, A, 3, generator=g, dtype=DT)


def _dense(pos, acc, omega, age, jerk_std, rate, e, F=None):
    """Per sample log p(y_t | ω_t, θ) (T,), constants included, from the naive dense covariance."""
    A = pos.shape[0]
    n = 3 * A
    H = _kinematic_H(pos)
    e = np.broadcast_to(np.asarray(e, dtype=float), (A,))
    out = []
    for t in range(acc.shape[0]):
        mean = specific_force(pos, omega[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
        r = (acc[t] - mean[0]).reshape(-1).numpy()
        d = (age[t] - age[t].mean()).numpy()
        Sig = SIG ** 2 * np.eye(n) + float(jerk_std[t]) ** 2 * np.kron(np.outer(d, d), np.eye(3))
        for k in range(A):
            rho = rate[t, k].numpy()
            Sig[3 * k:3 * k + 3, 3 * k:3 * k + 3] += e[k] ** 2 * np.outer(rho, rho)
        out.append(_dense_marginal(r, Sig, H, F))
    return np.array(out)


@pytest.mark.parametrize("prior", [None, "proper"])
def test_given_omega_equals_the_dense_gaussian_with_the_instant_error(prior):
    acc, omega, age, s = _case(T=6, seed=5)
    rate = _rate(6, 5)
    e = torch.tensor([1e-4, 2e-4, 0.5e-4, 3e-4, 1.5e-4], dtype=DT)
    F = None if prior is None else np.diag([30.0, 20.0, 25.0, 9.0, 16.0, 4.0])
    lik = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, phi_prior=None if F is None else torch.as_tensor(F),
                                 rate=rate, instant_std=e)
    w = omega.mean + 0.1
    const = lik.T * (-(3 * 5 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG))
    if F is not None:
        const += lik.T * (-0.5 * np.linalg.slogdet(F)[1] - 3 * math.log(2 * math.pi))
    for pos in (POS5, POS5 * 1.3):
        want = _dense(pos, acc, w, age, s, rate, e.numpy(), F=F)
        got = float(lik.log_lik_given_omega(pos, w)) + const
        assert got == pytest.approx(want.sum(), rel=1e-10, abs=1e-8)
        per = lik.log_lik_per_sample(pos, w).detach().numpy()
        # per sample too, up to the per-sample share of the constant
        assert np.allclose(per + const / lik.T, want, rtol=1e-10, atol=1e-8)
    # the term is not negligible in this case: without it the value differs
    plain = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, phi_prior=lik.phi_prior)
    assert abs(float(plain.log_lik_given_omega(POS5, w)) - float(lik.log_lik_given_omega(POS5, w))) > 1.0


def test_log_phat_equals_the_dense_monte_carlo_average_and_zero_error_is_the_jerk_model():
    acc, omega, age, s = _case(T=5, seed=9)
    rate = _rate(5, 5, seed=2)
    for N in (1, 7):
        lik = PerSampleCovLikelihood(acc, omega, SIG, N, age, s, rate=rate, instant_std=2e-4)
        z = lik.sample_z((), N, torch.Generator().manual_seed(N))
        om = lik.omega_draws(z)
        per = np.stack([_dense(POS5, acc, om[:, n], age, s, rate, 2e-4) for n in range(N)], -1)
        const = lik.T * (-(15 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG))
        want = (torch.logsumexp(torch.as_tensor(per), -1) - math.log(N)).sum().item()
        assert float(lik.log_phat(POS5, z=z)) + const == pytest.approx(want, rel=1e-9, abs=1e-8)
        # e = 0 through the general path is the jerk-only model (its closed-form path)
        zero = PerSampleCovLikelihood(acc, omega, SIG, N, age, s, rate=rate, instant_std=0.0)
        jerk = PerSampleCovLikelihood(acc, omega, SIG, N, age, s)
        pos = torch.stack((POS5, POS5 * 0.9))
        assert torch.allclose(zero.log_phat(pos, z=z), jerk.log_phat(pos, z=z), rtol=0, atol=1e-9)


def test_lowrank_terms_with_the_instant_error_loading_is_the_dense_gaussian():
    """The detector's residual algebra takes the same loading (one implementation of the physics)."""
    g = torch.Generator().manual_seed(4)
    T, K = 6, 4
    y = torch.randn(T, 3 * K, generator=g, dtype=DT)
    d = 1e-3 * torch.randn(T, K, generator=g, dtype=DT)
    rate = _rate(T, K, seed=5)
    v = 0.5 + torch.rand(T, 3 * K, generator=g, dtype=DT)
    U = torch.cat((loadings(d) * 800.0, instant_error_loadings(rate, 1.0)), -1)
    s2 = torch.cat((torch.ones(T, 3), torch.full((T, K), 3e-4 ** 2)), -1).to(DT)
    quad, logdet = lowrank_terms(y, U, s2, v=v)
    for t in range(T):
        C = np.diag(v[t].numpy()) + U[t].numpy() @ np.diag(s2[t].numpy()) @ U[t].numpy().T
        assert float(quad[t]) == pytest.approx(y[t].numpy() @ np.linalg.solve(C, y[t].numpy()), rel=1e-10)
        assert float(logdet[t]) == pytest.approx(np.linalg.slogdet(C)[1], rel=1e-10)


def test_gradient_matches_finite_differences_in_positions_and_in_the_instant_std():
    acc, omega, age, s = _case(T=8, seed=4)
    rate = _rate(8, 5, seed=3)
    for nu in (None, 5.0):
        lik = PerSampleCovLikelihood(acc, omega, SIG, 4, age, s, nu=nu, rate=rate, instant_std=1.5e-4)
        z = lik.sample_z((), 4, torch.Generator().manual_seed(2))
        pos = POS5.clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(lik.log_phat(pos, z=z), pos)
        h = 1e-6
        with torch.no_grad():
            for k, i in ((1, 0), (2, 1), (4, 2)):
                ep = torch.zeros_like(POS5)
                ep[k, i] = h
                fd = (lik.log_phat(POS5 + ep, z=z) - lik.log_phat(POS5 - ep, z=z)) / (2 * h)
                assert float(grad[k, i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-4)
    # in log e (what the type-II fit climbs)
    base = RaoBlackwellLikelihood(acc, omega, SIG, 1)
    w = omega.mean

    def f(le):
        return with_unresolved_motion(base, age, s, rate=rate, instant_std=torch.exp(le)).log_lik_given_omega(POS5, w)

    le = torch.tensor(math.log(1.5e-4), dtype=DT, requires_grad=True)
    (g,) = torch.autograd.grad(f(le), le)
    h = 1e-5
    with torch.no_grad():
        fd = (f(le + h) - f(le - h)) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=1e-6)
    assert abs(float(g)) > 1e-3  # the check can fail: the value depends on e here


def test_the_instant_error_is_recovered_from_data_that_have_it():
    """Concealed case: data simulated with e = 0.25 ms instant error on ρ (and an age-loaded jerk);
    the type-II fit, not told the value, recovers e within its sampling error, and finds ≈ 0 on
    the same data simulated without it."""
    g = torch.Generator().manual_seed(21)
    T, A = 1500, 5
    pos = POS5
    w = 4 * torch.randn(T, 3, generator=g, dtype=DT)
    wd = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    sf = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    age = 1e-3 * torch.rand(T, A, generator=g, dtype=DT)
    jerk = 400.0
    m = jerk * torch.randn(T, 3, generator=g, dtype=DT)
    rate = 2000 * torch.randn(T, A, 3, generator=g, dtype=DT)
    eps = 2.5e-4 * torch.randn(T, A, generator=g, dtype=DT)
    noise = SIG * torch.randn(T, A, 3, generator=g, dtype=DT)
    clean = specific_force(pos, w, wd, sf) - age[..., None] * m[:, None, :] + noise
    from accel_bayes.model.gyro_posterior import gyro_posterior
    gyro = w[:, None, :] + 0.02 * torch.randn(T, 4, 3, generator=g, dtype=DT)
    omega = gyro_posterior(gyro, torch.full((4,), 0.02, dtype=DT), "calibrated")
    band = torch.zeros(T, dtype=torch.long)
    got = {}
    for label, acc in (("with", clean + eps[..., None] * rate), ("without", clean)):
        base = RaoBlackwellLikelihood(acc, omega, SIG, 1)
        fit = fit_unresolved_scales(base, age, band, pos, w, rate=rate, fit_instant=True)
        got[label] = fit
    e = got["with"].instant_std
    assert abs(e - 2.5e-4) < 0.15e-4, e  # ~ 3 % sampling error with 7500 triad-samples
    assert got["without"].instant_std < 0.3e-4
    assert got["with"].gain_instant > 100.0 and got["without"].gain_instant < 5.0


def test_inputs_are_checked():
    acc, omega, age, s = _case(T=5)
    with pytest.raises(UserError, match="^rate, instant_std"):
        PerSampleCovLikelihood(acc, omega, SIG, 1, age, s, rate=_rate(5, 5))
    with pytest.raises(UserError, match="^rate: expected"):
        PerSampleCovLikelihood(acc, omega, SIG, 1, age, s, rate=_rate(5, 4), instant_std=1e-4)
    with pytest.raises(UserError, match="^instant_std"):
        PerSampleCovLikelihood(acc, omega, SIG, 1, age, s, rate=_rate(5, 5), instant_std=-1.0)

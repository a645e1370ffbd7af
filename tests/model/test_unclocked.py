"""IMUs a mismatch report leaves without a sampling clock (issue #30): their data age is not 0 but
unknown — uniform over the register hold [0, 1/f) plus the acc − gyro filter delay — so
``unresolved_terms`` gives them the expected age and its variance, and the per-sample likelihood
loads the unresolved jerk and angular jerk on that triad through the random age
(``accel_bayes.model.unresolved_cov.age_prior_blocks``).

References independent of the estimator's algebra: the covariance of d_kt (m_t + ω̈_t × c_k) with
the unclocked triad's age drawn uniform by Monte Carlo, put in a dense Gaussian with φ projected
out; the dense GLS for the gyro side; the age prior's moments against the report's clocks.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood, ages_from_clocks
from accel_bayes.model.report_terms import fused_gyro_posterior, unresolved_terms
from accel_bayes.physics.effects import make_effect
from accel_bayes.physics.models import specific_force
from tests.model.test_calibrate_percov import UNRESOLVED, _clock, _report
from tests.model.test_instant_error import _rate
from tests.model.test_likelihood_percov import POS5, SIG, _case, _dense_marginal, _kinematic_H

DT = torch.float64
F_HOLD = 1000.0  # Hz: the unclocked IMU's own sampling rate (its hold is 1/f)
UNC = 2  # the triad without a clock


def _angjerk(T, seed=8):
    g = torch.Generator().manual_seed(seed)
    return 2e4 * (0.5 + torch.rand(T, generator=g, dtype=DT))


def _model_lik(acc, omega, age, s, a, rate, with_var=True):
    """The likelihood as calibrate builds it for one unclocked triad: its expected age in ``age``,
    the hold's variance in ``age_var``, the triads' output rates in ``age_rate``."""
    age = age.clone()
    age[:, UNC] = 0.5 / F_HOLD
    var = torch.zeros(5, dtype=DT)
    var[UNC] = 1.0 / (12 * F_HOLD ** 2)
    return PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, angjerk_std=a, lever=POS5,
                                  age_var=var if with_var else None, age_rate=rate if with_var else None)


def _mc_cov(age_t, s_t, a_t, rho_t, n=400_000, seed=1):
    """Cov of the loading v_k = d_k (m + ω̈ × c_k) (15,) at one sample, the unclocked triad's age
    drawn uniform on [0, 1/f) and centred with the others' (the physics, no Gaussian algebra), plus
    on that triad its output rate ρ read late by the age's departure from the expected age (what
    the clocks' mean correction, made at the expected age, leaves)."""
    rng = np.random.default_rng(seed)
    ages = np.tile(age_t, (n, 1))
    ages[:, UNC] = rng.uniform(0.0, 1.0 / F_HOLD, n)
    d = ages - ages.mean(1, keepdims=True)
    m = s_t * rng.standard_normal((n, 3))
    w = a_t * rng.standard_normal((n, 3))
    c = POS5.numpy() - POS5.numpy().mean(0)
    v = d[:, :, None] * (m[:, None, :] + np.cross(w[:, None, :], c[None, :, :]))  # (n, 5, 3)
    v[:, UNC] += (ages[:, UNC] - 0.5 / F_HOLD)[:, None] * rho_t[UNC]
    v = v.reshape(n, 15)
    return v.T @ v / n


def _dense_mc(pos, acc, omega, age, s, a, rate):
    H = _kinematic_H(pos)
    out = []
    for t in range(acc.shape[0]):
        mean = specific_force(pos, omega[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
        r = (acc[t] - mean[0]).reshape(-1).numpy()
        Sig = SIG ** 2 * np.eye(15) + _mc_cov(age[t].numpy(), float(s[t]), float(a[t]), rate[t].numpy(), seed=t)
        out.append(_dense_marginal(r, Sig, H))
    return np.array(out)


def test_the_random_age_is_the_monte_carlo_dense_gaussian():
    """log p(y_t | ω_t, θ) with the age prior equals the dense Gaussian whose covariance is the Monte
    Carlo covariance of the age-loaded jerk and angular jerk with the unclocked age drawn uniform
    (to the Monte Carlo error); the expected age alone, or age 0, misses it by far more."""
    T = 4
    acc, omega, age, s = _case(T=T, seed=6)
    a = _angjerk(T)
    rate = _rate(T, 5, seed=7)
    w = omega.mean
    want = _dense_mc(POS5, acc, w, age, s, a, rate)
    const = -(15 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG)
    got = _model_lik(acc, omega, age, s, a, rate).log_lik_per_sample(POS5, w).detach().numpy() + const
    err = np.abs(got - want)
    assert err.max() < 0.02, err
    mean_only = _model_lik(acc, omega, age, s, a, rate, with_var=False).log_lik_per_sample(POS5, w)
    mean_only = mean_only.detach().numpy() + const
    age0 = age.clone()
    age0[:, UNC] = 0.0
    zero = PerSampleCovLikelihood(acc, omega, SIG, 3, age0, s, angjerk_std=a, lever=POS5)
    zero = zero.log_lik_per_sample(POS5, w).detach().numpy() + const
    assert np.abs(mean_only - want).max() > 20 * err.max()
    assert np.abs(zero - want).max() > 20 * err.max()


def test_the_age_prior_columns_are_exact_and_log_phat_takes_them():
    """Against the dense Gaussian with the analytic covariance v (s² I + a² [c]×[c]×ᵀ) on the
    unclocked triad beside the expected ages' loading, at two geometries; log p̂ is the dense
    Monte Carlo average over the same ω draws."""
    T = 5
    acc, omega, age, s = _case(T=T, seed=2)
    a = _angjerk(T, seed=3)
    rate = _rate(T, 5, seed=9)
    lik = _model_lik(acc, omega, age, s, a, rate)
    v = 1.0 / (12 * F_HOLD ** 2)
    c = POS5.numpy()[UNC] - POS5.numpy().mean(0)
    cx = np.array([[0, -c[2], c[1]], [c[2], 0, -c[0]], [-c[1], c[0], 0]])
    const = -(15 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG)
    lev = POS5.numpy() - POS5.numpy().mean(0)

    def dense(pos, om):
        H = _kinematic_H(pos)
        out = []
        for t in range(T):
            mean = specific_force(pos, om[t:t + 1], torch.zeros(1, 3, dtype=DT), torch.zeros(1, 3, dtype=DT))
            r = (acc[t] - mean[0]).reshape(-1).numpy()
            d = lik.age[t].numpy() - lik.age[t].numpy().mean()
            U = np.zeros((15, 6))
            for k in range(5):
                lx = np.array([[0, -lev[k, 2], lev[k, 1]], [lev[k, 2], 0, -lev[k, 0]], [-lev[k, 1], lev[k, 0], 0]])
                U[3 * k:3 * k + 3] = d[k] * np.hstack((float(s[t]) * np.eye(3), float(a[t]) * lx))
            Sig = SIG ** 2 * np.eye(15) + U @ U.T
            Sig[3 * UNC:3 * UNC + 3, 3 * UNC:3 * UNC + 3] += v * (float(s[t]) ** 2 * np.eye(3)
                                                                  + float(a[t]) ** 2 * cx @ cx.T
                                                                  + np.outer(rate[t, UNC], rate[t, UNC]))
            out.append(_dense_marginal(r, Sig, H))
        return np.array(out)

    for pos in (POS5, POS5 * 1.2):
        got = lik.log_lik_per_sample(pos, omega.mean).detach().numpy() + const
        np.testing.assert_allclose(got, dense(pos, omega.mean), rtol=1e-10, atol=1e-8)
    z = lik.sample_z((), 3, torch.Generator().manual_seed(4))
    om = lik.omega_draws(z)
    per = np.stack([dense(POS5, om[:, n]) for n in range(3)], -1)
    want = (torch.logsumexp(torch.as_tensor(per), -1) - math.log(3)).sum().item()
    assert float(lik.log_phat(POS5, z=z)) + T * const == pytest.approx(want, rel=1e-9, abs=1e-8)


def _terms(clocked, K=8, T=4000, rate=62.5):
    t = np.arange(T) / rate
    clocks = {1: _clock(1, 0.8, 0.1), 3: _clock(3, -2.3, 0.6), 6: _clock(6, 1.2, 0.35, delay=None),
              0: _clock(0, 3.1, 0.2), 2: _clock(2, -1.1, 0.9), 4: _clock(4, 0.4, 0.5), 5: _clock(5, 2.2, 0.05),
              7: _clock(7, -0.6, 0.7)}
    rep = _report(SimpleNamespace(K=K, T=T), [clocks[k] for k in clocked] + [UNRESOLVED])
    return t, unresolved_terms(rep, t, list(range(K)), list(range(K)), np.full(T, 4.0)), clocks


def test_an_imu_without_a_clock_gets_the_expected_age_and_the_holds_variance():
    """Not age 0 (the defect): the clocked IMUs' mean age, plus their mean filter delay on acc; variance
    (1/f̄)²/12 with f̄ their mean internal rate; listed with the reason and in what the terms used."""
    t, terms, clocks = _terms([1, 3, 6])
    unc = [0, 2, 4, 5, 7]
    eff = {k: make_effect("sampling_clock", imu=k, axis=None,
                          parameters={**clocks[k][2], "filter_delay_acc_minus_gyro_s": clocks[k][2][
                              "filter_delay_acc_minus_gyro_s"] or 0.0}) for k in (1, 3, 6)}
    tt = torch.as_tensor(t)
    gyro_mean = float(torch.stack([eff[k].physical_age(tt) for k in (1, 3, 6)]).mean())
    f = np.mean([clocks[k][2]["internal_rate_hz"] for k in (1, 3, 6)])
    for k in unc:
        np.testing.assert_allclose(terms.age_gyro[:, k].numpy(), gyro_mean, rtol=1e-12)
        np.testing.assert_allclose(terms.age_acc[:, k].numpy(), gyro_mean + (-1.5e-4 - 1.5e-4 + 0.0) / 3, rtol=1e-12)
    # the hold's sawtooth averages to half its width: the expected age is that of a uniform age
    assert gyro_mean == pytest.approx(0.5 / f, rel=0.02)
    np.testing.assert_allclose(terms.age_var_acc.numpy()[unc], 1 / (12 * f * f), rtol=1e-12)
    np.testing.assert_allclose(terms.age_var_gyro.numpy()[unc], 1 / (12 * f * f), rtol=1e-12)
    assert [u["imu"] for u in terms.unclocked] == unc and all("no sampling_clock" in u["why"] for u in terms.unclocked)
    assert terms.unclocked[0]["age_std_s"] == pytest.approx(1 / (f * math.sqrt(12)))
    assert any(u["effect"] == "sampling_clock" and u["imu"] == unc for u in terms.used)
    # a report without any clock: the vocabulary's 1 kHz hold, its own mean age, no filter delay
    _, none, _ = _terms([])
    np.testing.assert_allclose(none.age_acc.numpy(), 0.5e-3)
    np.testing.assert_allclose(none.age_var_acc.numpy(), 1 / 12e6)


def test_an_imu_with_a_clock_is_unchanged():
    """The clocked rows keep their clock's ages (ages_from_clocks) and get no variance; a report that
    clocks every IMU adds nothing: the likelihood takes the jerk-only closed-form path as before."""
    t, part, clocks = _terms([1, 3, 6])
    eff = {k: make_effect("sampling_clock", imu=k, axis=None,
                          parameters={**clocks[k][2], "filter_delay_acc_minus_gyro_s": clocks[k][2][
                              "filter_delay_acc_minus_gyro_s"] or 0.0}) for k in clocks}
    ref_acc = ages_from_clocks(t, eff, list(range(8)), "acc")
    for k in (1, 3, 6):
        np.testing.assert_array_equal(part.age_acc[:, k].numpy(), ref_acc[:, k].numpy())
        assert float(part.age_var_acc[k]) == 0.0 and float(part.age_var_gyro[k]) == 0.0
    _, full, _ = _terms(list(range(8)))
    np.testing.assert_array_equal(full.age_acc.numpy(), ref_acc.numpy())
    assert not full.unclocked and not bool(full.age_var_acc.any()) and not bool(full.age_var_gyro.any())
    acc, omega, age, s = _case(T=6, seed=1)
    plain = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s)
    same = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, age_var=torch.zeros(5, dtype=DT))
    assert same.W is None
    assert torch.equal(plain.log_lik_per_sample(POS5, omega.mean), same.log_lik_per_sample(POS5, omega.mean))


def test_the_gyro_of_an_unclocked_imu_takes_the_random_age_in_the_dense_gls():
    """fused_gyro_posterior with age_var: C_t,k += v_k (s_t² I₃ + ω̇_t ω̇_tᵀ) on that gyro, against
    numpy's GLS on the stacked covariance."""
    rng = np.random.default_rng(5)
    T, G = 5, 4
    tt = np.arange(T) * 0.01
    y = rng.normal(0, 3.0, (T, G, 3))
    std = np.array([0.01, 0.02, 0.015, 0.03])
    age = rng.uniform(0, 1e-3, (T, G))
    s = rng.uniform(50, 200, T)
    var = np.array([0.0, 1e-6 / 12, 0.0, 0.0])
    post, wdot = fused_gyro_posterior(torch.as_tensor(y), std, [0, 2, 5, 6], tt, [], age=age, angular_acc_std=s,
                                   age_var=var)
    X = np.tile(np.eye(3), (G, 1))
    for i in range(T):
        d = age[i] - age[i].mean()
        C_ = np.kron(np.diag(std ** 2 + var * s[i] ** 2), np.eye(3)) + s[i] ** 2 * np.kron(np.outer(d, d), np.eye(3))
        C_ += np.kron(np.diag(var), np.outer(wdot[i].numpy(), wdot[i].numpy()))
        Ci = np.linalg.inv(C_)
        P = np.linalg.inv(X.T @ Ci @ X)
        np.testing.assert_allclose(post.cov[i].numpy(), P, rtol=1e-9)
        np.testing.assert_allclose(post.mean[i].numpy(), P @ X.T @ Ci @ y[i].reshape(-1), rtol=1e-9, atol=1e-12)


def test_bad_age_prior_inputs_are_one_line_errors_naming_the_field():
    from accel_bayes.errors import UserError

    acc, omega, age, s = _case(T=4, seed=1)
    with pytest.raises(UserError, match=r"^age_var: expected finite variances >= 0 of shape \(A,\)"):
        PerSampleCovLikelihood(acc, omega, SIG, 1, age, s, age_var=torch.tensor([1e-7, -1.0, 0, 0, 0], dtype=DT))
    with pytest.raises(UserError, match=r"^age_rate: expected finite output rates of shape \(T, A, 3\)"):
        PerSampleCovLikelihood(acc, omega, SIG, 1, age, s, age_var=torch.full((5,), 1e-7, dtype=DT),
                               age_rate=torch.zeros(4, 5, dtype=DT))

"""The held-out physics model's predictive of its own clock (accel_bayes/mismatch/age_predictive.py;
issue #27 item 4): the exact sawtooth moments and the marginalised predictive against Monte Carlo
over the age distribution, the beat walk's rate on clockgen clocks with a known drift, and the
evidence rule reading the data age's width (fitted / λ) as the clock stage does."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from accel_bayes.mismatch import heldout
from accel_bayes.mismatch.age_predictive import (AgeMoments, age_moments, beat_walk_rate, moment_loadings,
                                                 sawtooth_moments)
from accel_bayes.mismatch.clock import physical_width
from accel_bayes.mismatch.generic import BandedWhite
from experiments.clockgen.sensing import Clock, beat_frequency


@pytest.mark.parametrize("mu,sigma", [(0.3, 0.0), (0.97, 0.01), (0.2, 0.1), (1.7, 0.3), (0.4, 0.49), (0.4, 0.51),
                                      (2.2, 0.8), (-0.05, 0.05)])
def test_sawtooth_moments_match_monte_carlo(mu, sigma):
    """E frac ψ and E frac² ψ for ψ ~ N(μ, σ²), both branches (cycle sums ≤ 0.5, series above), against
    4·10⁵ draws (seed 0): within 5 Monte Carlo standard errors."""
    x = np.random.default_rng(0).normal(mu, sigma, 400_000)
    f = x - np.floor(x)
    m1, m2 = sawtooth_moments(mu, sigma)
    for est, draws in ((m1, f), (m2, f * f)):
        se = max(draws.std() / np.sqrt(len(draws)), 1e-12)
        assert abs(float(est) - draws.mean()) < 5 * se + 1e-12


def _posts():
    """Four IMUs' phase posteriors (t_c = 0): a sharp clock, one loosening, one nearly lost, no clock."""
    cov = lambda vp, vb: np.array([[vp, 0.0], [0.0, vb]])  # noqa: E731
    return [{"t_c": 0.0, "phase": 0.21, "beat_hz": -2.5, "cov": cov(1e-5, 1e-8)},
            {"t_c": 0.0, "phase": 0.64, "beat_hz": 0.8, "cov": cov(4e-3, 1e-5)},
            {"t_c": 0.0, "phase": 0.05, "beat_hz": 1.1, "cov": cov(0.04, 1e-4)},
            None]


def test_marginalised_predictive_matches_monte_carlo_over_ages():
    """The Gaussian predictive's mean and covariance of y_kt = −c d_kt ẏ_kt + d_kt m_t + e_kt with the
    ages drawn from the phase predictive (Gaussian phase, sawtooth age, centred over the IMUs; no clock:
    uniform age) against 3·10⁵ Monte Carlo draws of (ψ, m, e), seed 1, at three times: every mean and
    covariance entry within 2 % of the covariance's largest diagonal."""
    rng = np.random.default_rng(1)
    W, q, c, s, v = 1e-3, 2e-6, 0.9, 300.0, 1e-4
    t = np.array([5.0, 40.0, 90.0])
    posts = _posts()
    K = len(posts)
    rate = torch.as_tensor(rng.normal(0, 40.0, (len(t), K, 3)))
    mean, var = age_moments(t, posts, q, W)
    m = AgeMoments.of(mean, var)
    m.rate_c = c * rate
    U, s2 = moment_loadings(m, torch.full((len(t),), s * s, dtype=torch.float64))
    cov_model = v * torch.eye(3 * K, dtype=torch.float64) + torch.einsum("tnr,tr,tmr->tnm", U, s2, U)
    mean_model = (-c * m.mean[:, :, None] * rate).reshape(len(t), -1)
    n = 300_000
    for i, ti in enumerate(t):
        age = np.empty((n, K))
        for k, p in enumerate(posts):
            if p is None:
                age[:, k] = W * rng.random(n)
                continue
            tau = ti - p["t_c"]
            sd = np.sqrt(p["cov"][0, 0] + tau * tau * p["cov"][1, 1] + q * tau ** 3 / 3)
            psi = rng.normal(p["phase"] + p["beat_hz"] * tau, sd, n)
            age[:, k] = W * (psi - np.floor(psi))
        d = age - age.mean(1, keepdims=True)
        y = (-c * d[:, :, None] * rate[i].numpy()[None] + d[:, :, None] * rng.normal(0, s, (n, 1, 3))
             + rng.normal(0, np.sqrt(v), (n, K, 3))).reshape(n, -1)
        tol = 0.02 * float(cov_model[i].diagonal().max())
        assert np.abs(y.mean(0) - mean_model[i].numpy()).max() < np.sqrt(tol)
        assert np.abs(np.cov(y.T) - cov_model[i].numpy()).max() < tol


def test_marginalised_density_is_the_deterministic_one_without_age_variance_and_exact_otherwise():
    """BandedWhite's density with AgeMoments: zero age variance gives the deterministic-age density to
    rounding; with variance it equals the dense Gaussian N(0, V + U S Uᵀ) (low-rank identity exact)."""
    rng = np.random.default_rng(2)
    T, K = 6, 4
    d = torch.as_tensor(rng.normal(0, 3e-4, (T, K)))
    d -= d.mean(1, keepdim=True)
    y = torch.as_tensor(rng.normal(0, 0.02, (T, K, 3)))
    lab = torch.zeros(T, dtype=torch.long)
    model = BandedWhite(torch.full((K, 1), 1e-4, dtype=torch.float64), torch.tensor([300.0], dtype=torch.float64))
    det = model.logpdf(y, lab, d)
    zero = AgeMoments(d, torch.zeros(T, K, K, dtype=torch.float64), torch.zeros(T, K, 3, dtype=torch.float64))
    assert torch.allclose(model.logpdf(y, lab, zero), det, rtol=0, atol=1e-9)
    mean, var = age_moments(np.linspace(0, 60, T), _posts(), 2e-6, 1e-3)
    m = AgeMoments.of(mean, var)
    m.rate_c = torch.as_tensor(rng.normal(0, 40.0, (T, K, 3)))
    U, s2 = moment_loadings(m, torch.full((T,), 300.0 ** 2, dtype=torch.float64))
    cov = 1e-4 * torch.eye(3 * K, dtype=torch.float64) + torch.einsum("tnr,tr,tmr->tnm", U, s2, U)
    dense = torch.distributions.MultivariateNormal(torch.zeros(3 * K, dtype=torch.float64), covariance_matrix=cov)
    assert torch.allclose(model.logpdf(y, lab, m), dense.log_prob(y.reshape(T, -1)), rtol=1e-9, atol=1e-8)


def _clock_statistics(clocks, f_host, T_s, seed):
    """Timing statistics (clock.py's model b = −a·age + N(0, a)) of IMUs whose data age is
    frac(θ(t))/f_int, θ the clockgen :class:`Clock`'s tick count at the reads."""
    g = np.random.default_rng(seed)
    t = np.arange(int(T_s * f_host)) / f_host
    age = np.stack([(c.count(t) - np.floor(c.count(t))) / c.f_int for c in clocks], 1)
    a = g.uniform(0.5, 2.0, age.shape) * 1e8
    return t, a, -a * age + np.sqrt(a) * g.normal(size=age.shape)


def _clock_dict(clocks, f_host, t0):
    """The clocks as :func:`~accel_bayes.mismatch.heldout.clocks_from` gives them (beat and phase at t = 0,
    no drift), from their nominal rates: what a whole-recording acquisition would start the tracking from."""
    beat = np.array([beat_frequency(c.f_int, c.eps, f_host) for c in clocks])
    return {"beat_hz": beat, "phase": np.array([c.phase % 1 for c in clocks]), "drift_hz_per_s": np.zeros(len(clocks)),
            "width_s": np.full(len(clocks), 1e-3)}


def test_beat_walk_rate_on_clockgen_clocks_with_known_drift():
    """clockgen clocks at 62.5 Hz with the generator's temperature drift (a = 1e-4, periods 150–200 s):
    the tracked rate q (maximum likelihood of the increments Δβ ~ N(0, qΔt + v₁ + v₂) over 20 s blocks)
    is within 20 % of the truth's, Σ Δβ²/ΣΔt of the true beats (block means of f_int(1 + ε + a sin(2πt/P
    + ψ)) − n f_host); the same clocks without drift give q under 2 % of it (the blocks' estimation
    variance accounted for)."""
    f_host, T_s, blk = 62.5, 120.0, 20.0
    spec = [(-2.4e-3, 0.3, 150.0, 0.4), (0.9e-3, 0.7, 200.0, 2.0)]
    drifting = [Clock(1000.0, e, ph, 1e-4, P, psi) for e, ph, P, psi in spec]
    t, a, b = _clock_statistics(drifting, f_host, T_s, seed=3)
    got = beat_walk_rate(t, a, b, _clock_dict(drifting, f_host, 0.0), start=0.0, block_s=blk)
    num = den = 0.0
    for c in drifting:
        tc = np.arange(0.0, T_s - blk + 1e-9, blk) + 0.5 * blk
        n_fold = np.round(c.f_int * (1 + c.eps) / f_host)
        beat = np.array([np.mean(c.rate(np.linspace(x - blk / 2, x + blk / 2, 2001))) for x in tc]) - n_fold * f_host
        num += float((np.diff(beat) ** 2).sum())
        den += float(np.diff(tc).sum())
    truth = num / den
    assert got["n_increments"] == 2 * (int(T_s / blk) - 1)
    assert got["q_hz2_per_s"] == pytest.approx(truth, rel=0.2)
    steady = [Clock(1000.0, e, ph, 0.0, P, psi) for e, ph, P, psi in spec]
    t, a, b = _clock_statistics(steady, f_host, T_s, seed=3)
    assert beat_walk_rate(t, a, b, _clock_dict(steady, f_host, 0.0), start=0.0, block_s=blk)["q_hz2_per_s"] < 0.02 * truth


def test_evidence_rule_reads_the_data_age_width_fitted_over_rate_scale():
    """The defect: the held-out evidence rule checked the *fitted* sawtooth width against the clock
    stage's range, without the regressor's scale λ.  A clock fitted 0.9 ms wide with λ = 0.2 is 4.5 ms
    of data age (outside 0.4–4 ms): the rule now drops it, as the clock stage would, and keeps the one
    with λ = 0.9 (1 ms); the width is the stage's own definition (clock.physical_width)."""
    clock = {"beat_hz": np.array([-2.5, 0.8, 1.1]), "phase": np.array([0.1, 0.5, 0.9]),
             "drift_hz_per_s": np.zeros(3), "width_s": np.array([0.9e-3, 0.9e-3, 0.9e-3]),
             "evidence": np.array([400.0, 400.0, 400.0]), "threshold": np.full(3, 40.0)}
    lam = np.array([0.9, 0.2, 1.0])
    ruled = heldout.with_rate_scale(clock, lam)
    assert list(heldout.clock_accepted(ruled)) == [True, False, True]
    assert ruled["width_s"][1] == physical_width(0.9e-3, 0.2)
    assert ruled["age_rms_s"][0] == pytest.approx(1e-3 / np.sqrt(12.0))
    with pytest.raises(ValueError, match="already"):
        heldout.with_rate_scale(ruled, lam)
    res = type("R", (), {"time": torch.linspace(0, 10, 50, dtype=torch.float64)})()
    age = heldout.acquired_age(res, ruled, accept="evidence")
    assert torch.allclose(age[:, 1], age[:, [0, 2]].mean(1))


def test_lost_phase_is_scored_as_lost_not_as_certain():
    """The defect: the held-out physics scored the 30 s acquisition's age extrapolated as if certain.
    Four IMUs whose beats walk (q = 2e-5 Hz²/s, seed 4) after an exact acquisition at t_c = 15 s, residuals
    = unresolved motion loaded by the true centred ages + white noise.  60–90 s after the acquisition
    (phase spread 1–2 cycles) the deterministic age scores below a white model of the same per-channel
    variance (the old failure, reproduced), the marginalised one above it and above the deterministic;
    within 3 s of t_c (spread ≤ 0.013 cycles) the marginalised one keeps the clock's information: over
    1 nat/sample above the white model (the deterministic one, a jump misplaced by 0.01 cycle costing
    hundreds of nats, is already at the white model's level there)."""
    rng = np.random.default_rng(4)
    f, K, W, q, s, v = 62.5, 4, 1e-3, 2e-5, 300.0, 1e-4
    t = np.arange(int(105 * f)) / f
    t_c = 15.0
    beat, phase = rng.uniform(-3, 3, K), rng.random(K)
    walk = np.cumsum(rng.normal(0, np.sqrt(q / f), (len(t), K)), 0)
    walk -= walk[np.searchsorted(t, t_c)]
    psi = phase + beat * (t - t_c)[:, None] + np.cumsum(walk, 0) / f
    psi -= psi[np.searchsorted(t, t_c)] - phase  # the walk's phase is zero at t_c
    d = W * (psi - np.floor(psi))
    d -= d.mean(1, keepdims=True)
    y = torch.as_tensor(d[:, :, None] * rng.normal(0, s, (len(t), 1, 3)) + rng.normal(0, np.sqrt(v), (len(t), K, 3)))
    lab = torch.zeros(len(t), dtype=torch.long)
    posts = [{"t_c": t_c, "phase": phase[k], "beat_hz": beat[k], "cov": np.diag([1e-6, 1e-9])} for k in range(K)]
    det = W * np.mod(phase + beat * (t - t_c)[:, None], 1.0)
    det -= det.mean(1, keepdims=True)
    physics = BandedWhite(torch.full((K, 1), v, dtype=torch.float64), torch.tensor([s], dtype=torch.float64))
    white = BandedWhite(torch.full((K, 1), v + s * s * W * W / 12 * (1 - 1 / K), dtype=torch.float64))
    ll_det = physics.logpdf(y, lab, torch.as_tensor(det)).numpy()
    ll_marg = physics.logpdf(y, lab, AgeMoments.of(*age_moments(t, posts, q, W))).numpy()
    ll_white = white.logpdf(y, lab).numpy()
    late = t - t_c > 60
    assert ll_det[late].mean() < ll_white[late].mean()
    assert ll_marg[late].mean() > ll_white[late].mean()
    assert ll_marg[late].mean() > ll_det[late].mean()
    early = np.abs(t - t_c) < 3
    assert ll_marg[early].mean() > ll_white[early].mean() + 1.0

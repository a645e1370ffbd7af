"""The phase forecast of the held-out physics (accel_bayes/mismatch/age_predictive.py; issue #27 item 4):
the acquisition posterior under autocorrelated timing noise, the forecast noise fitted on a recording's own
forecast errors, and the forecast's calibration on drifting clocks (the defect: a Brownian beat at the rate of
block-to-block beat increments is too narrow when the beat drifts)."""
from __future__ import annotations

import numpy as np
import pytest

from accel_bayes.mismatch.age_predictive import (ForecastNoise, beat_walk_rate, fit_forecast_noise, forecast_errors,
                                                 phase_posterior, phase_predictive)

F_READ, W = 62.5, 1e-3


def _timing(rng, t, phase, beat, drift, rho, noise):
    """Timing statistics (clock.py's model b = −a·age + noise·√a·u) of a sawtooth data age
    W·frac(phase + beat·t + ½drift·t²), t (n,) s; u AR(1) with lag-one correlation rho, unit variance."""
    e = rng.normal(size=len(t))
    u = np.empty(len(t))
    u[0] = e[0]
    for i in range(1, len(t)):
        u[i] = rho * u[i - 1] + np.sqrt(1 - rho * rho) * e[i]
    a = rng.uniform(0.5, 2.0, len(t)) * 1e8
    x = phase + beat * t + 0.5 * drift * t * t
    return a, -a * W * (x - np.floor(x)) + noise * np.sqrt(a) * u


def test_acquisition_posterior_is_not_too_narrow_under_autocorrelated_timing_noise():
    """Real timing residuals are autocorrelated; the acquisition's likelihood takes them as white.  Measured:
    with AR(1) noise of ρ = 0.8 (a zero-frequency variance 9× the white one) 40 15-s acquisitions of a steady
    clock still hold the true phase and beat within 1 posterior sd in ≥ 60 % of cases and within 2 sd in
    ≥ 90 % (the sawtooth's information is at the beat and its harmonics, where this noise is weaker than white,
    and ĉ² is the statistics' total variance): the forecast's narrowness is not the acquisition's."""
    rng = np.random.default_rng(11)
    t = np.arange(int(15.0 * F_READ)) / F_READ
    z = []
    for _ in range(40):
        phase, beat = rng.uniform(), -2.4 + rng.uniform(-0.3, 0.3)
        a, b = _timing(rng, t, phase, beat, 0.0, 0.8, 10.0)
        post = phase_posterior(t, a, b, beat_hz=beat + rng.uniform(-5e-3, 5e-3), phase=phase + rng.uniform(-0.02, 0.02),
                               t_c=7.5, n_grid=25, n_zoom=3)
        z.append(((post["phase"] - phase - beat * 7.5 + 0.5) % 1.0 - 0.5) / np.sqrt(post["cov"][0, 0]))
        z.append((post["beat_hz"] - beat) / np.sqrt(post["cov"][1, 1]))
    z = np.abs(np.array(z))
    assert np.mean(z < 1) >= 0.6 and np.mean(z < 2) >= 0.9


def test_fit_forecast_noise_recovers_known_rates():
    """Forecast errors drawn from the model itself (300 IMUs, τ = 20–90 s every 10 s, a 2×2 acquisition
    covariance and local variances as on the real windows, q = 2e-7 Hz²/s, σ²_d = 1e-8 Hz²/s², seed 5):
    the maximum-likelihood rates are within 25 % of the truth; with no drift in the errors the fitted
    drift variance is under 5 % of that value."""
    rng = np.random.default_rng(5)
    taus = np.arange(20.0, 90.1, 10.0)
    post = {"t_c": 0.0, "phase": 0.0, "beat_hz": -2.4, "cov": np.array([[2e-6, 0.0], [0.0, 4e-8]])}

    def draw(noise):
        J = np.stack([np.ones_like(taus), taus], 1)
        C = J @ post["cov"] @ J.T + np.diag(np.full(len(taus), 4e-6)) + noise.cov(taus, taus)
        L = np.linalg.cholesky(C)
        return [{"tau": taus, "e": L @ rng.normal(size=len(taus)), "var": np.full(len(taus), 4e-6)} for _ in range(300)]

    truth = ForecastNoise(q=2e-7, drift_var=1e-8)
    got = fit_forecast_noise(draw(truth), [post] * 300)
    assert got.q == pytest.approx(truth.q, rel=0.25) and got.drift_var == pytest.approx(truth.drift_var, rel=0.25)
    walk = fit_forecast_noise(draw(ForecastNoise(q=2e-7)), [post] * 300)
    assert walk.q == pytest.approx(2e-7, rel=0.25) and walk.drift_var < 0.05 * truth.drift_var


def _drifting(seed, K, sd_drift, T_s):
    """K clocks whose beats drift linearly at rates N(0, sd_drift²) Hz/s: (t, a, b (n, K), [(phase, beat, drift)])."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(T_s * F_READ)) / F_READ
    truth = [(rng.uniform(), rng.uniform(-2.6, 2.6), rng.normal(0.0, sd_drift)) for _ in range(K)]
    ab = [_timing(rng, t, *c, 0.5, 3.0) for c in truth]
    return t, np.stack([x[0] for x in ab], 1), np.stack([x[1] for x in ab], 1), truth


def _acquire(t, a, b, truth, window_s):
    """Each clock's :func:`phase_posterior` on the first ``window_s`` s, from the true beat at 0 (the search's)."""
    w = t < window_s
    return [phase_posterior(t[w], a[w, k], b[w, k], beat_hz=beat, phase=phase, t_c=0.5 * window_s)
            for k, (phase, beat, _) in enumerate(truth)]


@pytest.mark.slow
def test_forecast_is_calibrated_on_drifting_clocks():
    """The defect (real MIMU: 45–50 % of the phase errors within 1σ at 60–85 s): beats that drift linearly
    (rates N(0, (6e-5 Hz/s)²), AR(1) timing noise ρ = 0.5) forecast from a 30 s acquisition with a Brownian
    beat at the rate q of the source's 30 s block-to-block beat increments.  A drift d makes the increments
    dΔt, so q ≈ σ²_dΔt and the forecast's variance qτ³/3 ≈ 10σ²_dτ³ against the drift's σ²_dτ⁴/4: a factor
    τ/40 too narrow, 2.1 at τ = 85 s, the end of the scored stretch, where it is checked: over 48 target
    clocks (6 recordings × 8, seeds 1–6) the previous forecast's mean squared z-score is above 1.5 (nominal
    1).  With the source's :func:`fit_forecast_noise` on its own forecast errors it is within 0.6–1.4 and
    the 1σ/2σ coverage within 0.55–0.85 / ≥ 0.88 (48 clocks: binomial sd ≈ 0.07).  The source (seed 0)
    has 32 clocks: the fit recovers the drift variance its clocks realise, and 8 drifts (one board)
    realise σ²_d only to ~50 % — on the real recordings that spread between sources remains."""
    sd_drift, window_s, T_s, tau = 6e-5, 30.0, 110.0, 85.0
    t, a, b, truth = _drifting(0, 32, sd_drift, T_s)
    posts = _acquire(t, a, b, truth, window_s)
    clocks = {"beat_hz": np.array([c[1] for c in truth]), "phase": np.array([c[0] for c in truth]),
              "drift_hz_per_s": np.zeros(32), "width_s": np.full(32, W)}
    old = ForecastNoise(q=beat_walk_rate(t, a, b, clocks, start=0.0, block_s=window_s)["q_hz2_per_s"])
    new = fit_forecast_noise([forecast_errors(t, a[:, k], b[:, k], p, taus=np.arange(20.0, 90.1, 10.0))
                              for k, p in enumerate(posts)], posts)
    z = {"old": [], "new": []}
    for seed in range(1, 7):
        t, a, b, truth = _drifting(seed, 8, sd_drift, T_s)
        for p, (phase, beat, drift) in zip(_acquire(t, a, b, truth, window_s), truth):
            tt = np.array([p["t_c"] + tau])
            psi = phase + beat * tt + 0.5 * drift * tt * tt
            for name, noise in (("old", old), ("new", new)):
                m, sd = phase_predictive(tt, p, noise)
                z[name].append(float(((psi - m + 0.5) % 1.0 - 0.5)[0] / sd[0]))
    zo, zn = np.abs(np.array(z["old"])), np.abs(np.array(z["new"]))
    assert np.mean(zo ** 2) > 1.5
    assert 0.6 <= np.mean(zn ** 2) <= 1.4
    assert 0.55 <= np.mean(zn < 1) <= 0.85 and np.mean(zn < 2) >= 0.88

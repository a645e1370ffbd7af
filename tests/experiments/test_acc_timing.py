"""The estimators of experiments/acc_timing_check.py on planted synthetic structure (numpy only).

Residuals a_kt = (δ_kt − mean_k δ_kt) j_t + noise, K = 8 IMUs, j_t a random 3-vector per sample.
The per-sample jerk fit must recover the planted share of power (and j_t itself), the shuffled-δ
null must fall to the share three free parameters per sample soak up, and the gyro-side estimator
δ = r·ġ/|ġ|² must recover δ from r_gyro = δ ġ + noise.
"""
from __future__ import annotations

import numpy as np

from experiments import acc_timing_check as A

T, K = 2000, 8


def _planted(seed=0, noise=0.5):
    rng = np.random.default_rng(seed)
    delta = rng.uniform(-0.5e-3, 0.5e-3, (T, K))           # s, 1 ms wide
    j = rng.normal(0.0, 2000.0, (T, 3))                      # m/s³
    d = delta - delta.mean(1, keepdims=True)
    signal = d[:, :, None] * j[:, None, :]
    a = signal + rng.normal(0.0, noise, (T, K, 3))
    return a, delta, j, signal


def test_jerk_fit_recovers_planted_share_and_null():
    a, delta, j, signal = _planted()
    S = (signal ** 2).sum()
    N = ((a - signal) ** 2).sum()
    # expected: the signal, plus the noise's projection on the fitted direction (3 of 3K dimensions)
    expect = (S + N / K) / (S + N)
    fit = A.jerk_fit(a, delta)
    assert abs(fit["share"] - expect) < 0.03, (fit["share"], expect)
    # j recovered where the centred δ is not degenerate
    cos = (fit["j"] * j).sum(1) / (np.linalg.norm(fit["j"], axis=1) * np.linalg.norm(j, axis=1))
    assert np.median(cos) > 0.8
    # null: the signal's projection on a random centred direction (1/(K−1)) and the noise's (1/K)
    null = A.shuffled_shares(a, delta, n=5, seed=1)
    expect_null = (S / (K - 1) + N / K) / (S + N)
    assert abs(null.mean() - expect_null) < 0.02, (null.mean(), expect_null)
    assert fit["share"] - null.mean() > 0.3
    # the within-sample correlation is positive with the true δ, ~0 with shuffled δ
    c = A.within_sample_corr(a, delta)
    cn = A.within_sample_corr(a, delta[np.random.default_rng(2).permutation(T)])
    assert np.nanmedian(c) > 0.3 and abs(np.nanmedian(cn)) < 0.1


def test_pure_noise_gives_null_share():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(T, K, 3))
    delta = rng.uniform(-0.5e-3, 0.5e-3, (T, K))
    assert abs(A.jerk_fit(a, delta)["share"] - 1 / K) < 0.01
    # a per-sample error common to all IMUs is orthogonal to the centred δ: it adds nothing
    common = a + rng.normal(0, 5.0, (T, 1, 3))
    assert A.jerk_fit(common, delta)["share"] < 1 / K


def test_instant_errors_from_gyro_residual():
    rng = np.random.default_rng(4)
    delta = rng.uniform(-0.5e-3, 0.5e-3, (T, K))
    gdot = rng.normal(0.0, 50.0, (T, K, 3))                  # rad/s²
    r = delta[:, :, None] * gdot + rng.normal(0.0, 0.002, (T, K, 3))
    est = A.instant_errors(r, gdot)
    big = (gdot ** 2).sum(-1) > np.median((gdot ** 2).sum(-1))
    assert np.corrcoef(est[big], delta[big])[0, 1] > 0.95

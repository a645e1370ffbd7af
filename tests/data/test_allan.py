"""Bias random walk from the rests (accel_bayes.data.allan), on simulated series with a known K.

The criterion the export relies on: an accepted estimate lies within its stated uncertainty of
the truth (z = (K̂ − K)/se, RMS near 1 over seeds), and stretches too short for it are refused.
"""
import math

import numpy as np

from accel_bayes.data.allan import RELATIVE_SE_MAX, allan_random_walk, static_runs, static_time_needed

RATE, N, K = 100.0, 1e-3, 1e-3  # crossover τ_c = √3 N/K ≈ 1.7 s


def _series(rng, T, runs=1):
    """``runs`` static stretches of T samples each, with a different constant (orientation) per stretch."""
    x = [N * math.sqrt(RATE) * rng.standard_normal((T, 3)) + np.cumsum(K / math.sqrt(RATE) * rng.standard_normal((T, 3)), 0)
         + rng.normal(0.0, 5.0, 3) for _ in range(runs)]
    return np.concatenate(x), [(i * T, (i + 1) * T) for i in range(runs)]


def test_estimate_within_its_stated_uncertainty():
    """16 seeds, 3 stretches of 50 s (never differenced across stretches: their offsets differ by
    metres per second², which would swamp K): RMS z within 0.7–1.5, no |z| beyond 4."""
    z = []
    for seed in range(16):
        x, runs = _series(np.random.default_rng(seed), int(50 * RATE), runs=3)
        est = allan_random_walk(x, runs, RATE)
        assert est.accepted and est.k_se <= RELATIVE_SE_MAX * est.k
        z.append((est.k - K) / est.k_se)
        assert abs(est.n_density - N) < 0.05 * N
    z = np.array(z)
    rms = float(np.sqrt(np.mean(z ** 2)))
    assert 0.7 <= rms <= 1.5, rms
    assert np.abs(z).max() < 4.0


def test_short_rests_refused():
    """Two 2 s rests (≈ 1 τ_c each): the random walk is not resolved, the estimate is not
    accepted.  Twenty 8 s rests (≈ 5 τ_c each, 160 s in all) resolve it statistically but are
    refused by the stretch condition (longest ≥ 20 τ̂_c)."""
    x, runs = _series(np.random.default_rng(0), int(2 * RATE), runs=2)
    est = allan_random_walk(x, runs, RATE)
    assert est is not None and not est.accepted
    x, runs = _series(np.random.default_rng(0), int(8 * RATE), runs=20)
    est = allan_random_walk(x, runs, RATE)
    assert not est.accepted and est.longest_s == 8.0
    assert est.k_se <= RELATIVE_SE_MAX * est.k  # the statistics alone would have passed it


def test_static_runs_and_time_needed():
    seg = np.array(["dynamic"] * 3 + ["static"] * 10 + ["dynamic"] + ["static"] * 3 + ["static"] * 0)
    assert static_runs(seg) == [(3, 13)]
    assert static_runs(seg, min_samples=3) == [(3, 13), (14, 17)]
    # Longer crossover time → longer rests needed (doubling search from 60 s).
    short, long_ = static_time_needed(N, K, RATE), static_time_needed(N, K / 10, RATE)
    assert short <= long_ and math.isfinite(long_)

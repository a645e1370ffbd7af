"""Held-out scoring pieces (accel_bayes/mismatch/heldout.py): the block bootstrap's standard error
on series of known variance, the sawtooth age, and the clock acquisition on a first-principles
clock case (experiments/clockgen)."""
from __future__ import annotations


import numpy as np
import pytest
import torch

from accel_bayes.mismatch.heldout import block_bootstrap_se, centred, clock_age



def test_block_bootstrap_se_matches_known_standard_errors():
    """White series: σ/√n within 15 %; an AR(1) series with ρ = 0.9: its long-run SE
    σ/√n·√((1+ρ)/(1−ρ)) within 25 % with 2 s blocks (a white-noise SE would be 4.4× too small)."""
    g = np.random.default_rng(4)
    n = 6000
    x = g.normal(size=n)
    assert block_bootstrap_se(x, n_boot=800, seed=1) == pytest.approx(1 / np.sqrt(n), rel=0.15)
    rho, e = 0.9, g.normal(size=n)
    ar = np.empty(n)
    ar[0] = e[0]
    for t in range(1, n):
        ar[t] = rho * ar[t - 1] + np.sqrt(1 - rho ** 2) * e[t]
    want = np.sqrt((1 + rho) / (1 - rho) / n)
    assert block_bootstrap_se(ar, n_boot=800, seed=1) == pytest.approx(want, rel=0.25)


def test_clock_age_is_a_sawtooth_of_the_beat():
    t = torch.arange(0, 2, 1 / 62.5, dtype=torch.float64)
    age = clock_age(t, [2.0, -0.5], [0.25, 0.5], f_int=1000.0)
    assert float(age.min()) >= 0 and float(age.max()) < 1e-3
    # one wrap per 1/|beat| s; the ramp rises for a positive beat and falls for a negative one
    wraps = (torch.diff(age, dim=0).abs() > 5e-4).sum(0)
    assert wraps.tolist() == [4, 1]
    assert float(torch.diff(age[:5, 0]).min()) > 0 and float(torch.diff(age[:5, 1]).max()) < 0
    assert torch.allclose(centred(age).mean(1), torch.zeros(len(t), dtype=torch.float64))


@pytest.mark.slow
def test_clocks_of_recovers_the_beats_of_a_clockgen_case():
    """20 s clock case (seed 3, MIMU4444 board at 62.5 Hz, no gyro linear errors): every IMU's
    beat (the detector's beat search, clock.estimate_clock) within 0.05 Hz of the truth, and the
    acquired ages correlate with the true ones (centred, r > 0.6)."""
    from experiments.clockgen import draw_case

    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.heldout import acquired_age, clocks_of, residuals_of

    rec, truth = draw_case("clock", 3, duration=20.0, f_host=62.5, board_name="mimu4444")
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    res = residuals_of(prep, fit)
    clocks = clocks_of(res)
    np.testing.assert_allclose(clocks["beat_hz"], truth["clock"]["beat_frequency"], atol=0.05)
    idx = np.searchsorted(truth["pose"]["time"], prep.time.numpy())
    a_true = centred(torch.as_tensor(truth["data_age"][idx])).numpy()
    a_est = centred(acquired_age(res, clocks)).numpy()
    r = [np.corrcoef(a_true[:, k], a_est[:, k])[0, 1] for k in range(prep.K)]
    assert min(r) > 0.6, r

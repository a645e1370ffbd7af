"""The held-out study's rate regressor and timing statistics are the detector's clock stage's
(accel_bayes.mismatch.heldout.residuals_of vs accel_bayes.mismatch.clock.clock_ab): on a board that
vibrates above the read's Nyquist rate the finite difference of the sampled gyro outputs folds the
vibration (flipped and shrunk), so the true data age loaded on it explains nothing of the gyro residual."""
from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.fixture(scope="module")
def case():
    from experiments.clockgen import draw_case

    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.heldout import residuals_of

    # 125 Hz cube6 clock case with 30–95 Hz vibration (clock.py's docstring: the regressor's case)
    rec, truth = draw_case("clock", 14, duration=8.0, f_host=125.0, board_name="cube6")
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    return prep, fit, residuals_of(prep, fit), truth


def test_true_data_age_on_the_heldout_regressor_explains_the_gyro_residual(case):
    """The gyro residual regressed on −d·ġ (d the true centred data age): the coefficient is ≈ 1
    on the detector's regressor R_k ω̇; on the finite difference ``prep.gyro_rate`` it was −0.71 (97e5674)."""
    from accel_bayes.mismatch.heldout import _mean_coeff, centred

    prep, fit, res, truth = case
    idx = np.searchsorted(truth["pose"]["time"], prep.time.numpy())
    d = centred(torch.as_tensor(truth["data_age"][idx], dtype=torch.float64))
    ok = res.ok["gyro"]
    c = _mean_coeff(res.y["gyro"][ok], res.rate["gyro"][ok], d[ok], torch.ones(int(ok.sum()), dtype=torch.bool))
    assert 0.6 < c < 1.4, c


def test_timing_statistics_are_the_clock_stages(case):
    """residuals_of's (a, b) per IMU are clock_ab's: the beat search sees what the detector sees."""
    from accel_bayes.mismatch.clock import clock_ab

    prep, fit, res, _ = case
    for k in (0, prep.K - 1):
        a, b, *_ = clock_ab(prep, fit, k)
        torch.testing.assert_close(res.timing_a[:, k], a.to(torch.float64))
        torch.testing.assert_close(res.timing_b[:, k], b.to(torch.float64))

"""``experiments/acc_correction_probe.py``: its patch zeroes exactly the clock's accelerometer half, keeps
the gyro half, and restores the package's method on exit."""
import dataclasses
import math

import pytest
import torch

from accel_bayes.physics.effects import SamplingClock, SignalContext
from experiments import acc_correction_probe as probe


@pytest.fixture(scope="module")
def twin():
    """(prep, baseline fit) of an 8 s synchronised clockgen twin: no clock in the data."""
    from accel_bayes.mismatch.fit import baseline_fit
    from accel_bayes.mismatch.prepared import prepare
    from experiments.clockgen import draw_case

    rec, _ = draw_case("twin", 1, duration=8.0)
    prep = prepare(rec)
    return prep, baseline_fit(prep)[0]


def _clock(imu=2, beat=3.3, phase=0.2):
    """A 1 ms sawtooth clock on ``imu`` (internal rate 1000 Hz + beat), no acc − gyro delay, rate scale 1."""
    return SamplingClock(imu=imu, params={"internal_rate_hz": 1000.0 + beat, "beat_hz": beat, "phase": phase,
                                          "age_rms_s": 1e-3 / math.sqrt(12), "filter_delay_acc_minus_gyro_s": 0.0,
                                          "rate_scale": 1.0})


def _with_acc(prep, d):
    """(prep, baseline fit) with ``d`` (T, K, 3) m/s² added to the accelerometer outputs."""
    from accel_bayes.mismatch.fit import baseline_fit

    prep_c = dataclasses.replace(prep, y_acc=(prep.y_acc + d) * prep.m_acc)
    return prep_c, baseline_fit(prep_c)[0]


def _ctx():
    t = torch.arange(0, 1, 0.01, dtype=torch.float64)
    w = 2 * math.pi * 3
    y = torch.stack([torch.sin(w * t)] * 3, -1)[:, None, :]
    rate = torch.stack([w * torch.cos(w * t)] * 3, -1)[:, None, :]
    z = torch.zeros(len(t), 3, dtype=torch.float64)
    return SignalContext(t, y[:, 0], rate[:, 0], z, torch.zeros(1, 3, dtype=torch.float64),
                         torch.tensor([[1.0, 0, 0, 0]], dtype=torch.float64), y, y, rate, None)


def test_acc_half_off_zeroes_the_accelerometer_half_only():
    ctx = _ctx()
    e = SamplingClock(imu=0, params={"beat_hz": 1.3, "phase": 0.1, "age_rms_s": 1e-3 / math.sqrt(12),
                                     "filter_delay_acc_minus_gyro_s": 2e-4})
    da0, dg0 = e.perturbation(None, ctx)
    assert float(da0.abs().max()) > 0
    original = SamplingClock.perturbation
    with probe.patched("acc_half_off"):
        da, dg = e.perturbation(None, ctx)
    assert SamplingClock.perturbation is original
    assert float(da.abs().max()) == 0.0
    assert torch.equal(dg, dg0)


def test_acc_half_auto_restores_and_decides_from_the_data(twin):
    """On a synchronised clockgen twin (no clock in the data) a clock's accelerometer half only adds misfit:
    not kept; with that half put into the data it removes most of the misfit it made: kept.  The package's
    ``clock_corrected`` is back in both modules after the patch."""
    import accel_bayes.mismatch.clock as mc
    import accel_bayes.mismatch.detector as md

    prep, fit = twin
    c = _clock()
    clean = probe.acc_half_lowers_misfit(prep, fit, c)
    assert not clean["keep"] and clean["misfit_with"] > clean["misfit_without"]
    da, _ = c.perturbation(None, fit.ctx)
    prep_c, fit_c = _with_acc(prep, da)  # the clock's acc half in the data
    with_clock = probe.acc_half_lowers_misfit(prep_c, fit_c, c)
    assert with_clock["keep"] and with_clock["misfit_with"] < 0.5 * with_clock["misfit_without"]
    original = mc.clock_corrected
    with probe.patched("acc_half_auto") as decisions:
        assert mc.clock_corrected is not original and md.clock_corrected is mc.clock_corrected
        mc.clock_corrected(prep, fit, [c])
        assert decisions[2]["keep"] is False
    assert mc.clock_corrected is original and md.clock_corrected is original


def test_acc_half_fit_recovers_a_scaled_and_delayed_acc_half(twin):
    """A clock's accelerometer half put into a synchronised twin's data with a scale 0.6 and 0.15 ms of extra
    delay, −(0.6·age + 0.15 ms)·ȧ: the fitted (λ, δ) recover both and remove most of the misfit."""
    prep, fit = twin
    c = _clock()
    d = torch.zeros_like(prep.y_acc)
    d[:, 2] = -(0.6 * c.age(fit.ctx.time)[:, None] + 1.5e-4) * fit.ctx.acc_rate[:, 2]
    prep_c, fit_c = _with_acc(prep, d)
    est = probe.acc_half_fit(prep_c, fit_c, c)
    assert abs(est["scale"] - 0.6) < 0.1 and abs(est["delay_s"] - 1.5e-4) < 3e-5
    assert est["misfit_with"] < 0.5 * est["misfit_without"]


def test_acc_delay_fit_with_the_scale_fixed(twin):
    """λ fixed at 1 (``acc_delay_fitted``): a clock's accelerometer half with 0.15 ms of extra delay put into the
    data, −(age + 0.15 ms)·ȧ: δ recovered."""
    prep, fit = twin
    c = _clock(imu=1, beat=-2.9, phase=0.7)
    d = torch.zeros_like(prep.y_acc)
    d[:, 1] = -(c.age(fit.ctx.time)[:, None] + 1.5e-4) * fit.ctx.acc_rate[:, 1]
    prep_c, fit_c = _with_acc(prep, d)
    est = probe.acc_half_fit(prep_c, fit_c, c, scale=1.0)
    assert est["scale"] == 1.0 and abs(est["delay_s"] - 1.5e-4) < 3e-5
    assert est["misfit_with"] < 0.5 * est["misfit_without"]

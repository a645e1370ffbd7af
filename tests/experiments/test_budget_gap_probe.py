"""``experiments/budget_gap_probe.py``: the read-skew offsets (sign and centring) and its patch of the
clocks' ages, restored on exit."""
import math

import torch

from accel_bayes.physics.effects import SamplingClock
from experiments import budget_gap_probe as probe


def _clock(imu, const, lam=1.0):
    c = SamplingClock(imu=imu, params={"internal_rate_hz": 1001.0, "beat_hz": 1.0, "phase": 0.3,
                                       "age_rms_s": 1e-3 / math.sqrt(12), "filter_delay_acc_minus_gyro_s": 0.0,
                                       "rate_scale": lam})
    c.stats = {"const_s": const, "rate_scale": lam}
    return c


def test_offsets_are_centred_and_read_later_is_younger():
    """Truth: IMU k read s_k later holds data s_k younger (age − s_k), centred over the board.  Fitted: the
    stage's constant c_k/λ_k (δ = c − W·frac, so age = W·frac − c), centred over the clocked IMUs."""
    tru = probe.truth_offsets({"clock": {"read_skew": [0.0, 1e-4, 2e-4]}})
    assert [round(v * 1e6, 9) for v in tru.values()] == [100.0, 0.0, -100.0]
    fit = probe.fitted_offsets([_clock(0, 3e-4, 2.0), _clock(2, 5e-4, 1.0)])  # c/λ = 1.5e-4, 5e-4
    assert math.isclose(fit[0], 1.75e-4, rel_tol=1e-12) and math.isclose(fit[2], -1.75e-4, rel_tol=1e-12)
    assert probe.fitted_offsets([]) == {}


def test_patch_shifts_both_ages_and_restores():
    c = _clock(1, 0.0)
    t = torch.linspace(0, 2, 50, dtype=torch.float64)
    a0, p0 = c.age(t), c.physical_age(t)
    old = SamplingClock.age, SamplingClock.physical_age
    with probe.patched("skew_truth", {"clock": {"read_skew": [0.0, 3e-4]}}) as off:
        assert math.isclose(off[1], -1.5e-4, rel_tol=1e-12)
        assert torch.allclose(c.age(t), a0 - 1.5e-4) and torch.allclose(c.physical_age(t), p0 - 1.5e-4)
    assert (SamplingClock.age, SamplingClock.physical_age) == old
    assert torch.equal(c.age(t), a0)
    with probe.patched("angular_jerk", {"clock": {"read_skew": [0.0, 3e-4]}}) as off:  # an option, no patch
        assert off == {} and SamplingClock.age is old[0]


def test_estimated_acc_blocks_take_most_of_the_planted_errors():
    """clockgen clock case 0 (mimu4444 at 125 Hz, 12 s; every accelerometer carries the generator's 3×3 error and
    bias; the regression knows nothing of them): inverting the pre-pass's blocks leaves under 40 % of the errors'
    spread over the triads in the outputs (the part common to every triad is not identifiable); measured against
    the generator's own inverse."""
    from experiments.clockgen import draw_case

    rec, truth = draw_case("clock", 0, duration=12.0)
    A, b, info = probe.estimated_acc_blocks(rec, truth)
    assert A.shape == (rec.acc.shape[1], 3, 3) and b.shape == (rec.acc.shape[1], 3)
    assert info["output_error_before_rms"] > 0.05, info  # real-size errors: ~0.1 m/s²
    assert info["output_error_after_rms"] < 0.4 * info["output_error_before_rms"], info

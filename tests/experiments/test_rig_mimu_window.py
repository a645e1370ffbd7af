"""The MIMU rig window (experiments/rig_mimu_pairs.window) leaves out rotation near the gyro range:
the first version picked exp_1's final spin at ±2000 °/s, which the rig model cannot fit."""
import numpy as np

from accel_bayes.data.recording import Recording
from experiments.rig_mimu_pairs import imus, window


def _recording():
    t = np.arange(0, 100, 0.01)
    w = np.zeros((len(t), 2, 3))
    w[(t > 10) & (t < 40), :, 0] = 2.0 * np.sin(t[(t > 10) & (t < 40)])[:, None]   # hand motion
    w[t > 70, :, 2] = 30.0                                                            # the spin
    return Recording(time=t, acc=np.zeros_like(w), gyro=w, nominal_position=np.zeros((2, 3)),
                     acc_noise_std=np.full(2, 0.04), gyro_noise_std=np.full(2, 0.003), gyro_range=34.9)


def test_window_takes_the_most_rotation_below_the_range_cap():
    rec = _recording()
    sub = window(rec, 20.0)
    assert 10.0 <= sub.time[0] and sub.time[-1] <= 40.0
    # without the cap the spin wins: the case the cap exists for
    assert window(rec, 20.0, range_fraction=1.0).time[0] > 70.0


def test_imus_cuts_the_recording_to_a_pair_with_the_first_as_reference():
    rec = _recording()
    rec.gyro[:, 1] += 1.0
    pair = imus(rec, [1, 0])
    assert pair.K == 2 and pair.reference_imu == 0
    assert np.array_equal(pair.gyro[:, 0], rec.gyro[:, 1])


def test_offset_difference_ignores_an_unidentified_lever_arms_nan_rows():
    """With the accs muted (experiments/rig_mimu_diagnose.py's gyro_timing) the lever arms are
    unidentified and their covariance rows NaN; w·C·w over the whole matrix then gave a NaN std for
    every offset difference, although the offsets' own block is finite."""
    from types import SimpleNamespace

    from experiments.rig_mimu_pairs import offset_difference
    labels = [(1, "r", 0), (1, "o", 0), (2, "o", 0)]
    cov = np.array([[np.nan, np.nan, np.nan], [np.nan, 4.0, 1.0], [np.nan, 1.0, 9.0]])
    res = SimpleNamespace(free_labels=labels, free_cov=cov, time_offset=np.array([0.0, 0.5, 2.0]))
    d, s = offset_difference(res, 1, 2)
    assert d == 1.5 and s == np.sqrt(4.0 + 9.0 - 2.0)
    assert offset_difference(res, 0, 2) == (2.0, 3.0)

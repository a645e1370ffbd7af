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

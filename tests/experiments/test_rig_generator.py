"""The concealed-rig generator (experiments/clockgen/rig.py) honours its arguments."""
import numpy as np

from experiments.clockgen.rig import draw_rig
from experiments.clockgen.sensing import ACC_LSB, GYRO_LSB


def test_draw_rig_rates_replace_the_drawn_rates():
    # on 97e5674 the drawing loop overwrote ``rates``: the benchmark's "200 Hz" rig ran at drawn rates
    rec, truth = draw_rig(3, duration=2.0, n_imu=2, rates=[200.0, 200.0])
    assert truth["rate"] == [200.0, 200.0]
    for k in range(2):
        step = np.diff(np.asarray(truth["stamps"][k]))
        assert abs(np.median(step) - 1 / 200.0) < 1e-5


def test_draw_rig_rates_keep_the_other_draws():
    _, a = draw_rig(3, duration=2.0, n_imu=2)
    _, b = draw_rig(3, duration=2.0, n_imu=2, rates=[200.0, 200.0])
    np.testing.assert_array_equal(a["time_offset"], b["time_offset"])
    np.testing.assert_array_equal(a["position"], b["position"])


def test_draw_rig_bias_walk_switch_changes_only_the_walk():
    # on 97e5674 the walk was drawn from the noise stream: switching it off redrew the gyro noise
    # and the stamp jitter, so rig_offset_decomposition's "no bias walk" compared other noise too
    rec_w, tw = draw_rig(4, duration=3.0, n_imu=2)
    rec_n, tn = draw_rig(4, duration=3.0, n_imu=2, bias_walk=False)
    np.testing.assert_array_equal(rec_w.time, rec_n.time)          # the same jittered stamps
    dg = np.nan_to_num(rec_w.gyro - rec_n.gyro)
    da = np.nan_to_num(rec_w.acc - rec_n.acc)
    # a 3 s walk of 1e-4 m/s²/√s (1e-5 rad/s/√s) moves a reading by at most one quantisation step;
    # another noise draw (0.02–0.06 m/s², 0.2–0.6 °/s) by many
    assert np.abs(da).max() > 0 and np.abs(da).max() <= 1.01 * ACC_LSB
    assert np.abs(dg).max() <= 1.01 * GYRO_LSB

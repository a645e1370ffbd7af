"""The concealed-rig generator (experiments/clockgen/rig.py) honours its arguments."""
import numpy as np

from experiments.clockgen.rig import draw_rig


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

"""``experiments/gyro_common_stage_probe.py``: the generator's shared gyro error against a hand computation, and the
document's cells on a made-up record."""
import numpy as np

from experiments import gyro_common_stage_probe as gp


class _Rec:
    def __init__(self, quats):
        self.nominal_orientation = np.asarray(quats, dtype=np.float64)


def test_shared_error_is_the_array_frame_mean():
    # two gyros, the second turned 90° about z (sensor x = array y): the same sensor-frame x-scale error on both
    # is an x error on the first and a y error on the second in the array frame, so each shares half of it
    s = np.sqrt(0.5)
    rec = _Rec([[1, 0, 0, 0], [s, 0, 0, s]])
    M = np.diag([1.02, 1.0, 1.0])
    truth = {"errors": {"gyro": [{"M": M.tolist()}, {"M": M.tolist()}]}}
    assert abs(gp.shared_gyro_error(rec, truth) - 0.01) < 1e-12


def test_markdown_cells():
    v = [{"variant": name, "statistic": st, "statistic_model": 10 * st, "threshold": 39.0, "kept": k, "max_abs": mx,
          "blocks": 0, "seconds": 1.0}
         for (name, _, _), st, k, mx in zip(gp.VARIANTS, (62.0, 26.0, 54.0, 32.0), (True, False, True, False),
                                            (0.219, None, 0.293, None))]
    L = "\n".join(gp.markdown([{"seed": 6, "board": "mimu4444", "f_host": 200.0, "gyro_linear": True,
                                "shared_gyro_error": 0.0104, "variants": v}], "cmd", 1.0))
    assert ("| clock-006 | mimu4444 | 200 | 0.010 | 62 / 620 / 39: **0.219** | 26 / 260 / 39: — | 54 / 540 / 39: **0.293** "
            "| 32 / 320 / 39: — |") in L

"""experiments/mimu_blind_acc.py: the crop, the comparison against the reference and the document, on hand-made
records (the real run is the study itself)."""
import numpy as np
import pytest

from accel_bayes.simulate import simulate
from experiments import mimu_blind_acc as mba
from experiments import c21_coverage as cov


def test_crop_keeps_the_last_seconds_with_their_times():
    rec = simulate(cov.square_board(0.03), "smooth", 300, 100.0, seed=5, clip=False).recording
    t = np.asarray(rec.time)
    out = mba.crop(rec, 0.995)  # 100 Hz: the samples at 2.00 … 2.99 s
    kept = np.asarray(out.time)
    assert kept[0] >= t[-1] - 0.995 and kept[-1] == t[-1]
    assert len(kept) == 100
    np.testing.assert_array_equal(np.asarray(out.acc), np.asarray(rec.acc)[-100:])


def _rec(mean, std, ref=0):
    return {"mean": mean, "std": std, "reference_imu": ref}


def test_compare_is_relative_to_each_runs_reference_imu():
    """Both runs' means are taken relative to the reference IMU before differencing (a common offset
    of every IMU is no difference), and z divides by the combined std."""
    r = _rec([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]], [[0, 0, 0], [3e-4, 3e-4, 3e-4], [3e-4, 3e-4, 3e-4]])
    b = _rec([[1.0, 1, 1], [1.1004, 1, 1], [1, 1.1, 1]], [[0, 0, 0], [4e-4, 4e-4, 4e-4], [4e-4, 4e-4, 4e-4]])
    c = mba.compare(b, r)
    assert c["names"] == ["r[1, x]", "r[1, y]", "r[1, z]", "r[2, x]", "r[2, y]", "r[2, z]"]
    np.testing.assert_allclose(c["d_um"], [400, 0, 0, 0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(c["z"][0], 4e-4 / 5e-4)


def test_markdown_pools_the_experiments():
    r = _rec([[0.0, 0, 0], [0.1, 0, 0]], [[0, 0, 0], [3e-4, 3e-4, 3e-4]])
    r.update(intrinsics_applied=True)
    b = _rec([[0.0, 0, 0], [0.1005, 0, 0]], [[0, 0, 0], [4e-4, 4e-4, 4e-4]])
    b.update(intrinsics_applied=False, detect_seconds=100.0, calibrate_seconds=20.0,
             acc_blocks={"tau_matrix": 0.006, "tau_bias_m_s2": 0.08, "report_blocks": [0, 1],
                         "common_shift_std_median_m": 1e-4})
    text = "\n".join(mba.markdown({1: (r, b, None, None, None)}, "cmd", 1.0, 130.0))
    assert "| 1 | yes / no | 2/8 | 0.60 / 0.080 |" in text and "| — / — |" in text  # one layer: no shift
    assert "blind z RMS 0.58, max |z| 1.00, beyond 3: 0" in text
    with pytest.raises(SystemExit):
        mba.main(["--seconds", "0", "--no-doc"])


def test_layer_shift_is_lower_minus_upper_layer():
    """IMUs more than 1 mm below the reference IMU form the lower layer; the shift is the mean d there less
    the mean d of the upper layer's other IMUs."""
    r = _rec([[0.0, 0, 0], [0, 0, -0.002], [0.02, 0, 0], [0.02, 0, -0.002]], [[1e-4] * 3] * 4)
    b = _rec([[0.0, 0, 0], [-0.0001, 0.0002, -0.002], [0.02, 0, 0], [0.0199, 0.0002, -0.002]], [[1e-4] * 3] * 4)
    np.testing.assert_allclose(mba.layer_shift(b, r), [-100, 200], atol=1e-6)

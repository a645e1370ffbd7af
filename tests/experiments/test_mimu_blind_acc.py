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


def _report(blocks):
    """A report with one acc_scale finding per (IMU, rotation about the sensor's z rad, offset x)."""
    out = []
    for k, a, bx in blocks:
        M = np.zeros((3, 3))
        M[1, 0], M[0, 1] = a, -a
        out.append({"effect": "acc_scale", "imu": k, "parameters": {"scale": M.tolist(), "bias": [bx, 0.0, 0.0]},
                    "std": {"matrix": np.full((3, 3), 1e-3).tolist(), "bias": [0.01] * 3}})
    # each chip's gyro turned by half its accelerometer's rotation: correlation 1 over the chips
    gy = []
    for k, a, _ in blocks:
        G = np.zeros((3, 3))
        G[1, 0], G[0, 1] = 0.5 * a, -0.5 * a
        gy.append({"effect": "gyro_scale", "imu": k, "parameters": {"scale": G.tolist(), "bias": [0.0] * 3}})
    return {"findings": out + gy + [{"effect": "sampling_clock", "imu": 0, "parameters": {}}]}


def test_chip_blocks_reads_each_chips_rotation_in_the_array_frame_and_tests_its_repeatability():
    """A chip flipped about x (R = diag(1, −1, −1)) reads its own rotation with the opposite sign about the
    board's normal; per-chip constants plus small experiment noise give a large F, pure noise an F near 1."""
    R = np.stack([np.eye(3), np.diag([1.0, -1.0, -1.0]), np.eye(3)])
    g = np.random.default_rng(0)
    chips = [-2e-3, -3e-3, 4e-3]
    reps = {e: _report([(k, chips[k] + 2e-4 * g.standard_normal(), 0.1 * k) for k in range(3)]) for e in range(1, 7)}
    cb = mba.chip_blocks(reps, R)
    rot = np.asarray(cb["rot_mrad"])
    np.testing.assert_allclose(rot.mean(0), [-2.0, 3.0, 4.0], atol=0.2)  # IMU 1 flipped: −3 → +3
    np.testing.assert_allclose(np.asarray(cb["rot_sd_mrad"]), 0.5 * np.hypot(1.0, 1.0), rtol=1e-12)
    assert cb["anova_rot"]["F"] > 100 and cb["anova_rot"]["df"] == [2, 15]
    np.testing.assert_allclose(np.asarray(cb["offset_m_s2"])[0, :, 0], [0.0, 0.1, 0.2])
    noise = {e: _report([(k, 2e-4 * g.standard_normal(), 0.0) for k in range(3)]) for e in range(1, 7)}
    assert mba.chip_blocks(noise, R)["anova_rot"]["F"] < 6  # F(2, 15) beyond 6.4 has p < 1 %
    np.testing.assert_allclose(np.asarray(cb["gyro_rot_mrad"]), 0.5 * rot, rtol=1e-12)
    np.testing.assert_allclose(cb["acc_gyro_corr"], 1.0, atol=1e-12)
    md = "\n".join(mba.chip_markdown(cb, {1}))
    assert "| 1 | under |" in md and "F = " in md

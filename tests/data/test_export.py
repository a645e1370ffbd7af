"""``accel-bayes export``: Kalibr IMU chain / OpenVINS kalibr_imu_chain.yaml (accel_bayes.data.export).

Checked against what the exporter did not write: hand-written T_i_b of a board whose reference
IMU is yawed 90°; SciPy's rotations for estimated orientations; the files read back by the
parsers the target tools use (PyYAML for Kalibr, OpenCV's FileStorage for OpenVINS); and
OpenVINS' correction equations (ov_msckf, Propagator: a_I = R_ACCtoIMU Da (a_m − b_a),
w_I = R_GYROtoIMU Dw (w_m − b_g − Tg a_I), Da = Ta⁻¹, Dw = Tw⁻¹) applied with the parsed
matrices, reproducing the package's corrected readings.
"""
import json
import math

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from accel_bayes.cli import main
from accel_bayes.prep.intrinsics import Intrinsics
from accel_bayes.data.io import write_recording
from accel_bayes.data.positions import positions_document, write_positions
from accel_bayes.data.recording import Recording

cv2 = pytest.importorskip("cv2")

H = math.sqrt(0.5)
YAW90 = [H, 0.0, 0.0, -H]  # DESIGN §7.0 worked example: sensor x along the array's +y
FLIP_X = [0.0, 1.0, 0.0, 0.0]  # 180° about x: R = diag(1, −1, −1)
RATE = 200.0
SIG_A, SIG_G = 0.02, 0.003
RW_A, RW_G = 3e-3, 2e-5  # as stated at import (array description), m/s^3/√Hz, rad/s^2/√Hz


def _board(tmp_path):
    """4 IMUs; the reference (label 0) yawed 90°, IMU 2 flipped about x, IMU 3 yawed 90°."""
    rng = np.random.default_rng(0)
    T, K = 50, 4
    pos = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0], [0.0, 0.0, 0.01]])
    quat = np.array([YAW90, [1.0, 0.0, 0.0, 0.0], FLIP_X, YAW90])
    rec = Recording(time=np.arange(T) / RATE, acc=rng.normal(0, 1, (T, K, 3)), gyro=rng.normal(0, 0.1, (T, K, 3)),
                    nominal_position=pos, nominal_orientation=quat, acc_noise_std=np.full(K, SIG_A),
                    gyro_noise_std=np.full(K, SIG_G),
                    attrs={"acc_random_walk": [RW_A] * K, "gyro_random_walk": [RW_G] * K})
    path = write_recording(rec, tmp_path / "rec.nc")
    return rec, path


def _positions(tmp_path, orientations=None, name="positions.json"):
    means = np.array([[0.0, 0.0, 0.0], [0.0101, 0.0, 0.0], [0.0, 0.0199, 0.0], [0.0, 0.0, 0.0102]])
    covs = np.zeros((4, 3, 3))
    covs[1] = np.diag([1e-8, 2e-8, 3e-8])
    covs[2] = np.diag([1e-8, 4e-8, 9e-8])
    covs[3] = np.diag([1e-8, 4e-8, 9e-8])
    doc = positions_document(method="map", reference_imu=0, means=means, covs=covs, orientations=orientations,
                             diagnostics={"seconds": 1.0})
    return write_positions(doc, tmp_path / name)


def _export(tmp_path, rec_path, pos_path, *extra, out="chain.yaml"):
    o = tmp_path / out
    assert main(["export", str(rec_path), "--positions", str(pos_path), "-o", str(o), *extra]) == 0
    return o


def _cv_matrix(node):
    return np.array([[node.at(i).at(j).real() for j in range(node.at(i).size())] for i in range(node.size())])


def test_kalibr_chain_hand_written_t_i_b(tmp_path):
    rec, rp = _board(tmp_path)
    out = _export(tmp_path, rp, _positions(tmp_path))
    doc = yaml.safe_load(out.read_text())
    assert sorted(doc) == ["imu0", "imu1", "imu2", "imu3"]
    # Body = the reference IMU's frame (sensor x = array +y, sensor y = array −x).  IMU 1 (identity,
    # at array (0.0101, 0, 0)): body x (array +y) is IMU 1's +y, body y (array −x) is IMU 1's −x,
    # and the body origin is at IMU 1's (−0.0101, 0, 0).
    # (√½ in the quaternion: equal to float precision.)
    np.testing.assert_allclose(doc["imu1"]["T_i_b"], [[0.0, -1.0, 0.0, -0.0101], [1.0, 0.0, 0.0, 0.0],
                                                      [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], rtol=0, atol=1e-15)
    # IMU 2 (y and z flipped, at array (0, 0.0199, 0)): body x → IMU 2's −y, body y → −x, body z → −z;
    # the body origin is 0.0199 m along array −y, i.e. along IMU 2's +y.
    np.testing.assert_allclose(doc["imu2"]["T_i_b"], [[0.0, -1.0, 0.0, 0.0], [-1.0, 0.0, 0.0, 0.0199],
                                                      [0.0, 0.0, -1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(doc["imu0"]["T_i_b"], np.eye(4))
    # IMU 3 yawed like the reference: pure translation, −0.0102 along z.
    np.testing.assert_allclose(doc["imu3"]["T_i_b"], [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, -0.0102], [0, 0, 0, 1]],
                               rtol=0, atol=1e-15)
    # Covariance in IMU 3's frame: its x is the array's y (variance 4e-8), its y the array's x.
    np.testing.assert_allclose(doc["imu3"]["T_i_b_translation_cov"], np.diag([4e-8, 1e-8, 9e-8]), rtol=1e-12, atol=1e-22)
    e = doc["imu1"]
    assert e["accelerometer_noise_density"] == pytest.approx(SIG_A / math.sqrt(RATE), rel=1e-12)
    assert e["gyroscope_noise_density"] == pytest.approx(SIG_G / math.sqrt(RATE), rel=1e-12)
    assert e["update_rate"] == pytest.approx(RATE, rel=1e-12) and e["rostopic"] == "/imu1"
    assert e["model"] == "calibrated"
    # Random walks as stated at import (no rests in this recording); no time offset estimated.
    assert e["accelerometer_random_walk"] == RW_A and e["gyroscope_random_walk"] == RW_G
    assert "time_offset" not in e
    text = out.read_text()
    assert "# time_offset: not estimated" in text and "stated (array description" in text
    assert "p_i = T_i_b p_b" in text
    # The output is not replaced without --overwrite.
    assert main(["export", str(rp), "--positions", str(tmp_path / "positions.json"), "-o", str(out)]) == 2


def test_estimated_orientations_used_scipy_reference(tmp_path):
    rec, rp = _board(tmp_path)
    rng = np.random.default_rng(4)
    q = np.array(rec.nominal_orientation)
    for k in (0, 1, 3):  # small estimated deviations; IMU 2's stays as estimated = nominal
        dq = Rotation.from_rotvec(rng.normal(0, 0.02, 3))
        r = dq * Rotation.from_quat(np.roll(q[k], -1))  # scipy: (x, y, z, w)
        q[k] = np.roll(r.as_quat(), 1)
    out = _export(tmp_path, rp, _positions(tmp_path, orientations=q))
    doc = yaml.safe_load(out.read_text())
    R = [Rotation.from_quat(np.roll(q[k], -1)).as_matrix() for k in range(4)]  # array → sensor
    means = [[0.0, 0.0, 0.0], [0.0101, 0.0, 0.0], [0.0, 0.0199, 0.0], [0.0, 0.0, 0.0102]]
    for k in range(4):
        T = np.array(doc[f"imu{k}"]["T_i_b"])
        np.testing.assert_allclose(T[:3, :3], R[k] @ R[0].T, atol=1e-14)
        np.testing.assert_allclose(T[:3, 3], -R[k] @ means[k], atol=1e-16)
        # Round trip: the body origin maps to IMU k's view of the reference's position.
        np.testing.assert_allclose(T @ [0, 0, 0, 1], np.r_[R[k] @ (np.zeros(3) - means[k]), 1], atol=1e-16)
    assert "orientation from positions.json" in out.read_text()


def _intrinsics(K=4):
    T = np.tile(np.eye(3), (K, 1, 1))
    T[1] = [[1.012, 0.0, 0.0], [0.011, 0.987, 0.0], [-0.02, 0.006, 1.021]]
    T[2] = [[0.995, 0.0, 0.0], [-0.004, 1.003, 0.0], [0.009, -0.013, 0.99]]
    b = np.zeros((K, 3))
    b[1] = [0.05, -0.12, 0.2]
    b[2] = [-0.03, 0.01, 0.07]
    cov = np.tile(np.diag([1e-6] * 3 + [1e-8] * 6), (K, 1, 1))
    return Intrinsics(acc_bias=b, acc_matrix=T, acc_cov=cov, gyro_bias=np.full((K, 3), 1e-3),
                      gyro_bias_cov=np.tile(np.eye(3) * 1e-10, (K, 1, 1)), residual_rms=np.full(K, 0.01),
                      chi2_per_dof=np.ones(K), acc_noise_std=np.full(K, SIG_A), n_rests=np.full(K, 12),
                      n_orientations=12, g=9.80665)


def test_openvins_file_read_by_opencv_reproduces_package_correction(tmp_path):
    rec, rp = _board(tmp_path)
    intr = _intrinsics()
    ip = tmp_path / "intrinsics.json"
    intr.to_json(ip)
    out = _export(tmp_path, rp, _positions(tmp_path), "--intrinsics", str(ip), "--format", "openvins",
                  out="kalibr_imu_chain.yaml")
    assert out.read_text().startswith("%YAML:1.0")
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    raw = np.random.default_rng(7).normal(0, 9.0, (200, 4, 3))
    package = intr.correct_acc(raw)  # T (a_raw − b), what calibrate works with
    for k in range(4):
        n = fs.getNode(f"imu{k}")
        assert n.getNode("model").string() == "kalibr"
        Ta, R_IMUtoACC = _cv_matrix(n.getNode("Ta")), _cv_matrix(n.getNode("R_IMUtoACC"))
        b_a = np.array([n.getNode("accelerometer_bias").at(i).real() for i in range(3)])
        assert np.all(np.triu(Ta, 1) == 0)  # lower-triangular, as OpenVINS' kalibr model keeps Da
        Da = np.linalg.inv(Ta)
        assert np.abs(np.triu(Da, 1)).max() < 1e-15  # nothing lost in OpenVINS' lower-triangular vec_da
        R_ACCtoIMU = R_IMUtoACC.T
        openvins = (R_ACCtoIMU @ Da @ (raw[:, k] - b_a).T).T
        np.testing.assert_allclose(openvins, package[:, k], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(_cv_matrix(n.getNode("T_i_b")), yaml.safe_load(
            out.read_text().split("\n", 1)[1])[f"imu{k}"]["T_i_b"])  # both parsers read the same numbers
        # No gyro estimate given: identity / zero, and said so.
        np.testing.assert_array_equal(_cv_matrix(n.getNode("Tw")), np.eye(3))
        np.testing.assert_array_equal(_cv_matrix(n.getNode("Tg")), np.zeros((3, 3)))
        assert n.getNode("accelerometer_noise_density").real() == pytest.approx(SIG_A / math.sqrt(RATE), rel=1e-12)
    fs.release()
    assert "Tw:  # not estimated: identity" in out.read_text()


def test_ta_cov_matches_finite_differences(tmp_path):
    from accel_bayes.data.export import openvins_acc_intrinsics

    intr = _intrinsics()
    T, cov = intr.acc_matrix[1], intr.acc_cov[1]
    Ta, _, Ta_cov = openvins_acc_intrinsics(T, cov)
    # Independent: central differences of inv() over the six entries of T.
    idx = [(0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1)]
    order = [(0, 0), (1, 0), (2, 0), (1, 1), (2, 1), (2, 2)]
    J = np.zeros((6, 6))
    for j, (a, b) in enumerate(idx):
        E = np.zeros((3, 3))
        E[a, b] = 1e-6
        d = (np.linalg.inv(T + E) - np.linalg.inv(T - E)) / 2e-6
        J[:, j] = [d[i, k] for i, k in order]
    np.testing.assert_allclose(Ta_cov, J @ cov[3:, 3:] @ J.T, rtol=1e-7, atol=1e-20)


def _report():
    def finding(effect, imu, axis, params):
        return {"effect": effect, "imu": imu, "axis": axis, "evidence": 100.0, "parameters": params,
                "where": {"regime": "all", "time_s": None}, "explanation": "test finding"}

    return {"schema": "accel_bayes.mismatch/1", "mismatch_detected": True, "threshold": 19.5,
            "baseline": {"loglik": -1.0, "chi2_per_dof": 3.0, "dof": 1000},
            "findings": [finding("gyro_scale", 1, "x", {"scale": 0.01}),
                         finding("gyro_scale", 1, "y", {"scale": 0.005, "from_axis": "z"}),
                         finding("gyro_scale", 1, "z", {"scale": -0.008, "from_axis": "x"}),
                         finding("gyro_g_sensitivity", 1, None, {"sensitivity": [1e-3, 0.0, 2e-3]}),
                         finding("time_offset", 2, None, {"offset": 0.0005})],
            "refined": {"effects": ["gyro_scale"], "loglik": -0.5, "chi2_per_dof": 1.0}}


def test_gyro_couplings_from_report_and_time_offset(tmp_path):
    rec, rp = _board(tmp_path)
    mp = tmp_path / "report.json"
    mp.write_text(json.dumps(_report()))
    out = _export(tmp_path, rp, _positions(tmp_path), "--mismatch", str(mp), "--format", "openvins",
                  out="kalibr_imu_chain.yaml")
    fs = cv2.FileStorage(str(out), cv2.FILE_STORAGE_READ)
    n = fs.getNode("imu1")
    Tw, Rg, Tg = (_cv_matrix(n.getNode(x)) for x in ("Tw", "R_IMUtoGYRO", "Tg"))
    assert np.all(np.triu(Tw, 1) == 0) and np.all(np.diag(Tw) > 0)
    np.testing.assert_allclose(Rg @ Rg.T, np.eye(3), atol=1e-15)
    assert np.linalg.det(Rg) == pytest.approx(1.0, abs=1e-14)
    # Raw gyro by the DESIGN §7.2 effect definitions, written out by hand:
    # x += 0.01 ω_x;  y += 0.005 ω_z;  z += −0.008 ω_x;  x += 1e-3 f_x, z += 2e-3 f_z.
    rng = np.random.default_rng(9)
    w, f = rng.normal(0, 2.0, (100, 3)), rng.normal(0, 9.0, (100, 3))
    raw = w.copy()
    raw[:, 0] += 0.01 * w[:, 0] + 1e-3 * f[:, 0]
    raw[:, 1] += 0.005 * w[:, 2]
    raw[:, 2] += -0.008 * w[:, 0] + 2e-3 * f[:, 2]
    w_hat = (Rg.T @ np.linalg.inv(Tw) @ (raw - f @ Tg.T).T).T  # OpenVINS, zero gyro bias, a_I = f
    np.testing.assert_allclose(w_hat, w, rtol=0, atol=1e-12)
    assert fs.getNode("imu2").getNode("time_offset").real() == 0.0005
    assert fs.getNode("imu1").getNode("time_offset").empty()
    fs.release()


def test_export_refusals(tmp_path, capsys):
    rec, rp = _board(tmp_path)
    # A positions file for another board (3 IMUs).
    doc = positions_document(method="map", reference_imu=0, means=np.zeros((3, 3)), covs=np.zeros((3, 3, 3)),
                             diagnostics={"seconds": 1.0})
    bad = write_positions(doc, tmp_path / "other.json")
    o = tmp_path / "chain.yaml"
    assert main(["export", str(rp), "--positions", str(bad), "-o", str(o)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "positions: 3 IMUs, the recording has 4" in err and not o.exists()
    assert main(["export", str(rp), "--positions", str(tmp_path / "missing.json"), "-o", str(o)]) == 2
    assert "--positions" in capsys.readouterr().err and not o.exists()
    mp = tmp_path / "report.json"
    r = _report()
    r["findings"][0]["effect"] = "gyro_wobble"
    mp.write_text(json.dumps(r))
    assert main(["export", str(rp), "--positions", str(_positions(tmp_path)), "--mismatch", str(mp), "-o", str(o)]) == 2
    assert "unknown effect 'gyro_wobble'" in capsys.readouterr().err and not o.exists()

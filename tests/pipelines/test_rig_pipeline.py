"""Rig calibration end to end (issue #28 item 1): multi-rate recordings in format v1, the
``calibrate`` dispatch to the rig model, recovery on a short concealed rig, and the
``unidentified`` path of an under-excited rig."""
import json

import numpy as np
import pytest
import torch

from experiments.clockgen import draw_case, write_case

from accel_bayes.cli import main
from accel_bayes.data import io
from accel_bayes.data.validation import validate_recording
from accel_bayes.errors import RecordingError
from accel_bayes.physics.geometry import matrix_to_quat, quat_exp, quat_log, quat_mul, quat_to_matrix
from accel_bayes.pipelines.rig import is_rig


@pytest.fixture(scope="module")
def rig_file(tmp_path_factory):
    rec, truth = draw_case("rig", 7, n_imu=2, duration=10.0)
    # a stated nominal orientation 30° from the truth: the data must win and say so
    q = torch.as_tensor(np.asarray(truth["orientation"][1], float))
    rec.nominal_orientation[1] = quat_mul(q, quat_exp(torch.tensor([np.radians(30.0), 0.0, 0.0],
                                                                    dtype=torch.float64))).numpy()
    path = write_case(rec, truth, tmp_path_factory.mktemp("rig") / "rig.nc")
    return path, rec, truth


def test_multirate_rig_is_written_and_read_as_format_v1(rig_file):
    path, rec, _ = rig_file
    assert path.suffix == ".nc"  # validation no longer refuses NaN-union recordings
    back = io.read_recording(path)
    assert np.array_equal(np.isnan(back.acc), np.isnan(rec.acc)) and np.isnan(back.acc).any()
    assert is_rig(back)


def test_partly_missing_sample_is_refused(rig_file):
    _, rec, _ = rig_file
    bad = rec.copy()
    t = int(np.flatnonzero(np.isfinite(bad.acc[:, 1, 0]))[5])
    bad.acc[t, 1, 2] = np.nan  # one axis of a present sample: damaged, not missing
    with pytest.raises(RecordingError, match=r"acc: 1 non-finite value.*IMU 1"):
        validate_recording(bad)
    bad = rec.copy()
    t = int(np.flatnonzero(np.isfinite(bad.acc[:, 1, 0]))[5])
    bad.gyro[t, 1] = np.nan  # acc present, gyro missing at the same stamp
    with pytest.raises(RecordingError, match=r"gyro: .*IMU 1"):
        validate_recording(bad)


def test_two_imus_without_gyros_are_still_refused(rig_file):
    _, rec, _ = rig_file
    bad = rec.copy()
    bad.gyro[:, 1] = np.nan
    with pytest.raises(RecordingError, match=r"nominal_position: accelerometer triads: at least 3"):
        validate_recording(bad)


def _rot_err_deg(q_hat, q_true):
    R = quat_to_matrix(torch.as_tensor(np.asarray(q_hat, float))) @ quat_to_matrix(torch.as_tensor(np.asarray(q_true, float))).T
    return float(np.degrees(quat_log(matrix_to_quat(R)).norm()))


def test_calibrate_dispatches_to_rig_and_recovers_the_concealed_rig(rig_file, tmp_path, capsys):
    path, _, truth = rig_file
    rc = main(["calibrate", str(path), "--out", str(tmp_path / "cal")])
    out, err = capsys.readouterr()
    assert rc == 0, err
    assert "rig model" in err
    warn = [ln for ln in err.splitlines() if "nominal_orientation: IMU 1" in ln]
    assert len(warn) == 1 and "contradict" in warn[0] and "30.0°" in warn[0], err
    doc = json.loads((tmp_path / "cal" / "positions.json").read_text())
    assert doc["schema"] == "accel_bayes.positions/1" and doc["model"] == "rig" and doc["method"] == "map"
    e = doc["imus"][1]
    assert np.linalg.norm(np.subtract(e["mean"], truth["position"][1])) < 2e-3
    assert _rot_err_deg(e["orientation"], truth["orientation"][1]) < 0.2
    assert abs(e["time_offset"]["mean"] - truth["time_offset"][1]) < 0.5e-3
    assert abs(e["clock_drift"]["mean"] - truth["clock_drift"][1]) < 5 * e["clock_drift"]["std"] + 1e-6
    assert np.shape(e["orientation_cov"]) == (3, 3) and e["time_offset"]["std"] > 0
    assert doc["diagnostics"]["unidentified"] == []
    # the block sandwich beside §7.3's Laplace std, and the reported one by the rig's rule
    for blk, pre in ((e, ""), (e, "orientation_"), (e["time_offset"], ""), (e["clock_drift"], "")):
        lap = blk["std"] if pre == "" else e["orientation_std"]
        rob, rep, used = blk[f"{pre}std_robust"], blk[f"{pre}std_reported"], blk[f"{pre}robust_used"]
        assert np.allclose(blk[f"{pre}std_ratio"], np.divide(rob, lap))
        assert np.allclose(rep, np.where(used, rob, lap))
    assert np.allclose(np.sqrt(np.diag(e["cov_robust"])), e["std_robust"])
    assert (("block sandwich" in err) == any(np.any(x) for x in (e["robust_used"], e["orientation_robust_used"],
                                                                  e["time_offset"]["robust_used"],
                                                                  e["clock_drift"]["robust_used"])))
    # the walks the model marginalised: the ones the recording states, so no assumed-walk warning
    assert e["bias_random_walk"] == {"gyro": 1e-5, "acc": 1e-4} and "random_walk" not in err
    # the export gives each IMU of the 2-rate rig its own update_rate (tests/data/test_export_consumers.py);
    # the random walks a consumer needs stated, as an import from a description gives them
    rw = io.read_recording(path)
    rw.attrs.update(acc_random_walk=[3e-3, 3e-3], gyro_random_walk=[2e-5, 2e-5])
    rc = main(["export", str(io.write_recording(rw, tmp_path / "rw.nc")), "--positions", str(tmp_path / "cal" / "positions.json"),
               "-o", str(tmp_path / "chain.yaml")])
    assert rc == 0, capsys.readouterr().err
    import yaml
    chain = yaml.safe_load((tmp_path / "chain.yaml").read_text())
    for j in range(2):
        assert chain[f"imu{j}"]["update_rate"] == pytest.approx(truth["rate"][j], rel=1e-4)


def test_under_excited_rig_reports_the_lever_arm_along_the_axis_unidentified(tmp_path, capsys):
    rec, truth = draw_case("rig", 1001, n_imu=2, duration=10.0, rot_axes=(2,))
    path = write_case(rec, truth, tmp_path / "flat.nc")
    rc = main(["calibrate", str(path), "--out", str(tmp_path / "cal")])
    err = capsys.readouterr().err
    assert rc == 4, err
    assert "unidentified" in err and "IMU 1 position" in err
    doc = json.loads((tmp_path / "cal" / "positions.json").read_text())
    assert "position" in doc["imus"][1]["unidentified"]
    assert {"imu": 1, "parameter": "position"} in doc["diagnostics"]["unidentified"]
    # an unidentified coordinate has no robust std either (null, not a number)
    e = doc["imus"][1]
    assert None in e["std_robust"] and None in e["std_reported"] and e["robust_used"][e["std_robust"].index(None)] is False


def test_dispatch_only_rigs(rig_file):
    """Single-clock boards of >= 3 triads stay with the [C21] pipeline; a multi-rate recording
    without a gyro on every IMU has no model to go to and is refused naming gyro."""
    from accel_bayes.errors import UserError
    board, _ = draw_case("clean", 0, board_name="plate4", duration=2.0)
    assert not is_rig(board)
    _, rec, _ = rig_file
    bad = rec.copy()
    bad.gyro[:, 1] = np.nan
    with pytest.raises(UserError, match=r"^gyro: a multi-rate recording .* needs a gyroscope on every IMU"):
        is_rig(bad)


def test_a_wandering_offset_is_reported_with_the_sandwich_and_one_warning(tmp_path, capsys):
    """A timing the rig model cannot hold (clockgen seed 7, 2 IMUs, 15 s, IMU 1's offset wandering
    with RMS 0.3 ms): the offset's misspecification test fires, so ``std_reported`` is the block
    sandwich (larger than the Laplace ``std``, which keeps its §7.3 meaning), one warning line names
    it and the table marks it."""
    from experiments.clockgen.rig import draw_rig
    rec, truth = draw_rig(7, n_imu=2, duration=15.0, offset_wander=3e-4)
    rc = main(["calibrate", str(write_case(rec, truth, tmp_path / "wander.nc")), "--out", str(tmp_path / "cal")])
    out, err = capsys.readouterr()
    assert rc == 0, err
    warn = [ln for ln in err.splitlines() if "block sandwich" in ln and "warning" in ln]
    assert len(warn) == 1 and "IMU 1 time_offset" in warn[0], err
    row = [ln for ln in (out + err).splitlines() if ln.strip().startswith("1 ")]
    assert len(row) == 1 and "*" in row[0], out + err
    t = json.loads((tmp_path / "cal" / "positions.json").read_text())["imus"][1]["time_offset"]
    assert t["robust_used"] is True and t["std_reported"] == t["std_robust"] > 2 * t["std"]

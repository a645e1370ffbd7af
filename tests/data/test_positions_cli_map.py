"""positions.json (DESIGN §7.3) writer/reader and the `accel-bayes map` command."""
import json

import numpy as np
import pytest

from accel_bayes.physics import arrays
from accel_bayes.cli import main
from accel_bayes.errors import UserError
from accel_bayes.data.io import read_truth, write_recording
from accel_bayes.data.positions import positions_document, read_positions, write_positions
from accel_bayes.simulate import simulate


def test_document_roundtrip_and_checks(tmp_path):
    K = 4
    means = np.zeros((K, 3))
    means[1:] = np.arange(9).reshape(3, 3) * 1e-3
    covs = np.zeros((K, 3, 3))
    covs[1:] = np.eye(3) * 1e-8
    doc = positions_document(method="map", reference_imu=0, means=means, covs=covs, diagnostics={"seconds": 1.5})
    p = write_positions(doc, tmp_path / "positions.json")
    back = read_positions(p)
    assert back["schema"] == "accel_bayes.positions/1" and back["method"] == "map"
    np.testing.assert_allclose(back["means"], means)
    np.testing.assert_allclose(back["covs"], covs)
    assert [e["imu"] for e in back["imus"]] == [0, 1, 2, 3]
    assert back["imus"][0]["std"] == [0.0, 0.0, 0.0] and "cov" not in back["imus"][0]
    with pytest.raises(UserError, match="rhat_max"):
        positions_document(method="pmmh", reference_imu=0, means=means, covs=covs, diagnostics={"seconds": 1})
    with pytest.raises(UserError, match="method"):
        positions_document(method="ml", reference_imu=0, means=means, covs=covs, diagnostics={"seconds": 1})
    bad = dict(doc, schema="other/1")
    with pytest.raises(UserError, match="schema"):
        read_positions(bad)


def test_map_cli_recovers_positions_within_laplace_uncertainty(tmp_path, capsys):
    sim = simulate(arrays.mimu4444_8(), "smooth", T=400, rate=100.0, seed=3, position_error_std=3e-4)
    rec_path = tmp_path / "rec.nc"
    write_recording(sim.recording, rec_path)
    out = tmp_path / "out"
    assert main(["map", str(rec_path), "--out", str(out), "--no-progress"]) == 0
    doc = json.loads((out / "positions.json").read_text())
    assert doc["method"] == "map" and doc["reference_imu"] == 0 and len(doc["imus"]) == 8
    means = np.array([e["mean"] for e in doc["imus"]])
    stds = np.array([e["std"] for e in doc["imus"]])
    truth = np.array(sim.truth["true_position_relative"])
    z = (means[1:] - truth[1:]) / stds[1:]
    # 21 standardized errors: a consistent Laplace covariance keeps them all well inside 5σ
    assert np.abs(z).max() < 5.0, z
    assert 0.3 < np.sqrt(np.mean(z**2)) < 2.0
    assert "positions relative to IMU 0" in capsys.readouterr().out


def test_map_cli_user_errors(tmp_path, capsys):
    assert main(["map", str(tmp_path / "missing.nc"), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.nc" in err[0]
    sim = simulate(arrays.mimu4444_8(), "smooth", T=50, rate=100.0, seed=1)
    write_recording(sim.recording, tmp_path / "r.nc")
    with pytest.raises(SystemExit) as exc:  # refused by the option's type, at parse time
        main(["map", str(tmp_path / "r.nc"), "--out", str(tmp_path), "--prior-std", "-1"])
    assert exc.value.code == 2
    assert "--prior-std" in capsys.readouterr().err

"""The pipelines are library functions (issue #10 item 6): each one called from Python on a small
simulated recording, without the CLI, gives what the command line writes."""
import json

import numpy as np
import pytest
import torch

from accel_bayes.data.io import LoadedRecording, load_recording, write_recording
from accel_bayes.errors import UserError
from accel_bayes.physics.arrays import mimu4444_8, s16_plate
from accel_bayes.simulate import simulate


@pytest.fixture(scope="module")
def rec_file(tmp_path_factory):
    """8-IMU board, smooth motion, 300 samples: a file and its Recording."""
    path = tmp_path_factory.mktemp("pipe") / "rec.nc"
    sim = simulate(mimu4444_8(), "smooth", T=300, seed=3)
    write_recording(sim.recording, path)
    return path, sim


def test_load_recording_file_memory_and_refusal(rec_file):
    path, sim = rec_file
    loaded = load_recording(path)
    assert isinstance(loaded, LoadedRecording) and loaded.path == path
    assert len(loaded.sha256()) == 64 and loaded.sha256() == loaded.sha256()
    mem = load_recording(sim.recording)
    assert mem.path is None and mem.sha256() is None and mem.recording is sim.recording
    assert load_recording(loaded) is loaded
    with pytest.raises(UserError, match="recording: expected a Recording or a file path"):
        load_recording(42)


def test_map_pipeline(rec_file, tmp_path):
    from accel_bayes.data.positions import read_positions
    from accel_bayes.pipelines.map import map_positions, write_outputs

    path, sim = rec_file
    run = map_positions(path, max_iter=50)
    assert run.document["method"] == "map" and run.document["schema"] == "accel_bayes.positions/1"
    assert run.document["provenance"]["input_sha256"] == load_recording(path).sha256()
    assert run.means.shape == (8, 3) and np.all(run.std[run.labels[1:]] > 0)
    assert np.abs(run.means - np.asarray(sim.truth["true_position_relative"])).max() < 5e-3
    paths = write_outputs(run, tmp_path)
    doc = read_positions(paths["positions"])
    np.testing.assert_allclose(doc["means"], run.means)
    assert paths["omega"].read_text().splitlines()[0].startswith("time_s,omega_x")
    # in memory: the same estimate, no file hash
    mem = map_positions(sim.recording, max_iter=50)
    np.testing.assert_array_equal(mem.means, run.means)
    assert mem.document["provenance"]["input_sha256"] is None
    with pytest.raises(UserError, match="select"):
        map_positions(path, select="bogus")


def test_calibrate_pipeline_validates_before_reading(tmp_path):
    from accel_bayes.pipelines.calibrate import calibrate

    missing = tmp_path / "missing.nc"
    with pytest.raises(UserError, match="chains"):
        calibrate(missing, chains=0)
    with pytest.raises(UserError, match="noise"):
        calibrate(missing, noise="bogus")
    with pytest.raises(UserError, match="select"):
        calibrate(missing, select="bogus")


def test_calibrate_pipeline(rec_file, tmp_path):
    from accel_bayes.pipelines.calibrate import calibrate, write_outputs

    path, _ = rec_file
    res = calibrate(path, chains=2, draws=30, warmup=30, seed=1, progress=False)
    assert res.positions["method"] == "pmmh" and res.settings["chains"] == 2
    assert res.settings["input"] == str(path)
    assert res.run.theta.shape[:2] == (2, 30)
    again = calibrate(path, chains=2, draws=30, warmup=30, seed=1, progress=False)
    assert torch.equal(again.run.theta, res.run.theta)  # same seed, same draws, bit for bit
    paths = write_outputs(res, tmp_path, plots=False)
    assert json.loads(paths["positions"].read_text())["method"] == "pmmh"


def test_selfcal_pipeline(tmp_path):
    from accel_bayes.pipelines.selfcal import prepare, selfcal, write_outputs

    sim = simulate(s16_plate(), "table", T=200, seed=4)
    inp = prepare(sim.recording)
    assert inp.fixed_label == 0 and len(inp.labels) == 5
    run = selfcal(inp, max_iter=50)
    assert run.ok and run.document["method"] == "selfcal"
    assert len(run.poses) == 5 and run.motion.shape == (200, 10)
    paths = write_outputs(run, tmp_path, title="test")
    assert {"convergence", "positions", "poses", "motion"} <= set(paths)
    assert paths["poses"].read_text().startswith("imu,x_mm")
    with pytest.raises(UserError, match="--fixed"):
        prepare(sim.recording, fixed=9)


def test_motion_pipeline(rec_file, tmp_path):
    import xarray as xr

    from accel_bayes.pipelines.map import map_positions
    from accel_bayes.pipelines.motion import motion, write_outputs

    path, _ = rec_file
    doc = map_positions(path, max_iter=50).document
    run = motion(path, doc, draws=0)
    assert [r[0] for r in run.rows] == ["omega", "omega_dot", "s"]
    assert run.counts["ill_posed"] == 0 and run.dataset.sizes["time"] == 300
    out = write_outputs(run, tmp_path / "motion.nc")
    with xr.open_dataset(out) as ds:
        assert ds.attrs["schema"] == "accel_bayes.motion/1"


def test_intrinsics_pipeline(tmp_path):
    from test_intrinsics import _static_recording

    from accel_bayes.pipelines.intrinsics import intrinsics, write_outputs

    rec, (b, _, _) = _static_recording()
    run = intrinsics(rec)
    assert np.abs(run.intrinsics.acc_bias - b).max() < 0.05
    assert np.all(run.cal_err_max < run.raw_err_max)
    paths = write_outputs(run, tmp_path / "intr.json", apply_to=tmp_path / "cal.nc")
    assert json.loads(paths["intrinsics"].read_text())["schema"] == "accel_bayes.intrinsics/1"
    assert load_recording(paths["corrected"]).recording.T == rec.T


def test_summary(rec_file):
    from accel_bayes.data.summary import summarize

    path, _ = rec_file
    s = summarize(load_recording(path).recording, path)
    assert s["samples"] == 300 and s["imus"] == 8 and json.loads(json.dumps(s)) == s

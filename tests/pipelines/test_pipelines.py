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


def test_selfcal_takes_the_one_selection():
    """selfcal fits the samples of a prep.selection.Selection: keeping every sample is the same fit
    as no selection (bit for bit); a selection with a 20-sample gap and two dropped single samples
    fits only the kept times, records the selection and is no more certain than the whole record
    (the accuracy over gaps is tested on process-model data in test_selfcal.py); a selection of
    another recording, or one with under 3 samples, is refused in one line."""
    from accel_bayes.pipelines.selfcal import prepare, selfcal
    from accel_bayes.prep.selection import select_samples

    sim = simulate(s16_plate(), "table", T=200, seed=4)
    rec = sim.recording
    full = selfcal(rec, max_iter=50)
    everything = select_samples(rec, drop_clipped=False, min_rotation=None)
    assert everything.n_kept == 200
    same = selfcal(rec, selection=everything, max_iter=50)
    assert np.array_equal(same.means, full.means) and np.array_equal(same.pstd, full.pstd)

    keep = np.ones(200, bool)
    keep[90:110] = False
    keep[[30, 150]] = False
    sel = select_samples(rec, drop_clipped=False, min_rotation=None, user=keep)
    assert sel.kept_runs == 4 and sel.n_kept == 178
    part = selfcal(rec, selection=sel, max_iter=50)
    assert part.ok and part.motion.shape == (178, 10)
    assert np.array_equal(part.motion[:, 0], np.asarray(rec.time, float)[keep])
    settings = part.document["provenance"]["settings"]
    assert settings["samples"] == 178 and "kept 178 of 200" in settings["selection"]
    assert np.all(part.pstd[1:] >= full.pstd[1:] * 0.999)  # fewer samples: no more certain

    other = select_samples(simulate(s16_plate(), "table", T=120, seed=5).recording, drop_clipped=False,
                           min_rotation=None)
    with pytest.raises(UserError, match="selection: expected a Selection of this recording's 200"):
        prepare(rec, selection=other)
    few = np.zeros(200, bool)
    few[:2] = True
    with pytest.raises(UserError, match="selection: keeps 2 samples"):
        prepare(rec, selection=select_samples(rec, drop_clipped=False, min_rotation=None, user=few))


def test_selfcal_drop_clipped_leaves_out_flagged_accelerometer_samples(tmp_path):
    """drop_clipped (CLI --drop-clipped) fits only the samples without an accelerometer flag;
    gyroscope flags and readings do not count ([S16] ignores the gyros); the default fits all."""
    import dataclasses
    import subprocess
    import sys

    from accel_bayes.pipelines.selfcal import prepare

    rec = simulate(s16_plate(), "table", T=200, seed=4).recording
    flags = np.zeros((200, rec.K), bool)  # per triad (DESIGN §7.1)
    flags[50:60, 2] = True
    gflags = np.zeros((200, rec.K), bool) if rec.gyro is not None else None
    if gflags is not None:
        gflags[100:110, 1] = True
    rec = dataclasses.replace(rec, acc_clipped=flags, gyro_clipped=gflags)
    assert prepare(rec).acc.shape[0] == 200
    inp = prepare(rec, drop_clipped=True)
    assert inp.acc.shape[0] == 190 and inp.selection.dropped["clipped"] == 10 and inp.selection.kept_runs == 2
    assert inp.clipped == 0.0
    with pytest.raises(UserError, match="drop_clipped"):
        prepare(rec, drop_clipped=True, selection=inp.selection)
    path = tmp_path / "clip.nc"
    write_recording(rec, path)
    out = subprocess.run([sys.executable, "-m", "accel_bayes", "selfcal", str(path), "--out", str(tmp_path / "o"),
                          "--drop-clipped", "--no-progress", "--max-iter", "50"], capture_output=True, text=True)
    assert out.returncode in (0, 4), out.stderr
    doc = json.loads((tmp_path / "o" / "positions.json").read_text())
    assert doc["provenance"]["settings"]["samples"] == 190


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
    from tests.prep.test_intrinsics import _static_recording

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

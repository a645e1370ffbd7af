"""Issue #13 items 5–7: finished computations that crashed, inputs that ended in tracebacks, and
output that was silently wrong.  Each case: the exit status of DESIGN §7.5, one line on stderr
naming the field, no traceback, and (status 4) the written files marked.
"""
import dataclasses
import json

import numpy as np
import pytest

from accel_bayes.physics.arrays import preset
from accel_bayes.cli import main
from accel_bayes.data.io import write_recording
from accel_bayes.simulate import simulate

FAST = ["--num-draws", "2", "--no-map", "--quiet", "--no-plots", "--seed", "1"]


def _cli(argv, capsys):
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:
        rc = exc.code
    cap = capsys.readouterr()
    assert "Traceback" not in cap.err
    return rc, cap.out, cap.err.strip().splitlines()


@pytest.fixture(scope="module")
def rec8(tmp_path_factory):
    """8 IMUs, 60 samples of i.i.d. twisting, with acc_clipped set by hand on 5 samples."""
    r = simulate(preset("mimu8"), "iid", 60, seed=3, clip=False).recording
    flags = np.zeros((r.T, r.K), dtype=bool)
    flags[[3, 10, 20, 30, 40], 2] = True
    path = tmp_path_factory.mktemp("rec8") / "rec.nc"
    write_recording(dataclasses.replace(r, acc_clipped=flags), path)
    return path


# ------------------------------------------------------------------ item 5 (and status 4)

@pytest.mark.parametrize("run", [["--chains", "1", "--draws", "30", "--warmup", "30"],
                                 ["--chains", "2", "--draws", "3", "--warmup", "10"]], ids=["1 chain", "3 draws"])
def test_calibrate_without_computable_diagnostics_finishes_with_status_4(run, rec8, tmp_path, capsys):
    out = tmp_path / "out"
    rc, text, err = _cli(["calibrate", rec8, "--out", out, *run, *FAST], capsys)
    assert rc == 4, err
    assert "max R-hat n/a" in text  # the table printed instead of crashing on None
    assert len(err) == 1 and "not trustworthy" in err[0] and "R-hat could not be computed" in err[0], err
    d = json.loads((out / "positions.json").read_text())["diagnostics"]
    assert d["rhat_max"] is None and d["converged"] is False
    assert any("R-hat" in w for w in d["warnings"])


def test_keep_clipped_warns_on_stderr_and_default_drops(rec8, tmp_path, capsys):
    run = ["--chains", "1", "--draws", "5", "--warmup", "5", *FAST]
    rc, _, err = _cli(["calibrate", rec8, "--out", tmp_path / "keep", "--keep-clipped", *run], capsys)
    assert rc == 4 and any("--keep-clipped: 5 samples" in e for e in err), err
    rc, _, err = _cli(["calibrate", rec8, "--out", tmp_path / "drop", *run], capsys)
    assert not any("--keep-clipped" in e for e in err), err
    doc = json.loads((tmp_path / "drop" / "positions.json").read_text())
    assert doc["provenance"]["settings"]["preprocess"]["samples"]["clipped"] == 5


# ------------------------------------------------------------------ item 6: one line, not a traceback

def test_acc_far_beyond_acc_range_is_refused(tmp_path, capsys):
    r = simulate(preset("mimu8"), "iid", 60, seed=3).recording
    acc = np.asarray(r.acc).copy()
    acc[7, 2, 1] = 1e30
    path = tmp_path / "bad.nc"
    write_recording(dataclasses.replace(r, acc=acc), path, validate=False)
    rc, _, err = _cli(["map", path, "--out", tmp_path / "out", "--no-progress"], capsys)
    assert rc == 2 and len(err) == 1, err
    assert "acc: 1e+30" in err[0] and "acc_range" in err[0] and "time index 7" in err[0]
    assert not (tmp_path / "out").exists()


@pytest.fixture(scope="module")
def two_samples(tmp_path_factory):
    path = tmp_path_factory.mktemp("t2") / "t2.nc"
    write_recording(simulate(preset("mimu8"), "smooth", 2, seed=0).recording, path)
    return path


@pytest.mark.parametrize("cmd", ["selfcal", "mismatch"])
def test_fewer_than_3_samples_refused(cmd, two_samples, tmp_path, capsys):
    rc, _, err = _cli([cmd, two_samples, "--out", tmp_path / "out", *(["--no-progress"] if cmd == "selfcal" else [])],
                      capsys)
    assert rc == 2 and len(err) == 1 and "at least 3 samples" in err[0] and "has 2" in err[0], err
    assert not (tmp_path / "out").exists()


def test_mismatch_refuses_a_recording_without_rotation(tmp_path, capsys):
    """Gyros at 0 and constant specific force: before, 'math domain error'."""
    r = simulate(preset("mimu8"), "smooth", 100, seed=1).recording
    acc = np.broadcast_to(np.asarray(r.acc)[:1], np.asarray(r.acc).shape).copy()
    path = tmp_path / "still.nc"
    write_recording(dataclasses.replace(r, acc=acc, gyro=np.zeros_like(np.asarray(r.gyro)),
                                        acc_clipped=None, gyro_clipped=None), path)
    rc, _, err = _cli(["mismatch", path, "--out", tmp_path / "out"], capsys)
    assert rc == 2 and len(err) == 1 and "gyro: the recording does not rotate" in err[0], err


def test_simulate_T_beyond_memory_refused(tmp_path, capsys):
    rc, _, err = _cli(["simulate", "-T", str(10 ** 12), "-o", tmp_path / "x.nc"], capsys)
    assert rc == 2 and len(err) == 1 and "-T: 1000000000000 samples" in err[0] and "GiB" in err[0], err
    # 10¹² samples × 32 IMUs × 400 B = 1.28e16 B = 1.19e7 GiB, computed by hand
    assert "1.19e+07 GiB" in err[0] and "12800 B per sample" in err[0]
    assert list(tmp_path.iterdir()) == []


# ------------------------------------------------------------------ item 7: no silent wrong output

@pytest.mark.parametrize("layout, needle", [("coincident", "coincide"), ("collinear", "lie on one line")])
def test_motion_refuses_a_geometry_that_cannot_give_angular_acceleration(layout, needle, rec8, tmp_path, capsys):
    from accel_bayes.data.positions import positions_document, write_positions

    means = np.zeros((8, 3))
    if layout == "collinear":
        means[:, 0] = np.arange(8) * 0.01
    doc = positions_document(method="map", reference_imu=0, means=means, covs=np.zeros((8, 3, 3)),
                             diagnostics={"seconds": 0.0})
    cal = write_positions(doc, tmp_path / "positions.json")
    rc, _, err = _cli(["motion", rec8, "--calibration", cal, "-o", tmp_path / "m.nc"], capsys)
    assert rc == 2 and len(err) == 1 and needle in err[0] and "angular acceleration" in err[0], err
    assert not (tmp_path / "m.nc").exists()


def test_map_drops_clipped_samples_like_calibrate_and_warns_when_kept(rec8, tmp_path, capsys):
    rc, text, err = _cli(["map", rec8, "--out", tmp_path / "drop", "--no-progress"], capsys)
    assert rc == 0 and err == [] and "dropped 5 samples flagged clipped" in text
    assert len(np.loadtxt(tmp_path / "drop" / "omega.csv", delimiter=",", skiprows=1)) == 60 - 5
    rc, _, err = _cli(["map", rec8, "--out", tmp_path / "keep", "--no-progress", "--keep-clipped"], capsys)
    assert rc == 0 and len(err) == 1 and "--keep-clipped: 5 samples" in err[0], err
    assert len(np.loadtxt(tmp_path / "keep" / "omega.csv", delimiter=",", skiprows=1)) == 60


def test_map_not_converged_exits_4_and_marks_the_file(rec8, tmp_path, capsys):
    rc, _, err = _cli(["map", rec8, "--out", tmp_path / "o", "--no-progress", "--max-iter", "1"], capsys)
    assert rc == 4 and len(err) == 1 and "not trustworthy" in err[0], err
    d = json.loads((tmp_path / "o" / "positions.json").read_text())["diagnostics"]
    assert d["converged"] is False and "LM stopped" in d["warnings"][0]


def test_selfcal_not_converged_exits_4_and_marks_the_file(tmp_path, capsys):
    path = tmp_path / "t3.nc"
    write_recording(simulate(preset("mimu8"), "smooth", 3, seed=0).recording, path)
    rc, _, err = _cli(["selfcal", path, "--out", tmp_path / "o", "--no-progress", "--process-noise", "s16"], capsys)
    assert rc == 4 and len(err) == 1 and "not trustworthy" in err[0], err
    d = json.loads((tmp_path / "o" / "positions.json").read_text())["diagnostics"]
    assert d["converged"] is False and d["warnings"]

"""Issue #29 items 1, 2 and 4 (output safety, signals, one-line refusals): one test per defect,
each reproducing the failure of the code before the fix (see the commit message).

Inputs and helpers come from tests/data/test_outputs.py (one small simulated rig, a stream, a static
recording); the signal deliveries run through experiments/output_safety.py (a small seeded
version of its study)."""
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.data.test_outputs import COMMANDS, REPO, argv, inputs, one_line, snapshot  # noqa: F401  (inputs: fixture)

from accel_bayes.cli import main  # noqa: E402
from accel_bayes.data import output_sets, outputs  # noqa: E402


def _committed_set(target: Path, files=("positions.json",)) -> None:
    """An earlier output set written through OutputDir, so its marker lists its files."""
    with output_sets.OutputDir(target) as od:
        for f in files:
            (od / f).parent.mkdir(parents=True, exist_ok=True)
            outputs.write_text(od / f, '{"earlier": true}')


# ----------------------------------------------------------------------------- item 1: user files

@pytest.mark.parametrize("cmd", ["map", "calibrate", "selfcal"])
def test_overwrite_refuses_a_user_file_its_set_does_not_list(cmd, inputs, tmp_path, capsys):
    target = tmp_path / "out"
    _committed_set(target)
    (target / "my_notes.txt").write_text("mine")
    before = snapshot(tmp_path)
    rc = main(argv(cmd, inputs, target, "--overwrite"))
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and "my_notes.txt" in line and "--out" in line, line
    assert snapshot(tmp_path) == before  # the notes and the earlier set untouched, nothing left beside


def test_overwrite_still_replaces_a_set_holding_only_its_own_files(inputs, tmp_path, capsys):
    target = tmp_path / "out"
    _committed_set(target, files=("positions.json", "sub/old.txt"))
    assert main(argv("map", inputs, target, "--overwrite")) == 0
    capsys.readouterr()
    assert sorted(p.name for p in target.iterdir()) == sorted(["positions.json", "omega.csv", output_sets.SET_MARKER])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_resume_never_removes_a_file_it_did_not_write(inputs, tmp_path, capsys):
    out = tmp_path / "out"
    run = argv("calibrate", inputs, out, "--checkpoint-every", "5", "--no-plots")
    assert main(run) == COMMANDS["calibrate"][4]
    for p in out.iterdir():  # what a killed run leaves: its checkpoint only, no set marker
        if p.name != "checkpoint.pt":
            p.unlink()
    (out / "my_notes.txt").write_text("mine")
    capsys.readouterr()
    rc = main(run + ["--resume"])
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and "my_notes.txt" in line, line
    assert (out / "my_notes.txt").read_text() == "mine" and (out / "checkpoint.pt").is_file()


def _dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def test_leftover_cleanup_matches_exact_names_only(tmp_path):
    runs = tmp_path / "runs"
    runs.mkdir()
    dead = _dead_pid()
    others = [f".abc.old-{dead}-0123abcd", f".abc.partial-{dead}-0123abcd", f".a.b.partial-{dead}-0123abcd"]
    for name in others:  # another target's leftovers, and a name the target's glob would also match
        (runs / name).mkdir()
        (runs / name / "keep.txt").write_text("not this run's")
    (runs / f".abc.{dead}-0123abcd.tmp").write_text("another target's temporary file")
    no_pid = [".o.partial-", ".o.partial-xyz", ".o.old-notapid-0123abcd"]  # hidden folders without a pid
    for name in no_pid:
        (runs / name).mkdir()
    before = snapshot(runs)
    for name in ("a*", "a?", "[a]*", "o"):
        with output_sets.OutputDir(runs / name) as od:
            outputs.write_text(od / "x.txt", "x")
        with outputs.OutputFile(runs / f"{name}.nc", overwrite=True) as of:
            outputs.write_text(of.path, "x")
    after = snapshot(runs)
    assert {k: v for k, v in after.items() if k in before} == before  # nothing of theirs removed


def test_a_dead_runs_own_leftovers_are_still_cleared_but_not_a_file_put_there(tmp_path):
    dead = _dead_pid()
    target = tmp_path / "out"
    old = tmp_path / f".out.old-{dead}-0123abcd"
    _committed_set(old)  # a dead run's old set, moved aside, with a file a user put there
    (old / "my_notes.txt").write_text("mine")
    (tmp_path / f".out.partial-{dead}-0123abcd").mkdir()
    with output_sets.OutputDir(target) as od:
        outputs.write_text(od / "x.txt", "x")
    assert sorted(p.name for p in tmp_path.iterdir()) == [old.name, "out"]
    assert sorted(p.name for p in old.iterdir()) == ["my_notes.txt"]


# (command, the input flag whose file is also named as the output, how it is named)
SAME = [("import-mimu", "stream", "same"), ("import-mimu", "stream", "hardlink"), ("motion", "rec", "symlink"),
        ("export", "cal", "dotted"), ("intrinsics", "static", "apply-to"), ("import-csv", "toml", "same")]


@pytest.mark.parametrize("cmd, key, how", SAME)
def test_the_input_is_never_the_output(cmd, key, how, inputs, tmp_path, capsys):
    src = Path(inputs[key])
    work = tmp_path / "in"
    work.mkdir()
    mine = work / src.name
    mine.write_bytes(src.read_bytes())
    ins = dict(inputs, **{key: mine})
    out = mine
    if how == "hardlink":
        out = work / "linked.bin"
        os.link(mine, out)
    elif how == "symlink":
        out = work / "link.nc"
        out.symlink_to(mine)
    elif how == "dotted":
        out = Path(str(work / ".") + "/" + mine.name)
    extra = ["--overwrite"]
    if how == "apply-to":
        run = ["intrinsics", str(mine), "-o", str(work / "i.json"), "--apply-to", str(mine)] + extra
    else:
        run = argv(cmd, ins, out, *extra)
    before = snapshot(tmp_path)
    rc = main(run)
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and "input" in line, line
    assert snapshot(tmp_path) == before


# ----------------------------------------------------------------------------- item 2: signals

@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_signal_during_garbage_collection_is_not_lost(sig, inputs, tmp_path, monkeypatch, capsys):
    """The signal arrives while the collector runs (a gc callback sends it and runs on): before,
    the handler raised KeyboardInterrupt there, it was printed as "Exception ignored" and
    swallowed, and calibrate wrote a new set and exited 4."""
    import gc

    import accel_bayes.pipelines.calibrate as pc

    out = tmp_path / "out"
    _committed_set(out)
    before = snapshot(tmp_path)
    fired = []

    def bomb(phase, info):
        if phase == "start" and not fired:
            fired.append(1)
            os.kill(os.getpid(), getattr(signal, sig))
            x = 0
            for i in range(1000):  # bytecodes still inside the collection: where the handler runs
                x += i

    real = pc.calibrate

    def armed(*a, **k):  # armed once the command runs: main's handlers are in place
        gc.callbacks.append(bomb)
        try:
            return real(*a, **k)
        finally:
            gc.callbacks.remove(bomb)

    monkeypatch.setattr(pc, "calibrate", armed)
    rc = main(argv("calibrate", inputs, out, "--overwrite", "--no-plots"))
    err = capsys.readouterr().err
    assert fired and rc == 130, (rc, err[-2000:])
    assert one_line(err) == "accel-bayes calibrate: interrupted"
    assert snapshot(tmp_path) == before  # the earlier set as it was, nothing staged or locked left


def test_signal_study_small(tmp_path):
    """Ten seeded deliveries of the study in experiments/output_safety.py into two quick commands,
    forked processes only, one worker (the full study: 300 into five commands, real processes too)."""
    res = tmp_path / "study.json"
    proc = subprocess.run([sys.executable, str(REPO / "experiments" / "output_safety.py"), "--signals", "10",
                           "--workers", "1", "--only", "signals", "--kinds", "time,gc,fs", "--commands",
                           "simulate,selfcal", "--json", str(res), "--work", str(tmp_path / "w")],
                          capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO)), timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    doc = json.loads(res.read_text())["signals"]
    assert doc["delivered"] >= 8 and doc["failed"] == [], doc


# ----------------------------------------------------------------------------- item 4: messages

def test_numpy_warnings_are_not_shown_before_a_refusal(inputs, tmp_path, capsys):
    """Before, the rest detector's overflow warnings on a 1e300 CSV value (six lines on a
    terminal) came out of the command ahead of its refusal."""
    import shutil
    import warnings

    asl = tmp_path / "asl"
    shutil.copytree(inputs["asl"], asl)
    csv = sorted(asl.rglob("*.csv"))[0]
    lines = csv.read_text().splitlines()
    row = lines[5].split(",")
    row[-1] = "1e300"  # an accelerometer value
    lines[5] = ",".join(row)
    csv.write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        rc = main(["import-csv", str(asl), "--array", str(inputs["toml"]), "-o", str(tmp_path / "c.nc")])
    assert rc == 2 and "acc" in one_line(capsys.readouterr().err)
    assert [str(w.message) for w in shown] == []


def test_pickle_payload_checkpoint_refused_without_a_torch_warning(inputs, tmp_path, capsys):
    import pickle
    import warnings

    class Payload:
        def __reduce__(self):
            return (os.system, ("touch " + str(tmp_path / "executed"),))

    out = tmp_path / "out"
    out.mkdir()
    (out / "checkpoint.pt").write_bytes(pickle.dumps(Payload(), protocol=4))
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        rc = main(argv("calibrate", inputs, out, "--resume", "--checkpoint-every", "5", "--no-plots"))
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and "checkpoint" in line and not (tmp_path / "executed").exists(), line
    assert [str(w.message) for w in shown] == []  # before: "Detected pickle protocol 4 …" first


def test_an_impossible_omega_rms_is_refused_in_one_line(tmp_path, capfd):
    rc = main(["simulate", "--preset", "mimu8", "-T", "50", "--omega-rms", "1e300", "-o", str(tmp_path / "s.nc")])
    line = one_line(capfd.readouterr().err)
    assert rc == 2 and "omega_rms" in line, line


def test_out_dot_in_an_empty_directory_is_allowed(inputs, tmp_path, capsys, monkeypatch):
    here = tmp_path / "empty"
    here.mkdir()
    monkeypatch.chdir(here)
    assert main(argv("map", inputs, Path("."))) == 0
    capsys.readouterr()
    assert sorted(p.name for p in here.iterdir()) == sorted(["positions.json", "omega.csv", output_sets.SET_MARKER])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty"]  # no lock or staging folder left


def test_map_divergence_is_status_3_in_one_line(tmp_path, capsys):
    rec = tmp_path / "far.nc"
    # true positions 1 m std away from the nominal design: the MAP leaves the 3 mm prior
    assert main(["simulate", "--preset", "mimu8", "-T", "100", "--position-error", "1", "-o", str(rec)]) == 0
    capsys.readouterr()
    rc = main(["map", str(rec), "--out", str(tmp_path / "out"), "--no-progress"])
    line = one_line(capsys.readouterr().err)
    assert rc == 3 and "diverged" in line, line
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("what, cmd", [("acc_noise_std", "map"), ("gyro_noise_std", "mismatch"), ("gyro", "motion")])
def test_a_1e300_in_a_recording_is_refused_in_one_line(what, cmd, inputs, tmp_path, capsys):
    import xarray as xr

    ds = xr.load_dataset(inputs["rec"], engine="h5netcdf")
    if what == "gyro":
        g = ds["gyro"].values.copy()
        g.flat[7] = 1e300
        ds["gyro"].values = g
    else:
        ds.attrs[what] = 1e300  # before: a Cholesky/eigh traceback in the fit
    rec = tmp_path / "huge.nc"
    ds.to_netcdf(rec, engine="h5netcdf")
    rc = main(argv(cmd, dict(inputs, rec=rec), tmp_path / "out"))
    line = one_line(capsys.readouterr().err)
    assert rc == 2 and what in line, line


def test_a_1e300_time_tolerance_is_refused_in_one_line(inputs, tmp_path, capsys):
    with pytest.raises(SystemExit) as e:  # argparse's own refusal: status 2 (before: OverflowError traceback)
        main(argv("import-csv", inputs, tmp_path / "c.nc", "--time-tolerance", "1e300"))
    assert e.value.code == 2 and "--time-tolerance" in one_line(capsys.readouterr().err)

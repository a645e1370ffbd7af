"""Issue #13 items 5–7: finished computations that crashed, inputs that ended in tracebacks, and
output that was silently wrong.  Each case: the exit status of DESIGN §7.5, one line on stderr
naming the field, no traceback, and (status 4) the written files marked.
"""
import dataclasses
import json

import numpy as np
import pytest

from accel_bayes.arrays import preset
from accel_bayes.cli import main
from accel_bayes.io import write_recording
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

"""The command line answers at once (issue #26 item 5): ``--help``, ``--version``, every
``COMMAND --help`` and every refusal that the arguments and the file system decide (a missing
input, an existing output without --overwrite, a bad option value) import none of torch, pyro,
arviz or matplotlib.  Checked on the modules a fresh interpreter imports (``-X importtime``), never
on seconds; the timings are in experiments/bench_cli.md.  Also: ``import accel_bayes`` is
torch-free with its public names loaded on first use, and the 0.1 import aliases are gone."""
import importlib
import subprocess
import sys

import pytest
from tests.paths import REPO

HEAVY = {"torch", "pyro", "arviz", "matplotlib"}
ROOT = REPO


def _heavy_imports(args, cwd) -> tuple[set, subprocess.CompletedProcess]:
    """Run ``python -X importtime -m accel_bayes.cli ARGS`` and return the heavy top-level
    packages it imported (from the import-time lines on stderr) and the finished process."""
    p = subprocess.run([sys.executable, "-X", "importtime", "-m", "accel_bayes.cli", *args], capture_output=True,
                       text=True, cwd=cwd, env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    names = {ln.rsplit("|", 1)[1].strip().split(".")[0] for ln in p.stderr.splitlines()
             if ln.startswith("import time:") and ln.count("|") == 2}
    return names & HEAVY, p


def _commands():
    from accel_bayes.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sorted(sub.choices)


def test_the_import_lines_are_read():  # the check below would pass vacuously if nothing were parsed
    heavy, p = _heavy_imports(["--help"], ROOT)
    assert p.returncode == 0 and "import time:" in p.stderr and "accel_bayes.cli" in p.stderr


@pytest.mark.parametrize("args", [["--help"], ["--version"]] + [[c, "--help"] for c in _commands()],
                         ids=" ".join)
def test_help_and_version_import_no_numerical_library(args):
    heavy, p = _heavy_imports(args, ROOT)
    assert p.returncode == 0, p.stderr[-500:]
    assert not heavy, f"accel-bayes {' '.join(args)} imported {sorted(heavy)}"


REFUSALS = [  # (arguments, words of the one-line refusal); run in a folder holding rec.nc, out.json, full/a
    (["info", "missing.nc"], "missing.nc: no such recording file"),
    (["map", "missing.nc", "--out", "o"], "missing.nc: no such recording file"),
    (["map", "rec.nc", "--out", "full"], "--out: full is not empty"),
    (["calibrate", "missing.nc", "--out", "o"], "missing.nc: no such recording file"),
    (["calibrate", "rec.nc", "--out", "full"], "--out: full is not empty"),
    (["calibrate", "rec.nc", "--out", "o", "--intrinsics", "nope.json"], "--intrinsics: nope.json: no such"),
    (["calibrate", "rec.nc", "--out", "o", "--model", "nope.json"], "--model: nope.json: no such"),
    (["calibrate", "rec.nc", "--out", "o", "--prior-std", "nan"], "argument --prior-std"),
    (["selfcal", "missing.nc", "--out", "o"], "missing.nc: no such recording file"),
    (["selfcal", "rec.nc", "--out", "full"], "--out: full is not empty"),
    (["mismatch", "missing.nc", "--out", "o"], "missing.nc: no such recording file"),
    (["mismatch", "rec.nc", "--out", "full"], "--out: full is not empty"),
    (["demo", "--out", "full"], "--out: full is not empty"),
    (["simulate", "-o", "rec.nc"], "-o: rec.nc exists"),
    (["simulate", "-o", "x.nc", "--motion", "iid", "--omega-rms", "1"], "--omega-rms"),
    (["intrinsics", "missing.nc", "-o", "i.json"], "missing.nc: no such recording file"),
    (["intrinsics", "rec.nc", "-o", "out.json"], "-o: out.json exists"),
    (["motion", "missing.nc", "--calibration", "out.json", "-o", "m.nc"], "missing.nc: no such recording file"),
    (["motion", "rec.nc", "--calibration", "nope.json", "-o", "m.nc"], "--calibration: nope.json: no such"),
    (["motion", "rec.nc", "--calibration", "out.json", "-o", "out.json"], "-o: out.json is also the input"),
    (["motion", "rec.nc", "--calibration", "out.json", "-o", "rec.nc"], "-o: rec.nc is also the input"),
    (["export", "missing.nc", "--positions", "out.json", "-o", "k.yaml"], "REC: missing.nc: no such file"),
    (["export", "rec.nc", "--positions", "out.json", "-o", "out.json"], "-o: out.json is also the input"),
    (["import-mimu", "missing.bin", "-o", "r.nc"], "missing.bin: no such MIMU stream file"),
    (["import-mimu", "out.json", "-o", "rec.nc"], "-o: rec.nc exists"),
    (["import-csv", "missing", "--array", "a.toml", "-o", "r.nc"], "missing: no such CSV file or ASL folder"),
    (["import-csv", "full", "--array", "a.toml", "-o", "r.nc"], "--array: a.toml: no such"),
    (["import-csv", "full", "--array", "out.json", "-o", "rec.nc"], "-o: rec.nc exists"),
]


@pytest.mark.parametrize("args,says", REFUSALS, ids=[" ".join(a) for a, _ in REFUSALS])
def test_refusals_import_no_numerical_library(args, says, tmp_path):
    (tmp_path / "rec.nc").write_bytes(b"not read: refused before")
    (tmp_path / "out.json").write_text("{}")
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "a").write_text("x")
    before = sorted(p.name for p in tmp_path.rglob("*"))
    heavy, p = _heavy_imports(args, tmp_path)
    err = [ln for ln in p.stderr.splitlines() if not ln.startswith("import time:")]
    assert p.returncode == 2 and len(err) == 1 and says in err[0], p.stderr[-800:]
    assert not heavy, f"accel-bayes {' '.join(args)} imported {sorted(heavy)} before refusing"
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing written, no lock left


def test_every_command_is_refused_somewhere():
    assert {a[0] for a, _ in REFUSALS} == set(_commands())


def test_import_accel_bayes_is_torch_free_and_its_names_load_on_use():
    code = ("import sys, accel_bayes as ab; first = sorted({m.split('.')[0] for m in sys.modules} & %r); "
            "from accel_bayes.data.recording import Recording; from accel_bayes.physics import arrays; "
            "ok = ab.Recording is Recording and ab.mimu4444_8 is arrays.mimu4444_8 and ab.preset is arrays.preset; "
            "print(first, ok, ab.__version__)" % (HEAVY,))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT)}).stdout.split()
    assert out == ["[]", "True", "0.2.0"]
    import accel_bayes

    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        accel_bayes.nope  # noqa: B018
    assert {"Recording", "SensorArray", "UserError", "RecordingError"} <= set(dir(accel_bayes))


@pytest.mark.parametrize("old", ["io", "calibrate", "motion_estimation", "geometry", "inference.pmmh",
                                 "inference.linear", "mismatch.refine", "mismatch.effects"])
def test_old_import_paths_are_gone(old):
    import accel_bayes

    assert not hasattr(accel_bayes, "MOVED_MODULES")
    with pytest.raises(ModuleNotFoundError):
        importlib.import_module(f"accel_bayes.{old}")


def test_version_is_the_package_version():
    import tomllib

    import accel_bayes

    meta = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert accel_bayes.__version__ == meta["project"]["version"] == "0.2.0"


def test_calibrate_intrinsics_modes_are_the_pipelines():
    from accel_bayes.cli.calibrate import INTRINSICS_MODES
    from accel_bayes.prep.preprocess import INTRINSICS_MODES as PIPELINE

    assert INTRINSICS_MODES == PIPELINE

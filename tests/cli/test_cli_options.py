"""Every numeric option of every command is refused at parse time when it is not finite or out of range.

The recording paths given here do not exist: a refusal that names the option (and not the missing
file) shows the option was checked before anything was read.  Each refusal must be exit status 2,
one line on stderr naming the option, no traceback and no file written (DESIGN §7.5).
"""
import argparse
import math

import pytest

from accel_bayes.cli import _options as opt
from accel_bayes.cli import main

# kind of option -> values it must refuse (beyond non-numbers)
BAD = {
    "positive": ["nan", "inf", "-inf", "-1", "0"],
    "nonnegative": ["nan", "inf", "-1e-3"],
    "fraction_open": ["nan", "inf", "0", "1", "-0.5"],  # (0, 1)
    "fraction": ["nan", "inf", "1", "-0.5"],  # [0, 1)
    "angle": ["nan", "inf", "0", "-2", "181"],  # (0, 180] degrees
    "count1": ["nan", "inf", "-1", "0", "1.5", "1e3"],
    "count0": ["nan", "inf", "-1", "2.5"],
    "seed": ["nan", "inf", "-1", "1.5", str(2 ** 32)],
    "draws_motion": ["nan", "-1", "1"],  # 0 or >= 2
}

# command -> (arguments that make the rest of the command line valid, {option: kind})
COMMANDS = {
    "simulate": (["-o", "{tmp}/x.nc"], {
        "-T": "count1", "--rate": "positive", "--seed": "seed", "--position-error": "nonnegative",
        "--orientation-error": "nonnegative", "--acc-noise": "positive", "--gyro-noise": "positive",
        "--omega-rms": "nonnegative"}),
    "import-mimu": (["{tmp}/none.bin", "-o", "{tmp}/x.nc"], {
        "--tol-deg": "angle", "--min-static-s": "positive", "--max-fail-fraction": "fraction"}),
    "intrinsics": (["{tmp}/none.nc", "-o", "{tmp}/x.json"], {"--g": "positive"}),
    "map": (["{tmp}/none.nc", "--out", "{tmp}/out"], {"--prior-std": "positive", "--max-iter": "count1"}),
    "calibrate": (["{tmp}/none.nc", "--out", "{tmp}/out"], {
        "--chains": "count1", "--draws": "count1", "--warmup": "count0", "--num-draws": "count1",
        "--seed": "seed", "--prior-std": "positive", "--min-rotation": "nonnegative", "--noise-bins": "count1",
        "--checkpoint-every": "count0", "--max-draws": "count1", "--threads": "count1", "--check-every": "count1",
        "--max-seconds": "positive", "--rhat-max": "positive", "--ess-min": "positive",
        "--correlation": "fraction"}),
    "selfcal": (["{tmp}/none.nc", "--out", "{tmp}/out"], {
        "--fixed": "count0", "--max-iter": "count1", "--seed": "seed"}),
    "mismatch": (["{tmp}/none.nc", "--out", "{tmp}/out"], {
        "--alpha": "fraction_open", "--max-findings": "count0", "--seed": "seed", "--twins": "count1"}),
    "motion": (["{tmp}/none.nc", "--calibration", "{tmp}/none.json", "-o", "{tmp}/x.nc"], {
        "--draws": "draws_motion", "--seed": "seed", "--acc-noise-std": "positive", "--gyro-noise-std": "positive"}),
    "demo": (["--out", "{tmp}/out"], {"--seed": "seed"}),
    "import-csv": (["{tmp}/none", "--array", "{tmp}/none.toml", "-o", "{tmp}/x.nc"], {
        "--time-tolerance": "nonnegative", "--tol-deg": "angle", "--min-static-s": "positive"}),
}

CASES = [(cmd, flag, v) for cmd, (_, flags) in COMMANDS.items() for flag, kind in flags.items()
         for v in BAD[kind] + ["abc"]]


def _run(argv, capsys):
    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse refusals
        rc = exc.code
    return rc, capsys.readouterr()


@pytest.mark.parametrize("cmd, flag, value", CASES, ids=[f"{c} {f} {v}" for c, f, v in CASES])
def test_bad_numeric_option_is_refused_at_parse_time(cmd, flag, value, tmp_path, capsys):
    base, _ = COMMANDS[cmd]
    argv = [cmd, *(a.format(tmp=tmp_path) for a in base), f"{flag}={value}"]
    rc, out = _run(argv, capsys)
    err = out.err.strip().splitlines()
    assert rc == 2, (rc, out.err)
    assert len(err) == 1 and flag in err[0] and repr(value) in err[0], err
    assert "Traceback" not in out.err and "none." not in err[0]  # the option, not the missing input
    assert list(tmp_path.iterdir()) == []


def test_every_numeric_option_is_covered():
    """A numeric option added to a command without a type from _options (or without a row above) fails here."""
    from accel_bayes.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, p in sub.choices.items():
        for a in p._actions:
            if a.type in (int, float):
                pytest.fail(f"{name} {a.option_strings}: plain {a.type.__name__}, use accel_bayes.cli._options")
            if getattr(a.type, "__name__", "") in ("real", "integer"):
                assert a.option_strings[0] in COMMANDS.get(name, ([], {}))[1] \
                    or a.option_strings[-1] in COMMANDS.get(name, ([], {}))[1], (name, a.option_strings)


def test_converters_accept_the_range_and_name_it():
    assert opt.positive("m")("3e-3") == 3e-3
    assert opt.nonnegative()("0") == 0.0
    assert opt.fraction(lo_open=True)("0.01") == 0.01
    assert opt.integer(2, also=(0,))("0") == 0 and opt.integer(2, also=(0,))("7") == 7
    assert opt.seed(str(2 ** 32 - 1)) == 2 ** 32 - 1
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected a finite number > 0 \(m\), got 'nan'"):
        opt.positive("m")("nan")
    with pytest.raises(argparse.ArgumentTypeError, match=r"expected an integer >= 2 or 0, got '1'"):
        opt.integer(2, also=(0,))("1")
    assert math.isfinite(opt.real(-1, 1)("-1"))

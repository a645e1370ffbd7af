"""``DetectOptions`` (issue #26 "Options as frozen records", accel_bayes/mismatch/options.py): the
detector's options checked as a whole at construction, one line naming the field, before any
recording is read and without torch; the keyword form of ``detect`` builds the same record; the
command line's record equals the library's defaults."""
from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest

from accel_bayes.errors import UserError
from accel_bayes.mismatch.options import EFFECT_NAMES, DetectOptions
from tests.paths import REPO


@pytest.mark.parametrize("field, value, message", [
    ("alpha", 0.0, "alpha: expected a number in (0, 1)"),
    ("alpha", "x", "alpha: expected a number in (0, 1)"),
    ("alpha", True, "alpha: expected a number in (0, 1)"),
    ("max_findings", -1, "max_findings: expected an integer >= 0"),
    ("max_findings", 2.5, "max_findings: expected an integer >= 0"),
    ("seed", -3, "seed: expected a non-negative integer"),
    ("n_twins", 0, "n_twins: expected an integer >= 1"),
    ("n_refit", 0, "n_refit: expected an integer >= 1"),
    ("loo_draws", True, "loo_draws: expected an integer >= 1"),
    ("unresolved_permutations", -1, "unresolved_permutations: expected an integer >= 0"),
    ("threads", 0, "threads: expected an integer >= 1"),
    ("effects", "acc_bias,warp_drive", "effects: unknown name 'warp_drive'"),
    ("effects", " , ", "effects: expected at least one effect name"),
    ("posterior", "yes", "posterior: expected False or the calibration function"),
])
def test_a_bad_field_is_refused_in_one_line_naming_it(field, value, message):
    with pytest.raises(UserError) as e:
        DetectOptions(**{field: value})
    assert str(e.value).startswith(message) and "\n" not in str(e.value)


def test_record_normalises_and_is_frozen():
    o = DetectOptions(effects="acc_bias, unexplained,acc_bias", seed=np.int64(4), max_findings=np.int32(2))
    assert o.effects == ("acc_bias",) and o.seed == 4 and type(o.seed) is int and o.max_findings == 2
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.alpha = 0.5
    # 'unexplained' alone is allowed (it is always considered): no round candidate at all
    assert DetectOptions(effects=["unexplained"]).effects == ()
    assert DetectOptions(effects=None).to_settings()["effects"] == list(EFFECT_NAMES)


def test_fingerprint_holds_what_changes_the_numbers_only():
    a = DetectOptions(seed=1)
    assert a.fingerprint("h") == DetectOptions(seed=1, progress=True, threads=None).fingerprint("h")
    assert a.fingerprint("h") != DetectOptions(seed=2).fingerprint("h")
    assert a.fingerprint("h") != a.fingerprint("other recording")
    assert a.fingerprint("h")["options"]["effects"] is None


def test_effect_names_are_the_registry_and_the_module_imports_no_torch():
    code = ("import sys; from accel_bayes.mismatch.options import DetectOptions; DetectOptions(effects='acc_bias'); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'numpy', 'scipy', 'pyro', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**os.environ, "PYTHONPATH": str(REPO)}).stdout.strip()
    assert out == "[]"
    from accel_bayes.physics.effects import EFFECTS

    assert tuple(EFFECTS) == EFFECT_NAMES


def test_detect_keyword_form_and_record_form_are_one(monkeypatch):
    import importlib

    det = importlib.import_module("accel_bayes.mismatch.detector")
    from accel_bayes.mismatch import detect

    seen = []

    def fake(recording, options):
        seen.append(options)
        return "report"

    monkeypatch.setattr(det, "_detect", fake)
    assert detect("r.nc", alpha=0.05, seed=3) == "report"
    assert detect("r.nc", DetectOptions(alpha=0.05, seed=3)) == "report"
    assert seen[0] == seen[1]
    with pytest.raises(UserError, match="options: give a DetectOptions or keywords, not both"):
        detect("r.nc", DetectOptions(), seed=1)
    with pytest.raises(UserError, match="options: expected a DetectOptions"):
        detect("r.nc", {"seed": 1})


def test_command_line_record_is_the_library_default():
    from accel_bayes.cli import build_parser

    args = build_parser().parse_args(["mismatch", "r.nc", "--out", "o"])
    assert DetectOptions.from_args(args) == DetectOptions()
    args = build_parser().parse_args(["mismatch", "r.nc", "--out", "o", "--no-refine", "--max-findings", "5",
                                      "--effects", "acc_bias,gyro_bias", "--twins", "7"])
    o = DetectOptions.from_args(args)
    assert (o.refine, o.max_findings, o.effects, o.n_twins) == (False, 5, ("acc_bias", "gyro_bias"), 7)

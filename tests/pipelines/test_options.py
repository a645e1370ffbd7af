"""Options as frozen records (issue #26 item 3): ``CalibrateOptions`` and ``SelfcalOptions``.

Checked here: each record refuses a bad field at construction with one line naming it, before any
recording is read, and imports no torch; the command line's defaults are the library's; and the
refactoring changed nothing a user keeps — the provenance settings of calibrate and
self-calibration runs equal, key for key and in order, those that main 9279a3c wrote, and a
checkpoint written by 9279a3c is still accepted by ``--resume`` and continued bit-exactly.

The reference in ``tests/stored/options_9279a3c/`` was written by this file's :func:`write_reference`
with 9279a3c's package (the keyword form of ``calibrate``/``selfcal``, which both versions accept)::

    git -C /work/main archive 9279a3c | tar -x -C /tmp/base9279
    PYTHONPATH=/tmp/base9279 python3 tests/pipelines/test_options.py --write tests/stored/options_9279a3c
"""
from __future__ import annotations

import dataclasses
import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

# the checkout's root, wherever under tests/ this file lives
from tests.paths import REPO as ROOT, STORED
REFERENCE = STORED / "options_9279a3c"

# (name, keywords of calibrate): between them every step that writes settings (MAP, noise estimated,
# fixed and until-converged chains, a given φ prior, a user selection, no MAP)
CALIBRATE_RUNS = {
    "fixed": dict(chains=2, draws=30, warmup=30, seed=2),
    "until_converged": dict(chains=2, warmup=30, check_every=20, max_draws=40, num_draws=2, use_map=False, seed=2),
    "estimate": dict(chains=2, draws=20, warmup=20, noise="estimate", seed=3),
    "given": dict(chains=1, draws=20, warmup=10, phi_prior=(40.0, 7.0), min_rotation=0.0, prior="box", seed=1,
                  select="every other sample"),  # (the mask is made from the recording)
    "model": dict(chains=1, draws=20, warmup=20, seed=0, model="a sampling_jitter finding"),
}
RESUME = dict(chains=2, draws=30, warmup=30, seed=4)  # with the MAP: its settings are in the fingerprint
KILL_AT = (1, 23)  # (chain, iteration) where the interrupted run stops; its checkpoint holds iteration 20
SELFCAL = dict(max_iter=50, seed=7)


def _recording():
    from accel_bayes.physics.arrays import preset
    from accel_bayes.simulate import simulate

    return simulate(preset("mimu8"), "iid", 60, seed=3, clip=False).recording


def _selfcal_recording():
    from accel_bayes.physics.arrays import s16_plate
    from accel_bayes.simulate import simulate

    return simulate(s16_plate(), "table", T=200, seed=4).recording


def _keywords(name, rec) -> dict:
    kw = dict(CALIBRATE_RUNS[name], progress=False)
    if kw.get("select") == "every other sample":
        kw["select"] = np.arange(len(rec.time)) % 2 == 0
    if kw.get("model") == "a sampling_jitter finding":  # a minimal DESIGN §7.2 report of rec (tests/test_calibrate_model.py)
        kw["model"] = {
            "schema": "accel_bayes.mismatch/1", "mismatch_detected": True, "threshold": 20.0,
            "baseline": {"loglik": 0.0, "chi2_per_dof": 1.0, "dof": 1},
            "refined": {"effects": ["sampling_jitter"], "loglik": 0.0, "chi2_per_dof": 1.0},
            "findings": [{"effect": "sampling_jitter", "imu": 2, "axis": None, "evidence": 100.0,
                          "parameters": {"width": 5e-3}, "where": {"regime": "all", "time_s": None},
                          "explanation": "test finding"}],
            "details": {"recording": {"K": int(rec.K), "T_given": int(rec.T), "T": int(rec.T)}}}
    return kw


def _plain(x):
    """JSON round trip (what positions.json holds)."""
    return json.loads(json.dumps(x, default=str))


def _kill(chain, i, kernel):
    if (chain, i) == KILL_AT:
        raise KeyboardInterrupt


def write_reference(folder) -> None:
    """Write the reference of this file's tests with the package on ``sys.path`` (9279a3c's)."""
    import torch

    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.pipelines.selfcal import selfcal

    torch.set_num_threads(1)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    rec = _recording()
    settings = {name: _plain(calibrate(rec, **_keywords(name, rec)).settings) for name in CALIBRATE_RUNS}
    run = selfcal(_selfcal_recording(), **SELFCAL)
    settings["selfcal"] = _plain(run.document["provenance"]["settings"])
    (folder / "settings.json").write_text(json.dumps(settings, indent=1) + "\n", encoding="utf-8")
    ck = folder / "checkpoint.pt"
    ck.unlink(missing_ok=True)
    try:
        calibrate(rec, checkpoint=ck, checkpoint_every=10, callback=_kill, progress=False, **RESUME)
    except KeyboardInterrupt:
        pass
    else:
        raise RuntimeError("the interrupted run was not interrupted")


def _same(a, b, where="settings") -> list[str]:
    """Where two JSON values differ: keys (and their order), types and values, floats to 1e-9
    relative (the same code on another machine may round the last bits of a sum differently);
    the values of ``seconds`` (wall-clock times) are not compared."""
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            return [f"{where}: keys {list(a)} != {list(b)}"]
        return [d for k in a if k != "seconds" for d in _same(a[k], b[k], f"{where}.{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{where}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _same(x, y, f"{where}[{i}]")]
    if isinstance(a, float) and isinstance(b, (int, float)) and not isinstance(b, bool):
        ok = (math.isnan(a) and math.isnan(b)) or math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-300)
        return [] if ok else [f"{where}: {a!r} != {b!r}"]
    return [] if (type(a) is type(b) and a == b) else [f"{where}: {a!r} != {b!r}"]


def test_same_compares_keys_order_and_values():  # the comparison below must be able to fail
    assert _same({"a": 1, "b": [1.0, "x"]}, {"a": 1, "b": [1.0 + 1e-12, "x"]}) == []
    assert _same({"a": 1, "b": 2}, {"b": 2, "a": 1})  # same items, other order
    assert _same({"a": [1.0]}, {"a": [1.001]}) and _same({"a": True}, {"a": 1}) and _same({"a": None}, {"a": 0})
    assert _same({"seconds": 1.0}, {"seconds": 2.0}) == [] and _same({"seconds": 1.0}, {"s": 1.0})


# ---------------------------------------------------------------------------- the records themselves

@pytest.mark.parametrize("field,value,says", [
    ("chains", 0, "chains: expected an integer >= 1"), ("draws", 2.5, "draws"), ("warmup", -1, "warmup"),
    ("seed", True, "seed"), ("max_draws", 0, "max_draws"), ("check_every", 0, "check_every"),
    ("rhat_max", 1.0, "rhat_max"), ("ess_min", float("inf"), "ess_min"), ("max_seconds", float("nan"), "max_seconds"),
    ("num_draws", 0, "num_draws"), ("prior", "flat", "prior:"), ("prior_std", -1e-3, "prior_std"),
    ("gyro_method", "x", "gyro_method"), ("proposal", "hmc", "proposal"), ("init", "zero", "init"),
    ("correlation", 1.0, "correlation"), ("independence_prob", 1.0, "independence_prob"),
    ("checkpoint_every", 10, "checkpoint:"), ("resume", True, "checkpoint:"), ("noise", "guess", "noise:"),
    ("noise_bins", 3, "phi_prior"), ("select", "bogus", "select"), ("phi_prior", "uniform", "phi_prior"),
    ("phi_prior", (1.0, -2.0), "phi_prior"), ("threads", 0, "threads"), ("acc_blocks", "guess", "acc_blocks"),
    ("acc_blocks", "0.01,-0.1", "acc_blocks"), ("acc_blocks", (0.01, float("nan")), "acc_blocks"),
    ("acc_blocks", "0.01", "acc_blocks"),
])
def test_calibrate_options_refuse_a_bad_field_in_one_line(field, value, says):
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    with pytest.raises(UserError, match=says) as exc:
        CalibrateOptions(**{field: value})
    assert "\n" not in str(exc.value)


def test_calibrate_options_cross_checks_and_frozen():
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    with pytest.raises(UserError, match="gyro_method: a model's gyro posterior"):
        CalibrateOptions(model="report.json", gyro_method="sample_cov")
    opts = CalibrateOptions(chains=np.int64(3), prior_std=1, correlation=0)
    assert type(opts.chains) is int and type(opts.prior_std) is float and type(opts.correlation) is float
    assert opts.ess_target == 300.0 and opts.inflate_noise is True
    assert CalibrateOptions(model="r.json").inflate_noise is False
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.chains = 5
    with pytest.raises(UserError, match="chains"):  # a changed record is checked again
        dataclasses.replace(opts, chains=0)


@pytest.mark.parametrize("field,value,says", [
    ("fixed", -1, "fixed"), ("max_iter", 0, "max_iter"), ("seed", 2 ** 32, "seed"), ("process_noise", "jerk", "process_noise"),
    ("marginal_scale", "yes", "marginal_scale"), ("drop_clipped", True, "drop_clipped"),
])
def test_selfcal_options_refuse_a_bad_field_in_one_line(field, value, says):
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.selfcal_options import SelfcalOptions

    kw = {field: value}
    if field == "drop_clipped":
        kw["selection"] = object()  # either a selection or drop_clipped, not both
    with pytest.raises(UserError, match=says) as exc:
        SelfcalOptions(**kw)
    assert "\n" not in str(exc.value)


def test_command_line_defaults_are_the_library_defaults():
    """``from_args`` of a bare command line gives the record a library user gets with no arguments."""
    from accel_bayes.cli import build_parser
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions
    from accel_bayes.pipelines.selfcal_options import SelfcalOptions

    parser = build_parser()
    assert CalibrateOptions.from_args(parser.parse_args(["calibrate", "r.nc", "--out", "o"])) == CalibrateOptions()
    assert SelfcalOptions.from_args(parser.parse_args(["selfcal", "r.nc", "--out", "o"])) == SelfcalOptions()
    args = parser.parse_args(["calibrate", "r.nc", "--out", "o", "--no-map", "--keep-static", "--keep-clipped",
                              "--no-noise-inflation", "--chains", "3", "--correlation", "0.5"])
    opts = CalibrateOptions.from_args(args)
    assert (opts.use_map, opts.drop_static, opts.drop_clipped, opts.noise_inflation, opts.chains, opts.correlation) \
        == (False, False, False, False, 3, 0.5)


def test_options_modules_import_no_torch_and_their_choices_are_the_pipelines():
    code = ("import sys; from accel_bayes.pipelines.calibrate_options import CalibrateOptions; "
            "from accel_bayes.pipelines.selfcal_options import SelfcalOptions; "
            "CalibrateOptions(chains=2); SelfcalOptions(max_iter=5); "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'torch', 'pyro', 'arviz', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env={**__import__("os").environ, "PYTHONPATH": str(ROOT)}).stdout.strip()
    assert out == "[]"
    from accel_bayes.inference.selfcal import PROCESS_NOISE_MODES
    from accel_bayes.pipelines import calibrate_options as co, selfcal_options as so
    from accel_bayes.model.noise import NOISE_MODES
    from accel_bayes.model.phi_prior import PHI_PRIOR_CHOICES

    assert co.NOISE_MODES == NOISE_MODES and co.PHI_PRIOR_CHOICES == PHI_PRIOR_CHOICES
    assert set(so.PROCESS_NOISE_MODES) == set(PROCESS_NOISE_MODES)


# ---------------------------------------------------------------------------- against 9279a3c

@pytest.fixture(scope="module")
def reference():
    return json.loads((REFERENCE / "settings.json").read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def rec():
    import torch

    torch.set_num_threads(1)
    return _recording()


@pytest.mark.parametrize("name", list(CALIBRATE_RUNS))
def test_calibrate_settings_equal_9279a3c(name, rec, reference):
    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    kw = _keywords(name, rec)
    progress = kw.pop("progress")
    res = calibrate(rec, CalibrateOptions(**kw), progress=progress)
    assert _same(reference[name], _plain(res.settings)) == []


def test_selfcal_settings_equal_9279a3c(reference):
    from accel_bayes.pipelines.selfcal import selfcal
    from accel_bayes.pipelines.selfcal_options import SelfcalOptions

    run = selfcal(_selfcal_recording(), SelfcalOptions(**SELFCAL))
    assert _same(reference["selfcal"], _plain(run.document["provenance"]["settings"])) == []
    assert run.document["provenance"]["seed"] == SELFCAL["seed"]


def test_the_fingerprint_is_the_request_9279a3c_stored(rec):
    from accel_bayes.inference.mcmc import read_checkpoint
    from accel_bayes.pipelines.calibrate import _recording_hash
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    saved = read_checkpoint(REFERENCE / "checkpoint.pt")["fingerprint"]["request"]
    opts = CalibrateOptions(checkpoint="c.pt", checkpoint_every=10, resume=True, **RESUME)
    assert opts.fingerprint(_recording_hash(rec)) == saved
    assert opts.fingerprint(_recording_hash(rec), model_sha256="0" * 64) != saved  # it can differ


def test_a_checkpoint_of_9279a3c_resumes_bit_exactly(rec, tmp_path):
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    ck = tmp_path / "checkpoint.pt"
    shutil.copyfile(REFERENCE / "checkpoint.pt", ck)
    full = calibrate(rec, CalibrateOptions(**RESUME), progress=False)
    resumed = calibrate(rec, CalibrateOptions(checkpoint=ck, checkpoint_every=10, resume=True, **RESUME),
                        progress=False)
    assert resumed.run.resumed
    np.testing.assert_array_equal(resumed.idata.posterior["r"].values, full.idata.posterior["r"].values)
    np.testing.assert_array_equal(resumed.idata.sample_stats["log_phat"].values,
                                  full.idata.sample_stats["log_phat"].values)
    with pytest.raises(UserError, match="different settings"):
        calibrate(rec, CalibrateOptions(checkpoint=ck, resume=True, **dict(RESUME, seed=5)), progress=False)


if __name__ == "__main__":
    if sys.argv[1:2] != ["--write"] or len(sys.argv) != 3:
        raise SystemExit("usage: python3 tests/pipelines/test_options.py --write FOLDER")
    write_reference(sys.argv[2])


def test_acc_blocks_values_are_normalised():
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    assert CalibrateOptions().acc_blocks == "fit"
    assert CalibrateOptions(acc_blocks="fixed").acc_blocks == "fixed"
    assert CalibrateOptions(acc_blocks="0.01,0.2").acc_blocks == (0.01, 0.2)  # the command line's form
    assert CalibrateOptions(acc_blocks=[0.02, 0.5]).acc_blocks == (0.02, 0.5)

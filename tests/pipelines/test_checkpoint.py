"""`calibrate --resume` checks DIR/checkpoint.pt before any computation (DESIGN §7.5).

Each bad checkpoint must be refused with exit status 2 and one line naming it, and before the
preprocessing and the MAP: those are monkeypatched to fail, so a check that came after them would
show up as their error instead.
"""
import shutil

import pytest
import torch

import accel_bayes.pipelines.calibrate_steps as steps_mod
from accel_bayes.physics.arrays import preset
from accel_bayes.cli import main
from accel_bayes.inference.mcmc import CHECKPOINT_FORMAT
from accel_bayes.data.io import write_recording
from accel_bayes.simulate import simulate

RUN = ["--chains", "2", "--draws", "20", "--warmup", "20", "--num-draws", "2", "--no-map", "--seed", "4",
       "--quiet", "--no-plots"]


def _cli(argv, capsys):
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    return rc, capsys.readouterr()


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    """A recording and a real checkpoint of a finished run of it (RUN settings)."""
    d = tmp_path_factory.mktemp("ckpt")
    rec = d / "rec.nc"
    write_recording(simulate(preset("mimu8"), "iid", 60, seed=3, clip=False).recording, rec)
    other = d / "other.nc"
    write_recording(simulate(preset("mimu8"), "iid", 60, seed=4, clip=False).recording, other)
    rc = main(["calibrate", str(rec), "--out", str(d / "run"), *RUN, "--checkpoint-every", "20"])
    assert rc in (0, 4)
    return {"rec": rec, "other": other, "ckpt": d / "run" / "checkpoint.pt"}


def _modified(src, dst, change):
    saved = torch.load(src, weights_only=True)
    change(saved)
    torch.save(saved, dst)


def _foreign_torch(p, _):
    torch.save({"model": torch.zeros(3), "epoch": 7}, p)


CASES = {
    "empty": (lambda p, m: p.write_bytes(b""), "is empty"),
    "corrupt": (lambda p, m: p.write_bytes(m["ckpt"].read_bytes()[: m["ckpt"].stat().st_size // 2]),
                "not a readable PmMH checkpoint"),
    "not torch": (lambda p, m: p.write_text("time,acc\n0,1\n"), "not a readable PmMH checkpoint"),
    "foreign torch": (_foreign_torch, "not a PmMH checkpoint"),
    "bare tensor": (lambda p, m: torch.save(torch.ones(2), p), "not a PmMH checkpoint"),
    "format version": (lambda p, m: _modified(m["ckpt"], p, lambda s: s.update(format=CHECKPOINT_FORMAT[:-1] + "2")),
                       "this version reads"),
    "damaged": (lambda p, m: _modified(m["ckpt"], p, lambda s: s.pop("arrays")), "missing or mistyped: arrays"),
    "package version": (lambda p, m: _modified(m["ckpt"], p,
                                               lambda s: s["fingerprint"]["request"].update(version="0.0.1")),
                        "accel_bayes 0.0.1"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_checkpoint_refused_before_computation(case, made, tmp_path, capsys, monkeypatch):
    write, needle = CASES[case]
    out = tmp_path / "out"
    out.mkdir()
    write(out / "checkpoint.pt", made)

    def boom(*a, **k):
        raise AssertionError("preprocessing ran before the checkpoint was checked")

    monkeypatch.setattr(steps_mod, "preprocess", boom)
    monkeypatch.setattr(steps_mod, "_fit_map", boom)
    rc, cap = _cli(["calibrate", str(made["rec"]), "--out", str(out), *RUN, "--resume"], capsys)
    err = cap.err.strip().splitlines()
    assert rc == 2, cap.err
    assert len(err) == 1 and needle in err[0] and "checkpoint" in err[0], err
    assert "Traceback" not in cap.err
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt"]  # nothing written


@pytest.mark.parametrize("change, needle", [
    (("rec", ["--seed", "5"]), "different settings (options)"),
    (("other", []), "another recording"),
])
def test_checkpoint_of_another_run_refused_before_computation(change, needle, made, tmp_path, capsys, monkeypatch):
    which, extra = change
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(made["ckpt"], out / "checkpoint.pt")
    monkeypatch.setattr(steps_mod, "preprocess", lambda *a, **k: pytest.fail("preprocessing ran"))
    args = [a for a in RUN if a not in ("--seed", "4")] + (extra or ["--seed", "4"])
    rc, cap = _cli(["calibrate", str(made[which]), "--out", str(out), *args, "--resume"], capsys)
    err = cap.err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and needle in err[0], cap.err


def test_matching_checkpoint_resumes(made, tmp_path, capsys):
    """The check does not refuse the run that wrote the checkpoint: it resumes and finishes."""
    out = tmp_path / "out"
    out.mkdir()
    shutil.copy(made["ckpt"], out / "checkpoint.pt")
    rc, cap = _cli(["calibrate", str(made["rec"]), "--out", str(out), *RUN, "--resume"], capsys)
    assert rc in (0, 4), cap.err
    assert (out / "positions.json").is_file()

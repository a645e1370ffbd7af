"""The red-team probes of issue #29 items 1 and 4, and the results document of
experiments/output_safety.py (run that script; this module holds its probes and its writer).

Every probe runs the real command in a fresh forked process (the worker of output_safety.py:
its stderr is what a user sees) and is counted tried / passed by the rule stated with it.
"""
from __future__ import annotations

import gzip
import json
import os
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np

from output_safety import REPO, Worker, snapshot

HERE = Path(__file__).resolve().parent
MIMU = Path(os.environ.get("ACCEL_BAYES_SHARED", REPO.parent / "shared")) / "data" / "mimu4444-bcd"


def _one_line(err: str) -> bool:
    return len(err.strip().splitlines()) == 1


def _clean(rc: int, err: str) -> bool:
    """A run that either refused in one line (status 2) or finished (0, 3, 4) without a
    traceback, an "Exception ignored" or a warning printed before an error line."""
    if rc == 2:
        return _one_line(err)
    bad = ("Traceback", "Exception ignored", "Error:")
    return rc in (0, 3, 4) and not any(b in err for b in bad)


class _Runner:
    def __init__(self, work: Path):
        self.w = Worker()
        self.work = work
        self.n = 0

    def __call__(self, argv, cwd=None, timeout=300) -> tuple[int, str]:
        self.n += 1
        err = self.work / f"p{self.n:04d}.err"
        r = self.w.run(dict(argv=[str(a) for a in argv], cwd=str(cwd or self.work), stderr=str(err), timeout=timeout))
        return r["rc"], r["stderr"]


def _inputs(work: Path, run) -> dict:
    """A simulated rig, its MAP positions, its ASL/TOML copy, a real MIMU stream's first 4000
    packets (exp_1) and a pickle-payload checkpoint."""
    sys.path.insert(0, str(REPO))  # the test suite is the package tests/ of the repository root
    from tests.data.test_csv_import import write_asl, write_toml  # the test suite's writers of the CSV format

    from accel_bayes.data.io import read_recording

    d = work / "inputs"
    d.mkdir(parents=True, exist_ok=True)
    rec = d / "rec.nc"
    assert run(["simulate", "--preset", "mimu8", "-T", "80", "--seed", "3", "-o", rec])[0] == 0
    assert run(["map", rec, "--out", d / "cal", "--no-progress"])[0] == 0
    r = read_recording(rec)
    write_asl(r, d / "asl")
    write_toml(r, d / "array.toml")
    stream = d / "stream.bin"
    with gzip.open(MIMU / "exp_1" / "data.bin.gz", "rb") as f:
        stream.write_bytes(f.read(64 * 4000))
    return {"rec": rec, "cal": d / "cal" / "positions.json", "asl": d / "asl", "toml": d / "array.toml",
            "stream": stream}


# quick settings of every command that writes; {X}: the output target
BASE = {
    "simulate": ["simulate", "--preset", "mimu8", "-T", "50", "-o", "{X}.nc"],
    "import-mimu": ["import-mimu", "{stream}", "-o", "{X}.nc"],
    "import-csv": ["import-csv", "{asl}", "--array", "{toml}", "-o", "{X}.nc"],
    "intrinsics": ["intrinsics", "{rec}", "-o", "{X}.json"],
    "map": ["map", "{rec}", "--out", "{X}", "--no-progress"],
    "calibrate": ["calibrate", "{rec}", "--out", "{X}", "--chains", "2", "--draws", "10", "--warmup", "10", "--no-map",
                  "--quiet", "--no-plots"],
    "selfcal": ["selfcal", "{rec}", "--out", "{X}", "--no-progress", "--max-iter", "5", "--process-noise", "s16"],
    "mismatch": ["mismatch", "{rec}", "--out", "{X}", "--effects", "acc_bias", "--twins", "5", "--no-figures"],
    "motion": ["motion", "{rec}", "--calibration", "{cal}", "-o", "{X}.nc", "--draws", "0"],
    "export": ["export", "{rec}", "--positions", "{cal}", "-o", "{X}.yaml"],
    "info": ["info", "{rec}"],
}
DIR_CMDS = ["map", "calibrate", "selfcal", "mismatch"]


def _argv(cmd, inp, X, **over):
    return [a.format(X=X, **{**{k: str(v) for k, v in inp.items()}, **over}) for a in BASE[cmd]]


def _numeric_options():
    from accel_bayes.cli import build_parser

    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    out = {}
    for name, sp in sub.choices.items():
        out[name] = [a.option_strings[-1] for a in sp._actions if a.option_strings and a.type is not None
                     and getattr(a.type, "__name__", "") in ("real", "integer", "_correlation")]
    return out


def probes(work: Path) -> dict:
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    run = _Runner(work)
    try:
        inp = _inputs(work, run)
        res = {}
        res["foreign_file"] = _foreign(run, inp, work / "foreign")
        res["resume_foreign"] = _resume(run, inp, work / "resume")
        res["leftover_names"] = _leftovers(run, inp, work / "leftovers")
        res["input_is_output"] = _same(run, inp, work / "same")
        res["value_1e300"] = _huge(run, inp, work / "huge")
        res["pickle_checkpoint"] = _pickle(run, inp, work / "pickle")
        res["out_dot"] = _out_dot(run, inp, work / "dot")
        res["divergence"] = _divergence(run, inp, work / "diverge")
    finally:
        run.w.close()
    for v in res.values():
        v["tried"], v["passed"] = len(v["cases"]), sum(c["ok"] for c in v["cases"])
    return res


def _case(name, ok, rc, err, **kw):
    return dict(name=name, ok=bool(ok), rc=rc, err=err.strip().splitlines()[-1][:200] if err.strip() else "", **kw)


# ---------------------------------------------------------------- item 1

FOREIGN = {  # what a user put into an earlier output set, and the name the refusal must give
    "file": ("my_notes.txt", lambda d: (d / "my_notes.txt").write_text("mine")),
    "hidden file": (".my_notes", lambda d: (d / ".my_notes").write_text("mine")),
    "file in a folder": ("notes/today.txt", lambda d: ((d / "notes").mkdir(), (d / "notes" / "today.txt").write_text("x"))),
    "empty folder": ("empty/", lambda d: (d / "empty").mkdir()),
    "symlink": ("link", lambda d: (d / "link").symlink_to("/etc/hostname")),
}


def _foreign(run, inp, work):
    """--overwrite into an earlier set holding something its marker does not list: refused in
    one line naming it, everything as it was (rule of item 1)."""
    cases = []
    for cmd in DIR_CMDS:
        for kind, (name, make) in FOREIGN.items():
            d = work / f"{cmd}_{kind.replace(' ', '_')}"
            d.mkdir(parents=True)
            X = d / "out"
            rc, err = run(_argv(cmd, inp, X))  # the earlier set, written by the command itself
            make(X)
            before = snapshot(d)
            rc, err = run(_argv(cmd, inp, X) + ["--overwrite"])
            ok = rc == 2 and _one_line(err) and name.rstrip("/") in err and snapshot(d) == before
            cases.append(_case(f"{cmd} --overwrite, {kind}", ok, rc, err))
    return {"rule": "exit 2, one line naming the file, directory unchanged", "cases": cases}


def _resume(run, inp, work):
    """calibrate --resume into a folder with a checkpoint and a user's file (no set marker)."""
    cases = []
    for kind, (name, make) in FOREIGN.items():
        d = work / kind.replace(" ", "_")
        d.mkdir(parents=True)
        X = d / "out"
        argv = _argv("calibrate", inp, X) + ["--checkpoint-every", "5"]
        run(argv)
        for p in X.iterdir():
            if p.name != "checkpoint.pt":
                p.unlink()
        make(X)
        before = snapshot(d)
        rc, err = run(argv + ["--resume"])
        ok = rc == 2 and _one_line(err) and name.rstrip("/") in err and snapshot(d) == before
        cases.append(_case(f"calibrate --resume, {kind}", ok, rc, err))
    return {"rule": "exit 2, one line naming the file, directory unchanged", "cases": cases}


def _dead_pid() -> int:
    import subprocess

    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def _leftovers(run, inp, work):
    """A run into a target whose name holds glob characters, beside other targets' hidden
    leftovers and pid-less hidden folders: none of them removed; the run's own dead leftovers are."""
    cases = []
    dead = _dead_pid()
    for name in ["a*", "a?", "[a]*", "*", "a[!x]*", "o"]:
        for cmd in ("map", "simulate"):
            d = work / f"{cmd}_{len(cases)}"
            d.mkdir(parents=True)
            others = [f".abc.old-{dead}-0123abcd", f".abc.partial-{dead}-0123abcd", f".ab.{dead}-0123abcd.tmp",
                      f".abc.nc.{dead}-0123abcd.tmp", ".o.partial-", ".o.partial-xyz", ".o.old-12a-0123abcd",
                      f".o.partial-{dead}", f".o.nc.{dead}-0123abcd.tmp.keep"]
            for o in others:
                if o.endswith(".tmp") or ".tmp." in o:
                    (d / o).write_text("theirs")
                else:
                    (d / o).mkdir()
                    (d / o / "keep.txt").write_text("theirs")
            # the target's own leftover of a dead run: a staging folder, or a temporary file
            own = f".{name}.partial-{dead}-89abcdef" if cmd == "map" else f".{name}.{dead}-89abcdef.tmp"
            (d / own).mkdir() if cmd == "map" else (d / own).write_text("dead run's")
            before = {k: v for k, v in snapshot(d).items() if not k.startswith(own)}
            X = d / name
            argv = _argv(cmd, inp, X) if cmd == "map" else ["simulate", "--preset", "mimu8", "-T", "50", "-o", X]
            rc, err = run(argv)
            after = snapshot(d)
            kept = all(after.get(k, "gone") == v for k, v in before.items())
            ok = rc == 0 and kept and not (d / own).exists()
            cases.append(_case(f"{cmd} into {name!r}", ok, rc, err))
    return {"rule": "exit 0; every other target's leftover and every pid-less hidden folder kept; the "
                    "target's own dead staging folder removed", "cases": cases}


def _same(run, inp, work):
    """-o (or --apply-to) naming an input file, by the same path, a ./ path, a hard or a symbolic link."""
    cases = []
    combos = [("import-mimu", "stream", None), ("import-csv", "toml", None), ("intrinsics", "rec", None),
              ("intrinsics", "rec", "--apply-to"), ("motion", "rec", None), ("motion", "cal", None),
              ("export", "rec", None), ("export", "cal", None)]
    for cmd, key, flag in combos:
        for how in ("same", "dotted", "hardlink", "symlink"):
            d = work / f"{cmd}_{key}_{flag}_{how}"
            d.mkdir(parents=True)
            src = Path(inp[key])
            mine = d / src.name
            mine.write_bytes(src.read_bytes())
            ins = dict(inp, **{key: mine})
            out = {"same": mine, "dotted": Path(f"{d}/./{mine.name}"), "hardlink": d / ("hl" + mine.suffix),
                   "symlink": d / ("sl" + mine.suffix)}[how]
            if how == "hardlink":
                os.link(mine, out)
            elif how == "symlink":
                out.symlink_to(mine)
            argv = _argv(cmd, ins, d / "x")
            if flag:
                argv += [flag, str(out)]
            else:
                i = argv.index("-o")
                argv[i + 1] = str(out)
            before = snapshot(d)
            rc, err = run(argv + ["--overwrite"])
            ok = rc == 2 and _one_line(err) and "input" in err and snapshot(d) == before
            cases.append(_case(f"{cmd} {flag or '-o'} = {key} ({how})", ok, rc, err))
    # simulate reads no input file; a --out DIR holding the input is refused by its own rule
    for cmd in DIR_CMDS:
        d = work / f"{cmd}_inside"
        X = d / "out"
        X.mkdir(parents=True)
        rec = X / "rec.nc"
        rec.write_bytes(Path(inp["rec"]).read_bytes())
        before = snapshot(d)
        rc, err = run(_argv(cmd, dict(inp, rec=rec), X) + ["--overwrite"])
        ok = rc == 2 and _one_line(err) and "input" in err and snapshot(d) == before
        cases.append(_case(f"{cmd} --out holding REC", ok, rc, err))
    return {"rule": "exit 2, one line naming the input, nothing changed", "cases": cases}


# ---------------------------------------------------------------- item 4

def _huge(run, inp, work):
    """1e300 in every numeric option of every command, in every number of the array TOML, in a
    CSV value of each column kind, and in the recording's data and attributes read by each command."""
    import xarray as xr

    work.mkdir(parents=True)
    cases = []
    opts = _numeric_options()
    for cmd, names in opts.items():
        if cmd not in BASE:
            continue
        for o in names:
            if o in ("--device",):
                continue
            rc, err = run(_argv(cmd, inp, work / f"o{len(cases)}") + [o, "1e300"], timeout=300)
            cases.append(_case(f"option {cmd} {o} 1e300", _clean(rc, err), rc, err))
    toml = Path(inp["toml"]).read_text()
    import re

    keys = sorted(set(re.findall(r"^(\w+) = [-\d\[]", toml, flags=re.M)))
    for k in keys:
        t = work / f"t_{k}.toml"
        new = re.sub(rf"^{k} = (\[[^\]]*\]|\S+)", lambda m: f"{k} = " + (
            "[" + ", ".join(["1e300"] * len(m.group(1).strip("[]").split(","))) + "]" if m.group(1).startswith("[")
            else "1e300"), toml, count=1, flags=re.M)
        t.write_text(new)
        rc, err = run(["import-csv", inp["asl"], "--array", t, "-o", work / f"t_{k}.nc"])
        cases.append(_case(f"TOML {k} = 1e300", _clean(rc, err), rc, err))
    for col, name in ((0, "timestamp"), (1, "gyro"), (4, "acc")):
        a = work / f"asl_{name}"
        shutil.copytree(inp["asl"], a)
        csv = sorted(a.rglob("*.csv"))[0]
        lines = csv.read_text().splitlines()
        row = lines[5].split(",")
        row[col] = "1e300"
        lines[5] = ",".join(row)
        csv.write_text("\n".join(lines) + "\n")
        rc, err = run(["import-csv", a, "--array", inp["toml"], "-o", work / f"c_{name}.nc"])
        cases.append(_case(f"CSV {name} value 1e300", _clean(rc, err), rc, err))
    ds = xr.load_dataset(inp["rec"], engine="h5netcdf")
    variants = {}
    for var in ("acc", "gyro", "nominal_position"):
        v = ds.copy(deep=True)
        arr = v[var].values
        arr.flat[7] = 1e300
        v[var].values = arr
        variants[f"recording {var}"] = v
    v = ds.copy(deep=True)
    tv = v["time"].values.copy()
    tv[5] = 1e300
    variants["recording time"] = v.assign_coords(time=tv)
    for attr in ("acc_noise_std", "gyro_noise_std", "acc_range", "gyro_range"):
        v = ds.copy(deep=True)
        v.attrs[attr] = 1e300
        variants[f"recording attribute {attr}"] = v
    for label, v in variants.items():
        p = work / (label.replace(" ", "_") + ".nc")
        v.to_netcdf(p, engine="h5netcdf")
        for cmd in ("info", "map", "calibrate", "selfcal", "motion", "intrinsics", "mismatch", "export"):
            rc, err = run(_argv(cmd, dict(inp, rec=p), work / f"r{len(cases)}"), timeout=300)
            cases.append(_case(f"{label} 1e300 → {cmd}", _clean(rc, err), rc, err))
    return {"rule": "exit 2 with exactly one line, or 0/3/4 with no traceback and no warning before an error",
            "cases": cases}


def _pickle(run, inp, work):
    import torch

    work.mkdir(parents=True)
    cases = []

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {work / 'EXECUTED'}",))

    for how in ("pickle protocol 4", "pickle protocol 2", "torch.save of an object"):
        X = work / how.replace(" ", "_").replace(".", "")
        X.mkdir()
        if how.startswith("torch"):
            torch.save({"format": Payload()}, X / "checkpoint.pt")
        else:
            (X / "checkpoint.pt").write_bytes(pickle.dumps(Payload(), protocol=int(how[-1])))
        rc, err = run(_argv("calibrate", inp, X) + ["--resume", "--checkpoint-every", "5"])
        ok = rc == 2 and _one_line(err) and "checkpoint" in err and not (work / "EXECUTED").exists()
        cases.append(_case(f"calibrate --resume, {how}", ok, rc, err))
    return {"rule": "exit 2, one line, the payload not executed", "cases": cases}


def _out_dot(run, inp, work):
    cases = []
    for cmd in DIR_CMDS:
        d = work / cmd / "here"
        d.mkdir(parents=True)
        rc, err = run(_argv(cmd, inp, "."), cwd=d)
        from accel_bayes.data import output_sets

        names = sorted(p.name for p in d.parent.iterdir())
        ok = rc in (0, 3, 4) and output_sets.is_output_set(d) and names == ["here"]
        cases.append(_case(f"{cmd} --out . in an empty directory", ok, rc, err))
    return {"rule": "runs (its usual status), the set in the directory, no lock or staging folder left", "cases": cases}


def _divergence(run, inp, work):
    """A rig whose nominal design is 1 m (std) off the truth: the MAP leaves its 3 mm prior."""
    work.mkdir(parents=True)
    far = work / "far.nc"
    run(["simulate", "--preset", "mimu8", "-T", "100", "--position-error", "1", "-o", far])
    cases = []
    rc, err = run(["map", far, "--out", work / "map", "--no-progress"])
    cases.append(_case("map on a diverging rig", rc == 3 and _one_line(err) and "diverged" in err
                       and not (work / "map").exists(), rc, err))
    rc, err = run(["selfcal", far, "--out", work / "selfcal", "--no-progress"])
    cases.append(_case("selfcal on a diverging rig", rc in (3, 4, 0) and _clean(rc, err), rc, err))
    rc, err = run(["calibrate", far, "--out", work / "cal", "--chains", "2", "--draws", "10", "--warmup", "10",
                   "--quiet", "--no-plots"])
    cases.append(_case("calibrate on a diverging rig (MAP start abandoned: chains from prior draws)",
                       rc in (3, 4) and _clean(rc, err), rc, err))
    return {"rule": "map: exit 3 in one line, nothing written; the others: their documented status, no traceback",
            "cases": cases}


# ---------------------------------------------------------------- document

def write_md(path: Path, res: dict, command: str, when: str) -> None:
    from accel_bayes.data.outputs import write_text

    L = ["# Output safety: signals, user files, one-line refusals (issue #29 items 1, 2, 4)", "",
         f"Regenerate: `{command}`  ", f"Run: {when}. Every figure below is printed by that command.", ""]
    s = res.get("signals")
    if s:
        L += ["## Signal study", "",
              f"{s['signals']} seeded deliveries (seed {s['seed']}, {s['workers']} workers, {s['wall_s']:.0f} s) into "
              "real commands replacing an earlier output of their own (method: the docstring of "
              "experiments/output_safety.py).", "",
              f"- delivered while the command ran: **{s['delivered']}**; exit 130: **{s['exit_130']}**; "
              f"failed checks: **{len(s['failed'])}**",
              f"- of the delivered: earlier output intact {s['earlier_intact']}, complete new output "
              f"{s['new_complete']} (signal after the swap; the run still exits 130), a mix of two runs: "
              f"{s['delivered'] - s['earlier_intact'] - s['new_complete']}",
              f"- late (reached the process after it had decided its exit status, ignored): {s['late']}; "
              f"not delivered (the command had exited first): {s['not_delivered']}",
              f"- real processes (`python -m accel_bayes`) signalled before `accel_bayes.__main__` installed the "
              f"handlers, i.e. while `accel_bayes/__init__.py` imports torch, xarray and the package (seconds): "
              f"**{s['startup']}**, exit {s['startup_rc']} (SIGTERM's default action, or Python's "
              "KeyboardInterrupt), nothing touched in any of them (checked). Not counted as delivered: the "
              "package's code was not running yet. This window shrinks to the interpreter's start once the "
              "package imports lazily (issue #29's other part); until then it is where a signal is not 130.",
              f"- forked runs signalled before the child ran Python (CPython resets the signals a forked child "
              f"caught before its at-fork reset: a property of the harness, not of the command): "
              f"{s.get('fork_window', 0)}; each left the earlier or the complete new output (checked)", "",
              "| group | delivered | exit 130 | earlier intact | new complete |", "|---|---:|---:|---:|---:|"]
        for k, v in s["by"].items():
            L.append(f"| {k} | {v['delivered']} | {v['exit_130']} | {v['earlier_intact']} | {v['new_complete']} |")
        L += ["", "Unsignalled reference runs (exit status, seconds, calls hooked):", ""]
        for c, v in s["reference"].items():
            L.append(f"- {c}: exit {v['rc']}, {v['seconds']} s, {v['counts']}")
        if s["failed"]:
            L += ["", "Failures:", ""] + [f"- {f['cmd']} {f['kind']} {f['signal']} {f.get('point') or f.get('delay')}: "
                                          f"{'; '.join(f['problems'])}" for f in s["failed"][:20]]
        L.append("")
    p = res.get("probes")
    if p:
        L += ["## Red-team probes (items 1 and 4)", "",
              "Each case runs the real command in a fresh forked process; the rule is the pass criterion.", "",
              "| probe | rule | tried | passed | exit statuses |", "|---|---|---:|---:|---|"]
        for k, v in p.items():
            rcs = {}
            for c in v["cases"]:
                rcs[c["rc"]] = rcs.get(c["rc"], 0) + 1
            L.append(f"| {k} | {v['rule']} | {v['tried']} | {v['passed']} | "
                     + ", ".join(f"{n}× {rc}" for rc, n in sorted(rcs.items())) + " |")
        L.append("")
        for k, v in p.items():
            bad = [c for c in v["cases"] if not c["ok"]]
            L += [f"### {k}: {v['passed']}/{v['tried']}", ""]
            for c in (bad or v["cases"][:3]):
                L.append(f"- {'FAIL' if not c['ok'] else 'e.g.'} {c['name']}: exit {c['rc']}; `{c['err']}`")
            L.append("")
    write_text(path, "\n".join(L) + "\n")

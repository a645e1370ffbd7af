"""Output safety (issue #29, items 1, 2 and 4): the signal study and the red-team probes.

Regenerate experiments/output_safety.md (about 10 minutes on the 2-core development machine)::

    PYTHONPATH=$PWD python3 experiments/output_safety.py --md experiments/output_safety.md

Signal study (``--signals N``, default 300, ``--workers 2``, ``--seed 29``).  Real commands
(simulate, map, calibrate, selfcal, motion) on a small simulated rig, each replacing an earlier
output of its own (``--overwrite``).  Each worker imports the package once and forks one process
per delivery, which runs the command exactly as ``accel-bayes`` does (``accel_bayes.cli.main``
with ``sys.argv``); the interpreter start-up before that is the one part not exercised (see the
results).  A delivery is SIGINT or SIGTERM (seeded coin) at a seeded point of one of three kinds:

* time: after a uniform delay in [0, 1.05 T], T the command's unsignalled duration, sent by the
  worker;
* gc: at the start of the k-th garbage collection of the run (k uniform over the collections of
  the unsignalled run), sent by the process to itself from a ``gc.callbacks`` hook and followed by
  more bytecodes inside the collection: where the handler runs;
* fs: just before the k-th call of os.replace / os.rename / os.unlink / os.rmdir (file commits,
  the set's swap, the removal of the old set, lock release, cleanup), k uniform over the calls of
  the unsignalled run.

Pass: exit status 130; stderr exactly ``accel-bayes CMD: interrupted`` (no traceback, no
"Exception ignored"); no staging folder, old set, temporary file or lock beside the target; the
target holds the earlier output unchanged, or (a signal after the swap) the complete new one —
never a mix.  A time delivery that reaches the process after the command decided its exit status
(the handlers then ignore signals, :func:`accel_bayes.interrupts.hold_until_exit`) is counted
apart as "late"; it must still leave the complete new output and the unsignalled exit status.

Probes (``--only probes``): the red-team cases of items 1 and 4, counted tried/passed.
"""
from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import random
import shutil
import subprocess
import sys
import tempfile
import textwrap
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# command → (argv with {rec} {cal} {seed}, target flag, target name, extra argv of the earlier output)
COMMANDS = {
    "simulate": (["simulate", "--preset", "mimu8", "-T", "200", "--seed", "{seed}"], "-o", "out.nc"),
    "map": (["map", "{rec}", "--no-progress"], "--out", "out"),
    "calibrate": (["calibrate", "{rec}", "--chains", "2", "--draws", "60", "--warmup", "60", "--no-plots", "--quiet",
                   "--seed", "{seed}"], "--out", "out"),
    "selfcal": (["selfcal", "{rec}", "--no-progress", "--max-iter", "8", "--process-noise", "s16"], "--out", "out"),
    "motion": (["motion", "{rec}", "--calibration", "{cal}", "--draws", "20", "--seed", "{seed}"], "-o", "out.nc"),
}

WORKER = textwrap.dedent(r"""
    import gc, json, os, signal, sys, time
    import torch
    torch.set_num_threads(1)
    import importlib, pkgutil, accel_bayes
    for m in pkgutil.walk_packages(accel_bayes.__path__, "accel_bayes."):
        if not m.name.endswith("__main__"):
            importlib.import_module(m.name)
    import arviz, matplotlib.pyplot, xarray, h5netcdf
    from accel_bayes.cli import main
    try:
        from accel_bayes import interrupts
        interrupts.install()  # as accel_bayes.__main__ does first: a forked child records signals from its start
    except ImportError:  # a tree from before issue #29 (probing the old code)
        interrupts = None
    FS = ("replace", "rename", "unlink", "rmdir")
    for line in sys.stdin:
        job = json.loads(line)
        err = job["stderr"]
        t_fork = time.monotonic()
        pid = os.fork()
        if pid == 0:
            t_child = time.monotonic()  # the child runs Python from here (after CPython's at-fork reset)
            os.chdir(job["cwd"])
            fd = os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC)
            os.dup2(fd, 2)
            os.dup2(os.open(os.devnull, os.O_WRONLY), 1)
            sys.stderr = os.fdopen(2, "w", buffering=1)
            counts = {"gc": 0, **{f: 0 for f in FS}}
            sig = getattr(signal, job.get("signal") or "SIGTERM")
            point = job.get("point")  # ["gc"|fs-name, k] or None
            def fire():
                os.kill(os.getpid(), sig)
                x = 0
                for i in range(200):  # bytecodes where the handler runs, still inside the hooked call
                    x += i
            def on_gc(phase, info):
                if phase == "start":
                    counts["gc"] += 1
                    if point and point[0] == "gc" and counts["gc"] == point[1]:
                        fire()
            gc.callbacks.append(on_gc)
            for f in FS:
                real = getattr(os, f)
                def hooked(*a, _real=real, _f=f, **k):
                    counts[_f] += 1
                    if point and point[0] == _f and counts[_f] == point[1]:
                        fire()
                    return _real(*a, **k)
                setattr(os, f, hooked)
            decided = [None]
            if interrupts is not None:
                real_hold = interrupts.hold_until_exit
                def hold():
                    r = real_hold()
                    decided[0] = time.monotonic()
                    return r
                interrupts.hold_until_exit = hold
            sys.argv = ["accel-bayes", *job["argv"]]
            try:
                rc = main()
            except SystemExit as exc:  # argparse's refusals and --help, as the real command exits
                rc = exc.code if isinstance(exc.code, int) else 2
            except BaseException as exc:
                rc = 99
            gc.callbacks.remove(on_gc)
            with open(job["stderr"] + ".json", "w") as f:
                json.dump({"counts": counts, "decided": decided[0], "child": t_child}, f)
            os._exit(rc)
        sent = None
        done, status = 0, 0
        if job.get("delay") is not None:
            time.sleep(max(0.0, t_fork + job["delay"] - time.monotonic()))
            done, status = os.waitpid(pid, os.WNOHANG)
            if done == 0:  # still running (not yet reaped: the pid is its own)
                sent = time.monotonic()
                os.kill(pid, getattr(signal, job["signal"]))
        deadline = t_fork + (job.get("timeout") or 1e9)
        while not done:  # a hang is killed and reported (-9)
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                break
            if time.monotonic() > deadline:
                os.kill(pid, signal.SIGKILL)
                _, status = os.waitpid(pid, 0)
                break
            time.sleep(0.005)
        print(json.dumps({"rc": os.waitstatus_to_exitcode(status), "sent": sent,
                          "seconds": time.monotonic() - t_fork}), flush=True)
""")


class Worker:
    """One forking worker process (imports once; one fork per job)."""

    def __init__(self):
        self.proc = subprocess.Popen([sys.executable, "-c", WORKER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     text=True, env=dict(os.environ, PYTHONPATH=str(REPO)))

    def run(self, job: dict) -> dict:
        self.proc.stdin.write(json.dumps(job) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError("worker died")
        out = json.loads(line)
        side = Path(job["stderr"] + ".json")
        out.update(json.loads(side.read_text()) if side.exists() else {"counts": None, "decided": None, "child": None})
        out["stderr"] = Path(job["stderr"]).read_text()
        return out

    def close(self):
        self.proc.stdin.close()
        self.proc.wait(timeout=60)


def _process_run(argv, cwd: Path, delay: float, sig: str) -> dict:
    """The command as a user starts it (``python -m accel_bayes``), signalled after ``delay`` s."""
    import signal

    err = cwd.parent / (cwd.name + ".err")
    with open(err, "w") as fe:
        t0 = time.monotonic()
        p = subprocess.Popen([sys.executable, "-m", "accel_bayes", *argv], cwd=cwd, stdout=subprocess.DEVNULL,
                             stderr=fe, env=dict(os.environ, PYTHONPATH=str(REPO)))
        time.sleep(delay)
        sent = None
        if p.poll() is None:
            sent = time.monotonic()
            p.send_signal(getattr(signal, sig))
        rc = p.wait()
    return {"rc": rc, "sent": sent, "seconds": time.monotonic() - t0, "stderr": err.read_text(), "counts": None,
            "decided": None}


def snapshot(d: Path) -> dict:
    """Every entry under ``d`` (hidden ones included) → SHA-256 of its bytes (None: a directory)."""
    return {str(p.relative_to(d)): (hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else None)
            for p in sorted(d.rglob("*"))}


def _argv(cmd, inputs, target, seed):
    head, flag, _ = COMMANDS[cmd]
    return [a.format(seed=seed, **inputs) for a in head] + [flag, str(target), "--overwrite"]


def _complete(cmd, target: Path, ref_files) -> bool:
    """The target holds a complete output of ``cmd``: for a set, its marker lists exactly the
    files of the unsignalled run and each is there; for a file, it reads."""
    from accel_bayes.data import output_sets

    if COMMANDS[cmd][1] == "--out":
        if not output_sets.is_output_set(target):
            return False
        files = json.loads((target / output_sets.SET_MARKER).read_text())["files"]
        on_disk = sorted(str(p.relative_to(target)) for p in target.rglob("*") if p.is_file()
                         and p.name != output_sets.SET_MARKER)
        return sorted(files) == sorted(ref_files) == on_disk
    import xarray as xr

    try:
        xr.open_dataset(target, engine="h5netcdf").close()
    except Exception:
        return False
    if cmd == "simulate":
        from accel_bayes.data.io import read_truth

        try:
            read_truth(target)
        except Exception:
            return False
    return True


def _inputs(work: Path, with_cal: bool = True) -> dict:
    import contextlib
    import io

    from accel_bayes.cli import main

    work.mkdir(parents=True, exist_ok=True)
    rec, cal = work / "rec.nc", work / "cal"
    with contextlib.redirect_stdout(io.StringIO()):
        if not rec.exists():
            assert main(["simulate", "--preset", "mimu8", "-T", "120", "--seed", "3", "-o", str(rec)]) == 0
        if with_cal and not cal.exists():
            assert main(["map", str(rec), "--out", str(cal), "--no-progress"]) == 0
    return {"rec": str(rec), "cal": str(cal / "positions.json")}


KINDS = {"time": 0.4, "gc": 0.2, "fs": 0.2, "process": 0.2}  # shares of the deliveries


def signal_study(n: int, workers: int, seed: int, work: Path, kinds=tuple(KINDS), commands=tuple(COMMANDS)) -> dict:
    """Run ``n`` seeded deliveries (module docstring) of the given kinds into the given commands;
    returns the counts and every failure."""
    rng = random.Random(seed)
    inputs = _inputs(work, with_cal="motion" in commands)
    pool = [Worker() for _ in range(workers)]
    try:
        # the earlier output of every command, and its unsignalled run: duration, calls, files
        ref = {}
        for cmd in commands:
            base = work / f"earlier_{cmd}"
            shutil.rmtree(base, ignore_errors=True)
            base.mkdir()
            target = base / COMMANDS[cmd][2]
            r0 = pool[0].run(dict(argv=_argv(cmd, inputs, target, 1), cwd=str(base), stderr=str(base.parent / "e0")))
            assert r0["rc"] in (0, 3, 4), (cmd, r0)
            d = work / f"ref_{cmd}"
            shutil.rmtree(d, ignore_errors=True)
            shutil.copytree(base, d)
            t0 = d / COMMANDS[cmd][2]
            r = pool[0].run(dict(argv=_argv(cmd, inputs, t0, 2), cwd=str(d), stderr=str(work / f"ref_{cmd}.err")))
            files = None
            if COMMANDS[cmd][1] == "--out":
                from accel_bayes.data import output_sets

                files = json.loads((t0 / output_sets.SET_MARKER).read_text())["files"]
            shutil.rmtree(d, ignore_errors=True)
            shutil.copytree(base, d)
            t1 = time.monotonic()
            rp = subprocess.run([sys.executable, "-m", "accel_bayes", *_argv(cmd, inputs, t0, 2)], cwd=d,
                                capture_output=True, env=dict(os.environ, PYTHONPATH=str(REPO))) \
                if "process" in kinds else None
            ref[cmd] = dict(rc=r["rc"], seconds=r["seconds"], counts=r["counts"], files=files,
                            process_rc=rp and rp.returncode, process_seconds=time.monotonic() - t1)
        jobs = []
        cmds = list(commands)
        for i in range(n):
            cmd = cmds[i % len(cmds)]
            kind = rng.choices(list(kinds), weights=[KINDS[k] for k in kinds])[0]
            sig = rng.choice(["SIGINT", "SIGTERM"])
            job = dict(i=i, cmd=cmd, kind=kind, signal=sig, delay=None, point=None)
            c = ref[cmd]["counts"]
            if kind == "time":
                job["delay"] = rng.uniform(0, 1.05 * ref[cmd]["seconds"])
            elif kind == "process":
                job["delay"] = rng.uniform(0, 1.05 * ref[cmd]["process_seconds"])
            elif kind == "gc":
                job["point"] = ["gc", rng.randint(1, max(1, c["gc"]))]
            else:
                f = rng.choice([f for f in ("replace", "rename", "unlink", "rmdir") if c[f]] or ["replace"])
                job["point"] = [f, rng.randint(1, max(1, c[f]))]
            jobs.append(job)

        def one(args):
            w, job = args
            d = work / f"job{job['i']:04d}"
            shutil.rmtree(d, ignore_errors=True)
            shutil.copytree(work / f"earlier_{job['cmd']}", d)
            target = d / COMMANDS[job["cmd"]][2]
            before = snapshot(d)
            if job["kind"] == "process":
                r = _process_run(_argv(job["cmd"], inputs, target, 2), d, job["delay"], job["signal"])
            else:
                r = w.run(dict(argv=_argv(job["cmd"], inputs, target, 2), cwd=str(d),
                               stderr=str(work / f"job{job['i']:04d}.err"), signal=job["signal"], delay=job["delay"],
                               point=job["point"]))
            after = snapshot(d)
            late = job["kind"] == "time" and r["sent"] is not None and r["decided"] is not None and r["sent"] > r["decided"]
            startup = False
            # a harness artifact: CPython clears the signals a forked child caught before its
            # at-fork reset, so one sent then is lost to the fork, not to the command
            forkwin = job["kind"] == "time" and r["sent"] is not None and r.get("child") is not None \
                and r["sent"] < r["child"]
            if job["kind"] == "process" and r["sent"] is not None and r["rc"] != 130:
                # a real process gives no hook: classify by what it left.  Killed or interrupted
                # before interrupts.install() ran (the package's imports), nothing touched:
                startup = r["rc"] in (-15, -2, 1) and after == before and (r["rc"] != 1 or "KeyboardInterrupt" in r["stderr"])
                # or after it had decided its status: the unsignalled status and the new output
                late = not startup and r["rc"] == ref[job["cmd"]]["process_rc"]
            fired = job["kind"] != "time" and r["counts"] is not None and \
                r["counts"][job["point"][0]] >= job["point"][1]
            delivered = (job["kind"] in ("time", "process") and r["sent"] is not None and not late and not startup
                         and not forkwin) or fired
            hidden = sorted(k for k in after if k.startswith(".") and k not in before)
            intact = after == before
            complete = (not intact) and _complete(job["cmd"], target, ref[job["cmd"]]["files"])
            problems = []

            if delivered:
                if r["rc"] != 130:
                    problems.append(f"exit {r['rc']}")
                err = r["stderr"].strip().splitlines()
                last = f"accel-bayes {job['cmd']}: interrupted"
                # before the swap the refusal is the one line; after it the run may have printed
                # its own status line first
                if not err or err[-1] != last or (len(err) > 1 and intact) or \
                        any(b in r["stderr"] for b in ("Traceback", "Exception ignored")):
                    problems.append("stderr: " + r["stderr"].strip()[-300:])
            elif late:
                if r["rc"] != ref[job["cmd"]]["rc"]:
                    problems.append(f"late signal: exit {r['rc']} instead of {ref[job['cmd']]['rc']}")
            if hidden:
                problems.append(f"left {hidden[:3]}")
            if not intact and not complete:
                problems.append("target neither the earlier output nor a complete new one")
            if late and intact:
                problems.append("late signal but the new output is missing")
            shutil.rmtree(d, ignore_errors=True)
            if startup and (hidden or not intact):
                problems.append("start-up kill left something")
            if forkwin and (hidden or not (intact or complete)):
                problems.append("signal in the fork window left something")
            return dict(job, rc=r["rc"], delivered=delivered, late=late, startup=startup, forkwin=forkwin, intact=intact,
                        complete=complete,
                        problems=problems, seconds=r["seconds"])

        t0 = time.time()
        order = [(pool[i % workers], j) for i, j in enumerate(jobs)]
        with ThreadPoolExecutor(workers) as ex:
            # one job at a time per worker: each thread owns one worker
            lanes = [[o for o in order if o[0] is w] for w in pool]
            results = [r for lane in ex.map(lambda lane: [one(o) for o in lane], lanes) for r in lane]
        wall = time.time() - t0
    finally:
        for w in pool:
            w.close()
    results.sort(key=lambda r: r["i"])
    dl = [r for r in results if r["delivered"]]
    out = {
        "signals": n, "workers": workers, "seed": seed, "wall_s": wall,
        "delivered": len(dl), "late": sum(r["late"] for r in results),
        "startup": sum(r["startup"] for r in results),
        "startup_rc": sorted({r["rc"] for r in results if r["startup"]}),
        "fork_window": sum(r["forkwin"] for r in results),
        "not_delivered": sum(not (r["delivered"] or r["late"] or r["startup"] or r["forkwin"]) for r in results),
        "exit_130": sum(r["rc"] == 130 for r in dl),
        "earlier_intact": sum(r["intact"] for r in dl), "new_complete": sum(r["complete"] for r in dl),
        "failed": [r for r in results if r["problems"]],
        "reference": {c: {"rc": v["rc"], "seconds": round(v["seconds"], 2), "counts": v["counts"],
                          "process_seconds": round(v["process_seconds"], 2)} for c, v in ref.items()},
        "by": {},
    }
    for key in ("cmd", "kind", "signal"):
        for v in sorted({r[key] for r in results}):
            rs = [r for r in dl if r[key] == v]
            out["by"][f"{key}={v}"] = {"delivered": len(rs), "exit_130": sum(r["rc"] == 130 for r in rs),
                                      "earlier_intact": sum(r["intact"] for r in rs),
                                      "new_complete": sum(r["complete"] for r in rs)}
    return out


def main_(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--signals", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=29)
    ap.add_argument("--only", choices=("signals", "probes"), default=None)
    ap.add_argument("--kinds", default=",".join(KINDS), help="delivery kinds (default: all)")
    ap.add_argument("--commands", default=",".join(COMMANDS), help="commands signalled (default: all)")
    ap.add_argument("--work", default=None, help="scratch folder (default: a temporary one)")
    ap.add_argument("--json", default=None, help="write the results as JSON here")
    ap.add_argument("--md", default=None, help="write the results document here")
    a = ap.parse_args(argv)
    work = Path(a.work) if a.work else Path(tempfile.mkdtemp(prefix="output_safety_"))
    res = {}
    if a.only in (None, "signals"):
        res["signals"] = signal_study(a.signals, a.workers, a.seed, work / "signals", kinds=a.kinds.split(","),
                                      commands=a.commands.split(","))
        s = res["signals"]
        print(f"signals: {s['signals']} sent, {s['delivered']} delivered during the command, {s['late']} late, "
              f"{s['exit_130']} exit 130, {len(s['failed'])} failed, {s['wall_s']:.0f} s", file=sys.stderr)
    if a.only in (None, "probes"):
        from output_safety_probes import probes

        res["probes"] = probes(work / "probes")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1, default=str))
    if a.md:
        from output_safety_probes import write_md

        write_md(Path(a.md), res, " ".join(["PYTHONPATH=$PWD python3 experiments/output_safety.py", *(argv or sys.argv[1:])]),
                 f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.node()} "
                 f"({os.cpu_count()} CPUs, Python {platform.python_version()})")
    if not a.work:
        shutil.rmtree(work, ignore_errors=True)
    return 0 if not res.get("signals", {}).get("failed") else 1


if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).parent))
    sys.exit(main_())

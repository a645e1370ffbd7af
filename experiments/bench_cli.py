#!/usr/bin/env python3
"""Benchmark: start-up of the command line, now against 00ae2ff (issue #26 item 5).

At 00ae2ff every ``accel-bayes`` invocation imported torch, pyro, arviz and matplotlib before it
parsed its arguments (``accel_bayes/__init__.py`` imported the recording module; the parser's
``register`` functions imported pipelines), so ``--help`` or the refusal of a missing file took
seconds.  This script times, for this checkout and for a checkout of 00ae2ff (a ``git worktree``
under /tmp, made if ``--base`` is not given), each of

* ``help`` — ``accel-bayes --help``; ``version`` — ``--version``;
* ``map_help`` / ``calibrate_help`` — ``COMMAND --help``;
* ``refusal_missing`` — ``accel-bayes map missing.nc --out o`` (exit 2: no such recording file);
* ``refusal_exists`` — ``accel-bayes simulate -o rec.nc`` with rec.nc present (exit 2: exists);

as ``python -m accel_bayes ARGS`` (the console script's path: package, then ``cli.main``) in a fresh
process with the tree first on PYTHONPATH, one thread, run alone (one process at a time, ours and
00ae2ff alternating in every repetition so both see the same machine load), ``--reps`` times
(default 10); the median wall time is reported.  A separate untimed run with ``-X importtime``
says which of torch, pyro, arviz, matplotlib each command imported.  Each run's exit status is
checked (0 for help/version, 2 for the refusals) in both trees.  One line per case (DESIGN §7.4)::

    RESULT cli_<case>: ours <x> s, 00ae2ff <y> s, speedup <r>x

With ``--structure W1,W2``, it then runs ``bench_structure.py`` on those workloads against the same
00ae2ff checkout (``--structure-reps`` runs each), to show the computing commands are not slower,
and puts its output in the Markdown file too.

    python experiments/bench_cli.py [--reps 10] [--base DIR] [--md experiments/bench_cli.md]
                                    [--structure lm_selfcal,map,likelihood --structure-reps 5]
                                    [--previous experiments/bench_cli.md]
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BASE_COMMIT = "00ae2ff"
HEAVY = ("torch", "pyro", "arviz", "matplotlib")

# case -> (arguments, expected exit status)
CASES = {
    "help": (["--help"], 0),
    "version": (["--version"], 0),
    "map_help": (["map", "--help"], 0),
    "calibrate_help": (["calibrate", "--help"], 0),
    "refusal_missing": (["map", "missing.nc", "--out", "o"], 2),
    "refusal_exists": (["simulate", "-o", "rec.nc"], 2),
}


def ensure_base(path: Path | None) -> Path:
    """A checkout of :data:`BASE_COMMIT`: ``path``, or a git worktree under the temp directory."""
    if path is not None:
        return path
    path = Path(tempfile.gettempdir()) / f"accel_bayes_{BASE_COMMIT}"
    if not (path / "accel_bayes").is_dir():
        subprocess.run(["git", "worktree", "add", "--detach", str(path), BASE_COMMIT], cwd=REPO, check=True,
                       stdout=subprocess.DEVNULL)
    return path


def _env(tree: Path) -> dict:
    return dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1",
                OPENBLAS_NUM_THREADS="1")


def _check_tree(tree: Path, cwd: Path) -> None:
    # an editable install of another checkout must not serve the package
    out = subprocess.run([sys.executable, "-c", "import accel_bayes; print(accel_bayes.__file__)"], cwd=cwd,
                         env=_env(tree), capture_output=True, text=True, check=True).stdout.strip()
    if not Path(out).resolve().is_relative_to(tree.resolve()):
        raise SystemExit(f"{tree}: python imports accel_bayes from {out}, not from the tree under test")


def run_once(tree: Path, args: list[str], cwd: Path, expect: int) -> float:
    """Wall seconds of one ``python -m accel_bayes ARGS`` in a fresh process."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "accel_bayes", *args], cwd=cwd, env=_env(tree),
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    dt = time.perf_counter() - t0
    if p.returncode != expect:
        raise SystemExit(f"{tree}: accel-bayes {' '.join(args)} exited {p.returncode}, expected {expect}:\n"
                         f"{p.stderr[-1000:]}")
    return dt


def heavy_imports(tree: Path, args: list[str], cwd: Path) -> list[str]:
    """Which of :data:`HEAVY` ``python -m accel_bayes ARGS`` imports (untimed, ``-X importtime``)."""
    p = subprocess.run([sys.executable, "-X", "importtime", "-m", "accel_bayes", *args], cwd=cwd, env=_env(tree),
                       stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    names = {ln.rsplit("|", 1)[1].strip().split(".")[0] for ln in p.stderr.splitlines()
             if ln.startswith("import time:") and ln.count("|") == 2}
    return [h for h in HEAVY if h in names]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=10, help="timed runs of each case per tree (median; default 10)")
    ap.add_argument("--base", type=Path, default=None, help=f"a checkout of {BASE_COMMIT} (default: a git worktree "
                                                            f"{tempfile.gettempdir()}/accel_bayes_{BASE_COMMIT})")
    ap.add_argument("--md", type=Path, default=None, help="also write the results as Markdown to this file")
    ap.add_argument("--structure", default="", metavar="W1,W2",
                    help="also run bench_structure.py on these workloads against the same baseline (default: none)")
    ap.add_argument("--structure-reps", type=int, default=5, help="bench_structure.py --reps (default 5)")
    ap.add_argument("--previous", type=Path, default=None,
                    help="an earlier report of this script (e.g. the --md file before it is overwritten): its "
                         "measurement line and RESULT lines are carried into a 'previous run' section")
    args = ap.parse_args(argv)
    previous = _previous_results(args.previous) if args.previous is not None else None
    base = ensure_base(args.base)
    load0 = os.getloadavg()
    started = datetime.datetime.now(datetime.timezone.utc)
    rows = []
    with tempfile.TemporaryDirectory() as d:
        cwd = Path(d)
        (cwd / "rec.nc").write_bytes(b"present: the refusal must not read it")
        for tree in (REPO, base):
            _check_tree(tree, cwd)
        print(f"ours: {REPO}   baseline: {base} ({BASE_COMMIT})   reps: {args.reps}   "
              f"load (1/5/15 min): {load0[0]:.2f} {load0[1]:.2f} {load0[2]:.2f}", flush=True)
        for name, (cargs, expect) in CASES.items():
            t_ours, t_base = [], []
            for _ in range(args.reps):
                t_ours.append(run_once(REPO, cargs, cwd, expect))
                t_base.append(run_once(base, cargs, cwd, expect))
            h_ours, h_base = heavy_imports(REPO, cargs, cwd), heavy_imports(base, cargs, cwd)
            mo, mb = statistics.median(t_ours), statistics.median(t_base)
            rows.append((name, cargs, mo, mb, min(t_ours), max(t_ours), min(t_base), max(t_base), h_ours, h_base))
            print(f"INFO cli_{name}: accel-bayes {' '.join(cargs)}; ours {', '.join(f'{t:.3f}' for t in t_ours)} s "
                  f"(imports {', '.join(h_ours) or 'none of ' + '/'.join(HEAVY)}); {BASE_COMMIT} "
                  f"{', '.join(f'{t:.3f}' for t in t_base)} s (imports {', '.join(h_base) or 'none'})", flush=True)
    load1 = os.getloadavg()
    for name, _, mo, mb, *_ in rows:
        print(f"RESULT cli_{name}: ours {mo:.3f} s, {BASE_COMMIT} {mb:.3f} s, speedup {mb / mo:.1f}x", flush=True)
    structure = None
    if args.structure:
        cmd = [sys.executable, str(REPO / "experiments" / "bench_structure.py"), "--base", str(base), "--base-commit",
               BASE_COMMIT, "--only", args.structure, "--reps", str(args.structure_reps)]
        structure = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, check=True).stdout
        print(structure, end="", flush=True)
    if args.md is not None:
        _write_md(args.md, rows, args.reps, base, started, load0, load1, structure, args, previous)
    return 0


# the modules bench_structure's workloads time (the pipelines' plotting and I/O are not timed there)
TIMED_CODE = ("accel_bayes/model/likelihood.py", "accel_bayes/inference", "accel_bayes/physics", "accel_bayes/simulate.py",
              "accel_bayes/prep", "accel_bayes/threads.py")


def _diffstat() -> list[str]:
    out = subprocess.run(["git", "diff", "--stat", BASE_COMMIT, "--", *TIMED_CODE], cwd=REPO, capture_output=True,
                         text=True, check=True).stdout
    return [ln.rstrip() for ln in out.splitlines() if ln.strip()]


def _structure_verdict(structure: str) -> str:
    """One sentence from bench_structure's output: which workloads are not slower (speedup ≥ 0.95)
    on the same results, and which are slower or computed something else (the heading must not
    claim more than the numbers show)."""
    import re

    speed = {m.group(1): float(m.group(2)) for m in re.finditer(r"RESULT structure_(\w+): .* speedup ([0-9.]+)x", structure)}
    rel = {m.group(1): float(m.group(2))
           for m in re.finditer(r"INFO structure_(\w+): .*result max \|diff\| \S+ \(relative ([0-9.e+-]+)\)", structure)}
    same = [w for w in speed if speed[w] >= 0.95 and rel.get(w, 0.0) == 0.0]
    other = [f"{w} ({speed[w]:.3f}x, results relative {rel.get(w, 0.0):.1e})" for w in speed if w not in same]
    return (f"Not slower and the same results: {', '.join(same) or 'none'}. "
            f"Slower or not the same work in both trees: {', '.join(other) or 'none'}.")


def _previous_results(path: Path) -> list[str]:
    """The "Measured …" line and the RESULT lines of an earlier report written by :func:`_write_md`
    (read before the new report replaces it), so that a rerun keeps the numbers it is compared with."""
    text = path.read_text(encoding="utf-8").splitlines()
    measured = [ln for ln in text if ln.startswith("Measured ")][:1]
    results = [ln for ln in text if ln.startswith("RESULT ")]
    if not results:
        raise SystemExit(f"--previous: {path} holds no RESULT line; expected a report of this script")
    return measured + results


def _write_md(path: Path, rows, reps: int, base: Path, started, load0, load1, structure, args,
              previous: list[str] | None = None) -> None:
    sys.path.insert(0, str(REPO))
    from accel_bayes.data.outputs import write_text

    lines = [
        "# Start-up of the command line, now against 00ae2ff (issue #26 item 5)",
        "",
        f"Regenerate ({(time.time() - started.timestamp()) / 60:.0f} min here; run it when the machine is quiet):",
        "",
        "    python experiments/bench_cli.py --md experiments/bench_cli.md"
        + (f" --structure {args.structure} --structure-reps {args.structure_reps}" if structure else "")
        + (f" --previous {args.previous}" if previous else ""),
        "",
        f"Measured {started:%Y-%m-%d %H:%M} UTC on `{platform.node()}` ({os.cpu_count()} cores, "
        f"Python {platform.python_version()}), shared with other developers' jobs: load average (1/5/15 min) "
        f"{load0[0]:.2f} / {load0[1]:.2f} / {load0[2]:.2f} at the start, {load1[0]:.2f} / {load1[1]:.2f} / "
        f"{load1[2]:.2f} at the end. Each time is the median of {reps} runs of `python -m accel_bayes ARGS` in a "
        f"fresh process, one at a time, this checkout and 00ae2ff (`{base}`) alternating; one thread.",
        "",
        "| case | command | ours (s) | 00ae2ff (s) | speedup | ours: range (s) | 00ae2ff: range (s) | "
        "ours imports | 00ae2ff imports |",
        "|---|---|---:|---:|---:|---|---|---|---|",
    ]
    for name, cargs, mo, mb, lo_o, hi_o, lo_b, hi_b, h_o, h_b in rows:
        lines.append(f"| {name} | `accel-bayes {' '.join(cargs)}` | {mo:.3f} | {mb:.3f} | {mb / mo:.1f}x | "
                     f"{lo_o:.3f}–{hi_o:.3f} | {lo_b:.3f}–{hi_b:.3f} | {', '.join(h_o) or '—'} | "
                     f"{', '.join(h_b) or '—'} |")
    worst = max(r[2] for r in rows)
    lines += [
        "",
        f"Slowest case now: {worst:.3f} s (the issue's bar: ≤ 0.5 s). \"imports\" lists which of torch, pyro, "
        "arviz and matplotlib the command imported (`-X importtime`, an untimed extra run); "
        "`tests/cli/test_cli_startup.py` checks the same for every command's `--help` and refusals, on modules, "
        "not seconds.",
        "",
        "```",
        *[f"RESULT cli_{r[0]}: ours {r[2]:.3f} s, {BASE_COMMIT} {r[3]:.3f} s, speedup {r[3] / r[2]:.1f}x"
          for r in rows],
        "```",
        "",
    ]
    if structure:
        lines += [
            "## The computing commands",
            "",
            _structure_verdict(structure),
            "",
            f"`bench_structure.py` (workloads {args.structure}; median of {args.structure_reps} fresh processes per tree, "
            "alternating, one thread; `speedup` = 00ae2ff / ours, the bar of issue #10 ≥ 0.95; `result max |diff|`: "
            "the same work in both trees), run right after the table above. On this shared machine the wall time of "
            "the same work varies by tens of percent from run to run; the CPU-time ratio of each INFO line (process "
            "time, less disturbed by other jobs) is the steadier comparison. What changed since 00ae2ff in the "
            "modules these workloads run (`git diff --stat 00ae2ff -- " + " ".join(TIMED_CODE) + "`):",
            "",
            "```",
            *(_diffstat() or ["(nothing)"]),
            "```",
            "",
            "```",
            *structure.strip().splitlines(),
            "```",
            "",
        ]
    if previous:
        lines += [
            "## The previous run of this report",
            "",
            "Carried over by `--previous` (the same script, an earlier checkout; compare it with the tables "
            "above, minding the machine load of each run):",
            "",
            *(previous[:1] if previous[0].startswith("Measured ") else []),
            "",
            "```",
            *[ln for ln in previous if ln.startswith("RESULT ")],
            "```",
            "",
        ]
    write_text(path, "\n".join(lines))
    print(f"wrote {path}")


if __name__ == "__main__":
    sys.exit(main())

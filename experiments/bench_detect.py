#!/usr/bin/env python3
"""Benchmark: ``detect`` with its defaults on whole recordings, now against 7adf109 (issue #11 item 3).

What a user waits for: the wall time of :func:`accel_bayes.mismatch.detect` with every default
(baseline fit, locate with 100 PPC twins, screens, LM refits, drop-one refits, unexplained cells,
refined fit with PSIS-LOO), on every sample the one prepared selection keeps — nothing is
subsampled.  Each call runs in a fresh process with one CPU thread (OMP_NUM_THREADS=1, as the
package pins by default), the two trees alternating, on the same data in the same run; the time is
that of the ``detect`` call alone (imports and reading the data are outside it; lazy imports inside
``detect`` are in it).  Printed per workload::

    RESULT detect_<workload>: ours <x> s, 7adf109 <y> s, speedup <r>x

plus the CPU time, the load average before and after, and whether the findings (effect, IMU,
axis) agree.

Workloads (the same samples in both trees):

* ``mimu_exp1`` — the real MIMU4444 experiment 1, whole: ours is ``detect(import_mimu(...))``
  (:func:`~accel_bayes.mismatch.prepared.prepare` applies the intrinsics from the rests and the
  sample selection inside ``detect``).  7adf109's ``detect`` had no such preparation, so it gets the
  recording our preparation fits (intrinsics applied, the selected samples), written as a
  format-v1 file.  Goal: ≤ 180 s on an idle 2-core machine.
* ``mimu32_T3000`` — the 32-IMU ``mimu32`` preset, ``accel_bayes.simulate`` smooth (continuous)
  motion, T = 3000 at 100 Hz, seed 1, with one concealed effect (a 1 % scale error on IMU 9's
  accelerometer y axis) so the detector goes through a finding, its refits and the refined fit;
  one format-v1 file read by both trees.  Goal: ≤ 30 s on an idle 2-core machine.

7adf109 can take several minutes on exp_1 on a loaded machine: each of its calls gets
``--timeout`` seconds (default 300, so the default run stays within 10 minutes, DESIGN §7.4);
one that runs out is reported as "> timeout" and the speedup as a lower bound.  ``--full`` lifts
the timeout.

    python experiments/bench_detect.py [--base DIR] [--only mimu_exp1,mimu32_T3000] [--timeout S | --full] [--md PATH]

``--md PATH`` also writes the printed lines as a results document (``experiments/bench_detect.md``).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from bench_structure import BASE_COMMIT, ensure_base  # noqa: E402  (the one baseline worktree helper)

WORKLOADS = ("mimu_exp1", "mimu32_T3000")

# Runs in a fresh process with the tree under test first on PYTHONPATH.  ``mode`` "mimu" imports
# the raw MIMU stream (our tree); "file" reads a format-v1 file with whichever reader the tree has.
WORKER = textwrap.dedent('''
    import json, sys, time, warnings
    warnings.simplefilter("ignore")
    sys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in type(f).__name__
                        and "Editable" not in getattr(f, "__name__", "")]
    import torch
    from accel_bayes.mismatch import detect
    mode, path = sys.argv[1], sys.argv[2]
    if mode == "mimu":
        from accel_bayes.data.mimu import import_mimu
        rec = import_mimu(path)
    else:
        try:
            from accel_bayes.data.io import load_recording
            rec = load_recording(path, require_gyro=True).recording
        except ImportError:  # 7adf109
            from accel_bayes.io import read_recording
            rec = read_recording(path, require_gyro=True)
    t0, c0 = time.perf_counter(), time.process_time()
    rep = detect(rec)
    seconds, cpu = time.perf_counter() - t0, time.process_time() - c0
    d = rep.to_dict()
    T = (d.get("details", {}).get("recording") or {}).get("T")
    print(json.dumps({"seconds": seconds, "cpu": cpu, "T": T, "threads": torch.get_num_threads(),
                      "findings": [[f["effect"], f.get("imu"), f.get("axis")] for f in d["findings"]]}))
''')


def run_case(tree: Path, mode: str, path: Path, timeout: float | None) -> dict:
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    load0 = os.getloadavg()[0]
    try:
        out = subprocess.run([sys.executable, "-c", WORKER, mode, str(path)], cwd="/tmp", env=env, capture_output=True,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        return {"timeout": timeout, "load": [load0, os.getloadavg()[0]]}
    if out.returncode != 0:
        raise SystemExit(f"detect failed in {tree} on {path}:\n{out.stderr[-2000:]}")
    r = json.loads(out.stdout.strip().splitlines()[-1])
    r["load"] = [load0, os.getloadavg()[0]]
    return r


def write_cases(tmp: Path, only: list) -> dict:
    """{workload: (ours (mode, path), 7adf109 (mode, path))}, the data written once."""
    from accel_bayes.data.io import write_recording

    cases = {}
    if "mimu_exp1" in only:
        from _data import data_dir
        from accel_bayes.data.mimu import import_mimu
        from accel_bayes.mismatch.prepared import prepare

        raw = data_dir() / "exp_1" / "data.bin.gz"
        prep = prepare(import_mimu(raw))  # exactly what detect() fits in our tree
        p = tmp / "exp_1_prepared.nc"
        write_recording(prep.rec, p, overwrite=True)
        cases["mimu_exp1"] = (("mimu", raw), ("file", p), f"T = {prep.T} of {prep.source.T} samples, K = {prep.K}")
    if "mimu32_T3000" in only:
        from accel_bayes.physics.arrays import preset
        from accel_bayes.simulate import simulate

        sim = simulate(preset("mimu32"), "smooth", T=3000, rate=100.0, seed=1,
                       effects=[{"effect": "acc_scale", "imu": 9, "axis": "y", "parameters": {"scale": 0.01}}])
        p = tmp / "mimu32_T3000.nc"
        write_recording(sim.recording, p, overwrite=True)
        cases["mimu32_T3000"] = (("file", p), ("file", p), "T = 3000, K = 32, acc_scale 1 % on IMU 9 axis y")
    return cases


def _fmt(r: dict) -> str:
    if "timeout" in r:
        return f"> {r['timeout']:.0f} s (timed out; load {r['load'][0]:.1f} → {r['load'][1]:.1f})"
    f = ", ".join(f"{e}[{i},{a}]" if a else f"{e}[{i}]" for e, i, a in r["findings"]) or "none"
    return (f"{r['seconds']:6.1f} s wall, {r['cpu']:6.1f} s CPU, T = {r['T']}, load {r['load'][0]:.1f} → "
            f"{r['load'][1]:.1f}; findings: {f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", type=Path, default=None, help=f"checkout of {BASE_COMMIT} (default: a worktree in experiments/out)")
    ap.add_argument("--only", default=",".join(WORKLOADS), help="comma-separated workloads")
    ap.add_argument("--timeout", type=float, default=300.0, help=f"seconds per {BASE_COMMIT} call (default 300)")
    ap.add_argument("--full", action="store_true", help=f"no timeout for {BASE_COMMIT}")
    ap.add_argument("--md", type=Path, default=None, help="also write the printed lines to this markdown file")
    args = ap.parse_args(argv)
    lines = []

    def print(*a, **k):  # noqa: A001  every printed line also goes to --md
        import builtins

        lines.append(" ".join(str(x) for x in a))
        builtins.print(*a, **k)

    only = [w for w in args.only.split(",") if w]
    for w in only:
        if w not in WORKLOADS:
            raise SystemExit(f"--only: unknown workload {w!r}; expected some of {', '.join(WORKLOADS)}")
    base = ensure_base(args.base)
    timeout = None if args.full else args.timeout
    print(f"ours: {REPO}   baseline: {base} ({BASE_COMMIT})   one thread each, fresh processes   "
          f"load average: {' '.join(f'{v:.2f}' for v in os.getloadavg())}   CPUs: {os.cpu_count()}", flush=True)
    with tempfile.TemporaryDirectory() as td:
        cases = write_cases(Path(td), only)
        for i, (wl, (ours_in, base_in, desc)) in enumerate(cases.items()):
            order = [("ours", REPO, ours_in), ("base", base, base_in)]
            if i % 2:
                order.reverse()
            r = {who: run_case(tree, *inp, timeout=None if who == "ours" else timeout) for who, tree, inp in order}
            print(f"{wl} ({desc}):\n  ours:    {_fmt(r['ours'])}\n  {BASE_COMMIT}: {_fmt(r['base'])}", flush=True)
            xo, rb = r["ours"]["seconds"], r["base"]
            if "timeout" in rb:
                agree = "unknown (7adf109 timed out)"
                print(f"INFO detect_{wl}: findings agree: {agree}; speedup is a lower bound")
                print(f"RESULT detect_{wl}: ours {xo:.1f} s, {BASE_COMMIT} > {rb['timeout']:.0f} s, "
                      f"speedup > {rb['timeout'] / xo:.2f}x")
            else:
                agree = "yes" if r["ours"]["findings"] == rb["findings"] else "no"
                print(f"INFO detect_{wl}: findings agree: {agree}; CPU ours {r['ours']['cpu']:.1f} s, "
                      f"{BASE_COMMIT} {rb['cpu']:.1f} s")
                print(f"RESULT detect_{wl}: ours {xo:.1f} s, {BASE_COMMIT} {rb['seconds']:.1f} s, "
                      f"speedup {rb['seconds'] / xo:.2f}x")
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    if args.md is not None:
        cmd = "python experiments/bench_detect.py " + " ".join(argv if argv is not None else sys.argv[1:])
        args.md.write_text("# detect on whole recordings, ours vs 7adf109 (issue #11 item 3)\n\n"
                           "Written by `experiments/bench_detect.py` (its docstring says what is measured and how).\n\n"
                           f"Command: `{cmd.strip()}`\n\n```\n" + "\n".join(lines) + "\n```\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

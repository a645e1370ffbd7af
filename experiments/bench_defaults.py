#!/usr/bin/env python3
"""Benchmark: ``calibrate`` with its defaults, now against 7adf109, on boards nobody tuned on (issue #15 item 3).

What a new user waits for: the wall time of ``calibrate(recording)`` with every default (MAP,
choice of N, the chains, the summary), and whether the result is converged — every coordinate
R̂ < 1.01 and bulk and tail ESS ≥ 400.  The same recordings (format-v1 files written once into a
temporary directory) go through this checkout and through a checkout of 7adf109 (a git worktree;
``--base DIR``), each call in a fresh process with one CPU thread (OMP_NUM_THREADS=1: what
``calibrate`` now uses by default, and fair to 7adf109, whose two threads would only add contention
on this shared machine), the two trees alternating case by case so that both see the same load.

Workloads:

* ``boards`` — the 20 random boards of ``experiments/_boards.py`` (independent simulator, 6–10
  IMUs over 6–16 cm, smooth motion, 100–250 Hz, T = 2500, no rests).  Goal: converged in every
  case, median ≤ 30 s, max ≤ 60 s.
* ``mimu_exp1`` — the real MIMU4444 experiment 1 with all real-data defaults (intrinsics from its
  rests, sample selection, estimated and tempered noise).  Goal: ≤ 15 s wall.
* ``mimu32`` — 32 IMUs, T = 500, [C21] §IV-A i.i.d. motion (σ_a 0.04 m/s², no sensor ranges).
  Goal: bulk ESS ≥ 400 on every coordinate in ≤ 15 s.

Pyro NUTS, the external peer, is in ``experiments/bench_posterior.py`` (it needs minutes per
chain on these sizes).  Output: one line per case, then::

    RESULT defaults_<workload>_<stat>: ours <x> s, 7adf109 <y> s, speedup <r>x

    python experiments/bench_defaults.py [--base DIR] [--only boards,mimu_exp1,mimu32] [--boards 20]
    python experiments/bench_defaults.py --device cuda [--only ...]     # issue #15 item 4

``--device DEV``: "ours" is ``calibrate(..., device=DEV)`` (the chains on DEV; preparation, MAP and
summary stay on the CPU) and the peer is this same checkout on the CPU instead of 7adf109; the
RESULT lines then read ``RESULT defaults_<workload>_<stat>[DEV]: ours x s (DEV), cpu y s, …``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))
from bench_structure import BASE_COMMIT, ensure_base  # noqa: E402  (the one baseline worktree helper)

# Runs in a fresh process with the tree under test first on PYTHONPATH: calibrate from its 0.1 home,
# or from its 7adf109 path where the tree predates it (the alias went in 0.2.0).
WORKER = textwrap.dedent('''
    import json, sys, time, warnings
    warnings.simplefilter("ignore")
    sys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in type(f).__name__
                        and "Editable" not in getattr(f, "__name__", "")]
    import numpy as np
    import arviz as az
    try:
        from accel_bayes.pipelines.calibrate import calibrate
    except ImportError:  # 7adf109
        from accel_bayes.calibrate import calibrate
    path, device = sys.argv[1], (sys.argv[2] if len(sys.argv) > 2 else None)
    t0 = time.perf_counter()
    res = calibrate(path, seed=0, progress=False, **({"device": device} if device else {}))
    seconds = time.perf_counter() - t0
    post = res.idata.posterior["r"]
    ess_b = float(az.ess(res.idata, method="bulk")["r"].min())
    ess_t = float(az.ess(res.idata, method="tail")["r"].min())
    rhat = float(az.rhat(res.idata)["r"].max())
    print(json.dumps({"seconds": seconds, "rhat": rhat, "ess_bulk": ess_b, "ess_tail": ess_t,
                      "draws": int(post.sizes["draw"]), "chains": int(post.sizes["chain"]),
                      "mean": np.asarray(post.mean(("chain", "draw"))).tolist()}))
''')


def run_case(tree: Path, path: Path, device: str | None = None) -> dict:
    # one thread in both trees: calibrate pins one now (accel_bayes.threads), and 7adf109 with two
    # threads on a loaded shared machine would be slowed by contention, not by its algorithm
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", WORKER, str(path)] + ([device] if device else []), cwd="/tmp",
                         env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"calibrate failed in {tree} on {path}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def converged(r: dict) -> bool:
    return r["rhat"] < 1.01 and r["ess_bulk"] >= 400 and r["ess_tail"] >= 400


def write_cases(tmp: Path, only: set, n_boards: int) -> dict:
    """{workload: [(name, path)]}: the recordings as format-v1 files."""
    from accel_bayes.data.io import write_recording

    cases = {}
    if "boards" in only:
        import _boards

        cases["boards"] = []
        for name, case in _boards.random_boards(n_boards):
            p = tmp / f"{name}.nc"
            write_recording(case.recording, p, overwrite=True)
            cases["boards"].append((name, p))
    if "mimu_exp1" in only:
        from _data import data_dir
        from accel_bayes.data.mimu import import_mimu

        p = tmp / "exp_1.nc"
        write_recording(import_mimu(data_dir() / "exp_1" / "data.bin.gz"), p, overwrite=True)
        cases["mimu_exp1"] = [("exp_1", p)]
    if "mimu32" in only:
        from accel_bayes.constants import DEG_TO_RAD
        from accel_bayes.physics.arrays import preset
        from accel_bayes.simulate import simulate

        arr = preset("mimu32").with_(acc_range=None, gyro_range=None)
        sim = simulate(arr, "iid", T=500, seed=0, clip=False, acc_noise_std=0.04, gyro_noise_std=0.06 * DEG_TO_RAD,
                       position_error_std=1e-4)
        p = tmp / "mimu32.nc"
        write_recording(sim.recording, p, overwrite=True)
        cases["mimu32"] = [("mimu32 T=500", p)]
    return cases


def _fmt(r: dict) -> str:
    return (f"{r['seconds']:6.1f} s, R̂ {r['rhat']:.4f}, ESS bulk/tail {r['ess_bulk']:.0f}/{r['ess_tail']:.0f}, "
            f"{r['chains']}×{r['draws']} draws{'' if converged(r) else ' NOT CONVERGED'}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", type=Path, default=None, help=f"checkout of {BASE_COMMIT} (default: a worktree in experiments/out)")
    ap.add_argument("--only", default="boards,mimu_exp1,mimu32", help="comma-separated workloads")
    ap.add_argument("--boards", type=int, default=20, help="number of random boards (default 20)")
    ap.add_argument("--device", default=None, metavar="DEV",
                    help="run ours with calibrate(device=DEV) against this checkout on the CPU (e.g. cuda)")
    args = ap.parse_args(argv)
    only = set(args.only.split(","))
    if args.device:
        from accel_bayes.pipelines.calibrate import _device_option
        from accel_bayes.errors import UserError

        try:
            _device_option(args.device, None)
        except UserError as exc:
            raise SystemExit(f"--device: {str(exc).split(': ', 1)[1]}") from None
        base, peer, tag, on = REPO, "cpu", f"[{args.device}]", f" ({args.device})"
    else:
        base, peer, tag, on = ensure_base(args.base), BASE_COMMIT, "", ""
    res = {}
    with tempfile.TemporaryDirectory() as td:
        cases = write_cases(Path(td), only, args.boards)
        for wl, items in cases.items():
            res[wl] = []
            for i, (name, p) in enumerate(items):
                order = [("ours", REPO), ("base", base)] if i % 2 == 0 else [("base", base), ("ours", REPO)]
                r = {who: run_case(tree, p, args.device if who == "ours" else None) for who, tree in order}
                res[wl].append((name, r))
                print(f"{wl} {name}: ours{on} {_fmt(r['ours'])} | {peer} {_fmt(r['base'])}", flush=True)
    for wl, rows in res.items():
        ours = [r["ours"] for _, r in rows]
        basr = [r["base"] for _, r in rows]
        n_ok = sum(converged(r) for r in ours), sum(converged(r) for r in basr)
        print(f"INFO defaults_{wl}: converged (R̂ < 1.01, bulk and tail ESS ≥ 400) in {n_ok[0]}/{len(ours)} cases "
              f"(ours{on}), {n_ok[1]}/{len(basr)} ({peer})")
        stats = [("median", statistics.median)] if len(rows) > 1 else [("wall", statistics.median)]
        if len(rows) > 1:
            stats.append(("max", max))
        for stat, f in stats:
            xo, xb = f([r["seconds"] for r in ours]), f([r["seconds"] for r in basr])
            print(f"RESULT defaults_{wl}_{stat}{tag}: ours {xo:.1f} s{on}, {peer} {xb:.1f} s, speedup {xb / xo:.2f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

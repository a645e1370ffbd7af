#!/usr/bin/env python3
"""Benchmark: the package as it is now against the same code before the restructuring (issue #10).

Issue #10 moved every mechanism to one home (one Jacobian module, one LM, one sample selection,
packages that follow the pipeline) and promised that nothing got slower.  This script runs the
same three workloads, through public names that exist in both trees, once with this checkout on
``PYTHONPATH`` and once with a checkout of the baseline commit (default 7adf109, created as a git
worktree under ``experiments/out/`` if ``--base`` is not given), alternating the two in every
repetition so that both see the same machine load, each run in a fresh process with one torch
thread:

* ``lm_selfcal`` — [S16] self-calibration (``inference.selfcal.self_calibrate``) of the Table I
  plate (5 triads) under the slow table motion, 675 samples at 125 Hz, σ = 0.02 m/s²: the LM graph
  solver with its motion-only warm start and re-run remedy, time to solution;
* ``map`` — the [C21] MAP (``inference.map.fit_map_recording``) of the 8-IMU corner board,
  T = 600 smooth motion (the demo configuration), time to solution;
* ``likelihood`` — one Rao-Blackwellized log p̂ (``model.likelihood.RaoBlackwellLikelihood.log_phat``),
  32 IMUs, T = 500, N = 1000, [C21] §IV-A motion: median of 9 evaluations inside the process;
* ``posterior`` — ``calibrate`` with its defaults (MAP, choice of N, 4 chains × (1000 + 1000) PmMH
  iterations) on the demo configuration; wall time of the whole call.

Prints the median wall time over ``--reps`` runs (default 5) for each, the process CPU time beside it
(steadier on a shared machine), and one line per workload
(DESIGN §7.4)::

    RESULT structure_<workload>: ours <x> s, 7adf109 <y> s, speedup <r>x

``speedup`` = baseline / ours (> 1: faster now).  The issue's bar is ≥ 0.95.  Deterministic results
(positions, cost, log p̂) are compared too: the same inputs must give the same numbers to the
solver tolerance, or the timing compares different work.

    python experiments/bench_structure.py [--reps 5] [--base DIR] [--base-commit C] [--only lm_selfcal,map,...]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import textwrap
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BASE_COMMIT = "7adf109"

# Each workload prints one JSON line {"seconds": s, "value": [...]} and uses only names that exist
# at 7adf109 and now, from their 0.1 homes or, in a tree that predates them, their 7adf109 paths
# (_home; the aliases of the old paths went in 0.2.0).
WORKLOADS = {
    "lm_selfcal": """
        preset = _home("physics.arrays", "arrays").preset
        from accel_bayes.simulate import simulate
        from accel_bayes.inference.selfcal import self_calibrate
        sim = simulate(preset("s16plate"), "table", T=675, rate=125.0, seed=3, acc_noise_std=0.02,
                       position_error_std=0.0, clip=False)
        rec = sim.recording
        arr = rec.sensor_array()
        tic()
        res = self_calibrate(rec.acc, rec.time, nominal_positions=arr.positions,
                             nominal_orientations=arr.orientations, acc_noise_std=0.02)
        seconds, cpu = toc()
        value = res.positions.reshape(-1).tolist()
    """,
    "map": """
        preset = _home("physics.arrays", "arrays").preset
        from accel_bayes.simulate import simulate
        from accel_bayes.inference.map import fit_map_recording
        sim = simulate(preset("mimu8"), "smooth", T=600, seed=1)
        # the same work in both trees: [C21]'s flat φ (the default since issue #15 is the empirical prior)
        kw = {"phi_prior": "flat"} if "phi_prior" in inspect.signature(fit_map_recording).parameters else {}
        tic()
        res = fit_map_recording(sim.recording, progress=False, **kw)
        seconds, cpu = toc()
        value = res.positions.reshape(-1).tolist()
    """,
    "likelihood": """
        import statistics
        mimu4444_32 = _home("physics.arrays", "arrays").mimu4444_32
        from accel_bayes.simulate import simulate
        RaoBlackwellLikelihood = _home("model.likelihood", "likelihood").RaoBlackwellLikelihood
        sim = simulate(mimu4444_32(), "iid", T=500, seed=0, position_error_std=0.0, acc_noise_std=0.04, clip=False)
        lik = RaoBlackwellLikelihood.from_recording(sim.recording, num_draws=1000, gyro_method="calibrated")
        pos = sim.true_positions[list(lik.imu_labels)]
        z = lik.sample_z(generator=torch.Generator().manual_seed(2))
        gen = torch.Generator().manual_seed(1)
        lik.log_phat(pos, generator=gen)
        ts = []
        for _ in range(9):
            tic()
            lik.log_phat(pos, generator=gen)
            ts.append(toc())
        seconds = statistics.median(t[0] for t in ts)
        cpu = statistics.median(t[1] for t in ts)
        value = [float(lik.log_phat(pos, z=z))]
    """,
    "posterior": """
        preset = _home("physics.arrays", "arrays").preset
        from accel_bayes.simulate import simulate
        calibrate = _home("pipelines.calibrate", "calibrate").calibrate
        sim = simulate(preset("mimu8"), "smooth", T=600, seed=1)
        kw = {"phi_prior": "flat"} if "phi_prior" in inspect.signature(calibrate).parameters else {}
        tic()
        res = calibrate(sim.recording, seed=1, progress=False, **kw)
        seconds, cpu = toc()
        value = [e["mean"] for e in res.positions["imus"]]
        value = [v for m in value for v in (m or [])]
    """,
}

PRELUDE = """
import inspect
import json, sys, time, warnings
warnings.simplefilter("ignore")
# an editable install's finder would serve modules missing from the tree under test
sys.meta_path[:] = [f for f in sys.meta_path if "Editable" not in type(f).__name__ and "Editable" not in getattr(f, "__name__", "")]
import importlib
import torch
torch.set_num_threads(1)
def _home(new, old):
    try:
        return importlib.import_module("accel_bayes." + new)
    except ImportError:  # a tree before the 0.1 layout
        return importlib.import_module("accel_bayes." + old)
_clock = {}
def tic():
    _clock["wall"], _clock["cpu"] = time.perf_counter(), time.process_time()
def toc():
    return time.perf_counter() - _clock["wall"], time.process_time() - _clock["cpu"]
"""


def ensure_base(path: Path | None, commit: str = BASE_COMMIT) -> Path:
    if path is not None:
        return path
    path = REPO / "experiments" / "out" / f"base_{commit}"
    if not (path / "accel_bayes").is_dir():
        path.parent.mkdir(parents=True, exist_ok=True)
        subprocess.run(["git", "worktree", "add", "--detach", str(path), commit], cwd=REPO, check=True,
                       stdout=subprocess.DEVNULL)
    return path


def run_once(tree: Path, workload: str) -> dict:
    code = PRELUDE + textwrap.dedent(WORKLOADS[workload]) + '\nprint(json.dumps({"seconds": seconds, "cpu": cpu, "value": value}))\n'
    env = dict(os.environ, PYTHONPATH=str(tree), OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([sys.executable, "-c", code], cwd="/tmp", env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"{workload} failed in {tree}:\n{out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--reps", type=int, default=5, help="runs of each workload per tree (median reported; default 5)")
    ap.add_argument("--base", type=Path, default=None, help=f"a checkout of {BASE_COMMIT} (default: a git worktree "
                                                            "under experiments/out/)")
    ap.add_argument("--only", default=",".join(WORKLOADS), help="comma-separated workloads (default all)")
    ap.add_argument("--base-commit", default=BASE_COMMIT,
                    help=f"the baseline's commit, named in the output (default {BASE_COMMIT}; with --base, the commit "
                         "that checkout holds)")
    args = ap.parse_args(argv)
    base = ensure_base(args.base, args.base_commit)
    peer = args.base_commit
    names = [w for w in args.only.split(",") if w]
    for w in names:
        if w not in WORKLOADS:
            raise SystemExit(f"--only: unknown workload {w!r}; expected some of {', '.join(WORKLOADS)}")
    print(f"ours: {REPO}   baseline: {base} ({peer})   reps: {args.reps}   load: {os.getloadavg()[0]:.2f}")
    for w in names:
        t_ours, t_base, c_ours, c_base, v_ours, v_base = [], [], [], [], None, None
        for _ in range(args.reps):
            r = run_once(REPO, w)
            t_ours.append(r["seconds"])
            c_ours.append(r["cpu"])
            v_ours = r["value"]
            r = run_once(base, w)
            t_base.append(r["seconds"])
            c_base.append(r["cpu"])
            v_base = r["value"]
        diff = max(abs(a - b) for a, b in zip(v_ours, v_base)) if v_ours else 0.0
        scale = max(abs(b) for b in v_base) if v_base else 1.0
        mo, mb = statistics.median(t_ours), statistics.median(t_base)
        print(f"INFO structure_{w}: ours {', '.join(f'{t:.3f}' for t in t_ours)} s; "
              f"{peer} {', '.join(f'{t:.3f}' for t in t_base)} s; result max |diff| {diff:.2e} "
              f"(relative {diff / scale:.1e}); CPU time medians: ours {statistics.median(c_ours):.4f} s, "
              f"{peer} {statistics.median(c_base):.4f} s, ratio {statistics.median(c_base) / statistics.median(c_ours):.3f}")
        print(f"RESULT structure_{w}: ours {mo:.4f} s, {peer} {mb:.4f} s, speedup {mb / mo:.3f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Cost of ``calibrate --model report.json`` against the default ``calibrate`` on one whole real
experiment, in the same run (issue #30 Deliver 3: at most 2×).

Both are the command line's defaults (chains run until converged: R̂ < 1.01, bulk and tail ESS ≥ 400,
4 chains, seed 0), on the same loaded recording, in one process, alternating (model, default, model,
default, …) so that the shared machine's load falls on both alike; wall time per call of
:func:`accel_bayes.pipelines.calibrate.calibrate` (what ``accel-bayes calibrate`` runs; file writing
not included).  The report is the experiment's own ``mismatch`` report (``experiments/mimu_mismatch.py``;
its ``sampling_clock`` and ``unresolved_motion`` findings enter the per-sample likelihood, with the board's
angular jerk beside the jerk: ``calibrate``'s default under a model).

    PYTHONPATH=. python3 experiments/percov_bench_calibrate.py --reports DIR [--exp 1] [--rounds 2]

Writes ``experiments/percov_bench_calibrate.md`` and ends with ``RESULT`` lines (DESIGN §7.4).
"""
from __future__ import annotations

import argparse
import hashlib
import os
import platform
import sys
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _data import data_dir  # noqa: E402

from accel_bayes.data.mimu import import_mimu  # noqa: E402
from accel_bayes.data.outputs import write_text  # noqa: E402
from accel_bayes.pipelines.calibrate import calibrate  # noqa: E402

BAR = 2.0


def one(rec, model):
    """(wall s, draws per chain, converged, process CPU s) of one default calibration, with or
    without ``model``."""
    t0, c0 = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = calibrate(rec, seed=0, progress=False, model=model)
    d = r.positions["diagnostics"]
    return time.perf_counter() - t0, int(d["draws_per_chain"]), bool(d["converged"]), time.process_time() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reports", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--exp", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--doc", type=Path, default=HERE / "percov_bench_calibrate.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    path = data_dir() / f"exp_{args.exp}" / "data.bin.gz"
    report = args.reports / f"exp_{args.exp}" / "report.json"
    if not path.exists() or not report.exists():
        print(f"skipped: {path} or {report} not found")
        return 0
    rec = import_mimu(path)
    load0 = os.getloadavg()[0]
    rows = {"model": [], "default": []}
    for i in range(args.rounds):
        for name in (("model", "default") if i % 2 == 0 else ("default", "model")):
            rows[name].append(one(rec, report if name == "model" else None))
            print(name, rows[name][-1], flush=True)
    load1 = os.getloadavg()[0]
    med = {k: float(np.median([w for w, _, _, _ in v])) for k, v in rows.items()}
    cpu = {k: float(np.median([c for _, _, _, c in v])) for k, v in rows.items()}
    ratio = med["model"] / med["default"]
    stamp = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = [f"# `calibrate --model` against the default `calibrate`, exp_{args.exp} (issue #30 Deliver 3)", "",
         f"Regenerate: `PYTHONPATH=. python3 experiments/percov_bench_calibrate.py --reports {args.reports} "
         f"--exp {args.exp} --rounds {args.rounds}` ({stamp}, {platform.machine()} {platform.system()}, "
         f"{os.cpu_count()} cores, load average {load0:.1f} at the start and {load1:.1f} at the end, one torch "
         "thread; the two "
         "alternate in one process, so the ratio is what the load leaves comparable, the absolute times are "
         "inflated by it; the process CPU time beside it is what the other jobs disturb least).", "",
         "Both with the defaults (run until converged, 4 chains, seed 0) on the whole recording "
         f"(`{path.parent.name}/data.bin.gz`, {rec.T} samples); the model: the experiment's own `mismatch` report "
         f"(sha256 {hashlib.sha256(report.read_bytes()).hexdigest()[:16]}…), with the board's angular jerk (on by "
         "default under `--model`).",
         "", "| run | wall s per call | CPU s per call | draws per chain | converged |", "|---|---|---|---|---|"]
    for k, v in rows.items():
        L.append(f"| {k} | {', '.join(f'{w:.1f}' for w, _, _, _ in v)} (median {med[k]:.1f}) | "
                 f"{', '.join(f'{c:.1f}' for _, _, _, c in v)} | "
                 f"{', '.join(str(n) for _, n, _, _ in v)} | {', '.join(str(c) for _, _, c, _ in v)} |")
    L += ["", f"Bar (≤ {BAR:.0f}× the default): **{ratio:.2f}×** wall — {'met' if ratio <= BAR else 'NOT met'} "
          f"({cpu['model'] / cpu['default']:.2f}× in CPU time).", "",
          "```", f"RESULT calibrate_model_exp{args.exp}: ours {med['model']:.1f} s, default {med['default']:.1f} s, "
          f"speedup {1 / ratio:.2f}x", "```", ""]
    write_text(args.doc, "\n".join(L))
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Benchmark: one log p̂ with the per-sample covariance (unresolved jerk loaded by the data ages,
:mod:`accel_bayes.model.likelihood_percov`) against today's flat model, on the real exp_1
(issue #30 item 3: bar ≤ 4× the flat one).

Setting (as ``bench_iteration.py``'s exp1 case): exp_1 of the shared MIMU4444 recordings through
``calibrate``'s preparation (:func:`accel_bayes.prep.preprocess.preprocess`), N = 1, the nominal
positions, stated noise, the eq. 30 gyro posterior, one torch thread.  The data ages are the
sampling clocks that ``experiments/clock_mimu.py`` found on exp_1 (its
``results/clock_mimu/exp_1.json``: beat, phase, drift, width per IMU; filter delay 0) at the
kept samples' times.  The jerk scale is one number fitted here by maximising the exact
log p(y | ω̄, θ_nominal) (ω at the gyro mean) over a log grid — not a per-band fit; the cost does
not depend on it.  Both versions are evaluated in the same process, alternating blocks of calls,
on the same standard normals; medians of all calls (wall clock).  The per-sample model's ``nu``
variant (scale mixture, ν = 5) is timed too.

    PYTHONPATH=. python3 experiments/bench_likelihood_percov.py [--rounds 15] [--block 20]

Writes ``experiments/bench_likelihood_percov.md`` and ends with ``RESULT`` lines (DESIGN §7.4;
speedup < 1 means ours is slower).
"""
from __future__ import annotations

import argparse
import json
import math
import platform
import statistics
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from _data import data_dir  # noqa: E402

from accel_bayes.data.mimu import import_mimu  # noqa: E402
from accel_bayes.data.outputs import write_text  # noqa: E402
from accel_bayes.model.likelihood import RaoBlackwellLikelihood  # noqa: E402
from accel_bayes.model.likelihood_percov import with_unresolved_motion  # noqa: E402
from accel_bayes.physics.effects.clock import clock_age  # noqa: E402
from accel_bayes.prep.preprocess import preprocess  # noqa: E402


def exp1_ages(rec, lik) -> torch.Tensor:
    """(T, A) s: the clock_mimu sawtooth of each row's IMU at the kept samples' times."""
    clocks = json.loads((HERE / "results" / "clock_mimu" / "exp_1.json").read_text())["imus"]
    by_imu = {int(c["imu"]): c for c in clocks if c.get("accepted")}
    t = torch.as_tensor(np.asarray(rec.time)[np.asarray(lik.sample_index)], dtype=torch.float64)
    out = torch.zeros(lik.T, lik.A, dtype=torch.float64)
    for j, k in enumerate(lik.imu_labels):
        c = by_imu.get(int(k))
        if c is not None:
            out[:, j] = clock_age(t, c["beat_hz"], c["phase"], c["drift_hz_per_s"], c["width_s"])
    return out


def fit_jerk_scale(lik, age, pos) -> tuple[float, float]:
    """(s m/s³, gain nats) maximising log p(y | ω̄, θ) over a log grid (one scale for all samples)."""
    base = float(lik.log_lik_given_omega(pos, lik.omega.mean))
    best = (0.0, 0.0)
    for s in np.logspace(1, 6, 41):
        v = float(with_unresolved_motion(lik, age, float(s)).log_lik_given_omega(pos, lik.omega.mean)) - base
        if v > best[1]:
            best = (float(s), v)
    return best


def timed_blocks(fns: dict, rounds: int, block: int) -> dict:
    """Median ms per call of each function, blocks alternating between them."""
    times = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            for _ in range(block):
                t0 = time.perf_counter()
                fn()
                times[k].append(time.perf_counter() - t0)
    return {k: 1e3 * statistics.median(v) for k, v in times.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=15)
    ap.add_argument("--block", type=int, default=20)
    ap.add_argument("--md", type=Path, default=HERE / "bench_likelihood_percov.md")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    path = data_dir() / "exp_1" / "data.bin.gz"
    if not path.exists():
        print(f"skipped: {path} not found")
        return
    pre = preprocess(import_mimu(path))
    rec = pre.recording
    flat = RaoBlackwellLikelihood.from_recording(rec, num_draws=1, selection=pre.selection)
    pos = flat.nominal_positions.clone()
    age = exp1_ages(rec, flat)
    s, gain = fit_jerk_scale(flat, age, pos)
    per = with_unresolved_motion(flat, age, s)
    per_t = with_unresolved_motion(flat, age, s, nu=5.0)
    z = flat.sample_z((), 1, torch.Generator().manual_seed(0))
    with torch.no_grad():
        values = {"flat": float(flat.log_phat(pos, z=z)), "percov": float(per.log_phat(pos, z=z)),
                  "percov_t": float(per_t.log_phat(pos, z=z))}
        fns = {"flat": lambda: flat.log_phat(pos, generator=g), "percov": lambda: per.log_phat(pos, generator=g),
               "percov_t": lambda: per_t.log_phat(pos, generator=g)}
        g = torch.Generator().manual_seed(1)
        for fn in fns.values():  # warm the caches and scratch buffers
            fn()
        ms = timed_blocks(fns, args.rounds, args.block)
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    calls = args.rounds * args.block
    lines = [
        "# One log p̂ with the per-sample covariance vs the flat model, real exp_1 (issue #30 item 3)",
        "",
        f"Regenerate: `PYTHONPATH=. python3 experiments/bench_likelihood_percov.py --rounds {args.rounds} "
        f"--block {args.block}` ({now}, {platform.machine()} {platform.system()}, shared 2-core CPU, one torch "
        "thread; both models in one process, alternating blocks, medians of "
        f"{calls} calls each).",
        "",
        f"exp_1 prepared as `calibrate` does: T = {flat.T} samples, A = {flat.A} triads, N = 1 draw, nominal "
        "positions, stated noise. Data ages: the sampling clocks of `results/clock_mimu/exp_1.json` "
        f"(rms of the centred age over samples and IMUs {1e3 * float((age - age.mean(1, keepdim=True)).std()):.3f} ms). "
        f"Jerk scale fitted on a log grid at the gyro-mean ω: s = {s:.4g} m/s³ "
        f"(log p(y | ω̄, θ) gains {gain:.1f} nats over the flat model, {gain / flat.T:.3f} per sample; stated "
        "noise, so this gain is not the calibration's).",
        "",
        "| model | log p̂ (same z) | ms per log p̂ | × flat |",
        "|---|---|---|---|",
    ]
    for k, label in (("flat", "flat (today)"), ("percov", "per-sample covariance, Gaussian"),
                     ("percov_t", "per-sample covariance + scale mixture ν = 5")):
        lines.append(f"| {label} | {values[k]:.2f} | {ms[k]:.3f} | {ms[k] / ms['flat']:.2f} |")
    lines += ["", f"Bar (issue #30 item 3): ≤ 4× the flat model. Per-sample Gaussian: {ms['percov'] / ms['flat']:.2f}×; "
              f"with the scale mixture: {ms['percov_t'] / ms['flat']:.2f}×.", ""]
    results = [f"RESULT percov_log_phat_exp1: ours {ms['percov']:.3f} ms, flat {ms['flat']:.3f} ms, "
               f"speedup {ms['flat'] / ms['percov']:.2f}x",
               f"RESULT percov_t_log_phat_exp1: ours {ms['percov_t']:.3f} ms, flat {ms['flat']:.3f} ms, "
               f"speedup {ms['flat'] / ms['percov_t']:.2f}x"]
    lines += ["```", *results, "```", ""]
    write_text(args.md, "\n".join(lines))
    print("\n".join(lines[:-4 - len(results)]))
    for r in results:
        print(r)


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""Held-out scoring of the clock + unresolved-motion physics against strong generic models on the
six real MIMU4444 experiments (DESIGN §7.2.1; issue #27 item 4).

For each experiment (loaded as ``experiments/mimu_mismatch.py`` loads it: the raw import, the
package's preparation — intrinsics from the rests, the one sample selection — and the nominal
fit), the residuals of :func:`accel_bayes.mismatch.heldout.residuals_of`.  Each IMU's clock (beat,
phase, drift) is acquired by the detector's own beat search on its gyro timing statistics
(:func:`accel_bayes.mismatch.heldout.clocks_of`, i.e. :func:`accel_bayes.mismatch.clock.estimate_clock`)
twice: on the whole recording (used when the experiment is the source) and on its first
``--acquire-s`` seconds of kept samples (used when it is the target; every model is then scored on
the rest).  For all ordered pairs source → target, per sensor, in nats per sample on the same
residuals: banded white noise, Student-t per triad, multivariate t per sample, full cross-IMU
covariance per band, the physics model (clock-age mean + unresolved motion, white remainder) and
the physics model with each generic remainder; every parameter from the source.  Headline: the
physics-specific gain = best physics variant − best generic model (both chosen on the target's
scores), with a moving-block bootstrap standard error (blocks of 2 s) of that difference.

    python experiments/heldout_generic.py                      # all six, whole recordings
    python experiments/heldout_generic.py --experiments 1 2    # a subset (the document says so)
    python experiments/heldout_generic.py --from-results       # rewrite the document from results.json

Writes ``--out`` (default ``experiments/results/heldout_generic``): ``results.json``, and the
document ``experiments/heldout_generic.md``.
"""
from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
sys.path.insert(0, str(HERE))

from _data import data_dir  # noqa: E402
from mimu_mismatch import load_recording  # noqa: E402

from accel_bayes.data import outputs  # noqa: E402
from accel_bayes.mismatch import baseline_fit, prepare  # noqa: E402
from accel_bayes.mismatch.heldout import (GENERIC, PHYSICS, acquired_age, block_bootstrap_se,  # noqa: E402
                                          clocks_of, describe_source, fit_source, residuals_of, score)

SENSORS = ("acc", "gyro")


def load(i, args):
    """Experiment i's residuals and its two clock acquisitions (whole; first ``acquire_s``)."""
    rec, info = load_recording(i, args.data, args.max_samples)
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    res = residuals_of(prep, fit)
    n_acq = int(round(args.acquire_s * res.f_read))
    first = np.zeros(len(res.time), bool)
    first[:n_acq] = True
    c_all = clocks_of(res)
    c_acq = clocks_of(res, first)
    info.update(T_kept=int(len(res.time)), n_acquire=int(first.sum()), f_read=res.f_read,
                span_s=float(res.time[-1] - res.time[0]),
                acquire_span_s=float(res.time[n_acq - 1] - res.time[0]) if n_acq <= len(res.time) else None,
                beat_whole=c_all["beat_hz"].tolist(), phase_whole=c_all["phase"].tolist(),
                drift_whole=c_all["drift_hz_per_s"].tolist(),
                beat_first=c_acq["beat_hz"].tolist(), phase_first=c_acq["phase"].tolist(),
                drift_first=c_acq["drift_hz_per_s"].tolist())
    return {"res": res, "first": first, "info": info,
            "age_whole": acquired_age(res, c_all), "age_first": acquired_age(res, c_acq)}


def pair_result(src, tgt, args, seed):
    """Scores of every model of ``src`` on ``tgt``'s samples after its acquisition window, per
    sensor: mean nats/sample, gains over white, the headline and its bootstrap SE; the same
    physics scored with the target's clock acquired on its whole recording (a diagnostic that
    uses the scored samples for the clock: not a held-out number)."""
    keep = ~tgt["first"]
    sc = score(src["models"], tgt["res"], tgt["age_first"], keep)
    sc_in = score(src["models"], tgt["res"], tgt["age_whole"], keep)
    out = {}
    for s in SENSORS:
        ll = sc[s]["ll"]
        mean = {k: float(np.mean(v)) for k, v in ll.items()}
        best_g = max(GENERIC, key=lambda k: mean[k])
        best_p = max(PHYSICS, key=lambda k: mean[k])
        diff = ll[best_p] - ll[best_g]
        se = block_bootstrap_se(diff, block=args.block, n_boot=args.boot, seed=seed)
        se_pw = block_bootstrap_se(ll["physics"] - ll["white"], block=args.block, n_boot=args.boot, seed=seed)
        mean_in = {k: float(np.mean(v)) for k, v in sc_in[s]["ll"].items()}
        best_p_in = max(PHYSICS, key=lambda k: mean_in[k])
        out[s] = {"n": sc[s]["n"], "mean": mean, "best_generic": best_g, "best_physics": best_p,
                  "gain_over_white": {k: mean[k] - mean["white"] for k in mean},
                  "specific_gain": float(np.mean(diff)), "specific_se": se,
                  "physics_over_white_se": se_pw,
                  "specific_gain_clock_whole_target": mean_in[best_p_in] - max(mean_in[k] for k in GENERIC)}
    return out


def summary_markdown(R) -> str:
    """The results document's body from ``results.json``'s content."""
    exps = R["experiments"]
    L = ["## Clock acquisition (the detector's beat search): beat frequency per IMU (Hz)", "",
         "Whole recording (first-30-s acquisition in brackets), at t = 0 of the recording's clock. Acquired by "
         "`accel_bayes.mismatch.clock.estimate_clock` on each IMU's gyro timing statistics; the sign says which "
         "way the sawtooth ramps.", "",
         "| exp | " + " | ".join(f"IMU {k}" for k in range(len(R["info"][str(exps[0])]["beat_whole"]))) + " |",
         "|---|" + "---|" * len(R["info"][str(exps[0])]["beat_whole"])]
    for i in exps:
        inf = R["info"][str(i)]
        L.append(f"| {i} | " + " | ".join(f"{a:+.3f} ({b:+.3f})" for a, b in zip(inf["beat_whole"], inf["beat_first"])) + " |")
    L += ["", "Kept samples per experiment and the acquisition window (first "
          f"{R['acquire_s']:g} s of kept samples = {R['info'][str(exps[0])]['n_acquire']} samples):", "",
          "| exp | kept samples | recording span of kept samples (s) | acquisition window span (s) |", "|---|---|---|---|"]
    for i in exps:
        inf = R["info"][str(i)]
        L.append(f"| {i} | {inf['T_kept']} | {inf['span_s']:.0f} | {inf['acquire_span_s']:.0f} |")
    for s in SENSORS:
        rows = [R["pairs"][p][s] for p in R["pair_order"]]
        g = np.array([r["specific_gain"] for r in rows])
        se = np.array([r["specific_se"] for r in rows])
        z = g / se
        L += ["", f"## {s}: held-out nats per sample (target's samples after its acquisition window)", "",
              f"**Physics-specific gain** (best physics variant − best generic model): median {np.median(g):+.3f}, "
              f"range {g.min():+.3f} to {g.max():+.3f} nats/sample; above 3 block-bootstrap SE on "
              f"**{int((z > 3).sum())}/{len(g)}** pairs, below −3 SE on {int((z < -3).sum())}.", "",
              "Gains over banded white noise (nats/sample), per model; medians over the pairs: " + ", ".join(
                  f"{k} {np.median([r['gain_over_white'][k] for r in rows]):+.3f}" for k in GENERIC + PHYSICS) + ".", "",
              "| pair | n | best generic (gain over white) | physics over white ± SE | best physics variant (gain over white) "
              "| specific gain ± SE | z | clock from whole target (diagnostic) |",
              "|---|---|---|---|---|---|---|---|"]
        for p, r in zip(R["pair_order"], rows):
            gw = r["gain_over_white"]
            L.append(f"| {p} | {r['n']} | {r['best_generic']} ({gw[r['best_generic']]:+.3f}) | "
                     f"{gw['physics']:+.3f} ± {r['physics_over_white_se']:.3f} | {r['best_physics']} "
                     f"({gw[r['best_physics']]:+.3f}) | {r['specific_gain']:+.3f} ± {r['specific_se']:.3f} | "
                     f"{r['specific_gain'] / r['specific_se']:+.1f} | {r['specific_gain_clock_whole_target']:+.3f} |")
    L += ["", "## Source fits", "", "Per source and sensor: the clock-age mean's coefficient c (1 if the "
          "acquired age is the data age and the fitted outputs' rates the resolved motion), the unresolved "
          "scales per |ω| band (m/s³ for acc, rad/s² for gyro) of the physics model, and the fitted degrees "
          "of freedom of the t models.", "",
          "| source | sensor | c | unresolved scale per band (physics) | ν triad-t (per IMU) | ν sample-t |",
          "|---|---|---|---|---|---|"]
    for i in exps:
        d = R["sources"][str(i)]
        for s in SENSORS:
            m = d[s]
            L.append(f"| {i} | {s} | {m['c']:.3f} | " + ", ".join(f"{x:.3g}" for x in m["physics"]["unresolved_scale"])
                     + " | " + ", ".join(f"{x:.2g}" for x in m["triad_t"]["nu"]) + f" | {m['sample_t']['nu']:.3g} |")
    return "\n".join(L)


CAVEATS = """## Caveats (what this study does not settle)

- The target's acquisition window (its first 1875 kept samples) spans ~500 s of its ~580 s of
  kept-sample time, because the selection keeps scattered samples: the clock is extrapolated over
  the last ~80 s only, and the scored samples are the recording's last ~3900 kept samples.  A
  window of 30 s of wall time holds too few kept samples (50–77) to acquire a beat.
{headline}
- The clock is acquired by the detector's beat search (`estimate_clock`, with drift), but the
  acquisition sees the nominal fit's residuals, not the detector's (no gyro linear blocks removed
  first); a constant per-IMU lateness (read skew, filter-delay differences) is left out of the
  loading (the sawtooth's offset is dropped).
- Residuals are the nominal fit's: no mean effect (e.g. the gyro scale errors the detector finds)
  is removed before scoring, for any model.
- On the first-principles generator the unresolved-motion scale is over-stated by 1.2–1.9×
  (acc) and 1.6–1.9× (gyro) against the true unresolved jerk / angular acceleration at the board's
  centre (`tests/mismatch/test_unresolved_motion.py`, 10 s case); not yet explained (candidates: the
  per-IMU lever-arm jerk, which the board-common term cannot hold, and the linearisation at
  2π f × age ≈ 0.6 rad for 95 Hz vibration).
"""


def _headline(R) -> str:
    """The caveat on the headline (30/30 pairs above 3 SE per sensor), from the results."""
    parts = []
    for s in SENSORS:
        z = np.array([R["pairs"][p][s]["specific_gain"] / R["pairs"][p][s]["specific_se"] for p in R["pair_order"]])
        parts.append(f"{int((z > 3).sum())}/{len(z)} ({s})")
    met = all(int((np.array([R["pairs"][p][s]["specific_gain"] / R["pairs"][p][s]["specific_se"]
                             for p in R["pair_order"]]) > 3).sum()) == len(R["pair_order"]) for s in SENSORS)
    best = sorted({R["pairs"][p][s]["best_generic"] for p in R["pair_order"] for s in SENSORS})
    return (f"- The headline (above 3 SE on every pair, per sensor) is {'met' if met else 'not met'}: "
            f"{' and '.join(parts)}.  Best generic models chosen on the targets: {', '.join(best)}.")


def write_document(args, R, when) -> None:
    """The results document from ``R`` (the content of results.json)."""
    cmd = "python experiments/heldout_generic.py" + (
        f" --experiments {' '.join(map(str, args.experiments))}" if list(args.experiments) != [1, 2, 3, 4, 5, 6] else "") + (
        f" --max-samples {args.max_samples}" if args.max_samples else "")
    head = ["# Held-out scoring against strong generic models: the clock + unresolved-motion physics (issue #27 item 4)",
            "", f"Generated by `PYTHONPATH=. {cmd}` (finished {when}), "
            f"{platform.machine()} {platform.system()}, 2-core CPU shared with 6 other jobs, {R['seconds']:.0f} s "
            "(the document can be rewritten from the cached results with `--from-results`). "
            + ("Whole recordings (every kept sample)." if not args.max_samples else
               f"Last {args.max_samples} raw samples of each recording only."), "",
            "Method: `accel_bayes/mismatch/heldout.py` (module docstring). Every model scores the same residuals "
            "(the nominal fit's, leverage-corrected, array frame; samples with all 8 triads of the sensor observed). "
            "The target's clock is acquired on its first "
            f"{R['acquire_s']:g} s of *kept* samples (the sample selection keeps only ~50–77 samples in the "
            "first 30 s of wall time, too few to acquire a beat); every model is scored on the kept samples after "
            "that window. Best generic and best physics variant are chosen on the target's scores (so the generic "
            "side gets its best model). The last column re-acquires the target clock on its whole recording: a "
            "diagnostic of how much the clock's extrapolation costs, not a held-out number.", ""]
    outputs.write_text(args.doc, "\n".join(head) + "\n" + summary_markdown(R) + "\n\n"
                       + CAVEATS.format(headline=_headline(R)))
    print(f"written {args.doc}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--experiments", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--data", type=Path, default=data_dir())
    ap.add_argument("--out", type=Path, default=HERE / "results" / "heldout_generic")
    ap.add_argument("--doc", type=Path, default=HERE / "heldout_generic.md")
    ap.add_argument("--acquire-s", type=float, default=30.0, help="target clock acquisition window (s of kept samples)")
    ap.add_argument("--max-samples", type=int, default=None, help="last N raw samples only (off: whole recordings)")
    ap.add_argument("--block", type=int, default=125, help="bootstrap block length (samples)")
    ap.add_argument("--boot", type=int, default=400, help="bootstrap resamples")
    ap.add_argument("--from-results", action="store_true", help="only rewrite the document from OUT/results.json")
    args = ap.parse_args(argv)
    if args.from_results:
        R = json.loads((args.out / "results.json").read_text())
        args.experiments, args.max_samples = R["experiments"], R.get("max_samples")
        write_document(args, R, R.get("finished_utc", "unknown date"))
        return 0
    torch.manual_seed(0)
    args.out.mkdir(parents=True, exist_ok=True)  # before the long computation, so the results can be written
    t_start = time.perf_counter()
    data, R = {}, {"acquire_s": args.acquire_s, "experiments": args.experiments, "info": {}, "sources": {},
                   "pairs": {}, "pair_order": [], "max_samples": args.max_samples}
    for i in args.experiments:
        t0 = time.perf_counter()
        data[i] = load(i, args)
        t1 = time.perf_counter()
        data[i]["models"] = fit_source(data[i]["res"], data[i]["age_whole"], progress=lambda m: print(m, flush=True))
        R["info"][str(i)] = dict(data[i]["info"], load_seconds=t1 - t0, fit_seconds=time.perf_counter() - t1)
        R["sources"][str(i)] = describe_source(data[i]["models"])
        print(f"exp_{i}: {data[i]['info']['T_kept']} kept samples; loaded {t1 - t0:.0f} s, models fitted "
              f"{time.perf_counter() - t1:.0f} s; beats {np.round(data[i]['info']['beat_whole'], 3)}", flush=True)
    for n, i in enumerate(args.experiments):
        for j in args.experiments:
            if i == j:
                continue
            key = f"{i}->{j}"
            R["pairs"][key] = pair_result(data[i], data[j], args, seed=100 * i + j)
            R["pair_order"].append(key)
            print(key, {s: (R["pairs"][key][s]["best_generic"], R["pairs"][key][s]["best_physics"],
                            round(R["pairs"][key][s]["specific_gain"], 3), round(R["pairs"][key][s]["specific_se"], 3))
                        for s in SENSORS}, flush=True)
    R["seconds"] = time.perf_counter() - t_start
    R["finished_utc"] = f"{datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC"
    outputs.write_json(args.out / "results.json", outputs.to_jsonable(R))
    write_document(args, R, R["finished_utc"])
    print(f"written {args.doc} ({R['seconds']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

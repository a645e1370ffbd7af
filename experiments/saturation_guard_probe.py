#!/usr/bin/env python3
"""Do the detector's ``saturation`` findings reach their own limit?  A clip shows as outputs at ±L.  (issue #27)

``experiments/acc_stage_budget.md`` found ``saturation`` accepted on clockgen recordings that never clip
(clock-007 and -025 with the accelerometer stage; clock_budget's default run names one on clock-013, and
percov_conceal's reports on clock-007, -013 and -019): no flagged sample, |a| at most 53 m/s² against the
±157 m/s² range.  :class:`accel_bayes.physics.effects.Saturation` clamps the *model's* outputs at ±L, so a fitted
limit can also cut the model's peaks where they overshoot the data, which is not clipping.

Per detection, for every ``saturation`` finding: the fitted limit L, the largest |output| of its channel in the
recording the detector fitted (``report.prep``), (max |y| − L)/σ with σ the channel's stated noise, and how many
outputs lie within 5σ of L.  Cases: the ten concealed saturation cases of ``mismatch_proof`` (true clipping:
``_conceal`` clips the triad's outputs at 0.90–0.97 of its peak, after the noise), each rebuilt from its seed
and run with the proof's detector defaults; clockgen's clock-007, -013 and -025 as clock_budget draws them,
with the detector's defaults and with ``acc_linear=True``; and percov_conceal's clock-007, -013 and -019 (the
generator's accelerometer errors inverted, the mounting error applied, 20 s).

The rule this tested is now the detector's (``accel_bayes.mismatch.choose.SATURATION_AT_LIMIT``, counted by
``Saturation.outputs_at_limit``): a ``saturation`` refit whose channel holds fewer than 3 recorded outputs within
5σ of its fitted limit is refused (where none reach it, max |y| < L − 5σ, that count is 0).  A clip flattens every
peak beyond the range, so a real one holds several outputs at L; one output at L is a single peak cut.  Per case
the record keeps the findings (this script's own count, independent of the package's) and the refits the
detector refused by the rule, with the count it gave.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/saturation_guard_probe.py
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "saturation_guard_probe.md"
OUT = ROOT / "results" / "saturation_guard_probe"
from accel_bayes.mismatch.choose import SATURATION_AT_LIMIT  # noqa: E402

#: an output "at the limit" is within AT_LIMIT_SIGMAS stated-noise standard deviations of it; the rule keeps a clip
#: with at least MIN_AT_LIMIT outputs there (the detector's constants; the count below is this script's own)
AT_LIMIT_SIGMAS, MIN_AT_LIMIT = SATURATION_AT_LIMIT


def clip_findings(rep) -> list[dict]:
    """Every ``saturation`` finding of a :class:`~accel_bayes.mismatch.MismatchReport` with how far its channel's
    outputs (``rep.prep``, the recording the detector fitted) are from its limit."""
    p = rep.prep
    out = []
    for f in rep.to_dict()["findings"]:
        if f["effect"] != "saturation":
            continue
        L, k, sensor = float(f["parameters"]["limit"]), f["imu"], f.get("sensor") or "acc"
        y = (p.y_acc if sensor == "acc" else p.y_gyro).numpy()
        sig = (p.sigma_acc if sensor == "acc" else p.sigma_gyro).numpy()
        if k is None:  # every channel of the sensor
            ch, s = np.abs(y).reshape(-1), float(sig.max())
        else:
            ch, s = np.abs(y[:, int(k), "xyz".index(f["axis"])]), float(sig[int(k)])
        ch = ch[np.isfinite(ch)]
        out.append({"sensor": sensor, "imu": k, "axis": f.get("axis"), "limit": L, "max_abs": float(ch.max()),
                    "sigma": s, "reach_sigmas": float((ch.max() - L) / s),
                    "at_limit": int((np.abs(ch - L) <= AT_LIMIT_SIGMAS * s).sum()), "n": int(ch.size)})
    return out


def cases() -> list[tuple[str, str, callable]]:
    """(name, truth of clipping, recording maker) for every case of the module docstring."""
    from experiments._conceal import make_case
    from experiments.clock_proof import DURATION
    from experiments.clockgen import draw_case
    from experiments.percov_conceal import case_recording

    out = []
    for x in csv.DictReader((ROOT / "results" / "mismatch_proof" / "cases.csv").open()):
        if x["effect_true"] == "saturation":
            out.append((f"mismatch_proof {x['case']} ({x['board']})", "clips", {},
                        lambda b=x["board"], s=int(x["seed"]): make_case(b, "saturation", s).recording))
    for s in (7, 13, 25):
        for opt in ({}, {"acc_linear": True}):
            out.append((f"clock_budget clock-{s:03d}" + (" --acc-linear" if opt else ""), "no clipping", opt,
                        lambda s=s: draw_case("clock", s, duration=DURATION)[0]))
    for s in (7, 13, 19):
        out.append((f"percov_conceal clock-{s:03d}", "no clipping", {},
                    lambda s=s: case_recording(s, 20.0, 5e-4, acc_intrinsics="known")[0]))
    return out


def run_case(name: str, truth: str, options: dict, make, out: Path) -> dict:
    """One detection (defaults, seed 0, plus ``options``) and its clip findings; cached JSON in ``out``."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import detect

    path = out / (name.replace(" ", "_").replace("(", "").replace(")", "").replace("--", "") + ".json")
    if path.exists():
        return json.loads(path.read_text())
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        rep = detect(make(), seed=0, **options)
    res = {"case": name, "truth": truth, "options": options, "seconds": time.perf_counter() - t0,
           "clips": clip_findings(rep), "refused": guard_refusals(rep)}
    out.mkdir(parents=True, exist_ok=True)
    write_json(path, res)
    return res


def guard_refusals(rep) -> list[dict]:
    """The ``saturation`` refits the detector refused by its at-limit rule: candidate, outputs at its limit, why."""
    out = []
    for rnd in rep.rounds:
        counts = {r["candidate"]: r.get("outputs_at_limit") for r in rnd.get("refits", [])}
        out += [{"candidate": r["candidate"], "at_limit": counts.get(r["candidate"]), "why": r["why"]}
                for r in rnd.get("refused", []) if r["candidate"].startswith("saturation") and "of its limit" in r["why"]]
    return out


def refused(c: dict) -> bool:
    """The rule of the module docstring: fewer than :data:`MIN_AT_LIMIT` outputs at the fitted limit."""
    return c["at_limit"] < MIN_AT_LIMIT


def markdown(results: list[dict], cmd: str, secs: float) -> list[str]:
    from experiments._stamp import run_stamp

    L = ["# saturation_guard_probe — do the detector's saturation findings reach their own limit?", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; per-case records committed in "
         "`experiments/results/saturation_guard_probe/`).", "",
         "What runs: the script's docstring. Per finding: the fitted limit L, the channel's largest |output|, "
         f"(max − L)/σ, and the outputs within {AT_LIMIT_SIGMAS:g}σ of L; *rule* = the detector's rule (refuse a clip with "
         f"fewer than {MIN_AT_LIMIT} outputs at L) applied to the finding by this script's own count; *refused* = the "
         "refits the detector turned down by it (with its count).", ""]
    for truth in ("clips", "no clipping"):
        rows = [r for r in results if r["truth"] == truth]
        clips = [c for r in rows for c in r["clips"]]
        n_ref = sum(refused(c) for c in clips)
        n_guard = sum(len(r.get("refused", [])) for r in rows)
        L += [f"**{truth}**: {len(rows)} detections, {len(clips)} saturation findings, the rule refuses {n_ref}; "
              f"refits the detector refused by it: {n_guard}.", ""]
    L += ["| case | recording | finding | L | max \\|y\\| | (max − L)/σ | outputs at L | rule |", "|---|---|---|---|---|---|---|---|"]
    for r in results:
        if not r["clips"]:
            gone = "; ".join(f"{g['candidate']} ({g['at_limit']} at L)" for g in r.get("refused", []))
            L.append(f"| {r['case']} | {r['truth']} | none{' (refused: ' + gone + ')' if gone else ''} | | | | | |")
        for c in r["clips"]:
            L.append(f"| {r['case']} | {r['truth']} | {c['sensor']}[imu {c['imu']}, {c['axis']}] | {c['limit']:.3f} | "
                     f"{c['max_abs']:.3f} | {c['reach_sigmas']:+.1f} | {c['at_limit']}/{c['n']} | "
                     f"{'refuse' if refused(c) else 'keep'} |")
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    from experiments._reading import write_with_reading

    t0 = time.time()
    results = []
    for name, truth, options, make in cases():
        r = run_case(name, truth, options, make, args.out)
        print(f"{name}: " + ("; ".join(f"L {c['limit']:.3f}, reach {c['reach_sigmas']:+.1f}σ, at L {c['at_limit']}"
                                       for c in r["clips"]) or "no saturation finding"), flush=True)
        results.append(r)
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/saturation_guard_probe.py"
    write_with_reading(DOC, markdown(results, cmd, time.time() - t0))
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

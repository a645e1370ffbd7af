#!/usr/bin/env python3
"""The clock stage's wider search on every recording of the detector's single-effect proofs (issue #27).

Since 2026-11-29 the clock stage's beat search (:mod:`accel_bayes.mismatch.clock`, "Search") looks further: the
next 100 local maxima of the raw ranking are screened in the exact sawtooth model on its phase grid and the best
4 are tried besides the nominated peaks (:func:`~accel_bayes.mismatch.clock_screen.screen`).

That lets the stage try more candidates, so a recording without a clock has more chances of a false clock.
clock_proof covers the clockgen recordings (twins and clean ones included).  This script runs the stage as
``detect`` does with its defaults (:func:`experiments.clock_proof.clock_findings`: preparation, baseline fit,
the gyro linear stage, the clock stage at the detector's Bonferroni threshold) on

* ``proof``: mismatch_proof's 170 concealed single-effect recordings (``experiments/_conceal.py``; timing
  effects among them: ``sampling_jitter``, ``timing_wander``-like AR(1) instants, delays);
* ``multi``: mismatch_multi's 21 seeds, each as the effect case, its twin, the control (no linear gyro
  errors) and the clean set (84 recordings),

and records the clocks it accepts.  Those proofs' committed reports have no ``sampling_clock`` finding; where the
stage accepts none now either, the clock stage hands the rounds the recording unchanged and the proofs' findings
stand.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock_search_check.py --jobs 2
    PYTHONPATH=. python3 experiments/clock_search_check.py --summary    # the document from the cached records

Cached per recording in ``experiments/results/clock_search_check/{set}/`` (a rerun resumes).
"""
from __future__ import annotations

import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent
OUT = ROOT / "results" / "clock_search_check"
DOC = ROOT / "clock_search_check.md"
sys.path.insert(0, str(ROOT.parent))
sys.path.insert(0, str(ROOT))

SETS = ("proof", "multi")


def clock_record(rec) -> dict:
    """The clock stage's outcome on ``rec`` with the detector's defaults: accepted IMUs with their beat (Hz, at
    the kept samples' middle) and evidences, the stage threshold, and the largest evidence over the wander of an
    IMU's rejected pick (the stage's record of an IMU without a clock: rejected on its evidence, its width or its
    beat)."""
    from experiments.clock_proof import clock_findings

    st = clock_findings(rec)
    acc = [{"imu": int(f["imu"]), "beat_mid_hz": float(f["beat_mid_hz"]), "evidence": float(f["evidence"]),
            "evidence_vs_wander": float(f["evidence_vs_wander"]), "width_ms": 1e3 * float(f["width_s"])}
           for f in st.fits if f["accepted"]]
    rej = [float(f["evidence_vs_wander"]) for f in st.fits if not f["accepted"]]
    return {"accepted": acc, "threshold": float(st.threshold), "max_rejected_evw": max(rej) if rej else None,
            "n_imu": len(st.fits)}


def _job(spec) -> dict:
    from experiments.gyro_spread_check import recording

    which, name, _ = spec
    t0 = time.perf_counter()
    rec, meta = recording(spec)  # the same recordings as gyro_spread_check's sets, named alike
    r = clock_record(rec)
    r.update({"set": which, "name": name, **meta, "seconds": time.perf_counter() - t0})
    return r


def _path(which: str, name: str) -> Path:
    return OUT / which / (name.replace("/", "__") + ".json")


def _cached_job(spec) -> dict:
    from accel_bayes.data.outputs import write_json

    path = _path(spec[0], spec[1])
    if path.exists():
        return json.loads(path.read_text())
    r = _job(spec)
    write_json(path, r)
    return r


def run_set(which: str, jobs: int, cached_only: bool = False) -> tuple[list[dict], int]:
    """One set's records (computed, or read from ``OUT/{which}/``; ``cached_only``: those cached) and the
    number of recordings in the set."""
    from experiments.gyro_spread_check import _specs

    specs = _specs(which)
    (OUT / which).mkdir(parents=True, exist_ok=True)
    if cached_only:
        return [json.loads(_path(which, s[1]).read_text()) for s in specs if _path(which, s[1]).exists()], len(specs)
    if jobs > 1:
        with ProcessPoolExecutor(jobs) as ex:
            rows = list(ex.map(_cached_job, specs))
    else:
        rows = [_cached_job(s) for s in specs]
    return rows, len(specs)


def markdown(sets: dict, cmd: str) -> list[str]:
    from experiments._stamp import run_stamp

    L = ["# clock_search_check — the clock stage's wider search on the single-effect proofs' recordings", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; per-recording records cached in `experiments/results/clock_search_check/`).", "",
         "What is measured: the script's docstring (the exact model's screen of the ranking's next 100 local "
         "maxima).", "",
         "| set | recordings | recordings with a clock accepted | IMUs searched | largest evidence over the wander of "
         "an IMU's rejected pick / threshold (rejected on its evidence, width or beat) | seconds per recording "
         "(median) |", "|---|---|---|---|---|---|"]
    with_clock = []
    for which, (rows, n_set) in sets.items():
        if len(rows) < n_set:
            L.insert(-2, f"**Partial: {which} {len(rows)} of {n_set} recordings** (the run stopped at a deadline; "
                         "`clock_search_check.py --jobs 2` computes the rest, reusing the cached ones).\n")
        hit = [r for r in rows if r["accepted"]]
        with_clock += hit
        ratios = [r["max_rejected_evw"] / r["threshold"] for r in rows if r["max_rejected_evw"] is not None]
        secs = sorted(r["seconds"] for r in rows)
        L.append(f"| {which} | {len(rows)} | {len(hit)} | {sum(r['n_imu'] for r in rows)} | "
                 f"{max(ratios):.2f} | {secs[len(secs) // 2]:.1f} |" if ratios else
                 f"| {which} | {len(rows)} | {len(hit)} | {sum(r['n_imu'] for r in rows)} | — | — |")
    if with_clock:
        L += ["", "Recordings with a clock accepted (none has one: each is a false clock):", "",
              "| set | recording | board | effect | IMU | beat (Hz) | evidence over the wander / threshold |",
              "|---|---|---|---|---|---|---|"]
        for r in with_clock:
            for c in r["accepted"]:
                L.append(f"| {r['set']} | {r['name']} | {r['board']} | {r['effect']} | {c['imu']} | "
                         f"{c['beat_mid_hz']:+.3f} | {c['evidence_vs_wander']:.1f} / {r['threshold']:.1f} |")
    else:
        done, total = sum(len(r) for r, _ in sets.values()), sum(n for _, n in sets.values())
        L += ["", "No clock accepted on any recording: the proofs' findings (no `sampling_clock`) stand."
              if done == total else f"No clock accepted on any of the {done} recordings checked (of {total})."]
    return L


def main(argv=None) -> int:
    from experiments.gyro_spread_check import set_arguments

    which, a = set_arguments(__doc__.splitlines()[0], SETS, argv)
    sets = {s: run_set(s, a.jobs, cached_only=a.summary) for s in which}
    from experiments._reading import write_with_reading
    from experiments._stamp import invocation

    write_with_reading(DOC, markdown(sets, invocation("clock_search_check.py", argv)))
    print(DOC.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

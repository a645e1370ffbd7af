#!/usr/bin/env python3
"""Does the clock stage change the existing concealed proofs?  On a handful of cases of
``experiments/mismatch_proof.py`` (the 170-case proof, default settings) and
``experiments/mismatch_multi.py`` (effect case and clean twin), the detector's own steps up to its
clock stage (prepare, baseline fit, gyro linear stage where detect runs it, clock stage with the
detector's threshold).  Where the stage accepts no clock it leaves the prepared recording and the
fit untouched, so the rounds — and the case's top-1, location and false-alarm scores — are
exactly those of the detector before the stage; the table says where that holds.

    PYTHONPATH=. python3 experiments/clock_regression.py [--n 6]     # writes clock_regression.md
"""
from __future__ import annotations

import argparse
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT.parent))


def clock_only(rec) -> dict:
    """The detector's steps up to the clock stage on ``rec``: {"accepted", "best_evidence", "imus"}."""
    from accel_bayes.mismatch.clock import clock_stage
    from accel_bayes.mismatch.screens import candidate_effects, threshold_rule
    from accel_bayes.mismatch.fit import baseline_fit
    from accel_bayes.mismatch.gyro_linear import gyro_linear_stage
    from accel_bayes.mismatch.prepared import prepare

    prep = prepare(rec)
    base, _ = baseline_fit(prep)
    cands = candidate_effects(prep)
    n_gyro = int(np.asarray(prep.has_gyro).sum())
    m = len(cands) + (n_gyro + 1 if n_gyro >= 2 else 0)
    thr = threshold_rule(m, max(c.df for c in cands), 0.01)
    fit = base
    if n_gyro >= 2:
        st = gyro_linear_stage(prep, base, m=m, alpha=0.01)
        prep, fit = st.prep, st.fit
    cs = clock_stage(prep, fit, m=m, alpha=0.01, threshold=thr)
    return {"accepted": cs.info["accepted"], "K": prep.K,
            "max_evidence": max((f["evidence"] for f in cs.fits), default=0.0),
            "max_evidence_vs_wander": max((f["evidence_vs_wander"] for f in cs.fits), default=0.0),
            "threshold": cs.threshold}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=6, help="cases from each study")
    a = ap.parse_args(argv)
    import mismatch_proof as mp
    from _conceal import make_case, make_multi_case
    from mismatch_multi import build_cases as multi_cases
    from accel_bayes.data.outputs import write_text

    args = SimpleNamespace(effects=None, boards=list(mp.BOARDS), T=None, rate=None, seed=1, per_effect=10, clean=30)
    rows = []
    for c in mp.build_cases(args)[:a.n]:
        case = make_case(c["board"], c["effect"], c["seed"], **c["settings"])
        rows.append({"study": "mismatch_proof", "case": c["case_id"], **clock_only(case.recording)})
        print(rows[-1], flush=True)
    for c in multi_cases(max(a.n // 2, 1), 1):
        for kind, eff in (("", c["effect"]), ("twin ", "none")):
            case = make_multi_case(c["seed"], eff)
            rows.append({"study": "mismatch_multi", "case": kind + c["case_id"], **clock_only(case.recording)})
            print(rows[-1], flush=True)
    L = ["# clock_regression — the clock stage on cases of the existing concealed proofs", "",
         f"Regenerate: `PYTHONPATH=. python3 experiments/clock_regression.py --n {a.n}` "
         f"({datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC, {platform.machine()} {platform.system()}, shared 2-core CPU).",
         "", "No clock accepted = the detector's rounds and scores on that case are exactly those before the stage.", "",
         "| study | case | K | clocks accepted | largest evidence (vs none / vs wander) | stage threshold |", "|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['study']} | {r['case']} | {r['K']} | {r['accepted'] or 'none'} | "
                 f"{r['max_evidence']:.1f} / {r['max_evidence_vs_wander']:.1f} | {r['threshold']:.1f} |")
    n_un = sum(not r["accepted"] for r in rows)
    L += ["", f"Unchanged: {n_un}/{len(rows)} cases."]
    write_text(ROOT / "clock_regression.md", "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()

#!/usr/bin/env python3
"""The detector's accelerometer linear stage on issue #27's concealed budget: clock_budget's 30 cases.  (issue #27)

``experiments/budget_gap_probe.md`` found what fills the accelerometer gap a − b of the concealed budget:
every clockgen triad carries a real-size 3×3 error and offset (0.2–1 %, 0.1 m/s²) that its one-orientation
motion does not let ``prep`` calibrate, and inverting the generator's (``acc_known``) or an estimate of them
(``acc_blocks``) closes most of it.  The package's answer is the detector's accelerometer linear stage,
``DetectOptions(acc_linear=True)`` / ``accel-bayes mismatch --acc-linear`` (:mod:`accel_bayes.mismatch.acc_linear`;
opt-in): every triad's 3×3 + offset regressed on the fitted specific force after the gyro stage's relative
blocks, with its group, spread and per-block tests and six alternations with the motion; then the whole gyro
stage again (its common part, seen through the accelerometers' lever arms, now on corrected ones) and this
stage again on its gyros; the blocks held fixed and reported (``acc_scale``, axis null), no one-axis acc term
on a blocked triad.

Per case (clock seeds, the recordings and detector settings of ``experiments/clock_budget.py``; no oracle): the
whole detector with the option, its §7.2 budget and issue #27's per-band rule against clock_budget's committed
record of the same case (``experiments/results/clock_budget/``, defaults).  The record also keeps the blocks
(``A``, ``b``) and their output error against the generator's
(:func:`experiments.budget_gap_probe.block_output_error`), also projected off the per-sample linear motion
states (``identifiable_error_*``: on the coplanar plate4 the out-of-plane offsets affine in the in-plane
position are a constant angular acceleration, which no data see).  Unlike ``acc_blocks`` the stage leaves a as
it is (the baseline's residual on the recording as given) and is credited in b through the corrected outputs.

Records are committed in ``experiments/results/acc_stage/`` (a rerun reuses them; delete one to recompute it).

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_stage_budget.py
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "acc_stage_budget.md"
VARIANT = "acc_stage"
OUT = ROOT / "results"  # records in OUT / VARIANT / clock-SSS.json


def stage_blocks(doc: dict, K: int) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """(A (K, 3, 3), b (K, 3) in m/s², the blocked triads) from a report's acc_scale findings with a 3×3 scale
    (identity and zero where no block was kept)."""
    A, b, imus = np.eye(3)[None].repeat(K, 0), np.zeros((K, 3)), []
    for f in doc["findings"]:
        if f["effect"] == "acc_scale" and f.get("axis") is None:
            k = int(f["imu"])
            A[k], b[k] = np.eye(3) + np.asarray(f["parameters"]["scale"]), np.asarray(f["parameters"]["bias"])
            imus.append(k)
    return A, b, sorted(imus)


def run_case(variant: str, seed: int, out: Path) -> dict:
    """The detector with its accelerometer linear stage on clock case ``seed``; cached JSON in
    ``out/variant/clock-SSS.json`` (clock_budget's record, plus the blocks)."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import detect
    from experiments.budget_gap_probe import block_output_error
    from experiments.clock_budget import case_verdict
    from experiments.clock_proof import DURATION
    from experiments.clockgen import draw_case

    path = out / variant / f"clock-{seed:03d}.json"
    if path.exists():
        return json.loads(path.read_text())
    rec, truth = draw_case("clock", seed, duration=DURATION)
    t0 = time.perf_counter()
    doc = detect(rec, acc_linear=True).to_dict()
    seconds = time.perf_counter() - t0
    A, b, imus = stage_blocks(doc, rec.K)
    blocks = {"imus": imus, "stage": doc["details"].get("acc_linear_stage", {}).get("result"),
              "A": A.tolist(), "b": b.tolist(),
              # over every triad (identity where no block was kept), comparable with budget_gap_probe's acc_blocks
              **block_output_error(rec, truth, A, b, [int(k) for k in np.flatnonzero(np.asarray(rec.has_acc))])}
    res = {"variant": variant, "seed": seed, "board": truth["board"], "f_host": truth["f_host"], "seconds": seconds,
           "findings": [{"effect": f["effect"], "imu": f.get("imu"), "sensor": f.get("sensor")} for f in doc["findings"]],
           "budget": doc["budget"], "verdict": case_verdict(doc["budget"]), "acc_blocks": blocks}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, res)
    return res


def blocks_line(rows: list[tuple[dict, dict]]) -> str:
    """One paragraph: where blocks were kept and their output error against the generator's (medians)."""
    bl = [n["acc_blocks"] for _, n in rows if n.get("acc_blocks")]
    if not bl:
        return "No case has a block record."
    q = lambda key: np.median([x[key] for x in bl])  # noqa: E731
    kept = sum(len(x["imus"]) for x in bl)
    triads = sum(len(x["A"]) for x in bl)
    every = sum(1 for x in bl if x["imus"] and len(x["imus"]) == len(x["A"]))
    return (f"The stage kept blocks on {kept} of {triads} triads ({every} of {len(bl)} cases on every triad). Their "
            f"output error against the generator's, median over the cases (m/s², rms): less the triads' mean "
            f"{q('output_error_before_rms'):.4f} → {q('output_error_after_rms'):.4f}; projected off the per-sample s and "
            f"ω̇ (what no motion can absorb) {q('identifiable_error_before_rms'):.4f} → "
            f"{q('identifiable_error_after_rms'):.4f}.")


def markdown(rows: list[tuple[dict, dict]], cmd: str, secs: float) -> list[str]:
    """The document: the blocks, the failing bands' directions, the per-case table and totals."""
    from experiments._stamp import run_stamp
    from experiments.acc_correction_probe import variant_markdown
    from experiments.budget_gap_probe import fail_directions

    L = ["# acc_stage_budget — the accelerometer linear stage on issue #27's concealed budget", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; per-case records committed in "
         "`experiments/results/acc_stage/`).", "",
         "What runs: the script's docstring. Baseline: `clock_budget`'s records of the same cases, detector defaults "
         "(`experiments/results/clock_budget/`). Rule per band as clock_budget (b/a in 0.7–1.3, or |b − a| ≤ 3 SE where "
         "a ≤ 3 SE); 10 bands per sensor. Detector seconds per case with the stage: median "
         f"{np.median([n['seconds'] for _, n in rows]):.0f}, against {np.median([b['seconds'] for b, _ in rows]):.0f} in "
         "the baseline records (other runs, other load: not a timing comparison)."]
    part = variant_markdown(VARIANT, rows)
    fb, fn = fail_directions([b for b, _ in rows]), fail_directions([n for _, n in rows])
    part[3:3] = [blocks_line(rows), "",
                 f"Failing accelerometer bands, baseline → stage: b/a < 0.7 {fb[0]} → {fn[0]}, b/a > 1.3 {fb[1]} → "
                 f"{fn[1]}, a ≤ 3 SE with |b − a| > 3 SE {fb[2]} → {fn[2]}. Gyro: {'/'.join(map(str, fail_directions([b for b, _ in rows], 'gyro')))} → "
                 f"{'/'.join(map(str, fail_directions([n for _, n in rows], 'gyro')))}.", ""]
    return L + part


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default="0-29", help="clock case seeds, e.g. 0-29 or 1,3,5 (default 0-29)")
    ap.add_argument("--out", type=Path, default=OUT, help="records in OUT/acc_stage/ (default experiments/results)")
    ap.add_argument("--no-doc", action="store_true", help="run and cache the cases only")
    args = ap.parse_args(argv)
    from experiments.acc_correction_probe import rows_by_variant
    from experiments.clock020_sync import _cases

    t0 = time.time()
    rows = rows_by_variant([VARIANT], _cases(args.cases), run_case, args.out, ap.error)[VARIANT]
    if args.no_doc:
        return 0
    from experiments._reading import write_with_reading

    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_stage_budget.py" + (
        "" if args.cases == "0-29" else f" --cases {args.cases}")
    write_with_reading(DOC, markdown(rows, cmd, time.time() - t0))
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

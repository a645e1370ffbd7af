#!/usr/bin/env python3
"""Does a right clock help `calibrate --model`?  How the calibration uses the report's clocks (issues #27, #30).

``clock_proof.md``'s reading: searching beats of 2–5 cycles clocks clock-003's IMU 0 (+0.111 Hz for
+0.115, the reference IMU, 2.3 cycles in 20 s), and `calibrate --model` with that report got worse
(percov_conceal's z RMS 0.73 → 1.36, max |z| 2.19 → 4.50).  Was it the estimate, or does a clock on that
IMU hurt however right it is?  And on the 21 concealed cases of ``percov_conceal.md``, which parts of
the clocks' use carry the calibration?

Every calibration is percov_conceal's ``with_angjerk`` (:func:`experiments.percov_conceal.run_variant`:
`calibrate --model`, angular jerk, untempered, 2 chains × (300 + 400), sampler seed 0) on percov_conceal's
recording of the case (known acc intrinsics, 0.5 mm mounting error) with its cached ``detect`` report
(``experiments/out/percov_conceal/clock-SSS/report.json``) changed as follows:

* ``report``   — as the detector wrote it (percov_conceal's own cached ``with_angjerk.json``: the same call);
* ``no_mean``  — the clocks' mean correction y ← y + age·ẏ not applied (the ages load only the covariance;
  :func:`accel_bayes.model.report_terms.clock_corrected` replaced by the identity for the call);
* ``no_clock`` — every ``sampling_clock`` finding removed: every IMU on the unclocked age prior (expected
  age, and a random age of the register hold loading the unresolved motion and the resolved rate);
* ``report_ie`` — as ``report`` with the triads' own instant error (``instant_error=True``, CLI
  ``--instant-error``: each triad's timing error beyond its clock, times its output rate, e by type-II ML);

and on clock-003 only (:data:`ORACLE_CASE`), with the generator's truth
(:func:`experiments.clock020_oracle.variant_report`):

* ``true_0``   — the report plus IMU 0's true clock (the IMU the report leaves unclocked);
* ``true_all`` — every clock the truth's;
* ``true_0_ie``, ``true_all_ie`` — the same with the instant error.

Scored as percov_conceal: z = (posterior mean − truth) / posterior std per free coordinate.  Cached per
calibration in ``--out``; the document is written from the cache.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock_use_probe.py
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "clock_use_probe.md"
PERCOV = ROOT / "out" / "percov_conceal"
ORACLE_CASE = 3
#: variants on every case, and the oracle ones on :data:`ORACLE_CASE`
VARIANTS = ("report", "no_mean", "no_clock", "report_ie")
ORACLE_VARIANTS = ("true_0", "true_all", "true_0_ie", "true_all_ie")
SETTINGS = {"chains": 2, "draws": 400, "warmup": 300, "seed": 0}


def variant_report(report: dict, truth: dict, time_s, variant: str) -> dict:
    """The report a variant calibrates with (module docstring): a deep copy, its clocks changed."""
    from experiments.clock020_oracle import variant_report as oracle

    base = variant[:-3] if variant.endswith("_ie") else variant
    if base == "no_clock":
        doc = copy.deepcopy(report)
        doc["findings"] = [f for f in doc["findings"] if f["effect"] != "sampling_clock"]
        return doc
    if base in ("true_0", "true_all"):
        return oracle(report, truth, time_s, "b_oracle_0_2" if base == "true_0" else "c_oracle_all")
    return copy.deepcopy(report)


@contextlib.contextmanager
def clock_mean(on: bool):
    """The clocks' mean correction as `calibrate --model` applies it (``on``), or the identity (a probe's
    switch, not an option of the package: the calibration reads ``report_terms.clock_corrected`` at call time)."""
    import torch

    import accel_bayes.model.report_terms as rt

    orig = rt.clock_corrected
    if not on:
        rt.clock_corrected = lambda acc, gyro, *a: (torch.as_tensor(acc, dtype=torch.float64),
                                                    torch.as_tensor(gyro, dtype=torch.float64))
    try:
        yield
    finally:
        rt.clock_corrected = orig


def run_case(seed: int, variants, out: Path) -> dict:
    """{variant: cached calibration record} for one case (computed where missing)."""
    from accel_bayes.data.outputs import write_json
    from experiments.percov_conceal import case_recording, run_variant, score

    d = PERCOV / f"clock-{seed:03d}"
    rows, rec = {}, None
    for v in variants:
        f = d / "with_angjerk.json" if v == "report" else out / f"clock-{seed:03d}.{v}.json"
        if not f.exists():
            if rec is None:
                rec, truth, pos = case_recording(seed, 20.0, 5e-4, "known")
                report = json.loads((d / "report.json").read_text())
            rp = out / f"clock-{seed:03d}.{v}.report.json"
            write_json(rp, variant_report(report, truth, np.asarray(rec.time, dtype=np.float64), v))
            with clock_mean(v != "no_mean"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                r = run_variant(rec, "with_angjerk", rp, SETTINGS["chains"], SETTINGS["draws"], SETTINGS["warmup"],
                                SETTINGS["seed"], **({"instant_error": True} if v.endswith("_ie") else {}))
            r["score"] = score(r["positions"], pos)
            write_json(f, r)
        r = json.loads(f.read_text())
        rows[v] = {"z": r["score"]["z"], "coordinates": r["score"]["coordinates"], "seconds": r["seconds"]}
    return rows


def stats(z) -> dict:
    """{rms, max |z|, beyond4 (count of |z| > 4), n} of a list of z scores."""
    z = np.asarray(z, dtype=np.float64)
    return {"rms": float(np.sqrt(np.mean(z ** 2))), "max": float(np.abs(z).max()), "beyond4": int((np.abs(z) > 4).sum()),
            "n": int(z.size)}


def markdown(cases: dict, oracle: dict, cmd: str, secs: float) -> list[str]:
    """The document's generated lines: ``cases`` {seed: {variant: record}} of :data:`VARIANTS`, ``oracle`` the
    :data:`ORACLE_VARIANTS` records of :data:`ORACLE_CASE` ({} when it was not run)."""
    from experiments._stamp import run_stamp

    L = ["# clock_use_probe — does a right clock help `calibrate --model`? (issues #27, #30)", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; calibrations cached in "
         "`experiments/out/clock_use_probe/`, the `report` rows are percov_conceal's cached `with_angjerk`).", "",
         "What runs: the script's docstring (percov_conceal's recordings and reports, `calibrate --model` with the "
         "angular jerk, untempered, 2 chains × (300 + 400), sampler seed 0). z = (posterior mean − truth) / posterior std "
         "per free coordinate; cells z RMS / max |z|.", "",
         "## The 21 concealed clock cases", "",
         "| case | " + " | ".join(VARIANTS) + " |", "|---|" + "---|" * len(VARIANTS)]
    pooled = {v: [] for v in VARIANTS}
    for s, rows in sorted(cases.items()):
        cells = []
        for v in VARIANTS:
            st = stats(rows[v]["z"])
            pooled[v] += rows[v]["z"]
            cells.append(f"{st['rms']:.2f} / {st['max']:.2f}")
        L.append(f"| clock-{s:03d} | " + " | ".join(cells) + " |")
    L.append("| **pooled** (RMS / max, beyond 4) | " + " | ".join(
        f"**{st['rms']:.2f} / {st['max']:.2f}**, {st['beyond4']}/{st['n']}" for st in (stats(pooled[v]) for v in VARIANTS)) + " |")
    L += ["", "Median seconds per calibration: " + ", ".join(
        f"{v} {np.median([rows[v]['seconds'] for rows in cases.values()]):.0f}" for v in VARIANTS) + ".", ""]
    if oracle:
        L += [f"## clock-{ORACLE_CASE:03d}: IMU 0 (the reference, unclocked in the report) given its true clock", "",
              "| variant | without the instant error | with it (`_ie`) |", "|---|---|---|"]
        both = {**cases.get(ORACLE_CASE, {}), **oracle}
        for base in ("report", "true_0", "true_all"):
            a, b = both.get(base), both.get("report_ie" if base == "report" else base + "_ie")
            f = lambda r: "—" if r is None else "{rms:.2f} / {max:.2f}".format(**stats(r["z"]))  # noqa: E731
            L.append(f"| {base} | {f(a)} | {f(b)} |")
    return L


def main(argv=None) -> int:
    from experiments._reading import write_with_reading
    from experiments._stamp import invocation

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, nargs="*", default=None,
                    help="percov_conceal case seeds (default: every case it has cached)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "clock_use_probe")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    seeds = args.cases if args.cases is not None else sorted(
        int(p.name.split("-")[1]) for p in PERCOV.glob("clock-*") if (p / "with_angjerk.json").exists())
    if not seeds:
        print("error: --cases: no percov_conceal case cached (run experiments/percov_conceal.py first)", file=sys.stderr)
        return 2
    t0 = time.perf_counter()
    cases = {}
    for s in seeds:
        cases[s] = run_case(s, VARIANTS, args.out)
        print(f"clock-{s:03d}: " + ", ".join(f"{v} {stats(r['z'])['rms']:.2f}/{stats(r['z'])['max']:.2f}"
                                             for v, r in cases[s].items()), flush=True)
    oracle = run_case(ORACLE_CASE, ORACLE_VARIANTS, args.out) if ORACLE_CASE in seeds else {}
    write_with_reading(DOC, markdown(cases, oracle, invocation("clock_use_probe.py", argv), time.perf_counter() - t0))
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

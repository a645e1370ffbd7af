#!/usr/bin/env python3
"""Probe (issue #27, real data): what the clock stage's lower width bound costs on MIMU exp 5.

On exp 5 the clock stage rejects IMU 2's clock on its width alone (0.36 ms against
:data:`accel_bayes.mismatch.clock.WIDTH_RANGE_S`'s 0.4 ms; beat −0.38 Hz as in the other five experiments,
evidence over the wander 175 against a threshold of 51, ``clock_mimu.md``).  Exp 5 is also where the
accelerometers' filter delay beyond the gyros' comes out −0.10 ms against +1.23…+1.33 ms in the other five,
and where the §7.2 budget with every random-effect scale borrowed from exp 6 fails (``mimu_mismatch.md``).
This probe runs ``mimu_mismatch``'s ``detect`` and ``transfer`` stages on exp 5 (scales from exp 6) twice,
in the same run, with the default bound and with the bound lowered to ``--low-ms`` (0.3 ms); nothing else
changes.  Exp 6's default report lends the scales in both.

With ``--concealed`` it also reruns clock_proof's 70 concealed cases with the lowered bound (the detector's
steps up to its clock stage, ``clock_proof.clock_findings``) beside clock_proof's committed records: what
the bound guards against there.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock_width_probe.py --concealed --jobs 2

About 8 min for exp 5 on the shared 2-core machine (two whole-recording detections of exp 5, one of exp 6
when its default report is not cached), ~15 min more for ``--concealed`` with two processes.  Cached per
variant in ``experiments/out/clock_width_probe/`` (ignored by git); ``--from-default DIR`` copies the
default variant's exp 5 and exp 6 detections from a mimu_mismatch cache of the same code instead of
recomputing them.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
sys.path.insert(0, str(ROOT))
OUT = ROOT / "out" / "clock_width_probe"
DOC = ROOT / "clock_width_probe.md"
EXP, SOURCE = 5, 6


@contextlib.contextmanager
def width_bound(low_s: float | None):
    """The clock stage's width range with its lower end at ``low_s`` (s; None: unchanged)."""
    import accel_bayes.mismatch.clock as clock

    old = clock.WIDTH_RANGE_S
    if low_s is not None:
        clock.WIDTH_RANGE_S = (float(low_s), old[1])
    try:
        yield
    finally:
        clock.WIDTH_RANGE_S = old


def run_variant(out: Path, low_s: float | None, data: Path | None) -> dict:
    """``mimu_mismatch``'s detect (exp 5, and exp 6 where missing) and transfer (exp 5 ← exp 6) in ``out``."""
    import mimu_mismatch

    common = ["--out", str(out), "--no-figures"] + (["--data", str(data)] if data else [])
    with width_bound(low_s):
        mimu_mismatch.main(["--stage", "detect", "--experiments", str(EXP)] + common)
    # the lender is always the default detector: only the borrowing experiment's clocks differ
    mimu_mismatch.main(["--stage", "detect", "--experiments", str(SOURCE)] + common)
    with width_bound(low_s):
        mimu_mismatch.main(["--stage", "transfer", "--experiments", str(EXP), str(SOURCE), "--redo"] + common)
    return summarise(out)


def summarise(out: Path) -> dict:
    rep = json.loads((out / f"exp_{EXP}" / "report.json").read_text())
    tr = json.loads((out / f"exp_{EXP}" / "transfer.json").read_text())
    clocks = [f for f in rep["findings"] if f["effect"] == "sampling_clock"]
    fits = {f["imu"]: f for f in rep["details"]["clock_stage"]["imus"]}

    def ratio(rows, s):
        r = next(x for x in rows if x["sensor"] == s and x["regime"] == "all")
        return r["excess_var_explained"] / r["excess_var_observed"]

    def band_range(rows, s):  # [min, max] of b/a over the |ω| and |ω̇| bands
        v = [x["excess_var_explained"] / x["excess_var_observed"] for x in rows
             if x["sensor"] == s and x["regime"] != "all" and x["excess_var_observed"] > 0]
        return [min(v), max(v)]

    return {"clocks": sorted(f["imu"] for f in clocks),
            "imu2": {k: fits[2][k] for k in ("beat_mid_hz", "width_s", "evidence", "evidence_vs_wander", "accepted")},
            "threshold": rep["details"]["clock_stage"]["threshold"],
            "filter_delay_s": clocks[0]["parameters"]["filter_delay_acc_minus_gyro_s"] if clocks else None,
            "findings": [f"{f['effect']}[{f.get('imu')}]" for f in rep["findings"]
                         if f["effect"] not in ("sampling_clock", "gyro_scale")],
            "own": {s: ratio(rep["budget"], s) for s in ("acc", "gyro")},
            "own_bands": {s: band_range(rep["budget"], s) for s in ("acc", "gyro")},
            "borrowed": {s: ratio(tr["budget"], s) for s in ("acc", "gyro")},
            "borrowed_bands": {s: band_range(tr["budget"], s) for s in ("acc", "gyro")},
            "source": tr["source"], "detect_seconds": json.loads((out / f"exp_{EXP}" / "info.json").read_text()).get("detect_seconds")}


def _init_worker(low_s: float, out: str) -> None:
    # each worker process: the lowered bound, and clock_proof's cache redirected
    import accel_bayes.mismatch.clock as clock
    import clock_proof

    clock.WIDTH_RANGE_S = (float(low_s), clock.WIDTH_RANGE_S[1])
    clock_proof.OUT = Path(out)


def _proof_case(kind_seed):
    import clock_proof

    return clock_proof.run_case(kind_seed[0], kind_seed[1], clock_proof.DURATION)


def concealed(low_s: float, jobs: int) -> list[str]:
    """clock_proof's 70 concealed cases with the lowered bound (cached in ``OUT/clock_proof_low_*``), against its
    committed records with the default bound: the measure lines and the misses of each."""
    from concurrent.futures import ProcessPoolExecutor

    import clock_proof

    cases = [("clock", s) for s in clock_proof.clock_cases()] + [("twin", s) for s in clock_proof.clock_cases()] \
        + [("clean", 1000 + s) for s in range(10)]
    out = OUT / f"clock_proof_low_{low_s * 1e3:g}ms"
    out.mkdir(parents=True, exist_ok=True)
    with ProcessPoolExecutor(jobs, initializer=_init_worker, initargs=(low_s, str(out))) as ex:
        low = list(ex.map(_proof_case, cases))
    default = [json.loads((clock_proof.OUT / f"{k}-{s:03d}.json").read_text()) for k, s in cases]
    keep = lambda text: [ln for ln in text.splitlines() if ln.startswith(("| sampling_clock", "| beat within", "| … excluding"))]  # noqa: E731
    misses = lambda text: text.split("Misses and beat errors", 1)[1].split("\n\n", 2)[1].splitlines()[2:]  # noqa: E731
    a, b = clock_proof.summary(default, "", len(cases)), clock_proof.summary(low, "", len(cases))
    L = ["", f"clock_proof's {len(cases)} concealed cases (clock, synchronised twins, clean): the committed records with "
         f"the default bound (`experiments/results/clock_proof/`) and the same cases rerun with the bound at "
         f"{low_s * 1e3:g} ms.", "", "| measure | default (0.4 ms) | lowered |", "|---|---|---|"]
    for x, y in zip(keep(a), keep(b)):
        cells_x, cells_y = x.strip("|").split("|"), y.strip("|").split("|")
        L.append(f"| {cells_x[0].strip()} | {cells_x[1].strip()} | {cells_y[1].strip()} |")
    L += ["", "Misses and beat errors > 0.05 Hz, lowered bound:", "",
          "| case | IMU | true beat (mid) | estimate (mid) | width ms |", "|---|---|---|---|---|"] + misses(b)
    fa = [ln for ln in b.splitlines() if ln.startswith("- twin-") or ln.startswith("- clean-")]
    L += ["", "False alarms, lowered bound: " + ("; ".join(x[2:] for x in fa) if fa else "none") + "."]
    return L


def markdown(rows: dict, cmd: str, low_ms: float) -> list[str]:
    from experiments._stamp import run_stamp

    d, w = rows["default"], rows["low"]
    f = lambda v: "—" if v is None else f"{v * 1e3:+.3f} ms"  # noqa: E731
    rng = lambda r: f"{r[0]:.2f}–{r[1]:.2f}"  # noqa: E731
    L = [f"# clock_width_probe — the clock stage's lower width bound on MIMU exp {EXP}", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; detections cached in `experiments/out/clock_width_probe/`).", "",
         "What runs: the script's docstring. Both columns in the same run, same code, only the lower end of "
         "`clock.WIDTH_RANGE_S` differs; the budget ratios are b/a of \"all\" (range over the |ω| and |ω̇| bands).", "",
         f"| exp {EXP} | default (0.4 ms) | lower bound {low_ms:g} ms |", "|---|---|---|",
         f"| clocks accepted (IMUs) | {d['clocks']} | {w['clocks']} |",
         f"| IMU 2's clock: beat (mid), width, evidence / over the wander (threshold) | "
         f"{d['imu2']['beat_mid_hz']:+.3f} Hz, {d['imu2']['width_s'] * 1e3:.2f} ms, {d['imu2']['evidence']:.0f} / "
         f"{d['imu2']['evidence_vs_wander']:.0f} ({d['threshold']:.1f}), {'accepted' if d['imu2']['accepted'] else 'rejected'} | "
         f"{w['imu2']['beat_mid_hz']:+.3f} Hz, {w['imu2']['width_s'] * 1e3:.2f} ms, {w['imu2']['evidence']:.0f} / "
         f"{w['imu2']['evidence_vs_wander']:.0f} ({w['threshold']:.1f}), {'accepted' if w['imu2']['accepted'] else 'rejected'} |",
         f"| accelerometers' filter delay beyond the gyros' (other five experiments: +1.23…+1.33 ms) | "
         f"{f(d['filter_delay_s'])} | {f(w['filter_delay_s'])} |",
         f"| other findings (besides clocks and gyro blocks) | {', '.join(d['findings'])} | {', '.join(w['findings'])} |",
         f"| budget, own scales: acc | {d['own']['acc']:.3f} ({rng(d['own_bands']['acc'])}) | {w['own']['acc']:.3f} ({rng(w['own_bands']['acc'])}) |",
         f"| budget, own scales: gyro | {d['own']['gyro']:.3f} ({rng(d['own_bands']['gyro'])}) | {w['own']['gyro']:.3f} ({rng(w['own_bands']['gyro'])}) |",
         f"| budget, scales from exp {d['source']}: acc (must ≥ 0.8) | {d['borrowed']['acc']:.3f} ({rng(d['borrowed_bands']['acc'])}) | "
         f"{w['borrowed']['acc']:.3f} ({rng(w['borrowed_bands']['acc'])}) |",
         f"| budget, scales from exp {d['source']}: gyro (must ≥ 0.8) | {d['borrowed']['gyro']:.3f} ({rng(d['borrowed_bands']['gyro'])}) | "
         f"{w['borrowed']['gyro']:.3f} ({rng(w['borrowed_bands']['gyro'])}) |"]
    return L


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--low-ms", type=float, default=0.3, help="the lowered width bound, ms (default 0.3)")
    ap.add_argument("--data", type=Path, default=None, help="the MIMU data folder (default ../shared/data/mimu4444-bcd)")
    ap.add_argument("--concealed", action="store_true",
                    help="also rerun clock_proof's 70 concealed cases with the lowered bound (~15 min with --jobs 2)")
    ap.add_argument("--jobs", type=int, default=1, help="processes for --concealed (default 1)")
    ap.add_argument("--from-default", type=Path, default=None, metavar="DIR",
                    help="copy the default variant's exp_5/exp_6 detections from this mimu_mismatch cache (same code)")
    a = ap.parse_args(argv)
    if not 0 < a.low_ms < 4:
        ap.error(f"--low-ms: expected a width in (0, 4) ms, got {a.low_ms}")
    t0 = time.perf_counter()
    if a.from_default is not None:
        for i in (EXP, SOURCE):
            src, dst = a.from_default / f"exp_{i}", OUT / "default" / f"exp_{i}"
            if not (src / "report.json").exists():
                ap.error(f"--from-default: {src / 'report.json'} not found")
            if not dst.exists():
                shutil.copytree(src, dst, ignore=shutil.ignore_patterns("transfer.json"))
    rows = {"default": run_variant(OUT / "default", None, a.data),
            "low": run_variant(OUT / f"low_{a.low_ms:g}ms", a.low_ms * 1e-3, a.data)}
    from experiments._reading import write_with_reading
    from experiments._stamp import invocation

    lines = markdown(rows, invocation("clock_width_probe.py", argv), a.low_ms)
    if a.concealed:
        lines += concealed(a.low_ms * 1e-3, a.jobs)
    write_with_reading(DOC, lines)
    print(DOC.read_text())
    print(f"total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

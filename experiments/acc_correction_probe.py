#!/usr/bin/env python3
"""Does the clocks' accelerometer correction cost issue #27's concealed budget?  (issue #27)

``experiments/acc_budget_probe.md`` (reading, item 3) found that on restricted residuals what the
§7.2 budget leaves unexplained on the accelerometers is mostly the sampling clocks' own accelerometer
correction: ``sampling_clock``'s mean effect moves each triad's outputs by −(age + Δ)·ȧ
(:meth:`accel_bayes.physics.effects.clock.SamplingClock.perturbation`), ȧ the finite difference of
the fitted outputs at the read rate.  Where the read folds the board's vibration (30–95 Hz against
62.5–190 Hz) ȧ of the folded line is not the rate of the vibration, and the correction adds misfit
instead of removing it.  Put on the baseline's outputs it raised a in 7/7 cases read under 190 Hz.

Here the whole detector (defaults, blind) is rerun on ``clock_budget``'s 30 clockgen cases with one
change, and its budget compared with ``clock_budget``'s cached run of the same cases on the same
detector (``experiments/results/clock_budget/``):

* ``acc_half_off`` — every clock's accelerometer half set to zero (the gyro half, the ages that load
  ``unresolved_motion`` and everything else unchanged): the budget without the deterministic
  accelerometer correction, the unresolved motion left to carry the accelerometers' clock misfit;
* ``acc_half_auto`` — each accepted clock's accelerometer half applied only where it lowers its IMU's
  accelerometer misfit: at the fit the clocks were estimated on, the residual r and r − d_acc (d_acc
  the clock's accelerometer perturbation), both whitened by the stated noise and projected off the
  per-sample motion states (as ``mismatch.budget.restricted_sq``), summed over the IMU's accelerometer
  channels; one decision per clock, made on the stage's first correction and reused (a one-bit model
  choice per IMU from the data, no truth);
* ``acc_half_fitted`` — each accepted clock's accelerometer half fitted instead of taken as is:
  d_acc = −(λ_k·age + δ_k)·ȧ, (λ_k, δ_k) by least squares of the same restricted residual on the two
  regressors −age·ȧ and −ȧ of the IMU's accelerometer channels.  δ_k is the IMU's accelerometer timing
  beyond its gyro-fitted clock (the acc − gyro filter delay, and a read skew the sawtooth does not
  hold: clockgen reads the IMUs in turn), the vocabulary's per-IMU ``filter_delay_acc_minus_gyro_s``;
  λ_k the accelerometer half's own rate scale (where the read folds the vibration the finite-difference
  ȧ is not the rate the age multiplies), as the gyro half's ``rate_scale``.  Its part common to the
  IMUs is absorbed by each sample's specific force and is not identified; the fit sees only the rest;
* ``acc_delay_fitted`` — as ``acc_half_fitted`` with λ_k = 1: only the per-IMU delay δ_k fitted (the
  physical part alone; the scale is where ``acc_half_fitted`` strays, module reading).

Interception: the script replaces ``SamplingClock.perturbation`` (``acc_half_off``) or the clock
stage's ``clock_corrected`` (``acc_half_auto``) while it runs (its own patch; the package is not
changed).

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_correction_probe.py
"""
from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT.parent))
DOC = ROOT / "acc_correction_probe.md"
BASELINE = ROOT / "results" / "clock_budget"
VARIANTS = ("acc_half_off", "acc_half_auto", "acc_half_fitted", "acc_delay_fitted")
#: the read rate (Hz) below which clockgen's vibration (up to 95 Hz) folds
FOLD_BELOW_HZ = 190.0


def acc_half_lowers_misfit(prep, fit, clock) -> dict:
    """``acc_half_auto``'s decision for one clock (module docstring): {"keep", "misfit_without",
    "misfit_with"} (the IMU's restricted accelerometer sums of squares, stated-noise units)."""
    import torch

    from accel_bayes.mismatch.budget import stated_noise_system
    from accel_bayes.mismatch.model import project_off_states

    T, K = prep.T, prep.K
    Jx, Vinv, r = stated_noise_system(prep, fit)
    da, _ = clock.perturbation(None, fit.ctx)
    d = torch.zeros(T, 2, K, 3, dtype=torch.float64)
    d[:, 0] = da / prep.sigma_acc[None, :, None] * prep.m_acc
    k = int(clock.imu)
    sq = []
    for x in (r, r - d.reshape(T, 6 * K)):
        p = project_off_states(Jx, Vinv, x).reshape(T, 2, K, 3)
        sq.append(float((p[:, 0, k] ** 2 * prep.m_acc[:, k]).sum()))
    return {"imu": k, "keep": sq[1] < sq[0], "misfit_without": sq[0], "misfit_with": sq[1]}


def acc_half_fit(prep, fit, clock, scale: float | None = None) -> dict:
    """``acc_half_fitted``'s (λ_k, δ_k) for one clock (module docstring), or with ``scale`` λ_k fixed
    (``acc_delay_fitted``: 1) only δ_k: {"imu", "scale", "delay_s", "misfit_without", "misfit_with"}
    (restricted sums of squares, stated-noise units; "without": no accelerometer half)."""
    import torch

    from accel_bayes.mismatch.budget import stated_noise_system
    from accel_bayes.mismatch.model import project_off_states

    T, K = prep.T, prep.K
    Jx, Vinv, r = stated_noise_system(prep, fit)
    k = int(clock.imu)
    age = clock.age(fit.ctx.time)[:, None]
    rate = fit.ctx.acc_rate[:, k] / prep.sigma_acc[k] * prep.m_acc[:, k]          # (T, 3), whitened
    X = torch.zeros(T, 2, K, 3, 2, dtype=torch.float64)
    X[:, 0, k, :, 0] = -age * rate
    X[:, 0, k, :, 1] = -rate
    Xp = project_off_states(Jx, Vinv, X.reshape(T, 6 * K, 2)).reshape(T, 2, K, 3, 2)[:, 0, k]   # (T, 3, 2)
    rp = project_off_states(Jx, Vinv, r).reshape(T, 2, K, 3)[:, 0, k]                # (T, 3)
    A, b = Xp.reshape(-1, 2), rp.reshape(-1)
    if scale is None:
        coef = torch.linalg.lstsq(A, b, driver="gelsd").solution
    else:
        x1 = A[:, 1]
        coef = torch.stack((torch.tensor(float(scale), dtype=A.dtype), ((b - scale * A[:, 0]) @ x1) / (x1 @ x1)))
    return {"imu": k, "scale": float(coef[0]), "delay_s": float(coef[1]), "misfit_without": float((b ** 2).sum()),
            "misfit_with": float(((b - A @ coef) ** 2).sum())}


@contextlib.contextmanager
def patched(variant: str, decisions: dict | None = None):
    """The variant's change to the package, restored on exit; ``acc_half_auto`` fills ``decisions``
    {imu: :func:`acc_half_lowers_misfit`'s record}."""
    import dataclasses

    import torch

    import accel_bayes.mismatch.clock as mc
    import accel_bayes.mismatch.detector as md
    from accel_bayes.physics.effects.clock import SamplingClock

    old, old_cc = SamplingClock.perturbation, mc.clock_corrected
    decisions = {} if decisions is None else decisions

    def perturbation(self, params, ctx):
        acc, gyro = old(self, params, ctx)
        return torch.zeros_like(acc), gyro

    def clock_corrected(prep, fit, clocks):
        if not clocks:
            return prep
        ya, yg = prep.y_acc.clone(), prep.y_gyro.clone()
        for c in clocks:
            k = int(c.imu)
            if k not in decisions:
                decisions[k] = (acc_half_lowers_misfit(prep, fit, c) if variant == "acc_half_auto" else
                                acc_half_fit(prep, fit, c, 1.0 if variant == "acc_delay_fitted" else None))
            da, dg = c.perturbation(None, fit.ctx)
            if variant == "acc_half_auto":
                ya = ya - da if decisions[k]["keep"] else ya
            else:
                d = decisions[k]
                age = c.age(fit.ctx.time)[:, None]
                ya[:, k] = ya[:, k] + (d["scale"] * age + d["delay_s"]) * fit.ctx.acc_rate[:, k]
            yg = yg - dg
        return dataclasses.replace(prep, y_acc=ya * prep.m_acc, y_gyro=yg * prep.m_gyro)

    if variant == "acc_half_off":
        SamplingClock.perturbation = perturbation
    elif variant in ("acc_half_auto", "acc_half_fitted", "acc_delay_fitted"):
        mc.clock_corrected = md.clock_corrected = clock_corrected
    try:
        yield decisions
    finally:
        SamplingClock.perturbation, mc.clock_corrected, md.clock_corrected = old, old_cc, old_cc


def run_case(variant: str, seed: int, out: Path) -> dict:
    """The detector on clock case ``seed`` under ``variant``; cached JSON per case (clock_budget's record)."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.mismatch import detect
    from experiments.clock_budget import case_verdict
    from experiments.clock_proof import DURATION
    from experiments.clockgen import draw_case

    path = out / variant / f"clock-{seed:03d}.json"
    if path.exists():
        return json.loads(path.read_text())
    rec, truth = draw_case("clock", seed, duration=DURATION)
    t0 = time.perf_counter()
    with patched(variant) as decisions:
        doc = detect(rec).to_dict()
    res = {"variant": variant, "seed": seed, "board": truth["board"], "f_host": truth["f_host"],
           "seconds": time.perf_counter() - t0,
           "findings": [{"effect": f["effect"], "imu": f.get("imu"), "sensor": f.get("sensor")} for f in doc["findings"]],
           "budget": doc["budget"], "verdict": case_verdict(doc["budget"]),
           "acc_half": [decisions[k] for k in sorted(decisions)]}
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, res)
    return res


def _bands(rec: dict, sensor: str) -> int:
    """Bands (of 10) passing issue #27's rule for ``sensor``."""
    return 10 - len(rec["verdict"][sensor]["failing"])


def _ratio(rec: dict, sensor: str):
    return rec["verdict"][sensor]["all_ratio"]


def _clocks(rec: dict) -> int:
    return sum(f["effect"] == "sampling_clock" for f in rec["findings"])


def markdown(by_variant: dict, cmd: str, secs: float) -> str:
    """The document: per variant, the per-case table and the totals against the baseline."""
    from experiments._stamp import run_stamp

    L = ["# acc_correction_probe — the clocks' accelerometer correction and issue #27's concealed budget", "",
         f"Regenerate: `{cmd}` ({run_stamp()}; this invocation {secs:.0f} s; per-case records cached in "
         f"`experiments/out/acc_correction_probe/`).", "",
         "What runs: the script's docstring. Baseline: `clock_budget`'s records of the same cases on the same detector "
         "(`experiments/results/clock_budget/`). Rule per band as clock_budget (b/a in 0.7–1.3, or |b − a| ≤ 3 SE where "
         "a ≤ 3 SE); 10 bands per sensor."]
    for variant, rows in by_variant.items():
        L += variant_markdown(variant, rows)
    return "\n".join(L) + "\n"


def variant_markdown(variant: str, rows: list[tuple[dict, dict]]) -> list[str]:
    L = ["", f"## `{variant}`", ""]
    if variant == "acc_half_auto":
        dec = [d for _, new in rows for d in new.get("acc_half", [])]
        L += [f"Clocks whose accelerometer half was kept: {sum(d['keep'] for d in dec)} of {len(dec)}.", ""]
    if variant in ("acc_half_fitted", "acc_delay_fitted"):
        dec = [d for _, new in rows for d in new.get("acc_half", [])]
        sc = np.array([d["scale"] for d in dec])
        de = np.array([d["delay_s"] for d in dec]) * 1e3
        L += [f"Fitted on {len(dec)} clocks: scale λ_k median {np.median(sc):.2f} (10–90 % {np.quantile(sc, 0.1):.2f} – "
              f"{np.quantile(sc, 0.9):.2f}); delay δ_k median {np.median(de):+.3f} ms (10–90 % {np.quantile(de, 0.1):+.3f} – "
              f"{np.quantile(de, 0.9):+.3f} ms).", ""]
    L += ["| case | board | read Hz | acc bands | acc b/a all | gyro bands | gyro b/a all | clocks found | case passes |",
         "|---|---|---|---|---|---|---|---|---|"]
    fmt = lambda v: "—" if v is None else f"{v:.2f}"  # noqa: E731
    for base, new in rows:
        L.append(f"| clock-{new['seed']:03d} | {new['board']} | {new['f_host']:g} | {_bands(base, 'acc')} → "
                 f"{_bands(new, 'acc')} | {fmt(_ratio(base, 'acc'))} → {fmt(_ratio(new, 'acc'))} | "
                 f"{_bands(base, 'gyro')} → {_bands(new, 'gyro')} | {fmt(_ratio(base, 'gyro'))} → "
                 f"{fmt(_ratio(new, 'gyro'))} | {_clocks(base)} → {_clocks(new)} | "
                 f"{'yes' if base['verdict']['pass'] else 'no'} → {'yes' if new['verdict']['pass'] else 'no'} |")
    L += ["", "Totals (baseline → variant):", "",
          "| cases | n | cases passing | acc bands | gyro bands | median acc b/a all | median gyro b/a all |",
          "|---|---|---|---|---|---|---|"]
    groups = [("all", rows),
              (f"read < {FOLD_BELOW_HZ:g} Hz (the vibration folds)", [r for r in rows if r[1]["f_host"] < FOLD_BELOW_HZ]),
              (f"read ≥ {FOLD_BELOW_HZ:g} Hz", [r for r in rows if r[1]["f_host"] >= FOLD_BELOW_HZ])]
    for board in sorted({r[1]["board"] for r in rows}):
        groups.append((board, [r for r in rows if r[1]["board"] == board]))
    for name, g in groups:
        if not g:
            continue
        cells = []
        for key in ("pass", "acc", "gyro"):
            if key == "pass":
                b = sum(x[0]["verdict"]["pass"] for x in g)
                n = sum(x[1]["verdict"]["pass"] for x in g)
            else:
                b = sum(_bands(x[0], key) for x in g)
                n = sum(_bands(x[1], key) for x in g)
            cells.append(f"{b} → {n}")
        for s in ("acc", "gyro"):
            b = [v for v in (_ratio(x[0], s) for x in g) if v is not None]
            n = [v for v in (_ratio(x[1], s) for x in g) if v is not None]
            cells.append(f"{np.median(b):.2f} → {np.median(n):.2f}")
        L.append(f"| {name} | {len(g)} | " + " | ".join(cells) + " |")
    return L


def rows_by_variant(names, seeds, run, out: Path, error) -> dict:
    """{variant: [(clock_budget's record, the variant's record), …]} over the clock case ``seeds``, each case
    run (or read from its cache) by ``run(variant, seed, out)``, one progress line per case; ``error`` (argparse's
    ``ap.error``) reports a case without a clock_budget record.  Shared with ``budget_gap_probe``."""
    by_variant = {}
    for v in names:
        rows = []
        for s in seeds:
            base = BASELINE / f"clock-{s:03d}.json"
            if not base.exists():
                error(f"--cases: no clock_budget record for clock-{s:03d} in {BASELINE}; run experiments/clock_budget.py")
            new = run(v, s, out)
            print(f"{v} clock-{s:03d} {new['board']} {new['f_host']:g} Hz: acc bands {_bands(new, 'acc')}, gyro bands "
                  f"{_bands(new, 'gyro')}, {'pass' if new['verdict']['pass'] else 'FAIL'} ({new['seconds']:.0f} s)",
                  flush=True)
            rows.append((json.loads(base.read_text()), new))
        by_variant[v] = rows
    return by_variant


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma-separated subset of "
                    f"{', '.join(VARIANTS)} (default all)")
    ap.add_argument("--cases", default="0-29", help="clock case seeds, e.g. 0-29 or 1,3,5 (default 0-29)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "acc_correction_probe")
    ap.add_argument("--no-doc", action="store_true", help="run and cache the cases only")
    args = ap.parse_args(argv)
    from experiments.clock020_sync import _cases

    seeds = _cases(args.cases)
    names = [v for v in args.variants.split(",") if v]
    if any(v not in VARIANTS for v in names):
        ap.error(f"--variants: expected a subset of {', '.join(VARIANTS)}, got {args.variants!r}")
    t0 = time.time()
    by_variant = rows_by_variant(names, seeds, run_case, args.out, ap.error)
    if args.no_doc:
        return 0
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/acc_correction_probe.py" + (
        "" if args.cases == "0-29" else f" --cases {args.cases}") + (
        "" if args.variants == ",".join(VARIANTS) else f" --variants {args.variants}")
    from accel_bayes.data.outputs import write_text
    from experiments._reading import READING_MARKER, kept_reading

    write_text(DOC, markdown(by_variant, cmd, time.time() - t0) + "\n" + READING_MARKER
               + (kept_reading(DOC) or "\n"))
    print(f"wrote {DOC}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

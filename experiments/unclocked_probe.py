#!/usr/bin/env python3
"""IMUs a mismatch report leaves without a sampling clock: which age model ``calibrate --model`` should
give them (issue #30; the probe that chose :func:`accel_bayes.model.report_terms.unresolved_terms`'
age prior).

Every IMU of these boards samples on its own clock; a report without a ``sampling_clock`` finding for
IMU k (the detector found no beat, or rejected it) does not make its data age 0.  Three treatments of
such an IMU, everything else as ``calibrate(rec, model=report.json, angular_jerk=…)`` runs it:

* **zero**   — age 0 (the code before this probe: "IMUs without a clock get age 0");
* **mean**   — the expected age only: the clocked IMUs' mean age, plus their mean acc − gyro filter
  delay on the accelerometer (the clocks' mean correction and the loading use it);
* **prior**  — the mean plus the random age, variance (1/f)²/12 of the uniform register hold,
  loading the unresolved jerk (and angular jerk) on that triad's rows and the angular acceleration
  on its gyro (what the package now does).

The treatments are made by editing the terms :func:`unresolved_terms` returns (``zero``: the unclocked
rows' ages back to 0 and no variance; ``mean``: no variance), so the rest of the pipeline is the
package's own.  Per case and treatment: the type-II ML log-likelihood at the MAP (the fitted
per-sample model, nats; the unclocked IMU's outputs are shifted by its mean correction in ``mean``
and ``prior``, a shift that does not depend on θ), the sandwich/Laplace std ratio (max, and the
unclocked IMUs' coordinates) and, where the truth is known (the concealed clock recordings of
``experiments/percov_conceal.py``, its cached reports), z = (mean − truth)/std from the chains.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/unclocked_probe.py

Cost (:func:`bench`): one log p̂ (N = 1) at exp 5's size (T = 5724 samples, 8 triads, IMU 2 without a
clock; synthetic values — the cost does not depend on them), flat / jerk / jerk + the age prior /
angular jerk / angular jerk + the age prior, in one process, blocks of calls alternating, medians.

Writes ``experiments/unclocked_probe.md`` and caches each run in ``--out``.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
if __package__ in (None, ""):  # run as a script: the repository root on the path for ``experiments.*``
    sys.path.insert(0, str(HERE.parent))

from accel_bayes.data.outputs import write_json, write_text  # noqa: E402

MODES = ("zero", "mean", "prior")


def _patched_terms(mode: str):
    """unresolved_terms with the unclocked IMUs' ages as ``mode`` treats them (module docstring)."""
    import accel_bayes.model.report_terms as rt

    orig = rt.unresolved_terms

    def terms(*a, **k):
        t = orig(*a, **k)
        if t is None or mode == "prior":
            return t
        if mode == "zero":
            t.age_acc[:, t.age_var_acc > 0] = 0.0
            t.age_gyro[:, t.age_var_gyro > 0] = 0.0
        t.age_var_acc = torch.zeros_like(t.age_var_acc)
        t.age_var_gyro = torch.zeros_like(t.age_var_gyro)
        return t
    return orig, terms


def run(rec, report: Path, mode: str, angular_jerk: bool, chains: int, draws: int, warmup: int) -> dict:
    """One calibration with the ``mode`` treatment; the probe's numbers."""
    import accel_bayes.model.report_terms as rt
    import accel_bayes.model.unresolved_fit as uf
    from accel_bayes.pipelines.calibrate import calibrate

    orig, terms = _patched_terms(mode)
    fit_orig, fits = uf.fit_unresolved_scales, []

    def fit(*a, **k):
        fits.append(fit_orig(*a, **k))
        return fits[-1]
    rt.unresolved_terms, uf.fit_unresolved_scales = terms, fit
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            t0 = time.perf_counter()
            res = calibrate(rec, chains=chains, draws=draws, warmup=warmup, seed=0, progress=False, model=report,
                            angular_jerk=angular_jerk)
    finally:
        rt.unresolved_terms, uf.fit_unresolved_scales = orig, fit_orig
    m = res.settings["model"]
    um = m.get("unresolved_motion") or {}
    return {"mode": mode, "angular_jerk": angular_jerk, "loglik_type2": fits[-1].loglik if fits else None,
            "sandwich": m["sandwich"], "unclocked": [u["imu"] for u in um.get("unclocked", [])],
            "positions": res.positions, "seconds": time.perf_counter() - t0}


def unclocked_of(report: Path, K: int) -> list:
    doc = json.loads(Path(report).read_text())
    return sorted(set(range(K)) - {int(f["imu"]) for f in doc["findings"] if f["effect"] == "sampling_clock"})


def cases(args):
    """(name, recording, report path, true positions or None, chain settings)."""
    out = []
    if args.real:
        from accel_bayes.data.mimu import import_mimu
        from experiments._data import data_dir

        for e in [int(x) for x in args.real.split(",")]:
            rec = import_mimu(data_dir() / f"exp_{e}" / "data.bin.gz")
            out.append((f"exp_{e}", rec, args.reports / f"exp_{e}" / "report.json", None, (4, 500, 500)))
    if args.conceal:
        from experiments.percov_conceal import case_recording

        for s in [int(x) for x in args.conceal.split(",")]:
            rec, _, pos = case_recording(s, 20.0, 5e-4, "known")
            out.append((f"clock-{s:03d}", rec, args.conceal_reports / f"clock-{s:03d}" / "report.json", pos,
                        (2, 400, 300)))
    return out


def bench(rounds: int = 7, block: int = 10, T: int = 5724, A: int = 8, unclocked: int = 2) -> dict:
    """Median ms per log p̂ call of each model (module docstring, "Cost"); one torch thread."""
    from experiments.bench_likelihood_percov import timed_blocks

    from accel_bayes.model.gyro_posterior import gyro_posterior
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.model.likelihood_percov import with_unresolved_motion

    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    pos = 0.02 * torch.randn(A, 3, generator=g, dtype=torch.float64)
    acc = 3.0 * torch.randn(T, A, 3, generator=g, dtype=torch.float64)
    omega = gyro_posterior(4.0 * torch.randn(T, 4, 3, generator=g, dtype=torch.float64),
                           torch.full((4,), 0.01, dtype=torch.float64), "calibrated")
    flat = RaoBlackwellLikelihood(acc, omega, 1.5, 1)
    age = 1e-3 * torch.rand(T, A, generator=g, dtype=torch.float64)
    s = 3e3 * (0.5 + torch.rand(T, generator=g, dtype=torch.float64))
    a = 1e5 * (0.5 + torch.rand(T, generator=g, dtype=torch.float64))
    var = torch.zeros(A, dtype=torch.float64)
    var[unclocked] = 1.0 / 12e6
    prior = {"age_var": var, "age_rate": 3e3 * torch.randn(T, A, 3, generator=g, dtype=torch.float64)}
    rot = {"angjerk_std": a, "lever": pos}
    models = {"flat": flat, "jerk": with_unresolved_motion(flat, age, s),
              "jerk+prior": with_unresolved_motion(flat, age, s, **prior),
              "angjerk": with_unresolved_motion(flat, age, s, **rot),
              "angjerk+prior": with_unresolved_motion(flat, age, s, **rot, **prior)}
    z = flat.sample_z((), 1, torch.Generator().manual_seed(1))
    with torch.no_grad():
        ms, cpu = timed_blocks({k: (lambda m=m: m.log_phat(pos, z=z)) for k, m in models.items()}, rounds, block)
    return {"T": T, "A": A, "unclocked": unclocked, "ms": ms, "cpu_ms_p10": cpu, "rounds": rounds, "block": block}


def loo_with(row: dict, exp: int, cache: Path) -> dict | None:
    """Leave-one-out z (``mimu_repeatability.analyse``, the one implementation) of the six experiments
    with experiment ``exp`` replaced by this probe run: the other five from ``cache`` (the
    ``mimu_model_calibrate.py`` runs with the same calibrate settings).  RMS all / exp 1–3 / exp 4–6,
    max, and the replaced experiment's own RMS; None when the cache is incomplete."""
    from experiments.mimu_repeatability import analyse

    runs = []
    for e in range(1, 7):
        f = cache / f"exp_{e}.json"
        if not f.exists():
            return None
        r = json.loads(f.read_text())
        if e == exp:
            r = {**r, "mean": [i["mean"] for i in row["positions"]["imus"]],
                 "std": [i["std"] for i in row["positions"]["imus"]]}
        runs.append(r)
    z = np.asarray(analyse(runs)["z_loo"], dtype=float).reshape(6, -1)
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))  # noqa: E731
    return {"all": rms(z), "exp1_3": rms(z[:3]), "exp4_6": rms(z[3:]), "max": float(np.abs(z).max()),
            "own": rms(z[exp - 1])}


def markdown(rows: list, cmd: str, stamp: str, cost: dict | None = None) -> str:
    L = ["# Unclocked IMUs: zero age, expected age, or an age prior (issue #30)", "",
         f"Regenerate: `{cmd}` ({stamp}). Module docstring of `experiments/unclocked_probe.py`: what each "
         "treatment is. Every run is `calibrate --model` of the case's own report (real exp: 4 chains × 500 "
         "after 500, seed 0; concealed: 2 × 400 after 300, seed 0, as `percov_conceal.py`), untempered; the "
         "sandwich/Laplace ratio is `provenance.settings.model.sandwich` (at the per-sample model's mode); "
         "log-lik is the type-II ML maximum of the per-sample model at the MAP (nats).", "",
         "| case | angular jerk | unclocked IMUs | treatment | type-II log-lik (nats) | Δ vs zero | ratio max | "
         "ratio, unclocked IMUs' coordinates | z RMS | max abs z | z, unclocked IMUs' coordinates |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    base = {}
    for r in rows:
        key = (r["case"], r["angular_jerk"])
        if r["mode"] == "zero":
            base[key] = r["loglik_type2"]
        sw = r["sandwich"]
        unc = set(r["unclocked_report"])
        idx = [i for i, c in enumerate(sw["coordinates"]) if int(c[2:].split(",")[0]) in unc]
        rat = ", ".join(f"{sw['coordinates'][i]} {sw['std_ratio'][i]:.2f}" for i in idx) or "(reference)"
        d = r["loglik_type2"] - base[key] if key in base and r["loglik_type2"] is not None else None
        z = r.get("z")
        zs = "—" if z is None else f"{np.sqrt(np.mean(np.square(z))):.2f}"
        zm = "—" if z is None else f"{np.max(np.abs(z)):.2f}"
        zu = "—" if z is None else ", ".join(f"{r['z_names'][i]} {z[i]:+.2f}" for i, c in enumerate(r["z_names"])
                                             if int(c[2:].split(",")[0]) in unc) or "(reference)"
        L.append(f"| {r['case']} | {'yes' if r['angular_jerk'] else 'no'} | {sorted(unc)} | {r['mode']} | "
                 f"{r['loglik_type2']:.1f} | {'—' if d is None else f'{d:+.1f}'} | {sw['std_ratio_max']:.2f} | "
                 f"{rat} | {zs} | {zm} | {zu} |")
    if cost:
        ms = cost["ms"]
        L += ["", f"## Cost: one log p̂ at exp 5's size (T = {cost['T']}, {cost['A']} triads, one unclocked; "
              "N = 1)", "",
              "| model | ms per call | × flat | × the same model without the age prior |", "|---|---|---|---|"]
        for k, v in ms.items():
            base = ms.get(k.replace("+prior", "")) if k.endswith("+prior") else None
            L.append(f"| {k} | {v:.2f} | {v / ms['flat']:.2f} | {'—' if base is None else f'{v / base:.2f}'} |")
        L += ["", "RESULT lines: " + "; ".join(f"RESULT unclocked_{k}: {v:.2f} ms, flat {ms['flat']:.2f} ms"
                                              for k, v in ms.items() if k != "flat")]
    loo = [r for r in rows if r.get("loo")]
    if loo:
        L += ["", "## Repeatability: leave-one-out z of the six experiments with this run as the real experiment's",
              "", "The other five from `experiments/out/mimu_model_calibrate_unclocked/with_angjerk/` (same calibrate "
              "settings; their reports clock every IMU, so no treatment changes them).", "",
              "| case | treatment | LOO z RMS all / exp 1–3 / exp 4–6 | max \\|z\\| | "
              "this experiment's own LOO z RMS |",
              "|---|---|---|---|---|"]
        for r in loo:
            q = r["loo"]
            L.append(f"| {r['case']} | {r['mode']} | {q['all']:.2f} / {q['exp1_3']:.2f} / {q['exp4_6']:.2f} | "
                     f"{q['max']:.2f} | {q['own']:.2f} |")
    L += ["", "## Reading", "", "READING_PLACEHOLDER", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    from experiments._stamp import invocation, run_stamp
    from experiments.percov_conceal import score

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", default="5", help="MIMU experiments (comma-separated; '' for none)")
    ap.add_argument("--conceal", default="20,3,6,14", help="concealed clock seeds (comma-separated)")
    ap.add_argument("--reports", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--conceal-reports", type=Path, default=HERE / "out" / "percov_conceal")
    ap.add_argument("--angular-jerk", default="1", help="'1', '0' or '0,1': the variants run")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "unclocked_probe")
    ap.add_argument("--doc", type=Path, default=HERE / "unclocked_probe.md")
    ap.add_argument("--mimu-cache", type=Path, default=HERE / "out" / "mimu_model_calibrate_unclocked" / "with_angjerk",
                    help="the six experiments' with_angjerk runs the real probe rows are compared with (LOO z)")
    ap.add_argument("--no-bench", action="store_true", help="leave the cost bench out (its cache is used if present)")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for name, rec, report, pos, (chains, draws, warmup) in cases(args):
        for aj in [bool(int(x)) for x in args.angular_jerk.split(",")]:
            for mode in MODES:
                f = args.out / f"{name}_{'angjerk' if aj else 'jerk'}_{mode}.json"
                if not f.exists():
                    r = run(rec, report, mode, aj, chains, draws, warmup)
                    r["case"], r["unclocked_report"] = name, unclocked_of(report, rec.K)
                    if pos is not None:
                        sc = score(r["positions"], pos)
                        r["z"], r["z_names"] = sc["z"], sc["coordinates"]
                    write_json(f, r)
                r = json.loads(f.read_text())
                if name.startswith("exp_") and aj:
                    r["loo"] = loo_with(r, int(name[4:]), args.mimu_cache)
                rows.append(r)
                sw = r["sandwich"]
                print(f"{name} aj={aj} {mode}: loglik {r['loglik_type2']:.1f} ratio max {sw['std_ratio_max']:.2f} "
                      f"z {'' if r.get('z') is None else np.sqrt(np.mean(np.square(r['z']))):} "
                      f"{r['seconds']:.0f} s", flush=True)
    cost = None
    fb = args.out / "bench.json"
    if fb.exists():
        cost = json.loads(fb.read_text())
    elif not args.no_bench:
        cost = bench()
        write_json(fb, cost)
    if cost:
        print("\n".join(f"RESULT unclocked_{k}: {v:.2f} ms, flat {cost['ms']['flat']:.2f} ms"
                        for k, v in cost["ms"].items() if k != "flat"), flush=True)
    text = markdown(rows, invocation("unclocked_probe.py", argv), run_stamp(), cost)
    if args.doc.exists():  # the reading is written by hand: kept across regeneration
        old = args.doc.read_text()
        if "## Reading" in old:
            text = text.split("## Reading")[0] + "## Reading" + old.split("## Reading", 1)[1]
    write_text(args.doc, text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

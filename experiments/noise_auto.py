#!/usr/bin/env python3
"""Noise "auto" with a mismatch report on recordings without rests (issue #30 item 4).

``calibrate --model`` used the stated σ on a recording without rests; now "auto" estimates the
accelerometer levels (type-II ML at the MAP, untempered: a model refuses κ) when the report has an
``unexplained`` finding (``CalibrateOptions.noise_mode``).  Three measurements:

* **wander** — the simulation of ``tests/model/test_calibrate_model.py`` (mimu8, 100 Hz, T 800, a
  concealed 2 ms gyro timing wander + 0.5 rad/s white noise on one gyro, stated σ_a 5 mm/s² = the
  truth), which broke when "auto" estimated with *any* report: with a report without findings
  ("clean") and with the wander + ``unexplained`` findings ("found"), each on the stated and the
  estimated noise.  Whether the estimate is biased without rests (fitted σ against 5 mm/s²), the
  sandwich/Laplace std ratio and κ at the MAP (recorded, not applied), z against the truth.
* **stand-in** — ``tests/pipelines/test_noise_auto.py``'s case: mimu8, no rests, white accelerometer
  noise 50 mm/s² while 5 mm/s² is stated, a report with one ``unexplained`` finding; stated vs auto.
* **class 2** — the 7 concealed clock recordings without rests from ``percov_conceal``'s cache
  (``--conceal``): its ``with`` calibration before the rule (cached there as ``with_stated.json``:
  ``calibrate(rec, model=report.json, noise="stated")``, what "auto" ran before) and after
  (``with.json``, ``percov_conceal.py`` rerun on this code).

* **c21** (``--c21 N``) — the first N clean time-series replicates of ``c21_coverage.py --motion
  smooth`` (:func:`c21_coverage.replicate_pipeline`'s data, seeds and prior), calibrated without a
  model and with its forced-terms report, by "auto" (what the committed coverage ran) and by
  ``noise="estimate"``: the noise mode and whether the two-start MAP kept the design start
  (``settings.phi_prior.map_start``, present only then).  1 chain × (10 + 10): the settings only.

z = (posterior mean − truth) / posterior std per free coordinate (``percov_conceal.score``).  Every
row is cached in ``--out``.

    PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/noise_auto.py --c21 12
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
import warnings
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
DOC = ROOT / "noise_auto.md"
CLASS2 = (3, 4, 7, 13, 14, 15, 16)  # percov_conceal's cases without rests
SIM_RUN = dict(chains=2, draws=200, warmup=200, seed=0, progress=False)  # the simulations' chains


def minimal_report(rec, findings) -> dict:
    """A DESIGN §7.2 report of ``rec`` holding ``findings`` [(effect, imu, parameters)] as the detector writes them."""
    from experiments._reports import minimal_report as build

    return build(findings, rec, explanation="experiment finding")


def wander_case():
    """(recording, true positions (K, 3) m, {"clean", "found"} reports): test_calibrate_model's wander case."""
    from experiments._reports import wander_calibration_case

    return wander_calibration_case()


def standin_case():
    """(recording, true positions, reports): test_noise_auto's no-rest case, 50 mm/s² noise, 5 stated."""
    from experiments import _conceal as C

    case = C.make_case("mimu8", "none", seed=11, T=600, rate=100.0, sigma_a=0.005)
    rec = case.recording
    rec.acc = np.array(rec.acc) + np.random.default_rng(11).normal(0.0, np.sqrt(0.05**2 - 0.005**2), rec.acc.shape)
    rep = minimal_report(rec, [("unexplained", 0, {"chi2_ratio": 100.0, "scales_with": "nothing"})])
    return rec, np.asarray(case.truth["true_position"]), {"unexplained": rep}


def sim_row(name: str, rec, pos, report: dict, noise: str, out: Path) -> dict:
    """One calibration of a simulation with ``model=report`` and ``noise``; cached as ``out/name.json``."""
    from accel_bayes.data.outputs import write_json
    from accel_bayes.pipelines.calibrate import calibrate
    from experiments.percov_conceal import score

    f = out / f"{name}.json"
    if f.exists():
        return json.loads(f.read_text())
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = calibrate(rec, model=report, noise=noise, **SIM_RUN)
    st = r.settings
    sw = st["model"]["sandwich"]
    z = np.asarray(score(r.positions, pos)["z"])
    doc = {"name": name, "asked": noise, "noise": st["noise"], "noise_std": (st.get("noise_model") or {}).get("std"),
           "stated_std": np.asarray(rec.acc_noise_std, dtype=np.float64).tolist(),
           "ratio_max": sw["std_ratio_max"], "kappa": sw["kappa"], "z": z.tolist(), "seconds": r.seconds}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    print(f"{name}: noise {doc['noise']}, ratio max {doc['ratio_max']:.2f}, z RMS {np.sqrt(np.mean(z**2)):.2f}", flush=True)
    return doc


def c21_row(i: int, out: Path) -> dict:
    """Replicate ``i`` of c21_coverage's smooth study: noise mode and map_start per variant (module docstring)."""
    import torch

    from accel_bayes.data.outputs import write_json
    from accel_bayes.pipelines.calibrate import calibrate
    from accel_bayes.simulate import simulate
    from experiments import c21_coverage as cc
    from experiments.forced_terms import forced_report

    f = out / f"c21-{i:03d}.json"
    if f.exists():
        return json.loads(f.read_text())
    arr = cc.square_board(cc.SMOOTH_ACC_STD)
    g = torch.Generator().manual_seed(10_000 + i)  # replicate_pipeline's draw of the truth
    true = arr.positions.clone()
    true[1:] += cc.DEFAULT_PRIOR_STD * torch.randn(3, 3, generator=g, dtype=torch.float64)
    rec = simulate(arr, "smooth", 1000, cc.SMOOTH_RATE, seed=20_000 + i, true_positions=true, clip=False).recording
    doc = {"i": i, "variants": {}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rep = forced_report(rec)
        doc["report_unexplained"] = any(x["effect"] == "unexplained" for x in rep["findings"])
        for name, kw in (("none", {}), ("forced", {"model": rep}), ("none estimate", {"noise": "estimate"}),
                         ("forced estimate", {"model": rep, "noise": "estimate"})):
            r = calibrate(rec, chains=1, draws=10, warmup=10, seed=i, init="prior", prior_std=cc.DEFAULT_PRIOR_STD,
                          progress=False, **kw)
            pp = r.settings.get("phi_prior")
            doc["variants"][name] = {"noise": r.settings["noise"],
                                     "map_start": pp.get("map_start") if isinstance(pp, dict) else None}
    out.mkdir(parents=True, exist_ok=True)
    write_json(f, doc)
    print(f"c21 replicate {i}: " + ", ".join(f"{k} {v['noise']} {v['map_start'] is not None}"
                                            for k, v in doc["variants"].items()), flush=True)
    return doc


def class2_rows(conceal: Path) -> list[dict]:
    """Per no-rest case: the ``with`` calibration on the stated σ (before) and with "auto" now (after)."""
    rows = []
    for s in CLASS2:
        d = conceal / f"clock-{s:03d}"
        pair = {}
        for key, fn in (("before", "with_stated.json"), ("after", "with.json")):
            if (d / fn).exists():
                r = json.loads((d / fn).read_text())
                pair[key] = {"z": r["score"]["z"], "noise": r["noise"], "noise_std": r.get("noise_std"),
                             "ratio_max": (r.get("model") or {}).get("sandwich_ratio_max")}
        if len(pair) == 2:
            rows.append({"seed": s, **pair})
    return rows


def _rng(v) -> str:
    return f"{min(v):.3f}–{max(v):.3f}" if v else "—"


def _z(z) -> str:
    z = np.asarray(z)
    return f"{np.sqrt(np.mean(z**2)):.2f} / {np.abs(z).max():.2f} / {int((np.abs(z) > 4).sum())}/{z.size}"


def c21_markdown(rows: list[dict]) -> list[str]:
    if not rows:
        return []
    names = list(rows[0]["variants"])
    L = ["", f"## Clean c21 smooth replicates 0–{len(rows) - 1}: the noise mode and the design start", "",
         "Per variant: how many replicates ran on each noise mode, and on how many the two-start MAP kept the "
         "design start (`settings.phi_prior.map_start` present). Reports with an `unexplained` finding: "
         f"{sum(r['report_unexplained'] for r in rows)}/{len(rows)}.", "",
         "| variant | noise modes | design start kept |", "|---|---|---|"]
    for n in names:
        modes = sorted({r["variants"][n]["noise"] for r in rows})
        counts = ", ".join(f"{m} {sum(r['variants'][n]['noise'] == m for r in rows)}" for m in modes)
        kept = sum(r["variants"][n]["map_start"] is not None for r in rows)
        L.append(f"| {n} | {counts} | {kept}/{len(rows)} |")
    return L


def markdown(sims: dict, c2: list[dict], c21: list[dict], cmd: str, secs: float) -> str:
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    L = ["# noise_auto — calibrate --model on recordings without rests: stated or estimated noise (issue #30 item 4)", "",
         f"Regenerate: `{cmd}` ({now}, {platform.machine()} {platform.system()}, shared 2-core CPU, nice 5; rows cached in "
         f"`experiments/out/noise_auto/`, class 2 read from `percov_conceal`'s cache; this invocation {secs:.0f} s).", "",
         "What runs: the module docstring of [`noise_auto.py`](noise_auto.py). Simulations: "
         f"{SIM_RUN['chains']} chains × ({SIM_RUN['warmup']} + {SIM_RUN['draws']}), seed 0. *ratio*: the model's "
         "sandwich/Laplace std ratio at the MAP (max over coordinates), *κ* its variance inflation (recorded, not applied "
         "with a model). z: RMS / max |z| / beyond 4.", "",
         "## The wander simulation (stated σ = the truth, 0.005 m/s²)", "",
         "| report | noise | fitted σ (m/s², min–max) | ratio max | κ | z RMS / max / beyond 4 |", "|---|---|---|---|---|---|"]
    for key in ("wander-clean-stated", "wander-clean-estimate", "wander-found-stated", "wander-found-estimate"):
        d = sims[key]
        L.append(f"| {key.split('-')[1]} | {d['noise']} | {_rng(d['noise_std'])} | {d['ratio_max']:.2f} | {d['kappa']:.2f} "
                 f"| {_z(d['z'])} |")
    L += ["", "## The stand-in: no rests, 0.050 m/s² white noise, 0.005 stated, a report with one `unexplained`", "",
          "| noise | fitted σ (m/s², min–max) | ratio max | κ | z RMS / max / beyond 4 |", "|---|---|---|---|---|"]
    for key in ("standin-stated", "standin-auto"):
        d = sims[key]
        L.append(f"| {d['asked']} → {d['noise']} | {_rng(d['noise_std'])} | {d['ratio_max']:.2f} | {d['kappa']:.2f} "
                 f"| {_z(d['z'])} |")
    L += ["", "## Class 2: the concealed clock recordings without rests, `calibrate --model report.json` untempered", "",
          "Before: stated σ (the old \"auto\"); after: \"auto\" now (estimate: every one of these reports has an "
          "`unexplained` finding).", "",
          "| case | z RMS / max / beyond 4, before → after | σ before → after (m/s²) | ratio max before → after |",
          "|---|---|---|---|"]
    for r in c2:
        b, a = r["before"], r["after"]
        L.append(f"| clock-{r['seed']:03d} | {_z(b['z'])} → {_z(a['z'])} | {b['noise']} {_rng(b['noise_std'])} → "
                 f"{a['noise']} {_rng(a['noise_std'])} | {b['ratio_max']:.2f} → {a['ratio_max']:.2f} |")
    if c2:
        zb = np.concatenate([r["before"]["z"] for r in c2])
        za = np.concatenate([r["after"]["z"] for r in c2])
        L.append(f"| pooled | {_z(zb)} → {_z(za)} | | |")
    return "\n".join(L + c21_markdown(c21)) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--conceal", type=Path, default=ROOT / "out" / "percov_conceal",
                    help="percov_conceal's case folder (its cached with.json / with_stated.json)")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "noise_auto")
    ap.add_argument("--c21", type=int, default=0, help="clean c21 smooth replicates 0..N-1 to check (default 0: none)")
    args = ap.parse_args(argv)
    from accel_bayes.data.outputs import write_text
    from experiments._reading import READING_MARKER, kept_reading

    t0 = time.perf_counter()
    sims = {}
    rec, pos, reps = wander_case()
    for rname in ("clean", "found"):
        for noise in ("stated", "estimate"):
            sims[f"wander-{rname}-{noise}"] = sim_row(f"wander-{rname}-{noise}", rec, pos, reps[rname], noise, args.out)
    rec, pos, reps = standin_case()
    for noise in ("stated", "auto"):
        sims[f"standin-{noise}"] = sim_row(f"standin-{noise}", rec, pos, reps["unexplained"], noise, args.out)
    c2 = class2_rows(args.conceal)
    c21 = [c21_row(i, args.out) for i in range(args.c21)]
    cmd = "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/noise_auto.py" + "".join(
        f" {a}" for a in (argv if argv is not None else sys.argv[1:]))
    write_text(DOC, markdown(sims, c2, c21, cmd, time.perf_counter() - t0) + "\n" + READING_MARKER + (kept_reading(DOC) or "\n"))
    print(DOC.read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Model-mismatch discovery on the six real MIMU4444 experiments (issue #5, item 7).

For each experiment ``exp_i`` (``../shared/data/mimu4444-bcd``):

1. import the raw stream (:func:`accel_bayes.data.mimu.import_mimu`: checksums, rests, noise from the
   rests), estimate the accelerometer intrinsics and gyro biases from the rests
   (:func:`accel_bayes.prep.intrinsics.estimate_intrinsics`) and apply them
   (:meth:`Intrinsics.apply`), keep the samples labelled ``dynamic`` by the importer;
2. run the detector **unchanged** (:func:`accel_bayes.mismatch.detect`, default options) and
   write its report (``OUT/exp_i/report.json`` + ``report.md``);
3. held-out check: the effects found on experiment i — their fitted parameters held fixed —
   are added to the nominal model of experiment j's dynamic data; positions and motion are
   re-fitted on j in both models (:func:`accel_bayes.mismatch.transfer.heldout_fit`), and the
   log-likelihood difference (fixed effects − nominal) is reported for every ordered pair
   (the diagonal i = j is the in-sample value, for reference);
4. repeatability: the spread of the six position estimates per IMU, from the nominal fit
   (baseline) and from the refined fit (found effects modelled).

Everything is cached per experiment in ``OUT`` so a run can be interrupted and resumed; the
summary (``OUT/summary.json``, ``OUT/summary.md``, figures) is rebuilt from what is there.

    python experiments/mimu_mismatch.py                          # all stages, all six experiments
    python experiments/mimu_mismatch.py --stage detect --experiments 1 2
    python experiments/mimu_mismatch.py --stage heldout
    python experiments/mimu_mismatch.py --stage heldout-single     # each finding alone
    python experiments/mimu_mismatch.py --stage summary
    python experiments/mimu_mismatch.py --max-samples 3000       # subsample: last N dynamic samples

Honesty notes: the detector's options are its defaults; ``--max-samples`` (off by default)
keeps only the last N dynamic samples (the continuous hand rotation at the end of each
experiment) and is recorded in the outputs.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _data import data_dir  # noqa: E402


def load_dynamic(i: int, data: Path, max_samples: int | None = None):
    """Experiment i: imported, intrinsics applied, dynamic samples only.  Returns (rec, info)."""
    from accel_bayes.prep.intrinsics import estimate_intrinsics
    from accel_bayes.data.mimu import import_mimu

    raw = import_mimu(data / f"exp_{i}" / "data.bin.gz")
    intr = estimate_intrinsics(raw)
    cal = intr.apply(raw)
    seg = np.asarray(cal.segment)
    keep = seg == "dynamic"
    if max_samples is not None and keep.sum() > max_samples:
        idx = np.flatnonzero(keep)[-int(max_samples):]
        keep = np.zeros_like(keep)
        keep[idx] = True
    rec = cal.select(keep)
    gc = None if rec.gyro_clipped is None else np.asarray(rec.gyro_clipped)
    info = {"experiment": i, "T_total": int(len(seg)), "T_dynamic": int((seg == "dynamic").sum()),
            "T_used": int(keep.sum()), "max_samples": max_samples, "K": int(rec.K),
            "sample_rate_hz": float(raw.sample_rate),
            "gyro_clipped_fraction": None if gc is None else float(gc.mean()),
            "acc_noise_std": np.asarray(rec.acc_noise_std).tolist(),
            "gyro_noise_std": np.asarray(rec.gyro_noise_std).tolist()}
    return rec, info


def _effects_from_report(doc: dict):
    """The model effects of a report's findings (``unexplained`` has no model and is skipped)."""
    from accel_bayes.mismatch import make_effect

    out = []
    for f in doc.get("findings") or []:
        if f["effect"] == "unexplained":
            continue
        params = dict(f.get("parameters") or {})
        if "sensor" in f and "sensor" not in params:
            params["sensor"] = f["sensor"]
        out.append(make_effect(f["effect"], imu=f.get("imu"), axis=f.get("axis"), parameters=params))
    return out


# ---------------------------------------------------------------------------- stages

def stage_detect(args, exps):
    from accel_bayes.mismatch import detect

    for i in exps:
        d = args.out / f"exp_{i}"
        if (d / "report.json").exists() and not args.redo:
            print(f"exp_{i}: report exists, skipped (--redo to recompute)")
            continue
        rec, info = load_dynamic(i, args.data, args.max_samples)
        print(f"exp_{i}: T = {info['T_used']} dynamic samples (of {info['T_total']}), K = {info['K']}; detecting …",
              flush=True)
        t0 = time.perf_counter()
        rep = detect(rec, seed=0, progress=args.progress, **args.detect_kwargs)
        secs = time.perf_counter() - t0
        rep.write(d, figures=not args.no_figures)
        info["detect_seconds"] = secs
        info["detect_kwargs"] = args.detect_kwargs
        (d / "info.json").write_text(json.dumps(info, indent=1))
        doc = rep.to_dict()
        print(f"exp_{i}: {secs:.0f} s; χ²/dof {doc['baseline']['chi2_per_dof']:.4g} → "
              f"{(doc['refined'] or doc['baseline'])['chi2_per_dof']:.4g}; findings "
              + ", ".join(f"{f['effect']}[imu={f['imu']},axis={f['axis']}] {f['evidence']:.4g}" for f in doc["findings"]),
              flush=True)


def stage_heldout(args, exps):
    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.transfer import heldout_fit

    path = args.out / "heldout.json"
    res = json.loads(path.read_text()) if path.exists() and not args.redo else {}
    reports = {}
    for i in exps:
        p = args.out / f"exp_{i}" / "report.json"
        if p.exists():
            reports[i] = json.loads(p.read_text())
    if not reports:
        print("heldout: no reports yet; run --stage detect first")
        return
    for j in exps:
        todo = [i for i in reports if f"{i}->{j}" not in res]
        if not todo:
            continue
        rec, info = load_dynamic(j, args.data, args.max_samples)
        prep = prepare(rec)
        t0 = time.perf_counter()
        base, _ = baseline_fit(prep)
        tb = time.perf_counter() - t0
        for i in todo:
            effs = _effects_from_report(reports[i])
            if not effs:
                res[f"{i}->{j}"] = {"source": i, "target": j, "effects": [], "difference": 0.0, "note": "no findings"}
                continue
            h = heldout_fit(prep, effs, base=base)
            h.update(source=i, target=j, T=prep.T, baseline_seconds=tb)
            res[f"{i}->{j}"] = h
            print(f"held-out exp_{i} → exp_{j}: Δlog L = {h['difference']:+.1f} ({h['per_sample']:+.3f} per sample), "
                  f"χ²/dof {h['chi2_per_dof_nominal']:.4g} → {h['chi2_per_dof_fixed']:.4g} [{h['seconds']:.0f} s]",
                  flush=True)
            path.write_text(json.dumps(res, indent=1))
    path.write_text(json.dumps(res, indent=1))


def stage_heldout_single(args, exps):
    """The held-out check per finding: each effect found on experiment i, alone and with its
    parameters fixed, on every experiment j (which findings carry over)."""
    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.transfer import heldout_fit

    path = args.out / "heldout_single.json"
    res = json.loads(path.read_text()) if path.exists() and not args.redo else {}
    reports = {i: json.loads((args.out / f"exp_{i}" / "report.json").read_text()) for i in exps
               if (args.out / f"exp_{i}" / "report.json").exists()}
    for j in exps:
        todo = [(i, e) for i in reports for e in _effects_from_report(reports[i]) if f"{i}:{e.label()}->{j}" not in res]
        if not todo:
            continue
        rec, _ = load_dynamic(j, args.data, args.max_samples)
        prep = prepare(rec)
        base, _ = baseline_fit(prep)
        for i, e in todo:
            h = heldout_fit(prep, [e], base=base)
            res[f"{i}:{e.label()}->{j}"] = {"source": i, "target": j, "effect": e.label(),
                                              "difference": h["difference"], "per_sample": h["per_sample"]}
            print(f"held-out (single) exp_{i} {e.label()} → exp_{j}: Δlog L = {h['difference']:+.4g}", flush=True)
        path.write_text(json.dumps(res, indent=1))


def _spread(P: np.ndarray) -> dict:
    """P (E, K, 3) positions of E experiments: per IMU the std per axis (µm) and the RMS distance
    to the mean (µm)."""
    mean = P.mean(0)
    std = P.std(0, ddof=1) * 1e6
    rms = np.sqrt(((P - mean) ** 2).sum(-1).mean(0)) * 1e6
    return {"std_um": std.tolist(), "rms_um": rms.tolist(), "mean_m": mean.tolist()}


def stage_summary(args, exps):
    rows, P0, P1 = [], [], []
    for i in exps:
        p = args.out / f"exp_{i}" / "report.json"
        if not p.exists():
            continue
        doc = json.loads(p.read_text())
        info = json.loads((args.out / f"exp_{i}" / "info.json").read_text())
        det = doc["details"]
        ref = doc["refined"]
        P0.append(np.asarray(det["positions_baseline"]))
        P1.append(np.asarray(det["positions_refined"] if det["positions_refined"] is not None else det["positions_baseline"]))
        rows.append({"experiment": i, "T": info["T_used"], "seconds": info["detect_seconds"],
                     "chi2_before": doc["baseline"]["chi2_per_dof"], "loglik_before": doc["baseline"]["loglik"],
                     "chi2_after": ref["chi2_per_dof"] if ref else None,
                     "chi2_after_stated": ref.get("chi2_per_dof_stated_noise") if ref else None,
                     "chi2_noise": ref.get("chi2_noise") if ref else None,
                     "loglik_after": ref["loglik"] if ref else None,
                     "elpd_difference": ref.get("elpd_loo_difference") if ref else None,
                     "threshold": doc["threshold"],
                     "findings": [{k: f.get(k) for k in ("effect", "imu", "axis", "sensor", "evidence", "parameters")}
                                  for f in doc["findings"]],
                     "withdrawn": det.get("withdrawn")})
    hpath = args.out / "heldout.json"
    held = json.loads(hpath.read_text()) if hpath.exists() else {}
    spath = args.out / "heldout_single.json"
    summary = {"experiments": rows, "heldout": held,
               "heldout_single": json.loads(spath.read_text()) if spath.exists() else {}}
    if len(P0) >= 2:
        summary["repeatability_baseline"] = _spread(np.stack(P0))
        summary["repeatability_refined"] = _spread(np.stack(P1))
        summary["repeatability_experiments"] = [r["experiment"] for r in rows]
    (args.out / "summary.json").write_text(json.dumps(summary, indent=1, default=float))
    md = summary_markdown(summary)
    (args.out / "summary.md").write_text(md)
    print(md)
    if not args.no_figures:
        try:
            figures(summary, np.stack(P0) if P0 else None, np.stack(P1) if P1 else None, args.out)
        except Exception as exc:  # figures are a convenience
            print(f"figures failed: {exc}", file=sys.stderr)


def _fmt_params(p: dict) -> str:
    out = []
    for k, v in (p or {}).items():
        if k in ("rotation_vector_array",):
            continue
        if isinstance(v, list):
            out.append(f"{k}=[" + ", ".join(f"{x:.3g}" for x in v) + "]")
        elif isinstance(v, float):
            out.append(f"{k}={v:.4g}")
        else:
            out.append(f"{k}={v}")
    return "; ".join(out)


def summary_markdown(s: dict) -> str:
    L = []
    L.append("### Findings per experiment\n")
    L.append("| exp | T | effect | IMU | axis | sensor | evidence | parameters |")
    L.append("|---|---|---|---|---|---|---|---|")
    for r in s["experiments"]:
        if not r["findings"]:
            L.append(f"| {r['experiment']} | {r['T']} | (none) | | | | | |")
        for f in r["findings"]:
            L.append(f"| {r['experiment']} | {r['T']} | {f['effect']} | {f['imu']} | {f['axis'] or ''} | "
                     f"{f.get('sensor') or ''} | {f['evidence']:.4g} | {_fmt_params(f['parameters'])} |")
    L.append("\n### Fit before/after (dynamic samples, intrinsics applied)\n")
    L.append("| exp | χ²/dof nominal | χ²/dof refined | (noise) | χ²/dof refined, stated noise | log L nominal | "
             "log L refined | Δ log L | Δ ELPD (LOO) | threshold | detect s |")
    L.append("|---|---|---|---|---|---|---|---|---|---|---|")
    for r in s["experiments"]:
        a = r["chi2_after"]
        la = r["loglik_after"]
        dl = "" if la is None else f"{la - r['loglik_before']:.4g}"
        L.append(f"| {r['experiment']} | {r['chi2_before']:.4g} | {'' if a is None else f'{a:.4g}'} | "
                 f"{r['chi2_noise'] or ''} | {'' if r['chi2_after_stated'] is None else format(r['chi2_after_stated'], '.4g')} | "
                 f"{r['loglik_before']:.6g} | {'' if la is None else f'{la:.6g}'} | "
                 f"{dl} | "
                 f"{'' if r['elpd_difference'] is None else format(r['elpd_difference'], '.4g')} | {r['threshold']:.3g} | "
                 f"{r['seconds']:.0f} |")
    held = s.get("heldout") or {}
    if held:
        ex = sorted({v["source"] for v in held.values()} | {v["target"] for v in held.values()})
        L.append("\n### Held-out check: Δ log L (effects of the row's experiment, parameters fixed) − (nominal), "
                 "on the column's experiment\n")
        L.append("| from \\ on | " + " | ".join(f"exp {j}" for j in ex) + " |")
        L.append("|---|" + "---|" * len(ex))
        for i in ex:
            cells = []
            for j in ex:
                v = held.get(f"{i}->{j}")
                cells.append("" if v is None else (f"{v['difference']:+.4g}" + (" (in-sample)" if i == j else "")))
            L.append(f"| exp {i} | " + " | ".join(cells) + " |")
        off = [v for v in held.values() if v["source"] != v["target"] and v.get("effects")]
        pos = sum(v["difference"] > 0 for v in off)
        L.append(f"\nOff-diagonal pairs with findings: {len(off)}; log-likelihood raised in {pos}/{len(off)}.")
        L.append("\nPer sample (Δ log L / T):\n")
        L.append("| from \\ on | " + " | ".join(f"exp {j}" for j in ex) + " |")
        L.append("|---|" + "---|" * len(ex))
        for i in ex:
            L.append(f"| exp {i} | " + " | ".join(
                "" if held.get(f"{i}->{j}") is None or "per_sample" not in held[f"{i}->{j}"]
                else f"{held[f'{i}->{j}']['per_sample']:+.3f}" for j in ex) + " |")
    single = s.get("heldout_single") or {}
    if single:
        L.append("\n### Held-out check per finding (each finding alone, parameters fixed; off-diagonal targets)\n")
        L.append("| found on | finding | in-sample Δ log L | targets raised | median Δ log L per sample on the others | "
                 "min | max |")
        L.append("|---|---|---|---|---|---|---|")
        keys = sorted({(v["source"], v["effect"]) for v in single.values()})
        for i, lab in keys:
            vs = [v for v in single.values() if v["source"] == i and v["effect"] == lab]
            off = [v["per_sample"] for v in vs if v["target"] != i]
            ins = [v["difference"] for v in vs if v["target"] == i]
            L.append(f"| exp {i} | {lab} | {'' if not ins else format(ins[0], '.4g')} | "
                     f"{sum(x > 0 for x in off)}/{len(off)} | {np.median(off):+.1f} | {min(off):+.1f} | {max(off):+.1f} |"
                     if off else f"| exp {i} | {lab} | | | | | |")
    if "repeatability_baseline" in s:
        b, a = s["repeatability_baseline"], s["repeatability_refined"]
        L.append(f"\n### Repeatability of the position estimates across experiments "
                 f"{s['repeatability_experiments']} (relative to IMU 0)\n")
        L.append("| IMU | std x/y/z nominal fit (µm) | RMS dist. to mean, nominal (µm) | std x/y/z refined fit (µm) | "
                 "RMS dist. to mean, refined (µm) |")
        L.append("|---|---|---|---|---|")
        for k in range(len(b["rms_um"])):
            L.append(f"| {k} | {' / '.join(f'{v:.0f}' for v in b['std_um'][k])} | {b['rms_um'][k]:.0f} | "
                     f"{' / '.join(f'{v:.0f}' for v in a['std_um'][k])} | {a['rms_um'][k]:.0f} |")
        kk = range(1, len(b["rms_um"]))
        L.append(f"| mean (IMUs 1–{len(b['rms_um']) - 1}) | | {np.mean([b['rms_um'][k] for k in kk]):.0f} | | "
                 f"{np.mean([a['rms_um'][k] for k in kk]):.0f} |")
    return "\n".join(L) + "\n"


def figures(s, P0, P1, out: Path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if P0 is not None and len(P0) >= 2:
        K = P0.shape[1]
        fig, axes = plt.subplots(2, (K + 1) // 2, figsize=(3 * ((K + 1) // 2), 6))
        for k, ax in zip(range(K), axes.ravel()):
            m = P0[:, k].mean(0)
            ax.scatter((P0[:, k, 0] - m[0]) * 1e3, (P0[:, k, 1] - m[1]) * 1e3, marker="o", label="nominal fit")
            ax.scatter((P1[:, k, 0] - m[0]) * 1e3, (P1[:, k, 1] - m[1]) * 1e3, marker="x", label="refined fit")
            ax.set_title(f"IMU {k}")
            ax.set_xlabel("x − mean (mm)")
            ax.set_ylabel("y − mean (mm)")
        axes.ravel()[0].legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(out / "positions_spread.png", dpi=90)
        plt.close(fig)
    held = s.get("heldout") or {}
    if held:
        ex = sorted({v["source"] for v in held.values()} | {v["target"] for v in held.values()})
        M = np.full((len(ex), len(ex)), np.nan)
        for a, i in enumerate(ex):
            for b, j in enumerate(ex):
                v = held.get(f"{i}->{j}")
                if v is not None and "per_sample" in v:
                    M[a, b] = v["per_sample"]
        fig, ax = plt.subplots(figsize=(5, 4))
        im = ax.imshow(M, cmap="viridis")
        ax.set_xticks(range(len(ex)), [f"exp {j}" for j in ex])
        ax.set_yticks(range(len(ex)), [f"exp {i}" for i in ex])
        ax.set_xlabel("applied to")
        ax.set_ylabel("estimated on")
        fig.colorbar(im, label="Δ log L per sample")
        fig.tight_layout()
        fig.savefig(out / "heldout_matrix.png", dpi=90)
        plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="folder with exp_1..exp_6 (default ../shared/data/mimu4444-bcd)")
    ap.add_argument("--out", type=Path, default=HERE / "out" / "mimu_mismatch")
    ap.add_argument("--experiments", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--stage", choices=("detect", "heldout", "heldout-single", "summary", "all"), default="all")
    ap.add_argument("--max-samples", type=int, default=None, help="keep the last N dynamic samples (default all)")
    ap.add_argument("--detect-opt", action="append", default=[], metavar="KEY=VALUE",
                    help="extra keyword for detect() (JSON value), e.g. n_twins=20; default none")
    ap.add_argument("--redo", action="store_true", help="recompute cached results")
    ap.add_argument("--no-figures", action="store_true")
    ap.add_argument("--progress", action="store_true")
    args = ap.parse_args(argv)
    args.data = args.data or data_dir()
    args.out.mkdir(parents=True, exist_ok=True)
    args.detect_kwargs = {}
    for kv in args.detect_opt:
        k, v = kv.split("=", 1)
        try:
            args.detect_kwargs[k] = json.loads(v)
        except ValueError:
            args.detect_kwargs[k] = v
    import torch

    torch.set_num_threads(int(os.environ.get("OMP_NUM_THREADS", "1") or 1))
    if args.stage in ("detect", "all"):
        stage_detect(args, args.experiments)
    if args.stage in ("heldout", "all"):
        stage_heldout(args, args.experiments)
    if args.stage in ("heldout-single", "all"):
        stage_heldout_single(args, args.experiments)
    if args.stage in ("summary", "all"):
        stage_summary(args, args.experiments)
    return 0


if __name__ == "__main__":
    sys.exit(main())

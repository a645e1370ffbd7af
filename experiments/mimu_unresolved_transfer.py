#!/usr/bin/env python3
"""Can the unresolved motion's scales be borrowed from another recording of the same board? (issue #27
"Must show: real data": the §7.2 budget again with every random-effect scale taken from another
experiment, where the 80 % must still hold.)

Reads the detections cached by ``experiments/mimu_mismatch.py`` (``OUT/exp_i/state.pt`` and
``report.json``: the final prepared recording, the refined fit, the accepted clocks; restaged with
``--stage restage`` so that the reports' scales are this version's) and measures, on the six real
recordings:

1. **Loading.**  The unresolved term of each experiment and sensor fitted (``fit_grid``: scale per
   |ω| × |ω̇| cell, white variance per IMU, age error) on the *same absolute cells* for all six (the
   pooled 25/50/75/90 % quantiles of the six recordings' |ω| and |ω̇|), loaded either by each clock's
   fitted sawtooth width (``age_rms_s``, the detector's loading before this study) or by the physical
   width 1/f_k (:func:`accel_bayes.mismatch.unresolved_stage.physical_ages`): log-likelihood, the
   scale's rms over the samples, its spread across the six; per absolute cell, each experiment's scale
   over the six's geometric mean (does a session differ by a level or by a shape?).
2. **A resolved observable.**  Whether the fitted scale tracks something each recording shows
   without its residuals — the high-frequency content of the resolved motion: the board-mean gyro's
   and accelerometer's second differences (rad/s², m/s³ per read interval) and the increments of the
   fitted ω̇ and specific-force states — so that a borrowed *ratio* (scale² / observable per cell)
   would carry the session's level.  Per experiment: each quantity relative to the six's mean; per
   cyclic pair (i borrows from i + 1): the unresolved term's named variance on i with j's scales
   (absolute cells) and with j's ratio times i's observable, relative to i's own.
3. **All ordered pairs.**  ``mimu_mismatch.transferred_budget`` on every ordered pair (30): b/a of
   "all" and the issue's band rule, per sensor.

    python experiments/mimu_unresolved_transfer.py --doc experiments/mimu_unresolved_transfer.md
"""
from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

from _reading import READING_MARKER, kept_reading  # noqa: E402

EXPS = (1, 2, 3, 4, 5, 6)
SENSORS = ("acc", "gyro")
OBSERVABLES = {  # name: (what, units of its rms)
    "gyro_d2": ("board-mean gyro, second difference / read interval", "rad/s²"),
    "omega_dot_d1": ("fitted ω̇ state, first difference", "rad/s²"),
    "acc_d2": ("board-mean accelerometer, second difference / read interval", "m/s³"),
    "force_d1": ("fitted specific-force state, first difference / read interval", "m/s³"),
}


def _load(out: Path, i: int) -> dict:
    return torch.load(out / f"exp_{i}" / "state.pt", weights_only=False)


def _observables(prep, fit) -> dict:
    """Per sample (T,): the squared high-frequency content of the resolved motion (OBSERVABLES), from
    consecutive reads only (a gap in the kept samples leaves the sample at the recording's median)."""
    from accel_bayes.physics.geometry import quat_to_matrix

    t = prep.time.numpy()
    dt = float(np.median(np.diff(t)))
    cont = np.abs(np.diff(t) - dt) < 0.25 * dt
    R = quat_to_matrix(torch.as_tensor(prep.q, dtype=torch.float64)).numpy()
    out = {}
    for name, y, m in (("gyro", prep.y_gyro, prep.m_gyro), ("acc", prep.y_acc, prep.m_acc)):
        ya = np.einsum("kji,tkj->tki", R, y.numpy())
        ok = m.numpy().all(-1)
        mean = (ya * ok[..., None]).sum(1) / np.maximum(ok.sum(1), 1)[:, None]
        v = np.full(len(t), np.nan)
        both = cont[:-1] & cont[1:]
        d2 = mean[2:] - 2 * mean[1:-1] + mean[:-2]
        v[1:-1] = np.where(both, (d2 ** 2).sum(-1) / dt ** 2, np.nan)
        out[f"{name}_d2"] = v
    x = fit.x.detach().numpy()
    for name, sl, scale in (("omega_dot_d1", slice(3, 6), 1.0), ("force_d1", slice(6, 9), 1.0 / dt)):
        v = np.full(len(t), np.nan)
        v[1:] = np.where(cont, ((np.diff(x[:, sl], axis=0) * scale) ** 2).sum(-1), np.nan)
        out[name] = v
    return {k: np.where(np.isfinite(v), v, np.nanmedian(v)) for k, v in out.items()}


def _arrays(state, sensor, physical: bool):
    """(a, d, w, v_known, v_floor) of the unresolved stage for ``sensor``, the ages physical or fitted."""
    from accel_bayes.mismatch.budget import predicted_extra_variance
    from accel_bayes.mismatch.clock import data_age
    from accel_bayes.mismatch.unresolved_stage import _centred_ages, physical_ages
    from accel_bayes.mismatch.vibration import array_residuals

    prep, fit = state["prep"], state["refined"]
    clocks = [e for e in state["fixed"] if e.name == "sampling_clock"]
    has = torch.zeros(prep.K, dtype=torch.bool)
    has[sorted({int(c.imu) for c in clocks})] = True
    age = (physical_ages if physical else data_age)(clocks, prep.time, prep.K)
    a, ok = array_residuals(prep, fit, sensor)
    w = (ok & has[None, :]).to(a.dtype)
    d = _centred_ages(age, w)
    known = predicted_extra_variance(prep, fit)[SENSORS.index(sensor)].mean(-1)
    sig2 = ((prep.sigma_acc if sensor == "acc" else prep.sigma_gyro) ** 2)[has]
    return a[:, has], d[:, has], w[:, has], known[:, has] * w[:, has], sig2


def stage_fits(out: Path) -> dict:
    """Items 1 and 2 of the module docstring."""
    from accel_bayes.mismatch.unresolved import fit_grid

    motion, obs = {}, {}
    for i in EXPS:
        st = _load(out, i)
        x = st["refined"].x.detach().numpy()
        motion[i] = (np.linalg.norm(x[:, 0:3], axis=1), np.linalg.norm(x[:, 3:6], axis=1))
        obs[i] = _observables(st["prep"], st["refined"])
    we = np.quantile(np.concatenate([m[0] for m in motion.values()]), [0.25, 0.5, 0.75, 0.9])
    wde = np.quantile(np.concatenate([m[1] for m in motion.values()]), [0.25, 0.5, 0.75, 0.9])
    cells = {i: np.digitize(motion[i][0], we) * 5 + np.digitize(motion[i][1], wde) for i in EXPS}
    fits = {}
    for i in EXPS:
        st = _load(out, i)
        for s in SENSORS:
            for phys in (False, True):
                a, d, w, known, sig2 = _arrays(st, s, phys)
                g = fit_grid(a, d, w, torch.as_tensor(cells[i]), 25, v_known=known, v_floor=sig2, std=False)
                load = ((d ** 2 + g.e2) * w).sum(1).numpy()  # Σ_k (d² + e²) per sample: the named variance / s²
                fits[(i, s, phys)] = {"s2": g.s2.numpy(), "e2": g.e2, "loglik": g.loglik, "load": load,
                                      "load_d": (d ** 2 * w).sum(1).numpy(), "w": w.sum(1).numpy()}
        print(f"exp_{i}: fitted", flush=True)
    rows = {"omega_edges": we.tolist(), "omega_dot_edges": wde.tolist(), "loading": [], "observables": [],
            "cyclic": []}
    for i in EXPS:
        for s in SENSORS:
            f0, f1 = fits[(i, s, False)], fits[(i, s, True)]
            rows["loading"].append({"experiment": i, "sensor": s, "loglik_fitted_width": f0["loglik"],
                                    "loglik_physical": f1["loglik"],
                                    "scale_rms_fitted_width": float(np.sqrt(f0["s2"][cells[i]].mean())),
                                    "scale_rms_physical": float(np.sqrt(f1["s2"][cells[i]].mean())),
                                    "age_error_ms_fitted_width": 1e3 * np.sqrt(f0["e2"]),
                                    "age_error_ms_physical": 1e3 * np.sqrt(f1["e2"]),
                                    "age_rms_ms_fitted_width": 1e3 * float(np.sqrt(f0["load_d"].sum() / f0["w"].sum())),
                                    "age_rms_ms_physical": 1e3 * float(np.sqrt(f1["load_d"].sum() / f1["w"].sum()))})
    # per absolute cell: each experiment's scale over the six's geometric mean (a level shift or a shape?)
    rows["cells"] = {s: {i: fits[(i, s, True)]["s2"].tolist() for i in EXPS} for s in SENSORS}
    rows["cell_counts"] = {i: np.bincount(cells[i], minlength=25).tolist() for i in EXPS}
    for i in EXPS:
        rows["observables"].append({"experiment": i, **{k: float(np.sqrt(v.mean())) for k, v in obs[i].items()}})
    # cyclic borrowing of the physical-width term: scales by absolute cell, or a ratio to an observable
    for s in SENSORS:
        for i in EXPS:
            j = EXPS[(EXPS.index(i) + 1) % len(EXPS)]
            fi, fj = fits[(i, s, True)], fits[(j, s, True)]
            own = (fi["s2"][cells[i]] * fi["load"]).sum()
            load_ij = fi["load"] - fi["e2"] * fi["w"] + fj["e2"] * fi["w"]  # i's ages, j's age error
            r = {"sensor": s, "experiment": i, "source": j,
                 "cells": float((fj["s2"][cells[i]] * load_ij).sum() / own)}
            for k in OBSERVABLES:
                P = np.array([obs[j][k][cells[j] == c].mean() if (cells[j] == c).any() else np.nan for c in range(25)])
                ratio = fj["s2"] / P
                rt = np.where(np.isfinite(ratio[cells[i]]), ratio[cells[i]], np.nanmedian(ratio))
                r[k] = float((rt * obs[i][k] * load_ij).sum() / own)
            rows["cyclic"].append(r)
    return rows


def stage_pairs(out: Path) -> list:
    """Item 3: every ordered pair's transferred budget."""
    from mimu_mismatch import _ratios, _band_ok, transferred_budget

    docs = {j: json.loads((out / f"exp_{j}" / "report.json").read_text()) for j in EXPS}
    res = []
    for i in EXPS:
        st = _load(out, i)
        for j in EXPS:
            if j == i:
                continue
            rows, _ = transferred_budget(st, docs[j])
            r = {"target": i, "source": j}
            for s in SENSORS:
                r[f"{s}_all"] = _ratios(rows, s)[0]
                r[f"{s}_bad_bands"] = [x["regime"] for x in rows if x["sensor"] == s and x["regime"] != "all"
                                       and not _band_ok(x)]
            res.append(r)
        print(f"exp_{i}: pairs done", flush=True)
    return res


def markdown(fits: dict, pairs: list) -> str:
    L = ["### 1. Loading: the clocks' fitted sawtooth width against the physical 1/f_k (same absolute cells for all six)\n",
         f"Cells: |ω| edges {', '.join(f'{e:.1f}' for e in fits['omega_edges'])} rad/s × |ω̇| edges "
         f"{', '.join(f'{e:.0f}' for e in fits['omega_dot_edges'])} rad/s² (pooled quantiles of the six).\n",
         "| exp | sensor | centred age rms, fitted / physical (ms) | log L fitted width | log L physical | Δ log L | "
         "scale rms, fitted width | scale rms, physical | age error, fitted / physical (ms) |",
         "|---|---|---|---|---|---|---|---|---|"]
    for r in fits["loading"]:
        L.append(f"| {r['experiment']} | {r['sensor']} | {r['age_rms_ms_fitted_width']:.3f} / {r['age_rms_ms_physical']:.3f} | "
                 f"{r['loglik_fitted_width']:.1f} | {r['loglik_physical']:.1f} | "
                 f"{r['loglik_physical'] - r['loglik_fitted_width']:+.1f} | {r['scale_rms_fitted_width']:.4g} | "
                 f"{r['scale_rms_physical']:.4g} | {r['age_error_ms_fitted_width']:.3f} / {r['age_error_ms_physical']:.3f} |")
    for s, u in (("acc", "m/s³"), ("gyro", "rad/s²")):
        v0 = [r["scale_rms_fitted_width"] for r in fits["loading"] if r["sensor"] == s]
        v1 = [r["scale_rms_physical"] for r in fits["loading"] if r["sensor"] == s]
        L.append(f"\n{s}: scale rms max/min over the six {max(v0) / min(v0):.2f} (fitted width), "
                 f"{max(v1) / min(v1):.2f} (physical) ({u}).")
    L += ["\nPer absolute cell (|ω| band b × |ω̇| band c, physical loading): each experiment's scale over the six's "
          "geometric mean in that cell (cells with ≥ 30 samples in every experiment):\n",
          "| sensor | cell b,c | " + " | ".join(f"exp {i}" for i in EXPS) + " |", "|---|---|" + "---|" * len(EXPS)]
    for s in SENSORS:
        S = np.sqrt(np.array([fits["cells"][s][i] for i in EXPS]))  # (6, 25) rms per axis
        n = np.array([fits["cell_counts"][i] for i in EXPS])
        keep = (n >= 30).all(0) & (S > 0).all(0)
        rel = S[:, keep] / np.exp(np.log(S[:, keep]).mean(0))
        for c, col in zip(np.flatnonzero(keep), rel.T):
            L.append(f"| {s} | {c // 5},{c % 5} | " + " | ".join(f"{v:.2f}" for v in col) + " |")
        L.append(f"| {s} | below the mean in | " + " | ".join(f"{int((r < 1).sum())}/{keep.sum()}" for r in rel) + " |")
    L += ["\n### 2. Does the scale track the resolved motion's high-frequency content?\n",
          "Each quantity over its mean across the six (scale: the physical-width fit's rms; observables: rms over the "
          "recording):\n",
          "| exp | acc scale | gyro scale | " + " | ".join(f"{k} ({OBSERVABLES[k][0]})" for k in OBSERVABLES) + " |",
          "|---|---|---|" + "---|" * len(OBSERVABLES)]
    sc = {s: {r["experiment"]: r["scale_rms_physical"] for r in fits["loading"] if r["sensor"] == s} for s in SENSORS}
    ob = {k: {r["experiment"]: r[k] for r in fits["observables"]} for k in OBSERVABLES}
    rel = lambda d, i: d[i] / np.mean(list(d.values()))  # noqa: E731
    for i in EXPS:
        L.append(f"| {i} | {rel(sc['acc'], i):.3f} | {rel(sc['gyro'], i):.3f} | "
                 + " | ".join(f"{rel(ob[k], i):.3f}" for k in OBSERVABLES) + " |")
    for s in SENSORS:
        L.append(f"\n{s}: correlation over the six of the scale with each observable: " + ", ".join(
            f"{k} {np.corrcoef([sc[s][i] for i in EXPS], [ob[k][i] for i in EXPS])[0, 1]:+.2f}" for k in OBSERVABLES) + ".")
    L += ["\nThe unresolved term's named variance on exp i borrowed from exp i + 1 (cyclic), over i's own: by absolute "
          "cell, or as j's ratio scale²/observable per cell times i's own observable:\n",
          "| sensor | exp ← source | by cell | " + " | ".join(f"ratio to {k}" for k in OBSERVABLES) + " |",
          "|---|---|---|" + "---|" * len(OBSERVABLES)]
    for r in fits["cyclic"]:
        L.append(f"| {r['sensor']} | {r['experiment']} ← {r['source']} | {r['cells']:.2f} | "
                 + " | ".join(f"{r[k]:.2f}" for k in OBSERVABLES) + " |")
    L += ["\n### 3. Every ordered pair: the §7.2 budget with every random-effect scale from the source "
          "(`mimu_mismatch.transferred_budget`)\n",
          "b/a of \"all\"; a cell is marked * where some |ω| or |ω̇| band fails the issue's rule (0.7–1.3, or "
          "|b − a| ≤ 3 SE where a < 3 SE).\n"]
    for s in SENSORS:
        L += [f"\n{s} (rows: the recording; columns: where the scales come from)\n",
              "| exp \\ scales from | " + " | ".join(f"exp {j}" for j in EXPS) + " |", "|---|" + "---|" * len(EXPS)]
        for i in EXPS:
            cells = []
            for j in EXPS:
                p = next((x for x in pairs if x["target"] == i and x["source"] == j), None)
                cells.append("–" if p is None else f"{p[f'{s}_all']:.2f}" + ("*" if p[f"{s}_bad_bands"] else ""))
            L.append(f"| exp {i} | " + " | ".join(cells) + " |")
        v = [p[f"{s}_all"] for p in pairs]
        ok = [p for p in pairs if p[f"{s}_all"] >= 0.8]
        full = [p for p in ok if not p[f"{s}_bad_bands"]]
        L.append(f"\n{s}: \"all\" {min(v):.2f}–{max(v):.2f} (median {np.median(v):.2f}); ≥ 0.8 on {len(ok)}/{len(pairs)} "
                 f"pairs; ≥ 0.8 and every band passing on {len(full)}/{len(pairs)}.")
    return "\n".join(L) + "\n"


def figure(pairs: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.3), gridspec_kw={"wspace": 0.25})
    for ax, s in zip(axes, SENSORS):
        M = np.full((len(EXPS), len(EXPS)), np.nan)
        for p in pairs:
            M[EXPS.index(p["target"]), EXPS.index(p["source"])] = p[f"{s}_all"]
        im = ax.imshow(M, cmap="RdBu", vmin=0.4, vmax=1.6)
        for a in range(len(EXPS)):
            for b in range(len(EXPS)):
                if np.isfinite(M[a, b]):
                    bad = next(p for p in pairs if p["target"] == EXPS[a] and p["source"] == EXPS[b])[f"{s}_bad_bands"]
                    ax.text(b, a, f"{M[a, b]:.2f}" + ("*" if bad else ""), ha="center", va="center", fontsize=8)
        ax.set_xticks(range(len(EXPS)), [f"exp {j}" for j in EXPS])
        ax.set_yticks(range(len(EXPS)), [f"exp {i}" for i in EXPS])
        ax.set_xlabel("scales taken from")
        if s == "acc":
            ax.set_ylabel("budget of")
        ax.set_title({"acc": "accelerometers", "gyro": "gyroscopes"}[s] + ": b/a of \"all\" (* a band fails)", fontsize=10)
    fig.colorbar(im, ax=list(axes), label="explained share b/a")
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=HERE / "out" / "mimu_mismatch",
                    help="the cached (restaged) detections of experiments/mimu_mismatch.py")
    ap.add_argument("--doc", type=Path, default=None, help="write the results document there, keeping its reading")
    args = ap.parse_args(argv)
    from accel_bayes.data import outputs
    from accel_bayes.threads import torch_threads

    t0 = time.perf_counter()
    with torch_threads(1):
        fits = stage_fits(args.out)
        pairs = stage_pairs(args.out)
    md = markdown(fits, pairs)
    outputs.write_text(args.out / "unresolved_transfer.json", json.dumps({"fits": fits, "pairs": pairs}, indent=1,
                                                                          default=float))
    print(md)
    if args.doc is not None:
        doc = Path(args.doc)
        fig = HERE / "figures" / f"{doc.stem}_pairs.png"
        fig.parent.mkdir(exist_ok=True)
        figure(pairs, fig)
        rel = lambda p: p.resolve().relative_to(HERE.parent) if p.resolve().is_relative_to(HERE.parent) else p  # noqa: E731
        head = ["# Borrowing the unresolved motion's scales between the six MIMU4444 recordings (issue #27)", "",
                f"Generated {datetime.now(timezone.utc):%Y-%m-%d %H:%M} UTC on {platform.machine()} {platform.system()} "
                f"(2 CPUs shared with other jobs; {time.perf_counter() - t0:.0f} s) by `python experiments/"
                f"mimu_unresolved_transfer.py --out {rel(args.out)} --doc {rel(doc)}`, from the detections cached "
                f"in `{rel(args.out)}` (restaged by `python experiments/mimu_mismatch.py --stage restage`). Module "
                "docstring of `experiments/mimu_unresolved_transfer.py`: what each table measures.", ""]
        outputs.write_text(doc, "\n".join(head) + "\n" + md + f"\n![every ordered pair](figures/{fig.name})\n\n"
                           + READING_MARKER + kept_reading(doc))
        print(f"written {doc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

#!/usr/bin/env python3
"""Is the real-data ``timing_wander`` nothing but linear gyro errors?  (issue #11)

The detector names ``timing_wander`` on the gyros of IMUs 5, 4, 1 of every real MIMU4444
experiment (experiments/mimu_mismatch.md) — and names the same signature on simulated
MIMU-like data whose only errors are constant linear gyro errors (the clean twins of
``_conceal.make_multi_case``; experiments/mismatch_multi.md).  This script removes the
RELATIVE linear gyro errors before the detector sees the data, and runs the detector again.

The correction (:func:`fit_relative_gyro_linear`, independent of the detector)
------------------------------------------------------------------------------
All gyros of a rigid array measure the same angular rate ω_t (array frame), whatever their
position.  For IMU k with sensor-frame output y_kt and nominal orientation R_k
(v_sensor = R_k v_array, DESIGN §7.0) let z_kt = R_kᵀ y_kt (array frame) and ω̄_t the mean of
the z_kt over the IMUs (all gyros, IMU k included).  Least squares on the selected samples

    z_kt ≈ A_k ω̄_t + b_k,     A_k = I + E_k  (3 × 3),  b_k (3,)

(every IMU against the same regressor [ω̄_t, 1]).  Iterated: ω̄ is recomputed from the corrected
outputs and the fit repeated on the ORIGINAL z (``n_iter`` = 2 passes, the last one's A_k, b_k
are the whole map).  The frame is fixed by the mean gyro: the A_k are renormalised exactly so
that mean_k A_k = I and mean_k b_k = 0 (A_k ← A_k Ā⁻¹, b_k ← b_k − A_k b̄, the same family of
maps re-expressed against ω̄' = Ā ω̄ + b̄), i.e. **mean over IMUs of E_k = 0 and of b_k = 0**: a
linear error common to all gyros is not touched (it is not observable from gyros alone).
Correction: z_kt ← A_k⁻¹ (z_kt − b_k), back to the sensor frame y_kt = R_k z_kt.
E_k are reported in the array frame, in %.

How the detector gets the corrected samples
-------------------------------------------
``detect`` prepares the recording itself (``mismatch.prepared.prepare``: intrinsics from the
rests, the one sample selection).  This script wraps that very function: the recording is
preprocessed as always (:func:`accel_bayes.prep.preprocess.preprocess`, defaults), the map is
fitted on the KEPT samples of the preprocessed recording (intrinsics applied), applied to every
sample of it (rests included — so ``Prepared.rec``, ``.source`` and the tensors agree), and the
corrected ``Preprocessed`` is converted by the unchanged ``prepare``.  The selection is the
uncorrected recording's (it is not recomputed).  Everything else in ``detect`` runs with its
defaults, blind.

    python experiments/gyro_linear_check.py real              # six real experiments
    python experiments/gyro_linear_check.py sim               # the simulated cases (CASES below)
    python experiments/gyro_linear_check.py diag              # what is left after the correction (no detector)
    python experiments/gyro_linear_check.py common --only timing_wander-002 timing_wander-011
                                                  # control: twins corrected with the TRUE errors
    python experiments/gyro_linear_check.py crosscorr         # δ across IMUs and lags (real data, printed)
    python experiments/gyro_linear_check.py tables            # markdown tables of the stored results

Results: ``experiments/results/gyro_linear_check/{real,sim}.jsonl`` (one line per recording,
resumable).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
OUT = HERE / "results" / "gyro_linear_check"

# simulated cases: (case id, seed, effect) — the seeds of experiments/results/mismatch_multi/cases.csv
SIM_CASES = [
    ("timing_wander-002", 1700005, "timing_wander"),
    ("timing_wander-005", 1700008, "timing_wander"),
    ("timing_wander-008", 1700011, "timing_wander"),
    ("timing_wander-011", 1700014, "timing_wander"),
    ("sampling_jitter-000", 1700003, "sampling_jitter"),
    ("sampling_jitter-003", 1700006, "sampling_jitter"),
    ("timing_wander-014", 1700017, "timing_wander"),
]


# ----------------------------------------------------------------------------- the routine

def _rotations(q: np.ndarray) -> np.ndarray:
    import torch

    from accel_bayes.physics.geometry import quat_to_matrix

    return quat_to_matrix(torch.as_tensor(np.asarray(q, dtype=np.float64))).numpy()


def fit_relative_gyro_linear(gyro: np.ndarray, q: np.ndarray, keep: np.ndarray | None = None,
                             n_iter: int = 2) -> dict:
    """Relative linear gyro errors of an array from its own gyros.

    gyro (T, K, 3) sensor-frame outputs (NaN = missing), q (K, 4) nominal orientations,
    keep (T,) bool: the samples to fit on (default all).  Returns {"A": (K, 3, 3), "E": A − I,
    "b": (K, 3), "R": (K, 3, 3)} in the array frame, with mean_k A_k = I and mean_k b_k = 0
    exactly, and "rms_before"/"rms_after" (K,): RMS over the fitted samples of z_k − ω̄ before
    and after the correction (rad/s).  IMUs whose gyro is all NaN get A = I, b = 0 and are left
    out of ω̄.
    """
    R = _rotations(q)
    T, K, _ = gyro.shape
    keep = np.ones(T, bool) if keep is None else np.asarray(keep, bool)
    z = np.einsum("kji,tkj->tki", R, gyro)  # R_kᵀ y_k
    has = np.isfinite(z).all(-1).any(0)
    rows = keep & np.isfinite(z[:, has]).all((1, 2))
    zk = z[rows][:, has]  # (n, K', 3)
    Kh = zk.shape[1]
    A = np.repeat(np.eye(3)[None], Kh, 0)
    b = np.zeros((Kh, 3))
    zc = zk.copy()
    for _ in range(int(n_iter)):
        wbar = zc.mean(1)  # (n, 3)
        X = np.concatenate([wbar, np.ones((len(wbar), 1))], 1)  # (n, 4)
        coef, *_ = np.linalg.lstsq(X, zk.reshape(len(zk), -1), rcond=None)  # (4, Kh*3)
        coef = coef.reshape(4, Kh, 3)
        A = np.transpose(coef[:3], (1, 2, 0))  # A[k] (3, 3): z_k ≈ A_k ω̄ + b_k
        b = coef[3]
        Abar_inv = np.linalg.inv(A.mean(0))
        A = A @ Abar_inv
        b = b - np.einsum("kij,j->ki", A, b.mean(0))
        zc = np.einsum("kij,tkj->tki", np.linalg.inv(A), zk - b[None])
    A_all = np.repeat(np.eye(3)[None], K, 0)
    b_all = np.zeros((K, 3))
    A_all[has], b_all[has] = A, b
    rms = lambda v: np.sqrt(((v - v.mean(1, keepdims=True)) ** 2).sum(-1).mean(0))  # noqa: E731
    rb, ra = np.full(K, np.nan), np.full(K, np.nan)
    rb[has], ra[has] = rms(zk), rms(zc)
    return {"A": A_all, "E": A_all - np.eye(3)[None], "b": b_all, "R": R, "has": has,
            "n_samples": int(rows.sum()), "rms_before": rb, "rms_after": ra}


def apply_relative_gyro_linear(gyro: np.ndarray, fit: dict) -> np.ndarray:
    """y_k ← R_k A_k⁻¹ (R_kᵀ y_k − b_k) for every sample (NaN stays NaN)."""
    R, A, b = fit["R"], fit["A"], fit["b"]
    z = np.einsum("kji,tkj->tki", R, gyro)
    zc = np.einsum("kij,tkj->tki", np.linalg.inv(A), z - b[None])
    return np.einsum("kij,tkj->tki", R, zc)


def corrected_preprocessed(rec, record: dict | None = None):
    """The calibration's preprocessing of ``rec`` (defaults) with the relative linear gyro errors
    fitted on its kept samples and removed from every sample.  ``record`` gets the fit."""
    from accel_bayes.prep.preprocess import preprocess

    pre = preprocess(rec)
    r = pre.recording
    g = np.asarray(r.gyro, dtype=np.float64)
    fit = fit_relative_gyro_linear(g, np.asarray(r.nominal_orientation), keep=pre.selection.keep)
    rc = dataclasses.replace(r, gyro=apply_relative_gyro_linear(g, fit))
    if record is not None:
        record.update(fit)
    return dataclasses.replace(pre, recording=rc)


class corrected_detector:
    """Context: inside it ``accel_bayes.mismatch.detect`` prepares every recording through
    :func:`corrected_preprocessed` (the fit lands in ``self.fit``)."""

    def __enter__(self):
        import importlib

        self.mod = importlib.import_module("accel_bayes.mismatch.detect")
        self.orig = self.mod.prepare
        self.fit = {}

        def prepare(rec, **kw):
            if kw:
                raise RuntimeError(f"unexpected prepare options {kw}")
            return self.orig(corrected_preprocessed(rec, self.fit))

        self.mod.prepare = prepare
        return self

    def __exit__(self, *exc):
        self.mod.prepare = self.orig


# ----------------------------------------------------------------------------- measurements

def gyro_chi2(rec, corrected: bool) -> dict:
    """Nominal baseline fit (the detector's own, ``mismatch.fit.baseline_fit``) of the prepared
    recording, corrected or not: χ²/dof overall and the mean z² per sensor (z = residual /
    stated σ, observed channels) — the "gyro excess" before/after."""
    from accel_bayes.mismatch import baseline_fit, prepare

    prep = prepare(corrected_preprocessed(rec) if corrected else rec)
    base, _ = baseline_fit(prep)
    zg = (base.res_gyro / prep.sigma_gyro[None, :, None]) ** 2 * prep.m_gyro
    za = (base.res_acc / prep.sigma_acc[None, :, None]) ** 2 * prep.m_acc
    return {"chi2_per_dof": float(base.chi2_per_dof), "T": prep.T,
            "gyro_mean_z2": float(zg.sum() / prep.m_gyro.sum()), "acc_mean_z2": float(za.sum() / prep.m_acc.sum()),
            "gyro_mean_z2_per_imu": (zg.sum((0, 2)) / prep.m_gyro.sum((0, 2)).clamp(min=1)).tolist()}


def _short(rep: dict) -> list:
    return [{"effect": f["effect"], "imu": f.get("imu"), "axis": f.get("axis"), "evidence": f.get("evidence"),
             "parameters": f.get("parameters")} for f in rep.get("findings") or []]


def run_detect(rec, corrected: bool) -> dict:
    from accel_bayes.mismatch import detect

    t0 = time.perf_counter()
    if corrected:
        with corrected_detector() as cd:
            rep = detect(rec).to_dict()
        fit = cd.fit
    else:
        rep, fit = detect(rec).to_dict(), None
    out = {"seconds": time.perf_counter() - t0, "chi2_before": rep["baseline"]["chi2_per_dof"],
           "chi2_after": (rep.get("refined") or rep["baseline"])["chi2_per_dof"],
           "chi2_after_stated": (rep.get("refined") or {}).get("chi2_per_dof_stated"),
           "threshold": rep["threshold"], "T_used": rep["details"]["recording"].get("T"),
           "findings": _short(rep)}
    if fit:
        out["E_pct"] = (100 * fit["E"]).tolist()
        out["b_dps"] = np.degrees(fit["b"]).tolist()
        out["fit_samples"] = fit["n_samples"]
        out["rms_before"] = fit["rms_before"].tolist()
        out["rms_after"] = fit["rms_after"].tolist()
    return out


def _done(path: Path) -> set:
    if not path.exists():
        return set()
    return {json.loads(l)["id"] for l in path.read_text().splitlines() if l.strip()}


def _append(path: Path, row: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        f.write(json.dumps(row, default=float) + "\n")


def _line(row):
    return "; ".join(f"{f['effect']}[{f['imu']}{f['axis'] or ''}] {f['evidence']:.3g}" for f in row["findings"])


def stage_real(args):
    from _data import data_dir

    from accel_bayes.data.mimu import import_mimu

    path = OUT / "real.jsonl"
    done = _done(path)
    for i in args.experiments:
        if f"exp_{i}" in done:
            continue
        rec = import_mimu(data_dir() / f"exp_{i}" / "data.bin.gz")
        row = {"id": f"exp_{i}", "experiment": i,
               "baseline_uncorrected": gyro_chi2(rec, False), "baseline_corrected": gyro_chi2(rec, True)}
        if args.before:
            row["detect_uncorrected"] = run_detect(rec, False)
        row["detect_corrected"] = run_detect(rec, True)
        _append(path, row)
        d = row["detect_corrected"]
        print(f"exp_{i}: {d['seconds']:.0f} s; χ²/dof {d['chi2_before']:.4g} → {d['chi2_after']:.4g}; "
              f"gyro mean z² {row['baseline_uncorrected']['gyro_mean_z2']:.4g} → "
              f"{row['baseline_corrected']['gyro_mean_z2']:.4g}; {_line(d)}", flush=True)


def stage_sim(args):
    from _conceal import make_multi_case

    path = OUT / "sim.jsonl"
    done = _done(path)
    todo = []
    for cid, seed, eff in SIM_CASES[: args.n_sim]:
        todo.append((cid, seed, eff))
        todo.append((f"twin-{cid}", seed, "none"))
    order = [t for t in todo if t[2] == "none"] + [t for t in todo if t[2] != "none"] if args.twins_first else todo
    for cid, seed, eff in order:
        if cid in done:
            continue
        case = make_multi_case(seed, eff)
        tr = case.truth
        A_true = np.eye(3)[None] + np.asarray(tr["gyro_linear"]["matrix"])  # sensor frame
        R = _rotations(np.asarray(case.recording.nominal_orientation))
        A_arr = np.einsum("kji,kjl,klm->kim", R, A_true, R)  # R_kᵀ A_k R_k
        A_rel = A_arr @ np.linalg.inv(A_arr.mean(0))
        row = {"id": cid, "seed": seed, "effect_true": eff, "imu_true": tr.get("imu") if eff != "none" else None,
               "parameters_true": {k: v for k, v in (tr.get("parameters") or {}).items() if k != "instants"} if eff != "none" else None,
               "E_true_rel_pct": (100 * (A_rel - np.eye(3))).tolist(),
               "baseline_uncorrected": gyro_chi2(case.recording, False),
               "baseline_corrected": gyro_chi2(case.recording, True)}
        row["detect_corrected"] = d = run_detect(case.recording, True)
        E_est = np.asarray(d["E_pct"])
        row["E_error_max_pct"] = float(np.abs(E_est - np.asarray(row["E_true_rel_pct"])).max())
        _append(path, row)
        print(f"{cid}: {d['seconds']:.0f} s; χ²/dof {d['chi2_before']:.4g} → {d['chi2_after']:.4g}; max |E est − E true| "
              f"{row['E_error_max_pct']:.3f} %; {_line(d)}", flush=True)


def residual_diagnostic(rec, make_case=None) -> dict:
    """What is left of the gyros' disagreement after the correction (no detector involved).

    On the kept samples (and their neighbours kept), r_kt = z_kt − ω̄_t with z the corrected
    array-frame gyro outputs and ω̄ their mean; ω̇̄ by central differences of ω̄.  Per IMU: RMS of
    r (°/s); R² of r on [ω̇̄, 1] (a constant time offset), on the IMU's own specific force
    (g-sensitivity), on the six products ω_i ω_j (quadratic response) and on all of them; the
    share of r's power along the direction of ω̇̄_t (1/3 for an isotropic error, → 1 for a
    sampling-instant error δ_kt ω̇_t), in all samples and in the half with the larger |ω̇|, and
    along ω̄_t; the implied instant error δ_kt = r·ω̇ / |ω̇|² (its RMS in the larger-|ω̇| half and
    its lag-1 autocorrelation).
    """
    from accel_bayes.prep.preprocess import preprocess

    pre = preprocess(rec)
    r = pre.recording
    keep = pre.selection.keep
    g = np.asarray(r.gyro, dtype=np.float64)
    fit = fit_relative_gyro_linear(g, np.asarray(r.nominal_orientation), keep=keep)
    R = fit["R"]
    z = np.einsum("kji,tkj->tki", R, apply_relative_gyro_linear(g, fit))
    f = np.einsum("kji,tkj->tki", R, np.asarray(r.acc, dtype=np.float64))
    t = np.asarray(r.time, dtype=np.float64)
    dt = float(np.median(np.diff(t)))
    wbar = z.mean(1)
    wdot = np.gradient(wbar, dt, axis=0)
    ok = keep.copy()
    ok[1:] &= keep[:-1]
    ok[:-1] &= keep[1:]
    ok &= np.isfinite(z).all((1, 2)) & np.isfinite(f).all((1, 2))
    res = (z - wbar[:, None])[ok]
    w, wd = wbar[ok], wdot[ok]
    nwd = np.linalg.norm(wd, axis=1)
    big = nwd > np.median(nwd)
    u, uw = wd / nwd[:, None], w / np.linalg.norm(w, axis=1, keepdims=True)
    quad = np.stack([w[:, 0] ** 2, w[:, 1] ** 2, w[:, 2] ** 2, w[:, 0] * w[:, 1], w[:, 0] * w[:, 2], w[:, 1] * w[:, 2]], 1)
    out = {"rate_hz": 1 / dt, "n": int(ok.sum()), "rms_omega_dps": float(np.degrees(np.sqrt((w ** 2).sum(1).mean()))),
           "rms_omega_dot_dps2": float(np.degrees(np.sqrt((wd ** 2).sum(1).mean()))), "imus": []}
    for k in range(res.shape[1]):
        rk = res[:, k]
        tot = (rk ** 2).sum()

        def r2(X):
            X = np.concatenate([X, np.ones((len(X), 1))], 1)
            c, *_ = np.linalg.lstsq(X, rk, rcond=None)
            return float(1 - ((rk - X @ c) ** 2).sum() / tot)

        p = (rk ** 2).sum(1)
        along, alw = (rk * u).sum(1) ** 2, (rk * uw).sum(1) ** 2
        d = (rk * wd).sum(1) / (wd ** 2).sum(1)
        out["imus"].append({
            "imu": k, "rms_dps": float(np.degrees(np.sqrt(p.mean()))),
            "r2_omega_dot": r2(wd), "r2_specific_force": r2(f[ok, k]), "r2_quadratic": r2(quad),
            "r2_all": r2(np.concatenate([wd, f[ok, k], quad], 1)),
            "share_along_omega_dot": float(along.sum() / p.sum()),
            "share_along_omega_dot_top_half": float(along[big].sum() / p[big].sum()),
            "share_along_omega": float(alw.sum() / p.sum()),
            "delta_rms_ms_top_half": float(np.sqrt(np.mean(d[big] ** 2)) * 1e3),
            "delta_lag1": float(np.corrcoef(d[:-1], d[1:])[0, 1])})
    return out


def stage_diag(args):
    """The residual diagnostic on the six real experiments and on the simulated SIM_CASES."""
    from _conceal import make_multi_case
    from _data import data_dir

    from accel_bayes.data.mimu import import_mimu

    path = OUT / "diag.jsonl"
    done = _done(path)
    items = [(f"exp_{i}", lambda i=i: import_mimu(data_dir() / f"exp_{i}" / "data.bin.gz")) for i in args.experiments]
    for cid, seed, eff in SIM_CASES[: args.n_sim]:
        items.append((f"twin-{cid}", lambda s=seed: make_multi_case(s, "none").recording))
        items.append((cid, lambda s=seed, e=eff: make_multi_case(s, e).recording))
    for cid, load in items:
        if cid in done:
            continue
        row = {"id": cid, **residual_diagnostic(load())}
        _append(path, row)
        print(cid, " ".join(f"{m['imu']}:{m['rms_dps']:.2f}°/s,{m['share_along_omega_dot_top_half']:.2f},"
                            f"{m['delta_rms_ms_top_half']:.3f}ms" for m in row["imus"]), flush=True)


def _fmt_find(f) -> str:
    p = f.get("parameters") or {}
    extra = ""
    if f["effect"] == "timing_wander":
        extra = f" (w {1e3 * p['width']:.2f} ms, ρ {p['correlation']:.2f})"
    elif f["effect"] == "sampling_jitter":
        extra = f" (w {1e3 * p['width']:.2f} ms)"
    return f"{f['effect']}[{f['imu']}{f['axis'] or ''}] {f['evidence']:.2g}{extra}"


def stage_tables(args):
    """Markdown tables of everything stored (printed; pasted into gyro_linear_check.md)."""
    L = []
    real = [json.loads(l) for l in (OUT / "real.jsonl").read_text().splitlines() if l.strip()] \
        if (OUT / "real.jsonl").exists() else []
    if real:
        L += ["### Real experiments: detect before / after the correction", "",
              "| exp | detect (s) before / after | χ²/dof nominal → refined, before | χ²/dof nominal → refined, after | findings before | findings after |",
              "|---|---|---|---|---|---|"]
        for r in real:
            u, c = r.get("detect_uncorrected"), r["detect_corrected"]
            L.append(f"| {r['experiment']} | {u['seconds']:.0f} / {c['seconds']:.0f} | {u['chi2_before']:.4g} → {u['chi2_after']:.4g} | "
                     f"{c['chi2_before']:.4g} → {c['chi2_after']:.4g} | " + "; ".join(_fmt_find(f) for f in u["findings"])
                     + " | " + "; ".join(_fmt_find(f) for f in c["findings"]) + " |")
        L += ["", "### Real experiments: gyro excess of the nominal (baseline) fit before / after the correction", "",
              "| exp | T | χ²/dof (all) before → after | gyro mean z² before → after (share removed) | acc mean z² before → after | "
              "RMS gyro − mean gyro (°/s) per IMU 0…7 before | after |", "|---|---|---|---|---|---|---|"]
        for r in real:
            b0, b1, c = r["baseline_uncorrected"], r["baseline_corrected"], r["detect_corrected"]
            L.append(f"| {r['experiment']} | {b0['T']} | {b0['chi2_per_dof']:.4g} → {b1['chi2_per_dof']:.4g} | "
                     f"{b0['gyro_mean_z2']:.4g} → {b1['gyro_mean_z2']:.4g} ({1 - b1['gyro_mean_z2'] / b0['gyro_mean_z2']:.0%}) | "
                     f"{b0['acc_mean_z2']:.4g} → {b1['acc_mean_z2']:.4g} | "
                     + " ".join(f"{np.degrees(v):.1f}" for v in c["rms_before"]) + " | "
                     + " ".join(f"{np.degrees(v):.1f}" for v in c["rms_after"]) + " |")
        E = np.array([r["detect_corrected"]["E_pct"] for r in real])  # (n, K, 3, 3) %
        b = np.array([r["detect_corrected"]["b_dps"] for r in real])
        L += ["", "### Real experiments: the fitted relative gyro error matrices E_k (array frame, %, mean over IMUs = 0)", "",
              "Rows: IMU; entries E_xx E_xy E_xz / E_yx E_yy E_yz / E_zx E_zy E_zz; per experiment, then the mean over "
              "the experiments and the largest spread (max − min over experiments) of any entry.", ""]
        L += ["| IMU | " + " | ".join(f"exp {r['experiment']}" for r in real) + " | mean | max spread | bias b_k (°/s), mean over exps |",
              "|---|" + "---|" * (len(real) + 3)]
        fm = lambda M: " / ".join(" ".join(f"{v:+.2f}" for v in row) for row in M)  # noqa: E731
        for k in range(E.shape[1]):
            L.append(f"| {k} | " + " | ".join(fm(E[j, k]) for j in range(len(real))) + f" | {fm(E[:, k].mean(0))} | "
                     f"{(E[:, k].max(0) - E[:, k].min(0)).max():.3f} | "
                     + " ".join(f"{v:+.3f}" for v in b[:, k].mean(0)) + " |")
        L.append("")
        L.append(f"Largest |E| entry over IMUs and experiments: {np.abs(E).max():.2f} %; largest spread of an entry across "
                 f"the six experiments: {(E.max(0) - E.min(0)).max():.3f} % (median {np.median(E.max(0) - E.min(0)):.3f} %).")
    sim = [json.loads(l) for l in (OUT / "sim.jsonl").read_text().splitlines() if l.strip()] \
        if (OUT / "sim.jsonl").exists() else []
    if sim:
        import csv

        prev = {}
        for src in (HERE / "results" / "mismatch_multi" / "cases.csv",):
            if src.exists():
                for row in csv.DictReader(open(src)):
                    prev[row["case"]] = row
                break
        L += ["", "### Simulated cases (make_multi_case): detect after the correction, against the uncorrected run of "
              "mismatch_multi (cases.csv)", "",
              "| recording | truth | max \\|E est − E true\\| (%) | detect (s) | χ²/dof nominal → refined, uncorrected (CSV) | after correction | "
              "findings uncorrected (CSV) | findings after correction |", "|---|---|---|---|---|---|---|---|"]
        for r in sim:
            cid = r["id"]
            twin = cid.startswith("twin-")
            p = prev.get(cid[5:] if twin else cid, {})
            pre = "twin_" if twin else ""
            try:
                pf = "; ".join(_fmt_find(f) for f in json.loads(p.get(pre + "findings") or "[]"))
                pchi = f"{float(p[pre + 'chi2_before']):.4g} → {float(p[pre + 'chi2_after']):.4g}"
            except (KeyError, ValueError):
                pf, pchi = "", ""
            if twin:
                truth = "linear gyro errors only"
            else:
                tp = r["parameters_true"] or {}
                truth = f"{r['effect_true']} IMU {r['imu_true']}, w {1e3 * tp.get('width', float('nan')):.2f} ms" + (
                    f", ρ {tp['correlation']:.2f}" if "correlation" in tp else "")
            d = r["detect_corrected"]
            L.append(f"| {cid} | {truth} | {r['E_error_max_pct']:.3f} | {d['seconds']:.0f} | {pchi} | {d['chi2_before']:.4g} → "
                     f"{d['chi2_after']:.4g} | {pf} | " + "; ".join(_fmt_find(f) for f in d["findings"]) + " |")
    dg = [json.loads(l) for l in (OUT / "diag.jsonl").read_text().splitlines() if l.strip()] \
        if (OUT / "diag.jsonl").exists() else []
    if dg:
        L += ["", "### What is left after the correction (residual_diagnostic, no detector)", "",
              "Per recording: RMS |ω̄|, RMS |ω̇̄|; then per IMU the median over IMUs and the range: RMS of gyro − mean gyro "
              "after the correction (°/s), R² of it on ω̇ (constant time offset) / specific force (g-sensitivity) / ω_iω_j "
              "(quadratic) / all, share of its power along ω̇ (top half of |ω̇|; 1/3 = isotropic, 1 = pure timing error), "
              "implied instant error δ RMS (ms, top half of |ω̇|) and its lag-1 autocorrelation.", "",
              "| recording | RMS \\|ω\\| °/s | RMS \\|ω̇\\| °/s² | RMS residual °/s | R² ω̇ | R² f | R² quad | R² all | along ω̇ | along ω̇ (top half) | δ RMS ms | δ lag-1 |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in dg:
            def m(key, fmt):
                v = np.array([x[key] for x in r["imus"]])
                return f"{np.median(v):{fmt}} ({v.min():{fmt}}–{v.max():{fmt}})"
            L.append(f"| {r['id']} | {r['rms_omega_dps']:.0f} | {r['rms_omega_dot_dps2']:.3g} | {m('rms_dps', '.2f')} | {m('r2_omega_dot', '.3f')} | "
                     f"{m('r2_specific_force', '.3f')} | {m('r2_quadratic', '.3f')} | {m('r2_all', '.3f')} | {m('share_along_omega_dot', '.2f')} | "
                     f"{m('share_along_omega_dot_top_half', '.2f')} | {m('delta_rms_ms_top_half', '.3f')} | {m('delta_lag1', '.2f')} |")
    print("\n".join(L))


def stage_common(args):
    """Control for the corrected twins: the clean twin corrected with the TRUE linear gyro errors
    (every IMU's (I + E_k) and b_k, sensor frame: the common part included, which the relative
    correction cannot see), then detect with defaults.  Also records the common part (mean over
    IMUs of the true array-frame A_k, minus I) that the relative correction leaves."""
    from _conceal import make_multi_case

    from accel_bayes.mismatch import detect

    path = OUT / "common.jsonl"
    done = _done(path)
    for cid, seed, eff in SIM_CASES[: args.n_sim]:
        if cid.split("-")[0] not in ("timing_wander", "sampling_jitter") or f"truefix-twin-{cid}" in done:
            continue
        if args.only and cid not in args.only:
            continue
        case = make_multi_case(seed, "none")
        rec = case.recording
        E = np.asarray(case.truth["gyro_linear"]["matrix"])
        bias = np.asarray(case.truth["gyro_linear"]["bias"])
        A = np.eye(3)[None] + E
        g = np.asarray(rec.gyro, dtype=np.float64)
        gc = np.einsum("kij,tkj->tki", np.linalg.inv(A), g - bias[None])
        R = _rotations(np.asarray(rec.nominal_orientation))
        common = np.einsum("kji,kjl,klm->kim", R, A, R).mean(0) - np.eye(3)
        t0 = time.perf_counter()
        rep = detect(dataclasses.replace(rec, gyro=gc)).to_dict()
        row = {"id": f"truefix-twin-{cid}", "seed": seed, "common_E_pct": (100 * common).tolist(),
               "seconds": time.perf_counter() - t0, "chi2_before": rep["baseline"]["chi2_per_dof"],
               "chi2_after": (rep.get("refined") or rep["baseline"])["chi2_per_dof"], "findings": _short(rep)}
        _append(path, row)
        print(f"{row['id']}: common part max |E| {np.abs(common).max() * 100:.2f} %; {row['seconds']:.0f} s; "
              f"χ²/dof {row['chi2_before']:.4g} → {row['chi2_after']:.4g}; {_line(row) if row['findings'] else 'no findings'}", flush=True)


def stage_crosscorr(args):
    """The implied instant errors δ_kt of residual_diagnostic (faster half of the samples) on the
    real experiments: their correlation across IMUs (−1/(K−1) for independent errors, since each is
    taken against the mean gyro) and their autocorrelation at lags 1, 2, 3, 5 (consecutive kept
    samples only).  Printed."""
    from _data import data_dir

    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.prep.preprocess import preprocess

    for i in args.experiments:
        pre = preprocess(import_mimu(data_dir() / f"exp_{i}" / "data.bin.gz"))
        r, keep = pre.recording, pre.selection.keep
        g = np.asarray(r.gyro, dtype=np.float64)
        fit = fit_relative_gyro_linear(g, np.asarray(r.nominal_orientation), keep=keep)
        z = np.einsum("kji,tkj->tki", fit["R"], apply_relative_gyro_linear(g, fit))
        wbar = z.mean(1)
        wd = np.gradient(wbar, float(np.median(np.diff(r.time))), axis=0)
        ok = keep.copy()
        ok[1:] &= keep[:-1]
        ok[:-1] &= keep[1:]
        res, wd = (z - wbar[:, None])[ok], wd[ok]
        n = np.linalg.norm(wd, axis=1)
        big = n > np.median(n)
        d = (res * wd[:, None]).sum(2) / (wd ** 2).sum(1)[:, None]
        K = d.shape[1]
        C = np.corrcoef(d[big].T)[~np.eye(K, dtype=bool)]
        print(f"exp_{i}: correlation of δ across IMUs: median {np.median(C):.3f}, range {C.min():.3f}…{C.max():.3f} "
              f"(independent: {-1 / (K - 1):.3f})")
        idx = np.flatnonzero(ok)
        pos = {t: j for j, t in enumerate(idx)}
        for lag in (1, 2, 3, 5):
            a = np.array([pos[t] for t in idx if t + lag in pos])
            b = np.array([pos[t + lag] for t in idx if t + lag in pos])
            print(f"  lag {lag}: " + " ".join(f"{np.corrcoef(d[a, k], d[b, k])[0, 1]:+.2f}" for k in range(K)))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("stage", choices=("real", "sim", "diag", "tables", "common", "crosscorr"))
    ap.add_argument("--experiments", type=int, nargs="+", default=[1, 2, 3, 4, 5, 6])
    ap.add_argument("--before", action="store_true", help="also detect on the uncorrected real recording")
    ap.add_argument("--n-sim", type=int, default=6, help="how many of SIM_CASES (each with its clean twin)")
    ap.add_argument("--twins-first", action="store_true")
    ap.add_argument("--only", nargs="*", default=None, help="common: only these case ids")
    args = ap.parse_args(argv)
    from accel_bayes.threads import torch_threads

    with torch_threads(1):
        {"real": stage_real, "sim": stage_sim, "diag": stage_diag, "tables": stage_tables, "common": stage_common, "crosscorr": stage_crosscorr}[args.stage](args)


if __name__ == "__main__":
    main()

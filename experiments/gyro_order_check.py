#!/usr/bin/env python3
"""Odd- and even-order gyro nonlinearity and a gyro response to angular acceleration on the six
MIMU4444 recordings, held out (issue #11's candidates "gyro response to angular acceleration",
"odd- or even-order gyro nonlinearity", "different … delays between sensors").

After the detector's gyro linear stage (every gyro's 3 × 3 + offset error regressed on the fitted
rates and inverted, the motion refitted; ``acc_timing_check.fitted``, the package's own helpers),
each gyro's residual r_k (sensor frame, rad/s) is regressed, per axis i, on the polynomial terms of
its own sensor-frame rate ω_k = R_k ω (ω the fitted array-frame rate):

* **odd order** (3): ω_i³ and ω_i |ω|² — a cubic scale-factor nonlinearity, on-axis and isotropic;
* **even order** (2): ω_i² and |ω|² — what the catalogue's ``gyro_nonlinearity`` {k2} is a
  one-axis case of;
* **angular acceleration** (3): the three components of the gyro's own ω̇_k (the fitted gyro
  output's rate, rad/s²) — a response of the gyro to angular acceleration, and with it any
  constant delay of one gyro against the others (−τ ω̇, what ``gyro_delay`` / ``time_offset``
  model).

Coefficients are fitted per IMU and axis by least squares on experiment i and **held fixed** on
experiment j (30 ordered pairs).  Reported: the share of j's gyro residual power they remove (in
sample on the diagonal), and its null — the same with the regressors of j's samples permuted
across samples (the pairing broken, the distribution kept).  A term that is physics removes power
on every held-out pair; a term that only fits noise removes ≈ 0 in sample and less than 0 held out.
The gyro residual power here is that of the corrected fit (the wanders' part included: their
instants are not fitted here).

    python experiments/gyro_order_check.py            # writes experiments/gyro_order_check.md
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
OUT = HERE / "results" / "gyro_order_check"
CACHE = HERE / "out" / "gyro_order_check"  # the corrected fits' residuals (not committed)
MD = HERE / "gyro_order_check.md"
EXPERIMENTS = list(range(1, 7))
ORDERS = {"odd": "odd order (ω_i³, ω_i|ω|² per gyro axis)", "even": "even order (ω_i², |ω|² per gyro axis)",
          "rate": "angular acceleration (ω̇_x, ω̇_y, ω̇_z per gyro axis: a 3 × 3 response per gyro)"}


def design(omega_s: np.ndarray, order: str, rate_s: np.ndarray | None = None) -> np.ndarray:
    """(T, K, 3, p) regressors per sample, IMU and sensor axis from the sensor-frame rates
    omega_s (T, K, 3) rad/s: odd → [ω_i³, ω_i|ω|²], even → [ω_i², |ω|²] ((rad/s)³ or (rad/s)²),
    rate → the three components of rate_s (T, K, 3), the gyro's ω̇ (rad/s²), on every axis."""
    if order == "rate":
        return np.broadcast_to(rate_s[:, :, None, :], rate_s.shape[:2] + (3, 3))
    n2 = (omega_s ** 2).sum(-1, keepdims=True)
    if order == "odd":
        return np.stack([omega_s ** 3, omega_s * n2], -1)
    if order == "even":
        return np.stack([omega_s ** 2, np.broadcast_to(n2, omega_s.shape)], -1)
    raise ValueError(order)


def fit_coefficients(res: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Least squares per IMU and axis: res (T, K, 3), X (T, K, 3, p) → β (K, 3, p)."""
    T, K, _, p = X.shape
    beta = np.zeros((K, 3, p))
    for k in range(K):
        for i in range(3):
            beta[k, i] = np.linalg.lstsq(X[:, k, i], res[:, k, i], rcond=None)[0]
    return beta


def removed_share(res: np.ndarray, X: np.ndarray, beta: np.ndarray) -> float:
    """Share of the residual power Σ r² that r − Xβ removes (negative: it adds)."""
    pred = np.einsum("tkip,kip->tki", X, beta)
    return float(1 - ((res - pred) ** 2).sum() / (res ** 2).sum())


def load(i: int) -> dict:
    """The corrected fit of experiment i (cached in CACHE/exp_i.npz)."""
    path = CACHE / f"exp_{i}.npz"
    if path.exists():
        z = np.load(path)
        return {k: z[k] for k in z.files}
    from acc_timing_check import fitted
    from mimu_mismatch import load_recording
    from _data import data_dir

    rec, _ = load_recording(i, data_dir())
    F = fitted(rec)
    ok = F["ok"]
    omega_s = np.einsum("kij,tj->tki", F["R"], F["omega"])  # R_k: array → sensor
    out = {"res": F["res_gyro"][ok], "omega_s": omega_s[ok], "rate_s": F["gyro_rate"][ok], "sigma_gyro": F["sigma_gyro"]}
    CACHE.mkdir(parents=True, exist_ok=True)
    np.savez(path, **out)
    return out


def main() -> int:
    D = {i: load(i) for i in EXPERIMENTS}
    rng = np.random.default_rng(0)
    rows = {}
    for order in ORDERS:
        X = {i: design(D[i]["omega_s"], order, D[i]["rate_s"]) for i in D}
        B = {i: fit_coefficients(D[i]["res"], X[i]) for i in D}
        M = np.full((6, 6), np.nan)
        N = np.full((6, 6), np.nan)
        for a, i in enumerate(D):
            for b, j in enumerate(D):
                M[a, b] = removed_share(D[j]["res"], X[j], B[i])
                perm = rng.permutation(len(X[j]))
                N[a, b] = removed_share(D[j]["res"], X[j][perm], B[i])
        # size: the RMS of the fitted term in sample against the RMS of the residual (rad/s)
        size = [float(np.sqrt((np.einsum("tkip,kip->tki", X[i], B[i]) ** 2).mean())) for i in D]
        res_rms = [float(np.sqrt((D[i]["res"] ** 2).mean())) for i in D]
        rows[order] = {"share": M.tolist(), "null": N.tolist(), "term_rms": size, "residual_rms": res_rms}
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary.json").write_text(json.dumps(rows, indent=1))
    L = ["# Gyro nonlinearity (odd, even) and response to angular acceleration, held out (experiments/gyro_order_check.py)", "",
         "\n\n".join(par if par.lstrip().startswith("*") else par.replace("\n", " ")
                     for par in (__doc__ or "").split("\n\n")[1:4]), "",
         "**Verdict per term** (a term is physics only if it removes power on the held-out pairs): "
         + "; ".join(f"{ORDERS[o].split(' (')[0]}: positive on "
                     f"{int((np.asarray(rows[o]['share'])[~np.eye(6, dtype=bool)] > 0).sum())}/30 held-out pairs"
                     for o in ORDERS) + ".", "",
         "Generated by `python experiments/gyro_order_check.py`.", ""]
    for order in ORDERS:
        r = rows[order]
        M, N = np.asarray(r["share"]), np.asarray(r["null"])
        off = ~np.eye(6, dtype=bool)
        L += [f"## {ORDERS[order]}", "",
              "Share of the column's gyro residual power removed by the row's coefficients (diagonal: in sample); "
              "in brackets the same with the column's regressors permuted across samples.", "",
              "| from \\ on | " + " | ".join(f"exp {j}" for j in EXPERIMENTS) + " |", "|---|" + "---|" * 6]
        for a, i in enumerate(EXPERIMENTS):
            L.append(f"| exp {i} | " + " | ".join(f"{M[a, b]:+.4f} ({N[a, b]:+.4f})" for b in range(6)) + " |")
        L += ["", f"- held out: {M[off].min():+.4f} to {M[off].max():+.4f}, positive on {(M[off] > 0).sum()}/30 pairs; "
              f"in sample {np.diag(M).min():+.4f} to {np.diag(M).max():+.4f}; permuted {N[off].min():+.4f} to "
              f"{N[off].max():+.4f}.",
              f"- RMS of the fitted term in sample: {min(r['term_rms']):.3g}–{max(r['term_rms']):.3g} rad/s, against "
              f"a gyro residual RMS of {min(r['residual_rms']):.3g}–{max(r['residual_rms']):.3g} rad/s.", ""]
    MD.write_text("\n".join(L) + "\n")
    print("\n".join(L))
    return 0


if __name__ == "__main__":
    sys.exit(main())

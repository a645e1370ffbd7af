"""Intrinsic calibration of the six MIMU4444 recordings: self and transfer errors.

For every pair (i, j): intrinsics estimated on the rests of experiment i
(:func:`accel_bayes.prep.intrinsics.estimate_intrinsics`) are applied to experiment j, and the
error | |mean acc| − target | is taken over every static segment and IMU of j.  Printed: raw
figures, the 6×6 transfer matrices (median and max), the repeatability of the intrinsics across
experiments against their reported std, and the g check.

    python experiments/mimu_intrinsics.py [--g 9.80665] [--target 9.81] [--data DIR]

Runs in ~15 s (import ~1 s per experiment).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import data_dir  # noqa: E402
from accel_bayes.constants import RAD_TO_DEG  # noqa: E402
from accel_bayes.prep.intrinsics import estimate_intrinsics, static_acc_errors  # noqa: E402
from accel_bayes.data.mimu import import_mimu  # noqa: E402


def table(title, M, fmt="{:8.4f}"):
    print(title)
    n = M.shape[0]
    print("  est\\app " + "".join(f"{'exp_' + str(j + 1):>8}" for j in range(n)))
    for i in range(n):
        print(f"  exp_{i + 1:<4}" + "".join(fmt.format(v) for v in M[i]))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--g", type=float, default=9.80665, help="gravity magnitude used by the fit, m/s² (default 9.80665)")
    ap.add_argument("--target", type=float, default=9.81, help="|acc| the errors are measured against (default 9.81)")
    ap.add_argument("--data", type=Path, default=None, help="folder with exp_1..exp_6 (default ../shared/data/mimu4444-bcd)")
    args = ap.parse_args(argv)
    d = args.data or data_dir()
    t0 = time.perf_counter()
    recs = [import_mimu(d / f"exp_{i}" / "data.bin.gz") for i in range(1, 7)]
    t_imp = time.perf_counter() - t0
    t0 = time.perf_counter()
    intr = [estimate_intrinsics(r, g=args.g) for r in recs]
    t_fit = (time.perf_counter() - t0) / len(recs)
    n = len(recs)
    print(f"six MIMU4444 experiments; fit g = {args.g} m/s², errors against |acc| = {args.target} m/s²")
    print(f"import {t_imp:.1f} s total, intrinsics fit {t_fit:.2f} s per experiment\n")

    print("raw (no calibration): | |mean acc| - target | over static segments x IMUs")
    for j, r in enumerate(recs):
        e = np.abs(static_acc_errors(r, args.target))
        raw_norm = np.linalg.norm(static_acc_errors(r, 0.0)[..., None], axis=-1)
        print(f"  exp_{j + 1}: {e.shape[0]} rests x {e.shape[1]} IMUs, median {np.median(e):.4f}, max {e.max():.4f} m/s² "
              f"(median raw |acc| {np.median(raw_norm):.4f})")
    med = np.zeros((n, n))
    mx = np.zeros((n, n))
    for i in range(n):
        for j in range(n):
            e = np.abs(static_acc_errors(intr[i].apply(recs[j]), args.target))
            med[i, j], mx[i, j] = np.median(e), e.max()
    print()
    table("transfer: median error [m/s²] (rows: estimated on, columns: applied to)", med)
    table("transfer: max error [m/s²]", mx)
    diag = np.diag(mx)
    off = mx[~np.eye(n, dtype=bool)]
    print(f"self-calibration (diagonal): worst rest {diag.max():.4f} m/s²; transfer (off-diagonal): "
          f"median of max {np.median(off):.4f}, worst {off.max():.4f} m/s²\n")

    print("fit per experiment: residual RMS [m/s²] per IMU, chi2/dof range, acc bias std (median)")
    for i, e in enumerate(intr):
        print(f"  exp_{i + 1}: rms {np.array2string(e.residual_rms, precision=4)}; chi2/dof "
              f"{np.nanmin(e.chi2_per_dof):.1f}–{np.nanmax(e.chi2_per_dof):.1f}; bias std "
              f"{np.median(e.acc_bias_std):.2g} m/s²; gyro bias std {np.median(e.gyro_bias_std) * RAD_TO_DEG:.2g} °/s")

    # Repeatability: differences between experiments against the reported std.
    P = np.stack([e.acc_params() for e in intr])  # (n, K, 9)
    S = np.stack([e.acc_std for e in intr])
    z = []
    for i in range(n):
        for j in range(i + 1, n):
            z.append((P[i] - P[j]) / np.sqrt(S[i] ** 2 + S[j] ** 2))
    z = np.abs(np.stack(z))
    print("\nrepeatability across experiments (|difference| / combined reported std, all pairs, IMUs):")
    names = ["bias", "scale", "misalignment"]
    for name, sl in zip(names, (slice(0, 3), slice(3, 6), slice(6, 9))):
        spread = P[:, :, sl].std(0, ddof=1)
        print(f"  {name:>12}: median |z| {np.median(z[..., sl]):6.1f}, max {z[..., sl].max():6.1f}; "
              f"spread over experiments (median) {np.median(spread):.2g}, reported std (median) {np.median(S[:, :, sl]):.2g}")
    bg = np.stack([e.gyro_bias for e in intr]) * RAD_TO_DEG
    print(f"  gyro bias spread over experiments (median over IMUs/axes) {np.median(bg.std(0, ddof=1)):.3g} °/s; "
          f"reported std {np.median(np.stack([e.gyro_bias_std for e in intr])) * RAD_TO_DEG:.2g} °/s")

    # g: the fit is invariant under (T, g) -> (cT, cg); show it on exp_1.
    a = estimate_intrinsics(recs[0], g=9.80665)
    b = estimate_intrinsics(recs[0], g=9.8185)
    c = 9.8185 / 9.80665
    print("\ng check on exp_1: fit with g = 9.80665 vs 9.8185 (WGS84 normal gravity at 59.35° N, Stockholm):")
    print(f"  max |T(9.8185) - c T(9.80665)| = {np.abs(b.acc_matrix - c * a.acc_matrix).max():.2e}, "
          f"max |bias difference| = {np.abs(b.acc_bias - a.acc_bias).max():.2e} m/s², "
          f"residual RMS ratio {np.median(b.residual_rms / a.residual_rms):.6f} (c = {c:.6f})")
    print("  -> the rests cannot tell g; it only sets the overall scale of the corrected outputs.")
    for gg in (9.80665, 9.81, 9.8185):
        worst = max(np.abs(static_acc_errors(estimate_intrinsics(r, g=gg).apply(r), args.target)).max() for r in recs)
        print(f"  g = {gg}: worst self-calibrated rest error against {args.target}: {worst:.4f} m/s²")
    print(f"\nRESULT intrinsics_self_worst: {diag.max():.4f} m/s2")
    print(f"RESULT intrinsics_transfer_worst: {off.max():.4f} m/s2")


if __name__ == "__main__":
    main()

"""Starting values of a rig fit from the gyros alone: each IMU's orientation by Kabsch/Procrustes
on ω and its time offset by a search over lags (the conventional rig alignment, also what
``experiments/bench_rig.py`` runs as its peer)."""
from __future__ import annotations

import numpy as np

__all__ = ["kabsch", "align_gyros", "interp_rows"]


def kabsch(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Rotation R minimising Σ‖b_i − R a_i‖² over rotations (a, b: (N, 3)); returns (R, that sum)."""
    H = a.T @ b
    U, _, Vt = np.linalg.svd(H)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, float(((b - a @ R.T) ** 2).sum())


def interp_rows(t_new: np.ndarray, t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Linear interpolation of each column of y (N, c) sampled at t onto t_new (held at the ends)."""
    return np.stack([np.interp(t_new, t, y[:, i]) for i in range(y.shape[1])], -1)


def align_gyros(t_ref, w_ref, t_k, w_k, *, max_lag: float = 0.015, step: float = 5e-4):
    """Orientation and lag of IMU k's gyro against the reference's, both as readings at stamps.

    Model: w_k(s) = R ω_ref(s + o) (o > 0: k samples late).  For each lag on a grid over ±max_lag
    (s) the best R is Kabsch's; the lag with the least residual is refined by a parabola through its
    neighbours.  Returns (R (3, 3), o (s)).  Only the moving samples (|ω| above its 30th
    percentile) are used: rests carry neither orientation nor lag.
    """
    grid = np.arange(t_ref[0] + max_lag, t_ref[-1] - max_lag, step / 2)
    wr = interp_rows(grid, t_ref, w_ref)
    keep = np.linalg.norm(wr, axis=1) > np.percentile(np.linalg.norm(wr, axis=1), 30)
    lags = np.arange(-max_lag, max_lag + step / 2, step)
    cost, rots = [], []
    for lag in lags:
        wk = interp_rows(grid - lag, t_k, w_k)
        R, c = kabsch(wr[keep], wk[keep])
        cost.append(c), rots.append(R)
    cost = np.asarray(cost)
    i = int(np.argmin(cost))
    o = lags[i]
    if 0 < i < len(lags) - 1:
        c0, c1, c2 = cost[i - 1], cost[i], cost[i + 1]
        den = c0 - 2 * c1 + c2
        if den > 0:
            o = lags[i] + 0.5 * step * (c0 - c2) / den
    wk = interp_rows(grid - o, t_k, w_k)
    R, _ = kabsch(wr[keep], wk[keep])
    return R, float(o)

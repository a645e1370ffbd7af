"""The mismatch report's figures (:class:`accel_bayes.mismatch.report.MismatchReport`): residual
excess per IMU and channel, χ²/n per motion regime, and before/after a refined model.

The mismatch package imports this module inside functions only, so that importing
``accel_bayes.mismatch`` loads no matplotlib.  Figures are made without pyplot
(:func:`accel_bayes.diagnostics.plots.subplots`).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..data.outputs import save_figure
from .plots import subplots

__all__ = ["plot_residual_heatmap", "plot_residual_regimes", "plot_before_after", "save_mismatch_figures"]


def _mismatch_panels(location, location_after):
    panels = [("baseline", location)]
    if location_after is not None:
        panels.append(("refined", location_after))
    return panels


def plot_residual_heatmap(location, location_after=None, *, channels, K: int | None = None):
    """Residual excess z = (χ² − n)/√(2n) per IMU (rows) and channel (columns), baseline and,
    when given, refined.  ``location``: a :class:`accel_bayes.mismatch.locate.Location`."""
    K = location.heat.shape[0] if K is None else int(K)
    panels = _mismatch_panels(location, location_after)
    fig, axes = subplots(1, len(panels), figsize=(4.2 * len(panels) + 1, 0.35 * K + 2), squeeze=False)
    vmax = max(3.0, float(np.nanmax(np.abs(location.heat))))
    for ax, (title, loc) in zip(axes[0], panels):
        im = ax.imshow(loc.heat, cmap="RdBu_r", vmin=-vmax, vmax=vmax, aspect="auto")
        ax.set_xticks(range(len(channels)), channels, rotation=45, ha="right")
        ax.set_yticks(range(K), [str(k) for k in range(K)])
        ax.set_ylabel("IMU")
        ax.set_title(f"{title}: residual excess z")
    fig.colorbar(im, ax=axes[0].tolist(), label="(χ² − n)/√(2n)")
    return fig


def plot_residual_regimes(location, location_after=None):
    """χ²/n (all IMUs) per motion-regime bin, one panel per regime scheme (time last)."""
    panels = _mismatch_panels(location, location_after)
    schemes = [s for s in location.regimes if s != "time"] + ["time"]
    fig, axes = subplots(1, len(schemes), figsize=(3.3 * len(schemes), 3.4), squeeze=False)
    for ax, sch in zip(axes[0], schemes):
        for i, (title, loc) in enumerate(panels):
            rows = loc.regimes.get(sch, [])
            x = np.arange(len(rows))
            ax.bar(x + 0.4 * i - 0.2 * (len(panels) - 1), [r["chi2_ratio"] for r in rows], width=0.4, label=title)
            ax.set_xticks(x, [r["bin"].replace(sch, "").strip() or r["bin"] for r in rows], rotation=60,
                          ha="right", fontsize=7)
        ax.axhline(1.0, color="k", lw=0.8)
        ax.set_title(sch, fontsize=9)
    axes[0][0].set_ylabel("χ²/n (all IMUs)")
    axes[0][-1].legend(fontsize=7)
    return fig


def plot_before_after(location, location_after, positions_baseline, positions_refined):
    """χ²/n per IMU and sensor before/after, and the position change refined − baseline (µm);
    positions (K, 3) m."""
    panels = _mismatch_panels(location, location_after)
    pb = np.asarray(positions_baseline, dtype=np.float64)
    K = pb.shape[0]
    fig, (a1, a2) = subplots(1, 2, figsize=(10, 3.6))
    for i, (title, loc) in enumerate(panels):
        rows = [r for r in loc.imus]
        lab = [f"{r['imu']}{r['sensor'][0]}" for r in rows]
        a1.bar(np.arange(len(rows)) + 0.4 * i - 0.2, [r["chi2_ratio"] for r in rows], width=0.4, label=title)
    a1.set_xticks(range(len(lab)), lab, rotation=90, fontsize=7)
    a1.axhline(1.0, color="k", lw=0.8)
    a1.set_ylabel("χ²/n per IMU (a = acc, g = gyro)")
    a1.legend(fontsize=8)
    d = (np.asarray(positions_refined, dtype=np.float64) - pb) * 1e6
    a2.bar(np.arange(K) - 0.25, d[:, 0], width=0.25, label="x")
    a2.bar(np.arange(K), d[:, 1], width=0.25, label="y")
    a2.bar(np.arange(K) + 0.25, d[:, 2], width=0.25, label="z")
    a2.set_xlabel("IMU")
    a2.set_ylabel("position change refined − baseline (µm)")
    a2.legend(fontsize=8)
    return fig


def save_mismatch_figures(out, location, location_after=None, *, channels, K: int | None = None,
                          positions_baseline=None, positions_refined=None, dpi: int = 110) -> dict:
    """Write the mismatch report's figures into ``out``: residual_heatmap.png, residual_regimes.png
    and, with a refined model (``location_after`` and both positions), before_after.png.
    Returns {"heatmap", "regimes"[, "before_after"]: path}."""
    out = Path(out)
    jobs = [("heatmap", "residual_heatmap.png",
             lambda: plot_residual_heatmap(location, location_after, channels=channels, K=K)),
            ("regimes", "residual_regimes.png", lambda: plot_residual_regimes(location, location_after))]
    if location_after is not None and positions_refined is not None:
        jobs.append(("before_after", "before_after.png",
                     lambda: plot_before_after(location, location_after, positions_baseline, positions_refined)))
    paths = {}
    for key, name, fn in jobs:
        p = out / name
        save_figure(fn(), p, dpi=dpi, bbox_inches="tight")
        paths[key] = p
    return paths

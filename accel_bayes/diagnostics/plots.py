"""The posterior's figures and the [S16] convergence plot.

Each function returns a ``matplotlib.figure.Figure`` made without pyplot (:func:`subplots`), so that
neither importing this module nor plotting switches the caller's matplotlib backend; files are
written with Agg by :func:`accel_bayes.data.outputs.save_figure`.

* ArviZ's plots, laid out here and drawn by :func:`accel_bayes.diagnostics.arviz_calls.draw`:
  :func:`plot_trace`, :func:`plot_rank`, :func:`plot_autocorr`.
* The board: :func:`plot_ellipses` ([C21] Fig. 5), :func:`plot_offsets` (each triad's offset from its
  nominal position), :func:`auto_exaggeration`; :func:`save_plots` writes the four PNGs of
  ``calibrate``.
* :func:`plot_convergence` — [S16] Fig. 5: the self-calibration's cost per LM iteration.

Units: positions in metres in the data; plots draw millimetres.
"""
from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Ellipse, Rectangle

from ..data.outputs import save_figure
from ..errors import UserError
from .arviz_calls import VAR, as_numpy, draw
from .stats import posterior_moments

__all__ = ["subplots", "plot_trace", "plot_rank", "plot_autocorr", "plot_ellipses", "plot_offsets",
           "auto_exaggeration", "save_plots", "plot_convergence"]


def subplots(nrows=1, ncols=1, *, figsize, squeeze=True, layout="constrained", **kw):
    """``plt.subplots`` without pyplot: the figure belongs to no backend and no pyplot registry
    (nothing to close), and :func:`~accel_bayes.data.outputs.save_figure` renders it with Agg.
    Constrained layout by default, so that no title or label is clipped or overlaps."""
    fig = Figure(figsize=figsize, layout=layout)
    return fig, fig.subplots(nrows, ncols, squeeze=squeeze, **kw)


def _arviz_axes(idata, max_imus, ncols: int, row_height: float, *, trace: bool = False, **kw):
    """The coordinates to plot, a grid of axes for them and its figure size (ArviZ would otherwise
    make its figure with pyplot; it scales its fonts to the size): one axes per coordinate of r,
    ``ncols`` per row, or for a trace plot one row of (density, trace) per coordinate.  Width
    11 in; ``row_height`` in inches; ``kw`` to ``Figure.subplots`` (e.g. shared axes)."""
    coords = _coords_subset(idata, max_imus)
    n_imu = len(coords["imu"]) if coords else idata.posterior[VAR].sizes["imu"]
    n = n_imu * idata.posterior[VAR].sizes["axis"]
    rows, cols = (n, 2) if trace else (-(-n // ncols), ncols)
    figsize = (11.0, row_height * rows + 0.8)
    _, axes = subplots(rows, cols, figsize=figsize, squeeze=False, **kw)
    for a in axes.ravel()[n if not trace else axes.size:]:
        a.set_visible(False)
    return coords, axes, figsize


def _coords_subset(idata, max_imus):
    labels = [int(k) for k in idata.posterior[VAR].coords["imu"].values]
    if max_imus is None or len(labels) <= max_imus:
        return None
    return {"imu": labels[:max_imus]}


def plot_trace(idata, max_imus: int | None = 2, **kwargs):
    """Trace and marginal density per coordinate (``az.plot_trace``), mm; the first
    ``max_imus`` free IMUs only (None: all)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 2, 1.9, trace=True)
    axes = draw("trace", idata, axes, coords=coords, figsize=size, **kwargs)
    fig = np.ravel(axes)[0].figure
    fig.suptitle("PmMH trace, r relative to the reference triad [mm]")
    return fig


def plot_rank(idata, max_imus: int | None = 2, **kwargs):
    """Rank plots per coordinate (``az.plot_rank``): uniform bars when chains agree."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 3, 2.6)
    axes = draw("rank", idata, axes, coords=coords, figsize=size, **kwargs)
    return np.ravel(axes)[0].figure


def plot_autocorr(idata, max_imus: int | None = 2, **kwargs):
    """Autocorrelation per coordinate, chains combined (``az.plot_autocorr``), [C21] Fig. 3b."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 3, 2.4, sharex=True, sharey=True)  # as ArviZ shares them
    axes = draw("autocorr", idata, axes, coords=coords, figsize=size, **kwargs)
    return np.ravel(axes)[0].figure


def _chi2_2_quantile(level: float) -> float:
    """Quantile of χ²₂: the squared Mahalanobis radius of a 2-D Gaussian ellipse with
    probability ``level``."""
    return -2.0 * math.log(1.0 - level)


def _ellipse(ax, mean2, cov2, level, **kw):
    vals, vecs = np.linalg.eigh(cov2)
    vals = np.clip(vals, 0.0, None)
    k = math.sqrt(_chi2_2_quantile(level))
    w, h = 2 * k * np.sqrt(vals[::-1])
    ang = math.degrees(math.atan2(vecs[1, -1], vecs[0, -1]))
    ax.add_patch(Ellipse(mean2, w, h, angle=ang, fill=False, **kw))


def _moments(idata_or_moments):
    if hasattr(idata_or_moments, "posterior"):
        return posterior_moments(idata_or_moments)
    if isinstance(idata_or_moments, dict):
        m = idata_or_moments
        return {"imu": [int(k) for k in m["imu"]], "mean": np.asarray(as_numpy(m["mean"])),
                "cov": np.asarray(as_numpy(m["cov"]))}
    raise UserError("idata_or_moments: expected an InferenceData or a dict with 'imu', 'mean' (A-1, 3), "
                    "'cov' (A-1, 3, 3)")


def plot_ellipses(idata_or_moments, array, ax=None, level=0.5, prior_std=None, label=None, color="C0",
                  exaggerate: float = 1.0):
    """[C21] Fig. 5: x–y confidence ellipses of each free triad's position over the board.

    idata_or_moments : an InferenceData from :func:`~.arviz_calls.to_inference_data`, or a dict
        {"imu": labels, "mean": (A−1, 3) m, "cov": (A−1, 3, 3) m²} (e.g. a Laplace approximation),
        positions relative to the reference triad.
    array : :class:`~accel_bayes.physics.arrays.SensorArray` (or a Recording: its ``sensor_array()``) —
        nominal positions (the posterior is drawn at nominal_ref + r), package squares of side
        ``package_size`` around them; IMUs with nominal z ≥ 0 are the top side, z < 0 the bottom
        side, each in its own panel when both exist.
    ax : one Axes (everything drawn in it) or None (new figure, one panel per board side).
    level : probability of the ellipses, a float or a sequence (e.g. (0.5, 0.95)); Gaussian
        ellipses from the posterior mean and covariance of (x, y).
    prior_std : m — if given, the prior's ellipses (circles of radius √χ²₂(level)·σ) in cyan.
    exaggerate : k ≥ 1 draws each posterior's offset from its nominal position and its ellipses
        k times larger (packages stay at scale; the title says so) — posteriors of ~100 µm are
        invisible on a 20 mm board otherwise.
    Returns the Figure.
    """
    if hasattr(array, "sensor_array") and not hasattr(array, "package_size"):
        array = array.sensor_array()
    mom = _moments(idata_or_moments)
    k_ex = float(exaggerate)
    if not k_ex >= 1.0:
        raise UserError(f"exaggerate: expected a factor >= 1, got {exaggerate}")
    levels = [float(level)] if np.isscalar(level) else [float(v) for v in level]
    for lv in levels:
        if not 0.0 < lv < 1.0:
            raise UserError(f"level: expected probabilities in (0, 1), got {lv}")
    nominal = np.asarray(as_numpy(array.positions), dtype=float) * 1e3  # mm
    labels = list(getattr(array, "labels", range(len(nominal)))) or list(range(len(nominal)))
    ref = int(array.reference_imu)
    ref_pos = nominal[ref]
    top = nominal[:, 2] >= 0
    sides = [("top side", top), ("bottom side", ~top)]
    sides = [(nm, m) for nm, m in sides if m.any()]
    if ax is None:
        fig, axes = subplots(1, len(sides), figsize=(5.5 * len(sides), 5.5), squeeze=False)
        axes = list(axes[0])
    else:
        fig = ax.figure
        axes = [ax] * len(sides)
    pkg = getattr(array, "package_size", None)
    styles = ["-", "--", ":", "-."]
    for (side_name, mask), a in zip(sides, axes):
        for k in np.flatnonzero(mask):
            x, y = nominal[k, :2]
            if pkg:
                s = pkg * 1e3
                a.add_patch(Rectangle((x - s / 2, y - s / 2), s, s, fill=False, ls="--", lw=0.8, color="0.5"))
                a.plot([x - s / 2, x + s / 2], [y, y], ls=":", lw=0.5, color="0.7")
                a.plot([x, x], [y - s / 2, y + s / 2], ls=":", lw=0.5, color="0.7")
            a.annotate(str(labels[k]), (x, y), textcoords="offset points", xytext=(4, 4), fontsize=7, color="0.3")
            if k == ref:
                a.plot([x], [y], marker="*", ms=10, color="k", ls="none")
            if prior_std is not None and k != ref:
                for lv, st in zip(levels, styles):
                    rr = k_ex * float(prior_std) * 1e3 * math.sqrt(_chi2_2_quantile(lv))
                    a.add_patch(Ellipse((x, y), 2 * rr, 2 * rr, fill=False, color="c", ls=st, lw=0.8))
        for i, lab in enumerate(mom["imu"]):
            if lab >= len(nominal) or not mask[lab]:
                continue
            m = nominal[lab, :2] + k_ex * (ref_pos[:2] + mom["mean"][i, :2] * 1e3 - nominal[lab, :2])
            cv = mom["cov"][i, :2, :2] * 1e6 * k_ex**2
            a.plot([m[0]], [m[1]], marker=".", color=color, ls="none")
            for lv, st in zip(levels, styles):
                _ellipse(a, m, cv, lv, color=color, ls=st, lw=1.0)
        a.set_aspect("equal", adjustable="datalim")  # the panel fills its place: no title pushed off the figure
        scale = _board_scale(array)
        if scale:  # the board, not the (much wider) prior, sets the view
            sel = nominal[mask]
            pad = 1.25 * scale * 1e3
            a.set_xlim(sel[:, 0].min() - pad, sel[:, 0].max() + pad)
            a.set_ylim(sel[:, 1].min() - pad, sel[:, 1].max() + pad)
        else:
            a.autoscale_view()
        a.set_xlabel("x [mm]")
        a.set_ylabel("y [mm]")
        a.set_title(f"{side_name}: " + ", ".join(f"{int(round(lv * 100))} %" for lv in levels)
                    + " ellipses" + (f" ({label})" if label else "")
                    + (f"\noffsets from nominal and ellipses ×{k_ex:g}" if k_ex != 1.0 else ""))
        a.grid(True, lw=0.3)
    if ax is not None:  # the caller's figure; ours are laid out by constrained layout
        fig.tight_layout()
    return fig


def plot_offsets(idata_or_moments, array, truth=None, level=(0.5, 0.95), prior_std=None):
    """Each free triad's position as its offset from its nominal (design) position: one panel per
    IMU, x–y in mm on axes shared by all panels (so ellipses compare at a glance), with the
    posterior mean, its Gaussian ellipses at ``level`` and, where known, the truth; the z offset
    (mean ± std, mm) in the panel's title; a legend; laid out so that nothing is clipped.

    idata_or_moments, array : as :func:`plot_ellipses` (positions relative to the reference triad,
        m; nominal positions from ``array``).
    truth : (K, 3) true positions relative to the reference triad, m, one row per IMU label (a
        simulation's), or None.
    level : probability of the ellipses, a float or a sequence (solid, dashed, dotted, …).
    prior_std : m — the prior's std, named in the title (its circles, millimetres wide, would
        dwarf the panels).
    Returns the Figure.
    """
    if hasattr(array, "sensor_array") and not hasattr(array, "package_size"):
        array = array.sensor_array()
    from matplotlib.lines import Line2D
    from matplotlib.ticker import MaxNLocator

    mom = _moments(idata_or_moments)
    levels = [float(level)] if np.isscalar(level) else [float(v) for v in level]
    for lv in levels:
        if not 0.0 < lv < 1.0:
            raise UserError(f"level: expected probabilities in (0, 1), got {lv}")
    nominal = np.asarray(as_numpy(array.positions), dtype=float)
    ref = int(array.reference_imu)
    rows = [(i, lab) for i, lab in enumerate(mom["imu"]) if lab < len(nominal) and lab != ref]
    if not rows:
        raise UserError("idata_or_moments: no free IMU of the array to plot")
    tru = None if truth is None else np.asarray(as_numpy(truth), dtype=float)
    nom_rel = (nominal - nominal[ref]) * 1e3  # mm, relative to the reference like the posterior
    off = {lab: mom["mean"][i] * 1e3 - nom_rel[lab] for i, lab in rows}
    cov = {lab: mom["cov"][i] * 1e6 for i, lab in rows}
    t_off = {lab: tru[lab] * 1e3 - nom_rel[lab] for _, lab in rows} if tru is not None else {}
    k_out = math.sqrt(_chi2_2_quantile(max(levels)))
    half = max(max(np.abs(off[lab][:2]).max() + k_out * math.sqrt(max(np.linalg.eigvalsh(cov[lab][:2, :2])[-1], 0))
                   for _, lab in rows),
               max((np.abs(t[:2]).max() for t in t_off.values()), default=0.0))
    half = 1.15 * half if half > 0 else 1.0
    n = len(rows)
    ncols = n if n <= 4 else 4 if n <= 8 else 6 if n <= 18 else 8
    nrows = -(-n // ncols)
    fig, axes = subplots(nrows, ncols, figsize=(3.0 * ncols + 0.5, 3.2 * nrows + 1.4), squeeze=False,
                          sharex=True, sharey=True)
    styles = ["-", "--", ":", "-."]
    for a, (_, lab) in zip(axes.ravel(), rows):
        m, c = off[lab], cov[lab]
        a.axhline(0.0, color="0.8", lw=0.6)
        a.axvline(0.0, color="0.8", lw=0.6)
        a.plot([0.0], [0.0], marker="+", ms=9, color="k", ls="none")
        for lv, st in zip(levels, styles):
            _ellipse(a, m[:2], c[:2, :2], lv, color="C0", ls=st, lw=1.2)
        a.plot([m[0]], [m[1]], marker="o", ms=4, color="C0", ls="none")
        title = f"IMU {lab}\nΔz {m[2]:+.3f} ± {math.sqrt(max(c[2, 2], 0)):.3f}"
        if lab in t_off:
            t = t_off[lab]
            a.plot([t[0]], [t[1]], marker="x", ms=7, mew=1.8, color="C3", ls="none")
            title += f" (true {t[2]:+.3f})"
        a.set_title(title, fontsize=9)
        a.set_xlim(-half, half)
        a.set_ylim(-half, half)
        a.set_aspect("equal")
        a.grid(True, lw=0.3)
        a.tick_params(labelsize=8)
        for axis in (a.xaxis, a.yaxis):  # few ticks: the labels of narrow panels must not run together
            axis.set_major_locator(MaxNLocator(nbins=4, symmetric=True))
    for a in axes.ravel()[n:]:
        a.set_visible(False)
    for a in axes[:, 0]:
        a.set_ylabel("Δy [mm]")
    for j in range(ncols):  # the lowest visible panel of each column carries the x label
        col = [a for a in axes[:, j] if a.get_visible()]
        if col:
            col[-1].set_xlabel("Δx [mm]")
            col[-1].xaxis.set_tick_params(labelbottom=True)
    handles = [Line2D([], [], marker="+", ms=9, color="k", ls="none", label="nominal (design) position"),
               Line2D([], [], marker="o", ms=4, color="C0", ls="none", label="posterior mean")]
    handles += [Line2D([], [], color="C0", ls=st, lw=1.2, label=f"{int(round(lv * 100))} % ellipse")
                for lv, st in zip(levels, styles)]
    if t_off:
        handles.append(Line2D([], [], marker="x", ms=7, mew=1.8, color="C3", ls="none", label="truth"))
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8.5, frameon=False)
    sup = f"Triad positions relative to reference IMU {ref}: offset from the nominal position, mm (Δz in each title)"
    if prior_std is not None:
        sup += f"\nprior: Gaussian around the nominal position, std {float(prior_std) * 1e3:g} mm per axis"
    fig.suptitle(sup, fontsize=10)
    return fig


def _board_scale(array) -> float | None:
    """Length (m) that sets the picture's scale: the package side, or — for arrays without one,
    e.g. built from a recording — half the smallest x–y spacing of distinct nominal positions."""
    pkg = getattr(array, "package_size", None)
    if pkg:
        return float(pkg)
    xy = np.unique(np.round(np.asarray(as_numpy(array.positions), dtype=float)[:, :2], 9), axis=0)
    if len(xy) < 2:
        return None
    d = np.sqrt(((xy[:, None, :] - xy[None, :, :]) ** 2).sum(-1))
    d = d[d > 0]
    return float(d.min()) / 2 if d.size else None


def auto_exaggeration(idata_or_moments, array, fraction: float = 0.25) -> float:
    """A round factor (1, 2, 5, 10, 20, …) that makes the typical 95 % ellipse about
    ``fraction`` of a package side (or of half the IMU spacing when the package size is unknown),
    limited so that no exaggerated offset from a nominal position exceeds 0.45 of that length;
    1 when no magnification is needed or possible."""
    if hasattr(array, "sensor_array") and not hasattr(array, "package_size"):
        array = array.sensor_array()
    scale = _board_scale(array)
    mom = _moments(idata_or_moments)
    if not scale or len(mom["imu"]) == 0:
        return 1.0
    sd = np.sqrt(np.clip(np.linalg.eigvalsh(mom["cov"][:, :2, :2])[:, -1], 0, None))
    semi = float(np.median(sd)) * math.sqrt(_chi2_2_quantile(0.95))
    if semi <= 0:
        return 1.0
    want = fraction * scale / semi
    # ...but never push an estimate out of its own patch of the board: offsets from the nominal
    # positions (relative to the reference) times k stay under 0.45 of the scale length
    nominal = np.asarray(as_numpy(array.positions), dtype=float)
    ref = int(array.reference_imu)
    idx = [lab for lab in mom["imu"] if lab < len(nominal)]
    if idx:
        rel_nom = nominal[idx, :2] - nominal[ref, :2]
        off = float(np.abs(mom["mean"][: len(idx), :2] - rel_nom).max())
        if off > 0:
            want = min(want, 0.45 * scale / off)
    if want <= 1:
        return 1.0
    steps = [m * 10**e for e in range(0, 7) for m in (1, 2, 5)]
    return float(max(s for s in steps if s <= want))


def save_plots(idata, array, outdir, prior_std=None, max_imus: int | None = 2, dpi: int = 110,
               truth=None) -> list[Path]:
    """Write trace.png, rank.png, autocorr.png and ellipses.png (:func:`plot_offsets`: each
    triad's offset from its nominal position with its 50 % and 95 % ellipses, and ``truth`` —
    (K, 3) m relative to the reference, a simulation's — where given) to ``outdir``; returns their
    paths."""
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, fn in (("trace", lambda: plot_trace(idata, max_imus=max_imus)),
                     ("rank", lambda: plot_rank(idata, max_imus=max_imus)),
                     ("autocorr", lambda: plot_autocorr(idata, max_imus=max_imus)),
                     ("ellipses", lambda: plot_offsets(idata, array, truth=truth, level=(0.5, 0.95),
                                                       prior_std=prior_std))):
        paths.append(save_figure(fn(), out / f"{name}.png", dpi=dpi))
    return paths


# ============================================================================ [S16] self-calibration

def plot_convergence(cost_log: list, n_constraints: dict, path, title: str = "") -> Path:
    """[S16] Fig. 5 style: F / number of constraints vs LM iteration (log scale), total and per
    constraint type (triad, process), the stages and runs laid end to end and marked.  Writes
    ``path`` atomically and returns it."""
    x = np.arange(len(cost_log), dtype=float)  # attempts laid end to end over stages and runs
    run = [e.get("run", "first") for e in cost_log]
    n_all = n_constraints["triad"] + n_constraints["process"]
    tot = np.array([e["F"] for e in cost_log]) / n_all
    tri = np.array([e["F_triad"] for e in cost_log]) / n_constraints["triad"]
    pro = np.array([e["F_process"] for e in cost_log]) / max(n_constraints["process"], 1)
    fig, ax = subplots(figsize=(6.4, 4.0))
    pos = lambda v: np.where(v > 0, v, np.nan)  # noqa: E731  (zero process cost at a zero-motion start)
    ax.semilogy(x, pos(tot), "k-", lw=2, label="F / all constraints")
    ax.semilogy(x, pos(tri), "C0--", label="triad part / triad constraints")
    ax.semilogy(x, pos(pro), "C1:", label="process part / process constraints")
    stage = [e.get("stage", "joint") for e in cost_log]
    for i in range(1, len(x)):
        if stage[i] != stage[i - 1] or run[i] != run[i - 1]:
            ax.axvline(x[i] - 0.5, color="0.7", lw=0.8)
    for i in range(len(x)):
        if i == 0 or stage[i] != stage[i - 1] or run[i] != run[i - 1]:
            ax.annotate(f"{run[i]}: {stage[i]}", (x[i], 1.0), xycoords=("data", "axes fraction"), fontsize=7,
                        va="top", ha="left", rotation=90, xytext=(2, -2), textcoords="offset points")
    ax.set_xlabel("LM iteration (all stages and runs, end to end)")
    ax.set_ylabel("F / number of constraints")
    ax.set_title(title or "self-calibration convergence ([S16] Fig. 5)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return save_figure(fig, path, dpi=120)

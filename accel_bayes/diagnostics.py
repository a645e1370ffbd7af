"""Posterior diagnostics with ArviZ: data, statistics and plots kept apart (as ArviZ does).

Every ArviZ call of the package lives in this module, so a move to ArviZ 1.x is one change.

* Data: :func:`to_inference_data` turns PmMH draws into an ``az.InferenceData`` (posterior
  variable ``r`` with dims ("imu", "axis"), sample statistics, the log-likelihood estimates);
  :func:`save` / :func:`load` write and read it as NetCDF (h5netcdf engine).
* Statistics: :func:`summarize` (R̂, bulk/tail ESS, MCSE: ``az.summary``), :func:`rhat_max`,
  :func:`ess_bulk_min`, :func:`posterior_moments`; :func:`convergence_check` (the one rule for
  "converged": every coordinate with R̂ < 1.01 and bulk and tail ESS ≥ 400, thresholds
  adjustable; used by ``calibrate`` to decide when to stop and for its exit status),
  :func:`convergence_warnings` (the older max-R̂ / min-bulk-ESS form), :func:`format_stat`.
* Plots (each returns a ``matplotlib.figure.Figure`` made without pyplot, so that neither importing
  this module nor plotting switches the caller's matplotlib backend; saved with Agg): :func:`plot_trace`,
  :func:`plot_rank`, :func:`plot_autocorr`, :func:`plot_ellipses` ([C21] Fig. 5: the board),
  :func:`plot_offsets` (each triad's offset from its nominal position) and :func:`save_plots`.
* Model mismatch (last section): :func:`psis_loo`, :func:`compare_loo` and the mismatch
  report's figures (:func:`save_mismatch_figures`).

Units: positions in metres in the data; plots draw millimetres.
"""
from __future__ import annotations

import contextlib
import logging
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)  # arviz 0.23 announces its 1.0 refactor
    import arviz as az

from matplotlib.figure import Figure
from matplotlib.patches import Ellipse, Rectangle

from .constants import ESS_PER_CHAIN, RHAT_MAX
from .errors import UserError
from .data.outputs import save_figure

__all__ = [
    "truth_check",
    "to_inference_data",
    "summarize",
    "rhat_max",
    "ess_bulk_min",
    "convergence_warnings",
    "convergence_check",
    "ConvergenceCheck",
    "RHAT_MAX",
    "ESS_MIN",
    "format_stat",
    "posterior_moments",
    "save",
    "load",
    "plot_trace",
    "plot_rank",
    "plot_autocorr",
    "plot_ellipses",
    "plot_offsets",
    "save_plots",
    "auto_exaggeration",
    "AXES",
    # model mismatch (section at the end of the module)
    "psis_loo",
    "compare_loo",
    "plot_residual_heatmap",
    "plot_residual_regimes",
    "plot_before_after",
    "save_mismatch_figures",
]

AXES = ("x", "y", "z")
VAR = "r"


def _np(x):
    if x is None:
        return None
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def to_inference_data(
    draws,
    imu_labels,
    log_phat=None,
    *,
    log_prior=None,
    accepted=None,
    accept_prob=None,
    step_size=None,
    pointwise_log_lik=None,
    reference_imu: int | None = None,
    attrs: dict | None = None,
) -> "az.InferenceData":
    """PmMH draws → ``az.InferenceData``.

    draws : (C, D, A−1, 3) m — θ, positions of the free triads relative to the reference triad,
        array frame.  Posterior variable ``r`` with dims ("chain", "draw", "imu", "axis"),
        coords imu = ``imu_labels`` (the A−1 free IMU labels), axis = x, y, z.
    log_phat : (C, D) — the cached estimate log p̂(y | θ) of each draw (stored as sample stat
        ``log_phat`` and as the log-likelihood group's ``y``, a whole-data-set estimate).
    log_prior : (C, D) — log p(θ); with log_phat it gives sample stat ``lp`` = log p̂ + log p.
    accepted : (C, D) bool — sample stat ``accept`` (the move into this draw was accepted).
    accept_prob : (C, D) — min(1, α) of that move (sample stat ``acceptance_rate``, ArviZ's name).
    step_size : (C,) — the frozen σ_q per chain (sample stat ``step_size``).
    pointwise_log_lik : (C, D, T) optional per-sample contributions (log-likelihood ``y`` with a
        "time" dim instead of the total).
    reference_imu, attrs : stored as posterior attributes (plain values only).
    """
    x = _np(draws)
    if x is None or x.ndim != 4 or x.shape[-1] != 3:
        raise UserError(f"draws: expected shape (chains, draws, A-1, 3), got {None if x is None else x.shape}")
    C, D, Af, _ = x.shape
    labels = [int(k) for k in imu_labels]
    if len(labels) != Af:
        raise UserError(f"imu_labels: expected {Af} labels (one per free triad), got {len(labels)}")

    def cd(name, v):
        v = _np(v)
        if v is None:
            return None
        if v.shape != (C, D):
            raise UserError(f"{name}: expected shape ({C}, {D}), got {v.shape}")
        return v

    stats = {}
    lphat = cd("log_phat", log_phat)
    lprior = cd("log_prior", log_prior)
    if lphat is not None:
        stats["log_phat"] = lphat.astype(np.float64)
        stats["lp"] = lphat + (lprior if lprior is not None else 0.0)
    if lprior is not None:
        stats["log_prior"] = lprior.astype(np.float64)
    acc = cd("accepted", accepted)
    if acc is not None:
        stats["accept"] = acc.astype(bool)
    ap = cd("accept_prob", accept_prob)
    if ap is not None:
        stats["acceptance_rate"] = ap.astype(np.float64)
    if step_size is not None:
        s = _np(step_size).reshape(C, 1)
        stats["step_size"] = np.broadcast_to(s, (C, D)).astype(np.float64).copy()

    loglik = None
    dims = {VAR: ["imu", "axis"]}
    coords = {"imu": labels, "axis": list(AXES)}
    if pointwise_log_lik is not None:
        pw = _np(pointwise_log_lik)
        if pw.ndim != 3 or pw.shape[:2] != (C, D):
            raise UserError(f"pointwise_log_lik: expected shape ({C}, {D}, T), got {pw.shape}")
        loglik = {"y": pw}
        dims["y"] = ["time"]
        coords["time"] = np.arange(pw.shape[-1])
    elif lphat is not None:
        loglik = {"y": lphat.astype(np.float64)}
    at = {"accel_bayes_variable": "r = triad position relative to the reference triad, array frame, m"}
    if reference_imu is not None:
        at["reference_imu"] = int(reference_imu)
    for k, v in (attrs or {}).items():
        if isinstance(v, (bool, np.bool_)):
            at[k] = int(v)
        elif isinstance(v, (int, float, str, np.integer, np.floating)):
            at[k] = v
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        idata = az.from_dict(posterior={VAR: x}, sample_stats=stats or None, log_likelihood=loglik,
                             dims=dims, coords=coords)
    idata.posterior.attrs.update(at)
    return idata


# ---------------------------------------------------------------------------- statistics

@contextlib.contextmanager
def _arviz_quiet():
    """Silence ArviZ's logger ("Shape validation failed" for one chain): the NaN it returns is
    reported by :func:`convergence_warnings`, and the command line keeps stderr to one line."""
    # ArviZ 0.x logs through its own Logger instance, not one registered with logging.getLogger
    log = getattr(az, "_log", None) or logging.getLogger("arviz")
    level = log.level
    log.setLevel(logging.ERROR)
    try:
        yield
    finally:
        log.setLevel(level)


def summarize(idata, var_names=(VAR,), round_to=None):
    """``az.summary`` of the posterior: mean, sd, HDI, MCSE of mean and sd, bulk/tail ESS, R̂ —
    one row per coordinate ``r[imu, axis]`` (metres)."""
    with warnings.catch_warnings(), _arviz_quiet():
        warnings.simplefilter("ignore")
        return az.summary(idata, var_names=list(var_names), kind="all",
                          round_to="none" if round_to is None else round_to)


def rhat_max(idata, var_name: str = VAR) -> float:
    """Largest rank-normalised split R̂ over all coordinates (NaN with one chain too short)."""
    with warnings.catch_warnings(), _arviz_quiet():
        warnings.simplefilter("ignore")
        v = az.rhat(idata, var_names=[var_name])[var_name].values
    return float(np.nanmax(v)) if np.isfinite(v).any() else float("nan")


def ess_bulk_min(idata, var_name: str = VAR) -> float:
    """Smallest bulk ESS over all coordinates."""
    with warnings.catch_warnings(), _arviz_quiet():
        warnings.simplefilter("ignore")
        v = az.ess(idata, var_names=[var_name], method="bulk")[var_name].values
    return float(np.nanmin(v)) if np.isfinite(v).any() else float("nan")


# Vehtari, Gelman, Simpson, Carpenter & Bürkner (2021), "Rank-normalization, folding, and
# localization: an improved R̂", §4: R̂ < 1.01 and bulk ESS > 100 per chain before trusting moments.
RHAT_LIMIT = 1.01


def convergence_warnings(rhat: float | None, ess_bulk: float | None, chains: int) -> list[str]:
    """Why PmMH chains cannot be trusted yet, one sentence each; ``[]`` when they can — the older
    summary form of the rule (max R̂, min bulk ESS, 100 per chain); ``calibrate`` decides with
    :func:`convergence_check` (every coordinate, bulk and tail ESS).

    rhat : largest split R̂ (:func:`rhat_max`); ess_bulk : smallest bulk ESS (:func:`ess_bulk_min`),
    draws; chains : number of chains.  None or NaN (too few draws to compute the statistic) counts
    as not converged: convergence that cannot be checked is not established.
    """
    out = []
    need = ESS_PER_CHAIN * int(chains)
    if rhat is None or not math.isfinite(rhat):
        out.append("R-hat could not be computed (too few draws per chain)")
    elif rhat >= RHAT_LIMIT:
        out.append(f"max R-hat {rhat:.3f} >= {RHAT_LIMIT}")
    if ess_bulk is None or not math.isfinite(ess_bulk):
        out.append("bulk ESS could not be computed (too few draws per chain)")
    elif ess_bulk < need:
        out.append(f"min bulk ESS {ess_bulk:.0f} < {ESS_PER_CHAIN} per chain ({need} for {int(chains)})")
    return out


# Defaults of :func:`convergence_check` (Vehtari et al. 2021 §4: R̂ < 1.01 — RHAT_MAX, in
# constants — and bulk and tail ESS > 100 per chain, i.e. 400 for the 4 default chains of ``calibrate``).
ESS_MIN = 400.0


def _finite_or_none(v):
    v = float(v)
    return v if math.isfinite(v) else None


@dataclass
class ConvergenceCheck:
    """Outcome of :func:`convergence_check` on C chains × D draws.

    converged : every coordinate has R̂ < ``rhat_limit`` and bulk and tail ESS ≥ ``ess_min``
        (all three computable).
    failed : one human-readable sentence per failed criterion, naming the worst coordinate, its
        value, the threshold and how many coordinates fail (``[]`` when converged).
    rhat_max, ess_bulk_min, ess_tail_min : the worst values (NaN where not computable) and
    rhat_at, ess_bulk_at, ess_tail_at : the coordinates where they occur.
    chains, draws : C and D (draws per chain).
    """

    converged: bool
    failed: list = field(default_factory=list)
    rhat_max: float = float("nan")
    ess_bulk_min: float = float("nan")
    ess_tail_min: float = float("nan")
    rhat_at: str | None = None
    ess_bulk_at: str | None = None
    ess_tail_at: str | None = None
    rhat_limit: float = RHAT_MAX
    ess_min: float = ESS_MIN
    chains: int = 0
    draws: int = 0

    def as_dict(self) -> dict:
        """Plain JSON-ready values (NaN → None)."""
        return {"draws": int(self.draws), "chains": int(self.chains), "converged": bool(self.converged),
                "rhat_max": _finite_or_none(self.rhat_max), "rhat_at": self.rhat_at,
                "ess_bulk_min": _finite_or_none(self.ess_bulk_min), "ess_bulk_at": self.ess_bulk_at,
                "ess_tail_min": _finite_or_none(self.ess_tail_min), "ess_tail_at": self.ess_tail_at,
                "failed": list(self.failed)}

    def line(self) -> str:
        """One short line for a progress display."""
        return (f"{self.draws} draws/chain: max R-hat {format_stat(self.rhat_max, '.4f')}, min ESS bulk "
                f"{format_stat(self.ess_bulk_min, '.0f')} tail {format_stat(self.ess_tail_min, '.0f')}")

    def __str__(self) -> str:
        return self.line()


def convergence_check(theta_chains, rhat_max: float = RHAT_MAX, ess_min: float = ESS_MIN, names=None
                      ) -> ConvergenceCheck:
    """The convergence rule: every coordinate has rank-normalised split R̂ < ``rhat_max`` and bulk
    and tail ESS ≥ ``ess_min`` (ArviZ ``rhat`` and ``ess(method="bulk"/"tail")``).

    theta_chains : (C, D, ...) array or tensor of draws, C chains × D draws; the trailing
        dimensions are flattened into coordinates.
    rhat_max : R̂ threshold (> 1); a coordinate passes when R̂ < rhat_max.
    ess_min : ESS threshold, draws in total over the chains (ArviZ's ESS is pooled); a coordinate
        passes when its bulk and its tail ESS are ≥ ess_min.
    names : optional labels of the flattened coordinates (e.g. ``"r[3, y]"``) for the messages;
        default ``"coordinate j"``.

    A statistic that cannot be computed (NaN: too few draws) fails: convergence that cannot be
    checked is not established.  Returns a :class:`ConvergenceCheck`.
    """
    x = _np(theta_chains)
    if x is None or x.ndim < 2:
        raise UserError(f"theta_chains: expected an array (chains, draws, ...), got shape "
                        f"{None if x is None else x.shape}")
    rl, em = float(rhat_max), float(ess_min)
    if not (math.isfinite(rl) and rl > 1.0):
        raise UserError(f"rhat_max: expected a finite number > 1, got {rhat_max!r}")
    if not (math.isfinite(em) and em > 0):
        raise UserError(f"ess_min: expected a finite number > 0, got {ess_min!r}")
    C, D = int(x.shape[0]), int(x.shape[1])
    flat = np.asarray(x, dtype=np.float64).reshape(C, D, -1)
    P = flat.shape[-1]
    names = [f"coordinate {j}" for j in range(P)] if names is None else [str(n) for n in names]
    if len(names) != P:
        raise UserError(f"names: expected {P} coordinate labels, got {len(names)}")
    with warnings.catch_warnings(), _arviz_quiet(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        ds = az.convert_to_dataset({"x": flat}, dims={"x": ["coord"]})
        rh = np.asarray(az.rhat(ds)["x"].values, dtype=np.float64).reshape(P)
        eb = np.asarray(az.ess(ds, method="bulk")["x"].values, dtype=np.float64).reshape(P)
        et = np.asarray(az.ess(ds, method="tail")["x"].values, dtype=np.float64).reshape(P)
    failed = []
    out = ConvergenceCheck(converged=False, rhat_limit=rl, ess_min=em, chains=C, draws=D)
    # R̂: worst is the largest (NaN counts as worst)
    bad = ~(rh < rl)
    key = np.where(np.isfinite(rh), rh, np.inf)
    j = int(np.argmax(key))
    out.rhat_max, out.rhat_at = float(rh[j]), names[j]
    if bad.any():
        if not np.isfinite(rh[j]):
            failed.append(f"R-hat could not be computed at {names[j]} (too few draws per chain)")
        else:
            failed.append(f"R-hat {rh[j]:.4f} at {names[j]} >= {rl:g} ({int(bad.sum())} of {P} coordinates fail)")
    for kind, v in (("bulk", eb), ("tail", et)):
        bad = ~(v >= em)
        key = np.where(np.isfinite(v), v, -np.inf)
        j = int(np.argmin(key))
        setattr(out, f"ess_{kind}_min", float(v[j]))
        setattr(out, f"ess_{kind}_at", names[j])
        if bad.any():
            if not np.isfinite(v[j]):
                failed.append(f"{kind} ESS could not be computed at {names[j]} (too few draws per chain)")
            else:
                failed.append(f"{kind} ESS {v[j]:.0f} at {names[j]} < {em:g} ({int(bad.sum())} of {P} coordinates "
                              "fail)")
    out.failed = failed
    out.converged = not failed
    return out


def format_stat(v, spec: str) -> str:
    """R̂ or ESS formatted with ``spec``, or "n/a" where it could not be computed (None/NaN)."""
    return "n/a" if v is None or not math.isfinite(v) else format(v, spec)


def posterior_moments(idata, var_name: str = VAR) -> dict:
    """Posterior mean (A−1, 3) and covariance (A−1, 3, 3) per IMU, pooled over chains and draws,
    with the IMU labels: {"imu": [...], "mean": ndarray, "cov": ndarray}."""
    da = idata.posterior[var_name]
    x = np.asarray(da.values)  # (C, D, A-1, 3)
    flat = x.reshape(-1, x.shape[-2], 3)
    mean = flat.mean(0)
    dev = flat - mean
    n = max(1, flat.shape[0] - 1)
    cov = np.einsum("nki,nkj->kij", dev, dev) / n
    return {"imu": [int(k) for k in da.coords["imu"].values], "mean": mean, "cov": cov}


# ---------------------------------------------------------------------------- storage

def truth_check(idata, truth, var_name: str = VAR) -> dict:
    """How far the posterior mean is from a known truth, in the posterior's own units.

    truth : (K, 3) true positions relative to the reference triad, m, one row per IMU label.  With
    m and C the mean and covariance of the draws of the free coordinates (the IMUs of the
    posterior, every one but the reference; d = 3 × their number):

    * ``chi2`` = eᵀC⁻¹e, e = m − truth: χ²_d distributed when the posterior is calibrated (the
      error of the posterior mean ~ N(0, C)), reported with its 99 % band and upper-tail p;
    * ``radial_z`` = uᵀe / (uᵀCu)^½ with u the true free positions: the error along the board's
      scale mode in std (< 0: the fit is smaller than the truth; N(0, 1) when calibrated).  A median
      |z| hides this mode, which all coordinates share.
    """
    from scipy import stats

    da = idata.posterior[var_name]
    labels = [int(k) for k in da.coords["imu"].values]
    x = _np(da.values).reshape(-1, 3 * len(labels))  # (chain·draw, d)
    u = np.asarray(truth, dtype=float)[labels].reshape(-1)
    m, C = x.mean(0), np.cov(x, rowvar=False)
    e = m - u
    d = e.size
    chi2 = float(e @ np.linalg.solve(C, e))
    radial = float(u @ e / math.sqrt(u @ C @ u))
    lo, hi = stats.chi2.ppf([0.005, 0.995], d)
    return {"chi2": chi2, "dof": d, "band99": (float(lo), float(hi)), "p_upper": float(stats.chi2.sf(chi2, d)),
            "inside99": bool(lo <= chi2 <= hi), "radial_z": radial}


def save(idata, path) -> Path:
    """Write ``idata`` to NetCDF-4 (h5netcdf engine, one group per InferenceData group, float
    variables zlib-compressed as ArviZ does), atomically (:func:`accel_bayes.data.outputs.write_netcdf`);
    returns the path.  :func:`load` (``arviz.from_netcdf``) reads it back."""
    from .data.outputs import write_netcdf

    tree = idata.to_datatree()
    enc = {node.path: {name: {"zlib": True} for name, v in node.dataset.variables.items()
                       if v.dtype.kind in "fiub" and v.ndim > 0}
           for node in tree.subtree if node.has_data}
    return write_netcdf(Path(path), tree, engine="h5netcdf", encoding={k: v for k, v in enc.items() if v})


def load(path):
    """Read an InferenceData written by :func:`save`."""
    p = Path(path)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such file")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return az.from_netcdf(str(p), engine="h5netcdf")


# ---------------------------------------------------------------------------- plots

def _subplots(nrows=1, ncols=1, *, figsize, squeeze=True, layout="constrained", **kw):
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
    _, axes = _subplots(rows, cols, figsize=figsize, squeeze=False, **kw)
    for a in axes.ravel()[n if not trace else axes.size:]:
        a.set_visible(False)
    return coords, axes, figsize


def _coords_subset(idata, max_imus):
    labels = [int(k) for k in idata.posterior[VAR].coords["imu"].values]
    if max_imus is None or len(labels) <= max_imus:
        return None
    return {"imu": labels[:max_imus]}


def _mm(idata):
    """A copy of the posterior with r in millimetres (plots read better)."""
    post = idata.posterior[[VAR]] * 1e3
    return az.InferenceData(posterior=post)


def plot_trace(idata, max_imus: int | None = 2, **kwargs):
    """Trace and marginal density per coordinate (``az.plot_trace``), mm; the first
    ``max_imus`` free IMUs only (None: all)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 2, 1.9, trace=True)
        axes = az.plot_trace(_mm(idata), var_names=[VAR], coords=coords, compact=False, show=False, axes=axes,
                             figsize=size, **kwargs)
    fig = np.ravel(axes)[0].figure
    fig.suptitle("PmMH trace, r relative to the reference triad [mm]")
    return fig


def plot_rank(idata, max_imus: int | None = 2, **kwargs):
    """Rank plots per coordinate (``az.plot_rank``): uniform bars when chains agree."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 3, 2.6)
        axes = az.plot_rank(_mm(idata), var_names=[VAR], coords=coords, show=False, ax=axes, figsize=size, **kwargs)
    fig = np.ravel(axes)[0].figure
    return fig


def plot_autocorr(idata, max_imus: int | None = 2, **kwargs):
    """Autocorrelation per coordinate, chains combined (``az.plot_autocorr``), [C21] Fig. 3b."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        coords, axes, size = _arviz_axes(idata, max_imus, 3, 2.4, sharex=True, sharey=True)  # as ArviZ shares them
        axes = az.plot_autocorr(_mm(idata), var_names=[VAR], coords=coords, combined=True, show=False, ax=axes,
                                figsize=size, **kwargs)
    fig = np.ravel(axes)[0].figure
    return fig


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
        return {"imu": [int(k) for k in m["imu"]], "mean": np.asarray(_np(m["mean"])),
                "cov": np.asarray(_np(m["cov"]))}
    raise UserError("idata_or_moments: expected an InferenceData or a dict with 'imu', 'mean' (A-1, 3), "
                    "'cov' (A-1, 3, 3)")


def plot_ellipses(idata_or_moments, array, ax=None, level=0.5, prior_std=None, label=None, color="C0",
                  exaggerate: float = 1.0):
    """[C21] Fig. 5: x–y confidence ellipses of each free triad's position over the board.

    idata_or_moments : an InferenceData from :func:`to_inference_data`, or a dict
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
    nominal = np.asarray(_np(array.positions), dtype=float) * 1e3  # mm
    labels = list(getattr(array, "labels", range(len(nominal)))) or list(range(len(nominal)))
    ref = int(array.reference_imu)
    ref_pos = nominal[ref]
    top = nominal[:, 2] >= 0
    sides = [("top side", top), ("bottom side", ~top)]
    sides = [(nm, m) for nm, m in sides if m.any()]
    if ax is None:
        fig, axes = _subplots(1, len(sides), figsize=(5.5 * len(sides), 5.5), squeeze=False)
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
    nominal = np.asarray(_np(array.positions), dtype=float)
    ref = int(array.reference_imu)
    rows = [(i, lab) for i, lab in enumerate(mom["imu"]) if lab < len(nominal) and lab != ref]
    if not rows:
        raise UserError("idata_or_moments: no free IMU of the array to plot")
    tru = None if truth is None else np.asarray(_np(truth), dtype=float)
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
    fig, axes = _subplots(nrows, ncols, figsize=(3.0 * ncols + 0.5, 3.2 * nrows + 1.4), squeeze=False,
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
    xy = np.unique(np.round(np.asarray(_np(array.positions), dtype=float)[:, :2], 9), axis=0)
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
    nominal = np.asarray(_np(array.positions), dtype=float)
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


# =====================================================================================================
# Model mismatch (accel_bayes.mismatch): PSIS-LOO, model comparison and the mismatch report's figures.
# Moved here from mismatch/refine.py and mismatch/report.py (issue #10 item 5) so that every ArviZ
# call and every plot of the package lives in this module.  The mismatch package imports these
# lazily (inside functions): importing accel_bayes.mismatch does not load ArviZ or matplotlib.
# =====================================================================================================

def psis_loo(loglik, globals_draws=None):
    """PSIS-LOO (``az.loo``) over the observations of pointwise log-likelihood draws.

    loglik : (S, N) array — log p(y_n | draw s) for S posterior (or Laplace) draws and N
        observations (for the mismatch fits: time samples).
    globals_draws : (S, d) array of the draws themselves (stored as the posterior group; only
        its shape matters to PSIS), or None.
    Returns (dict with ``elpd_loo``, ``se``, ``p_loo`` and ``pareto_k_over_0.7`` (count of
    observations with Pareto k > 0.7, where the estimate is unreliable), the ``InferenceData``,
    ArviZ's pointwise ``ELPDData``).
    """
    ll = np.asarray(loglik, dtype=np.float64)
    S = ll.shape[0]
    post = np.zeros((S, 1)) if globals_draws is None else np.asarray(globals_draws, dtype=np.float64)
    idata = az.from_dict(posterior={"globals": post[None]}, log_likelihood={"y": ll[None]}, dims={"y": ["time"]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Pareto-k warnings: counted and reported instead
        loo = az.loo(idata, pointwise=True)
    k = np.asarray(loo.pareto_k)
    return {"elpd_loo": float(loo.elpd_loo), "se": float(loo.se), "p_loo": float(loo.p_loo),
            "pareto_k_over_0.7": int((k > 0.7).sum())}, idata, loo


def compare_loo(loos: dict) -> dict:
    """``az.compare`` (ic="loo") of named pointwise ``ELPDData`` (from :func:`psis_loo`; passing
    them rather than InferenceData keeps ArviZ from recomputing PSIS-LOO).  Returns
    {name: {"rank", "elpd_diff", "dse", "weight"}}."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cmp = az.compare(dict(loos), ic="loo")
    return {str(ix): {"rank": int(row["rank"]), "elpd_diff": float(row["elpd_diff"]), "dse": float(row["dse"]),
                      "weight": float(row["weight"])} for ix, row in cmp.iterrows()}


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
    fig, axes = _subplots(1, len(panels), figsize=(4.2 * len(panels) + 1, 0.35 * K + 2), squeeze=False)
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
    fig, axes = _subplots(1, len(schemes), figsize=(3.3 * len(schemes), 3.4), squeeze=False)
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
    fig, (a1, a2) = _subplots(1, 2, figsize=(10, 3.6))
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


# ============================================================================ [S16] self-calibration
# (issue #10 item 6: moved here from cli/selfcal.py, so that every plot lives in this module)

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
    fig, ax = _subplots(figsize=(6.4, 4.0))
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

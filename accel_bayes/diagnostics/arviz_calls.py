"""Every call of the package into ArviZ, so that a move to ArviZ 1.x is one module's change.

* Data: :func:`to_inference_data` turns PmMH draws into an ``az.InferenceData`` (posterior
  variable ``r`` with dims ("imu", "axis"), sample statistics, the log-likelihood estimates);
  :func:`save` / :func:`load` write and read it as NetCDF (h5netcdf engine).
* Statistics: :func:`summarize` (R̂, bulk/tail ESS, MCSE: ``az.summary``), :func:`rhat_max`,
  :func:`ess_bulk_min`, :func:`rank_diagnostics` (per-coordinate R̂ and ESS for the convergence
  rule of :mod:`accel_bayes.diagnostics.stats`); :func:`psis_loo` and :func:`compare_loo` for the
  model-mismatch comparisons.
* Plots: :func:`draw` — ArviZ's trace, rank and autocorrelation plots into axes the caller made
  (:mod:`accel_bayes.diagnostics.plots` makes them without pyplot).

Units: positions in metres; :func:`draw` plots millimetres.
"""
from __future__ import annotations

import contextlib
import logging
import warnings
from pathlib import Path

import numpy as np

with warnings.catch_warnings():
    warnings.simplefilter("ignore", FutureWarning)  # arviz 0.23 announces its 1.0 refactor
    import arviz as az

from ..errors import UserError

__all__ = ["AXES", "VAR", "as_numpy", "to_inference_data", "save", "load", "summarize", "rhat_max", "ess_bulk_min",
           "rank_diagnostics", "psis_loo", "compare_loo", "draw"]

# The posterior variable of every InferenceData made here: r[imu, axis], metres.
AXES = ("x", "y", "z")
VAR = "r"


def as_numpy(x):
    """A NumPy view of an array or tensor (detached, on the CPU); None stays None."""
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
    x = as_numpy(draws)
    if x is None or x.ndim != 4 or x.shape[-1] != 3:
        raise UserError(f"draws: expected shape (chains, draws, A-1, 3), got {None if x is None else x.shape}")
    C, D, Af, _ = x.shape
    labels = [int(k) for k in imu_labels]
    if len(labels) != Af:
        raise UserError(f"imu_labels: expected {Af} labels (one per free triad), got {len(labels)}")

    def cd(name, v):
        v = as_numpy(v)
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
        s = as_numpy(step_size).reshape(C, 1)
        stats["step_size"] = np.broadcast_to(s, (C, D)).astype(np.float64).copy()

    loglik = None
    dims = {VAR: ["imu", "axis"]}
    coords = {"imu": labels, "axis": list(AXES)}
    if pointwise_log_lik is not None:
        pw = as_numpy(pointwise_log_lik)
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


def save(idata, path) -> Path:
    """Write ``idata`` to NetCDF-4 (h5netcdf engine, one group per InferenceData group, float
    variables zlib-compressed as ArviZ does), atomically (:func:`accel_bayes.data.outputs.write_netcdf`);
    returns the path.  :func:`load` (``arviz.from_netcdf``) reads it back."""
    from ..data.outputs import write_netcdf

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


# ---------------------------------------------------------------------------- statistics

@contextlib.contextmanager
def _arviz_quiet():
    """Silence ArviZ's logger ("Shape validation failed" for one chain): the NaN it returns is
    reported by :func:`accel_bayes.diagnostics.stats.convergence_warnings`, and the command line
    keeps stderr to one line."""
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


def rank_diagnostics(flat) -> tuple:
    """Rank-normalised split R̂ and bulk and tail ESS (draws, pooled over chains) of each coordinate
    of ``flat`` (C chains, D draws, P coordinates): three (P,) float64 arrays, NaN where a statistic
    cannot be computed (too few draws)."""
    flat = np.asarray(flat, dtype=np.float64)
    P = flat.shape[-1]
    with warnings.catch_warnings(), _arviz_quiet(), np.errstate(all="ignore"):
        warnings.simplefilter("ignore")
        ds = az.convert_to_dataset({"x": flat}, dims={"x": ["coord"]})
        rh = np.asarray(az.rhat(ds)["x"].values, dtype=np.float64).reshape(P)
        eb = np.asarray(az.ess(ds, method="bulk")["x"].values, dtype=np.float64).reshape(P)
        et = np.asarray(az.ess(ds, method="tail")["x"].values, dtype=np.float64).reshape(P)
    return rh, eb, et


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


# ---------------------------------------------------------------------------- plots

def _mm(idata):
    """A copy of the posterior with r in millimetres (plots read better)."""
    post = idata.posterior[[VAR]] * 1e3
    return az.InferenceData(posterior=post)


def draw(kind: str, idata, axes, *, coords, figsize, **kwargs):
    """ArviZ's ``plot_trace`` / ``plot_rank`` / ``plot_autocorr`` (``kind`` "trace", "rank",
    "autocorr"; chains combined for the autocorrelation, [C21] Fig. 3b) of r in millimetres, into
    the caller's ``axes`` (ArviZ would otherwise make its figure with pyplot); ``coords`` selects
    IMUs (None: all), ``figsize`` (in) scales ArviZ's fonts.  Returns ArviZ's axes."""
    mm = _mm(idata)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if kind == "trace":
            return az.plot_trace(mm, var_names=[VAR], coords=coords, compact=False, show=False, axes=axes,
                                 figsize=figsize, **kwargs)
        if kind == "rank":
            return az.plot_rank(mm, var_names=[VAR], coords=coords, show=False, ax=axes, figsize=figsize, **kwargs)
        if kind == "autocorr":
            return az.plot_autocorr(mm, var_names=[VAR], coords=coords, combined=True, show=False, ax=axes,
                                    figsize=figsize, **kwargs)
    raise UserError(f"kind: expected 'trace', 'rank' or 'autocorr', got {kind!r}")

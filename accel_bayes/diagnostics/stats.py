"""Posterior statistics: the convergence rule, posterior moments, the check against a truth.

* :func:`convergence_check` — the one rule for "converged": every coordinate with R̂ < 1.01 and bulk
  and tail ESS ≥ 400, thresholds adjustable; used by ``calibrate`` to decide when to stop and for
  its exit status.  :func:`convergence_warnings` is the older max-R̂ / min-bulk-ESS form;
  :func:`format_stat` prints a statistic that may not be computable.
* :func:`posterior_moments` — mean and covariance per IMU; :func:`truth_check` — the posterior
  mean's error against a known truth, in the posterior's own units.

The ArviZ statistics these use are in :mod:`accel_bayes.diagnostics.arviz_calls`.  Units: metres.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..constants import ESS_PER_CHAIN, RHAT_MAX
from ..errors import UserError
from .arviz_calls import VAR, as_numpy, rank_diagnostics

__all__ = ["RHAT_LIMIT", "RHAT_MAX", "ESS_MIN", "convergence_warnings", "ConvergenceCheck", "convergence_check",
           "format_stat", "posterior_moments", "truth_check"]

# Vehtari, Gelman, Simpson, Carpenter & Bürkner (2021), "Rank-normalization, folding, and
# localization: an improved R̂", §4: R̂ < 1.01 and bulk ESS > 100 per chain before trusting moments.
RHAT_LIMIT = 1.01


def convergence_warnings(rhat: float | None, ess_bulk: float | None, chains: int) -> list[str]:
    """Why PmMH chains cannot be trusted yet, one sentence each; ``[]`` when they can — the older
    summary form of the rule (max R̂, min bulk ESS, 100 per chain); ``calibrate`` decides with
    :func:`convergence_check` (every coordinate, bulk and tail ESS).

    rhat : largest split R̂ (:func:`~.arviz_calls.rhat_max`); ess_bulk : smallest bulk ESS
    (:func:`~.arviz_calls.ess_bulk_min`), draws; chains : number of chains.  None or NaN (too few
    draws to compute the statistic) counts as not converged: convergence that cannot be checked is
    not established.
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
    and tail ESS ≥ ``ess_min`` (ArviZ ``rhat`` and ``ess(method="bulk"/"tail")``, through
    :func:`~accel_bayes.diagnostics.arviz_calls.rank_diagnostics`).

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
    x = as_numpy(theta_chains)
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
    rh, eb, et = rank_diagnostics(flat)
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
    x = as_numpy(da.values).reshape(-1, 3 * len(labels))  # (chain·draw, d)
    u = np.asarray(truth, dtype=float)[labels].reshape(-1)
    m, C = x.mean(0), np.cov(x, rowvar=False)
    e = m - u
    d = e.size
    chi2 = float(e @ np.linalg.solve(C, e))
    radial = float(u @ e / math.sqrt(u @ C @ u))
    lo, hi = stats.chi2.ppf([0.005, 0.995], d)
    return {"chi2": chi2, "dof": d, "band99": (float(lo), float(hi)), "p_upper": float(stats.chi2.sf(chi2, d)),
            "inside99": bool(lo <= chi2 <= hi), "radial_z": radial}

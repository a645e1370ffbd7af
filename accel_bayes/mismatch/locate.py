"""Locate a mismatch: where (IMU, sensor, axis, motion regime, time) the residuals of a fit
exceed the noise the model states, and whether that excess is more than chance.

Given a fit of the (nominal or augmented) model (:func:`accel_bayes.mismatch.fit.fit_model`):

1. **Standardized residuals** z = r / (σ c √(1 − h)) per sample, IMU, sensor (acc / gyro) and
   sensor-frame axis: r the raw residual, σ the stated noise, c the model's noise factor (1 for
   the nominal model), h the leverage of the sample's fitted motion state ([ω, ω̇, s] is fitted
   per sample, which shrinks residuals: without the correction a clean recording shows
   E[z²] ≈ 1 − 9/(6K) instead of 1).  Under the model, z ~ N(0, 1).
2. **Excess statistics**: per cell (IMU, sensor, axis) and per IMU/sensor, χ² = Σz² against its
   expectation n, as the z-score (χ² − n)/√(2n); the mean of z (a bias shows as √n·z̄); the lag-1
   autocorrelation of z in time (√n·ρ₁, unmodelled dynamics and timing errors correlate).
3. **Motion regimes** (:func:`regimes`): tertiles of |ω|, |ω̇| and |s| (specific force of the
   origin), the direction of s (dominant array axis and sign — the board's attitude relative to
   gravity when the motion is slow) and ten equal time bins; the excess per regime bin, overall
   and per cell.
4. **Posterior predictive check** (:func:`ppc`): twin recordings y* = ŷ + e*, e* drawn at the
   model's noise, refitted by one Gauss–Newton step from the fitted values (exact for a model
   linear around the fit; every nuisance parameter — geometry, motion, effect parameters — is
   refitted, so the twins' residuals carry the same leverage as the real ones); the same
   statistics on the twins give PPC p-values = (1 + #{twin ≥ real}) / (1 + N).
5. **Located excess test** (:func:`excess_cells`): per cell and regime scheme, the
   likelihood-ratio statistic of a model with a free mean and variance of z in every bin of the
   scheme, 2ΔlogL = Σ_b n_b (m2_b − 1 − log v_b) (m2 the mean z², v the variance), χ² with 2B
   degrees of freedom under the model.  This is what ``unexplained`` findings are made of.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..physics.effects import AXES
from .model import ModelFit
from .prepared import Prepared

__all__ = ["CHANNELS", "Location", "standardized", "regimes", "locate", "ppc", "excess_cells", "regime_concentration",
           "time_window", "log10_chi2_sf"]

CHANNELS = tuple(f"{s}_{a}" for s in ("acc", "gyro") for a in AXES)  # the 6 channels of an IMU


def _chi2_logsf(x: float, df: int) -> float:
    """``scipy.stats.chi2.logsf(x, df)`` for one float, computed as SciPy computes it (log of the
    upper tail above the median, log1p of minus the lower tail below it) from the same special
    functions, without the ~40 µs of argument handling per call of the distribution object
    (the detector ranks a few thousand statistics per round)."""
    from scipy import special as sc

    if x > 2.0 * float(sc.gammaincinv(0.5 * df, 0.5)):
        with np.errstate(divide="ignore"):
            return float(np.log(sc.chdtrc(df, x)))
    return float(np.log1p(-sc.chdtr(df, x)))


def log10_chi2_sf(stat: float, df: int) -> float:
    """log10 P(χ²_df > stat), finite for every finite stat.

    SciPy's ``chi2.logsf`` underflows to −inf beyond stat ≈ 1400 (df ≤ 20); there the asymptotic
    series of the upper incomplete gamma function, log Γ(s, z)/Γ(s) ≈ (s−1) log z − z − log Γ(s)
    + log(1 + (s−1)/z + (s−1)(s−2)/z²), s = df/2, z = stat/2, is accurate to better than 1e-6
    relative.  Finite values matter: tests are *ranked* by this number, and a tie at −inf
    would rank them by enumeration order instead of by their evidence."""
    if not math.isfinite(stat):
        return -math.inf if stat > 0 else 0.0
    df = max(int(df), 1)
    x = max(float(stat), 0.0)
    v = _chi2_logsf(x, df)
    if not math.isfinite(v) or x > 500:
        sh, zh = 0.5 * df, 0.5 * x
        v = (sh - 1) * math.log(zh) - zh - math.lgamma(sh) + math.log1p((sh - 1) / zh + (sh - 1) * (sh - 2) / zh ** 2)
    return v / math.log(10)


def standardized(prep: Prepared, fit: ModelFit) -> tuple[torch.Tensor, torch.Tensor]:
    """(z (T, K, 6), observed mask (T, K, 6) bool): leverage-corrected standardized residuals in
    the model's noise units, channels ``CHANNELS`` (sensor frame).  NaN where unobserved."""
    lin = fit.linear()
    T, K = prep.T, prep.K
    z = lin.r / torch.sqrt((1 - lin.h).clamp_min(1e-3))
    z = z.reshape(T, 2, K, 3).permute(0, 2, 1, 3).reshape(T, K, 6)
    mask = torch.cat((prep.m_acc, prep.m_gyro), -1) > 0
    return torch.where(mask, z, torch.full_like(z, float("nan"))), mask


def _tertiles(v: np.ndarray, name: str):
    q1, q2 = np.quantile(v, [1 / 3, 2 / 3])
    lab = np.digitize(v, [q1, q2])
    return lab, [f"low {name}", f"mid {name}", f"high {name}"]


def regimes(prep: Prepared, fit: ModelFit, n_time_bins: int = 10) -> dict:
    """Motion regimes of every sample from the fitted motion: scheme → (labels (T,) int, bin names)."""
    x = fit.x.numpy()
    w = np.linalg.norm(x[:, 0:3], axis=1)
    wd = np.linalg.norm(x[:, 3:6], axis=1)
    s = x[:, 6:9]
    out = {
        "|omega|": _tertiles(w, "|omega|"),
        "|omega_dot|": _tertiles(wd, "|omega_dot|"),
        "specific force": _tertiles(np.linalg.norm(s, axis=1), "specific force"),
    }
    dom = np.argmax(np.abs(s), axis=1)
    sign = np.sign(s[np.arange(len(s)), dom]) > 0
    lab = 2 * dom + (~sign).astype(int)
    out["s direction"] = (lab, [f"s along {sg}{a}" for a in AXES for sg in ("+", "-")])
    t = prep.time.numpy()
    T = len(t)
    nb = max(1, min(int(n_time_bins), T // 20 if T >= 20 else 1))
    edges = np.linspace(0, T, nb + 1).astype(int)
    lab_t = np.zeros(T, dtype=int)
    names = []
    for b in range(nb):
        lab_t[edges[b]:edges[b + 1]] = b
        names.append(f"time {t[edges[b]]:.3g}-{t[max(edges[b + 1] - 1, edges[b])]:.3g} s")
    out["time"] = (lab_t, names)
    return out


def _time_window(prep: Prepared, reg: dict, b: int):
    lab = reg["time"][0]
    t = prep.time.numpy()[lab == b]
    return [float(t.min()), float(t.max())] if len(t) else None


# ------------------------------------------------------------------------------ statistics

def _cell_stats(z: torch.Tensor, mask: torch.Tensor):
    """Per cell (K, 6): n, chi2, excess z-score, mean, lag-1 statistic."""
    zz = torch.nan_to_num(z)
    n = mask.sum(0).double()
    chi2 = (zz ** 2).sum(0)
    excess = (chi2 - n) / torch.sqrt(2 * n.clamp_min(1))
    mean = zz.sum(0) / n.clamp_min(1)
    both = mask[1:] & mask[:-1]
    lag = (zz[1:] * zz[:-1] * both).sum(0) / torch.sqrt(n.clamp_min(1))
    return n, chi2, excess, mean, lag


def _batch_stats(z: torch.Tensor, mask: torch.Tensor, reg_labels: list):
    """Headline statistics of z (..., T, K, 6) for the PPC (batched over leading dims)."""
    zz = torch.where(mask, z, torch.zeros_like(z))
    n = mask.sum(-3).double()
    z2 = zz ** 2
    chi2_cell = z2.sum(-3)
    excess = (chi2_cell - n) / torch.sqrt(2 * n.clamp_min(1))
    both = (mask[1:] & mask[:-1])
    lag = ((zz[..., 1:, :, :] * zz[..., :-1, :, :] * both).sum(-3) / torch.sqrt(n.clamp_min(1))).abs()
    reg_max = []
    tdim = z2.dim() - 3
    for lab, nb in reg_labels:
        idx = torch.as_tensor(lab, dtype=torch.long)
        c = z2.new_zeros(*z2.shape[:tdim], nb, *z2.shape[tdim + 1:]).index_add_(tdim, idx, z2)
        nn_ = mask.double().new_zeros(nb, *mask.shape[1:]).index_add_(0, idx, mask.double())
        reg_max.append(((c - nn_) / torch.sqrt(2 * nn_.clamp_min(1))).flatten(-3).amax(-1))
    return {
        "chi2": chi2_cell.sum((-2, -1)),
        "max_abs_z": zz.abs().flatten(-3).amax(-1),
        "max_cell_excess": excess.flatten(-2).amax(-1),
        "max_regime_excess": torch.stack(reg_max, -1).amax(-1),
        "max_lag1": lag.flatten(-2).amax(-1),
    }


def ppc(prep: Prepared, fit: ModelFit, *, n_twins: int = 100, seed: int = 0, reg: dict | None = None,
        batch: int | None = None) -> dict:
    """Posterior predictive check of a fit (module docstring, item 4): statistic → {real,
    twin_mean, twin_q95, p_value}.  Seeded: same seed, same twins."""
    lin = fit.linear()
    T, K = prep.T, prep.K
    reg = regimes(prep, fit) if reg is None else reg
    reg_labels = [(lab, len(names)) for lab, names in reg.values()]
    z, mask = standardized(prep, fit)
    real = _batch_stats(z, mask, reg_labels)
    if int(n_twins) <= 0:  # no PPC requested: the real statistics only
        out = {k: {"real": float(v), "twin_mean": None, "twin_q95": None, "p_value": None} for k, v in real.items()}
        out["n_twins"] = 0
        return out
    g = torch.Generator().manual_seed(int(seed))
    m_rows = torch.cat((prep.m_acc.reshape(T, -1), prep.m_gyro.reshape(T, -1)), -1)
    scale = torch.sqrt((1 - lin.h).clamp_min(1e-3))
    if batch is None:
        batch = max(1, min(n_twins, int(4e6 // max(T * 6 * K, 1))))
    stats = {k: [] for k in real}
    done = 0
    while done < n_twins:
        b = min(batch, n_twins - done)
        e = torch.randn(b, T, 6 * K, generator=g, dtype=torch.float32).double() * m_rows
        rt = lin.project(e)  # unobserved rows are zeroed by the mask in _batch_stats
        zt = (rt / scale).reshape(b, T, 2, K, 3).permute(0, 1, 3, 2, 4).reshape(b, T, K, 6)
        st = _batch_stats(zt, mask, reg_labels)
        for k in stats:
            stats[k].append(st[k])
        done += b
    out = {}
    for k, v in real.items():
        tw = torch.cat(stats[k]).numpy()
        rv = float(v)
        out[k] = {"real": rv, "twin_mean": float(tw.mean()), "twin_q95": float(np.quantile(tw, 0.95)),
                  "p_value": float((1 + (tw >= rv).sum()) / (1 + len(tw)))}
    out["n_twins"] = int(n_twins)
    return out


def excess_cells(prep: Prepared, fit: ModelFit, reg: dict | None = None, z=None, mask=None) -> list[dict]:
    """Located-excess tests (module docstring, item 5): one dict per (IMU, sensor, axis, scheme)
    with the statistic, df = 2B, the bin carrying most of it and the cell's χ² ratio; sorted by
    decreasing significance (log10 p)."""
    reg = regimes(prep, fit) if reg is None else reg
    if z is None:
        z, mask = standardized(prep, fit)
    zz = torch.nan_to_num(z).numpy()
    mk = mask.numpy()
    K = prep.K
    out = []
    for scheme, (lab, names) in reg.items():
        B = len(names)
        oh = np.eye(B)[lab]  # (T, B)
        n_b = np.einsum("tkc,tb->bkc", mk.astype(float), oh)
        s1 = np.einsum("tkc,tb->bkc", zz, oh)
        s2 = np.einsum("tkc,tb->bkc", zz ** 2, oh)
        with np.errstate(divide="ignore", invalid="ignore"):
            m1 = np.where(n_b > 0, s1 / np.maximum(n_b, 1), 0.0)
            m2 = np.where(n_b > 0, s2 / np.maximum(n_b, 1), 1.0)
            v = np.maximum(m2 - m1 ** 2, 1e-12)
            contrib = np.where(n_b > 1, n_b * (m2 - 1 - np.log(v)), 0.0)  # (B, K, 6)
        stat = contrib.sum(0)
        df = 2 * (n_b > 1).sum(0)
        for k in range(K):
            for c in range(6):
                if df[k, c] == 0 or mk[:, k, c].sum() == 0:
                    continue
                st = float(stat[k, c])
                lp = log10_chi2_sf(st, int(df[k, c]))
                b = int(np.argmax(contrib[:, k, c]))
                ntot = float(n_b[:, k, c].sum())
                out.append({"imu": k, "sensor": CHANNELS[c].split("_")[0], "axis": AXES[c % 3], "scheme": scheme,
                            "statistic": st, "df": int(df[k, c]), "log10_p": lp, "bin": names[b],
                            "bin_index": b, "bin_share": float(contrib[b, k, c] / st) if st > 0 else 0.0,
                            "chi2_ratio": float(s2[:, k, c].sum() / max(ntot, 1)),
                            "mean_z": float(s1[:, k, c].sum() / max(ntot, 1)),
                            "contributions": [float(v) for v in contrib[:, k, c]]})
    out.sort(key=lambda d: (d["log10_p"], -d["statistic"]))
    return out


def time_window(prep: Prepared, reg: dict, contributions, rel: float = 0.25):
    """[t0, t1] s spanned by the contiguous time bins around the largest contribution whose
    contribution is at least ``rel`` × the largest."""
    c = np.asarray(contributions, dtype=float)
    if c.size == 0 or not np.isfinite(c).all() or c.max() <= 0:
        return None
    b = int(np.argmax(c))
    lo = hi = b
    while lo > 0 and c[lo - 1] >= rel * c[b]:
        lo -= 1
    while hi < len(c) - 1 and c[hi + 1] >= rel * c[b]:
        hi += 1
    lab = reg["time"][0]
    t = prep.time.numpy()[(lab >= lo) & (lab <= hi)]
    return [float(t.min()), float(t.max())] if len(t) else None


def regime_concentration(prep: Prepared, reg: dict, per_sample: np.ndarray) -> dict:
    """Where a per-sample quantity (e.g. the log-likelihood gain of a finding) concentrates:
    the regime bin (outside the time scheme) with the largest share relative to its sample
    share, and a time window when one time bin holds more than half of the total."""
    tot = float(np.sum(per_sample))
    if not np.isfinite(tot) or tot <= 0:
        return {"regime": None, "time_s": None}
    best, best_ratio = None, -np.inf
    for scheme, (lab, names) in reg.items():
        if scheme == "time":
            continue
        for b, nm in enumerate(names):
            sel = lab == b
            if sel.mean() < 0.1:  # small bins make noisy ratios
                continue
            ratio = (per_sample[sel].sum() / tot) / (sel.mean())
            if ratio > best_ratio:
                best, best_ratio = nm, ratio
    lab, names = reg["time"]
    shares = np.array([per_sample[lab == b].sum() / tot for b in range(len(names))])
    tw = None
    if len(names) > 1 and shares.max() > 0.5:
        tw = _time_window(prep, reg, int(np.argmax(shares)))
    return {"regime": best if best_ratio > 1.25 else "all regimes", "regime_ratio": float(best_ratio), "time_s": tw}


# ------------------------------------------------------------------------------ result

@dataclass
class Location:
    """Where the residuals of one fit exceed its noise (module docstring).

    cells : list of dicts per (imu, sensor, axis): n, chi2, chi2_ratio, excess_z, mean_z, lag1_z.
    imus : per (imu, sensor) aggregates.  regimes : per scheme → list of bins with n, chi2_ratio,
    excess_z (all IMUs) and the worst cell in that bin.  ppc : :func:`ppc` output.
    excess_tests : the first rows of :func:`excess_cells`.  heat : (K, 6) excess z-scores (for
    the heat map).  summary : one sentence.
    """

    cells: list
    imus: list
    regimes: dict
    ppc: dict
    excess_tests: list
    heat: np.ndarray
    summary: str
    z: torch.Tensor = field(repr=False, default=None)
    reg: dict = field(repr=False, default=None)

    def to_dict(self, max_rows: int = 20) -> dict:
        top = sorted(self.cells, key=lambda d: -d["excess_z"])[:max_rows]
        tests = [{k: v for k, v in d.items() if k != "contributions"} for d in self.excess_tests[:max_rows]]
        return {"summary": self.summary, "cells_top": top, "imus": self.imus, "regimes": self.regimes,
                "ppc": self.ppc, "excess_tests_top": tests,
                "heat_channels": list(CHANNELS), "heat_excess_z": self.heat.tolist()}


def locate(prep: Prepared, fit: ModelFit, *, n_twins: int = 100, seed: int = 0) -> Location:
    """Residual analysis of a fit: excess per cell, IMU and regime, PPC and located-excess tests."""
    reg = regimes(prep, fit)
    z, mask = standardized(prep, fit)
    n, chi2, excess, mean, lag = _cell_stats(z, mask)
    K = prep.K
    cells = []
    for k in range(K):
        for c in range(6):
            if n[k, c] == 0:
                continue
            cells.append({"imu": k, "sensor": CHANNELS[c].split("_")[0], "axis": AXES[c % 3], "n": int(n[k, c]),
                          "chi2": float(chi2[k, c]), "chi2_ratio": float(chi2[k, c] / n[k, c]),
                          "excess_z": float(excess[k, c]), "mean_z": float(mean[k, c]),
                          "bias_z": float(mean[k, c] * torch.sqrt(n[k, c])), "lag1_z": float(lag[k, c])})
    imus = []
    for k in range(K):
        for si, sname in enumerate(("acc", "gyro")):
            sl = slice(3 * si, 3 * si + 3)
            nn_ = float(n[k, sl].sum())
            if nn_ == 0:
                continue
            c2 = float(chi2[k, sl].sum())
            imus.append({"imu": k, "sensor": sname, "n": int(nn_), "chi2_ratio": c2 / nn_,
                         "excess_z": (c2 - nn_) / math.sqrt(2 * nn_)})
    zz = torch.nan_to_num(z)
    regs = {}
    for scheme, (lab, names) in reg.items():
        rows = []
        for b, nm in enumerate(names):
            sel = torch.as_tensor(lab == b)
            if int(sel.sum()) == 0:
                continue
            nb = mask[sel].sum(0).double()
            cb = (zz[sel] ** 2).sum(0)
            ex_cell = (cb - nb) / torch.sqrt(2 * nb.clamp_min(1))
            kk, cc = divmod(int(torch.argmax(ex_cell)), 6)
            ntot = float(nb.sum())
            rows.append({"bin": nm, "n_samples": int(sel.sum()), "chi2_ratio": float(cb.sum()) / max(ntot, 1),
                         "excess_z": float((cb.sum() - ntot) / math.sqrt(2 * max(ntot, 1))),
                         "worst_cell": {"imu": kk, "channel": CHANNELS[cc], "excess_z": float(ex_cell[kk, cc])}})
        regs[scheme] = rows
    pp = ppc(prep, fit, n_twins=n_twins, seed=seed, reg=reg)
    tests = excess_cells(prep, fit, reg, z, mask)
    heat = excess.numpy()
    worst = sorted(cells, key=lambda d: -d["excess_z"])[:3]
    p_chi2, p_cell = pp["chi2"]["p_value"], pp["max_cell_excess"]["p_value"]
    sig_test = bool(tests) and tests[0]["log10_p"] < math.log10(0.01 / len(tests))
    if (p_chi2 is not None and (p_chi2 < 0.01 or p_cell < 0.01)) or sig_test:
        parts = [f"IMU {d['imu']} {d['sensor']} {d['axis']} (χ²/n = {d['chi2_ratio']:.3g})" for d in worst
                 if d["excess_z"] > 3]
        top = tests[0] if tests else None
        reg_txt = f"; most concentrated in '{top['bin']}'" if top else ""
        ptxt = f" (PPC p = {p_chi2:.3g} for the total χ²)" if p_chi2 is not None else ""
        summary = ("Residual excess beyond the stated noise at " + (", ".join(parts) if parts else "no single cell")
                   + reg_txt + ptxt + ".")
    elif p_chi2 is not None:
        summary = (f"Residuals are consistent with the stated noise (PPC p = {p_chi2:.3g} for the "
                   f"total χ², {p_cell:.3g} for the worst cell).")
    else:
        summary = "Residuals are consistent with the stated noise (no located excess is significant; no PPC twins)."
    return Location(cells=cells, imus=imus, regimes=regs, ppc=pp, excess_tests=tests, heat=heat, summary=summary,
                    z=z, reg=reg)

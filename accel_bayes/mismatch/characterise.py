"""Characterise what a fit leaves unexplained: what the remaining excess scales with, where it
sits, and whether it looks like timing, like a mean error, or like extra noise (issue #11 item 2).

Input: a fit (:class:`~accel_bayes.mismatch.model.ModelFit`, usually the detector's final
model) and its prepared recording.  Everything is computed from the leverage-corrected
standardized residuals z = r / (σ c √(1 − h)) of :func:`accel_bayes.mismatch.locate.standardized`
(z ~ N(0, 1) under the model), per sensor (accelerometer, gyroscope) and per IMU:

* **excess** — mean z² − 1 per channel-sample (0 under the model), its share per IMU and per
  sensor-frame axis;
* **covariates** — what the excess grows with.  For each candidate covariate c (per sample:
  ``|omega|`` rad/s, ``|omega_dot|`` rad/s², ``jerk`` = |ds/dt| m/s³ of the origin's specific
  force between consecutive samples, ``|s|`` m/s², ``time`` s; per IMU and sensor: ``|output|``
  — the magnitude of the sensor's own fitted output (m/s² or rad/s) — and ``|output rate|`` —
  its time derivative (m/s³ or rad/s²)) the per-sample excess e = mean over the triad's axes of z²
  is grouped into the quintiles of c, and the covariates are ranked by the correlation ratio
  η² = between-quintile / total variance of e (the same 4 degrees of freedom for every
  covariate, so the ranking is fair; its F statistic gives a p-value under "no dependence").
  ``power`` is the slope of log(mean z² per quintile) against log(median c per quintile):
  the excess *power* grows like c^power (2 for an error proportional to c);
* **autocorrelation** of z at lags 1–3 samples over consecutive samples (gaps excluded), averaged
  over the triad's axes, with the z-score √n·ρ₁: white extra noise and per-sample jitter give
  ρ ≈ 0; slowly varying errors (mean effects, drifting timing, filters) give ρ > 0;
* **anisotropy** — on the samples where the triad's own output rate is above its median, the
  mean of (z·u)² along the rate direction u over the mean per perpendicular direction: ≈ 1 for
  isotropic extra noise, ≫ 1 for a timing error (which moves the output along its rate);
* **timing wander** — the AR(1) sampling-instant error of :mod:`accel_bayes.mismatch.wander`
  fitted per triad together with a white-noise factor: its std σ_δ (ms), lag-one correlation ρ,
  the likelihood ratio against the best noise-only model (``evidence``) and the share of the
  triad's excess power it accounts for;
* **aliased jerk** (accelerometers, across the IMUs; ``coupling=True``) — the coupling of
  :mod:`accel_bayes.mismatch.vibration`: every IMU's accelerometer read at the instant its gyro
  reveals, times a per-sample jerk the outputs do not resolve.  Its jerk scale per |ω| band, the
  likelihood ratio against a white variance per IMU and band (``evidence``) and the share of the
  accelerometer excess its conditional mean explains.

The covariates, the autocorrelation and the anisotropy are computed per IMU and sensor and pooled
over the IMUs; :func:`characterise` returns both, and :func:`describe` turns one IMU/sensor (or a
pooled sensor) into the sentence the ``unexplained`` finding carries.  The rule that names the
**top covariate** is the largest F statistic (equivalently η²).

This is a description, not a test of a physical model: it says what a model of the remaining
excess would have to scale with.  Measured on the real MIMU4444 recordings (exp_1, nominal fit,
``experiments/mimu_mismatch.md``): the accelerometer excess is white in time (ρ₁ ≈ 0.03),
nearly isotropic about the output rate and grows with |ω|; the gyroscope excess lies along the
rate direction (anisotropy 3–4) with ρ₁ ≈ 0.6–0.9 — a slowly wandering per-IMU timing error.
"""
from __future__ import annotations

import math

import numpy as np

from .locate import standardized
from .model import ModelFit
from .prepared import Prepared

__all__ = ["COVARIATES", "characterise", "describe"]

#: the covariates tried, in the order they are reported
COVARIATES = ("|omega|", "|omega_dot|", "jerk", "|s|", "time", "|output|", "|output rate|")
_SENSORS = {"acc": slice(0, 3), "gyro": slice(3, 6)}
_N_BINS = 5
_GAP_FACTOR = 1.5  # consecutive samples: time step within 1.5× the median step


def _consecutive(t: np.ndarray) -> np.ndarray:
    """(T−1,) bool: samples t and t+1 are neighbours in time (no selection gap between them)."""
    dt = np.diff(t)
    if dt.size == 0:
        return np.zeros(0, dtype=bool)
    return dt <= _GAP_FACTOR * float(np.median(dt))


def _global_covariates(prep: Prepared, fit: ModelFit) -> dict:
    """Per-sample covariates (T,) shared by every IMU."""
    x = fit.x.detach().cpu().double().numpy()
    t = prep.time.detach().cpu().double().numpy()
    s = x[:, 6:9]
    nb = _consecutive(t)
    jerk = np.full(len(t), np.nan)
    if nb.any():
        ds = np.linalg.norm(np.diff(s, axis=0), axis=1) / np.diff(t)
        # a sample's jerk: the mean of its (valid) forward and backward differences
        fwd = np.where(nb, ds, np.nan)
        both = np.stack([np.r_[fwd, np.nan], np.r_[np.nan, fwd]])
        cnt = np.isfinite(both).sum(0)
        jerk = np.where(cnt > 0, np.nansum(both, 0) / np.maximum(cnt, 1), np.nan)
    return {"|omega|": np.linalg.norm(x[:, 0:3], axis=1), "|omega_dot|": np.linalg.norm(x[:, 3:6], axis=1),
            "jerk": jerk, "|s|": np.linalg.norm(s, axis=1), "time": t}


def _imu_covariates(fit: ModelFit, sensor: str) -> dict:
    """Per-sample, per-IMU covariates (T, K) of one sensor: its fitted output and output rate."""
    pred = (fit.pred_acc if sensor == "acc" else fit.pred_gyro).detach().cpu().double().numpy()
    rate = fit.ctx.acc_rate if sensor == "acc" else fit.ctx.gyro_rate
    out = {"|output|": np.linalg.norm(pred, axis=2)}
    out["|output rate|"] = (np.linalg.norm(rate.detach().cpu().double().numpy(), axis=2) if rate is not None
                            else np.full(pred.shape[:2], np.nan))
    return out


def _covariate_stats(e: np.ndarray, c: np.ndarray) -> dict | None:
    """How the per-sample excess ``e`` (mean z² of a triad, n,) depends on covariate ``c`` (n,)."""
    ok = np.isfinite(e) & np.isfinite(c)
    e, c = e[ok], c[ok]
    n = len(e)
    if n < 10 * _N_BINS or np.ptp(c) <= 0:
        return None
    edges = np.quantile(c, np.linspace(0, 1, _N_BINS + 1))
    lab = np.clip(np.searchsorted(edges, c, side="right") - 1, 0, _N_BINS - 1)
    cnt = np.bincount(lab, minlength=_N_BINS).astype(float)
    if (cnt == 0).any():
        return None
    mean_b = np.bincount(lab, weights=e, minlength=_N_BINS) / cnt
    med_b = np.array([np.median(c[lab == b]) for b in range(_N_BINS)])
    tot = float(((e - e.mean()) ** 2).sum())
    between = float((cnt * (mean_b - e.mean()) ** 2).sum())
    eta2 = between / tot if tot > 0 else 0.0
    df1, df2 = _N_BINS - 1, n - _N_BINS
    F = (eta2 / df1) / max((1 - eta2) / df2, 1e-300)
    from scipy.stats import f as f_dist

    log10_p = float(f_dist.logsf(F, df1, df2)) / math.log(10)
    power = None
    if (med_b > 0).all() and (mean_b > 0).all() and np.ptp(np.log(med_b)) > 0:
        power = float(np.polyfit(np.log(med_b), np.log(mean_b), 1)[0])
    return {"eta2": eta2, "F": float(F), "log10_p": log10_p, "power": power,
            "quintile_median": med_b.tolist(), "quintile_mean_z2": mean_b.tolist()}


def _autocorrelation(z: np.ndarray, nb: np.ndarray, lags=(1, 2, 3)) -> dict:
    """Lag autocorrelations of z (T, C) (NaN = unobserved) over consecutive samples, averaged
    over the C channels; ``z_lag1`` = √n·ρ₁ (≈ N(0, 1) for white residuals)."""
    zz = np.nan_to_num(z)
    obs = np.isfinite(z)
    out = {}
    T = len(z)
    for lag in lags:
        if T <= lag:
            out[f"lag{lag}"] = None
            continue
        ok = np.ones(T - lag, dtype=bool)
        for j in range(lag):
            ok &= nb[j:T - lag + j]
        pair = ok[:, None] & obs[:-lag] & obs[lag:]
        num = (zz[:-lag] * zz[lag:] * pair).sum(0)
        den = np.sqrt((zz[:-lag] ** 2 * pair).sum(0) * (zz[lag:] ** 2 * pair).sum(0))
        rho = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
        out[f"lag{lag}"] = float(np.nanmean(rho)) if np.isfinite(rho).any() else None
        if lag == 1:
            n = int(pair.sum() / max(z.shape[1], 1))
            out["z_lag1"] = None if out["lag1"] is None else float(out["lag1"] * math.sqrt(max(n, 1)))
    return out


def _anisotropy(z: np.ndarray, rate: np.ndarray) -> float | None:
    """Mean (z·u)² along the rate direction u over the mean per perpendicular direction, on the
    samples whose |rate| is above its median (z, rate: (n, 3), NaN-free rows only)."""
    ok = np.isfinite(z).all(1) & np.isfinite(rate).all(1)
    z, rate = z[ok], rate[ok]
    nr = np.linalg.norm(rate, axis=1)
    if len(nr) < 20 or not (nr > 0).any():
        return None
    hi = nr > np.median(nr)
    if hi.sum() < 10:
        return None
    u = rate[hi] / nr[hi, None]
    along = ((z[hi] * u).sum(1)) ** 2
    perp = ((z[hi] ** 2).sum(1) - along) / 2.0
    return float(along.mean() / perp.mean()) if perp.mean() > 0 else None


def _one(e_imu: np.ndarray, covs: dict) -> tuple[list, str | None]:
    rows = []
    for name in COVARIATES:
        c = covs.get(name)
        if c is None:
            continue
        st = _covariate_stats(e_imu, c)
        if st is not None:
            rows.append({"name": name, **st})
    rows.sort(key=lambda r: -r["F"])
    return rows, (rows[0]["name"] if rows else None)


def characterise(prep: Prepared, fit: ModelFit, *, coupling: bool = False) -> dict:
    """What the residual excess of ``fit`` scales with, where it sits and how it is structured
    (module docstring).  ``coupling``: also fit the aliased-jerk coupling of the accelerometers
    (:func:`accel_bayes.mismatch.vibration.fit_aliased_jerk`, about a second on 6000 samples of 8
    IMUs), reported as the accelerometers' ``aliased_jerk`` (its ``to_dict``; None where fewer than
    three IMUs have both triads).  Returns a JSON-ready dict ``{"acc": {...}, "gyro": {...}}``; per sensor:
    ``excess`` (mean z² − 1 per channel-sample), ``imus`` (per IMU: excess, share of the sensor's
    total excess, per-axis excess, ranked ``covariates``, ``top_covariate``, ``autocorrelation``,
    ``anisotropy``), the pooled ``covariates`` / ``top_covariate`` / ``autocorrelation`` /
    ``anisotropy`` over all IMUs, and ``summary`` (a sentence)."""
    z_t, mask_t = standardized(prep, fit)
    z = z_t.detach().cpu().double().numpy()
    t = prep.time.detach().cpu().double().numpy()
    nb = _consecutive(t)
    gcov = _global_covariates(prep, fit)
    out = {}
    for sensor, sl in _SENSORS.items():
        zs = z[:, :, sl]  # (T, K, 3)
        obs = np.isfinite(zs)
        if not obs.any():
            continue
        K = zs.shape[1]
        z2 = np.where(obs, zs ** 2, np.nan)
        with np.errstate(invalid="ignore"):
            e = np.nanmean(z2, axis=2)  # (T, K) per-sample excess power of each triad
        icov = _imu_covariates(fit, sensor)
        rate = (fit.ctx.acc_rate if sensor == "acc" else fit.ctx.gyro_rate)
        rate = None if rate is None else rate.detach().cpu().double().numpy()
        tot_excess = float(np.nansum(z2) - obs.sum())
        imus = []
        try:
            from .jitter import wander_table

            wander = {r["imu"]: r for r in wander_table(prep, fit, sensors=(sensor,))[sensor]}
        except Exception:  # a diagnostic: never let it stop a report (e.g. a fit without output rates)
            wander = {}
        for k in range(K):
            if not obs[:, k].any():
                continue
            ek = e[:, k]
            covs = dict(gcov)
            covs.update({nm: v[:, k] for nm, v in icov.items()})
            rows, top = _one(ek, covs)
            exc_k = float(np.nansum(z2[:, k]) - obs[:, k].sum())
            axes = [float(np.nanmean(z2[:, k, a]) - 1.0) if obs[:, k, a].any() else None for a in range(3)]
            imus.append({"imu": int(k), "excess": float(np.nanmean(z2[:, k]) - 1.0),
                         "share": exc_k / tot_excess if tot_excess > 0 else None, "axes": axes,
                         "covariates": rows, "top_covariate": top,
                         "autocorrelation": _autocorrelation(zs[:, k], nb),
                         "anisotropy": None if rate is None else _anisotropy(zs[:, k], rate[:, k]),
                         "timing_wander": wander.get(k)})
        # pooled over IMUs: per-IMU covariates enter with their own values
        covs_p = {nm: np.repeat(v[:, None], K, 1).reshape(-1) for nm, v in gcov.items()}
        covs_p.update({nm: v.reshape(-1) for nm, v in icov.items()})
        rows_p, top_p = _one(e.reshape(-1), covs_p)
        ac = [r["autocorrelation"] for r in imus]
        lag1 = [a["lag1"] for a in ac if a.get("lag1") is not None]
        an = [r["anisotropy"] for r in imus if r["anisotropy"] is not None]
        tw = [r["timing_wander"] for r in imus if r.get("timing_wander")]
        d = {"excess": float(np.nanmean(z2) - 1.0), "imus": imus, "covariates": rows_p, "top_covariate": top_p,
             "timing_wander": None if not tw else {
                 "sigma_ms_range": [min(x["sigma_ms"] for x in tw), max(x["sigma_ms"] for x in tw)],
                 "rho_range": [min(x["rho"] for x in tw), max(x["rho"] for x in tw)],
                 "evidence_range": [min(x["evidence"] for x in tw), max(x["evidence"] for x in tw)],
                 "share_range": [min(x["share"] or 0 for x in tw), max(x["share"] or 0 for x in tw)]},
             "autocorrelation": {"lag1_mean": float(np.mean(lag1)) if lag1 else None,
                                 "lag1_range": [float(min(lag1)), float(max(lag1))] if lag1 else None},
             "anisotropy": {"median": float(np.median(an)) if an else None,
                            "range": [float(min(an)), float(max(an))] if an else None}}
        if sensor == "acc" and coupling:
            from .vibration import fit_aliased_jerk

            try:
                aj = fit_aliased_jerk(prep, fit)
            except Exception:  # a diagnostic: never let it stop a report
                aj = None
            d["aliased_jerk"] = None if aj is None else aj.to_dict()
        d["summary"] = describe(d, sensor)
        out[sensor] = d
    return out


def _shape_words(lag1, aniso) -> str:
    parts = []
    if lag1 is not None:
        parts.append("white in time" if abs(lag1) < 0.1 else
                     f"correlated in time (lag-1 autocorrelation {lag1:.2f})")
    if aniso is not None:
        parts.append("concentrated along the output's rate of change, as a timing error would be "
                     f"(anisotropy {aniso:.2f})" if aniso > 2 else
                     f"about isotropic relative to the output's rate of change (anisotropy {aniso:.2f})")
    return ", ".join(parts)


def describe(d: dict, sensor: str, imu: int | None = None) -> str:
    """One sentence for a sensor's characterisation ``d`` (from :func:`characterise`), pooled or
    for one IMU."""
    what = {"acc": "accelerometer", "gyro": "gyroscope"}[sensor]
    wander = ""
    if imu is not None:
        r = next((x for x in d["imus"] if x["imu"] == imu), None)
        if r is None:
            return ""
        rows, lag1, an = r["covariates"], r["autocorrelation"].get("lag1"), r["anisotropy"]
        w = r.get("timing_wander")
        if w and w["evidence"] > 0 and w.get("share") is not None:
            wander = (f" A wandering timing error (std {w['sigma_ms']:.3g} ms, lag-one correlation {w['rho']:.2f}) "
                      f"would account for {100 * w['share']:.0f} % of it (likelihood ratio {w['evidence']:.3g} "
                      f"against extra white noise).")
        head = f"IMU {imu}'s {what} excess (mean z² − 1 = {r['excess']:.3g}"
        head += f", {100 * r['share']:.0f} % of the {what} total)" if r.get("share") is not None else ")"
    else:
        rows, lag1, an = d["covariates"], d["autocorrelation"]["lag1_mean"], d["anisotropy"]["median"]
        big = sorted(d["imus"], key=lambda r: -(r["share"] or 0))[:2]
        where = ", ".join(f"IMU {r['imu']} {100 * (r['share'] or 0):.0f} %" for r in big)
        head = f"The {what} excess (mean z² − 1 = {d['excess']:.3g}; largest shares {where})"
    aj = d.get("aliased_jerk") if imu is None else None
    perm = (aj or {}).get("permutation") or {}
    if aj and aj["evidence"] > 0 and perm and aj["share"] == aj["share"]:
        sig = perm["p_value"] <= 0.05
        wander += (f" Read at the instants the gyros reveal, times a per-sample jerk the outputs do not resolve "
                   f"(aliased vibration; {', '.join(f'{x:.3g}' for x in aj['jerk_rms'])} m/s³ rms by |ω| band), "
                   f"the accelerometers' pattern across the IMUs accounts for {100 * aj['share']:.0f} % of it "
                   f"(likelihood ratio {aj['evidence']:.3g} against a white variance per IMU and |ω| band; "
                   f"permutation test: {perm['statistic']:.3g} with the variances held, at most "
                   f"{perm['statistic_max']:.3g} in {perm['n']} permutations of the instants"
                   + (")." if sig else f": not significant, p = {perm['p_value']:.2g}")
                   + ("" if sig else ")."))
    if not rows:
        return head + "." + wander
    top = rows[0]
    lo, hi = top["quintile_mean_z2"][0], top["quintile_mean_z2"][-1]
    grow = f"its power goes from {lo:.3g} to {hi:.3g}× the model's noise across the quintiles of {top['name']}"
    if top.get("power") is not None:
        grow += f" (∝ {top['name']}^{top['power']:.2g})"
    shape = _shape_words(lag1, an)
    return (f"{head} grows most with {top['name']} (η² {top['eta2']:.2g}): {grow}" + (f"; it is {shape}." if shape else ".")
            + wander)

"""The detector's unresolved-motion stage (:func:`accel_bayes.mismatch.detect`, step 7a; issue #27
item 3): ``unresolved_motion`` (:mod:`accel_bayes.mismatch.unresolved`) fitted at the final model,
loaded on every IMU by its accepted clock's data age, on both sensors.

Data.  Per sensor, the final fit's leverage-corrected residuals in the array frame
(:func:`accel_bayes.mismatch.vibration.array_residuals`) on the IMUs that have an accepted
``sampling_clock``; their physical data ages (each clock's sawtooth of width 1/f_k,
:func:`physical_ages`) centred over those IMUs per sample (a common age is absorbed by the motion
states); the |ω| quantile bands of the final fit's motion.  Needs clocks on ≥ 2 IMUs.

Fit.  The test below uses :func:`~accel_bayes.mismatch.unresolved.fit_scales` (a white variance per
IMU and |ω| band, the term's scale per band).  A kept sensor's term is then fitted by
:func:`~accel_bayes.mismatch.unresolved.fit_grid` (issue #27 budget): the scale per cell of the
budget's |ω| × |ω̇| quantile bands (``jerk_rms`` m/s³ on the accelerometers, ``angular_acc_rms``
rad/s² on the gyroscopes), one white variance per IMU, and the age error e — the part of each IMU's
sampling instant its clock does not give, iid per IMU and sample, which carries the same unresolved
motion: y_kt = (d_kt + ε_kt) m_t + e_kt.  On the six real recordings (97e5674's final models) the
accelerometer excess the band model left white grew with the band's jerk² and lay along the fitted
jerk; e came out 0.17–0.23 ms on both sensors (``experiments/mimu_budget_decompose.md``).  What
else the model already predicts (noise factors, random effects) is a known part of the white
variance, so the term is fitted on top of it.  By maximum likelihood with the per-sample motion
marginalised exactly (ε m by its first two moments).  The mean model is not refitted with the term
(the term is profiled at the final mean, as the random effects are); the term's log-likelihood gain
over the band model's null is added to the refined model's (``refined.loglik``).

Superseded random timing (:func:`supersede_random_timing`): a ``timing_wander`` or
``sampling_jitter`` on a sensor where the age error is kept names the same instant error on one IMU
with a variance that does not follow the unresolved motion; it is withdrawn when the model without
it, refitted, has the higher likelihood with the term.

Test, per sensor.  The likelihood ratio is not χ²-distributed on fitted residuals (the per-sample
motion states correlate the residuals of a sample, and a rank-3 term soaks that up; see
:mod:`accel_bayes.mismatch.vibration`), so its null is the same statistic with the ages
permuted among the samples of each band (seeded; breaks only the pairing of a sample's residuals
with its IMUs' ages).  The statistic is the profile ratio with the white variances held at the
null's (:func:`accel_bayes.mismatch.vibration._profile_lr`, O(T) per permutation).  A sensor's term
is kept when its statistic exceeds the detector's threshold, the largest permuted statistic, and
the permutations' mean + z·sd with z the normal quantile at 1 − α/m (a Gaussian reading of the
permutation null at the detector's family-wise level).  A sensor that fails has scale 0; the
finding (vocabulary 1.2, imu and axis null) is reported when either sensor passes, its evidence
the sum of the kept sensors' likelihood ratios (white variances refitted).

Budget: the term's predicted variance s²_c (d²_kt + e²) per channel-sample (the same on the three
axes) is part of b (:func:`accel_bayes.mismatch.budget.residual_budget`'s ``extra``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .budget import band_edges, predicted_extra_variance
from .model import ModelFit
from .prepared import Prepared
from .unresolved import UnresolvedMotion, fit_grid, fit_scales
from .vibration import _bands, _profile_lr, array_residuals, omega_edges

__all__ = ["UnresolvedStage", "UnresolvedEffect", "unresolved_stage", "supersede_random_timing", "term_for", "physical_ages",
           "SENSORS"]

SENSORS = ("acc", "gyro")
_SCALE_NAME = {"acc": "jerk_rms", "gyro": "angular_acc_rms"}


class UnresolvedEffect:
    """The fitted term as a report finding's model and a fixed effect of the refined model: the
    §7.2 names (``unresolved_motion``, imu and axis null), parameters per |ω| band and the budget's
    ``predicted_variance`` hook (:class:`~accel_bayes.mismatch.unresolved.UnresolvedMotion`)."""

    name = vocabulary_name = "unresolved_motion"
    kind = "random"
    imu = axis = None
    df = 0

    def __init__(self, term: UnresolvedMotion, std: dict, sensors: list):
        self.term, self.sensors = term, list(sensors)
        self.std = {}  # the Finding's Laplace block: the scales' standard errors go in the parameters instead
        self._std = std
        n = len(term.jerk_rms) + (1 if term.omega_dot_edges is not None else 0)  # scales (+ the age error)
        self.df = n * len(self.sensors)

    def label(self) -> str:
        return "unresolved_motion"

    def vocabulary_parameters(self) -> dict:
        j, g = self.term.band_rms()
        p = {"omega_edges": [float(e) for e in self.term.edges], "jerk_rms": j, "angular_acc_rms": g,
             "sensors": self.sensors}
        if self.term.omega_dot_edges is not None:
            p.update({"omega_dot_edges": [float(e) for e in self.term.omega_dot_edges],
                      "jerk_rms_grid": [float(x) for x in self.term.jerk_rms],
                      "angular_acc_rms_grid": [float(x) for x in self.term.angular_acc_rms],
                      "age_error_rms_s": {"acc": float(self.term.age_error_rms[0]),
                                          "gyro": float(self.term.age_error_rms[1])}})
        if self.term.angular_jerk_rms is not None:  # beyond vocabulary 1.2's two scales (opt-in, DetectOptions)
            p["angular_jerk_rms"] = self.term.band_rms(self.term.angular_jerk_rms)[0]
            if self.term.omega_dot_edges is not None:
                p["angular_jerk_rms_grid"] = [float(x) for x in self.term.angular_jerk_rms]
        p.update({f"{k}_std": [float(x) for x in v] for k, v in self._std.items()})
        return p

    def explain(self) -> str:
        return ("board motion faster than the outputs resolve (vibration, impacts), seen through each IMU's clock "
                "data age and the part of its sampling instant the clock does not give, on " + " and ".join(
                    {"acc": "the accelerometers (jerk)", "gyro": "the gyroscopes (angular acceleration)"}[s]
                    for s in self.sensors))

    def predicted_variance(self, params=None, ctx=None):
        """(acc, gyro) (T, K, 3) units²: s² (d² + e²) per channel (0 on IMUs without a clock)."""
        return self.term.predicted_variance()


@dataclass
class UnresolvedStage:
    """What :func:`unresolved_stage` found: ``effect`` (an :class:`UnresolvedEffect`, or None when
    no sensor passes), ``evidence`` (nats ×2), ``loglik_gain`` (nats, the kept sensors' ll − ll_null),
    ``info`` (the report's ``details.unresolved_stage``: per sensor the statistic, the permutation
    null, the scales and why a sensor was not kept)."""

    effect: UnresolvedEffect | None
    evidence: float
    loglik_gain: float
    info: dict = field(default_factory=dict)


def _centred_ages(age: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Ages less their mean over the IMUs that enter the sample (weights w (T, K) 0/1), s."""
    n = w.sum(1, keepdim=True).clamp_min(1)
    return (age - (age * w).sum(1, keepdim=True) / n) * w


def physical_ages(clocks, time, K: int) -> torch.Tensor:
    """(T, K) the data age (s) of every IMU at the read times ``time`` (s) on its clock's physical
    sawtooth (:meth:`~accel_bayes.physics.effects.SamplingClock.physical_age`: width 1/``internal_rate_hz``,
    the register holds the latest of samples taken every 1/f_k; the clock's beat, phase and drift);
    0 on IMUs without a clock.  A clock without ``physical_age`` (an object with ``imu`` and
    ``age(t)``, e.g. a simulator's true age) gives its own age.

    Why not the clock's fitted width (``age_rms_s``, :func:`accel_bayes.mismatch.clock.data_age`):
    that is the regression coefficient of the gyro outputs on their rate, shrunk wherever the
    regressor is noisy (0.12–0.32 ms rms on the six real recordings where the sawtooth gives
    0.29 ms), and a term loaded on it carries that shrinkage in its scale — so the scale would not
    mean the same in two recordings.  On the six, the physical width also fits better: the
    term's log-likelihood is higher by 0.6e4–2.2e4 nats on every recording and sensor
    (``experiments/mimu_unresolved_transfer.md``).  The held-out study loads the same physical
    sawtooth (:func:`accel_bayes.mismatch.heldout.clock_age`)."""
    t = torch.as_tensor(time, dtype=torch.float64)
    out = torch.zeros(len(t), K, dtype=torch.float64)
    for c in clocks:
        # an age known exactly (a generator's truth, no physical_age): physical already
        out[:, c.imu] = c.physical_age(t) if hasattr(c, "physical_age") else c.age(t)
    return out


def _ages_and_bands(prep: Prepared, fit: ModelFit, clocks, edges=None):
    """(ages (T, K) s, has (K,) bool: IMUs with a clock, |ω| inner edges, band labels (T,)) at ``fit``;
    ``edges`` (rad/s) absolute |ω| edges to use instead of ``fit``'s own quantiles."""
    has = torch.zeros(prep.K, dtype=torch.bool)
    has[sorted({int(c.imu) for c in clocks})] = True
    edges = omega_edges(fit) if edges is None else [float(e) for e in edges]
    return physical_ages(clocks, prep.time, prep.K), has, edges, _bands(fit, edges)


def _cells(fit: ModelFit, lab: torch.Tensor, od_edges=None) -> tuple[list, torch.Tensor]:
    """(|ω̇| inner edges rad/s², cell (T,) = b·C + c): each sample's |ω| band b (``lab``) and |ω̇|
    band c among the budget's C quantile bands of ``fit``'s motion, or of the absolute edges
    ``od_edges`` (rad/s²) when given."""
    od = np.linalg.norm(fit.x[:, 3:6].detach().cpu().numpy(), axis=1)
    od_edges = band_edges(od) if od_edges is None else [float(e) for e in od_edges]
    C = len(od_edges) + 1
    return od_edges, lab * C + torch.as_tensor(np.digitize(od, od_edges), dtype=torch.long)


def term_for(prep: Prepared, fit: ModelFit, clocks, jerk_rms, angular_acc_rms, *, sensors=SENSORS, std=None,
             grid: bool = False, age_error_rms=(0.0, 0.0), omega_edges=None, omega_dot_edges=None,
             angular_jerk_rms=None) -> UnresolvedEffect:
    """The term with given scales (m/s³, rad/s² per axis) loaded by ``clocks``' physical data ages
    (:func:`physical_ages`) at ``prep``'s samples — e.g. scales fitted on another recording of the
    same board.  Scales per |ω| band b, or with ``grid`` per cell b·C + c (|ω̇| band c,
    :func:`_cells`) with ``age_error_rms`` (acc, gyro) s.  The bands are ``fit``'s own |ω| and |ω̇|
    quantile bands, or the absolute inner edges ``omega_edges`` (rad/s) and ``omega_dot_edges``
    (rad/s²) when given: with scales from another recording, give that recording's edges (its
    report's), so that each borrowed scale is applied to the same motion it was fitted on.
    ``angular_jerk_rms`` (rad/s³, per band or cell like ``jerk_rms``): the board's unresolved angular
    jerk on the accelerometers too, lever arms the design positions about the clocked triads' centroid."""
    age, has, edges, lab = _ages_and_bands(prep, fit, clocks, omega_edges)
    # one term: the accelerometers' and the gyroscopes' ages differ only by which triads enter
    w = has[None, :].to(age.dtype).expand_as(age)
    d = _centred_ages(age, w)
    od_edges = None
    if grid:
        od_edges, lab = _cells(fit, lab, omega_dot_edges)
    term = UnresolvedMotion(d=d, lab=lab, edges=list(edges), jerk_rms=torch.as_tensor(jerk_rms, dtype=torch.float64),
                            angular_acc_rms=torch.as_tensor(angular_acc_rms, dtype=torch.float64),
                            omega_dot_edges=od_edges, age_error_rms=tuple(float(e) for e in age_error_rms), w=w)
    if angular_jerk_rms is not None:
        nominal = torch.as_tensor(prep.nominal, dtype=torch.float64)
        term.angular_jerk_rms = torch.as_tensor(angular_jerk_rms, dtype=torch.float64)
        term.lever = nominal - nominal[has].mean(0, keepdim=True)
    n = (len(edges) + 1) * (len(od_edges) + 1 if grid else 1)
    for name, v in (("jerk_rms", term.jerk_rms), ("angular_acc_rms", term.angular_acc_rms)) + (
            () if angular_jerk_rms is None else (("angular_jerk_rms", term.angular_jerk_rms),)):
        if v.shape != (n,):
            raise ValueError(f"{name}: expected {n} scales ({'cells' if grid else '|omega| bands'}), got {tuple(v.shape)}")
    return UnresolvedEffect(term, std or {}, list(sensors))


def _band_rms_std(s2: torch.Tensor, sd_log: torch.Tensor, cell: torch.Tensor, C: int, B: int) -> list:
    """Standard error (units/s) of each |ω| band's rms √(Σ_c n_bc s²_c / n_b), by the delta method
    from the cells' log-variance standard errors (taken as independent)."""
    out = []
    for b in range(B):
        n = torch.bincount(cell[cell // C == b] - b * C, minlength=C).to(s2.dtype)
        s2b, sdb = s2[b * C:(b + 1) * C], torch.nan_to_num(sd_log[b * C:(b + 1) * C])
        rms = torch.sqrt((n * s2b).sum() / n.sum().clamp_min(1))
        out.append(float(torch.sqrt((((n * s2b) / (2 * n.sum().clamp_min(1) * rms.clamp_min(1e-30))) * sdb).pow(2).sum())))
    return out


def unresolved_stage(prep: Prepared, fit: ModelFit, clocks, *, threshold: float, alpha: float, m: int,
                     n_permutations: int = 19, seed: int = 0, angular_jerk: bool = False) -> UnresolvedStage:
    """Fit and test ``unresolved_motion`` at ``fit`` with the data ages of the accepted ``clocks``
    (:class:`~accel_bayes.physics.effects.SamplingClock`) — module docstring.  ``threshold``,
    ``alpha``, ``m``: the detector's threshold, family-wise rate and Bonferroni count;
    ``n_permutations`` 0 skips the stage.  ``angular_jerk``: the kept accelerometer term also carries
    the board's unresolved angular jerk through the triads' lever arms (design positions; :func:`fit_grid`'s
    ``lever``), its predicted variance part of b; the test is the jerk's alone."""
    from scipy.stats import norm

    imus = sorted({int(c.imu) for c in clocks})
    if len(imus) < 2 or n_permutations < 1:
        why = "fewer than 2 IMUs with an accepted clock" if len(imus) < 2 else "unresolved_permutations = 0"
        return UnresolvedStage(None, 0.0, 0.0, {"skipped": why, "imus": imus})
    age, has, edges, lab = _ages_and_bands(prep, fit, clocks)
    B = len(edges) + 1
    z = float(norm.isf(alpha / max(int(m), 1)))
    rng = np.random.default_rng(seed)
    # the same permutations for both sensors: one pairing broken, two sensors tested on it
    perms = []
    for _ in range(n_permutations):
        idx = np.arange(len(lab))
        for b in range(B):
            sel = np.flatnonzero(lab.numpy() == b)
            idx[sel] = rng.permutation(sel)
        perms.append(torch.as_tensor(idx))
    od_edges, cell = _cells(fit, lab)
    C = len(od_edges) + 1
    # what the model's own variance effects already predict (noise factors, random timing): the term
    # is fitted on top of it, so that b does not count the same variance twice
    known = dict(zip(SENSORS, (v.mean(-1) for v in predicted_extra_variance(prep, fit))))
    scales, ages_rms, stds, kept, per = {}, {}, {}, [], {}
    gain = evidence = 0.0
    for s in SENSORS:
        a, ok = array_residuals(prep, fit, s)
        w = (ok & has[None, :]).to(a.dtype)
        d = _centred_ages(age, w)
        # only the clocked IMUs enter (the others' white variances would have no information)
        a, d, w, ag = a[:, has], d[:, has], w[:, has], age[:, has]
        v0, lv, ls, ll0, ll1, sd = fit_scales(a, d, w, lab, B, std=False)
        v_null = v0[:, lab].T
        stat = _profile_lr(a, d, w, v_null, lab, B)
        null = np.array([_profile_lr(a, _centred_ages(ag[p], w), w, v_null, lab, B) for p in perms])
        bar = max(threshold, float(null.max()), float(null.mean() + z * null.std(ddof=1)) if len(null) > 1 else 0.0)
        ok_s = bool(stat > bar)
        per[s] = {"statistic": stat, "permuted_max": float(null.max()), "permuted_mean": float(null.mean()),
                  "permuted_sd": float(null.std(ddof=1)) if len(null) > 1 else None, "bar": bar,
                  "likelihood_ratio_bands": 2.0 * (ll1 - ll0), "kept": ok_s, "white_var_bands": v0.mean(0).tolist(),
                  _SCALE_NAME[s]: torch.exp(0.5 * ls).tolist()}  # per |ω| band; replaced by the cells' below
        if not ok_s:
            scales[s], ages_rms[s] = torch.zeros(B * C, dtype=a.dtype), 0.0
            continue
        # the kept term's scales per |ω| × |ω̇| cell, the white noise one constant per IMU, and the
        # age error the clocks do not give (fit_grid); the age error is kept only past the threshold
        sig2 = ((prep.sigma_acc if s == "acc" else prep.sigma_gyro) ** 2)[has]
        lever = torch.as_tensor(prep.nominal, dtype=a.dtype)[has] if (angular_jerk and s == "acc") else None
        g = fit_grid(a, d, w, cell, B * C, v_known=known[s][:, has] * w, v_floor=sig2, lever=lever)
        lr_age = 2.0 * (g.loglik - g.loglik_no_age_error)
        # a fit that failed (non-finite scales or likelihood) is never reported: the other one is used,
        # and with neither the sensor is not kept (a report with null scales is refused by calibrate --model)
        fine = [math.isfinite(ll_) and bool(torch.isfinite(s2_).all())
                for ll_, s2_ in ((g.loglik, g.s2), (g.loglik_no_age_error, g.s2_no_age_error))]
        if not any(fine):
            per[s].update(kept=False, why="the scale fit failed (non-finite) with and without the age error")
            scales[s], ages_rms[s] = torch.zeros(B * C, dtype=a.dtype), 0.0
            continue
        use_age = fine[0] and (not fine[1] or not lr_age <= threshold)
        s2, ll, sd_log = (g.s2, g.loglik, g.sd_log_s2) if use_age else (g.s2_no_age_error, g.loglik_no_age_error,
                                                                        torch.full_like(g.s2, float("nan")))
        a2 = g.a2 if use_age else g.a2_no_age_error
        rms = torch.sqrt(s2)
        lr = 2.0 * (ll - ll0)
        per[s].update({"likelihood_ratio": lr, f"{_SCALE_NAME[s]}_cells": rms.tolist(),
                       _SCALE_NAME[s]: [float(torch.sqrt(s2[cell][lab == b].mean())) for b in range(B)],
                       "age_error_rms_s": math.sqrt(g.e2) if use_age else 0.0, "age_error_lr": lr_age,
                       "age_error_kept": bool(use_age), "white_var": (g.v if use_age else g.v_no_age_error).tolist(),
                       "loglik_cells": ll, "loglik_bands": ll1, "loglik_null": ll0})
        if a2 is not None:
            ang_rms = torch.sqrt(a2)
            per[s].update({"angular_jerk_rms_cells": ang_rms.tolist(),
                           "angular_jerk_rms": [float(torch.sqrt(a2[cell][lab == b].mean())) for b in range(B)]})
            scales["angular_jerk"] = ang_rms
        kept.append(s)
        scales[s], ages_rms[s] = rms, (math.sqrt(g.e2) if use_age else 0.0)
        stds[_SCALE_NAME[s]] = _band_rms_std(s2, sd_log, cell, C, B)
        gain += 0.5 * lr
        evidence += lr
    info = {"imus": imus, "omega_edges": [float(e) for e in edges], "omega_dot_edges": [float(e) for e in od_edges],
            "permutations": int(n_permutations), "seed": int(seed), "z": z, "sensors": per, "kept": kept,
            "mean_refit": False, "angular_jerk": bool(angular_jerk)}
    if not kept:
        return UnresolvedStage(None, 0.0, 0.0, info)
    eff = term_for(prep, fit, clocks, scales["acc"], scales["gyro"], sensors=kept, std=stds, grid=True,
                   age_error_rms=(ages_rms["acc"], ages_rms["gyro"]), angular_jerk_rms=scales.get("angular_jerk"))
    info["loglik_gain"] = gain
    return UnresolvedStage(eff, evidence, gain, info)


def _sensor_of(effect) -> str | None:
    return getattr(effect, "which", None) or getattr(effect, "params", {}).get("sensor") or getattr(effect, "sensor", None)


def supersede_random_timing(prep: Prepared, fit: ModelFit, clocks, stage: UnresolvedStage, **stage_kw):
    """(stage, fit, withdrawn): a random timing effect (``timing_wander``, ``sampling_jitter``) on a
    sensor where ``stage`` keeps the age error describes the same thing — that sensor's instant
    error times the motion — on one IMU, with a variance that does not follow the unresolved motion.
    Per sensor (acc, then gyro) the model is refitted without those effects and the stage rerun on
    the refit; the refit replaces ``fit`` when the sensor's log-likelihood with the term
    (``loglik_cells``) is higher without them than with them (their predicted variance a known part,
    their conditional means taken off: the comparison favours keeping them).  ``stage_kw``: the
    arguments of :func:`unresolved_stage`.  ``withdrawn``: [{"effect", "reason", "loglik_with",
    "loglik_without"}]."""
    from .fit import fit_model

    withdrawn = []
    for s in SENSORS:
        info = stage.info.get("sensors", {}).get(s, {})
        if not info.get("age_error_kept"):
            continue
        cands = [e for e in fit.effects if e.kind == "random" and e.name in ("timing_wander", "sampling_jitter")
                 and _sensor_of(e) == s]
        if not cands:
            continue
        refit = fit_model(prep, [e.copy() for e in fit.effects if not any(e is c for c in cands)], init=fit,
                          laplace=False)
        st2 = unresolved_stage(prep, refit, clocks, **stage_kw)
        with_, without = info["loglik_cells"], st2.info.get("sensors", {}).get(s, {}).get("loglik_cells")
        if without is None or not without > with_:
            continue
        withdrawn += [{"effect": e.label(), "loglik_with": with_, "loglik_without": without,
                       "reason": f"superseded by unresolved_motion's age error on the {s} (every clocked IMU)"}
                      for e in cands]
        stage, fit = st2, refit
    return stage, fit, withdrawn

"""The detector's unresolved-motion stage (:func:`accel_bayes.mismatch.detect`, step 7a; issue #27
item 3): ``unresolved_motion`` (:mod:`accel_bayes.mismatch.unresolved`) fitted at the final model,
loaded on every IMU by its accepted clock's data age, on both sensors.

Data.  Per sensor, the final fit's leverage-corrected residuals in the array frame
(:func:`accel_bayes.mismatch.vibration.array_residuals`) on the IMUs that have an accepted
``sampling_clock``; their data ages centred over those IMUs per sample (a common age is absorbed by
the motion states); the |ω| quantile bands of the final fit's motion.  Needs clocks on ≥ 2 IMUs.

Fit.  :func:`~accel_bayes.mismatch.unresolved.fit_scales`: a white variance per IMU and band and
the term's scale per band (``jerk_rms`` m/s³ on the accelerometers, ``angular_acc_rms`` rad/s² on
the gyroscopes), both by maximum likelihood with the per-sample motion marginalised exactly.  The
mean model is not refitted with the term (the term is profiled at the final mean, as the random
effects are); the term's log-likelihood gain is added to the refined model's (``refined.loglik``).

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

Budget: the term's predicted variance s²_b d²_kt per channel-sample (the same on the three axes)
is part of b (:func:`accel_bayes.mismatch.budget.residual_budget`'s ``extra_variance``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from .clock import data_age
from .model import ModelFit
from .prepared import Prepared
from .unresolved import UnresolvedMotion, fit_scales
from .vibration import _bands, _profile_lr, array_residuals, omega_edges

__all__ = ["UnresolvedStage", "UnresolvedEffect", "unresolved_stage", "term_for", "SENSORS"]

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
        self.df = 2 * len(term.edges) + 2 if len(self.sensors) == 2 else len(term.edges) + 1

    def label(self) -> str:
        return "unresolved_motion"

    def vocabulary_parameters(self) -> dict:
        p = {"omega_edges": [float(e) for e in self.term.edges],
             "jerk_rms": [float(x) for x in self.term.jerk_rms],
             "angular_acc_rms": [float(x) for x in self.term.angular_acc_rms], "sensors": self.sensors}
        p.update({f"{k}_std": [float(x) for x in v] for k, v in self._std.items()})
        return p

    def explain(self) -> str:
        return ("board motion faster than the outputs resolve (vibration, impacts), seen through each IMU's clock "
                "data age as a per-sample error common to the board, on " + " and ".join(
                    {"acc": "the accelerometers (jerk)", "gyro": "the gyroscopes (angular acceleration)"}[s]
                    for s in self.sensors))

    def predicted_variance(self, params=None, ctx=None):
        """(acc, gyro) (T, K, 3) units²: s²_b d² per channel (0 on IMUs without a clock)."""
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


def _ages_and_bands(prep: Prepared, fit: ModelFit, clocks):
    """(ages (T, K) s, has (K,) bool: IMUs with a clock, |ω| inner edges, band labels (T,)) at ``fit``."""
    has = torch.zeros(prep.K, dtype=torch.bool)
    has[sorted({int(c.imu) for c in clocks})] = True
    edges = omega_edges(fit)
    return data_age(clocks, prep.time, prep.K), has, edges, _bands(fit, edges)


def term_for(prep: Prepared, fit: ModelFit, clocks, jerk_rms, angular_acc_rms, *, sensors=SENSORS, std=None) -> UnresolvedEffect:
    """The term with given scales per |ω| band (m/s³, rad/s² per axis; band b of ``fit``'s own |ω|
    quantile bands) loaded by ``clocks``' data ages at ``prep``'s samples — e.g. scales fitted on
    another recording of the same board."""
    age, has, edges, lab = _ages_and_bands(prep, fit, clocks)
    # one term: the accelerometers' and the gyroscopes' ages differ only by which triads enter
    d = _centred_ages(age, has[None, :].to(age.dtype).expand_as(age))
    term = UnresolvedMotion(d=d, lab=lab, edges=list(edges), jerk_rms=torch.as_tensor(jerk_rms, dtype=torch.float64),
                            angular_acc_rms=torch.as_tensor(angular_acc_rms, dtype=torch.float64))
    return UnresolvedEffect(term, std or {}, list(sensors))


def unresolved_stage(prep: Prepared, fit: ModelFit, clocks, *, threshold: float, alpha: float, m: int,
                     n_permutations: int = 19, seed: int = 0) -> UnresolvedStage:
    """Fit and test ``unresolved_motion`` at ``fit`` with the data ages of the accepted ``clocks``
    (:class:`~accel_bayes.physics.effects.SamplingClock`) — module docstring.  ``threshold``,
    ``alpha``, ``m``: the detector's threshold, family-wise rate and Bonferroni count;
    ``n_permutations`` 0 skips the stage."""
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
    scales, stds, kept, per = {}, {}, [], {}
    gain = evidence = 0.0
    for s in SENSORS:
        a, ok = array_residuals(prep, fit, s)
        w = (ok & has[None, :]).to(a.dtype)
        d = _centred_ages(age, w)
        # only the clocked IMUs enter (the others' white variances would have no information)
        a, d, w, ag = a[:, has], d[:, has], w[:, has], age[:, has]
        v0, lv, ls, ll0, ll1, sd = fit_scales(a, d, w, lab, B)
        v_null = v0[:, lab].T
        stat = _profile_lr(a, d, w, v_null, lab, B)
        null = np.array([_profile_lr(a, _centred_ages(ag[p], w), w, v_null, lab, B) for p in perms])
        bar = max(threshold, float(null.max()), float(null.mean() + z * null.std(ddof=1)) if len(null) > 1 else 0.0)
        lr = 2.0 * (ll1 - ll0)
        ok_s = bool(stat > bar)
        rms = torch.exp(0.5 * ls)
        per[s] = {"statistic": stat, "permuted_max": float(null.max()), "permuted_mean": float(null.mean()),
                  "permuted_sd": float(null.std(ddof=1)) if len(null) > 1 else None, "bar": bar,
                  "likelihood_ratio": lr, "kept": ok_s, _SCALE_NAME[s]: rms.tolist(),
                  f"{_SCALE_NAME[s]}_std": (0.5 * rms * sd).tolist(),
                  "white_var": v0.mean(0).tolist()}
        if ok_s:
            kept.append(s)
            scales[s] = rms
            stds[_SCALE_NAME[s]] = 0.5 * rms * sd  # d s = ½ s d(log s²)
            gain += 0.5 * lr
            evidence += lr
        else:
            scales[s] = torch.zeros(B, dtype=a.dtype)
    info = {"imus": imus, "omega_edges": [float(e) for e in edges], "permutations": int(n_permutations),
            "seed": int(seed), "z": z, "sensors": per, "kept": kept,
            "mean_refit": False}
    if not kept:
        return UnresolvedStage(None, 0.0, 0.0, info)
    eff = term_for(prep, fit, clocks, scales["acc"], scales["gyro"], sensors=kept, std=stds)
    info["loglik_gain"] = gain
    return UnresolvedStage(eff, evidence, gain, info)

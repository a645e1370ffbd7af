"""A mismatch report with the model's clock and unresolved-motion terms forced on (issue #30, the
coverage must-show with the model's terms): what ``calibrate --model`` reads, built on a recording
where the detector would find nothing to model.

:func:`forced_report` runs the detector's own stages on the recording and keeps what they fit,
whatever its evidence:

* the clock stage (:func:`accel_bayes.mismatch.clock.clock_stage` at the baseline fit, the
  detector's defaults): every IMU's chosen sawtooth (``ClockStage.fits``: the first accepted
  candidate, else the best rejected one) becomes a ``sampling_clock`` finding — acceptance forced;
* the unresolved-motion stage's band fit (:func:`accel_bayes.mismatch.unresolved.fit_scales`, the
  fit its test statistic is made from, on the leverage-corrected array residuals of the fit
  corrected for those clocks, ages centred over the IMUs, the fit's |ω| quantile bands): the
  per-band ``jerk_rms`` and ``angular_acc_rms`` of an ``unresolved_motion`` finding on both sensors —
  the permutation test and the |ω| × |ω̇| grid refit skipped (the grid only refines the scales the
  calibration refits itself: ``calibrate --model`` fits the jerk per report band by type-II ML and
  reads only the bands' angular-acceleration scales).

The smallest honest equivalent of the detector with acceptance forced: the same stages and fits,
without the tests that would drop the terms on clean data.
"""
from __future__ import annotations

import math

import numpy as np
import torch

__all__ = ["forced_report"]


def _clock_finding(est: dict) -> tuple[dict, object]:
    """A ``sampling_clock`` finding (DESIGN §7.2) from one IMU's clock-stage fit, and its effect."""
    from accel_bayes.mismatch.clock import NOMINAL_INTERNAL_RATE_HZ
    from accel_bayes.physics.effects import make_effect

    f_read = float(est["f_read_hz"])
    params = {"internal_rate_hz": f_read * round(NOMINAL_INTERNAL_RATE_HZ / f_read) + float(est["beat_hz"]),
              "beat_hz": float(est["beat_hz"]), "phase": float(est["phase"]),
              "drift_hz_per_s": float(est["drift_hz_per_s"]),
              # a fit without a positive width has no age: width 0 loads nothing
              "age_rms_s": max(float(est["width_s"]), 0.0) / math.sqrt(12.0),
              "filter_delay_acc_minus_gyro_s": 0.0, "rate_scale": float(est["rate_scale"])}
    k = int(est["imu"])
    finding = {"effect": "sampling_clock", "imu": k, "axis": None, "evidence": float(est["evidence"]),
               "parameters": params, "where": {"regime": "all regimes", "time_s": None},
               "explanation": f"IMU {k}: the clock stage's fit, acceptance forced (accepted by the stage: "
                              f"{bool(est['accepted'])})"}
    return finding, make_effect("sampling_clock", imu=k, axis=None, parameters=params)


def forced_report(rec, *, alpha: float = 0.01) -> dict:
    """The report (a DESIGN §7.2 dict ``calibrate(model=…)`` accepts) of ``rec`` with a
    ``sampling_clock`` finding on every IMU with a gyroscope and an ``unresolved_motion`` finding,
    their parameters fitted on ``rec`` (module docstring).  ``alpha``: the detector's default
    family-wise rate (enters only the clock stage's bookkeeping, not what is kept).  Scales in
    m/s³ (jerk) and rad/s² (angular acceleration) per axis, |ω| band edges in rad/s."""
    from accel_bayes.data.mismatch_report import SCHEMA
    from accel_bayes.mismatch.clock import clock_corrected, clock_stage
    from accel_bayes.mismatch.fit import baseline_fit, fit_model
    from accel_bayes.mismatch.prepared import prepare
    from accel_bayes.mismatch.unresolved import fit_scales
    from accel_bayes.mismatch.unresolved_stage import SENSORS, _ages_and_bands, _centred_ages
    from accel_bayes.mismatch.vibration import array_residuals

    prep = prepare(rec)
    base, _ = baseline_fit(prep, use_map=True)
    stage = clock_stage(prep, base, m=1, alpha=alpha, threshold=0.0)
    found = [_clock_finding(est) for est in stage.fits]
    clocks = [c for _, c in found]
    prep_c = clock_corrected(prep, base, clocks)
    fit_c = fit_model(prep_c, [], init=base, laplace=False)
    age, has, edges, lab = _ages_and_bands(prep_c, fit_c, clocks)
    B = len(edges) + 1
    scales = {}
    for s in SENSORS:
        a, ok = array_residuals(prep_c, fit_c, s)
        w = (ok & has[None, :]).to(a.dtype)
        d = _centred_ages(age, w)
        _, _, ls, _, _, _ = fit_scales(a[:, has], d[:, has], w[:, has], lab, B, std=False)
        scales[s] = [float(v) for v in torch.exp(0.5 * ls)]
    um = {"effect": "unresolved_motion", "imu": None, "axis": None, "evidence": 0.0,
          "parameters": {"omega_edges": [float(e) for e in edges], "jerk_rms": scales["acc"],
                         "angular_acc_rms": scales["gyro"], "sensors": list(SENSORS)},
          "where": {"regime": "all |omega| bands", "time_s": None},
          "explanation": "the unresolved-motion stage's band fit, test skipped (forced on)"}
    b = base
    return {"schema": SCHEMA, "mismatch_detected": True, "threshold": float(stage.threshold),
            "baseline": {"loglik": float(b.loglik), "chi2_per_dof": float(b.chi2_per_dof), "dof": int(b.dof)},
            "findings": [f for f, _ in found] + [um], "refined": None,
            "details": {"recording": {"K": int(rec.K), "T_given": int(rec.T)},
                        "forced": {"clock_accepted_by_stage": [int(e["imu"]) for e in stage.fits if e["accepted"]],
                                   "how": "experiments/forced_terms.py: detector stages with acceptance forced",
                                   "age_rms_s": [float(np.sqrt(np.mean(age[:, k].numpy() ** 2)))
                                                 for k in range(age.shape[1])]}}}

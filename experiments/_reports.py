"""Hand-built DESIGN §7.2 mismatch reports and the concealed case they are used with, for the
studies and tests that feed ``calibrate --model`` a report without running the detector.

Written apart from the detector on purpose (the reports are inputs whose content the caller
states); one builder here so the studies and the tests build the same document.
"""
from __future__ import annotations

import numpy as np

__all__ = ["minimal_report", "wander_calibration_case"]


def minimal_report(findings, rec=None, explanation: str = "stated finding") -> dict:
    """A minimal valid DESIGN §7.2 report holding ``findings`` [(effect, imu, parameters)] as the
    detector writes them (evidence 100, regime "all"); with ``rec`` the recording's K and T are
    recorded in ``details`` as the detector does."""
    rows = [{"effect": name, "imu": imu, "axis": None, "evidence": 100.0, "parameters": dict(params),
             "where": {"regime": "all", "time_s": None}, "explanation": explanation}
            for name, imu, params in findings]
    doc = {"schema": "accel_bayes.mismatch/1", "mismatch_detected": bool(rows), "threshold": 20.0,
           "baseline": {"loglik": 0.0, "chi2_per_dof": 1.0, "dof": 1},
           "refined": {"effects": [r["effect"] for r in rows], "loglik": 0.0, "chi2_per_dof": 1.0} if rows else None,
           "findings": rows}
    if rec is not None:
        doc["details"] = {"recording": {"K": int(rec.K), "T_given": int(rec.T), "T": int(rec.T)}}
    return doc


def wander_calibration_case():
    """mimu8 at 100 Hz with a concealed gyro timing wander (2 ms) on one IMU, plus white noise of std
    0.5 rad/s on that gyro (the ``excess_noise_var`` part of the real-data findings); accelerometer
    noise 5 mm/s², stated as the truth, so that the gyro error shared by every triad dominates the
    misspecification.  Returns (recording, true positions (K, 3) m, {"clean": a report without
    findings, "found": the wander and an ``unexplained`` finding as the detector names them})."""
    from experiments import _conceal as C

    case = C.make_case("mimu8", "timing_wander", seed=4, T=800, rate=100.0, magnitude=2e-3, sigma_a=0.005)
    rec, k = case.recording, case.truth["imu"]
    g = np.array(rec.gyro)
    g[:, k] += np.random.default_rng(4).normal(0.0, 0.5, (rec.T, 3))
    rec.gyro = g
    p = case.truth["parameters"]
    found = minimal_report([("timing_wander", k, {"width": p["width"], "correlation": p["correlation"],
                                                  "excess_noise_var": 0.25, "sensor": "gyro"}),
                            ("unexplained", 0, {"chi2_ratio": 5.0, "scales_with": "|omega_dot|"})], rec)
    return rec, np.asarray(case.truth["true_position"]), {"clean": minimal_report([], rec), "found": found}

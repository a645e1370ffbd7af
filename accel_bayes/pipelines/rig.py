"""Rig calibration as a pipeline: recording → :func:`~accel_bayes.inference.rig.fit_rig` → the
DESIGN §7.3 ``positions.json`` with orientation, time offset and clock drift (issue #28 item 1).

``accel-bayes calibrate`` comes here, with no flag, when the recording is a rig: ≥ 2 IMUs that
all have gyroscopes, and either fewer than 3 accelerometer triads (the [C21] projection needs 3)
or IMUs stamped separately (multi-rate NaN-union ``time`` or ``imu_time_offset``, DESIGN §7.1).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import __version__
from ..data import io
from ..data.outputs import to_jsonable
from ..data.positions import positions_document, write_positions
from ..data.validation import is_multirate, rig_model_applies
from ..errors import UserError
from ..inference.rig import RigResult, RigSettings, fit_rig
from ..inference.rig.robust import robust_summary

__all__ = ["is_rig", "RigRun", "calibrate_rig", "write_rig_outputs", "format_rig_table"]


def is_rig(rec) -> bool:
    """True when ``calibrate`` must use the rig model for ``rec``
    (:func:`~accel_bayes.data.validation.rig_model_applies`).  A multi-rate recording that is not a
    gyro rig is refused here: no other model reads it."""
    if rig_model_applies(rec):
        return True
    if is_multirate(rec):
        raise UserError("gyro: a multi-rate recording is calibrated by the rig model, which needs a gyroscope "
                        "on every IMU")
    return False


@dataclass
class RigRun:
    """A finished rig calibration: the fit, the positions document, the input's hash."""

    result: RigResult
    positions: dict
    input_sha256: str | None


def _document(res: RigResult, rec, sha: str | None, settings: RigSettings) -> dict:
    K = rec.K
    doc = positions_document(
        method="map", reference_imu=res.reference_imu, means=res.position, covs=res.position_cov,
        orientations=res.orientation,
        diagnostics={"seconds": res.seconds, "converged": res.converged, "laplace_hessian": res.hessian, "lm_reason": res.reason,
                     "lm_iterations": int(res.n_iter), "chi2_per_dof": res.chi2_per_dof,
                     "unidentified": [{"imu": int(k), "parameter": _NAMES[n]} for k, n in res.unidentified],
                     "warnings": list(res.warnings) + [f"IMU {k}: {_NAMES[n]} unidentified (not excited by the motion)"
                                                       for k, n in res.unidentified]},
        provenance={"version": __version__, "input_sha256": sha, "seed": None,
                    "settings": {"model": "rig", "knot_spacing": res.knot_spacing,
                                 "orientation_prior_deg": settings.orientation_prior_deg,
                                 # s, [gyro, acc]: the grids the walking biases were fitted on
                                 "bias_knot_spacing": [float(v) for v in res.bias_knot_spacing]}})
    doc["model"] = "rig"
    unid = {(int(k), n) for k, n in res.unidentified}
    robust = robust_summary(res)
    for k, e in enumerate(doc["imus"]):
        if k == res.reference_imu:
            e["orientation_cov"] = [[0.0] * 3 for _ in range(3)]
            e["time_offset"] = {"mean": 0.0, "std": 0.0}
            continue
        # strict JSON: an unidentified coordinate has no std (NaN → null)
        js = lambda v: to_jsonable(np.asarray(v, dtype=float), nonfinite="null")  # noqa: E731
        e["orientation_cov"] = js(res.orientation_cov[k])
        e["orientation_std"] = js(np.sqrt(np.clip(np.diag(res.orientation_cov[k]), 0, None)))
        e["time_offset"] = {"mean": js(res.time_offset[k]), "std": js(res.time_offset_std[k])}
        if res.own_stamps[k]:
            e["clock_drift"] = {"mean": js(res.clock_drift[k]), "std": js(res.clock_drift_std[k])}
        # time means of the walking biases, relative to the reference's; the walk densities used
        e["gyro_bias"] = js(res.gyro_bias[k])
        e["acc_bias"] = js(res.acc_bias[k])
        e["bias_random_walk"] = {"gyro": float(res.random_walk[k, 0]), "acc": float(res.random_walk[k, 1])}
        _robust_keys(e, robust.get(k, {}), js)
        names = sorted(_NAMES[n] for kk, n in unid if kk == k)
        if names:
            e["unidentified"] = names
    return doc


_NAMES = {"q": "orientation", "r": "position", "o": "time_offset", "d": "clock_drift"}


def _robust_keys(e: dict, summ: dict, js) -> None:
    """Add the block-sandwich keys beside §7.3's Laplace ``std``/``cov`` (whose meaning stays):
    ``std_robust``, ``cov_robust``, ``std_ratio`` (robust/Laplace), ``std_reported`` (the rig's rule:
    the sandwich where its misspecification test fires, else the Laplace) and ``robust_used``
    (per coordinate) — on the position entry itself, as ``orientation_*`` for the orientation, inside
    ``time_offset`` and ``clock_drift``."""
    for key, target, prefix in (("position", e, ""), ("orientation", e, "orientation_"),
                                ("time_offset", e.get("time_offset"), ""), ("clock_drift", e.get("clock_drift"), "")):
        if key not in summ or target is None:
            continue
        v = summ[key]
        scalar = key in ("time_offset", "clock_drift")
        one = (lambda a: js(np.asarray(a)[0])) if scalar else js  # noqa: E731
        target[f"{prefix}std_robust"] = one(v["std_robust"])
        if not scalar:
            target[f"{prefix}cov_robust"] = js(v["cov_robust"])
        target[f"{prefix}std_ratio"] = one(v["ratio"])
        target[f"{prefix}std_reported"] = one(v["std_reported"])
        used = np.asarray(v["robust_used"], dtype=bool)
        target[f"{prefix}robust_used"] = bool(used[0]) if scalar else [bool(u) for u in used]


def calibrate_rig(recording, settings: RigSettings = RigSettings()) -> RigRun:
    """Calibrate a rig from a recording path (format v1) or an in-memory Recording."""
    sha = None
    if isinstance(recording, (str, Path)):
        sha = io.recording_sha256(recording)
        rec = io.read_recording(recording)
    else:
        rec = recording
    res = fit_rig(rec, settings)
    return RigRun(result=res, positions=_document(res, rec, sha, settings), input_sha256=sha)


def write_rig_outputs(run: RigRun, out_dir) -> dict:
    """Write ``positions.json`` into ``out_dir`` (atomically); returns {"positions": path}."""
    return {"positions": write_positions(run.positions, Path(out_dir) / "positions.json")}


def format_rig_table(run: RigRun) -> str:
    """Per IMU: lever arm (mm) ± std (µm), orientation std (°), time offset (ms) ± std (µs), drift (ppm);
    the stds are the reported ones (Laplace, or the block sandwich where the misspecification test
    fired: marked *)."""
    res = run.result
    robust = robust_summary(res)
    lines = [f"rig model (MAP; stds Laplace, * block sandwich): {len(res.position)} IMUs, reference IMU {res.reference_imu}, "
             f"LM {res.reason} after {res.n_iter} steps, {res.seconds:.1f} s",
             f"{'IMU':>4} {'x mm':>9} {'y mm':>9} {'z mm':>9} {'s µm':>7} {'ori s °':>8} {'offset ms':>10} "
             f"{'s µs':>7} {'drift ppm':>10}"]
    for k in range(len(res.position)):
        if k == res.reference_imu:
            lines.append(f"{k:>4}  reference")
            continue
        m = res.position[k] * 1e3
        rb = robust.get(k, {})
        rms = lambda key, fallback: (float(np.sqrt(np.mean(rb[key]["std_reported"] ** 2))), bool(rb[key]["robust_used"].any())) \
            if key in rb else (fallback, False)  # noqa: E731
        s, ms = rms("position", math.sqrt(max(np.trace(res.position_cov[k]), 0.0) / 3))
        so, mo = rms("orientation", math.sqrt(max(np.trace(res.orientation_cov[k]), 0.0) / 3))
        st, mt = rms("time_offset", float(res.time_offset_std[k]))
        dr = f"{res.clock_drift[k] * 1e6:10.2f}" if res.own_stamps[k] else f"{'-':>10}"
        star = lambda b: "*" if b else " "  # noqa: E731
        lines.append(f"{k:>4} {m[0]:9.3f} {m[1]:9.3f} {m[2]:9.3f} {s * 1e6:7.1f}{star(ms)}{math.degrees(so):8.4f}{star(mo)}"
                     f"{res.time_offset[k] * 1e3:10.4f} {st * 1e6:7.1f}{star(mt)}{dr}")
    for k, n in res.unidentified:
        lines.append(f"unidentified: IMU {k} {_NAMES[n]} (the motion does not excite it)")
    return "\n".join(lines)

"""Intrinsic calibration of one recording, as a library function (``accel-bayes intrinsics``).

:func:`intrinsics` loads the recording (a format-v1 file, or a MIMU4444 stream imported on the
fly), estimates each IMU's accelerometer bias, scale and non-orthogonality and its gyro bias from
the rests (:func:`accel_bayes.prep.intrinsics.estimate_intrinsics`), applies them and measures
the static |acc| − g error before and after (:class:`IntrinsicsRun`); :func:`write_outputs`
writes the ``accel_bayes.intrinsics/1`` JSON and, optionally, the corrected recording.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..constants import G0, RAD_TO_DEG
from ..data.io import load_recording

__all__ = ["IntrinsicsRun", "intrinsics", "write_outputs"]


@dataclass
class IntrinsicsRun:
    """What :func:`intrinsics` returns.

    intrinsics : the :class:`~accel_bayes.prep.intrinsics.Intrinsics`.
    recording : the raw recording; corrected : it with the intrinsics applied.
    raw_err_max, cal_err_max : (K,) largest static | |acc| − g | per IMU before/after, m/s².
    gyro_bias_dps : (K, 3) gyro bias, °/s.
    acc_bias_std_median (m/s²), gyro_bias_std_median_dps (°/s) : medians over IMUs and axes.
    """

    intrinsics: object
    recording: object
    corrected: object
    raw_err_max: np.ndarray
    cal_err_max: np.ndarray
    gyro_bias_dps: np.ndarray
    acc_bias_std_median: float
    gyro_bias_std_median_dps: float

    def has_acc(self, k: int) -> bool:
        """Whether IMU k has an estimated accelerometer (its bias is finite)."""
        return bool(np.isfinite(self.intrinsics.acc_bias[k]).all())

    def has_gyro_bias(self, k: int) -> bool:
        """Whether IMU k has an estimated gyro bias."""
        return bool(np.isfinite(self.intrinsics.gyro_bias[k]).all())


def intrinsics(recording, *, g: float = G0) -> IntrinsicsRun:
    """Estimate and apply the intrinsics of one recording from its rests.

    recording : a path (format-v1 .nc or MIMU4444 .bin/.bin.gz), a Recording or a LoadedRecording.
    g : gravity magnitude, m/s².
    """
    from ..prep.intrinsics import estimate_intrinsics, static_acc_errors

    rec = load_recording(recording, streams=True).recording
    intr = estimate_intrinsics(rec, g=g)
    cal = intr.apply(rec)
    raw_err = np.abs(static_acc_errors(rec, intr.g))
    cal_err = np.abs(static_acc_errors(cal, intr.g))
    with warnings.catch_warnings():  # all-NaN columns (IMUs without accelerometer) give NaN, as intended
        warnings.simplefilter("ignore", RuntimeWarning)
        raw_max = np.array([np.nanmax(raw_err[:, k]) for k in range(intr.K)])
        cal_max = np.array([np.nanmax(cal_err[:, k]) for k in range(intr.K)])
    return IntrinsicsRun(intrinsics=intr, recording=rec, corrected=cal, raw_err_max=raw_max, cal_err_max=cal_max,
                         gyro_bias_dps=RAD_TO_DEG * np.asarray(intr.gyro_bias),
                         acc_bias_std_median=float(np.nanmedian(intr.acc_bias_std)),
                         gyro_bias_std_median_dps=float(np.nanmedian(intr.gyro_bias_std) * RAD_TO_DEG))


def write_outputs(run: IntrinsicsRun, path, *, apply_to=None, overwrite: bool = False) -> dict:
    """Write the intrinsics JSON to ``path`` and, with ``apply_to``, the corrected recording there
    (each file atomically); returns {name: path}."""
    run.intrinsics.to_json(path, overwrite=overwrite)
    paths = {"intrinsics": Path(path)}
    if apply_to:
        from ..data.io import write_recording

        paths["corrected"] = write_recording(run.corrected, apply_to, overwrite=overwrite)
    return paths

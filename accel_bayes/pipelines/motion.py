"""Per-sample motion from a calibrated array, as a library function (``accel-bayes motion``).

:func:`motion` loads the recording (a format-v1 file, or a MIMU4444 stream imported on the fly),
estimates ω, ω̇ and the specific force s at every sample with their uncertainty
(:func:`accel_bayes.inference.motion_estimate.estimate_motion`) and summarises them (:class:`MotionRun`);
:func:`write_outputs` writes the ``accel_bayes.motion/1`` NetCDF file.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..constants import RAD_TO_DEG
from ..data.io import load_recording

__all__ = ["MotionRun", "motion", "prepare_motion", "write_outputs"]

# (variable, factor to the printed unit, printed unit)
_ROWS = (("omega", RAD_TO_DEG, "°/s"), ("omega_dot", RAD_TO_DEG, "°/s²"), ("s", 1.0, "m/s²"))


@dataclass
class MotionRun:
    """What :func:`motion` returns.

    dataset : the ``accel_bayes.motion/1`` xarray Dataset.
    recording : the (loaded) recording.
    rows : per variable (name, max |x|, median std, median noise std, median geometry std, unit)
        over the well-posed samples, in the printed unit (°/s, °/s², m/s²).
    chi2_per_dof : median χ²/dof over all samples, and over the static / dynamic ones (None when
        the recording has no segment labels).
    counts : gyro_clipped, omega_needs_acc, ill_posed and not_converged sample counts.
    """

    dataset: object
    recording: object
    rows: list
    chi2_per_dof: dict
    counts: dict


def motion(recording, calibration, *, intrinsics=None, draws: int = 200, seed: int = 0, geometry: str = "draws",
           acc_noise_std=None, gyro_noise_std=None) -> MotionRun:
    """ω (rad/s), ω̇ (rad/s²) and s (m/s², at the calibration's reference IMU) for every sample.

    recording : a path (format-v1 .nc or MIMU4444 .bin/.bin.gz), a Recording or a LoadedRecording.
    calibration : a positions.json path or document (DESIGN §7.3) or a (K, 3) array, m.
    intrinsics : an intrinsics JSON to apply first.  draws / seed / geometry: the geometry
        uncertainty (draws re-solved per sample, or first-order "linear").
    acc_noise_std, gyro_noise_std : noise std to assume (m/s², rad/s; default the recording's).
    """
    from ..inference.motion_estimate import estimate_motion

    if isinstance(calibration, (str, Path)) and not Path(calibration).exists():
        raise FileNotFoundError(f"{calibration}: no such calibration file")
    rec = load_recording(recording, streams=True).recording
    ds = estimate_motion(prepare_motion(rec, intrinsics), calibration, draws=draws, seed=seed, geometry=geometry,
                         acc_noise_std=acc_noise_std, gyro_noise_std=gyro_noise_std)
    ok = ~ds["ill_posed"].values
    rows = []
    for name, f, unit in _ROWS:
        x = ds[name].values[ok]
        st = ds[f"{name}_std"].values[ok]
        rows.append((name, f * np.abs(x).max(initial=0), f * np.median(st) if st.size else np.nan,
                     f * np.median(ds[f"{name}_std_noise"].values[ok]) if st.size else np.nan,
                     f * np.median(ds[f"{name}_std_geometry"].values[ok]) if st.size else np.nan, unit))
    dof = ds["dof"].values
    ratio = np.where(ok & (dof > 0), ds["chi2"].values / np.maximum(dof, 1), np.nan)
    med = lambda m: float(np.nanmedian(ratio[m])) if np.isfinite(ratio[m]).any() else float("nan")  # noqa: E731
    chi2 = {"all": med(slice(None)), "static": None, "dynamic": None}
    if rec.segment is not None:
        st = np.asarray(rec.segment).astype(str) == "static"
        chi2.update(static=med(st), dynamic=med(~st))
    counts = {"gyro_clipped": int(ds["gyro_clipped"].values.sum()),
              "omega_needs_acc": int(ds["omega_needs_acc"].values.sum()), "ill_posed": int((~ok).sum()),
              "not_converged": int((~ds["converged"].values).sum())}
    return MotionRun(dataset=ds, recording=rec, rows=rows, chi2_per_dof=chi2, counts=counts)


def prepare_motion(rec, intrinsics=None):
    """The :class:`~accel_bayes.prep.prepared.PreparedRecording` motion estimation takes: the
    intrinsics (an :class:`~accel_bayes.prep.intrinsics.Intrinsics` or its JSON path/dict)
    applied first and named in its provenance, every sample kept (an estimate per sample is the
    output), gyroscopes used when the recording has them."""
    from ..prep.prepared import prepare_recording

    note = "none"
    if intrinsics is not None:
        from ..prep.intrinsics import Intrinsics

        intr = intrinsics if isinstance(intrinsics, Intrinsics) else Intrinsics.from_json(intrinsics)
        rec = intr.apply(rec)
        note = intr.source or "given"
    return prepare_recording(rec, select="all", gyro="optional", stated_noise=False, provenance={"intrinsics": note})


def write_outputs(run: MotionRun, path, *, overwrite: bool = False) -> Path:
    """Write the motion NetCDF file (atomically; an existing file only with ``overwrite``)."""
    from ..inference.motion_estimate import write_motion

    return write_motion(run.dataset, path, overwrite=overwrite)

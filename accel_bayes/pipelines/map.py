"""MAP of the [C21] model for one recording, as a library function (``accel-bayes map``).

:func:`map_positions` loads the recording, drops the samples flagged clipped (as ``calibrate``
does by default; ``drop_clipped=False`` fits them), fits θ and ω_t jointly by Levenberg–Marquardt
(:func:`accel_bayes.inference.map.fit_map_recording`) and builds the DESIGN §7.3 positions
document (method "map", Laplace covariance) with :mod:`accel_bayes.data.positions`.
:func:`write_outputs` writes ``positions.json`` and ``omega.csv``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..constants import DEFAULT_PRIOR_STD
from ..data.io import load_recording
from ..data.outputs import write_csv
from ..data.positions import positions_document, write_positions

__all__ = ["MapRun", "map_positions", "write_outputs", "SELECTS", "GYRO_METHODS"]

SELECTS = ("all", "rotation")
GYRO_METHODS = ("sample_cov", "sample_cov_mean", "calibrated")


@dataclass
class MapRun:
    """What :func:`map_positions` returns.

    result : the :class:`~accel_bayes.inference.map.MAPResult` (rows follow ``labels``).
    document : the DESIGN §7.3 ``positions.json`` document (method "map").
    means, std : (K, 3) positions relative to the reference IMU and their Laplace std, m.
    labels : IMU labels with an accelerometer triad that were fitted.
    omega : (T_used, 4) time (s) and ω at the mode (rad/s), the rows of ``omega.csv``.
    n_clipped : samples flagged clipped in the recording (dropped unless ``drop_clipped=False``).
    seconds : wall time of the fit, s.
    warnings : why the result is not trustworthy (empty when LM converged).
    """

    result: object
    document: dict
    means: np.ndarray
    std: np.ndarray
    labels: list
    omega: np.ndarray
    n_clipped: int
    drop_clipped: bool
    seconds: float
    reference_imu: int
    warnings: list


def map_positions(recording, *, prior_std: float = DEFAULT_PRIOR_STD, gyro_method: str = "sample_cov",
                  select: str = "all", max_iter: int = 100, drop_clipped: bool = True,
                  progress: bool = False, phi_prior="empirical") -> MapRun:
    """MAP positions (and Laplace covariance) of the accelerometer triads of one recording.

    recording : a path to a format-v1 file, a :class:`~accel_bayes.data.recording.Recording` or a
        :class:`~accel_bayes.data.io.LoadedRecording`.
    prior_std : std of the Gaussian prior around the nominal positions, m.
    gyro_method : gyroscope posterior ([C21] eq. 30 "sample_cov", "sample_cov_mean", "calibrated").
    select : "all", or "rotation" (drop samples whose mean gyro rate is below 0.5 rad/s).
    max_iter : LM iteration limit.
    drop_clipped : drop samples flagged clipped (the model cannot explain a sensor at its range).
    phi_prior : the prior on φ = [ω̇; s], as in :func:`accel_bayes.pipelines.calibrate.calibrate`:
        "empirical" (default, estimated from the recording), "flat" ([C21]) or a given prior.
    """
    from .. import __version__
    from ..errors import UserError
    from ..inference.map import fit_map_recording
    from ..prep.prepared import prepare_recording
    from ..prep.selection import clipped_mask

    if select not in SELECTS:
        raise UserError(f"select: expected one of {SELECTS}, got {select!r}")
    loaded = load_recording(recording)
    rec = loaded.recording
    n_clip = int(clipped_mask(rec).sum())
    t0 = time.perf_counter()
    prepared = prepare_recording(rec, select=None if select == "all" else "rotation", drop_clipped=drop_clipped)
    res = fit_map_recording(prepared, gyro_method=gyro_method, prior_std=prior_std, max_iter=max_iter,
                            progress=progress, phi_prior=phi_prior)
    seconds = time.perf_counter() - t0
    labels = list(res.imu_labels)
    K = rec.K
    means = np.zeros((K, 3))
    covs = np.zeros((K, 3, 3))
    means[labels] = res.positions.detach().cpu().numpy()
    covs[labels] = res.position_cov().detach().cpu().numpy()
    settings = {"prior_std": prior_std, "gyro_method": gyro_method, "select": select,
                "max_iter": max_iter, "converged": bool(res.converged), "reason": res.reason,
                "n_iter": int(res.n_iter), "imus_used": labels, "drop_clipped": drop_clipped,
                "clipped_samples": n_clip,
                "phi_prior": {"source": "flat"} if res.phi_prior is None else res.phi_prior.describe()}
    reasons = [] if res.converged else [f"LM stopped without converging ({res.reason}); the estimate may be poor"]
    doc = positions_document(method="map", reference_imu=int(rec.reference_imu), means=means, covs=covs,
                             diagnostics={"seconds": seconds, "log_posterior": float(res.log_posterior),
                                          "converged": not reasons, "warnings": reasons},
                             provenance={"version": __version__, "input_sha256": loaded.sha256(),
                                         "seed": None, "settings": settings})
    omega = res.omega.detach().cpu().numpy()
    t = prepared.time
    std = np.sqrt(np.clip(np.diagonal(covs, axis1=1, axis2=2), 0, None))
    return MapRun(result=res, document=doc, means=means, std=std, labels=labels, omega=np.column_stack([t, omega]),
                  n_clipped=n_clip, drop_clipped=bool(drop_clipped), seconds=seconds,
                  reference_imu=int(rec.reference_imu), warnings=reasons)


def write_outputs(run: MapRun, out_dir) -> dict:
    """Write ``positions.json`` and ``omega.csv`` into ``out_dir`` (each file atomically; the CLI
    passes an :class:`~accel_bayes.data.output_sets.OutputDir`); returns {name: path}."""
    out = Path(out_dir)
    paths = {"positions": write_positions(run.document, out / "positions.json")}
    paths["omega"] = write_csv(out / "omega.csv", run.omega, "time_s,omega_x_rad_s,omega_y_rad_s,omega_z_rad_s")
    return paths

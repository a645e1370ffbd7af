"""[S16] self-calibration of accelerometer-only arrays: triad poses and motion, jointly.

The factor graph of [S16] Fig. 2 / eq. 15 — a triad residual per sample and triad (eq. 13), a
process residual between consecutive motion states (eq. 14), one triad's pose fixed (eq. 16) —
solved by the structured Levenberg–Marquardt of :mod:`accel_bayes.inference.lm`.  Modules, in the
order they build on each other:

* :mod:`.factors` — the triad and process residuals, their analytic Jacobians, the motion's
  block-tridiagonal Gauss–Newton matrix and the selected blocks of its inverse;
* :mod:`.motion_priors` — every motion prior: the state transition ([S16] eq. 7 and its smoother
  variants), eq. 8 (fixed variances, bridged over left-out samples) and the continuous-time
  models (white noise on the jerk or the snap);
* :mod:`.problem` — the graph as an LM problem, one LM run with its cost log;
* :mod:`.noise_em` — the process-noise intensities: start and type-II ML fixed point;
* :mod:`.result` — :class:`SelfCalResult`, :class:`SelfCalDiverged`, the poses' covariance;
* :mod:`.scale` — the accelerometer-only scale orbit and the two corrections along it;
* :mod:`.fitcheck` — divergence ([S16] Table III) and the fit check (residuals, scale);
* :mod:`.inputs` — the checked input arrays;
* :mod:`.solve` — the driver :func:`self_calibrate` and its options record.

The public names are re-exported here: ``from accel_bayes.inference.selfcal import
self_calibrate``.  Motion drawn from the process model itself, for tests and studies, is a motion
generator: :func:`accel_bayes.physics.motion_generators.simulate_process_motion`.
"""
from .factors import process_jacobians, process_residuals, triad_jacobians, triad_residuals
from .fitcheck import MISFIT_RMS, UNIDENTIFIED_SCALE_STD, FitCheck, check_divergence, fit_check
from .motion_priors import (
    MOTION_MODEL_DIMS,
    MOTION_STATE_DIMS,
    PROCESS_NOISE_MODES,
    S16_PROCESS_VARIANCES,
    bridged_process_whitening,
    continuous_process_covariance,
    continuous_process_whitening,
    integrated_wiener_covariance,
    process_covariance,
    process_model,
    process_sqrt_information,
    process_transition,
    process_variances,
    wnoj_process_covariance,
    wnoj_process_whitening,
)
from .noise_em import (
    initial_process_intensities,
    initial_smooth_process_intensities,
    process_noise_statistics,
    update_process_intensities,
)
from .problem import build_problem
from .result import SelfCalDiverged, SelfCalResult
from .scale import laplace_scale_nll, marginal_scale_score, scale_orbit
from .solve import SelfcalSolveOptions, self_calibrate

__all__ = [
    "triad_residuals",
    "triad_jacobians",
    "process_residuals",
    "process_jacobians",
    "process_sqrt_information",
    "bridged_process_whitening",
    "MOTION_STATE_DIMS",
    "process_model",
    "process_transition",
    "S16_PROCESS_VARIANCES",
    "process_variances",
    "process_covariance",
    "PROCESS_NOISE_MODES",
    "wnoj_process_covariance",
    "wnoj_process_whitening",
    "MOTION_MODEL_DIMS",
    "integrated_wiener_covariance",
    "continuous_process_covariance",
    "continuous_process_whitening",
    "initial_process_intensities",
    "initial_smooth_process_intensities",
    "process_noise_statistics",
    "update_process_intensities",
    "build_problem",
    "scale_orbit",
    "marginal_scale_score",
    "laplace_scale_nll",
    "SelfCalResult",
    "SelfCalDiverged",
    "check_divergence",
    "SelfcalSolveOptions",
    "self_calibrate",
    "MISFIT_RMS",
    "UNIDENTIFIED_SCALE_STD",
    "FitCheck",
    "fit_check",
]

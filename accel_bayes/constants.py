"""Physical constants and unit conversions used across the package, one definition each.

Degree conversions are named by direction (``x_deg * DEG_TO_RAD`` is in rad, ``x_rad *
RAD_TO_DEG`` in degrees), so that a bare ``DEG`` can never mean the one or the other.
"""
from __future__ import annotations

import math

__all__ = ["G0", "DEG_TO_RAD", "RAD_TO_DEG", "DEFAULT_PRIOR_STD", "DEFAULT_MIN_ROTATION", "DEFAULT_RATE_BINS",
           "DEFAULT_THREADS", "RHAT_MAX", "ESS_PER_CHAIN"]

G0 = 9.80665
"""Standard gravity, m/s² (also the MPU-9150 scale of the MIMU importer)."""

DEG_TO_RAD = math.pi / 180.0
"""rad per degree."""

RAD_TO_DEG = 180.0 / math.pi
"""degrees per rad."""

ACC_PARAMS = ("b_x", "b_y", "b_z", "t_xx", "t_yy", "t_zz", "t_yx", "t_zx", "t_zy")
"""The 9 accelerometer intrinsic parameters per IMU, in the order of ``intrinsics.json``'s
``acc_params`` and of the rows of its ``acc_cov`` (bias, m/s²; then the lower-triangular T)."""

ACC_T_INDEX = ((0, 0), (1, 1), (2, 2), (1, 0), (2, 0), (2, 1))
"""(row, column) in the 3×3 T of each of the six entries ``ACC_PARAMS[3:]``."""

ACC_OUTPUTS = ("as recorded", "rest-calibrated")
"""A mismatch report's ``details.acc_linear_stage.outputs``: the accelerometer outputs its blocks were
estimated on, indexed by whether the preparation applied rest intrinsics (the detector writes it,
``calibrate --model`` matches it; a report without the key was made on the outputs as recorded)."""

DEFAULT_PRIOR_STD = 3e-3
"""m — the [C21] §IV-A Gaussian prior std of the positions, deliberately wider than the
4 mm × 4 mm × 1 mm package (MAP, PmMH, mismatch refits)."""

# The defaults below are the command line's too: kept here, with no numerical import, so that
# ``accel-bayes calibrate --help`` shows them without importing torch (issue #26).  Their modules
# (prep.selection, model.noise, threads, diagnostics.stats) re-export them.

DEFAULT_MIN_ROTATION = 0.5
"""rad/s (≈ 29 °/s) — |ω̄_t| below this marks a sample "without rotation": at 20 mm the centripetal
term ω×(ω×r) is then < 0.25 % of g ([C21] §IV-C)."""

DEFAULT_RATE_BINS = 1
"""Gyro-rate bins of the estimated accelerometer noise model (1: one level per IMU)."""

DEFAULT_THREADS = 1
"""torch CPU threads of a fit: the tensors are small, and extra threads cost more than they give
on a shared machine."""

RHAT_MAX = 1.01
"""R̂ threshold of :func:`accel_bayes.diagnostics.stats.convergence_check` (Vehtari, Gelman, Simpson,
Carpenter & Bürkner 2021, §4: R̂ < 1.01)."""

ESS_PER_CHAIN = 100
"""Bulk and tail ESS per chain before trusting posterior moments (Vehtari et al. 2021, §4): the
default ``ess_min`` of a calibration is this times the number of chains."""

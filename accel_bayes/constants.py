"""Physical constants and unit conversions used across the package, one definition each.

Degree conversions are named by direction (``x_deg * DEG_TO_RAD`` is in rad, ``x_rad *
RAD_TO_DEG`` in degrees), so that a bare ``DEG`` can never mean the one or the other.
"""
from __future__ import annotations

import math

__all__ = ["G0", "DEG_TO_RAD", "RAD_TO_DEG", "DEFAULT_PRIOR_STD"]

G0 = 9.80665
"""Standard gravity, m/s² (also the MPU-9150 scale of the MIMU importer)."""

DEG_TO_RAD = math.pi / 180.0
"""rad per degree."""

RAD_TO_DEG = 180.0 / math.pi
"""degrees per rad."""

DEFAULT_PRIOR_STD = 3e-3
"""m — the [C21] §IV-A Gaussian prior std of the positions, deliberately wider than the
4 mm × 4 mm × 1 mm package (MAP, PmMH, mismatch refits)."""

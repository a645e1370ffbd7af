"""accel_bayes — Bayesian self-calibration of inertial sensor arrays.

See README.md for the pipeline; DESIGN notes live in ``../shared/DESIGN.md``.
"""
__version__ = "0.1.0"

from .arrays import SensorArray, mimu4444_8, mimu4444_32, preset, s16_plate  # noqa: F401
from .errors import RecordingError, UserError  # noqa: F401
from .recording import Recording  # noqa: F401

"""accel_bayes — Bayesian self-calibration of inertial sensor arrays.

The sub-packages follow the pipeline (README "Layout"; the order is ``LAYERS`` in
``tests/test_layering.py``: each imports only from those before it): ``physics`` (geometry,
arrays, motion, the signal model, its Jacobians, the effects library), ``data`` (recordings,
format v1, importers, exporters, output files, the mismatch report schema), ``prep`` (intrinsics,
sample selection), ``model`` (the likelihood, gyro posterior, φ prior, noise and tempering, a
mismatch report read into likelihood terms), ``simulate``, ``inference`` (LM, MAP, CRB,
self-calibration, PmMH), ``diagnostics``, ``mismatch``, ``pipelines`` (calibrate, map, selfcal,
motion, intrinsics, demo: library functions) and ``cli`` (parsing and printing only).
DESIGN notes live in ``../shared/DESIGN.md``.

Importing the package imports no numerical library: the public names below that need torch are
loaded on first use (PEP 562), so that ``accel-bayes --help`` and every refusal of a bad argument
answer without paying for torch (issue #26).
"""
from .errors import RecordingError, UserError

__version__ = "0.2.0"

# public name -> the module that defines it, imported on first access
_LAZY = {
    "Recording": "data.recording",
    "SensorArray": "physics.arrays", "mimu4444_8": "physics.arrays", "mimu4444_32": "physics.arrays",
    "preset": "physics.arrays", "s16_plate": "physics.arrays",
}

__all__ = ["__version__", "RecordingError", "UserError", *_LAZY]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))

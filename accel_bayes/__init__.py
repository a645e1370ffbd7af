"""accel_bayes — Bayesian self-calibration of inertial sensor arrays.

The sub-packages follow the pipeline (README "Layout"): ``physics`` (geometry, arrays, motion,
the signal model, its Jacobians, the effects library), ``data`` (recordings, format v1, importers,
exporters, output files), ``prep`` (intrinsics, sample selection, noise), ``simulate``,
``likelihood``, ``inference`` (LM, MAP, CRB, self-calibration, PmMH), ``mismatch``,
``diagnostics``, ``pipelines`` (calibrate, map, selfcal, motion,
intrinsics, demo: library functions) and ``cli`` (parsing and printing only).  DESIGN notes live in ``../shared/DESIGN.md``.
"""
__version__ = "0.1.0"

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

# Modules that moved into the sub-packages in 0.1 (issue #10).  Their old import paths keep
# working for one release: ``import accel_bayes.io`` gives the very module object
# ``accel_bayes.data.io`` (so monkeypatching, pickles and private names behave as before), with a
# DeprecationWarning naming the new path.
MOVED_MODULES = {
    "geometry": "physics.geometry", "arrays": "physics.arrays", "motion": "physics.motion",
    "models": "physics.models",
    "recording": "data.recording", "io": "data.io", "validation": "data.validation", "mimu": "data.mimu",
    "segments": "data.segments", "positions": "data.positions", "csv_import": "data.csv_import",
    "export": "data.export", "outputs": "data.outputs",
    "intrinsics": "prep.intrinsics", "preprocess": "prep.preprocess", "noise": "prep.noise",
    "inference.pmmh": "inference.mcmc", "inference.priors": "inference.mcmc.priors",
    "inference.damping": "inference.lm.damping", "inference.linear": "inference.lm.linear",
    "inference.robust": "inference.lm.robust",
    "calibrate": "pipelines.calibrate", "demo": "pipelines.demo", "motion_estimation": "inference.motion",
}


class _MovedModule(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``accel_bayes.<old>`` and returns the module at its new path."""

    def find_spec(self, fullname, path=None, target=None):
        head, _, old = fullname.partition(".")
        if head != __name__ or old not in MOVED_MODULES:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        old = spec.name.partition(".")[2]
        new = f"{__name__}.{MOVED_MODULES[old]}"
        warnings.warn(f"{spec.name} moved to {new}; the old path works for one release", DeprecationWarning,
                      stacklevel=3)
        module = importlib.import_module(new)
        self._specs[new] = module.__spec__  # the import machinery stamps the alias spec on it next
        return module

    def exec_module(self, module):  # already executed under its new name: give it its own spec back
        module.__spec__ = self._specs[module.__name__]

    _specs: dict = {}


sys.meta_path.append(_MovedModule())

from .data.recording import Recording  # noqa: E402,F401
from .errors import RecordingError, UserError  # noqa: E402,F401
from .physics.arrays import SensorArray, mimu4444_8, mimu4444_32, preset, s16_plate  # noqa: E402,F401

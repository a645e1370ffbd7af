"""Deprecated: ``accel_bayes.mismatch.refine`` was split (issue #10 item 5) into

* :mod:`accel_bayes.mismatch.prepared` — :func:`prepare`, :class:`Prepared` (the calibration's
  preparation: intrinsics and THE sample selection);
* :mod:`accel_bayes.mismatch.model` — the augmented model and its linear algebra
  (:class:`ModelFit`, :class:`LinearSystem`);
* :mod:`accel_bayes.mismatch.fit` — :func:`fit_model`, :func:`baseline_fit`;
* :mod:`accel_bayes.mismatch.compare` — :func:`compare_fits`, :func:`elpd_loo`,
  :func:`corrected_recording`, :func:`posterior_comparison`;
* :mod:`accel_bayes.mismatch.transfer` — :func:`heldout_fit`.

This module re-exports those public names for one release and warns on import.
"""
import warnings

from ..constants import DEFAULT_PRIOR_STD
from .compare import compare_fits, corrected_recording, elpd_loo, posterior_comparison
from .fit import baseline_fit, fit_model
from .model import LinearSystem, ModelFit
from .prepared import Prepared, prepare
from .transfer import heldout_fit

__all__ = ["Prepared", "ModelFit", "LinearSystem", "prepare", "fit_model", "baseline_fit", "compare_fits", "elpd_loo",
           "corrected_recording", "posterior_comparison", "heldout_fit", "DEFAULT_PRIOR_STD"]

warnings.warn("accel_bayes.mismatch.refine is deprecated: import from accel_bayes.mismatch (or its prepared, model, "
              "fit, compare, transfer modules)", DeprecationWarning, stacklevel=2)

"""Model-mismatch discovery (DESIGN §1, §2 "mismatch", §7.2): find where a recording disagrees
with the nominal array model, name the physics the model left out, add it, refit, compare.

* :mod:`accel_bayes.physics.effects` — the effects library (one class per physical effect,
  vocabulary v1.1), re-exported here;
* :mod:`.locate` — standardized residuals, excess per IMU/axis/regime, posterior predictive check;
* :mod:`.detect` — :func:`detect`, the public entry point (screen → refit → rank → threshold);
* :mod:`.prepared` — the recording prepared as the calibration prepares it (intrinsics, THE
  sample selection), in the fits' form;
* :mod:`.model` — the augmented model and its linear algebra; :mod:`.fit` — fitting it jointly
  with geometry and motion; :mod:`.compare` — before/after comparison (χ²/dof, log-likelihood,
  ELPD by PSIS-LOO); :mod:`.transfer` — held-out transfer of effects to another recording;
* :mod:`.budget` — the residual budget (excess variance per sensor and motion regime, observed
  and explained; vocabulary 1.1);
* :mod:`.jitter` — random effects (``sampling_jitter``): the exact marginal likelihood at a
  mean fit, the profiled width, :func:`random_variance` (predicted extra variance per sample
  and channel, for variance budgets);
* :mod:`.report` — :class:`MismatchReport` and the human report; the §7.2 ``report.json`` format
  (schema, check, reading, writing) is :mod:`accel_bayes.data.mismatch_report`.

>>> from accel_bayes.mismatch import detect          # doctest: +SKIP
>>> report = detect("rec.nc"); report.write("out")   # doctest: +SKIP
"""
from ..physics.effects import EFFECTS, VOCABULARY, Effect, SignalContext, get_effect, make_effect, register_effect
from .detect import candidate_effects, detect, screen, threshold_rule
from .locate import Location, locate
from .compare import compare_fits
from .fit import baseline_fit, fit_model
from .jitter import jitter_evidence, random_variance
from .model import ModelFit
from .prepared import Prepared, prepare
from ..data.mismatch_report import SCHEMA, validate_report
from .report import Finding, MismatchReport

__all__ = [
    "detect", "MismatchReport", "Finding", "SCHEMA", "validate_report",
    "EFFECTS", "VOCABULARY", "Effect", "SignalContext", "get_effect", "make_effect", "register_effect",
    "candidate_effects", "screen", "threshold_rule", "locate", "Location",
    "prepare", "Prepared", "baseline_fit", "fit_model", "compare_fits", "ModelFit",
    "jitter_evidence", "random_variance",
]

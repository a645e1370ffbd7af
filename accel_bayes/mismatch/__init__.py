"""Model-mismatch discovery (DESIGN §1, §2 "mismatch", §7.2): find where a recording disagrees
with the nominal array model, name the physics the model left out, add it, refit, compare.

* :mod:`.effects` — the effects library (one class per physical effect, vocabulary v1);
* :mod:`.locate` — standardized residuals, excess per IMU/axis/regime, posterior predictive check;
* :mod:`.detect` — :func:`detect`, the public entry point (screen → refit → rank → threshold);
* :mod:`.refine` — the augmented model fitted jointly with geometry and motion, before/after
  comparison (χ²/dof, log-likelihood, ELPD by PSIS-LOO);
* :mod:`.report` — :class:`MismatchReport`, the §7.2 ``report.json`` and the human report.

>>> from accel_bayes.mismatch import detect          # doctest: +SKIP
>>> report = detect("rec.nc"); report.write("out")   # doctest: +SKIP
"""
from ..physics.effects import EFFECTS, VOCABULARY, Effect, SignalContext, get_effect, make_effect, register_effect
from .detect import candidate_effects, detect, screen, threshold_rule
from .locate import Location, locate
from .refine import ModelFit, baseline_fit, compare_fits, fit_model, prepare
from .report import SCHEMA, Finding, MismatchReport, validate_report

__all__ = [
    "detect", "MismatchReport", "Finding", "SCHEMA", "validate_report",
    "EFFECTS", "VOCABULARY", "Effect", "SignalContext", "get_effect", "make_effect", "register_effect",
    "candidate_effects", "screen", "threshold_rule", "locate", "Location",
    "prepare", "baseline_fit", "fit_model", "compare_fits", "ModelFit",
]

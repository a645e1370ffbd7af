"""Model-mismatch discovery (DESIGN §1, §2 "mismatch", §7.2): find where a recording disagrees
with the nominal array model, name the physics the model left out, add it, refit, compare.

* :mod:`accel_bayes.physics.effects` — the effects library (one class per physical effect,
  vocabulary v1.1), re-exported here;
* :mod:`.locate` — standardized residuals, excess per IMU/axis/regime, posterior predictive check;
* :mod:`.detector` — :func:`detect`, the public entry point (stages → screen → refit → rank →
  threshold), its options record :class:`~.options.DetectOptions` (:mod:`.options`, torch-free), the
  screens (:mod:`.screens`) and the choice rules (:mod:`.choose`);
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

Importing this package imports no numerical library: the public names below are loaded on first use
(PEP 562), so that ``accel-bayes mismatch`` checks its :class:`DetectOptions` before torch is paid for.
"""
# public name -> the module that defines it, imported on first access
_LAZY = {
    **{n: "..physics.effects" for n in ("EFFECTS", "VOCABULARY", "Effect", "SignalContext", "get_effect", "make_effect",
                                        "register_effect")},
    "detect": ".detector", "DetectOptions": ".options",
    **{n: ".screens" for n in ("candidate_effects", "screen", "threshold_rule")},
    # not ``locate``: the submodule of that name, once imported, would shadow it on the package
    "Location": ".locate", "compare_fits": ".compare", "baseline_fit": ".fit", "fit_model": ".fit",
    "jitter_evidence": ".jitter", "random_variance": ".jitter", "ModelFit": ".model", "Prepared": ".prepared",
    "prepare": ".prepared", "SCHEMA": "..data.mismatch_report", "validate_report": "..data.mismatch_report",
    "Finding": ".report", "MismatchReport": ".report",
}

__all__ = [
    "detect", "DetectOptions", "MismatchReport", "Finding", "SCHEMA", "validate_report",
    "EFFECTS", "VOCABULARY", "Effect", "SignalContext", "get_effect", "make_effect", "register_effect",
    "candidate_effects", "screen", "threshold_rule", "Location",
    "prepare", "Prepared", "baseline_fit", "fit_model", "compare_fits", "ModelFit",
    "jitter_evidence", "random_variance",
]


def __getattr__(name: str):
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    import importlib

    value = getattr(importlib.import_module(_LAZY[name], __name__), name)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(_LAZY))

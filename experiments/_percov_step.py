"""Stop ``calibrate(rec, model=report)`` at its per-sample-covariance step and hand that step to a
probe (the chains are not run): the one interception the probes of that step share
(``angjerk_probe``, ``gyro_common_probe``, ``acc_intrinsics_probe``)."""
from __future__ import annotations

import warnings

__all__ = ["at_percov_step"]


class _Stop(Exception):
    """Raised once the probe has run at the step (the chains are not run)."""


def at_percov_step(rec, report, probe, **calibrate_kwargs) -> None:
    """Run :func:`accel_bayes.pipelines.calibrate.calibrate` on ``rec`` with ``model=report`` (1 chain ×
    (10 + 10) draws, seed 0, plus ``calibrate_kwargs``) up to the point where it builds its per-sample
    likelihood, call ``probe(build, lik, terms, omega_norm, sample_scale, map_res, nominal_acc, prior_std,
    **kw)`` there — ``build`` is that builder (``pipelines.calibrate._model_percov_step``), the rest its
    arguments — and stop.  The builder is restored whatever happens; RuntimeWarnings are silenced."""
    import accel_bayes.pipelines.calibrate as cal

    build = cal._model_percov_step

    def hook(*args, **kw):
        probe(build, *args, **kw)
        raise _Stop

    cal._model_percov_step = hook
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            cal.calibrate(rec, **{"chains": 1, "draws": 10, "warmup": 10, "seed": 0, "progress": False,
                                  **calibrate_kwargs, "model": report})
    except _Stop:
        pass
    finally:
        cal._model_percov_step = build

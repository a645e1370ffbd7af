"""Held-out transfer (:func:`heldout_fit`): effects estimated on one recording, their parameters
held fixed, added to the nominal model of another recording; both models re-fit the positions
and the motion, so their log-likelihoods compare directly (the real-data check of
``experiments/mimu_mismatch.py``).
"""
from __future__ import annotations

import copy as _copy
import time as _time

import torch

from ..constants import DEFAULT_PRIOR_STD
from ..errors import UserError
from ..physics.effects import noise_factors
from .fit import baseline_fit, fit_model
from .model import ModelFit, _loglik_terms
from .prepared import Prepared

__all__ = ["heldout_fit"]


class _Fixed:
    """An effect whose parameters are held at given values (no free parameters, df = 0): it
    perturbs (``mean``) or clips (``clip``) the outputs exactly as the wrapped effect does, but
    the fit never moves it.  Used by :func:`heldout_fit`."""

    parameters = ()
    needs_rates = False

    def __init__(self, effect):
        if effect.kind not in ("mean", "clip"):
            raise UserError(f"{effect.label()}: only mean and clip effects can be held fixed in a fit")
        self.inner = effect.copy()
        self.name = effect.name
        self.kind = effect.kind
        self.imu = effect.imu
        self.needs_rates = effect.needs_rates
        self.params, self.std, self.stats = {}, {}, {}

    df = 0

    def flatten(self, params=None):
        return torch.zeros(0, dtype=torch.float64)

    def unflatten(self, vec):
        return {}

    def prior_scales(self):
        return torch.zeros(0, dtype=torch.float64)

    def _at(self):
        e = _copy.copy(self.inner)
        e.imu = self.imu  # the fit may re-index IMUs into a sub-context
        return e

    def perturbation(self, params, ctx):
        return self._at().perturbation(None, ctx)

    def transform(self, params, acc, gyro, ctx):
        return self._at().transform(None, acc, gyro, ctx)

    def update_stats(self, acc, gyro) -> None:
        pass

    def label(self) -> str:
        return "fixed:" + self.inner.label()


def heldout_fit(prep: Prepared, effects, *, base: "ModelFit | None" = None, prior_std: float = DEFAULT_PRIOR_STD) -> dict:
    """Log-likelihood of a recording under the nominal model and under the nominal model plus
    ``effects`` **held at their given parameter values** (e.g. estimated on another recording).

    Both models re-fit the same nuisance parameters on this recording — positions and the
    per-sample motion — so they have the same number of free parameters and their
    log-likelihoods compare directly (a held-out check: no parameter of the effects is fitted
    here).  ``mean``/``clip`` effects enter the signal model unchanged (:class:`_Fixed`);
    ``noise_level`` effects fix the noise factors (stated std × factor); ``unexplained``
    findings carry no model and are skipped.  ``time_offset`` uses this recording's output
    rates (from ``base``).

    base : the nominal fit of ``prep`` (:func:`baseline_fit`), computed if None.
    Returns {"loglik_nominal", "loglik_fixed", "difference" (fixed − nominal), "per_sample"
    (difference / T), "chi2_per_dof_nominal", "chi2_per_dof_fixed" (stated noise),
    "effects" (labels used), "skipped", "converged", "seconds"}.
    """
    t0 = _time.perf_counter()
    if base is None:
        base, _ = baseline_fit(prep, prior_std=prior_std)
    used, skipped, fixed, noise = [], [], [], []
    for e in effects:
        if e.kind in ("mean", "clip"):
            fixed.append(_Fixed(e))
            used.append(e.label())
        elif e.kind == "noise":
            noise.append(e)
            used.append(e.label())
        else:
            skipped.append(e.label())
    p2 = prep
    if noise:
        fa, fg = noise_factors(noise, prep.K)
        p2 = _copy.copy(prep)
        p2.sigma_acc = prep.sigma_acc * fa
        p2.sigma_gyro = prep.sigma_gyro * fg
    f = fit_model(p2, fixed, init=base, prior_std=prior_std, laplace=False)
    # χ² with the stated noise for both models
    _, quad_stated = _loglik_terms(prep, f.res_acc, f.res_gyro, torch.ones(prep.K, dtype=torch.float64),
                                   torch.ones(prep.K, dtype=torch.float64))
    return {"loglik_nominal": base.loglik, "loglik_fixed": f.loglik, "difference": f.loglik - base.loglik,
            "per_sample": (f.loglik - base.loglik) / prep.T,
            "chi2_per_dof_nominal": base.chi2_per_dof, "chi2_per_dof_fixed": quad_stated / max(base.dof, 1),
            "positions_nominal": base.positions.tolist(), "positions_fixed": f.positions.tolist(),
            "effects": used, "skipped": skipped, "converged": bool(f.converged) and bool(base.converged),
            "seconds": _time.perf_counter() - t0}

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

__all__ = ["heldout_fit", "noise_variances", "predictive_loglik"]


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


def heldout_fit(prep: Prepared, effects, *, base: "ModelFit | None" = None, prior_std: float = DEFAULT_PRIOR_STD,
                return_fit: bool = False) -> dict:
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
    return_fit : also return the fit with the fixed effects under ``"fit"`` (a
        :class:`~accel_bayes.mismatch.model.ModelFit`, not JSON) and the nominal one under ``"base"``.
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
    out = {"loglik_nominal": base.loglik, "loglik_fixed": f.loglik, "difference": f.loglik - base.loglik,
            "per_sample": (f.loglik - base.loglik) / prep.T,
            "chi2_per_dof_nominal": base.chi2_per_dof, "chi2_per_dof_fixed": quad_stated / max(base.dof, 1),
            "positions_nominal": base.positions.tolist(), "positions_fixed": f.positions.tolist(),
            "effects": used, "skipped": skipped, "converged": bool(f.converged) and bool(base.converged),
            "seconds": _time.perf_counter() - t0}
    if return_fit:
        out.update(fit=f, base=base)
    return out


# ---------------------------------------------------------------------- held-out predictive density

def noise_variances(prep: Prepared, fit: ModelFit, *, omega_edges=None, extra=None) -> dict:
    """A Gaussian noise model fitted to a fit's residuals: the variance per IMU, sensor and, with
    ``omega_edges`` (rad/s, increasing inner edges), per |ω| band of the fit's motion — the mean
    leverage-corrected squared residual r²/(1 − h) of the cell minus ``extra`` (a (acc, gyro)
    pair of (T, K, 3) variances the model already predicts per sample, e.g. a random effect's),
    floored at 1 % of the stated variance.  Units²; returns {"edges": edges or [], "acc": (K, B),
    "gyro": (K, B)} numpy arrays, B = len(edges) + 1 bands.

    The physics-free baseline of the held-out comparison (issue #11 item 4) is this with the
    |ω| bands of the *source* recording on its nominal fit; a physics model is its findings plus
    this without bands on its refined fit."""
    import numpy as np

    from .budget import leverage_corrected_sq

    sq = leverage_corrected_sq(prep, fit)
    edges = [] if omega_edges is None else [float(e) for e in omega_edges]
    lab = np.digitize(np.linalg.norm(fit.x[:, 0:3].detach().cpu().numpy(), axis=1), edges)
    out = {"edges": edges}
    for j, (name, sig, m) in enumerate((("acc", prep.sigma_acc, prep.m_acc), ("gyro", prep.sigma_gyro, prep.m_gyro))):
        r2 = sq[j].detach().cpu().numpy()
        if extra is not None:
            r2 = r2 - extra[j].detach().cpu().numpy()
        mm = m.detach().cpu().numpy()
        v = np.zeros((prep.K, len(edges) + 1))
        floor = 0.01 * sig.detach().cpu().numpy() ** 2
        for b in range(len(edges) + 1):
            sel = lab == b
            n = mm[sel].sum((0, 2))
            s = (r2[sel] * mm[sel]).sum((0, 2))
            v[:, b] = np.where(n > 0, s / np.maximum(n, 1), np.nan)
        # a band with no samples in the source borrows the IMU's overall level
        overall = (r2 * mm).sum((0, 2)) / np.maximum(mm.sum((0, 2)), 1)
        v = np.where(np.isfinite(v), v, overall[:, None])
        out[name] = np.maximum(v, floor[:, None])
    return out


def predictive_loglik(prep: Prepared, fit: ModelFit, noise: dict, *, extra=None, wander=(), per_sensor: bool = False):
    """Σ over observed outputs of log N(r̃; 0, v): r̃² = r²/(1 − h) the leverage-corrected squared
    residual of ``fit`` (so that a fit's shrinkage of its own residuals does not pass for
    predictive skill), v the variance of ``noise`` (:func:`noise_variances`, possibly from another
    recording; bands by this fit's |ω|) plus ``extra`` ((acc, gyro) (T, K, 3) per-sample variances
    predicted by the model's independent random effects).  Nats.

    ``wander``: ``timing_wander`` effects (parameters held, e.g. from another recording); their
    triads get the exact joint density of the AR(1) timing error with white noise of variance
    v + ``excess_noise_var`` (:func:`accel_bayes.mismatch.wander.ar1_gain`) instead of
    independent terms — the correlated error predicts a sample from its neighbours, which a
    marginal variance cannot express.  (Unbanded ``noise`` only for those triads: the first
    band's variance is used.)  ``per_sensor``: return {"acc": nats, "gyro": nats} instead."""
    import math

    import numpy as np

    from .budget import leverage_corrected_sq
    from .jitter import jitter_ab
    from .wander import ar1_gain, sample_steps

    sq = leverage_corrected_sq(prep, fit)
    lab = np.digitize(np.linalg.norm(fit.x[:, 0:3].detach().cpu().numpy(), axis=1), noise["edges"])
    joint = {(int(e.imu), e.which): e for e in wander}
    steps = sample_steps(prep.time) if joint else None
    parts = {}
    for j, (name, m) in enumerate((("acc", prep.m_acc), ("gyro", prep.m_gyro))):
        total = 0.0
        r2 = sq[j].detach().cpu().numpy()
        v = np.asarray(noise[name])[:, lab].T[:, :, None] * np.ones_like(r2)  # (T, K, 3)
        if extra is not None:
            v = v + extra[j].detach().cpu().numpy()
        mm = m.detach().cpu().numpy() > 0
        dens = -0.5 * (r2 / v + np.log(2 * np.pi * v))
        for k in range(prep.K):
            e = joint.get((k, name))
            if e is None:
                total += float(dens[:, k][mm[:, k]].sum())
                continue
            sig_m = float((prep.sigma_acc[k] * fit.acc_factor[k]) if name == "acc" else
                          (prep.sigma_gyro[k] * fit.gyro_factor[k]))
            a, b, rr, n = jitter_ab(prep, fit, k, name, with_residual_power=True)
            white = float(np.asarray(noise[name])[k, 0]) + float(e.params["excess_noise_var"])
            c = math.sqrt(white) / sig_m
            g = ar1_gain(a.numpy(), b.numpy(), steps, float(e.params["width"]) / math.sqrt(12.0),
                         float(e.params["correlation"]), c, rr, n)
            total += g - 0.5 * rr - 0.5 * n * math.log(2 * math.pi) - n * math.log(sig_m)
        parts[name] = total
    return parts if per_sensor else parts["acc"] + parts["gyro"]

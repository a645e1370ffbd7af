"""Fitting the augmented model (:mod:`accel_bayes.mismatch.model`) to a prepared recording.

Solver: the package's structured Levenberg–Marquardt
(:class:`accel_bayes.inference.lm.LevenbergMarquardt`: Nielsen damping with Marquardt scaling,
the Schur-complement solver that eliminates the per-sample motion states — cost linear in T —
and its stopping rules), driven by :class:`~accel_bayes.mismatch.model._Model`'s structure-aware
linearisation through the problem protocol (:class:`_ModelProblem`).

Noise factors (``noise_level``) are not in the least-squares problem: after each fit they are
re-estimated in closed form, c² = mean of z² = r²/(σ²(1 − h)) over the IMU's (or all IMUs')
residuals of that sensor, with h the leverage of the per-sample motion states (REML-like: the
leverage correction keeps E[z²] = 1 under the stated noise), and the fit repeated (≤ 5 rounds).

Random effects (``sampling_jitter``, ``timing_wander``) are not in the least-squares problem
either: after the fit their parameters are profiled on the exact marginal likelihood at the
fitted mean and their gains added to the log-likelihood (:mod:`accel_bayes.mismatch.jitter`), and
the mean is refitted, ≤ ``random_rounds`` times until the parameters and the offsets settle:
first with per-sample weights 1/(noise variance + predicted random variance) (IRLS-style,
diagonal: the moment-matched variance's diagonal), then with each random effect's conditional
mean taken off the outputs (GLS; the model's ``offset``), a wander's white part alone in the
weights.
With noise factors in the same model, z² is taken in those weights, so the factors measure
noise beyond the random effects' prediction.

The baseline (:func:`baseline_fit`) starts from the package's MAP
(:func:`accel_bayes.inference.map.fit_map_recording`, calibrated gyros) and is re-optimised under
the augmented model's objective, so "with" and "without" an effect are always two optima of the
same function.
"""
from __future__ import annotations

import math
import time as _time
import warnings
from dataclasses import dataclass, field
from dataclasses import replace as _dc_replace

import torch

from ..constants import DEFAULT_PRIOR_STD
from ..errors import UserError
from ..inference.lm import LevenbergMarquardt, Linearization, StoppingRule
from ..physics.effects import check_effects, model_outputs, noise_factors, output_rates
from .model import ModelFit, _detach_ctx, _gyro_mean, _init_locals, _local_leverage, _loglik_terms, _mean_effects, \
    _Model, _positions, _split_eta
from .jitter import fit_random_effects, random_offsets, variance_ratio, weight_effects
from .prepared import Prepared

__all__ = ["fit_model", "baseline_fit"]


@dataclass
class _LMOut:
    theta: torch.Tensor
    eta: torch.Tensor
    x: torch.Tensor
    cost: float
    converged: bool
    reason: str
    n_iter: int
    log: list
    model: _Model = field(repr=False)


class _ModelProblem:
    """:class:`_Model` through the problem protocol of the package's structured LM
    (:class:`~accel_bayes.inference.lm.LevenbergMarquardt`): globals {"theta" (F, 3), "eta"
    (p,)}, both Euclidean; locals x (T, 9), block-diagonal."""

    local_structure = "diagonal"
    x0 = None

    def __init__(self, model: _Model):
        self.model = model
        self.n_free = model.n

    def linearize(self, values, x, *, step: bool = True) -> Linearization:
        lin = self.model.linearize(values["theta"], values["eta"], x)
        return Linearization(lin["cost"], lin["U"], lin["W"], lin["V"], None, lin["b_g"], lin["b_x"])

    def cost(self, values, x) -> float:
        return self.model.cost(values["theta"], values["eta"], x)

    def retract(self, values, delta):
        F, th, eta = self.model.F, values["theta"], values["eta"]
        return {"theta": th + delta[:3 * F].reshape(F, 3) if F else th,
                "eta": eta + delta[3 * F:] if self.model.p else eta}


def _lm_solve(model: _Model, theta, eta, x, *, max_iter: int = 60, ftol: float = 1e-11, xtol: float = 1e-12,
              gtol: float = 1e-12) -> _LMOut:
    """The package's structured Levenberg–Marquardt (Nielsen damping, Marquardt scaling, Schur
    solver, stopping rules: :class:`~accel_bayes.inference.lm.LevenbergMarquardt`) on the
    linearisation of :class:`_Model` (one iteration is O(T·K), no dense position Jacobian)."""
    lm = LevenbergMarquardt(stopping=StoppingRule(max_iter, ftol, xtol, gtol))
    res = lm.solve(_ModelProblem(model), {"theta": theta, "eta": eta}, x)
    return _LMOut(res.values["theta"], res.values["eta"], res.locals, res.cost, res.converged, str(res.reason),
                  res.n_iter, res.log, model)


def fit_model(prep: Prepared, effects=(), *, init: "ModelFit | None" = None, init_positions=None, init_x=None,
              prior_std: float = DEFAULT_PRIOR_STD, max_iter: int = 60, noise_rounds: int = 5,
              laplace: bool = True, progress: bool = False, random_rounds: int = 4) -> ModelFit:
    """Fit the augmented model (module docstring) with ``effects`` (their current ``params`` are
    the starting values; estimates are written back into them, with Laplace ``std``).

    init : a previous :class:`ModelFit` to start from (positions, motion, shared effects'
        values); else ``init_positions`` (K, 3) and ``init_x`` (T, 9), else the design and the
        gyro mean with least-squares [ω̇; s].
    laplace : compute the effect parameters' Laplace standard deviations (one more
        linearisation; detection refits skip it).  ``progress`` is accepted for symmetry with
        the package's fitters; the structured LM prints nothing.
    """
    t0 = _time.perf_counter()
    effects = check_effects(effects, prep.K, "model effect")
    for e in effects:
        if e.needs_rates and prep.acc_rate is None:
            raise UserError(f"{e.label()}: needs output rates; fit the baseline first (baseline_fit sets them)")
    K = prep.K
    if init is not None:
        pos0 = init.positions.clone()
        x0 = init.x.clone()
    else:
        pos0 = prep.nominal.clone() if init_positions is None else torch.as_tensor(init_positions, dtype=torch.float64)
        pos0 = pos0 - pos0[prep.ref]
        x0 = _init_locals(prep, pos0, _gyro_mean(prep)) if init_x is None else torch.as_tensor(init_x, dtype=torch.float64)
    noise_eff = [e for e in effects if e.kind == "noise"]
    rand_eff = [e for e in effects if e.kind == "random"]
    fa, fg = noise_factors(noise_eff, K)  # each noise effect starts from its current factor
    mean_eff = _mean_effects(effects)
    eta0 = torch.cat([e.flatten() for e in mean_eff]) if mean_eff else torch.zeros(0, dtype=torch.float64)
    rounds = noise_rounds if noise_eff else 1
    lm = model = None
    free = prep.free_imus

    offset = None

    def solve(pos0, x0, eta0, fa, fg):
        # random effects' current widths (a candidate's screening estimate, a previous fit's) give
        # the per-sample weights; None while every width is 0.  A timing_wander's conditional mean
        # (``offset``, once known) is taken off the outputs instead of re-weighting its triad
        wts = weight_effects(rand_eff) if offset is not None else rand_eff
        ratio = variance_ratio(prep, None, wts, fa, fg) if any(float(e.params["width"]) > 0 for e in rand_eff) \
            else None
        model = _Model(prep, effects, fa, fg, pos0, prior_std, var_ratio=ratio, offset=offset)
        th0 = pos0[torch.as_tensor(free)].clone() if free else pos0.new_zeros(0, 3)
        lm = _lm_solve(model, th0, eta0.clone(), x0.clone(), max_iter=max_iter)
        return lm, model, _positions(lm.theta, prep, pos0), lm.x, lm.eta

    for rnd in range(rounds):
        lm, model, pos0, x0, eta0 = solve(pos0, x0, eta0, fa, fg)
        if not noise_eff:
            break
        # closed-form noise factors from leverage-corrected residuals (module docstring)
        z2a, z2g = _z2(prep, model, lm)
        changed = 0.0
        for e in noise_eff:
            z2 = z2a if e.which == "acc" else z2g
            mask = prep.m_acc if e.which == "acc" else prep.m_gyro
            sel = mask.clone()
            if e.imu is not None:
                keep = torch.zeros(K, dtype=torch.float64)
                keep[e.imu] = 1.0
                sel = sel * keep[None, :, None]
            # z2 is in the current model's noise units; take this effect's own factor out, so
            # overlapping noise effects (one IMU and all IMUs) multiply
            f_old = float(e.params["factor"])
            own = z2 * f_old ** 2
            f_new = math.sqrt(float((own * sel).sum() / sel.sum().clamp_min(1)))
            changed = max(changed, abs(f_new - f_old))
            e.set_params({"factor": f_new})
        fa_new, fg_new = noise_factors(noise_eff, K)
        fa, fg = fa_new, fg_new
        if changed < 1e-5:
            break
    if noise_eff and rounds > 1:
        lm, model, pos0, x0, eta0 = solve(pos0, x0, eta0, fa, fg)
    fit = _evaluate(prep, effects, mean_eff, lm, model, pos0, x0, eta0, fa, fg, t0)
    # random effects: parameters profiled at the mean, then the mean refitted with their
    # conditional means taken off the outputs (GLS, jitter.random_offsets), until the parameters
    # and the offsets settle (offsets within 1 % of the noise std anywhere)
    sig = torch.stack((prep.sigma_acc * fa, prep.sigma_gyro * fg))[None, :, :, None]  # (1, 2, K, 1)
    for _ in range(random_rounds if rand_eff else 0):
        w_old = [float(e.params["width"]) for e in rand_eff]
        fit_random_effects(prep, fit)
        w_new = [float(e.params["width"]) for e in rand_eff]
        new_off = random_offsets(prep, fit, rand_eff)
        off_settled = (new_off is None and offset is None) or (
            new_off is not None and offset is not None and float(((new_off - offset) / sig).abs().max()) < 1e-2)
        if max(abs(a - b) / max(b, 1e-12) for a, b in zip(w_old, w_new)) < 1e-3 and off_settled:
            break
        offset = new_off
        lm, model, pos0, x0, eta0 = solve(pos0, x0, eta0, fa, fg)
        fit = _evaluate(prep, effects, mean_eff, lm, model, pos0, x0, eta0, fa, fg, t0)
        if offset is not None:
            # the fit's linear system (fit.linear(): every residual diagnostic, the evidences, the
            # Laplace std) is that of the recorded outputs at the GLS mean, whitened by the noise
            # plus the random effects' whole predicted variance, as with re-weighting alone: the
            # residuals with the conditional means taken off are shrunk below the noise (the
            # BLUP takes part of the noise along the rate too) and would read as too little noise
            diag = _Model(prep, effects, fa, fg, pos0, prior_std, var_ratio=variance_ratio(prep, None, rand_eff, fa, fg))
            diag.gls_offset = offset  # what the mean fit took off (jitter._noise_projection)
            fit.lm = _dc_replace(fit.lm, model=diag)
    else:
        if rand_eff:
            fit_random_effects(prep, fit)
    if mean_eff and laplace:
        _effect_std(fit, mean_eff)
    return fit


def _evaluate(prep, effects, mean_eff, lm, model, pos0, x0, eta0, fa, fg, t0) -> ModelFit:
    """The :class:`ModelFit` of a converged solve (estimates written back into the effects)."""
    K = prep.K
    with torch.no_grad():
        acc, gyro, ctx = model.outputs(lm.theta, lm.eta, lm.x)
        if mean_eff:
            for e, pv in zip(mean_eff, _split_eta(mean_eff, eta0)):
                e.params = {k: v.detach().clone() for k, v in pv.items()}
            # clip effects' derived statistics on the unclipped outputs
            acc_u, gyro_u = model_outputs([e for e in mean_eff if e.kind == "mean"], ctx)
            for e in mean_eff:
                if e.kind == "clip":
                    e.update_stats(acc_u, gyro_u)
    res_acc = (prep.y_acc - acc) * prep.m_acc
    res_gyro = (prep.y_gyro - gyro) * prep.m_gyro
    ll_t, quad = _loglik_terms(prep, res_acc, res_gyro, fa, fg)
    _, quad_stated = _loglik_terms(prep, res_acc, res_gyro, torch.ones(K, dtype=torch.float64),
                                   torch.ones(K, dtype=torch.float64))
    n_params = 9 * prep.T + 3 * len(prep.free_imus) + sum(e.df for e in effects if e.kind != "finding")
    fit = ModelFit(effects=effects, positions=pos0.detach().clone(), x=x0.detach().clone(), acc_factor=fa.clone(),
                   gyro_factor=fg.clone(), loglik=float(ll_t.sum()), loglik_t=ll_t.detach(), chi2_stated=quad_stated,
                   chi2=quad, n_obs=prep.n_obs, n_params=n_params, converged=bool(lm.converged), reason=str(lm.reason),
                   n_iter=int(lm.n_iter), seconds=_time.perf_counter() - t0, pred_acc=acc.detach(),
                   pred_gyro=gyro.detach(), res_acc=res_acc.detach(), res_gyro=res_gyro.detach(),
                   ctx=_detach_ctx(ctx), lm=lm, _prep=prep)
    return fit


def _z2(prep, model: _Model, lm: _LMOut):
    """Leverage-corrected squared standardized residuals (T, K, 3) for acc and gyro at a fit
    (in the fit's own noise units)."""
    r, Jx, _, _ = model.jacobians(lm.theta, lm.eta, lm.x)
    T, K = prep.T, prep.K
    h = _local_leverage(Jx.reshape(T, 6 * K, 9)).reshape(T, 2, K, 3)
    z2 = r ** 2 / (1 - h).clamp_min(1e-3)
    return z2[:, 0], z2[:, 1]


def _effect_std(fit: ModelFit, mean_eff) -> None:
    """Laplace standard deviations of the effect parameters (Schur-reduced information)."""
    try:
        lin = fit.linear()
        F3 = 3 * len(fit._prep.free_imus)
        var = torch.diagonal(lin.Sinv)[F3:].clamp_min(0)
        i = 0
        for e in mean_eff:
            v = var[i:i + e.df].sqrt()
            e.std = e.unflatten(v)
            i += e.df
    except Exception as exc:  # pragma: no cover - a singular system leaves std unknown
        warnings.warn(f"effect standard deviations unavailable: {exc}", RuntimeWarning, stacklevel=2)


def baseline_fit(prep: Prepared, *, use_map: bool = True, prior_std: float = DEFAULT_PRIOR_STD,
                 progress: bool = False) -> tuple[ModelFit, dict]:
    """The nominal model's fit (no effects) and the output rates for ``time_offset``.

    Starts from the package's MAP (:func:`accel_bayes.inference.map.fit_map_recording` with the
    calibrated gyro posterior, Gauss–Newton Laplace) when ``use_map``; falls back to the design
    and the gyro mean if the MAP is unavailable or diverges (recorded in the returned info).
    Sets ``prep.acc_rate``/``prep.gyro_rate`` from the fitted nominal outputs
    (:func:`accel_bayes.physics.effects.output_rates`).  Returns (fit, info).
    """
    info = {"start": "design"}
    init_pos = init_x = None
    if use_map:
        try:
            from ..inference.map import fit_map_recording

            t0 = _time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                # the flat φ of the mismatch model (mismatch/model.py), not calibrate's default prior
                mres = fit_map_recording(prep.prepared, gyro_method="calibrated", prior_std=prior_std,
                                         hessian="gauss_newton", on_divergence="ignore", phi_prior="flat")
            labels = list(mres.imu_labels)
            if mres.converged or not str(mres.reason).startswith("diverged"):
                pos = prep.nominal.clone()
                pos[torch.as_tensor(labels)] = torch.as_tensor(mres.positions, dtype=torch.float64)
                pos = pos - pos[prep.ref]
                idx = getattr(mres, "sample_index", None)
                if idx is None or len(idx) == prep.T:
                    init_pos = pos
                    init_x = _init_locals(prep, pos, torch.as_tensor(mres.omega, dtype=torch.float64))
                    info = {"start": "map", "map_seconds": _time.perf_counter() - t0, "map_reason": str(mres.reason),
                            "map_positions": pos.tolist()}
            if init_pos is None:
                info = {"start": "design", "map_failure": str(mres.reason)}
        except Exception as exc:  # the MAP is a starting point only; the fit below is the result
            info = {"start": "design", "map_failure": f"{type(exc).__name__}: {exc}"}
    fit = fit_model(prep, (), init_positions=init_pos, init_x=init_x, prior_std=prior_std, progress=progress)
    prep.acc_rate, prep.gyro_rate = output_rates(prep.time, fit.ctx.acc, fit.ctx.gyro)
    fit.ctx.acc_rate, fit.ctx.gyro_rate = prep.acc_rate, prep.gyro_rate
    return fit, info

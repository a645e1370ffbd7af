"""The [S16] eq. 15 graph as a problem of the structured LM (:mod:`accel_bayes.inference.lm`), and
one LM run of it with the cost log the self-calibration reports.

The motion states are the locals (eliminated by the block-tridiagonal Schur complement), the
triad poses the globals; the factors are :mod:`.factors`'.
"""
from __future__ import annotations

import torch

from ..lm import ChainResidual, LevenbergMarquardt, Problem, SampleResidual, Variable
from ..lm.damping import MarquardtDamping
from ..lm.linear import SchurComplementSolver
from .factors import _pad_state_columns, _whiten, process_jacobians, triad_jacobians, triad_residuals
from .motion_priors import process_model

__all__ = ["build_problem"]


_LINEARIZE_CHUNK = 2048  # samples per chunk of the triad linearisation (intermediates stay in cache)


def build_problem(
    acc: torch.Tensor,
    dt: torch.Tensor,
    positions: torch.Tensor,
    orientations: torch.Tensor,
    states: torch.Tensor,
    fixed: int,
    inv_std: torch.Tensor,
    sqrt_info: torch.Tensor,
    S: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
    poses_fixed: bool = False,
):
    """The [S16] eq. 15 graph as an :class:`accel_bayes.inference.lm.Problem`.

    Globals "position" (A, 3) and "rotation" (A, 4, quaternion manifold), the fixed triad's rows
    held fixed (all rows with ``poses_fixed``: the motion-only problem); locals: the motion
    states (T, d) (d = 9, or 12/15 with the smoother continuous-time models); residual groups "triad" (per sample, analytic Jacobians of
    :func:`triad_jacobians`) and "process" (chain, :func:`process_jacobians`).
    """
    A = positions.shape[0]
    dim = states.shape[-1]
    fixed_mask = torch.zeros(A, dtype=torch.bool, device=acc.device)
    fixed_mask[fixed] = True
    if poses_fixed:
        fixed_mask[:] = True
    eyeA = torch.eye(A, dtype=acc.dtype, device=acc.device)

    # data = the measurements, so that LM can linearise in chunks of samples (SampleResidual.chunk)
    def triad_fn(g, x, data):
        return triad_residuals(x, g["rotation"], g["position"], data, inv_std, S, offset).reshape(-1, 3 * A)

    def _blockdiag(J):  # (t, A, 3, 3) → (t, 3A, 3A), zero across triads
        return (J.unsqueeze(3) * eyeA[None, :, None, :, None]).reshape(J.shape[0], 3 * A, 3 * A)

    def triad_jac(g, x, data):
        Jx, Jp, Jr = triad_jacobians(x, g["rotation"], g["position"], inv_std, S)
        Jx = _pad_state_columns(Jx, dim)
        return {"position": _blockdiag(Jp), "rotation": _blockdiag(Jr)}, Jx.reshape(-1, 3 * A, dim)

    J_prev, J_next = process_jacobians(dt, sqrt_info)

    def proc_fn(g, xp, xn, data):
        return _whiten(xn - process_model(xp, dt), sqrt_info)

    def proc_jac(g, xp, xn, data):
        return {}, J_prev, J_next

    return Problem(
        {"position": Variable(positions, fixed=fixed_mask),
         "rotation": Variable(orientations, manifold="quaternion", fixed=fixed_mask)},
        states,
        [SampleResidual(triad_fn, data=acc, jac=triad_jac, name="triad", chunk=_LINEARIZE_CHUNK),
         ChainResidual(proc_fn, jac=proc_jac, name="process")],
        dtype=acc.dtype, device=acc.device,
    )


def _run_lm(problem, *, max_iter, ftol, xtol, gtol, progress, desc, damping=None):
    log = []

    def cb(it, values, x, entry):
        if entry["accepted"] or not log:
            terms = problem.cost_terms(values, x)
            ft, fp = 2 * terms["triad"], 2 * terms["process"]
        else:  # a rejected step leaves the point unchanged
            ft, fp = log[-1]["F_triad"], log[-1]["F_process"]
        log.append({"iteration": it, "F_triad": ft, "F_process": fp,
                    "lambda": entry["lambda"], "accepted": bool(entry["accepted"])})

    if damping is None:
        # Marquardt's rule (λ ÷ 10 / × 10) from λ₀ = 10⁻⁶ with diag(H) scaling: on the [S16]
        # problems it needs ~30 % fewer iterations than Nielsen's rule from 10⁻³ (which spends ~10
        # iterations walking λ down after the first step) and reaches the same minima.
        damping = MarquardtDamping(tau=1e-6, scaling="marquardt")
    elif callable(damping) and not hasattr(damping, "update"):
        damping = damping()
    lm = LevenbergMarquardt(damping, SchurComplementSolver("tridiagonal"), max_iter=max_iter, ftol=ftol, xtol=xtol,
                            gtol=gtol, progress=progress, desc=desc, callback=cb)
    terms0 = problem.cost_terms(problem.initial_values(), problem.x0)
    log.append({"iteration": 0, "F_triad": 2 * terms0["triad"], "F_process": 2 * terms0["process"],
                "lambda": float("nan"), "accepted": True})
    res = lm.solve(problem)
    return res, log

"""Levenberg–Marquardt on many small independent dense problems at once (one λ, one stopping reason
and one convergence flag per problem, no Python loop over problems)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import torch

from ... import interrupts

from .damping import DampingStrategy, get_damping
from .linear import damped_step
from .stopping import StoppingRule

__all__ = ["BatchedLevenbergMarquardt", "BatchedLMResult"]


@dataclass
class BatchedLMResult:
    """Outcome of :meth:`BatchedLevenbergMarquardt.solve`, one entry per problem (batch shape B).

    x : (*B, n) solutions; cost : (*B,) F at x; b : (*B, n) −∇F at x; H : (*B, n, n) the
    Gauss–Newton matrix at x (its inverse is the Laplace covariance); converged : (*B,) bool;
    reason : (*B,) int64 codes into :attr:`StoppingRule.REASONS`; n_iter : loop iterations
    (the same for all problems: the loop runs until every problem has stopped).
    """

    x: torch.Tensor
    cost: torch.Tensor
    b: torch.Tensor
    H: torch.Tensor
    converged: torch.Tensor
    reason: torch.Tensor
    n_iter: int

    def reasons(self) -> list:
        """The stopping reason of each problem as a string (flattened batch order)."""
        return [StoppingRule.REASONS[int(c)] for c in self.reason.reshape(-1)]


class BatchedLevenbergMarquardt:
    """Levenberg–Marquardt on many small independent problems at once (no loop over problems).

    The problems share one size n and one ``linearize`` that evaluates all of them together —
    e.g. the 9 motion unknowns of every sample (:mod:`accel_bayes.inference.motion_estimate`, batched over
    samples and geometry draws) or the 9 rest-model parameters of every IMU
    (:mod:`accel_bayes.prep.intrinsics`).  The pieces are those of :class:`LevenbergMarquardt`: the
    damping strategy (:mod:`~accel_bayes.inference.lm.damping`, one λ per problem), the stopping
    rule (:class:`StoppingRule`, one reason per problem) and a batched Cholesky solve of the
    damped n×n systems; a problem whose damped matrix is not positive definite has its step
    refused and its λ raised, as in the structured solver.  Problems that have stopped keep their
    values (per-problem convergence masks) while the others go on.

    Protocol: ``linearize(x) -> (F (*B,), b (*B, n), H (*B, n, n))`` with F the cost in the
    ½‖r‖² convention, b = −∇F and H the Gauss–Newton matrix JᵀJ; ``retract(x, δ)`` (default
    x + δ) for non-Euclidean parameters.  One ``linearize`` per iteration (at the trial point;
    accepted problems keep it).

    Parameters: damping (DampingStrategy, "nielsen", "marquardt" or None = Nielsen with
    Marquardt scaling), stopping (StoppingRule) or max_iter/ftol/xtol/gtol.
    """

    def __init__(self, damping=None, stopping: StoppingRule | None = None, *, max_iter: int = 100,
                 ftol: float = 1e-10, xtol: float = 1e-10, gtol: float = 1e-10):
        self.damping_spec = damping
        self.stopping = stopping if stopping is not None else StoppingRule(max_iter, ftol, xtol, gtol)

    def solve(self, linearize: Callable, x0: torch.Tensor, retract: Callable | None = None, *,
              subset: bool = False) -> BatchedLMResult:
        """Minimise every problem from x0 (*B, n).

        subset : the problem can evaluate a subset of itself: ``linearize(x_sub (k, n), idx (k,))``
            with idx the indices of the problems (x0 must then be (B, n)).  Each iteration then
            evaluates only the problems still running — most stop after a few iterations, so the
            later ones cost little.
        """
        damping: DampingStrategy = get_damping(self.damping_spec)
        stop = self.stopping
        R = StoppingRule.REASONS
        if subset and x0.dim() != 2:
            raise ValueError(f"BatchedLevenbergMarquardt: subset mode needs x0 of shape (B, n), got {tuple(x0.shape)}")
        x = x0.clone()
        F, b, H = linearize(x, torch.arange(x.shape[0], device=x.device)) if subset else linearize(x)
        n = x.shape[-1]
        diag = torch.diagonal(H, dim1=-2, dim2=-1)
        D = damping.scale(diag)
        damping.init(diag, D, batched=True)
        reason = torch.zeros(F.shape, dtype=torch.long, device=x.device)
        n_iter = 0
        while True:
            interrupts.check()  # SIGINT/SIGTERM: stop between iterations (accel_bayes.interrupts)
            active = reason == 0
            code = stop.batched_at_linearization(b.abs().amax(-1) if n else torch.zeros_like(F))
            reason = torch.where(active & (code > 0), code, reason)
            active = reason == 0
            if not bool(active.any()):
                break
            if n_iter >= stop.max_iter:
                reason = torch.where(active, R.index("max_iter"), reason)
                break
            n_iter += 1
            # the running problems (all of them without subset; their own tensors then)
            idx = torch.nonzero(active).squeeze(-1) if subset else None
            sel = (lambda t: t[idx]) if subset else (lambda t: t)  # noqa: E731
            xs, Fs, bs, Hs, Ds, lam, act = sel(x), sel(F), sel(b), sel(H), sel(D), sel(damping.lam), sel(active)
            step, ok = damped_step(Hs, bs, lam.unsqueeze(-1) * Ds)
            ok = ok & act
            pred = 0.5 * (step * (bs + lam.unsqueeze(-1) * Ds * step)).sum(-1)
            x_new = xs + step if retract is None else retract(xs, step)
            F_new, b_new, H_new = linearize(x_new, idx) if subset else linearize(x_new)
            good = ok & (pred > 0) & torch.isfinite(F_new)
            rho = torch.where(good, (Fs - F_new) / torch.where(good, pred, 1.0), -math.inf)
            accepted = good & (rho > 0)
            after = stop.batched_after_step(accepted, Fs, F_new, step.norm(dim=-1), xs.norm(dim=-1))
            xs = torch.where(accepted[..., None], x_new, xs)
            Fs = torch.where(accepted, F_new, Fs)
            bs = torch.where(accepted[..., None], b_new, bs)
            Hs = torch.where(accepted[..., None, None], H_new, Hs)
            if subset:
                rho_all = torch.full_like(F, -math.inf).index_put_((idx,), rho)
                acc_all = torch.zeros_like(active).index_put_((idx,), accepted)
                damping.update(rho_all, acc_all, active)
                x[idx], F[idx], b[idx], H[idx] = xs, Fs, bs, Hs
                D[idx] = torch.where(accepted[..., None], damping.scale(torch.diagonal(Hs, dim1=-2, dim2=-1)), Ds)
            else:
                damping.update(rho, accepted, active)
                x, F, b, H = xs, Fs, bs, Hs
                D = torch.where(accepted[..., None], damping.scale(torch.diagonal(H, dim1=-2, dim2=-1)), D)
            code = torch.where(ok, after, 0)
            code = torch.where((code == 0) & ~accepted & sel(damping.exhausted), R.index("damping_limit"), code)
            if subset:
                reason[idx] = code
            else:
                reason = torch.where(active, code, reason)
        conv = torch.zeros_like(reason, dtype=torch.bool)
        for nm in StoppingRule.CONVERGED:
            conv |= reason == R.index(nm)
        return BatchedLMResult(x=x, cost=F, b=b, H=H, converged=conv, reason=reason, n_iter=n_iter)

"""Levenberg–Marquardt on one structured problem (DESIGN §6), with Schur elimination of the locals,
and its result (minimum, log, information and Laplace covariance)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from ... import interrupts

from .damping import DampingStrategy, get_damping
from .linear import NotPositiveDefinite, SchurComplementSolver, cholesky
from .problem import Problem
from .stopping import StoppingRule

__all__ = ["LevenbergMarquardt", "LMResult", "solve"]


@dataclass
class LMResult:
    """Outcome of :meth:`LevenbergMarquardt.solve`.

    values : dict name → optimised global tensors; locals : (T, d) or None; cost : final F;
    converged : bool; reason : "gtol" | "ftol" | "xtol" (converged) or "max_iter" |
    "damping_limit" | "non_finite"; n_iter : step attempts; log : one dict per attempt with keys
    iteration, cost (after the attempt), step_norm, lambda, rho, accepted, grad_inf.
    """

    values: dict
    locals: torch.Tensor | None
    cost: float
    converged: bool
    reason: str
    n_iter: int
    log: list
    problem: Problem = field(repr=False)

    @property
    def globals(self) -> dict:
        return self.values

    def free_labels(self):
        """(block, tangent index) per row of :meth:`information`."""
        return self.problem.free_labels()

    def information(self, hessian: str = "gauss_newton") -> torch.Tensor:
        """Reduced information matrix of the free global coordinates at the optimum, locals
        marginalised: S = U − W V⁻¹ Wᵀ (Schur complement).  Its inverse is the Laplace covariance.

        hessian : "gauss_newton" (JᵀJ with robust weights, exact Hessians of extra terms) or
            "exact" (full second derivatives by autodiff, see :meth:`Problem.exact_hessian`).
        """
        if hessian == "gauss_newton":
            lin = self.problem.linearize(self.values, self.locals, step=False)
        elif hessian == "exact":
            lin = self.problem.exact_hessian(self.values, self.locals)
        else:
            raise ValueError(f"hessian: expected 'gauss_newton' or 'exact', got {hessian!r}")
        S = SchurComplementSolver(self.problem.local_structure).reduce(lin.U, lin.W, lin.V, lin.V_off)
        return 0.5 * (S + S.T)

    def covariance(self, hessian: str = "gauss_newton") -> torch.Tensor:
        """Laplace covariance of the free globals (inverse of :meth:`information`)."""
        S = self.information(hessian)
        L = cholesky(S, "reduced information matrix")
        return torch.cholesky_inverse(L)


class LevenbergMarquardt:
    """Levenberg–Marquardt on a :class:`Problem` with Schur elimination of the locals.

    Parameters
    ----------
    damping : DampingStrategy | "nielsen" | "marquardt" | None (Nielsen, Marquardt scaling).
    linear_solver : SchurComplementSolver or None (built from the problem's local structure).
    stopping : StoppingRule or None; or pass max_iter/ftol/xtol/gtol.
    progress : show a tqdm bar (cost, λ) — off by default.
    callback : called as callback(iteration, values, locals, log_entry) after each attempt.

    Problem protocol (what :meth:`solve` uses; :class:`Problem` implements it): ``n_free`` and
    ``local_structure`` ("diagonal"/"tridiagonal"); ``linearize(values, x) -> Linearization``;
    ``cost(values, x) -> float``; ``retract(values, δ_free) -> values``; and, only when
    :meth:`solve` is not given start values, ``initial_values()`` and ``x0``.

    One iteration = one step attempt: solve (H + λD) δ = b through the Schur complement, try
    g ⊞ δ_g, x + δ_x, accept if the gain ratio ρ > 0, update λ; re-linearise after acceptance.
    Per-iteration cost is linear in T.  Deterministic: no random numbers anywhere.
    """

    def __init__(self, damping=None, linear_solver: SchurComplementSolver | None = None,
                 stopping: StoppingRule | None = None, *, max_iter: int = 100, ftol: float = 1e-10,
                 xtol: float = 1e-10, gtol: float = 1e-10, progress: bool = False, desc: str = "LM",
                 callback: Callable | None = None):
        self.damping_spec = damping
        self.linear_solver = linear_solver
        self.stopping = stopping if stopping is not None else StoppingRule(max_iter, ftol, xtol, gtol)
        self.progress = bool(progress)
        self.desc = desc
        self.callback = callback

    @staticmethod
    def _norm(values: dict, x) -> float:
        s = sum(float((v * v).sum()) for v in values.values())
        if x is not None:
            s += float((x * x).sum())
        return math.sqrt(s)

    def solve(self, problem: Problem, values: dict | None = None, locals: torch.Tensor | None = None) -> LMResult:
        """Minimise F from the problem's initial values (or the given ones)."""
        damping: DampingStrategy = get_damping(self.damping_spec)
        solver = self.linear_solver or SchurComplementSolver(problem.local_structure)
        stop = self.stopping
        values = problem.initial_values() if values is None else {k: v.clone() for k, v in values.items()}
        x = (problem.x0.clone() if problem.x0 is not None else None) if locals is None else locals.clone()

        lin = problem.linearize(values, x)
        if not math.isfinite(lin.cost):
            raise ValueError("LM: the cost is not finite at the initial point")
        cost = lin.cost
        dg_h, dx_h = lin.diag()
        diag_h = torch.cat((dg_h, dx_h.reshape(-1))) if dx_h is not None else dg_h
        D = damping.scale(diag_h)
        damping.init(diag_h, D)
        log: list[dict] = []
        n_iter = 0
        reason = None
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=stop.max_iter, desc=self.desc, leave=False)
        n = problem.n_free
        try:
            while True:
                interrupts.check()  # SIGINT/SIGTERM: stop between iterations (accel_bayes.interrupts)
                reason = stop.at_linearization(lin.grad_inf, n_iter)
                if reason is not None:
                    break
                n_iter += 1
                lam = damping.lam
                Dg = D[:n]
                Dx = D[n:].reshape(lin.V.shape[:-1]) if lin.V is not None else None
                Ud = lin.U + torch.diag(lam * Dg)
                Vd = lin.V + torch.diag_embed(lam * Dx) if lin.V is not None else None
                entry = {"iteration": n_iter, "lambda": lam, "grad_inf": lin.grad_inf}
                try:
                    dg, dx = solver.solve(Ud, lin.W, Vd, lin.b_g, lin.b_x, lin.V_off)
                except NotPositiveDefinite:
                    damping.update(-math.inf, False)
                    entry.update(cost=cost, step_norm=float("nan"), rho=-math.inf, accepted=False)
                    log.append(entry)
                    if bar is not None:
                        bar.update(1)
                    if damping.exhausted:
                        reason = "damping_limit"
                        break
                    continue
                step_sq = float((dg * dg).sum())
                pred = float(dg @ (lin.b_g + lam * Dg * dg))
                if dx is not None:
                    step_sq += float((dx * dx).sum())
                    pred += float((dx * (lin.b_x + lam * Dx * dx)).sum())
                pred *= 0.5
                step_norm = math.sqrt(step_sq)
                new_values = problem.retract(values, dg)
                new_x = x + dx if dx is not None else x
                new_cost = problem.cost(new_values, new_x)
                if pred > 0 and math.isfinite(new_cost):
                    rho = (cost - new_cost) / pred
                else:
                    rho = -math.inf
                accepted = rho > 0
                entry.update(cost=new_cost if accepted else cost, step_norm=step_norm, rho=rho, accepted=accepted)
                log.append(entry)
                damping.update(rho, accepted)
                x_norm = self._norm(values, x)
                old_cost = cost
                if accepted:
                    values, x, cost = new_values, new_x, new_cost
                if self.callback is not None:
                    self.callback(n_iter, values, x, entry)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(cost=f"{cost:.6g}", lam=f"{lam:.2g}")
                reason = stop.after_step(accepted, old_cost, new_cost, step_norm, x_norm)
                if reason is not None:
                    break
                if accepted:
                    lin = problem.linearize(values, x)
                    dg_h, dx_h = lin.diag()
                    diag_h = torch.cat((dg_h, dx_h.reshape(-1))) if dx_h is not None else dg_h
                    D = damping.scale(diag_h)
                elif damping.exhausted:
                    reason = "damping_limit"
                    break
        finally:
            if bar is not None:
                bar.close()
        return LMResult(values=values, locals=x, cost=cost, converged=reason in StoppingRule.CONVERGED,
                        reason=reason, n_iter=n_iter, log=log, problem=problem)


def solve(problem: Problem, *, damping=None, max_iter: int = 100, ftol: float = 1e-10, xtol: float = 1e-10,
          gtol: float = 1e-10, progress: bool = False, callback: Callable | None = None) -> LMResult:
    """Convenience wrapper: ``LevenbergMarquardt(damping, max_iter=…, …).solve(problem)``."""
    return LevenbergMarquardt(damping, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol,
                              progress=progress, callback=callback).solve(problem)

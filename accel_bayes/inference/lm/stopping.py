"""The stopping rules of both LM loops (ftol / xtol / gtol / max_iter), each test written once."""
from __future__ import annotations

import math

import torch

__all__ = ["StoppingRule"]


class StoppingRule:
    """All stopping tests of the LM loop in one place.

    ftol : stop (converged) after an accepted step with F_old − F_new ≤ ftol·F_old.
    xtol : stop (converged) when ‖δ‖ ≤ xtol·(‖x‖ + xtol) (‖·‖ over free globals and locals; ‖x‖
        over all variable values), accepted or not — no step of that size can change anything.
    gtol : stop (converged) when ‖∇F‖∞ ≤ gtol at a linearisation point.
    max_iter : stop (not converged) after that many step attempts (accepted or rejected).
    flat_rejected : also stop (converged, "ftol") after a *rejected* step that changed F by at
        most ftol·F either way — at round-off level no step can make progress, and raising λ
        until the xtol test fires only costs iterations (default False).
    Beyond these, the loop stops unconverged with "damping_limit" when λ exceeds the strategy's
    lambda_max, and with "non_finite" when the linearisation is not finite.
    """

    CONVERGED = ("gtol", "ftol", "xtol")
    # reason codes of the batched mode (index into REASONS; "" = still running)
    REASONS = ("", "gtol", "ftol", "xtol", "max_iter", "damping_limit", "non_finite")

    def __init__(self, max_iter: int = 100, ftol: float = 1e-10, xtol: float = 1e-10, gtol: float = 1e-10, *,
                 flat_rejected: bool = False):
        if max_iter < 0:
            raise ValueError(f"max_iter must be ≥ 0, got {max_iter}")
        for nm, v in (("ftol", ftol), ("xtol", xtol), ("gtol", gtol)):
            if not v >= 0:
                raise ValueError(f"{nm} must be ≥ 0, got {v}")
        self.max_iter, self.ftol, self.xtol, self.gtol = int(max_iter), float(ftol), float(xtol), float(gtol)
        self.flat_rejected = bool(flat_rejected)

    # The tests themselves, each written once; they take floats (one problem) or (B,) tensors
    # (batched mode) alike.
    def _gtol(self, grad_inf):
        return grad_inf <= self.gtol

    def _ftol(self, accepted, cost_old, cost_new):
        hit = accepted & ((cost_old - cost_new) <= self.ftol * abs(cost_old))
        if self.flat_rejected:
            hit = hit | (~accepted & (abs(cost_old - cost_new) <= self.ftol * abs(cost_old)))
        return hit

    def _xtol(self, step_norm, x_norm):
        return step_norm <= self.xtol * (x_norm + self.xtol)

    def at_linearization(self, grad_inf: float, n_iter: int) -> str | None:
        if not math.isfinite(grad_inf):
            return "non_finite"
        if self._gtol(grad_inf):
            return "gtol"
        if n_iter >= self.max_iter:
            return "max_iter"
        return None

    def after_step(self, accepted: bool, cost_old: float, cost_new: float, step_norm: float, x_norm: float) -> str | None:
        if self._ftol(accepted, cost_old, cost_new):
            return "ftol"
        if self._xtol(step_norm, x_norm):
            return "xtol"
        return None

    def batched_at_linearization(self, grad_inf: torch.Tensor) -> torch.Tensor:
        """Reason codes (B,) (index into :attr:`REASONS`, 0 = go on) at a linearisation point;
        ``max_iter`` is the loop's to apply (one count for all problems)."""
        R = self.REASONS
        code = torch.where(self._gtol(grad_inf), R.index("gtol"), 0)
        return torch.where(torch.isfinite(grad_inf), code, R.index("non_finite"))

    def batched_after_step(self, accepted, cost_old, cost_new, step_norm, x_norm) -> torch.Tensor:
        """Reason codes (B,) after a step attempt, as :meth:`after_step` per problem."""
        R = self.REASONS
        return torch.where(self._ftol(accepted, cost_old, cost_new), R.index("ftol"),
                           torch.where(self._xtol(step_norm, x_norm), R.index("xtol"), 0))

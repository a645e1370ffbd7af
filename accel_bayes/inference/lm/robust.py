"""Robust losses for the least-squares solver (the "kernel" + "corrector" of the PyPose split).

A residual group of the solver is cut into blocks (one block = one sample, or one triad of a
sample, see ``group_size`` in :mod:`accel_bayes.inference.lm`).  With s = ‖r_b‖² the squared
norm of a whitened block, the cost of the block is ½ ρ(s) instead of ½ s.  The robust loss ρ is
applied by *reweighting* (iteratively reweighted least squares): residual and Jacobian rows of a
block are scaled by √ρ'(s), so the Gauss–Newton model becomes ½ Σ ρ'(s) ‖r_b + J_b δ‖².  This is
the first-order ("trivial") corrector; it drops the ρ''-term of the Triggs correction, which keeps
the normal matrix positive semi-definite even where ρ is concave (Cauchy in its tails).  The LM
gain ratio is evaluated with the true robust cost, so steps remain safe.

Every loss here satisfies ρ(0) = 0, ρ'(0) = 1: a block far inside the threshold costs ½ s as in
plain least squares.
"""
from __future__ import annotations

import torch

__all__ = ["RobustLoss", "TrivialLoss", "HuberLoss", "CauchyLoss", "apply_robust", "robust_weights", "get_loss"]


class RobustLoss:
    """Base class: ``rho(s)`` returns (ρ(s), ρ'(s)) for squared norms s ≥ 0 (any shape)."""

    def rho(self, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:  # pragma: no cover - abstract
        raise NotImplementedError

    def __repr__(self) -> str:
        fields = ", ".join(f"{k}={v!r}" for k, v in vars(self).items())
        return f"{type(self).__name__}({fields})"


class TrivialLoss(RobustLoss):
    """ρ(s) = s: ordinary least squares."""

    def rho(self, s):
        return s, torch.ones_like(s)


class HuberLoss(RobustLoss):
    """Huber loss on the block norm with threshold δ (in whitened units, i.e. standard deviations).

    ρ(s) = s for s ≤ δ², 2δ√s − δ² beyond: quadratic core, linear tails (influence bounded by δ).
    """

    def __init__(self, delta: float = 1.345):
        if not delta > 0:
            raise ValueError(f"HuberLoss: delta must be > 0, got {delta}")
        self.delta = float(delta)

    def rho(self, s):
        d2 = self.delta**2
        inside = s <= d2
        root = torch.sqrt(torch.where(inside, torch.full_like(s, d2), s))
        rho = torch.where(inside, s, 2 * self.delta * root - d2)
        rho1 = torch.where(inside, torch.ones_like(s), self.delta / root)
        return rho, rho1


class CauchyLoss(RobustLoss):
    """Cauchy (Lorentzian) loss with scale δ: ρ(s) = δ² log(1 + s/δ²), ρ'(s) = 1/(1 + s/δ²).

    Redescending: a block at s ≫ δ² has almost no influence on the solution.
    """

    def __init__(self, delta: float = 2.3849):
        if not delta > 0:
            raise ValueError(f"CauchyLoss: delta must be > 0, got {delta}")
        self.delta = float(delta)

    def rho(self, s):
        d2 = self.delta**2
        return d2 * torch.log1p(s / d2), 1.0 / (1.0 + s / d2)


_LOSSES = {"linear": TrivialLoss, "trivial": TrivialLoss, "huber": HuberLoss, "cauchy": CauchyLoss}


def get_loss(loss) -> RobustLoss | None:
    """Accept a :class:`RobustLoss`, None, or a name ("huber", "cauchy", "linear")."""
    if loss is None or isinstance(loss, RobustLoss):
        return loss
    if isinstance(loss, str) and loss.lower() in _LOSSES:
        return _LOSSES[loss.lower()]()
    raise ValueError(f"robust loss: expected a RobustLoss, None or one of {sorted(_LOSSES)}, got {loss!r}")


def apply_robust(r: torch.Tensor, jacobians: list, loss: RobustLoss | None, group_size: int | None):
    """Robust cost of a residual group and its reweighted residual/Jacobians.

    r: (B, m) whitened residual rows (B = samples or pairs; a global group uses B = 1).
    jacobians: list of tensors (B, m, k) (one per variable block; None entries pass through).
    group_size: length of a robust block along m (must divide m); None = the whole row.

    Returns (cost, r_w, jacobians_w) with cost = ½ Σ_blocks ρ(s) (a 0-dim tensor) and rows scaled by
    √ρ'(s) of their block.
    """
    if loss is None or isinstance(loss, TrivialLoss):
        return 0.5 * (r * r).sum(), r, jacobians
    B, m = r.shape
    k = m if group_size is None else int(group_size)
    if m % k:
        raise ValueError(f"robust group_size {k} does not divide the residual length {m}")
    rb = r.reshape(B, m // k, k)
    s = (rb * rb).sum(-1)
    rho, rho1 = loss.rho(s)
    w = torch.sqrt(rho1).unsqueeze(-1).expand(B, m // k, k).reshape(B, m)
    jw = [None if J is None else J * w.unsqueeze(-1) for J in jacobians]
    return 0.5 * rho.sum(), r * w, jw


def robust_weights(r: torch.Tensor, loss: RobustLoss | None, group_size: int | None) -> torch.Tensor | None:
    """ρ'(s) of every row element's block, (B, m); None for plain least squares."""
    if loss is None or isinstance(loss, TrivialLoss):
        return None
    B, m = r.shape
    k = m if group_size is None else int(group_size)
    s = (r.reshape(B, m // k, k) ** 2).sum(-1)
    return loss.rho(s)[1].unsqueeze(-1).expand(B, m // k, k).reshape(B, m)

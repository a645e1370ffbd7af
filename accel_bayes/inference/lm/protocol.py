"""What the LM solvers ask of a problem, and the normal-equation blocks it answers with.

:class:`StructuredProblem` is the protocol of :class:`~accel_bayes.inference.lm.LevenbergMarquardt`
(:class:`~accel_bayes.inference.lm.Problem` implements it, and so does the mismatch refinement);
the batched solver's protocol is two callables, see
:class:`~accel_bayes.inference.lm.BatchedLevenbergMarquardt`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

__all__ = ["Linearization", "StructuredProblem"]


@dataclass
class Linearization:
    """Normal-equation blocks at one point (see :mod:`accel_bayes.inference.lm.linear`).

    cost: float; U (n, n); W (T, n, d) or None; V (T, d, d) or None; V_off (T−1, d, d) or None;
    b_g (n,) = −∂F/∂g; b_x (T, d) = −∂F/∂x (or None).
    """

    cost: float
    U: torch.Tensor
    W: torch.Tensor | None
    V: torch.Tensor | None
    V_off: torch.Tensor | None
    b_g: torch.Tensor
    b_x: torch.Tensor | None

    @property
    def grad_inf(self) -> float:
        g = self.b_g.abs().max() if self.b_g.numel() else self.b_g.new_zeros(())
        if self.b_x is not None and self.b_x.numel():
            g = torch.maximum(g, self.b_x.abs().max())
        return float(g)

    def diag(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        dg = torch.diagonal(self.U)
        dx = None if self.V is None else torch.diagonal(self.V, dim1=-2, dim2=-1)
        return dg, dx



class StructuredProblem(Protocol):
    """A least-squares problem with global blocks (free tangent size ``n_free``) and optional local
    blocks x (T, d) coupled as ``local_structure`` says ("diagonal" or "tridiagonal")."""

    n_free: int
    local_structure: str

    def linearize(self, values: dict, x: torch.Tensor | None) -> Linearization:
        """Cost and Gauss–Newton blocks at (values, x)."""

    def cost(self, values: dict, x: torch.Tensor | None) -> float:
        """F at (values, x)."""

    def retract(self, values: dict, delta_free: torch.Tensor) -> dict:
        """values ⊞ δ (δ over the free global coordinates)."""

"""Global variable blocks of an LM problem: Euclidean tensors or unit quaternions on their manifold
(tangent: rotation vectors, rad; update ``geometry.boxplus``), each with an optional fixed mask."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

__all__ = ["Variable", "EUCLIDEAN", "QUATERNION"]

EUCLIDEAN = "euclidean"
QUATERNION = "quaternion"


@dataclass
class Variable:
    """A global variable block.

    value : tensor — Euclidean (any shape) or unit quaternions (..., 4) (w, x, y, z).
    manifold : "euclidean" (default) or "quaternion" (tangent: rotation vectors (..., 3), rad).
    fixed : bool or bool tensor over the tangent shape (or a prefix of it) — True = held fixed.
    """

    value: torch.Tensor
    manifold: str = EUCLIDEAN
    fixed: Any = False

    def __post_init__(self):
        if self.manifold not in (EUCLIDEAN, QUATERNION):
            raise ValueError(f"Variable.manifold: expected 'euclidean' or 'quaternion', got {self.manifold!r}")
        if self.manifold == QUATERNION and (self.value.dim() == 0 or self.value.shape[-1] != 4):
            raise ValueError(f"Variable: a quaternion block needs shape (..., 4), got {tuple(self.value.shape)}")

    @property
    def tangent_shape(self) -> tuple:
        return tuple(self.value.shape) if self.manifold == EUCLIDEAN else tuple(self.value.shape[:-1]) + (3,)

    def free_mask(self) -> torch.Tensor:
        """(tangent_shape) bool, True where the coordinate is optimised."""
        shp = self.tangent_shape
        m = torch.as_tensor(self.fixed, dtype=torch.bool, device=self.value.device)
        if m.dim() > len(shp) or tuple(m.shape) != tuple(shp[: m.dim()]) and m.dim() > 0:
            raise ValueError(f"Variable.fixed: expected a bool or a mask of shape {shp} (or a prefix), "
                             f"got shape {tuple(m.shape)}")
        while m.dim() < len(shp):
            m = m.unsqueeze(-1)
        return ~m.expand(shp)


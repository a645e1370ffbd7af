"""Damping strategies for Levenberg–Marquardt (the "strategy" of the PyPose split).

The LM step solves (H + λ D) δ = −g, with H the Gauss–Newton matrix, g the gradient and D a
diagonal scaling: D = I (Levenberg) or D = diag(H) (Marquardt scaling, invariant to the units of
the variables — positions in metres next to angular rates in rad/s).  A strategy owns λ and its
update from the gain ratio

    ρ = (F(x) − F(x + δ)) / (L(0) − L(δ)),   L(0) − L(δ) = ½ δᵀ(λ D δ − g),

the actual over the predicted cost decrease.  Two rules are offered:

* :class:`NielsenDamping` (default; H. B. Nielsen, "Damping parameter in Marquardt's method",
  IMM-REP-1999-05; Madsen, Nielsen & Tingleff, "Methods for non-linear least squares problems",
  2004, §3.2): accept if ρ > 0 and set λ ← λ·max(1/3, 1 − (2ρ − 1)³), ν ← 2; otherwise
  λ ← λ·ν, ν ← 2ν.  Smooth in ρ, and repeated failures grow λ geometrically faster.
* :class:`MarquardtDamping` (Marquardt 1963, the classic rule): accept if ρ > 0; λ ← λ/down if
  ρ > 0.75, λ ← λ·up if ρ < 0.25 (or the step is rejected).

Both start from λ₀ = τ·max(diag H·/D) — i.e. τ·max diag(H) with Levenberg scaling and τ with
Marquardt scaling — and refuse λ beyond ``lambda_max`` (the solver then stops, reason
"damping_limit").
"""
from __future__ import annotations

import torch

__all__ = ["DampingStrategy", "NielsenDamping", "MarquardtDamping", "get_damping"]


class DampingStrategy:
    """Base class.  Parameters
    ----------
    tau : float, default 1e-3 — λ₀ = τ·max(diag(H)/D).
    scaling : "marquardt" (D = diag H, clamped below at ``min_diagonal``·max diag H) or "levenberg"
        (D = I).  Default "marquardt".
    lambda_min, lambda_max : float — bounds on λ; λ is clamped below, and exceeding the upper bound
        ends the optimisation.
    min_diagonal : float, default 1e-10 — relative floor of the Marquardt diagonal, so a variable the
        data do not touch still gets damped.
    """

    def __init__(self, tau: float = 1e-3, scaling: str = "marquardt", lambda_min: float = 1e-15,
                 lambda_max: float = 1e16, min_diagonal: float = 1e-10):
        if not tau > 0:
            raise ValueError(f"tau must be > 0, got {tau}")
        if scaling not in ("marquardt", "levenberg"):
            raise ValueError(f"scaling: expected 'marquardt' or 'levenberg', got {scaling!r}")
        if not 0 < lambda_min < lambda_max:
            raise ValueError("expected 0 < lambda_min < lambda_max")
        self.tau = float(tau)
        self.scaling = scaling
        self.lambda_min = float(lambda_min)
        self.lambda_max = float(lambda_max)
        self.min_diagonal = float(min_diagonal)
        self.lam = None

    # ------------------------------------------------------------------ scaling
    def scale(self, diag_h: torch.Tensor) -> torch.Tensor:
        """The diagonal D (same shape as diag_h) for the current linearisation."""
        if self.scaling == "levenberg":
            return torch.ones_like(diag_h)
        top = diag_h.abs().max() if diag_h.numel() else torch.ones((), dtype=diag_h.dtype)
        floor = torch.clamp(top * self.min_diagonal, min=torch.finfo(diag_h.dtype).tiny)
        return torch.maximum(diag_h, floor)

    def init(self, diag_h: torch.Tensor, D: torch.Tensor) -> float:
        """Set and return λ₀ from the first linearisation."""
        ratio = (diag_h / D).max() if diag_h.numel() else torch.ones(())
        self.lam = min(max(self.tau * float(ratio), self.lambda_min), self.lambda_max)
        self._reset_state()
        return self.lam

    def _reset_state(self):
        pass

    def update(self, rho: float, accepted: bool) -> float:  # pragma: no cover - abstract
        """New λ after a step with gain ratio ρ (accepted or not)."""
        raise NotImplementedError

    @property
    def exhausted(self) -> bool:
        """True once λ exceeds lambda_max (no step can make progress)."""
        return self.lam is not None and self.lam > self.lambda_max

    def __repr__(self):
        return f"{type(self).__name__}(tau={self.tau}, scaling={self.scaling!r})"


class NielsenDamping(DampingStrategy):
    """Nielsen's rule (see module docstring)."""

    def _reset_state(self):
        self.nu = 2.0

    def update(self, rho, accepted):
        if accepted:
            self.lam = max(self.lam * max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), self.lambda_min)
            self.nu = 2.0
        else:
            self.lam = self.lam * self.nu
            self.nu = 2.0 * self.nu
        return self.lam


class MarquardtDamping(DampingStrategy):
    """Marquardt's rule: λ/``down`` if ρ > 0.75, λ·``up`` if ρ < 0.25 or the step is rejected."""

    def __init__(self, *args, up: float = 10.0, down: float = 10.0, **kw):
        super().__init__(*args, **kw)
        if not (up > 1 and down > 1):
            raise ValueError("MarquardtDamping: up and down must be > 1")
        self.up, self.down = float(up), float(down)

    def update(self, rho, accepted):
        if accepted and rho > 0.75:
            self.lam = max(self.lam / self.down, self.lambda_min)
        elif not accepted or rho < 0.25:
            self.lam = self.lam * self.up
        return self.lam


def get_damping(damping) -> DampingStrategy:
    """Accept a strategy instance, None (Nielsen, Marquardt scaling) or "nielsen"/"marquardt"."""
    if damping is None:
        return NielsenDamping()
    if isinstance(damping, DampingStrategy):
        return damping
    if damping == "nielsen":
        return NielsenDamping()
    if damping == "marquardt":
        return MarquardtDamping()
    raise ValueError(f"damping: expected a DampingStrategy, None, 'nielsen' or 'marquardt', got {damping!r}")

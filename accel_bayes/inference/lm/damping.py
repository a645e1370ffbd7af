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

Batched mode (many small independent problems solved together, :class:`~accel_bayes.inference.lm.
BatchedLevenbergMarquardt`): :meth:`DampingStrategy.init` with ``batched=True`` takes diag H of
shape (B, n) and keeps one λ per problem, a (B,) tensor; :meth:`~DampingStrategy.update` then takes
ρ and ``accepted`` as (B,) tensors and applies the same rule to each problem elementwise, and
:attr:`~DampingStrategy.exhausted` is a (B,) mask.  Each rule is stated once per class, its scalar
and elementwise forms side by side (``tests/inference/test_lm.py`` checks that they agree).
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
        """The diagonal D (same shape as diag_h) for the current linearisation; in batched mode
        diag_h is (B, n) and the floor is relative to each problem's own largest entry."""
        if self.scaling == "levenberg":
            return torch.ones_like(diag_h)
        if self.batched:
            top = diag_h.abs().amax(-1, keepdim=True) if diag_h.shape[-1] else torch.ones_like(diag_h[..., :1])
        else:
            top = diag_h.abs().max() if diag_h.numel() else torch.ones((), dtype=diag_h.dtype)
        floor = torch.clamp(top * self.min_diagonal, min=torch.finfo(diag_h.dtype).tiny)
        return torch.maximum(diag_h, floor)

    def init(self, diag_h: torch.Tensor, D: torch.Tensor, *, batched: bool = False):
        """Set and return λ₀ from the first linearisation: a float, or with ``batched`` a (B,)
        tensor for diag_h (B, n) (one λ per problem)."""
        self.batched = bool(batched)
        if self.batched:
            ratio = (diag_h / D).amax(-1) if diag_h.shape[-1] else torch.ones_like(diag_h[..., 0])
            self.lam = (self.tau * ratio).clamp(self.lambda_min, self.lambda_max)
        else:
            ratio = (diag_h / D).max() if diag_h.numel() else torch.ones(())
            self.lam = min(max(self.tau * float(ratio), self.lambda_min), self.lambda_max)
        self._reset_state()
        return self.lam

    batched = False

    def _reset_state(self):
        pass

    def update(self, rho, accepted, active=None):  # pragma: no cover - abstract
        """New λ after a step with gain ratio ρ (accepted or not).  Batched mode: ρ, accepted
        and ``active`` are (B,) tensors; only the problems where ``active`` is True change."""
        raise NotImplementedError

    @property
    def exhausted(self):
        """True once λ exceeds lambda_max (no step can make progress); a (B,) mask in batched mode."""
        if self.batched:
            return self.lam > self.lambda_max
        return self.lam is not None and self.lam > self.lambda_max

    def __repr__(self):
        return f"{type(self).__name__}(tau={self.tau}, scaling={self.scaling!r})"


class NielsenDamping(DampingStrategy):
    """Nielsen's rule (see module docstring)."""

    def _reset_state(self):
        self.nu = torch.full_like(self.lam, 2.0) if self.batched else 2.0

    def update(self, rho, accepted, active=None):
        if self.batched:
            # ρ = −inf on rejected steps gives inf here; torch.where discards it
            shrink = (1.0 - (2.0 * rho - 1.0) ** 3).clamp_min(1.0 / 3.0)
            lam = torch.where(accepted, (self.lam * shrink).clamp_min(self.lambda_min), self.lam * self.nu)
            nu = torch.where(accepted, torch.full_like(self.nu, 2.0), 2.0 * self.nu)
            if active is not None:
                lam, nu = torch.where(active, lam, self.lam), torch.where(active, nu, self.nu)
            self.lam, self.nu = lam, nu
        elif accepted:
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

    def update(self, rho, accepted, active=None):
        if self.batched:
            down = accepted & (rho > 0.75)
            up = ~accepted | (rho < 0.25)
            if active is not None:
                down, up = down & active, up & active
            self.lam = torch.where(down, (self.lam / self.down).clamp_min(self.lambda_min),
                                   torch.where(up, self.lam * self.up, self.lam))
        elif accepted and rho > 0.75:
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

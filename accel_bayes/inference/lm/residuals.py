"""Residual groups and extra cost terms of an LM problem (the ``fn``/``jac`` conventions are in the
docstring of :mod:`accel_bayes.inference.lm`): per sample, between consecutive samples, on the
globals only, and smooth non-least-squares terms on the globals."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable

__all__ = ["SampleResidual", "ChainResidual", "GlobalResidual", "ExtraCost"]


@dataclass
class SampleResidual:
    """Per-sample residual group r_t(g, x_t) (T, m); see the module docstring for ``fn``/``jac``.

    loss : robust loss (RobustLoss, "huber", "cauchy") or None; group_size : length of a robust
    block along m (None = the whole row of a sample).
    local_hessian : optional ``local_hessian(g, x, data, r) -> (T, d, d)``, the second-order term
        Σ_m r_tm ∂²r_tm/∂x_t² of the local blocks (r given with robust weights ρ' applied).  LM
        steps then use a Newton model in the locals: V_t ← PSD part of (J_xᵀJ_x + that term)
        (eigenvalues clamped at 1e-6 of the block's largest).  This pays off in large-residual
        problems, where Gauss–Newton converges only linearly (e.g. the [C21] MAP on real data
        with a wide gyroscope posterior: 41 instead of > 300 iterations).  Information matrices
        are not affected.
    """

    fn: Callable
    data: Any = None
    jac: Callable | None = None
    loss: Any = None
    group_size: int | None = None
    name: str = "sample"
    local_hessian: Callable | None = None
    chunk: int | None = None
    """Linearise in chunks of this many samples (None: all at once).  Requires ``data`` to be None,
    a tensor or a tuple of tensors with leading dim T (sliced along with x); the blocks of long
    records are then built with cache-sized intermediates (per-iteration time linear in T)."""


@dataclass
class ChainResidual:
    """Pairwise residual group r_t(g, x_t, x_{t+1}) (T−1, m) — e.g. the [S16] process model (eq. 14)."""

    fn: Callable
    data: Any = None
    jac: Callable | None = None
    loss: Any = None
    group_size: int | None = None
    name: str = "chain"


@dataclass
class GlobalResidual:
    """Residuals on the globals only, r(g) (m,) — e.g. Gaussian priors (θ − μ)/σ."""

    fn: Callable
    jac: Callable | None = None
    loss: Any = None
    name: str = "global"


@dataclass
class ExtraCost:
    """A smooth non-least-squares term c(g) added to the cost (e.g. (T/2)·log|M(θ)|, DESIGN §4).

    step_hessian : "exact" (default) uses its Hessian as is inside LM steps (Newton-like local
    convergence; an indefinite system is answered by raising λ); "psd" projects it on the PSD cone
    (always-PD steps, but only linear convergence where the term has negative curvature).
    Information matrices always use the exact Hessian.
    """

    fn: Callable
    grad_hess: Callable | None = None
    step_hessian: str = "exact"
    name: str = "extra"

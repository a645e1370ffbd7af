"""PmMH proposals ([C21] eq. 27; DESIGN §5): a Gaussian random walk, a Gaussian independence
proposal, and their random mixture.  Each move type is a valid MH kernel for the same target, so
the mixture is too.

Every proposal takes its standard-normal draws from the caller (the kernel's generator), so the
order of the random numbers — and with it every chain — is fixed by the kernel alone.
"""
from __future__ import annotations

import math

import torch

from ...errors import UserError

__all__ = ["RandomWalkProposal", "IndependenceProposal", "ProposalMixture", "MOVE_RW", "MOVE_IND",
           "WARMUP_MAX_INDEPENDENCE", "cholesky_factor"]

MOVE_RW, MOVE_IND = 0, 1

# Largest share of independence moves during warm-up (the rest adapt the random walk).
WARMUP_MAX_INDEPENDENCE = 0.5


def cholesky_factor(cov: torch.Tensor, name: str) -> torch.Tensor:
    """Lower Cholesky factor of ``cov``; :class:`UserError` naming ``name`` when it is not SPD."""
    L, info = torch.linalg.cholesky_ex(cov)
    if int(info) != 0:
        raise UserError(f"{name}: expected a symmetric positive-definite matrix")
    return L


class RandomWalkProposal:
    """θ' = θ + σ_q L ε, L Lᵀ = Σ ([C21] eq. 27 with a general Σ), symmetric: log q-ratio 0.

    :param cov: (d, d) Σ in m² (row-major vec θ).
    :param float log_step: log σ_q (σ_q dimensionless).
    """

    def __init__(self, cov: torch.Tensor, log_step: float):
        self.set_cov(cov)
        self.log_step = float(log_step)

    def set_cov(self, cov: torch.Tensor) -> None:
        self.cov = cov
        self.chol = cholesky_factor(cov, "proposal_cov")

    @property
    def step_size(self) -> float:
        """σ_q."""
        return math.exp(self.log_step)

    def propose(self, theta: torch.Tensor, eps: torch.Tensor) -> torch.Tensor:
        """θ' from θ (A−1, 3) m and ε ~ N(0, I_d)."""
        return theta + math.exp(self.log_step) * (self.chol @ eps).reshape(theta.shape)


class IndependenceProposal:
    """θ' ~ N(μ, c² Σ_ind), independent of the current state; unavailable until :meth:`set`.

    :param event_shape: (A−1, 3).
    :param float scale: c > 0.
    """

    def __init__(self, event_shape: tuple, scale: float):
        self.event_shape = tuple(event_shape)
        self.scale = float(scale)
        self.mean = self.cov = self.chol = None

    def set(self, mean: torch.Tensor | None, cov: torch.Tensor | None) -> None:
        """Centre μ (A−1, 3) m and covariance Σ_ind (d, d) m²; None, None makes it unavailable."""
        self.mean, self.cov = mean, cov
        self.chol = None if cov is None else cholesky_factor(cov, "independence_cov") * self.scale

    @property
    def available(self) -> bool:
        return self.chol is not None

    def propose(self, eps: torch.Tensor) -> torch.Tensor:
        return self.mean + (self.chol @ eps).reshape(self.event_shape)

    def log_q(self, theta: torch.Tensor) -> torch.Tensor:
        """log q(θ) up to its constant (the constant cancels in the MH ratio)."""
        x = (theta - self.mean).reshape(-1, 1)
        z = torch.linalg.solve_triangular(self.chol, x, upper=False)
        return -0.5 * (z * z).sum()


class ProposalMixture:
    """Independence move with probability p (at most :data:`WARMUP_MAX_INDEPENDENCE` during
    warm-up, so σ_q gets enough Robbins–Monro steps), random walk otherwise.

    :param RandomWalkProposal random_walk:
    :param IndependenceProposal independence:
    :param float independence_prob: p in [0, 1).
    """

    def __init__(self, random_walk: RandomWalkProposal, independence: IndependenceProposal,
                 independence_prob: float):
        self.random_walk = random_walk
        self.independence = independence
        self.independence_prob = float(independence_prob)

    def propose(self, theta: torch.Tensor, generator: torch.Generator, warming_up: bool):
        """(θ', log q(θ|θ') − log q(θ'|θ), move type) from the current θ; draws, in this order, the
        uniform of the move choice (only when an independence move is possible) and ε ~ N(0, I_d)."""
        use_ind = False
        if self.independence_prob > 0 and self.independence.available:
            p_ind = min(self.independence_prob, WARMUP_MAX_INDEPENDENCE) if warming_up else self.independence_prob
            use_ind = bool(torch.rand((), generator=generator, dtype=theta.dtype, device=theta.device) < p_ind)
        eps = torch.randn(theta.numel(), generator=generator, dtype=theta.dtype, device=theta.device)
        if use_ind:
            prop = self.independence.propose(eps)
            return prop, self.independence.log_q(theta) - self.independence.log_q(prop), MOVE_IND
        return self.random_walk.propose(theta, eps), 0.0, MOVE_RW

"""Priors on the array geometry θ for the PmMH sampler ([C21] eq. 7–8, §IV-A).

θ is the (A−1, 3) tensor of accelerometer-triad positions relative to the reference triad
(array frame, metres): the [C21] parameterisation with r_ref ≡ 0 (their footnote 2).  Both
priors are independent over coordinates, which is what [C21] §IV-A uses (a Gaussian with
σ_r = 3 mm around the design positions) and what it names as the alternative (a uniform box).

The sampler only needs point-wise evaluation (``log_prob``) and, to start chains away from
the truth and the MAP, exact draws (``sample``).  Every draw takes a ``torch.Generator``.
"""
from __future__ import annotations

import math

import torch

from ...errors import UserError
from ...constants import DEFAULT_PRIOR_STD
from ...model.likelihood import theta_from_positions

__all__ = ["GaussianPrior", "BoxPrior", "DEFAULT_PRIOR_STD"]


_LOG_2PI = math.log(2.0 * math.pi)


def _device_of(x, device):
    """The device asked for, else the device of a tensor argument: a float std or bound must land
    beside the GPU positions it goes with, not on torch's default device (tests/mcmc/test_device.py)."""
    if device is not None:
        return device
    return x.device if isinstance(x, torch.Tensor) else None


def _as_tensor(x, dtype, device):
    return torch.as_tensor(x, dtype=dtype, device=_device_of(x, device))


def _prior_to(prior, device):
    """A copy of ``prior`` with its tensors on ``device`` (the chains' device)."""
    import copy

    new = copy.copy(prior)
    for name, value in vars(prior).items():
        if isinstance(value, torch.Tensor):
            setattr(new, name, value.to(device))
    return new


class GaussianPrior:
    """Independent Gaussian prior on the relative positions θ ([C21] §IV-A).

        θ_kj ~ N(m_kj, σ_kj²),  m = design positions relative to the reference triad.

    :param mean_positions: (A, 3) design positions of the A accelerometer triads, array frame, m.
    :param std: prior standard deviation σ_r in m — a float, or anything broadcastable to
        (A−1, 3).  Default 3 mm ([C21] §IV-A).
    :param int reference: row of ``mean_positions`` that is the reference triad (its position
        is the origin and is not a parameter).
    """

    def __init__(self, mean_positions, std=DEFAULT_PRIOR_STD, reference: int = 0,
                 dtype=torch.float64, device=None):
        pos = _as_tensor(mean_positions, dtype, device)
        device = pos.device
        if pos.ndim != 2 or pos.shape[-1] != 3 or pos.shape[0] < 2:
            raise UserError(f"mean_positions: expected shape (A, 3) with A >= 2, got {tuple(pos.shape)}")
        A = pos.shape[0]
        if not 0 <= int(reference) < A:
            raise UserError(f"reference: expected a row index in 0..{A - 1}, got {reference}")
        self.A = A
        self.reference = int(reference)
        self.mean = theta_from_positions(pos, self.reference)
        std_t = _as_tensor(std, dtype, device)
        if not bool(torch.isfinite(std_t).all()) or bool((std_t <= 0).any()):
            raise UserError(f"prior_std: expected a finite value > 0 (metres), got {std}")
        self.std = torch.broadcast_to(std_t, self.mean.shape).clone()
        self._log_norm = -(torch.log(self.std).sum() + 0.5 * self.std.numel() * _LOG_2PI)

    @property
    def shape(self) -> tuple:
        """Event shape of θ, (A−1, 3)."""
        return tuple(self.mean.shape)

    def log_prob(self, theta: torch.Tensor) -> torch.Tensor:
        """log p(θ), summed over the event (A−1, 3): theta (..., A−1, 3) → (...)."""
        z = (theta - self.mean) / self.std
        return self._log_norm - 0.5 * (z * z).sum((-1, -2))

    def sample(self, shape=(), generator: torch.Generator | None = None) -> torch.Tensor:
        """Exact draws θ ~ p(θ): returns (*shape, A−1, 3)."""
        shape = tuple(shape)
        eps = torch.randn(shape + self.shape, generator=generator, dtype=self.mean.dtype, device=self.mean.device)
        return self.mean + self.std * eps

    def to(self, device) -> "GaussianPrior":
        """A copy on ``device``."""
        return _prior_to(self, device)

    def covariance(self) -> torch.Tensor:
        """Prior covariance of vec(θ), (3(A−1), 3(A−1)), diagonal."""
        return torch.diag(self.std.reshape(-1) ** 2)

    def __repr__(self):
        return f"GaussianPrior(A={self.A}, reference={self.reference}, std≈{float(self.std.mean()):.3g} m)"


class BoxPrior:
    """Independent uniform prior on θ within a box ([C21] §IV-A's alternative).

        θ_kj ~ U(low_kj, high_kj)

    :param low, high: tensors broadcastable to each other, the event shape (A−1, 3), m.
        ``high > low`` everywhere.  Use :meth:`around` to centre a box on design positions.
    """

    def __init__(self, low, high, dtype=torch.float64, device=None):
        lo = _as_tensor(low, dtype, _device_of(low, device))
        hi = _as_tensor(high, dtype, lo.device)
        lo, hi = torch.broadcast_tensors(lo, hi)
        if lo.ndim != 2 or lo.shape[-1] != 3:
            raise UserError(f"low/high: expected shape (A-1, 3), got {tuple(lo.shape)}")
        if not bool(torch.isfinite(lo).all() & torch.isfinite(hi).all()) or bool((hi <= lo).any()):
            raise UserError("low/high: expected finite bounds with high > low for every coordinate")
        self.low = lo.clone()
        self.high = hi.clone()
        self.A = lo.shape[0] + 1
        self.reference = 0  # only informative; :meth:`around` records the row it used
        self.mean = 0.5 * (lo + hi)
        self.std = (hi - lo) / math.sqrt(12.0)
        self._log_norm = -torch.log(hi - lo).sum()

    @classmethod
    def around(cls, mean_positions, half_width, reference: int = 0, dtype=torch.float64, device=None) -> "BoxPrior":
        """Box of half-width ``half_width`` (m, float or (A−1, 3)) around the design positions
        relative to the reference row of ``mean_positions`` (A, 3)."""
        pos = _as_tensor(mean_positions, dtype, device)
        device = pos.device
        if pos.ndim != 2 or pos.shape[-1] != 3 or pos.shape[0] < 2:
            raise UserError(f"mean_positions: expected shape (A, 3) with A >= 2, got {tuple(pos.shape)}")
        if not 0 <= int(reference) < pos.shape[0]:
            raise UserError(f"reference: expected a row index in 0..{pos.shape[0] - 1}, got {reference}")
        hw = _as_tensor(half_width, dtype, device)
        if not bool(torch.isfinite(hw).all()) or bool((hw <= 0).any()):
            raise UserError(f"half_width: expected a finite value > 0 (metres), got {half_width}")
        m = theta_from_positions(pos, int(reference))
        out = cls(m - hw, m + hw, dtype=dtype, device=device)
        out.reference = int(reference)
        return out

    @classmethod
    def with_std(cls, mean_positions, std=DEFAULT_PRIOR_STD, reference: int = 0, dtype=torch.float64,
                 device=None) -> "BoxPrior":
        """The box centred on the design positions whose per-coordinate standard deviation is
        ``std`` (half-width √3·std), so ``--prior box --prior-std`` means the same spread as the
        Gaussian prior."""
        s = _as_tensor(std, dtype, _device_of(mean_positions, device))
        if not bool(torch.isfinite(s).all()) or bool((s <= 0).any()):
            raise UserError(f"prior_std: expected a finite value > 0 (metres), got {std}")
        return cls.around(mean_positions, math.sqrt(3.0) * s, reference, dtype=dtype, device=device)

    def to(self, device) -> "BoxPrior":
        """A copy on ``device``."""
        return _prior_to(self, device)

    @property
    def shape(self) -> tuple:
        """Event shape of θ, (A−1, 3)."""
        return tuple(self.low.shape)

    def log_prob(self, theta: torch.Tensor) -> torch.Tensor:
        """log p(θ) (−∞ outside the box): theta (..., A−1, 3) → (...)."""
        inside = ((theta >= self.low) & (theta <= self.high)).flatten(-2).all(-1)
        lp = torch.full(inside.shape, float("-inf"), dtype=theta.dtype, device=theta.device)
        return torch.where(inside, self._log_norm.to(theta.dtype), lp)

    def sample(self, shape=(), generator: torch.Generator | None = None) -> torch.Tensor:
        """Exact draws θ ~ U(box): (*shape, A−1, 3)."""
        shape = tuple(shape)
        u = torch.rand(shape + self.shape, generator=generator, dtype=self.low.dtype, device=self.low.device)
        return self.low + (self.high - self.low) * u

    def covariance(self) -> torch.Tensor:
        """Prior covariance of vec(θ), diagonal with (high − low)²/12."""
        return torch.diag(self.std.reshape(-1) ** 2)

    def __repr__(self):
        return f"BoxPrior(A={self.A}, half-width≈{float((self.high - self.low).mean()) / 2:.3g} m)"

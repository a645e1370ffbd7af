"""The likelihood tempered by the misspecification factor κ, p(y | θ)^(1/κ) (issue #6 item 2; why
and how κ is measured: :mod:`accel_bayes.model.noise`, :func:`accel_bayes.inference.noise_fit.sandwich_inflation`).
"""
from __future__ import annotations

import torch

from ..errors import UserError
from ..physics.models import H_matrix
from .likelihood import RaoBlackwellLikelihood
from .phi_prior import PhiPrior

__all__ = ["TemperedLikelihood"]


class TemperedLikelihood(RaoBlackwellLikelihood):
    """The [C21] likelihood raised to the power 1/κ (a coarsened / generalised-Bayes posterior).

    Constructed like :class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood` with the noise
    std ALREADY scaled by √κ: that tempers the Gaussian exponent (and integrates ω under the
    correspondingly wider likelihood).  The Occam factor −(T/2) log|M(θ)| of the φ integral does
    not scale with σ (only shifts by a constant), so :meth:`log_phat` re-weights it to
    −(T/(2κ)) log|M(θ)| by adding the deterministic (1 − 1/κ)(T/2) log|M(θ)|.  p̂ times a
    deterministic function of θ is an unbiased estimator of that function × p, so PmMH stays
    exact for the tempered target.

    With a proper prior N(0, F) on φ (``phi_prior``, the UNtempered F) the sample's density is
    N(y; Gu, Q + HFHᵀ); its power 1/κ is the Gaussian with covariance κ(Q + HFHᵀ), i.e. noise
    std × √κ AND F × κ (done here), times |Q + HFHᵀ|^(−1/(2κ)), whose θ-part is
    |M + F⁻¹|^(−1/(2κ)) — unchanged under that joint scaling up to a constant, so the same Occam
    re-weighting applies with M + F⁻¹ in place of M.
    """

    def __init__(self, acc, omega, acc_noise_std, num_draws, kappa: float, reference: int = 0,
                 dtype=torch.float64, device=None, phi_prior=None, prepared=None):
        self.kappa = float(kappa)
        if not self.kappa >= 1.0:
            raise UserError(f"kappa: expected a factor >= 1, got {kappa!r}")
        prior = PhiPrior.coerce(phi_prior, dtype=dtype, device=device)
        super().__init__(acc, omega, acc_noise_std, num_draws, reference=reference, dtype=dtype, device=device,
                         phi_prior=None if prior is None else prior.scaled(self.kappa), prepared=prepared)

    def occam_correction(self, positions) -> torch.Tensor:
        """(1 − 1/κ)(T/2) log|M(θ) + F⁻¹| for positions (..., A, 3) (M alone for the flat prior);
        O(A) per θ and invariant to a common translation (H(r + c) = H(r)·E with det E = 1)."""
        r = self._positions(positions)
        H = H_matrix(r)
        M = self._with_phi_prior(H.transpose(-1, -2) @ (self.lam[:, None] * H))
        return (1.0 - 1.0 / self.kappa) * 0.5 * self.T * torch.linalg.slogdet(M)[1]

    def log_phat(self, positions, *args, **kwargs) -> torch.Tensor:
        """log p̂ of the [C21] estimator plus the Occam re-weighting (class docstring)."""
        out = super().log_phat(positions, *args, **kwargs)
        return out + self.occam_correction(positions).to(out.dtype).reshape(out.shape)

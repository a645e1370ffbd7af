"""The prior on φ_t = [ω̇_t; s_t], estimated from the recording (empirical Bayes; issue #15 item 0).

Why a proper prior is the default
---------------------------------
[C21] integrates φ_t (angular acceleration, rad/s², and specific force, m/s², both array frame)
out under a flat prior.  That leaves the factor −(T/2)·log|M(θ)|, M = HᵀΛH (DESIGN §4), which
grows with the array's size: it does not vanish as T grows, and on the demo configuration it
pulls the fitted array inward by 0.19 % (scale 0.99812 ± 0.00034 over 20 seeds,
``experiments/phi_prior_probe.md``), 2–3 posterior std per coordinate.

With a zero-mean Gaussian prior N(0, F) on φ_t the sample's marginal is
y_t | ω_t, θ ~ N(G u(ω_t), Q + H F Hᵀ) ([C21] eq. 19–21 at finite β, f = 0).  Its expected
log-density depends on the data only through E[(y − Gu)(y − Gu)ᵀ] = Q + H E[φφᵀ] Hᵀ, so with
F = E[φ_t φ_tᵀ] (the second moment, mean included: gravity makes s_t far from zero-mean) the true
θ maximises it — whatever the distribution of φ_t, Gaussian or not.  That is the estimator's
consistency; the flat prior has no such property.

The estimate (type-II maximum likelihood)
-----------------------------------------
Given ω_t = ω̄_t (the gyroscopes' posterior mean) and θ, φ̂_t = M⁻¹HᵀΛ(y_t − G u(ω̄_t)) is a
sufficient statistic for φ_t, with φ̂_t | φ_t ~ N(φ_t, M⁻¹); under the prior φ̂_t ~ N(0, F + M⁻¹).
The maximum of the marginal likelihood over F is therefore

    F̂ = (1/T) Σ_t φ̂_t φ̂_tᵀ − M⁻¹,

with eigenvalues raised to a floor (:data:`EIGEN_FLOOR` × the largest) so that F̂ stays positive
definite (a direction the motion never excites would otherwise get a zero-variance prior).  θ is
the nominal design (the Gaussian prior's mean): the 21 numbers of F̂ come from T samples, and
a few mm of position error change them by far less than their sampling spread.

What is left out: the spread of ω_t about ω̄_t adds M⁻¹HᵀΛG Cov[u(ω_t)] GᵀΛHM⁻¹ to the
covariance of φ̂_t, so F̂ is slightly too wide (a weaker prior, closer to the flat one), and
φ_t is correlated in time, which a per-sample prior ignores.  Both are measured, not argued:
``experiments/phi_prior_probe.md``.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

from ..errors import UserError
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, u_of_omega

__all__ = ["PhiPrior", "empirical_phi_prior", "PHI_PRIOR_CHOICES", "EIGEN_FLOOR"]

# Relative floor on F̂'s eigenvalues (of the largest): keeps the prior proper where the motion
# leaves a direction of φ unexcited, far below any excited direction's variance.
EIGEN_FLOOR = 1e-8

# The options of calibrate's ``phi_prior``: "empirical" (default, :func:`empirical_phi_prior`) and
# "flat" ([C21] as published; DESIGN §4).
PHI_PRIOR_CHOICES = ("empirical", "flat")

_NAMES = ("omega_dot_x", "omega_dot_y", "omega_dot_z", "s_x", "s_y", "s_z")


@dataclass(frozen=True)
class PhiPrior:
    """A zero-mean Gaussian prior N(0, F) on φ_t = [ω̇_t (rad/s²); s_t (m/s²)], array frame.

    cov : (6, 6) F, units rad²/s⁴ (ω̇ block), m²/s⁴ (s block) and rad·m/s⁴ (cross terms).
    source : how it was obtained ("empirical_bayes", "given").
    details : plain values for provenance (samples used, positions, eigenvalues clipped …).
    """

    cov: torch.Tensor
    source: str = "given"
    details: dict = field(default_factory=dict)

    def __post_init__(self):
        cov = self.cov
        if not isinstance(cov, torch.Tensor) or cov.shape != (6, 6) or not bool(torch.isfinite(cov).all()):
            raise UserError(f"phi_prior: expected a finite (6, 6) covariance, got {getattr(cov, 'shape', cov)!r}")
        if not bool(torch.allclose(cov, cov.T, rtol=1e-10, atol=0.0)):
            raise UserError("phi_prior: the covariance must be symmetric")
        if torch.linalg.cholesky_ex(cov)[1] != 0:
            raise UserError("phi_prior: the covariance must be positive definite")

    @classmethod
    def coerce(cls, value, dtype=torch.float64, device=None) -> "PhiPrior | None":
        """None (flat), a :class:`PhiPrior`, (σ_ω̇ rad/s², σ_s m/s²), six standard deviations, or
        a (6, 6) covariance → a :class:`PhiPrior` (or None)."""
        if value is None:
            return None
        if isinstance(value, PhiPrior):
            return PhiPrior(value.cov.to(dtype=dtype, device=device), value.source, dict(value.details))
        t = torch.as_tensor(value, dtype=dtype, device=device)
        if t.shape == (6, 6):
            return cls(0.5 * (t + t.T), "given")
        std = t.flatten()
        if std.shape == (2,):
            std = std.repeat_interleave(3)
        if std.shape != (6,) or not bool(torch.isfinite(std).all()) or bool((std <= 0).any()):
            raise UserError(f"phi_prior: expected (σ_ω̇ rad/s², σ_s m/s²), 6 standard deviations > 0 or a (6, 6) "
                            f"covariance, got {value!r}")
        return cls(torch.diag(std.square()), "given")

    @property
    def precision(self) -> torch.Tensor:
        """F⁻¹ (6, 6), symmetrised."""
        P = torch.cholesky_inverse(torch.linalg.cholesky(self.cov))
        return 0.5 * (P + P.T)

    @property
    def std(self) -> torch.Tensor:
        """(6,) marginal standard deviations √diag F (rad/s² ×3, m/s² ×3)."""
        return torch.diagonal(self.cov).sqrt()

    def scaled(self, factor: float) -> "PhiPrior":
        """The prior with F × ``factor`` (tempering by κ scales the noise and F alike)."""
        return PhiPrior(self.cov * float(factor), self.source, {**self.details, "scaled_by": float(factor)})

    def describe(self) -> dict:
        """Plain values for positions.json provenance: the source, the marginal std per component,
        the correlation matrix and the estimation details."""
        sd = self.std
        corr = self.cov / (sd[:, None] * sd[None, :])
        return {"source": self.source, "std": {k: float(v) for k, v in zip(_NAMES, sd)},
                "correlation": [[round(float(c), 6) for c in row] for row in corr], **self.details}


def empirical_phi_prior(acc: torch.Tensor, omega_mean: torch.Tensor, acc_noise_std, positions: torch.Tensor) -> PhiPrior:
    """Type-II ML estimate F̂ = (1/T) Σ_t φ̂_t φ̂_tᵀ − M⁻¹ of the prior on φ_t (module docstring).

    acc : (T, A, 3) m/s², array frame; omega_mean : (T, 3) rad/s, the gyroscope posterior mean;
    acc_noise_std : (A,), (A, 3) or a scalar, m/s²; positions : (A, 3) m, array frame (e.g. the
    nominal design).  Returns a :class:`PhiPrior` with ``source="empirical_bayes"``.
    """
    acc = torch.as_tensor(acc)
    dtype, device = acc.dtype, acc.device
    T, A, _ = acc.shape
    if T < 12:
        raise UserError(f"acc: the empirical prior on φ needs at least 12 samples, got T={T}")
    pos = torch.as_tensor(positions, dtype=dtype, device=device)
    if pos.shape != (A, 3):
        raise UserError(f"positions: expected shape ({A}, 3), got {tuple(pos.shape)}")
    lam = acc_noise_std_per_axis(acc_noise_std, A, dtype=dtype, device=device).reshape(3 * A).pow(-2)
    r = pos - pos[0]  # the likelihood is invariant to a common translation; H needs only differences
    H, G = H_matrix(r), G_matrix(r)
    M = H.T @ (lam[:, None] * H)
    L = torch.linalg.cholesky(M)
    res = acc.reshape(T, 3 * A) - u_of_omega(torch.as_tensor(omega_mean, dtype=dtype, device=device)) @ G.T
    phi = torch.cholesky_solve(((res * lam) @ H).T, L).T  # (T, 6)
    second = phi.T @ phi / T
    F = second - torch.cholesky_inverse(L)
    F = 0.5 * (F + F.T)
    ev, V = torch.linalg.eigh(F)
    floor = EIGEN_FLOOR * float(ev.max().clamp_min(0))
    clipped = int((ev < floor).sum())
    if floor <= 0:
        raise UserError("acc: the recording does not excite φ = [ω̇; s] at all (no motion, no gravity)")
    F = (V * ev.clamp_min(floor)) @ V.T
    return PhiPrior(0.5 * (F + F.T), "empirical_bayes",
                    {"samples": int(T), "at": "nominal positions", "eigenvalues_clipped": clipped})

"""The Gaussian posterior of the angular rate ω_t from the gyroscopes ([C21] eq. 15, 26b, 30):
the ω part of the model that the likelihood integrates over (:mod:`.likelihood`).  The fusion
with a mismatch report's random gyro effects is :func:`.report_terms.fused_gyro_posterior`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import UserError

__all__ = ["GyroPosterior", "gyro_posterior", "gyro_posterior_timing"]


@dataclass
class GyroPosterior:
    """Gaussian p(ω_t | y_t^g) per sample ([C21] eq. 15, 26b, 30).

    mean : (T, 3) rad/s, array frame;  cov : (T, 3, 3) (rad/s)²;  method : how it was built.
    """

    mean: torch.Tensor
    cov: torch.Tensor
    method: str

    @property
    def T(self) -> int:
        return int(self.mean.shape[0])

    def select(self, index) -> "GyroPosterior":
        """The posterior of the samples ``index`` (bool mask or integer indices)."""
        idx = torch.as_tensor(np.asarray(index), device=self.mean.device)
        return GyroPosterior(self.mean[idx], self.cov[idx], self.method)

    def to(self, dtype=None, device=None) -> "GyroPosterior":
        return GyroPosterior(self.mean.to(dtype=dtype, device=device), self.cov.to(dtype=dtype, device=device),
                             self.method)


_GYRO_METHODS = ("sample_cov", "sample_cov_mean", "calibrated")


def _checked_gyros(gyro_array: torch.Tensor, gyro_noise_std) -> torch.Tensor:
    """The gyro posteriors' input checks, one line naming the field: ``gyro_array`` (T, G, 3) rad/s with
    G ≥ 1 and no NaN; returns ``gyro_noise_std`` as (G,) rad/s, each > 0 (a scalar is broadcast)."""
    if gyro_array.dim() != 3 or gyro_array.shape[-1] != 3:
        raise UserError(f"gyro_array: expected shape (T, G, 3), got {tuple(gyro_array.shape)}")
    G = gyro_array.shape[1]
    std = torch.as_tensor(gyro_noise_std, dtype=gyro_array.dtype, device=gyro_array.device)
    std = std.expand(G) if std.dim() == 0 else std
    if std.shape != (G,):
        raise UserError(f"gyro_noise_std: expected shape ({G},) for G={G} gyros, got {tuple(std.shape)}")
    if bool((std <= 0).any()):
        raise UserError("gyro_noise_std: expected > 0 for every gyro")
    if G < 1:
        raise UserError("gyro_array: no gyroscope triad (G = 0); the likelihood needs at least one")
    if bool(torch.isnan(gyro_array).any()):
        raise UserError("gyro_array: contains NaN; select samples/IMUs with gyro data first")
    return std


def gyro_posterior(gyro_array: torch.Tensor, gyro_noise_std, method: str = "sample_cov") -> GyroPosterior:
    """Gaussian posterior of ω_t from the G gyroscope triads of one sample (flat prior on ω_t).

    gyro_array : (T, G, 3) rad/s, already rotated into the array frame.
    gyro_noise_std : (G,) rad/s (or a scalar), white noise std per axis.
    method :
      * ``"calibrated"`` — gyros with known, calibrated noise: the inverse-variance weighted mean,
        covariance (Σ_k σ_k⁻²)⁻¹ I (= Q_g/G for equal noise).
      * ``"sample_cov"`` (default) — [C21] eq. 30 **as printed**: mean ȳ_t = plain average of the
        G gyros (eq. 30a); covariance Q̄_t = per-sample sample covariance across the gyros with
        1/(G−1) (eq. 30b), **not divided by G**.  That is the spread of a single gyro, not the
        uncertainty of the mean, so it is deliberately wide (the paper uses it to absorb
        uncalibrated gyro scale/misalignment errors that grow with |ω|, [C21] §IV-B).
      * ``"sample_cov_mean"`` — the same divided by G (the standard error of the mean).

    Floor (sample-covariance methods): with few gyros Q̄_t is rank-deficient (rank ≤ G−1) or
    tiny by chance, so its eigenvalues are raised to at least the calibrated variance
    (Σ_k σ_k⁻²)⁻¹: Q̄_t ← V diag(max(λ_i, σ²_cal)) Vᵀ.  The result is never singular and never
    narrower than what the stated gyro noise alone allows.  Needs G ≥ 2.
    """
    std = _checked_gyros(gyro_array, gyro_noise_std)
    T, G, _ = gyro_array.shape
    dtype, device = gyro_array.dtype, gyro_array.device
    w = std.pow(-2)
    var_cal = 1.0 / w.sum()
    eye = torch.eye(3, dtype=dtype, device=device)
    if method == "calibrated":
        mean = (gyro_array * w[:, None]).sum(-2) / w.sum()
        cov = (var_cal * eye).expand(T, 3, 3).clone()
        return GyroPosterior(mean, cov, method)
    if method not in _GYRO_METHODS:
        raise UserError(f"method: expected one of {_GYRO_METHODS}, got {method!r}")
    if G < 2:
        raise UserError(f"method={method!r}: the sample covariance needs at least 2 gyros, got G={G}; "
                        "use method='calibrated'")
    mean = gyro_array.mean(-2)
    dev = gyro_array - mean.unsqueeze(-2)
    cov = dev.transpose(-1, -2) @ dev / (G - 1)
    if method == "sample_cov_mean":
        cov = cov / G
    lam, V = torch.linalg.eigh(cov)
    lam = lam.clamp_min(var_cal)
    cov = (V * lam.unsqueeze(-2)) @ V.transpose(-1, -2)
    cov = 0.5 * (cov + cov.transpose(-1, -2))
    return GyroPosterior(mean, cov, method)



def gyro_posterior_timing(gyro_array: torch.Tensor, gyro_noise_std, age, angular_acc_std) -> GyroPosterior:
    """The calibrated posterior of ω_t with the unresolved angular acceleration loaded by the gyros'
    data ages: the gyro twin of :mod:`.likelihood_percov`'s jerk term (issue #30 item 1).

    Model per sample: y_kt = ω_t − d_kt α_t + e_kt, e_kt ~ N(0, σ_k² I₃), α_t ~ N(0, s_t² I₃)
    (rad/s²), d_kt = age_kt − mean_k age_kt (s), flat prior on ω_t.  The G gyros' covariance is
    (diag(σ²) + s_t² d_t d_tᵀ) ⊗ I₃, so the generalised least-squares weights are
    ρ_t = Σ_t⁻¹1 (Sherman–Morrison, elementwise over t): mean Σ_k ρ_kt y_kt / Σ_k ρ_kt,
    covariance I₃ / Σ_k ρ_kt.  With equal gyro noise Σ_k d_kt = 0 makes the term orthogonal to the
    mean, so it changes nothing ("calibrated" exactly); it matters through unequal noise levels.

    gyro_array (T, G, 3) rad/s array frame; gyro_noise_std (G,) rad/s; age (T, G) s; angular_acc_std
    scalar or (T,) rad/s².  Method "timing".
    """
    y = torch.as_tensor(gyro_array)
    std = _checked_gyros(y, gyro_noise_std)
    T, G, _ = y.shape
    dtype, device = y.dtype, y.device
    age = torch.as_tensor(age, dtype=dtype, device=device)
    if age.shape != (T, G) or not bool(torch.isfinite(age).all()):
        raise UserError(f"age: expected finite data ages of shape (T, G) = ({T}, {G}) s, got {tuple(age.shape)}")
    s = torch.as_tensor(angular_acc_std, dtype=dtype, device=device)
    s = s.expand(T) if s.dim() == 0 else s
    if s.shape != (T,) or not bool(torch.isfinite(s).all()) or bool((s < 0).any()):
        raise UserError(f"angular_acc_std: expected a finite scale >= 0 (rad/s²), scalar or ({T},)")
    w = std.pow(-2)
    d = age - age.mean(-1, keepdim=True)
    s2 = s * s
    wd = w * d  # (T, G)
    rho = w - (s2 * wd.sum(-1) / (1 + s2 * (wd * d).sum(-1)))[:, None] * wd  # Σ_t⁻¹ 1
    prec = rho.sum(-1)
    mean = (rho[..., None] * y).sum(-2) / prec[:, None]
    cov = torch.eye(3, dtype=dtype, device=device) / prec[:, None, None]
    return GyroPosterior(mean, cov, "timing")

"""Cramér–Rao bound of the accelerometer positions under the [C21] model (DESIGN §3.1, §6).

Measurements per sample t ([C21] eq. 4–5), array frame::

    y_t^a = h(ω_t, θ) + H(θ) φ_t + e_t^a,   e^a ~ N(0, Q_a),   Q_a = diag(σ_a²) (3A numbers)
    y_t^g = 1_G ⊗ ω_t + e_t^g,              e^g ~ N(0, Q_g)    (G gyroscope triads)

Unknowns: θ (3(A−1) positions relative to the reference triad) and, per sample, the nuisance
parameters η_t = (ω_t, φ_t) = (ω_t, ω̇_t, s_t) (9 numbers).  For Gaussian noise the Fisher
information is Σ_t J_tᵀ Q⁻¹ J_t with J_t the Jacobian of the noise-free outputs; its structure is
the same arrow as the LM normal equations:

    U   = Σ_t J_θ,tᵀ Λ J_θ,t                      (n × n, n = 3(A−1))
    W_t = J_θ,tᵀ Λ [J_ω,t  H]                     (n × 9)
    V_t = [J_ω,t  H]ᵀ Λ [J_ω,t  H] + diag(I_g, 0)  (9 × 9),  I_g = Σ_k Q_g,k⁻¹ (gyro information on ω)

with, from the one signal model (:mod:`accel_bayes.physics.models`): J_θ for triad k = ∂f_k/∂r_k =
Ω(ω)² + Ω(ω̇) (f = :func:`~accel_bayes.physics.models.specific_force`; derivatives from
:mod:`accel_bayes.physics.jacobians`), J_ω = G(θ) ∂u/∂ω
(:func:`~accel_bayes.physics.models.G_matrix`, :func:`~accel_bayes.physics.models.u_of_omega`), J_φ =
:func:`~accel_bayes.physics.models.H_matrix`.  The nuisance parameters are eliminated by the Schur
complement (the information of θ with η unknown), S = U − Σ_t W_t V_t⁻¹ W_tᵀ, and

    CRB(θ) = (S + I_prior)⁻¹,   I_prior = diag(σ_r⁻²) with a Gaussian prior (Bayesian / van Trees
    bound; for a Gaussian prior its information is exactly σ_r⁻²), none by default.

Eliminating φ_t by the Schur complement is the same as the φ-projection S-norm of DESIGN §4, so
this is the bound that the MAP of :mod:`accel_bayes.inference.map` attains asymptotically.
"""
from __future__ import annotations

import torch

from ..errors import UserError
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, per_axis
from ..physics.jacobians import df_dr, du_domega
from .lm.linear import SchurComplementSolver, cholesky

__all__ = ["fisher_blocks", "fisher_information_theta", "crb_theta"]


def _gyro_information(T, gyro_noise_std, gyro_cov, dtype, device):
    eye = torch.eye(3, dtype=dtype, device=device)
    if gyro_noise_std is not None and gyro_cov is not None:
        raise UserError("give gyro_noise_std or gyro_cov, not both")
    if gyro_cov is not None:
        C = torch.as_tensor(gyro_cov, dtype=dtype, device=device)
        if C.shape == (3, 3):
            C = C.expand(T, 3, 3)
        if C.shape != (T, 3, 3):
            raise UserError(f"gyro_cov: expected (3, 3) or ({T}, 3, 3), got {tuple(C.shape)}")
        return torch.cholesky_inverse(cholesky(C, "gyro_cov"))
    if gyro_noise_std is None:
        return torch.zeros(T, 3, 3, dtype=dtype, device=device)
    s = torch.as_tensor(gyro_noise_std, dtype=dtype, device=device).reshape(-1)
    if bool((s <= 0).any()):
        raise UserError("gyro_noise_std: expected > 0")
    return (s.pow(-2).sum() * eye).expand(T, 3, 3)


def fisher_blocks(positions, omega, omega_dot, s, acc_noise_std, gyro_noise_std=None, *, gyro_cov=None,
                  reference: int = 0, dtype=torch.float64, device=None):
    """Fisher-information blocks (U (n, n), W (T, n, 9), V (T, 9, 9)) of (θ; ω_t, ω̇_t, s_t), module doc.

    positions (A, 3) m (true geometry, array frame); omega, omega_dot, s (T, 3) — the true motion;
    acc_noise_std scalar/(A,)/(A, 3) m/s²; gyro_noise_std scalar or (G,) rad/s (one entry per gyro
    triad: information Σ σ_k⁻² per axis), or gyro_cov (3, 3)/(T, 3, 3) — the covariance of one
    combined ω measurement; neither: no gyroscopes.
    """
    r = torch.as_tensor(positions, dtype=dtype, device=device)
    A = r.shape[0]
    if r.shape != (A, 3) or A < 3:
        raise UserError(f"positions: expected shape (A, 3) with A ≥ 3, got {tuple(r.shape)}")
    if not 0 <= reference < A:
        raise UserError(f"reference: expected an index in 0..{A - 1}, got {reference}")
    w = torch.as_tensor(omega, dtype=dtype, device=r.device)
    wd = torch.as_tensor(omega_dot, dtype=dtype, device=r.device)
    s = torch.as_tensor(s, dtype=dtype, device=r.device)
    T = w.shape[0]
    for nm, v in (("omega", w), ("omega_dot", wd), ("s", s)):
        if v.shape != (T, 3):
            raise UserError(f"{nm}: expected shape ({T}, 3), got {tuple(v.shape)}")
    r = r - r[reference]
    sl = acc_noise_std_per_axis(acc_noise_std, A, dtype=dtype, device=r.device).reshape(3 * A).reciprocal()  # Λ^{1/2}
    # ∂f_k/∂r_k = Ω(ω)² + Ω(ω̇), the same 3×3 for every triad (T, 3, 3)
    Jr = df_dr(w, wd)
    keep = [k for k in range(A) if k != reference]
    n = 3 * (A - 1)
    Jth = r.new_zeros(T, 3 * A, n)
    for j, k in enumerate(keep):  # loop over triads (A is small), batched over t
        Jth[:, 3 * k:3 * k + 3, 3 * j:3 * j + 3] = Jr
    Jw = G_matrix(r) @ du_domega(w)  # (T, 3A, 3)
    Jphi = H_matrix(r).expand(T, 3 * A, 6)
    Jeta = torch.cat((Jw, Jphi), -1) * sl[:, None]  # whitened (T, 3A, 9)
    Jth = Jth * sl[:, None]
    U = torch.einsum("tmi,tmj->ij", Jth, Jth)
    W = torch.einsum("tmi,tmj->tij", Jth, Jeta)
    V = torch.einsum("tmi,tmj->tij", Jeta, Jeta)
    V[:, :3, :3] += _gyro_information(T, gyro_noise_std, gyro_cov, dtype, r.device)
    return U, W, V


def fisher_information_theta(positions, omega, omega_dot, s, acc_noise_std, gyro_noise_std=None, *,
                             gyro_cov=None, reference: int = 0, prior_std=None, dtype=torch.float64,
                             device=None) -> torch.Tensor:
    """Information matrix of vec(θ) (3(A−1) square, rows triad-major), nuisance motion eliminated,
    plus the prior information diag(σ_r⁻²) when ``prior_std`` (scalar, (A,) or (A, 3) m) is given."""
    U, W, V = fisher_blocks(positions, omega, omega_dot, s, acc_noise_std, gyro_noise_std, gyro_cov=gyro_cov,
                            reference=reference, dtype=dtype, device=device)
    S = SchurComplementSolver("diagonal").reduce(U, W, V)
    S = 0.5 * (S + S.T)
    if prior_std is not None:
        A = U.shape[0] // 3 + 1
        ps = per_axis(prior_std, A, "prior_std", dtype=dtype, device=S.device)
        if bool((ps <= 0).any()):
            raise UserError("prior_std: expected values > 0")
        ps = torch.cat((ps[:reference], ps[reference + 1:]), 0).reshape(-1)
        S = S + torch.diag(ps.pow(-2))
    return S


def crb_theta(positions, omega, omega_dot, s, acc_noise_std, gyro_noise_std=None, *, gyro_cov=None,
              reference: int = 0, prior_std=None, dtype=torch.float64, device=None) -> torch.Tensor:
    """Cramér–Rao bound (3(A−1), 3(A−1)) m² of vec(θ) under the [C21] model (module docstring).

    Arguments as :func:`fisher_blocks`; ``prior_std`` adds a Gaussian prior's information (the
    Bayesian bound).  Rows/columns: non-reference triads in order, x, y, z each.
    """
    S = fisher_information_theta(positions, omega, omega_dot, s, acc_noise_std, gyro_noise_std, gyro_cov=gyro_cov,
                                 reference=reference, prior_std=prior_std, dtype=dtype, device=device)
    return torch.cholesky_inverse(cholesky(S, "Fisher information of θ (is the motion rich enough?)"))

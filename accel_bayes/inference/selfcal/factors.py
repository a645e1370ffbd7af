"""The factors of the [S16] self-calibration graph (Fig. 2 / eq. 15) and their analytic Jacobians.

* one **triad residual** per sample i and triad j ([S16] eq. 13), whitened by the axis noise
  ``acc_noise_std`` (σ² = 4·10⁻⁴ (m/s²)² in [S16] §IV-B):

      e_ij = (z_ij − h(x_i, q_j, r_j)) / σ_j,   h = Sᵀ R(q)(a_lin + ω̇×r + ω×(ω×r)) + o

  with h = :func:`accel_bayes.physics.models.triad_output` (the one signal model) and known sensor
  parameters S, o (identity / zero by default: "calibrated triads", [S16] §IV);
* one **process residual** between consecutive states ([S16] eq. 14), whitened by a square root
  W of the inverse process covariance (:mod:`.motion_priors`):

      e_i = W_i (x_{i+1} − f(x_i)),   f = :func:`.motion_priors.process_model`.

Quaternions are updated on their manifold with the exponential-map box-plus q ⊞ δ = q ∘ exp(δ)
(:func:`accel_bayes.physics.geometry.boxplus`; δ a rotation vector, so Laplace covariances in δ
are covariances of rotation angles).  [S16] eq. 18 is the half-angle variant (δ = quaternion
vector part); it has the same fixed points but its covariances would be in half-angles.

The residuals and Jacobians are written for batches of samples (no loops over time).  With the
poses held, the Gauss–Newton matrix of the motion is block tridiagonal (:func:`motion_hessian`);
the selected blocks of its inverse (:func:`motion_posterior`) are what the noise estimation and
the scale corrections need.
"""
from __future__ import annotations

import torch

from ...physics import jacobians as jac
from ...physics import models
from ...physics.geometry import quat_to_matrix, skew
from ..lm.linear import block_tridiagonal_selected_inverse
from .motion_priors import process_model, process_transition

__all__ = ["triad_residuals", "triad_jacobians", "process_residuals", "process_jacobians", "motion_hessian",
           "motion_posterior"]


def _as_inv_std(acc_noise_std, A: int, dtype, device) -> torch.Tensor:
    """(A, 3) inverse noise std from a scalar, (A,) or (A, 3) std (checked by
    :func:`accel_bayes.physics.models.acc_noise_std_per_axis`)."""
    return 1.0 / models.acc_noise_std_per_axis(acc_noise_std, A, dtype=dtype, device=device)


def triad_residuals(
    states: torch.Tensor,
    q: torch.Tensor,
    r: torch.Tensor,
    z: torch.Tensor,
    inv_std: torch.Tensor,
    S: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
) -> torch.Tensor:
    """Whitened triad residuals e_ij = (z_ij − h(x_i, P_j, C_j)) / σ_j ([S16] eq. 13).

    states (T, 9) = [a_lin, ω, ω̇] (m/s², rad/s, rad/s², array frame); q (A, 4), r (A, 3) m: triad
    poses; z (T, A, 3) m/s² triad outputs (sensor frame); inv_std (A, 3) 1/(m/s²); S (A, 3, 3),
    offset (A, 3): known sensor parameters (identity / zero if None).  Returns (T, A, 3),
    dimensionless.
    """
    return (z - models.triad_output(states, q, r, S, offset)) * inv_std


def triad_jacobians(
    states: torch.Tensor,
    q: torch.Tensor,
    r: torch.Tensor,
    inv_std: torch.Tensor,
    S: torch.Tensor | None = None,
):
    """Analytic Jacobians of :func:`triad_residuals` (whitened, so signs are those of −h).

    Returns ``(J_state, J_pos, J_rot)``:

    * J_state (T, A, 3, 9): ∂e_ij/∂x_i, columns [a_lin, ω, ω̇];
    * J_pos (T, A, 3, 3): ∂e_ij/∂r_j;
    * J_rot (T, A, 3, 3): ∂e_ij/∂δ_j for q_j ⊞ δ_j = q_j ∘ exp(δ_j) at δ = 0.  From
      R(q ∘ exp δ) = R(q)(I + Ω(δ)) + O(δ²):  ∂h/∂δ = −M Ω(f) with M = Sᵀ R(q).
    """
    a, w, wd = states[:, 0:3], states[:, 3:6], states[:, 6:9]
    f = models.specific_force(r, w, wd, a)  # (T, A, 3), array frame
    R = quat_to_matrix(q)  # (A, 3, 3)
    M = R if S is None else S.transpose(-1, -2) @ R
    Mw = -(inv_std.unsqueeze(-1) * M)  # (A, 3, 3): ∂e/∂f
    T, A = f.shape[0], r.shape[0]
    J_a = Mw.unsqueeze(0).expand(T, A, 3, 3)
    J_w = Mw @ jac.df_domega(r, w)
    J_wd = (Mw @ jac.df_domega_dot(r)).unsqueeze(0).expand(T, A, 3, 3)
    J_state = torch.cat((J_a, J_w, J_wd), -1)
    J_pos = Mw @ jac.df_dr(w, wd).unsqueeze(1)
    J_rot = -(Mw @ skew(f))
    return J_state, J_pos, J_rot


def _pad_state_columns(J: torch.Tensor, dim: int) -> torch.Tensor:
    """∂e/∂x over the first 9 state columns → over all ``dim`` (the extra derivatives ω̈, ȧ_lin do not
    enter the triad model: zero columns)."""
    if dim == J.shape[-1]:
        return J
    return torch.nn.functional.pad(J, (0, dim - J.shape[-1]))


def _whiten(e: torch.Tensor, sqrt_info: torch.Tensor) -> torch.Tensor:
    """W e for a diagonal W given as (…, 9) or a full one (…, 9, 9)."""
    if sqrt_info.dim() == e.dim():
        return e * sqrt_info
    return (sqrt_info @ e.unsqueeze(-1)).squeeze(-1)


def process_residuals(states: torch.Tensor, dt: torch.Tensor, sqrt_info: torch.Tensor) -> torch.Tensor:
    """Whitened process residuals ([S16] eq. 14 with eq. 8): (x_{i+1} − f(x_i)) / (Δt_i σ).

    states (T, 9); dt (T−1,) s; sqrt_info (T−1, 9) from :func:`process_sqrt_information`, or the
    full (T−1, 9, 9) whitening of :func:`bridged_process_whitening`.  Returns (T−1, 9).  For the
    continuous-time models: states (T, d) of a width in
    :data:`.motion_priors.MOTION_STATE_DIMS` and W (T−1, d, d) from
    :func:`continuous_process_whitening` (the transition of :func:`.motion_priors.process_model` of width d).
    """
    return _whiten(states[1:] - process_model(states[:-1], dt), sqrt_info)


def process_jacobians(dt: torch.Tensor, sqrt_info: torch.Tensor):
    """Jacobians of :func:`process_residuals` (constant: the process model is linear).

    Returns ``(J_prev, J_next)`` (T−1, 9, 9): ∂e_i/∂x_i = −W F_i and ∂e_i/∂x_{i+1} = W with
    W = diag(sqrt_info_i) (or sqrt_info_i itself when it is a full (9, 9) whitening) and
    F_i = [[I, 0, 0], [0, I, Δt_i I], [0, 0, I]] (width 9; :func:`.motion_priors.process_transition` for
    the wider states of the continuous-time models, W then (T−1, d, d)).
    """
    W = torch.diag_embed(sqrt_info) if sqrt_info.dim() == 2 else sqrt_info
    F = process_transition(dt, W.shape[-1])
    return -(W @ F), W


def motion_hessian(states, positions, orientations, dt, W, inv_std, S=None):
    """The Gauss–Newton matrix H_xx of the motion with the poses held (triad + process rows),
    block tridiagonal: (J_prev, J_next, diagonal blocks D (T, d, d), off-diagonal blocks
    B = J_prevᵀ J_next (T−1, d, d))."""
    Jx, _, _ = triad_jacobians(states, orientations, positions, inv_std, S)
    Jx = _pad_state_columns(Jx, states.shape[-1])
    D = torch.einsum("tajk,tajl->tkl", Jx, Jx)
    Jp, Jn = process_jacobians(dt, W)
    D[:-1] += Jp.transpose(-1, -2) @ Jp
    D[1:] += Jn.transpose(-1, -2) @ Jn
    return Jp, Jn, D, Jp.transpose(-1, -2) @ Jn


def motion_posterior(states, positions, orientations, dt, W, inv_std, S=None):
    """Process Jacobians and the selected blocks of the motion's Laplace covariance Σ = H_xx⁻¹
    (poses held): (J_prev, J_next, Σ_i (T, 9, 9), Σ_{i,i+1} (T−1, 9, 9))."""
    Jp, Jn, D, B = motion_hessian(states, positions, orientations, dt, W, inv_std, S)
    Sig, C = block_tridiagonal_selected_inverse(D, B)
    return Jp, Jn, Sig, C

"""The signal models of an inertial sensor array (DESIGN §3), batched, in torch.

One implementation serves simulation, likelihood, MAP and mismatch detection:

* :func:`specific_force` is the rigid-body kinematics ([C21] eq. 4a, [S16] eq. 2): the specific
  force at points r of the board, array frame.  Everything else is built on it.
* :func:`imu_outputs` turns a motion into ideal accelerometer and gyroscope triad outputs in each
  IMU's sensor frame (what a recording stores, before noise and clipping).
* The gyro-aided array model of [C21] eq. 5, y = h(ω, θ) + H(θ) φ + e, with the linear
  structure h(ω, θ) = G(θ) u(ω): :func:`u_of_omega`, :func:`B_of_position`, :func:`G_matrix`,
  :func:`H_matrix`.  Measurements for it are array-frame (sensor readings rotated by R(q)ᵀ).
* The [S16] triad model with pose and sensor parameters (eq. 4, 21–22): :func:`triad_output`.

The [S16] process model (eq. 7–8) and its smoother continuous-time variants are motion priors,
not signal models: they live with the other motion priors in
:mod:`accel_bayes.inference.selfcal.motion_priors` (nothing below inference uses them).

Shapes: motion tensors carry their batch (time, draws, chains …) first, e.g. ω (..., 3);
positions are (A, 3) or batched (..., A, 3); outputs are (..., A, 3).
"""
from __future__ import annotations

import torch

from ..errors import UserError
from .geometry import quat_to_matrix, skew

__all__ = [
    "acc_noise_std_per_axis",
    "specific_force",
    "imu_outputs",
    "to_array_frame",
    "to_sensor_frame",
    "u_of_omega",
    "B_of_position",
    "G_matrix",
    "H_matrix",
    "array_model_mean",
    "triad_output",
    "sensitivity_matrix",
]


def specific_force(r: torch.Tensor, omega: torch.Tensor, omega_dot: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Specific force at positions r, array frame ([C21] eq. 4a without noise; [S16] eq. 2).

        f_k = ω × (ω × r_k) + ω̇ × r_k + s

    r: (..., A, 3) m; omega (..., 3) rad/s; omega_dot (..., 3) rad/s²; s (..., 3) m/s² — the
    specific force at the array origin (translational acceleration minus gravity, array frame).
    Returns (..., A, 3) m/s².  Batch dimensions of r and of the motion broadcast.
    """
    w = omega.unsqueeze(-2)
    wd = omega_dot.unsqueeze(-2)
    w, r_b = torch.broadcast_tensors(w, r)
    wd = wd.expand_as(w)
    centripetal = torch.linalg.cross(w, torch.linalg.cross(w, r_b, dim=-1), dim=-1)
    euler = torch.linalg.cross(wd, r_b, dim=-1)
    return centripetal + euler + s.unsqueeze(-2)


def to_sensor_frame(v_array: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Rotate array-frame vectors (..., K, 3) into each IMU's sensor frame, q (..., K, 4)."""
    return (quat_to_matrix(q) @ v_array.unsqueeze(-1)).squeeze(-1)


def to_array_frame(v_sensor: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`to_sensor_frame`: R(q)ᵀ v_sensor."""
    return (quat_to_matrix(q).transpose(-1, -2) @ v_sensor.unsqueeze(-1)).squeeze(-1)


def imu_outputs(
    positions: torch.Tensor,
    orientations: torch.Tensor,
    omega: torch.Tensor,
    omega_dot: torch.Tensor,
    s: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noise-free accelerometer and gyroscope triad outputs, each in its IMU's sensor frame.

    positions (K, 3) m and orientations (K, 4) are the *true* poses; the motion is (..., 3).
    Returns (acc (..., K, 3) m/s², gyro (..., K, 3) rad/s).  Gyros see the same ω everywhere on a
    rigid body ([C21] eq. 4b), rotated into their own frame.
    """
    f = specific_force(positions, omega, omega_dot, s)
    acc = to_sensor_frame(f, orientations)
    w = omega.unsqueeze(-2).expand(f.shape)
    gyro = to_sensor_frame(w, orientations)
    return acc, gyro


# ---------------------------------------------------------------- [C21] linear structure

def u_of_omega(omega: torch.Tensor) -> torch.Tensor:
    """u(ω) = [ωx², ωy², ωz², ωxωy, ωxωz, ωyωz] (DESIGN §3.1): (..., 3) → (..., 6)."""
    x, y, z = omega.unbind(-1)
    return torch.stack((x * x, y * y, z * z, x * y, x * z, y * z), -1)


def B_of_position(r: torch.Tensor) -> torch.Tensor:
    """B(r), linear in r, with Ω(ω)² r = (ωωᵀ − |ω|² I) r = B(r) u(ω): (..., 3) → (..., 3, 6)."""
    x, y, z = r.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (
            torch.stack((o, -x, -x, y, z, o), -1),
            torch.stack((-y, o, -y, x, o, z), -1),
            torch.stack((-z, -z, o, o, x, y), -1),
        ),
        -2,
    )


def G_matrix(r: torch.Tensor) -> torch.Tensor:
    """G(θ) with h(ω, θ) = G(θ) u(ω) ([C21] eq. 5): r (..., A, 3) → (..., 3A, 6)."""
    B = B_of_position(r)
    return B.reshape(*B.shape[:-3], -1, 6)


def H_matrix(r: torch.Tensor) -> torch.Tensor:
    """H(θ) = [−Ω(r_k)  I₃] stacked over triads ([C21] eq. 5): (..., A, 3) → (..., 3A, 6).

    Columns 0–2 multiply ω̇, columns 3–5 multiply s, i.e. φ = [ω̇; s].
    """
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand(*r.shape[:-1], 3, 3)
    Hk = torch.cat((-skew(r), eye), -1)
    return Hk.reshape(*Hk.shape[:-3], -1, 6)


def array_model_mean(r: torch.Tensor, omega: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """h(ω, θ) + H(θ) φ, stacked (..., 3A), array frame ([C21] eq. 5a).

    Equal to :func:`specific_force` with φ = [ω̇; s]; written through G and H so tests can pin
    the linear structure to the kinematics.
    """
    G = G_matrix(r)
    H = H_matrix(r)
    return (G @ u_of_omega(omega).unsqueeze(-1)).squeeze(-1) + (H @ phi.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------- [S16] triad model

def sensitivity_matrix(params: torch.Tensor) -> torch.Tensor:
    """Upper-triangular S = [s1 s2 s3] from its 6 free entries ([S16] eq. 21–22).

    params (..., 6) = (s1x, s2x, s2y, s3x, s3y, s3z): s1 along the sensor x axis, s2 in the xy
    plane, s3 free.  Returns (..., 3, 3); the identity for params (1, 0, 1, 0, 0, 1).
    """
    s1x, s2x, s2y, s3x, s3y, s3z = params.unbind(-1)
    o = torch.zeros_like(s1x)
    return torch.stack(
        (torch.stack((s1x, s2x, s3x), -1), torch.stack((o, s2y, s3y), -1), torch.stack((o, o, s3z), -1)),
        -2,
    )


def triad_output(
    state: torch.Tensor,
    q: torch.Tensor,
    r: torch.Tensor,
    S: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
) -> torch.Tensor:
    """[S16] triad model (eq. 4 for three axes, Appendix A): z = Sᵀ R_q(a_lin + ω̇×r + ω×(ω×r)) + o.

    state (..., 9) = [a_lin, ω, ω̇] ([S16] eq. 3, array frame; a_lin is the specific force of the
    origin); q (A, 4) body → sensor quaternions; r (A, 3) m; S (A, 3, 3) upper-triangular
    sensitivities (identity if None); offset (A, 3) m/s² (zero if None).  Returns (..., A, 3).
    S and o are the triangular gauge of the accelerometer effects' general gain + bias
    (:func:`accel_bayes.physics.effects.s16_gain` / :func:`~accel_bayes.physics.effects.gain_to_s16`).
    """
    a_lin, omega, omega_dot = state[..., 0:3], state[..., 3:6], state[..., 6:9]
    z = to_sensor_frame(specific_force(r, omega, omega_dot, a_lin), q)
    if S is not None:
        z = (S.transpose(-1, -2) @ z.unsqueeze(-1)).squeeze(-1)
    if offset is not None:
        z = z + offset
    return z


def per_axis(value, A: int, name: str, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """A per-triad-axis quantity broadcast to (A, 3): a scalar (all triads and axes), an (A,)
    per-triad value or an (A, 3) per-axis value.  Raises :class:`UserError` naming ``name`` for
    any other shape; the values themselves are the caller's to check."""
    v = torch.as_tensor(value, dtype=dtype, device=device)
    if v.dim() == 0:
        return v.expand(A, 3)
    if v.shape == (A,):
        return v.unsqueeze(-1).expand(A, 3)
    if v.shape != (A, 3):
        raise UserError(f"{name}: expected a scalar, ({A},) or ({A}, 3), got {tuple(v.shape)}")
    return v


def acc_noise_std_per_axis(acc_noise_std, A: int, *, dtype=torch.float64, device=None) -> torch.Tensor:
    """Accelerometer white-noise standard deviations broadcast to (A, 3), m/s².

    The one place that interprets a user's noise level for the array model (DESIGN §3.1: e ~ N(0,
    diag σ²)): a scalar (all triads and axes), an (A,) per-triad value or an (A, 3) per-axis value.
    Raises :class:`UserError` naming ``acc_noise_std`` for any other shape, or for values that are
    not finite and > 0.
    """
    std = per_axis(acc_noise_std, A, "acc_noise_std", dtype=dtype, device=device)
    if bool((std <= 0).any()) or not bool(torch.isfinite(std).all()):
        raise UserError("acc_noise_std: expected finite values > 0 for every triad")
    return std

"""[S16] conventional calibration (eq. 19) of accelerometer triads from a known reference motion.

For each triad separately, with the reference motion states x_i^R = [a_lin, ω, ω̇] (array frame)
known, the pose P = {q, r} and the triad parameters ᵗC = {S, o} of the Appendix A model
([S16] eq. 21–22)

    z_i = Sᵀ R(q) (a_lin + ω̇ × r + ω × (ω × r)) + o,   S upper-triangular

are the minimisers of Σ_i ‖(z_i − h(x_i^R, P, ᵗC)) / σ‖² ([S16] eq. 19).  The upper-triangular S
(first sensitive axis along the sensor x axis, the second in its xy plane) removes the
redundancy between the orientation and the sensitive axes, so P and ᵗC are identifiable when
the motion excites all directions (a_lin, ω̇ and the quadratic terms of ω, [S16] §III).

The problem has no local variables: it goes through the same LM solver
(:mod:`accel_bayes.inference.lm`, global blocks only) with analytic Jacobians — position (3),
rotation (quaternion manifold, q ⊞ δ = q ∘ exp δ), sensitivity (6) and offset (3), 15 numbers
per triad.  The body frame is the frame of the reference motion; no triad is fixed.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import torch

from ..physics import models
from ..physics.geometry import quat_normalize, quat_to_matrix, skew
from ..physics.jacobians import df_dr
from .selfcal.factors import _as_inv_std

__all__ = ["ConventionalResult", "conventional_residuals", "conventional_jacobians", "conventional_calibrate",
           "IDENTITY_SENSITIVITY"]

# The 6 free entries (s1x, s2x, s2y, s3x, s3y, s3z) of an ideal triad: S = I.
IDENTITY_SENSITIVITY = (1.0, 0.0, 1.0, 0.0, 0.0, 1.0)


def conventional_residuals(states, q, r, sens, offset, z, inv_std):
    """Whitened residuals of [S16] eq. 19 for one or more triads.

    states (T, 9) reference motion; q (A, 4); r (A, 3) m; sens (A, 6) parameters of S
    (:func:`accel_bayes.physics.models.sensitivity_matrix`); offset (A, 3) m/s²; z (T, A, 3) m/s²;
    inv_std (A, 3).  Returns (T, A, 3).
    """
    S = models.sensitivity_matrix(sens)
    return (z - models.triad_output(states, q, r, S, offset)) * inv_std


def conventional_jacobians(states, q, r, sens, inv_std):
    """Analytic Jacobians of :func:`conventional_residuals` w.r.t. the triad parameters.

    Returns (J_pos, J_rot, J_sens, J_off), shapes (T, A, 3, 3), (T, A, 3, 3), (T, A, 3, 6),
    (T, A, 3, 3).  With v = R(q) f and h = Sᵀ v + o: ∂h/∂r = Sᵀ R ∂f/∂r, ∂h/∂δ = −Sᵀ R Ω(f)
    (q ⊞ δ = q ∘ exp δ), ∂h/∂o = I and ∂h_k/∂S = the rows of v that column k of S multiplies:
    h₁ = s1x v_x;  h₂ = s2x v_x + s2y v_y;  h₃ = s3x v_x + s3y v_y + s3z v_z.
    """
    f = models.specific_force(r, states[:, 3:6], states[:, 6:9], states[:, 0:3])  # (T, A, 3)
    dfdr = df_dr(states[:, 3:6], states[:, 6:9]).unsqueeze(1)  # (T, 1, 3, 3), the same for every triad
    R = quat_to_matrix(q)
    S = models.sensitivity_matrix(sens)
    M = S.transpose(-1, -2) @ R  # (A, 3, 3)
    neg = -inv_std.unsqueeze(-1)  # residual = (z − h)·inv_std
    J_pos = neg * (M @ dfdr)
    J_rot = -(neg * (M @ skew(f)))
    v = (R @ f.unsqueeze(-1)).squeeze(-1)  # (T, A, 3) sensor-frame specific force
    vx, vy, vz = v.unbind(-1)
    o = torch.zeros_like(vx)
    dh = torch.stack((
        torch.stack((vx, o, o, o, o, o), -1),
        torch.stack((o, vx, vy, o, o, o), -1),
        torch.stack((o, o, o, vx, vy, vz), -1),
    ), -2)  # (T, A, 3, 6)
    J_sens = neg * dh
    T, A = f.shape[0], f.shape[1]
    J_off = (neg * torch.eye(3, dtype=f.dtype, device=f.device)).unsqueeze(0).expand(T, A, 3, 3)
    return J_pos, J_rot, J_sens, J_off


@dataclass
class ConventionalResult:
    """Outcome of :func:`conventional_calibrate` (one row per triad).

    positions (A, 3) m and orientations (A, 4) (array → sensor, DESIGN §7.0) in the frame of the
    reference motion; sensitivity (A, 6) parameters of S (eq. 21) and S itself (A, 3, 3);
    offset (A, 3) m/s²; cost (A,) final Σ‖e‖² per triad ([S16] eq. 19, whitened);
    covariance (A, 15, 15) Laplace covariance ordered [r (3), δ (3, rotation vector, rad),
    s (6), o (3)]; position_cov (A, 3, 3) m²; rotation_cov (A, 3, 3) rad²; converged (A,)
    bools; n_iter (A,) LM iterations; seconds.
    """

    positions: torch.Tensor
    orientations: torch.Tensor
    sensitivity: torch.Tensor
    offset: torch.Tensor
    cost: torch.Tensor
    covariance: torch.Tensor | None
    converged: list
    n_iter: list
    seconds: float = 0.0
    reasons: list = field(default_factory=list)

    @property
    def S(self) -> torch.Tensor:
        return models.sensitivity_matrix(self.sensitivity)

    @property
    def position_cov(self):
        return None if self.covariance is None else self.covariance[:, 0:3, 0:3]

    @property
    def rotation_cov(self):
        return None if self.covariance is None else self.covariance[:, 3:6, 3:6]

    @property
    def position_std(self):
        c = self.position_cov
        return None if c is None else torch.diagonal(c, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def angle_std(self):
        """(A,) rad — √trace of the rotation-vector covariance."""
        c = self.rotation_cov
        return None if c is None else torch.diagonal(c, dim1=-2, dim2=-1).sum(-1).clamp_min(0).sqrt()


def conventional_calibrate(
    acc,
    reference_states,
    *,
    nominal_positions,
    nominal_orientations=None,
    acc_noise_std=0.02,
    init_sensitivity=None,
    init_offset=None,
    estimate_sensor_params: bool = True,
    max_iter: int = 100,
    ftol: float = 1e-14,
    xtol: float = 1e-14,
    gtol: float = 1e-10,
    covariance: bool = True,
    damping=None,
    dtype=torch.float64,
    device=None,
) -> ConventionalResult:
    """[S16] eq. 19: pose and triad parameters of every triad from a known reference motion.

    Parameters
    ----------
    acc : (T, A, 3) m/s² triad outputs (sensor frames).
    reference_states : (T, 9) reference motion [a_lin (m/s²), ω (rad/s), ω̇ (rad/s²)] in the body
        frame (the frame the poses are estimated in).
    nominal_positions (A, 3) m, nominal_orientations (A, 4): starting poses (identity if None).
    acc_noise_std : m/s², scalar / (A,) / (A, 3) — only weights (and scales the covariance).
    init_sensitivity (A, 6) / init_offset (A, 3): starting triad parameters (ideal triad if None).
    estimate_sensor_params : False holds S and o at their initial values (pose only).
    max_iter, ftol, xtol, gtol, damping : LM settings (:mod:`accel_bayes.inference.lm`).
    covariance : Laplace covariance per triad (inverse Gauss–Newton information).

    Each triad is its own LM problem (the cost separates over triads, [S16] §III).
    """
    from .lm import LevenbergMarquardt, Problem, SampleResidual, Variable
    from .lm.linear import NotPositiveDefinite

    t0 = _time.perf_counter()
    z = torch.as_tensor(acc, dtype=dtype, device=device)
    if z.dim() != 3 or z.shape[-1] != 3:
        raise ValueError(f"acc: expected shape (T, A, 3), got {tuple(z.shape)}")
    T, A = z.shape[0], z.shape[1]
    x = torch.as_tensor(reference_states, dtype=dtype, device=z.device)
    if x.shape != (T, 9):
        raise ValueError(f"reference_states: expected shape ({T}, 9), got {tuple(x.shape)}")
    if not bool(torch.isfinite(z).all()) or not bool(torch.isfinite(x).all()):
        raise ValueError("acc / reference_states: expected finite values")
    p0 = torch.as_tensor(nominal_positions, dtype=dtype, device=z.device)
    if p0.shape != (A, 3):
        raise ValueError(f"nominal_positions: expected shape ({A}, 3), got {tuple(p0.shape)}")
    if nominal_orientations is None:
        q0 = torch.zeros(A, 4, dtype=dtype, device=z.device)
        q0[:, 0] = 1
    else:
        q0 = quat_normalize(torch.as_tensor(nominal_orientations, dtype=dtype, device=z.device))
    s0 = (torch.tensor(IDENTITY_SENSITIVITY, dtype=dtype, device=z.device).expand(A, 6).clone()
          if init_sensitivity is None else torch.as_tensor(init_sensitivity, dtype=dtype, device=z.device).clone())
    o0 = torch.zeros(A, 3, dtype=dtype, device=z.device) if init_offset is None else \
        torch.as_tensor(init_offset, dtype=dtype, device=z.device).clone()
    inv_std = _as_inv_std(acc_noise_std, A, dtype, z.device)

    out_p, out_q, out_s, out_o, costs, covs, conv, iters, reasons = [], [], [], [], [], [], [], [], []
    for j in range(A):
        zj, wj = z[:, j:j + 1], inv_std[j:j + 1]

        def fn(g, _x, _d, zj=zj, wj=wj):
            return conventional_residuals(x, g["rotation"], g["position"], g["sensitivity"], g["offset"],
                                         zj, wj).reshape(T, 3)

        def jac(g, _x, _d, wj=wj):
            Jp, Jr, Js, Jo = conventional_jacobians(x, g["rotation"], g["position"], g["sensitivity"], wj)
            return {"position": Jp[:, 0], "rotation": Jr[:, 0], "sensitivity": Js[:, 0], "offset": Jo[:, 0]}, None

        prob = Problem(
            {"position": Variable(p0[j:j + 1]),
             "rotation": Variable(q0[j:j + 1], manifold="quaternion"),
             "sensitivity": Variable(s0[j:j + 1], fixed=not estimate_sensor_params),
             "offset": Variable(o0[j:j + 1], fixed=not estimate_sensor_params)},
            None, [SampleResidual(fn, jac=jac, name="triad")], dtype=dtype, device=z.device,
        )
        res = LevenbergMarquardt(damping, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol).solve(prob)
        v = res.values
        out_p.append(v["position"][0])
        out_q.append(v["rotation"][0])
        out_s.append(v["sensitivity"][0])
        out_o.append(v["offset"][0])
        costs.append(2.0 * res.cost)
        conv.append(bool(res.converged))
        iters.append(res.n_iter)
        reasons.append(res.reason)
        if covariance:
            try:
                C = res.covariance()
            except NotPositiveDefinite:
                C = torch.full((prob.n_free, prob.n_free), math.nan, dtype=dtype, device=z.device)
            if not estimate_sensor_params:  # pad to the 15-number layout
                full = torch.zeros(15, 15, dtype=dtype, device=z.device)
                full[:6, :6] = C
                C = full
            covs.append(C)
    return ConventionalResult(
        positions=torch.stack(out_p), orientations=torch.stack(out_q), sensitivity=torch.stack(out_s),
        offset=torch.stack(out_o), cost=torch.tensor(costs, dtype=dtype), covariance=torch.stack(covs) if covs else None,
        converged=conv, n_iter=iters, seconds=_time.perf_counter() - t0, reasons=reasons,
    )

"""[S16] self-calibration of accelerometer-only arrays: triad poses and motion, jointly.

The factor graph of [S16] Fig. 2 / eq. 15:

* one **triad residual** per sample i and triad j ([S16] eq. 13), whitened by the axis noise
  ``acc_noise_std`` (σ² = 4·10⁻⁴ (m/s²)² in [S16] §IV-B):

      e_ij = (z_ij − h(x_i, q_j, r_j)) / σ_j,   h = Sᵀ R(q)(a_lin + ω̇×r + ω×(ω×r)) + o

  with h = :func:`accel_bayes.physics.models.triad_output` (the one signal model) and known sensor
  parameters S, o (identity / zero by default: "calibrated triads", [S16] §IV);
* one **process residual** between consecutive states ([S16] eq. 14), whitened by the Cholesky
  factor of the process covariance of eq. 8 (:func:`accel_bayes.physics.models.process_covariance`):

      e_i = L_i⁻¹ (x_{i+1} − f(x_i)),   f = :func:`accel_bayes.physics.models.process_model`;

* one triad's pose is fixed at its nominal value ([S16] eq. 16): it defines the array frame.

Unknowns are the motion states x_i = [a_lin, ω, ω̇] (T, 9) — or, with the smoother continuous-time
motion model of issue #12 (``process_noise="estimate-snap"``), [a_lin, ω, ω̇, ω̈, ȧ_lin] (T, 15),
whose extra derivatives enter the process residuals only — local blocks, one per sample,
coupled in a chain by the process residuals — and the poses of the free triads (global blocks:
a Euclidean position and a unit quaternion).  Quaternions are updated on their manifold with
the exponential-map box-plus q ⊞ δ = q ∘ exp(δ) (:func:`accel_bayes.physics.geometry.boxplus`; δ is a
rotation vector, so Laplace covariances in δ are covariances of rotation angles).  [S16] eq. 18
is the half-angle variant (δ = quaternion vector part); it has the same fixed points but its
covariances would be in half-angles.

The residuals and their analytic Jacobians below are written for batches of samples (no loops
over time); :func:`self_calibrate` hands them to the structured Levenberg-Marquardt solver of
:mod:`accel_bayes.inference.lm`.
"""
from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field

import torch

from ..physics import models
from ..constants import G0
from ..errors import UserError
from ..physics.geometry import quat_normalize, quat_to_matrix, skew
from ..physics import jacobians as jac

__all__ = [
    "triad_residuals",
    "triad_jacobians",
    "process_residuals",
    "process_jacobians",
    "process_sqrt_information",
    "bridged_process_whitening",
    "PROCESS_NOISE_MODES",
    "wnoj_process_covariance",
    "wnoj_process_whitening",
    "MOTION_MODEL_DIMS",
    "integrated_wiener_covariance",
    "continuous_process_covariance",
    "continuous_process_whitening",
    "initial_process_intensities",
    "process_noise_statistics",
    "update_process_intensities",
    "scale_orbit",
    "marginal_scale_score",
    "laplace_scale_nll",
    "simulate_process_motion",
    "SelfCalResult",
    "SelfCalDiverged",
    "check_divergence",
    "self_calibrate",
    "FitCheck",
    "fit_check",
]


# ---------------------------------------------------------------------------- residuals

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


def process_sqrt_information(dt: torch.Tensor, variances: dict | None = None) -> torch.Tensor:
    """Diagonal of L⁻¹ for the eq. 8 covariance: 1 / (Δt_i σ), shape (T−1, 9)."""
    cov = models.process_covariance(dt, variances, dtype=dt.dtype, device=dt.device)
    d = torch.diagonal(cov, dim1=-2, dim2=-1)
    if bool((d <= 0).any()):
        raise ValueError("process variances and time steps must be > 0")
    return d.rsqrt()


def bridged_process_whitening(dt: torch.Tensor, steps, variances: dict | None = None) -> torch.Tensor:
    """Whitening of the process factors when samples between two fitted ones were left out.

    Between kept samples i and i+1 lie ``steps_i`` steps of the recording's grid, each of
    δ = Δt_i / steps_i.  Leaving those samples' states in the graph without measurements and
    integrating them out is exact for the linear [S16] process model: x_{i+1} = F(Δt_i) x_i + w
    with Cov(w) = Σ_{j<n} F(jδ) Q(δ) F(jδ)ᵀ, n = steps_i, Q(δ) = δ² diag(σ_a², σ_int², σ_ω̇²)
    (eq. 8).  Per axis this is

        Var(a) = n δ² σ_a²,  Var(ω̇) = n δ² σ_ω̇²,
        Var(ω) = n δ² σ_int² + δ⁴ σ_ω̇² Σj²,  Cov(ω, ω̇) = δ³ σ_ω̇² Σj   (j = 0 … n−1),

    the ω–ω̇ coupling being what a single step of length Δt_i (a constant ω̇ across the gap)
    would miss.  Returns W (T−1, 9, 9) with W Cov Wᵀ = I (the inverse Cholesky factor); for
    ``steps_i = 1`` it is eq. 8's diagonal.
    """
    v = models.process_variances(variances)
    n = torch.as_tensor(steps, dtype=dt.dtype, device=dt.device)
    if n.shape != dt.shape or bool((n < 1).any()) or bool((n != torch.round(n)).any()):
        raise ValueError(f"steps: expected whole numbers >= 1 of shape {tuple(dt.shape)}")
    d = dt / n
    s1 = n * (n - 1) / 2  # Σ j
    s2 = (n - 1) * n * (2 * n - 1) / 6  # Σ j²
    cov = torch.zeros(dt.shape + (9, 9), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    cov[:, idx, idx] = (n * d ** 2 * v["acc"]).unsqueeze(-1)
    cov[:, 3 + idx, 3 + idx] = (n * d ** 2 * v["int"] + d ** 4 * v["omega_dot"] * s2).unsqueeze(-1)
    cov[:, 6 + idx, 6 + idx] = (n * d ** 2 * v["omega_dot"]).unsqueeze(-1)
    cov[:, 3 + idx, 6 + idx] = cov[:, 6 + idx, 3 + idx] = (d ** 3 * v["omega_dot"] * s1).unsqueeze(-1)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process variances and time steps must be > 0")
    eye = torch.eye(9, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


# ---------------------------------------------------------------------------- estimated process noise

# process_noise modes of :func:`self_calibrate`: the paper's fixed eq. 8 variances, or the
# continuous-time model below with its two intensities estimated from the recording.
PROCESS_NOISE_MODES = ("s16", "estimate", "estimate-snap")

# Width of the motion state of each continuous-time model (layouts: physics.models.MOTION_STATE_DIMS).
# "estimate": white noise on the jerk ω̈ and on ȧ_lin, x = [a_lin, ω, ω̇] (9);
# "estimate-snap": white noise on the snap ω⃛ and on ä_lin, x = [a_lin, ω, ω̇, ω̈, ȧ_lin] (15) —
# smooth ω̇ and a_lin, as hand motion has (issue #12; ω̇ is a Brownian path under the jerk model).
MOTION_MODEL_DIMS = {"estimate": 9, "estimate-snap": 15}
# (order of the a_lin chain, order of the ω chain) per state width: the white noise drives the
# order-th derivative of a_lin / ω.
_CHAIN_ORDERS = {9: (1, 2), 12: (1, 3), 15: (2, 3)}
# first state column of each element of the chains (a_lin, ȧ_lin) and (ω, ω̇, ω̈)
_ACC_CHAIN = (0, 12)
_OMEGA_CHAIN = (3, 6, 9)


def wnoj_process_covariance(dt: torch.Tensor, intensities: dict) -> torch.Tensor:
    """Covariance (T−1, 9, 9) of the process noise of the continuous-time motion model.

    The model behind ``process_noise="estimate"``: ω̈ (the jerk) is white noise of intensity
    q_ω ((rad/s³)²·s) and ȧ_lin white noise of intensity q_a ((m/s³)²·s), per axis of the array
    frame.  ω is then *exactly* the integral of ω̇ (no σ_int), and the exact discretisation over a
    step Δt has the transition of [S16] eq. 7, x_{i+1} = [a ; ω + ω̇ Δt ; ω̇] + w, with

        Cov(w_a) = q_a Δt I,   Cov([w_ω; w_ω̇]) = q_ω [[Δt³/3, Δt²/2], [Δt²/2, Δt]] ⊗ I

    (the white-noise-on-jerk prior of continuous-time estimation).  Exact for any Δt, so left-out
    samples need no bridge: the step to the next kept sample is just longer.
    """
    qa = torch.as_tensor(intensities["acc"], dtype=dt.dtype, device=dt.device)
    qw = torch.as_tensor(intensities["omega"], dtype=dt.dtype, device=dt.device)
    if not bool(qa > 0) or not bool(qw > 0) or not bool(torch.isfinite(qa) & torch.isfinite(qw)):
        raise ValueError(f"process intensities must be finite and > 0, got {intensities}")
    cov = torch.zeros(dt.shape + (9, 9), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    cov[:, idx, idx] = (qa * dt).unsqueeze(-1)
    cov[:, 3 + idx, 3 + idx] = (qw * dt ** 3 / 3).unsqueeze(-1)
    cov[:, 6 + idx, 6 + idx] = (qw * dt).unsqueeze(-1)
    cov[:, 3 + idx, 6 + idx] = cov[:, 6 + idx, 3 + idx] = (qw * dt ** 2 / 2).unsqueeze(-1)
    return cov


def integrated_wiener_covariance(dt: torch.Tensor, order: int) -> torch.Tensor:
    """Q(Δt)/q (n, p, p) of a chain of p = ``order`` integrators driven by unit-intensity white noise.

    y^(p) = w(t) with E[w(t) w(s)] = δ(t − s); the state (y, y′, …, y^(p−1)) moves over a step Δt
    by F_kl = Δt^(l−k)/(l−k)! (l ≥ k) plus a noise of covariance

        Q_kl = ∫₀^Δt τ^(p−1−k) τ^(p−1−l) / ((p−1−k)! (p−1−l)!) dτ
             = Δt^(2p−1−k−l) / ((2p−1−k−l) (p−1−k)! (p−1−l)!)   (k, l = 0 … p−1),

    the exact discretisation of the integrated Wiener process (p = 2: [[Δt³/3, Δt²/2], [Δt²/2, Δt]];
    p = 3: [[Δt⁵/20, Δt⁴/8, Δt³/6], [Δt⁴/8, Δt³/3, Δt²/2], [Δt³/6, Δt²/2, Δt]]).  dt (n,) s.
    """
    k = torch.arange(order, device=dt.device)
    e = (2 * order - 1 - k[:, None] - k[None, :]).to(dt.dtype)
    fact = torch.tensor([float(math.factorial(order - 1 - i)) for i in range(order)], dtype=dt.dtype, device=dt.device)
    den = e * fact[:, None] * fact[None, :]
    return dt[:, None, None] ** e / den


def continuous_process_covariance(dt: torch.Tensor, intensities: dict, dim: int = 9) -> torch.Tensor:
    """Covariance (T−1, dim, dim) of the process noise of a continuous-time motion model.

    Per axis of the array frame, white noise of intensity q_a drives the chain (a_lin, ȧ_lin) at its
    top derivative and white noise of intensity q_ω the chain (ω, ω̇, ω̈); the orders follow the
    state width ``dim`` (:data:`accel_bayes.physics.models.MOTION_STATE_DIMS`): 9 — ȧ_lin and the
    jerk ω̈ white (q_a (m/s³)²·s, q_ω (rad/s³)²·s; :func:`wnoj_process_covariance`); 12 — the snap
    ω⃛ white (q_ω (rad/s⁴)²·s); 15 — ä_lin white too (q_a (m/s⁴)²·s).  Each chain's block is
    q · :func:`integrated_wiener_covariance`, exact for any Δt; the chains are independent.  The
    transition is :func:`accel_bayes.physics.models.process_model` of the same width.
    """
    if dim == 9:
        return wnoj_process_covariance(dt, intensities)
    if dim not in _CHAIN_ORDERS:
        raise ValueError(f"dim: expected one of {tuple(_CHAIN_ORDERS)}, got {dim}")
    qa = torch.as_tensor(intensities["acc"], dtype=dt.dtype, device=dt.device)
    qw = torch.as_tensor(intensities["omega"], dtype=dt.dtype, device=dt.device)
    if not bool(qa > 0) or not bool(qw > 0) or not bool(torch.isfinite(qa) & torch.isfinite(qw)):
        raise ValueError(f"process intensities must be finite and > 0, got {intensities}")
    pa, pw = _CHAIN_ORDERS[dim]
    cov = torch.zeros(dt.shape + (dim, dim), dtype=dt.dtype, device=dt.device)
    idx = torch.arange(3, device=dt.device)
    for starts, q in ((_ACC_CHAIN[:pa], qa), (_OMEGA_CHAIN[:pw], qw)):
        Qc = q * integrated_wiener_covariance(dt, len(starts))
        for u, su in enumerate(starts):
            for v, sv in enumerate(starts):
                cov[:, su + idx[:, None], sv + idx[None, :]] = Qc[:, u, v, None, None] * torch.eye(
                    3, dtype=dt.dtype, device=dt.device)
    return cov


def continuous_process_whitening(dt: torch.Tensor, intensities: dict, dim: int = 9) -> torch.Tensor:
    """W (T−1, dim, dim) with W Cov Wᵀ = I for :func:`continuous_process_covariance` (inverse
    Cholesky factor; it keeps the two chains apart, so each intensity owns its whitened rows)."""
    if dim == 9:
        return wnoj_process_whitening(dt, intensities)
    cov = continuous_process_covariance(dt, intensities, dim)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process intensities and time steps must be > 0")
    eye = torch.eye(dim, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


def _intensity_rows(dim: int) -> dict:
    """Rows of the whitened process residual that belong to each intensity (the chains' rows)."""
    pa, pw = _CHAIN_ORDERS[dim]
    acc = [s + i for s in _ACC_CHAIN[:pa] for i in range(3)]
    om = [s + i for s in _OMEGA_CHAIN[:pw] for i in range(3)]
    return {"acc": acc, "omega": om}


def wnoj_process_whitening(dt: torch.Tensor, intensities: dict) -> torch.Tensor:
    """W (T−1, 9, 9) with W Cov Wᵀ = I for :func:`wnoj_process_covariance` (inverse Cholesky
    factor; block-diagonal between the a_lin rows 0–2 and the ω, ω̇ rows 3–8)."""
    cov = wnoj_process_covariance(dt, intensities)
    L, info = torch.linalg.cholesky_ex(cov)
    if bool((info != 0).any()):
        raise ValueError("process intensities and time steps must be > 0")
    eye = torch.eye(9, dtype=dt.dtype, device=dt.device).expand_as(cov)
    return torch.linalg.solve_triangular(L, eye, upper=False)


def initial_process_intensities(acc: torch.Tensor, dt: torch.Tensor, positions: torch.Tensor,
                                orientations: torch.Tensor, fixed: int, inv_std: torch.Tensor) -> dict:
    """A start for the intensities from the raw outputs (the fixed point below refines it).

    q_a from the fixed triad's sample-to-sample changes (≈ Δa_lin: E|Δa|² = 3 q_a Δt), q_ω from
    the changes of the difference of each triad's output and the fixed one's, rotated into the
    array frame with the nominal orientations (≈ Δω̇ × Δr plus centripetal changes, an upper
    bound): E|Δω̇|² = 3 q_ω Δt.  Noise (2σ² per component) is subtracted.
    """
    R = quat_to_matrix(orientations)  # array → sensor
    f = (R.transpose(-1, -2).unsqueeze(0) @ acc.unsqueeze(-1)).squeeze(-1)  # (T, A, 3) array frame
    var_n = (1.0 / inv_std ** 2)  # (A, 3)
    d0 = torch.diff(f[:, fixed], dim=0)
    ms0 = (d0 ** 2).sum(-1) - 2 * var_n[fixed].sum()
    qa = float((ms0.clamp_min(0) / (3 * dt)).mean())
    others = [j for j in range(acc.shape[1]) if j != fixed]
    qws = []
    for j in others:
        dr2 = float(((positions[j] - positions[fixed]) ** 2).sum())
        dd = torch.diff(f[:, j] - f[:, fixed], dim=0)
        ms = (dd ** 2).sum(-1) - 2 * (var_n[j].sum() + var_n[fixed].sum())
        qws.append(float((ms.clamp_min(0) / (3 * dt)).mean()) / max(dr2, 1e-12))
    qw = float(torch.tensor(qws).median()) if qws else 1.0
    return {"acc": max(qa, 1e-6), "omega": max(qw, 1e-6)}


def initial_smooth_process_intensities(acc: torch.Tensor, dt: torch.Tensor, positions: torch.Tensor,
                                       orientations: torch.Tensor, fixed: int, inv_std: torch.Tensor,
                                       dim: int = 15) -> dict:
    """Start intensities of the smoother models (state width 12 or 15) from the raw outputs.

    As :func:`initial_process_intensities`, with second differences at a lag of k samples
    (h = kΔ ≈ 20 ms, Δ the median step: a smooth signal's second difference grows as h², its noise
    stays 6σ²): when ω̇ (or a_lin) is an integrated Brownian path of intensity q, its second
    difference at lag h has E|Δ²|² = 3 · (2/3) q h³ = 2 q h³ (three axes).  For the jerk-driven a_lin
    of width 12 the first-difference rule of :func:`initial_process_intensities` is kept.
    """
    pa, _ = _CHAIN_ORDERS[dim]
    step = float(dt.median())
    k = max(1, int(round(0.02 / step)))
    h = k * step
    R = quat_to_matrix(orientations)
    f = (R.transpose(-1, -2).unsqueeze(0) @ acc.unsqueeze(-1)).squeeze(-1)  # (T, A, 3) array frame
    var_n = 1.0 / inv_std ** 2

    def d2(y):
        return y[2 * k:] - 2 * y[k:-k] + y[:-2 * k]

    if acc.shape[0] <= 2 * k:
        k, h = 1, step
    base = initial_process_intensities(acc, dt, positions, orientations, fixed, inv_std)
    if pa == 2:
        ms0 = (d2(f[:, fixed]) ** 2).sum(-1) - 6 * var_n[fixed].sum()
        qa = float(ms0.clamp_min(0).mean()) / (2 * h ** 3)
    else:
        qa = base["acc"]
    qws = []
    for j in range(acc.shape[1]):
        if j == fixed:
            continue
        dr2 = float(((positions[j] - positions[fixed]) ** 2).sum())
        ms = (d2(f[:, j] - f[:, fixed]) ** 2).sum(-1) - 6 * (var_n[j].sum() + var_n[fixed].sum())
        qws.append(float(ms.clamp_min(0).mean()) / (2 * h ** 3) / max(dr2, 1e-12))
    qw = float(torch.tensor(qws).median()) if qws else 1.0
    return {"acc": max(qa, 1e-6), "omega": max(qw, 1e-6)}


def _block_tridiagonal_selected_inverse(D: torch.Tensor, B: torch.Tensor):
    """Diagonal blocks Σ_i (T, n, n) and first off-diagonal blocks Σ_{i,i+1} (T−1, n, n) of H⁻¹ for a
    symmetric positive definite block-tridiagonal H with diagonal blocks D (T, n, n) and
    H_{i,i+1} = B_i (T−1, n, n) (forward elimination, then the backward recursion
    Σ_i = S_i⁻¹ + G_i Σ_{i+1} G_iᵀ, Σ_{i,i+1} = −G_i Σ_{i+1}, G_i = S_i⁻¹ B_i; numpy loop over T)."""
    import numpy as np

    Dn, Bn = D.detach().cpu().numpy(), B.detach().cpu().numpy()
    T = Dn.shape[0]
    Sinv = np.empty_like(Dn)
    S = Dn[0]
    for i in range(T - 1):
        Si = np.linalg.inv(S)
        Sinv[i] = Si
        S = Dn[i + 1] - Bn[i].T @ Si @ Bn[i]
    Sinv[T - 1] = np.linalg.inv(S)
    Sig = np.empty_like(Dn)
    C = np.empty_like(Bn)
    Sig[T - 1] = Sinv[T - 1]
    for i in range(T - 2, -1, -1):
        G = Sinv[i] @ Bn[i]
        C[i] = -G @ Sig[i + 1]
        Sig[i] = Sinv[i] - C[i] @ G.T
    Sig = 0.5 * (Sig + Sig.transpose(0, 2, 1))
    return torch.as_tensor(Sig, dtype=D.dtype, device=D.device), torch.as_tensor(C, dtype=D.dtype, device=D.device)


# The estimated q_ω starts this much below the raw-output guess: a stiff motion model ties ω to ∫ω̇
# firmly in the first fit from zero motion (a loose one lets ω flip sign between segments and the
# poses run off), and the fixed point then loosens it, at most ×_MAX_FACTOR per step.
_START_STIFFNESS = 1e-3
_MAX_FACTOR = 10.0

# residual rows of each intensity in the whitened process residual
_INTENSITY_ROWS = {"acc": slice(0, 3), "omega": slice(3, 9)}  # width 9; _intensity_rows in general


def process_noise_statistics(states, positions, orientations, dt, W, inv_std, S=None) -> dict:
    """Per intensity: the sum of squared whitened process residuals at the estimate, their number
    and their leverage in the motion fit (poses held at the estimate).

    With H the Gauss–Newton matrix of the motion states (triad + process rows; block
    tridiagonal), a group k of whitened residual rows with Jacobian J_k has leverage
    h_k = tr(J_k H⁻¹ J_kᵀ), computed from the diagonal and first off-diagonal blocks of H⁻¹.
    Returns {"acc": (rss, n, h), "omega": (rss, n, h)}.  States (T, d) of any width of
    :data:`accel_bayes.physics.models.MOTION_STATE_DIMS` (W (T−1, d, d) of the same width).
    """
    Jp, Jn, Sig, C = _motion_posterior(states, positions, orientations, dt, W, inv_std, S)
    M = (Jp @ Sig[:-1] @ Jp.transpose(-1, -2) + Jp @ C @ Jn.transpose(-1, -2)
         + Jn @ C.transpose(-1, -2) @ Jp.transpose(-1, -2) + Jn @ Sig[1:] @ Jn.transpose(-1, -2))
    lev = torch.diagonal(M, dim1=-2, dim2=-1)  # (T−1, 9)
    r = process_residuals(states, dt, W)
    rows = _INTENSITY_ROWS if states.shape[-1] == 9 else _intensity_rows(states.shape[-1])
    return {k: (float((r[:, sl] ** 2).sum()), int(r[:, sl].numel()), float(lev[:, sl].sum()))
            for k, sl in rows.items()}


def _motion_hessian(states, positions, orientations, dt, W, inv_std, S=None):
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


def _motion_posterior(states, positions, orientations, dt, W, inv_std, S=None):
    """Process Jacobians and the selected blocks of the motion's Laplace covariance Σ = H_xx⁻¹
    (poses held): (J_prev, J_next, Σ_i (T, 9, 9), Σ_{i,i+1} (T−1, 9, 9))."""
    Jp, Jn, D, B = _motion_hessian(states, positions, orientations, dt, W, inv_std, S)
    Sig, C = _block_tridiagonal_selected_inverse(D, B)
    return Jp, Jn, Sig, C


def _pad_state_columns(J: torch.Tensor, dim: int) -> torch.Tensor:
    """∂e/∂x over the first 9 state columns → over all ``dim`` (the extra derivatives ω̈, ȧ_lin do not
    enter the triad model: zero columns)."""
    if dim == J.shape[-1]:
        return J
    return torch.nn.functional.pad(J, (0, dim - J.shape[-1]))


def scale_orbit(positions, states, fixed: int, c: float):
    """The accelerometer-only symmetry: poses and motion that explain the outputs exactly as well.

    Free positions r_j → r_f + c (r_j − r_f) about the fixed triad f; ω → ω/√c, ω̇ → ω̇/c and
    a_lin → a_lin + (1 − 1/c) K with K = ω̇×r_f + ω×(ω×r_f) (keeps the fixed triad's specific force;
    zero when the fixed triad sits at the array origin).  Every triad's specific force is unchanged.
    With the smoother states (width 12, 15) ω̈ → ω̈/c (like ω̇, so the ω̇–ω̈ link keeps its
    consistency) and ȧ_lin is left as it is: neither enters the data, so any choice is an orbit."""
    rf = positions[fixed]
    p = rf + c * (positions - rf)
    a, w, wd = states[:, 0:3], states[:, 3:6], states[:, 6:9]
    K = torch.cross(wd, rf.expand_as(wd), dim=-1) + torch.cross(w, torch.cross(w, rf.expand_as(w), dim=-1), dim=-1)
    parts = [a + (1 - 1 / c) * K, w / math.sqrt(c), wd / c]
    if states.shape[-1] >= 12:
        parts.append(states[:, 9:12] / c)
        parts.append(states[:, 12:])
    x = torch.cat(parts, -1)
    return p, x


def marginal_scale_score(states, positions, orientations, dt, W, inv_std, fixed: int, S=None) -> float:
    """d/dc of −log p(z | poses on the scale orbit) at c = 1, motion integrated out (Laplace).

    The joint MAP over poses and motion is biased along the scale orbit (:func:`scale_orbit`): the
    data term is constant along it, so the MAP's scale is set by the motion prior alone, which
    prefers slower motion (a larger board).  Integrating the motion out adds the volume of the
    orbit map (det = c^(−9T/2)) and the posterior spread: with x = φ_c(x′),

        d/dc [−log p] = 9T/2 + Σ_i r_iᵀ (J_prev,i v_i + J_next,i v_{i+1}) + tr(Λ V Σ),

    r_i the whitened process residuals, v = dφ_c/dc at c = 1 (per sample (K, −ω/2, −ω̇)), V its
    Jacobian, Λ = J_pᵀJ_p the process information and Σ the motion's Laplace covariance (poses
    held).  The middle term vanishes at the joint MAP.  With the smoother states (width d = 12,
    15) v also carries −ω̈ (ȧ_lin: 0) and the volume term is 15T/2 (ω̈ → ω̈/c adds c^(−3) per sample).
    """
    T, d = states.shape
    Jp, Jn, Sig, C = _motion_posterior(states, positions, orientations, dt, W, inv_std, S)
    rf = positions[fixed]
    w, wd = states[:, 3:6], states[:, 6:9]
    K = torch.cross(wd, rf.expand_as(wd), dim=-1) + torch.cross(w, torch.cross(w, rf.expand_as(w), dim=-1), dim=-1)
    v = torch.cat((K, -0.5 * w, -wd), -1)  # (T, 9)
    if d > 9:
        v = torch.cat((v, -states[:, 9:12], torch.zeros_like(states[:, 12:])), -1)
    V = torch.zeros(T, d, d, dtype=states.dtype, device=states.device)
    eye3 = torch.eye(3, dtype=states.dtype, device=states.device)
    V[:, 0:3, 3:6] = jac.df_domega(rf.expand(T, 1, 3), w)[:, 0]  # ∂(ω×(ω×r_f))/∂ω
    V[:, 0:3, 6:9] = -skew(rf).expand(T, 3, 3)
    V[:, 3:6, 3:6] = -0.5 * eye3
    V[:, 6:9, 6:9] = -eye3
    if d > 9:
        V[:, 9:12, 9:12] = -eye3
    r = process_residuals(states, dt, W)
    middle = float((r * ((Jp @ v[:-1].unsqueeze(-1)).squeeze(-1) + (Jn @ v[1:].unsqueeze(-1)).squeeze(-1))).sum())
    JpT, JnT = Jp.transpose(-1, -2), Jn.transpose(-1, -2)
    SL = torch.zeros_like(Sig)  # (Σ Λ)_ii
    SL[:-1] += Sig[:-1] @ (JpT @ Jp) + C @ (JnT @ Jp)       # Σ_ii Λ_ii(prev part) + Σ_{i,i+1} Λ_{i+1,i}
    SL[1:] += Sig[1:] @ (JnT @ Jn) + C.transpose(-1, -2) @ (JpT @ Jn)  # Σ_ii Λ_ii(next part) + Σ_{i,i−1} Λ_{i−1,i}
    trace = float(torch.einsum("tij,tji->", V, SL))
    volume = 4.5 * T if d == 9 else 7.5 * T
    return volume + middle + trace


def update_process_intensities(intensities: dict, stats: dict, max_factor: float = _MAX_FACTOR) -> dict:
    """One step of the type-II ML fixed point q_k ← q_k · rss_k / (n_k − h_k).

    The marginal likelihood of the intensities in the model linearised at the estimate (motion
    integrated out by Laplace) is stationary where each group's whitened residual sum of squares
    equals its residual degrees of freedom n_k − h_k (as for the accelerometer noise in
    :mod:`accel_bayes.model.noise`); the factor is clamped to [1/max_factor, max_factor]."""
    out = {}
    for k, q in intensities.items():
        rss, n, h = stats[k]
        dof = max(n - h, 1e-3 * n)
        fac = min(max(rss / dof, 1.0 / max_factor), max_factor)
        out[k] = float(q) * fac
    return out


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
    :data:`accel_bayes.physics.models.MOTION_STATE_DIMS` and W (T−1, d, d) from
    :func:`continuous_process_whitening` (the transition of :func:`models.process_model` of width d).
    """
    return _whiten(states[1:] - models.process_model(states[:-1], dt), sqrt_info)


def process_jacobians(dt: torch.Tensor, sqrt_info: torch.Tensor):
    """Jacobians of :func:`process_residuals` (constant: the process model is linear).

    Returns ``(J_prev, J_next)`` (T−1, 9, 9): ∂e_i/∂x_i = −W F_i and ∂e_i/∂x_{i+1} = W with
    W = diag(sqrt_info_i) (or sqrt_info_i itself when it is a full (9, 9) whitening) and
    F_i = [[I, 0, 0], [0, I, Δt_i I], [0, 0, I]] (width 9; :func:`models.process_transition` for
    the wider states of the continuous-time models, W then (T−1, d, d)).
    """
    W = torch.diag_embed(sqrt_info) if sqrt_info.dim() == 2 else sqrt_info
    F = models.process_transition(dt, W.shape[-1])
    return -(W @ F), W


# ---------------------------------------------------------------------------- test motion

def simulate_process_motion(
    T: int,
    dt: float,
    *,
    segment_length: int = 25,
    omega_dot_std: float = 8.0,
    omega0_std: float = 1.0,
    acc_std: float = 3.0,
    acc_segment_length: int | None = None,
    omega_max: float = 6.0,
    gravity: float = G0,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype=torch.float64,
    device=None,
) -> torch.Tensor:
    """Motion states drawn from the [S16] process model itself (eq. 7), integrated exactly.

    ω̇ is piecewise constant (a new N(0, omega_dot_std²) value every ``segment_length`` samples,
    rad/s²); ω_{i+1} = ω_i + ω̇_i Δt holds to machine precision, so the integration residual of
    eq. 14 is zero at the truth; a_lin is piecewise constant (gravity-sized, new values every
    ``acc_segment_length`` samples, default 4 × segment_length).  Where |ω| would exceed
    ``omega_max`` rad/s, the next ω̇ segment is drawn to point back towards zero (keeps the
    accelerations within a triad's range).  Returns states (T, 9).
    """
    g = generator
    if g is None:
        g = torch.Generator(device="cpu")
        g.manual_seed(0 if seed is None else int(seed))
    acc_seg = acc_segment_length or 4 * segment_length
    n_seg = (T + segment_length - 1) // segment_length
    n_aseg = (T + acc_seg - 1) // acc_seg
    wd_draws = torch.randn(n_seg, 3, generator=g, dtype=torch.float64) * omega_dot_std
    w = torch.randn(3, generator=g, dtype=torch.float64) * omega0_std
    a_dir = torch.randn(n_aseg, 3, generator=g, dtype=torch.float64)
    a = gravity * a_dir / a_dir.norm(dim=-1, keepdim=True) + acc_std * torch.randn(n_aseg, 3, generator=g, dtype=torch.float64)
    # The piecewise structure is a short loop over segments (not samples); the sample loop is a
    # cumulative sum, exact in the sense of eq. 7 up to float64 rounding.
    wd = torch.empty(T, 3, dtype=torch.float64)
    w_seg = w.clone()
    for k in range(n_seg):
        lo, hi = k * segment_length, min(T, (k + 1) * segment_length)
        d = wd_draws[k]
        end = w_seg + d * dt * (hi - lo)
        if end.norm() > omega_max:  # steer back: point ω̇ against ω, same magnitude
            d = -d.norm() * w_seg / w_seg.norm().clamp_min(1e-12)
            end = w_seg + d * dt * (hi - lo)
        wd[lo:hi] = d
        w_seg = end
    omega = torch.cat((w.unsqueeze(0), w + torch.cumsum(wd[:-1] * dt, 0)), 0)
    a_lin = a.repeat_interleave(acc_seg, 0)[:T]
    return torch.cat((a_lin, omega, wd), -1).to(dtype=dtype, device=device)


# ---------------------------------------------------------------------------- divergence

class SelfCalDiverged(RuntimeError):
    """The self-calibration ended in a diverged minimum ([S16] Table III); no poses are given.

    ``result`` holds the :class:`SelfCalResult` (status "diverged", the reason, cost log and the
    raw estimate for inspection through ``result.raw_positions``).
    """

    def __init__(self, message: str, result: "SelfCalResult | None" = None):
        super().__init__(message)
        self.result = result


def check_divergence(
    positions: torch.Tensor,
    states: torch.Tensor,
    nominal_positions: torch.Tensor,
    fixed: int,
    cost: float | None = None,
    *,
    rms_residual: float | None = None,
    position_ratio: tuple[float, float] = (0.25, 4.0),
    omega_limits: tuple[float, float] = (1e-3, 100.0),
    omega_dot_limits: tuple[float, float] = (1e-2, 1e4),
    max_rms_residual: float = 30.0,
) -> str | None:
    """Detect the completely diverged minima of [S16] Table III; returns a reason or None.

    * non-finite cost, positions or motion states;
    * triad positions → 0 (types 1, 3): the largest distance of a free triad from the fixed one
      is below ``position_ratio[0]`` × the largest nominal distance;
    * triad positions → ∞ (type 2): it is above ``position_ratio[1]`` × that distance;
    * angular motion → ∞ (type 3): RMS |ω| > ``omega_limits[1]`` rad/s or RMS |ω̇| >
      ``omega_dot_limits[1]`` rad/s² (100 rad/s ≈ 5700 °/s: beyond any handheld or table motion);
    * angular motion → 0 (types 1, 2): RMS |ω| < ``omega_limits[0]`` rad/s and RMS |ω̇| <
      ``omega_dot_limits[0]`` rad/s² — with no rotation the positions cannot be calibrated
      ([S16] §II), so such an estimate is not a calibration either.

    * the estimate does not explain the data: the RMS whitened triad residual ``rms_residual``
      (√(F_triad / 3TA), ≈ 1 for a fit at the stated noise) exceeds ``max_rms_residual`` — a
      minimum that misses the measurements by tens of noise standard deviations is not a
      calibration either (it is where the runs towards Table III minima stop when the iteration
      budget ends first).

    The bounds are deliberately wide: a diverged estimate runs off by orders of magnitude, while
    a converged one (even in a partial minimum, [S16] §VI-A) stays near the nominal plan; the
    default position bounds allow a nominal plan that is wrong by a factor of up to 4 in size.
    """
    if cost is not None and not math.isfinite(cost):
        return "non-finite cost"
    if not bool(torch.isfinite(positions).all()) or not bool(torch.isfinite(states).all()):
        return "non-finite estimate"
    free = [j for j in range(positions.shape[0]) if j != fixed]
    if free:
        d_est = (positions[free] - positions[fixed]).norm(dim=-1).max()
        d_nom = (nominal_positions[free] - nominal_positions[fixed]).norm(dim=-1).max()
        if float(d_nom) > 0:
            ratio = float(d_est / d_nom)
            if ratio < position_ratio[0]:
                return (f"triad positions collapsed towards the fixed triad ([S16] Table III type 1/3): "
                        f"largest distance {float(d_est) * 1e3:.3g} mm vs nominal {float(d_nom) * 1e3:.3g} mm")
            if ratio > position_ratio[1]:
                return (f"triad positions ran off to infinity ([S16] Table III type 2): "
                        f"largest distance {float(d_est):.3g} m vs nominal {float(d_nom):.3g} m")
    if rms_residual is not None and not math.isfinite(rms_residual):
        return "non-finite residuals"
    w_rms = float(states[:, 3:6].norm(dim=-1).pow(2).mean().sqrt())
    wd_rms = float(states[:, 6:9].norm(dim=-1).pow(2).mean().sqrt())
    if w_rms > omega_limits[1] or wd_rms > omega_dot_limits[1]:
        return (f"angular motion ran off to infinity ([S16] Table III type 3): RMS |ω| = {w_rms:.3g} rad/s, "
                f"RMS |ω̇| = {wd_rms:.3g} rad/s²")
    if w_rms < omega_limits[0] and wd_rms < omega_dot_limits[0]:
        return (f"angular motion collapsed to zero ([S16] Table III type 1/2): RMS |ω| = {w_rms:.3g} rad/s, "
                f"RMS |ω̇| = {wd_rms:.3g} rad/s²")
    if rms_residual is not None and rms_residual > max_rms_residual:
        return (f"the estimate does not explain the data: RMS whitened triad residual {rms_residual:.3g} "
                f"(> {max_rms_residual:g} noise standard deviations)")
    return None


# ---------------------------------------------------------------------------- result

@dataclass
class SelfCalResult:
    """Outcome of :func:`self_calibrate`.

    Poses are in the array frame defined by the fixed triad sitting at its nominal pose
    ([S16] eq. 16): ``positions`` (A, 3) m — the fixed triad's row is its nominal position —
    and ``orientations`` (A, 4) array → sensor quaternions (DESIGN §7.0).  Accessing either on a
    diverged result raises :class:`SelfCalDiverged`: a diverged estimate is never a calibration.

    Attributes
    ----------
    status : "ok" or "diverged"; reason : why it diverged ("" when ok).
    fixed : index of the fixed triad.
    states : (T, 9) estimated motion [a_lin (m/s²), ω (rad/s), ω̇ (rad/s²)], array frame; with
        ``process_noise="estimate-snap"`` (T, 15): ω̈ (rad/s³) and ȧ_lin (m/s³) appended.
    cost : final F of [S16] eq. 15 (Σ eᵀΣ⁻¹e, i.e. twice the solver's ½-scaled cost).
    cost_log : one dict per LM iteration of the returned run: iteration, F, F_triad, F_process
        (paper scaling), F_per_constraint (F / number of constraints, [S16] Fig. 5), lambda,
        accepted.
    full_cost_log : the cost logs of all runs made, in order (entries carry "run" and "stage":
        "motion" for the motion-only warm start, "joint" for the pose + motion LM).
    n_constraints : {"triad": T·A, "process": T−1}.
    position_cov : (A, 3, 3) m² Laplace covariance (zeros for the fixed triad).
    rotation_cov : (A, 3, 3) rad² covariance of the rotation vector δ with q = q̂ ∘ exp(δ)
        (full rotation angles, not the half-angles of [S16] eq. 18).
    angle_std : (A,) rad — √trace(rotation_cov), the RMS rotation-angle error.
    covariance : (6(A−1), 6(A−1)) joint Laplace covariance of the free coordinates, ordered
        [positions of the free triads (x, y, z each), rotation vectors of the free triads].
    runs : one dict per LM run made (first run, then the re-run from the estimate): label, F,
        rms_residual, n_iter, lm_reason, converged, diverged (reason or None), kept (re-run),
        and that run's raw estimate (positions, orientations, states) for diagnostics.
    converged, lm_reason, n_iter : of the returned run; seconds : total wall time.
    """

    status: str
    reason: str
    fixed: int
    raw_positions: torch.Tensor
    raw_orientations: torch.Tensor
    states: torch.Tensor
    cost: float
    cost_log: list
    n_constraints: dict
    position_cov: torch.Tensor | None = None
    rotation_cov: torch.Tensor | None = None
    covariance: torch.Tensor | None = None
    runs: list = field(default_factory=list)
    full_cost_log: list = field(default_factory=list)
    converged: bool = False
    lm_reason: str = ""
    n_iter: int = 0
    seconds: float = 0.0
    process_noise: dict = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def _require_ok(self):
        if not self.ok:
            raise SelfCalDiverged(f"self-calibration diverged: {self.reason}", self)

    @property
    def positions(self) -> torch.Tensor:
        """(A, 3) m, array frame (raises :class:`SelfCalDiverged` if diverged)."""
        self._require_ok()
        return self.raw_positions

    @property
    def orientations(self) -> torch.Tensor:
        """(A, 4) array → sensor quaternions (raises :class:`SelfCalDiverged` if diverged)."""
        self._require_ok()
        return self.raw_orientations

    @property
    def relative_positions(self) -> torch.Tensor:
        """Positions relative to the fixed triad, (A, 3) m."""
        p = self.positions
        return p - p[self.fixed]

    @property
    def position_std(self) -> torch.Tensor | None:
        """(A, 3) m — per-axis Laplace standard deviations."""
        return None if self.position_cov is None else torch.diagonal(self.position_cov, dim1=-2, dim2=-1).clamp_min(0).sqrt()

    @property
    def angle_std(self) -> torch.Tensor | None:
        """(A,) rad — √trace of the rotation-vector covariance (RMS rotation-angle error)."""
        if self.rotation_cov is None:
            return None
        return torch.diagonal(self.rotation_cov, dim1=-2, dim2=-1).sum(-1).clamp_min(0).sqrt()


# ---------------------------------------------------------------------------- the solver

def _time_steps(time_or_dt, T: int, dtype, device) -> torch.Tensor:
    t = torch.as_tensor(time_or_dt, dtype=dtype, device=device)
    if t.dim() == 0:
        dt = t.expand(T - 1).clone()
    elif t.shape == (T,):
        dt = torch.diff(t)
    else:
        raise ValueError(f"time_or_dt: expected a scalar step (s) or sample times of shape ({T},), got {tuple(t.shape)}")
    if not bool(torch.isfinite(dt).all()) or bool((dt <= 0).any()):
        raise ValueError("time_or_dt: sample times must be finite and strictly increasing (steps > 0)")
    return dt


def _sensor_params(sensor_params, A: int, dtype, device):
    if sensor_params is None:
        return None, None
    if isinstance(sensor_params, dict):
        S = sensor_params.get("S", sensor_params.get("sensitivity"))
        o = sensor_params.get("offset")
    else:
        S, o = sensor_params
    if S is not None:
        S = torch.as_tensor(S, dtype=dtype, device=device)
        if S.shape == (A, 6):
            S = models.sensitivity_matrix(S)
        if S.shape != (A, 3, 3):
            raise ValueError(f"sensor_params: S expected (A, 3, 3) or (A, 6) with A={A}, got {tuple(S.shape)}")
    if o is not None:
        o = torch.as_tensor(o, dtype=dtype, device=device)
        if o.shape != (A, 3):
            raise ValueError(f"sensor_params: offset expected ({A}, 3), got {tuple(o.shape)}")
    return S, o


_LINEARIZE_CHUNK = 2048  # samples per chunk of the triad linearisation (intermediates stay in cache)


def build_problem(
    acc: torch.Tensor,
    dt: torch.Tensor,
    positions: torch.Tensor,
    orientations: torch.Tensor,
    states: torch.Tensor,
    fixed: int,
    inv_std: torch.Tensor,
    sqrt_info: torch.Tensor,
    S: torch.Tensor | None = None,
    offset: torch.Tensor | None = None,
    poses_fixed: bool = False,
):
    """The [S16] eq. 15 graph as an :class:`accel_bayes.inference.lm.Problem`.

    Globals "position" (A, 3) and "rotation" (A, 4, quaternion manifold), the fixed triad's rows
    held fixed (all rows with ``poses_fixed``: the motion-only problem); locals: the motion
    states (T, d) (d = 9, or 12/15 with the smoother continuous-time models); residual groups "triad" (per sample, analytic Jacobians of
    :func:`triad_jacobians`) and "process" (chain, :func:`process_jacobians`).
    """
    from .lm import ChainResidual, Problem, SampleResidual, Variable

    A = positions.shape[0]
    dim = states.shape[-1]
    fixed_mask = torch.zeros(A, dtype=torch.bool, device=acc.device)
    fixed_mask[fixed] = True
    if poses_fixed:
        fixed_mask[:] = True
    eyeA = torch.eye(A, dtype=acc.dtype, device=acc.device)

    # data = the measurements, so that LM can linearise in chunks of samples (SampleResidual.chunk)
    def triad_fn(g, x, data):
        return triad_residuals(x, g["rotation"], g["position"], data, inv_std, S, offset).reshape(-1, 3 * A)

    def _blockdiag(J):  # (t, A, 3, 3) → (t, 3A, 3A), zero across triads
        return (J.unsqueeze(3) * eyeA[None, :, None, :, None]).reshape(J.shape[0], 3 * A, 3 * A)

    def triad_jac(g, x, data):
        Jx, Jp, Jr = triad_jacobians(x, g["rotation"], g["position"], inv_std, S)
        Jx = _pad_state_columns(Jx, dim)
        return {"position": _blockdiag(Jp), "rotation": _blockdiag(Jr)}, Jx.reshape(-1, 3 * A, dim)

    J_prev, J_next = process_jacobians(dt, sqrt_info)

    def proc_fn(g, xp, xn, data):
        return _whiten(xn - models.process_model(xp, dt), sqrt_info)

    def proc_jac(g, xp, xn, data):
        return {}, J_prev, J_next

    return Problem(
        {"position": Variable(positions, fixed=fixed_mask),
         "rotation": Variable(orientations, manifold="quaternion", fixed=fixed_mask)},
        states,
        [SampleResidual(triad_fn, data=acc, jac=triad_jac, name="triad", chunk=_LINEARIZE_CHUNK),
         ChainResidual(proc_fn, jac=proc_jac, name="process")],
        dtype=acc.dtype, device=acc.device,
    )


def _run_lm(problem, *, max_iter, ftol, xtol, gtol, progress, desc, damping=None):
    from .lm.damping import MarquardtDamping
    from .lm import LevenbergMarquardt
    from .lm.linear import SchurComplementSolver

    log = []

    def cb(it, values, x, entry):
        if entry["accepted"] or not log:
            terms = problem.cost_terms(values, x)
            ft, fp = 2 * terms["triad"], 2 * terms["process"]
        else:  # a rejected step leaves the point unchanged
            ft, fp = log[-1]["F_triad"], log[-1]["F_process"]
        log.append({"iteration": it, "F_triad": ft, "F_process": fp,
                    "lambda": entry["lambda"], "accepted": bool(entry["accepted"])})

    if damping is None:
        # Marquardt's rule (λ ÷ 10 / × 10) from λ₀ = 10⁻⁶ with diag(H) scaling: on the [S16]
        # problems it needs ~30 % fewer iterations than Nielsen's rule from 10⁻³ (which spends ~10
        # iterations walking λ down after the first step) and reaches the same minima.
        damping = MarquardtDamping(tau=1e-6, scaling="marquardt")
    elif callable(damping) and not hasattr(damping, "update"):
        damping = damping()
    lm = LevenbergMarquardt(damping, SchurComplementSolver("tridiagonal"), max_iter=max_iter, ftol=ftol, xtol=xtol,
                            gtol=gtol, progress=progress, desc=desc, callback=cb)
    terms0 = problem.cost_terms(problem.initial_values(), problem.x0)
    log.append({"iteration": 0, "F_triad": 2 * terms0["triad"], "F_process": 2 * terms0["process"],
                "lambda": float("nan"), "accepted": True})
    res = lm.solve(problem)
    return res, log


def self_calibrate(
    acc,
    time_or_dt,
    *,
    steps=None,
    nominal_positions,
    nominal_orientations=None,
    fixed: int = 0,
    acc_noise_std=0.02,
    process_variances: dict | None = None,
    process_noise="s16",
    marginal_scale: bool | str = True,
    noise_max_iter: int = 30,
    noise_rtol: float = 0.01,
    sensor_params=None,
    init_motion=None,
    max_iter: int = 200,
    ftol: float = 1e-12,
    xtol: float = 1e-12,
    gtol: float = 1e-9,
    progress: bool = False,
    rerun_from_estimate: bool | str = True,
    rerun_rms: float = 1.5,
    covariance: bool = True,
    raise_on_divergence: bool = False,
    divergence_kwargs: dict | None = None,
    warm_start_motion: bool = True,
    restart_on_divergence: bool = True,
    damping=None,
    dtype=torch.float64,
    device=None,
) -> SelfCalResult:
    """[S16] self-calibration: triad poses and motion from accelerometer triad outputs alone.

    Minimises F of [S16] eq. 15 — triad residuals (eq. 13) + process residuals (eq. 14, weights
    from eq. 8) — over the motion states x_1:T and the poses of all triads but ``fixed``
    (eq. 16), with the structured Levenberg–Marquardt of :mod:`accel_bayes.inference.lm`
    (motion eliminated by a block-tridiagonal Schur complement; quaternions on the manifold via
    q ⊞ δ = q ∘ exp(δ)).

    Parameters
    ----------
    acc : (T, A, 3) m/s² triad outputs, each in its sensor frame.
    time_or_dt : sample step Δt (s, scalar) or sample times (T,) s.
    steps : None (consecutive samples of the recording) or (T−1,) whole numbers ≥ 1: how many
        steps of the recording's sample grid lie between consecutive fitted samples, when some
        were left out (a sample selection).  The left-out samples' states are integrated out
        exactly (:func:`bridged_process_whitening`).
    nominal_positions : (A, 3) m — starting positions (the construction plan); the fixed
        triad's row defines the origin of the array frame.
    nominal_orientations : (A, 4) array → sensor quaternions (identity if None); likewise.
    fixed : index of the triad held at its nominal pose.
    acc_noise_std : m/s², scalar, (A,) or (A, 3); default 0.02 ([S16] §IV-B: σ² = 4·10⁻⁴).
    process_variances : dict acc / int / omega_dot of eq. 8 (default
        :data:`accel_bayes.physics.models.S16_PROCESS_VARIANCES`, the paper's 10³, 10⁻⁷, 10³).
        Only with ``process_noise="s16"``.
    process_noise : the motion model.  ``"s16"`` (default; the paper's experiments): eq. 8 with the
        fixed ``process_variances``.  ``"estimate"`` (issue #12): the continuous-time white-noise-on-jerk model (:func:`wnoj_process_covariance`; same
        eq. 7 transition, ω the exact integral of ω̇) whose two intensities q_a, q_ω are estimated
        by the type-II ML fixed point q ← q · rss/(n − h) (:func:`process_noise_statistics`,
        :func:`update_process_intensities`) alternated with the joint LM; q_ω starts 10³ below the
        raw-output guess (stiff) and every LM run from zero motion starts stiff again.  A dict
        ``"estimate-snap"`` (issue #12; the default of the pipeline and the CLI): the smoother
        continuous-time model — white noise on the snap
        ω⃛ and on ä_lin, state x = [a_lin, ω, ω̇, ω̈, ȧ_lin] (T, 15), exact discretisation
        (:func:`continuous_process_covariance`, :func:`integrated_wiener_covariance`); ω̇ and a_lin
        are then smooth paths, as in hand motion, where the jerk model makes ω̇ a Brownian path.
        Intensities and scale as with "estimate"; the start intensities come from second
        differences of the outputs (:func:`initial_smooth_process_intensities`).  The triad residuals
        read only [a_lin, ω, ω̇]; ω̈, ȧ_lin enter the process residuals alone.
        ``{"acc": q_a, "omega": q_ω}`` (optionally ``"dim": 12 or 15``): that model with fixed
        intensities.
        ``result.process_noise`` records the mode, the intensities and the fixed-point history.
    marginal_scale : with the continuous-time model, move the joint MAP along the accelerometer-only
        scale orbit (:func:`scale_orbit`) to the maximum of the Laplace marginal likelihood of the
        poses (:func:`marginal_scale_score`): the joint MAP's scale is set by the motion prior alone
        and comes out too large (experiments/s16_handlike_map.md).  The covariance stays the MAP's.
        ``True`` (default): the Laplace marginal −log p(z | poses_c) ≈ ½F(x̂_c) + ½ log det H_xx(x̂_c)
        itself is minimised over the orbit parameter c (x̂_c the motion-only MAP at the orbit's
        poses; :func:`laplace_scale_nll`, safeguarded parabolic steps).  ``"score"``: the root of
        :func:`marginal_scale_score` instead (the earlier method; its trace term neglects how the
        triad Jacobians change with the motion, which on slow, weakly determined motion left the
        board 0.46 % large where the Laplace marginal's minimum is at the truth, issue #12).
    noise_max_iter, noise_rtol : iteration limit and relative tolerance of the intensity fixed point.
    sensor_params : known triad parameters ``(S, offset)`` or a dict with keys "S" and "offset";
        S (A, 3, 3) upper-triangular (or its 6 parameters (A, 6), [S16] eq. 21), offset (A, 3).
        Default: ideal triads (S = I, o = 0).
    init_motion : (T, 9) initial states ((T, 15) also accepted with "estimate-snap"; a (T, 9) start
        gets zero extra derivatives); default zeros ([S16] §VI-B: a non-zero start would
        predetermine the sign of ω).
    max_iter, ftol, xtol, gtol : LM stopping rules (:class:`~accel_bayes.inference.lm.StoppingRule`).
    progress : tqdm bar per LM run.
    rerun_from_estimate : after a run that did not diverge, run again from its poses with zero
        motion and keep the run with the lower cost ([S16] §VI-A remedy for partial minima,
        where ω took the wrong sign over part of the record).  ``"auto"``: re-run only when the
        first run's RMS whitened triad residual exceeds ``rerun_rms`` (a partial minimum misfits
        the data by many noise std; the global one fits to ≈ 1) — half the time on good data.
    covariance : compute the Laplace covariance (Schur complement of the Gauss–Newton matrix at
        the optimum, motion marginalised).
    raise_on_divergence : raise :class:`SelfCalDiverged` instead of returning a result with
        status "diverged" (whose poses cannot be read either way).
    divergence_kwargs : bounds passed to :func:`check_divergence`.
    warm_start_motion : first solve the motion alone with the poses held at their start values
        (from ``init_motion``, zero by default), then run the joint LM from that motion.  [S16]
        starts the joint LM from zero motion directly (``False``); the joint problem is then
        easily pulled into the diverged minima of Table III, even from the true poses, because
        the pose Jacobians vanish at zero motion and the first steps move poses and motion
        against each other.  The warm start keeps the zero-motion principle of [S16] §VI-B (the
        sign of ω is not predetermined: ω enters the motion-only stage through ω̇ and the
        integration constraint) and converges in ~20 iterations.
    restart_on_divergence : when the first run ends in a diverged minimum ([S16] Table III), run
        once more from the start positions with the diverged run's *orientations* and zero motion
        (label "restart"), and continue from that run if it does not diverge.  Orientations are
        fixed by the common (gravity-dominated) specific force that all triads see, so they
        converge even in the runs whose positions collapse or run off: with 20° initial
        orientation errors on the [S16] table motion, a run whose positions collapsed towards
        the fixed triad had brought the orientations to within 2–5°, and the restart from there
        converged to the global minimum.  The restart uses no information beyond the data and
        the start poses.
    damping : a zero-argument factory of LM damping strategies (each LM run needs a fresh one),
        or None: Marquardt's rule, diag(H) scaling, λ₀ = 10⁻⁶ (see ``_run_lm``).  A strategy
        instance is also accepted (it is then shared by the runs and re-initialised by each).

    Returns
    -------
    :class:`SelfCalResult`.
    """
    t_start = _time.perf_counter()
    acc = torch.as_tensor(acc, dtype=dtype, device=device)
    if acc.dim() != 3 or acc.shape[-1] != 3:
        raise ValueError(f"acc: expected shape (T, A, 3), got {tuple(acc.shape)}")
    T, A = acc.shape[0], acc.shape[1]
    if T < 3:
        # the process model ([S16] eq. 7–8) links consecutive samples: fewer than 3 leave it nothing to constrain
        raise UserError(f"acc: self-calibration needs at least 3 samples (time), the recording has {T}")
    if not bool(torch.isfinite(acc).all()):
        raise ValueError("acc: expected finite triad outputs (NaN/inf found); drop missing triads or samples first")
    if not 0 <= int(fixed) < A:
        raise ValueError(f"fixed: expected a triad index in 0..{A - 1}, got {fixed}")
    fixed = int(fixed)
    p0 = torch.as_tensor(nominal_positions, dtype=dtype, device=device)
    if p0.shape != (A, 3):
        raise ValueError(f"nominal_positions: expected shape ({A}, 3), got {tuple(p0.shape)}")
    if nominal_orientations is None:
        q0 = torch.zeros(A, 4, dtype=dtype, device=device)
        q0[:, 0] = 1.0
    else:
        q0 = torch.as_tensor(nominal_orientations, dtype=dtype, device=device)
        if q0.shape != (A, 4):
            raise ValueError(f"nominal_orientations: expected shape ({A}, 4), got {tuple(q0.shape)}")
        q0 = quat_normalize(q0)
    from ..physics.arrays import check_triad_geometry

    check_triad_geometry(p0)
    dt = _time_steps(time_or_dt, T, dtype, acc.device)
    inv_std = _as_inv_std(acc_noise_std, A, dtype, acc.device)
    S, offset = _sensor_params(sensor_params, A, dtype, acc.device)
    if isinstance(process_noise, dict):
        mode, intensities = "fixed", {k: float(process_noise[k]) for k in ("acc", "omega")}
        dim = int(process_noise.get("dim", 9))
        if dim not in _CHAIN_ORDERS:
            raise ValueError(f"process_noise: 'dim' expected one of {tuple(_CHAIN_ORDERS)}, got {dim}")
    elif process_noise in PROCESS_NOISE_MODES:
        mode, intensities = process_noise, None
        dim = MOTION_MODEL_DIMS.get(mode, 9)
    else:
        raise ValueError(f"process_noise: expected one of {PROCESS_NOISE_MODES} or a dict of intensities "
                         f"acc, omega, got {process_noise!r}")
    estimated = mode in MOTION_MODEL_DIMS
    if mode != "s16" and process_variances is not None:
        raise ValueError("process_variances are the [S16] eq. 8 variances: give them with process_noise='s16'")
    if mode == "s16":
        if steps is None or bool((torch.as_tensor(steps) == 1).all()):
            sqrt_info = process_sqrt_information(dt, process_variances)
        else:
            sqrt_info = bridged_process_whitening(dt, steps, process_variances)
    else:
        if intensities is None:
            if dim == 9:
                intensities = initial_process_intensities(acc, dt, p0, q0, fixed, inv_std)
            else:
                intensities = initial_smooth_process_intensities(acc, dt, p0, q0, fixed, inv_std, dim)
            intensities["omega"] *= _START_STIFFNESS
        sqrt_info = continuous_process_whitening(dt, intensities, dim)
    noise = {"W": sqrt_info, "q": intensities, "start": intensities, "history": []}
    if init_motion is None:
        x0 = torch.zeros(T, dim, dtype=dtype, device=acc.device)
    else:
        x0 = torch.as_tensor(init_motion, dtype=dtype, device=acc.device).clone()
        if x0.shape == (T, 9) and dim > 9:  # [a_lin, ω, ω̇] given: the extra derivatives start at zero
            x0 = torch.cat((x0, x0.new_zeros(T, dim - 9)), -1)
        if x0.shape != (T, dim):
            raise ValueError(f"init_motion: expected shape ({T}, 9) or ({T}, {dim}), got {tuple(x0.shape)}")
    n_con = {"triad": T * A, "process": T - 1}
    n_total = n_con["triad"] + n_con["process"]
    dkw = divergence_kwargs or {}

    def one_run(p_start, q_start, x_start, label):
        log = []
        if estimated and noise["q"] != noise["start"]:
            # every run from zero motion starts stiff again (continuation, see _START_STIFFNESS):
            # the re-run and the restart from the loose intensities let the poses run off.
            noise["q"] = {"acc": noise["q"]["acc"], "omega": noise["q"]["omega"] * _START_STIFFNESS}
            noise["W"] = continuous_process_whitening(dt, noise["q"], dim)
        x_start = x_start.clone()
        if warm_start_motion:
            # Motion-only stage at the start poses (a well-posed problem in the states alone);
            # from zero motion it does not predetermine the sign of ω either ([S16] §VI-B).
            prob0 = build_problem(acc, dt, p_start, q_start, x_start, fixed, inv_std, noise["W"], S, offset,
                                  poses_fixed=True)
            res0, log0 = _run_lm(prob0, max_iter=max_iter, ftol=1e-10, xtol=xtol, gtol=gtol, progress=progress,
                                 desc=f"selfcal {label} (motion)", damping=damping)
            for e in log0:
                e["stage"] = "motion"
            log.extend(log0)
            if bool(torch.isfinite(res0.locals).all()):
                x_start = res0.locals
        prob = build_problem(acc, dt, p_start, q_start, x_start, fixed, inv_std, noise["W"], S, offset)
        res, log1 = _run_lm(prob, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol, progress=progress,
                            desc=f"selfcal {label}", damping=damping)
        offset_it = log[-1]["iteration"] if log else 0
        for e in log1:
            e["stage"] = "joint"
            e["iteration"] += offset_it
        log.extend(log1[1:] if log else log1)
        if estimated:
            res = _estimate_noise(res, log, label)
        for e in log:
            e["F"] = e["F_triad"] + e["F_process"]
            e["F_per_constraint"] = e["F"] / n_total
            e["run"] = label
        F = 2.0 * res.cost
        p, q, x = res.values["position"], res.values["rotation"], res.locals
        reason = res.reason
        rms = _whitened_rms(log[-1]["F_triad"], 3 * T * A)
        why = check_divergence(p, x, p0, fixed, F, rms_residual=rms, **dkw)
        if why is None and reason == "non_finite":
            why = "the LM linearisation became non-finite"
        summary = {"label": label, "F": F, "rms_residual": rms, "n_iter": res.n_iter,
                   "iterations": len(log) - 1, "lm_reason": reason,
                   "converged": bool(res.converged), "diverged": why,
                   "positions": p.detach(), "orientations": q.detach(), "states": x.detach()}
        return res, log, F, why, summary

    def _estimate_noise(res, log, label):
        # Type-II ML of the process intensities: alternate the fixed-point update with the joint
        # LM (warm-started at the previous estimate) until the intensities move < noise_rtol.
        for k in range(noise_max_iter):
            vals, x = res.values, res.locals
            if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(vals["position"]).all())):
                break
            stats = process_noise_statistics(x, vals["position"], vals["rotation"], dt, noise["W"], inv_std, S)
            new = update_process_intensities(noise["q"], stats)
            change = max(abs(math.log(new[c] / noise["q"][c])) for c in new)
            noise["history"].append({"run": label, "intensities": dict(noise["q"]),
                                     "stats": stats, "change": change})
            if change < noise_rtol:
                break
            noise["q"] = new
            noise["W"] = continuous_process_whitening(dt, new, dim)
            prob_k = build_problem(acc, dt, vals["position"], vals["rotation"], x, fixed, inv_std, noise["W"],
                                   S, offset)
            res, log_k = _run_lm(prob_k, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol, progress=progress,
                                 desc=f"selfcal {label} (noise {k + 1})", damping=damping)
            off = log[-1]["iteration"]
            for e in log_k:
                e["stage"] = f"noise {k + 1}"
                e["iteration"] += off
            log.extend(log_k)  # its iteration 0 carries the cost at the new intensities
        return res

    runs = []
    res, log, F, why, summ = one_run(p0, q0, x0, "first")
    runs.append(summ)
    full_log = list(log)
    q_div = res.values["rotation"]
    if why is not None and restart_on_divergence and bool(torch.isfinite(q_div).all()):
        res_r, log_r, F_r, why_r, summ_r = one_run(p0, quat_normalize(q_div), torch.zeros_like(x0), "restart")
        runs.append(summ_r)
        full_log.extend(log_r)
        summ_r["kept"] = why_r is None
        if why_r is None:
            res, log, F, why, summ = res_r, log_r, F_r, why_r, summ_r
    best = (res, log, F, why)
    if rerun_from_estimate not in (True, False, "auto"):
        raise ValueError(f"rerun_from_estimate: expected True, False or 'auto', got {rerun_from_estimate!r}")
    do_rerun = bool(rerun_from_estimate) if rerun_from_estimate != "auto" else summ["rms_residual"] > rerun_rms
    if why is None and do_rerun:
        res2, log2, F2, why2, summ2 = one_run(res.values["position"], res.values["rotation"],
                                              torch.zeros_like(x0), "rerun")
        runs.append(summ2)
        full_log.extend(log2)
        # Keep the re-run unless it is worse: on the global optimum both runs agree, while a
        # partial minimum of the first run has the higher cost.
        if why2 is None and F2 <= F * (1 + 1e-9):
            best = (res2, log2, F2, why2)
        summ2["kept"] = best[0] is res2
    res, log, F, why = best
    status = "ok" if why is None else "diverged"
    out = SelfCalResult(
        status=status, reason=why or "", fixed=fixed,
        raw_positions=res.values["position"].detach(), raw_orientations=res.values["rotation"].detach(),
        states=res.locals.detach(), cost=F, cost_log=log, full_cost_log=full_log, n_constraints=n_con, runs=runs,
        converged=bool(res.converged), lm_reason=res.reason, n_iter=res.n_iter,
        process_noise={"mode": mode, "state_dim": dim,
                       "intensities": None if noise["q"] is None else dict(noise["q"]),
                       "variances": models.process_variances(process_variances) if mode == "s16" else None,
                       "history": noise["history"]},
    )
    if status == "ok" and covariance:
        _attach_covariance(out, res, A, fixed)
    if status == "ok" and mode != "s16" and marginal_scale:
        if marginal_scale == "score":
            _correct_scale(out, res, A, fixed, dt, noise["W"], inv_std, S)
        else:
            _laplace_scale(out, res, A, fixed, acc, dt, noise["W"], inv_std, S, offset, max_iter)
    out.seconds = _time.perf_counter() - t_start
    if status != "ok" and raise_on_divergence:
        raise SelfCalDiverged(f"self-calibration diverged: {why}", out)
    return out


# A whitened residual RMS above this contradicts the stated noise or the process variances: on
# the simulator's table motion the fit leaves triad 0.83–0.99 and process 0.40–1.70 (s16_plate,
# mimu8, T = 400–2000), on smooth hand-like motion triad 2.3–7.0 and process 4.6–12 (the
# constant-ω̇ process model cannot follow it; issue #12; experiments/s16_fitcheck.md).
MISFIT_RMS = 1.5
# A relative std of the board's scale above this means the motion does not fix the scale
# (accelerometer-only data are unchanged under r → c·r, ω → ω/√c, ω̇ → ω̇/c; only ω̇ = dω/dt ties c).
UNIDENTIFIED_SCALE_STD = 0.1


@dataclass
class FitCheck:
    """Whether a self-calibration's residuals agree with the stated noise, and whether the motion
    fixed the board's scale (:func:`fit_check`).

    rms_triad, rms_process : RMS whitened triad / process residual of the returned run (≈ 1 or
        below when the model and the stated noise describe the data).
    misfit : rms_triad or rms_process > ``rms_limit``: the Laplace covariance assumes the stated
        noise and the process model (fixed [S16] variances or estimated intensities), which the residuals contradict; ``inflation`` =
        max(rms_triad, rms_process)² is the factor a covariance takes to match them (1 when no
        misfit).  Only a necessary check: a fit can leave residuals ≈ 1 and still be wrong in
        scale (experiments/s16_fitcheck.md).
    scale : fitted size along the board's scale mode relative to the start (1 = unchanged), and
        scale_std its relative Laplace std, inflated; identified : scale_std <= ``scale_limit``.
    """

    rms_triad: float
    rms_process: float
    misfit: bool
    inflation: float
    scale: float
    scale_std: float
    identified: bool
    rms_limit: float
    scale_limit: float

    def warnings(self) -> list[str]:
        """Why the result is not trustworthy (empty when it is), one sentence each, with numbers."""
        out = []
        if self.misfit:
            out.append(f"the residuals contradict the model (RMS of the whitened residuals: triad "
                       f"{self.rms_triad:.3g}, process {self.rms_process:.3g}; > {self.rms_limit:g} is a misfit): the "
                       f"motion model or the stated noise does not describe this recording, so the poses may "
                       f"be biased; the reported std are inflated by {math.sqrt(self.inflation):.3g}")
        if not self.identified:
            out.append(f"unidentified: the motion does not fix the board's scale (relative std "
                       f"{self.scale_std:.3g} > {self.scale_limit:g})")
        return out

    def to_dict(self) -> dict:
        return {"rms_triad": self.rms_triad, "rms_process": self.rms_process, "misfit": self.misfit,
                "covariance_inflation": self.inflation, "scale": self.scale, "scale_std": self.scale_std,
                "scale_identified": self.identified, "rms_limit": self.rms_limit, "scale_limit": self.scale_limit}


def fit_check(result: SelfCalResult, nominal_positions, *, rms_limit: float = MISFIT_RMS,
              scale_limit: float = UNIDENTIFIED_SCALE_STD) -> FitCheck:
    """Residuals against the stated noise and the std of the scale mode of an "ok" result.

    The scale mode: with u the start positions relative to the fixed triad (the nominal board,
    stacked over the free triads), the fitted scale is c = uᵀp̂ / uᵀu (p̂ likewise relative) and
    its variance uᵀ C u / (uᵀu)² with C the joint Laplace covariance of the free positions
    (correlations across triads included), times ``inflation`` when the residuals say the noise
    is larger than stated.
    """
    result._require_ok()
    last = result.cost_log[-1]
    T, A = result.states.shape[0], result.raw_positions.shape[0]
    rms_t = _whitened_rms(last["F_triad"], 3 * T * A)  # the returned run's rms_residual
    rms_p = _whitened_rms(last["F_process"], result.states.shape[-1] * (T - 1))
    misfit = rms_t > rms_limit or rms_p > rms_limit
    inflation = max(rms_t, rms_p) ** 2 if misfit else 1.0
    fixed = result.fixed
    free = [j for j in range(A) if j != fixed]
    p0 = torch.as_tensor(nominal_positions, dtype=result.raw_positions.dtype)
    u = (p0 - p0[fixed])[free].reshape(-1)
    p = (result.raw_positions - result.raw_positions[fixed])[free].reshape(-1)
    uu = float(u @ u)
    scale = float(u @ p) / uu
    if result.covariance is not None:
        Cp = result.covariance[:3 * len(free), :3 * len(free)]
        scale_std = math.sqrt(max(float(u @ Cp @ u), 0.0) * inflation) / uu
    else:
        scale_std = math.nan
    identified = bool(scale_std <= scale_limit)  # NaN (no covariance) counts as not identified
    return FitCheck(rms_triad=rms_t, rms_process=rms_p, misfit=bool(misfit), inflation=float(inflation),
                    scale=scale, scale_std=scale_std, identified=identified, rms_limit=float(rms_limit),
                    scale_limit=float(scale_limit))


def _block_tridiagonal_logdet(D: torch.Tensor, B: torch.Tensor) -> float:
    """log det of the symmetric positive definite block-tridiagonal matrix with diagonal blocks D
    (T, n, n) and upper blocks B (T−1, n, n): Σ log det of the Schur complements
    S_{i+1} = D_{i+1} − B_iᵀ S_i⁻¹ B_i (forward elimination, Cholesky per block; numpy loop over T)."""
    import numpy as np

    Dn, Bn = D.detach().cpu().numpy(), B.detach().cpu().numpy()
    S = Dn[0]
    total = 0.0
    for i in range(Dn.shape[0]):
        L = np.linalg.cholesky(S)
        total += 2.0 * float(np.log(np.diag(L)).sum())
        if i + 1 < Dn.shape[0]:
            Y = np.linalg.solve(L, Bn[i])  # L⁻¹ B_i
            S = Dn[i + 1] - Y.T @ Y
    return total


def laplace_scale_nll(c: float, positions, states, orientations, fixed: int, acc, dt, W, inv_std, S=None,
                      offset=None, max_iter: int = 100):
    """Laplace −log p(z | poses on the scale orbit at c), motion integrated out, up to a constant.

    Poses and a start motion from :func:`scale_orbit` (positions (A, 3) m, states (T, d)); the
    motion-only MAP x̂_c at those poses by the structured LM; then ½F(x̂_c) + ½ log det H_xx(x̂_c)
    with H_xx the Gauss–Newton matrix of the motion (triad + process rows, block tridiagonal).
    Returns (value, positions_c, x̂_c).  Dimensionless (a negative log-likelihood)."""
    pc, xc = scale_orbit(positions, states, fixed, c)
    prob = build_problem(acc, dt, pc, orientations, xc, fixed, inv_std, W, S, offset, poses_fixed=True)
    r, _ = _run_lm(prob, max_iter=max_iter, ftol=1e-14, xtol=1e-14, gtol=1e-12, progress=False, desc="scale")
    x = r.locals
    _, _, D, B = _motion_hessian(x, pc, orientations, dt, W, inv_std, S)
    logdet = _block_tridiagonal_logdet(D, B)
    return float(r.cost) + 0.5 * logdet, pc, x


def _scale_orbit_start(out: SelfCalResult, res, A: int, fixed: int):
    """Where both scale corrections start: (positions, states and orientations of the joint MAP,
    copies; Var(c), the Laplace variance of the relative scale c along the fitted board, from the
    positions' joint covariance), or None when the MAP has no usable covariance."""
    from .lm.linear import NotPositiveDefinite

    free = [j for j in range(A) if j != fixed]
    if out.covariance is not None:
        Cp = out.covariance[:3 * len(free), :3 * len(free)]
    else:
        try:
            Cp = res.covariance()[:3 * len(free), :3 * len(free)]
        except NotPositiveDefinite:
            return None
    p0, x0, q = out.raw_positions.clone(), out.states.clone(), out.raw_orientations
    d = (p0 - p0[fixed])[free].reshape(-1)
    return p0, x0, q, float(d @ Cp @ d) / float(d @ d) ** 2


def _laplace_scale(out: SelfCalResult, res, A: int, fixed: int, acc, dt, W, inv_std, S, offset, max_iter: int,
                   max_steps: int = 10) -> None:
    """Move the joint MAP along the scale orbit to the minimum of the Laplace marginal
    :func:`laplace_scale_nll` over c.  Start: c = 1, 1 ± sd (sd the Laplace std of the relative
    scale at the joint MAP); then parabolic steps through the three best points, each at most
    4 sd (and 5 %) from the best, until a step is below 0.02 sd.  Poses and motion become the
    orbit's poses at the best c and the motion-only MAP there; the covariance stays the joint
    MAP's.  Records the evaluations in ``out.process_noise["scale_correction"]``."""
    import numpy as np
    from .lm.linear import NotPositiveDefinite

    start = _scale_orbit_start(out, res, A, fixed)
    if start is None:
        return
    p0, x0, q, var_c = start
    sd = math.sqrt(max(var_c, 1e-16))
    evals = {}
    steps = []

    def f(c):
        c = float(c)
        if c not in evals:
            try:
                val, pc, xc = laplace_scale_nll(c, p0, x0, q, fixed, acc, dt, W, inv_std, S, offset, max_iter)
            except (np.linalg.LinAlgError, NotPositiveDefinite):
                val, pc, xc = math.inf, None, None
            evals[c] = (val, pc, xc)
            steps.append({"c": c, "nll": val})
        return evals[c][0]

    for c in (1.0, 1.0 - sd, 1.0 + sd):
        f(c)
    for _ in range(max_steps):
        finite = [c for c in evals if math.isfinite(evals[c][0])]
        if len(finite) < 3:
            break
        best3 = sorted(sorted(finite, key=lambda c: evals[c][0])[:3])
        cb = min(finite, key=lambda c: evals[c][0])
        ys = [evals[c][0] - evals[cb][0] for c in best3]
        a2, a1, _ = np.polyfit(np.array(best3) - cb, ys, 2)
        if a2 > 0:
            c_new = cb - a1 / (2 * a2)
        else:  # not convex through these points: walk downhill
            c_new = cb + (2 * sd if best3[-1] == cb else -2 * sd)
        c_new = min(max(c_new, cb - 4 * sd, 0.95), cb + 4 * sd, 1.05)
        if min(abs(c_new - c) for c in evals) < 0.02 * sd:
            break
        f(c_new)
    cb = min(evals, key=lambda c: evals[c][0])
    if not math.isfinite(evals[cb][0]):
        return
    _, pc, xc = evals[cb]
    out.raw_positions, out.states = pc, xc.detach()
    out.process_noise["scale_correction"] = {"method": "laplace", "factor": cb, "steps": steps}


def _correct_scale(out: SelfCalResult, res, A: int, fixed: int, dt, W, inv_std, S, max_steps: int = 6) -> None:
    """Move the joint MAP along the scale orbit to the maximum of the Laplace marginal likelihood
    of the poses (motion integrated out): the root of d(−log p)/dc (:func:`marginal_scale_score`),
    bracketed from the joint MAP by Newton steps with Var(c), the Laplace variance of the scale along
    the fitted board (positions' joint covariance, motion marginalised), then regula falsi.  The
    covariance is the joint MAP's.  Records the evaluations in
    ``out.process_noise["scale_correction"]``."""
    start = _scale_orbit_start(out, res, A, fixed)
    if start is None:
        return
    p0, x0, q, var_c = start
    sd = math.sqrt(max(var_c, 1e-30))
    steps = []

    def g(c):  # d(−log p)/dc at the orbit point φ_c(MAP)
        pc, xc = scale_orbit(p0, x0, fixed, c)
        val = marginal_scale_score(xc, pc, q, dt, W, inv_std, fixed, S) / c
        steps.append({"c": c, "dnll_dc": val})
        return val

    # Root of g(c) = 0: first bracket it (Newton steps with the Laplace curvature 1/Var(c), then
    # secant extrapolation, at most 5 % per step), then the Illinois variant of regula falsi inside
    # the bracket.  The Laplace curvature can be several times off, so plain Newton may oscillate.
    a, ga = 1.0, g(1.0)
    b = 1.0 - max(min(ga * var_c, 0.05), -0.05)
    gb = g(b)
    for _ in range(max_steps):
        if (ga > 0) != (gb > 0):
            break
        slope = (gb - ga) / (b - a)
        step = -gb / slope if slope > 0 else (b - a)
        step = max(min(step, 0.05), -0.05)
        a, ga, b = b, gb, b + step
        gb = g(b)
    if (ga > 0) != (gb > 0):
        for _ in range(12):
            if abs(b - a) < 0.01 * sd:
                break
            c = b - gb * (b - a) / (gb - ga)
            gc = g(c)
            if (gc > 0) != (gb > 0):
                a, ga = b, gb
            else:
                ga = 0.5 * ga
            b, gb = c, gc
    c_b = b
    p, x = scale_orbit(p0, x0, fixed, c_b)
    total = c_b
    out.raw_positions, out.states = p, x
    out.process_noise["scale_correction"] = {"method": "score", "factor": total, "steps": steps}


def _whitened_rms(F: float, count: int) -> float:
    """RMS of ``count`` whitened residuals whose sum of squares is ``F`` (≈ 1 at the stated noise)."""
    return math.sqrt(max(F, 0.0) / max(count, 1))


def _attach_covariance(out: SelfCalResult, res, A: int, fixed: int) -> None:
    """Laplace covariance of the free poses (Gauss–Newton information, motion marginalised).

    The solver's cost is ½Σ‖e‖², so its Gauss–Newton matrix JᵀJ is the information matrix of the
    whitened model; its Schur complement over the motion is the information of the poses.
    """
    from .lm.linear import NotPositiveDefinite

    try:
        C = res.covariance()
    except NotPositiveDefinite:
        return
    labels = res.free_labels()
    free = [j for j in range(A) if j != fixed]
    nf = len(free)
    pos_cov = C.new_zeros(A, 3, 3)
    rot_cov = C.new_zeros(A, 3, 3)
    # free_labels order: "position" rows (free triads × xyz), then "rotation" rows.
    assert len(labels) == 6 * nf and labels[0][0] == "position" and labels[3 * nf][0] == "rotation"
    for k, j in enumerate(free):
        pos_cov[j] = C[3 * k:3 * k + 3, 3 * k:3 * k + 3]
        o = 3 * nf + 3 * k
        rot_cov[j] = C[o:o + 3, o:o + 3]
    out.position_cov = pos_cov
    out.rotation_cov = rot_cov
    out.covariance = C

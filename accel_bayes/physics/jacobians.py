"""Derivatives of the rigid-body kinematics, the one home of every Jacobian of the signal model.

The model ([C21] eq. 4a, [S16] eq. 2; :func:`accel_bayes.physics.models.specific_force`): the specific
force at a point r of the board, array frame,

    f(r; ω, ω̇, s) = ω × (ω × r) + ω̇ × r + s = Ω(ω)² r + Ω(ω̇) r + s,

with Ω(a) the skew matrix of a.  Its partial derivatives:

    ∂f/∂ω  = (ω·r) I + ω rᵀ − 2 r ωᵀ          (from ω × (ω × r) = ω (ωᵀr) − r |ω|²)
    ∂f/∂ω̇ = −Ω(r)
    ∂f/∂s  = I
    ∂f/∂r  = Ω(ω)² + Ω(ω̇)                     (the same for every point)

and, for the linear structure h(ω, θ) = G(θ) u(ω) of [C21] eq. 5 (DESIGN §3.1), ∂u/∂ω (6×3) and
the constant ∂²u/∂ω² (6×3×3).

:class:`AxisProjection` is the same model projected on the sensing axes of an array and factored
for speed (motion estimation solves millions of 9-unknown problems): with R_a the direction of
sensor axis m = (k, a) in the array frame,

    f_m = R_a·f(r_k) = α_m β_m − |ω|² p_m + C_m·φ,    α_m = R_a·ω,  β_m = r_k·ω,  p_m = R_a·r_k,
    ∂f_m/∂ω = α_m r_k + β_m R_a + γ_m ω,  γ_m = −2 p_m,   ∂f_m/∂φ = C_m = [r_k × R_a, R_a],

φ = [ω̇; s].  ``tests/physics/test_jacobians.py`` pins every function here against finite differences,
against autograd of :func:`~accel_bayes.physics.models.specific_force`, and the factored form against
the plain one.

Shapes follow :func:`~accel_bayes.physics.models.specific_force`: ω, ω̇ (..., 3) (batch first); points
r (..., A, 3); the batch dimensions broadcast.  Units: r in m, ω in rad/s, ω̇ in rad/s².
"""
from __future__ import annotations

import torch

from .geometry import skew

__all__ = [
    "df_domega",
    "df_domega_dot",
    "df_ds",
    "df_dr",
    "df_dmotion",
    "du_domega",
    "d2u_domega2",
    "AxisProjection",
    "axis_force",
    "axis_force_jacobian",
]


def df_domega(r: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """∂f/∂ω = (ω·r) I + ω rᵀ − 2 r ωᵀ at points r (..., A, 3) m for ω (..., 3) rad/s
    ([C21] eq. 4a).  Returns (..., A, 3, 3) in m/rad (m/s² per rad/s)."""
    w = omega.unsqueeze(-2)
    w, r = torch.broadcast_tensors(w, r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device)
    wr = (w * r).sum(-1)[..., None, None]
    return wr * eye + w.unsqueeze(-1) * r.unsqueeze(-2) - 2.0 * r.unsqueeze(-1) * w.unsqueeze(-2)


def df_domega_dot(r: torch.Tensor) -> torch.Tensor:
    """∂f/∂ω̇ = −Ω(r) at points r (..., A, 3) m ([C21] eq. 4a; the first three columns of H(θ),
    eq. 5).  Returns (..., A, 3, 3) m/rad."""
    return -skew(r)


def df_ds(r: torch.Tensor) -> torch.Tensor:
    """∂f/∂s = I at points r (..., A, 3): (..., A, 3, 3), dimensionless ([C21] eq. 4a)."""
    return torch.eye(3, dtype=r.dtype, device=r.device).expand(*r.shape, 3)


def df_dr(omega: torch.Tensor, omega_dot: torch.Tensor) -> torch.Tensor:
    """∂f/∂r = Ω(ω)² + Ω(ω̇) for ω (..., 3) rad/s, ω̇ (..., 3) rad/s² ([C21] eq. 4a): (..., 3, 3)
    in s⁻² — the same matrix for every point of the board."""
    W = skew(omega)
    return W @ W + skew(omega_dot)


def df_dmotion(r: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """∂f/∂(ω, ω̇, s) at points r (..., A, 3) for ω (..., 3): (..., A, 3, 9), columns
    [∂f/∂ω, ∂f/∂ω̇, ∂f/∂s] (f is linear in ω̇ and s, so ω̇ is not needed)."""
    Jw = df_domega(r, omega)
    Jwd = df_domega_dot(r).expand(Jw.shape)
    return torch.cat((Jw, Jwd, df_ds(r).expand(Jw.shape)), -1)


def du_domega(omega: torch.Tensor) -> torch.Tensor:
    """∂u/∂ω (..., 6, 3) for u(ω) = [ωx², ωy², ωz², ωxωy, ωxωz, ωyωz] (DESIGN §3.1,
    :func:`accel_bayes.physics.models.u_of_omega`); ω (..., 3) rad/s, entries in rad/s."""
    x, y, z = omega.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (
            torch.stack((2 * x, o, o), -1),
            torch.stack((o, 2 * y, o), -1),
            torch.stack((o, o, 2 * z), -1),
            torch.stack((y, x, o), -1),
            torch.stack((z, o, x), -1),
            torch.stack((o, z, y), -1),
        ),
        -2,
    )


def d2u_domega2(dtype=torch.float64, device=None) -> torch.Tensor:
    """∂²u/∂ω_i∂ω_j (6, 3, 3), constant because u(ω) is quadratic (DESIGN §3.1)."""
    D = torch.zeros(6, 3, 3, dtype=dtype, device=device)
    D[0, 0, 0] = D[1, 1, 1] = D[2, 2, 2] = 2.0
    D[3, 0, 1] = D[3, 1, 0] = D[4, 0, 2] = D[4, 2, 0] = D[5, 1, 2] = D[5, 2, 1] = 1.0
    return D


class AxisProjection:
    """The kinematics projected on the M = 3K sensing axes of an array, factored (module doc).

    R (K, 3, 3) array → sensor rotations (row a of R_k: sensor axis a in the array frame);
    r (*G, K, 3) m positions, ``G`` () for one geometry or (D,) for D geometry draws.

    Attributes, per axis m = (k, a): ``Rm`` (M, 3) R_a; ``rk`` (*G, M, 3) r_k (``rkT`` its
    transpose); ``p`` (*G, M) p_m = R_a·r_k; ``gamma`` = −2p, ``gamma2`` = γ²; ``C`` (*G, M, 6)
    the constant rows ∂f_m/∂φ; and the per-geometry outer products flattened on the last axis
    (``rr`` r rᵀ, ``RR`` R Rᵀ, ``rR`` r Rᵀ, ``rC`` r Cᵀ, ``RC`` R Cᵀ, ``CC`` C Cᵀ) with which
    every normal-equation block is a sum over m of per-sample scalars times these, i.e. matrix
    products (N, M) × (M, c) and no per-sample small matmuls.
    """

    def __init__(self, R: torch.Tensor, r: torch.Tensor):
        K = R.shape[0]
        self.K = K
        self.Rm = R.reshape(3 * K, 3)
        self.r = r
        self.rk = r.repeat_interleave(3, dim=-2)
        self.rkT = self.rk.transpose(-1, -2)
        self.p = (self.rk * self.Rm).sum(-1)
        self.gamma = -2 * self.p
        self.gamma2 = self.gamma * self.gamma
        Rm = self.Rm.expand(self.rk.shape)
        self.C = torch.cat((torch.linalg.cross(self.rk, Rm, dim=-1), Rm), -1)
        outer = lambda u, v: (u.unsqueeze(-1) * v.unsqueeze(-2)).flatten(-2)  # noqa: E731
        self.rr = outer(self.rk, self.rk)
        self.RR = outer(self.Rm, self.Rm)
        self.rR = outer(self.rk, Rm)
        self.rC = outer(self.rk, self.C)
        self.RC = outer(Rm, self.C)
        self.CC = outer(self.C, self.C)


def axis_force(x: torch.Tensor, proj: AxisProjection):
    """Projected specific force f_m (…, N, M) m/s² for motions x (…, N, 9) = [ω, ω̇, s], with
    the factors α = R_a·ω and β = r_k·ω (…, N, M) that the Jacobian rows reuse (module doc)."""
    w = x[..., 0:3]
    al = w @ proj.Rm.T
    be = w @ proj.rkT
    f = al * be - (w * w).sum(-1, keepdim=True) * proj.p.unsqueeze(-2) + x[..., 3:9] @ proj.C.transpose(-1, -2)
    return f, al, be


def axis_force_jacobian(x: torch.Tensor, proj: AxisProjection) -> torch.Tensor:
    """∂f_m/∂x (…, N, M, 9) of :func:`axis_force`: [α_m r_k + β_m R_a + γ_m ω, C_m]."""
    w = x[..., 0:3]
    _, al, be = axis_force(x, proj)
    a = (al.unsqueeze(-1) * proj.rk.unsqueeze(-3) + be.unsqueeze(-1) * proj.Rm
         + proj.gamma.unsqueeze(-2).unsqueeze(-1) * w.unsqueeze(-2))
    return torch.cat((a, proj.C.unsqueeze(-3).expand(*a.shape[:-1], 6)), -1)

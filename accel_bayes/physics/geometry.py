"""Rotation and cross-product algebra in torch, batched over leading dimensions.

Conventions (DESIGN §7.0, fixed by the recording contract):

* Quaternions are stored ``(w, x, y, z)`` (scalar first), Hamilton product.
* ``quat_to_matrix(q)`` is R(q) of DESIGN §7.0; an IMU with ``nominal_orientation = q`` reads
  ``v_sensor = R(q) @ v_array``.  This is the "body → sensor" rotation R_q of [S16] eq. 4.
* Rotation vectors (axis × angle, rad) are the tangent coordinates used by ``quat_exp`` /
  ``quat_log`` and by :func:`boxplus`.  [S16] eq. 18 uses the quaternion's vector part instead
  (half-angle coordinates); :func:`boxplus_s16` is kept for reference and comparison only.

Every function accepts any number of leading batch dimensions and keeps dtype/device of its
inputs.
"""
from __future__ import annotations


import torch

__all__ = [
    "skew",
    "unskew",
    "quat_normalize",
    "quat_mul",
    "quat_conj",
    "quat_to_matrix",
    "matrix_to_quat",
    "quat_rotate",
    "quat_exp",
    "quat_log",
    "boxplus",
    "boxminus",
    "boxplus_s16",
    "random_quaternion",
    "rotation_angle",
    "quat_identity",
]

_SMALL = 1e-8


def skew(v: torch.Tensor) -> torch.Tensor:
    """Skew matrix Ω(v) with Ω(v) @ b = v × b ([C21] notation below eq. 5).

    v: (..., 3) → (..., 3, 3).
    """
    x, y, z = v.unbind(-1)
    o = torch.zeros_like(x)
    return torch.stack(
        (
            torch.stack((o, -z, y), -1),
            torch.stack((z, o, -x), -1),
            torch.stack((-y, x, o), -1),
        ),
        -2,
    )


def unskew(m: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`skew` (antisymmetric part): (..., 3, 3) → (..., 3)."""
    return 0.5 * torch.stack(
        (m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), -1
    )


def quat_identity(*batch: int, dtype=torch.float64, device=None) -> torch.Tensor:
    """Identity quaternions of shape (*batch, 4)."""
    q = torch.zeros(*batch, 4, dtype=dtype, device=device)
    q[..., 0] = 1.0
    return q


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion with non-negative scalar part (a canonical sign for q ≡ −q)."""
    q = q / q.norm(dim=-1, keepdim=True)
    sign = torch.where(q[..., :1] < 0, -1.0, 1.0).to(q.dtype)
    return q * sign


def quat_mul(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product p ∘ q; R(p ∘ q) = R(p) R(q)."""
    pw, px, py, pz = p.unbind(-1)
    qw, qx, qy, qz = q.unbind(-1)
    return torch.stack(
        (
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ),
        -1,
    )


def quat_conj(q: torch.Tensor) -> torch.Tensor:
    """Conjugate (the inverse of a unit quaternion)."""
    return q * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=q.dtype, device=q.device)


def quat_to_matrix(q: torch.Tensor) -> torch.Tensor:
    """R(q) of DESIGN §7.0 for unit q = (w, x, y, z): (..., 4) → (..., 3, 3)."""
    w, x, y, z = q.unbind(-1)
    return torch.stack(
        (
            torch.stack((1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)), -1),
            torch.stack((2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)), -1),
            torch.stack((2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)), -1),
        ),
        -2,
    )


def matrix_to_quat(m: torch.Tensor) -> torch.Tensor:
    """Unit quaternion (w ≥ 0) of a rotation matrix, robust for all angles (Shepperd's method)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    tr = m00 + m11 + m22
    # Four candidate formulas; pick per element the one with the largest pivot.
    cands = torch.stack(
        (
            torch.stack((1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]), -1),
            torch.stack((m[..., 2, 1] - m[..., 1, 2], 1 + m00 - m11 - m22, m[..., 0, 1] + m[..., 1, 0], m[..., 0, 2] + m[..., 2, 0]), -1),
            torch.stack((m[..., 0, 2] - m[..., 2, 0], m[..., 0, 1] + m[..., 1, 0], 1 - m00 + m11 - m22, m[..., 1, 2] + m[..., 2, 1]), -1),
            torch.stack((m[..., 1, 0] - m[..., 0, 1], m[..., 0, 2] + m[..., 2, 0], m[..., 1, 2] + m[..., 2, 1], 1 - m00 - m11 + m22), -1),
        ),
        -2,
    )
    pivots = torch.stack((1 + tr, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22), -1)
    idx = pivots.argmax(-1)
    q = torch.gather(cands, -2, idx[..., None, None].expand(*idx.shape, 1, 4)).squeeze(-2)
    return quat_normalize(q)


def quat_rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """R(q) @ v, broadcasting q (..., 4) against v (..., 3)."""
    return (quat_to_matrix(q) @ v.unsqueeze(-1)).squeeze(-1)


def quat_exp(rotvec: torch.Tensor) -> torch.Tensor:
    """Unit quaternion of a rotation vector φ (rad): (cos|φ|/2, sin(|φ|/2) φ/|φ|)."""
    angle = rotvec.norm(dim=-1, keepdim=True)
    half = 0.5 * angle
    # sin(x/2)/x with its Taylor series near 0 so gradients stay finite at the identity.
    small = angle < 1e-6
    safe = torch.where(small, torch.ones_like(angle), angle)
    k = torch.where(small, 0.5 - angle * angle / 48.0, torch.sin(half) / safe)
    return torch.cat((torch.cos(half), k * rotvec), -1)


def quat_log(q: torch.Tensor) -> torch.Tensor:
    """Rotation vector (rad, angle in [0, π]) of a unit quaternion; inverse of :func:`quat_exp`."""
    q = quat_normalize(q)
    v = q[..., 1:]
    s = v.norm(dim=-1, keepdim=True)
    w = q[..., :1]
    angle = 2.0 * torch.atan2(s, w)
    small = s < 1e-7
    safe = torch.where(small, torch.ones_like(s), s)
    k = torch.where(small, 2.0 / w.clamp_min(_SMALL) * (1 - s * s / (3 * w * w).clamp_min(_SMALL)), angle / safe)
    return k * v


def boxplus(q: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """q ⊞ δ = q ∘ exp(δ): a tangent increment δ (rotation vector, rad) applied on the right.

    This is the exponential-map variant of [S16] eq. 17–18; its coordinates are full rotation
    angles, so covariances in them are directly angle covariances.  The result is re-normalised,
    which keeps long LM runs on the unit sphere to machine precision.
    """
    return quat_normalize(quat_mul(q, quat_exp(delta)))


def boxminus(q1: torch.Tensor, q0: torch.Tensor) -> torch.Tensor:
    """q1 ⊟ q0 = log(q0⁻¹ ∘ q1), the inverse of :func:`boxplus` (q0 ⊞ (q1 ⊟ q0) = q1)."""
    return quat_log(quat_mul(quat_conj(q0), q1))


def boxplus_s16(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """[S16] eq. 18: q ∘ (√(1 − |v|²), v); v is a quaternion vector part (half-angle scale).

    Valid for |v| < 1 only.  Kept to document the paper's choice; the package uses :func:`boxplus`.
    """
    n2 = (v * v).sum(-1, keepdim=True)
    if bool((n2 >= 1).any()):
        raise ValueError("boxplus_s16: increment norm must be < 1 (it is a quaternion vector part)")
    return quat_mul(q, torch.cat((torch.sqrt(1 - n2), v), -1))


def random_quaternion(
    *batch: int, generator: torch.Generator | None = None, dtype=torch.float64, device=None
) -> torch.Tensor:
    """Uniformly distributed (Haar) unit quaternions of shape (*batch, 4), w ≥ 0.

    Normalised 4-D standard normals are uniform on S³, hence Haar on SO(3).
    """
    g = torch.randn(*batch, 4, generator=generator, dtype=dtype, device=device)
    return quat_normalize(g)


def rotation_angle(q1: torch.Tensor, q0: torch.Tensor | None = None) -> torch.Tensor:
    """Rotation angle (rad, in [0, π]) of q1, or of the relative rotation q0⁻¹ ∘ q1."""
    if q0 is not None:
        q1 = quat_mul(quat_conj(q0), q1)
    q1 = quat_normalize(q1)
    return 2.0 * torch.atan2(q1[..., 1:].norm(dim=-1), q1[..., 0].abs())

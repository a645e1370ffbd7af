"""Property tests of the rotation algebra against independent constructions."""
import math

import numpy as np
import torch
from hypothesis import given, settings, strategies as st

from accel_bayes.physics import geometry as g

F64 = torch.float64
vec3 = st.tuples(*[st.floats(-3.0, 3.0, allow_nan=False)] * 3)
quat4 = st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 4).filter(lambda q: sum(x * x for x in q) > 1e-3)


def t(x):
    return torch.tensor(x, dtype=F64)


def rodrigues(rotvec):
    """Independent rotation matrix from a rotation vector (numpy, Rodrigues' formula)."""
    v = np.asarray(rotvec, float)
    th = np.linalg.norm(v)
    if th < 1e-12:
        return np.eye(3)
    k = v / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


@given(vec3, vec3)
def test_skew_is_cross_product(a, b):
    assert torch.allclose(g.skew(t(a)) @ t(b), torch.linalg.cross(t(a), t(b)), atol=1e-12)
    assert torch.allclose(g.unskew(g.skew(t(a))), t(a), atol=1e-15)


@given(vec3)
def test_exp_matches_rodrigues(v):
    R = g.quat_to_matrix(g.quat_exp(t(v))).numpy()
    np.testing.assert_allclose(R, rodrigues(v), atol=1e-12)


@given(quat4, quat4)
def test_product_composes_rotations(p, q):
    p, q = g.quat_normalize(t(p)), g.quat_normalize(t(q))
    lhs = g.quat_to_matrix(g.quat_mul(p, q))
    assert torch.allclose(lhs, g.quat_to_matrix(p) @ g.quat_to_matrix(q), atol=1e-12)


@given(quat4)
def test_matrix_is_orthonormal_and_inverts(q):
    q = g.quat_normalize(t(q))
    R = g.quat_to_matrix(q)
    assert torch.allclose(R @ R.T, torch.eye(3, dtype=F64), atol=1e-12)
    assert abs(float(torch.linalg.det(R)) - 1) < 1e-12
    q2 = g.matrix_to_quat(R)
    # q and −q are the same rotation; at w = 0 the canonical sign is not unique
    assert min(float((q2 - q).abs().max()), float((q2 + q).abs().max())) < 1e-10
    assert torch.allclose(g.quat_to_matrix(g.quat_conj(q)), R.T, atol=1e-12)


@given(st.tuples(*[st.floats(-3.0, 3.0)] * 3).filter(lambda v: sum(x * x for x in v) < 3.1**2))
def test_log_inverts_exp(v):
    assert torch.allclose(g.quat_log(g.quat_exp(t(v))), t(v), atol=1e-9)


@given(quat4, vec3)
def test_boxplus_boxminus_roundtrip_and_unit_norm(q, d):
    q = g.quat_normalize(t(q))
    d = t(d) * 0.5  # |δ| < π keeps the log unique
    q2 = g.boxplus(q, d)
    assert abs(float(q2.norm()) - 1) < 1e-14
    assert torch.allclose(g.boxminus(q2, q), d, atol=1e-9)


def test_boxplus_keeps_unit_norm_over_many_updates():
    gen = torch.Generator().manual_seed(3)
    q = g.random_quaternion(100, generator=gen)
    for _ in range(2000):
        q = g.boxplus(q, 0.3 * torch.randn(100, 3, generator=gen, dtype=F64))
    assert float((q.norm(dim=-1) - 1).abs().max()) < 1e-14


def test_rotate_matches_matrix_and_design_worked_example():
    gen = torch.Generator().manual_seed(0)
    q = g.random_quaternion(50, generator=gen)
    v = torch.randn(50, 3, generator=gen, dtype=F64)
    assert torch.allclose(g.quat_rotate(q, v), (g.quat_to_matrix(q) @ v[..., None])[..., 0], atol=1e-14)
    # DESIGN §7.0: an IMU yawed +90° has q = (√½, 0, 0, −√½); array (0,1,0) reads (1,0,0).
    q90 = t([math.sqrt(0.5), 0, 0, -math.sqrt(0.5)])
    assert torch.allclose(g.quat_rotate(q90, t([0.0, 1.0, 0.0])), t([1.0, 0.0, 0.0]), atol=1e-15)
    # The MIMU bottom-side C of the data README is its own transpose; its quaternion:
    C = t([[0, -1, 0], [-1, 0, 0], [0, 0, -1]])
    assert torch.allclose(g.quat_to_matrix(t([0, math.sqrt(0.5), -math.sqrt(0.5), 0])), C, atol=1e-15)


def test_random_quaternions_are_haar_distributed():
    # For Haar rotations, the rotation angle θ has density (1 − cos θ)/π, so E[cos θ] = −1/2... of
    # trace: E[tr R] = 0 and E[R] = 0 elementwise. Check both with 200k draws (tolerance 5 s.e.).
    gen = torch.Generator().manual_seed(11)
    R = g.quat_to_matrix(g.random_quaternion(200_000, generator=gen))
    se = 1 / math.sqrt(3 * 200_000)  # entries have variance 1/3
    assert float(R.mean(0).abs().max()) < 5 * se
    ang = g.rotation_angle(g.random_quaternion(200_000, generator=gen))
    assert abs(float(torch.cos(ang).mean()) + 0.5) < 0.01


def test_rotation_angle_of_relative_rotation():
    a = g.quat_exp(t([0.0, 0.0, 0.3]))
    b = g.quat_exp(t([0.0, 0.0, -0.2]))
    assert abs(float(g.rotation_angle(a, b)) - 0.5) < 1e-12


def test_boxplus_s16_is_half_angle_variant():
    q = g.quat_normalize(t([0.9, 0.1, -0.2, 0.3]))
    v = t([0.05, -0.02, 0.01])
    # eq. 18 increment v is the vector part sin(φ/2)·axis; the exp-map increment is φ·axis.
    phi = 2 * torch.asin(v.norm()) * v / v.norm()
    assert torch.allclose(g.boxplus_s16(q, v), g.boxplus(q, phi), atol=1e-12)
    with __import__("pytest").raises(ValueError):
        g.boxplus_s16(q, t([1.0, 0.5, 0.0]))

"""Tests of the Cramér–Rao bound (accel_bayes.inference.crb).

Reference: the inverse of a dense Fisher information built from an autograd Jacobian of the full
stacked noise-free measurement vector (all accelerometer and gyroscope outputs of all samples)
with respect to all parameters (θ, ω_{1:T}, ω̇_{1:T}, s_{1:T}).
"""
import math

import pytest
import torch

from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.errors import UserError
from accel_bayes.inference.crb import crb_theta, fisher_information_theta
from accel_bayes.physics.models import specific_force
from accel_bayes.physics.motion_generators import iid_motion

DT = torch.float64
DEG = math.pi / 180


def _setup(T, A=4, seed=0):
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(A, 3, generator=g, dtype=DT) * 0.02
    pos[0] = 0
    w = torch.randn(T, 3, generator=g, dtype=DT) * 5
    wd = torch.randn(T, 3, generator=g, dtype=DT) * 50
    s = torch.randn(T, 3, generator=g, dtype=DT) * 10
    sa = 0.01 + 0.05 * torch.rand(A, 3, generator=g, dtype=DT)  # per-axis, unequal
    sg = torch.tensor([0.01, 0.02, 0.015], dtype=DT)  # three gyros
    return pos, w, wd, s, sa, sg


def _dense_crb(pos, w, wd, s, sa, sg, reference=0, prior_std=None):
    A, T = pos.shape[0], w.shape[0]
    G = sg.numel()
    keep = [k for k in range(A) if k != reference]
    n = 3 * (A - 1)

    def outputs(z):
        th = z[:n].reshape(A - 1, 3)
        r = torch.zeros(A, 3, dtype=DT)
        r[keep] = th
        eta = z[n:].reshape(T, 9)
        acc = specific_force(r, eta[:, :3], eta[:, 3:6], eta[:, 6:])  # (T, A, 3)
        gyro = eta[:, :3].unsqueeze(1).expand(T, G, 3)
        return torch.cat((acc.reshape(-1), gyro.reshape(-1)))

    z0 = torch.cat((pos[keep].reshape(-1), torch.cat((w, wd, s), -1).reshape(-1)))
    J = torch.autograd.functional.jacobian(outputs, z0)
    prec = torch.cat((sa.pow(-2).expand(T, A, 3).reshape(-1), sg.pow(-2).repeat_interleave(3).expand(T, 3 * G).reshape(-1)))
    F = J.T @ (prec[:, None] * J)
    if prior_std is not None:
        F[:n, :n] += torch.eye(n, dtype=DT) / prior_std**2
    return torch.linalg.inv(F)[:n, :n]


@pytest.mark.parametrize("reference", [0, 2])
def test_crb_equals_dense_autograd_fisher_inverse(reference):
    pos, w, wd, s, sa, sg = _setup(T=12, A=4, seed=1)
    C = crb_theta(pos, w, wd, s, sa, sg, reference=reference)
    Cd = _dense_crb(pos - pos[reference], w, wd, s, sa, sg, reference)
    assert torch.allclose(C, Cd, rtol=1e-8, atol=0)
    Cp = crb_theta(pos, w, wd, s, sa, sg, reference=reference, prior_std=0.01)
    Cpd = _dense_crb(pos - pos[reference], w, wd, s, sa, sg, reference, prior_std=0.01)
    assert torch.allclose(Cp, Cpd, rtol=1e-8, atol=0)
    assert bool((Cp.diagonal() < C.diagonal()).all())  # a prior only adds information


def test_crb_without_gyros_and_with_gyro_cov():
    pos, w, wd, s, sa, sg = _setup(T=10, A=5, seed=2)
    C_none = crb_theta(pos, w, wd, s, sa)
    C_g = crb_theta(pos, w, wd, s, sa, sg)
    # the gyro information Σσ⁻² per axis as one combined (3, 3) covariance gives the same bound
    C_cov = crb_theta(pos, w, wd, s, sa, gyro_cov=torch.eye(3, dtype=DT) / sg.pow(-2).sum())
    assert torch.allclose(C_g, C_cov, rtol=1e-12)
    assert bool((C_g.diagonal() <= C_none.diagonal() * (1 + 1e-12)).all())
    with pytest.raises(UserError):
        crb_theta(pos, w, wd, s, sa, sg, gyro_cov=torch.eye(3, dtype=DT))


def test_crb_shrinks_like_one_over_T():
    arr = mimu4444_8()
    sg = torch.full((8,), 0.06 * DEG, dtype=DT)
    m = iid_motion(800, seed=3)
    tr = []
    for T in (100, 200, 400, 800):
        C = crb_theta(arr.positions, m.omega[:T], m.omega_dot[:T], m.s[:T], 0.04, sg)
        tr.append(float(C.diagonal().sum()))
    ratios = [tr[i] / tr[i + 1] for i in range(3)]
    assert all(1.7 < r < 2.3 for r in ratios), ratios
    # exactly 1/2 for the same samples repeated twice
    w2, wd2, s2 = (torch.cat((x[:100], x[:100])) for x in (m.omega, m.omega_dot, m.s))
    C2 = crb_theta(arr.positions, w2, wd2, s2, 0.04, sg)
    C1 = crb_theta(arr.positions, m.omega[:100], m.omega_dot[:100], m.s[:100], 0.04, sg)
    assert torch.allclose(C2, C1 / 2, rtol=1e-10)


def test_information_is_symmetric_positive_definite():
    pos, w, wd, s, sa, sg = _setup(T=30, A=6, seed=5)
    S = fisher_information_theta(pos, w, wd, s, sa, sg, prior_std=torch.full((6,), 3e-3, dtype=DT))
    assert torch.allclose(S, S.T)
    assert float(torch.linalg.eigvalsh(S).min()) > 0

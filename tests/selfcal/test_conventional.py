"""[S16] eq. 19 conventional calibration: Jacobians, exact recovery, covariance vs scatter."""
import math

import pytest
import torch

from accel_bayes import s16_plate
from accel_bayes.physics import models
from accel_bayes.physics.geometry import boxplus, random_quaternion, rotation_angle
from accel_bayes.inference.conventional import (
    IDENTITY_SENSITIVITY,
    conventional_calibrate,
    conventional_jacobians,
    conventional_residuals,
)
from accel_bayes.physics.motion_generators import smooth_motion

F64 = torch.float64
RATE = 125.0


def _rand(gen, *shape, scale=1.0):
    return scale * torch.randn(*shape, generator=gen, dtype=F64)


def _motion(T, seed=1):
    m = smooth_motion(T, RATE, seed=seed, omega_rms=3.0, freq_range=(0.1, 0.5), accel_rms=2.0)
    return torch.cat((m.s, m.omega, m.omega_dot), -1)


def _triads(gen, A=5):
    arr = s16_plate()
    p = arr.positions + _rand(gen, A, 3, scale=3e-3)
    q = boxplus(arr.orientations, _rand(gen, A, 3, scale=0.05))
    sp = torch.tensor(IDENTITY_SENSITIVITY, dtype=F64) + _rand(gen, A, 6, scale=0.02)
    o = _rand(gen, A, 3, scale=0.1)
    return arr, p, q, sp, o


def test_conventional_jacobians_match_finite_differences():
    gen = torch.Generator().manual_seed(31)
    A, T, h = 3, 5, 1e-6
    x = torch.cat((_rand(gen, T, 3, scale=10), _rand(gen, T, 3, scale=5), _rand(gen, T, 3, scale=30)), -1)
    q = random_quaternion(A, generator=gen)
    r = _rand(gen, A, 3, scale=0.1)
    sp = torch.tensor(IDENTITY_SENSITIVITY, dtype=F64) + _rand(gen, A, 6, scale=0.05)
    o = _rand(gen, A, 3, scale=0.1)
    z = _rand(gen, T, A, 3, scale=10)
    inv = 1.0 / (0.01 + torch.rand(A, 3, generator=gen, dtype=F64))
    Jp, Jr, Js, Jo = conventional_jacobians(x, q, r, sp, inv)

    def res(q_, r_, s_, o_):
        return conventional_residuals(x, q_, r_, s_, o_, z, inv)

    for k in range(3):
        e = torch.zeros(A, 3, dtype=F64)
        e[:, k] = h
        fd = (res(q, r + e, sp, o) - res(q, r - e, sp, o)) / (2 * h)
        assert (fd - Jp[..., k]).abs().max() < 1e-7 * Jp.abs().max()
        fd = (res(boxplus(q, e), r, sp, o) - res(boxplus(q, -e), r, sp, o)) / (2 * h)
        assert (fd - Jr[..., k]).abs().max() < 1e-7 * Jr.abs().max()
        fd = (res(q, r, sp, o + e) - res(q, r, sp, o - e)) / (2 * h)
        assert (fd - Jo[..., k]).abs().max() < 1e-7 * Jo.abs().max()
    for k in range(6):
        e = torch.zeros(A, 6, dtype=F64)
        e[:, k] = h
        fd = (res(q, r, sp + e, o) - res(q, r, sp - e, o)) / (2 * h)
        assert (fd - Js[..., k]).abs().max() < 1e-7 * Js.abs().max()


def test_conventional_calibration_recovers_pose_and_sensor_parameters():
    gen = torch.Generator().manual_seed(32)
    x = _motion(500)
    arr, p, q, sp, o = _triads(gen)
    z = models.triad_output(x, q, p, models.sensitivity_matrix(sp), o)
    res = conventional_calibrate(z, x, nominal_positions=arr.positions, nominal_orientations=arr.orientations)
    assert all(res.converged)
    assert (res.positions - p).abs().max() < 1e-12
    assert rotation_angle(res.orientations, q).max() < 1e-12
    assert (res.sensitivity - sp).abs().max() < 1e-12
    assert (res.offset - o).abs().max() < 1e-12
    assert torch.allclose(res.S, models.sensitivity_matrix(sp), atol=1e-12)
    assert res.cost.max() < 1e-18
    # covariance: SPD per triad, 15 × 15
    assert res.covariance.shape == (5, 15, 15)
    assert torch.all(torch.linalg.eigvalsh(res.covariance) > 0)


def test_conventional_pose_only_with_known_sensor_parameters():
    gen = torch.Generator().manual_seed(33)
    x = _motion(300, seed=2)
    arr, p, q, sp, o = _triads(gen)
    z = models.triad_output(x, q, p, models.sensitivity_matrix(sp), o)
    res = conventional_calibrate(z, x, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                                 init_sensitivity=sp, init_offset=o, estimate_sensor_params=False)
    assert (res.positions - p).abs().max() < 1e-12
    assert torch.equal(res.sensitivity, sp) and torch.equal(res.offset, o)
    assert torch.all(res.covariance[:, 6:, :] == 0)


def test_conventional_covariance_matches_monte_carlo_scatter():
    """Laplace std of the pose vs the spread over noise draws (one triad, 40 draws)."""
    gen = torch.Generator().manual_seed(34)
    x = _motion(300, seed=3)
    arr, p, q, sp, o = _triads(gen, A=5)
    j = slice(2, 3)
    z0 = models.triad_output(x, q[j], p[j], models.sensitivity_matrix(sp[j]), o[j])
    sigma = 0.02
    pos, stds = [], None
    for k in range(40):
        z = z0 + sigma * _rand(gen, *z0.shape)
        r = conventional_calibrate(z, x, nominal_positions=arr.positions[j], nominal_orientations=arr.orientations[j],
                                   acc_noise_std=sigma)
        pos.append(r.positions[0])
        stds = r.position_std[0]
    emp = torch.stack(pos).std(0)
    ratio = emp / stds
    assert torch.all((ratio > 0.6) & (ratio < 1.5)), ratio
    # unbiased to well within its spread (linear-in-r model, Gaussian noise)
    assert ((torch.stack(pos).mean(0) - p[2]).abs() < 3 * stds / math.sqrt(40) + 1e-9).all()


def test_conventional_refuses_bad_shapes():
    x = _motion(300)[:50]
    z = torch.zeros(50, 2, 3, dtype=F64)
    with pytest.raises(ValueError, match="reference_states"):
        conventional_calibrate(z, x[:40], nominal_positions=torch.zeros(2, 3, dtype=F64))
    with pytest.raises(ValueError, match="nominal_positions"):
        conventional_calibrate(z, x, nominal_positions=torch.zeros(3, 3, dtype=F64))

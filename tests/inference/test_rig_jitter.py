"""Stamp jitter in the rig model (issue #28 item 1): per-sample timing noise whose covariance
σ_j² ẏ ẏᵀ is added to each sample's white noise, with σ_j estimated from the stamps."""
import numpy as np
import torch

from accel_bayes.inference.rig.model import (measurement_jacobian, measurement_residual, stamp_jitter_std,
                                             timing_noise_directions, _jitter_whiten)
from accel_bayes.physics.geometry import boxplus
from tests.inference.test_rig_model import _small_rig


def _rig_with_jitter(sig=(2e-4, 1e-4, 3e-4)):
    g, x, data, R0 = _small_rig()
    data.u = timing_noise_directions(g, x[:-1], x[1:], data, R0, np.asarray(sig))
    return g, x, data, R0


def test_whitening_is_the_inverse_square_root_of_the_jitter_covariance():
    _, _, data, _ = _rig_with_jitter()
    u = data.u[data.wg > 0]
    assert float((u * u).sum(-1).max()) > 0.5  # the test exercises a jitter comparable to the noise
    eye = torch.eye(6, dtype=torch.float64).expand(u.shape[0], 6, 6)
    one = type(data)(**{**data.__dict__, "u": u[None]})
    W = _jitter_whiten(one, eye[None])[0]
    cov = eye + u[:, :, None] * u[:, None, :]
    assert torch.allclose(W.transpose(-1, -2) @ W @ cov, eye, atol=1e-10)


def test_jitter_direction_is_sigma_times_the_residual_time_derivative():
    g, x, data, R0 = _rig_with_jitter((2e-4, 2e-4, 2e-4))
    data_plain = type(data)(**{**data.__dict__, "u": None})
    eps = 1e-7
    moved = type(data)(**{**data_plain.__dict__, "ds": data.ds + eps})
    # a later stamp on every IMU's own clock moves the instant by eps/(1+d)
    fd = (measurement_residual(g, x[:-1], x[1:], moved, R0) - measurement_residual(g, x[:-1], x[1:], data_plain, R0)) / eps
    d = torch.cat((g["d"].new_zeros(1), g["d"]))[data.imu]
    u = data.u / 2e-4 / (1.0 / (1.0 + d))[..., None]
    assert torch.allclose(u.reshape(fd.shape), fd, rtol=1e-4, atol=1e-4 * float(fd.abs().max()))


def test_measurement_jacobian_with_jitter_matches_finite_differences():
    g, x, data, R0 = _rig_with_jitter()
    jac, A, B = measurement_jacobian(g, x[:-1], x[1:], data, R0)
    f = lambda gg, xx: measurement_residual(gg, xx[:-1], xx[1:], data, R0)  # noqa: E731
    eps = 1e-6
    for name in ("q", "r", "o", "d"):
        v = g[name]
        n_t = v.shape[0] * (3 if name in ("q", "r") else 1)
        for c in range(n_t):
            delta = torch.zeros(n_t, dtype=torch.float64)
            delta[c] = eps

            def moved(s):
                gg = dict(g)
                gg[name] = boxplus(v, (s * delta).reshape(-1, 3)) if name == "q" else v + (s * delta).reshape(v.shape)
                return f(gg, x)
            fd = (moved(1) - moved(-1)) / (2 * eps)
            assert torch.allclose(jac[name][..., c], fd, rtol=1e-5, atol=1e-4 * (1 + fd.abs().max())), (name, c)
    for c in (0, 4, 7, 11):
        dx = torch.zeros_like(x)
        dx[5, c] = eps
        fd = (f(g, x + dx) - f(g, x - dx)) / (2 * eps)
        assert torch.allclose(A[5, :, c], fd[5], rtol=1e-5, atol=1e-4 * (1 + fd.abs().max()))
        assert torch.allclose(B[4, :, c], fd[4], rtol=1e-5, atol=1e-4 * (1 + fd.abs().max()))


def test_stamp_jitter_std_recovers_the_jitter_through_drift_wander_and_a_dropped_sample():
    rng = np.random.default_rng(3)
    n = np.arange(20000)
    ticks = 0.01 + n / 200.0 * (1 + 80e-6) + 2e-5 * np.sin(2 * np.pi * n / 200.0 / 30.0)  # drift and slow wander
    ticks = np.delete(ticks, [500, 9001])
    for sig in (0.0, 3e-5, 2e-4):
        est = stamp_jitter_std(ticks + rng.normal(0, sig, len(ticks)))
        assert abs(est - sig) < 0.05 * sig + 1e-8, (sig, est)

"""The signal models against independent constructions (numpy kinematics, finite differences)."""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics import arrays, geometry as g, models as m

F64 = torch.float64


def _rand(gen, *shape, scale=1.0):
    return scale * torch.randn(*shape, generator=gen, dtype=F64)


def test_specific_force_matches_numpy_cross_products():
    gen = torch.Generator().manual_seed(1)
    r, w, wd, s = _rand(gen, 6, 3, scale=0.01), _rand(gen, 9, 3, scale=10), _rand(gen, 9, 3, scale=300), _rand(gen, 9, 3, scale=20)
    f = m.specific_force(r, w, wd, s).numpy()
    for t in range(9):
        for k in range(6):
            ref = np.cross(w[t], np.cross(w[t], r[k])) + np.cross(wd[t], r[k]) + s[t].numpy()
            np.testing.assert_allclose(f[t, k], ref, rtol=1e-12, atol=1e-12)


def test_linear_structure_G_u_and_H_phi():
    gen = torch.Generator().manual_seed(2)
    r, w, wd, s = _rand(gen, 5, 3, scale=0.01), _rand(gen, 7, 3, scale=10), _rand(gen, 7, 3, scale=300), _rand(gen, 7, 3, scale=20)
    # Ω(ω)² r = B(r) u(ω)
    Om = g.skew(w)[:, None]
    lhs = (Om @ Om @ r[None, ..., None])[..., 0]
    rhs = (m.B_of_position(r)[None] @ m.u_of_omega(w)[:, None, :, None])[..., 0]
    assert torch.allclose(lhs, rhs, atol=1e-14)
    # y = G u + H φ equals the kinematics, batched over time
    y = m.array_model_mean(r, w, torch.cat((wd, s), -1))
    assert torch.allclose(y, m.specific_force(r, w, wd, s).reshape(7, -1), atol=1e-12)


def test_H_columns_are_derivatives_of_the_kinematics():
    gen = torch.Generator().manual_seed(4)
    r, w = _rand(gen, 4, 3, scale=0.01), _rand(gen, 3, scale=5)
    phi = _rand(gen, 6, scale=50)
    f = lambda p: m.specific_force(r, w, p[:3], p[3:]).reshape(-1)  # noqa: E731
    J = torch.autograd.functional.jacobian(f, phi)
    assert torch.allclose(J, m.H_matrix(r), atol=1e-14)


def test_imu_outputs_rotate_into_sensor_frames():
    arr = arrays.mimu4444_8()
    gen = torch.Generator().manual_seed(5)
    w, wd, s = _rand(gen, 11, 3), _rand(gen, 11, 3), _rand(gen, 11, 3)
    acc, gyro = m.imu_outputs(arr.positions, arr.orientations, w, wd, s)
    f = m.specific_force(arr.positions, w, wd, s)
    assert torch.allclose(m.to_array_frame(acc, arr.orientations), f, atol=1e-13)
    # bottom IMU (label 1): sensor = C · array with the data README's C
    C = torch.tensor([[0, -1, 0], [-1, 0, 0], [0, 0, -1]], dtype=F64)
    assert torch.allclose(gyro[:, 1], w @ C.T, atol=1e-14)
    assert torch.allclose(gyro[:, 0], w, atol=1e-15)


def test_triad_model_reduces_to_imu_outputs_and_applies_sensor_params():
    arr = arrays.s16_plate()
    gen = torch.Generator().manual_seed(6)
    state = _rand(gen, 13, 9, scale=3)
    q = g.random_quaternion(5, generator=gen)
    z0 = m.triad_output(state, q, arr.positions)
    acc, _ = m.imu_outputs(arr.positions, q, state[:, 3:6], state[:, 6:9], state[:, 0:3])
    assert torch.allclose(z0, acc, atol=1e-13)
    p = torch.tensor([1.01, 0.002, 0.99, -0.003, 0.001, 1.02], dtype=F64).expand(5, 6)
    S = m.sensitivity_matrix(p)
    o = _rand(gen, 5, 3, scale=0.1)
    z = m.triad_output(state, q, arr.positions, S, o)
    # each axis j reads s_j · (sensor-frame acceleration) + o_j  ([S16] eq. 4 per axis)
    ref = torch.einsum("kij,tki->tkj", S, acc) + o
    assert torch.allclose(z, ref, atol=1e-13)
    assert torch.allclose(m.sensitivity_matrix(torch.tensor([1.0, 0, 1, 0, 0, 1], dtype=F64)), torch.eye(3, dtype=F64))


def test_process_model_and_covariance():
    from accel_bayes.inference.selfcal import motion_priors as mp

    x = torch.arange(9, dtype=F64)
    nxt = mp.process_model(x, 0.01)
    assert torch.allclose(nxt[3:6], x[3:6] + 0.01 * x[6:9])
    assert torch.equal(nxt[[0, 1, 2, 6, 7, 8]], x[[0, 1, 2, 6, 7, 8]])
    C = mp.process_covariance(0.008)
    assert torch.allclose(torch.diagonal(C), 0.008**2 * torch.tensor([1e3] * 3 + [1e-7] * 3 + [1e3] * 3, dtype=F64))
    with pytest.raises(ValueError, match="unknown keys"):
        mp.process_covariance(0.01, {"gyro": 1.0})


def test_presets_and_geometry_checks():
    a32 = arrays.mimu4444_32()
    assert a32.K == 32 and bool(a32.has_gyro.all())
    xy = a32.positions[:, :2]
    # 16 packages on a 6.3 mm grid, each holding a top and a bottom IMU at the same (x, y)
    assert torch.allclose(xy[0::2], xy[1::2])
    assert sorted(set(np.round(xy[:, 0].numpy() * 1e5).astype(int).tolist())) == [-945, -315, 315, 945]
    # the 8-corner preset is the corner subset of the 32 grid, in the data README's order
    a8 = arrays.mimu4444_8()
    csv = np.array([[-9.45, -9.45, -9.45, -9.45, 9.45, 9.45, 9.45, 9.45],
                    [9.45, 9.45, -9.45, -9.45, 9.45, 9.45, -9.45, -9.45],
                    [1, -1, 1, -1, 1, -1, 1, -1]]).T * 1e-3
    np.testing.assert_allclose(a8.positions.numpy(), csv, atol=1e-15)
    for k in range(8):
        j = int(np.argmin(np.abs(a32.positions.numpy() - csv[k]).sum(1)))
        assert torch.equal(a32.orientations[j], a8.orientations[k])
    s16 = arrays.s16_plate()
    assert s16.K == 5 and int(s16.has_gyro.sum()) == 1
    for a in (a32, a8, s16):
        a.check()
    with pytest.raises(ValueError, match="at least 3"):
        arrays.check_triad_geometry(a8.positions[:2])
    line = torch.tensor([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.05, 0, 0]], dtype=F64)
    with pytest.raises(ValueError, match="collinear.*unobservable"):
        arrays.check_triad_geometry(line)
    with pytest.raises(ValueError, match="reference_imu"):
        a8.with_(reference_imu=8)
    with pytest.raises(ValueError, match="preset"):
        arrays.preset("nope")


def test_acc_noise_std_per_axis_broadcasts_and_names_bad_input():
    from accel_bayes.errors import UserError
    from accel_bayes.physics.models import acc_noise_std_per_axis

    A = 4
    assert torch.equal(acc_noise_std_per_axis(0.1, A), torch.full((A, 3), 0.1, dtype=torch.float64))
    per = torch.arange(1, A + 1, dtype=torch.float64)
    assert torch.equal(acc_noise_std_per_axis(per, A)[:, 2], per)
    full = torch.rand(A, 3, dtype=torch.float64) + 0.1
    assert torch.equal(acc_noise_std_per_axis(full, A), full)
    for bad, why in ((torch.ones(A + 1), "expected a scalar"), (torch.ones(3, A), "expected a scalar"),
                     (0.0, "> 0"), (float("nan"), "finite"), (-1.0, "> 0")):
        with pytest.raises(UserError, match="acc_noise_std") as e:
            acc_noise_std_per_axis(bad, A)
        assert why.split()[-1] in str(e.value)

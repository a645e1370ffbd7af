"""Motion generators against independent checks: finite differences of world positions and
attitudes, sample statistics, and exact re-evaluation at shifted times."""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics import geometry as g, models
from accel_bayes.physics import motion_generators as G, trajectories as M
from accel_bayes.errors import UserError

F64 = torch.float64
DEG = math.pi / 180
GW = torch.tensor(M.G_WORLD, dtype=F64)

# board points, array frame, m: the origin, a MIMU-sized offset and an [S16]-plate-sized one
POINTS = torch.tensor([[0.0, 0.0, 0.0], [9.45e-3, -9.45e-3, 1e-3], [0.05, -0.03, 0.02], [-0.12, 0.1, 0.025]], dtype=F64)


def _fd2(traj, r, t, h):
    """Five-point second difference of p₀(t) + R(t) r (error O(h⁴) for a C⁶ path)."""
    P = lambda dt: M.point_trajectory(traj, r, t + dt)  # noqa: E731
    return (-P(2 * h) + 16 * P(h) - 30 * P(0.0) + 16 * P(-h) - P(-2 * h)) / (12 * h * h)


def _model_world_acc(tr, r):
    """World acceleration of the points from the signal model: R (ω×(ω×r) + ω̇×r + s) + g."""
    f = models.specific_force(r, tr.omega, tr.omega_dot, tr.s)  # (T, A, 3) array frame
    R = g.quat_to_matrix(tr.attitude)
    return (R.unsqueeze(1) @ f.unsqueeze(-1)).squeeze(-1) + GW


def _check_fd(tr, tol_rel):
    """MUST-SHOW: the signal model's acceleration at board points equals the second finite
    difference of their world positions, with the error shrinking at the stencil's 4th order."""
    a = _model_world_acc(tr, POINTS)
    errs = []
    for h in (4e-3, 2e-3, 1e-3):
        errs.append(float((_fd2(tr.trajectory, POINTS, tr.time, h) - a).abs().max()))
    scale = float(a.abs().max())
    assert errs[-1] < tol_rel * scale, (errs, scale)
    # truncation error, not a modelling error: halving h divides it by ≈ 2⁴
    assert errs[0] / errs[1] > 10, errs
    return errs


def test_smooth_motion_matches_finite_differences_of_point_positions():
    tr = G.smooth_motion(300, 100.0, omega_rms=600 * DEG, accel_rms=8.0, generator=3)
    errs = _check_fd(tr, tol_rel=1e-6)
    print("smooth FD max error (h = 4, 2, 1 ms):", errs)


def test_table_motion_matches_finite_differences_of_point_positions():
    tr = G.table_motion(675, 125.0, omega_amplitude=300 * DEG, frequency=1.3, rest_duration=0.3,
                        center=(0.01, -0.02, 0.03), initial_attitude="random", generator=5)
    errs = _check_fd(tr, tol_rel=1e-6)
    print("table FD max error (h = 4, 2, 1 ms):", errs)


@pytest.mark.parametrize("make", [
    lambda: G.smooth_motion(200, 62.5, omega_rms=250 * DEG, generator=11),
    lambda: G.table_motion(300, 125.0, rest_duration=0.2, generator=1),
])
def test_omega_and_omega_dot_are_derivatives_of_the_attitude(make):
    tr = make()
    traj, t, h = tr.trajectory, tr.time, 1e-5
    R = g.quat_to_matrix(traj.attitude(t))
    Rdot = (g.quat_to_matrix(traj.attitude(t + h)) - g.quat_to_matrix(traj.attitude(t - h))) / (2 * h)
    # Ṙ = R Ω(ω): ω is the body (array-frame) angular velocity
    w_fd = g.unskew(R.transpose(-1, -2) @ Rdot)
    assert torch.allclose(w_fd, tr.omega, atol=1e-7 * (1 + float(tr.omega.abs().max())))
    wd_fd = (traj.omega(t + h) - traj.omega(t - h)) / (2 * h)
    assert torch.allclose(wd_fd, tr.omega_dot, atol=1e-6 * (1 + float(tr.omega_dot.abs().max())))
    # s is the specific force of the origin: Rᵀ(p̈₀ − g), p̈₀ by finite differences of p₀
    p = lambda dt: traj.position(t + dt)  # noqa: E731
    a_fd = (p(h * 100) - 2 * p(0.0) + p(-h * 100)) / (h * 100) ** 2
    s_fd = (R.transpose(-1, -2) @ (a_fd - GW).unsqueeze(-1)).squeeze(-1)
    assert torch.allclose(s_fd, tr.s, atol=1e-4)


def test_iid_motion_statistics():
    T = 20000
    tr = G.iid_motion(T, generator=7)
    # [C21] §IV-A standard deviations, SI
    for x, sd in ((tr.omega, 1000 * DEG), (tr.omega_dot, 35000 * DEG), (tr.s, 20.0)):
        std = x.std(0)
        # std of a sample std ≈ σ/√(2T) = 0.5 %; allow 2 % (4 standard errors)
        assert torch.allclose(std, torch.full((3,), sd, dtype=F64), rtol=0.02), (std, sd)
        assert float(x.mean(0).abs().max()) < 4 * sd / math.sqrt(T)
    # independence across the three quantities and axes: correlations near zero
    c = torch.corrcoef(torch.cat((tr.omega, tr.omega_dot, tr.s), 1).T)
    off = c - torch.eye(9, dtype=F64)
    assert float(off.abs().max()) < 4 / math.sqrt(T)
    assert tr.attitude is None and tr.kind == "iid"
    assert torch.allclose(torch.diff(tr.time), torch.full((T - 1,), 0.01, dtype=F64))


def test_iid_motion_custom_std_and_determinism():
    a = G.iid_motion(500, omega_std=2.0, omega_dot_std=0.0, s_std=1.0, generator=1)
    b = G.iid_motion(500, omega_std=2.0, omega_dot_std=0.0, s_std=1.0, generator=1)
    c = G.iid_motion(500, omega_std=2.0, omega_dot_std=0.0, s_std=1.0, generator=2)
    assert torch.equal(a.omega, b.omega) and torch.equal(a.s, b.s)
    assert not torch.equal(a.omega, c.omega)
    assert torch.count_nonzero(a.omega_dot) == 0


@pytest.mark.parametrize("omega_rms_deg,rate", [(250, 62.5), (600, 1000.0)])
def test_smooth_motion_hits_requested_rms(omega_rms_deg, rate):
    tr = G.smooth_motion(400, rate, omega_rms=omega_rms_deg * DEG, accel_rms=3.0, freq_range=(0.5, 5.0), generator=2)
    w_rms = float(torch.sqrt((tr.omega ** 2).sum(-1).mean()))
    a_rms = float(torch.sqrt((tr.trajectory.acceleration(tr.time) ** 2).sum(-1).mean()))
    assert w_rms == pytest.approx(omega_rms_deg * DEG, rel=1e-9)
    assert a_rms == pytest.approx(3.0, rel=1e-9)
    assert torch.allclose(tr.attitude.norm(dim=-1), torch.ones(400, dtype=F64), atol=1e-14)


def test_still_level_board_reads_plus_one_g():
    tr = G.smooth_motion(50, 100.0, omega_rms=0.0, accel_rms=0.0, initial_attitude="level", generator=0)
    assert torch.count_nonzero(tr.omega) == 0 and torch.count_nonzero(tr.omega_dot) == 0
    assert torch.allclose(tr.s, torch.tensor([0.0, 0.0, 9.80665], dtype=F64).expand(50, 3), atol=1e-14)


def test_continuous_motion_evaluates_at_shifted_times_and_rebuilds_from_dict():
    tr = G.smooth_motion(100, 100.0, generator=4)
    traj = tr.trajectory
    # one sample later on the grid equals the next sample
    nxt = traj.trace(tr.time + 0.01)
    for a, b in ((nxt.omega, tr.omega), (nxt.omega_dot, tr.omega_dot), (nxt.s, tr.s)):
        assert torch.allclose(a[:-1], b[1:], atol=1e-11)
    # an off-grid shift is a genuine re-evaluation (differs, but only by ≈ δ·derivative)
    d = traj.trace(tr.time + 1e-3)
    assert not torch.allclose(d.omega, tr.omega, atol=1e-6)
    assert torch.allclose(d.omega, tr.omega + 1e-3 * tr.omega_dot, atol=1e-3 * 1e-3 * 1e5)
    # a sidecar's trajectory dict rebuilds the same motion
    again = M.trajectory_from_dict(tr.to_dict()["trajectory"]).trace(tr.time)
    assert torch.equal(again.omega, tr.omega) and torch.equal(again.s, tr.s)


def test_smooth_motion_seed_and_dtype():
    a = G.smooth_motion(100, 100.0, generator=9)
    b = G.smooth_motion(100, 100.0, generator=torch.Generator().manual_seed(9))
    c = G.smooth_motion(100, 100.0, generator=10)
    assert torch.equal(a.omega, b.omega) and torch.equal(a.s, b.s)
    assert not torch.allclose(a.omega, c.omega)
    f = G.smooth_motion(100, 100.0, generator=9, dtype=torch.float32)
    assert f.omega.dtype == torch.float32
    assert torch.allclose(f.omega.double(), a.omega, rtol=1e-5, atol=1e-5)


def test_table_motion_structure():
    T, rate, rest = 500, 125.0, 0.2
    tr = G.table_motion(T, rate, axes="xyz", omega_amplitude=200 * DEG, frequency=1.0, rest_duration=rest)
    seg = tr.segment
    assert seg is not None and set(seg) == {"static", "dynamic"}
    st = torch.as_tensor(seg == "static")
    assert torch.count_nonzero(tr.omega[st]) == 0
    # level, centred table: the origin never moves; gravity reads (0, 0, g) while at rest
    assert torch.allclose(tr.position, torch.zeros(T, 3, dtype=F64), atol=1e-15)
    assert torch.allclose(tr.s[st], torch.tensor([0.0, 0.0, 9.80665], dtype=F64).expand(int(st.sum()), 3), atol=1e-12)
    # one body axis per segment, in the order x, y, z
    dyn_axes = []
    for i in range(T):
        if seg[i] == "dynamic" and float(tr.omega[i].norm()) > 1e-9:
            ax = int(tr.omega[i].abs().argmax())
            assert float(tr.omega[i].abs().sum() - tr.omega[i, ax].abs()) == 0.0
            if not dyn_axes or dyn_axes[-1] != ax:
                dyn_axes.append(ax)
    assert dyn_axes == [0, 1, 2]
    # peak rate close to the requested amplitude (the taper lowers it a little)
    assert 0.8 * 200 * DEG < float(tr.omega.abs().max()) <= 200 * DEG * 1.05


def test_table_without_rests_has_no_segment_labels_and_offset_centre_accelerates_origin():
    tr = G.table_motion(300, 100.0, center=(0.0, 0.0, 0.05))
    assert tr.segment is None
    a = tr.trajectory.acceleration(tr.time)
    assert float(a.norm(dim=-1).max()) > 0.1
    # the centre itself stays put
    pc = M.point_trajectory(tr.trajectory, torch.tensor([[0.0, 0.0, 0.05]], dtype=F64), tr.time)
    assert torch.allclose(pc, pc[:1].expand_as(pc), atol=1e-15)


@pytest.mark.parametrize("call", [
    lambda: G.smooth_motion(100, 4.0),  # band above Nyquist
    lambda: G.smooth_motion(0, 100.0),
    lambda: G.iid_motion(10, rate=-1.0),
    lambda: G.iid_motion(10, omega_std=-1.0),
    lambda: G.table_motion(100, 100.0, axes="xq"),
    lambda: G.table_motion(10, 100.0, rest_duration=1.0),  # rests leave no time to move
    lambda: G.make_motion("wave", 10, 100.0),
    lambda: G.make_motion("iid", 10, 100.0, bogus=1),
])
def test_bad_arguments_raise_user_error(call):
    with pytest.raises(UserError):
        call()


def test_motion_trace_to_dict_is_json_ready():
    import json

    tr = G.table_motion(50, 100.0, rest_duration=0.05)
    d = json.loads(json.dumps(tr.to_dict()))
    assert d["kind"] == "table" and len(d["omega"]) == 50 and d["trajectory"]["class"] == "TableTrajectory"
    assert np.allclose(d["s"], tr.s.numpy())

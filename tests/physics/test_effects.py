"""The effects library (accel_bayes.physics.effects): every perturbation against an independent
computation — the signal model evaluated at the perturbed geometry/time/orientation, closed
forms, finite differences — and the simulator's ``effects=`` path."""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.errors import UserError
from accel_bayes.physics.geometry import boxplus, quat_exp, quat_mul, quat_to_matrix
from accel_bayes.physics.models import imu_outputs, to_array_frame
from accel_bayes.physics.motion_generators import smooth_motion
from accel_bayes.physics.effects import (
    AXES, EFFECTS, VOCABULARY, CandidateLayout, SignalContext, apply_effects, get_effect, make_effect,
    model_outputs, noise_factors, output_rates,
)
from accel_bayes.simulate import simulate

DEG = math.pi / 180
# DESIGN §7.2: effect → its report parameters
DESIGN_PARAMS = {
    "acc_bias": {"bias"}, "acc_scale": {"scale"}, "acc_misalignment": {"coupling", "from_axis"},
    "acc_nonlinearity": {"k2"}, "axis_displacement": {"displacement"}, "triad_orientation": {"rotation_vector"},
    "gyro_bias": {"bias"}, "gyro_scale": {"scale"}, "gyro_misalignment": {"coupling", "from_axis"},
    "gyro_g_sensitivity": {"sensitivity"}, "gyro_nonlinearity": {"k2"}, "time_offset": {"offset"},
    "saturation": {"limit", "clipped_fraction"}, "noise_level": {"factor"}, "sampling_jitter": {"width"},
}


@pytest.fixture(scope="module")
def setup():
    arr = mimu4444_8()
    tr = smooth_motion(400, 200.0, seed=3)
    g = torch.Generator().manual_seed(5)
    pos = arr.positions + 1e-4 * torch.randn(8, 3, generator=g, dtype=torch.float64)
    q = arr.orientations
    ctx = SignalContext.from_motion(pos, q, tr.omega, tr.omega_dot, tr.s, tr.time)
    return arr, tr, pos, q, ctx


def _one(name, **kw):
    return make_effect(name, **kw)


def test_vocabulary_and_parameters():
    # The report vocabulary is DESIGN §7.2's, a fixed contract; gyro_misalignment is the
    # cross-axis part of gyro_scale and is reported under that name.
    assert VOCABULARY == ("acc_bias", "acc_scale", "acc_misalignment", "acc_nonlinearity", "axis_displacement",
                          "triad_orientation", "gyro_bias", "gyro_scale", "gyro_g_sensitivity",
                          "gyro_nonlinearity", "time_offset",
                          "saturation", "noise_level", "unexplained", "sampling_jitter", "sampling_clock")
    assert EFFECTS["gyro_misalignment"].vocabulary_name == "gyro_scale"
    e = make_effect("gyro_scale", imu=2, axis="z", parameters={"scale": 0.01, "from_axis": "x"})
    assert e.name == "gyro_misalignment" and e.vocabulary_parameters() == {"scale": 0.01, "from_axis": "x"}
    assert make_effect("gyro_scale", imu=2, axis="z", parameters={"scale": 0.01}).name == "gyro_scale"
    diag = make_effect("gyro_scale", imu=2, axis="z", parameters={"scale": 0.01, "from_axis": "z"})
    assert diag.name == "gyro_scale" and diag.report_parameters() == {"scale": 0.01}
    assert make_effect("gyro_scale", imu=2, axis="z", from_axis="y").name == "gyro_misalignment"
    layout = CandidateLayout(8, np.ones(8, bool), np.ones(8, bool), 0)
    for name, keys in DESIGN_PARAMS.items():
        cls = EFFECTS[name]
        assert cls.description and cls.__doc__
        cands = cls.candidates(layout)
        assert cands, name
        e = cands[0]
        rp = e.report_parameters()
        assert keys <= set(rp), (name, rp)
        for p in cls.parameters:
            assert p.unit and (p.shape in ((), (3,)))
        # axis-local effects name a sensor-frame axis, the others none (saturation/noise: either)
        if name not in ("saturation",):
            assert (e.axis is not None) == cls.local_axis
        assert isinstance(e.explain(), str) and e.explain().endswith(".")
    assert {c.imu for c in EFFECTS["acc_bias"].candidates(layout)} == set(range(8))
    assert len(EFFECTS["acc_misalignment"].candidates(layout)) == 8 * 6
    assert len(EFFECTS["gyro_misalignment"].candidates(layout)) == 8 * 6
    # every IMU-local effect has candidates at the reference IMU too (identifiable, module docstring)
    for name in ("axis_displacement", "triad_orientation", "gyro_misalignment", "gyro_scale", "gyro_nonlinearity"):
        assert 0 in {c.imu for c in EFFECTS[name].candidates(layout)}, name
    with pytest.raises(UserError):
        get_effect("acc_wobble")
    with pytest.raises(UserError):
        make_effect("acc_bias", imu=1, axis="w")
    with pytest.raises(UserError):
        make_effect("acc_misalignment", imu=1, axis="x", from_axis="x")
    with pytest.raises(UserError):
        make_effect("acc_bias", imu=1, axis="x", parameters={"offset": 1.0})


@pytest.mark.parametrize("name", [n for n in VOCABULARY if EFFECTS[n].kind == "mean" and not EFFECTS[n].needs_rates])
def test_zero_at_null_and_local_to_its_imu(setup, name):
    arr, tr, pos, q, ctx = setup
    kw = {"imu": 5}
    if EFFECTS[name].local_axis:
        kw["axis"] = "y"
    if name in ("acc_misalignment", "gyro_misalignment"):
        kw["from_axis"] = "z"
    e = make_effect(name, **kw)
    da, dg = e.perturbation(None, ctx)
    assert float(da.abs().max()) == 0 and float(dg.abs().max()) == 0
    g = torch.Generator().manual_seed(1)
    vals = {p.name: 1e-3 * torch.randn(p.shape, generator=g, dtype=torch.float64) for p in e.parameters}
    da, dg = e.perturbation(vals, ctx)
    other = [k for k in range(8) if k != 5]
    assert float(da[:, other].abs().max()) == 0 and float(dg[:, other].abs().max()) == 0
    assert float(da[:, 5].abs().max() + dg[:, 5].abs().max()) > 0
    if EFFECTS[name].local_axis and e.sensor == "acc":
        assert float(da[:, 5, [0, 2]].abs().max()) == 0


def test_closed_forms(setup):
    arr, tr, pos, q, ctx = setup
    k = 3
    da, dg = _one("acc_bias", imu=k, axis="z", parameters={"bias": 0.07}).perturbation(None, ctx)
    assert torch.allclose(da[:, k, 2], torch.full((400,), 0.07, dtype=torch.float64))
    da, _ = _one("acc_scale", imu=k, axis="x", parameters={"scale": 0.01}).perturbation(None, ctx)
    assert torch.allclose(da[:, k, 0], 0.01 * ctx.acc[:, k, 0], rtol=0, atol=1e-15)
    da, _ = _one("acc_misalignment", imu=k, axis="y", from_axis="x", parameters={"coupling": 0.004}).perturbation(None, ctx)
    assert torch.allclose(da[:, k, 1], 0.004 * ctx.acc[:, k, 0], rtol=0, atol=1e-15)
    da, _ = _one("acc_nonlinearity", imu=k, axis="z", parameters={"k2": 1e-4}).perturbation(None, ctx)
    assert torch.allclose(da[:, k, 2], 1e-4 * ctx.acc[:, k, 2] ** 2, rtol=0, atol=1e-15)
    _, dg = _one("gyro_bias", imu=k, axis="y", parameters={"bias": 0.3 * DEG}).perturbation(None, ctx)
    assert torch.allclose(dg[:, k, 1], torch.full((400,), 0.3 * DEG, dtype=torch.float64))
    da, dg = _one("gyro_misalignment", imu=k, axis="z", from_axis="x", parameters={"coupling": 0.006}).perturbation(None, ctx)
    assert float(da.abs().max()) == 0 and float(dg[:, k, :2].abs().max()) == 0
    # gyro z of IMU k picks up 0.6 % of the x-axis rate in IMU k's own sensor frame (R ω)
    R = quat_to_matrix(q[k])
    assert torch.allclose(dg[:, k, 2], 0.006 * (ctx.omega @ R.T)[:, 0], rtol=0, atol=1e-15)
    with pytest.raises(UserError):
        _one("gyro_misalignment", imu=k, axis="x", from_axis="x")
    _, dg = _one("gyro_scale", imu=k, axis="z", parameters={"scale": 0.002}).perturbation(None, ctx)
    assert torch.allclose(dg[:, k, 2], 0.002 * ctx.gyro[:, k, 2], rtol=0, atol=1e-15)
    S = torch.tensor([1e-4, -2e-4, 3e-4], dtype=torch.float64)
    _, dg = _one("gyro_g_sensitivity", imu=k, parameters={"sensitivity": S}).perturbation(None, ctx)
    assert torch.allclose(dg[:, k], S * ctx.acc[:, k], rtol=0, atol=1e-15)


def test_gyro_nonlinearity_against_independent_numpy():
    """gyro_nonlinearity on random motion, mounting and k2 against numpy from first principles:
    the sensor-frame rate is R(q) ω with R(q) written out from the quaternion here (DESIGN §7.0,
    array → sensor), the axis' output gains k2 (R ω)_a², every other output is untouched."""
    rng = np.random.default_rng(11)
    T, K = 50, 4
    omega = rng.normal(0, 4.0, (T, 3))  # rad/s
    q = rng.normal(size=(K, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    pos = rng.normal(0, 0.02, (K, 3))
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    ctx = SignalContext.from_motion(t(pos), t(q), t(omega), t(rng.normal(0, 20, (T, 3))), t(rng.normal(0, 9, (T, 3))))
    for k, a in ((2, "z"), (0, "x"), (3, "y")):
        k2 = float(rng.normal(0, 1e-3))
        da, dg = make_effect("gyro_nonlinearity", imu=k, axis=a, parameters={"k2": k2}).perturbation(None, ctx)
        w, x, y, z = q[k]
        R = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                      [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                      [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
        i = "xyz".index(a)
        expect = np.zeros((T, K, 3))
        expect[:, k, i] = k2 * (omega @ R.T)[:, i] ** 2
        np.testing.assert_allclose(dg.numpy(), expect, rtol=1e-12, atol=1e-15)
        assert float(da.abs().max()) == 0
        # even in ω: the same motion run backwards gives the same perturbation
        ctx_r = SignalContext.from_motion(ctx.positions, ctx.orientations, -ctx.omega, ctx.omega_dot, ctx.s)
        _, dg_r = make_effect("gyro_nonlinearity", imu=k, axis=a, parameters={"k2": k2}).perturbation(None, ctx_r)
        assert torch.allclose(dg_r, dg, rtol=1e-12, atol=1e-15)
    e = make_effect("gyro_nonlinearity", imu=1, axis="y", parameters={"k2": -2e-4})
    assert e.explain().endswith(".") and "too low" in e.explain() and "IMU 1" in e.explain()
    assert e.report_parameters() == {"k2": -2e-4}
    assert EFFECTS["gyro_nonlinearity"].parameters[0].unit == "(rad s-1)-1"
    assert len(EFFECTS["gyro_nonlinearity"].candidates(CandidateLayout(3, np.ones(3, bool), np.array([1, 0, 1], bool)))) == 6


def test_axis_displacement_is_the_specific_force_at_the_displaced_point(setup):
    """Independent check: models.imu_outputs evaluated with IMU k moved by Rᵀd (array frame)."""
    arr, tr, pos, q, ctx = setup
    k, a = 6, 1
    d = torch.tensor([4e-4, -7e-4, 2.5e-4], dtype=torch.float64)  # sensor frame
    e = _one("axis_displacement", imu=k, axis=AXES[a], parameters={"displacement": d})
    da, dg = e.perturbation(None, ctx)
    moved = pos.clone()
    moved[k] = pos[k] + to_array_frame(d.reshape(1, 3), q[k:k + 1])[0]
    acc_moved, _ = imu_outputs(moved, q, tr.omega, tr.omega_dot, tr.s)
    expected = acc_moved[:, k, a] - ctx.acc[:, k, a]
    assert float((da[:, k, a] - expected).abs().max()) < 1e-12
    assert float(expected.abs().max()) > 1e-3  # a real signal, not a vacuous comparison
    assert float(dg.abs().max()) == 0


def test_triad_orientation_matches_rotated_imu_and_simulator_convention(setup):
    arr, tr, pos, q, ctx = setup
    k = 1  # a bottom-side IMU: nominal orientation is not the identity
    rho = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64) * DEG
    e = _one("triad_orientation", imu=k, parameters={"rotation_vector": rho})
    da, dg = e.perturbation(None, ctx)
    q_true = q.clone()
    q_true[k] = quat_mul(quat_exp(rho), q[k])
    acc_t, gyro_t = imu_outputs(pos, q_true, tr.omega, tr.omega_dot, tr.s)
    assert float((ctx.acc + da - acc_t).abs().max()) < 1e-12
    assert float((ctx.gyro + dg - gyro_t).abs().max()) < 1e-12
    # the simulator's orientation error δ (array frame, q ⊞ δ) is Rᵀρ — reported as rotation_vector_array
    delta = torch.tensor(e.report_parameters(orientations=q)["rotation_vector_array"], dtype=torch.float64)
    assert torch.allclose(quat_to_matrix(boxplus(q[k], delta)), quat_to_matrix(q_true[k]), atol=1e-12)
    assert abs(e.report_parameters()["angle_deg"] - float(rho.norm()) / DEG) < 1e-12


def test_time_offset_linear_term_against_shifted_trajectory():
    """Independent check: the continuous trajectory evaluated at t + δ (accel_bayes.physics.trajectories);
    the linearisation error must shrink as δ² (halving δ quarters it)."""
    arr = mimu4444_8()
    tr = smooth_motion(300, 200.0, seed=11)
    pos, q = arr.positions, arr.orientations
    k = 2
    h = 1e-5
    outs = [imu_outputs(pos, q, *(lambda m: (m.omega, m.omega_dot, m.s))(tr.trajectory.trace(tr.time + sg * h)))
            for sg in (1.0, -1.0)]
    acc_rate = (outs[0][0] - outs[1][0]) / (2 * h)
    gyro_rate = (outs[0][1] - outs[1][1]) / (2 * h)
    ctx = SignalContext.from_motion(pos, q, tr.omega, tr.omega_dot, tr.s, tr.time, acc_rate, gyro_rate)
    errs = []
    for dt in (1e-3, 5e-4):
        e = _one("time_offset", imu=k, parameters={"offset": dt})
        da, dg = e.perturbation(None, ctx)
        late = tr.trajectory.trace(tr.time + dt)
        acc_l, gyro_l = imu_outputs(pos, q, late.omega, late.omega_dot, late.s)
        exact_a = acc_l[:, k] - ctx.acc[:, k]
        err = float((da[:, k] - exact_a).abs().max())
        assert err < 0.02 * float(exact_a.abs().max())
        assert float((dg[:, k] - (gyro_l[:, k] - ctx.gyro[:, k])).abs().max()) < 0.02 * float((gyro_l[:, k] - ctx.gyro[:, k]).abs().max())
        errs.append(err)
    assert 3.0 < errs[0] / errs[1] < 5.0  # second-order remainder
    with pytest.raises(UserError):
        _one("time_offset", imu=k, parameters={"offset": 1e-3}).perturbation(None, SignalContext.from_motion(
            pos, q, tr.omega, tr.omega_dot, tr.s))


def test_output_rates_finite_differences():
    t = torch.linspace(0, 2, 401, dtype=torch.float64)
    y = torch.sin(3 * t)[:, None, None].expand(401, 2, 3).clone()
    ra, rg = output_rates(t, y, 2 * y)
    assert float((ra[:, 0, 0] - 3 * torch.cos(3 * t)).abs().max()) < 2e-3
    assert torch.allclose(rg, 2 * ra)
    # a gap is not differentiated across
    tg = torch.cat((t[:200], t[200:] + 5.0))
    ra2, _ = output_rates(tg, y, y)
    assert float((ra2[195:205, 0, 0] - 3 * torch.cos(3 * t[195:205])).abs().max()) < 2e-2


@pytest.mark.parametrize("name,kw", [("acc_scale", {"axis": "y"}), ("axis_displacement", {"axis": "x"}),
                                     ("triad_orientation", {}), ("gyro_g_sensitivity", {}),
                                     ("acc_nonlinearity", {"axis": "z"}), ("gyro_nonlinearity", {"axis": "y"})])
def test_perturbation_gradients_match_finite_differences(setup, name, kw):
    arr, tr, pos, q, ctx = setup
    e = make_effect(name, imu=4, **kw)
    sub = SignalContext(ctx.time[:40], ctx.omega[:40], ctx.omega_dot[:40], ctx.s[:40], pos, q, ctx.acc[:40], ctx.gyro[:40])
    g = torch.Generator().manual_seed(2)
    v = (1e-3 * torch.randn(e.df, generator=g, dtype=torch.float64)).requires_grad_(True)
    f = lambda v: torch.cat([t[:, 4].reshape(-1) for t in e.perturbation(e.unflatten(v), sub)])  # noqa: E731
    assert torch.autograd.gradcheck(f, (v,), eps=1e-7, atol=1e-6, rtol=1e-5)


def test_saturation_and_noise(setup):
    arr, tr, pos, q, ctx = setup
    e = _one("saturation", imu=2, axis="x", sensor="acc", parameters={"limit": 5.0})
    acc, gyro = e.transform(None, ctx.acc, ctx.gyro, ctx)
    assert float(acc[:, 2, 0].abs().max()) <= 5.0
    assert torch.equal(acc[:, :, 1:], ctx.acc[:, :, 1:]) and torch.equal(acc[:, [0, 1, 3, 4, 5, 6, 7]], ctx.acc[:, [0, 1, 3, 4, 5, 6, 7]])
    assert torch.equal(gyro, ctx.gyro)
    e.update_stats(ctx.acc, ctx.gyro)
    assert e.report_parameters()["clipped_fraction"] == pytest.approx(float((ctx.acc[:, 2, 0].abs() > 5).double().mean()))
    allc = _one("saturation", sensor="gyro", parameters={"limit": 2.0})
    _, g2 = allc.transform(None, ctx.acc, ctx.gyro, ctx)
    assert float(g2.abs().max()) <= 2.0
    assert allc.imu is None and allc.axis is None
    with pytest.raises(UserError):
        make_effect("saturation", imu=2, sensor="acc")
    fa, fg = noise_factors([_one("noise_level", imu=3, sensor="gyro", parameters={"factor": 1.5}),
                            _one("noise_level", sensor="acc", parameters={"factor": 1.2})], 8)
    assert torch.allclose(fa, torch.full((8,), 1.2, dtype=torch.float64))
    assert float(fg[3]) == 1.5 and float(fg.sum()) == 7 + 1.5


def test_simulate_with_effects_uses_the_same_definitions():
    arr = mimu4444_8()
    kw = dict(T=300, rate=200.0, seed=4, acc_noise_std=0.02, gyro_noise_std=0.1 * DEG)
    plain = simulate(arr, "smooth", **kw)
    effs = [_one("acc_bias", imu=3, axis="y", parameters={"bias": 0.1}),
            _one("gyro_scale", imu=6, axis="x", parameters={"scale": 0.01}),
            _one("noise_level", imu=1, sensor="acc", parameters={"factor": 2.0})]
    sim = simulate(arr, "smooth", effects=effs, **kw)
    ra, rb = plain.recording, sim.recording
    ctx = SignalContext(torch.as_tensor(ra.time), plain.motion.omega, plain.motion.omega_dot, plain.motion.s,
                        plain.true_positions, plain.true_orientations, plain.acc_clean, plain.gyro_clean)
    acc_m, gyro_m = model_outputs(effs[:2], ctx)
    noise_a = torch.as_tensor(ra.acc) - plain.acc_clean
    noise_a[:, 1] *= 2.0
    assert np.allclose(rb.acc, (acc_m + noise_a).numpy(), atol=1e-12)
    assert np.allclose(rb.gyro, ra.gyro + (gyro_m - plain.gyro_clean).numpy(), atol=1e-12)
    assert np.allclose(rb.acc_noise_std, ra.acc_noise_std)  # the stated noise is unchanged
    assert [d["effect"] for d in sim.truth["effects"]] == ["acc_bias", "gyro_scale", "noise_level"]
    # dict specs (report style) are accepted and give the same recording
    sim2 = simulate(arr, "smooth", effects=[{"effect": "acc_bias", "imu": 3, "axis": "y", "parameters": {"bias": 0.1}},
                                            {"effect": "gyro_scale", "imu": 6, "axis": "x", "parameters": {"scale": 0.01}},
                                            {"effect": "noise_level", "imu": 1, "sensor": "acc",
                                             "parameters": {"factor": 2.0}}], **kw)
    assert np.array_equal(sim2.recording.acc, rb.acc)
    # time_offset through simulate ≈ the exact time_offsets path (linearisation error only)
    exact = simulate(arr, "smooth", time_offsets=[0, 0, 5e-4, 0, 0, 0, 0, 0], **kw)
    lin = simulate(arr, "smooth", effects=[_one("time_offset", imu=2, parameters={"offset": 5e-4})], **kw)
    diff = np.abs(lin.recording.acc - exact.recording.acc).max()
    shift = np.abs(exact.recording.acc - ra.acc).max()
    assert diff < 0.02 * shift
    with pytest.raises(UserError):
        simulate(arr, "iid", T=50, effects=[_one("time_offset", imu=2, parameters={"offset": 5e-4})])
    with pytest.raises(UserError):
        simulate(arr, "smooth", T=50, effects=["acc_bias"])


def test_time_offset_exact_and_linearised_forms_agree_to_second_order():
    """The one time-offset parameter (DESIGN §7.2: positive = sampled late) evaluated both ways
    by the simulator: exactly (``time_offsets=``: the trajectory at t + δ) and linearised
    (``effects=[time_offset]``: δ·ẏ).  Noise-free, for late and early offsets: the difference is
    the Taylor remainder, ≤ ½δ²·max|ÿ| (ÿ by central differences of the exact outputs), and halving
    δ quarters it; a sign mismatch would instead leave an error of twice the effect."""
    arr = mimu4444_8()
    kw = dict(T=300, rate=200.0, seed=5, acc_noise_std=0.0, gyro_noise_std=0.0, validate=False, clip=False)
    k = 3
    base = simulate(arr, "smooth", **kw).recording
    h = 2e-3
    outs = [simulate(arr, "smooth", time_offsets=[h * sg if i == k else 0.0 for i in range(arr.K)], **kw).recording
            for sg in (1.0, -1.0)]
    curv = {n: np.abs(getattr(outs[0], n)[:, k] - 2 * getattr(base, n)[:, k] + getattr(outs[1], n)[:, k]).max() / h**2
            for n in ("acc", "gyro")}
    for sign in (1.0, -1.0):
        errs = []
        for delta in (1e-3, 5e-4):
            d = sign * delta
            exact = simulate(arr, "smooth", time_offsets=[d if i == k else 0.0 for i in range(arr.K)], **kw).recording
            lin = simulate(arr, "smooth", effects=[_one("time_offset", imu=k, parameters={"offset": d})], **kw).recording
            for n in ("acc", "gyro"):
                err = np.abs(getattr(lin, n) - getattr(exact, n)).max()
                effect = np.abs(getattr(exact, n) - getattr(base, n)).max()
                assert err <= 0.5 * d**2 * curv[n] * 1.1 + 1e-9, (n, d, err, curv[n])
                assert err < 0.05 * effect
            errs.append(np.abs(lin.acc - exact.acc).max())
        assert 3.0 < errs[0] / errs[1] < 5.0, errs  # O(δ²)


def test_apply_effects_clips_after_noise(setup):
    arr, tr, pos, q, ctx = setup
    e = _one("saturation", imu=0, axis="z", sensor="acc", parameters={"limit": 9.0})
    noise = 0.05 * torch.randn(ctx.acc.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    acc, gyro = apply_effects([e], ctx, noise, torch.zeros_like(noise))
    clipped = (ctx.acc[:, 0, 2] + noise[:, 0, 2]).abs() >= 9.0
    assert bool(clipped.any())
    assert torch.all(acc[clipped, 0, 2].abs() == 9.0)
    assert torch.allclose(acc[~clipped, 0, 2], ctx.acc[~clipped, 0, 2] + noise[~clipped, 0, 2])


def test_report_parameters_round_trip(setup):
    """A finding's (effect, imu, axis, parameters) rebuilds the same effect (make_effect)."""
    arr, tr, pos, q, ctx = setup
    layout = CandidateLayout(8, np.ones(8, bool), np.ones(8, bool), 0)
    g = torch.Generator().manual_seed(9)
    for name in VOCABULARY:
        cls = EFFECTS[name]
        if cls.kind == "finding":
            continue
        e = cls.candidates(layout)[5]
        # (a width is >= 0 by definition)
        vals = {p.name: (1e-3 * torch.randn(p.shape, generator=g, dtype=torch.float64) if p.null == 0 else
                         torch.tensor(1.3 if name == "noise_level" else 4.0, dtype=torch.float64))
                for p in cls.parameters}
        if name == "sampling_jitter":
            vals = {k: v.abs() for k, v in vals.items()}
        e.set_params(vals)
        rp = e.report_parameters()
        json_rp = {k: (v if not isinstance(v, float) or math.isfinite(v) else None) for k, v in rp.items()}
        e2 = make_effect(name, imu=e.imu, axis=e.axis, parameters=json_rp)
        assert e2.label() == e.label()
        for k in vals:
            assert torch.allclose(e2.params[k], e.params[k])
        if cls.kind == "mean":
            c = SignalContext(ctx.time, ctx.omega, ctx.omega_dot, ctx.s, pos, q, ctx.acc, ctx.gyro,
                              ctx.acc, ctx.gyro)  # any rates will do for the comparison
            for a, b in zip(e.perturbation(None, c), e2.perturbation(None, c)):
                assert torch.equal(a, b)


def test_intrinsics_and_s16_sensor_parameters_are_conversions_of_the_effects():
    """The lower-triangular intrinsic model a_true = T(a_raw − b) and the [S16] model
    z = Sᵀ R(q) f + o (S upper-triangular) are the effects' general gain + bias in the triangular
    gauge: convert → apply the effects → compare with the old formulas on random inputs, and
    convert back.  A general gain factors as L·Q; the rotation Q goes into the orientation."""
    from accel_bayes.physics import models
    from accel_bayes.physics.geometry import matrix_to_quat
    from accel_bayes.physics.effects import (acc_gain_effects, acc_gain_of_effects, gain_to_intrinsics, gain_to_s16,
                                             intrinsics_gain, s16_gain, triangular_gauge)

    gen = torch.Generator().manual_seed(8)
    T_, K = 50, 3
    rnd = lambda *s, sc=1.0: sc * torch.randn(*s, generator=gen, dtype=torch.float64)  # noqa: E731
    f = rnd(T_, K, 3, sc=10.0)  # true sensor-frame specific force
    zero = torch.zeros(T_, 3, dtype=torch.float64)
    ctx = SignalContext(torch.arange(T_, dtype=torch.float64), zero, zero, zero, torch.zeros(K, 3, dtype=torch.float64),
                        torch.tensor([[1.0, 0, 0, 0]] * K, dtype=torch.float64), f, torch.zeros_like(f))
    k = 1
    # intrinsics: T lower-triangular with positive diagonal
    Tm = torch.tril(rnd(3, 3, sc=0.01)) + torch.eye(3, dtype=torch.float64)
    b = rnd(3, sc=0.3)
    eff = acc_gain_effects(*intrinsics_gain(Tm, b), imu=k)
    y, _ = model_outputs(eff, ctx)
    raw = (torch.linalg.inv(Tm) @ f[:, k].unsqueeze(-1)).squeeze(-1) + b  # old formula, inverted
    torch.testing.assert_close(y[:, k], raw, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close((Tm @ (y[:, k] - b).unsqueeze(-1)).squeeze(-1), f[:, k], rtol=1e-13, atol=1e-12)
    assert torch.equal(y[:, [0, 2]], f[:, [0, 2]])  # other IMUs untouched
    T2, b2, Q = gain_to_intrinsics(*acc_gain_of_effects(eff, k))
    torch.testing.assert_close(T2, Tm, rtol=0, atol=1e-13)
    torch.testing.assert_close(b2, b, rtol=0, atol=0)
    torch.testing.assert_close(Q, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-13)
    # [S16]: S upper-triangular (eq. 21 parameters), offset o; the old formula is models.triad_output
    sp = torch.tensor([1.0, 0.0, 1.0, 0.0, 0.0, 1.0], dtype=torch.float64) + rnd(6, sc=0.02)
    S = models.sensitivity_matrix(sp)
    o = rnd(3, sc=0.1)
    eff = acc_gain_effects(*s16_gain(S, o), imu=k)
    y, _ = model_outputs(eff, ctx)
    state = torch.cat((rnd(T_, 3, sc=5.0), rnd(T_, 3, sc=2.0), rnd(T_, 3, sc=10.0)), -1)
    q = quat_exp(rnd(1, 3, sc=0.5))
    r = rnd(1, 3, sc=0.05)
    fs = models.triad_output(state, q, r)  # sensor-frame specific force of that triad (T, 1, 3)
    ctx_s = SignalContext(ctx.time, zero, zero, zero, r, q, fs, torch.zeros_like(fs))
    y, _ = model_outputs(acc_gain_effects(*s16_gain(S, o), imu=0), ctx_s)
    torch.testing.assert_close(y, models.triad_output(state, q, r, S.unsqueeze(0), o.unsqueeze(0)), rtol=1e-13, atol=1e-12)
    S2, o2, Q = gain_to_s16(*acc_gain_of_effects(eff, k))
    torch.testing.assert_close(S2, S, rtol=0, atol=1e-13)
    torch.testing.assert_close(o2, o, rtol=0, atol=0)
    # the gauge: a general gain = L·Q; the [S16] triad with S = Lᵀ and orientation Q·R(q) gives
    # the same outputs as the general gain on orientation q
    G = torch.eye(3, dtype=torch.float64) + rnd(3, 3, sc=0.05)
    L, Q = triangular_gauge(G)
    assert torch.equal(L, torch.tril(L)) and bool((torch.diagonal(L) > 0).all())
    torch.testing.assert_close(Q @ Q.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-14)
    assert abs(float(torch.linalg.det(Q)) - 1.0) < 1e-14
    torch.testing.assert_close(L @ Q, G, rtol=0, atol=1e-14)
    y, _ = model_outputs(acc_gain_effects(G, o, imu=0), ctx_s)
    S3, o3, Q3 = gain_to_s16(G, o)
    q3 = matrix_to_quat(Q3 @ quat_to_matrix(q))
    torch.testing.assert_close(y, models.triad_output(state, q3, r, S3.unsqueeze(0), o3.unsqueeze(0)), rtol=1e-12, atol=1e-11)

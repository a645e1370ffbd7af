"""``sampling_jitter`` (DESIGN §7.2 vocabulary 1.1), checked against independent computations:

(a) the closed-form marginal over the uniform sampling-instant error against brute-force
    quadrature over δ of the *nonlinear* signal (exact outputs at t + δ of a known trajectory,
    from the independent generator ``experiments/_conceal.py``), and against plain quadrature of
    E[exp(bδ − aδ²/2)] over extreme values;
(b) the simulator's jittered outputs against kinematics at the jittered instants computed here
    by finite differences of the trajectory's pose (no ``imu_outputs``);
(c) detection on concealed jitter cases (right IMU, width inside its interval, named before
    ``noise_level``), and (slow) the noise_level / sampling_jitter confusion on fixed seeds.
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.physics.effects import log_marginal_gain, make_effect
from accel_bayes.simulate import simulate

from experiments import _conceal as C

DEG = math.pi / 180


def _quad_gain(a, b, w, n=400001):
    """log E_δ[exp(bδ − aδ²/2)], δ ~ U(−w/2, w/2), by the trapezoid rule (max-shifted)."""
    d = np.linspace(-w / 2, w / 2, n)
    f = b * d - a * d * d / 2
    mx = f.max()
    return mx + math.log(np.trapezoid(np.exp(f - mx), d) / w)


@pytest.mark.parametrize("a,b,w", [(1e9, 3e5, 8e-4), (1e9, -3e5, 8e-4), (1e6, 50.0, 1e-3), (1.0, 0.1, 1e-4),
                                   (1e10, 1e7, 5e-4), (1e8, 1e6, 1e-4), (1e9, 1e3, 8e-4), (4e6, 2e3, 1e-3)])
def test_closed_form_gain_matches_quadrature(a, b, w):
    got = float(log_marginal_gain(torch.tensor(a), torch.tensor(b), w))
    # trapezoid with 4e5 nodes: relative error ~1e-10 on these smooth integrands
    assert got == pytest.approx(_quad_gain(a, b, w), rel=1e-7, abs=1e-9)
    assert float(log_marginal_gain(torch.tensor(a), torch.tensor(b), 0.0)) == 0.0


def test_marginal_matches_quadrature_of_the_nonlinear_signal():
    """Small case: 2 IMUs of the mimu8 board, 6 samples, w = 0.3 ms; outputs at t + δ evaluated
    exactly on a random trajectory of the independent generator.  The linearised closed form
    must match the brute-force quadrature of p(r) = (1/w)∫ N(y; f(t + δ), D) dδ to within the
    neglected second-order term (bound below), and the Gaussian moment-matched alternative
    N(r; 0, D + (w²/12) v vᵀ) must not (so the test can fail)."""
    rng = np.random.default_rng(4)
    b = C.board("mimu8")
    t = np.array([0.4, 0.9, 1.3, 1.8, 2.2, 2.7])
    traj = C.RotvecTrajectory.random(rng, np.linspace(0, 3, 300), omega_rms=5.0, acc_rms=5.0)
    sa, sg = 0.02, 0.1 * DEG
    D = np.r_[np.full(3, sa ** 2), np.full(3, sg ** 2)]
    w = 3e-4
    for k in (2, 5):
        R, P = b.rotations[k:k + 1], np.repeat(b.positions[k:k + 1, None], 3, 1)

        def f(tt):
            acc, gyro = C.sensor_outputs(traj, tt, R, P)
            return np.concatenate((acc[:, 0], gyro[:, 0]), -1)  # (n, 6)

        h = 1e-6
        mu, v = f(t), (f(t + h) - f(t - h)) / (2 * h)
        delta0 = rng.uniform(-w / 2, w / 2, t.size)
        y = f(t + delta0) + rng.standard_normal((t.size, 6)) * np.sqrt(D)
        r = y - mu
        a_ = (v * v / D).sum(-1)
        b_ = (v * r / D).sum(-1)
        closed = log_marginal_gain(torch.as_tensor(a_), torch.as_tensor(b_), w).numpy()
        grid = np.linspace(-w / 2, w / 2, 4001)
        for i in range(t.size):
            fy = f(t[i] + grid)  # exact outputs at every candidate instant (nonlinear in δ)
            ll = -0.5 * (((y[i] - fy) ** 2) / D).sum(-1)
            ll0 = -0.5 * ((r[i] ** 2) / D).sum()
            mx = ll.max()
            brute = mx + math.log(np.trapezoid(np.exp(ll - mx), grid) / w) - ll0
            # neglected term: the δ²/2·f'' part of f(t + δ) − μ − vδ, in noise units, times the
            # whitened residual it multiplies (≲ 2 here), plus quadrature error.  Measured: the
            # differences are 5e-5–1.8e-3, the bounds 8e-3–1.5e-2
            f2 = (f(t[i:i + 1] + 1e-4) - 2 * f(t[i:i + 1]) + f(t[i:i + 1] - 1e-4))[0] / 1e-8
            bound = 2 * np.sqrt(((w / 2) ** 4 / 4 * f2 ** 2 / D).sum()) + 1e-6
            assert abs(closed[i] - brute) <= bound, (k, i, closed[i], brute, bound)
            assert bound < 0.02
        # the moment-matched Gaussian is a different likelihood here (√a·w ≫ 1): it must fail
        # (measured max differences 0.23 and 0.30)
        Sig = np.diag(D)[None] + w * w / 12 * v[:, :, None] * v[:, None, :]
        ll_mm = np.array([-0.5 * r[i] @ np.linalg.solve(Sig[i], r[i]) - 0.5 * np.linalg.slogdet(Sig[i])[1]
                          for i in range(t.size)]) + 0.5 * np.log(D).sum() + 0.5 * ((r ** 2) / D).sum(-1)
        assert np.abs(ll_mm - closed).max() > 0.1


def _pose_kinematics(trajectory, t, r, Rk):
    """Independent outputs of an IMU at board point r (array frame) with array → sensor rotation
    Rk, at times t: specific force R_k R_wbᵀ (p̈ − g) with p̈ the 8th-order finite difference of
    the world position p₀ + R_wb r, and ω from Ω = R_wbᵀ Ṙ_wb (4th-order difference of R_wb)."""
    def Rwb(tt):
        return C.quat_to_rotmat(trajectory.evaluate(torch.as_tensor(tt))["attitude"].numpy())

    def pos(tt):
        e = trajectory.evaluate(torch.as_tensor(tt))
        return e["position"].numpy() + Rwb(tt) @ r

    h = 2e-3
    pdd = C.fd_second_derivative(pos, t, h)
    R0 = Rwb(t)
    acc = np.einsum("tji,tj->ti", R0, pdd - C.G_WORLD) @ Rk.T
    hh = 1e-4
    Rd = (-Rwb(t + 2 * hh) + 8 * Rwb(t + hh) - 8 * Rwb(t - hh) + Rwb(t - 2 * hh)) / (12 * hh)
    W = R0.transpose(0, 2, 1) @ Rd
    om = np.stack((W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]), -1)
    return acc, om @ Rk.T


def test_simulated_jitter_matches_kinematics_at_the_jittered_instants():
    arr = mimu4444_8()
    k, w = 3, 1e-3
    eff = make_effect("sampling_jitter", imu=k, parameters={"width": w})
    sim = simulate(arr, "smooth", T=300, rate=200.0, seed=11, effects=[eff])
    plain = simulate(arr, "smooth", T=300, rate=200.0, seed=11)
    inst = sim.sampling_instants[k].numpy()
    t = sim.recording.time
    d = inst - t
    assert np.abs(d).max() <= w / 2 and d.std() == pytest.approx(w / math.sqrt(12), rel=0.15)
    Rk = C.quat_to_rotmat(sim.true_orientations[k].numpy())
    acc_x, gyro_x = _pose_kinematics(sim.motion.trajectory, inst, sim.true_positions[k].numpy(), Rk)
    np.testing.assert_allclose(sim.acc_clean[:, k].numpy(), acc_x, rtol=0, atol=1e-6)
    np.testing.assert_allclose(sim.gyro_clean[:, k].numpy(), gyro_x, rtol=0, atol=1e-7)
    # the jitter is visible (far above the tolerances above), other IMUs and the noise stream untouched
    assert np.abs(sim.gyro_clean[:, k].numpy() - plain.gyro_clean[:, k].numpy()).max() > 1e-4
    others = [j for j in range(arr.K) if j != k]
    np.testing.assert_array_equal(sim.recording.acc[:, others], plain.recording.acc[:, others])
    assert sim.truth["effects"][0]["effect"] == "sampling_jitter"
    with pytest.raises(UserError):
        make_effect("sampling_jitter", imu=k, parameters={"width": -1e-4})
    with pytest.raises(UserError):
        simulate(arr, "iid", T=50, seed=1, effects=[eff])


def test_conceal_jitter_is_exact_kinematics_at_random_instants():
    case = C.make_case("irregular6", "sampling_jitter", seed=5, T=400, noise=False)
    twin = C.make_case("irregular6", "none", seed=5, T=400, noise=False)
    k, w = case.truth["imu"], case.truth["parameters"]["width"]
    assert 1e-4 <= w <= 1e-3 and case.truth["axis"] is None
    dg = case.recording.gyro[:, k] - twin.recording.gyro[:, k]
    # to first order the difference is rate·δ with one δ per sample shared by all six channels
    h = 1e-6
    tr = C.RotvecTrajectory.from_dict(case.truth["trajectory"])
    R = C.board("irregular6").rotations[k:k + 1]
    P = np.repeat(case.truth["true_position"][k:k + 1, None], 3, 1)
    t = case.recording.time
    rate = (C.sensor_outputs(tr, t + h, R, P)[1] - C.sensor_outputs(tr, t - h, R, P)[1])[:, 0] / (2 * h)
    delta = (dg * rate).sum(-1) / (rate * rate).sum(-1)
    assert np.abs(delta).max() <= w / 2 * 1.01 and np.abs(delta).max() > 0.4 * w
    assert np.abs(dg - rate * delta[:, None]).max() < 0.02 * np.abs(dg).max()


# half the twins and LOO draws of test_detect's settings: these tests run detect on many cases
JITTER_DETECT = dict(n_twins=10, loo_draws=20, n_refit=3)
VARIANCE_EFFECTS = ["sampling_jitter", "noise_level", "time_offset", "gyro_scale", "acc_scale"]


def _named(case, **kw):
    from accel_bayes.mismatch import detect

    rep = detect(case.recording, seed=0, **{**JITTER_DETECT, **kw})
    f = [x for x in rep.findings if x.effect != "unexplained"]
    return rep, f


def test_detects_concealed_jitter_with_its_width():
    case = C.make_case("mimu8", "sampling_jitter", seed=2, T=500)
    rep, f = _named(case, effects=VARIANCE_EFFECTS, max_findings=2)
    assert f and f[0].effect == "sampling_jitter" and f[0].model.imu == case.truth["imu"]
    lo, hi = f[0].model.stats["width_interval_s"]
    assert lo <= case.truth["magnitude"] <= hi and hi - lo < 0.2 * case.truth["magnitude"]
    d = rep.to_dict()
    assert d["refined"]["chi2_noise"].startswith("refined") and abs(d["refined"]["chi2_per_dof"] - 1) < 0.05
    assert "sampling_jitter" in d["refined"]["effects"]
    assert d["findings"][0]["parameters"]["width"] == pytest.approx(f[0].model.params["width"].item())
    assert d["findings"][0]["axis"] is None


@pytest.mark.slow
def test_noise_level_and_jitter_are_not_confused():
    """Concealed noise_level (accelerometer noise × 1.2–2) and sampling_jitter (0.1–1 ms) on 4
    fixed seeds each, plus one gyroscope noise_level case from the package simulator, every
    effect of the vocabulary tried: the named effect is the concealed one on the right IMU (aim
    ≤ 10 % confusion; with 9 cases any confusion fails), and each jitter width lies within its
    profile interval.  (Measured: 0/9 confused; 0.1-ms widths on seeds 21, 22 are found too.)"""
    wrong = []
    for eff in ("noise_level", "sampling_jitter"):
        for seed in (11, 12, 13, 14):
            case = C.make_case("mimu8", eff, seed=seed, T=500)
            rep, f = _named(case, max_findings=2)
            ok = bool(f) and f[0].effect == eff and f[0].model.imu == case.truth["imu"]
            if ok and eff == "sampling_jitter":
                lo, hi = f[0].model.stats["width_interval_s"]
                ok = lo <= case.truth["magnitude"] <= hi
            if not ok:
                wrong.append((eff, seed, [(x.model.label(), x.evidence) for x in f]))
    # gyroscope noise larger than stated (the sensor jitter shows up on most): simulated by the
    # package, factor 1.5 on IMU 5's gyroscope — must stay noise_level
    eff = make_effect("noise_level", imu=5, sensor="gyro", parameters={"factor": 1.5})
    sim = simulate(mimu4444_8(), "smooth", T=400, rate=200.0, seed=31, effects=[eff], acc_noise_std=0.02,
                   gyro_noise_std=0.1 * DEG)
    rep, f = _named(sim, max_findings=2)
    if not (f and f[0].effect == "noise_level" and f[0].model.imu == 5 and f[0].model.which == "gyro"):
        wrong.append(("noise_level gyro", 31, [(x.model.label(), x.evidence) for x in f]))
    assert not wrong, wrong

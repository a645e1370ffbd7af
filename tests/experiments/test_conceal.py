"""Checks of the independent blind-test generator ``experiments/_conceal.py``.

The generator is the yardstick of the mismatch benchmark, so it is checked against closed forms
and finite differences, never against the package's own signal model (one test at the end only
*compares* the two, to catch a frame-convention disagreement between them).
"""
import math

import numpy as np
import pytest

from experiments import _conceal as C

G0 = C.G0


def _static(R0=None):
    z = np.zeros((3, 1))
    return C.RotvecTrajectory(np.eye(3) if R0 is None else R0, np.zeros(3), z, np.ones((3, 1)), z,
                              z, np.ones((3, 1)), z)


def _spin_about_z(rate=0.0, amp=0.0, freq=1.0):
    """Rotation about the array (and world) z axis through the origin: θ(t) = rate·t + amp·sin(2πft)."""
    z = np.zeros((3, 1))
    ra = np.zeros((3, 1))
    ra[2, 0] = amp
    return C.RotvecTrajectory(np.eye(3), np.zeros(3), ra, np.full((3, 1), freq), z, z, np.ones((3, 1)), z,
                              rot_rate=np.array([0.0, 0.0, rate]))


def test_design_quaternion_convention():
    # DESIGN §7.0 worked example: q = (0.7071, 0, 0, −0.7071) reads array (0, 1, 0) as (1, 0, 0).
    R = C.quat_to_rotmat(np.array([math.sqrt(0.5), 0, 0, -math.sqrt(0.5)]))
    np.testing.assert_allclose(R @ [0, 1, 0], [1, 0, 0], atol=1e-15)
    # MIMU bottom side: C of the data README maps z to −z and swaps x, y.
    Rb = C.quat_to_rotmat(np.array([0, math.sqrt(0.5), -math.sqrt(0.5), 0]))
    np.testing.assert_allclose(Rb, [[0, -1, 0], [-1, 0, 0], [0, 0, -1]], atol=1e-15)
    rng = np.random.default_rng(0)
    for _ in range(20):
        Rr = C.random_rotation(rng)
        np.testing.assert_allclose(C.quat_to_rotmat(C.rotmat_to_quat(Rr)), Rr, atol=1e-14)


@pytest.mark.parametrize("board", ["mimu8", "irregular6"])
def test_stationary_board_reads_plus_g_up(board):
    b = C.board(board)
    t = np.arange(50) / 100.0
    for R0 in (np.eye(3), C.random_rotation(np.random.default_rng(4))):
        acc, gyro = C.sensor_outputs(_static(R0), t, b.rotations, np.repeat(b.positions[:, None], 3, 1))
        # up = −g direction, world (0, 0, 1) → array R0ᵀ e_z → sensor R_k R0ᵀ e_z, times +g.
        expect = G0 * np.einsum("kij,j->ki", b.rotations, R0.T @ [0.0, 0.0, 1.0])
        np.testing.assert_allclose(acc, np.broadcast_to(expect, acc.shape), atol=1e-12)
        np.testing.assert_allclose(gyro, 0.0, atol=1e-15)
    # Level board, MIMU: top-side IMUs read +g on z, bottom-side ones −g (their z points down).
    if board == "mimu8":
        acc, _ = C.sensor_outputs(_static(), t[:1], b.rotations, np.repeat(b.positions[:, None], 3, 1))
        np.testing.assert_allclose(acc[0, :, 2], G0 * np.array([1, -1] * 4), atol=1e-12)


def test_constant_spin_gives_centripetal_omega_squared_rho():
    w = 7.0  # rad/s about z through the origin
    tr = _spin_about_z(rate=w)
    t = np.linspace(0.0, 2.0, 101)  # θ up to 14 rad: Exp of a long rotation vector too
    rho, alpha = 0.0137, 0.6
    x = np.array([rho * math.cos(alpha), rho * math.sin(alpha), 0.004])
    f = tr.specific_force(t, x)
    # Array frame: centripetal −ω²ρ along the radius, gravity +g on z (the axis stays vertical).
    expect = np.array([-w * w * x[0], -w * w * x[1], G0])
    np.testing.assert_allclose(f, np.broadcast_to(expect, f.shape), atol=1e-10)
    np.testing.assert_allclose(tr.omega_body(t), np.broadcast_to([0, 0, w], (t.size, 3)), atol=1e-12)
    # A point on the axis feels no rotation.
    np.testing.assert_allclose(tr.specific_force(t, np.array([0, 0, 0.01])), np.broadcast_to([0, 0, G0], f.shape),
                               atol=1e-11)


def test_oscillating_spin_centripetal_and_tangential():
    A, fr = 1.3, 0.8
    tr = _spin_about_z(amp=A, freq=fr)
    t = np.linspace(0.0, 3.0, 301)
    W = 2 * math.pi * fr
    th_d = A * W * np.cos(W * t)
    th_dd = -A * W * W * np.sin(W * t)
    rho = 0.02
    f = tr.specific_force(t, np.array([rho, 0.0, 0.0]))
    # Radial −θ̇²ρ, tangential +θ̈ρ (body frame, point on the body x axis).
    np.testing.assert_allclose(f[:, 0], -th_d ** 2 * rho, atol=1e-11)
    np.testing.assert_allclose(f[:, 1], th_dd * rho, atol=1e-11)
    np.testing.assert_allclose(f[:, 2], G0, atol=1e-11)


def test_second_derivative_matches_finite_difference_within_bound():
    rng = np.random.default_rng(11)
    t = np.sort(rng.uniform(0.0, 20.0, 200))
    tr = C.RotvecTrajectory.random(rng, t, omega_rms=600 * C.DEG, acc_rms=8.0)
    x = np.array([[0.0, 0.0, 0.0], [0.0095, -0.0095, 0.001], [0.023, 0.004, -0.003]])
    chk = C.check_point_acceleration(tr, t, x, h=2e-3)
    assert chk["bound"] < 1e-7, chk          # the FD itself is accurate enough to judge by
    assert chk["max_error"] <= chk["bound"], chk
    # A wrong analytic term (e.g. the factor 2 of the 2ṘṘ cross terms) would be far outside.
    assert chk["max_error"] < 1e-7


def test_gyro_rate_matches_attitude_finite_difference():
    rng = np.random.default_rng(12)
    t = np.sort(rng.uniform(0.0, 10.0, 100))
    tr = C.RotvecTrajectory.random(rng, t, omega_rms=500 * C.DEG)
    h = 1e-3
    # 4th-order central difference of R; Ω(ω) = Rᵀ Ṙ.
    Rd = (-tr.attitude(t + 2 * h) + 8 * tr.attitude(t + h) - 8 * tr.attitude(t - h) + tr.attitude(t - 2 * h)) / (12 * h)
    w_fd = C.unskew(np.swapaxes(tr.attitude(t), -1, -2) @ Rd)
    np.testing.assert_allclose(tr.omega_body(t), w_fd, atol=1e-6)
    # and from the quaternion: ω = 2 Im(q* ⊗ q̇) (independent of the matrix route)
    q = lambda tt: np.stack([C.rotmat_to_quat(R) for R in tr.attitude(tt)])  # noqa: E731
    q0, qp, qm = q(t), q(t + 1e-5), q(t - 1e-5)
    qp *= np.sign((qp * q0).sum(-1, keepdims=True))  # same hemisphere
    qm *= np.sign((qm * q0).sum(-1, keepdims=True))
    qd = (qp - qm) / 2e-5
    w0, v0 = q0[:, :1], -q0[:, 1:]  # conjugate
    vec = w0 * qd[:, 1:] + qd[:, :1] * v0 + np.cross(v0, qd[:, 1:])
    np.testing.assert_allclose(tr.omega_body(t), 2 * vec, atol=1e-6)


def test_time_offset_equals_shifted_samples():
    kw = dict(T=400, rate=200.0, noise=False)
    clean = C.make_case("mimu8", "none", seed=5, **kw)
    late = C.make_case("mimu8", "time_offset", seed=5, magnitude=3 / 200.0, **kw)
    k = late.truth["imu"]
    a0, a1 = clean.recording.acc, late.recording.acc
    np.testing.assert_allclose(a1[:-3, k], a0[3:, k], atol=1e-10)
    np.testing.assert_allclose(late.recording.gyro[:-3, k], clean.recording.gyro[3:, k], atol=1e-12)
    others = [j for j in range(8) if j != k]
    np.testing.assert_array_equal(a1[:, others], a0[:, others])
    assert np.abs(a1[:, k] - a0[:, k]).max() > 0.1  # the shift is not negligible


def test_determinism_and_clean_twin():
    a = C.make_case("mimu32", "acc_bias", seed=21, T=300)
    b = C.make_case("mimu32", "acc_bias", seed=21, T=300)
    c = C.make_case("mimu32", "acc_bias", seed=22, T=300)
    np.testing.assert_array_equal(a.recording.acc, b.recording.acc)
    np.testing.assert_array_equal(a.recording.gyro, b.recording.gyro)
    assert a.truth["imu"] == b.truth["imu"] and a.truth["magnitude"] == b.truth["magnitude"]
    assert not np.array_equal(a.recording.acc, c.recording.acc)
    twin = C.make_case("mimu32", "none", seed=21, T=300)
    d = a.recording.acc - twin.recording.acc
    k, i = a.truth["imu"], "xyz".index(a.truth["axis"])
    np.testing.assert_allclose(d[:, k, i], a.truth["magnitude"], atol=1e-12)
    d[:, k, i] = 0
    assert np.abs(d).max() < 1e-12
    np.testing.assert_array_equal(a.recording.gyro, twin.recording.gyro)
    np.testing.assert_array_equal(a.truth["true_position"], twin.truth["true_position"])
    # Oracle non-centrality of a bias: T (b/σ_a)², the noise cancelling exactly against the twin.
    lam = C.oracle_noncentrality(a, twin)
    np.testing.assert_allclose(lam, 300 * (a.truth["magnitude"] / a.truth["settings"]["sigma_a"]) ** 2, rtol=1e-9)


def test_effects_act_where_the_truth_says():
    kw = dict(T=600, rate=150.0)
    twin = C.make_case("irregular6", "none", seed=8, noise=False, **kw)
    R = C.board("irregular6").rotations
    for eff in C.EFFECTS:
        case = C.make_case("irregular6", eff, seed=8, noise=False, **kw)
        tr = case.truth
        k = tr["imu"]
        assert k is not None and k != 0
        da = np.abs(case.recording.acc - twin.recording.acc).max(0)  # (K, 3)
        dg = np.abs(case.recording.gyro - twin.recording.gyro).max(0)
        others = [j for j in range(6) if j != k]
        assert da[others].max() < 1e-12 and dg[others].max() < 1e-12, eff
        if eff == "noise_level":
            assert da.max() < 1e-12  # noise-free: only the truth changes
            continue
        assert max(da[k].max(), dg[k].max()) > 1e-6, eff
        if eff in ("acc_bias", "acc_scale", "acc_misalignment", "acc_nonlinearity", "axis_displacement"):
            i = "xyz".index(tr["axis"])
            assert dg[k].max() < 1e-12 and np.delete(da[k], i).max() < 1e-12, eff
        if eff.startswith("gyro_"):
            i = "xyz".index(tr["axis"])
            assert da[k].max() < 1e-12 and np.delete(dg[k], i).max() < 1e-12, eff
        if eff == "triad_orientation":
            rho = np.asarray(tr["parameters"]["rotation_vector"])
            np.testing.assert_allclose(np.linalg.norm(rho), abs(tr["magnitude"]))
            np.testing.assert_allclose(case.recording.gyro[:, k], twin.recording.gyro[:, k] @ C.so3_exp(rho).T,
                                       atol=1e-12)
            np.testing.assert_allclose(C.quat_to_rotmat(np.asarray(tr["true_orientation"][k])), C.so3_exp(rho) @ R[k],
                                       atol=1e-12)
        if eff == "axis_displacement":
            # The displaced axis reads exactly what a whole triad at the displaced point reads.
            i = "xyz".index(tr["axis"])
            xk = np.asarray(tr["true_position"][k]) + R[k].T @ np.asarray(tr["parameters"]["displacement"])
            traj = C.RotvecTrajectory.from_dict(tr["trajectory"])
            f = traj.specific_force(case.recording.time, xk)
            np.testing.assert_allclose(case.recording.acc[:, k, i], f @ R[k][i], atol=1e-10)
        if eff == "gyro_nonlinearity":
            # the axis gains k2·ω_i² on the rate the twin (no effect, same motion) reads
            i = "xyz".index(tr["axis"])
            w = twin.recording.gyro[:, k, i]
            np.testing.assert_allclose(case.recording.gyro[:, k, i] - w, tr["parameters"]["k2"] * w * w,
                                       rtol=1e-9, atol=1e-15)
            assert 4e-5 <= abs(tr["parameters"]["k2"]) <= 2e-4
        if eff == "saturation":
            lim = tr["parameters"]["limit"]
            assert np.abs(case.recording.acc[:, k]).max() <= lim + 1e-12
            assert 0 < tr["parameters"]["clipped_fraction"] < 0.2


def test_noise_levels_and_recording_contract(tmp_path):
    from accel_bayes.data.io import read_recording, read_truth
    from accel_bayes.data.validation import validate_recording

    case = C.make_case("mimu8", "noise_level", seed=3, T=2000)
    twin = C.make_case("mimu8", "none", seed=3, T=2000)
    rec, tr = case.recording, case.truth
    validate_recording(rec)
    k = tr["imu"]
    s = tr["settings"]
    # Noise = twin noise × factor on IMU k's accelerometer, exactly.
    e_case = rec.acc - case.clean_acc
    e_twin = twin.recording.acc - twin.clean_acc
    np.testing.assert_allclose(e_case[:, k], tr["magnitude"] * e_twin[:, k], atol=1e-12)
    # The stated noise is the base std, and the empirical std agrees with it (2000×3 draws:
    # relative standard error 0.9 %, tolerance 5 %).
    np.testing.assert_allclose(rec.acc_noise_std, s["sigma_a"])
    assert abs(e_twin.std() / s["sigma_a"] - 1) < 0.05
    assert abs((twin.recording.gyro - twin.clean_gyro).std() / s["sigma_g"] - 1) < 0.05
    assert s["T"] == 2000 and 100 <= s["rate"] <= 250 and 0.01 <= s["sigma_a"] <= 0.04
    assert 250 * C.DEG * 0.99 <= s["omega_rms_achieved"] <= 600 * C.DEG * 1.01
    # Nothing of the truth in the recording; the sidecar round-trips.
    text = " ".join([rec.description, rec.source, str(rec.attrs)])
    assert "noise_level" not in text and rec.acc_clipped is None
    np.testing.assert_array_equal(rec.nominal_position, C.board("mimu8").positions)
    p = C.save_case(case, tmp_path / "case.nc")
    back = read_recording(p)
    np.testing.assert_array_equal(back.acc, rec.acc)
    t2 = read_truth(p)
    assert t2["effect"] == "noise_level" and t2["imu"] == k
    np.testing.assert_allclose(t2["true_relative_position"][0], [0, 0, 0])
    d = np.linalg.norm(np.asarray(t2["true_position"]) - rec.nominal_position, axis=1)
    assert np.all((d >= 1e-4 - 1e-12) & (d <= 3e-4 + 1e-12))


def test_agrees_with_package_model_conventions():
    """Cross-check only (not used to generate anything): the package's [C21] eq. 4 model, fed the
    ω, ω̇ and s of this trajectory, must give the same noise-free outputs.  A failure here means
    the two disagree on a frame convention, which would make the benchmark unfair either way."""
    torch = pytest.importorskip("torch")
    from accel_bayes.physics.models import imu_outputs

    rng = np.random.default_rng(9)
    t = np.arange(300) / 200.0
    tr = C.RotvecTrajectory.random(rng, t, omega_rms=400 * C.DEG)
    b = C.board("irregular6")
    acc, gyro = C.sensor_outputs(tr, t, b.rotations, np.repeat(b.positions[:, None], 3, 1))
    k = tr.kinematics(t)
    s = np.einsum("tji,tj->ti", k["R"], k["pdd"] - C.G_WORLD)
    T = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    a_pkg, g_pkg = imu_outputs(T(b.positions), T(b.orientations), T(tr.omega_body(t)), T(tr.omega_dot_body(t)), T(s))
    np.testing.assert_allclose(a_pkg.numpy(), acc, atol=1e-9)
    np.testing.assert_allclose(g_pkg.numpy(), gyro, atol=1e-12)


# ---------------------------------------------------------------------------- resumable benchmark

def _fake_runner(calls):
    """A stand-in for mismatch_proof.run_case: a deterministic, scored-looking row per case and a
    record of which cases were run (no data generated, no detector)."""
    def run_case(case_id, board, effect, seed, settings, twin, detect_kwargs, save_dir=None, generate_only=False):
        calls.append(case_id)
        clean = effect == "none"
        imu = 1 + seed % 3
        return {"case": case_id, "board": board, "effect_true": effect, "seed": seed, "imu_true": imu,
                "axis_true": None if clean or effect not in C.AXIS_EFFECTS else "x", "T": 100, "K": 8,
                "lambda_oracle": 0.0 if clean else 1e4, "seconds": 1.0, "mismatch_detected": not clean,
                "top_effect": "none" if clean else effect, "top_imu": None if clean else imu,
                "top_axis": None if clean else "x", "top_axis_scored": None if clean else "x",
                "threshold": 20.0, "chi2_before": 1.2, "chi2_after": 1.01,
                "pos_err_before_um": 30.0, "pos_err_after_um": 10.0 if clean else 12.0}
    return run_case


def test_proof_resumes_from_its_csv(tmp_path, monkeypatch, capsys):
    from experiments import mismatch_proof as mp

    calls = []
    monkeypatch.setattr(mp, "run_case", _fake_runner(calls))
    out = tmp_path / "bench"
    base = ["--workers", "0", "--no-twin", "--boards", "mimu8", "--effects", "acc_bias", "gyro_bias",
            "--clean", "2", "--out", str(out)]
    # a bounded first run: 3 of the 6 cases, interleaved across effects and clean sets
    mp.main(base + ["--per-effect", "2", "--max-cases", "3"])
    assert len(calls) == 3 and len({c.split("-")[0] for c in calls}) == 3
    rows = mp.read_rows(out / "cases.csv")
    assert [r["case"] for r in rows] == calls
    # rerun with the same options: only the missing cases run
    calls.clear()
    mp.main(base + ["--per-effect", "2"])
    assert sorted(calls) == sorted({"acc_bias-000", "acc_bias-001", "gyro_bias-000", "gyro_bias-001",
                                    "none-000", "none-001"} - set(r["case"] for r in rows))
    assert len(mp.read_rows(out / "cases.csv")) == 6
    # nothing left: a third run runs nothing and still summarises every row
    calls.clear()
    rc = mp.main(base + ["--per-effect", "2"])
    assert calls == [] and rc == 0
    text = capsys.readouterr().out
    assert "required cases done: 6/50" in text and "INCOMPLETE" in text
    summ = __import__("json").loads((out / "summary.json").read_text())
    assert summ["progress"]["per_effect"] == {"acc_bias": 2, "gyro_bias": 2} and summ["progress"]["clean"] == 2
    assert summ["right_effect"][1:] == [4, 4] and summ["clean_quiet"][1:] == [2, 2]
    # more cases per effect extend the same benchmark
    mp.main(base + ["--per-effect", "3"])
    assert sorted(calls) == ["acc_bias-002", "gyro_bias-002"]
    # other options with the same directory are refused
    with pytest.raises(SystemExit, match="other options"):
        mp.main(base + ["--per-effect", "2", "--seed", "7"])


def test_proof_retries_crashed_cases_only_when_asked(tmp_path, monkeypatch):
    from experiments import mismatch_proof as mp

    calls, every = [], []
    good = _fake_runner(calls)

    def flaky(case_id, **kw):
        row = good(case_id, **kw)
        every.append(case_id)
        if case_id == "acc_bias-000" and every.count(case_id) == 1:  # crashes the first time only
            return {k: row[k] for k in ("case", "board", "effect_true", "seed", "imu_true", "axis_true")} | \
                {"error": "RuntimeError: boom"}
        return row

    monkeypatch.setattr(mp, "run_case", flaky)
    args = ["--workers", "0", "--no-twin", "--boards", "mimu8", "--effects", "acc_bias", "--per-effect", "1",
            "--clean", "1", "--out", str(tmp_path)]
    assert mp.main(args) == 1  # the crash counts as a failed case
    calls.clear()
    mp.main(args)
    assert calls == []
    mp.main(args + ["--retry-errors"])
    assert calls == ["acc_bias-000"]
    rows = mp.read_rows(tmp_path / "cases.csv")
    assert len(rows) == 2 and not any("error" in r for r in rows)


def test_proof_store_gains_baseline_twins_and_a_figure(tmp_path, monkeypatch):
    """A store run without twins may be resumed with --twin-baseline: the stored effect rows get
    their clean-twin reference filled in (no detector result changes), options.json records the
    new mode, and the summary figure is written."""
    import types

    from experiments import mismatch_proof as mp

    calls = []
    monkeypatch.setattr(mp, "run_case", _fake_runner(calls))
    twins = []
    monkeypatch.setattr(mp, "make_case", lambda board, effect, seed, **kw: types.SimpleNamespace(
        truth={"true_relative_position": np.zeros((8, 3))}, recording=types.SimpleNamespace(reference_imu=0)))
    monkeypatch.setattr(mp, "twin_baseline_error", lambda clean, ref, true_rel: twins.append(ref) or 11.0)
    out = tmp_path / "bench"
    base = ["--workers", "0", "--boards", "mimu8", "--effects", "acc_bias", "--per-effect", "2", "--clean", "1",
            "--out", str(out)]
    mp.main(base + ["--no-twin"])
    assert len(calls) == 3 and twins == []
    with pytest.raises(SystemExit, match="other options"):  # a full-detect twin would change the benchmark
        mp.main(base + ["--twin"])
    mp.main(base + ["--twin-baseline"])
    rows = mp.read_rows(out / "cases.csv")
    assert len(twins) == 2 and len(calls) == 3  # both effect rows filled, no case rerun
    assert [r["pos_err_clean_um"] for r in rows if r["effect_true"] != "none"] == [11.0, 11.0]
    assert __import__("json").loads((out / "options.json").read_text())["twin"] == "baseline"
    assert (out / "summary.png").stat().st_size > 10_000


def test_multi_case_hides_linear_gyro_errors_and_one_new_effect():
    # make_multi_case (issue #11 item 6): deterministic per seed; the clean twin shares motion,
    # geometry, linear gyro errors and noise; each new effect is where and what the truth says,
    # checked against the exact kinematics at the recorded sampling instants.
    T = 300
    a = C.make_multi_case(4, "sampling_jitter", T=T)
    b = C.make_multi_case(4, "sampling_jitter", T=T)
    np.testing.assert_array_equal(a.recording.acc, b.recording.acc)
    np.testing.assert_array_equal(a.recording.gyro, b.recording.gyro)
    assert a.recording.time[1] - a.recording.time[0] == pytest.approx(1 / 62.5)
    assert not np.array_equal(a.recording.gyro, C.make_multi_case(5, "sampling_jitter", T=T).recording.gyro)

    twin = C.make_multi_case(4, "none", T=T, noise=False)
    tr0 = twin.truth
    R = C.board("mimu8").rotations
    E, bias = np.asarray(tr0["gyro_linear"]["matrix"]), np.asarray(tr0["gyro_linear"]["bias"])
    c = np.abs(E).max(axis=(1, 2))
    assert (c >= 0.015).all() and (c <= 0.027).all()
    assert (np.abs(bias) >= 0.05 * C.DEG - 1e-15).all() and (np.abs(bias) <= 0.5 * C.DEG + 1e-15).all()
    traj = C.RotvecTrajectory.from_dict(tr0["trajectory"])
    t = twin.recording.time
    w = traj.omega_body(t)  # (T, 3) array frame
    # every IMU's gyro reads (I + E_k) R_k ω + b_k
    expect = np.einsum("kij,kjl,tl->tki", np.eye(3)[None] + E, R, w) + bias[None]
    np.testing.assert_allclose(twin.recording.gyro, expect, atol=1e-12)
    assert 600 <= tr0["settings"]["omega_rms_achieved"] / C.DEG <= 1200
    assert tr0["settings"]["omega_peak_component"] <= 0.95 * 2000 * C.DEG + 1e-9

    for eff in C.MULTI_EFFECTS:
        case = C.make_multi_case(4, eff, T=T, noise=False)
        tr = case.truth
        k = tr["imu"]
        assert k is not None and k != 0
        np.testing.assert_array_equal(tr["gyro_linear"]["matrix"], E)  # the twin's linear errors
        others = [j for j in range(8) if j != k]
        np.testing.assert_array_equal(case.recording.acc[:, others], twin.recording.acc[:, others])
        np.testing.assert_array_equal(case.recording.gyro[:, others], twin.recording.gyro[:, others])
        if eff in ("sampling_jitter", "timing_wander"):
            d = np.asarray(tr["parameters"]["instants"])
            wk = traj.omega_body(t + d)  # the exact rate at the IMU's own instants
            np.testing.assert_allclose(case.recording.gyro[:, k], wk @ R[k].T @ (np.eye(3) + E[k]).T + bias[k],
                                       atol=1e-12)
            if eff == "sampling_jitter":
                w_ = tr["magnitude"]
                assert 1e-4 <= w_ <= 1e-3 and np.abs(d).max() <= w_ / 2 and np.abs(d).max() > 0.4 * w_
                f = traj.specific_force(t + d, np.asarray(tr["true_position"][k]))
                np.testing.assert_allclose(case.recording.acc[:, k], f @ R[k].T, atol=1e-10)
            else:
                np.testing.assert_array_equal(case.recording.acc[:, k], twin.recording.acc[:, k])
                w_, rho = tr["magnitude"], tr["parameters"]["correlation"]
                assert 1.1e-3 <= w_ <= 1.35e-3 and 0.70 <= rho <= 0.87
                # AR(1): the innovations δ_j − ρ δ_{j−1} have std √(1 − ρ²) w/√12
                innov = d[1:] - rho * d[:-1]
                assert np.std(innov) == pytest.approx(math.sqrt(1 - rho * rho) * w_ / math.sqrt(12), rel=0.2)
                assert np.std(d) == pytest.approx(w_ / math.sqrt(12), rel=0.5)
        else:  # gyro_nonlinearity: axis i gains k2·ω_i², ω_i the true rate of that axis
            i = "xyz".index(tr["axis"])
            wi = (w @ R[k].T)[:, i]
            dg = case.recording.gyro[:, k] - twin.recording.gyro[:, k]
            np.testing.assert_allclose(dg[:, i], tr["magnitude"] * wi * wi, rtol=1e-9, atol=1e-15)
            assert np.abs(np.delete(dg, i, axis=1)).max() == 0
            m = abs(tr["magnitude"]) * (wi * wi).max() / tr["settings"]["sigma_g"]
            assert 2.0 <= m <= 6.0
            np.testing.assert_array_equal(case.recording.acc, twin.recording.acc)
    # the control: the same new effect without linear gyro errors
    ctl = C.make_multi_case(4, "gyro_nonlinearity", T=T, noise=False, gyro_linear=False)
    half = C.make_multi_case(4, "none", T=T, noise=False, gyro_linear=0.5)
    np.testing.assert_allclose(half.truth["gyro_linear"]["matrix"], 0.5 * E, rtol=1e-15)
    k = ctl.truth["imu"]
    np.testing.assert_allclose(ctl.recording.gyro[:, 0], w @ R[0].T, atol=1e-12)
    assert ctl.truth["imu"] == C.make_multi_case(4, "gyro_nonlinearity", T=T).truth["imu"] == k

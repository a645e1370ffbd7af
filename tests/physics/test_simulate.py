"""The simulator against independent checks: finite differences of world positions, explicit
rotations, noise statistics, exact clipping, determinism, the DESIGN §7.0 worked example, file
round trips and the CLI."""
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from accel_bayes.physics import geometry as g
from accel_bayes.physics import trajectories as M
from accel_bayes.physics.arrays import SensorArray, mimu4444_8, mimu4444_32, s16_plate
from accel_bayes.errors import UserError
from accel_bayes.physics.models import specific_force, to_array_frame
from accel_bayes.simulate import simulate

F64 = torch.float64
DEG = math.pi / 180
YAW90 = (math.sqrt(0.5), 0.0, 0.0, -math.sqrt(0.5))  # DESIGN §7.0: IMU yawed +90° on the board


def _yawed_array() -> SensorArray:
    """Four IMUs on a square; IMU 2 yawed +90° (its x axis along the array's +y)."""
    pos = torch.tensor([[0.0, 0.0, 0.0], [0.02, 0.0, 0.0], [0.0, 0.02, 0.0], [0.02, 0.02, 0.001]], dtype=F64)
    q = torch.tensor([[1.0, 0, 0, 0], [1.0, 0, 0, 0], YAW90, [1.0, 0, 0, 0]], dtype=F64)
    K = 4
    return SensorArray(positions=pos, orientations=q, has_acc=torch.ones(K, dtype=torch.bool),
                       has_gyro=torch.ones(K, dtype=torch.bool), acc_noise_std=torch.full((K,), 0.05, dtype=F64),
                       gyro_noise_std=torch.full((K,), 0.01, dtype=F64), acc_range=16 * 9.80665,
                       gyro_range=2000 * DEG, name="yawed")


def test_simulated_accelerations_match_finite_differences_of_the_true_positions():
    """MUST-SHOW at the simulator level: each IMU's noise-free output, rotated back to the
    array frame and then to the world, plus gravity, equals the second finite difference of the
    world position of that IMU's true position."""
    arr = mimu4444_8()
    res = simulate(arr, "smooth", T=200, rate=100.0, seed=3, position_error_std=5e-4,
                   orientation_error_std=0.02, clip=False, motion_kwargs={"omega_rms": 600 * DEG})
    tr = res.motion
    f_arr = to_array_frame(res.acc_clean, res.true_orientations)  # (T, K, 3)
    R = g.quat_to_matrix(tr.attitude)
    a_model = (R.unsqueeze(1) @ f_arr.unsqueeze(-1)).squeeze(-1) + torch.tensor(M.G_WORLD, dtype=F64)
    h = 1e-3
    P = lambda dt: M.point_trajectory(tr.trajectory, res.true_positions, tr.time + dt)  # noqa: E731
    a_fd = (-P(2 * h) + 16 * P(h) - 30 * P(0.0) + 16 * P(-h) - P(-2 * h)) / (12 * h * h)
    err = float((a_fd - a_model).abs().max())
    assert err < 1e-6 * float(a_model.abs().max()), err


def test_gyro_outputs_are_the_rotated_angular_velocity():
    res = simulate(mimu4444_32(), "iid", T=50, seed=2, orientation_error_std=0.05)
    R = g.quat_to_matrix(res.true_orientations)  # (K, 3, 3)
    expect = torch.einsum("kij,tj->tki", R, res.motion.omega)
    assert torch.allclose(res.gyro_clean, expect, atol=1e-12)
    # and R(q) is the DESIGN §7.0 matrix written out
    w, x, y, z = res.true_orientations[5].tolist()
    R5 = torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                       [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                       [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=F64)
    assert torch.allclose(res.gyro_clean[:, 5], res.motion.omega @ R5.T, atol=1e-12)


def test_noise_std_matches_the_stated_level_per_imu():
    arr = mimu4444_32()
    K = arr.K
    acc_sd = torch.linspace(0.02, 0.2, K, dtype=F64)
    gyro_sd = torch.linspace(0.001, 0.01, K, dtype=F64)
    res = simulate(arr, "smooth", T=2000, seed=5, acc_noise_std=acc_sd, gyro_noise_std=gyro_sd)
    rec = res.recording
    assert not rec.acc_clipped.any() and not rec.gyro_clipped.any()
    ea = torch.as_tensor(rec.acc) - res.acc_clean
    eg = torch.as_tensor(rec.gyro) - res.gyro_clean
    # per IMU: 6000 draws, the sample std has ≈ 0.9 % relative error; allow 4 %
    assert torch.allclose(ea.reshape(-1, K, 3).permute(1, 0, 2).reshape(K, -1).std(1), acc_sd, rtol=0.04)
    assert torch.allclose(eg.permute(1, 0, 2).reshape(K, -1).std(1), gyro_sd, rtol=0.04)
    assert float((ea / acc_sd[:, None]).mean().abs()) < 4 / math.sqrt(ea.numel())
    np.testing.assert_array_equal(rec.acc_noise_std, acc_sd.numpy())
    np.testing.assert_array_equal(rec.gyro_noise_std, gyro_sd.numpy())


def test_clipping_is_exact_and_flagged():
    arr = mimu4444_8().with_(acc_range=12.0, gyro_range=3.0)
    clipped = simulate(arr, "smooth", T=300, seed=8, motion_kwargs={"omega_rms": 300 * DEG}).recording
    raw = simulate(arr, "smooth", T=300, seed=8, motion_kwargs={"omega_rms": 300 * DEG}, clip=False).recording
    assert raw.acc_clipped is None and raw.gyro_clipped is None
    for y, y0, lim, flags in ((clipped.acc, raw.acc, 12.0, clipped.acc_clipped),
                              (clipped.gyro, raw.gyro, 3.0, clipped.gyro_clipped)):
        over = np.abs(y0) >= lim
        assert 0.01 < over.any(-1).mean() < 0.9  # the test exercises both cases
        np.testing.assert_array_equal(flags, over.any(-1))
        np.testing.assert_array_equal(y[over], np.sign(y0[over]) * lim)  # exactly at the range
        np.testing.assert_array_equal(y[~over], y0[~over])  # untouched elsewhere
        assert np.abs(y).max() == lim


def test_same_seed_same_recording_different_seed_different():
    a = simulate(s16_plate(), "table", T=120, seed=4).recording
    b = simulate(s16_plate(), "table", T=120, seed=4).recording
    c = simulate(s16_plate(), "table", T=120, seed=5).recording
    np.testing.assert_array_equal(a.acc, b.acc)
    np.testing.assert_array_equal(a.gyro, b.gyro)  # NaN rows compare equal
    assert not np.array_equal(a.acc, c.acc)
    gen_a = simulate(s16_plate(), "iid", T=20, generator=torch.Generator().manual_seed(1)).recording
    gen_b = simulate(s16_plate(), "iid", T=20, generator=torch.Generator().manual_seed(1)).recording
    np.testing.assert_array_equal(gen_a.acc, gen_b.acc)


def test_true_geometry_draws_and_recording_contents():
    arr = mimu4444_32()
    res = simulate(arr, "iid", T=10, seed=6, position_error_std=1e-3, orientation_error_std=0.01)
    d = res.true_positions - arr.positions
    assert torch.count_nonzero(d[arr.reference_imu]) == 0
    others = torch.cat((d[: arr.reference_imu], d[arr.reference_imu + 1:])).flatten()
    assert 0.75e-3 < float(others.std()) < 1.25e-3  # 93 draws of N(0, 1 mm²)
    ang = g.rotation_angle(res.true_orientations, arr.orientations)
    assert float(ang[arr.reference_imu]) == 0.0 and 0.005 < float(ang.mean()) < 0.03
    rec = res.recording
    # the recording holds the design, never the truth
    np.testing.assert_array_equal(rec.nominal_position, arr.positions.numpy())
    np.testing.assert_array_equal(rec.nominal_orientation, arr.orientations.numpy())
    assert rec.segment is None and rec.reference_imu == arr.reference_imu
    assert "true" not in json.dumps(rec.attrs)
    t = res.truth
    json.dumps(t)  # JSON-ready
    np.testing.assert_allclose(t["true_position"], res.true_positions.numpy(), rtol=0, atol=0)
    assert t["seed"] == 6 and t["settings"]["position_error_std"] == 1e-3 and t["motion"]["kind"] == "iid"
    assert len(t["motion"]["omega"]) == 10


def test_explicit_truth_and_missing_triads():
    arr = s16_plate()
    p = arr.positions + 0.001
    res = simulate(arr, "table", T=60, seed=1, true_positions=p, motion_kwargs={"rest_duration": 0.05})
    assert torch.equal(res.true_positions, p)
    rec = res.recording
    assert rec.segment is not None and set(rec.segment) == {"static", "dynamic"}
    # only IMU 0 of the [S16] plate carries a gyroscope: NaN elsewhere, no clip flags there
    assert np.isnan(rec.gyro[:, 1:]).all() and not np.isnan(rec.gyro[:, 0]).any()
    np.testing.assert_array_equal(rec.has_gyro, arr.has_gyro.numpy())
    assert not rec.gyro_clipped[:, 1:].any()


def test_time_offset_samples_one_imu_late():
    arr = mimu4444_8()
    rate = 100.0
    base = simulate(arr, "smooth", T=80, rate=rate, seed=12, clip=False)
    off = torch.zeros(arr.K, dtype=F64)
    off[3] = 1 / rate  # exactly one sample late: IMU 3 reads what it would read one sample later
    late = simulate(arr, "smooth", T=80, rate=rate, seed=12, clip=False, time_offsets=off)
    assert torch.allclose(late.acc_clean[:-1, 3], base.acc_clean[1:, 3], atol=1e-10)
    assert torch.allclose(late.gyro_clean[:-1, 3], base.gyro_clean[1:, 3], atol=1e-10)
    others = [k for k in range(arr.K) if k != 3]
    assert torch.equal(late.acc_clean[:, others], base.acc_clean[:, others])
    assert late.truth["settings"]["time_offsets"][3] == 0.01
    with pytest.raises(UserError):
        simulate(arr, "iid", T=10, time_offsets=off)


@pytest.mark.parametrize("kw", [
    {"position_error_std": -1.0},
    {"acc_noise_std": [0.1, 0.2]},
    {"true_positions": torch.zeros(3, 3)},
    {"motion": "spin"},
    {"motion_kwargs": {"nonsense": 1}},
])
def test_bad_options_raise_user_error(kw):
    kw = dict(kw)
    motion = kw.pop("motion", "smooth")
    with pytest.raises(UserError):
        simulate(mimu4444_8(), motion, T=10, **kw)


def test_design_worked_example_yawed_imu():
    """DESIGN §7.0: an IMU yawed +90° reads an array-frame (0, 1, 0) as (1, 0, 0); the
    recording's array-frame view recovers the simulator's specific force plus rotated-back noise."""
    arr = _yawed_array()
    zero = torch.zeros(1, 3, dtype=F64)
    from accel_bayes.physics.models import imu_outputs

    acc, _ = imu_outputs(arr.positions, arr.orientations, zero, zero, torch.tensor([[0.0, 1.0, 0.0]], dtype=F64))
    assert torch.allclose(acc[0, 2], torch.tensor([1.0, 0.0, 0.0], dtype=F64), atol=1e-15)
    assert torch.allclose(acc[0, 0], torch.tensor([0.0, 1.0, 0.0], dtype=F64), atol=1e-15)

    res = simulate(arr, "smooth", T=100, seed=2, position_error_std=2e-4, clip=False)
    tr = res.motion
    f_true = specific_force(res.true_positions, tr.omega, tr.omega_dot, tr.s)  # array frame
    noise_sensor = torch.as_tensor(res.recording.acc) - res.acc_clean
    expect = f_true + to_array_frame(noise_sensor, arr.orientations)
    got = res.recording.acc_tensor(frame="array")
    assert float((got - expect).abs().max()) < 1e-12
    # the yawed IMU's sensor x axis carries the array y component
    assert torch.allclose(torch.as_tensor(res.recording.acc)[:, 2, 0], got[:, 2, 1], atol=1e-12)


def test_worked_example_survives_a_file_round_trip(tmp_path):
    io = pytest.importorskip("accel_bayes.data.io")
    arr = _yawed_array()
    res = simulate(arr, "smooth", T=100, seed=2, position_error_std=2e-4, clip=False)
    path = tmp_path / "yaw.nc"
    io.write_recording(res.recording, path)
    back = io.read_recording(path)
    tr = res.motion
    f_true = specific_force(res.true_positions, tr.omega, tr.omega_dot, tr.s)
    noise_sensor = torch.as_tensor(res.recording.acc) - res.acc_clean
    expect = f_true + to_array_frame(noise_sensor, torch.as_tensor(back.nominal_orientation))
    assert float((back.acc_tensor(frame="array") - expect).abs().max()) < 1e-12


def _assert_same_recording(a, b):
    for name in ("time", "acc", "gyro", "nominal_position", "nominal_orientation", "acc_noise_std",
                 "gyro_noise_std", "acc_clipped", "gyro_clipped", "segment"):
        x, y = getattr(a, name), getattr(b, name)
        if x is None:
            assert y is None, name
            continue
        x, y = np.asarray(x), np.asarray(y)
        assert x.shape == y.shape, name
        if x.dtype.kind == "f":
            assert x.dtype == y.dtype, name
            # bit-exact, NaN included
            np.testing.assert_array_equal(x.view(np.uint64), y.view(np.uint64), err_msg=name)
        else:
            np.testing.assert_array_equal(x.astype(str) if x.dtype.kind in "US" else x,
                                          y.astype(str) if y.dtype.kind in "US" else y, err_msg=name)
    for name in ("reference_imu", "acc_range", "gyro_range", "description", "source"):
        assert getattr(a, name) == getattr(b, name), name


@pytest.mark.parametrize("preset_fn,motion,kw", [
    (s16_plate, "table", {"rest_duration": 0.1}),
    (mimu4444_8, "iid", None),
])
def test_written_recording_reads_back_bit_exact(tmp_path, preset_fn, motion, kw):
    io = pytest.importorskip("accel_bayes.data.io")
    res = simulate(preset_fn(), motion, T=150, seed=9, motion_kwargs=kw)
    path = tmp_path / "sim.nc"
    io.write_recording(res.recording, path)
    io.write_truth(path, res.truth)
    back = io.read_recording(path)
    _assert_same_recording(res.recording, back)
    back_truth = io.read_truth(path)
    written = json.loads(json.dumps(res.truth))
    assert {k: back_truth[k] for k in written} == written  # io may add keys (recording_sha256)
    assert Path(path).with_suffix(".truth.json").is_file()


# ------------------------------------------------------------------------------- CLI

def _cli(capsys, *argv):
    """Run ``accel-bayes`` in-process (the same main() the console script calls)."""
    from accel_bayes.cli import main

    try:
        rc = main(list(argv))
    except SystemExit as exc:  # argparse usage errors
        rc = exc.code
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_cli_simulate_writes_recording_and_sidecar(tmp_path, capsys):
    io = pytest.importorskip("accel_bayes.data.io")
    out = tmp_path / "rec.nc"
    rc, stdout, stderr = _cli(capsys, "simulate", "--preset", "mimu8", "--motion", "table", "-T", "200",
                              "--rate", "125", "--seed", "1", "--orientation-error", "0.01", "-o", str(out))
    assert rc == 0, stderr
    side = tmp_path / "rec.truth.json"
    assert out.is_file() and side.is_file()
    assert str(side) in stdout and "mimu8" in stdout
    rec = io.read_recording(out)
    assert rec.T == 200 and rec.K == 8
    truth = io.read_truth(out)
    assert truth["seed"] == 1 and truth["settings"]["orientation_error_std"] == 0.01
    # same options, same numbers as the library call
    lib = simulate(mimu4444_8(), "table", T=200, rate=125.0, seed=1, orientation_error_std=0.01).recording
    np.testing.assert_array_equal(rec.acc, lib.acc)
    # refusing to overwrite is a one-line user error; --overwrite replaces both files
    rc, _, stderr = _cli(capsys, "simulate", "--preset", "mimu8", "-o", str(out))
    assert rc == 2 and "--overwrite" in stderr and len(stderr.strip().splitlines()) == 1
    rc, _, stderr = _cli(capsys, "simulate", "--preset", "s16plate", "-T", "50", "-o", str(out), "--overwrite")
    assert rc == 0, stderr
    assert io.read_recording(out).K == 5 and io.read_truth(out)["array"] == "s16plate"


@pytest.mark.parametrize("argv", [
    ["--preset", "mimu99"],
    ["--motion", "spin"],
    ["-T", "0"],
    ["--rate", "-5"],
    ["--acc-noise", "-1"],
    ["--motion", "iid", "--omega-rms", "5"],
    ["--rate", "4"],  # smooth motion band above Nyquist
])
def test_cli_bad_options_exit_2_one_line(tmp_path, capsys, argv):
    rc, _, stderr = _cli(capsys, "simulate", *argv, "-o", str(tmp_path / "x.nc"))
    assert rc == 2, (rc, stderr)
    assert len(stderr.strip().splitlines()) == 1 and "Traceback" not in stderr
    assert not (tmp_path / "x.nc").exists()

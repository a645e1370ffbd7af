"""CSV importer (accel_bayes.data.csv_import) and ``accel-bayes import-csv``.

* Round trips: a simulated recording written as ASL folders / one wide CSV by the helpers here
  (plain text formatting, independent of the importer) and imported again is the same recording.
* Time base: IMUs stamped separately are matched to the reference's stamps; the offsets kept in
  ``imu_time_offset`` are the ones the helper wrote, and stamps near 1.4e18 ns (EuRoC's epoch
  stamps, where a float64 is 256 ns coarse) are subtracted exactly.
* Noise from rests of a hand-made static recording with a known σ; clipping from stated ranges.
* Every bad CSV refused with one line naming file, line and column; nothing written.
"""
import math
import re

import numpy as np
import pytest
import torch
import xarray as xr

from accel_bayes.physics.arrays import G0, mimu4444_8, s16_plate
from accel_bayes.cli import main
from accel_bayes.data.csv_import import import_csv, read_array_description, write_imported
from accel_bayes.errors import UserError
from accel_bayes.physics.geometry import quat_to_matrix
from accel_bayes.data.io import read_recording
from accel_bayes.simulate import simulate

ASL_HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
              "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
FIELDS = ("time", "acc", "gyro", "nominal_position", "acc_noise_std", "gyro_noise_std", "acc_clipped",
          "gyro_clipped", "reference_imu", "acc_range", "gyro_range")


# ------------------------------------------------------------------------------ writers (test helpers)
def write_asl(rec, folder, stamps_ns=None, t0_ns=0):
    """``folder/imu<k>/data.csv`` in the ASL layout; ``stamps_ns`` (K, T) gives each IMU its own
    stamps (default ``t0_ns`` + round(time·1e9)).  IMUs without a gyro get no w_RS_S columns."""
    folder.mkdir(parents=True, exist_ok=True)
    base = t0_ns + np.round(np.asarray(rec.time) * 1e9).astype(np.int64)
    for k in range(rec.K):
        own = base if stamps_ns is None else stamps_ns[k]
        d = folder / f"imu{k}"
        d.mkdir(exist_ok=True)
        has_g = rec.gyro is not None and not np.isnan(rec.gyro[:, k]).all()
        header = ASL_HEADER if has_g else ASL_HEADER.split(",")[0] + "," + ",".join(ASL_HEADER.split(",")[4:])
        rows = [header]
        for t in range(rec.T):
            vals = ([repr(float(v)) for v in rec.gyro[t, k]] if has_g else []) + [repr(float(v)) for v in rec.acc[t, k]]
            rows.append(",".join([str(int(own[t]))] + vals))
        (d / "data.csv").write_text("\n".join(rows) + "\n")
    return folder


def write_toml(rec, path, *, noise=True, extra_top="", extra_imu=None, labels=None, orientation_matrix=False):
    """An array description of ``rec`` (stated noise, ranges, reference IMU)."""
    labels = labels or [f"imu{k}" for k in range(rec.K)]
    lines = [f"reference_imu = {int(rec.reference_imu)}"]
    if rec.acc_range is not None:
        lines.append(f"acc_range = {rec.acc_range!r}")
    if rec.gyro_range is not None:
        lines.append(f"gyro_range = {rec.gyro_range!r}")
    lines.append(extra_top)
    has_g = rec.has_gyro
    for k in range(rec.K):
        lines += ["[[imu]]", f'label = "{labels[k]}"',
                  f"position = {[float(v) for v in rec.nominal_position[k]]!r}"]
        if orientation_matrix:
            R = quat_to_matrix(torch.as_tensor(rec.nominal_orientation[k])).numpy()
            lines.append(f"orientation_matrix = {[[float(v) for v in r] for r in R]!r}")
        else:
            lines.append(f"orientation = {[float(v) for v in rec.nominal_orientation[k]]!r}")
        lines.append('sensors = ["acc", "gyro"]' if has_g[k] else 'sensors = ["acc"]')
        if noise:
            lines.append(f"acc_noise_std = {float(rec.acc_noise_std[k])!r}")
            if np.isfinite(rec.gyro_noise_std[k]):
                lines.append(f"gyro_noise_std = {float(rec.gyro_noise_std[k])!r}")
        if extra_imu:
            lines.append(extra_imu(k))
    path.write_text("\n".join(lines) + "\n")
    return path


def assert_same(a, b, quat_atol=1e-15):
    for name in FIELDS:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y), err_msg=name)
        else:
            assert x == y, name
    # A unit quaternion read from text is renormalised: equal to the last bit or one ulp off.
    np.testing.assert_allclose(b.nominal_orientation, a.nominal_orientation, rtol=0, atol=quat_atol)


@pytest.fixture(scope="module")
def sim():
    # MIMU8: bottom IMUs rotated (non-trivial quaternions), gyros on every IMU, stated ranges.
    return simulate(mimu4444_8(), "smooth", T=300, rate=100.0, seed=3).recording


# ------------------------------------------------------------------------------ round trips
def test_asl_round_trip_is_identical(sim, tmp_path):
    write_asl(sim, tmp_path / "asl")
    toml = write_toml(sim, tmp_path / "array.toml")
    res = import_csv(tmp_path / "asl", toml, noise="stated")
    assert res.imu_time_offset is None  # every IMU stamped at the same instants
    assert_same(sim, res.recording)
    assert res.recording.attrs["imu_labels"] == [f"imu{k}" for k in range(sim.K)]
    # Through the command and the file as well.
    out = tmp_path / "rec.nc"
    assert main(["import-csv", str(tmp_path / "asl"), "--array", str(toml), "-o", str(out), "--noise", "stated"]) == 0
    back = read_recording(out)
    assert_same(sim, back)
    assert back.segment is None and "csv_import" in back.source


def test_orientation_matrix_and_no_gyro_imus(tmp_path):
    # s16plate: only IMU 0 has a gyro; the description gives orientations as matrices.
    rec = simulate(s16_plate(), "smooth", T=120, rate=100.0, seed=5).recording
    write_asl(rec, tmp_path / "asl")
    toml = write_toml(rec, tmp_path / "array.toml", orientation_matrix=True)
    got = import_csv(tmp_path / "asl", toml, noise="stated").recording
    assert_same(rec, got, quat_atol=1e-12)
    assert got.has_gyro.tolist() == [True, False, False, False, False]


def test_wide_csv_with_column_map_and_declared_units(sim, tmp_path):
    # Columns named freely (map in the description), time in seconds declared in [csv.units],
    # gyro in deg/s declared in the header, acc in g declared in [csv.units].
    K, T = sim.K, sim.T
    header = ["t"]
    cols = []
    for k in range(K):
        header += [f"a{k}{a}" for a in "xyz"] + [f"g{k}{a} [deg s^-1]" for a in "xyz"]
    header.append("temperature")
    lines = [",".join(header)]
    for t in range(T):
        row = [f"{t / 100:.2f}"]  # decimal seconds → exact integer ns (10 ms steps)
        for k in range(K):
            row += [repr(float(v)) for v in sim.acc[t, k] / G0] + [repr(float(v)) for v in np.degrees(sim.gyro[t, k])]
        row.append("21.5")
        lines.append(",".join(row))
    f = tmp_path / "wide.csv"
    f.write_text("\n".join(lines) + "\n")
    toml = write_toml(sim, tmp_path / "array.toml",
                      extra_top='[csv]\ntime = "t"\nunits = {time = "s", acc = "g"}\nignore = ["temperature"]\n',
                      extra_imu=lambda k: f'columns = {{acc = ["a{k}x", "a{k}y", "a{k}z"], gyro = ["g{k}x", "g{k}y", "g{k}z"]}}')
    got = import_csv(f, toml, noise="stated").recording
    np.testing.assert_array_equal(got.time, sim.time)
    np.testing.assert_allclose(got.acc, sim.acc, rtol=4e-16, atol=0)
    np.testing.assert_allclose(got.gyro, sim.gyro, rtol=4e-16, atol=0)
    np.testing.assert_array_equal(got.nominal_position, sim.nominal_position)


def test_separate_stamps_time_base_and_offsets(sim, tmp_path):
    rng = np.random.default_rng(11)
    K, T = sim.K, sim.T
    t0 = 1_403_636_579_758_555_392  # an EuRoC stamp: float64 resolves it only to 256 ns
    base = t0 + np.arange(T, dtype=np.int64) * 10_000_000 + rng.integers(-3, 4, T)  # ref jitter of a few ns
    offs = np.zeros((K, T), dtype=np.int64)
    offs[2] = 300_000  # IMU 2 stamped 0.3 ms late
    offs[5] = rng.integers(-100_000, 100_001, T)  # IMU 5 jitters ±0.1 ms
    stamps = base[None, :] + offs
    stamps[4] = stamps[4] + 20_000_000  # IMU 4 starts two samples late (and ends two late)
    write_asl(sim, tmp_path / "asl", stamps_ns=stamps)
    toml = write_toml(sim, tmp_path / "array.toml")
    res = import_csv(tmp_path / "asl", toml, noise="stated")
    rec = res.recording
    # The reference's first two stamps have no IMU 4 partner: dropped at the start; at the end
    # IMU 4's last two samples have no reference stamp (unused).
    assert rec.T == T - 2
    expected_time = np.array([(int(b) - int(base[2])) / 1e9 for b in base[2:]])  # Python ints: exact
    np.testing.assert_array_equal(rec.time, expected_time)
    exp_off = offs[:, 2:].T.astype(float) / 1e9
    # IMU 4's sample k−2 is matched to reference stamp k: the offset is the difference of two ref jitters.
    exp_off[:, 4] = (base[:-2] + 20_000_000 - base[2:]).astype(float) / 1e9
    np.testing.assert_array_equal(res.imu_time_offset, exp_off)
    np.testing.assert_array_equal(rec.acc[:, 4], sim.acc[:T - 2, 4])
    np.testing.assert_array_equal(rec.acc[:, 2], sim.acc[2:, 2])
    worst5 = np.abs(offs[5, 2:]).max() / 1e6
    assert any(f"IMU imu5: 300 samples read, 298 used, worst stamp mismatch {worst5:.6g} ms" in ln for ln in res.lines)
    assert any("dropped 2 reference stamps" in ln for ln in res.lines)
    out = write_imported(res, tmp_path / "rec.nc")
    with xr.open_dataset(out, engine="h5netcdf") as ds:
        assert ds["imu_time_offset"].dims == ("time", "imu") and ds["imu_time_offset"].attrs["units"] == "s"
        np.testing.assert_array_equal(ds["imu_time_offset"].values, exp_off)
    back = read_recording(out)  # the reader loads it back (format v1 optional variable)
    np.testing.assert_array_equal(back.acc, rec.acc)
    np.testing.assert_array_equal(back.imu_time_offset, exp_off)
    np.testing.assert_array_equal(back.select(np.arange(5, 9)).imu_time_offset, exp_off[5:9])


def test_stamps_beyond_tolerance_refused_with_numbers(sim, tmp_path):
    stamps = np.tile(np.round(sim.time * 1e9).astype(np.int64), (sim.K, 1))
    stamps[3, 150] += 3_000_000  # 3 ms off; default tolerance 2.5 ms (a quarter of 10 ms)
    write_asl(sim, tmp_path / "asl", stamps_ns=stamps)
    toml = write_toml(sim, tmp_path / "array.toml")
    with pytest.raises(UserError, match=r"imu3/data.csv: 1 of 300 stamps .* within 2.5 ms \(worst 3 ms"):
        import_csv(tmp_path / "asl", toml, noise="stated")
    # A stated tolerance that covers it accepts, and keeps the 3 ms in imu_time_offset.
    res = import_csv(tmp_path / "asl", toml, noise="stated", time_tolerance=0.004)
    assert res.imu_time_offset[150, 3] == 0.003 and np.count_nonzero(res.imu_time_offset) == 1


# ------------------------------------------------------------------------------ sensor.yaml, rests, clipping
def test_sensor_yaml_noise_density_and_random_walk(sim, tmp_path):
    write_asl(sim, tmp_path / "asl")
    for k in range(sim.K):
        (tmp_path / "asl" / f"imu{k}" / "sensor.yaml").write_text(
            "%YAML:1.0\nsensor_type: imu\nrate_hz: 100\n"
            f"gyroscope_noise_density: {1e-4 * (k + 1)!r}\ngyroscope_random_walk: 2.0e-5\n"
            "accelerometer_noise_density: 2.0e-3\naccelerometer_random_walk: 3.0e-3\n")
    toml = write_toml(sim, tmp_path / "array.toml", noise=False)
    rec = import_csv(tmp_path / "asl", toml, noise="stated").recording
    np.testing.assert_allclose(rec.acc_noise_std, 2.0e-3 * 10.0, rtol=1e-15)  # density · √(100 Hz)
    np.testing.assert_allclose(rec.gyro_noise_std, 1e-4 * np.arange(1, 9) * 10.0, rtol=1e-15)
    assert rec.attrs["acc_random_walk"] == [3.0e-3] * 8 and rec.attrs["gyro_random_walk"] == [2.0e-5] * 8


def _static_board(sigma=0.01, rate=100.0, seed=0):
    """Two 8 s rests in different orientations joined by 2 s of rotation; white noise σ."""
    rng = np.random.default_rng(seed)
    K, n_rest, n_move = 4, 800, 200
    g1, g2 = np.array([0.0, 0.0, G0]), np.array([0.0, G0, 0.0])
    tm = np.arange(n_move) / rate
    move_acc = np.stack([3 * np.sin(5 * tm), G0 * np.sin(np.pi / 2 * tm / tm[-1]), G0 * np.cos(np.pi / 2 * tm / tm[-1])], -1)
    move_gyro = np.stack([np.full(n_move, math.pi / 4), np.sin(7 * tm), np.cos(3 * tm)], -1)
    acc = np.concatenate([np.tile(g1, (n_rest, 1)), move_acc, np.tile(g2, (n_rest, 1))])
    gyro = np.concatenate([np.zeros((n_rest, 3)), move_gyro, np.zeros((n_rest, 3))])
    T = acc.shape[0]
    acc = np.repeat(acc[:, None], K, 1) + sigma * rng.standard_normal((T, K, 3))
    gyro = np.repeat(gyro[:, None], K, 1) + 1e-3 * rng.standard_normal((T, K, 3))
    from accel_bayes.data.recording import Recording

    pos = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]], dtype=float)
    return Recording(time=np.arange(T) / rate, acc=acc, gyro=gyro, nominal_position=pos,
                     acc_noise_std=np.full(K, 1.0), gyro_noise_std=np.full(K, 1.0))


def test_noise_from_rests_and_clipping_from_ranges(tmp_path):
    rec = _static_board()
    rec.acc[1000, 2, 0] = 20.0  # exactly at the stated range below → clipped
    rec.acc[1001, 2, 0] = -19.999  # inside
    write_asl(rec, tmp_path / "asl")
    toml = write_toml(rec, tmp_path / "array.toml", extra_top="acc_range = 20.0")
    res = import_csv(tmp_path / "asl", toml)  # stated σ = 1 m/s² is wrong on purpose
    got = res.recording
    np.testing.assert_allclose(got.acc_noise_std, 0.01, rtol=0.05)
    np.testing.assert_allclose(got.gyro_noise_std, 1e-3, rtol=0.05)
    assert "estimated from 2 static segments" in got.source
    assert set(np.unique(got.segment)) == {"static", "dynamic"}
    expected = np.zeros((rec.T, rec.K), dtype=bool)
    expected[1000, 2] = True
    np.testing.assert_array_equal(got.acc_clipped, expected)
    assert got.gyro_clipped is None and got.acc_range == 20.0


# ------------------------------------------------------------------------------ refusals
TOML2 = """reference_imu = "a"
[[imu]]
label = "a"
position = [0.0, 0.0, 0.0]
acc_noise_std = 0.01
gyro_noise_std = 0.001
[[imu]]
label = "b"
position = [0.01, 0.0, 0.0]
acc_noise_std = 0.01
gyro_noise_std = 0.001
[[imu]]
label = "c"
position = [0.0, 0.01, 0.0]
acc_noise_std = 0.01
gyro_noise_std = 0.001
"""
GOOD_ROWS = ["1000000,0.1,0.2,0.3,0.0,0.0,9.8", "2000000,0.1,0.2,0.3,0.0,0.0,9.8",
             "3000000,0.1,0.2,0.3,0.0,0.0,9.8", "4000000,0.1,0.2,0.3,0.0,0.0,9.8"]


def _small_asl(tmp_path, bad_b=None, header_b=ASL_HEADER, extra_folder=None):
    toml = tmp_path / "array.toml"
    toml.write_text(TOML2)
    for lab in ["a", "b", "c"] + ([extra_folder] if extra_folder else []):
        d = tmp_path / "asl" / lab
        d.mkdir(parents=True)
        rows = bad_b if (lab == "b" and bad_b is not None) else GOOD_ROWS
        head = header_b if lab == "b" else ASL_HEADER
        (d / "data.csv").write_text("\n".join([head] + rows) + "\n")
    return tmp_path / "asl", toml


def _refused(capsys, tmp_path, src, toml, *extra):
    out = tmp_path / "out.nc"
    rc = main(["import-csv", str(src), "--array", str(toml), "-o", str(out), "--noise", "stated", *extra])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and not out.exists() and len(err.splitlines()) == 1, (rc, err)
    assert "Traceback" not in err
    return err


def test_good_small_asl_imports(tmp_path, capsys):
    src, toml = _small_asl(tmp_path)
    out = tmp_path / "out.nc"
    assert main(["import-csv", str(src), "--array", str(toml), "-o", str(out), "--noise", "stated"]) == 0
    rec = read_recording(out)
    np.testing.assert_array_equal(rec.time, [0.0, 0.001, 0.002, 0.003])
    assert rec.K == 3 and rec.reference_imu == 0
    # Refuses an existing output without --overwrite, replaces it with.
    assert main(["import-csv", str(src), "--array", str(toml), "-o", str(out), "--noise", "stated"]) == 2
    assert "exists; pass --overwrite" in capsys.readouterr().err
    assert main(["import-csv", str(src), "--array", str(toml), "-o", str(out), "--noise", "stated", "--overwrite"]) == 0


@pytest.mark.parametrize("case, rows, header, pattern", [
    ("missing column", [r.rsplit(",", 1)[0] for r in GOOD_ROWS], ASL_HEADER.rsplit(",", 1)[0],
     r"b/data.csv:1: missing column 'a_RS_S_z' \(acc z axis\)"),
    ("unsorted stamps", [GOOD_ROWS[0], GOOD_ROWS[2], GOOD_ROWS[1], GOOD_ROWS[3]], ASL_HEADER,
     r"b/data.csv:4: column 'timestamp \[ns\]': time stamp 2000000 is earlier than the one before \(line 3: 3000000\)"),
    ("duplicated stamps", [GOOD_ROWS[0], GOOD_ROWS[1], GOOD_ROWS[1], GOOD_ROWS[3]], ASL_HEADER,
     r"b/data.csv:4: column 'timestamp \[ns\]': time stamp 2000000 is duplicated"),
    ("mixed units", GOOD_ROWS, ASL_HEADER.replace("a_RS_S_y [m s^-2]", "a_RS_S_y [g]"),
     r"b/data.csv:1: column 'a_RS_S_y \[g\]': unit 'g' differs from 'm s-2' .*mixed units"),
    ("wrong kind of unit", GOOD_ROWS, ASL_HEADER.replace("w_RS_S_x [rad s^-1]", "w_RS_S_x [m s^-2]"),
     r"b/data.csv:1: column 'w_RS_S_x \[m s\^-2\]': unit 'm s\^-2' is not a gyro unit"),
    ("no unit", GOOD_ROWS, ASL_HEADER.replace("a_RS_S_x [m s^-2]", "a_RS_S_x"),
     r"b/data.csv:1: column 'a_RS_S_x': no unit"),
    ("ragged row", [GOOD_ROWS[0], GOOD_ROWS[1] + ",7.0", GOOD_ROWS[2]], ASL_HEADER,
     r"b/data.csv:3: expected 7 fields \(as in the header\), got 8"),
    ("not a number", [GOOD_ROWS[0], GOOD_ROWS[1].replace("9.8", "9x"), GOOD_ROWS[2]], ASL_HEADER,
     r"b/data.csv:3: column 'a_RS_S_z \[m s\^-2\]': expected a finite number, got '9x'"),
    ("fractional ns", [GOOD_ROWS[0], "2000000.5" + GOOD_ROWS[1][7:], GOOD_ROWS[2]], ASL_HEADER,
     r"b/data.csv:3: column 'timestamp \[ns\]': expected a time stamp in ns that is a whole number"),
], ids=lambda v: v if isinstance(v, str) and " " in v and "[" not in v and "\\" not in v else "")
def test_bad_csv_refused_with_file_line_column(tmp_path, capsys, case, rows, header, pattern):
    src, toml = _small_asl(tmp_path, bad_b=rows, header_b=header)
    err = _refused(capsys, tmp_path, src, toml)
    assert re.search(pattern, err), (case, err)


def test_imu_missing_from_description_refused(tmp_path, capsys):
    src, toml = _small_asl(tmp_path, extra_folder="d")
    err = _refused(capsys, tmp_path, src, toml)
    assert "d/data.csv: IMU 'd' is not in array.toml" in err
    # Wide layout: columns of an undescribed IMU are refused as well.
    f = tmp_path / "wide.csv"
    head = ["time [ns]"] + [f"{lab}_{s}_{a} [{u}]" for lab in "abcd" for s, u in (("acc", "m s^-2"), ("gyro", "rad s^-1"))
                            for a in "xyz"]
    f.write_text(",".join(head) + "\n" + "\n".join(f"{i * 1000},{','.join(['0.5'] * 24)}" for i in range(1, 4)) + "\n")
    err = _refused(capsys, tmp_path, f, toml)
    assert "wide.csv:1: column 'd_acc_x [m s^-2]' belongs to no IMU of array.toml" in err


def test_description_refusals(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(TOML2.replace("position = [0.01, 0.0, 0.0]", "position = [0.01, 0.0]"))
    with pytest.raises(UserError, match=r"bad.toml: imu\[1\].position: expected \[x, y, z\] in m"):
        read_array_description(bad)
    bad.write_text(TOML2 + "orientation_matrix = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]]\n")
    with pytest.raises(UserError, match=r"imu\[2\].orientation_matrix: expected a rotation matrix"):
        read_array_description(bad)
    bad.write_text(TOML2 + "orientation = [1.0, 0.1, 0.0, 0.0]\n")
    with pytest.raises(UserError, match=r"imu\[2\].orientation: expected a unit quaternion"):
        read_array_description(bad)
    bad.write_text(TOML2.replace('reference_imu = "a"', 'reference_imu = "z"'))
    with pytest.raises(UserError, match=r"reference_imu: 'z' is not an IMU label"):
        read_array_description(bad)
    # A yawed IMU given as a matrix: the §7.0 worked example, q = (0.7071, 0, 0, −0.7071).
    good = tmp_path / "good.toml"
    good.write_text(TOML2 + "orientation_matrix = [[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]\n")
    q = read_array_description(good).imus[2].orientation
    np.testing.assert_allclose(q, [math.sqrt(0.5), 0, 0, -math.sqrt(0.5)], atol=1e-15)


def test_wide_csv_per_imu_time_columns(tmp_path):
    # Three IMUs in one file: a and b share a stamp column, c has its own (µs), 0.2 ms late.
    toml = tmp_path / "array.toml"
    toml.write_text(TOML2.replace('label = "c"', 'label = "c"\ncolumns = {time = "t_c"}')
                    + '[csv]\ntime = "t_ab"\nunits = {time = "us"}\n')
    head = ["t_ab", "t_c"] + [f"{lab}_{s}_{a} [{u}]" for lab in "abc" for s, u in (("acc", "m s^-2"), ("gyro", "rad s^-1"))
                              for a in "xyz"]
    rows = [",".join([str(1000 * i), str(1000 * i + 200)] + [str(0.1 * i + j) for j in range(18)]) for i in range(1, 6)]
    f = tmp_path / "wide.csv"
    f.write_text(",".join(head) + "\n" + "\n".join(rows) + "\n")
    res = import_csv(f, toml, noise="stated")
    np.testing.assert_array_equal(res.recording.time, [0.0, 0.001, 0.002, 0.003, 0.004])
    np.testing.assert_array_equal(res.imu_time_offset, np.tile([0.0, 0.0, 0.0002], (5, 1)))
    np.testing.assert_array_equal(res.recording.acc[:, 2, 0], [0.1 * i + 12 for i in range(1, 6)])


def test_header_and_description_units_must_agree(tmp_path, capsys):
    toml = tmp_path / "array.toml"
    toml.write_text(TOML2 + '[csv]\nunits = {acc = "m s^-2", time = "ns"}\n')
    head = ["time"] + [f"{lab}_{s}_{a}" + (" [g]" if (lab, s, a) == ("b", "acc", "x") else "")
                       for lab in "abc" for s in ("acc", "gyro") for a in "xyz"]
    f = tmp_path / "wide.csv"
    f.write_text(",".join(head) + "\n" + "\n".join(f"{i * 1000},{','.join(['0.5'] * 18)}" for i in range(1, 4)) + "\n")
    err = _refused(capsys, tmp_path, f, toml)
    # The gyro columns have no unit anywhere (IMU a's are read before b's acc).
    assert "wide.csv:1: column 'a_gyro_x': no unit; expected 'a_gyro_x [unit]' in the header or csv.units.gyro" in err
    toml.write_text(TOML2 + '[csv]\nunits = {acc = "m s^-2", gyro = "rad/s", time = "ns"}\n')
    err = _refused(capsys, tmp_path, f, toml)
    assert "wide.csv:1: column 'b_acc_x [g]': the header says 'g', csv.units.acc says 'm s-2'; expected them to agree" in err
    toml.write_text(TOML2 + '[csv]\nunits = {acc = "furlong"}\n')
    err = _refused(capsys, tmp_path, f, toml)
    assert "array.toml: csv.units.acc: expected one of ['g', 'm s-2'], got 'furlong'" in err
    assert main(["import-csv", str(f), "--array", str(tmp_path / "nope.toml"), "-o", str(tmp_path / "o.nc")]) == 2
    assert "--array" in capsys.readouterr().err


# ------------------------------------------------------------------------------ issue #29: paths, units, plausibility
def test_dot_labels_and_folders_outside_the_source_are_refused(tmp_path, capsys):
    # An IMU labelled '..' used to read SOURCE/../data.csv and import with exit 0.
    src, toml = _small_asl(tmp_path)
    (src / "c" / "data.csv").rename(tmp_path / "data.csv")  # beside the source, not in it
    (src / "c").rmdir()
    toml.write_text(TOML2.replace('label = "c"', 'label = ".."'))
    err = _refused(capsys, tmp_path, src, toml)
    assert "imu[2].label: expected a name of letters, digits, '_', '.', '-' other than '.' or '..', got '..'" in err
    toml.write_text(TOML2.replace('label = "c"', 'label = "."'))
    assert "got '.'" in _refused(capsys, tmp_path, src, toml)
    # A folder that resolves outside the source (a link) is refused as well.
    outside = tmp_path / "elsewhere" / "c"
    outside.mkdir(parents=True)
    (tmp_path / "data.csv").rename(outside / "data.csv")
    (src / "c").symlink_to(outside, target_is_directory=True)
    toml.write_text(TOML2)
    err = _refused(capsys, tmp_path, src, toml)
    assert "outside the source folder" in err and "IMU 'c'" in err


def test_csv_rigid_board_check_marks_a_lone_wrong_value(sim, tmp_path, capsys):
    rec = sim.copy()
    write_asl(rec, tmp_path / "clean")
    toml = write_toml(rec, tmp_path / "array.toml")
    clean = import_csv(tmp_path / "clean", toml, noise="stated").recording
    assert clean.acc_flagged is not None and not clean.acc_flagged.any() and not clean.gyro_flagged.any()
    rec.gyro[150, 5, 1] += 1.5  # 86 °/s on one gyro axis, one sample
    rec.acc[200, 2, 0] += 6.0  # 0.6 g on one accelerometer axis, one sample
    write_asl(rec, tmp_path / "bad")
    res = import_csv(tmp_path / "bad", toml, noise="stated")
    got = res.recording
    assert np.argwhere(got.gyro_flagged).tolist() == [[150, 5]]
    assert np.argwhere(got.acc_flagged).tolist() == [[200, 2]]
    assert any("1 samples marked gyro_flagged" in line for line in res.lines)
    np.testing.assert_array_equal(got.gyro, rec.gyro)  # marked, not changed or removed
    out = tmp_path / "bad.nc"
    write_imported(res, out)
    back = read_recording(out)
    np.testing.assert_array_equal(back.gyro_flagged, got.gyro_flagged)

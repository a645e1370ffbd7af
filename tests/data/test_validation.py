"""Validation of recordings: every refusal names the problem (DESIGN §7.1 "nothing is guessed")."""
import math

import numpy as np
import pytest

from accel_bayes.errors import RecordingError
from accel_bayes.data.io import read_recording, recording_from_dataset, recording_to_dataset, write_recording
from accel_bayes.data.validation import DEFAULT_GYRO_BOUND, gyro_unit_diagnostics, validate_recording

from tests.data.test_io import make_recording

DEG = math.pi / 180


@pytest.fixture(scope="module")
def rec():
    return make_recording(T=400)


@pytest.fixture
def ds(rec):
    return recording_to_dataset(rec)


def refused(obj, match, **kw):
    """Assert that validating ``obj`` (Recording or Dataset) raises RecordingError matching all
    the regular expressions in ``match``; return the message."""
    with pytest.raises(RecordingError) as exc:
        if hasattr(obj, "data_vars"):
            recording_from_dataset(obj, **kw)
        else:
            validate_recording(obj, **kw)
    msg = str(exc.value)
    for m in [match] if isinstance(match, str) else match:
        assert __import__("re").search(m, msg), (m, msg)
    assert "\n" not in msg
    return msg


def test_good_recording_passes(rec, ds):
    validate_recording(rec)
    validate_recording(rec, require_gyro=True, reference_imu=5)
    recording_from_dataset(ds)


# ---------------------------------------------------------------- names, dimensions, labels

def test_misnamed_acc_is_reported_with_the_near_name(ds):
    refused(ds.rename({"acc": "accel"}), [r'variable "acc" is missing', r'\(time, imu, axis\)',
                                          r'the file has "accel" — rename it to "acc"'])
    refused(ds.rename({"acc": "Accelerometer"}), r'the file has "Accelerometer"')


def test_missing_variable_without_near_name_lists_what_is_there(ds):
    refused(ds.drop_vars("nominal_position"), [r'"nominal_position" is missing', r"design positions, m",
                                               r"the file has \[acc"])


def test_optional_variable_under_another_name_is_not_dropped_silently(ds):
    refused(ds.rename({"gyro": "gyroscope"}), r'"gyroscope" is not part of format v1 but looks like "gyro"')


def test_missing_coordinate(ds):
    refused(ds.drop_vars("axis"), r'coordinate "axis" is missing: expected labels "x", "y", "z"')
    refused(ds.drop_vars("time"), r'coordinate "time" is missing: expected sample times')


def test_wrong_axis_order_of_acc(ds):
    bad = ds.assign(acc=ds["acc"].transpose("imu", "time", "axis"))
    refused(bad, r"acc: expected dimensions \(time, imu, axis\), got \(imu, time, axis\) \(axis order differs")


def test_wrong_dimension_name(ds):
    refused(ds.rename({"time": "sample"}), r'acc: expected dimensions \(time, imu, axis\), got \(sample, imu, axis\); '
                                            r'rename dimension "sample" to "time"')


def test_axis_labels_and_quaternion_order(ds):
    refused(ds.assign_coords(axis=["a", "b", "c"]), r"axis: expected labels \('x', 'y', 'z'\) in that order, got \('a', 'b', 'c'\)")
    refused(ds.assign_coords(axis=["z", "y", "x"]), r"same labels, different order")
    refused(ds.assign_coords(quat=["x", "y", "z", "w"]), r"quat: expected labels \('w', 'x', 'y', 'z'\).*scalar-last")


def test_imu_labels(ds):
    refused(ds.assign_coords(imu=np.arange(1, 9)), r"imu: expected labels 0\.\.7 in file order, got \[1, 2")


def test_units_that_are_not_si(ds):
    bad = ds.copy()
    bad["acc"] = bad["acc"].assign_attrs(units="g")
    refused(bad, r"acc: units attribute is 'g'; expected 'm s-2'")
    bad = ds.copy()
    bad["gyro"] = bad["gyro"].assign_attrs(units="rpm")
    refused(bad, r'gyro: units attribute is .rpm.; expected "rad s-1" \(format v1\) or an explicit "deg s-1"')


def test_format_version(ds):
    refused(ds.assign_attrs(format="accel_bayes.recording/2"), r"format: this reader understands 'accel_bayes.recording/1'")


def test_non_boolean_mask(ds):
    m = ds["acc_clipped"].values.astype(np.int8)
    m[5, 1] = 2
    refused(ds.assign(acc_clipped=(("time", "imu"), m)), r"acc_clipped: expected a bool mask \(0/1\), found value 2 at index \(5, 1\)")
    ok = ds.assign(acc_clipped=ds["acc_clipped"].astype(np.int8))  # int8 0/1 is fine
    assert recording_from_dataset(ok).acc_clipped.dtype == bool


# ---------------------------------------------------------------- samples

def test_nan_in_acc_is_located(rec):
    bad = rec.copy()
    bad.acc[17, 3, 1] = np.nan
    bad.acc[200:205, 6, 0] = np.inf
    refused(bad, [r"^acc: 6 non-finite value", r"first NaN at time index 17", r"t = 12\.67 s", r"IMU 3"])


def test_nan_in_gyro_of_an_imu_with_a_gyro(rec):
    bad = rec.copy()
    bad.gyro[:, 2] = np.nan  # IMU 2 has no gyroscope: fine
    validate_recording(bad)
    bad.gyro[40, 5, 2] = np.inf
    refused(bad, [r"^gyro: 1 non-finite", r"first inf at time index 40", r"IMU 5"])


def test_non_increasing_time(rec):
    bad = rec.copy()
    bad.time[100] = bad.time[99]
    refused(bad, r"time: expected strictly increasing sample times; time\[100\] = 13\.49 s is not after time\[99\]")


def test_nan_in_acc_read_from_a_file_names_the_file(tmp_path, rec):
    bad = rec.copy()
    bad.acc[3, 0, 0] = np.nan
    p = write_recording(bad, tmp_path / "nan.nc", validate=False)
    with pytest.raises(RecordingError, match=r"nan\.nc: acc: 1 non-finite.*time index 3"):
        read_recording(p)


# ---------------------------------------------------------------- gyro units

def test_gyro_in_degrees_declared_as_radians_is_refused(rec):
    bad = rec.copy()
    bad.gyro = bad.gyro / DEG
    refused(bad, [r"gyro: values look like deg/s, not the declared rad s-1", r"centripetal",
                  r"c ≈ 0\.017", r"convert gyro to rad/s"])


def test_gyro_in_radians_declared_as_degrees_is_refused(tmp_path, rec):
    p = tmp_path / "deg.nc"
    ds = recording_to_dataset(rec)
    ds["gyro"].attrs["units"] = "deg/s"  # values are rad/s, the attribute says degrees
    ds.to_netcdf(p, engine="h5netcdf")
    with pytest.raises(RecordingError, match=r'values look like rad/s, not the declared deg s-1.*c ≈ 5[67]\.'
                                             r'.*set the gyro units attribute to "rad s-1"'):
        read_recording(p)


def test_range_rule_when_the_accelerometers_cannot_decide(rec):
    bad = rec.copy()
    bad.gyro = bad.gyro / DEG
    bad.acc_clipped = np.ones_like(bad.acc_clipped)  # no usable accelerometer samples: test C is silent
    d = gyro_unit_diagnostics(bad)
    assert d["array_verdict"] == "inconclusive" and d["range_flag"]
    refused(bad, [r"99\.9th percentile \|gyro\| = \d+(\.\d+)? rad/s exceeds 1\.5 × gyro_range = 52\.36 rad/s",
                  r"convert gyro to rad/s"])
    bad.gyro_range = None
    refused(bad, rf"exceeds {DEFAULT_GYRO_BOUND:g} rad/s \(no gyro_range given")


def test_static_noise_rule_both_directions():
    still = make_recording(T=300, static_frac=1.0)  # no rotation: only the static-noise rule can tell
    validate_recording(still)
    bad = still.copy()
    bad.gyro = bad.gyro / DEG
    d = gyro_unit_diagnostics(bad)
    assert d["array_verdict"] == "inconclusive" and not d["range_flag"]
    assert 40 < d["static_ratio"] < 80
    refused(bad, [r"static segments the gyro std is 5\d\.?\d* × the stated gyro_noise_std",
                  r"rule: 19\.1–172×"])
    rev = still.copy()  # rad/s values that a file declared as deg/s were multiplied by π/180
    rev.gyro = rev.gyro * DEG
    refused(rev, r"values look like rad/s, not the declared deg s-1.*gyro std is 0\.01\d+ ×", gyro_units="deg s-1")
    validate_recording(still, gyro_units="deg s-1")  # the right scale passes whatever the declaration


def test_no_false_alarm_when_noise_is_understated_but_motion_decides(rec):
    noisy = rec.copy()
    noisy.gyro_noise_std = noisy.gyro_noise_std / 40  # static ratio ≈ 40 would flag deg/s on its own …
    d = gyro_unit_diagnostics(noisy)
    assert d["array_verdict"] == "declared" and abs(d["beta"] - 1) < 0.1  # … but the accelerometers say rad/s
    validate_recording(noisy)


# ---------------------------------------------------------------- noise, geometry, reference

def test_noise_std_must_be_positive(rec, ds):
    bad = rec.copy()
    bad.gyro_noise_std[4] = 0.0
    refused(bad, r"gyro_noise_std: IMU 4 has 0\.0; expected a finite value > 0 rad s-1")
    refused(ds.assign_attrs(acc_noise_std=-0.1), r"acc_noise_std: global attribute must be a finite number > 0, got -0\.1")
    per = ds.assign(acc_noise_std=("imu", np.r_[0.04, 0.04, -1.0, np.full(5, 0.04)]))
    refused(per, r"acc_noise_std: IMU 2 has -1\.0")
    refused(ds.drop_attrs().assign_attrs(gyro_noise_std=1e-3), r"acc_noise_std is missing: expected a global attribute")


def test_fewer_than_three_triads(rec):
    bad = rec.copy()
    bad.acc[:, 2:] = np.nan  # only IMUs 0 and 1 keep an accelerometer
    bad.gyro[:, 1] = np.nan  # and IMU 1 no gyro: not a rig (two IMUs with gyros are, tests/test_rig_pipeline.py)
    refused(bad, r"nominal_position: accelerometer triads: at least 3 are needed.*got 2")


def test_collinear_triads(rec):
    bad = rec.copy()
    bad.nominal_position = np.c_[np.linspace(-0.01, 0.01, 8), np.zeros(8), np.zeros(8)]
    refused(bad, [r"collinear", r"rotation about the line through them is unobservable"], check_gyro_units=False)


def test_reference_imu_out_of_range(rec, ds):
    bad = rec.copy()
    bad.reference_imu = 8
    refused(bad, r"reference_imu: expected an IMU label in 0\.\.7, got 8")
    refused(rec, r"got -1", reference_imu=-1)
    refused(ds.assign_attrs(reference_imu=2.5), r"reference_imu: global attribute must be an integer IMU label")


def test_require_gyro(rec):
    nog = rec.copy()
    nog.gyro = None
    nog.gyro_clipped = None
    refused(nog, r"gyro: this analysis needs gyroscope data", require_gyro=True)


# ---------------------------------------------------------------- shapes and labels

@pytest.mark.parametrize("field, value, match", [
    ("gyro", np.zeros((400, 7, 3)), r"gyro: expected shape \(400, 8, 3\), got \(400, 7, 3\)"),
    ("nominal_position", np.zeros((7, 3)), r"nominal_position: expected shape \(8, 3\), got \(7, 3\)"),
    ("nominal_orientation", np.tile([1.0, 0, 0, 0], (8, 1))[:, :3], r"nominal_orientation: expected shape \(8, 4\)"),
    ("acc_clipped", np.zeros((399, 8), bool), r"acc_clipped: expected shape \(400, 8\), got \(399, 8\)"),
    ("gyro_clipped", np.zeros((400, 8)), r"gyro_clipped: expected a bool array, got dtype float64"),
    ("segment", np.array(["static"] * 399), r"segment: expected shape \(400,\), got \(399,\)"),
    ("acc_noise_std", np.full(9, 0.04), r"acc_noise_std: expected shape \(8,\), got \(9,\)"),
    ("acc", np.zeros((400, 8, 4)), r"acc: expected shape \(T, K, 3\) = \(400, K, 3\)"),
])
def test_shape_mismatches(rec, field, value, match):
    bad = rec.copy()
    setattr(bad, field, value)
    refused(bad, match)


def test_segment_labels(rec):
    bad = rec.copy()
    bad.segment = bad.segment.astype("<U8")
    bad.segment[250] = "moving"
    refused(bad, r'segment: expected labels "static" or "dynamic", got .moving. at time index 250')


def test_orientation_must_be_unit_quaternions(rec):
    bad = rec.copy()
    bad.nominal_orientation = bad.nominal_orientation.copy()
    bad.nominal_orientation[6] *= 2
    refused(bad, r"nominal_orientation: IMU 6 .*norm 2.*expected a unit quaternion")


# ---------------------------------------------------------------- the unit rule on real data

def _mimu_exp1(mimu_dir):
    """exp_1 of the shared MIMU4444 recordings, decoded from the README's packet layout (just
    enough for this test; the importer is accel_bayes' own business, not this test's)."""
    import gzip

    from accel_bayes.physics.arrays import mimu4444_8
    from accel_bayes.data.recording import Recording

    raw = gzip.open(mimu_dir / "exp_1" / "data.bin.gz").read()[4:]
    n = len(raw) // 106
    b = np.frombuffer(raw[: n * 106], dtype=np.uint8).reshape(n, 106)
    ticks = b[:, 4:8].copy().view(">u4").ravel().astype(np.int64)
    v = b[:, 8:104].copy().view(">i2").reshape(n, 8, 6).astype(float)
    t = np.cumsum(np.r_[0, np.diff(ticks) % 2**32]) / 64e6
    arr = mimu4444_8()
    return Recording(
        time=t, acc=v[..., :3] * 9.80665 / 2048, gyro=np.radians(v[..., 3:] / 16.4),
        nominal_position=arr.positions.numpy(), nominal_orientation=arr.orientations.numpy(),
        acc_noise_std=np.full(8, 0.04), gyro_noise_std=np.full(8, np.radians(0.06)),
        acc_clipped=(np.abs(v[..., :3]) >= 32767).any(-1), gyro_clipped=(np.abs(v[..., 3:]) >= 32767).any(-1),
        acc_range=arr.acc_range, gyro_range=arr.gyro_range)


def test_gyro_unit_rule_on_the_real_mimu_recording(mimu_dir):
    real = _mimu_exp1(mimu_dir)
    d = gyro_unit_diagnostics(real)
    # Raw sensors (no intrinsic calibration) and nominal positions: c² is still 1 within a few %.
    assert d["array_verdict"] == "declared" and abs(d["beta"] - 1) < 0.05, d
    validate_recording(real)
    deg = real.copy()
    deg.gyro = deg.gyro / DEG
    refused(deg, r"values look like deg/s.*c ≈ 0\.017")


# ---------------------------------------------------------------- accelerometer units (issue #29)

def test_acc_in_g_declared_as_m_s2_is_refused(rec, tmp_path):
    # Formerly imported silently: |a| at rest ≈ 1 where 9.81 is expected.
    bad = rec.copy()
    bad.acc = bad.acc / 9.80665
    refused(bad, [r"acc: values look like g, not the declared m s-2: \|acc\| at rest = 1 ",
                  r"static segments", r"convert acc to m/s²"])
    twice = rec.copy()
    twice.acc = twice.acc * 9.80665
    refused(twice, r"acc: values look like m/s² declared as g \(converted twice\): \|acc\| at rest = 96\.")
    # Without rest labels the still samples (gyros below 0.1 rad/s) serve.
    bad.segment = None
    refused(bad, r"\|acc\| at rest = 1 \(median over 200 rest samples, samples with \|ω\| < 0\.1 rad/s\)")
    with pytest.raises(RecordingError, match=r"acc: values look like g"):
        write_recording(bad, tmp_path / "g.nc")
    assert not (tmp_path / "g.nc").exists()
    validate_recording(rec)  # m/s² passes
    nograv = rec.copy()  # no gravity at rest (a simulation): not a unit question
    nograv.acc = nograv.acc - np.array([0.0, 0.0, 9.80665])
    validate_recording(nograv, check_gyro_units=False)


def test_csv_acc_in_g_declared_as_m_s2_is_refused(tmp_path, capsys):
    # import-csv of a still board whose accelerometers wrote g under an [m s^-2] header: one line,
    # exit 2, no file (formerly imported silently).
    try:
        from tests.data.test_csv_import import _refused, _small_asl
    except ImportError:
        from .test_csv_import import _refused, _small_asl

    rows = [f"{(i + 1) * 1_000_000},0.0,0.0,0.0,0.01,-0.02,{g}" for i in range(30) for g in ["1.0"]]
    src, toml = _small_asl(tmp_path, bad_b=rows)
    for lab in "ac":
        f = src / lab / "data.csv"
        f.write_text("\n".join([f.read_text().splitlines()[0]] + rows) + "\n")
    err = _refused(capsys, tmp_path, src, toml)
    assert "acc: values look like g, not the declared m s-2: |acc| at rest = 1 (median over 30 rest samples" in err

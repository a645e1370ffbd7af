"""Recording files (format v1): round trips, atomic writes, foreign files, truth sidecars, `info`."""
import dataclasses
import hashlib
import json
import os

import numpy as np
import pytest
import torch
import xarray as xr

from accel_bayes.physics import arrays, models
from accel_bayes.errors import RecordingError, UserError
from accel_bayes.data.io import (
    FORMAT,
    TRUTH_SCHEMA,
    read_recording,
    read_truth,
    recording_sha256,
    recording_to_dataset,
    truth_path,
    write_recording,
    write_truth,
)
from accel_bayes.data.recording import Recording


def make_recording(T=400, fs=100.0, preset="mimu8", seed=0, amp=3.0, static_frac=0.5, gyro=True,
                   segment=True, clipped=True, acc_noise=0.04, gyro_noise=1e-3):
    """A small, physically consistent recording: rigid-body outputs of the DESIGN §3 model for a
    preset board, a static first part and a sinusoidal rotation after it, plus white noise."""
    arr = arrays.preset(preset)
    rng = np.random.default_rng(seed)
    t = np.arange(T) / fs + 12.5
    n_st = int(static_frac * T)
    w = np.zeros((T, 3))
    wd = np.zeros((T, 3))
    for ax in range(3):
        for j in range(3):
            a, f, ph = amp * rng.uniform(0.3, 1.0) / (j + 1), rng.uniform(0.3, 2.5), rng.uniform(0, 2 * np.pi)
            w[:, ax] += a * np.sin(2 * np.pi * f * t + ph)
            wd[:, ax] += a * 2 * np.pi * f * np.cos(2 * np.pi * f * t + ph)
    w[:n_st] = 0.0
    wd[:n_st] = 0.0
    s = np.tile([0.0, 0.0, 9.80665], (T, 1))
    s[n_st:] += rng.normal(0, 3, (T - n_st, 3))
    acc, gyr = models.imu_outputs(arr.positions, arr.orientations, torch.tensor(w), torch.tensor(wd), torch.tensor(s))
    K = arr.K
    return Recording(
        time=t,
        acc=acc.numpy() + rng.normal(0, acc_noise, (T, K, 3)),
        nominal_position=arr.positions.numpy().copy(),
        nominal_orientation=arr.orientations.numpy().copy(),
        acc_noise_std=np.full(K, acc_noise),
        gyro_noise_std=np.full(K, gyro_noise),
        gyro=(gyr.numpy() + rng.normal(0, gyro_noise, (T, K, 3))) if gyro else None,
        acc_clipped=np.zeros((T, K), bool) if clipped else None,
        gyro_clipped=np.zeros((T, K), bool) if (clipped and gyro) else None,
        segment=np.where(np.arange(T) < n_st, "static", "dynamic") if segment else None,
        reference_imu=0,
        acc_range=arr.acc_range,
        gyro_range=arr.gyro_range,
        description="test recording",
        source="tests/data/test_io.py",
        attrs={"seed": seed},
    )


def assert_same_recording(a: Recording, b: Recording):
    for f in dataclasses.fields(Recording):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), f.name
            assert x.shape == y.shape and x.dtype == y.dtype, (f.name, x.dtype, y.dtype)
            if x.dtype.kind == "f":  # bit-exact, NaNs included
                assert np.array_equal(x.view(np.uint64), y.view(np.uint64)), f.name
            else:
                assert np.array_equal(x, y), f.name
        else:
            assert x == y and type(x) is type(y), (f.name, x, y)


# ---------------------------------------------------------------- round trips and layout

def test_round_trip_is_bit_exact(tmp_path):
    rec = make_recording()
    rec.gyro[:, 3] = np.nan  # an IMU without a gyroscope
    rec.gyro_noise_std[3] = np.nan
    rec.acc_noise_std[5] = 0.05  # per-IMU noise → variable, not attribute
    rec.acc_clipped[10, 2] = True
    rec.gyro_clipped[300, 1] = True
    rec.reference_imu = 2
    rec.attrs.update(note="ünïcode", n=7, x=0.125, flag=True, none=None, lst=[1, 2.5], d={"a": [1, 2]},
                     arr=np.arange(3))
    p = write_recording(rec, tmp_path / "r.nc")
    back = read_recording(p)
    expected = dict(rec.attrs, arr=[0, 1, 2])  # arrays come back as lists (JSON)
    assert back.attrs == expected
    back.attrs = rec.attrs
    assert_same_recording(rec, back)


def test_round_trip_minimal_recording(tmp_path):
    rec = make_recording(gyro=False, segment=False, clipped=False)
    rec.acc_range = None
    rec.gyro_range = None
    rec.gyro_noise_std = np.full(rec.K, np.nan)
    rec.description = ""
    rec.attrs = {}
    back = read_recording(write_recording(rec, tmp_path / "m.nc"))
    assert back.gyro is None and back.segment is None and back.acc_clipped is None
    assert back.acc_range is None and back.gyro_range is None
    assert_same_recording(rec, back)


def test_file_layout_follows_design_7_1(tmp_path):
    rec = make_recording()
    rec.gyro_noise_std[2] = 2e-3
    p = write_recording(rec, tmp_path / "r.nc")
    with xr.open_dataset(p, engine="h5netcdf") as ds:
        assert ds.attrs["format"] == FORMAT == "accel_bayes.recording/1"
        assert ds["acc"].dims == ("time", "imu", "axis") and ds["acc"].attrs["units"] == "m s-2"
        assert ds["gyro"].dims == ("time", "imu", "axis") and ds["gyro"].attrs["units"] == "rad s-1"
        assert ds["nominal_position"].dims == ("imu", "axis") and ds["nominal_position"].attrs["units"] == "m"
        assert ds["nominal_orientation"].dims == ("imu", "quat")
        assert ds["acc_clipped"].dims == ("time", "imu") and ds["acc_clipped"].dtype == bool
        assert ds["segment"].dims == ("time",)
        assert list(ds["axis"].values) == ["x", "y", "z"] and list(ds["quat"].values) == ["w", "x", "y", "z"]
        assert list(ds["imu"].values) == list(range(8))
        assert ds["time"].attrs["units"] == "s"
        assert ds.attrs["acc_noise_std"] == 0.04 and "acc_noise_std" not in ds.variables
        assert "gyro_noise_std" not in ds.attrs and ds["gyro_noise_std"].dims == ("imu",)
        assert ds.attrs["reference_imu"] == 0 and ds.attrs["description"] == "test recording"
        np.testing.assert_array_equal(ds["acc"].values, rec.acc)


# ---------------------------------------------------------------- atomic writes

def test_refuses_to_overwrite_and_leaves_file_alone(tmp_path):
    p = tmp_path / "r.nc"
    write_recording(make_recording(seed=1), p)
    before = recording_sha256(p)
    with pytest.raises(UserError, match=r"r\.nc.*exists.*overwrite"):
        write_recording(make_recording(seed=2), p)
    assert recording_sha256(p) == before
    write_recording(make_recording(seed=2), p, overwrite=True)
    assert recording_sha256(p) != before
    assert read_recording(p).attrs["seed"] == 2
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.nc"]  # no temporary files left


def test_failed_write_never_corrupts_existing_file(tmp_path, monkeypatch):
    p = tmp_path / "r.nc"
    write_recording(make_recording(seed=1), p)
    before = recording_sha256(p)

    def broken(self, path=None, *a, **k):  # writes half a file (if given one), then fails
        if path is not None:
            with open(path, "wb") as f:
                f.write(b"\x89HDF partial")
        raise OSError("disk full")

    with monkeypatch.context() as m:
        m.setattr(xr.Dataset, "to_netcdf", broken)
        with pytest.raises(OSError, match="disk full"):
            write_recording(make_recording(seed=2), p, overwrite=True)
    assert recording_sha256(p) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.nc"]

    # the disk fills once the bytes are in the temporary file (caught at fsync, before the rename)
    import errno

    from accel_bayes.data import outputs

    def full(fd):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(outputs.os, "fsync", full)
    with pytest.raises(OSError, match="No space left") as info:
        write_recording(make_recording(seed=2), p, overwrite=True)
    assert info.value.filename == str(p)  # the error names the target, not the temporary file
    assert recording_sha256(p) == before
    assert sorted(x.name for x in tmp_path.iterdir()) == ["r.nc"]


def test_write_refuses_invalid_recordings_and_reserved_attrs(tmp_path):
    rec = make_recording()
    rec.acc[5, 1, 0] = np.nan
    with pytest.raises(RecordingError, match="acc"):
        write_recording(rec, tmp_path / "bad.nc")
    assert not (tmp_path / "bad.nc").exists()
    rec = make_recording()
    rec.attrs["description"] = "x"
    with pytest.raises(UserError, match="reserved"):
        write_recording(rec, tmp_path / "bad.nc")
    with pytest.raises(UserError, match="does not exist"):
        write_recording(make_recording(), tmp_path / "nodir" / "r.nc")


# ---------------------------------------------------------------- reading

def test_read_never_modifies_the_file(tmp_path):
    p = write_recording(make_recording(), tmp_path / "r.nc")
    os.chmod(p, 0o444)  # reading must work on a read-only file
    st = p.stat()
    sha = recording_sha256(p)
    read_recording(p)
    assert recording_sha256(p) == sha and p.stat().st_mtime_ns == st.st_mtime_ns


def _plain_xarray_dataset(rec: Recording, *, per_imu_noise=False):
    """The contract written by hand with plain xarray, the way another tool would."""
    ds = xr.Dataset(
        {
            "acc": (("time", "imu", "axis"), rec.acc.astype(np.float32)),  # float32, no units attribute
            "gyro": (("time", "imu", "axis"), rec.gyro, {"units": "rad/s"}),
            "nominal_position": (("imu", "axis"), rec.nominal_position, {"units": "m"}),
            "nominal_orientation": (("imu", "quat"), rec.nominal_orientation),
            "acc_clipped": (("time", "imu"), rec.acc_clipped.astype(np.int8)),  # bool as int8
            "gyro_clipped": (("time", "imu"), rec.gyro_clipped.astype(np.int8)),
            "segment": (("time",), rec.segment.astype(object)),
        },
        coords={"time": rec.time, "imu": np.arange(rec.K), "axis": ["x", "y", "z"], "quat": ["w", "x", "y", "z"]},
        attrs={"acc_noise_std": 0.04, "gyro_noise_std": 1e-3, "source": "other tool"},
    )
    if per_imu_noise:
        ds["acc_noise_std"] = (("imu",), np.linspace(0.03, 0.05, rec.K))
    return ds


def test_reads_a_file_written_by_plain_xarray(tmp_path):
    rec = make_recording()
    rec.acc_clipped[7, 3] = True
    ds = _plain_xarray_dataset(rec, per_imu_noise=True)
    p = tmp_path / "foreign.nc"
    ds.to_netcdf(p, engine="h5netcdf", encoding={"acc_clipped": {"dtype": "int8"}})
    back = read_recording(p)
    np.testing.assert_array_equal(back.acc, rec.acc.astype(np.float32).astype(np.float64))
    assert back.acc.dtype == np.float64
    np.testing.assert_array_equal(back.gyro, rec.gyro)
    assert back.acc_clipped.dtype == bool and back.acc_clipped[7, 3] and back.acc_clipped.sum() == 1
    assert list(back.segment) == list(rec.segment)
    np.testing.assert_array_equal(back.acc_noise_std, np.linspace(0.03, 0.05, rec.K))  # variable overrides
    np.testing.assert_array_equal(back.gyro_noise_std, np.full(rec.K, 1e-3))
    assert back.reference_imu == 0 and back.source == "other tool" and back.description == ""
    assert back.attrs == {}


def test_gyro_declared_in_degrees_is_converted(tmp_path):
    rec = make_recording()
    ds = _plain_xarray_dataset(rec)
    ds["gyro"] = ds["gyro"] * (180 / np.pi)
    ds["gyro"].attrs["units"] = "deg s-1"
    p = tmp_path / "deg.nc"
    ds.to_netcdf(p, engine="h5netcdf")
    back = read_recording(p)
    np.testing.assert_allclose(back.gyro, rec.gyro, rtol=1e-14, atol=1e-17)


def test_unreadable_and_missing_files(tmp_path):
    bad = tmp_path / "junk.nc"
    bad.write_bytes(b"this is not netcdf")
    with pytest.raises(RecordingError, match=r"junk\.nc: not a NetCDF-4/HDF5"):
        read_recording(bad)
    with pytest.raises(FileNotFoundError, match="nope.nc"):
        read_recording(tmp_path / "nope.nc")


# ---------------------------------------------------------------- truth sidecar and hashing

def test_truth_sidecar_round_trip(tmp_path):
    rec_path = write_recording(make_recording(), tmp_path / "sim.nc")
    assert truth_path(rec_path) == tmp_path / "sim.truth.json"
    pos = torch.arange(6, dtype=torch.float64).reshape(2, 3) * 1e-3
    truth = {"positions": pos, "omega": np.array([[0.5, -1.0, 2.0]]), "seed": np.int64(3),
             "effects": ("acc_bias",), "scale": np.float32(0.5)}
    p = write_truth(rec_path, truth)
    raw = json.loads(p.read_text())
    assert raw["schema"] == TRUTH_SCHEMA == "accel_bayes.truth/1"
    assert raw["recording_sha256"] == recording_sha256(rec_path)
    back = read_truth(rec_path)
    assert back["positions"] == pos.tolist() and back["omega"] == [[0.5, -1.0, 2.0]]
    assert back["seed"] == 3 and back["effects"] == ["acc_bias"] and back["scale"] == 0.5
    # the recording holds no ground truth
    with xr.open_dataset(rec_path, engine="h5netcdf") as ds:
        assert "positions" not in ds.variables and "truth" not in " ".join(ds.attrs)
    # a sidecar from another version of the recording is refused
    write_recording(make_recording(seed=9), rec_path, overwrite=True)
    with pytest.raises(UserError, match="recording_sha256 does not match"):
        read_truth(rec_path)
    assert read_truth(rec_path, verify=False)["seed"] == 3
    with pytest.raises(FileNotFoundError):
        read_truth(tmp_path / "other.nc")


def test_recording_sha256_matches_hashlib(tmp_path):
    p = write_recording(make_recording(), tmp_path / "r.nc")
    assert recording_sha256(p) == hashlib.sha256(p.read_bytes()).hexdigest()


# ---------------------------------------------------------------- CLI info

@pytest.fixture
def cli_main(monkeypatch):
    """The real dispatcher with only the `info` sub-command registered (other helpers' commands
    may not exist yet, and this test must not depend on them)."""
    import accel_bayes.cli as cli

    monkeypatch.setattr(cli, "COMMANDS", ["info"])
    return cli.main


def test_info_on_a_good_file(tmp_path, capsys, cli_main):
    rec = make_recording()
    rec.acc_clipped[:20, 4] = True
    p = write_recording(rec, tmp_path / "r.nc")
    assert cli_main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "samples T:       400" in out
    assert "IMUs K:          8 (8 with accelerometer, 8 with gyroscope)" in out
    assert "sample rate:     100 Hz" in out
    assert "worst IMU 4: 5 %" in out  # 20 of 400 samples
    assert "gyro clipped:    none" in out
    assert "static 200 samples (50 %, 1 runs)" in out
    assert "test recording" in out
    assert cli_main(["info", "--json", str(p)]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["samples"] == 400 and s["imus"] == 8 and abs(s["duration_s"] - 3.99) < 1e-9
    assert s["acc_clipped"]["worst_imu"] == 4 and s["gyro_clipped"]["overall"] == 0.0


def test_info_on_a_bad_file_exits_2_with_one_line(tmp_path, capsys, cli_main):
    rec = make_recording()
    ds = recording_to_dataset(rec).rename({"acc": "accel"})
    p = tmp_path / "bad.nc"
    ds.to_netcdf(p, engine="h5netcdf")
    assert cli_main(["info", str(p)]) == 2
    cap = capsys.readouterr()
    err = cap.err.strip().splitlines()
    assert len(err) == 1 and "Traceback" not in cap.err
    assert '"acc" is missing' in err[0] and '"accel"' in err[0] and "bad.nc" in err[0]
    assert cli_main(["info", str(tmp_path / "none.nc")]) == 2
    assert "none.nc" in capsys.readouterr().err


def test_extra_variables_are_reported_not_silently_dropped(tmp_path):
    rec = make_recording()
    ds = recording_to_dataset(rec)
    ds["temperature"] = (("time", "imu"), np.full((rec.T, rec.K), 25.0))
    p = tmp_path / "extra.nc"
    ds.to_netcdf(p, engine="h5netcdf")
    with pytest.warns(UserWarning, match=r"extra\.nc: variables \['temperature'\] are not part of format v1"):
        back = read_recording(p)
    np.testing.assert_array_equal(back.acc, rec.acc)


def test_plausibility_marks_round_trip_and_info_counts_them(tmp_path, capsys, cli_main):
    rec = make_recording()
    rec.acc_flagged = np.zeros((rec.T, rec.K), bool)
    rec.gyro_flagged = np.zeros((rec.T, rec.K), bool)
    rec.acc_flagged[250, 3] = True
    rec.gyro_flagged[[260, 261], 5] = True
    p = write_recording(rec, tmp_path / "f.nc")
    back = read_recording(p)
    assert_same_recording(rec, back)
    assert back.gyro_flagged[260, 5] and not back.gyro_flagged[260, 4]
    assert cli_main(["info", str(p)]) == 0
    out = capsys.readouterr().out
    assert "acc flagged:     1 samples marked implausible" in out
    assert "gyro flagged:    2 samples marked implausible" in out
    # a mark of the wrong shape is refused, naming the field
    rec.gyro_flagged = np.zeros((rec.T, rec.K - 1), bool)
    with pytest.raises(RecordingError, match="gyro_flagged"):
        write_recording(rec, tmp_path / "g.nc")

"""Import of real files' quirks (issue #28, item 3), on a faithful copy of EuRoC's IMU folders.

No EuRoC data is committed: the writer below reproduces what the files of the public EuRoC MAV
dataset (``mav0/imu0/``, ADIS16448 at 200 Hz) look like, which is what the importer has to read:

* ``data.csv``: the header ``#timestamp [ns],w_RS_S_x [rad s^-1],…,a_RS_S_z [m s^-2]``, epoch
  stamps near 1.4036e18 ns whose steps are not exactly 5 ms (mostly 4 999 936 ns, every third
  5 000 128 ns, so the median stamp rate is 200.00256 Hz), values written to 17 digits;
* ``sensor.yaml``: EuRoC's text (comments, ``sensor_type``, ``comment``, ``T_BS`` as
  {cols, rows, data}, ``rate_hz: 200``, the four noise figures 1.6968e-04, 1.9393e-05, 2.0000e-3,
  3.0000e-3); the OpenCV variant written by cv::FileStorage tools (``%YAML:1.0`` first line,
  ``T_BS: !!opencv-matrix`` with ``dt: d``, further fields this importer does not use);
* the Windows variants: a UTF-8 byte-order mark and CRLF line ends in both files.

The IMU values come from the package's simulator on a three-IMU rig with lever arms, so the
gyro-unit check sees a real array; "identical files" copies one IMU's folder three times.
"""
import math

import numpy as np
import pytest
import torch
import yaml

from accel_bayes.cli import main
from accel_bayes.data.io import read_recording
from accel_bayes.physics.arrays import SensorArray
from accel_bayes.physics.geometry import quat_to_matrix
from accel_bayes.simulate import simulate

HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
          "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")
T0_NS = 1403636579758555392  # EuRoC MH_01's first IMU stamp
NOISE = {"gyroscope_noise_density": "1.6968e-04", "gyroscope_random_walk": "1.9393e-05",
         "accelerometer_noise_density": "2.0000e-3", "accelerometer_random_walk": "3.0000e-3"}
POS = np.array([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0], [0.0, 0.05, 0.01]])
RIG_T_BS = np.tile(np.eye(4), (3, 1, 1))
RIG_T_BS[:, :3, 3] = POS  # a rig's sensor.yaml files: each IMU's pose in the body (= array) frame


def euroc_stamps(T):
    k = np.arange(T, dtype=np.int64)
    return T0_NS + k * 4_999_936 + (k // 3) * 192


def _rig(T=800, seed=0):
    K = 3
    arr = SensorArray(positions=torch.as_tensor(POS), orientations=torch.tensor([[1.0, 0, 0, 0]] * K, dtype=torch.float64),
                      has_acc=torch.ones(K, dtype=torch.bool), has_gyro=torch.ones(K, dtype=torch.bool),
                      acc_noise_std=torch.full((K,), 2e-3 * math.sqrt(200)),
                      gyro_noise_std=torch.full((K,), 1.6968e-4 * math.sqrt(200)))
    return simulate(arr, "smooth", T=T, rate=200.0, seed=seed, position_error_std=0.0).recording


def sensor_yaml_text(variant, T_BS=None):
    T_BS = np.eye(4) if T_BS is None else T_BS
    rows = ",\n         ".join(", ".join(repr(float(v)) for v in r) for r in T_BS)
    noise = "\n".join(f"{k}: {v}" for k, v in NOISE.items())
    if variant == "opencv":
        return ("%YAML:1.0\n---\nsensor_type: imu\ncomment: VI-Sensor IMU (ADIS16448)\n"
                f"T_BS: !!opencv-matrix\n  rows: 4\n  cols: 4\n  dt: d\n  data: [{rows}]\n"
                "distortion: !!opencv-matrix\n  rows: 1\n  cols: 4\n  dt: d\n  data: [0.1, 0.0, 0.0, 0.0]\n"
                "camera_model: pinhole\nresolution: [752, 480]\n"
                f"rate_hz: 200\n{noise}\n")
    return ("#Default imu sensor yaml file\nsensor_type: imu\ncomment: VI-Sensor IMU (ADIS16448)\n\n"
            "# Sensor extrinsics wrt. the body-frame.\n"
            f"T_BS:\n  cols: 4\n  rows: 4\n  data: [{rows}]\nrate_hz: 200\n\n"
            "# inertial sensor noise model parameters (static)\n" + noise + "\n")


def write_euroc(rec, folder, variant="euroc", labels=("imu0", "imu1", "imu2"), T_BS=None, same_as=None):
    """EuRoC-like ``folder/<label>/data.csv`` + ``sensor.yaml`` (module docstring); ``variant``
    "euroc", "windows" (BOM + CRLF) or "opencv" (OpenCV sensor.yaml); ``same_as``: write IMU
    ``same_as``'s samples into every folder (identical files)."""
    stamps = euroc_stamps(rec.T)
    nl, bom = ("\r\n", "\ufeff") if variant == "windows" else ("\n", "")
    for k, lab in enumerate(labels):
        src = k if same_as is None else same_as
        d = folder / lab
        d.mkdir(parents=True, exist_ok=True)
        rows = [HEADER] + [",".join([str(int(stamps[t]))] + [repr(float(v)) for v in rec.gyro[t, src]]
                                    + [repr(float(v)) for v in rec.acc[t, src]]) for t in range(rec.T)]
        (d / "data.csv").write_bytes((bom + nl.join(rows) + nl).encode("utf-8"))
        y = sensor_yaml_text(variant, None if T_BS is None else T_BS[k])
        (d / "sensor.yaml").write_bytes((bom + y.replace("\n", nl)).encode("utf-8"))
    return folder


def write_toml(path, positions=True, extra="", topics=False):
    lines = ['reference_imu = "imu0"']
    for k in range(3):
        lines += ["[[imu]]", f'label = "imu{k}"'] + ([f'rostopic = "/vi_sensor/imu{k}"'] if topics else [])
        if positions:
            lines.append(f"position = {POS[k].tolist()!r}")
        lines.append(extra)
    path.write_text("\n".join(lines) + "\n")
    return path


def _import(tmp_path, src, toml, *extra, out="rec.nc"):
    return main(["import-csv", str(src), "--array", str(toml), "-o", str(tmp_path / out), "--noise", "stated", *extra])


@pytest.fixture(scope="module")
def rig():
    return _rig()


@pytest.mark.parametrize("variant", ["euroc", "windows", "opencv"])
def test_euroc_folders_import_and_export_stated_figures(tmp_path, rig, variant, capsys):
    """Each variant imports (old code: the BOM gave "missing column 'timestamp'", the OpenCV tag
    "not valid YAML"), reproduces the samples, and the export gives back sensor.yaml's figures:
    densities from rate_hz = 200, not the 200.00256 Hz median stamp rate (old: 0.0019999872)."""
    src = write_euroc(rig, tmp_path / "mav0", variant, T_BS=RIG_T_BS)
    assert _import(tmp_path, src, write_toml(tmp_path / "array.toml", topics=variant == "opencv")) == 0
    out = capsys.readouterr()
    assert "gyro [0.0024, 0.0024, 0.0024] rad/s" in out.out  # rad/s, as `info` prints it
    assert out.err == ""  # T_BS agrees with the description: no warning
    assert main(["info", str(tmp_path / "rec.nc")]) == 0
    assert "gyro noise std:  0.0024 rad/s (all)" in capsys.readouterr().out  # the same unit and figure
    rec = read_recording(tmp_path / "rec.nc")
    np.testing.assert_array_equal(rec.acc, rig.acc)
    np.testing.assert_array_equal(rec.gyro, rig.gyro)
    assert rec.attrs["rate_hz"] == 200.0
    assert rec.sample_rate == pytest.approx(200.00256, rel=1e-6)
    from accel_bayes.data.positions import positions_document, write_positions

    doc = positions_document(method="map", reference_imu=0, means=POS, covs=np.zeros((3, 3, 3)),
                             diagnostics={"seconds": 1.0})
    pp = write_positions(doc, tmp_path / "positions.json")
    assert main(["export", str(tmp_path / "rec.nc"), "--positions", str(pp), "--format", "kalibr-imu",
                 "--out", str(tmp_path / "kalibr")]) == 0
    d = yaml.safe_load((tmp_path / "kalibr" / "imu1.yaml").read_text())
    assert d["update_rate"] == 200.0
    assert d["rostopic"] == ("/vi_sensor/imu1" if variant == "opencv" else "/imu1")  # the TOML's, else /imu<j>
    assert d["gyroscope_noise_density"] == pytest.approx(1.6968e-04, rel=1e-14)
    assert d["accelerometer_noise_density"] == pytest.approx(2.0e-3, rel=1e-14)
    assert d["gyroscope_random_walk"] == 1.9393e-05 and d["accelerometer_random_walk"] == 3.0e-3


def test_t_bs_gives_the_nominal_pose_and_is_compared(tmp_path, rig, capsys):
    """No pose in the description: T_BS's (position = translation, R(q) = R_BSᵀ).  A description
    pose 3 mm from T_BS: one warning line, the description's pose kept.  No position and no
    T_BS (wide CSV): refused naming imu[k].position."""
    R1 = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # sensor x = body y
    T_BS = np.tile(np.eye(4), (3, 1, 1))
    T_BS[:, :3, 3] = POS
    T_BS[1, :3, :3] = R1
    rec = _rig(T=400)
    # IMU 1's samples in its rotated frame: v_S = R_BSᵀ v_B.
    rec.acc[:, 1] = rec.acc[:, 1] @ R1
    rec.gyro[:, 1] = rec.gyro[:, 1] @ R1
    src = write_euroc(rec, tmp_path / "a", "opencv", T_BS=T_BS)
    assert _import(tmp_path, src, write_toml(tmp_path / "nopose.toml", positions=False)) == 0
    assert capsys.readouterr().err == ""
    got = read_recording(tmp_path / "rec.nc")
    np.testing.assert_array_equal(got.nominal_position, POS)
    R = quat_to_matrix(torch.as_tensor(got.nominal_orientation[1])).numpy()
    np.testing.assert_allclose(R, R1.T, atol=1e-15)

    toml = tmp_path / "off.toml"
    text = write_toml(tmp_path / "tmp.toml").read_text().replace(f"{POS[2].tolist()!r}", "[0.0, 0.053, 0.01]")
    toml.write_text(text + "")
    T_BS[1, :3, :3] = np.eye(3)  # imu1 identity here, to isolate IMU 2's offset
    src = write_euroc(_rig(T=400), tmp_path / "b", "euroc", T_BS=T_BS)
    assert _import(tmp_path, src, toml, out="rec2.nc") == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "imu[2] ('imu2')" in err[0] and "differs from the array description by 3 mm" in err[0]
    np.testing.assert_allclose(read_recording(tmp_path / "rec2.nc").nominal_position[2], [0.0, 0.053, 0.01])

    wide = tmp_path / "wide.csv"
    cols = [f"imu{k}_{kind}_{a} [{'m s^-2' if kind == 'acc' else 'rad s^-1'}]" for k in range(3)
            for kind in ("acc", "gyro") for a in "xyz"]
    wide.write_text("time [s]," + ",".join(cols) + "\n" + "\n".join(f"{t * 0.005},"
                    + ",".join(["0.1"] * 18) for t in range(5)) + "\n")
    assert main(["import-csv", str(wide), "--array", str(tmp_path / "nopose.toml"), "-o", str(tmp_path / "w.nc")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "imu[0].position: missing" in err and "T_BS" in err


def test_identical_files_refusal_names_causes_and_override(tmp_path, rig, capsys):
    """Three copies of one IMU's file (zero lever arm between them): the old refusal said
    "values look like deg/s" and advised editing a NetCDF attribute.  Now it names the likely
    causes and the option; the option imports, and later reads accept the file."""
    src = write_euroc(rig, tmp_path / "same", "euroc", T_BS=RIG_T_BS, same_as=0)
    toml = write_toml(tmp_path / "array.toml")
    assert _import(tmp_path, src, toml) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "identical samples" in err and "'imu0' and 'imu1'" in err and "--skip-gyro-unit-check" in err
    assert "attribute" not in err and not (tmp_path / "rec.nc").exists()
    assert _import(tmp_path, src, toml, "--skip-gyro-unit-check") == 0
    rec = read_recording(tmp_path / "rec.nc")  # validated on read: the override holds
    assert rec.attrs["gyro_unit_check"] == "skipped"
    # The check is not silenced for everything: the rig's own (different) files pass it untouched.
    assert _import(tmp_path, write_euroc(rig, tmp_path / "good", T_BS=RIG_T_BS), toml, out="good.nc") == 0
    assert "gyro_unit_check" not in read_recording(tmp_path / "good.nc").attrs


def test_mimu_importer_prints_gyro_noise_in_rad_s(tmp_path, capsys):
    """import-mimu printed the gyro noise in °/s while `info` prints rad/s."""

    from tests.data.test_mimu import _stream

    (tmp_path / "s.bin").write_bytes(_stream(n=40)[0])
    assert main(["import-mimu", str(tmp_path / "s.bin"), "-o", str(tmp_path / "m.nc")]) == 0
    line = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("noise std")][0]
    assert line.endswith("rad/s") and "°/s" not in line

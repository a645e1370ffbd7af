"""The README's "Your own array" section runs as written (issue #28, item 3).

The ``array.toml`` block is taken from README.md verbatim, a rig matching it is simulated and
written as ASL folders under ``my_run/``, and every command of the section's ``bash`` block is
run through the CLI in that order — ``calibrate`` replaced by ``map`` (same positions.json
contract, seconds instead of minutes), every other command exactly as printed.  The README's old
two-IMU example failed at calibrate with "nominal_position: accelerometer triads: at least 3 are
needed"; a two-IMU description (gyros on both) now imports and calibrates with the rig model.
"""
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from accel_bayes.cli import main
from accel_bayes.data.csv_import import read_array_description
from accel_bayes.physics.arrays import SensorArray
from accel_bayes.simulate import simulate
from tests.paths import REPO

README = REPO / "README.md"
HEADER = ("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
          "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]")


def _section_blocks():
    text = README.read_text(encoding="utf-8")
    sec = text[text.index("## Your own array"):]
    sec = sec[:sec.index("\n## ", 5)]
    blocks = re.findall(r"```(\w+)\n(.*?)```", sec, flags=re.S)
    toml = [b for lang, b in blocks if lang == "toml"]
    bash = [b for lang, b in blocks if lang == "bash"]
    assert len(toml) == 1 and len(bash) == 1, "the section's examples changed: update this test"
    return toml[0], bash[0]


def _commands(bash):
    out = []
    for line in bash.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            argv = shlex.split(line)
            assert argv[0] == "accel-bayes"
            out.append(argv[1:])
    return out


def _write_run(spec, folder, T=600, rate=200.0):
    K = len(spec.imus)
    arr = SensorArray(positions=torch.as_tensor(np.stack([s.position for s in spec.imus])),
                      orientations=torch.as_tensor(np.stack([s.orientation for s in spec.imus])),
                      has_acc=torch.ones(K, dtype=torch.bool), has_gyro=torch.ones(K, dtype=torch.bool),
                      acc_noise_std=torch.as_tensor([s.acc_noise_std for s in spec.imus]),
                      gyro_noise_std=torch.as_tensor([s.gyro_noise_std for s in spec.imus]),
                      acc_range=spec.acc_range)
    rec = simulate(arr, "smooth", T=T, rate=rate, seed=4).recording
    stamps = 1_000_000_000 + np.round(rec.time * 1e9).astype(np.int64)
    for k, s in enumerate(spec.imus):
        d = folder / s.label
        d.mkdir(parents=True)
        rows = [HEADER] + [",".join([str(int(stamps[t]))] + [repr(float(v)) for v in rec.gyro[t, k]]
                                    + [repr(float(v)) for v in rec.acc[t, k]]) for t in range(rec.T)]
        (d / "data.csv").write_text("\n".join(rows) + "\n")


def test_your_own_array_section_runs_as_written(tmp_path, monkeypatch, capsys):
    toml, bash = _section_blocks()
    monkeypatch.chdir(tmp_path)
    Path("array.toml").write_text(toml)
    spec = read_array_description("array.toml")
    assert len(spec.imus) >= 3
    _write_run(spec, Path("my_run"))
    commands = _commands(bash)
    assert [c[0] for c in commands] == ["import-csv", "calibrate", "export", "export"]
    for argv in commands:
        if argv[0] == "calibrate":
            argv = ["map"] + argv[1:]
        assert main(argv) == 0, (argv, capsys.readouterr().err)
    ov = yaml.safe_load(Path("kalibr_imu_chain.yaml").read_text().split("\n", 1)[1])
    assert sorted(ov) == [f"imu{j}" for j in range(len(spec.imus))]
    assert ov["imu0"]["rostopic"] == "/imu0" and ov["imu0"]["accelerometer_random_walk"] == 3e-3
    assert sorted(p.name for p in Path("kalibr").glob("*.yaml")) == [f"imu{j}.yaml" for j in range(len(spec.imus))]


def test_two_imu_description_imports_and_calibrates_as_a_rig(tmp_path, capsys):
    """The README's first two IMUs (both with gyros) import, and calibrate takes the rig model."""
    import json
    toml, _ = _section_blocks()
    two = toml[:toml.index('[[imu]]\nlabel = "imu2"')]
    (tmp_path / "array.toml").write_text(two)
    spec = read_array_description(tmp_path / "array.toml")
    assert len(spec.imus) == 2
    _write_run(spec, tmp_path / "my_run")
    assert main(["import-csv", str(tmp_path / "my_run"), "--array", str(tmp_path / "array.toml"),
                 "-o", str(tmp_path / "rec.nc")]) == 0, capsys.readouterr().err
    rc = main(["calibrate", str(tmp_path / "rec.nc"), "--out", str(tmp_path / "cal")])
    err = capsys.readouterr().err
    assert rc in (0, 4), err
    doc = json.loads((tmp_path / "cal" / "positions.json").read_text())
    assert doc["model"] == "rig" and "time_offset" in doc["imus"][1] and "orientation" in doc["imus"][1]
    # the chain carries the rig's estimated orientation and time offset
    assert main(["export", str(tmp_path / "rec.nc"), "--positions", str(tmp_path / "cal" / "positions.json"),
                 "-o", str(tmp_path / "chain.yaml")]) == 0, capsys.readouterr().err
    chain = yaml.safe_load((tmp_path / "chain.yaml").read_text().split("\n", 1)[1])
    assert chain["imu1"]["time_offset"] == pytest.approx(doc["imus"][1]["time_offset"]["mean"], abs=1e-12)
    assert np.allclose(chain["imu1"]["T_i_b_rotation_cov"], doc["imus"][1]["orientation_cov"], rtol=1e-9, atol=0)
    R = np.asarray(chain["imu1"]["T_i_b"])[:3, :3]
    q = np.asarray(doc["imus"][1]["orientation"])
    from accel_bayes.physics.geometry import quat_to_matrix
    R_doc = quat_to_matrix(torch.as_tensor(q)).numpy()
    assert np.allclose(R, R_doc, atol=1e-9) or np.allclose(R, R_doc.T, atol=1e-9)

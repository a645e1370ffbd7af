"""Every export format read back the way its consumer reads it (issue #28, item 2).

The readers below re-implement, read by read, the code of the tools that load these files:

* Kalibr, ``aslam_offline_calibration/kalibr/python/kalibr_common/ConfigReader.py``
  (ethz-asl/kalibr): ``ParametersBase.readYaml`` (``yaml.safe_load`` of the file),
  ``catch_keyerror`` (a missing key → RuntimeError "Field <key> missing in file"),
  ``ImuParameters.getRosTopic`` / ``checkRosTopic`` (``isinstance(topic, str)``),
  ``getUpdateRate`` / ``checkUpdateRate`` (``update_rate <= 0.0`` → "invalid update_rate"),
  ``getAccelerometerStatistics`` / ``checkAccelerometerStatistics`` and ``getGyroStatistics`` /
  ``checkGyroStatistics`` (density and random walk each ``<= 0.0`` → invalid; discrete noise =
  density / √(1/update_rate)) — the reads the issue cites as ConfigReader.py:467-472.
  ``kalibr_imu_camera_calibration/IccSensors.py``: the first ``--imu`` file is the reference IMU
  (``IccImu(..., isReferenceImu=True)`` for the first, its ``q_i_b``/``r_b`` fixed at identity /
  zero, ``addDesignVariables``), an IMU measurement stamped t is placed at ``t + timeOffset``
  (``addAccelerometerErrorTerms``: ``tk = im.stamp.toSec() + self.timeOffset``), and the
  chain's ``T_i_b`` / ``time_offset`` are what ``IccImu.ImuParameters.setImuPose`` /
  ``setTimeOffset`` write.
* OpenVINS, ``ov_core/src/utils/opencv_yaml_parse.h`` (rpng/open_vins): the IMU file is opened
  with ``cv::FileStorage``; ``parse_external(..., "imu0", node)`` looks the node up under the
  first-level ``imu0`` node; ``node_found`` iterates the map's items comparing ``item.name()``;
  a required node that is missing sets ``all_params_found_successfully = false`` (the node is
  "not found", and ov_msckf exits when the parser is not successful); a scalar is read with
  ``file_node[node_name] >> node_result``; a Matrix3d row by row,
  ``(double)file_node[node_name][r][c]`` for r, c < 3.  ``VioManagerOptions.h``
  (``print_and_load_noise``): ``gyroscope_noise_density``, ``gyroscope_random_walk``,
  ``accelerometer_noise_density``, ``accelerometer_random_walk`` of ``imu0``, all required;
  (``print_and_load_state``, "IMU intrinsics"): ``Tw``, ``Ta``, ``R_IMUtoACC``,
  ``R_IMUtoGYRO``, ``Tg`` of ``imu0``, required, and ``model``; only ``imu0`` is read.
  ``cv2.FileStorage`` is the same OpenCV parser.

Line numbers as issue #28 cites them (versions differ; the functions above are what is
re-implemented): ConfigReader.py:467-472 (random walks read and checked), IccSensors.py:775-777
(the first IMU is the reference), VioManagerOptions.h:159-162 (only imu0 read),
opencv_yaml_parse.h:360-365 (a missing required node fails the parse).
"""
import math

import numpy as np
import pytest
import yaml

from accel_bayes.cli import main
from accel_bayes.data.export import t_i_b
from accel_bayes.data.io import write_recording
from accel_bayes.data.positions import positions_document, write_positions
from accel_bayes.data.recording import Recording

cv2 = pytest.importorskip("cv2")

RATE = 200.0
SIG_A = np.array([0.02, 0.021, 0.022, 0.023])  # one per IMU, so that every entry can be traced
SIG_G = np.array([0.003, 0.0031, 0.0032, 0.0033])
RW_A = [3e-3, 3.1e-3, 3.2e-3, 3.3e-3]
RW_G = [2e-5, 2.1e-5, 2.2e-5, 2.3e-5]
H = math.sqrt(0.5)
QUAT = np.array([[1.0, 0.0, 0.0, 0.0], [H, 0.0, 0.0, -H], [0.0, 1.0, 0.0, 0.0], [H, H, 0.0, 0.0]])
POS = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.02, 0.0], [0.0, 0.0, 0.01]])


# ---------------------------------------------------------------- Kalibr's reads (ConfigReader.py)
class KalibrImuParameters:
    """ConfigReader.ImuParameters: the accessors Kalibr calls on each IMU (module docstring)."""

    def __init__(self, data, name="file"):
        self.data, self.yamlFile = data, name

    @classmethod
    def from_file(cls, path):
        with open(path) as f:  # ParametersBase.readYaml
            return cls(yaml.safe_load(f), str(path))

    def _get(self, key):  # catch_keyerror
        try:
            return self.data[key]
        except KeyError as e:
            raise RuntimeError(f"[ImuConfig Reader]: Field {e} missing in file: {self.yamlFile}") from None

    def getRosTopic(self):
        t = self._get("rostopic")
        if not isinstance(t, str):
            raise RuntimeError("rostopic has to be a string")
        return t

    def getUpdateRate(self):
        r = self._get("update_rate")
        if r <= 0.0:
            raise RuntimeError("invalid update_rate")
        return r

    def _stats(self, word):
        nd, rw = self._get(f"{word}_noise_density"), self._get(f"{word}_random_walk")
        if nd <= 0.0:
            raise RuntimeError(f"invalid {word}_noise_density")
        if rw <= 0.0:
            raise RuntimeError(f"invalid {word}_random_walk")
        return nd / math.sqrt(1.0 / self.getUpdateRate()), rw, nd

    def getAccelerometerStatistics(self):
        return self._stats("accelerometer")

    def getGyroStatistics(self):
        return self._stats("gyroscope")

    def read_all(self):
        """What IccImu.__init__ reads of every IMU it is given."""
        return {"rostopic": self.getRosTopic(), "update_rate": self.getUpdateRate(),
                "acc": self.getAccelerometerStatistics(), "gyro": self.getGyroStatistics()}


# ---------------------------------------------------------------- OpenVINS' reads (opencv_yaml_parse.h)
class OpenVinsImuReader:
    """parse_external(relative_config_imu, "imu0", …) through cv::FileStorage (module docstring)."""

    def __init__(self, path):
        self.fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
        assert self.fs.isOpened()
        self.all_params_found_successfully = True
        self.missing = []

    def _node(self, sensor, name):
        top = self.fs.getNode(sensor)
        found = top.isMap() and name in top.keys()  # node_found: some item.name() == node_name
        if not found:
            self.all_params_found_successfully = False
            self.missing.append(f"{sensor}.{name}")
            return None
        return top.getNode(name)

    def scalar(self, sensor, name, default=math.nan):
        n = self._node(sensor, name)
        return default if n is None else n.real()

    def string(self, sensor, name, default=""):
        n = self._node(sensor, name)
        return default if n is None else n.string()

    def matrix3(self, sensor, name, default):
        n = self._node(sensor, name)
        if n is None:
            return default
        M = np.eye(3)
        for r in range(min(n.size(), 3)):
            for c in range(min(n.at(r).size(), 3)):
                M[r, c] = n.at(r).at(c).real()
        return M

    def load(self):
        """VioManagerOptions: print_and_load_noise + the IMU intrinsics of print_and_load_state."""
        out = {k: self.scalar("imu0", k) for k in ("gyroscope_noise_density", "gyroscope_random_walk",
                                                   "accelerometer_noise_density", "accelerometer_random_walk")}
        out["model"] = self.string("imu0", "model", "kalibr")
        for name, default in (("Tw", np.eye(3)), ("Ta", np.eye(3)), ("R_IMUtoACC", np.eye(3)),
                              ("R_IMUtoGYRO", np.eye(3)), ("Tg", np.zeros((3, 3)))):
            out[name] = self.matrix3("imu0", name, default)
        self.fs.release()
        return out


# ---------------------------------------------------------------- fixtures
def _recording(tmp_path, ref=0, random_walks=True, T=60):
    rng = np.random.default_rng(1)
    K = 4
    attrs = {"acc_random_walk": RW_A, "gyro_random_walk": RW_G} if random_walks else {}
    rec = Recording(time=np.arange(T) / RATE, acc=rng.normal(0, 1, (T, K, 3)), gyro=rng.normal(0, 0.1, (T, K, 3)),
                    nominal_position=POS, nominal_orientation=QUAT, acc_noise_std=SIG_A, gyro_noise_std=SIG_G,
                    reference_imu=ref, attrs=attrs)
    return rec, write_recording(rec, tmp_path / "rec.nc")


def _positions(tmp_path, ref=0, time_offset=None):
    means = POS + np.array([[0.0, 0.0, 0.0], [1e-4, 0.0, 0.0], [0.0, -2e-4, 0.0], [0.0, 0.0, 3e-4]])
    means = means - means[ref]
    covs = np.tile(np.diag([1e-8, 2e-8, 3e-8]), (4, 1, 1))
    covs[ref] = 0.0
    doc = positions_document(method="map", reference_imu=ref, means=means, covs=covs, diagnostics={"seconds": 1.0})
    if time_offset is not None:
        for e in doc["imus"]:
            e["time_offset"] = {"mean": float(time_offset[e["imu"]]), "std": 1e-4}
    return write_positions(doc, tmp_path / "positions.json"), means


def _run(*args):
    return main(["export", *map(str, args)])


# ---------------------------------------------------------------- tests
@pytest.mark.parametrize("ref", [0, 2])
def test_every_format_through_the_consumers_reads(tmp_path, ref):
    """The chain, OpenVINS' file and Kalibr's per-IMU files, each read as its tool reads it;
    with reference_imu = 2 the reference is imu0 everywhere (the old export kept file order,
    so imu0 was IMU 0 with a non-identity T_i_b)."""
    rec, rp = _recording(tmp_path, ref=ref)
    pp, means = _positions(tmp_path, ref=ref)
    order = [ref] + [k for k in range(4) if k != ref]
    chain, ov, kdir = tmp_path / "chain.yaml", tmp_path / "kalibr_imu_chain.yaml", tmp_path / "kalibr"
    assert _run(rp, "--positions", pp, "-o", chain) == 0
    assert _run(rp, "--positions", pp, "--format", "openvins", "-o", ov) == 0
    assert _run(rp, "--positions", pp, "--format", "kalibr-imu", "--out", kdir) == 0

    doc = yaml.safe_load(chain.read_text())
    files = sorted(p.name for p in kdir.glob("imu*.yaml"))
    assert sorted(doc) == [f"imu{j}" for j in range(4)] and files == [f"imu{j}.yaml" for j in range(4)]
    for j, k in enumerate(order):
        for source in (KalibrImuParameters(doc[f"imu{j}"]), KalibrImuParameters.from_file(kdir / f"imu{j}.yaml")):
            got = source.read_all()
            assert got["update_rate"] == RATE and got["rostopic"] == f"/imu{j}"
            assert got["acc"][2] == SIG_A[k] / math.sqrt(RATE) and got["acc"][1] == RW_A[k]
            assert got["gyro"][2] == SIG_G[k] / math.sqrt(RATE) and got["gyro"][1] == RW_G[k]
            assert got["acc"][0] == pytest.approx(SIG_A[k], rel=1e-12)  # Kalibr's discrete σ is the recording's
        T = np.array(doc[f"imu{j}"]["T_i_b"])
        expect = np.eye(4) if k == ref else t_i_b(QUAT[k], QUAT[ref], means[k])
        np.testing.assert_array_equal(T, expect)
    np.testing.assert_array_equal(doc["imu0"]["T_i_b"], np.eye(4))  # IccSensors: the first IMU is the body

    r = OpenVinsImuReader(ov)
    got = r.load()
    assert r.all_params_found_successfully, r.missing
    assert got["accelerometer_noise_density"] == SIG_A[ref] / math.sqrt(RATE)
    assert got["gyroscope_random_walk"] == RW_G[ref] and got["accelerometer_random_walk"] == RW_A[ref]
    assert got["model"] == "kalibr"
    np.testing.assert_array_equal(got["Tw"], np.eye(3))
    np.testing.assert_array_equal(got["Tg"], np.zeros((3, 3)))
    assert f"imu0 <- {ref}" in chain.read_text()


def test_reader_reimplementations_refuse_what_the_tools_refuse(tmp_path):
    """The readers above are not vacuous: a file without a random walk fails both, as the tools do."""
    rec, rp = _recording(tmp_path)
    pp, _ = _positions(tmp_path)
    ov = tmp_path / "ov.yaml"
    assert _run(rp, "--positions", pp, "--format", "openvins", "-o", ov) == 0
    text = ov.read_text()
    cut = "\n".join(ln for ln in text.splitlines() if not ln.startswith("  accelerometer_random_walk:"))
    bad = tmp_path / "bad.yaml"
    bad.write_text(cut)
    r = OpenVinsImuReader(bad)
    r.load()
    assert not r.all_params_found_successfully and r.missing == ["imu0.accelerometer_random_walk"]
    d = yaml.safe_load(cut.split("\n", 1)[1])["imu1"]
    with pytest.raises(RuntimeError, match="Field 'accelerometer_random_walk' missing"):
        KalibrImuParameters(d).read_all()
    d["accelerometer_random_walk"] = 0.0
    with pytest.raises(RuntimeError, match="invalid accelerometer_random_walk"):
        KalibrImuParameters(d).read_all()


def test_unknown_random_walk_refused_naming_the_key(tmp_path, capsys):
    """Old behaviour: exit 0 and a file Kalibr rejects ("Field 'accelerometer_random_walk'
    missing").  Now: no rests, nothing stated → exit 2, one line naming the TOML key."""
    rec, rp = _recording(tmp_path, ref=1, random_walks=False)
    pp, _ = _positions(tmp_path, ref=1)
    for fmt, dest in (("kalibr", ["-o", tmp_path / "c.yaml"]), ("openvins", ["-o", tmp_path / "o.yaml"]),
                      ("kalibr-imu", ["--out", tmp_path / "k"])):
        assert _run(rp, "--positions", pp, "--format", fmt, *dest) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1
        assert "imu[1].acc_random_walk" in err and "the recording has no rests" in err  # the reference, first read
    assert not (tmp_path / "c.yaml").exists() and not (tmp_path / "o.yaml").exists() and not (tmp_path / "k").exists()


def test_random_walk_from_long_rests(tmp_path):
    """A recording with a long static stretch: the random walks come from its Allan deviation
    (within their stated standard error of the simulated truth), not from the attributes."""
    rate, L, K_A, K_G, N_A, N_G = 100.0, 300.0, 3e-3, 1e-4, 2e-3, 2e-4
    T, K = int(L * rate), 3
    rng = np.random.default_rng(5)

    def series(n, k, mean):
        return (mean + n * math.sqrt(rate) * rng.standard_normal((T, K, 3))
                + np.cumsum(k / math.sqrt(rate) * rng.standard_normal((T, K, 3)), 0))

    acc = series(N_A, K_A, np.array([0.0, 0.0, 9.81]))
    gyro = series(N_G, K_G, np.zeros(3))
    rec = Recording(time=np.arange(T) / rate, acc=acc, gyro=gyro, nominal_position=POS[:3] + [[0, 0, 0.001]] * 3,
                    acc_noise_std=np.full(K, N_A * math.sqrt(rate)), gyro_noise_std=np.full(K, N_G * math.sqrt(rate)),
                    segment=np.full(T, "static"), attrs={"rate_hz": rate})
    rp = write_recording(rec, tmp_path / "rest.nc")
    doc = positions_document(method="map", reference_imu=0, means=POS[:3], covs=np.zeros((3, 3, 3)),
                             diagnostics={"seconds": 1.0})
    pp = write_positions(doc, tmp_path / "p.json")
    out = tmp_path / "chain.yaml"
    assert _run(rp, "--positions", pp, "-o", out) == 0
    d = yaml.safe_load(out.read_text())
    for j in range(K):
        e = d[f"imu{j}"]
        for word, truth in (("accelerometer", K_A), ("gyroscope", K_G)):
            est, se = e[f"{word}_random_walk"], e[f"{word}_random_walk_std"]
            assert abs(est - truth) < 4 * se and se < 0.25 * est  # 4 se: tests/data/test_allan.py measures the calibration
    assert "rests, Allan deviation: 300 s static" in out.read_text()


def test_time_offset_from_positions_relative_to_reference(tmp_path):
    """DESIGN §7.3 time offsets (lag, positive = late) → Kalibr's time_offset relative to imu0,
    same sign (IccSensors: a sample stamped t is at t + timeOffset)."""
    rec, rp = _recording(tmp_path, ref=2)
    offsets = [0.004, -0.002, 0.001, 0.0]
    pp, _ = _positions(tmp_path, ref=2, time_offset=offsets)
    out = tmp_path / "chain.yaml"
    assert _run(rp, "--positions", pp, "-o", out) == 0
    d = yaml.safe_load(out.read_text())
    for j, k in enumerate([2, 0, 1, 3]):
        assert d[f"imu{j}"]["time_offset"] == pytest.approx(offsets[k] - offsets[2], abs=1e-18)
        assert d[f"imu{j}"]["time_offset_std"] == 1e-4


def test_time_offset_std_is_the_rigs_reported_one(tmp_path):
    """A rig's positions.json carries the Laplace ``std`` and its ``std_reported`` (the block sandwich
    where the misspecification test fired, DESIGN §7.3 added keys): the export wrote the Laplace std
    even where the rig had reported the sandwich — 4x too narrow on the MIMU pairs."""
    import json

    rec, rp = _recording(tmp_path)
    pp, _ = _positions(tmp_path, time_offset=[0.0, 0.001, -0.002, 0.0005])
    doc = json.loads(pp.read_text())
    for e in doc["imus"]:
        used = e["imu"] == 1
        e["time_offset"].update({"std_robust": 4e-4, "std_ratio": 4.0, "std_reported": 4e-4 if used else 1e-4,
                                 "robust_used": used})
        e["clock_drift"] = {"mean": 1e-5, "std": 2e-6, "std_reported": 5e-6 if used else 2e-6, "robust_used": used}
    pp.write_text(json.dumps(doc))
    out = tmp_path / "chain.yaml"
    assert _run(rp, "--positions", pp, "-o", out) == 0
    d = yaml.safe_load(out.read_text())
    assert d["imu1"]["time_offset_std"] == 4e-4 and d["imu1"]["clock_drift_std"] == 5e-6
    assert d["imu2"]["time_offset_std"] == 1e-4 and d["imu2"]["clock_drift_std"] == 2e-6
    text = out.read_text()
    assert text.count("block sandwich: the Laplace std failed its test") == 2 and "# s, Laplace" in text


def test_kalibr_imu_needs_out_dir(tmp_path, capsys):
    rec, rp = _recording(tmp_path)
    pp, _ = _positions(tmp_path)
    assert _run(rp, "--positions", pp, "--format", "kalibr-imu", "-o", tmp_path / "x.yaml") == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "--out DIR" in err and not (tmp_path / "x.yaml").exists()
    assert _run(rp, "--positions", pp, "--out", tmp_path / "d") == 2
    assert "expected -o FILE" in capsys.readouterr().err


def test_positions_draw_counts_are_ints(tmp_path):
    """positions.json stored draw counts as floats (1000.0): counts now stay JSON integers."""
    import json

    doc = positions_document(method="pmmh", reference_imu=0, means=np.zeros((3, 3)), covs=np.zeros((3, 3, 3)),
                             diagnostics={"seconds": 1.5, "rhat_max": 1.001, "ess_bulk_min": 812.4,
                                          "draws_per_chain": np.int64(1000), "checks": 2, "num_draws": 1,
                                          "converged": True})
    text = write_positions(doc, tmp_path / "p.json").read_text()
    d = json.loads(text)["diagnostics"]
    assert '"draws_per_chain": 1000,' in text and type(d["draws_per_chain"]) is int
    assert type(d["checks"]) is int and type(d["num_draws"]) is int and d["converged"] is True
    assert type(d["seconds"]) is float and d["ess_bulk_min"] == 812.4


# ---------------------------------------------------------------- multi-rate rigs, per-IMU rates
def test_multirate_rig_every_format_with_each_imus_own_rate(tmp_path):
    """A 125/250/250/400 Hz rig (DESIGN §7.1 union of stamps): each IMU's update_rate and
    densities from its own stamps, read by Kalibr's and OpenVINS' reads.  Before: refused
    ("recording.time: IMUs at different rates"), since one rate was written for all IMUs."""
    from experiments.clockgen import draw_case

    rec, truth = draw_case("rig", 190, n_imu=4, duration=3.0)
    assert list(truth["rate"]) == [125.0, 250.0, 250.0, 400.0]
    rec.reference_imu = 3  # the 400 Hz IMU: it must come first, with its own rate
    rec.attrs = {"acc_random_walk": RW_A, "gyro_random_walk": RW_G}
    rp = write_recording(rec, tmp_path / "rig.nc")
    means = np.asarray(truth["position"]) - np.asarray(truth["position"])[3]
    doc = positions_document(method="map", reference_imu=3, means=means, covs=np.tile(np.eye(3) * 1e-8, (4, 1, 1)),
                             orientations=np.asarray(truth["orientation"]), diagnostics={"seconds": 1.0})
    for e in doc["imus"]:
        e["time_offset"] = {"mean": float(truth["time_offset"][e["imu"]]), "std": 1e-4}
    pp = write_positions(doc, tmp_path / "positions.json")
    chain, ov, kdir = tmp_path / "chain.yaml", tmp_path / "ov.yaml", tmp_path / "kalibr"
    assert _run(rp, "--positions", pp, "-o", chain) == 0
    assert _run(rp, "--positions", pp, "--format", "openvins", "-o", ov) == 0
    assert _run(rp, "--positions", pp, "--format", "kalibr-imu", "--out", kdir) == 0
    d = yaml.safe_load(chain.read_text())
    order = [3, 0, 1, 2]
    for j, k in enumerate(order):
        for source in (KalibrImuParameters(d[f"imu{j}"]), KalibrImuParameters.from_file(kdir / f"imu{j}.yaml")):
            got = source.read_all()
            # the stamps jitter by 20-100 µs: their mean rate is the nominal one to 1e-4
            assert got["update_rate"] == pytest.approx(truth["rate"][k], rel=1e-4), (j, k)
            assert got["acc"][0] == pytest.approx(rec.acc_noise_std[k], rel=1e-12)  # Kalibr's σ = density·√rate
            assert got["gyro"][0] == pytest.approx(rec.gyro_noise_std[k], rel=1e-12)
            assert got["acc"][1] == RW_A[k]
        assert d[f"imu{j}"]["time_offset"] == pytest.approx(truth["time_offset"][k] - truth["time_offset"][3], abs=1e-15)
    np.testing.assert_array_equal(d["imu0"]["T_i_b"], np.eye(4))
    r = OpenVinsImuReader(ov)
    got = r.load()
    assert r.all_params_found_successfully, r.missing
    assert got["accelerometer_noise_density"] == pytest.approx(rec.acc_noise_std[3] / math.sqrt(400.0), rel=1e-4)


def test_density_from_the_stamps_mean_rate(tmp_path):
    """No stated rate: σ/√rate with the mean rate of the stamps.  At 1666 Hz (an LSM6DS ODR) with
    EuRoC-like uneven steps, 2.0e-3·√1666 must read back as 2.0e-3; the median step rounded to 3
    significant figures gave 1670 Hz and 0.0019976."""
    T, K = 4000, 3
    k = np.arange(T, dtype=np.int64)
    period_ns = round(1e9 / 1666)  # 600240 ns
    ns = k * (period_ns - 64) + (k // 3) * 192  # steps P−64, P−64, P+128: mean P, median P−64
    rng = np.random.default_rng(3)
    sig = 2.0e-3 * math.sqrt(1e9 / period_ns)
    rec = Recording(time=ns / 1e9, acc=rng.normal(0, 0.05, (T, K, 3)) + [0.0, 0.0, 9.81], gyro=rng.normal(0, 0.01, (T, K, 3)),
                    nominal_position=POS[:3], acc_noise_std=np.full(K, sig), gyro_noise_std=np.full(K, sig),
                    attrs={"acc_random_walk": RW_A[:3], "gyro_random_walk": RW_G[:3]})
    rp = write_recording(rec, tmp_path / "r.nc")
    doc = positions_document(method="map", reference_imu=0, means=POS[:3], covs=np.zeros((3, 3, 3)),
                             diagnostics={"seconds": 1.0})
    pp = write_positions(doc, tmp_path / "p.json")
    assert _run(rp, "--positions", pp, "--format", "kalibr-imu", "--out", tmp_path / "k") == 0
    got = KalibrImuParameters.from_file(tmp_path / "k" / "imu1.yaml").read_all()
    assert got["update_rate"] == pytest.approx(1e9 / period_ns, rel=1e-6)
    assert got["acc"][2] == pytest.approx(2.0e-3, rel=1e-6) and got["gyro"][2] == pytest.approx(2.0e-3, rel=1e-6)

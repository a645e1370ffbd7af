"""Importer for CSV recordings of an IMU array → format v1 (DESIGN §7.1).

Two layouts, one array description:

* **ASL / EuRoC**: a folder with one sub-folder per IMU, named by its label (``imu0/data.csv``,
  ``imu1/data.csv``, …), each with the header ::

      #timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]

  (``w_RS_S`` and ``a_RS_S`` are the angular rate and specific force of the sensor frame S,
  expressed in S: the sensor-frame outputs of §7.1).  A ``sensor.yaml`` beside a ``data.csv``
  (EuRoC's, with or without its ``%YAML:1.0`` line, OpenCV's ``!!opencv-matrix`` tags, fields
  it does not use ignored) is read where present: ``rate_hz`` (kept as the ``rate_hz``
  attribute, the stated rate of the export's densities), ``accelerometer_noise_density`` /
  ``gyroscope_noise_density`` (σ = density·√rate, used where the noise is stated rather than
  estimated), the two ``*_random_walk`` values (kept in the recording's attributes for
  :mod:`accel_bayes.data.export`) and ``T_BS``, the IMU's pose in the body frame B, taken as the
  array frame: the nominal pose where the description gives none, compared with it otherwise
  (:func:`_apply_t_bs`).  A UTF-8 byte-order mark and CRLF line ends are read as such.
* **Wide CSV**: one file, a time column and three columns per IMU and sensor.  Columns are named
  by the description's column map, by default ``<label>_acc_x`` … ``<label>_gyro_z`` and
  ``time``.

The **array description** is a TOML file (see :func:`read_array_description` for every key):
per IMU its label, nominal position (m, array frame), orientation (a quaternion (w, x, y, z) in
the §7.0 convention, array → sensor, or the 3×3 matrix R with v_sensor = R v_array), which
sensors it has, stated noise stds, ranges and random walks; the reference IMU.

What the importer does, and why:

* **Units** are those the header declares in brackets (``[m s^-2]``, ``[g]``, ``[rad s^-1]``,
  ``[deg s^-1]``, ``[ns]``, ``[us]``, ``[ms]``, ``[s]``) or, for columns without one, that the
  description's ``[csv.units]`` declares; a column with neither, a unit of the wrong kind, a
  header and a description that disagree, or one triad whose axes are in different units is
  refused.  Nothing is guessed.
* **Time stamps** are read as exact integers of nanoseconds (decimal text is converted digit by
  digit, not through a float) and every subtraction is done in integers before the conversion
  to seconds: ``time = (stamp − first stamp of the reference IMU) / 1e9``.  Stamps must be
  strictly increasing in every file.
* **One time base**: the reference IMU's stamps.  Every other IMU contributes, at each of them,
  its sample with the nearest stamp; a reference stamp whose nearest partner is farther than the
  tolerance (default a quarter of the reference's median sample period) refuses the import with
  the numbers, except at the two ends of the recording, where stamps outside the span every IMU
  covers are dropped (IMUs that start or stop at slightly different times) and counted.  Each
  IMU's own stamp minus ``time`` is kept in ``imu_time_offset`` (§7.1), so that the timing stays
  visible to the mismatch detector; the variable is written only when some offset is non-zero.
* **Noise**: with ``noise="rests"`` (default) the rests are found and the noise std estimated
  from them exactly as :mod:`accel_bayes.data.mimu` does (:func:`accel_bayes.data.segments.analyse_static`);
  without rests, and with ``noise="stated"``, the description's std, else the ``sensor.yaml``
  density·√rate, is used, and a missing one is refused.  ``source`` says which.
* **Clipping**: a sample is flagged where any axis has |value| ≥ the stated range (per IMU, else
  the array's); no range, no flags.
* **Gyro units**: the recording's rad/s plausibility check
  (:func:`accel_bayes.data.validation.gyro_unit_diagnostics`) runs before writing; a failure is
  refused with its likely causes in an import (identical files, triads without a lever arm,
  wrong positions, °/s under a rad/s header), and ``check_gyro_units=False``
  (``--skip-gyro-unit-check``) overrides it, recorded as ``gyro_unit_check = "skipped"`` so that
  later reads skip it too.
* Fewer than three IMUs with an accelerometer are refused naming ``[[imu]]`` unless they are a rig of
  two or more that all have gyroscopes (calibrated by the rig model; earlier versions refused two-IMU rigs).
* Refusals raise :class:`~accel_bayes.errors.UserError` whose message names the file, the line
  and the column, and what was expected.
"""
from __future__ import annotations

import copy
import csv
import math
import re
import tomllib
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np
import torch

from ..constants import DEG_TO_RAD, G0
from ..errors import UserError
from ..physics.geometry import matrix_to_quat
from .outputs import to_jsonable
from .recording import Recording
from .segments import analyse_static, segment_labels
from .validation import units_kind

__all__ = [
    "ASL_COLUMNS",
    "ImuSpec",
    "ArraySpec",
    "ImuStream",
    "CsvImport",
    "read_array_description",
    "read_sensor_yaml",
    "read_asl_imu",
    "read_wide_csv",
    "align_streams",
    "import_csv",
    "write_imported",
]

# (name in the ASL header, sensor, axis index)
ASL_COLUMNS = (("w_RS_S_x", "gyro", 0), ("w_RS_S_y", "gyro", 1), ("w_RS_S_z", "gyro", 2),
               ("a_RS_S_x", "acc", 0), ("a_RS_S_y", "acc", 1), ("a_RS_S_z", "acc", 2))
ASL_TIME = "timestamp"
AXES = ("x", "y", "z")
SENSORS = ("acc", "gyro")

# Factors to SI of the units each kind of column accepts, by canonical name.  The SI and degree
# spellings are those :func:`accel_bayes.data.validation.units_kind` knows; g and the sub-second time
# units are added here.  Time factors are integers: nanoseconds per unit.
_FACTORS = {"acc": {"m s-2": 1.0, "g": G0}, "gyro": {"rad s-1": 1.0, "deg s-1": DEG_TO_RAD},
            "time": {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}}
_MORE_UNITS = {"g": "g", "ns": "ns", "us": "us", "µs": "us", "ms": "ms"}
_HEADER_RE = re.compile(r"^(.*?)\s*\[([^\]]*)\]\s*$")


def _unit(text, kind: str) -> str | None:
    """The canonical name of unit ``text`` if it is a unit of ``kind`` ("acc", "gyro", "time")."""
    c = _MORE_UNITS.get(str(text).strip().lower()) or units_kind(text)
    return c if c in _FACTORS[kind] else None


# ------------------------------------------------------------------------------ description
@dataclass
class ImuSpec:
    """One IMU of an array description (SI units; NaN where not stated)."""

    label: str
    position: np.ndarray  # (3,) m, array frame
    orientation: np.ndarray  # (4,) array → sensor quaternion (w, x, y, z), §7.0
    has_acc: bool = True
    has_gyro: bool = True
    acc_noise_std: float = math.nan  # m s-2
    gyro_noise_std: float = math.nan  # rad s-1
    acc_range: float = math.nan  # m s-2
    gyro_range: float = math.nan  # rad s-1
    acc_random_walk: float = math.nan  # m s-3 / √Hz
    gyro_random_walk: float = math.nan  # rad s-2 / √Hz
    columns: dict = field(default_factory=dict)  # wide layout: {"time": name, "acc": [x, y, z], "gyro": [...]}
    rostopic: str = ""  # for the Kalibr export; "" = /imu<j>
    position_given: bool = True  # False: from sensor.yaml's T_BS (ASL layout) or refused
    orientation_given: bool = True  # False: from sensor.yaml's T_BS where present, else identity


@dataclass
class ArraySpec:
    """An array description (:func:`read_array_description`)."""

    path: Path
    imus: list
    reference_imu: int = 0
    description: str = ""
    acc_range: float = math.nan
    gyro_range: float = math.nan
    time_column: str = "time"
    units: dict = field(default_factory=dict)  # declared units for columns without [unit]: time/acc/gyro
    ignore_columns: tuple = ()

    @property
    def labels(self) -> list[str]:
        return [s.label for s in self.imus]


def _num(v, where: str, what: str, *, positive: bool = False) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (positive and v <= 0):
        raise UserError(f"{where}: expected {what}, got {v!r}")
    return float(v)


def _vec(v, n: int, where: str, what: str) -> np.ndarray:
    if not isinstance(v, list) or len(v) != n:
        raise UserError(f"{where}: expected {what}, got {v!r}")
    return np.array([_num(x, where, what) for x in v], dtype=np.float64)


def _orientation(e: dict, where: str) -> np.ndarray:
    if "orientation" in e and "orientation_matrix" in e:
        raise UserError(f"{where}: give orientation (quaternion) or orientation_matrix, not both")
    if "orientation_matrix" in e:
        m = e["orientation_matrix"]
        w = f"{where}.orientation_matrix"
        if not isinstance(m, list) or len(m) != 3:
            raise UserError(f"{w}: expected a 3x3 matrix R (v_sensor = R v_array) as 3 rows of 3 numbers")
        R = np.stack([_vec(r, 3, w, "a 3x3 matrix R (v_sensor = R v_array) as 3 rows of 3 numbers") for r in m])
        err = float(np.abs(R @ R.T - np.eye(3)).max())
        if err > 1e-6 or np.linalg.det(R) < 0:
            raise UserError(f"{w}: expected a rotation matrix (R Rᵀ = I within 1e-6, det +1); "
                            f"max |R Rᵀ − I| = {err:.2g}, det = {np.linalg.det(R):.6g}")
        return matrix_to_quat(torch.as_tensor(R, dtype=torch.float64)).numpy()
    if "orientation" not in e:
        return np.array([1.0, 0.0, 0.0, 0.0])
    w = f"{where}.orientation"
    q = _vec(e["orientation"], 4, w, "a unit quaternion [w, x, y, z] (array → sensor, DESIGN §7.0)")
    n = float(np.linalg.norm(q))
    if abs(n - 1.0) > 1e-6:
        raise UserError(f"{w}: expected a unit quaternion [w, x, y, z] (array → sensor, DESIGN §7.0), norm {n:.9g}")
    return q / n


_IMU_KEYS = {"label", "position", "orientation", "orientation_matrix", "sensors", "acc_noise_std",
             "gyro_noise_std", "acc_range", "gyro_range", "acc_random_walk", "gyro_random_walk", "columns", "rostopic"}
_TOP_KEYS = {"description", "reference_imu", "acc_range", "gyro_range", "csv", "imu"}


def read_array_description(path) -> ArraySpec:
    """Read an array description (TOML).  Keys (SI units; unknown keys are refused)::

        description = "my board"               # optional free text
        reference_imu = "imu0"                 # label (or 0-based index); default the first IMU
        acc_range = 156.9                      # optional, m s-2: |value| >= range flags clipping
        gyro_range = 34.9                      # optional, rad s-1

        [csv]                                  # optional; the wide layout and unit declarations
        time = "time"                          # the wide CSV's time column
        units = {time = "ns", acc = "m s^-2", gyro = "rad s^-1"}   # for columns without [unit]
        ignore = ["temperature"]               # wide CSV columns that are not IMU data

        [[imu]]                                # one per IMU; file order = labels 0..K-1
        label = "imu0"                         # ASL folder name / wide column prefix
        position = [0.0, 0.0, 0.0]             # m, array frame (ASL: may be left out when the
                                               #   IMU's sensor.yaml has T_BS, array frame = B)
        orientation = [1.0, 0.0, 0.0, 0.0]     # (w, x, y, z), v_sensor = R(q) v_array (§7.0);
                                               #   default T_BS's, else identity
        # orientation_matrix = [[1,0,0],[0,1,0],[0,0,1]]   # or R itself
        sensors = ["acc", "gyro"]              # default both
        acc_noise_std = 0.01                   # optional, m s-2 (white noise std per axis)
        gyro_noise_std = 0.001                 # optional, rad s-1
        acc_range = 156.9                      # optional per-IMU override, m s-2
        gyro_range = 34.9                      # optional, rad s-1
        acc_random_walk = 3e-3                 # optional, m s-3/√Hz (kept for export)
        gyro_random_walk = 2e-5                # optional, rad s-2/√Hz
        columns = {time = "t", acc = ["ax", "ay", "az"], gyro = ["gx", "gy", "gz"]}  # wide layout
        rostopic = "/imu0"                     # optional: the topic written by the Kalibr export

    Raises :class:`UserError` naming the file and key (``array.toml: imu[2].position: …``).
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such array description file")
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not a valid TOML array description ({exc})") from None
    try:
        return _parse_description(doc, path)
    except UserError as exc:
        raise UserError(f"{path}: {exc}") from None


def _parse_description(doc: dict, path: Path) -> ArraySpec:
    unknown = sorted(set(doc) - _TOP_KEYS)
    if unknown:
        raise UserError(f"{unknown[0]}: unknown key; expected one of {sorted(_TOP_KEYS)}")
    imus = doc.get("imu")
    if not isinstance(imus, list) or not imus:
        raise UserError("imu: expected at least one [[imu]] table")
    specs, seen = [], set()
    for i, e in enumerate(imus):
        w = f"imu[{i}]"
        bad = sorted(set(e) - _IMU_KEYS)
        if bad:
            raise UserError(f"{w}.{bad[0]}: unknown key; expected one of {sorted(_IMU_KEYS)}")
        label = e.get("label")
        if not isinstance(label, str) or not re.fullmatch(r"[A-Za-z0-9_.-]+", label) or set(label) == {"."}:
            # '.' and '..' would name the source folder or its parent as an IMU's folder
            raise UserError(f"{w}.label: expected a name of letters, digits, '_', '.', '-' other than '.' or '..', "
                            f"got {label!r}")
        if label in seen:
            raise UserError(f"{w}.label: {label!r} is used twice; expected one entry per IMU")
        seen.add(label)
        sensors = e.get("sensors", ["acc", "gyro"])
        if not isinstance(sensors, list) or not sensors or any(s not in SENSORS for s in sensors):
            raise UserError(f"{w}.sensors: expected a non-empty list of 'acc', 'gyro', got {sensors!r}")
        # A missing position is refused at import unless the IMU's sensor.yaml has T_BS (_apply_t_bs).
        pos = (_vec(e["position"], 3, f"{w}.position", "[x, y, z] in m (array frame)") if "position" in e
               else np.full(3, np.nan))
        spec = ImuSpec(label=label, position=pos, orientation=_orientation(e, w), has_acc="acc" in sensors,
                       has_gyro="gyro" in sensors, position_given="position" in e,
                       orientation_given="orientation" in e or "orientation_matrix" in e)
        if "rostopic" in e:
            if not isinstance(e["rostopic"], str) or not e["rostopic"].strip():
                raise UserError(f"{w}.rostopic: expected a topic name such as '/imu0', got {e['rostopic']!r}")
            spec.rostopic = e["rostopic"]
        for key, unit in (("acc_noise_std", "m s-2"), ("gyro_noise_std", "rad s-1"), ("acc_range", "m s-2"),
                          ("gyro_range", "rad s-1"), ("acc_random_walk", "m s-3 Hz^-1/2"),
                          ("gyro_random_walk", "rad s-2 Hz^-1/2")):
            if key in e:
                setattr(spec, key, _num(e[key], f"{w}.{key}", f"a positive number ({unit})", positive=True))
        cols = e.get("columns", {})
        if not isinstance(cols, dict) or set(cols) - {"time", "acc", "gyro"}:
            raise UserError(f"{w}.columns: expected a table with keys time, acc, gyro")
        for s in SENSORS:
            if s in cols and (not isinstance(cols[s], list) or len(cols[s]) != 3
                              or not all(isinstance(c, str) for c in cols[s])):
                raise UserError(f"{w}.columns.{s}: expected 3 column names [x, y, z]")
        if "time" in cols and not isinstance(cols["time"], str):
            raise UserError(f"{w}.columns.time: expected a column name")
        spec.columns = dict(cols)
        specs.append(spec)
    labels = [s.label for s in specs]
    ref = doc.get("reference_imu", 0)
    if isinstance(ref, str):
        if ref not in labels:
            raise UserError(f"reference_imu: {ref!r} is not an IMU label; expected one of {labels}")
        ref = labels.index(ref)
    elif isinstance(ref, bool) or not isinstance(ref, int) or not 0 <= ref < len(specs):
        raise UserError(f"reference_imu: expected an IMU label or an index 0..{len(specs) - 1}, got {ref!r}")
    if not specs[ref].has_acc:
        raise UserError(f"reference_imu: {labels[ref]!r} has no accelerometer; expected an IMU with one")
    out = ArraySpec(path=path, imus=specs, reference_imu=int(ref), description=str(doc.get("description", "")))
    for key, unit in (("acc_range", "m s-2"), ("gyro_range", "rad s-1")):
        if key in doc:
            setattr(out, key, _num(doc[key], key, f"a positive number ({unit})", positive=True))
    c = doc.get("csv", {})
    if not isinstance(c, dict) or set(c) - {"time", "units", "ignore"}:
        raise UserError("csv: expected a table with keys time, units, ignore")
    if "time" in c:
        if not isinstance(c["time"], str):
            raise UserError(f"csv.time: expected a column name, got {c['time']!r}")
        out.time_column = c["time"]
    units = c.get("units", {})
    if not isinstance(units, dict) or set(units) - {"time", "acc", "gyro"}:
        raise UserError("csv.units: expected a table with keys time, acc, gyro")
    for kind, u in units.items():
        cu = _unit(u, kind) if isinstance(u, str) else None
        if cu is None:
            raise UserError(f"csv.units.{kind}: expected one of {sorted(_FACTORS[kind])}, got {u!r}")
        out.units[kind] = cu
    ign = c.get("ignore", [])
    if not isinstance(ign, list) or not all(isinstance(x, str) for x in ign):
        raise UserError("csv.ignore: expected a list of column names")
    out.ignore_columns = tuple(ign)
    return out


# ------------------------------------------------------------------------------ CSV tables
class _Table:
    """A CSV file as text cells, with the file line of every row, for messages that point at it."""

    def __init__(self, path: Path):
        self.path = path
        # utf-8-sig: a byte-order mark (Windows editors) is not part of the first column's name;
        # newline="" lets csv take CRLF line ends as ends, not as data.
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.reader(f)
            try:
                header = next(reader)
            except StopIteration:
                raise UserError(f"{path}:1: empty file; expected a header line") from None
            except (csv.Error, UnicodeDecodeError) as exc:
                raise UserError(f"{path}:1: not readable as CSV ({exc})") from None
            if header and header[0].startswith("#"):
                header[0] = header[0][1:]
            self.raw = [h.strip() for h in header]
            self.names, self.units = [], []
            for h in self.raw:
                m = _HEADER_RE.match(h)
                self.names.append(m.group(1).strip() if m else h)
                self.units.append(m.group(2).strip() if m else None)
            dup = [n for n in set(self.names) if self.names.count(n) > 1]
            if dup:
                raise UserError(f"{path}:1: column {dup[0]!r} appears {self.names.count(dup[0])} times; expected once")
            C = len(self.raw)
            rows, lines = [], []
            try:
                for row in reader:
                    if not row or (len(row) == 1 and not row[0].strip()):
                        continue  # blank line
                    if len(row) != C:
                        raise UserError(f"{path}:{reader.line_num}: expected {C} fields (as in the header), got {len(row)}")
                    rows.append(row)
                    lines.append(reader.line_num)
            except (csv.Error, UnicodeDecodeError) as exc:
                raise UserError(f"{path}:{reader.line_num}: not readable as CSV ({exc})") from None
        if not rows:
            raise UserError(f"{path}:2: no data rows; expected at least one sample after the header")
        self.cells = np.array(rows, dtype=str)
        self.lines = np.array(lines, dtype=np.int64)

    def index(self, name: str, what: str) -> int:
        if name not in self.names:
            raise UserError(f"{self.path}:1: missing column {name!r} ({what}); the header has {self.raw}")
        return self.names.index(name)

    def unit(self, col: int, kind: str, declared: str | None) -> str:
        """The canonical unit of a column: the header's ``[unit]``, else the declared one (already
        canonical); refused if neither, of the wrong kind, or if both are given and disagree."""
        got = self.units[col]
        if got is None:
            if declared is None:
                raise UserError(f"{self.path}:1: column {self.raw[col]!r}: no unit; expected '{self.names[col]} [unit]' "
                                f"in the header or csv.units.{kind} in the array description")
            return declared
        c = _unit(got, kind)
        if c is None:
            raise UserError(f"{self.path}:1: column {self.raw[col]!r}: unit {got!r} is not a {kind} unit; expected one of "
                            f"{sorted(_FACTORS[kind])}")
        if declared is not None and c != declared:
            raise UserError(f"{self.path}:1: column {self.raw[col]!r}: the header says {got!r}, csv.units.{kind} says "
                            f"{declared!r}; expected them to agree")
        return c

    def floats(self, col: int) -> np.ndarray:
        x = self.cells[:, col]
        try:
            v = x.astype(np.float64)
        except ValueError:
            v = None
        if v is None or not np.isfinite(v).all():
            for i, s in enumerate(x.tolist()):
                try:
                    ok = math.isfinite(float(s))
                except ValueError:
                    ok = False
                if not ok:
                    raise UserError(f"{self.path}:{self.lines[i]}: column {self.raw[col]!r}: expected a finite number, "
                                    f"got {s!r}")
        return v

    def stamps_ns(self, col: int, unit: str) -> np.ndarray:
        """Integer nanoseconds, exactly: no float ever holds a stamp."""
        x = self.cells[:, col]
        factor = _FACTORS["time"][unit]
        if factor == 1:
            try:
                return x.astype(np.int64)
            except (ValueError, OverflowError):
                pass
        out = np.empty(x.shape[0], dtype=np.int64)
        for i, s in enumerate(x.tolist()):
            try:
                d = Decimal(s.strip()) * factor
                ok = d.is_finite() and d == d.to_integral_value() and abs(d) < 2**63
            except InvalidOperation:
                ok = False
            if not ok:
                raise UserError(f"{self.path}:{self.lines[i]}: column {self.raw[col]!r}: expected a time stamp in {unit} "
                                f"that is a whole number of nanoseconds, got {s!r}")
            out[i] = int(d)
        return out

    def check_increasing(self, col: int, ns: np.ndarray) -> None:
        d = np.diff(ns)
        bad = np.flatnonzero(d <= 0)
        if bad.size:
            i = int(bad[0]) + 1
            what = "duplicated" if d[i - 1] == 0 else "earlier than the one before"
            raise UserError(f"{self.path}:{self.lines[i]}: column {self.raw[col]!r}: time stamp {self.cells[i, col]} is "
                            f"{what} (line {self.lines[i - 1]}: {self.cells[i - 1, col]}); "
                            "expected strictly increasing stamps")


@dataclass
class ImuStream:
    """One IMU's samples as read: own stamps (int64 ns), outputs in SI units, sensor frame."""

    label: str
    file: Path
    stamps_ns: np.ndarray  # (N,) int64
    acc: np.ndarray | None  # (N, 3) m s-2
    gyro: np.ndarray | None  # (N, 3) rad s-1
    sensor_yaml: dict = field(default_factory=dict)


def _triad(table: _Table, names, kind: str, declared: str | None) -> np.ndarray:
    cols = [table.index(n, f"{kind} {a} axis") for n, a in zip(names, AXES)]
    units = [table.unit(c, kind, declared) for c in cols]
    if len(set(units)) > 1:
        j = next(j for j in range(3) if units[j] != units[0])
        raise UserError(f"{table.path}:1: column {table.raw[cols[j]]!r}: unit {units[j]!r} differs from {units[0]!r} of "
                        f"{table.raw[cols[0]]!r}; expected one unit per triad (mixed units)")
    return np.stack([table.floats(c) for c in cols], -1) * _FACTORS[kind][units[0]]


def _yaml_loader():
    """PyYAML's safe loader that also reads OpenCV's ``!!opencv-matrix`` (rows, cols, data → an
    array) and skips any other unknown tag (None): fields this importer does not use must not
    fail the import."""
    import yaml

    class Loader(yaml.SafeLoader):
        pass

    def opencv_matrix(loader, node):
        m = loader.construct_mapping(node, deep=True)
        try:
            return np.asarray(m["data"], dtype=np.float64).reshape(int(m["rows"]), int(m["cols"]))
        except (KeyError, TypeError, ValueError):
            return None  # malformed: treated as absent, and refused only if it is a field we use

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", opencv_matrix)
    Loader.add_multi_constructor("", lambda loader, suffix, node: None)
    return Loader


def _t_bs(v, path: Path) -> np.ndarray:
    """sensor.yaml's ``T_BS`` (EuRoC: {cols, rows, data}; OpenCV: !!opencv-matrix) as a checked 4×4."""
    if isinstance(v, dict):
        try:
            v = np.asarray(v["data"], dtype=np.float64).reshape(int(v["rows"]), int(v["cols"]))
        except (KeyError, TypeError, ValueError):
            v = None
    T = None if v is None else np.asarray(v, dtype=np.float64)
    what = "a 4x4 rigid transform (rows, cols, data) with a rotation block and last row [0, 0, 0, 1]"
    if T is None or T.shape != (4, 4) or not np.isfinite(T).all():
        raise UserError(f"{path}: T_BS: expected {what}")
    R = T[:3, :3]
    if (np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0
            or np.abs(T[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-12):
        raise UserError(f"{path}: T_BS: expected {what} (R Rᵀ = I within 1e-6)")
    return T


def read_sensor_yaml(path) -> dict:
    """The fields of an ASL/EuRoC ``sensor.yaml`` this importer uses, in SI units: ``rate_hz``,
    ``accelerometer_noise_density`` (m s-2/√Hz), ``gyroscope_noise_density`` (rad s-1/√Hz),
    ``accelerometer_random_walk``, ``gyroscope_random_walk`` and ``T_BS`` (4×4: p_B = T_BS p_S,
    the sensor's pose in the body frame) — those present.  OpenCV's ``%YAML:1.0`` first line, a
    byte-order mark, CRLF line ends, ``!!opencv-matrix`` tags and fields it does not use are
    accepted."""
    import yaml

    path = Path(path)
    text = path.read_text(encoding="utf-8-sig")
    text = re.sub(r"\A%YAML:1\.0[^\n]*\n", "", text)  # OpenCV's header, which PyYAML does not read
    try:
        doc = yaml.load(text, Loader=_yaml_loader())
    except yaml.YAMLError as exc:
        raise UserError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a YAML mapping with rate_hz and noise densities")
    out = {}
    for key in ("rate_hz", "accelerometer_noise_density", "gyroscope_noise_density",
                "accelerometer_random_walk", "gyroscope_random_walk"):
        if key in doc:
            v = doc[key]
            if isinstance(v, str):  # YAML 1.1 reads "2e-3" (no point in the mantissa) as a string
                try:
                    v = float(v)
                except ValueError:
                    pass
            out[key] = _num(v, f"{path}: {key}", "a positive number", positive=True)
    if "T_BS" in doc:
        out["T_BS"] = _t_bs(doc["T_BS"], path)
    return out


# A sensor.yaml T_BS and a description's pose further apart than this give a warning.
T_BS_TOLERANCE_M, T_BS_TOLERANCE_DEG = 1e-3, 0.5


def _apply_t_bs(spec: ArraySpec, streams) -> list[str]:
    """Nominal poses from sensor.yaml's T_BS where the description has none (array frame = B:
    position = T_BS translation, R(q) = R_BSᵀ since v_S = R_BSᵀ v_B); where it has one, compare
    and return a one-line warning per IMU beyond :data:`T_BS_TOLERANCE_M` / ``_DEG`` (the
    description wins: it is what was written for this rig).  Refuses a missing position that
    no T_BS supplies."""
    warnings = []
    for i, (s, st) in enumerate(zip(spec.imus, streams)):
        T = st.sensor_yaml.get("T_BS")
        if T is None:
            if not s.position_given:
                raise UserError(f"{spec.path}: imu[{i}].position: missing, and IMU {s.label!r} has no sensor.yaml "
                                "with T_BS; expected [x, y, z] in m (array frame)")
            continue
        q_bs = matrix_to_quat(torch.as_tensor(T[:3, :3].T.copy(), dtype=torch.float64)).numpy()
        if not s.position_given:
            s.position = T[:3, 3].copy()
        if not s.orientation_given:
            s.orientation = q_bs
        dp = float(np.linalg.norm(s.position - T[:3, 3]))
        dang = math.degrees(2.0 * math.acos(min(1.0, abs(float(np.dot(s.orientation, q_bs))))))
        if dp > T_BS_TOLERANCE_M or dang > T_BS_TOLERANCE_DEG:
            warnings.append(f"imu[{i}] ({s.label!r}): {st.file.parent / 'sensor.yaml'} T_BS differs from the array "
                            f"description by {dp * 1e3:.3g} mm and {dang:.3g}° (tolerance {T_BS_TOLERANCE_M * 1e3:g} mm, "
                            f"{T_BS_TOLERANCE_DEG:g}°); the description's pose is used")
    return warnings


def _gyro_unit_refusal(flag: str, acc, gyro, spec: ArraySpec) -> str:
    """The gyro-unit check's refusal, with the likely causes of a failed check in an import."""
    K = len(spec.imus)
    causes = []
    same = [(a, b) for a in range(K) for b in range(a + 1, K)
            if np.array_equal(acc[:, a], acc[:, b], equal_nan=True)
            and (gyro is None or np.array_equal(gyro[:, a], gyro[:, b], equal_nan=True))]
    if same:
        a, b = same[0]
        causes.append(f"IMUs {spec.labels[a]!r} and {spec.labels[b]!r} have identical samples (the same data "
                      "file twice? identical files have no lever arm between them)")
    pos = np.stack([s.position for s in spec.imus if s.has_acc])
    spread = float(np.linalg.norm(pos - pos.mean(0), axis=1).max()) if len(pos) else 0.0
    if spread < 5e-3:
        causes.append(f"the triads lie within {spread * 1e3:.2g} mm of their centre (too small a lever arm to "
                      "check the gyro against)")
    causes.append("a lever arm in the description that the data do not have (IMUs on different bodies, wrong "
                  "positions)")
    causes.append("gyro columns in °/s under a [rad s^-1] header (then declare [deg s^-1])")
    evidence = flag.split(";")[0]  # the measured evidence, without advice about file attributes
    return (f"{evidence}; likely causes: {'; '.join(causes)}; if the gyro values are rad/s, import with "
            "--skip-gyro-unit-check")


def read_asl_imu(folder, spec: ImuSpec, units: dict | None = None) -> ImuStream:
    """Read ``folder/data.csv`` (ASL layout, module docstring) and ``folder/sensor.yaml`` if present."""
    folder = Path(folder)
    f = folder / "data.csv"
    if not f.is_file():
        raise UserError(f"{f}: missing; expected the ASL data.csv of IMU {spec.label!r}")
    table = _Table(f)
    units = units or {}
    tcol = table.index(ASL_TIME, "time stamps")
    stamps = table.stamps_ns(tcol, table.unit(tcol, "time", units.get("time")))
    table.check_increasing(tcol, stamps)
    acc = _triad(table, [n for n, s, _ in ASL_COLUMNS if s == "acc"], "acc", units.get("acc")) if spec.has_acc else None
    gyro = _triad(table, [n for n, s, _ in ASL_COLUMNS if s == "gyro"], "gyro", units.get("gyro")) if spec.has_gyro else None
    y = folder / "sensor.yaml"
    return ImuStream(spec.label, f, stamps, acc, gyro, read_sensor_yaml(y) if y.is_file() else {})


def read_wide_csv(path, array: ArraySpec) -> list[ImuStream]:
    """Read a wide CSV: every IMU's columns from the description's column map (default
    ``<label>_acc_x`` …, the time column ``csv.time``).  Columns that no IMU uses and that are not
    listed in ``csv.ignore`` are refused (an IMU missing from the description)."""
    path = Path(path)
    table = _Table(path)
    used, streams = set(array.ignore_columns), []
    for s in array.imus:
        cols = s.columns
        tname = cols.get("time", array.time_column)
        tcol = table.index(tname, f"time stamps of IMU {s.label!r}")
        stamps = table.stamps_ns(tcol, table.unit(tcol, "time", array.units.get("time")))
        table.check_increasing(tcol, stamps)
        used.add(tname)
        out = {}
        for kind, has in (("acc", s.has_acc), ("gyro", s.has_gyro)):
            if not has:
                continue
            names = cols.get(kind, [f"{s.label}_{kind}_{a}" for a in AXES])
            out[kind] = _triad(table, names, kind, array.units.get(kind))
            used.update(names)
        streams.append(ImuStream(s.label, path, stamps, out.get("acc"), out.get("gyro")))
    extra = [r for n, r in zip(table.names, table.raw) if n not in used]
    if extra:
        raise UserError(f"{path}:1: column {extra[0]!r} belongs to no IMU of {array.path.name} (labels {array.labels}); "
                        "expected it in an IMU's columns, or listed in csv.ignore")
    return streams


# ------------------------------------------------------------------------------ time base
def align_streams(streams: list[ImuStream], reference: int, tolerance_ns: int):
    """Put the IMUs on the reference IMU's stamps (module docstring).

    Returns ``(base_ns (T,), index (T, K) into each stream, rows)``, ``rows`` one dict per IMU
    with ``label``, ``samples``, ``used``, ``worst_ns`` (largest |own stamp − base stamp| kept)
    and ``median_ns`` (median signed offset); ``dropped_ends`` (reference stamps outside the span
    all IMUs cover) is in every row.  Raises :class:`UserError` with the numbers where a stamp
    inside the common span has no partner within ``tolerance_ns``, or two stamps share one.
    """
    base = streams[reference].stamps_ns
    lo = max(int(s.stamps_ns[0]) for s in streams) - tolerance_ns
    hi = min(int(s.stamps_ns[-1]) for s in streams) + tolerance_ns
    keep = (base >= lo) & (base <= hi)
    if not keep.any():
        raise UserError(f"time: the IMUs' recordings do not overlap (reference {streams[reference].label!r} spans "
                        f"{base[0]}..{base[-1]} ns); expected a common time span")
    first, last = int(np.argmax(keep)), int(len(keep) - np.argmax(keep[::-1]))
    base = base[first:last]
    dropped = len(keep) - base.size
    index = np.empty((base.size, len(streams)), dtype=np.int64)
    rows = []
    for k, s in enumerate(streams):
        st = s.stamps_ns
        j = np.clip(np.searchsorted(st, base), 1, st.size - 1) if st.size > 1 else np.zeros(base.size, np.int64)
        if st.size > 1:
            # Nearest of the two neighbours, compared in integers.
            left_closer = (base - st[j - 1]) <= (st[j] - base)
            j = np.where(left_closer, j - 1, j)
        off = st[j] - base
        bad = np.flatnonzero(np.abs(off) > tolerance_ns)
        if bad.size:
            i = int(bad[np.argmax(np.abs(off[bad]))])
            raise UserError(
                f"{s.file}: {bad.size} of {base.size} stamps of the reference IMU {streams[reference].label!r} have no "
                f"sample of IMU {s.label!r} within {tolerance_ns / 1e6:g} ms (worst {abs(int(off[i])) / 1e6:g} ms, at "
                f"reference stamp {int(base[i])} ns); expected one sample per reference stamp — raise --time-tolerance "
                "or fix the stamps")
        if np.any(np.diff(j) == 0):
            i = int(np.flatnonzero(np.diff(j) == 0)[0])
            raise UserError(f"{s.file}: sample at stamp {int(st[j[i]])} ns of IMU {s.label!r} is the nearest to two "
                            f"reference stamps ({int(base[i])} and {int(base[i + 1])} ns); expected a tolerance below "
                            "half the sample period (--time-tolerance)")
        index[:, k] = j
        rows.append({"label": s.label, "samples": int(st.size), "used": int(base.size),
                     "worst_ns": int(np.abs(off).max()), "median_ns": int(np.median(off)), "dropped_ends": int(dropped)})
    return base, index, rows


# ------------------------------------------------------------------------------ import
@dataclass
class CsvImport:
    """What :func:`import_csv` returns.

    recording : the format-v1 :class:`Recording`; its ``imu_time_offset`` (T, K) s holds each
        IMU's own stamp minus ``time`` (§7.1), or None when all are zero (every IMU stamped at the
        reference's instants).
    lines : the import report, one line per fact.
    """

    recording: Recording
    lines: list
    warnings: list = field(default_factory=list)  # one line each (the CLI prints them on stderr)

    @property
    def imu_time_offset(self) -> np.ndarray | None:
        """(T, K) s, the recording's ``imu_time_offset``."""
        return self.recording.imu_time_offset


def import_csv(source, array, *, time_tolerance: float | None = None, noise: str = "rests",
               tol_deg: float = 2.0, check_gyro_units: bool = True, **static_kwargs) -> CsvImport:
    """Import a CSV recording of an IMU array (module docstring).

    source : a folder (ASL layout, one sub-folder per IMU label) or a wide CSV file.
    array : the description, a path to its TOML file or an :class:`ArraySpec`.
    time_tolerance : s — largest |own stamp − reference stamp| accepted when putting IMUs on one
        time base; default a quarter of the reference IMU's median sample period.
    noise : "rests" (estimated from the rests where found, stated otherwise) or "stated" (no
        rest detection, the description's / sensor.yaml's noise).
    tol_deg, static_kwargs : rest detection, as :func:`accel_bayes.data.mimu.import_mimu`.
    check_gyro_units : the rad/s plausibility check
        (:func:`accel_bayes.data.validation.gyro_unit_diagnostics`); a failure is refused naming
        its likely causes.  False skips it here and, through the recording's
        ``gyro_unit_check = "skipped"`` attribute, in every later read.
    """
    if noise not in ("rests", "stated"):
        raise UserError(f"noise: expected 'rests' or 'stated', got {noise!r}")
    # A copy: poses filled in from sensor.yaml must not leak into the caller's description.
    spec = copy.deepcopy(array) if isinstance(array, ArraySpec) else read_array_description(array)
    source = Path(source)
    if not source.exists():
        raise FileNotFoundError(f"{source}: no such CSV file or ASL folder")
    K, ref = len(spec.imus), spec.reference_imu
    n_acc = sum(s.has_acc for s in spec.imus)
    rig = n_acc >= 2 and all(s.has_gyro for s in spec.imus if s.has_acc)  # the rig model's case (issue #28)
    if n_acc < 3 and not rig:
        # Said here, in the description's terms, rather than by the recording's validation
        # ("nominal_position: accelerometer triads …"), which names an internal field.
        raise UserError(f"{spec.path}: [[imu]]: {n_acc} IMU{'s' if n_acc != 1 else ''} with an accelerometer; "
                        "expected at least 3 not on one line, or at least 2 that all have gyroscopes (a rig)")
    if source.is_dir():
        layout = "ASL"
        found = sorted(p.name for p in source.iterdir() if (p / "data.csv").is_file())
        extra = [n for n in found if n not in spec.labels]
        if extra:
            raise UserError(f"{source / extra[0] / 'data.csv'}: IMU {extra[0]!r} is not in {spec.path.name}; expected "
                            f"one [[imu]] entry per IMU folder (labels {spec.labels})")
        streams = [read_asl_imu(_imu_folder(source, s.label), s, spec.units) for s in spec.imus]
    else:
        layout = "wide CSV"
        streams = read_wide_csv(source, spec)
    warns = _apply_t_bs(spec, streams)

    ref_period = np.median(np.diff(streams[ref].stamps_ns)) if streams[ref].stamps_ns.size > 1 else 0
    if time_tolerance is None:
        tol_ns = int(ref_period // 4)
    else:
        if not (time_tolerance >= 0 and math.isfinite(time_tolerance)):
            raise UserError(f"--time-tolerance: expected a non-negative number of seconds, got {time_tolerance}")
        tol_ns = int(round(time_tolerance * 1e9))
    base, index, rows = align_streams(streams, ref, tol_ns)
    T = base.size
    # Integer differences first; only the differences become float seconds.
    time = (base - base[0]).astype(np.float64) / 1e9
    offsets_ns = np.stack([streams[k].stamps_ns[index[:, k]] - base for k in range(K)], -1)
    offsets = offsets_ns.astype(np.float64) / 1e9 if np.any(offsets_ns) else None

    acc = np.full((T, K, 3), np.nan)
    any_gyro = any(s.has_gyro for s in spec.imus)
    gyro = np.full((T, K, 3), np.nan) if any_gyro else None
    for k, (s, st) in enumerate(zip(spec.imus, streams)):
        if st.acc is not None:
            acc[:, k] = st.acc[index[:, k]]
        if st.gyro is not None:
            gyro[:, k] = st.gyro[index[:, k]]

    # Clipping from the stated ranges (per IMU, else the array's).
    def ranges(kind):
        r = np.array([getattr(s, f"{kind}_range") for s in spec.imus])
        return np.where(np.isnan(r), getattr(spec, f"{kind}_range"), r)

    acc_r, gyro_r = ranges("acc"), ranges("gyro")
    acc_clipped = None if np.isnan(acc_r).all() else (np.abs(acc) >= acc_r[None, :, None]).any(-1)
    gyro_clipped = None if gyro is None or np.isnan(gyro_r).all() else (np.abs(gyro) >= gyro_r[None, :, None]).any(-1)

    acc_flagged, gyro_flagged, mark_lines = _plausibility_marks(spec, acc, gyro, time, acc_r, gyro_r)

    def common(r, present):
        r = r[present]
        return float(r[0]) if r.size and np.isfinite(r).all() and np.all(r == r[0]) else None

    has_acc = np.array([s.has_acc for s in spec.imus])
    has_gyro = np.array([s.has_gyro for s in spec.imus])

    # Stated noise: the description's std, else sensor.yaml's density·√rate.
    stated, stated_from = {}, {}
    for kind, yk in (("acc", "accelerometer_noise_density"), ("gyro", "gyroscope_noise_density")):
        v, frm = np.full(K, np.nan), [""] * K
        for k, (s, st) in enumerate(zip(spec.imus, streams)):
            if math.isfinite(getattr(s, f"{kind}_noise_std")):
                v[k], frm[k] = getattr(s, f"{kind}_noise_std"), "description"
            elif yk in st.sensor_yaml:
                rate = st.sensor_yaml.get("rate_hz", 1e9 / ref_period if ref_period else math.nan)
                v[k], frm[k] = st.sensor_yaml[yk] * math.sqrt(rate), "sensor.yaml density·√rate"
        stated[kind], stated_from[kind] = v, frm

    segment, lines = None, []
    quat = np.stack([s.orientation for s in spec.imus])
    noise_est = {}
    if noise == "rests":
        st = analyse_static(acc, gyro, time, quat, tol_deg=tol_deg, **static_kwargs)
        segment = segment_labels(st.mask)
        if st.n_segments:
            noise_est = {"acc": st.acc_noise_std, "gyro": st.gyro_noise_std}
            noise_phrase = (f"noise std estimated from {st.n_segments} static segments (pooled within-segment std "
                            "after removing each segment's mean, RMS over axes)")
        else:
            noise_phrase = "no static segment found: noise std as stated"
        lines.append(f"static segments: {st.n_segments} ({100 * float(st.mask.mean()):.1f} % of samples), "
                     f"{st.n_orientations} distinct orientations")
    else:
        noise_phrase = "noise std as stated (rests not used)"
    final = {}
    for kind, present in (("acc", has_acc), ("gyro", has_gyro)):
        v = noise_est.get(kind)
        if v is None:
            v = stated[kind]
            miss = np.flatnonzero(present & ~np.isfinite(v))
            if miss.size:
                lab = spec.imus[int(miss[0])].label
                raise UserError(f"{spec.path}: imu[{int(miss[0])}].{kind}_noise_std: IMU {lab!r} has no stated noise "
                                f"({'no rests found' if noise == 'rests' else '--noise stated'}); expected {kind}_noise_std "
                                "in the description or a noise density in its sensor.yaml")
        final[kind] = np.asarray(v, dtype=np.float64)  # a stated value of an absent triad is kept as stated
    if not noise_est:
        srcs = sorted({f for kind in ("acc", "gyro") for f in stated_from[kind] if f})
        noise_phrase += f", from {' and '.join(srcs)}" if srcs else ""

    attrs = {"importer": "accel_bayes.data.csv_import", "imu_labels": spec.labels}
    if any(s.rostopic for s in spec.imus):
        attrs["imu_rostopics"] = [s.rostopic for s in spec.imus]
    rate_hz = streams[ref].sensor_yaml.get("rate_hz")
    if rate_hz is not None:
        attrs["rate_hz"] = float(rate_hz)  # the stated rate, for densities in the export
    if any_gyro and check_gyro_units:
        from .validation import gyro_unit_diagnostics

        probe = Recording(time=time, acc=acc, gyro=gyro, nominal_position=np.stack([s.position for s in spec.imus]),
                          nominal_orientation=quat, acc_noise_std=final["acc"], gyro_noise_std=final["gyro"],
                          acc_clipped=acc_clipped, gyro_clipped=gyro_clipped, segment=segment)
        d = gyro_unit_diagnostics(probe)
        if d["flag"]:
            raise UserError(_gyro_unit_refusal(d["flag"], acc, gyro, spec))
    elif any_gyro:
        attrs["gyro_unit_check"] = "skipped"  # --skip-gyro-unit-check: later reads skip it too
    for kind, yk in (("acc", "accelerometer_random_walk"), ("gyro", "gyroscope_random_walk")):
        rw = [getattr(s, f"{kind}_random_walk") if math.isfinite(getattr(s, f"{kind}_random_walk"))
              else st_.sensor_yaml.get(yk) for s, st_ in zip(spec.imus, streams)]
        if any(r is not None and math.isfinite(r) for r in rw):
            attrs[f"{kind}_random_walk"] = to_jsonable(rw, nonfinite="null")
    for kind, r in (("acc", acc_r), ("gyro", gyro_r)):
        if np.isfinite(r).any() and common(r, np.ones(K, bool)) is None:
            attrs[f"{kind}_range_per_imu"] = to_jsonable(np.asarray(r, dtype=np.float64), nonfinite="null")

    files = ", ".join(str(s.file) for s in streams) if layout == "ASL" else str(source)
    source_text = (f"CSV import ({layout}) of {files}; array description {spec.path}; time base = stamps of the "
                   f"reference IMU {spec.labels[ref]!r} (integer ns), others matched to the nearest sample within "
                   f"{tol_ns / 1e6:g} ms; {noise_phrase}; imported by accel_bayes.data.csv_import")
    rec = Recording(
        time=time, acc=acc, gyro=gyro,
        nominal_position=np.stack([s.position for s in spec.imus]), nominal_orientation=quat,
        acc_noise_std=final["acc"], gyro_noise_std=final["gyro"],
        acc_clipped=acc_clipped, gyro_clipped=gyro_clipped, acc_flagged=acc_flagged, gyro_flagged=gyro_flagged,
        segment=segment, imu_time_offset=offsets,
        reference_imu=ref,
        acc_range=common(acc_r, has_acc), gyro_range=common(gyro_r, has_gyro) if any_gyro else None,
        description=spec.description or f"CSV import of {source.name}", source=source_text, attrs=attrs,
    )
    head = [f"layout: {layout}, {K} IMUs, {T} samples on the time base of {spec.labels[ref]!r} "
            f"(tolerance {tol_ns / 1e6:g} ms)"]
    if rows and rows[0]["dropped_ends"]:
        head.append(f"dropped {rows[0]['dropped_ends']} reference stamps outside the span every IMU covers")
    for r in rows:
        head.append(f"IMU {r['label']}: {r['samples']} samples read, {r['used']} used, worst stamp mismatch "
                    f"{r['worst_ns'] / 1e6:.6g} ms, median offset {r['median_ns'] / 1e6:.6g} ms")
    lines = head + lines
    lines.append(f"noise std: acc {_fmt(final['acc'])} m/s², gyro {_fmt(final['gyro'])} rad/s "
                 f"({noise_phrase})")  # rad/s, as `info` prints it
    for kind, m in (("acc", acc_clipped), ("gyro", gyro_clipped)):
        lines.append(f"{kind} clipped: {100 * float(m.mean()):.3g} % of samples" if m is not None
                     else f"{kind} clipped: no range stated, not flagged")
    lines.extend(mark_lines)
    if not check_gyro_units and any_gyro:
        lines.append("gyro unit check: skipped (--skip-gyro-unit-check), recorded as gyro_unit_check = skipped")
    return CsvImport(rec, lines, warns)


def _imu_folder(source: Path, label: str) -> Path:
    """``source/label`` resolved (links followed), refused unless it lies inside ``source``: an
    IMU's files are read from the recording's own folder, never from outside it."""
    root = source.resolve()
    folder = (source / label).resolve()
    if folder.parent != root:
        raise UserError(f"{source / label}: IMU {label!r} resolves to {folder}, outside the source folder {root}; "
                        "expected its folder inside the source folder")
    f = folder / "data.csv"
    if f.exists() and not f.resolve().is_relative_to(root):
        raise UserError(f"{f}: resolves to {f.resolve()}, outside the source folder {root}; expected the IMU's own file")
    return folder


# Floors of the rigid-board check: 1/128 of full scale (256 LSB of an int16 sensor), or, with no
# range stated, that fraction of the MIMU4444's ±16 g / ±2000 °/s.
_FLOOR_FRACTION = 1 / 128
_DEFAULT_RANGE = {"acc": 16 * G0, "gyro": 2000 * DEG_TO_RAD}


def _plausibility_marks(spec: ArraySpec, acc, gyro, time, acc_r, gyro_r):
    """The rigid-board check (:mod:`accel_bayes.data.plausibility`) with the description's nominal
    geometry: ``(acc_flagged, gyro_flagged, report lines)``.  Samples are marked, not removed (a
    CSV row holds one IMU only, so there is no packet to drop); a mark is None for a sensor with
    fewer than three IMUs (nothing to judge by)."""
    from .plausibility import rigid_board_check

    floor = {}
    for kind, r in (("acc", acc_r), ("gyro", gyro_r)):
        r = r[np.isfinite(r)]
        floor[kind] = _FLOOR_FRACTION * (float(np.median(r)) if r.size else _DEFAULT_RANGE[kind])
    p = rigid_board_check(acc, gyro, time, np.stack([s.position for s in spec.imus]),
                          np.stack([s.orientation for s in spec.imus]), floor_acc=floor["acc"],
                          floor_gyro=floor["gyro"], acc_range=np.where(np.isfinite(acc_r), acc_r, np.inf),
                          gyro_range=np.where(np.isfinite(gyro_r), gyro_r, np.inf))
    marks = {"acc": p.acc_flagged if p.checked["acc"] else None,
             "gyro": p.gyro_flagged if p.checked["gyro"] and gyro is not None else None}
    lines = []
    for kind in SENSORS:
        m = marks[kind]
        if m is None:
            lines.append(f"{kind} plausibility: fewer than 3 IMUs with it, not checked")
        else:
            rows = [r for r in p.rows() if r[2] == kind]
            lines.append(f"{kind} plausibility (rigid board, floor {floor[kind]:.3g} {'m/s²' if kind == 'acc' else 'rad/s'}): "
                         f"{int(m.sum())} samples marked {kind}_flagged"
                         + (f" [sample, IMU {spec.labels[0]!r}=0…, sensor, test, ratio] {rows[:10]}"
                            + (f" … {len(rows) - 10} more" if len(rows) > 10 else "") if rows else ""))
    return marks["acc"], marks["gyro"], lines


def _fmt(x) -> str:
    return "[" + ", ".join("-" if not math.isfinite(v) else f"{v:.3g}" for v in np.asarray(x, dtype=float)) + "]"


def write_imported(result: CsvImport, path, overwrite: bool = False) -> Path:
    """Write an import atomically through :func:`accel_bayes.data.io.write_recording` (validation,
    format v1; the recording carries ``imu_time_offset``, DESIGN §7.1).  An existing ``path`` is
    refused unless ``overwrite``."""
    from .io import write_recording

    return write_recording(result.recording, path, overwrite=overwrite)

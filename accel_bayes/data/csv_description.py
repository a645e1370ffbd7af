"""The array description of a CSV import (a TOML file) and the units a CSV column may carry.

:func:`read_array_description` reads it (every key in its docstring): per IMU its label, nominal
position (m, array frame), orientation (a quaternion (w, x, y, z) in the DESIGN §7.0 convention,
array → sensor, or the 3×3 matrix R with v_sensor = R v_array), which sensors it has, stated
noise stds, ranges and random walks; the reference IMU; the wide layout's columns and the units
declared for columns whose header has none.  Refusals name the file and the TOML key.
"""
from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..constants import DEG_TO_RAD, G0
from ..errors import UserError
from ..physics.geometry import matrix_to_quat
from .format_v1 import units_kind

__all__ = ["ImuSpec", "ArraySpec", "read_array_description", "AXES", "SENSORS"]

AXES = ("x", "y", "z")
SENSORS = ("acc", "gyro")

# Factors to SI of the units each kind of column accepts, by canonical name.  The SI and degree
# spellings are those :func:`accel_bayes.data.validation.units_kind` knows; g and the sub-second time
# units are added here.  Time factors are integers: nanoseconds per unit.
_FACTORS = {"acc": {"m s-2": 1.0, "g": G0}, "gyro": {"rad s-1": 1.0, "deg s-1": DEG_TO_RAD},
            "time": {"ns": 1, "us": 1_000, "ms": 1_000_000, "s": 1_000_000_000}}
_MORE_UNITS = {"g": "g", "ns": "ns", "us": "us", "µs": "us", "ms": "ms"}


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

"""Reading the CSV files of an import: the ASL/EuRoC per-IMU ``data.csv`` and the wide CSV.

* **ASL / EuRoC**: ``<label>/data.csv`` with the header ::

      #timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]

  (``w_RS_S`` and ``a_RS_S``: angular rate and specific force of the sensor frame S, expressed in
  S), and ``sensor.yaml`` beside it where present (:mod:`accel_bayes.data.sensor_yaml`).
* **Wide CSV**: one file, a time column and three columns per IMU and sensor, named by the
  description's column map, by default ``<label>_acc_x`` … ``<label>_gyro_z`` and ``time``.
  IMUs at different rates leave their cells empty in the rows of the other IMUs' stamps.

Units are those the header declares in brackets or, for columns without one, the description's
``[csv.units]``; nothing is guessed.  Stamps are read as exact integers of nanoseconds (decimal
text converted digit by digit, never through a float) and must be strictly increasing.  A UTF-8
byte-order mark and CRLF line ends are read as such.  Refusals name the file, line and column.
"""
from __future__ import annotations

import copy
import csv
import math
import re
from dataclasses import dataclass, field
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from ..errors import UserError
from .csv_description import _FACTORS, AXES, ArraySpec, ImuSpec, _unit
from .sensor_yaml import read_sensor_yaml

__all__ = ["ASL_COLUMNS", "ASL_TIME", "ImuStream", "read_asl_imu", "read_wide_csv"]

# (name in the ASL header, sensor, axis index)
ASL_COLUMNS = (("w_RS_S_x", "gyro", 0), ("w_RS_S_y", "gyro", 1), ("w_RS_S_z", "gyro", 2),
               ("a_RS_S_x", "acc", 0), ("a_RS_S_y", "acc", 1), ("a_RS_S_z", "acc", 2))
ASL_TIME = "timestamp"
_HEADER_RE = re.compile(r"^(.*?)\s*\[([^\]]*)\]\s*$")


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

    def rows(self, keep: np.ndarray) -> "_Table":
        """The same table restricted to the rows where ``keep`` (line numbers kept for messages)."""
        sub = copy.copy(self)
        sub.cells, sub.lines = self.cells[keep], self.lines[keep]
        return sub

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
        names = {kind: cols.get(kind, [f"{s.label}_{kind}_{a}" for a in AXES])
                 for kind, has in (("acc", s.has_acc), ("gyro", s.has_gyro)) if has}
        data_cols = [table.index(n, f"{kind} {a} axis") for kind in names for n, a in zip(names[kind], AXES)]
        # IMUs at different rates in one file: a row where all of an IMU's cells are empty is a
        # stamp of another IMU (a partly empty row is refused below, naming its line and column)
        blank = np.char.str_len(np.char.strip(table.cells[:, data_cols])).max(1) == 0
        own = table.rows(~blank) if blank.any() else table
        if not own.cells.shape[0]:
            raise UserError(f"{path}:1: IMU {s.label!r} has no sample (its columns are empty in every row)")
        stamps = own.stamps_ns(tcol, own.unit(tcol, "time", array.units.get("time")))
        own.check_increasing(tcol, stamps)
        used.add(tname)
        out = {}
        for kind in names:
            out[kind] = _triad(own, names[kind], kind, array.units.get(kind))
            used.update(names[kind])
        streams.append(ImuStream(s.label, path, stamps, out.get("acc"), out.get("gyro")))
    extra = [r for n, r in zip(table.names, table.raw) if n not in used]
    if extra:
        raise UserError(f"{path}:1: column {extra[0]!r} belongs to no IMU of {array.path.name} (labels {array.labels}); "
                        "expected it in an IMU's columns, or listed in csv.ignore")
    return streams

"""The recording format v1 (DESIGN §7.1): its contract tables and the check of a dataset's structure.

* The contract: :data:`FORMAT`, :data:`VARIABLES` (name → dims, required, what it is),
  :data:`COORDS`, the axis, quaternion and segment labels, and the unit spellings
  (:func:`units_kind`).
* :func:`validate_dataset` checks an :class:`xarray.Dataset` as read from a file *before* a
  :class:`~accel_bayes.data.recording.Recording` is built from it: variable and coordinate names
  (with a suggestion when a near name is present), dimension names and order, axis and
  quaternion labels, declared units, dtypes of the masks and labels, global attributes.

The in-memory recording is checked by :func:`accel_bayes.data.validation.validate_recording`.
Every failure raises :class:`~accel_bayes.errors.RecordingError` with a one-line message that
names the field, what was expected and what was found.  Nothing is altered or guessed.
"""
from __future__ import annotations

import difflib
import math
import re

import numpy as np

from ..errors import RecordingError

__all__ = ["FORMAT", "SEGMENT_LABELS", "VARIABLES", "COORDS", "AXIS_LABELS", "QUAT_LABELS", "units_kind",
           "gyro_declared_units", "validate_dataset", "plain_value"]

FORMAT = "accel_bayes.recording/1"
SEGMENT_LABELS = ("static", "dynamic")

# ---------------------------------------------------------------- contract tables

# name → (dims, required, what it is)
VARIABLES = {
    "acc": (("time", "imu", "axis"), True, "accelerometer triad output, m s-2, sensor frame"),
    "gyro": (("time", "imu", "axis"), False, "gyroscope triad output, rad s-1, sensor frame"),
    "nominal_position": (("imu", "axis"), True, "design positions, m, array frame"),
    "nominal_orientation": (("imu", "quat"), False, "array → sensor quaternions (w, x, y, z)"),
    "acc_clipped": (("time", "imu"), False, "bool mask of accelerometer samples at the range"),
    "gyro_clipped": (("time", "imu"), False, "bool mask of gyroscope samples at the range"),
    "acc_flagged": (("time", "imu"), False, "bool mask of accelerometer samples an importer distrusts"),
    "gyro_flagged": (("time", "imu"), False, "bool mask of gyroscope samples an importer distrusts"),
    "segment": (("time",), False, '"static"/"dynamic" labels'),
    "imu_time_offset": (("time", "imu"), False, "an IMU's own time stamp minus time, s"),
    "acc_noise_std": (("imu",), False, "per-IMU accelerometer noise std, m s-2"),
    "gyro_noise_std": (("imu",), False, "per-IMU gyroscope noise std, rad s-1"),
}
COORDS = {
    "time": "sample times, s, strictly increasing",
    "imu": "integer IMU labels 0..K-1",
    "axis": 'labels "x", "y", "z"',
    "quat": 'labels "w", "x", "y", "z"',
}
AXIS_LABELS = ("x", "y", "z")
QUAT_LABELS = ("w", "x", "y", "z")

# Names other tools use for the contract's fields (compared after lower-casing and dropping
# everything but letters and digits).
_SYNONYMS = {
    "acc": ["accel", "accels", "accelerometer", "accelerometers", "acceleration", "accelerations",
            "accdata", "a", "f", "specificforce", "accs", "acce"],
    "gyro": ["gyr", "gyros", "gyroscope", "gyroscopes", "omega", "angularvelocity", "angularrate",
             "gyrodata"],
    "nominal_position": ["position", "positions", "nominalpositions", "pos", "r", "imuposition",
                         "imupositions", "triadpositions", "triadposition", "designposition"],
    "nominal_orientation": ["orientation", "orientations", "nominalorientations", "quaternion",
                            "quaternions", "q", "imuorientation", "imuorientations"],
    "acc_clipped": ["accclip", "accsaturated", "accsaturation", "accelclipped", "accclipping"],
    "gyro_clipped": ["gyroclip", "gyrosaturated", "gyrosaturation", "gyroclipping"],
    "segment": ["segments", "label", "labels", "segmentlabel", "segmentlabels"],
    "time": ["t", "times", "timestamp", "timestamps", "sampletime", "sampletimes", "sec"],
    "imu": ["imus", "sensor", "sensors", "imulabel", "triad", "triads", "k", "board_imu"],
    "axis": ["axes", "component", "components", "xyz"],
    "quat": ["quaternioncomponent", "wxyz", "q4"],
    "acc_noise_std": ["accnoise", "accstd", "accnoisestd", "sigmaa", "accsigma"],
    "gyro_noise_std": ["gyronoise", "gyrostd", "gyronoisestd", "sigmag", "gyrosigma"],
}

_UNITS = {
    "s": {"s", "sec", "second", "seconds"},
    "m s-2": {"m s-2", "m/s^2", "m/s2", "m s^-2", "m.s-2", "m s**-2", "m/s/s", "m/s²", "m s⁻²",
              "meter second-2", "metre second-2", "meters/second^2", "ms-2", "m*s-2"},
    "rad s-1": {"rad s-1", "rad/s", "rad s^-1", "rad.s-1", "rad s**-1", "radian s-1", "radians s-1",
                "radian/s", "radians/s", "rad*s-1", "rads-1"},
    "deg s-1": {"deg s-1", "deg/s", "deg s^-1", "deg.s-1", "deg s**-1", "degree s-1", "degrees s-1",
                "degree/s", "degrees/s", "°/s", "° s-1", "dps", "deg*s-1"},
    "m": {"m", "meter", "meters", "metre", "metres"},
}


def _norm_unit(u) -> str:
    return re.sub(r"\s+", " ", str(u).strip().lower())


def units_kind(units) -> str | None:
    """The canonical unit ("s", "m s-2", "rad s-1", "deg s-1", "m") a ``units`` string names, or
    None if it names none of them.  ``"seconds since …"`` counts as seconds."""
    u = _norm_unit(units)
    for kind, names in _UNITS.items():
        if u in names:
            return kind
    if re.match(r"^(s|sec|second|seconds) since ", u):
        return "s"
    return None


def _key(name) -> str:
    return re.sub(r"[^a-z0-9]", "", str(name).lower())


def _suggest(expected: str, candidates) -> str | None:
    """A name among ``candidates`` that probably means ``expected``: same letters, a known
    synonym, or a close spelling."""
    cands = [c for c in candidates if isinstance(c, str)]
    key = _key(expected)
    syn = set(_SYNONYMS.get(expected, []))
    for c in cands:
        if _key(c) == key or _key(c) in syn:
            return c
    close = difflib.get_close_matches(expected.lower(), [c.lower() for c in cands], n=1, cutoff=0.8)
    if close:
        return next(c for c in cands if c.lower() == close[0])
    return None


def plain_value(x):
    """Plain Python value for messages (numpy 2 reprs read ``np.float64(0.5)``)."""
    if isinstance(x, np.ndarray):
        return x.item() if x.ndim == 0 else x.tolist()
    return x.item() if isinstance(x, np.generic) else x


def _fmt_list(xs, n=8) -> str:
    xs = list(xs)
    s = ", ".join(str(x) for x in xs[:n])
    return f"[{s}{', …' if len(xs) > n else ''}]"


# ---------------------------------------------------------------- dataset level

def gyro_declared_units(ds) -> str:
    """The unit the file declares for ``gyro``: ``"rad s-1"`` (also when the ``units`` attribute is
    absent: that is the format's unit) or ``"deg s-1"`` (an explicit declaration; the reader
    converts).  Raises :class:`RecordingError` for any other declaration."""
    if "gyro" not in ds.variables:
        return "rad s-1"
    units = ds["gyro"].attrs.get("units")
    if units is None:
        return "rad s-1"
    kind = units_kind(units)
    if kind not in ("rad s-1", "deg s-1"):
        raise RecordingError(f'gyro: units attribute is {units!r}; expected "rad s-1" (format v1) '
                             'or an explicit "deg s-1"')
    return kind


def _check_units(ds, name, expected: str, also: tuple = ()):
    if name not in ds.variables:
        return
    units = ds[name].attrs.get("units")
    if units is None:  # the format fixes the unit; an absent attribute means the format's unit
        return
    kind = units_kind(units)
    if kind != expected and kind not in also:
        raise RecordingError(f"{name}: units attribute is {units!r}; expected {expected!r}"
                             + (" (format v1 stores SI units; convert the values)" if not also else ""))


def _check_bool_like(ds, name):
    if name not in ds.variables:
        return
    v = np.asarray(ds[name].values)
    if v.dtype == bool:
        return
    if v.dtype.kind in "iuf":
        bad = ~np.isin(v, (0, 1))
        if not bad.any():
            return
        i = np.argwhere(bad)[0]
        raise RecordingError(f"{name}: expected a bool mask (0/1), found value {plain_value(v[tuple(i)])!r} at index {tuple(int(x) for x in i)}")
    raise RecordingError(f"{name}: expected a bool mask, got dtype {v.dtype}")


def _scalar_attr(ds, name, *, positive=True, integer=False):
    if name not in ds.attrs:
        return None
    v = np.asarray(ds.attrs[name])
    if v.size != 1 or v.dtype.kind not in "iuf":
        raise RecordingError(f"{name}: global attribute must be one number, got {plain_value(ds.attrs[name])!r}")
    x = float(v.reshape(()))
    if integer:
        if not math.isfinite(x) or x != round(x):
            raise RecordingError(f"{name}: global attribute must be an integer IMU label, got {plain_value(ds.attrs[name])!r}")
        return int(round(x))
    if positive and not (math.isfinite(x) and x > 0):
        raise RecordingError(f"{name}: global attribute must be a finite number > 0, got {x!r}")
    return x


def validate_dataset(ds) -> None:
    """Check the structure of a format-v1 dataset (DESIGN §7.1) before a Recording is built.

    Checks, in order: the ``format`` attribute (if present); required variables ``acc`` and
    ``nominal_position`` (a missing one is reported with any near name the file has, e.g.
    ``accel``); optional variables under a non-contract name (``gyroscope`` for ``gyro``);
    dimensions and their order of every contract variable; the ``time``, ``imu``, ``axis`` (and
    ``quat``) coordinates and their labels; declared units; mask and label dtypes; the global
    attributes ``acc_noise_std``, ``gyro_noise_std``, ``reference_imu``, ``acc_range``,
    ``gyro_range``.  Raises :class:`RecordingError` on the first problem.
    """
    fmt = ds.attrs.get("format")
    if isinstance(fmt, str) and fmt.startswith("accel_bayes.recording/") and fmt != FORMAT:
        raise RecordingError(f"format: this reader understands {FORMAT!r}, the file says {fmt!r}")

    names = set(ds.variables) | set(ds.dims)
    present = [n for n in list(ds.variables) + list(ds.dims) if n not in VARIABLES and n not in COORDS]

    # Required variables, then optional ones stored under another name.
    for name, (dims, required, what) in VARIABLES.items():
        if name in names:
            continue
        near = _suggest(name, present)
        if required:
            hint = (f'; the file has "{near}" — rename it to "{name}"' if near
                    else f"; the file has {_fmt_list(sorted(map(str, ds.data_vars)))}")
            raise RecordingError(f'variable "{name}" is missing: expected {what} with dimensions '
                                 f"({', '.join(dims)}){hint}")
        if (near is not None and near in ds.data_vars and set(ds[near].dims) == set(dims)
                and name not in ("acc_noise_std", "gyro_noise_std")):
            raise RecordingError(f'variable "{near}" is not part of format v1 but looks like "{name}" '
                                 f"({what}); rename it to \"{name}\" (or drop it)")

    # Dimensions and their order.
    for name, (dims, _, what) in VARIABLES.items():
        if name not in ds.variables:
            continue
        got = tuple(ds[name].dims)
        if got == dims:
            continue
        exp = "(" + ", ".join(dims) + ")"
        gots = "(" + ", ".join(map(str, got)) + ")"
        if sorted(map(str, got)) == sorted(dims):
            raise RecordingError(f"{name}: expected dimensions {exp}, got {gots} (axis order differs; "
                                 f"transpose to {exp})")
        extra = [d for d in got if d not in dims]
        missing = [d for d in dims if d not in got]
        hint = ""
        if len(extra) == 1 and len(missing) == 1:
            hint = f'; rename dimension "{extra[0]}" to "{missing[0]}"'
        raise RecordingError(f"{name}: expected dimensions {exp}, got {gots}{hint}")

    # Coordinates.
    needed = ["time", "imu", "axis"] + (["quat"] if "nominal_orientation" in ds.variables else [])
    for c in needed:
        if c not in ds.variables:
            near = _suggest(c, [n for n in ds.variables if n not in VARIABLES and n not in COORDS])
            hint = f'; the file has "{near}" — make it the "{c}" coordinate' if near else ""
            raise RecordingError(f'coordinate "{c}" is missing: expected {COORDS[c]} along dimension "{c}"{hint}')
        if tuple(ds[c].dims) != (c,):
            raise RecordingError(f'coordinate "{c}": expected dimension ("{c}",), got {tuple(ds[c].dims)}')

    t = np.asarray(ds["time"].values)
    if t.dtype.kind not in "iuf":
        raise RecordingError(f"time: expected numbers of seconds (float64), got dtype {t.dtype}; "
                             "store seconds, e.g. seconds from the start")
    imu = np.asarray(ds["imu"].values)
    K = imu.shape[0]
    if imu.dtype.kind not in "iu" and not (imu.dtype.kind == "f" and np.all(imu == np.round(imu))):
        raise RecordingError(f"imu: expected integer labels 0..{K - 1}, got {_fmt_list(imu.tolist())}")
    if not np.array_equal(imu.astype(np.int64), np.arange(K)):
        raise RecordingError(f"imu: expected labels 0..{K - 1} in file order, got {_fmt_list(imu.tolist())}")
    for c, exp in (("axis", AXIS_LABELS), ("quat", QUAT_LABELS)):
        if c not in ds.variables:
            continue
        lab = tuple(str(x.decode() if isinstance(x, bytes) else x) for x in np.asarray(ds[c].values).tolist())
        if lab != exp:
            hint = ""
            if c == "quat" and lab == ("x", "y", "z", "w"):
                hint = " (scalar-last order; format v1 stores the scalar w first)"
            elif sorted(lab) == sorted(exp):
                hint = " (same labels, different order; reorder the data, do not just relabel)"
            raise RecordingError(f"{c}: expected labels {exp} in that order, got {lab}{hint}")

    # Units.
    _check_units(ds, "time", "s")
    _check_units(ds, "acc", "m s-2")
    gyro_declared_units(ds)
    _check_units(ds, "nominal_position", "m")
    _check_units(ds, "acc_noise_std", "m s-2")
    _check_units(ds, "gyro_noise_std", "rad s-1", also=("deg s-1",))

    # Dtypes.
    for name in ("acc", "gyro", "nominal_position", "nominal_orientation", "acc_noise_std", "gyro_noise_std"):
        if name in ds.variables and np.asarray(ds[name].values).dtype.kind not in "iuf":
            raise RecordingError(f"{name}: expected numbers, got dtype {ds[name].dtype}")
    _check_bool_like(ds, "acc_clipped")
    _check_bool_like(ds, "gyro_clipped")
    _check_bool_like(ds, "acc_flagged")
    _check_bool_like(ds, "gyro_flagged")
    if "segment" in ds.variables and np.asarray(ds["segment"].values).dtype.kind not in "USO":
        raise RecordingError(f'segment: expected string labels "static"/"dynamic", got dtype {ds["segment"].dtype}')

    # Global attributes.
    for name in ("acc_noise_std", "gyro_noise_std"):
        if name in ds.attrs and name not in ds.variables:
            _scalar_attr(ds, name)
    if "acc_noise_std" not in ds.attrs and "acc_noise_std" not in ds.variables:
        raise RecordingError("acc_noise_std is missing: expected a global attribute acc_noise_std (m s-2) "
                             "or a per-IMU variable acc_noise_std(imu)")
    if "gyro" in ds.variables and "gyro_noise_std" not in ds.attrs and "gyro_noise_std" not in ds.variables:
        raise RecordingError("gyro_noise_std is missing (the file has gyro): expected a global attribute "
                             "gyro_noise_std (rad s-1) or a per-IMU variable gyro_noise_std(imu)")
    _scalar_attr(ds, "reference_imu", integer=True)
    _scalar_attr(ds, "acc_range")
    _scalar_attr(ds, "gyro_range")
    for name in ("description", "source"):
        if name in ds.attrs and not isinstance(ds.attrs[name], str):
            raise RecordingError(f"{name}: global attribute must be a string, got {plain_value(ds.attrs[name])!r}")

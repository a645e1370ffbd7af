"""Recording files (format v1, DESIGN §7.1) and ground-truth sidecars.

* :func:`write_recording` / :func:`read_recording`: NetCDF-4/HDF5 through xarray + h5netcdf.
  A write → read round trip returns an identical :class:`Recording` (bit-exact arrays, same
  attributes).  Writing is atomic (:mod:`accel_bayes.data.outputs`: built in memory, written to a
  temporary file in the target directory, fsynced, then :func:`os.replace`), so a failed write
  never leaves a half-written or corrupted file, and an existing file is only replaced with
  ``overwrite=True``.  Reading never modifies the file and
  validates it (:mod:`accel_bayes.data.format_v1`, :mod:`accel_bayes.data.validation`); files from other tools that follow the contract
  are accepted (no ``format`` attribute, bool masks stored as integers, float32 data, an
  explicit ``units = "deg s-1"`` on ``gyro``, which is converted).
* :func:`write_truth` / :func:`read_truth`: simulator ground truth in a JSON sidecar
  ``<recording stem>.truth.json`` (schema ``accel_bayes.truth/1``).  Ground truth never goes
  into the recording file.
* :func:`recording_sha256`: the file's SHA-256, for provenance.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import warnings
from pathlib import Path

import numpy as np

from . import outputs
from .outputs import to_jsonable
from .paths import require_file, truth_path
from ..constants import DEG_TO_RAD
from ..errors import RecordingError, UserError
from .recording import Recording
from .format_v1 import COORDS, FORMAT, VARIABLES, gyro_declared_units, units_kind, validate_dataset
from .validation import validate_recording

__all__ = [
    "FORMAT",
    "TRUTH_SCHEMA",
    "write_recording",
    "read_recording",
    "recording_to_dataset",
    "recording_from_dataset",
    "truth_path",
    "write_truth",
    "read_truth",
    "recording_sha256",
    "to_jsonable",
    "load_recording",
    "LoadedRecording",
]

TRUTH_SCHEMA = "accel_bayes.truth/1"
ENGINE = "h5netcdf"
# Global attributes the format defines; Recording.attrs may not use these keys.
RESERVED_ATTRS = ("format", "acc_noise_std", "gyro_noise_std", "reference_imu", "acc_range", "gyro_range",
                  "description", "source")
# Attributes whose values are not plain strings/numbers are stored as JSON text; this attribute
# lists their keys so that the reader can decode them again.
JSON_ATTRS_KEY = "accel_bayes_json_attrs"


# ---------------------------------------------------------------- helpers

def recording_sha256(path) -> str:
    """SHA-256 (hex) of a file's bytes, for provenance records (DESIGN §7.3 ``input_sha256``)."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _encode_attr(key, value):
    """(stored value, is_json)."""
    if isinstance(value, (bool, np.bool_)) or value is None:
        return json.dumps(to_jsonable(value, where=f"attrs[{key!r}]")), True
    if isinstance(value, str):
        return value, False
    if isinstance(value, (int, np.integer)) and -(2**63) <= int(value) < 2**63:
        return int(value), False
    if isinstance(value, (float, np.floating)):
        return float(value), False
    return json.dumps(to_jsonable(value, where=f"attrs[{key!r}]")), True


def _decode_attr(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.item() if value.ndim == 0 else value.tolist()
    if isinstance(value, bytes):
        return value.decode()
    return value


def _uniform(x: np.ndarray):
    """The common value of x if all entries are equal and finite, else None."""
    x = np.asarray(x, dtype=float)
    if x.size and np.isfinite(x).all() and np.all(x == x[0]):
        return float(x[0])
    return None


# ---------------------------------------------------------------- recording ↔ dataset

def recording_to_dataset(rec: Recording):
    """The :class:`xarray.Dataset` of format v1 for a recording (DESIGN §7.1 layout)."""
    import xarray as xr

    K = rec.K
    dv = {
        "acc": (("time", "imu", "axis"), np.asarray(rec.acc, dtype=np.float64),
                {"units": "m s-2", "long_name": "accelerometer triad output, sensor frame"}),
        "nominal_position": (("imu", "axis"), np.asarray(rec.nominal_position, dtype=np.float64),
                             {"units": "m", "long_name": "design position, array frame"}),
        "nominal_orientation": (("imu", "quat"), np.asarray(rec.nominal_orientation, dtype=np.float64),
                                {"long_name": "array -> sensor rotation quaternion",
                                 "convention": "v_sensor = R(q) v_array, q = (w, x, y, z), Hamilton"}),
    }
    if rec.gyro is not None:
        dv["gyro"] = (("time", "imu", "axis"), np.asarray(rec.gyro, dtype=np.float64),
                      {"units": "rad s-1", "long_name": "gyroscope triad output, sensor frame; NaN where an IMU has none"})
    for name, x in (("acc_clipped", rec.acc_clipped), ("gyro_clipped", rec.gyro_clipped)):
        if x is not None:
            dv[name] = (("time", "imu"), np.asarray(x, dtype=bool),
                        {"long_name": "sample known to be at the sensor range"})
    for name, x in (("acc_flagged", rec.acc_flagged), ("gyro_flagged", rec.gyro_flagged)):
        if x is not None:
            dv[name] = (("time", "imu"), np.asarray(x, dtype=bool),
                        {"long_name": "sample an importer's plausibility check distrusts; fits leave it out"})
    if rec.segment is not None:
        dv["segment"] = (("time",), np.asarray(rec.segment).astype(str), {"long_name": "static / dynamic label"})
    if rec.imu_time_offset is not None:
        dv["imu_time_offset"] = (("time", "imu"), np.asarray(rec.imu_time_offset, dtype=np.float64),
                                 {"units": "s", "long_name": "IMU's own time stamp minus time (stamped separately, "
                                                             "put on one time base by an importer)"})

    attrs = {"format": FORMAT}
    for name, unit in (("acc_noise_std", "m s-2"), ("gyro_noise_std", "rad s-1")):
        x = np.asarray(getattr(rec, name), dtype=np.float64)
        u = _uniform(x)
        if u is not None:
            attrs[name] = u
        elif name == "gyro_noise_std" and rec.gyro is None and np.isnan(x).all():
            pass  # nothing to say: no gyroscope data and no stated gyro noise
        else:
            dv[name] = (("imu",), x, {"units": unit, "long_name": "white-noise standard deviation per axis"})
    attrs["reference_imu"] = int(rec.reference_imu)
    if rec.acc_range is not None:
        attrs["acc_range"] = float(rec.acc_range)
    if rec.gyro_range is not None:
        attrs["gyro_range"] = float(rec.gyro_range)
    attrs["description"] = str(rec.description)
    attrs["source"] = str(rec.source)
    json_keys = []
    for key, value in rec.attrs.items():
        if not isinstance(key, str) or not key or "/" in key:
            raise UserError(f"attrs: key {key!r} is not a valid attribute name (non-empty string without '/')")
        if key in RESERVED_ATTRS or key == JSON_ATTRS_KEY:
            raise UserError(f"attrs: key {key!r} is reserved by format v1; set the Recording field instead")
        stored, is_json = _encode_attr(key, value)
        attrs[key] = stored
        if is_json:
            json_keys.append(key)
    if json_keys:
        attrs[JSON_ATTRS_KEY] = json.dumps(json_keys)

    coords = {
        "time": ("time", np.asarray(rec.time, dtype=np.float64), {"units": "s", "long_name": "sample time"}),
        "imu": ("imu", np.arange(K, dtype=np.int64), {"long_name": "IMU label"}),
        "axis": ("axis", np.array(["x", "y", "z"])),
        "quat": ("quat", np.array(["w", "x", "y", "z"])),
    }
    return xr.Dataset(dv, coords=coords, attrs=attrs)


def recording_from_dataset(ds, *, require_gyro: bool = False, check_gyro_units: bool = True) -> Recording:
    """Build and validate a :class:`Recording` from a format-v1 dataset (fully loaded).

    Structure is checked first (:func:`~accel_bayes.data.format_v1.validate_dataset`), then the
    recording (:func:`~accel_bayes.data.validation.validate_recording`).  Conversions made here are
    only those the file declares or the contract implies: float32 → float64, 0/1 integer masks →
    bool, gyro declared ``"deg s-1"`` → rad/s, scalar noise attributes → per-IMU arrays.
    """
    validate_dataset(ds)
    K = int(ds.sizes["imu"])

    def arr(name, dtype=np.float64):
        return np.array(ds[name].values, dtype=dtype, copy=True) if name in ds.variables else None

    time = arr("time")
    acc = arr("acc")
    gyro_units = gyro_declared_units(ds)
    gyro = arr("gyro")
    if gyro is not None and gyro_units == "deg s-1":
        gyro = gyro * DEG_TO_RAD
    masks = {}
    for name in ("acc_clipped", "gyro_clipped", "acc_flagged", "gyro_flagged"):
        masks[name] = None if name not in ds.variables else np.asarray(ds[name].values).astype(bool)
    segment = None
    if "segment" in ds.variables:
        seg = np.asarray(ds["segment"].values)
        segment = np.array([s.decode() if isinstance(s, bytes) else str(s) for s in seg.tolist()]) if seg.dtype.kind in "OS" else seg.astype(str)

    noise = {}
    for name in ("acc_noise_std", "gyro_noise_std"):
        if name in ds.variables:
            x = arr(name)
            if name == "gyro_noise_std" and units_kind(ds[name].attrs.get("units", "rad s-1")) == "deg s-1":
                x = x * DEG_TO_RAD
            noise[name] = x
        elif name in ds.attrs:
            noise[name] = np.full(K, float(np.asarray(ds.attrs[name]).reshape(())))
        else:  # only gyro_noise_std can be absent here (validate_dataset), and only without gyro
            noise[name] = np.full(K, np.nan)

    a = ds.attrs
    json_keys = []
    if JSON_ATTRS_KEY in a:
        try:
            json_keys = json.loads(a[JSON_ATTRS_KEY])
        except (TypeError, ValueError):
            raise RecordingError(f"{JSON_ATTRS_KEY}: expected a JSON list of attribute names, got {a[JSON_ATTRS_KEY]!r}") from None
    extra = {}
    for key, value in a.items():
        if key in RESERVED_ATTRS or key == JSON_ATTRS_KEY:
            continue
        if key in json_keys:
            try:
                extra[key] = json.loads(value)
            except (TypeError, ValueError):
                raise RecordingError(f"attrs[{key!r}]: listed in {JSON_ATTRS_KEY} but not valid JSON") from None
        else:
            extra[key] = _decode_attr(value)

    unknown = [str(n) for n in ds.data_vars if n not in VARIABLES and n not in COORDS]
    if unknown:
        warnings.warn(f"variables {unknown} are not part of format v1 and were not loaded", stacklevel=3)

    def scalar(name):
        return None if name not in a else float(np.asarray(a[name]).reshape(()))

    rec = Recording(
        time=time,
        acc=acc,
        nominal_position=arr("nominal_position"),
        acc_noise_std=noise["acc_noise_std"],
        gyro_noise_std=noise["gyro_noise_std"],
        gyro=gyro,
        nominal_orientation=arr("nominal_orientation"),
        acc_clipped=masks["acc_clipped"],
        gyro_clipped=masks["gyro_clipped"],
        acc_flagged=masks["acc_flagged"],
        gyro_flagged=masks["gyro_flagged"],
        segment=segment,
        imu_time_offset=arr("imu_time_offset"),
        reference_imu=int(round(float(np.asarray(a.get("reference_imu", 0)).reshape(())))),
        acc_range=scalar("acc_range"),
        gyro_range=scalar("gyro_range"),
        description=str(a.get("description", "")),
        source=str(a.get("source", "")),
        attrs=extra,
    )
    validate_recording(rec, require_gyro=require_gyro, gyro_units=gyro_units, check_gyro_units=check_gyro_units)
    return rec


# ---------------------------------------------------------------- files

def write_recording(rec: Recording, path, overwrite: bool = False, *, validate: bool = True) -> Path:
    """Write ``rec`` to ``path`` as a format-v1 NetCDF-4 file (DESIGN §7.1); returns the path.

    The recording is validated first (:func:`~accel_bayes.data.validation.validate_recording`;
    ``validate=False`` skips that, for tests of the reader).  The file is written to a temporary
    name in the same directory and renamed over ``path`` only when complete, so an existing
    file survives a failed write intact.  An existing ``path`` raises :class:`UserError` unless
    ``overwrite=True``.  Noise levels shared by all IMUs are written as global attributes,
    otherwise as per-IMU variables.  ``rec.attrs`` values that are not strings or numbers
    (bool, None, lists, dicts, arrays) are stored as JSON text and decoded again on reading
    (tuples come back as lists).
    """
    path = Path(path)
    if validate:
        validate_recording(rec)
    ds = recording_to_dataset(rec)
    outputs.check_file_target(path, overwrite=overwrite)
    enc = {}
    for name, var in ds.variables.items():
        e = {}
        if var.dtype.kind == "f":
            e["_FillValue"] = None  # NaN is stored as NaN: bit-exact round trips, no masking
        if name in ("acc", "gyro", "acc_clipped", "gyro_clipped", "acc_flagged", "gyro_flagged") and var.size > 0:
            e.update(zlib=True, complevel=4, shuffle=True)
        if e:
            enc[name] = e
    return outputs.write_netcdf(path, ds, engine=ENGINE, encoding=enc, overwrite=overwrite)


def read_recording(path, *, require_gyro: bool = False, check_gyro_units: bool = True) -> Recording:
    """Read and validate a format-v1 recording file (DESIGN §7.1).

    The file is opened read-only with xarray (engine h5netcdf), loaded fully and closed before
    checking.  A file that breaks the contract raises :class:`RecordingError` whose message
    starts with the path and names the field (see :mod:`accel_bayes.data.validation`); a missing
    file raises :class:`FileNotFoundError`.  ``require_gyro`` refuses files without gyroscope
    data; ``check_gyro_units=False`` skips the rad/s plausibility test.
    """
    import xarray as xr

    path = require_file(path, "recording file")
    try:
        ds = xr.open_dataset(path, engine=ENGINE, decode_times=False, decode_timedelta=False)
    except Exception as exc:  # h5py/h5netcdf raise OSError, ValueError, KeyError… for foreign bytes
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise RecordingError(f"{path}: not a NetCDF-4/HDF5 recording readable by xarray ({msg})") from None
    with ds:
        ds.load()
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            rec = recording_from_dataset(ds, require_gyro=require_gyro, check_gyro_units=check_gyro_units)
        for w in caught:
            warnings.warn(f"{path}: {w.message}", w.category, stacklevel=2)
    except RecordingError as exc:
        raise RecordingError(f"{path}: {exc}") from None
    return rec


# ---------------------------------------------------------------- ground truth sidecar

@dataclasses.dataclass
class LoadedRecording:
    """A recording and where it came from (:func:`load_recording`).

    recording : the :class:`~accel_bayes.data.recording.Recording`.
    path : the path it was read from, exactly as given (it is recorded in provenance as such),
        or None for an in-memory recording.
    """

    recording: Recording
    path: object = None
    _sha256: str | None = dataclasses.field(default=None, repr=False)

    def sha256(self) -> str | None:
        """SHA-256 (hex) of the file's bytes (DESIGN §7.3 ``input_sha256``), computed once; None
        for an in-memory recording."""
        if self.path is None:
            return None
        if self._sha256 is None:
            self._sha256 = recording_sha256(self.path)
        return self._sha256


def load_recording(source, *, require_gyro: bool = False, streams: bool = False) -> LoadedRecording:
    """The one recording loader of the pipelines: a :class:`Recording` (used as it is), a
    :class:`LoadedRecording` (returned unchanged), or a path to a format-v1 file
    (:func:`read_recording`, which validates it; ``require_gyro`` refuses one without
    gyroscopes).  ``streams=True`` also accepts a MIMU4444 stream (.bin/.bin.gz), imported on the
    fly (:func:`accel_bayes.data.mimu.import_mimu`).  Anything else is refused with one line."""
    if isinstance(source, LoadedRecording):
        return source
    if isinstance(source, Recording):
        return LoadedRecording(source, None)
    if not isinstance(source, (str, bytes)) and not hasattr(source, "__fspath__"):
        raise UserError(f"recording: expected a Recording or a file path, got {type(source).__name__}")
    if streams:
        path = require_file(source, "recording file")
        with open(path, "rb") as f:
            head = f.read(8)
        if not (head.startswith(b"\x89HDF") or path.suffix == ".nc"):
            from .mimu import import_mimu

            return LoadedRecording(import_mimu(path), source)
    return LoadedRecording(read_recording(source, require_gyro=require_gyro), source)


def write_truth(rec_path, truth: dict, *, overwrite: bool = True) -> Path:
    """Write simulator ground truth next to its recording (``truth_path(rec_path)``), atomically.

    ``truth`` is a dict; numpy/torch arrays become nested lists.  The sidecar gets
    ``"schema": "accel_bayes.truth/1"`` and, if the recording file already exists,
    ``"recording_sha256"`` so that :func:`read_truth` can tell a stale sidecar.  The sidecar
    follows its recording, so it is replaced by default (``write_recording`` is the guarded
    step); pass ``overwrite=False`` to refuse.
    """
    if not isinstance(truth, dict):
        raise UserError(f"truth: expected a dict, got {type(truth).__name__}")
    out = to_jsonable(dict(truth), where="truth")
    schema = out.setdefault("schema", TRUTH_SCHEMA)
    if schema != TRUTH_SCHEMA:
        raise UserError(f"truth: schema is {schema!r}; expected {TRUTH_SCHEMA!r}")
    if "recording_sha256" not in out and Path(rec_path).is_file():
        out["recording_sha256"] = recording_sha256(rec_path)
    return outputs.write_json(truth_path(rec_path), out, indent=1, overwrite=overwrite)


def read_truth(rec_path, *, verify: bool = True) -> dict:
    """Read the ground-truth sidecar of a recording (lists stay lists; use ``np.asarray``).

    Raises :class:`FileNotFoundError` if there is none, :class:`UserError` if its schema is not
    ``accel_bayes.truth/1`` or (``verify``) its ``recording_sha256`` does not match the
    recording file beside it.
    """
    path = truth_path(rec_path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no ground-truth sidecar for {rec_path}")
    try:
        with open(path, encoding="utf-8") as f:
            truth = json.load(f)
    except ValueError as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    if not isinstance(truth, dict) or truth.get("schema") != TRUTH_SCHEMA:
        got = truth.get("schema") if isinstance(truth, dict) else type(truth).__name__
        raise UserError(f"{path}: schema is {got!r}; expected {TRUTH_SCHEMA!r}")
    sha = truth.get("recording_sha256")
    if verify and sha and Path(rec_path).is_file() and recording_sha256(rec_path) != sha:
        raise UserError(f"{path}: recording_sha256 does not match {rec_path}; the sidecar belongs to another "
                        "version of the recording")
    return truth

"""Importer for CSV recordings of an IMU array → format v1 (DESIGN §7.1): the driver.

Two layouts, one array description: an ASL / EuRoC folder (``imu0/data.csv``, ``imu1/data.csv``,
…, with ``sensor.yaml`` beside each where present) or one wide CSV.  The pieces live beside this
module: :mod:`~accel_bayes.data.csv_description` (the TOML array description, every key),
:mod:`~accel_bayes.data.csv_read` (the CSV files: units, exact integer-nanosecond stamps, BOM and
CRLF), :mod:`~accel_bayes.data.sensor_yaml` (EuRoC/OpenCV ``sensor.yaml`` and its ``T_BS``) and
:mod:`~accel_bayes.data.csv_timebase` (one time base for all IMUs).

What the importer does, and why:

* **Units** are those the header declares in brackets or the description's ``[csv.units]``;
  nothing is guessed.  Every subtraction of stamps is done in integer nanoseconds before the
  conversion to seconds: ``time = (stamp − first stamp of the time base) / 1e9``.
* **One time base.**  IMUs at the reference's rate are put on the reference IMU's stamps (each
  contributes its nearest sample within a tolerance, default a quarter of the reference's median
  sample period; its own stamp minus ``time`` is kept in ``imu_time_offset``).  IMUs at
  different rates (median sample periods further apart than
  :data:`~accel_bayes.data.csv_timebase.SAME_RATE_REL`) are not resampled and lose no sample:
  ``time`` is the sorted union of every IMU's stamps, NaN where an IMU has no sample (DESIGN
  §7.1), ``imu_time_offset`` 0 where it has one; the rigid-board plausibility check, which
  compares IMUs at one instant, is not run; rests and the gyro-unit check use each IMU's nearest
  sample to the reference's stamps (a rest marks the union rows between two static reference
  samples).  On the reference's stamps, stamps outside the span every
  IMU covers (IMUs that start or stop at slightly different times) are dropped and counted.
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
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..constants import DEG_TO_RAD, G0
from ..errors import UserError
from .csv_description import SENSORS, ArraySpec, ImuSpec, read_array_description
from .csv_read import ASL_COLUMNS, ImuStream, read_asl_imu, read_wide_csv
from .csv_timebase import align_streams, median_period_ns, nearest_index, rates_agree, union_streams
from .outputs import to_jsonable
from .recording import Recording, stamp_rate
from .segments import analyse_static, segment_labels
from .sensor_yaml import apply_t_bs, read_sensor_yaml

# The public names of the importer, wherever they are defined (callers import them from here).
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
    warns = apply_t_bs(spec, streams)

    tb = _time_base(streams, ref, time_tolerance)
    time, present, T = tb.time, tb.present, tb.time.size

    acc = np.full((T, K, 3), np.nan)
    any_gyro = any(s.has_gyro for s in spec.imus)
    gyro = np.full((T, K, 3), np.nan) if any_gyro else None
    for k, (s, st) in enumerate(zip(spec.imus, streams)):
        rows_k, idx = present[:, k], tb.index[present[:, k], k]
        if st.acc is not None:
            acc[rows_k, k] = st.acc[idx]
        if st.gyro is not None:
            gyro[rows_k, k] = st.gyro[idx]

    # Clipping from the stated ranges (per IMU, else the array's).
    def ranges(kind):
        r = np.array([getattr(s, f"{kind}_range") for s in spec.imus])
        return np.where(np.isnan(r), getattr(spec, f"{kind}_range"), r)

    acc_r, gyro_r = ranges("acc"), ranges("gyro")
    acc_clipped = None if np.isnan(acc_r).all() else (np.abs(acc) >= acc_r[None, :, None]).any(-1)
    gyro_clipped = None if gyro is None or np.isnan(gyro_r).all() else (np.abs(gyro) >= gyro_r[None, :, None]).any(-1)

    if tb.union:
        # The rigid-board check compares IMUs at one instant; at different rates they share none.
        acc_flagged = gyro_flagged = None
        mark_lines = ["plausibility (rigid board): IMUs at different rates share no instants, not checked"]
    else:
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
                # the IMU's own rate: at mixed rates the reference's would be wrong by up to 2x in σ
                rate = st.sensor_yaml.get("rate_hz", stamp_rate((st.stamps_ns - st.stamps_ns[0]) / 1e9))
                v[k], frm[k] = st.sensor_yaml[yk] * math.sqrt(rate), "sensor.yaml density·√rate"
        stated[kind], stated_from[kind] = v, frm

    segment, lines = None, []
    quat = np.stack([s.orientation for s in spec.imus])
    noise_est = {}
    if noise == "rests":
        if tb.union:
            # A rest is the whole board at rest, judged where every IMU has a sample: on the
            # reference's stamps (each IMU's nearest sample), then carried to the union's rows.
            rows, pick = _reference_picks(tb, ref)
            cols = np.arange(K)[None, :]
            st = analyse_static(acc[pick, cols], None if gyro is None else gyro[pick, cols], time[rows], quat,
                                tol_deg=tol_deg, **static_kwargs)
            mask = _between_reference_rows(st.mask, rows, T)
        else:
            st = analyse_static(acc, gyro, time, quat, tol_deg=tol_deg, **static_kwargs)
            mask = st.mask
        segment = segment_labels(mask)
        if st.n_segments:
            noise_est = {"acc": st.acc_noise_std, "gyro": st.gyro_noise_std}
            noise_phrase = (f"noise std estimated from {st.n_segments} static segments (pooled within-segment std "
                            "after removing each segment's mean, RMS over axes)")
        else:
            noise_phrase = "no static segment found: noise std as stated"
        lines.append(f"static segments: {st.n_segments} ({100 * float(mask.mean()):.1f} % of samples), "
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
    own_rates = [s.sensor_yaml.get("rate_hz") for s in streams]
    if any(r is not None for r in own_rates):
        attrs["imu_rate_hz"] = to_jsonable(own_rates, nonfinite="null")  # per IMU, for the export's densities
    if any_gyro and check_gyro_units:
        from .validation import gyro_unit_diagnostics

        probe = Recording(time=time, acc=acc, gyro=gyro, nominal_position=np.stack([s.position for s in spec.imus]),
                          nominal_orientation=quat, acc_noise_std=final["acc"], gyro_noise_std=final["gyro"],
                          acc_clipped=acc_clipped, gyro_clipped=gyro_clipped, segment=segment)
        if tb.union:
            probe = _on_reference_stamps(probe, tb, ref)
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
    source_text = (f"CSV import ({layout}) of {files}; array description {spec.path}; time base = {tb.how}; "
                   f"{noise_phrase}; imported by accel_bayes.data.csv_import")
    rec = Recording(
        time=time, acc=acc, gyro=gyro,
        nominal_position=np.stack([s.position for s in spec.imus]), nominal_orientation=quat,
        acc_noise_std=final["acc"], gyro_noise_std=final["gyro"],
        acc_clipped=acc_clipped, gyro_clipped=gyro_clipped, acc_flagged=acc_flagged, gyro_flagged=gyro_flagged,
        segment=segment, imu_time_offset=tb.offsets,
        reference_imu=ref,
        acc_range=common(acc_r, has_acc), gyro_range=common(gyro_r, has_gyro) if any_gyro else None,
        description=spec.description or f"CSV import of {source.name}", source=source_text, attrs=attrs,
    )
    lines = [f"layout: {layout}, {K} IMUs, {T} samples; time base = {tb.how}"] + tb.lines + lines
    lines.append(f"noise std: acc {_fmt(final['acc'])} m/s², gyro {_fmt(final['gyro'])} rad/s "
                 f"({noise_phrase})")  # rad/s, as `info` prints it
    for kind, m in (("acc", acc_clipped), ("gyro", gyro_clipped)):
        lines.append(f"{kind} clipped: {100 * float(m.mean()):.3g} % of samples" if m is not None
                     else f"{kind} clipped: no range stated, not flagged")
    lines.extend(mark_lines)
    if not check_gyro_units and any_gyro:
        lines.append("gyro unit check: skipped (--skip-gyro-unit-check), recorded as gyro_unit_check = skipped")
    return CsvImport(rec, lines, warns)


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



@dataclass
class _TimeBase:
    """The recording's time axis and where each IMU's samples go on it."""

    time: np.ndarray  # (T,) s from the first stamp of the time base
    index: np.ndarray  # (T, K) into each stream (−1: no sample)
    present: np.ndarray  # (T, K) bool
    offsets: np.ndarray | None  # (T, K) s, imu_time_offset, or None when all zero
    union: bool
    how: str  # for ``source``
    lines: list  # for the import report


def _time_base(streams, ref: int, time_tolerance: float | None) -> _TimeBase:
    """The reference's stamps when every IMU runs at its rate, else the union of all stamps
    (module docstring, :mod:`accel_bayes.data.csv_timebase`)."""
    K = len(streams)
    if time_tolerance is not None and not (time_tolerance >= 0 and math.isfinite(time_tolerance)):
        raise UserError(f"--time-tolerance: expected a non-negative number of seconds, got {time_tolerance}")
    if not rates_agree(streams, ref):
        base, index, rows = union_streams(streams)
        present = index >= 0
        offsets = np.where(present, 0.0, np.nan)  # §7.1: the IMU's own stamp is the union stamp where it has one
        rates = ", ".join(f"{r['rate_hz']:.4g}" for r in rows)
        how = (f"the union of the IMUs' own stamps (integer ns; rates {rates} Hz), every sample kept, NaN where an "
               "IMU has none (DESIGN 7.1)")
        lines = [f"IMU {r['label']}: {r['samples']} samples read, {r['used']} kept, {r['rate_hz']:.6g} Hz" for r in rows]
        return _TimeBase((base - base[0]).astype(np.float64) / 1e9, index, present, offsets, True, how, lines)
    p0 = median_period_ns(streams[ref].stamps_ns)
    p0 = p0 if p0 > 0 else 0
    tol_ns = int(p0 // 4) if time_tolerance is None else int(round(time_tolerance * 1e9))
    base, index, rows = align_streams(streams, ref, tol_ns)
    # Integer differences first; only the differences become float seconds.
    offsets_ns = np.stack([streams[k].stamps_ns[index[:, k]] - base for k in range(K)], -1)
    offsets = offsets_ns.astype(np.float64) / 1e9 if np.any(offsets_ns) else None
    how = (f"stamps of the reference IMU {streams[ref].label!r} (integer ns), others matched to the nearest sample "
           f"within {tol_ns / 1e6:g} ms")
    lines = []
    if rows and rows[0]["dropped_ends"]:
        lines.append(f"dropped {rows[0]['dropped_ends']} reference stamps outside the span every IMU covers")
    lines += [f"IMU {r['label']}: {r['samples']} samples read, {r['used']} used, worst stamp mismatch "
              f"{r['worst_ns'] / 1e6:.6g} ms, median offset {r['median_ns'] / 1e6:.6g} ms" for r in rows]
    return _TimeBase((base - base[0]).astype(np.float64) / 1e9, index, np.ones(index.shape, bool), offsets,
                     False, how, lines)


def _reference_picks(tb: _TimeBase, ref: int):
    """(rows (T_ref,), pick (T_ref, K)): the union rows of the reference IMU's samples and, for
    each IMU, the union row of its sample nearest to each of them."""
    rows = np.flatnonzero(tb.present[:, ref])
    t_ns = np.round(tb.time * 1e9).astype(np.int64)
    pick = np.stack([np.flatnonzero(tb.present[:, k])[nearest_index(t_ns[tb.present[:, k]], t_ns[rows])]
                     for k in range(tb.present.shape[1])], -1)
    return rows, pick


def _between_reference_rows(mask_ref: np.ndarray, rows: np.ndarray, T: int) -> np.ndarray:
    """(T,) a union row is marked where the reference samples on both sides of it are (rows
    before the first or after the last reference sample take their one neighbour's mark)."""
    j = np.searchsorted(rows, np.arange(T))  # first reference row at or after each union row
    nxt = np.clip(j, 0, rows.size - 1)
    prev = np.clip(np.where(rows[nxt] == np.arange(T), nxt, j - 1), 0, rows.size - 1)
    return np.asarray(mask_ref, bool)[prev] & np.asarray(mask_ref, bool)[nxt]


def _on_reference_stamps(rec: Recording, tb: _TimeBase, ref: int) -> Recording:
    """``rec`` (a union of stamps) resampled to the reference IMU's stamps by nearest sample: for
    the gyro-unit check only, which compares IMUs at one instant.  Offsets of up to half a
    reference period do not matter there: it tells factors of 57 apart."""
    rows, pick = _reference_picks(tb, ref)
    cols = np.arange(pick.shape[1])[None, :]
    take = lambda x: None if x is None else np.asarray(x)[pick, cols]  # noqa: E731
    return Recording(time=tb.time[rows], acc=take(rec.acc), gyro=take(rec.gyro), nominal_position=rec.nominal_position,
                     nominal_orientation=rec.nominal_orientation, acc_noise_std=rec.acc_noise_std,
                     gyro_noise_std=rec.gyro_noise_std, acc_clipped=take(rec.acc_clipped),
                     gyro_clipped=take(rec.gyro_clipped),
                     segment=None if rec.segment is None else np.asarray(rec.segment)[rows])

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

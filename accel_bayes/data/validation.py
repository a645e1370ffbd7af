"""Validation of an in-memory recording against format v1 (DESIGN §7.1), with errors that name the problem.

:func:`validate_recording` checks a :class:`~accel_bayes.data.recording.Recording` (what
:func:`read_recording` returns, and what the simulator and importers build): shapes, finite
samples, strictly increasing time, positive noise levels, observable accelerometer geometry,
reference IMU, segment labels, and whether the gyroscope values plausibly are in rad/s (see
:func:`gyro_unit_diagnostics` for the rule; :func:`acc_unit_diagnostics` for m/s²).  Which kind of
recording it is: :func:`sample_present`, :func:`is_multirate`, :func:`rig_model_applies`.

The structure of a dataset read from a file is checked before, by
:func:`accel_bayes.data.format_v1.validate_dataset` (the format's contract tables live there).
Every failure raises :class:`~accel_bayes.errors.RecordingError` with a one-line message that
names the field, what was expected and what was found.  Nothing is altered or guessed: a
recording either passes as it is or is refused.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..physics.arrays import check_triad_geometry
from ..errors import RecordingError
from ..physics.geometry import quat_to_matrix
from ..constants import DEG_TO_RAD, G0, RAD_TO_DEG
from .format_v1 import SEGMENT_LABELS, plain_value, units_kind

__all__ = [
    "validate_recording",
    "sample_present",
    "is_multirate",
    "is_gyro_rig",
    "rig_model_applies",
    "acc_unit_diagnostics",
    "gyro_unit_diagnostics",
    "DEFAULT_GYRO_BOUND",
]

# Without a stated gyro_range, |ω| above this is not a plausible rad/s reading: 150 rad/s ≈ 8600 °/s,
# over twice the full scale of the fastest common MEMS gyroscopes (±4000 °/s ≈ 70 rad/s), and well
# above the ω ~ N(0, 1000 °/s) motion of the [C21] §IV-A simulations (99.9th percentile ≈ 57 rad/s).
DEFAULT_GYRO_BOUND = 150.0
# A sensor cannot read beyond its full scale: |acc| above this × acc_range is not a reading (units
# or corrupt data), not a clipped sample (DESIGN §7.1: acc_clipped marks samples *at* the range).
# The margin leaves room for intrinsics applied to clipped samples (scale and bias of a few %).
ACC_RANGE_FACTOR = 1.5
# Without acc_range: 10⁵ m/s² ≈ 10 000 g, beyond any inertial-array accelerometer; values far
# beyond it also overflow the squared residuals of the fits ("cost is not finite").
DEFAULT_ACC_BOUND = 1e5
# Static-noise rule: σ_static / σ_stated within a factor 3 of 180/π (i.e. 19×–172×) flags deg/s.
STATIC_RATIO_BAND = 3.0
# Accelerometer-array rule: decisions need the estimate 5 standard errors clear of the midpoint.
Z_DECISIVE = 5.0

# ---------------------------------------------------------------- recording level

def sample_present(rec) -> np.ndarray:
    """(T, K) bool: IMU k has a sample at ``time[t]`` — False only where its acc (and gyro, if it
    has one) is NaN in every axis (DESIGN §7.1: multi-rate recordings hold the union of stamps)."""
    acc = np.asarray(rec.acc, dtype=float)
    miss = np.isnan(acc).all(-1)
    if rec.gyro is not None:
        g = np.asarray(rec.gyro, dtype=float)
        has_g = ~np.all(np.isnan(g), axis=(0, 2))
        miss = miss & (np.isnan(g).all(-1) | ~has_g[None, :])
    return ~miss


def is_multirate(rec) -> bool:
    """True when some IMU with an accelerometer lacks a sample at some union stamp (DESIGN §7.1)."""
    acc = np.asarray(rec.acc, dtype=float)
    has_acc = ~np.all(np.isnan(acc), axis=(0, 2))
    return bool((~sample_present(rec)[:, has_acc]).any())


def is_gyro_rig(has_acc: np.ndarray, has_gyro: np.ndarray) -> bool:
    """≥ 2 IMUs with an accelerometer, each with a gyroscope: what the rig model calibrates."""
    return bool(has_acc.sum() >= 2 and np.all(has_gyro[has_acc]))


def rig_model_applies(rec) -> bool:
    """True for a rig the rig model calibrates (``accel-bayes calibrate`` dispatches there): ≥ 2 IMUs
    with accelerometers, all with gyroscopes, and either < 3 triads or separately stamped IMUs
    (multi-rate NaN-union ``time`` or a finite ``imu_time_offset``)."""
    acc = np.asarray(rec.acc, dtype=float)
    has_acc = ~np.all(np.isnan(acc), axis=(0, 2))
    has_gyro = (np.zeros(acc.shape[1], bool) if rec.gyro is None
                else ~np.all(np.isnan(np.asarray(rec.gyro, dtype=float)), axis=(0, 2)))
    own = rec.imu_time_offset is not None and np.isfinite(np.asarray(rec.imu_time_offset, dtype=float)).any()
    return is_gyro_rig(has_acc, has_gyro) and bool(has_acc.sum() < 3 or own or is_multirate(rec))


def _shape_check(name, x, shape):
    if x is None:
        return
    got = np.shape(x)
    if tuple(got) != tuple(shape):
        raise RecordingError(f"{name}: expected shape {tuple(shape)}, got {tuple(got)}")


def _first_bad(x: np.ndarray, ok: np.ndarray, time: np.ndarray, name: str, labels, what: str):
    """Report the first (time index, IMU) where ``ok`` fails, with the count."""
    bad = ~ok
    n = int(bad.sum())
    t_idx, k_idx = np.argwhere(bad)[0][:2]
    kind = "NaN" if np.isnan(x[t_idx, k_idx]).any() else "inf"
    raise RecordingError(
        f"{name}: {n} non-finite value(s) for IMUs {what}; first {kind} at time index {int(t_idx)} "
        f"(t = {float(time[t_idx]):.6g} s), IMU {int(labels[k_idx])}; expected finite samples "
        "(mark missing IMUs with NaN in every sample, not a few)")


def _full_scale(rec, sensor: str) -> tuple[float, str]:
    """The largest value ``sensor`` ("acc" or "gyro") can read: its stated range, else the
    default bound; and how to name it in a message."""
    rng = getattr(rec, f"{sensor}_range")
    unit = "m s-2" if sensor == "acc" else "rad s-1"
    if rng is not None:
        return float(rng), f"{sensor}_range = {float(rng):.4g} {unit}"
    b = DEFAULT_ACC_BOUND if sensor == "acc" else DEFAULT_GYRO_BOUND
    return b, f"{b:g} {unit} (no {sensor}_range given)"


def _check_gyro_bound(rec, time) -> None:
    """Refuse a gyroscope value no gyroscope reads: above 10 × :data:`DEFAULT_GYRO_BOUND`
    (1500 rad/s ≈ 86 000 °/s, whatever the stated range: unclipped simulations legitimately go
    past it).  A single 1e300 passed the unit check's percentile rule and made the fits fail
    with a traceback."""
    if rec.gyro is None:
        return
    bound = 10 * DEFAULT_GYRO_BOUND
    g = np.abs(np.asarray(rec.gyro, dtype=float))
    over = np.nan_to_num(g, nan=0.0).max(axis=2) > bound
    if over.any():
        t_idx, k_idx = np.argwhere(over)[0]
        raise RecordingError(f"gyro: {float(np.nanmax(g[t_idx, k_idx])):.4g} rad s-1 at time index {int(t_idx)} "
                             f"(t = {float(time[t_idx]):.6g} s), IMU {int(k_idx)} ({int(over.sum())} such samples); "
                             f"expected |gyro| <= {bound:g} rad s-1 (no gyroscope reads beyond it)")


def _check_acc_bound(rec, time) -> None:
    """Refuse accelerometer values beyond what the sensor can read (:data:`ACC_RANGE_FACTOR`)."""
    if rec.acc_range is not None:
        bound = ACC_RANGE_FACTOR * float(rec.acc_range)
        what = f"|acc| <= {ACC_RANGE_FACTOR:g} × acc_range = {bound:.4g} m s-2 (a sensor cannot read beyond its range)"
    else:
        bound = DEFAULT_ACC_BOUND
        what = f"|acc| <= {bound:g} m s-2 (no acc_range given; ≈ 10 000 g)"
    a = np.abs(np.asarray(rec.acc, dtype=float))
    over = np.nan_to_num(a, nan=0.0).max(axis=2) > bound  # (T, K)
    if over.any():
        t_idx, k_idx = np.argwhere(over)[0]
        raise RecordingError(f"acc: {float(np.nanmax(a[t_idx, k_idx])):.4g} m s-2 at time index {int(t_idx)} "
                             f"(t = {float(time[t_idx]):.6g} s), IMU {int(k_idx)} ({int(over.sum())} such samples); "
                             f"expected {what}; check the units or the acc_range attribute")


def validate_recording(rec, *, require_gyro: bool = False, reference_imu: int | None = None,
                       gyro_units: str = "rad s-1", check_gyro_units: bool = True,
                       check_acc_units: bool = True) -> None:
    """Check an in-memory :class:`Recording` against format v1 (DESIGN §7.1).

    Raises :class:`RecordingError` naming the field and what was expected when:

    * a shape disagrees: time (T,), acc (T, K, 3), gyro (T, K, 3), nominal_position (K, 3),
      nominal_orientation (K, 4) unit quaternions, acc/gyro_noise_std (K,), acc/gyro_clipped
      (T, K) bool, segment (T,) with labels "static"/"dynamic";
    * time is not finite or not strictly increasing (the first failing index is named);
    * acc of an IMU that has an accelerometer (not all NaN), or gyro of an IMU that has a
      gyroscope, holds NaN/inf (first time index, time value, IMU label and count are named);
    * a noise std is ≤ 0 or not finite for an IMU with that sensor (the IMU is named);
    * fewer than 3 accelerometer triads, or collinear ones (rotation about their line is
      unobservable) — :func:`accel_bayes.physics.arrays.check_triad_geometry`;
    * the reference IMU (``reference_imu`` if given, else ``rec.reference_imu``) is not a label
      0..K−1 of an IMU with an accelerometer;
    * acc_range / gyro_range are given but not finite positive numbers;
    * an accelerometer value exceeds :data:`ACC_RANGE_FACTOR` × acc_range (or
      :data:`DEFAULT_ACC_BOUND` without acc_range): not a reading, so not flagged as clipped either;
    * ``require_gyro`` and the recording has no gyroscope data;
    * ``check_gyro_units`` and the gyro values do not look like rad/s (:func:`gyro_unit_diagnostics`);
      not checked where ``rec.attrs["gyro_unit_check"] == "skipped"`` (an importer's recorded
      override, ``import-csv --skip-gyro-unit-check``);
    * ``check_acc_units`` and |acc| at rest is far from g, as accelerometer data in g, or in m/s²
      converted once more, would be (:func:`acc_unit_diagnostics`).

    ``gyro_units`` is the unit the values were *declared* in before they were converted to rad/s
    ("rad s-1" for in-memory recordings; :func:`read_recording` passes "deg s-1" for a file that
    declared degrees).  It only selects which unit mistake to look for and how to word it.
    """
    time = np.asarray(rec.time)
    acc = np.asarray(rec.acc)
    if time.ndim != 1:
        raise RecordingError(f"time: expected a 1-D array (T,), got shape {time.shape}")
    T = time.shape[0]
    if T < 1:
        raise RecordingError("time: the recording has no samples (T = 0)")
    if acc.ndim != 3 or acc.shape[0] != T or acc.shape[2] != 3:
        raise RecordingError(f"acc: expected shape (T, K, 3) = ({T}, K, 3) (time, imu, axis), got {acc.shape}")
    K = acc.shape[1]
    if K < 1:
        raise RecordingError("acc: the recording has no IMUs (K = 0)")
    _shape_check("gyro", rec.gyro, (T, K, 3))
    _shape_check("nominal_position", rec.nominal_position, (K, 3))
    _shape_check("nominal_orientation", rec.nominal_orientation, (K, 4))
    _shape_check("acc_noise_std", rec.acc_noise_std, (K,))
    _shape_check("gyro_noise_std", rec.gyro_noise_std, (K,))
    _shape_check("acc_clipped", rec.acc_clipped, (T, K))
    _shape_check("gyro_clipped", rec.gyro_clipped, (T, K))
    _shape_check("acc_flagged", rec.acc_flagged, (T, K))
    _shape_check("gyro_flagged", rec.gyro_flagged, (T, K))
    _shape_check("segment", rec.segment, (T,))
    _shape_check("imu_time_offset", rec.imu_time_offset, (T, K))
    for name in ("time", "acc", "gyro", "nominal_position", "nominal_orientation", "acc_noise_std", "gyro_noise_std",
                 "imu_time_offset"):
        x = getattr(rec, name)
        if x is not None and np.asarray(x).dtype.kind not in "iuf":
            raise RecordingError(f"{name}: expected a float array, got dtype {np.asarray(x).dtype}")
    for name in ("acc_clipped", "gyro_clipped", "acc_flagged", "gyro_flagged"):
        x = getattr(rec, name)
        if x is not None and np.asarray(x).dtype != bool:
            raise RecordingError(f"{name}: expected a bool array, got dtype {np.asarray(x).dtype}")
    for name in ("gyro_clipped", "gyro_flagged"):
        if rec.gyro is None and getattr(rec, name) is not None:
            raise RecordingError(f"{name}: given but the recording has no gyro")

    # Time.
    if not np.all(np.isfinite(time)):
        i = int(np.flatnonzero(~np.isfinite(time))[0])
        raise RecordingError(f"time: expected finite sample times, got {time[i]} at index {i}")
    if T > 1:
        dt = np.diff(time)
        if not np.all(dt > 0):
            i = int(np.flatnonzero(~(dt > 0))[0]) + 1
            raise RecordingError(f"time: expected strictly increasing sample times; time[{i}] = {time[i]:.9g} s "
                                 f"is not after time[{i - 1}] = {time[i - 1]:.9g} s")

    labels = np.arange(K)
    has_acc = ~np.all(np.isnan(acc), axis=(0, 2))
    if not has_acc.any():
        raise RecordingError("acc: every IMU is all-NaN; expected accelerometer data for at least 3 IMUs")
    gyro = None if rec.gyro is None else np.asarray(rec.gyro)
    has_gyro = np.zeros(K, bool) if gyro is None else ~np.all(np.isnan(gyro), axis=(0, 2))
    # DESIGN §7.1 multi-rate: an IMU without a sample at a union stamp is NaN in every axis of
    # every sensor it has there; a partly NaN sample is a damaged reading, not a missing one
    present = sample_present(rec)
    for name, x, has, what in (("acc", acc, has_acc, "with an accelerometer"),
                               ("gyro", gyro, has_gyro, "with a gyroscope")):
        if x is None or not has.any():
            continue
        fin = np.isfinite(x[:, has, :]).all(-1) | ~present[:, has]
        if not fin.all():
            _first_bad(x[:, has, :], fin, time, name, labels[has], what)
    if not present[:, has_acc].any(-1).all():
        i = int(np.flatnonzero(~present[:, has_acc].any(-1))[0])
        raise RecordingError(f"acc: no IMU has a sample at time index {i} (t = {float(time[i]):.6g} s); expected "
                             "time to be the union of the IMUs' stamps")
    if require_gyro and not has_gyro.any():
        raise RecordingError("gyro: this analysis needs gyroscope data (variable gyro, rad s-1), the recording has none")

    # Noise levels.
    for name, has, unit in (("acc_noise_std", has_acc, "m s-2"), ("gyro_noise_std", has_gyro, "rad s-1")):
        s = np.asarray(getattr(rec, name), dtype=float)
        bad = has & ~(np.isfinite(s) & (s > 0))
        if not bad.any():
            # a noise std beyond the sensor's full scale is not a noise level (1e300 made the fits'
            # Cholesky factorisations fail with a traceback)
            top, top_txt = _full_scale(rec, name[:-len("_noise_std")])
            big = has & (s > top)
            if big.any():
                k = int(np.flatnonzero(big)[0])
                raise RecordingError(f"{name}: IMU {k} has {float(s[k])!r}; expected a noise std <= {top_txt}")
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise RecordingError(f"{name}: IMU {k} has {float(s[k])!r}; expected a finite value > 0 {unit} for every "
                                 f"IMU with {'an accelerometer' if name.startswith('acc') else 'a gyroscope'}"
                                 + (f" ({int(bad.sum())} IMUs affected)" if bad.sum() > 1 else ""))

    if rec.imu_time_offset is not None and np.isinf(np.asarray(rec.imu_time_offset, dtype=float)).any():
        t_idx, k = np.argwhere(np.isinf(np.asarray(rec.imu_time_offset, dtype=float)))[0]
        raise RecordingError(f"imu_time_offset: infinite value at time index {int(t_idx)}, IMU {int(k)}; expected "
                             "finite offsets in s (NaN where unknown)")

    # Geometry.
    pos = np.asarray(rec.nominal_position, dtype=float)
    if not np.isfinite(pos).all():
        k = int(np.flatnonzero(~np.isfinite(pos).all(-1))[0])
        raise RecordingError(f"nominal_position: IMU {k} has {pos[k].tolist()}; expected finite positions in m")
    q = np.asarray(rec.nominal_orientation, dtype=float)
    qn = np.linalg.norm(q, axis=-1)
    bad = ~np.isfinite(qn) | (np.abs(qn - 1.0) > 1e-6)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        raise RecordingError(f"nominal_orientation: IMU {k} has {q[k].tolist()} (norm {qn[k]:.6g}); expected a "
                             "unit quaternion (w, x, y, z)")
    # a rig of >= 2 IMUs that all have gyros, with < 3 triads or separately stamped IMUs, is
    # calibrated by the rig model (lever arms from the gyros' ω, ω̇; pipelines.rig.is_rig), so the
    # [C21] need for three non-collinear triads does not apply to it
    if not rig_model_applies(rec):
        try:
            check_triad_geometry(torch.as_tensor(pos[has_acc]), labels=labels[has_acc].tolist())
        except ValueError as exc:
            raise RecordingError(f"nominal_position: {exc}") from None

    ref = rec.reference_imu if reference_imu is None else reference_imu
    if isinstance(ref, (bool, np.bool_)) or not isinstance(ref, (int, np.integer)):
        raise RecordingError(f"reference_imu: expected an integer IMU label in 0..{K - 1}, got {plain_value(ref)!r}")
    if not 0 <= int(ref) < K:
        raise RecordingError(f"reference_imu: expected an IMU label in 0..{K - 1}, got {int(ref)}")
    if not has_acc[int(ref)]:
        raise RecordingError(f"reference_imu: IMU {int(ref)} has no accelerometer data; choose one of "
                             f"{labels[has_acc].tolist()}")
    for name in ("acc_range", "gyro_range"):
        v = getattr(rec, name)
        if v is not None and not (math.isfinite(float(v)) and float(v) > 0):
            raise RecordingError(f"{name}: expected a finite full scale > 0 (or None), got {plain_value(v)!r}")
    _check_acc_bound(rec, time)

    if rec.segment is not None:
        seg = np.asarray(rec.segment)
        ok = np.isin(seg.astype(str), SEGMENT_LABELS)
        if not ok.all():
            i = int(np.flatnonzero(~ok)[0])
            raise RecordingError(f'segment: expected labels "static" or "dynamic", got {str(seg[i])!r} at time index {i} '
                                 f"({int((~ok).sum())} such samples)")

    # An importer's explicit override (csv_import --skip-gyro-unit-check) holds for every later read.
    if check_gyro_units and has_gyro.any() and (getattr(rec, "attrs", None) or {}).get("gyro_unit_check") != "skipped":
        _raise_on_gyro_units(rec, gyro_units)
    _check_gyro_bound(rec, time)  # after the unit check: data in the other unit get its message
    if check_acc_units:
        flag = acc_unit_diagnostics(rec)["flag"]
        if flag:
            raise RecordingError(flag)


# ---------------------------------------------------------------- accelerometer unit plausibility

# At rest an accelerometer reads g = 9.81 m/s² whatever its bias or scale error (a few % at most).
# Data in g declared as m/s² reads ≈ 1, and m/s² declared as g (converted once more) ≈ 96: a factor
# of two either way of those leaves room for any sensor error and still cannot be a real rest.
ACC_REST_BAND = 2.0
REST_RATE = 0.1  # rad/s (5.7 °/s): without rest labels, samples whose gyros turn slower are "still"
MIN_REST_SAMPLES = 20


def acc_unit_diagnostics(rec) -> dict:
    """Evidence on whether ``rec.acc`` is in m/s²: the median ‖acc‖ (m/s², over the IMUs with an
    accelerometer) at rest.

    Rest samples: ``segment == "static"`` where there are at least 20, else, with gyros, the
    samples whose gyros' median ‖ω‖ is below ``REST_RATE``; fewer than 20 of either leaves the
    test inconclusive (``rest_norm`` NaN).  Clipped samples are left out.  The unit is flagged
    when the rest norm lies within a factor ``ACC_REST_BAND`` of 1 (values in g) or of g²
    (m/s² values declared as g, converted again); a recording without gravity (|a| ≈ 0 at rest,
    a simulation) is not flagged.  Returns ``rest_norm``, ``n_rest``, ``rest_from`` and ``flag``
    (the one-line message to raise, or None).
    """
    acc = np.asarray(rec.acc, dtype=float)
    has_a = ~np.all(np.isnan(acc), axis=(0, 2))
    T = acc.shape[0]
    rest, rest_from = np.zeros(T, bool), "none"
    if rec.segment is not None:
        rest = np.asarray(rec.segment).astype(str) == "static"
        rest_from = "static segments"
    if rest.sum() < MIN_REST_SAMPLES and rec.gyro is not None:
        g = np.asarray(rec.gyro, dtype=float)
        has_g = ~np.all(np.isnan(g), axis=(0, 2))
        if has_g.any():
            rate = np.median(np.linalg.norm(g[:, has_g], axis=-1), axis=1)
            rest, rest_from = rate < REST_RATE, f"samples with |ω| < {REST_RATE:g} rad/s"
    if rec.acc_clipped is not None:
        rest &= ~np.asarray(rec.acc_clipped)[:, has_a].any(1)
    out = {"rest_norm": float("nan"), "n_rest": int(rest.sum()), "rest_from": rest_from, "flag": None}
    if rest.sum() < MIN_REST_SAMPLES or not has_a.any():
        return out
    norm = float(np.median(np.linalg.norm(acc[rest][:, has_a], axis=-1)))
    out["rest_norm"] = norm
    where = f"(median over {int(rest.sum())} rest samples, {rest_from}) where g = {G0:.4g} is expected"
    if 1 / ACC_REST_BAND <= norm <= ACC_REST_BAND:
        out["flag"] = (f"acc: values look like g, not the declared m s-2: |acc| at rest = {norm:.3g} {where}; "
                       "convert acc to m/s² (× 9.80665) or declare its unit as g")
    elif G0**2 / ACC_REST_BAND <= norm <= G0**2 * ACC_REST_BAND:
        out["flag"] = (f"acc: values look like m/s² declared as g (converted twice): |acc| at rest = {norm:.4g} m/s² "
                       f"{where}; declare the unit as m s-2")
    return out


# ---------------------------------------------------------------- gyro unit plausibility

def _declared_kind(gyro_units: str) -> str:
    kind = units_kind(gyro_units)
    if kind not in ("rad s-1", "deg s-1"):
        raise ValueError(f'gyro_units: expected "rad s-1" or "deg s-1", got {gyro_units!r}')
    return kind


def gyro_unit_diagnostics(rec, gyro_units: str = "rad s-1", max_samples: int = 20000) -> dict:
    """Evidence on whether ``rec.gyro`` (rad/s after any declared conversion) really is rad/s.

    Let the true rate be ω = c·gyro.  If the values are what they were declared to be, c = 1.
    The mistake looked for is the other unit: declared rad/s but written in °/s (c = π/180), or
    declared °/s but written in rad/s (c = 180/π).  Three tests:

    **C — accelerometer-array consistency (decides when it can).**  On a rigid body the triads
    read f_k = W p_k + s with W = Ω(ω)² + Ω(ω̇) ([C21] eq. 4a).  Per sample, W is fitted by least
    squares from the nominal positions (array frame), restricted by the projector P to the
    directions the centred positions span (spreads under 20 % of the widest count as flat, so a
    two-sided PCB is treated as planar).  Ω(ω̇) is skew, so
    τ = −tr(P W P) = rank(P)·|ω|² − |Pω|² depends on the rotation rate only, not on ω̇, s, or (for
    3-D arrays) the gyro's orientation.  Regressing τ_acc = α + β·τ_gyro over samples (α takes up
    accelerometer biases; clipped samples are left out) estimates β = c².  With standard error
    se(β): β + 5·se < c_alt (i.e. below the geometric midpoint 1/57.3 between 1 and (π/180)²)
    means "the values are in the other unit"; 1/57.3 < β − 5·se and β + 5·se < 57.3 means
    "consistent with the declared unit" and the other tests are skipped; otherwise there is too
    little rotation to tell, and A and B decide.

    **A — range (declared rad/s only).**  The 99.9th percentile of |gyro| over all axes, samples
    and gyro IMUs must not exceed 1.5 × gyro_range if given (a sensor cannot read beyond its
    range), else :data:`DEFAULT_GYRO_BOUND` = 150 rad/s.

    **B — static noise (needs ``segment`` labels with ≥ 20 static samples).**  The gyro std about
    the mean of each static run (median over gyro IMUs) divided by the stated gyro_noise_std is
    ≈ 1 for the right unit and ≈ 57.3 (or 1/57.3) for the wrong one; a ratio within a factor 3
    of 57.3 (declared rad/s) or of 1/57.3 (declared °/s) flags the unit.

    Returns a dict with the quantities and verdicts (``"declared"``, ``"other"``,
    ``"inconclusive"`` for C; bools ``range_flag`` and ``static_flag``) and ``flag`` (the
    message to raise, or None).
    """
    kind = _declared_kind(gyro_units)
    other = "deg s-1" if kind == "rad s-1" else "rad s-1"
    c_alt = DEG_TO_RAD if kind == "rad s-1" else RAD_TO_DEG
    out = {"declared": kind, "c_alt": c_alt, "flag": None}
    gyro = np.asarray(rec.gyro, dtype=float)
    has_g = ~np.all(np.isnan(gyro), axis=(0, 2))
    g_idx = np.flatnonzero(has_g)
    acc = np.asarray(rec.acc, dtype=float)
    has_a = ~np.all(np.isnan(acc), axis=(0, 2))
    a_idx = np.flatnonzero(has_a)
    T = acc.shape[0]

    # --- C: accelerometer-array consistency
    use = np.ones(T, bool)
    if rec.acc_clipped is not None:
        use &= ~np.asarray(rec.acc_clipped)[:, a_idx].any(1)
    if rec.gyro_clipped is not None:
        use &= ~np.asarray(rec.gyro_clipped)[:, g_idx].any(1)
    idx = np.flatnonzero(use)
    if idx.size > max_samples:
        idx = idx[:: int(math.ceil(idx.size / max_samples))]
    beta = se = float("nan")
    verdict = "inconclusive"
    if idx.size >= 10 and a_idx.size >= 3:
        R = quat_to_matrix(torch.as_tensor(np.asarray(rec.nominal_orientation, dtype=float))).numpy()
        y = np.einsum("kji,tkj->tki", R[a_idx], acc[idx][:, a_idx])  # array frame: R(q)ᵀ f
        w = np.einsum("kji,tkj->tki", R[g_idx], gyro[idx][:, g_idx]).mean(1)
        p = np.asarray(rec.nominal_position, dtype=float)[a_idx]
        D = p - p.mean(0)
        U, sv, Vt = np.linalg.svd(D, full_matrices=False)
        # Directions along which the triads spread less than 20 % of the widest one (a two-sided
        # PCB is ~2 mm thick, ~20 mm wide) are treated as flat: their column of W is poorly
        # determined and would only add noise.
        rank = int((sv > 0.2 * sv[0]).sum())
        V = Vt[:rank].T
        P = V @ V.T
        Dp = V @ np.diag(1.0 / sv[:rank]) @ U[:, :rank].T  # truncated D⁺ (3, A): Wᵀ = D⁺ (y − ȳ)
        yc = y - y.mean(1, keepdims=True)
        tau_acc = -np.einsum("ia,tai->t", Dp, yc)
        tau_gyr = rank * (w * w).sum(-1) - ((w @ P) ** 2).sum(-1)
        xm = tau_gyr - tau_gyr.mean()
        sxx = float((xm * xm).sum())
        if sxx > 0 and np.isfinite(sxx):
            beta = float((xm * (tau_acc - tau_acc.mean())).sum() / sxx)
            res = tau_acc - tau_acc.mean() - beta * xm
            se = float(math.sqrt(max((res * res).sum() / max(idx.size - 2, 1), 0.0) / sxx))
            mid = c_alt  # geometric midpoint between β = 1 and β = c_alt²
            lo, hi = beta - Z_DECISIVE * se, beta + Z_DECISIVE * se
            if (kind == "rad s-1" and hi < mid) or (kind == "deg s-1" and lo > mid):
                verdict = "other"
            elif 1.0 / RAD_TO_DEG < lo and hi < RAD_TO_DEG:
                verdict = "declared"
    out.update(beta=beta, beta_se=se, array_verdict=verdict, n_used=int(idx.size))
    word = "deg/s" if other == "deg s-1" else "rad/s"
    fix = ('convert gyro to rad/s (× π/180) or declare its units attribute "deg s-1"' if kind == "rad s-1"
           else 'set the gyro units attribute to "rad s-1"')
    head = (f"gyro: values look like {word}, not the declared {kind}"
            + (" (converted to rad s-1 on read)" if kind == "deg s-1" else "") + ": ")
    if verdict == "other":
        out["flag"] = (head + f"the centripetal acceleration seen across the accelerometer triads fits "
                       f"(c·gyro)² with c² = {beta:.3g} ± {se:.2g}, i.e. c ≈ {math.sqrt(max(beta, 0)):.3g} "
                       f"(rule: flagged when c² {'+' if kind == 'rad s-1' else '−'} 5 s.e. "
                       f"{'<' if kind == 'rad s-1' else '>'} {c_alt:.4g}, the geometric midpoint between c² = 1 and "
                       f"{c_alt:.4g}²); {fix}")
        return out

    # --- A: range
    absg = np.abs(gyro[:, g_idx, :])
    p999 = float(np.quantile(absg[np.isfinite(absg)], 0.999)) if absg.size else 0.0
    if rec.gyro_range is not None:
        bound, bound_txt = 1.5 * float(rec.gyro_range), f"1.5 × gyro_range = {1.5 * float(rec.gyro_range):.4g} rad/s"
    else:
        bound, bound_txt = DEFAULT_GYRO_BOUND, f"{DEFAULT_GYRO_BOUND:g} rad/s (no gyro_range given; ≈ 8600 °/s)"
    out.update(p999=p999, bound=bound)
    out["range_flag"] = kind == "rad s-1" and verdict != "declared" and p999 > bound

    # --- B: static noise
    ratio = float("nan")
    if rec.segment is not None:
        st = np.asarray(rec.segment).astype(str) == "static"
        if rec.gyro_clipped is not None:
            st &= ~np.asarray(rec.gyro_clipped)[:, g_idx].any(1)
        if st.sum() >= 20:
            run = np.cumsum(np.r_[True, st[1:] != st[:-1]])  # a new id wherever static/dynamic changes
            g = gyro[st][:, g_idx, :]  # (n, G, 3)
            r_id = np.unique(run[st], return_inverse=True)[1]
            n_run = np.bincount(r_id)
            flat = g.reshape(g.shape[0], -1)
            means = np.stack([np.bincount(r_id, weights=flat[:, j]) / n_run for j in range(flat.shape[1])], 1)
            dev = flat - means[r_id]
            dof = max(g.shape[0] - n_run.size, 1)
            var = (dev * dev).sum(0).reshape(len(g_idx), 3).mean(1) / dof  # per gyro IMU
            sig = np.asarray(rec.gyro_noise_std, dtype=float)[g_idx]
            ratio = float(np.median(np.sqrt(var) / sig))
    out["static_ratio"] = ratio
    target = 1.0 / c_alt  # values in the other unit: σ_static / σ_stated ≈ 1/c
    out["static_flag"] = (verdict != "declared" and math.isfinite(ratio)
                          and target / STATIC_RATIO_BAND <= ratio <= target * STATIC_RATIO_BAND)

    if out["range_flag"]:
        out["flag"] = (head + f"99.9th percentile |gyro| = {p999:.4g} rad/s exceeds {bound_txt}; {fix}"
                       + (" (or correct gyro_range)" if rec.gyro_range is not None else ""))
    elif out["static_flag"]:
        out["flag"] = (head + f"in the static segments the gyro std is {ratio:.3g} × the stated gyro_noise_std "
                       f"(rule: {target / STATIC_RATIO_BAND:.3g}–{target * STATIC_RATIO_BAND:.3g}× flags the unit); "
                       f"{fix}, or, if the unit is right, correct gyro_noise_std (global attribute, rad s-1)")
    return out


def _raise_on_gyro_units(rec, gyro_units):
    d = gyro_unit_diagnostics(rec, gyro_units)
    if d["flag"]:
        raise RecordingError(d["flag"])

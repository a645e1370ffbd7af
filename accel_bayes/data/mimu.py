"""Importer for the MIMU4444 binary stream (OpenShoe/MIMU streaming protocol) → :class:`Recording`.

:func:`import_mimu` reads and verifies the stream (:func:`accel_bayes.data.mimu_decode.read_mimu_stream`:
the packet format and framing in :mod:`accel_bayes.data.mimu_packets`, the rules that keep, order
and time the packets in :mod:`accel_bayes.data.mimu_decode`, what they found in
:class:`~accel_bayes.data.mimu_report.ImportReport`), then makes the recording
(:func:`recording_from_stream`):

* **Scaling** (MPU-9150 at ±16 g, ±2000 °/s): acc = raw · 9.80665/2048 m/s²,
  gyro = raw/16.4 °/s converted to rad/s.  Outputs stay in each IMU's SENSOR frame (DESIGN §7.1);
  the nominal orientations (top IMUs identity, bottom IMUs ``MIMU_BOTTOM_QUAT``) and positions
  come from :func:`accel_bayes.physics.arrays.mimu4444_8`.
* **Clipping**: a sample is clipped where any axis reads −32768 or 32767 (the recordings show
  thousands of gyro samples exactly at those codes and almost none one code inside them).
* **Rests and noise**: :func:`accel_bayes.data.segments.analyse_static` labels samples
  ``"static"``/``"dynamic"`` and the per-IMU noise std is the pooled within-rest std (each rest's
  mean removed, RMS over axes).  ``source`` says so, with the number of rests used.
"""
from __future__ import annotations

import json

import numpy as np

from ..errors import RecordingError
from ..physics.arrays import SensorArray, mimu4444_8
from .mimu_decode import MimuStream, read_mimu_stream
from .mimu_packets import ACC_RANGE, ACC_SCALE, GYRO_RANGE, GYRO_SCALE, INT16_LIMITS, N_IMU
from .mimu_report import ImportReport
from .recording import Recording
from .segments import StaticAnalysis, analyse_static, difference_noise_std, segment_labels

__all__ = ["import_mimu", "recording_from_stream"]


def _nominal_numpy(nominal: SensorArray | None):
    nominal = mimu4444_8() if nominal is None else nominal
    pos = np.asarray(nominal.positions.detach().cpu().numpy(), dtype=np.float64)
    quat = np.asarray(nominal.orientations.detach().cpu().numpy(), dtype=np.float64)
    if pos.shape != (N_IMU, 3):
        raise RecordingError(f"nominal: expected a SensorArray of {N_IMU} IMUs (packet order), got {pos.shape[0]}")
    return nominal, pos, quat


def recording_from_stream(stream: MimuStream, report: ImportReport, *, nominal: SensorArray | None = None,
                          tol_deg: float = 2.0, whiteness_tol: float = 0.05, **static_kwargs) -> tuple[Recording, StaticAnalysis]:
    """Scale a parsed stream into a :class:`Recording` (sensor frame), find its rests, estimate
    the noise from them and fill the report's rest/clipping figures.  IMUs whose pooled rest std
    differs from the first-difference estimate by more than ``whiteness_tol`` (relative) get a
    note in the report (non-white noise)."""
    nominal, pos, quat = _nominal_numpy(nominal)
    raw = stream.raw
    acc = raw[..., :3].astype(np.float64) * ACC_SCALE
    gyro = raw[..., 3:].astype(np.float64) * GYRO_SCALE
    at_limit = (raw == INT16_LIMITS[0]) | (raw == INT16_LIMITS[1])
    acc_clipped = at_limit[..., :3].any(-1)
    gyro_clipped = at_limit[..., 3:].any(-1)
    time = stream.time

    st = analyse_static(acc, gyro, time, quat, tol_deg=tol_deg, **static_kwargs)
    S = st.n_segments
    if S:
        acc_std, gyro_std = st.acc_noise_std, st.gyro_noise_std
        noise_phrase = (
            f"noise std estimated from {S} static segments (pooled within-segment std after removing "
            "each segment's mean, RMS over axes)"
        )
    else:
        acc_std = nominal.acc_noise_std.detach().cpu().numpy().astype(np.float64)
        gyro_std = nominal.gyro_noise_std.detach().cpu().numpy().astype(np.float64)
        noise_phrase = "no static segment found: noise std is the nominal preset's, not estimated"
        report.notes.append(noise_phrase)
    for kind, x, sd in (("acc", acc, acc_std), ("gyro", gyro, gyro_std)) if S else ():
        # Flag IMUs whose rest noise is not white: the pooled spread then also holds coloured or
        # tonal content (the shared recordings show a ~9 Hz tone on IMU 3's and a ~21 Hz one on
        # IMU 6's accelerometer) that a white-noise model will not explain.
        ratio = sd / difference_noise_std(x, st.segments)
        setattr(report, f"{kind}_whiteness_ratio", [round(float(r), 4) for r in ratio])
        off = np.flatnonzero(np.abs(ratio - 1) > whiteness_tol)
        if off.size:
            report.notes.append(
                f"{kind} rest noise not white (pooled / first-difference std outside 1 ± {whiteness_tol:g}): "
                + ", ".join(f"IMU {k} {ratio[k]:.2f}" for k in off)
            )

    report.static_segments = S
    report.orientations = st.n_orientations
    report.static_fraction = float(st.mask.mean()) if st.mask.size else 0.0
    report.acc_clipped_fraction = float(acc_clipped.mean())
    report.gyro_clipped_fraction = float(gyro_clipped.mean())

    source = (
        f"MIMU4444 stream {report.file} (sha256 of decompressed stream {report.sha256}); "
        f"command ack {'present' if report.ack_present else 'absent'}; "
        f"{report.packets_read} packets read, {report.packets_kept} kept, "
        f"{report.checksum_failures} checksum failures, {report.header_failures} header failures, "
        f"{report.partial_bytes} trailing partial bytes ignored, {report.missing_packets} missing packet numbers, "
        f"{report.bytes_skipped} bytes skipped to resynchronise, "
        f"{report.reordered_packets} late packets put back in number order, dropped packets by reason "
        + json.dumps({k: v for k, v in report.drop_counts.items() if v}) + "; "
        f"time = measured timestamps (64 MHz, unwrapped by packet number); {noise_phrase}; imported by accel_bayes.data.mimu"
    )
    summary = report.to_dict()
    rec = Recording(
        time=time,
        acc=acc,
        gyro=gyro,
        nominal_position=pos,
        nominal_orientation=quat,
        acc_noise_std=np.asarray(acc_std, dtype=np.float64),
        gyro_noise_std=np.asarray(gyro_std, dtype=np.float64),
        acc_clipped=acc_clipped,
        gyro_clipped=gyro_clipped,
        segment=segment_labels(st.mask),
        reference_imu=0,
        acc_range=ACC_RANGE,
        gyro_range=GYRO_RANGE,
        description=f"MIMU4444, 8 corner IMUs (packet order), {report.file}",
        source=source,
        attrs={"importer": "accel_bayes.data.mimu", "import_report": json.dumps(summary)},
    )
    return rec, st


def import_mimu(path, *, nominal: SensorArray | None = None, max_fail_fraction: float = 0.01,
                tol_deg: float = 2.0, return_report: bool = False, **static_kwargs):
    """Import a MIMU4444 ``data.bin`` / ``data.bin.gz`` as a :class:`Recording`.

    Parameters
    ----------
    path : the stream file (gzip recognised by its magic bytes).
    nominal : the board design (default :func:`mimu4444_8`, packet order): nominal positions and
        orientations written to the recording.
    max_fail_fraction : refuse the file when more than this fraction of the stream is damaged
        (:mod:`accel_bayes.data.mimu_decode`, "Refusal").
    tol_deg : rests whose gravity directions agree within this angle are one orientation.
    return_report : also return the :class:`ImportReport` and the
        :class:`~accel_bayes.data.segments.StaticAnalysis`.
    static_kwargs : passed to :func:`accel_bayes.data.segments.detect_static` (``window_s``,
        ``factor``, ``min_duration_s`` …).

    Returns the recording, or ``(recording, report, static_analysis)`` with ``return_report``.
    """
    stream, report = read_mimu_stream(path, max_fail_fraction=max_fail_fraction)
    rec, st = recording_from_stream(stream, report, nominal=nominal, tol_deg=tol_deg, **static_kwargs)
    return (rec, report, st) if return_report else rec

"""Importer for the MIMU4444 binary stream (OpenShoe/MIMU streaming protocol) → :class:`Recording`.

Stream layout (data README, ``../shared/data/mimu4444-bcd/README.md``): an optional 4-byte
command acknowledgement ``A0 28 00 C8``, then back-to-back 106-byte packets, big-endian:

====== ===============================================================
bytes  meaning
====== ===============================================================
0      header ``0xAA``
1–2    packet number, uint16, +1 per packet (wraps at 2^16)
3      payload size, 100
4–7    timestamp, uint32, 64 MHz ticks (wraps at 2^32, ≈ 67 s)
8–103  8 IMUs × [ax, ay, az, gx, gy, gz], int16
104–5  checksum, uint16 = (Σ bytes 0..103) mod 65536
====== ===============================================================

What the importer does, and why:

* The whole stream is parsed at once with a structured big-endian numpy dtype (no per-packet
  Python loop).  ``.gz`` is recognised by its magic bytes, not by the file name.
* Every packet's checksum, header byte and payload size are verified.  Failing packets are
  dropped and reported (count and the packet numbers they carry); more than
  ``max_fail_fraction`` (1 %) failing, or no valid header anywhere, means the file is not a
  (usable) MIMU stream and it is refused with :class:`RecordingError`.  A lost byte mid-stream
  would misalign every later packet; the importer does not resynchronise (the error names the
  byte offset of the first failing packet).
* A trailing partial packet is ignored and its byte count reported.  Missing packet numbers
  (gaps, counted modulo 2^16) are reported as dropped packets.
* **Time.**  The measured timestamps are kept: each interval is unwrapped modulo 2^32 with the
  packet-number step telling how many wraps a (possibly long) gap spans, and ``time`` is
  (ticks − first tick) / 64 MHz.  The device stamps are ±8 ticks (±0.125 µs, 1e-5 of the 16 ms
  period) of jitter and the first interval of a file is ~0.35 ms short; both are real properties
  of the sample instants, so no regression onto the packet number is made.  The report carries
  the jitter statistics.  Non-increasing stamps are refused.
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

import gzip
import hashlib
import json
import math
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..physics.arrays import SensorArray, mimu4444_8
from ..constants import G0
from ..errors import RecordingError
from .recording import Recording
from .segments import StaticAnalysis, analyse_static, difference_noise_std, segment_labels

__all__ = [
    "MIMU_ACK",
    "PACKET_SIZE",
    "PACKET_DTYPE",
    "TICK_HZ",
    "NOMINAL_PERIOD_TICKS",
    "ACC_SCALE",
    "GYRO_SCALE",
    "MimuStream",
    "ImportReport",
    "read_mimu_bytes",
    "read_mimu_stream",
    "decode_mimu_bytes",
    "encode_mimu_packets",
    "import_mimu",
    "recording_from_stream",
]

MIMU_ACK = bytes.fromhex("a02800c8")
HEADER = 0xAA
PAYLOAD_SIZE = 100
N_IMU = 8
PACKET_SIZE = 106
TICK_HZ = 64e6
NOMINAL_PERIOD_TICKS = 1_024_000  # 16 ms at 64 MHz
ACC_SCALE = G0 / 2048.0  # m/s² per LSB at ±16 g
GYRO_SCALE = math.radians(1.0 / 16.4)  # rad/s per LSB at ±2000 °/s
INT16_LIMITS = (-32768, 32767)
ACC_RANGE = 16 * G0
GYRO_RANGE = math.radians(2000.0)

PACKET_DTYPE = np.dtype(
    [
        ("header", "u1"),
        ("number", ">u2"),
        ("size", "u1"),
        ("timestamp", ">u4"),
        ("data", ">i2", (N_IMU, 6)),
        ("checksum", ">u2"),
    ]
)
assert PACKET_DTYPE.itemsize == PACKET_SIZE

_MAX_LISTED = 100  # packet numbers listed in a report (the count is always exact)


@dataclass
class MimuStream:
    """The valid packets of a stream, in stream order.

    number : (N,) uint16 packet numbers as sent.  ticks : (N,) int64 unwrapped timestamps,
    64 MHz ticks.  raw : (N, 8, 6) int16 [ax, ay, az, gx, gy, gz] counts, packet IMU order.
    """

    number: np.ndarray
    ticks: np.ndarray
    raw: np.ndarray

    @property
    def time(self) -> np.ndarray:
        """(N,) s from the first kept packet."""
        return (self.ticks - self.ticks[0]) / TICK_HZ


@dataclass
class ImportReport:
    """What reading a MIMU stream found (all counts exact; lists capped at 100 entries)."""

    file: str = ""
    sha256: str = ""  # of the decompressed stream
    gzipped: bool = False
    n_bytes: int = 0  # decompressed
    ack_present: bool = False
    leading_bytes: int = 0  # bytes before the first packet (4 when the ack is present)
    packets_read: int = 0  # complete 106-byte packets
    packets_kept: int = 0
    checksum_failures: int = 0
    header_failures: int = 0  # wrong header byte or payload size (checksum may be fine)
    failed_packet_numbers: list = field(default_factory=list)
    first_failure_offset: int | None = None
    partial_bytes: int = 0
    duplicate_packets: int = 0
    missing_packets: int = 0  # gaps in the packet numbers of the kept packets
    gaps: list = field(default_factory=list)  # [after packet number, how many missing]
    packet_number_wraps: int = 0
    timestamp_wraps: int = 0
    duration_s: float = 0.0
    sample_rate_hz: float = float("nan")
    period_median_ticks: float = float("nan")
    jitter_std_ticks: float = float("nan")  # std of the 1-step intervals, first excluded
    jitter_max_ticks: float = float("nan")  # max |interval − median|, first excluded
    first_interval_ticks: float = float("nan")
    # Filled by import_mimu:
    static_segments: int | None = None
    orientations: int | None = None
    static_fraction: float | None = None
    acc_clipped_fraction: float | None = None
    gyro_clipped_fraction: float | None = None
    acc_whiteness_ratio: list | None = None  # per IMU: pooled rest std / first-difference std
    gyro_whiteness_ratio: list | None = None
    notes: list = field(default_factory=list)

    @property
    def failed_packets(self) -> int:
        """Packets dropped for a bad checksum, header byte or payload size."""
        return self.packets_read - self.packets_kept - self.duplicate_packets

    def to_dict(self) -> dict:
        return asdict(self)

    def lines(self) -> list[str]:
        """A short human report (what ``accel-bayes import-mimu`` prints)."""
        out = [
            f"file: {self.file} ({'gzip, ' if self.gzipped else ''}{self.n_bytes} bytes, sha256 {self.sha256[:16]}…)",
            f"command ack A0 28 00 C8: {'present' if self.ack_present else 'ABSENT'}"
            + (f" ({self.leading_bytes} leading bytes skipped)" if not self.ack_present and self.leading_bytes else ""),
            f"packets: {self.packets_read} read, {self.packets_kept} kept; checksum failures: {self.checksum_failures}"
            + (f" (packet numbers {self.failed_packet_numbers[:10]}{' …' if len(self.failed_packet_numbers) > 10 else ''})" if self.checksum_failures else "")
            + (f"; header/size failures: {self.header_failures}" if self.header_failures else ""),
            f"trailing partial packet: {self.partial_bytes} bytes ignored",
            f"missing packet numbers: {self.missing_packets}" + (f" in {len(self.gaps)} gap(s)" if self.missing_packets else "")
            + (f"; duplicates dropped: {self.duplicate_packets}" if self.duplicate_packets else ""),
            f"duration: {self.duration_s:.2f} s at {self.sample_rate_hz:.3f} Hz "
            f"(period {self.period_median_ticks / TICK_HZ * 1e3:.4f} ms, jitter std {self.jitter_std_ticks:.2f} ticks, "
            f"max {self.jitter_max_ticks:.0f} ticks; first interval {self.first_interval_ticks / TICK_HZ * 1e3:.3f} ms)",
        ]
        if self.static_segments is not None:
            out.append(
                f"static segments: {self.static_segments} ({100 * self.static_fraction:.1f} % of samples), "
                f"distinct orientations: {self.orientations}"
            )
        if self.acc_clipped_fraction is not None:
            out.append(
                f"clipped samples: acc {100 * self.acc_clipped_fraction:.3f} %, gyro {100 * self.gyro_clipped_fraction:.3f} %"
            )
        out.extend(f"note: {n}" for n in self.notes)
        return out

    def __str__(self) -> str:
        return "\n".join(self.lines())


# ---------------------------------------------------------------------------------------- reading
def read_mimu_bytes(path) -> tuple[bytes, bool]:
    """The decompressed stream of ``path`` and whether it was gzip (by its magic bytes)."""
    p = Path(path)
    data = p.read_bytes()  # FileNotFoundError / IsADirectoryError propagate (CLI: exit 2)
    if data[:2] == b"\x1f\x8b":
        try:
            return gzip.decompress(data), True
        except (OSError, EOFError, zlib.error) as exc:
            raise RecordingError(f"{p.name}: gzip data is corrupt ({exc})") from None
    return data, False


def _checksums(buf: np.ndarray) -> np.ndarray:
    """(N,) uint16 checksums of (N, 106) packet bytes: Σ bytes 0..103 mod 65536."""
    return (buf[:, :104].sum(1, dtype=np.uint32) & 0xFFFF).astype(np.uint16)


def _first_packet_offset(data: bytes, search: int) -> int | None:
    """Offset of the first position within ``search`` bytes where a whole valid packet starts."""
    n = min(search, len(data) - PACKET_SIZE + 1)
    if n <= 0:
        return None
    b = np.frombuffer(data, dtype=np.uint8)
    cand = np.flatnonzero((b[:n] == HEADER) & (b[3 : n + 3] == PAYLOAD_SIZE))
    for o in cand:  # a few candidates at most
        pkt = b[o : o + PACKET_SIZE]
        if int(pkt[:104].sum(dtype=np.uint32) & 0xFFFF) == (int(pkt[104]) << 8 | int(pkt[105])):
            return int(o)
    return None


def decode_mimu_bytes(data: bytes, *, name: str = "<bytes>", gzipped: bool = False,
                      max_fail_fraction: float = 0.01) -> tuple[MimuStream, ImportReport]:
    """Parse a decompressed MIMU stream held in memory (see :func:`read_mimu_stream`)."""
    rep = ImportReport(file=name, gzipped=gzipped, n_bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    if data[:4] == MIMU_ACK:
        off = 4
        rep.ack_present = True
    else:
        off = _first_packet_offset(data, 4 + PACKET_SIZE)
        if off is None:
            raise RecordingError(
                f"{name}: not an MIMU stream: no command ack A0 28 00 C8 and no valid packet "
                f"(header 0xAA, payload size 100, checksum) in the first {4 + PACKET_SIZE} bytes"
            )
        rep.notes.append(f"command ack A0 28 00 C8 absent; first packet at byte {off}")
    rep.leading_bytes = off
    N = (len(data) - off) // PACKET_SIZE
    rep.partial_bytes = (len(data) - off) - N * PACKET_SIZE
    rep.packets_read = N
    if N == 0:
        raise RecordingError(f"{name}: not an MIMU stream: fewer than {PACKET_SIZE} bytes after the command ack")

    pk = np.frombuffer(data, dtype=PACKET_DTYPE, count=N, offset=off)
    buf = np.frombuffer(data, dtype=np.uint8, count=N * PACKET_SIZE, offset=off).reshape(N, PACKET_SIZE)
    head_ok = (pk["header"] == HEADER) & (pk["size"] == PAYLOAD_SIZE)
    if not head_ok.any():
        raise RecordingError(f"{name}: not an MIMU stream: no packet with header 0xAA and payload size 100")
    cs_ok = _checksums(buf) == pk["checksum"]
    good = head_ok & cs_ok
    bad = ~good
    rep.checksum_failures = int((~cs_ok).sum())
    rep.header_failures = int((~head_ok).sum())
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        rep.first_failure_offset = off + first * PACKET_SIZE
        rep.failed_packet_numbers = pk["number"][bad][:_MAX_LISTED].astype(int).tolist()
    frac = bad.mean()
    if frac > max_fail_fraction:
        raise RecordingError(
            f"{name}: {int(bad.sum())} of {N} packets fail their checksum/header check "
            f"({100 * frac:.1f} % > {100 * max_fail_fraction:g} %; first at byte {rep.first_failure_offset}): "
            "not an MIMU stream, or corrupted/misaligned"
        )

    number = pk["number"][good].astype(np.int64)
    stamp = pk["timestamp"][good].astype(np.int64)
    raw = pk["data"][good].astype(np.int16)
    # Duplicates (same number and stamp as the previous packet) carry no new sample.
    dup = np.concatenate(([False], (np.diff(number) == 0) & (np.diff(stamp) == 0)))
    if dup.any():
        rep.duplicate_packets = int(dup.sum())
        number, stamp, raw = number[~dup], stamp[~dup], raw[~dup]
    rep.packets_kept = int(number.size)

    dn = np.diff(number) % 65536
    rep.packet_number_wraps = int((np.diff(number) < 0).sum())
    gap = dn != 1
    if gap.any():
        idx = np.flatnonzero(gap)
        # dn == 0 with a different stamp: a repeated number, i.e. 65536 packets apart (or garbage).
        miss = np.where(dn[idx] == 0, 65535, dn[idx] - 1)
        rep.missing_packets = int(miss.sum())
        rep.gaps = [[int(number[i]), int(m)] for i, m in zip(idx[:_MAX_LISTED], miss[:_MAX_LISTED])]
        dn = np.where(dn == 0, 65536, dn)

    # Unwrap the 32-bit stamps: the packet-number step predicts each interval, which fixes how
    # many 2^32 wraps it spans even across a long gap.
    d_mod = np.diff(stamp) % (1 << 32)
    wraps = np.maximum(np.rint((dn * NOMINAL_PERIOD_TICKS - d_mod) / float(1 << 32)), 0).astype(np.int64)
    d = d_mod + wraps * (1 << 32)
    if (d <= 0).any():
        i = int(np.flatnonzero(d <= 0)[0])
        raise RecordingError(
            f"{name}: timestamp: expected strictly increasing stamps, packet {int(number[i + 1])} "
            f"repeats the stamp of packet {int(number[i])}"
        )
    ticks = stamp[0] + np.concatenate(([0], np.cumsum(d)))
    rep.timestamp_wraps = int(ticks[-1] // (1 << 32) - ticks[0] // (1 << 32))

    if ticks.size > 1:
        rep.duration_s = float((ticks[-1] - ticks[0]) / TICK_HZ)
        single = d[dn == 1]
        rep.first_interval_ticks = float(d[0]) if dn[0] == 1 else float("nan")
        rest = d[1:][dn[1:] == 1] if d.size > 1 else single
        ref = rest if rest.size else single
        rep.period_median_ticks = float(np.median(ref))
        rep.sample_rate_hz = TICK_HZ / rep.period_median_ticks
        if rest.size:
            rep.jitter_std_ticks = float(rest.std())
            rep.jitter_max_ticks = float(np.abs(rest - rep.period_median_ticks).max())
    return MimuStream(number=number.astype(np.uint16), ticks=ticks, raw=raw), rep


def read_mimu_stream(path, *, max_fail_fraction: float = 0.01) -> tuple[MimuStream, ImportReport]:
    """Read and verify a MIMU4444 stream file (``.bin`` or gzip, told by its magic bytes).

    Returns the valid packets (:class:`MimuStream`: packet numbers, unwrapped 64 MHz ticks,
    int16 counts) and an :class:`ImportReport`.  Raises :class:`RecordingError` if the file is
    not an MIMU stream or more than ``max_fail_fraction`` of its packets fail verification.
    """
    p = Path(path)
    data, gz = read_mimu_bytes(p)
    name = f"{p.parent.name}/{p.name}" if p.parent.name else p.name
    return decode_mimu_bytes(data, name=name, gzipped=gz, max_fail_fraction=max_fail_fraction)


def encode_mimu_packets(number, timestamp, raw, *, ack: bool = True) -> bytes:
    """Build a MIMU stream from packet fields (tests and simulators): ``number`` (N,) uint16,
    ``timestamp`` (N,) uint32 ticks, ``raw`` (N, 8, 6) int16.  Checksums are computed."""
    number = np.asarray(number)
    N = number.shape[0]
    pk = np.zeros(N, dtype=PACKET_DTYPE)
    pk["header"] = HEADER
    pk["size"] = PAYLOAD_SIZE
    pk["number"] = number.astype(np.int64) % 65536
    pk["timestamp"] = np.asarray(timestamp, dtype=np.int64) % (1 << 32)
    pk["data"] = np.asarray(raw).astype(np.int16)
    buf = pk.view(np.uint8).reshape(N, PACKET_SIZE)
    pk["checksum"] = _checksums(buf)
    return (MIMU_ACK if ack else b"") + pk.tobytes()


# ---------------------------------------------------------------------------------------- recording
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
        f"{report.partial_bytes} trailing partial bytes ignored, {report.missing_packets} missing packet numbers; "
        f"time = measured timestamps (64 MHz, unwrapped); {noise_phrase}; imported by accel_bayes.data.mimu"
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
    max_fail_fraction : refuse the file when more packets than this fail verification.
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

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

What the importer does, and why (every rule below is a judgement written down; the report
lists every packet each rule touched, by reason, packet number and byte offset):

* **Framing and resynchronisation.**  Every byte offset where a header ``0xAA``, a payload size
  100 and a matching checksum line up is a *valid packet start* (found vectorised, no per-packet
  loop).  Chains of valid starts 106 bytes apart are the packets; where two chains overlap (a
  packet-like pattern inside another packet) the earlier one wins, except that a lone packet
  gives way to an overlapping chain of two or more.  The bytes between accepted packets are
  classified: a gap that is a whole number of 106-byte slots between aligned packets is that many
  packets damaged *in place* (counted as checksum or header/size failures, with the packet
  numbers they carry); any other gap is bytes lost or inserted, reported as *skipped bytes*
  (offset, length) and the stream resynchronises on the next valid packet.  The tail after the
  last packet is whole damaged slots plus a trailing partial packet (ignored and reported).
* **Order and duplicates by packet number.**  The uint16 numbers are unwrapped with serial-number
  arithmetic (each step taken in [−2^15, 2^15)): a packet that arrives late is put back in its
  place, and reported as *reordered* (kept).  Forward gaps of 2^15 packets or more (≥ 524 s with
  no packet at all) cannot be told from reordering and are out of scope.  A single packet whose
  number is more than 4096 away from both neighbours while they are within 4096 of each other
  is stepped over when unwrapping, so one wrong number cannot move all later packets by 2^16.
  Copies of one number whose 106 bytes are identical are one packet sent twice: the first is
  kept, the others are dropped as *duplicate*.  Copies that differ cannot both be right and the
  checksum cannot say which is: all copies are dropped as *conflict*.
* **Time.**  The time axis never depends on arrival order.  Every packet's stamp is compared with
  the 16 ms grid its packet number predicts, ``c + 1 024 000 · number`` (c one robust offset of the
  whole stream); the unwrapped tick is that grid value plus the packet's own residual (so the
  measured stamps are kept exactly: their ±8 ticks of jitter and the short first interval are
  real properties of the sample instants).  The 2^32 wraps thus follow from the packet number,
  even across long gaps.  A packet whose residual differs from the median of its six nearest
  neighbours (three each side, in number order; the first packet never serves as one) by more
  than ``TIME_TOL_TICKS`` = 24 ticks (8 per packet step to the farthest: the README's ±8 ticks of
  jitter, whether the stamps jitter about a grid, as in the shared recordings, or the intervals
  do; widened in proportion across gaps) has a stamp or a number that is wrong: dropped as
  *timestamp* (largest deviation in the shared recordings: 6.5 ticks).  A wrong number always
  shows: a number off by Δ moves the residual by 1 024 000 · Δ mod 2^32, a non-zero multiple of
  8192 ticks.  Exempt: the first packet of a
  stream — the lowest number whose stamp is on the grid or at most that lead after it — is
  stamped up to ``FIRST_PACKET_LEAD_TICKS`` (0.5 ms) after the grid of the others (every shared
  recording: ~0.35 ms, the README's short first interval); it never serves as a reference.
* **Plausibility beyond the checksum.**  The byte sum misses byte swaps, compensating ± edits
  and many double bit flips, so the values of a checksum-valid packet are judged against the
  rigid board (:mod:`accel_bayes.data.plausibility`, the same check the CSV importer runs).  The
  eight IMUs sit within 27 mm on one PCB; rotated into the array frame (bottom IMUs by the
  README's C) every gyro reads the same ω and every accelerometer the same specific force plus
  the rigid-body term of its nominal position.  At ±16 g and ±2000 °/s every int16 code is a
  possible output (the recordings use both −32768 and 32767), so no code is out of range by
  itself; the range that applies is the board's.  Per IMU, sensor and sample: the *range* test
  bounds the deviation from the other seven's median by ``PLAUSIBILITY_FLOOR_LSB`` (256 LSB:
  0.125 g, 15.6 °/s) + a multiple of the board's change per sample (sampling skew of the
  free-running IMU clocks) + 8 × the board's median deviation (honest spread); the *jump* test
  bounds the smaller of the deviation's two one-sample steps by the floor + a multiple of the
  board's change of slope + 8 × the median step: a wrong value steps away from both neighbours,
  an honest deviation follows the motion.  Across the six shared recordings (vigorous hand
  rotation up to the ±2000 °/s range included) the largest ratio to the bound is 0.60 (range,
  accelerometer, exp_5): margin 1.7; every other margin ≥ 2.1 (``experiments/mimu_fuzz.md``).
  A channel is exempt where full scale is corroborated: the board's median within 1/16 of full
  scale (``NEAR_LIMIT_LSB``), or an IMU saturated (``SATURATED_LSB`` = 32704, the top 0.2 %)
  whose own previous or next sample is within 1/16 too — IMUs saturate ±3 % apart.  A lone
  full-scale code that neither the board nor its own neighbours share (issue #29: one gyro at
  +1998 °/s while seven read −0.24) is a wrong value, not clipping.  What the rules cannot see —
  a change below the bound, values where full scale is corroborated — is measured per operator
  and magnitude in the fuzz study.
* **Drop, never flag-and-keep, for values.**  A packet with any IMU failing the rigid-board check
  is dropped whole, and the report lists every rejected IMU sensor (``implausible``: packet
  number, byte offset, IMU, sensor, test, ratio): the damage is an edit the checksum could not
  see, and a byte swap or ± edit moves two values, one of which may sit below the bound; one
  packet of ~37 000 costs nothing, a wrong value biases a calibration.  (A CSV row holds one
  IMU, so the CSV importer marks ``acc_flagged``/``gyro_flagged`` instead.)  Reordered packets
  are kept and listed: their number and stamp agree, only their arrival was late.
* **Refusal.**  More than ``max_fail_fraction`` (1 %) of the stream damaged — dropped packets
  other than duplicates, plus skipped bytes counted in 106-byte packets — or no valid packet at
  all means the file is not a (usable) MIMU stream: :class:`RecordingError`.
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
import warnings
import zlib
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ..constants import DEG_TO_RAD, G0
from ..errors import RecordingError
from ..physics.arrays import SensorArray, mimu4444_8
from .plausibility import NEAR_LIMIT_FRACTION, SATURATED_FRACTION, rigid_board_check
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
    "JITTER_TICKS",
    "TIME_TOL_TICKS",
    "FIRST_PACKET_LEAD_TICKS",
    "PLAUSIBILITY_FLOOR_LSB",
    "NEAR_LIMIT_LSB",
    "SATURATED_LSB",
    "DROP_REASONS",
    "MimuStream",
    "ImportReport",
    "read_mimu_bytes",
    "read_mimu_stream",
    "decode_mimu_bytes",
    "encode_mimu_packets",
    "plausibility_statistics",
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
GYRO_SCALE = (1.0 / 16.4) * DEG_TO_RAD  # rad/s per LSB at ±2000 °/s
INT16_LIMITS = (-32768, 32767)
NEAR_LIMIT_LSB = round(NEAR_LIMIT_FRACTION * 32768)  # 30720: IMUs saturate ±3 % apart (sensitivity tolerance)
SATURATED_LSB = round(SATURATED_FRACTION * 32768)  # 32704, the top 64 codes: this IMU is at its limit
ACC_RANGE = 16 * G0
GYRO_RANGE = 2000.0 * DEG_TO_RAD

JITTER_TICKS = 8  # README: ±8 ticks per 16 ms interval
_TIME_NEIGHBOURS = 3  # packets each side whose median predicts a packet's stamp
TIME_TOL_TICKS = JITTER_TICKS * _TIME_NEIGHBOURS  # 24 ticks, the tolerance where no packet is missing
FIRST_PACKET_LEAD_TICKS = 32_000  # 0.5 ms: how late the first packet of a stream may be stamped
PLAUSIBILITY_FLOOR_LSB = 256.0  # 0.125 g, 15.6 °/s: 1/128 of full scale, the bounds' floor at rest

_NOMINAL_POS = mimu4444_8().positions.detach().double().numpy()
_NOMINAL_QUAT = mimu4444_8().orientations.detach().double().numpy()

_ISOLATED_STEP = 4096  # packets (65 s): a number step this large next to a normal one is an outlier

DROP_REASONS = ("checksum", "header", "timestamp", "duplicate", "conflict", "range", "jump")

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

_MAX_LISTED = 10  # entries of a list printed in the text report (to_dict holds them all)
_ROW = np.arange(PACKET_SIZE)


@dataclass
class MimuStream:
    """The kept packets of a stream, in packet-number order.

    number : (N,) uint16 packet numbers as sent.  ticks : (N,) int64 unwrapped timestamps,
    64 MHz ticks.  raw : (N, 8, 6) int16 [ax, ay, az, gx, gy, gz] counts, packet IMU order.
    offset : (N,) int64 byte offset of each packet in the decompressed stream.
    """

    number: np.ndarray
    ticks: np.ndarray
    raw: np.ndarray
    offset: np.ndarray | None = None

    @property
    def time(self) -> np.ndarray:
        """(N,) s from the first kept packet."""
        return (self.ticks - self.ticks[0]) / TICK_HZ


@dataclass
class ImportReport:
    """What reading a MIMU stream found.  All counts are exact and every list is complete
    (:meth:`lines` prints the first few entries of each)."""

    file: str = ""
    sha256: str = ""  # of the decompressed stream
    gzipped: bool = False
    n_bytes: int = 0  # decompressed
    ack_present: bool = False
    leading_bytes: int = 0  # bytes before the first packet (4 when the ack is present)
    packets_read: int = 0  # complete 106-byte packets: the framed ones plus those damaged in place
    packets_kept: int = 0
    checksum_failures: int = 0
    header_failures: int = 0  # wrong header byte or payload size (checksum may be fine)
    failed_packet_numbers: list = field(default_factory=list)  # as read from the failing packets
    first_failure_offset: int | None = None  # byte offset of the first dropped (not duplicate) packet or skipped byte
    partial_bytes: int = 0
    bytes_skipped: int = 0  # lost/inserted bytes passed over to resynchronise (not partial, not leading)
    skipped: list = field(default_factory=list)  # [byte offset, length] of every skipped run
    duplicate_packets: int = 0
    timestamp_failures: int = 0  # stamp disagrees with its neighbours' grid (> TIME_TOL_TICKS without gaps)
    conflicting_packets: int = 0  # copies of one packet number with different bytes (all dropped)
    range_failures: int = 0  # one IMU alone off the board's consensus
    jump_failures: int = 0  # one IMU alone jumping in one sample
    # [packet number, byte offset, IMU, "acc"/"gyro", "range"/"jump", |deviation| / bound] of every
    # IMU sensor the rigid-board check rejected (its packet is dropped)
    implausible: list = field(default_factory=list)
    reordered_packets: int = 0  # arrived after a higher packet number; put back in place and kept
    dropped: list = field(default_factory=list)  # [reason, packet number, byte offset] of every drop
    reordered: list = field(default_factory=list)  # [packet number, byte offset] of every reordered packet
    missing_packets: int = 0  # gaps in the packet numbers of the kept packets
    gaps: list = field(default_factory=list)  # [after packet number, how many missing]
    packet_number_wraps: int = 0
    timestamp_wraps: int = 0
    first_packet_lead_ticks: float = 0.0  # how late the first packet sits after the others' grid
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
        """Packets dropped for any reason but duplication (checksum, header, timestamp,
        conflict, range, jump)."""
        return self.packets_read - self.packets_kept - self.duplicate_packets

    @property
    def drop_counts(self) -> dict:
        """{reason: packets dropped for it}, reasons as in :data:`DROP_REASONS`."""
        out = dict.fromkeys(DROP_REASONS, 0)
        for reason, *_ in self.dropped:
            out[reason] += 1
        return out

    def to_dict(self) -> dict:
        return asdict(self)

    def lines(self) -> list[str]:
        """A short human report (what ``accel-bayes import-mimu`` prints)."""
        out = [
            f"file: {self.file} ({'gzip, ' if self.gzipped else ''}{self.n_bytes} bytes, sha256 {self.sha256[:16]}…)",
            f"command ack A0 28 00 C8: {'present' if self.ack_present else 'ABSENT'}"
            + (f" ({self.leading_bytes} leading bytes skipped)" if not self.ack_present and self.leading_bytes else ""),
            f"packets: {self.packets_read} read, {self.packets_kept} kept; checksum failures: {self.checksum_failures}"
            + (f" (packet numbers {_capped(self.failed_packet_numbers)})" if self.checksum_failures else "")
            + (f"; header/size failures: {self.header_failures}" if self.header_failures else ""),
            f"trailing partial packet: {self.partial_bytes} bytes ignored",
            f"missing packet numbers: {self.missing_packets}" + (f" in {len(self.gaps)} gap(s)" if self.missing_packets else "")
            + (f"; duplicates dropped: {self.duplicate_packets}" if self.duplicate_packets else ""),
        ]
        if self.bytes_skipped:
            out.append(f"resynchronised: {self.bytes_skipped} bytes skipped in {len(self.skipped)} run(s) "
                       f"[byte offset, length] {_capped(self.skipped)}")
        if self.reordered_packets:
            out.append(f"reordered packets put back by number (kept): {self.reordered_packets} "
                       f"[number, byte offset] {_capped(self.reordered)}")
        counts = {k: v for k, v in self.drop_counts.items() if v}
        if counts:
            out.append("dropped packets by reason: " + ", ".join(f"{k} {v}" for k, v in counts.items())
                       + f"; [reason, number, byte offset] {_capped(self.dropped)}")
        if self.implausible:
            out.append(f"implausible values (rigid-board check; packets dropped): {len(self.implausible)} "
                       f"[number, byte offset, IMU, sensor, test, deviation/bound] {_capped(self.implausible)}")
        out.append(
            f"duration: {self.duration_s:.2f} s at {self.sample_rate_hz:.3f} Hz "
            f"(period {self.period_median_ticks / TICK_HZ * 1e3:.4f} ms, jitter std {self.jitter_std_ticks:.2f} ticks, "
            f"max {self.jitter_max_ticks:.0f} ticks; first interval {self.first_interval_ticks / TICK_HZ * 1e3:.3f} ms)"
        )
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


def _capped(items: list) -> str:
    """The first few entries of a report list, and how many more the full report holds."""
    head = ", ".join(str(x) for x in items[:_MAX_LISTED])
    return f"[{head}{f', … {len(items) - _MAX_LISTED} more' if len(items) > _MAX_LISTED else ''}]"


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


def _stored_checksums(buf: np.ndarray) -> np.ndarray:
    return (buf[:, 104].astype(np.uint16) << 8) | buf[:, 105]


def _valid_starts(b: np.ndarray) -> np.ndarray:
    """Sorted byte offsets where a whole packet with header, size and checksum right starts."""
    m = b.size - PACKET_SIZE + 1
    if m <= 0:
        return np.zeros(0, dtype=np.int64)
    cand = np.flatnonzero((b[:m] == HEADER) & (b[3 : m + 3] == PAYLOAD_SIZE))
    keep = []
    for i in range(0, cand.size, 1 << 16):  # bounded memory on a stream made of header patterns
        c = cand[i : i + (1 << 16)]
        rows = b[c[:, None] + _ROW]
        keep.append(c[_checksums(rows) == _stored_checksums(rows)])
    return np.concatenate(keep).astype(np.int64) if keep else np.zeros(0, dtype=np.int64)


def _chain(v: np.ndarray) -> np.ndarray:
    """Accepted packet offsets from the sorted valid starts: runs 106 bytes apart, overlaps
    resolved (earlier wins; a lone packet gives way to a longer overlapping run).  The loop is
    over runs, i.e. over damage events, not over packets."""
    if v.size == 0:
        return v
    brk = np.flatnonzero(np.diff(v) != PACKET_SIZE) + 1
    runs: list[list[int]] = []  # [first offset, count]
    end = -1
    for i, j in zip(np.concatenate(([0], brk)), np.concatenate((brk, [v.size]))):
        o, c = int(v[i]), int(j - i)
        if o < end and c > 1 and runs and runs[-1][1] == 1:
            runs.pop()  # the lone packet was the pattern inside the longer run's packet
            end = runs[-1][0] + runs[-1][1] * PACKET_SIZE if runs else -1
        if o < end:
            k = -(-(end - o) // PACKET_SIZE)  # packets of this run overlapping accepted bytes
            o, c = o + k * PACKET_SIZE, c - k
            if c <= 0:
                continue
        runs.append([o, c])
        end = o + c * PACKET_SIZE
    return np.concatenate([o + PACKET_SIZE * np.arange(c, dtype=np.int64) for o, c in runs])


def _frame(b: np.ndarray, start: int, ack: bool):
    """Split the stream into accepted packet offsets, damaged-in-place slots, skipped runs,
    leading junk and the trailing partial packet (see the module docstring)."""
    off = _chain(_valid_starts(b))
    off = off[off >= start]
    n = b.size
    failed: list[int] = []
    skipped: list[list[int]] = []
    leading = start
    if off.size == 0:
        return off, np.zeros(0, dtype=np.int64), skipped, leading, 0

    def classify(a: int, length: int) -> None:
        if length % PACKET_SIZE == 0:
            failed.extend(range(a, a + length, PACKET_SIZE))
        else:
            skipped.append([a, length])

    head = int(off[0]) - start
    if head:
        if ack:
            classify(start, head)
        elif head % PACKET_SIZE == 0 and np.all(b[start : int(off[0]) : PACKET_SIZE] == HEADER):
            failed.extend(range(start, int(off[0]), PACKET_SIZE))
        else:
            leading = int(off[0])
    ends = off[:-1] + PACKET_SIZE
    for i in np.flatnonzero(off[1:] != ends):  # damage events only
        classify(int(ends[i]), int(off[i + 1] - ends[i]))
    tail_start = int(off[-1]) + PACKET_SIZE
    whole = (n - tail_start) // PACKET_SIZE
    failed.extend(range(tail_start, tail_start + whole * PACKET_SIZE, PACKET_SIZE))
    partial = n - tail_start - whole * PACKET_SIZE
    return off, np.asarray(sorted(failed), dtype=np.int64), skipped, leading, partial


def _serial(d: np.ndarray) -> np.ndarray:
    """Packet-number differences taken in [−2^15, 2^15) (serial-number arithmetic)."""
    return (d + (1 << 15)) % (1 << 16) - (1 << 15)


def _stamp_deviation(res: np.ndarray, seq: np.ndarray, ref_ok: np.ndarray | None = None):
    """Each packet's stamp residual minus the median of its ``_TIME_NEIGHBOURS`` nearest
    neighbours on either side (in number order; only those with ``ref_ok`` serve as references),
    and the tolerance: ``JITTER_TICKS`` per packet step to the farthest of them.  ±8 ticks per
    step bounds both a stamp grid with jitter and a random walk of intervals; one wrong neighbour
    cannot move the median of six (three at an end) out of the good ones' range."""
    n, k = res.size, _TIME_NEIGHBOURS
    if n == 1:
        return np.zeros(1), np.full(1, float(TIME_TOL_TICKS))
    ref = res.astype(np.float64)
    if ref_ok is not None:
        ref = np.where(ref_ok, ref, np.nan)
    pad = np.full(n + 2 * k, np.nan)
    pad[k:-k] = ref
    spad = np.full(n + 2 * k, np.nan)
    spad[k:-k] = np.where(np.isnan(ref), np.nan, seq)
    shifts = [j for j in range(2 * k + 1) if j != k]
    nb = np.stack([pad[j : j + n] for j in shifts], 1)
    dist = np.abs(np.stack([spad[j : j + n] for j in shifts], 1) - seq[:, None])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # no reference at all: NaN, never flagged
        med = np.nanmedian(nb, axis=1)
        far = np.nanmax(dist, axis=1)
    return res - med, JITTER_TICKS * np.maximum(far, k)


def plausibility_statistics(raw: np.ndarray, seq: np.ndarray | None = None):
    """The rigid-board range and jump tests (:mod:`accel_bayes.data.plausibility`) on a stream's
    counts, as ratios to their bounds.

    raw : (N, 8, 6) int16 counts (packet IMU order, sensor frame); seq : (N,) increasing packet
    numbers (unwrapped; default 0..N−1): the neighbours in time and the 16 ms steps between them.
    Returns ``(range_ratio, jump_ratio)``, each (N, 8, 2) float64, [acc, gyro] of each IMU: the
    largest |statistic| / bound over the array-frame axes (a sample fails above 1), −inf where
    exempt.  Floors ``PLAUSIBILITY_FLOOR_LSB``; full scale the int16 range.
    """
    n = raw.shape[0]
    seq = np.arange(n, dtype=np.int64) if seq is None else np.asarray(seq, dtype=np.int64)
    x = raw.astype(np.float64)
    period = NOMINAL_PERIOD_TICKS / TICK_HZ
    p = rigid_board_check(x[..., :3] * ACC_SCALE, x[..., 3:] * GYRO_SCALE, (seq - seq[0]) * period if n else seq,
                          _NOMINAL_POS, _NOMINAL_QUAT, floor_acc=PLAUSIBILITY_FLOOR_LSB * ACC_SCALE,
                          floor_gyro=PLAUSIBILITY_FLOOR_LSB * GYRO_SCALE, acc_range=32768 * ACC_SCALE,
                          gyro_range=32768 * GYRO_SCALE, period=period)
    return p.range_ratio, p.jump_ratio


def _implausible(raw: np.ndarray, seq: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
    """(N,) bool packets failing the range test, those failing only the jump test, and
    [row, IMU, sensor, test, ratio] of every failing IMU sensor."""
    rng, jmp = plausibility_statistics(raw, seq)
    rows = []
    for test, ratio in (("range", rng), ("jump", jmp)):
        for i, k, s in zip(*np.nonzero(ratio > 1)):
            rows.append([int(i), int(k), ("acc", "gyro")[s], test, round(float(ratio[i, k, s]), 3)])
    bad_r = (rng > 1).any((1, 2))
    bad_j = (jmp > 1).any((1, 2)) & ~bad_r
    return bad_r, bad_j, rows


def decode_mimu_bytes(data: bytes, *, name: str = "<bytes>", gzipped: bool = False,
                      max_fail_fraction: float = 0.01) -> tuple[MimuStream, ImportReport]:
    """Parse a decompressed MIMU stream held in memory (see :func:`read_mimu_stream`)."""
    rep = ImportReport(file=name, gzipped=gzipped, n_bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    b = np.frombuffer(data, dtype=np.uint8)
    rep.ack_present = data[:4] == MIMU_ACK
    start = 4 if rep.ack_present else 0
    off, failed, skipped, leading, partial = _frame(b, start, rep.ack_present)
    if off.size == 0:
        raise RecordingError(
            f"{name}: not an MIMU stream: no packet with header 0xAA, payload size 100 and a matching checksum"
            + (" after the command ack" if rep.ack_present else "")
        )
    rep.leading_bytes, rep.partial_bytes = leading, partial
    rep.skipped, rep.bytes_skipped = skipped, int(sum(L for _, L in skipped))
    if not rep.ack_present:
        rep.notes.append(f"command ack A0 28 00 C8 absent; first packet at byte {int(off[0])}")
    rep.packets_read = int(off.size + failed.size)

    dropped: list[tuple[str, int, int]] = []
    if failed.size:
        rows = b[failed[:, None] + _ROW]
        head_ok = (rows[:, 0] == HEADER) & (rows[:, 3] == PAYLOAD_SIZE)
        cs_ok = _checksums(rows) == _stored_checksums(rows)
        rep.checksum_failures = int((~cs_ok).sum())
        rep.header_failures = int((~head_ok).sum())
        nums = ((rows[:, 1].astype(np.int64) << 8) | rows[:, 2]).tolist()
        rep.failed_packet_numbers = nums
        dropped += [("header" if not h else "checksum", k, o) for h, k, o in zip(head_ok, nums, failed.tolist())]

    pk = b[off[:, None] + _ROW].view(PACKET_DTYPE)[:, 0]
    number = pk["number"].astype(np.int64)
    # Serial-number arithmetic: a late packet is a small step back, not a 2^16 gap.
    step = _serial(np.diff(number))
    if number.size >= 3:
        # One wrong number (a checksum-blind edit) makes two large steps whose wrapped sum can be
        # off by 2^16, which would move every later packet by 2^16 numbers: an isolated outlier —
        # both steps beyond _ISOLATED_STEP while its neighbours are close to each other — is
        # stepped over (the timestamp check then drops it).
        a, after = step[:-1], step[1:]
        direct = _serial(number[2:] - number[:-2])
        iso = (np.abs(a) > _ISOLATED_STEP) & (np.abs(after) > _ISOLATED_STEP) & (np.abs(direct) <= _ISOLATED_STEP)
        step[1:] = np.where(iso, direct - a, after)
    seq = number[0] + np.concatenate(([0], np.cumsum(step)))
    stamp = pk["timestamp"].astype(np.int64)
    M32 = 1 << 32
    u = (stamp - NOMINAL_PERIOD_TICKS * seq) % M32  # the packet's offset from its number's grid
    mid = u[u.size // 2]
    c = mid + int(np.median((u - mid + (M32 >> 1)) % M32 - (M32 >> 1)))
    res = (u - c + (M32 >> 1)) % M32 - (M32 >> 1)

    order = np.argsort(seq, kind="stable")  # number order; copies stay in arrival order
    keep = np.ones(off.size, dtype=bool)
    # The first packet of the stream sits off the grid (its lead): it is the lowest number whose
    # stamp is on the grid or at most the lead after it (a wrong number elsewhere that sorts
    # earlier is neither), and it never serves as a reference for the others.
    dev, tol = _stamp_deviation(res[order], seq[order])
    like = (dev >= -tol) & (dev <= FIRST_PACKET_LEAD_TICKS)
    first = seq[order] == (seq[order][like][0] if like.any() else seq[order][0])
    dev, tol = _stamp_deviation(res[order], seq[order], ref_ok=~first)
    bad_t = np.abs(dev) > tol
    lead = first & (dev > 0) & (dev <= FIRST_PACKET_LEAD_TICKS)
    bad_t &= ~lead
    if lead.any():
        rep.first_packet_lead_ticks = float(dev[lead][0])
    keep[order[bad_t]] = False

    # Copies of one number: identical bytes → one packet sent twice; different → a conflict.
    o2 = order[keep[order]]
    s2 = seq[o2]
    same_num = s2[1:] == s2[:-1]
    dup = np.zeros(o2.size, dtype=bool)
    conflict = np.zeros(o2.size, dtype=bool)
    if same_num.any():
        raw_bytes = b[off[o2][:, None] + _ROW]
        identical = same_num & (raw_bytes[1:] == raw_bytes[:-1]).all(1)
        dup[1:] = identical
        group = np.concatenate(([0], np.cumsum(~same_num)))
        bad_groups = np.unique(group[1:][same_num & ~identical])
        conflict = np.isin(group, bad_groups)
        dup &= ~conflict
    keep[o2[dup | conflict]] = False

    o3 = order[keep[order]]
    bad_r, bad_j, rows = _implausible(pk["data"][o3].astype(np.int16), seq[o3])
    keep[o3[bad_r | bad_j]] = False
    rep.implausible = sorted([int(number[o3[i]]), int(off[o3[i]]), k, sensor, test, ratio]
                             for i, k, sensor, test, ratio in rows)

    reason = np.full(off.size, "", dtype=object)
    reason[order[bad_t]] = "timestamp"
    reason[o2[dup]] = "duplicate"
    reason[o2[conflict]] = "conflict"
    reason[o3[bad_r]] = "range"
    reason[o3[bad_j]] = "jump"
    for r in DROP_REASONS[2:]:
        idx = np.flatnonzero(reason == r)
        dropped += [(r, int(number[i]), int(off[i])) for i in idx]
    dropped.sort(key=lambda d: d[2])
    rep.dropped = [list(d) for d in dropped]
    starts = [d[2] for d in dropped if d[0] != "duplicate"][:1] + [r[0] for r in skipped[:1]]
    rep.first_failure_offset = min(starts) if starts else None
    counts = rep.drop_counts
    rep.duplicate_packets = counts["duplicate"]
    rep.timestamp_failures = counts["timestamp"]
    rep.conflicting_packets = counts["conflict"]
    rep.range_failures = counts["range"]
    rep.jump_failures = counts["jump"]

    kept_arrival = np.flatnonzero(keep)  # arrival order
    late = np.zeros(kept_arrival.size, dtype=bool)
    late[1:] = seq[kept_arrival][1:] < np.maximum.accumulate(seq[kept_arrival])[:-1]
    rep.reordered = [[int(number[i]), int(off[i])] for i in kept_arrival[late]]
    rep.reordered_packets = len(rep.reordered)

    k = order[keep[order]]
    rep.packets_kept = int(k.size)
    damaged = rep.packets_read - rep.packets_kept - rep.duplicate_packets
    junk = rep.bytes_skipped + (0 if rep.ack_present else rep.leading_bytes)
    frac = (damaged + junk / PACKET_SIZE) / (rep.packets_read + junk / PACKET_SIZE)
    if frac > max_fail_fraction or k.size == 0:
        why = {**{r: v for r, v in counts.items() if v and r != "duplicate"}}
        why_txt = ", ".join(f"{r} {v}" for r, v in why.items()) or "none"
        raise RecordingError(
            f"{name}: {damaged} of {rep.packets_read} packets fail verification ({why_txt})"
            + (f" and {junk} bytes are skipped to resynchronise" if junk else "")
            + f" ({100 * frac:.1f} % > {100 * max_fail_fraction:g} %; first at byte {rep.first_failure_offset}): "
            "not an MIMU stream, or corrupted/misaligned"
        )

    seq_k = seq[k]
    ticks = stamp[k[0]] + NOMINAL_PERIOD_TICKS * (seq_k - seq_k[0]) + (res[k] - res[k[0]])
    d = np.diff(ticks)
    if (d <= 0).any():  # cannot happen after the checks above; refuse rather than write it
        i = int(np.flatnonzero(d <= 0)[0])
        raise RecordingError(
            f"{name}: timestamp: expected strictly increasing stamps, packet {int(number[k[i + 1]])} "
            f"is stamped no later than packet {int(number[k[i]])}"
        )
    dn = np.diff(seq_k)
    gap = dn != 1
    if gap.any():
        idx = np.flatnonzero(gap)
        rep.missing_packets = int((dn[idx] - 1).sum())
        rep.gaps = [[int(number[k[i]]), int(dn[i] - 1)] for i in idx]
    rep.packet_number_wraps = int(seq_k[-1] // (1 << 16) - seq_k[0] // (1 << 16))
    rep.timestamp_wraps = int(ticks[-1] // M32 - ticks[0] // M32)

    if ticks.size > 1:
        rep.duration_s = float((ticks[-1] - ticks[0]) / TICK_HZ)
        single = d[dn == 1]
        rep.first_interval_ticks = float(d[0]) if dn[0] == 1 else float("nan")
        rest = d[1:][dn[1:] == 1] if d.size > 1 else single
        ref = rest if rest.size else single
        if ref.size:
            rep.period_median_ticks = float(np.median(ref))
            rep.sample_rate_hz = TICK_HZ / rep.period_median_ticks
        if rest.size:
            rep.jitter_std_ticks = float(rest.std())
            rep.jitter_max_ticks = float(np.abs(rest - rep.period_median_ticks).max())
    stream = MimuStream(number=number[k].astype(np.uint16), ticks=ticks, raw=pk["data"][k].astype(np.int16),
                        offset=off[k])
    return stream, rep


def read_mimu_stream(path, *, max_fail_fraction: float = 0.01) -> tuple[MimuStream, ImportReport]:
    """Read and verify a MIMU4444 stream file (``.bin`` or gzip, told by its magic bytes).

    Returns the kept packets in packet-number order (:class:`MimuStream`: packet numbers,
    unwrapped 64 MHz ticks, int16 counts, byte offsets) and an :class:`ImportReport` listing
    every dropped, skipped and reordered packet (module docstring).  Raises
    :class:`RecordingError` if the file is not an MIMU stream or more than
    ``max_fail_fraction`` of it is damaged (dropped packets other than duplicates, plus skipped
    bytes in 106-byte packets).
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
        (module docstring, "Refusal").
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

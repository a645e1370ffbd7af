"""The MIMU4444 binary stream (OpenShoe/MIMU streaming protocol): the packet format, framing and
resynchronisation, and the encoder tests and simulators use.

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

Scaling (MPU-9150 at ±16 g, ±2000 °/s): :data:`ACC_SCALE` = 9.80665/2048 m/s² and
:data:`GYRO_SCALE` = 1/16.4 °/s (in rad/s) per count.  What the importer then checks is in
:mod:`accel_bayes.data.mimu_decode`; the recording it makes, in :mod:`accel_bayes.data.mimu`.
"""
from __future__ import annotations

import gzip
import zlib
from pathlib import Path

import numpy as np

from ..constants import DEG_TO_RAD, G0
from ..errors import RecordingError

__all__ = ["MIMU_ACK", "HEADER", "PAYLOAD_SIZE", "N_IMU", "PACKET_SIZE", "PACKET_DTYPE", "TICK_HZ",
           "NOMINAL_PERIOD_TICKS", "ACC_SCALE", "GYRO_SCALE", "INT16_LIMITS", "ACC_RANGE", "GYRO_RANGE",
           "read_mimu_bytes", "packet_rows", "checksum_ok", "frame", "encode_mimu_packets"]

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
ACC_RANGE = 16 * G0
GYRO_RANGE = 2000.0 * DEG_TO_RAD

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

_ROW = np.arange(PACKET_SIZE)


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


def packet_rows(b: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """(N, 106) uint8: the bytes of the packets starting at byte ``offsets`` (N,) of stream ``b``."""
    return b[np.asarray(offsets)[:, None] + _ROW]


def checksum_ok(rows: np.ndarray) -> np.ndarray:
    """(N,) bool: the stored checksum of each of the (N, 106) packet ``rows`` matches its bytes."""
    return _checksums(rows) == _stored_checksums(rows)


def _valid_starts(b: np.ndarray) -> np.ndarray:
    """Sorted byte offsets where a whole packet with header, size and checksum right starts."""
    m = b.size - PACKET_SIZE + 1
    if m <= 0:
        return np.zeros(0, dtype=np.int64)
    cand = np.flatnonzero((b[:m] == HEADER) & (b[3 : m + 3] == PAYLOAD_SIZE))
    keep = []
    for i in range(0, cand.size, 1 << 16):  # bounded memory on a stream made of header patterns
        c = cand[i : i + (1 << 16)]
        keep.append(c[checksum_ok(packet_rows(b, c))])
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


def frame(b: np.ndarray, start: int, ack: bool):
    """Split the stream ``b`` (uint8) after byte ``start`` (4 when the command ``ack`` opens it) into
    accepted packet offsets, damaged-in-place slots (offsets), skipped runs ([offset, length]),
    leading junk (bytes) and the trailing partial packet (bytes): see the module docstring."""
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

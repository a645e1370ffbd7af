"""Decoding a MIMU4444 stream: which packets are kept, in what order, on what time axis.

The packets are framed by :func:`accel_bayes.data.mimu_packets.frame`; every rule below is a
judgement written down, and the report (:class:`~accel_bayes.data.mimu_report.ImportReport`) lists
every packet each rule touched, by reason, packet number and byte offset:

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
"""
from __future__ import annotations

import hashlib
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import RecordingError
from ..physics.arrays import mimu4444_8
from .mimu_packets import (
    ACC_SCALE,
    GYRO_SCALE,
    HEADER,
    MIMU_ACK,
    NOMINAL_PERIOD_TICKS,
    PACKET_DTYPE,
    PACKET_SIZE,
    PAYLOAD_SIZE,
    TICK_HZ,
    checksum_ok,
    frame,
    packet_rows,
    read_mimu_bytes,
)
from .mimu_report import DROP_REASONS, ImportReport
from .plausibility import NEAR_LIMIT_FRACTION, SATURATED_FRACTION, rigid_board_check

__all__ = ["JITTER_TICKS", "TIME_TOL_TICKS", "FIRST_PACKET_LEAD_TICKS", "PLAUSIBILITY_FLOOR_LSB", "NEAR_LIMIT_LSB",
           "SATURATED_LSB", "MimuStream", "decode_mimu_bytes", "read_mimu_stream", "plausibility_statistics"]

NEAR_LIMIT_LSB = round(NEAR_LIMIT_FRACTION * 32768)  # 30720: IMUs saturate ±3 % apart (sensitivity tolerance)
SATURATED_LSB = round(SATURATED_FRACTION * 32768)  # 32704, the top 64 codes: this IMU is at its limit

JITTER_TICKS = 8  # README: ±8 ticks per 16 ms interval
_TIME_NEIGHBOURS = 3  # packets each side whose median predicts a packet's stamp
TIME_TOL_TICKS = JITTER_TICKS * _TIME_NEIGHBOURS  # 24 ticks, the tolerance where no packet is missing
FIRST_PACKET_LEAD_TICKS = 32_000  # 0.5 ms: how late the first packet of a stream may be stamped
PLAUSIBILITY_FLOOR_LSB = 256.0  # 0.125 g, 15.6 °/s: 1/128 of full scale, the bounds' floor at rest

_NOMINAL_POS = mimu4444_8().positions.detach().double().numpy()
_NOMINAL_QUAT = mimu4444_8().orientations.detach().double().numpy()

_ISOLATED_STEP = 4096  # packets (65 s): a number step this large next to a normal one is an outlier


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
    off, failed, skipped, leading, partial = frame(b, start, rep.ack_present)
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
        rows = packet_rows(b, failed)
        head_ok = (rows[:, 0] == HEADER) & (rows[:, 3] == PAYLOAD_SIZE)
        cs_ok = checksum_ok(rows)
        rep.checksum_failures = int((~cs_ok).sum())
        rep.header_failures = int((~head_ok).sum())
        nums = ((rows[:, 1].astype(np.int64) << 8) | rows[:, 2]).tolist()
        rep.failed_packet_numbers = nums
        dropped += [("header" if not h else "checksum", k, o) for h, k, o in zip(head_ok, nums, failed.tolist())]

    pk = packet_rows(b, off).view(PACKET_DTYPE)[:, 0]
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
        raw_bytes = packet_rows(b, off[o2])
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

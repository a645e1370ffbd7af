"""Fuzz study of the MIMU4444 stream importer (issue #13 part A): seeded damaged streams, an
oracle that knows from construction what every packet was.

Each variant is a synthetic stream (:func:`board_stream`: ``n`` packets of smooth rigid-board
motion, the eight IMUs reading one array-frame ω and specific force through their own small
bias, scale error and noise, bottom IMUs rotated by the data README's C; the 16 ms stamp grid
with ±4 ticks of jitter; packet number and stamp start at random, so both wrap in some
variants) damaged by 1–3 operators drawn uniformly from :data:`OPERATORS`:

=================  ==============================================================================
``bitflip1``       one bit of one packet flipped (any byte, header and checksum included)
``bitflip2``       two bits of one packet flipped
``byteswap``       two bytes of one packet exchanged (checksum-preserving when both are in 0..103)
``pm_edit``        +d on one byte of bytes 0..103 and −d on another: the byte sum, so the checksum,
                   is unchanged (d uniform over what keeps both bytes in 0..255)
``lost``           1–20 consecutive bytes removed anywhere
``inserted``       1–20 random bytes inserted anywhere
``truncated``      1–300 bytes cut off the end
``swap``           two adjacent packets exchanged
``repeat_near``    a packet sent again 1–5 packets later
``repeat_far``     a packet sent again 100–300 packets later (a copy of a damaged packet carries
                   its damage)
``dropped``        1–3 consecutive packets removed
``garbage``        1–500 random bytes inserted between two packets
=================  ==============================================================================

The oracle (:func:`judge`) is independent of the importer: the bytes of the damaged stream carry
an owner per byte (which copy of which packet, or which insertion), so it knows which packets
are still intact (all 106 bytes present, unchanged, contiguous) and, for every sample the importer
keeps, what the true values and stamp of that packet number were.  A kept sample is *wrong* if
its values or its time differ from the truth; the importer drops every packet it suspects, so a
wrong kept sample is a wrong sample kept without a flag.  Each is attributed to the operators
that touched its bytes, and the study checks that each one is in the residue the checksum and the
plausibility checks provably cannot see (:func:`explain_residue`).

    python experiments/mimu_fuzz.py [--variants 10000] [--packets 400] [--seed 13]
        [--data ../shared/data/mimu4444-bcd] [--out experiments/results/mimu_fuzz]

It also measures, on the six shared recordings, how close every check comes to firing
(``real_margins.csv``).

Runtime: ~2 min for 10⁴ variants on the shared 2-core machine.  Results:
``experiments/mimu_fuzz.md``.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import sys
import tempfile
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _data import data_dir  # noqa: E402
from accel_bayes.errors import RecordingError
from accel_bayes.data.plausibility import JUMP_MOTION, SPREAD_FACTOR
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.data.mimu_decode import (  # noqa: I001 - _stamp_deviation: the importer's own rule, measured
    FIRST_PACKET_LEAD_TICKS,
    NEAR_LIMIT_LSB,
    PLAUSIBILITY_FLOOR_LSB,
    SATURATED_LSB,
    TIME_TOL_TICKS,
    _stamp_deviation,
    decode_mimu_bytes,
    plausibility_statistics,
)
from accel_bayes.data.mimu_packets import (
    ACC_SCALE,
    GYRO_SCALE,
    MIMU_ACK,
    NOMINAL_PERIOD_TICKS,
    encode_mimu_packets,
    read_mimu_bytes,
)

CHECKSUM_BLIND = ("bitflip2", "byteswap", "pm_edit")  # operators that can leave the byte sum unchanged
OPERATORS = ("bitflip1", "bitflip2", "byteswap", "pm_edit", "lost", "inserted", "truncated",
             "swap", "repeat_near", "repeat_far", "dropped", "garbage")
ACK_OWNER = -1
P = 106

# sensor ← array for the bottom IMUs (packet order 2, 4, 6, 8): the README's C is its own inverse.
C = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1]])


# ---------------------------------------------------------------------------------------- streams
def board_stream(n: int, rng: np.random.Generator, first_lead: bool = True):
    """(numbers, stamps, raw) of ``n`` packets of smooth motion of a rigid eight-IMU board.

    numbers (n,) int64 unwrapped packet numbers; stamps (n,) int64 unwrapped 64 MHz ticks
    (``% 2**32`` is what is sent); raw (n, 8, 6) int16 [ax, ay, az, gx, gy, gz] counts.
    """
    t = np.arange(n) * 0.016
    omega = np.zeros((n, 3))
    force = np.zeros((n, 3))
    for ax in range(3):  # a few smooth components per axis, up to ~ 700 °/s and ~ 3 g
        for _ in range(3):
            f, ph = rng.uniform(0.1, 3.0), rng.uniform(0, 2 * np.pi)
            omega[:, ax] += rng.uniform(0, 4000) * np.sin(2 * np.pi * f * t + ph)
            force[:, ax] += rng.uniform(0, 2000) * np.sin(2 * np.pi * f * t + ph)
    force[:, 2] += 2048  # 1 g
    # The rigid body: each IMU's specific force adds α×r + ω×(ω×r) at its nominal position
    # (≈ 3 m/s², 300 LSB, between opposite corners at 700 °/s).
    w = omega * GYRO_SCALE
    alpha = np.gradient(w, t, axis=0)
    r = mimu4444_8().positions.double().numpy()
    r = r - r.mean(0)
    raw = np.empty((n, 8, 6))
    for k in range(8):
        scale = 1 + rng.uniform(-0.02, 0.02, 6)
        bias = np.concatenate((rng.uniform(-60, 60, 3), rng.uniform(-40, 40, 3)))
        f_k = force + (np.cross(alpha, r[k]) + np.cross(w, np.cross(w, r[k]))) / ACC_SCALE
        f_s, w_s = (f_k, omega) if k % 2 == 0 else (f_k @ C.T, omega @ C.T)
        raw[:, k] = np.concatenate((f_s, w_s), 1) * scale + bias
        raw[:, k, :3] += rng.normal(0, 8, (n, 3))
        raw[:, k, 3:] += rng.normal(0, 4, (n, 3))
    raw = np.clip(np.rint(raw), -32768, 32767).astype(np.int16)
    # Start near a wrap now and then, so both wraps are exercised.
    n0 = int(rng.integers(65536 - n, 65536)) if rng.random() < 0.3 else int(rng.integers(0, 65536))
    s0 = int(rng.integers(0, 1 << 32))
    if rng.random() < 0.3:
        s0 = (1 << 32) - int(rng.integers(1, n)) * NOMINAL_PERIOD_TICKS
    numbers = n0 + np.arange(n, dtype=np.int64)
    stamps = s0 + np.arange(n, dtype=np.int64) * NOMINAL_PERIOD_TICKS + rng.integers(-4, 5, n)
    if first_lead:  # like the shared recordings: the first packet ~0.35 ms after the grid
        stamps[0] += 22_190
    return numbers, stamps, raw


# ---------------------------------------------------------------------------------------- damage
@dataclass
class Damaged:
    """A damaged stream with, for every byte, its owner: ≥ 0 a copy (item) of a packet,
    ``ACK_OWNER`` the ack, ≤ −2 an insertion event."""

    data: bytearray
    owner: np.ndarray
    item_packet: list  # item id → packet index
    touched: dict = field(default_factory=dict)  # owner id → set of operators that changed it
    events: list = field(default_factory=list)  # operator names applied, in order

    def items(self) -> np.ndarray:
        """Item id of each packet-start currently in place (for packet-level operators)."""
        ids, first = np.unique(self.owner[self.owner >= 0], return_index=True)
        return ids[np.argsort(first)]


def _touch(d: Damaged, owners, op: str) -> None:
    for o in set(int(x) for x in np.atleast_1d(owners)):
        d.touched.setdefault(o, set()).add(op)


def _item_span(d: Damaged, item: int) -> np.ndarray:
    return np.flatnonzero(d.owner == item)


def _splice(d: Damaged, at: int, remove: int, insert: bytes, owner_id: int) -> None:
    d.data[at : at + remove] = insert
    d.owner = np.concatenate((d.owner[:at], np.full(len(insert), owner_id, dtype=np.int64), d.owner[at + remove :]))


def apply(d: Damaged, op: str, rng: np.random.Generator) -> None:
    """Apply one operator (module docstring) in place."""
    d.events.append(op)
    items = d.items()
    if items.size < 4:
        return
    new_id = -2 - len(d.events)
    if op in ("bitflip1", "bitflip2", "byteswap", "pm_edit"):
        span = _item_span(d, int(rng.choice(items)))
        if op.startswith("bitflip"):
            for _ in range(1 if op == "bitflip1" else 2):
                i = int(rng.choice(span))
                d.data[i] ^= 1 << int(rng.integers(8))
        elif op == "byteswap":
            i, j = rng.choice(span, 2, replace=False)
            d.data[i], d.data[j] = d.data[j], d.data[i]
        else:  # checksum-preserving ± edit inside bytes 0..103 of the packet
            body = span[: min(104, span.size)]
            i, j = rng.choice(body, 2, replace=False)
            hi = min(255 - d.data[i], d.data[j])
            if hi >= 1:
                dd = int(rng.integers(1, hi + 1))
                d.data[i] += dd
                d.data[j] -= dd
        _touch(d, d.owner[span[0]], op)
    elif op in ("lost", "inserted", "garbage", "truncated"):
        if op == "truncated":
            L = int(rng.integers(1, 301))
            _touch(d, d.owner[-L:], op)
            d.data = d.data[:-L]
            d.owner = d.owner[:-L]
            return
        if op == "garbage":  # between two packets
            it = int(rng.choice(items))
            at = int(_item_span(d, it)[0])
            _splice(d, at, 0, rng.integers(0, 256, int(rng.integers(1, 501)), dtype=np.uint8).tobytes(), new_id)
            _touch(d, new_id, op)
            return
        at = int(rng.integers(4, len(d.data)))
        L = int(rng.integers(1, 21))
        if op == "lost":
            _touch(d, d.owner[at : at + L], op)
            _splice(d, at, L, b"", new_id)
        else:
            _touch(d, [d.owner[at], new_id], op)
            _splice(d, at, 0, rng.integers(0, 256, L, dtype=np.uint8).tobytes(), new_id)
    elif op == "swap":
        pos = int(rng.integers(0, items.size - 1))
        a, b = _item_span(d, int(items[pos])), _item_span(d, int(items[pos + 1]))
        whole = a.size and b.size and a[-1] - a[0] + 1 == a.size and b[-1] - b[0] + 1 == b.size
        if whole and b[0] == a[-1] + 1:  # adjacent, each in one piece
            lo, hi = a[0], b[-1] + 1
            d.data[lo:hi] = bytes(d.data[b[0] : b[-1] + 1]) + bytes(d.data[a[0] : a[-1] + 1])
            d.owner[lo:hi] = np.concatenate((d.owner[b], d.owner[a]))
    elif op in ("repeat_near", "repeat_far"):
        pos = int(rng.integers(0, items.size))
        later = int(rng.integers(1, 6)) if op == "repeat_near" else int(rng.integers(100, 301))
        src = _item_span(d, int(items[pos]))
        target = pos + later
        at = len(d.data) if target >= items.size else int(_item_span(d, int(items[target]))[0])
        new_item = len(d.item_packet)
        d.item_packet.append(d.item_packet[int(items[pos])])
        _splice(d, at, 0, bytes(d.data[src[0] : src[-1] + 1]), new_item)
        # A copy of a damaged packet carries the same damage.
        d.touched[new_item] = set(d.touched.get(int(items[pos]), set()))
        if src.size != P or src[-1] - src[0] + 1 != P:
            _touch(d, new_item, op)
    elif op == "dropped":
        pos = int(rng.integers(0, items.size))
        for it in items[pos : pos + int(rng.integers(1, 4))]:
            span = _item_span(d, int(it))
            _splice(d, int(span[0]), span.size, b"", new_id)
    else:
        raise ValueError(f"operator: expected one of {OPERATORS}, got {op!r}")


def damage(numbers, stamps, raw, rng: np.random.Generator, n_ops: int | None = None, ops=None) -> Damaged:
    """The encoded stream (with ack) damaged by ``n_ops`` (default 1–3) operators drawn from
    ``ops`` (default all of :data:`OPERATORS`)."""
    data = bytearray(encode_mimu_packets(numbers, stamps, raw))
    n = len(numbers)
    owner = np.concatenate((np.full(4, ACK_OWNER), np.repeat(np.arange(n), P))).astype(np.int64)
    d = Damaged(data=data, owner=owner, item_packet=list(range(n)))
    ops = OPERATORS if ops is None else ops
    for _ in range(int(rng.integers(1, 4)) if n_ops is None else n_ops):
        apply(d, str(rng.choice(ops)), rng)
    return d


# ---------------------------------------------------------------------------------------- oracle
def intact_items(d: Damaged, original: bytes) -> dict:
    """{item: packet index} of the copies whose 106 bytes are all there, unchanged, in one piece."""
    out = {}
    ids, start, count = np.unique(d.owner, return_index=True, return_counts=True)
    for it, s0, c in zip(ids, start, count):
        if it < 0 or c != P or d.owner[s0 + P - 1] != it:
            continue
        k = d.item_packet[int(it)]
        if d.data[s0 : s0 + P] == original[4 + k * P : 4 + (k + 1) * P]:
            out[int(it)] = k
    return out


def array_frame(raw: np.ndarray) -> np.ndarray:
    """(n, 8, 6) counts in the array frame, written out with the README's C (not the importer's)."""
    x = raw.astype(np.float64).copy()
    for k in range(1, 8, 2):
        x[:, k, :3] = raw[:, k, :3] @ C.T
        x[:, k, 3:] = raw[:, k, 3:] @ C.T
    return x


def blind_envelope(raw: np.ndarray) -> np.ndarray:
    """(n, 6) per array-frame channel: the largest single-IMU error the jump rule can miss on this
    TRUE stream, 2·(floor + JUMP_MOTION·A₂ + SPREAD_FACTOR·S_j): A₂ the board's largest |second
    difference| within two samples (a neighbour may be missing in the damaged stream), S_j the
    eight IMUs' median of their smaller one-sample step off the median.  A corrupted IMU's step is
    its error plus its honest step (≤ the bound); doubled for that and the medians' shift.
    Computed from the truth only, with the study's own frame (no rigid-body correction: the
    honest steps then include it, which only widens the envelope)."""
    x = array_frame(raw)
    med = np.median(x, axis=1)  # (n, 6)
    n = med.shape[0]
    d2 = np.zeros_like(med)
    if n >= 3:
        d2[1:-1] = np.abs(med[2:] - 2 * med[1:-1] + med[:-2])
    a2 = np.zeros_like(med)
    for sl in (slice(0, 3), slice(3, 6)):
        a2[:, sl] = d2[:, sl].max(1, keepdims=True)
    wide = a2.copy()
    for s in (1, 2):
        wide[s:] = np.maximum(wide[s:], a2[:-s])
        wide[:-s] = np.maximum(wide[:-s], a2[s:])
    dev = x - med[:, None]
    step = np.abs(np.diff(dev, axis=0))
    j = np.full(dev.shape, np.inf)
    j[1:] = step
    j[:-1] = np.minimum(j[:-1], step)
    sj = np.median(j, axis=1)
    motion = np.array([JUMP_MOTION["acc"]] * 3 + [JUMP_MOTION["gyro"]] * 3)
    return 2 * (PLAUSIBILITY_FLOOR_LSB + motion * wide + SPREAD_FACTOR * sj)


def explain_residue(kept_raw, true_raw, stamp_err, packet_bytes: bytes, envelope, first_lead=None) -> str | None:
    """Why a wrong kept sample got through, if it is in the provable blind spot; else None.

    * the checksum must hold on the damaged bytes (else the checksum alone would have caught it);
    * ``time within jitter``: a stamp error within ``TIME_TOL_TICKS`` is indistinguishable from
      the ±8-tick jitter (and every value right);
    * ``first packet lead``: the first kept packet may sit up to ``FIRST_PACKET_LEAD_TICKS`` after
      the grid of the others (the stated exemption); ``first_lead`` is its lead as kept, in ticks,
      measured by the caller against the TRUE stamp of the next packet (None: not the first);
    * ``near limit``: the true board's median within 1/16 of full scale on a wrong channel, or a
      wrong IMU's true value saturated (the stated exemption: full scale corroborated by the
      board, or by the IMU's own neighbour, which a truly saturated value may have);
    * ``below bound``: every wrong array-frame channel is off by less than
      :func:`blind_envelope` of the true stream.
    """
    body = np.frombuffer(packet_bytes, dtype=np.uint8)
    if len(body) != P or int(body[:104].sum()) % 65536 != (int(body[104]) << 8 | int(body[105])):
        return None
    lead_ok = first_lead is not None and 0 < first_lead <= FIRST_PACKET_LEAD_TICKS + 8
    if abs(stamp_err) > TIME_TOL_TICKS and not lead_ok:
        return None
    err = np.abs(array_frame(kept_raw[None])[0] - array_frame(true_raw[None])[0])  # (8, 6)
    if not err.any():
        return "time within jitter" if abs(stamp_err) <= TIME_TOL_TICKS else "first packet lead"
    true_af = array_frame(true_raw[None])[0]
    wrong_ch = (err > 0).any(0)
    board = np.abs(np.median(true_af, axis=0))  # the true board's consensus per channel
    if ((board >= NEAR_LIMIT_LSB) & wrong_ch).any() or ((np.abs(true_af) >= SATURATED_LSB) & (err > 0)).any():
        return "near limit"
    big = err > envelope[None]
    if not big.any():
        return "below bound"
    return None


@dataclass
class Verdict:
    crashed: str | None = None
    refused: str | None = None
    refused_at_default: bool = False
    seconds: float = 0.0
    intact: int = 0
    intact_kept: int = 0
    kept: int = 0
    wrong: list = field(default_factory=list)  # (operators, reason or None, max |value err|, time err)
    events: list = field(default_factory=list)
    intact_lost: list = field(default_factory=list)  # why each lost intact packet went: the importer's drop reasons


def judge(numbers, stamps, raw, d: Damaged, *, default_threshold: bool = True) -> Verdict:
    """Import the damaged stream (``max_fail_fraction=1``: what the importer keeps, whatever the
    refusal policy) and compare every kept sample with the truth; ``default_threshold`` also
    records whether the default 1 % policy would refuse the stream."""
    original = encode_mimu_packets(numbers, stamps, raw)
    v = Verdict(events=list(d.events))
    intact = intact_items(d, original)
    v.intact = len(set(intact.values()))
    data = bytes(d.data)
    t0 = time.perf_counter()
    try:
        s, rep = decode_mimu_bytes(data, max_fail_fraction=1.0)
    except RecordingError as exc:
        v.seconds = time.perf_counter() - t0
        v.refused = str(exc)
        return v
    except Exception as exc:  # noqa: BLE001 - a crash is what the study counts
        v.seconds = time.perf_counter() - t0
        v.crashed = f"{type(exc).__name__}: {exc}"
        return v
    v.seconds = time.perf_counter() - t0
    if default_threshold:
        try:
            decode_mimu_bytes(data)
        except RecordingError:
            v.refused_at_default = True
    v.kept = int(s.number.size)
    envelope = blind_envelope(raw)
    index = {int(k) % 65536: i for i, k in enumerate(numbers)}
    true_idx = np.array([index.get(int(k), -1) for k in s.number])
    good = np.zeros(s.number.size, dtype=bool)
    e0 = None
    for i, ti in enumerate(true_idx):
        owner = int(d.owner[s.offset[i]])
        ops = sorted(d.touched.get(owner, set())) or ["none"]
        if ti < 0:  # a packet number the stream never had
            v.wrong.append((ops, None, float("inf"), float("inf")))
            continue
        # Stamp error of this sample (mod 2^32, signed), and of its place on the time axis
        # relative to the first kept sample: the two differ only if a wrap was mis-unwrapped.
        e = (int(s.ticks[i]) - int(stamps[ti]) + (1 << 31)) % (1 << 32) - (1 << 31)
        if e0 is None:
            e0, base = e, (int(s.ticks[i]), int(stamps[ti]))
        axis = (int(s.ticks[i]) - base[0]) - (int(stamps[ti]) - base[1]) - (e - e0)
        order_ok = i == 0 or true_idx[i - 1] < ti
        if np.array_equal(s.raw[i], raw[ti]) and e == 0 and axis == 0 and order_ok:
            good[i] = True
            continue
        why = None
        lead = None
        if i == 0 and ti + 1 < len(stamps):  # against the true grid: next true stamp − one period
            lead = int(stamps[ti]) + e - (int(stamps[ti + 1]) - NOMINAL_PERIOD_TICKS)
        if order_ok and axis == 0:
            why = explain_residue(s.raw[i], raw[ti], e, data[s.offset[i] : s.offset[i] + P], envelope[ti], lead)
        v.wrong.append((ops, why, float(np.abs(s.raw[i].astype(np.int64) - raw[ti]).max()), float(e)))
    kept_true = set(true_idx[good].tolist())
    v.intact_kept = len(kept_true & set(intact.values()))
    for k in sorted(set(intact.values()) - kept_true):
        why = sorted({d[0] for d in rep.dropped if d[1] == int(numbers[k]) % 65536}) or ["not dropped: kept wrong or absent"]
        v.intact_lost.append("/".join(why))
    return v


# ---------------------------------------------------------------------------------------- study
def run(variants: int, packets: int, seed: int, ops=None, default_threshold: bool = True) -> list[Verdict]:
    """``variants`` seeded damaged streams of ``packets`` packets; one child seed per variant."""
    out = []
    for child in np.random.SeedSequence(seed).spawn(variants):
        rng = np.random.default_rng(child)
        numbers, stamps, raw = board_stream(packets, rng)
        d = damage(numbers, stamps, raw, rng, ops=ops)
        out.append(judge(numbers, stamps, raw, d, default_threshold=default_threshold))
    return out


ERR_BINS = ((0, "err 0 (time only)"), (255, "err 1-255 LSB"), (1023, "err 256-1023 LSB"),
            (4095, "err 1024-4095 LSB"), (float("inf"), "err >= 4096 LSB"))


def _err_bin(err: float) -> str:
    """Label of the largest wrong value's magnitude (LSB) in :data:`ERR_BINS`."""
    return next(label for top, label in ERR_BINS if err <= top)


def summarise(verdicts: list[Verdict]) -> dict:
    """Headline figures and per-operator rows."""
    per = {op: Counter() for op in OPERATORS}
    for v in verdicts:
        for op in set(v.events):
            per[op]["streams"] += 1
        for op in v.events:
            per[op]["applied"] += 1
        for ops, why, verr, terr in v.wrong:
            for op in ops:
                c = per.setdefault(op, Counter())
                c["wrong_kept"] += 1
                c["explained" if why else "unexplained"] += 1
                c[f"why: {why}"] += 1
                c["max_value_err_lsb"] = max(c["max_value_err_lsb"], verr)
                c[_err_bin(verr)] += 1
                c["max_time_err_ticks"] = max(c["max_time_err_ticks"], abs(terr))
    intact = sum(v.intact for v in verdicts)
    kept = sum(v.intact_kept for v in verdicts)
    big = [(v, w) for v in verdicts for w in v.wrong if w[2] >= 1024]
    return {
        "streams_checksum_blind": sum(bool(set(v.events) & set(CHECKSUM_BLIND)) for v in verdicts),
        "wrong_kept_ge_1024_lsb": len(big),
        "streams_wrong_kept_ge_1024_lsb": len({id(v) for v, _ in big}),
        "variants": len(verdicts),
        "crashes": sum(v.crashed is not None for v in verdicts),
        "refused_any_threshold": sum(v.refused is not None for v in verdicts),
        "refused_at_default_1pct": sum(v.refused_at_default for v in verdicts),
        "max_seconds": max(v.seconds for v in verdicts),
        "mean_seconds": float(np.mean([v.seconds for v in verdicts])),
        "intact_packets": intact,
        "intact_kept": kept,
        "intact_kept_fraction": kept / intact if intact else float("nan"),
        "intact_lost_by_reason": dict(Counter(r for v in verdicts for r in v.intact_lost)),
        "intact_lost_variants": [[i, v.events, v.intact_lost] for i, v in enumerate(verdicts) if v.intact_lost],
        "wrong_kept": sum(len(v.wrong) for v in verdicts),
        "wrong_kept_unexplained": sum(why is None for v in verdicts for _, why, *_ in v.wrong),
        "per_operator": {op: dict(c) for op, c in per.items()},
    }


def real_margins(data_dir: Path) -> list[dict]:
    """Per shared recording: what was dropped, and how close each check came to firing — the
    largest plausibility ratio (fires above 1), stamp deviation (fires above the tolerance) and
    the first packet's lead (exempt up to ``FIRST_PACKET_LEAD_TICKS``)."""
    rows = []
    for exp in sorted(data_dir.glob("exp_*/data.bin.gz")):
        data, _ = read_mimu_bytes(exp)
        s, rep = decode_mimu_bytes(data)
        rng, jmp = plausibility_statistics(s.raw)  # no gaps in the shared recordings
        seq = np.arange(s.number.size)
        res = (s.ticks - s.ticks[0] - NOMINAL_PERIOD_TICKS * seq).astype(np.float64)
        dev, tol = _stamp_deviation(res, seq, ref_ok=seq > 0)  # as the importer: the first is no reference
        rows.append({
            "experiment": exp.parent.name, "packets_kept": rep.packets_kept, "dropped": len(rep.dropped),
            "implausible": len(rep.implausible), "dropped_rate": len(rep.dropped) / rep.packets_read,
            "bytes_skipped": rep.bytes_skipped, "reordered": rep.reordered_packets, "partial_bytes": rep.partial_bytes,
            "range_acc": float(rng[..., 0].max()), "range_gyro": float(rng[..., 1].max()),
            "jump_acc": float(jmp[..., 0].max()), "jump_gyro": float(jmp[..., 1].max()),
            "stamp_dev_max_ticks": float(np.abs(dev[1:]).max()), "stamp_tol_ticks": float(tol[1:].min()),
            "first_lead_ticks": rep.first_packet_lead_ticks,
        })
    return rows


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".")
    with os.fdopen(fd, "w", newline="") as f:
        f.write(text)
    os.replace(tmp, path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", type=int, default=10_000, help="damaged streams (default 10000)")
    ap.add_argument("--packets", type=int, default=400, help="packets per synthetic stream (default 400)")
    ap.add_argument("--seed", type=int, default=13, help="root seed (default 13)")
    ap.add_argument("--data", type=Path, default=data_dir(),
                    help="shared MIMU recordings for the real-data margins (skipped if absent)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "mimu_fuzz",
                    help="folder for summary.json and per_operator.csv")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    verdicts = run(a.variants, a.packets, a.seed)
    summ = summarise(verdicts)
    summ.update(seed=a.seed, packets=a.packets, seconds=time.perf_counter() - t0)
    _write_atomic(a.out / "summary.json", json.dumps(summ, indent=1, default=str) + "\n")
    cols = ["operator", "streams", "applied", "wrong_kept", "explained", "unexplained", "max_value_err_lsb",
            "max_time_err_ticks"]
    whys = sorted({k for c in summ["per_operator"].values() for k in c if k.startswith("why: ")})
    whys += [label for _, label in ERR_BINS]
    rows = [",".join(cols + [w.replace(",", ";") for w in whys])]
    for op, c in summ["per_operator"].items():
        rows.append(",".join([op] + [str(c.get(k, 0)) for k in cols[1:]] + [str(c.get(w, 0)) for w in whys]))
    _write_atomic(a.out / "per_operator.csv", "\n".join(rows) + "\n")
    print(json.dumps({k: v for k, v in summ.items() if k != "per_operator"}, indent=1))
    print("\n".join(rows))
    if a.data.is_dir():
        real = real_margins(a.data)
        text = "\n".join([",".join(real[0])] + [",".join(f"{v:.6g}" if isinstance(v, float) else str(v)
                                                           for v in r.values()) for r in real]) + "\n"
        _write_atomic(a.out / "real_margins.csv", text)
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())

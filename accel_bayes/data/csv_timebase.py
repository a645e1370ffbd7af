"""One time base for the IMUs of a CSV import (DESIGN §7.1).

* :func:`align_streams` puts IMUs that share the reference's rate on the reference IMU's stamps:
  each contributes, at every reference stamp, its sample with the nearest stamp within a
  tolerance, and its own stamp minus ``time`` becomes ``imu_time_offset``.
* :func:`union_streams` is for IMUs at different rates (:func:`rates_agree` false): the time
  base is the sorted union of every IMU's stamps and each IMU keeps every sample, NaN where it
  has none — matching a 400 Hz IMU to a 125 Hz reference would throw away 69 % of its samples.
"""
from __future__ import annotations

import numpy as np

from ..errors import UserError
from .csv_read import ImuStream

__all__ = ["align_streams", "union_streams", "rates_agree", "median_period_ns", "nearest_index", "SAME_RATE_REL"]

# Median sample periods that differ by more than this fraction mean different rates.  Clock
# drifts are ~1e-4 and EuRoC's stamp steps differ by 4e-5, while the nearest distinct rates an
# IMU offers (e.g. 100 / 104 Hz) differ by 4 %.
SAME_RATE_REL = 0.01


def median_period_ns(stamps_ns: np.ndarray) -> float:
    """Median step of integer-ns stamps (ns); NaN for fewer than two stamps."""
    return float(np.median(np.diff(stamps_ns))) if stamps_ns.size > 1 else float("nan")


def rates_agree(streams: list[ImuStream], reference: int) -> bool:
    """True when every IMU's median sample period is within :data:`SAME_RATE_REL` of the
    reference's (an IMU with a single sample has no rate and agrees)."""
    p0 = median_period_ns(streams[reference].stamps_ns)
    ps = [median_period_ns(s.stamps_ns) for s in streams]
    return all(not (p > 0) or not (p0 > 0) or abs(p / p0 - 1.0) <= SAME_RATE_REL for p in ps)


def nearest_index(stamps_ns: np.ndarray, base_ns: np.ndarray) -> np.ndarray:
    """Index into ``stamps_ns`` (sorted) of the stamp nearest to each of ``base_ns``, compared in
    integers (a tie goes to the earlier stamp)."""
    st = stamps_ns
    if st.size < 2:
        return np.zeros(base_ns.size, np.int64)
    j = np.clip(np.searchsorted(st, base_ns), 1, st.size - 1)
    left_closer = (base_ns - st[j - 1]) <= (st[j] - base_ns)
    return np.where(left_closer, j - 1, j)


def union_streams(streams: list[ImuStream]):
    """The sorted union of the IMUs' stamps as the time base; every sample kept.

    Returns ``(base_ns (T,), index (T, K) into each stream, −1 where the IMU has no sample at
    that stamp, rows)``, ``rows`` one dict per IMU with ``label``, ``samples``, ``used`` (=
    ``samples``) and ``rate_hz`` (from the median step).  Raises :class:`UserError` when the
    IMUs' recordings do not overlap in time (then they are not one recording).
    """
    lo = max(int(s.stamps_ns[0]) for s in streams)
    hi = min(int(s.stamps_ns[-1]) for s in streams)
    if lo > hi:
        late = max(range(len(streams)), key=lambda k: int(streams[k].stamps_ns[0]))
        raise UserError(f"{streams[late].file}: IMU {streams[late].label!r} starts at {lo} ns, after another IMU's last "
                        f"stamp ({hi} ns); expected the IMUs' recordings to overlap in time")
    base = np.unique(np.concatenate([s.stamps_ns for s in streams]))
    index = np.full((base.size, len(streams)), -1, dtype=np.int64)
    rows = []
    for k, s in enumerate(streams):
        # stamps are strictly increasing per file (csv_read), so each lands on its own union slot
        index[np.searchsorted(base, s.stamps_ns), k] = np.arange(s.stamps_ns.size)
        p = median_period_ns(s.stamps_ns)
        rows.append({"label": s.label, "samples": int(s.stamps_ns.size), "used": int(s.stamps_ns.size),
                     "rate_hz": 1e9 / p if p > 0 else float("nan")})
    return base, index, rows


def align_streams(streams: list[ImuStream], reference: int, tolerance_ns: int):
    """Put the IMUs on the reference IMU's stamps (module docstring).

    Returns ``(base_ns (T,), index (T, K) into each stream, rows)``, ``rows`` one dict per IMU
    with ``label``, ``samples``, ``used``, ``worst_ns`` (largest |own stamp − base stamp| kept)
    and ``median_ns`` (median signed offset); ``dropped_ends`` (reference stamps outside the span
    all IMUs cover) is in every row.  Raises :class:`UserError` with the numbers where a stamp
    inside the common span has no partner within ``tolerance_ns``, or two stamps share one.
    """
    base = streams[reference].stamps_ns
    lo = max(int(s.stamps_ns[0]) for s in streams) - tolerance_ns
    hi = min(int(s.stamps_ns[-1]) for s in streams) + tolerance_ns
    keep = (base >= lo) & (base <= hi)
    if not keep.any():
        raise UserError(f"time: the IMUs' recordings do not overlap (reference {streams[reference].label!r} spans "
                        f"{base[0]}..{base[-1]} ns); expected a common time span")
    first, last = int(np.argmax(keep)), int(len(keep) - np.argmax(keep[::-1]))
    base = base[first:last]
    dropped = len(keep) - base.size
    index = np.empty((base.size, len(streams)), dtype=np.int64)
    rows = []
    for k, s in enumerate(streams):
        st = s.stamps_ns
        j = nearest_index(st, base)
        off = st[j] - base
        bad = np.flatnonzero(np.abs(off) > tolerance_ns)
        if bad.size:
            i = int(bad[np.argmax(np.abs(off[bad]))])
            raise UserError(
                f"{s.file}: {bad.size} of {base.size} stamps of the reference IMU {streams[reference].label!r} have no "
                f"sample of IMU {s.label!r} within {tolerance_ns / 1e6:g} ms (worst {abs(int(off[i])) / 1e6:g} ms, at "
                f"reference stamp {int(base[i])} ns); expected one sample per reference stamp — raise --time-tolerance "
                "or fix the stamps")
        if np.any(np.diff(j) == 0):
            i = int(np.flatnonzero(np.diff(j) == 0)[0])
            raise UserError(f"{s.file}: sample at stamp {int(st[j[i]])} ns of IMU {s.label!r} is the nearest to two "
                            f"reference stamps ({int(base[i])} and {int(base[i + 1])} ns); expected a tolerance below "
                            "half the sample period (--time-tolerance)")
        index[:, k] = j
        rows.append({"label": s.label, "samples": int(st.size), "used": int(base.size),
                     "worst_ns": int(np.abs(off).max()), "median_ns": int(np.median(off)), "dropped_ends": int(dropped)})
    return base, index, rows

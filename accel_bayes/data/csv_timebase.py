"""One time base for the IMUs of a CSV import (DESIGN §7.1).

:func:`align_streams` puts IMUs that share the reference's rate on the reference IMU's stamps:
each contributes, at every reference stamp, its sample with the nearest stamp within a
tolerance, and its own stamp minus ``time`` becomes ``imu_time_offset``.
"""
from __future__ import annotations

import numpy as np

from ..errors import UserError
from .csv_read import ImuStream

__all__ = ["align_streams"]


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
        j = np.clip(np.searchsorted(st, base), 1, st.size - 1) if st.size > 1 else np.zeros(base.size, np.int64)
        if st.size > 1:
            # Nearest of the two neighbours, compared in integers.
            left_closer = (base - st[j - 1]) <= (st[j] - base)
            j = np.where(left_closer, j - 1, j)
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

"""Option types of the command line: argparse ``type=`` functions that refuse bad numbers at parse time.

Every numeric option of every command is parsed by one of these, so a value that is not a number,
not finite (``nan``, ``inf``) or out of its range is refused before anything is read or computed,
with one line naming the option (argparse adds ``argument --name:``; the command line exits with
status 2, DESIGN §7.5)::

    accel-bayes calibrate: error: argument --prior-std: expected a finite number > 0 (m), got 'nan'

:func:`real` and :func:`integer` build a converter for a range; the names below are the common
ones.  Checks that need more than one option (e.g. ``-T`` against the preset's size) stay in the
command, after parsing.
"""
from __future__ import annotations

import argparse
import math
from typing import Callable

__all__ = ["real", "integer", "positive", "nonnegative", "fraction", "count", "seed"]


def _range_text(lo, hi, lo_open, hi_open) -> str:
    def num(v):  # integers in full (a seed bound), floats short
        return str(v) if isinstance(v, int) else f"{v:g}"

    parts = []
    if lo is not None:
        parts.append(f"{'>' if lo_open else '>='} {num(lo)}")
    if hi is not None:
        parts.append(f"{'<' if hi_open else '<='} {num(hi)}")
    return " and ".join(parts)


def real(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
         unit: str = "") -> Callable[[str], float]:
    """A converter to a finite float in the range [lo, hi] (open ends with ``lo_open``/``hi_open``;
    None: unbounded on that side).  ``unit`` is only named in the refusal."""
    rng = _range_text(lo, hi, lo_open, hi_open)
    want = "a finite number" + (f" {rng}" if rng else "") + (f" ({unit})" if unit else "")

    def conv(s: str) -> float:
        try:
            v = float(s)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {want}, got {s!r}") from None
        ok = math.isfinite(v)
        if ok and lo is not None:
            ok = v > lo if lo_open else v >= lo
        if ok and hi is not None:
            ok = v < hi if hi_open else v <= hi
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {want}, got {s!r}")
        return v

    conv.__name__ = "real"
    return conv


def integer(lo: int | None = None, hi: int | None = None, *, also: tuple = ()) -> Callable[[str], int]:
    """A converter to an int in [lo, hi] (None: unbounded), or one of the values ``also``.
    Decimal digits only: ``1e3`` or ``2.5`` are refused rather than rounded."""
    rng = _range_text(lo, hi, False, False)
    want = "an integer" + (f" {rng}" if rng else "") + "".join(f" or {a}" for a in also)

    def conv(s: str) -> int:
        try:
            v = int(str(s).strip(), 10)
        except (TypeError, ValueError):
            raise argparse.ArgumentTypeError(f"expected {want}, got {s!r}") from None
        if v in also:
            return v
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise argparse.ArgumentTypeError(f"expected {want}, got {s!r}")
        return v

    conv.__name__ = "integer"
    return conv


def positive(unit: str = "") -> Callable[[str], float]:
    """Finite float > 0 (a std, a rate, a length scale)."""
    return real(0.0, lo_open=True, unit=unit)


def nonnegative(unit: str = "") -> Callable[[str], float]:
    """Finite float >= 0 (a threshold where 0 switches it off, an error std that may be zero)."""
    return real(0.0, unit=unit)


def fraction(*, lo_open: bool = False, hi_open: bool = True) -> Callable[[str], float]:
    """Finite float in [0, 1) by default (ends chosen by ``lo_open``/``hi_open``)."""
    return real(0.0, 1.0, lo_open=lo_open, hi_open=hi_open)


def count(lo: int = 1) -> Callable[[str], int]:
    """Integer >= ``lo`` (draws, chains, iterations)."""
    return integer(lo)


# The package derives child seeds as seed·10⁶ + n (model/likelihood.py) and seed·7919 + 17 (calibrate.py);
# below 2³² these stay inside torch.Generator.manual_seed's 64-bit range.
seed = integer(0, 2 ** 32 - 1)
"""Random seed: an integer in [0, 2³² − 1]."""

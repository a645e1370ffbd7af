"""Exceptions the package raises for bad input.

:class:`UserError` (a ``ValueError``) marks problems a user can fix: a malformed recording, an
option out of range.  The CLI turns it into one line on stderr and exit status 2; library callers
can catch it as ``ValueError``.  :class:`DivergenceError` (a ``RuntimeError``) is a fit that
diverged: one line and exit status 3.
"""

import math

__all__ = ["UserError", "RecordingError", "DivergenceError", "nonnegative"]


class UserError(ValueError):
    """Bad input from the user; the message names the field and what was expected."""


class RecordingError(UserError):
    """A recording (file or in-memory) that breaks format v1 (DESIGN §7.1)."""


class DivergenceError(RuntimeError):
    """An optimisation left the region where its model makes sense (a MAP far outside the prior,
    non-finite values).  The CLI turns it into one line and exit status 3 (DESIGN §7.5)."""


def nonnegative(value, name: str, unit: str = "") -> float:
    """``value`` as a float, or a :class:`UserError` naming ``name`` unless it is a finite number
    >= 0 (``unit`` is only for the message, e.g. "rad/s").  The one check of the library's
    non-negative scalar options (the CLI checks its own with cli/_options before reading input)."""
    what = f"a finite number of {unit} >= 0" if unit else "a finite number >= 0"
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise UserError(f"{name}: expected {what}, got {value!r}") from None
    if not (v >= 0 and math.isfinite(v)):
        raise UserError(f"{name}: expected {what}, got {value!r}")
    return v

"""Exceptions the package raises for bad input.

:class:`UserError` (a ``ValueError``) marks problems a user can fix: a malformed recording, an
option out of range.  The CLI turns it into one line on stderr and exit status 2; library callers
can catch it as ``ValueError``.
"""

__all__ = ["UserError", "RecordingError"]


class UserError(ValueError):
    """Bad input from the user; the message names the field and what was expected."""


class RecordingError(UserError):
    """A recording (file or in-memory) that breaks format v1 (DESIGN §7.1)."""

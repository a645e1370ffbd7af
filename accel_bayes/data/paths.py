"""Where input files are and what they are called: the one existence check of every reader and
of the command line, and the ground-truth sidecar's name.

Nothing here imports a numerical library, so the command line refuses a missing input before it
pays for torch (issue #26: every refusal decided from the arguments and the file system at once).
"""
from __future__ import annotations

from pathlib import Path

__all__ = ["require_file", "truth_path"]


def require_file(path, what: str, *, flag: str | None = None, directory_ok: bool = False) -> Path:
    """``path`` as a Path, or a one-line refusal naming it: :class:`FileNotFoundError`
    ("``[FLAG: ]PATH: no such WHAT``") when nothing is there, :class:`IsADirectoryError` when it is
    a directory (unless ``directory_ok``: an input that may be a folder).  ``what`` names the
    expected input with its kind, e.g. ``"recording file"``."""
    p = Path(path)
    pre = f"{flag}: " if flag else ""
    if not p.exists():
        raise FileNotFoundError(f"{pre}{p}: no such {what}")
    if p.is_dir() and not directory_ok:
        raise IsADirectoryError(f"{pre}{p}: is a directory; expected a {what}")
    return p


def truth_path(rec_path) -> Path:
    """The ground-truth sidecar of a recording: ``rec.nc`` → ``rec.truth.json``."""
    return Path(rec_path).with_suffix(".truth.json")

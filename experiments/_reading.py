"""The hand-written reading of a results document, kept when its script regenerates it (one
mechanism for every script that has one): everything below :data:`READING_MARKER`."""
from __future__ import annotations

from pathlib import Path

__all__ = ["READING_MARKER", "kept_reading", "write_with_reading"]

READING_MARKER = "<!-- reading: hand-written below this line, kept when the document is regenerated -->"


def kept_reading(path) -> str:
    """The text after :data:`READING_MARKER` in the document at ``path`` (starting with the
    marker line's newline), or "" where the document or the marker is absent."""
    p = Path(path)
    if not p.exists():
        return ""
    text = p.read_text(encoding="utf-8")
    return text.split(READING_MARKER, 1)[1] if READING_MARKER in text else ""


def write_with_reading(path, lines) -> None:
    """Write the generated document ``lines`` (a list of Markdown lines) to ``path`` atomically, then the
    marker and the reading the document at ``path`` already has below it (none yet: an empty line)."""
    from accel_bayes.data.outputs import write_text

    write_text(path, "\n".join(lines) + "\n\n" + READING_MARKER + (kept_reading(path) or "\n"))

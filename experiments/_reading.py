"""The hand-written reading of a results document, kept when its script regenerates it (one
mechanism for every script that has one): everything below :data:`READING_MARKER`."""
from __future__ import annotations

from pathlib import Path

__all__ = ["READING_MARKER", "kept_reading"]

READING_MARKER = "<!-- reading: hand-written below this line, kept when the document is regenerated -->"


def kept_reading(path) -> str:
    """The text after :data:`READING_MARKER` in the document at ``path`` (starting with the
    marker line's newline), or "" where the document or the marker is absent."""
    p = Path(path)
    if not p.exists():
        return ""
    text = p.read_text(encoding="utf-8")
    return text.split(READING_MARKER, 1)[1] if READING_MARKER in text else ""

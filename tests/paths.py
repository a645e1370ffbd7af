"""Where the tests find the repository and their stored reference files (one definition, so a
test file can move between subject folders without its paths changing)."""
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# reference files written by earlier commits (recordings, chains, checkpoints); never regenerated
# by a test
STORED = REPO / "tests" / "stored"

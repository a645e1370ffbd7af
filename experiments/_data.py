"""Where the experiments find the shared real recordings (one definition for every script)."""
from __future__ import annotations

import os
from pathlib import Path

__all__ = ["data_dir"]

HERE = Path(__file__).resolve().parent


def data_dir() -> Path:
    """The six MIMU4444 recordings (``exp_1`` … ``exp_6``): ``$ACCEL_BAYES_SHARED/data/mimu4444-bcd``,
    else ``../shared/data/mimu4444-bcd`` beside the repository (never copied into it)."""
    env = os.environ.get("ACCEL_BAYES_SHARED")
    root = Path(env) if env else HERE.parents[1] / "shared"
    return root / "data" / "mimu4444-bcd"

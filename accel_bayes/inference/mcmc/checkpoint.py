"""Crash-safe PmMH checkpoints: the format gate, loading with checks, and the settings
fingerprint a resume must match.

A checkpoint is one torch file holding only tensors, dicts, lists, strings and numbers:
``format`` (:data:`CHECKPOINT_FORMAT`), ``fingerprint`` (settings and data hash), ``chain`` and
``iteration`` to continue from, ``kernel`` (:meth:`PMMHKernel.state_dict`, or None between
chains), ``arrays`` (the draws so far), ``diagnostics`` and ``seconds``.  The format string is the
gate: a file of another version is refused with one line.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

import torch

from ...errors import UserError

__all__ = ["CHECKPOINT_FORMAT", "read_checkpoint", "write_checkpoint", "check_checkpoint_request",
           "fingerprint_mismatch"]

CHECKPOINT_FORMAT = "accel_bayes.pmmh-checkpoint/1"


def write_checkpoint(obj: dict, path: Path) -> None:
    """Write ``obj`` to ``path`` atomically (temporary file + rename: a crash leaves the old file)."""
    from ...data.outputs import atomic_path

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


# what a checkpoint must hold (keys and types) for run_pmmh to resume from it
_CHECKPOINT_KEYS = {"format": str, "fingerprint": dict, "chain": int, "iteration": int, "arrays": dict,
                    "diagnostics": list, "seconds": (int, float)}


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Load and check a checkpoint written by :func:`run_pmmh`, before anything is computed.

    Loaded with ``torch.load(weights_only=True)``: a checkpoint holds only tensors, dicts, lists,
    strings and numbers, so nothing in it is executed.  Raises :class:`UserError` (one line naming
    ``checkpoint`` and the file) for an empty, truncated or corrupt file, a file that is not a
    torch file, a torch file that is not a PmMH checkpoint, another checkpoint format version, or
    a checkpoint with missing or mistyped parts.
    """
    p = Path(path)
    if p.is_dir():
        raise UserError(f"checkpoint: {p} is a directory; expected a checkpoint file")
    if p.stat().st_size == 0:
        raise UserError(f"checkpoint: {p} is empty (a run killed while creating it?); delete it or rerun without "
                        "--resume")
    try:
        # torch warns about a foreign pickle protocol before refusing it: the refusal below is
        # the one line the user gets
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            saved = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... by damage
        raise UserError(f"checkpoint: {p} is not a readable PmMH checkpoint (corrupt, truncated or not a torch "
                        f"file: {type(exc).__name__}); delete it or rerun without --resume") from None
    fmt = saved.get("format") if isinstance(saved, dict) else None
    if not isinstance(fmt, str) or not fmt.startswith(CHECKPOINT_FORMAT.rsplit("/", 1)[0] + "/"):
        raise UserError(f"checkpoint: {p} is a torch file but not a PmMH checkpoint (expected format "
                        f"{CHECKPOINT_FORMAT!r})")
    if fmt != CHECKPOINT_FORMAT:
        raise UserError(f"checkpoint: {p} has format {fmt!r}; this version reads {CHECKPOINT_FORMAT!r}; rerun without "
                        "--resume")
    bad = [k for k, t in _CHECKPOINT_KEYS.items() if not isinstance(saved.get(k), t) or isinstance(saved.get(k), bool)]
    if bad:
        raise UserError(f"checkpoint: {p} is incomplete or damaged (missing or mistyped: {', '.join(bad)}); delete it "
                        "or rerun without --resume")
    return saved


def check_checkpoint_request(saved: dict, request: dict, path) -> None:
    """Refuse (:class:`UserError`) a checkpoint written for another recording, other settings or by
    another package version: ``request`` is the caller's dict of plain values known before any
    computation (``version``, ``recording`` hash, the options), stored as ``fingerprint["request"]``."""
    old = saved["fingerprint"].get("request")
    if not isinstance(old, dict):
        raise UserError(f"checkpoint: {path} holds no settings fingerprint to check a resume against; rerun without "
                        "--resume")
    if old.get("version") != request.get("version"):
        raise UserError(f"resume: checkpoint {path} was written by accel_bayes {old.get('version')}, this is "
                        f"{request.get('version')}; rerun without --resume")
    if old.get("recording") != request.get("recording"):
        raise UserError(f"resume: checkpoint {path} was written for another recording; rerun with that recording or "
                        "without --resume")
    bad = fingerprint_mismatch(old, request)
    if bad:
        raise UserError(f"resume: checkpoint {path} was written with different settings ({', '.join(bad)}); "
                        "rerun with the same options or without --resume")


def fingerprint_mismatch(saved: dict, now: dict) -> list[str]:
    """Keys whose values differ between two fingerprints."""
    keys = sorted(set(saved) | set(now))
    return [k for k in keys if saved.get(k) != now.get(k)]

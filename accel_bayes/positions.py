"""Calibration outputs, format v1: the ``positions.json`` document (DESIGN §7.3).

One writer and one reader for every method that estimates the geometry ("pmmh", "map",
"selfcal", "conventional"), so the contract is kept in one place.
"""
from __future__ import annotations

import json
import math
import os
import tempfile
from pathlib import Path

import numpy as np

from .errors import UserError

__all__ = ["POSITIONS_SCHEMA", "METHODS", "positions_document", "write_positions", "read_positions"]

POSITIONS_SCHEMA = "accel_bayes.positions/1"
METHODS = ("pmmh", "map", "selfcal", "conventional")


def _f(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def positions_document(
    *,
    method: str,
    reference_imu: int,
    means,
    covs,
    orientations=None,
    diagnostics: dict | None = None,
    provenance: dict | None = None,
) -> dict:
    """Build the DESIGN §7.3 document.

    means : (K, 3) m, array frame, relative to the reference IMU (its row must be zero).
    covs : (K, 3, 3) m² — posterior (pmmh) or Laplace (other methods) covariance per IMU; the
        reference row is zero.
    orientations : (K, 4) quaternions (§7.0 convention) or None when not estimated.
    diagnostics : must hold ``seconds``; "pmmh" also needs ``rhat_max`` and ``ess_bulk_min``.
    """
    if method not in METHODS:
        raise UserError(f"method: expected one of {METHODS}, got {method!r}")
    means = np.asarray(means, dtype=float)
    covs = np.asarray(covs, dtype=float)
    K = means.shape[0]
    if means.shape != (K, 3) or covs.shape != (K, 3, 3):
        raise UserError(f"means/covs: expected shapes (K, 3) and (K, 3, 3), got {means.shape} and {covs.shape}")
    if not 0 <= reference_imu < K:
        raise UserError(f"reference_imu: expected a label in 0..{K - 1}, got {reference_imu}")
    diagnostics = dict(diagnostics or {})
    required = ("seconds", "rhat_max", "ess_bulk_min") if method == "pmmh" else ("seconds",)
    missing = [k for k in required if k not in diagnostics]
    if missing:
        raise UserError(f"diagnostics: method {method!r} needs {missing}")
    imus = []
    for k in range(K):
        entry = {"imu": k, "mean": [_f(v) for v in means[k]],
                 "std": [_f(v) for v in np.sqrt(np.clip(np.diag(covs[k]), 0, None))]}
        if k != reference_imu:
            entry["cov"] = [[_f(v) for v in row] for row in covs[k]]
        if orientations is not None:
            entry["orientation"] = [_f(v) for v in np.asarray(orientations, dtype=float)[k]]
        imus.append(entry)
    return {
        "schema": POSITIONS_SCHEMA,
        "method": method,
        "reference_imu": int(reference_imu),
        "imus": imus,
        "diagnostics": {k: (_f(v) if isinstance(v, (int, float, np.floating, np.integer)) else v)
                        for k, v in diagnostics.items()},
        "provenance": provenance or {},
    }


def write_positions(doc: dict, path) -> Path:
    """Write the document atomically (temp file + rename), so a crash never leaves half a file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(doc, fh, indent=2)
            fh.write("\n")
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_positions(source) -> dict:
    """Read and check a positions document from a path or a dict.

    Returns the dict with two extra numpy entries: ``means`` (K, 3) and ``covs`` (K, 3, 3).
    """
    if isinstance(source, dict):
        doc = dict(source)
        where = "calibration"
    else:
        p = Path(source)
        if not p.is_file():
            raise FileNotFoundError(f"calibration file not found: {p}")
        try:
            doc = json.loads(p.read_text(encoding="utf-8"))
        except json.JSONDecodeError as exc:
            raise UserError(f"{p}: not a JSON document ({exc.msg} at line {exc.lineno})") from None
        where = str(p)
    if doc.get("schema") != POSITIONS_SCHEMA:
        raise UserError(f"{where}: schema: expected {POSITIONS_SCHEMA!r}, got {doc.get('schema')!r}")
    imus = doc.get("imus")
    if not isinstance(imus, list) or not imus:
        raise UserError(f"{where}: imus: expected a non-empty list of IMU entries")
    K = len(imus)
    means = np.zeros((K, 3))
    covs = np.zeros((K, 3, 3))
    for i, e in enumerate(sorted(imus, key=lambda e: e.get("imu", -1))):
        if e.get("imu") != i:
            raise UserError(f"{where}: imus: expected labels 0..{K - 1} each once, got {[e.get('imu') for e in imus]}")
        try:
            means[i] = np.asarray(e["mean"], dtype=float).reshape(3)
            if "cov" in e:
                covs[i] = np.asarray(e["cov"], dtype=float).reshape(3, 3)
            else:
                covs[i] = np.diag(np.asarray(e.get("std", [0, 0, 0]), dtype=float).reshape(3) ** 2)
        except (KeyError, ValueError, TypeError) as exc:
            raise UserError(f"{where}: imus[{i}]: expected 'mean' (3 numbers) and 'cov' (3×3) or 'std' ({exc})") from None
    doc["means"], doc["covs"] = means, covs
    return doc

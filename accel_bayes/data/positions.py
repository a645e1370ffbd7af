"""Calibration outputs, format v1: the ``positions.json`` document (DESIGN §7.3).

One writer and one reader for every method that estimates the geometry ("pmmh", "map",
"selfcal", "conventional"), so the contract is kept in one place.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from . import outputs
from .outputs import to_jsonable
from ..errors import UserError

__all__ = ["POSITIONS_SCHEMA", "METHODS", "positions_document", "write_positions", "read_positions"]

POSITIONS_SCHEMA = "accel_bayes.positions/1"
METHODS = ("pmmh", "map", "selfcal", "conventional")


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
        # strict JSON (DESIGN §7.3): a number that is not finite (unknown) is written as null
        entry = {"imu": k, "mean": to_jsonable(means[k], nonfinite="null"),
                 "std": to_jsonable(np.sqrt(np.clip(np.diag(covs[k]), 0, None)), nonfinite="null")}
        if k != reference_imu:
            entry["cov"] = to_jsonable(covs[k], nonfinite="null")
        if orientations is not None:
            entry["orientation"] = to_jsonable(np.asarray(orientations, dtype=float)[k], nonfinite="null")
        imus.append(entry)
    return {
        "schema": POSITIONS_SCHEMA,
        "method": method,
        "reference_imu": int(reference_imu),
        "imus": imus,
        # Counts (draws_per_chain, checks, num_draws) stay ints, flags such as ``converged`` bools.
        "diagnostics": {k: (int(v) if isinstance(v, (int, np.integer)) and not isinstance(v, bool)
                            else to_jsonable(float(v), nonfinite="null") if isinstance(v, (float, np.floating))
                            else v) for k, v in diagnostics.items()},
        "provenance": provenance or {},
    }


def write_positions(doc: dict, path) -> Path:
    """Write the document atomically (:func:`accel_bayes.data.outputs.write_json`), so a crash never
    leaves half a file; a missing parent directory is created."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return outputs.write_json(path, doc, indent=2)


def _numbers(v, shape, where, what):
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        a = None
    if a is None or a.shape != shape or not np.isfinite(a).all():
        raise UserError(f"{where}: expected {what}")
    return a


def _parse(doc) -> dict:
    """Check a positions document and add numpy ``means``, ``covs``, ``orientations``."""
    if not isinstance(doc, dict):
        raise UserError(f"calibration: expected a JSON object, got {type(doc).__name__}")
    doc = dict(doc)
    if doc.get("schema") != POSITIONS_SCHEMA:
        raise UserError(f"calibration.schema: expected {POSITIONS_SCHEMA!r}, got {doc.get('schema')!r}")
    imus = doc.get("imus")
    if not isinstance(imus, list) or not imus:
        raise UserError("calibration.imus: expected a non-empty list of IMU entries")
    K = len(imus)
    ref = doc.get("reference_imu", 0)
    if isinstance(ref, bool) or not isinstance(ref, int) or not 0 <= ref < K:
        raise UserError(f"calibration.reference_imu: expected an IMU label 0..{K - 1}, got {ref!r}")
    means = np.full((K, 3), np.nan)
    covs = np.zeros((K, 3, 3))
    ori = np.full((K, 4), np.nan)
    for i, e in enumerate(imus):
        w = f"calibration.imus[{i}]"
        if not isinstance(e, dict):
            raise UserError(f"{w}: expected an object with imu, mean, std/cov")
        if e.get("imu") != i or isinstance(e.get("imu"), bool):
            raise UserError(f"{w}.imu: expected {i} (every IMU listed once, sorted by label), got {e.get('imu')!r}")
        if e.get("mean") is None:  # no accelerometer triad: writers put null moments
            continue
        means[i] = _numbers(e["mean"], (3,), f"{w}.mean", "3 finite numbers (m)")
        if e.get("cov") is not None:
            c = _numbers(e["cov"], (3, 3), f"{w}.cov", "a 3x3 matrix of finite numbers (m^2)")
            scale = max(float(np.abs(c).max()), 1e-300)
            if not np.allclose(c, c.T, rtol=1e-6, atol=1e-12 * scale) \
                    or np.linalg.eigvalsh(0.5 * (c + c.T)).min() < -1e-9 * scale:
                raise UserError(f"{w}.cov: expected a symmetric positive semi-definite 3x3 matrix (m^2)")
            covs[i] = 0.5 * (c + c.T)
        elif e.get("std") is not None:
            sd = _numbers(e["std"], (3,), f"{w}.std", "3 finite standard deviations >= 0 (m)")
            if (sd < 0).any():
                raise UserError(f"{w}.std: expected 3 finite standard deviations >= 0 (m)")
            covs[i] = np.diag(sd * sd)
        if e.get("orientation") is not None:
            q = _numbers(e["orientation"], (4,), f"{w}.orientation", "a quaternion (w, x, y, z) of 4 finite numbers")
            n = np.linalg.norm(q)
            if not 0.5 < n < 2.0:
                raise UserError(f"{w}.orientation: expected a unit quaternion (w, x, y, z), norm {n:.3g}")
            ori[i] = q / n
    doc["means"], doc["covs"], doc["orientations"] = means, covs, ori
    return doc


def read_positions(source) -> dict:
    """Read and check a positions document (DESIGN §7.3) from a path or a parsed dict.

    Returns the document with three extra numpy entries: ``means`` (K, 3) m (NaN rows for IMUs
    without an accelerometer), ``covs`` (K, 3, 3) m² (from ``cov``, else ``diag(std²)``, else 0) and
    ``orientations`` (K, 4) unit quaternions (NaN rows where none is given).  Raises
    :class:`UserError` naming the offending field (``calibration.imus[3].mean`` …), prefixed with the
    file name when read from a file; FileNotFoundError / IsADirectoryError for a bad path.
    """
    if isinstance(source, dict):
        return _parse(source)
    p = Path(source)
    if not p.exists():
        raise FileNotFoundError(f"{p}: no such calibration file")
    if p.is_dir():
        raise IsADirectoryError(f"{p}: is a directory; expected a positions.json file")
    try:
        doc = json.loads(p.read_text(encoding="utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise UserError(f"{p}: not valid JSON ({exc})") from None
    try:
        return _parse(doc)
    except UserError as exc:
        raise UserError(f"{p}: {exc}") from None

"""The mismatch report file, ``report.json`` (DESIGN §7.2 format v1): its schema name, the check of a
document against the contract, reading one (path, dict or report object) and writing one atomically.

The report itself — what :func:`accel_bayes.mismatch.detect` returns, its human report and figures —
is :class:`accel_bayes.mismatch.report.MismatchReport`; this module is the file format, next to the
other formats of ``data/``, so that what reads a report (the calibration's ``--model``, the export)
needs nothing from ``mismatch/``.
"""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ..errors import UserError
from ..physics.effects import EXTENSIONS, VOCABULARY

#: vocabulary-1.2 names the detector fits as terms beside the model, not as effects-library classes
#: (``unresolved_motion``: accel_bayes.mismatch.unresolved_stage)
TERMS = ("unresolved_motion",)
from .outputs import write_text

__all__ = ["SCHEMA", "validate_report", "read_report", "report_json", "write_report_json"]

SCHEMA = "accel_bayes.mismatch/1"


def report_json(doc: dict, indent: int = 1) -> str:
    """The report document as strict JSON text (no NaN or inf: the writer replaces them first)."""
    return json.dumps(doc, indent=indent, allow_nan=False)


def write_report_json(path, doc: dict) -> Path:
    """Write ``doc`` to ``path`` as ``report.json`` text, atomically; returns the path."""
    return write_text(path, report_json(doc) + "\n")


def read_report(source, field: str = "model") -> tuple[dict, str | None, str]:
    """(document, source path or None, sha256 hex) of a report given as a ``report.json`` path, a
    dict or an object with ``to_dict`` (a :class:`~accel_bayes.mismatch.report.MismatchReport`),
    checked against the contract (:func:`validate_report`).  ``field`` names the argument in the
    one-line :class:`UserError` a bad source gets.  The sha256 is of the file's bytes, or of the
    dict's sorted-key JSON."""
    if hasattr(source, "to_dict") and not isinstance(source, dict):
        source = source.to_dict()
    if isinstance(source, dict):
        blob = json.dumps(source, sort_keys=True, default=str).encode()
        doc, path, sha = source, None, hashlib.sha256(blob).hexdigest()
    elif not isinstance(source, (str, Path)):
        raise UserError(f"{field}: expected a report.json path, a report dict or None, got {type(source).__name__}")
    else:
        p = Path(source)
        try:
            blob = p.read_bytes()
        except OSError as exc:
            raise UserError(f"{field}: cannot read {p}: {exc.strerror or exc}") from None
        try:
            doc = json.loads(blob)
        except (ValueError, UnicodeDecodeError) as exc:
            raise UserError(f"{field}: {p} is not JSON ({exc})") from None
        path, sha = str(p), hashlib.sha256(blob).hexdigest()
    validate_report(doc)  # schema (format version) and vocabulary of every finding
    return doc, path, sha


def validate_report(doc: dict) -> None:
    """Raise :class:`~accel_bayes.errors.UserError` if ``doc`` breaks the DESIGN §7.2 contract."""
    def need(cond, msg):
        if not cond:
            raise UserError(f"mismatch report: {msg}")

    need(isinstance(doc, dict), "expected a JSON object")
    for k in ("schema", "mismatch_detected", "threshold", "baseline", "findings", "refined"):
        need(k in doc, f"missing key {k!r}")
    need(doc["schema"] == SCHEMA, f"schema is {doc['schema']!r}, expected {SCHEMA!r}")
    need(isinstance(doc["mismatch_detected"], bool), "mismatch_detected must be a bool")
    need(isinstance(doc["threshold"], (int, float)) and doc["threshold"] > 0, "threshold must be a positive number")
    b = doc["baseline"]
    need(isinstance(b, dict) and all(k in b for k in ("loglik", "chi2_per_dof", "dof")), "baseline needs loglik, chi2_per_dof, dof")
    need(isinstance(doc["findings"], list), "findings must be a list")
    need(doc["mismatch_detected"] == (len(doc["findings"]) > 0), "mismatch_detected must equal (findings non-empty)")
    for f in doc["findings"]:
        for k in ("effect", "imu", "axis", "evidence", "parameters", "where", "explanation"):
            need(k in f, f"finding missing key {k!r}")
        need(f["effect"] in VOCABULARY + EXTENSIONS + TERMS,
             f"unknown effect {f['effect']!r}; expected one of {VOCABULARY + EXTENSIONS + TERMS}")
        need(f["imu"] is None or isinstance(f["imu"], int), "finding imu must be an int label or null")
        need(f["axis"] in (None, "x", "y", "z"), "finding axis must be x, y, z or null")
        need(isinstance(f["where"], dict) and "regime" in f["where"] and "time_s" in f["where"],
             "finding where needs regime and time_s")
        need(isinstance(f["explanation"], str) and f["explanation"], "finding explanation must be a sentence")
        need(isinstance(f["parameters"], dict), "finding parameters must be an object")
    ev = [f["evidence"] for f in doc["findings"]]
    if doc["refined"] is None:
        need(True, "")
    else:
        r = doc["refined"]
        need(all(k in r for k in ("effects", "loglik", "chi2_per_dof")), "refined needs effects, loglik, chi2_per_dof")
    if not doc["mismatch_detected"]:
        need(doc["refined"] is None, "a clean report has refined = null")
    if "budget" in doc:  # vocabulary 1.1
        need(isinstance(doc["budget"], list), "budget must be a list")
        for r in doc["budget"]:
            need(isinstance(r, dict) and r.get("sensor") in ("acc", "gyro") and isinstance(r.get("regime"), str)
                 and isinstance(r.get("samples"), int) and all(k in r for k in ("excess_var_observed",
                                                                                  "excess_var_explained")),
                 "budget rows need sensor (acc|gyro), regime, samples, excess_var_observed, excess_var_explained")
    _ = ev

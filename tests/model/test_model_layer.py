"""What moved for the layering of issue #26 keeps working where it went: the report.json format in
``data/`` (read, check, write), the calibration that ``mismatch.detect(posterior=...)`` runs passed
in by the caller (``mismatch`` cannot import ``pipelines``)."""
import json

import pytest

from accel_bayes.data.mismatch_report import SCHEMA, read_report, validate_report, write_report_json
from accel_bayes.errors import UserError
from accel_bayes.mismatch import detect


def _clean_report() -> dict:
    return {"schema": SCHEMA, "mismatch_detected": False, "threshold": 12.5,
            "baseline": {"loglik": -10.0, "chi2_per_dof": 1.01, "dof": 300}, "findings": [], "refined": None}


def test_report_json_written_and_read_back(tmp_path):
    doc = _clean_report()
    path = write_report_json(tmp_path / "report.json", doc)
    assert json.loads(path.read_text(encoding="utf-8")) == doc
    got, source, sha = read_report(path)
    assert got == doc and source == str(path) and len(sha) == 64
    same, none, sha_dict = read_report(doc)
    assert same is doc and none is None and sha_dict != sha  # a dict's digest is of its sorted-key JSON


def test_report_refusals_name_the_field(tmp_path):
    bad = _clean_report() | {"schema": "accel_bayes.mismatch/0"}
    with pytest.raises(UserError, match="schema is 'accel_bayes.mismatch/0'"):
        validate_report(bad)
    with pytest.raises(UserError, match=r"^model: cannot read"):
        read_report(tmp_path / "missing.json")
    (tmp_path / "x.json").write_text("{", encoding="utf-8")
    with pytest.raises(UserError, match=r"^report: .* is not JSON"):
        read_report(tmp_path / "x.json", "report")
    with pytest.raises(UserError, match="^model: expected a report.json path"):
        read_report(3)


def test_detect_posterior_must_be_the_calibration_function():
    """posterior=True named the pipeline mismatch imported upward; now the caller passes it."""
    with pytest.raises(UserError, match=r"^posterior: expected False or the calibration function"):
        detect("no-such-recording.nc", posterior=True)

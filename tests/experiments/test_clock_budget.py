"""experiments/clock_budget.py's per-band rule (issue #27 "Must show"): b/a within 0.7–1.3, or where
the excess a is under 3 standard errors, |b − a| ≤ 3 standard errors — on a tiny synthetic budget."""
from __future__ import annotations

from experiments.clock_budget import band_ok, case_verdict

BANDS = ["all"] + [f"{q} {b}" for q in ("|omega|", "|omega_dot|") for b in ("0-25%", "25-50%", "50-75%", "75-90%", "90-100%")]


def _row(sensor, regime, a, b, se):
    return {"sensor": sensor, "regime": regime, "excess_var_observed": a, "excess_var_explained": b,
            "excess_var_observed_se": se}


def _table(changes=()):
    """Every band of both sensors at b/a = 1 with a far above its SE, then ``changes`` applied."""
    rows = {(s, g): _row(s, g, 1.0, 1.0, 0.01) for s in ("acc", "gyro") for g in BANDS}
    for (s, g), (a, b, se) in dict(changes).items():
        rows[s, g] = _row(s, g, a, b, se)
    return list(rows.values())


def test_ratio_rule_where_the_excess_is_resolved():
    assert band_ok(_row("acc", "x", 1.0, 0.71, 0.01))
    assert band_ok(_row("acc", "x", 1.0, 1.29, 0.01))
    assert not band_ok(_row("acc", "x", 1.0, 0.69, 0.01))
    assert not band_ok(_row("acc", "x", 1.0, 1.31, 0.01))
    # a just above 3 SE: the ratio rule decides, so b = 0 fails though |b − a| is only 3.3 SE;
    # with a just under 3 SE the same b passes on |b − a| ≤ 3 SE
    assert not band_ok(_row("gyro", "x", 1.0, 0.0, 0.3))
    assert band_ok(_row("gyro", "x", 1.0, 0.0, 0.34))


def test_se_rule_where_the_excess_is_under_three_standard_errors():
    # a = 0.1 ≤ 3·0.05: the ratio 5 would fail, |b − a| = 0.05 ≤ 0.15 passes
    assert band_ok(_row("acc", "x", 0.1, 0.15, 0.05))
    # same a and SE, |b − a| = 0.2 > 0.15 fails although b > 0
    assert not band_ok(_row("acc", "x", 0.1, 0.3, 0.05))
    # a negative excess (clean band) with b = 0 passes; with a large b it fails
    assert band_ok(_row("gyro", "x", -0.02, 0.0, 0.05))
    assert not band_ok(_row("gyro", "x", -0.02, 0.5, 0.05))


def test_case_verdict_names_the_failing_bands_and_ignores_all():
    v = case_verdict(_table())
    assert v["pass"] and v["acc"]["failing"] == [] and v["gyro"]["all_ratio"] == 1.0
    v = case_verdict(_table({("gyro", "|omega_dot| 90-100%"): (1.0, 0.5, 0.01),
                             ("acc", "all"): (1.0, 0.2, 0.01),            # "all" is reported, not a band
                             ("acc", "|omega| 0-25%"): (0.1, 0.4, 0.05)}))  # SE rule, |b − a| too big
    assert not v["pass"]
    assert v["gyro"]["failing"] == ["|omega_dot| 90-100%"]
    assert v["acc"]["failing"] == ["|omega| 0-25%"]
    assert abs(v["acc"]["all_ratio"] - 0.2) < 1e-12


def test_regenerating_the_document_keeps_its_reading(tmp_path):
    # the summary of the cached cases is rewritten, the hand-written reading below the marker is kept
    # (until 2026-11-29 every rerun dropped it)
    import shutil
    from pathlib import Path

    from experiments import clock_budget as cb
    from experiments._reading import READING_MARKER

    src = Path(cb.__file__).parent / "results" / "clock_budget"
    for name in ("clock-000.json", "clock-001.json"):
        shutil.copy(src / name, tmp_path / name)
    doc = tmp_path / "clock_budget.md"
    doc.write_text("old summary\n\n" + READING_MARKER + "\n## Reading\nkept words\n")
    cb.main(["--summary", "--out", str(tmp_path), "--n-clock", "2"])
    text = doc.read_text()
    assert "old summary" not in text and "# clock_budget" in text
    assert text.endswith(READING_MARKER + "\n## Reading\nkept words\n")

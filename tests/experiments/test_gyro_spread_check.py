"""``experiments/gyro_spread_check.py``: the before/now decision rule it reports (the stage's spread test
with the share alone, and with the direct test below the share), its table, and, on one recording, the
record against the stage's own decision."""
import pytest

from experiments import gyro_spread_check as gs


def _rec(share=None, stat=0.0, stat_thr=1.0, others=None, others_thr=1.0, **kw):
    r = {"set": "clock", "name": "x", "board": "b", "n": 4, "group": 10.0, "group_threshold": 1.0, **kw}
    if share is not None:
        r.update(share=share, spread_statistic=stat, spread_threshold=stat_thr)
    if others is not None:
        r.update(others=others, others_threshold=others_thr)
    return r


def test_decisions_before_and_now():
    assert gs.decisions({"n": 4, "group": 0.5, "group_threshold": 1.0}) == ("none", "none")
    assert gs.decisions(_rec(0.9, stat=5.0)) == ("fitted", "fitted")
    assert gs.decisions(_rec(0.9, stat=0.5)) == ("refused", "refused")  # the spread statistic refuses both
    assert gs.decisions(_rec(0.5, others=50.0)) == ("refused", "fitted")  # the direct test overrides the screen
    assert gs.decisions(_rec(0.5, others=0.5)) == ("refused", "refused")


def test_markdown_counts_and_lists_the_changed():
    sets = {"clock": [_rec(0.56, others=2.5e4, others_thr=79.0, name="clock-022"), _rec(0.9, stat=5.0),
                      {"set": "clock", "name": "c", "n": 4, "group": 0.5, "group_threshold": 1.0}],
            "proof": [_rec(0.1, others=40.0, others_thr=100.0, effect="gyro_bias", set="proof"),
                      _rec(0.2, others=80.0, others_thr=100.0, effect="gyro_scale", set="proof")]}
    text = "\n".join(gs.markdown(sets, "cmd"))
    assert "| clock | 3 | 2 | 1 | 0 (—) | 1 |" in text
    assert "| proof | 2 | 2 | 2 | 2 (0.80) | 0 |" in text
    assert "| clock | clock-022 | b | 4 | 0.560 | 2.5e+04 / 79 |" in text
    assert "gyro_bias 1, gyro_scale 1; every one refused" in text


def test_record_agrees_with_the_stage():
    # the script rebuilds the stage's tests outside it: on clock-022 (plate4, share 0.56) its record must
    # say what gyro_linear_stage does
    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.gyro_linear import gyro_linear_stage
    from experiments.clockgen import draw_case

    rec, _ = draw_case("clock", 22, duration=20.0)
    r = gs.spread_record(rec)
    prep = prepare(rec)
    st = gyro_linear_stage(prep, baseline_fit(prep)[0], m=r["m"], alpha=gs.ALPHA)
    assert gs.decisions(r)[1] == ("fitted" if st.blocks else "refused") == "fitted"
    assert r["share"] == pytest.approx(st.info["spread_share"], rel=1e-9)
    assert r["others"] == pytest.approx(st.info["others_statistic_robust"], rel=1e-9)

"""``experiments/clock_search_check.py``: its table on records made up here (the stage itself is
exercised by tests/mismatch/test_clock_candidates.py)."""
from experiments import clock_search_check as cs


def _row(name, accepted=(), evw=30.0, thr=40.0, n_imu=8, seconds=10.0):
    return {"set": "multi", "name": name, "board": "mimu8", "effect": "none", "accepted": list(accepted),
            "threshold": thr, "max_rejected_evw": evw, "n_imu": n_imu, "seconds": seconds}


def test_no_clock_means_the_proofs_stand():
    text = "\n".join(cs.markdown({"multi": ([_row("a"), _row("b", evw=36.0)], 2)}, "cmd"))
    assert "| multi | 2 | 0 | 16 | 0.90 | 10.0 |" in text
    assert "No clock accepted on any recording" in text and "Partial" not in text


def test_a_false_clock_and_a_partial_set_are_said():
    clk = {"imu": 3, "beat_mid_hz": -0.25, "evidence": 80.0, "evidence_vs_wander": 55.0, "width_ms": 1.0}
    text = "\n".join(cs.markdown({"proof": ([_row("x/twin", accepted=[clk])], 5)}, "cmd"))
    assert "**Partial: proof 1 of 5 recordings**" in text
    assert "| multi | x/twin | mimu8 | none | 3 | -0.250 | 55.0 / 40.0 |" in text
    assert cs._path("multi", "x/twin").name == "x__twin.json"

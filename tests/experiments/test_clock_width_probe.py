"""``experiments/clock_width_probe.py``: the width bound it changes is restored, and its table."""
import accel_bayes.mismatch.clock as clock
from experiments import clock_width_probe as cw


def test_width_bound_is_set_and_restored():
    before = clock.WIDTH_RANGE_S
    with cw.width_bound(0.3e-3):
        assert clock.WIDTH_RANGE_S == (0.3e-3, before[1])
    assert clock.WIDTH_RANGE_S == before
    with cw.width_bound(None):
        assert clock.WIDTH_RANGE_S == before


def test_markdown_reads_both_variants():
    def row(acc, fd, w):
        return {"clocks": [0, 1] + ([2] if acc else []), "threshold": 51.4, "filter_delay_s": fd, "findings": ["unexplained[2]"],
                "imu2": {"beat_mid_hz": -0.377, "width_s": w, "evidence": 6337.0, "evidence_vs_wander": 175.0, "accepted": acc},
                "own": {"acc": 0.846, "gyro": 0.896}, "own_bands": {"acc": [0.81, 0.92], "gyro": [0.87, 0.92]},
                "borrowed": {"acc": 0.652, "gyro": 0.721}, "borrowed_bands": {"acc": [0.48, 0.93], "gyro": [0.55, 0.86]},
                "source": 6}
    text = "\n".join(cw.markdown({"default": row(False, -1.04e-4, 3.6e-4), "low": row(True, 1.299e-3, 3.4e-4)}, "cmd", 0.3))
    assert "| clocks accepted (IMUs) | [0, 1] | [0, 1, 2] |" in text
    assert "-0.104 ms | +1.299 ms |" in text
    assert "0.36 ms, 6337 / 175 (51.4), rejected" in text and "0.34 ms" in text
    assert "| budget, scales from exp 6: acc (must ≥ 0.8) | 0.652 (0.48–0.93) |" in text


def test_invocation_names_the_script_and_its_arguments():
    from experiments._stamp import invocation

    assert invocation("clock_width_probe.py", ["--concealed", "--jobs", "2"]) == (
        "PYTHONPATH=. OMP_NUM_THREADS=1 nice -n 5 python3 experiments/clock_width_probe.py --concealed --jobs 2")
    assert invocation("clock_width_probe.py", []).endswith("experiments/clock_width_probe.py")

"""The oracle clocks of ``experiments/clock020_oracle.py``: the truth clock fitted from the generator's
data ages is the vocabulary's sawtooth of those ages (so the oracle calibrations load the true ages),
and the oracle reports change only the ``sampling_clock`` findings they say they change."""
import numpy as np
import torch

from accel_bayes.data.mismatch_report import SCHEMA, read_report
from accel_bayes.physics.effects.clock import clock_age
from experiments import clock020_oracle as co
from experiments.clockgen import draw_case


def test_truth_clock_reproduces_the_generators_data_age():
    rec, truth = draw_case("clock", 20, duration=4.0)
    t = np.asarray(rec.time, dtype=np.float64)
    for k in range(rec.K):
        p = co.truth_clock(truth, t, k)
        assert abs(p["beat_hz"] - truth["clock"]["beat_frequency"][k]) < 2e-3
        age = clock_age(torch.as_tensor(t), p["beat_hz"], p["phase"], p["drift_hz_per_s"],
                        1.0 / p["internal_rate_hz"]).numpy()
        # compared on the circle of one tick: a read within the jitter of a tick wraps to the other end
        w = 1.0 / p["internal_rate_hz"]
        d = (age - truth["data_age"][:, k] + 0.5 * w) % w - 0.5 * w
        # the read jitter (≤ 30 µs in clockgen) is all that is left
        assert np.sqrt(np.mean(d ** 2)) < 30e-6 and np.sqrt(np.mean(d ** 2)) < 0.1 * w


def _report(clocked):
    f = lambda k: {"effect": "sampling_clock", "imu": k, "axis": None, "evidence": 100.0,  # noqa: E731
                   "where": {"regime": "all regimes", "time_s": None}, "explanation": "x",
                   "parameters": {"internal_rate_hz": 1000.0, "beat_hz": 1.0, "phase": 0.1, "drift_hz_per_s": 0.0,
                                  "age_rms_s": 2.9e-4, "filter_delay_acc_minus_gyro_s": -1e-4, "rate_scale": 0.9}}
    return {"schema": SCHEMA, "mismatch_detected": True,
            "threshold": 20.0, "baseline": {"loglik": 0.0, "chi2_per_dof": 1.0, "dof": 1},
            "findings": [f(k) for k in clocked], "refined": {"effects": [], "loglik": 0.0, "chi2_per_dof": 1.0}}


def test_oracle_reports_change_only_the_clocks_they_name():
    rec, truth = draw_case("clock", 20, duration=4.0)
    t = np.asarray(rec.time, dtype=np.float64)
    rep = _report([1, 3, 4, 5])
    a = co.variant_report(rep, truth, t, "a_report")
    assert a == rep and a is not rep
    b = co.variant_report(rep, truth, t, "b_oracle_0_2")
    clocks = {f["imu"]: f["parameters"] for f in b["findings"]}
    assert sorted(clocks) == list(range(6))
    for k in (1, 3, 4, 5):  # the report's own clocks untouched
        assert clocks[k] == rep["findings"][[1, 3, 4, 5].index(k)]["parameters"]
    for k in (0, 2):  # the truth's, with the report's shared delay and regressor scale
        assert abs(clocks[k]["beat_hz"] - truth["clock"]["beat_frequency"][k]) < 2e-3
        assert clocks[k]["filter_delay_acc_minus_gyro_s"] == -1e-4 and clocks[k]["rate_scale"] == 0.9
    d = co.variant_report(rep, truth, t, "d_oracle_acc_timing")
    for f in d["findings"]:
        assert abs(f["parameters"]["filter_delay_acc_minus_gyro_s"] - co.true_acc_delay(truth, f["imu"])) < 1e-15
    for doc in (b, d):
        read_report(doc, "model")  # a valid report


def test_impact_windows_drop_every_impact_sample_and_little_else():
    from experiments.clockgen.cases import motion_of

    rec, truth = draw_case("clock", 20, duration=20.0, noise=False)
    keep = co.impact_windows(rec, truth)
    t = np.asarray(rec.time, dtype=np.float64)
    burst = np.abs(motion_of(truth).rot_imp(t)).sum(1)
    assert (burst[keep] == 0).all() and (burst[~keep] > 0).sum() > 0.5 * (~keep).sum()
    assert (~keep).sum() < 0.1 * keep.size

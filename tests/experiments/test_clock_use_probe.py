"""``experiments/clock_use_probe.py``: its report variants change only the clocks they name, its switch
of the clocks' mean correction is the identity only inside its block, and its table pools what it says."""
import numpy as np
import torch

import accel_bayes.model.report_terms as rt
from experiments import clock_use_probe as cu
from experiments.clockgen import draw_case
from tests.experiments.test_clock020_oracle import _report


def test_variant_reports():
    rec, truth = draw_case("clock", 20, duration=4.0)
    t = np.asarray(rec.time, dtype=np.float64)
    rep = _report([1, 3, 4, 5])
    rep["findings"].append({"effect": "unresolved_motion", "imu": None, "parameters": {"x": 1}})
    assert cu.variant_report(rep, truth, t, "report") == rep
    assert cu.variant_report(rep, truth, t, "report_ie") == rep
    assert cu.variant_report(rep, truth, t, "no_mean") == rep
    nc = cu.variant_report(rep, truth, t, "no_clock")
    assert [f["effect"] for f in nc["findings"]] == ["unresolved_motion"]
    assert len(rep["findings"]) == 5  # the input untouched
    t0 = cu.variant_report(rep, truth, t, "true_0_ie")
    clocks = {f["imu"]: f["parameters"] for f in t0["findings"] if f["effect"] == "sampling_clock"}
    assert sorted(clocks) == list(range(6))
    assert clocks[1] == rep["findings"][0]["parameters"]  # the report's own clock kept
    for k in (0, 2):
        assert abs(clocks[k]["beat_hz"] - truth["clock"]["beat_frequency"][k]) < 2e-3
    ta = cu.variant_report(rep, truth, t, "true_all")
    for f in ta["findings"]:
        if f["effect"] == "sampling_clock":
            assert abs(f["parameters"]["beat_hz"] - truth["clock"]["beat_frequency"][f["imu"]]) < 2e-3


def test_clock_mean_switch_is_scoped():
    acc, gyro = torch.ones(5, 2, 3), torch.ones(5, 2, 3)
    time = torch.arange(5.0) * 0.01
    age = torch.full((5, 2), 1e-3)
    acc_rate = torch.arange(5.0)[:, None, None] * torch.ones(5, 2, 3)
    orig = rt.clock_corrected
    with cu.clock_mean(False):
        a, g = rt.clock_corrected(acc + acc_rate, gyro, time, age, age)
        assert torch.equal(a, acc + acc_rate) and torch.equal(g, gyro)
    assert rt.clock_corrected is orig
    a, _ = rt.clock_corrected(acc + acc_rate, gyro, time, age, age)
    assert not torch.equal(a, acc + acc_rate)  # the real correction moves a ramp


def test_table_pools_every_coordinate():
    cases = {s: {v: {"z": [0.5 * (s + 1), -5.0 if (s, v) == (1, "no_mean") else 1.0], "coordinates": ["a", "b"],
                     "seconds": 10.0} for v in cu.VARIANTS} for s in (0, 1)}
    L = cu.markdown(cases, {}, "cmd", 1.0)
    pooled = next(x for x in L if x.startswith("| **pooled**"))
    # report: z = 0.5, 1, 1, 1 -> RMS sqrt(3.25/4); no_mean: 0.5, 1, 1, -5 -> max 5, one beyond 4
    assert f"**{np.sqrt(3.25 / 4):.2f} / 1.00**, 0/4" in pooled
    assert "**{:.2f} / 5.00**, 1/4".format(np.sqrt((0.25 + 1 + 1 + 25) / 4)) in pooled

"""``experiments/acc_stage_budget.py``: the blocks read back from a report, and its document's counts against
hand counts on made-up records."""
import numpy as np

from experiments import acc_stage_budget as asb
from experiments.clock_budget import case_verdict


def test_stage_blocks_reads_only_the_three_by_three_findings():
    scale = [[0.01, 0.0, 0.002], [0.0, -0.004, 0.0], [0.003, 0.0, 0.0]]
    doc = {"findings": [{"effect": "acc_scale", "imu": 2, "axis": None, "parameters": {"scale": scale, "bias": [0.1, 0, -0.2]}},
                        {"effect": "acc_scale", "imu": 0, "axis": 1, "parameters": {"scale": 0.01}},  # one-axis term: not a block
                        {"effect": "gyro_scale", "imu": 1, "axis": None, "parameters": {"scale": scale, "bias": [0, 0, 0]}}]}
    A, b, imus = asb.stage_blocks(doc, 4)
    assert imus == [2]
    np.testing.assert_allclose(A[2], np.eye(3) + np.asarray(scale))
    np.testing.assert_allclose(b[2], [0.1, 0, -0.2])
    np.testing.assert_array_equal(A[[0, 1, 3]], np.eye(3)[None].repeat(3, 0))
    assert not b[[0, 1, 3]].any()


def _band(sensor, regime, a, b, se):
    return {"sensor": sensor, "regime": regime, "excess_var_observed": a, "excess_var_explained": b,
            "excess_var_observed_se": se}


def _record(seed, budget, blocks=None, seconds=40.0):
    return {"seed": seed, "board": "cube6", "f_host": 125.0, "seconds": seconds, "findings": [],
            "budget": budget, "acc_blocks": blocks, "verdict": case_verdict(budget)}


def test_document_counts_blocks_and_failing_directions():
    base_budget = [_band("acc", "all", 1.0, 0.8, 0.01), _band("acc", "w1", 1.0, 0.5, 0.01), _band("acc", "w2", 1.0, 1.0, 0.01),
                   _band("gyro", "all", 1.0, 1.0, 0.01), _band("gyro", "w1", 1.0, 1.0, 0.01)]
    new_budget = [_band("acc", "all", 1.0, 1.1, 0.01), _band("acc", "w1", 1.0, 1.5, 0.01), _band("acc", "w2", 0.01, 0.2, 0.01),
                  _band("gyro", "all", 1.0, 1.0, 0.01), _band("gyro", "w1", 1.0, 0.6, 0.01)]
    err = {"output_error_before_rms": 0.1, "output_error_after_rms": 0.05,
           "identifiable_error_before_rms": 0.09, "identifiable_error_after_rms": 0.02}
    rows = [(_record(0, base_budget), _record(0, new_budget, {"imus": [0, 1, 2], "A": [0] * 3, **err})),
            (_record(1, base_budget), _record(1, new_budget, {"imus": [1], "A": [0] * 4, **err}))]
    L = "\n".join(asb.markdown(rows, "cmd", 1.0))
    assert "kept blocks on 4 of 7 triads (1 of 2 cases on every triad)" in L
    assert "less the triads' mean 0.1000 → 0.0500" in L and "0.0900 → 0.0200" in L
    # per case: baseline w1 low; stage w1 high and w2 small-a with |b − a| = 0.19 > 0.03; gyro w1 low in the stage
    assert "b/a < 0.7 2 → 0, b/a > 1.3 0 → 2, a ≤ 3 SE with |b − a| > 3 SE 0 → 2. Gyro: 0/0/0 → 2/0/0." in L
    assert "## `acc_stage`" in L and "| clock-001 | cube6 | 125 |" in L

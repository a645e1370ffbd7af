"""``experiments/saturation_guard_probe.py``: a clip's reach against hand counts on made-up outputs, and the rule."""
from types import SimpleNamespace

import numpy as np
import torch

from experiments import saturation_guard_probe as sg


class _Rep:
    def __init__(self, prep, findings):
        self.prep, self._f = prep, findings

    def to_dict(self):
        return {"findings": self._f}


def _prep(y_acc, sigma):
    T, K, _ = y_acc.shape
    return SimpleNamespace(y_acc=torch.as_tensor(y_acc), y_gyro=torch.zeros(T, K, 3),
                           sigma_acc=torch.as_tensor(sigma), sigma_gyro=torch.full((K,), 1e-3))


def test_a_true_clip_reaches_its_limit_and_a_cut_peak_does_not():
    rng = np.random.default_rng(0)
    y = rng.normal(0.0, 5.0, (400, 2, 3))
    y[:, 0, 1] = np.clip(y[:, 0, 1], -6.0, 6.0)  # IMU 0's y clips at ±6
    sat = lambda k, axis, L: {"effect": "saturation", "imu": k, "axis": axis, "sensor": "acc",  # noqa: E731
                              "parameters": {"limit": L}}
    rep = _Rep(_prep(y, np.array([0.02, 0.02])), [sat(0, "y", 6.0), sat(1, "z", np.abs(y[:, 1, 2]).max() + 0.5),
                                                    {"effect": "acc_bias", "imu": 0, "axis": "x"}])
    true_clip, cut_peak = sg.clip_findings(rep)
    assert true_clip["max_abs"] == 6.0 and true_clip["reach_sigmas"] == 0.0
    assert true_clip["at_limit"] == int((np.abs(y[:, 0, 1]) >= 6.0 - 5 * 0.02).sum()) > 10
    assert abs(cut_peak["reach_sigmas"] - (-0.5 / 0.02)) < 1e-9 and cut_peak["at_limit"] == 0
    assert not sg.refused(true_clip) and sg.refused(cut_peak)
    # one peak cut exactly at its own value: reached, but by one output only
    assert sg.refused({**true_clip, "reach_sigmas": 0.0, "at_limit": 1})
    gone = {"candidate": "saturation[imu=1,axis=z,sensor=acc]", "at_limit": 0, "why": "0 ... of its limit"}
    L = "\n".join(sg.markdown([{"case": "c", "truth": "clips", "clips": [true_clip]},
                               {"case": "d", "truth": "no clipping", "clips": [cut_peak]},
                               {"case": "e", "truth": "no clipping", "clips": [], "refused": [gone]}], "cmd", 1.0))
    assert "**clips**: 1 detections, 1 saturation findings, the rule refuses 0; refits the detector refused by it: 0." in L
    assert "**no clipping**: 2 detections, 1 saturation findings, the rule refuses 1; refits the detector refused by it: 1." in L
    assert "| -25.0 | 0/400 | refuse |" in L
    assert "| e | no clipping | none (refused: saturation[imu=1,axis=z,sensor=acc] (0 at L)) |" in L


def test_the_probe_counts_with_the_detectors_constants():
    from accel_bayes.mismatch.choose import SATURATION_AT_LIMIT

    assert (sg.AT_LIMIT_SIGMAS, sg.MIN_AT_LIMIT) == SATURATION_AT_LIMIT


def test_guard_refusals_reads_the_rounds():
    rounds = [{"refits": [{"candidate": "saturation[imu=1,axis=z,sensor=acc]", "outputs_at_limit": 1},
                          {"candidate": "acc_bias[imu=1,axis=z]"}],
               "refused": [{"candidate": "saturation[imu=1,axis=z,sensor=acc]", "why": "1 recorded output(s) within 5 σ of its limit ±3"},
                           {"candidate": "acc_bias[imu=1,axis=z]", "why": "its parameter is not constant"}]}]
    out = sg.guard_refusals(SimpleNamespace(rounds=rounds))
    assert out == [{"candidate": "saturation[imu=1,axis=z,sensor=acc]", "at_limit": 1,
                    "why": "1 recorded output(s) within 5 σ of its limit ±3"}]

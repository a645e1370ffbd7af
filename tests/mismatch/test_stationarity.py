"""The stationarity guard of the detector's rounds (accel_bayes.mismatch.screens.stationarity): a
constant-parameter effect whose parameter the data want different in different parts of the
recording is refused.  Data from the independent generator ``experiments/_conceal.py``."""
from __future__ import annotations


import pytest
import torch
from scipy.stats import chi2

from experiments import _conceal as C

from accel_bayes.mismatch import detect
from accel_bayes.mismatch.screens import STATIONARITY_SEGMENTS, stationarity  # noqa: E402
from accel_bayes.mismatch.fit import baseline_fit, fit_model  # noqa: E402
from accel_bayes.mismatch.prepared import prepare  # noqa: E402
from accel_bayes.physics.effects import make_effect  # noqa: E402


def _fit(case, effect):
    torch.set_num_threads(1)
    prep = prepare(case.recording)
    base = baseline_fit(prep)[0]
    return prep, fit_model(prep, [effect], init=base, laplace=False)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_constant_effect_passes(seed):
    """The true effect fitted on its own concealed recording (a constant misalignment, a constant
    bias): Q is a χ²_{4d} draw — below its 99.9 % point on every seed (Q measured 0.9–5.7, df 4)."""
    for name, make in (("acc_misalignment", lambda c: make_effect(
            "acc_misalignment", imu=c.truth["imu"], axis=c.truth["axis"],
            from_axis=c.truth["parameters"]["from_axis"])),
            ("acc_bias", lambda c: make_effect("acc_bias", imu=c.truth["imu"], axis=c.truth["axis"]))):
        case = C.make_case("mimu8", name, seed=seed, T=1500)
        prep, fit = _fit(case, make(case))
        q, df = stationarity(prep, fit, fit.effects[-1])
        assert df == (STATIONARITY_SEGMENTS - 1) * fit.effects[-1].df
        assert q < chi2.isf(1e-3, df), (name, seed, q)


def test_a_drifting_bias_fitted_as_a_constant_one_is_not_stationary():
    """A bias drifting linearly (±0.07 m/s² on IMU 2's y axis) fitted as a constant acc_bias: the
    early segments want it negative, the late ones positive — Q far above any threshold (measured 2868)."""
    case = C.make_case("mimu8", "acc_drift", seed=0)
    k, ax = case.truth["imu"], case.truth["axis"]
    prep, fit = _fit(case, make_effect("acc_bias", imu=k, axis=ax))
    q, df = stationarity(prep, fit, fit.effects[-1])
    assert q > 10 * chi2.isf(1e-6, df), q


def test_detect_names_no_vocabulary_effect_on_a_drifting_accelerometer():
    """characterise_proof's acc_drift seed 7: before the guard an acc_misalignment (evidence 216)
    was named on the drifting IMU; now the drift is an ``unexplained`` finding scaling with time,
    and the refused candidate says why."""
    case = C.make_case("mimu8", "acc_drift", seed=7)
    k = case.truth["imu"]
    doc = detect(case.recording, seed=0).to_dict()
    from accel_bayes.physics.effects import VOCABULARY

    vocab = [f for f in doc["findings"] if f["effect"] in VOCABULARY and f["effect"] != "unexplained"
             and f["imu"] == k]
    assert not vocab, vocab
    un = [f for f in doc["findings"] if f["effect"] == "unexplained" and f["imu"] == k]
    assert un and un[0]["parameters"]["scales_with"] == "time"
    refused = [x for r in doc["details"]["rounds"] for x in r.get("refused", [])]
    assert any("not constant" in x["why"] for x in refused), refused

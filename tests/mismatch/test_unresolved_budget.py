"""``unresolved_motion`` in the detector's §7.2 budget (issue #27 item 3,
accel_bayes/mismatch/unresolved_stage.py).

Before this stage the budget had no unresolved term: on a concealed case whose board vibrates
above the read's Nyquist rate, b left the aliased vibration's whole variance unexplained.  Here
the stage is given each IMU's true data age (a clock known exactly: the test is of the term and
the budget, not of the beat search), the clocks' mean effect is taken off as the detector's clock
stage does, and the budget with the stage's term must explain a large share of the excess in
every |ω| band — far more than on the same case without vibration.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from accel_bayes.mismatch.budget import residual_budget
from accel_bayes.mismatch.unresolved_stage import unresolved_stage
from tests.mismatch._true_clocks import true_clock_case


def _budget(vibration: bool):
    prep, fit, _, clocks = true_clock_case(vibration=vibration)
    st = unresolved_stage(prep, fit, clocks, threshold=24.0, alpha=0.01, m=400, n_permutations=5, seed=0)
    without = residual_budget(prep, fit, fit)
    with_term = residual_budget(prep, fit, fit, extra=[st.effect] if st.effect is not None else [])
    return st, without, with_term


def _omega_rows(rows, sensor):
    return [r for r in rows if r["sensor"] == sensor and r["regime"].startswith("|omega| ")]


@pytest.fixture(scope="module")
def vibrating():
    return _budget(True)


def test_budget_b_rises_by_the_unresolved_term_where_the_board_vibrates(vibrating):
    st, without, with_term = vibrating
    assert st.effect is not None and set(st.info["kept"]) == {"acc", "gyro"}
    for sensor in ("acc", "gyro"):
        for r0, r1 in zip(_omega_rows(without, sensor), _omega_rows(with_term, sensor)):
            assert r0["excess_var_explained"] == 0.0  # the model without the term names none of it
            # the term names a large share of the aliased vibration's excess in every |ω| band
            assert r1["excess_var_explained"] > 0.2 * r1["excess_var_observed"] > 0, (sensor, r1)
            assert r1["excess_var_explained"] < 1.3 * r1["excess_var_observed"], (sensor, r1)


def test_the_term_is_far_smaller_without_vibration(vibrating):
    st_v, _, with_v = vibrating
    st_q, _, with_q = _budget(False)
    b_v = next(r for r in with_v if r["sensor"] == "acc" and r["regime"] == "all")["excess_var_explained"]
    b_q = next((r for r in with_q if r["sensor"] == "acc" and r["regime"] == "all"))["excess_var_explained"]
    assert b_q < 0.1 * b_v, (b_q, b_v)
    jv = st_v.info["sensors"]["acc"]["jerk_rms"]
    jq = st_q.info["sensors"]["acc"]["jerk_rms"]
    assert np.median(jq) < 0.3 * np.median(jv), (jq, jv)


@pytest.mark.parametrize("broken", ["age_error", "both"])
def test_a_failed_scale_fit_is_never_reported(monkeypatch, broken):
    """A concealed clock case (clockgen clock-004 through the whole detector) gave an
    ``unresolved_motion`` finding listing the accelerometers with every ``jerk_rms`` null: the fit
    with the age error had failed (NaN) and was kept, and ``calibrate --model`` refused the report.
    A failed fit falls back to the other one; with both failed the sensor is not kept."""
    import math

    import accel_bayes.mismatch.unresolved_stage as us

    real = us.fit_grid

    def failing(*a, **k):
        g = real(*a, **k)
        nan = torch.full_like(g.s2, float("nan"))
        g = dataclasses.replace(g, s2=nan, loglik=float("nan"), e2=float("nan"))
        if broken == "both":
            g = dataclasses.replace(g, s2_no_age_error=nan, loglik_no_age_error=float("nan"))
        return g

    monkeypatch.setattr(us, "fit_grid", failing)
    st, _, _ = _budget(True)
    for s in ("acc", "gyro"):
        info = st.info["sensors"][s]
        if broken == "both":
            assert s not in st.info["kept"] and not info["kept"] and "non-finite" in info["why"]
        else:
            assert s in st.info["kept"] and info["age_error_kept"] is False
            assert all(math.isfinite(v) for v in info["jerk_rms" if s == "acc" else "angular_acc_rms"])
    if broken == "both":
        assert st.effect is None
    else:
        p = st.effect.vocabulary_parameters()
        assert all(math.isfinite(v) for v in p["jerk_rms"] + p["angular_acc_rms"])

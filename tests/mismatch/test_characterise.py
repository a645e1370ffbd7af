"""The characteriser of what a fit leaves unexplained (accel_bayes.mismatch.characterise).

Its statistics against series with known answers (power law, AR(1) autocorrelation, gaps,
timing-like anisotropy), and end to end on the independent generator's recordings
(experiments/_conceal.py): a low-pass filter on one gyro — physics outside the vocabulary — is
described as growing with the gyro's own rate of change, correlated in time and along the rate.
"""
from __future__ import annotations

import math

import numpy as np
import pytest


from accel_bayes.mismatch.characterise import (COVARIATES, _anisotropy, _autocorrelation, _consecutive,  # noqa: E402
                                               _covariate_stats, characterise, describe)


def test_covariate_power_law_and_ranking():
    rng = np.random.default_rng(0)
    n = 20000
    c = rng.uniform(5.0, 50.0, n)
    other = rng.uniform(0.0, 1.0, n)
    # per-sample excess power of a triad: mean of 3 squared N(0, c²) residuals → E = c²
    e = (c[:, None] * rng.standard_normal((n, 3))) ** 2
    e = e.mean(1)
    st = _covariate_stats(e, c)
    so = _covariate_stats(e, other)
    # E[z²] ∝ c² exactly, so the quintile slope is 2 up to sampling error (SE ≈ 0.02 here)
    assert abs(st["power"] - 2.0) < 0.1
    assert st["F"] > 50 * so["F"]
    assert so["log10_p"] > -4  # no dependence on an unrelated covariate (p > 1e-4)
    assert st["log10_p"] < -50
    # quintile means rise monotonically
    assert np.all(np.diff(st["quintile_mean_z2"]) > 0)


def test_autocorrelation_ar1_and_white():
    rng = np.random.default_rng(1)
    T, rho = 20000, 0.7
    z = np.empty((T, 3))
    z[0] = rng.standard_normal(3)
    for t in range(1, T):
        z[t] = rho * z[t - 1] + math.sqrt(1 - rho ** 2) * rng.standard_normal(3)
    nb = _consecutive(np.arange(T) * 0.01)
    ac = _autocorrelation(z, nb)
    # SE of ρ̂₁ ≈ √((1 − ρ²)/n)/√3 channels ≈ 0.003; tolerances 10 SE
    assert abs(ac["lag1"] - rho) < 0.03
    assert abs(ac["lag2"] - rho ** 2) < 0.04
    w = rng.standard_normal((T, 3))
    aw = _autocorrelation(w, nb)
    assert abs(aw["z_lag1"]) < 4  # √n·ρ₁ ~ N(0, 1/3)-ish averaged over channels


def test_autocorrelation_skips_selection_gaps():
    """Pairs across a gap are not neighbours: make them identical and the within-run pairs
    independent — the lag-1 estimate must stay near 0."""
    rng = np.random.default_rng(2)
    n_runs = 5000
    t = np.concatenate([[10.0 * j, 10.0 * j + 0.01] for j in range(n_runs)])  # runs of two, gaps of ~10 s
    z = rng.standard_normal((2 * n_runs, 3))
    z[2::2] = z[1:-1:2]  # the first sample of each run repeats the last of the previous run
    nb = _consecutive(t)
    assert nb.sum() == n_runs  # only the within-run pairs (the median step is the in-run one)
    ac = _autocorrelation(z, nb)
    assert abs(ac["lag1"]) < 0.05
    # …and treating every pair as consecutive would have seen the repeats
    assert _autocorrelation(z, np.ones(len(t) - 1, bool))["lag1"] > 0.3


def test_anisotropy_timing_vs_isotropic():
    rng = np.random.default_rng(3)
    n = 20000
    rate = rng.standard_normal((n, 3)) * rng.uniform(0.5, 2.0, (n, 1))
    u = rate / np.linalg.norm(rate, axis=1, keepdims=True)
    iso = rng.standard_normal((n, 3))
    timing = iso + u * 3.0 * rng.standard_normal((n, 1))  # extra variance 9 along the rate only
    assert abs(_anisotropy(iso, rate) - 1.0) < 0.1
    assert abs(_anisotropy(timing, rate) - 10.0) < 1.0


@pytest.fixture(scope="module")
def lowpass_fit():
    import torch

    from experiments import _conceal as C
    from accel_bayes.mismatch import baseline_fit, prepare

    torch.set_num_threads(1)
    case = C.make_case("mimu8", "gyro_lowpass", seed=3, T=1500)
    prep = prepare(case.recording)
    base, _ = baseline_fit(prep)
    clean = C.make_case("mimu8", "none", seed=3, T=1500)
    prep0 = prepare(clean.recording)
    base0, _ = baseline_fit(prep0)
    return case, prep, base, prep0, base0


def test_characterise_lowpass_gyro_end_to_end(lowpass_fit):
    case, prep, base, _, _ = lowpass_fit
    k = case.truth["imu"]
    c = characterise(prep, base)
    g = c["gyro"]
    shares = {r["imu"]: r["share"] for r in g["imus"]}
    assert max(shares, key=shares.get) == k
    imu = next(r for r in g["imus"] if r["imu"] == k)
    assert imu["top_covariate"] in ("|output rate|", "|omega_dot|")
    assert imu["autocorrelation"]["lag1"] > 0.3   # a filter's error is smooth in time
    assert imu["anisotropy"] > 2.0                # and lies along the rate of change
    assert {row["name"] for row in imu["covariates"]} <= set(COVARIATES)
    s = describe(g, "gyro", k)
    assert f"IMU {k}'s gyroscope" in s and imu["top_covariate"] in s


def test_characterise_clean_recording_has_no_excess(lowpass_fit):
    _, _, _, prep0, base0 = lowpass_fit
    c = characterise(prep0, base0)
    for sensor in ("acc", "gyro"):
        # mean z² − 1 over ~1500·8·3 leverage-corrected residuals: SE ≈ √(2/36000) ≈ 0.008
        assert abs(c[sensor]["excess"]) < 0.05
        assert isinstance(c[sensor]["summary"], str) and c[sensor]["summary"]


def test_characterise_coupling_on_a_clean_recording(lowpass_fit):
    """``coupling=True`` adds the accelerometers' aliased-jerk fit; on a clean recording its
    permutation test does not call it significant, and the sentence says so or leaves it out."""
    _, _, _, prep0, base0 = lowpass_fit
    c = characterise(prep0, base0, coupling=True)
    aj = c["acc"]["aliased_jerk"]
    assert aj is not None and aj["permutation"]["n"] == 19
    assert aj["permutation"]["p_value"] > 0.05
    assert "aliased" not in c["acc"]["summary"] or "not significant" in c["acc"]["summary"]
    assert "aliased_jerk" not in characterise(prep0, base0)["acc"]


def test_gyro_delay_is_a_first_order_lowpass():
    """The extension gyro_delay (−delay·dω/dt on one IMU's gyro) against the independent
    generator's exact first-order low-pass filter (τ ẏ = ω − y solved on the continuous
    trajectory): with delay = τ they agree to the filter's second-order term."""
    import torch

    from experiments import _conceal as C
    from accel_bayes.physics.effects import SignalContext, make_effect

    lp = C.make_case("mimu8", "gyro_lowpass", seed=4, T=1200)
    clean = C.make_case("mimu8", "none", seed=4, T=1200)
    k, tau = lp.truth["imu"], lp.truth["parameters"]["time_constant"]
    t = np.asarray(lp.recording.time)
    rate = np.gradient(clean.clean_gyro, t, axis=0)  # d/dt of the unfiltered gyro outputs
    T_, K = clean.clean_gyro.shape[:2]
    z = torch.zeros(T_, 3, dtype=torch.float64)
    ctx = SignalContext(torch.as_tensor(t), z, z, z, torch.zeros(K, 3, dtype=torch.float64),
                        torch.tensor([[1.0, 0, 0, 0]] * K, dtype=torch.float64),
                        torch.as_tensor(clean.clean_acc), torch.as_tensor(clean.clean_gyro),
                        torch.zeros(T_, K, 3, dtype=torch.float64), torch.as_tensor(rate))
    eff = make_effect("gyro_delay", imu=k, parameters={"delay": tau})
    d_acc, d_gyro = eff.perturbation(None, ctx)
    truth = lp.clean_gyro - clean.clean_gyro
    assert float(d_acc.abs().max()) == 0.0
    assert np.allclose(d_gyro.numpy()[:, [j for j in range(K) if j != k]], 0.0)
    err = np.sqrt(((d_gyro.numpy()[:, k] - truth[:, k]) ** 2).mean()) / np.sqrt((truth[:, k] ** 2).mean())
    assert err < 0.05, err  # measured 1.4 % (τ² d²ω/dt² and the finite-difference rate)


def test_noise_level_refused_for_a_structured_excess():
    from accel_bayes.mismatch.choose import HETEROSCEDASTIC_RATIO, heteroscedastic as _heteroscedastic
    from accel_bayes.physics.effects import make_effect

    def char(q, log10_p):
        row = {"name": "|output rate|", "quintile_mean_z2": q, "log10_p": log10_p, "F": 10.0, "eta2": 0.1, "power": 1.0}
        flat = {**row, "quintile_mean_z2": [1.0] * 5, "log10_p": -0.1}
        return {"acc": {"covariates": [flat], "imus": [{"imu": 0, "covariates": [flat]},
                                                       {"imu": 2, "covariates": [row]}]}}

    e2 = make_effect("noise_level", imu=2, parameters={"sensor": "acc"})
    e0 = make_effect("noise_level", imu=0, parameters={"sensor": "acc"})
    pooled = make_effect("noise_level", parameters={"sensor": "acc"})
    structured = char([1.0, 1.2, 1.5, 2.0, 3.0], -30.0)
    assert _heteroscedastic(structured, e2, 0.01) is not None
    assert _heteroscedastic(structured, e0, 0.01) is None           # IMU 0 is homoscedastic
    assert "IMU 2" in _heteroscedastic(structured, pooled, 0.01)    # a pooled factor claims IMU 2 too
    # a large but insignificant, or a significant but small, variation is not a refusal
    assert _heteroscedastic(char([1.0, 1.2, 1.5, 2.0, 3.0], -1.0), e2, 0.01) is None
    small = 1.0 + 0.9 * (HETEROSCEDASTIC_RATIO - 1.0)
    assert _heteroscedastic(char([1.0, 1.0, 1.0, 1.0, small], -30.0), e2, 0.01) is None


def test_noise_variances_and_predictive_loglik_on_known_noise(lowpass_fit):
    """On a clean concealed recording the fitted noise model recovers the stated variances
    (leverage-corrected, so no 1 − h shrinkage) and the predictive log density with the true
    variances matches its expectation −½ Σ (1 + log 2πσ²) within 4 standard errors."""
    import numpy as np

    from accel_bayes.mismatch.transfer import noise_variances, predictive_loglik

    _, _, _, prep0, base0 = lowpass_fit
    nv = noise_variances(prep0, base0, omega_edges=[3.0, 6.0])
    for name, sig in (("acc", prep0.sigma_acc.numpy()), ("gyro", prep0.sigma_gyro.numpy())):
        ratio = nv[name] / sig[:, None] ** 2
        # each cell averages ≥ ~1000 channel-samples: SE of a variance ratio ≈ √(2/n) ≈ 0.045
        assert np.all(np.abs(ratio - 1) < 0.25), ratio
    true = {"edges": [], "acc": prep0.sigma_acc.numpy()[:, None] ** 2, "gyro": prep0.sigma_gyro.numpy()[:, None] ** 2}
    ll = predictive_loglik(prep0, base0, true)
    n_a, n_g = float(prep0.m_acc.sum()), float(prep0.m_gyro.sum())
    expect = -0.5 * (n_a + n_g) - 0.5 * float((prep0.m_acc.sum((0, 2)) * np.log(2 * np.pi * true["acc"][:, 0])).sum()
                                              + (prep0.m_gyro.sum((0, 2)) * np.log(2 * np.pi * true["gyro"][:, 0])).sum())
    se = np.sqrt(0.5 * (n_a + n_g))  # Var of −½z² is ½ per output
    assert abs(ll - expect) < 4 * se, (ll, expect, se)

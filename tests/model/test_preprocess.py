"""Real-data preprocessing (:mod:`accel_bayes.prep.preprocess`) and the estimated noise model
(:mod:`accel_bayes.model.noise`).

Fast tests on small simulated recordings (exact sample counts, noise recovery, exactness of the
sample-scaling and tempering identities against the likelihood class), and one test on the real
MIMU exp_1 (import, intrinsics, selection; ~5 s).
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import preset
from accel_bayes.errors import UserError
from accel_bayes.prep.intrinsics import Intrinsics
from accel_bayes.model.gyro_posterior import GyroPosterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.inference.noise_fit import fit_map_with_noise, sandwich_inflation
from accel_bayes.model.noise import residual_statistics, scale_samples
from accel_bayes.model.tempering import TemperedLikelihood
from accel_bayes.prep.preprocess import draw_intrinsics, preprocess
from accel_bayes.prep.selection import rotation_rate
from accel_bayes.simulate import simulate


@pytest.fixture(scope="module")
def sim():
    return simulate(preset("mimu8"), "iid", 400, seed=11, clip=False)


def _lik(rec, std=None, method="calibrated"):
    r = rec.copy()
    if std is not None:
        r.acc_noise_std = np.asarray(std, dtype=float) * np.ones(r.K)
    return RaoBlackwellLikelihood.from_recording(r, num_draws=1, gyro_method=method)


# ---------------------------------------------------------------------------- preprocess

def test_preprocess_without_rests_skips_intrinsics_with_a_note(sim):
    rec = sim.recording
    pre = preprocess(rec)
    assert pre.intrinsics is None and not pre.has_rests
    assert pre.summary["intrinsics"]["applied"] is False
    assert any("intrinsic calibration skipped" in n and "no static" in n for n in pre.notes)
    s = pre.summary["samples"]
    w = rotation_rate(rec)
    assert s["static"] == 0 and s["clipped"] == 0
    assert s["slow"] == int((w < 0.5).sum()) and s["kept"] == rec.T - s["slow"]
    np.testing.assert_array_equal(pre.keep, w >= 0.5)
    assert pre.recording.acc is not rec.acc or np.array_equal(pre.recording.acc, rec.acc)
    np.testing.assert_array_equal(pre.recording.acc, rec.acc)  # nothing applied
    with pytest.raises(UserError, match="intrinsics"):
        preprocess(rec, intrinsics="estimate")


def test_preprocess_counts_each_reason_once(sim):
    rec = sim.recording.copy()
    T, K = rec.T, rec.K
    static = np.zeros(T, dtype=bool)
    static[10:60] = True
    static[200:230] = True
    rec.gyro_clipped = np.zeros((T, K), dtype=bool)
    rec.acc_clipped = np.zeros((T, K), dtype=bool)
    rec.gyro_clipped[[5, 20, 100, 101], 3] = True  # 20 is also static: counted as static only
    rec.acc_clipped[[150, 151, 152], 6] = True
    g = rec.gyro.copy()
    g[300:310] = 0.01  # slow (|ω| < 0.5 rad/s)
    g[[100]] = 0.0  # clipped AND slow: counted as clipped
    rec.gyro = g
    pre = preprocess(rec, intrinsics="none", segments=static)
    s = pre.summary["samples"]
    assert s["static"] == 80
    assert s["clipped"] == 6  # 5, 100, 101, 150, 151, 152 (20 is static)
    slow = rotation_rate(rec) < 0.5
    clip = np.isin(np.arange(T), [5, 100, 101, 150, 151, 152])
    assert slow[300:310].all() and slow[100]
    assert s["slow"] == int((slow & ~static & ~clip).sum()) >= 10
    assert s["kept"] == T - s["static"] - s["clipped"] - s["slow"] == int(pre.keep.sum())
    assert not pre.keep[static].any() and not pre.keep[[5, 100, 101, 150, 151, 152]].any()
    assert not pre.keep[300:310].any()
    # switches: nothing dropped
    pre2 = preprocess(rec, intrinsics="none", segments=static, drop_static=False, drop_clipped=False,
                      min_rotation=0)
    assert pre2.keep.all() and pre2.summary["samples"]["kept"] == T
    with pytest.raises(UserError, match="min_rotation"):
        preprocess(rec, min_rotation=-1)


def test_preprocess_applies_given_intrinsics(sim):
    rec = sim.recording
    K = rec.K
    bias = np.tile([0.01, -0.02, 0.03], (K, 1))
    intr = Intrinsics(acc_bias=np.tile([0.1, 0.0, -0.1], (K, 1)), acc_matrix=np.tile(np.diag([1.01, 0.99, 1.0]), (K, 1, 1)),
                      acc_cov=np.zeros((K, 9, 9)), gyro_bias=bias, gyro_bias_cov=np.zeros((K, 3, 3)),
                      residual_rms=np.zeros(K), chi2_per_dof=np.ones(K), acc_noise_std=np.full(K, 0.04),
                      n_rests=np.full(K, 12), n_orientations=12, g=9.80665, source="test")
    pre = preprocess(rec, intrinsics=intr)
    assert pre.summary["intrinsics"]["applied"] and pre.intrinsics is intr
    np.testing.assert_allclose(pre.recording.gyro, rec.gyro - bias, atol=1e-15)
    np.testing.assert_allclose(pre.recording.acc[..., 0], 1.01 * (rec.acc[..., 0] - 0.1), rtol=1e-12)
    # draws from a zero covariance are the estimate itself; from a positive one they differ
    d = draw_intrinsics(intr, 3)
    np.testing.assert_allclose(d.acc_matrix, intr.acc_matrix)
    intr.gyro_bias_cov[:] = np.eye(3) * 1e-6
    d1, d2 = draw_intrinsics(intr, 3), draw_intrinsics(intr, 3)
    np.testing.assert_array_equal(d1.gyro_bias, d2.gyro_bias)  # same seed, same draw
    assert 1e-5 < np.abs(d1.gyro_bias - bias).max() < 1e-2


# ---------------------------------------------------------------------------- noise model

@pytest.mark.parametrize("factor", [2.0, 0.5])
def test_estimated_noise_recovers_the_truth_when_stated_is_wrong(sim, factor):
    """σ stated wrong by 2× either way: the type-II ML estimate recovers the simulated σ.
    Per IMU the residual dof are ≈ 3T − 0.75T ≈ 900, relative sd ≈ 2.4 %: 10 % tolerance
    per IMU (4 sd), 4 % on the mean of the 8 (≈ 5 sd)."""
    rec = sim.recording
    true = np.asarray(rec.acc_noise_std)
    lik = _lik(rec, true * factor, method="sample_cov")
    nominal = torch.as_tensor(rec.nominal_position)
    res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, prior_mean=nominal)
    ratio = nm.std / true
    assert nm.converged and len(nm.history) <= 6
    assert np.abs(ratio - 1).max() < 0.10, ratio
    assert abs(ratio.mean() - 1) < 0.04, ratio
    np.testing.assert_allclose(nm.stated, true * factor)
    assert abs(nm.chi2_per_dof_stated - 1 / factor**2) < 0.1 / factor**2


def test_noise_estimate_maximises_the_exact_marginal_likelihood(sim):
    """Independent check of the REML fixed point: with ω known (calibrated gyros, leverage ≈ 0)
    and one common factor c on σ, the exact likelihood (log p̂ + its dropped constant, which
    holds the σ dependence) is maximal at the estimated c."""
    rec = sim.recording
    lik = _lik(rec)
    nominal = torch.as_tensor(rec.nominal_position)
    res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std * 2.0, prior_mean=nominal)
    st = residual_statistics(lik.acc, res.positions, res.omega, lik.omega.cov, nm.std)
    c_hat = math.sqrt((st["rss"] / nm.std**2).sum() / st["dof"].sum())  # pooled scale at the fitted levels
    assert abs(c_hat - 1) < 1e-2  # fixed point reached

    def loglik(c):
        L = RaoBlackwellLikelihood(lik.acc, lik.omega, nm.std * c, num_draws=64, reference=lik.reference)
        g = torch.Generator().manual_seed(0)
        return float(L.log_phat(res.positions, generator=g)) + L.log_constant

    l0, lm, lp = loglik(1.0), loglik(0.97), loglik(1.03)
    assert l0 > lm and l0 > lp
    # parabola through the three points: vertex within 1 % of c = 1
    vert = 1.0 + 0.03 * (lm - lp) / (2 * (lm - 2 * l0 + lp))
    assert abs(vert - 1.0) < 0.01, vert


def test_rate_bins_recover_a_rate_dependent_noise(sim):
    """Extra noise on the faster half of the samples (total std 3× the base there): two |ω|
    bins recover the factor ratio within 10 %."""
    rec = sim.recording.copy()
    w = rotation_rate(rec)
    fast = w > np.median(w)
    g = np.random.default_rng(5)
    base = np.asarray(rec.acc_noise_std)[None, :, None]
    rec.acc = rec.acc + np.where(fast[:, None, None], math.sqrt(8.0) * base * g.standard_normal(rec.acc.shape), 0.0)
    lik = _lik(rec)
    res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std,
                                 prior_mean=torch.as_tensor(rec.nominal_position), bins=2)
    assert nm.bins == 2
    assert abs(nm.bin_scale[1] / nm.bin_scale[0] / 3.0 - 1) < 0.10, nm.bin_scale
    # the mean of s_t² is 1, so the level is the RMS noise: sqrt((1 + 9)/2) × base
    np.testing.assert_allclose(nm.std / np.asarray(rec.acc_noise_std), math.sqrt(5.0), rtol=0.1)


def test_scale_samples_is_the_heteroscedastic_likelihood(sim):
    """Dividing sample t by s_t (and its gyro posterior by √s_t) gives the likelihood with
    noise σ·s_t, up to a θ-free constant: compared with the two-group likelihood built directly."""
    rec = sim.recording
    lik = _lik(rec)
    T = lik.T
    s = np.where(np.arange(T) < T // 2, 0.5, 2.0)
    a_s, w_s, P_s = scale_samples(lik.acc, lik.omega.mean, lik.omega.cov, s)
    scaled = RaoBlackwellLikelihood(a_s, GyroPosterior(w_s, P_s, "x"), lik.acc_noise_std, 1, reference=lik.reference)
    halves = [RaoBlackwellLikelihood(lik.acc[idx], GyroPosterior(lik.omega.mean[idx], lik.omega.cov[idx], "x"),
                                     lik.acc_noise_std * f, 1, reference=lik.reference)
              for idx, f in ((slice(0, T // 2), 0.5), (slice(T // 2, T), 2.0))]
    p1 = torch.as_tensor(rec.nominal_position)
    p2 = p1 + 1e-3 * torch.randn(p1.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    ws = lik.omega.mean

    def direct(p):
        return sum(float(h.log_lik_given_omega(p, ws[idx]))
                   for h, idx in zip(halves, (slice(0, T // 2), slice(T // 2, T))))

    d_scaled = float(scaled.log_lik_given_omega(p1, w_s)) - float(scaled.log_lik_given_omega(p2, w_s))
    d_direct = direct(p1) - direct(p2)
    assert abs(d_scaled - d_direct) < 1e-6 * max(1.0, abs(d_direct)), (d_scaled, d_direct)


@pytest.mark.parametrize("phi_prior", [None, (40.0, 7.0)])
def test_tempered_likelihood_is_the_power_of_the_likelihood(sim, phi_prior):
    """log p̂ of the tempered likelihood (σ·√κ, F·κ, Occam term re-weighted) differs between two θ
    by exactly 1/κ × the difference of the untempered one (ω known: calibrated gyros, N draws
    shared through the same generator seed), with the flat and with a proper prior on φ."""
    rec = sim.recording
    lik = _lik(rec)
    if phi_prior is not None:
        lik = RaoBlackwellLikelihood(lik.acc, lik.omega, lik.acc_noise_std, 1, reference=lik.reference,
                                     phi_prior=phi_prior)
    kappa = 2.5
    tmp = TemperedLikelihood(lik.acc, lik.omega, lik.acc_noise_std * math.sqrt(kappa), 1, kappa, reference=lik.reference,
                             phi_prior=phi_prior)
    p1 = torch.as_tensor(rec.nominal_position)
    p2 = p1 + 2e-4 * torch.randn(p1.shape, generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    w = lik.omega.mean
    d_base = float(lik.log_lik_given_omega(p1, w)) - float(lik.log_lik_given_omega(p2, w))
    # log_phat with calibrated gyros (σ_ω ≈ 0.001 rad/s) is the given-ω value to ~1e-3
    g = lambda: torch.Generator().manual_seed(0)  # noqa: E731
    d_tmp = float(tmp.log_phat(p1, generator=g())) - float(tmp.log_phat(p2, generator=g()))
    assert abs(d_tmp - d_base / kappa) < 1e-2 * max(1.0, abs(d_base) / kappa), (d_tmp, d_base / kappa)
    with pytest.raises(UserError, match="kappa"):
        TemperedLikelihood(lik.acc, lik.omega, lik.acc_noise_std, 1, 0.5)


def test_sandwich_is_near_one_for_a_correct_model(sim):
    """Correctly specified simulated data: the sandwich covariance matches the Laplace one
    (κ ≈ 1; T = 400 scores estimate a 21×21 B, so ±30 %)."""
    rec = sim.recording
    lik = _lik(rec)
    res, nm = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std,
                                 prior_mean=torch.as_tensor(rec.nominal_position))
    sw = sandwich_inflation(lik.acc, lik.omega.mean, lik.omega.cov, nm.std, res,
                            prior_mean=torch.as_tensor(rec.nominal_position))
    assert 0.7 < sw["kappa"] < 1.3, sw["kappa"]
    assert sw["lags"] == 5  # floor(4 (400/100)^(2/9))


# ---------------------------------------------------------------------------- real data

def test_real_mimu_preprocessing(mimu_dir):
    """exp_1: intrinsics from its 20 rests applied (every rest within 0.0134 m/s² of g after,
    > 0.5 before; gyro rest means ≈ 0), static / clipped / slow samples dropped and counted."""
    from accel_bayes.data.mimu import import_mimu
    from accel_bayes.data.segments import mask_from_labels

    raw = import_mimu(mimu_dir / "exp_1" / "data.bin.gz")
    pre = preprocess(raw)
    it = pre.summary["intrinsics"]
    assert it["applied"] and it["rests"] == 20
    assert it["rest_error_max_before"] > 0.5 and it["rest_error_max_after"] < 0.0134
    assert pre.recording.attrs.get("intrinsics_applied") and "intrinsic calibration applied" in pre.recording.source
    static = mask_from_labels(raw.segment)
    clipped = raw.gyro_clipped.any(1) | raw.acc_clipped.any(1)
    w = rotation_rate(pre.recording)
    # gyro bias removed: the rest means of the corrected gyros are ~0 (raw: up to ~2 °/s)
    gm = np.abs(pre.recording.gyro[static].mean(0)).max()
    assert gm < 0.1 * math.pi / 180 < np.abs(raw.gyro[static].mean(0)).max()
    s = pre.summary["samples"]
    assert s["static"] == int(static.sum()) and s["clipped"] == int((clipped & ~static).sum())
    assert s["slow"] == int((~static & ~clipped & (w < 0.5)).sum())
    assert s["kept"] == raw.T - s["static"] - s["clipped"] - s["slow"] == int(pre.keep.sum())
    assert 5000 < s["kept"] < 7000  # ~100 s of hand rotation at 62.5 Hz
    k = pre.keep
    assert not (k & static).any() and not (k & clipped).any() and (w[k] >= 0.5).all()
    # a second application is refused in "estimate" mode and skipped in "auto" mode
    with pytest.raises(UserError, match="already applied"):
        preprocess(pre.recording, intrinsics="estimate")
    again = preprocess(pre.recording)
    assert again.intrinsics is None and "already applied" in again.summary["intrinsics"]["why"]

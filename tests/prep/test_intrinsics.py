"""Intrinsic calibration from rests (accel_bayes.prep.intrinsics).

Independent checks: simulated rests made from known bias/scale/non-orthogonality (recovered
within the reported uncertainty; the uncertainty itself checked by Monte Carlo over replicates),
exact recovery without noise, the g ↔ scale invariance, and the six real MIMU4444 recordings
(the MUST-SHOW: after calibration every rest of every IMU has |acc| within 0.05 m/s² of 9.81).
"""
import json

import numpy as np
import pytest
from scipy import stats
import torch

from accel_bayes.errors import UserError
from accel_bayes.prep.intrinsics import (
    ACC_PARAMS,
    SCHEMA,
    Intrinsics,
    estimate_intrinsics,
    static_acc_errors,
)
from accel_bayes.data.recording import Recording

G = 9.80665


# ------------------------------------------------------------------ simulated rests
def _truth(K, seed=11):
    rng = np.random.default_rng(seed)
    b = rng.normal(0, 0.3, (K, 3))
    T = np.zeros((K, 3, 3))
    for k in range(K):
        T[k] = np.diag(1 + rng.normal(0, 0.01, 3))
        T[k][np.tril_indices(3, -1)] = rng.normal(0, 0.005, 3)
    bg = rng.normal(0, 0.02, (K, 3))
    return b, T, bg


def _static_recording(K=4, n_orient=24, n=400, sigma=0.04, sigma_g=0.003, seed=0, truth_seed=11,
                      corrupt=0, dyn=50):
    """Rests in ``n_orient`` random orientations separated by ``dyn`` dynamic samples.  Raw
    outputs a_raw = T⁻¹ (g u) + b + noise, so that T (a_raw − b) has |·| = g at rest.  ``corrupt``
    samples per rest are overwritten with garbage and flagged as clipped."""
    b, T, bg = _truth(K, truth_seed)
    rng = np.random.default_rng(seed)
    dirs = np.random.default_rng(99).normal(size=(n_orient, K, 3))  # same orientations for every seed
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    Tinv = np.linalg.inv(T)
    acc, gyro, seg, clip = [], [], [], []
    for s in range(n_orient):
        true = G * dirs[s]  # (K, 3) sensor-frame specific force at rest
        raw = np.einsum("kij,kj->ki", Tinv, true) + b
        a = raw + sigma * rng.normal(size=(n, K, 3))
        c = np.zeros((n, K), bool)
        if corrupt:
            a[:corrupt] = 150.0
            c[:corrupt] = True
        acc += [rng.normal(0, 20, (dyn, K, 3)), a]
        gyro += [rng.normal(0, 3, (dyn, K, 3)), bg + sigma_g * rng.normal(size=(n, K, 3))]
        seg += ["dynamic"] * dyn + ["static"] * n
        clip += [np.zeros((dyn, K), bool), c]
    acc = np.concatenate(acc)
    Tn = acc.shape[0]
    rec = Recording(time=np.arange(Tn) / 100.0, acc=acc, gyro=np.concatenate(gyro),
                    nominal_position=np.random.default_rng(1).normal(0, 0.01, (K, 3)), acc_noise_std=np.full(K, sigma),
                    gyro_noise_std=np.full(K, sigma_g), acc_clipped=np.concatenate(clip),
                    gyro_clipped=np.concatenate(clip), segment=np.array(seg),
                    description="simulated rests", source="test")
    return rec, (b, T, bg)


def _params(b, T):
    t = np.stack([T[:, 0, 0], T[:, 1, 1], T[:, 2, 2], T[:, 1, 0], T[:, 2, 0], T[:, 2, 1]], -1)
    return np.concatenate((b, t), -1)


def test_noise_free_exact():
    rec, (b, T, bg) = _static_recording(sigma=0.0, sigma_g=0.0)
    est = estimate_intrinsics(rec)
    np.testing.assert_allclose(est.acc_bias, b, atol=1e-10)
    np.testing.assert_allclose(est.acc_matrix, T, atol=1e-11)
    np.testing.assert_allclose(est.gyro_bias, bg, atol=1e-14)
    assert np.all(np.triu(est.acc_matrix, 1) == 0)
    assert est.residual_rms.max() < 1e-10


def test_recovers_truth_within_reported_uncertainty():
    rec, (b, T, bg) = _static_recording(seed=3)
    est = estimate_intrinsics(rec)
    err = est.acc_params() - _params(b, T)
    z = err / est.acc_std
    assert np.abs(z).max() < 4.0, z
    # Mahalanobis distance per IMU against χ²(9): 99.9 % quantile.
    m2 = np.einsum("ki,kij,kj->k", err, np.linalg.inv(est.acc_cov), err)
    assert m2.max() < stats.chi2.ppf(0.999, 9), m2
    # Only white noise here: χ²/dof ≈ 1 (dof = 24 − 9 = 15; 99.9 % band of χ²(15)/15).
    assert np.all(est.chi2_per_dof < stats.chi2.ppf(0.999, 15) / 15)
    assert np.all(est.chi2_per_dof > stats.chi2.ppf(0.001, 15) / 15)
    zg = (est.gyro_bias - bg) / est.gyro_bias_std
    assert np.abs(zg).max() < 4.5
    assert np.all(est.n_rests == 24) and est.n_orientations >= 20  # random directions: a pair may be < 2° apart
    assert est.g == G


def test_reported_std_matches_monte_carlo_spread():
    """60 replicates (same truth, new noise): the spread of the estimates matches the reported
    std within 25 % for every parameter (pooled over 4 IMUs: 240 estimates per parameter; the
    covariance is inflated by max(1, χ²/dof), which adds ~5 % here)."""
    est = [estimate_intrinsics(_static_recording(seed=100 + i, n=200)[0]) for i in range(60)]
    p = np.stack([e.acc_params() for e in est])  # (R, K, 9)
    sd_rep = np.stack([e.acc_std for e in est]).mean(0)  # (K, 9)
    z = (p - p.mean(0)) / sd_rep
    ratio = z.std(0, ddof=1).reshape(-1, 9)
    ratio = np.sqrt((ratio**2).mean(0))  # per parameter, pooled over IMUs
    assert np.all((ratio > 0.75) & (ratio < 1.25)), dict(zip(ACC_PARAMS, ratio.round(3)))


def test_clipped_samples_are_excluded():
    clean, _ = _static_recording(seed=5)
    bad, _ = _static_recording(seed=5, corrupt=40)
    e0, e1 = estimate_intrinsics(clean), estimate_intrinsics(bad)
    # Same noise draws except the 40 flagged samples per rest (10 % of the data): the estimates
    # move by ~0.3 std, far less than the garbage would cause.
    assert np.all(np.abs(e0.acc_params() - e1.acc_params()) < 1.5 * e0.acc_std)
    assert np.abs(e1.gyro_bias - e0.gyro_bias).max() < 5 * e0.gyro_bias_std.max()
    # The flags are what keeps the garbage out: without them the rest means are ruined.
    assert np.abs(static_acc_errors(bad)).max() < 1.0
    bad.acc_clipped = None
    assert np.abs(static_acc_errors(bad)).max() > 10.0


def test_g_sets_only_the_scale():
    rec, _ = _static_recording(seed=7)
    a, b = estimate_intrinsics(rec, g=9.80665), estimate_intrinsics(rec, g=9.81)
    c = 9.81 / 9.80665
    np.testing.assert_allclose(b.acc_bias, a.acc_bias, atol=1e-9)
    np.testing.assert_allclose(b.acc_matrix, c * a.acc_matrix, atol=1e-10)
    np.testing.assert_allclose(b.residual_rms, c * a.residual_rms, rtol=1e-6)


def test_apply_returns_new_recording_and_corrects():
    rec, (b, T, bg) = _static_recording(seed=8)
    before = rec.copy()
    est = estimate_intrinsics(rec)
    out = est.apply(rec)
    assert out is not rec
    for name in ("acc", "gyro", "acc_noise_std"):
        np.testing.assert_array_equal(getattr(rec, name), getattr(before, name))
    assert rec.source == before.source and out.source.startswith(rec.source + "; intrinsic calibration applied")
    assert out.attrs["intrinsics_applied"] == SCHEMA and "intrinsics_applied" not in rec.attrs
    raw = np.abs(static_acc_errors(rec))
    cal = np.abs(static_acc_errors(out))
    assert raw.max() > 0.2 and cal.max() < 5 * 0.04 / np.sqrt(400) * 3
    # gyro bias removed in every rest
    st = np.asarray(out.segment) == "static"
    assert np.abs(out.gyro[st].mean(0)).max() < 5 * 0.003 / np.sqrt(st.sum() / 1)
    # corrected acc = T(a − b) exactly
    np.testing.assert_allclose(out.acc[5], np.einsum("kij,kj->ki", est.acc_matrix, rec.acc[5] - est.acc_bias))


def test_static_acc_errors_direct():
    rec, _ = _static_recording(seed=9, n_orient=12, corrupt=10)
    err = static_acc_errors(rec, g=9.81)
    st = np.asarray(rec.segment) == "static"
    starts = np.flatnonzero(np.diff(np.r_[0, st.astype(int)]) == 1)
    a0 = starts[0]
    seg = rec.acc[a0 + 10:a0 + 400]  # the first 10 samples of each rest are the flagged ones
    np.testing.assert_allclose(err[0], np.linalg.norm(seg.mean(0), axis=-1) - 9.81, atol=1e-12)
    assert err.shape == (12, rec.K)


def test_json_round_trip(tmp_path):
    rec, _ = _static_recording(seed=10)
    est = estimate_intrinsics(rec)
    p = tmp_path / "intr.json"
    est.to_json(p)
    back = Intrinsics.from_json(p)
    for name in ("acc_bias", "acc_matrix", "acc_cov", "gyro_bias", "gyro_bias_cov", "residual_rms", "n_rests"):
        np.testing.assert_array_equal(getattr(back, name), getattr(est, name))
    assert back.g == est.g and back.source == est.source
    d = json.loads(p.read_text())
    assert d["schema"] == SCHEMA and d["imus"][2]["imu"] == 2
    np.testing.assert_allclose(back.apply(rec).acc, est.apply(rec).acc)
    with pytest.raises(UserError, match="existing|exists"):
        est.to_json(p, overwrite=False)
    d["imus"][1]["acc_matrix"][0][2] = 0.1
    with pytest.raises(UserError, match=r"imus\[1\]\.acc_matrix"):
        Intrinsics.from_json(d)
    d["schema"] = "other/1"
    with pytest.raises(UserError, match="intrinsics.schema"):
        Intrinsics.from_json(json.dumps(d))


def test_refuses_too_few_orientations():
    rec, _ = _static_recording(n_orient=6)
    with pytest.raises(UserError, match="distinct orientations"):
        estimate_intrinsics(rec)
    rec, _ = _static_recording(n_orient=12)
    with pytest.raises(UserError, match="g:"):
        estimate_intrinsics(rec, g=-1)
    other, _ = _static_recording(K=3, n_orient=12)
    with pytest.raises(UserError, match="3 IMUs"):
        estimate_intrinsics(other).apply(rec)


def test_cli(tmp_path, capsys):
    from accel_bayes.cli import main
    from accel_bayes.data.io import read_recording, write_recording

    rec, _ = _static_recording(seed=12, n=200)
    src = tmp_path / "rec.nc"
    write_recording(rec, src)
    out, cal = tmp_path / "intr.json", tmp_path / "cal.nc"
    assert main(["intrinsics", str(src), "-o", str(out), "--apply-to", str(cal)]) == 0
    text = capsys.readouterr().out
    assert "rests" in text and "wrote" in text
    est = Intrinsics.from_json(out)
    np.testing.assert_allclose(read_recording(cal).acc, est.apply(rec).acc)
    assert main(["intrinsics", str(src), "-o", str(out)]) == 2  # exists, no --overwrite
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "exists" in err
    assert main(["intrinsics", str(tmp_path / "missing.nc"), "-o", str(tmp_path / "x.json")]) == 2


# ------------------------------------------------------------------ the six real recordings
@pytest.fixture(scope="module")
def mimu_recordings():
    from tests.conftest import mimu_data_dir

    d = mimu_data_dir()
    if not d.is_dir():
        pytest.skip(f"shared MIMU data not found at {d}")
    from accel_bayes.data.mimu import import_mimu

    recs = [import_mimu(d / f"exp_{i}" / "data.bin.gz") for i in range(1, 7)]
    return recs, [estimate_intrinsics(r) for r in recs]


def test_mimu_every_rest_within_005_of_981(mimu_recordings):
    """MUST-SHOW: intrinsics estimated on an experiment, applied to it: in every static segment
    of every experiment, |acc| of every IMU is within 0.05 m/s² of 9.81 (raw: up to ~0.75)."""
    recs, intr = mimu_recordings
    for i, (rec, est) in enumerate(zip(recs, intr)):
        raw = np.abs(static_acc_errors(rec, g=9.81))
        cal = np.abs(static_acc_errors(est.apply(rec), g=9.81))
        assert cal.shape[0] >= 20 and np.isfinite(cal).all()
        assert raw.max() > 0.5, f"exp_{i + 1}: raw data already calibrated?"
        assert cal.max() < 0.05, f"exp_{i + 1}: worst calibrated rest error {cal.max():.4f} m/s²"
        assert est.extra["converged"]
        assert np.all(est.n_rests >= 20)


def test_mimu_gyro_bias_removed(mimu_recordings):
    recs, intr = mimu_recordings
    rec, est = recs[0], intr[0]
    cal = est.apply(rec)
    st = np.asarray(rec.segment) == "static"
    raw_mean = np.abs(rec.gyro[st].mean(0)).max()
    cal_mean = np.abs(cal.gyro[st].mean(0)).max()
    assert raw_mean > 0.02 and cal_mean < 1e-3  # rad/s: raw offsets ~1–2 °/s


def test_acc_effects_are_the_inverse_of_the_correction():
    """Intrinsics.acc_effects (the errors as effects of the physics library) applied to the
    corrected outputs give back the raw outputs: one definition of the accelerometer errors."""
    from accel_bayes.physics.effects import SignalContext, model_outputs

    rec, _ = _static_recording(n_orient=12, n=100)
    est = estimate_intrinsics(rec)
    raw = torch.as_tensor(rec.acc[:200])
    f = torch.as_tensor(est.correct_acc(rec.acc[:200]))
    K = rec.K
    z = torch.zeros(200, 3, dtype=torch.float64)
    ctx = SignalContext(torch.arange(200, dtype=torch.float64), z, z, z, torch.zeros(K, 3, dtype=torch.float64),
                        torch.tensor([[1.0, 0, 0, 0]] * K, dtype=torch.float64), f, torch.zeros_like(f))
    y, _ = model_outputs(est.acc_effects(), ctx)
    torch.testing.assert_close(y, raw, rtol=1e-12, atol=1e-10)

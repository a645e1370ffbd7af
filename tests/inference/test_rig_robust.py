"""The rig posterior's misspecification-robust std (issue #28: on the MIMU4444 the Laplace std of the
clock offsets was 20–65× below a jackknife's): the block sandwich of
:mod:`accel_bayes.inference.rig.robust` and the rule that picks the reported std."""
import numpy as np
import pytest

from accel_bayes.inference.rig import RigSettings, fit_rig
from accel_bayes.inference.rig.robust import BlockScores, contrast_variances, robust_summary
from experiments.clockgen.rig import draw_rig


def _offset_z(seed, wander, duration, settings=RigSettings()):
    """Offset errors of one 2-IMU clockgen rig over the Laplace and over the reported std."""
    rec, truth = draw_rig(seed, duration=duration, n_imu=2, offset_wander=wander)
    res = fit_rig(rec, settings)
    d = float(truth["clock_drift"][1])
    # DESIGN §7.3's t₀ is the first stamp: the lag there is o − t_first·d/(1 + d)
    err = res.time_offset[1] - (truth["time_offset"][1] - float(rec.time[0]) * d / (1 + d))
    rep = robust_summary(res)[1]["time_offset"]
    return err / res.time_offset_std[1], err / float(rep["std_reported"][0]), res, rep


def test_sandwich_matches_the_laplace_on_a_correctly_specified_rig():
    """White noise only (no stamp jitter, walks or quantisation: every effect in the data is in the
    model), 10 s at the drawn 250/100 Hz, 1 s blocks.  (a) The model's expected block variance
    Σ_b V_b, built from the profiled rows, is the Laplace covariance within [0.45, 1.6] per
    coordinate: below 1 where the motion prior informs the knots (the MAP's sampling variance is
    below the posterior's by C G ᵀΛG C), above where the exact Hessian's errors-in-variables term
    lowers the clock's information; rows not profiled would count the knots' information too and
    give ratios of tens.  (b) The realised sandwich: its geometric-mean std ratio to the Laplace
    within [0.6, 1.6] (≈ 4 sd of the mean of 8 log ratios from ~10 blocks), and the test fires on at
    most one of the 8 reported coordinates (1 % each; here the sensor-frame orientation x sits at the
    edge, variance ratio 2.9 against a quantile of 2.8).  Not at 100/100 Hz: there the 10 ms knots hold one sample of each IMU
    and the Laplace itself is off (offset z of −8.4 and ±2.8 on seeds 0, 3, 4 of 8), which the
    sandwich rightly flags."""
    rec, _ = draw_rig(2, duration=10.0, n_imu=2, jitter=False, bias_walk=False, quantised=False)
    res = fit_rig(rec, RigSettings(score_block=1.0))
    sc = res.block_scores
    assert len(sc.influence) == 10
    ratio = np.diag(sc.model_cov.sum(0)) / np.diag(res.free_cov)
    assert np.all((ratio > 0.45) & (ratio < 1.6)), ratio
    summ = robust_summary(res)[1]
    r = np.concatenate([e["ratio"] for e in summ.values()])
    assert 0.6 < float(np.exp(np.mean(np.log(r)))) < 1.6, r
    assert sum(int(e["robust_used"].sum()) for e in summ.values()) <= 1, summ


def test_contrast_rule_picks_the_sandwich_only_where_the_blocks_disagree_with_the_model():
    """Hand-made block scores: ten equal blocks whose model variance is 1 each (V = 10); influences
    of RMS 1 per block pass, of RMS 3 per block (variance 9× the model's) fire; an unidentified
    coordinate's contrast stays NaN and never fires."""
    rng = np.random.default_rng(0)
    nb = 10
    model_cov = np.tile(np.diag([1.0, 1.0, 1.0]), (nb, 1, 1))
    infl = np.c_[rng.normal(0, 1, nb), 3.0 * rng.normal(0, 1, nb), rng.normal(0, 1, nb)]
    sc = BlockScores(edges=np.arange(nb + 1.0), influence=infl, model_cov=model_cov)
    lap = np.diag([10.0, 10.0, np.nan])
    v = contrast_variances(sc, lap, np.eye(3))
    # leverage: each block holds a tenth of the information, so E[Σ a²] = 0.9 V before the correction
    assert np.allclose(v["shrink"][:2], 0.9) and np.allclose(v["robust"][:2], (infl[:, :2] ** 2).sum(0) / 0.9)
    assert list(v["fired"]) == [False, True, False]
    assert v["reported"][0] == 10.0 and v["reported"][1] == v["robust"][1]
    assert np.isnan(v["reported"][2])


@pytest.mark.slow
def test_sandwich_covers_a_wandering_offset_where_the_laplace_does_not():
    """The defect: 2-IMU clockgen rigs (30 s) whose offset wanders (three 0.2–1 Hz sinusoids, RMS
    0.3 ms, fresh phases per seed; the model's offset is constant).  Over 8 seeds the Laplace z of
    the offset has RMS > 3 (the old std); with the reported std (the sandwich, where the test
    fires) RMS within 0.6–1.6 (10 blocks: t-like z with RMS ≈ 1.1 if calibrated)."""
    zl, zr = [], []
    for seed in range(8):
        a, b, _, _ = _offset_z(seed, 3e-4, 30.0)
        zl.append(a), zr.append(b)
    rms = lambda z: float(np.sqrt(np.mean(np.square(z))))  # noqa: E731
    assert rms(zl) > 3.0, zl
    assert 0.6 < rms(zr) < 1.6, zr


@pytest.mark.slow
def test_sandwich_agrees_with_a_delete_one_block_jackknife():
    """Seed 0 of the wandering-offset rigs (30 s): the offset refitted with each 3 s block's samples
    flagged; the sandwich std within a factor 2 of the jackknife's (0.76 in
    ``experiments/rig_robust_check.md``), the Laplace std below 0.3 of it (0.12 there)."""
    from experiments.rig_robust_check import jackknife
    jk = jackknife(0, 30.0, 3e-4)
    assert 0.5 < jk["robust"] / jk["jackknife"] < 2.0, jk
    assert jk["laplace"] / jk["jackknife"] < 0.3, jk

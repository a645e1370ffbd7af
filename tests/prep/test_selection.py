"""THE sample selection (issue #10 item 3): one rotation test, reasons counted once, runs and gaps."""
import math

import numpy as np
import pytest

from accel_bayes.data.recording import Recording
from accel_bayes.errors import UserError
from accel_bayes.prep.selection import REASONS, Selection, clipped_mask, rotation_rate, select_samples

RNG = np.random.default_rng(3)


def _rec(T=20, K=4, gyro_std=(0.001, 0.002, 0.004, 0.001), rate=1.0):
    """K IMUs with identity orientations (sensor frame = array frame), gyros reading ω ≈ rate·x̂."""
    q = np.tile([1.0, 0, 0, 0], (K, 1))
    pos = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0, 0, 0.01]], dtype=float)[:K]
    gyro = np.zeros((T, K, 3))
    gyro[..., 0] = rate
    gyro += 0.01 * RNG.standard_normal(gyro.shape)
    acc = np.tile([0, 0, 9.81], (T, K, 1)) + 0.01 * RNG.standard_normal((T, K, 3))
    return Recording(time=np.arange(T) / 100.0, acc=acc, gyro=gyro, nominal_position=pos, nominal_orientation=q,
                     acc_noise_std=np.full(K, 0.04), gyro_noise_std=np.asarray(gyro_std, dtype=float))


def test_rotation_rate_is_the_inverse_variance_weighted_gyro_mean_brute_force():
    rec = _rec()
    g = rec.gyro.copy()
    g[3, 1] = np.nan           # one gyro missing at t = 3
    g[7, 2, 1] = np.nan        # one axis of one gyro missing at t = 7: that gyro is left out there
    g[9] = np.nan              # no gyro at t = 9
    rec.gyro = g
    w = rotation_rate(rec)
    sd = rec.gyro_noise_std
    for t in range(rec.T):  # brute force: loop over samples and gyros
        num, den = np.zeros(3), 0.0
        for k in range(rec.K):
            if np.all(np.isfinite(g[t, k])):
                num += g[t, k] / sd[k] ** 2
                den += 1.0 / sd[k] ** 2
        if den == 0:
            assert math.isnan(w[t])
        else:
            assert w[t] == pytest.approx(np.linalg.norm(num / den), rel=1e-12)
    # equal noise: the plain mean (the rule preprocess used before)
    rec2 = _rec(gyro_std=(0.001,) * 4)
    np.testing.assert_allclose(rotation_rate(rec2), np.linalg.norm(rec2.gyro.mean(1), axis=-1), rtol=1e-12)


def test_mask_runs_gaps_and_reasons_on_a_hand_made_case():
    T = 20
    rec = _rec(T)
    g = rec.gyro.copy()
    g[[8, 9], :, :] = 0.05          # slow
    g[12] = np.nan                  # no finite gyro
    rec.gyro = g
    rec.acc_clipped = np.zeros((T, rec.K), dtype=bool)
    rec.acc_clipped[[2, 5], 1] = True      # 2 is also static: counted as static only
    static = np.zeros(T, dtype=bool)
    static[0:4] = True
    sel = select_samples(rec, static=static, min_rotation=0.5, user=np.setdiff1d(np.arange(T), [17]))
    expect = np.ones(T, dtype=bool)
    expect[[0, 1, 2, 3, 5, 8, 9, 12, 17]] = False
    np.testing.assert_array_equal(sel.keep, expect)
    assert sel.dropped == {"static": 4, "clipped": 1, "flagged": 0, "non_finite": 1, "slow": 2, "user": 1}
    assert tuple(sel.dropped) == REASONS
    np.testing.assert_array_equal(sel.index, np.flatnonzero(expect))
    np.testing.assert_array_equal(sel.runs, [[4, 5], [6, 8], [10, 12], [13, 17], [18, 20]])
    np.testing.assert_array_equal(sel.gaps, [[5, 6], [8, 10], [12, 13], [17, 18]])
    assert sel.kept_runs == 5 and sel.n_kept == 11 == sel.T - sum(sel.dropped.values())
    line = sel.summary()
    assert "\n" not in line and "kept 11 of 20" in line and "2 slow" in line and "1 non_finite" in line
    assert sel.to_dict()["dropped"]["static"] == 4
    with pytest.raises(Exception):
        sel.keep[0] = True  # frozen
    with pytest.raises(Exception):
        sel.n = 3  # type: ignore[attr-defined]
    assert isinstance(sel, Selection) and sel == sel and hash(sel) == hash(sel)  # identity, no array comparison


def test_min_rotation_zero_keeps_every_moving_sample_and_switches_work():
    T = 30
    rec = _rec(T, rate=0.2)  # slow everywhere
    rec.gyro_clipped = np.zeros((T, rec.K), dtype=bool)
    rec.gyro_clipped[4, 0] = True
    assert select_samples(rec).n_kept == 0 and select_samples(rec).dropped["slow"] == T - 1
    sel = select_samples(rec, min_rotation=0, drop_clipped=False)
    assert sel.keep.all() and sel.kept_runs == 1 and len(sel.gaps) == 0
    assert select_samples(rec, min_rotation=None).dropped["clipped"] == 1
    static = np.zeros(T, dtype=bool)
    static[:5] = True
    assert select_samples(rec, static=static, drop_static=False, min_rotation=0, drop_clipped=False).keep.all()
    for bad in (-1, float("nan"), "x"):
        with pytest.raises(UserError, match="min_rotation"):
            select_samples(rec, min_rotation=bad)
    with pytest.raises(UserError, match="select"):
        select_samples(rec, user=np.ones(3, dtype=bool))


def test_imu_subsets_restrict_the_clip_flags_and_the_rotation_test():
    rec = _rec(10)
    rec.acc_clipped = np.zeros((10, rec.K), dtype=bool)
    rec.acc_clipped[3, 2] = True
    assert clipped_mask(rec)[3] and not clipped_mask(rec, acc_imus=[0, 1, 3])[3]
    g = rec.gyro.copy()
    g[:, 3] = 0.0
    rec.gyro = g
    np.testing.assert_allclose(rotation_rate(rec, gyro_imus=[3]), 0.0, atol=0)
    assert select_samples(rec, gyro_imus=[3], drop_clipped=False).dropped["slow"] == 10


def test_every_fit_takes_the_same_selection():
    """preprocess, the likelihood and the MAP use one Selection object."""
    from accel_bayes.inference.map import fit_map_recording
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.physics.arrays import mimu4444_8
    from accel_bayes.prep.prepared import prepare_recording
    from accel_bayes.prep.preprocess import preprocess
    from accel_bayes.simulate import simulate

    sim = simulate(mimu4444_8(), T=200, motion="iid", seed=2)
    rec = sim.recording
    pre = preprocess(rec)
    assert pre.keep is pre.selection.keep and 0 < pre.n_kept < rec.T
    prepared = prepare_recording(rec, selection=pre.selection)
    lik = RaoBlackwellLikelihood.from_recording(prepared, num_draws=1)
    assert lik.selection is pre.selection and lik.T == pre.n_kept
    np.testing.assert_array_equal(lik.sample_index, pre.selection.index)
    lik2 = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, select="rotation", drop_clipped=True),
                                                 num_draws=1)
    np.testing.assert_array_equal(lik2.sample_index, pre.selection.index)  # same rule, no rests here
    res = fit_map_recording(prepared, max_iter=5)
    assert res.selection is pre.selection
    np.testing.assert_array_equal(res.sample_index, pre.selection.index)
    with pytest.raises(UserError, match="selection"):
        prepare_recording(rec, selection=pre.selection, select="rotation")


def test_flagged_samples_are_left_out_with_their_own_reason():
    T = 20
    rec = _rec(T)
    rec.acc_clipped = np.zeros((T, rec.K), dtype=bool)
    rec.acc_clipped[6, 0] = True
    rec.acc_flagged = np.zeros((T, rec.K), dtype=bool)
    rec.gyro_flagged = np.zeros((T, rec.K), dtype=bool)
    rec.acc_flagged[[6, 10], 2] = True   # 6 is also clipped: counted as clipped only
    rec.gyro_flagged[14, 3] = True
    sel = select_samples(rec, min_rotation=0.5)
    assert sel.dropped["clipped"] == 1 and sel.dropped["flagged"] == 2
    assert not sel.keep[[6, 10, 14]].any() and sel.n_kept == T - 3
    # only the IMUs used count, and the switch turns the reason off
    assert select_samples(rec, min_rotation=0.5, acc_imus=[0, 1], gyro_imus=[0, 1]).dropped["flagged"] == 0
    assert select_samples(rec, min_rotation=0.5, drop_flagged=False).dropped["flagged"] == 0

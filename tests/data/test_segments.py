"""Static/dynamic segmentation, orientation clustering and noise estimation (accel_bayes.data.segments).

Synthetic recordings with known rests, known gravity directions and known noise; checks against
closed forms and brute-force loops.
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import G0, MIMU_BOTTOM_QUAT
from accel_bayes.errors import UserError
from accel_bayes.physics.models import to_sensor_frame
from accel_bayes.data.segments import (
    analyse_static,
    angle_deg,
    cluster_orientations,
    detect_static,
    estimate_noise_std,
    gravity_directions,
    mask_from_labels,
    segment_labels,
    segment_means,
    static_segments,
)

DT = 0.016


def _unit(v):
    v = np.asarray(v, dtype=float)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _slerp_dirs(a, b, n):
    """n unit vectors turning from a to b at constant rate (great circle)."""
    ang = math.acos(np.clip(a @ b, -1, 1))
    t = np.linspace(0, 1, n)[:, None]
    if ang < 1e-9:
        return np.repeat(a[None], n, 0)
    return (np.sin((1 - t) * ang) * a + np.sin(t * ang) * b) / math.sin(ang)


def synthetic(rest_s, move_s=2.0, dirs=None, *, K=4, sigma_a=0.04, sigma_g=0.003, quats=None, seed=0):
    """Rests of the given durations joined by constant-rate turns of ``move_s``.

    Returns time, acc (T,K,3) sensor frame, gyro (T,K,3), the true static mask (the rest
    samples), the true up directions (array frame) and the quaternions.
    """
    rng = np.random.default_rng(seed)
    n_rest = len(rest_s)
    if dirs is None:
        dirs = _unit(rng.normal(size=(n_rest, 3)))
    up, mask, rate = [], [], []
    for i, r in enumerate(rest_s):
        n = int(round(r / DT))
        up.append(np.repeat(dirs[i][None], n, 0))
        mask.append(np.ones(n, bool))
        rate.append(np.zeros(n))
        if i + 1 < n_rest:
            m = int(round(move_s / DT))
            up.append(_slerp_dirs(dirs[i], dirs[i + 1], m))
            mask.append(np.zeros(m, bool))
            ang = math.acos(np.clip(dirs[i] @ dirs[i + 1], -1, 1))
            rate.append(np.full(m, ang / move_s))
    up = np.concatenate(up)
    mask = np.concatenate(mask)
    rate = np.concatenate(rate)
    T = up.shape[0]
    f_array = np.repeat((G0 * up)[:, None, :], K, 1)
    w_array = np.zeros((T, K, 3))
    w_array[..., 2] = rate[:, None]
    if quats is None:
        quats = np.tile([1.0, 0, 0, 0], (K, 1))
    q = torch.as_tensor(quats, dtype=torch.float64)
    acc = to_sensor_frame(torch.as_tensor(f_array), q).numpy() + sigma_a * rng.normal(size=(T, K, 3))
    gyro = to_sensor_frame(torch.as_tensor(w_array), q).numpy() + sigma_g * rng.normal(size=(T, K, 3))
    time = np.arange(T) * DT
    return time, acc, gyro, mask, dirs, quats


def test_segments_and_labels_roundtrip():
    mask = np.array([1, 1, 0, 0, 1, 0, 1, 1, 1], bool)
    segs = static_segments(mask)
    assert segs == [(0, 2), (4, 5), (6, 9)]
    lab = segment_labels(mask)
    assert lab.tolist() == ["static" if m else "dynamic" for m in mask]
    assert np.array_equal(mask_from_labels(lab), mask)
    assert static_segments(np.zeros(5, bool)) == []
    assert static_segments(np.ones(3, bool)) == [(0, 3)]


def test_detect_static_finds_the_rests():
    rest = [20.0, 8.0, 2.0, 15.0, 10.0]  # the 2 s rest is shorter than min_duration_s = 3 s
    time, acc, gyro, truth, dirs, _ = synthetic(rest, move_s=2.0, seed=1)
    mask = detect_static(acc, gyro, time, window_s=0.5, min_duration_s=3.0, trim_s=0.25)
    segs = static_segments(mask)
    true_segs = [s for s in static_segments(truth) if (s[1] - s[0]) * DT >= 3.0]
    assert len(segs) == 4
    # Every found sample is truly static (no false positive) and each found rest lies inside a
    # true one, losing at most half a window + trim + 2 samples at each end.
    assert not (mask & ~truth).any()
    slack = int(round((0.25 + 0.25) / DT)) + 2
    for (a, b), (ta, tb) in zip(segs, true_segs):
        assert ta <= a <= ta + slack and tb - slack <= b <= tb


def test_detect_static_no_rest_means_no_static():
    # A board that keeps turning: the caps must stop the quietest motion from being called static.
    rng = np.random.default_rng(3)
    T = 4000
    t = np.arange(T) * DT
    w = np.stack([2 * np.sin(0.7 * t), 1.5 * np.cos(0.3 * t), 1 + 0.5 * np.sin(1.1 * t)], -1)
    gyro = np.repeat(w[:, None], 4, 1) + 0.003 * rng.normal(size=(T, 4, 3))
    acc = np.repeat((G0 * _unit(np.stack([np.sin(t), np.cos(t), 0.3 * np.ones(T)], -1)))[:, None], 4, 1)
    acc = acc + 0.04 * rng.normal(size=acc.shape)
    assert not detect_static(acc, gyro, t).any()


def test_detect_static_without_gyro_and_with_absent_imu():
    time, acc, gyro, truth, _, _ = synthetic([10.0, 10.0, 10.0], seed=2)
    m_acc = detect_static(acc, None, time)
    assert len(static_segments(m_acc)) == 3 and not (m_acc & ~truth).any()
    g = gyro.copy()
    g[:, 1] = np.nan  # IMU 1 has no gyroscope (DESIGN §7.1: NaN rows)
    m = detect_static(acc, g, time)
    assert len(static_segments(m)) == 3 and not (m & ~truth).any()


def test_detect_static_rejects_bad_shapes():
    with pytest.raises(UserError, match="acc"):
        detect_static(np.zeros((10, 3)), None, np.arange(10.0))
    with pytest.raises(UserError, match="time"):
        detect_static(np.zeros((10, 2, 3)), None, np.arange(9.0))
    with pytest.raises(UserError, match="gyro"):
        detect_static(np.zeros((10, 2, 3)), np.zeros((10, 3, 3)), np.arange(10.0))


def test_angle_deg_small_and_large():
    a = np.array([1.0, 0, 0])
    for deg in (1e-6, 0.5, 2.0, 90.0, 179.9):
        r = math.radians(deg)
        b = np.array([math.cos(r), math.sin(r), 0.0]) * 7.0
        assert angle_deg(a, b) == pytest.approx(deg, rel=1e-9, abs=1e-12)


def _tilted(base, deg, seed):
    """A unit vector at exactly ``deg`` from ``base`` (random azimuth)."""
    rng = np.random.default_rng(seed)
    p = np.cross(base, rng.normal(size=3))
    p /= np.linalg.norm(p)
    r = math.radians(deg)
    return math.cos(r) * base + math.sin(r) * p


def test_cluster_orientations():
    e = np.eye(3)
    d = np.stack([e[2], _tilted(e[2], 1.0, 0), e[0], _tilted(e[0], 3.0, 1), e[2], e[1]])
    # Global (default): rests 0, 1 and the return at index 4 are one orientation; 3 is 3° off.
    assert cluster_orientations(d, 2.0).tolist() == [0, 0, 1, 2, 0, 3]
    # Neighbours only: the return to +z counts again.
    assert cluster_orientations(d, 2.0, neighbours_only=True).tolist() == [0, 0, 1, 2, 3, 4]
    assert cluster_orientations(d, 5.0).tolist() == [0, 0, 1, 1, 0, 2]
    # Single linkage chains 1.5° steps (brute force: every step within tol).
    base = e[2]
    chain = [base]
    for i in range(4):
        chain.append(_tilted(chain[-1], 1.5, 10 + i))
    lab = cluster_orientations(np.stack(chain), 2.0)
    assert lab.tolist() == [0] * 5
    assert cluster_orientations(np.zeros((0, 3))).size == 0


def test_noise_estimate_matches_truth_and_brute_force():
    rng = np.random.default_rng(7)
    K, sig = 3, np.array([0.02, 0.05, 0.1])
    T = 30000
    x = rng.normal(size=(T, K, 3)) * sig[None, :, None]
    segs = [(0, 8000), (9000, 20000), (21000, 30000)]
    # Large, different offsets per segment must not leak into the estimate.
    for i, (a, b) in enumerate(segs):
        x[a:b] += rng.normal(scale=5.0, size=(1, K, 3))
    x[8000:9000] += 100.0  # motion between rests: ignored
    est = estimate_noise_std(x, segs)
    # Brute force: loop over segments and axes, same pooled formula.
    ss = np.zeros((K, 3))
    n = 0
    for a, b in segs:
        r = x[a:b] - x[a:b].mean(0)
        ss += (r ** 2).sum(0)
        n += b - a - 1
    assert np.allclose(est, np.sqrt((ss / n).mean(-1)), rtol=1e-10)
    # Against the truth: std of a std estimate from ~84k dof is ~0.25 %; allow 2 %.
    assert np.allclose(est, sig, rtol=0.02)


def test_segment_means_and_directions_in_array_frame():
    K = 4
    quats = np.array([[1.0, 0, 0, 0], MIMU_BOTTOM_QUAT, [1.0, 0, 0, 0], MIMU_BOTTOM_QUAT])
    dirs = _unit(np.array([[0, 0, 1.0], [1.0, 0.2, -0.3], [0.1, -1.0, 0.4]]))
    time, acc, gyro, truth, _, _ = synthetic([10.0, 10.0, 10.0], dirs=dirs, K=K, quats=quats, seed=4)
    segs = static_segments(truth)
    means_sensor = segment_means(acc, segs)
    # Brute force mean.
    assert np.allclose(means_sensor[1], acc[segs[1][0]:segs[1][1]].mean(0), atol=1e-12)
    # Sensor-frame means of upside-down IMUs disagree with the top ones ...
    assert angle_deg(means_sensor[0, 0], means_sensor[0, 1]) > 90
    # ... array-frame means agree, and the directions are the true ones within noise.
    means = segment_means(acc, segs, quats)
    d = gravity_directions(means)
    assert np.all(angle_deg(d, dirs) < 0.1)
    st = analyse_static(acc, gyro, time, quats)
    assert st.n_segments == 3 and st.n_orientations == 3
    assert np.all(angle_deg(st.directions, dirs) < 0.1)
    assert np.allclose(st.acc_noise_std, 0.04, rtol=0.05)
    assert np.allclose(st.gyro_noise_std, 0.003, rtol=0.05)

"""Static/dynamic segmentation of a recording, orientation clustering and noise from rests.

Generic: works on any (T, K, 3) accelerometer (and optional gyroscope) outputs, not only MIMU
files.  The calibration protocols of [C21] §IV-A and [S16] §IV-B rest the array in a number of
orientations between motions; the rests give

* the gravity direction of each orientation (what the intrinsic/orientation checks compare),
* the white-noise level of every triad (residual spread about each rest's mean).

Detection (:func:`detect_static`) looks at a centred moving-window spread of each IMU's outputs,
``sqrt(trace(Cov_window)/3)`` (the RMS over axes of the per-axis windowed std; rotation
invariant, so the sensor frame does not matter and a slow turn at constant |f| is still seen),
averaged over IMUs.  Its noise floor is a low quantile of that statistic over the recording
(the rests are the quiet majority of a calibration recording); a sample is static where both the
accelerometer and the gyroscope statistic stay below ``factor`` × floor (and below absolute caps,
so a recording with no rest at all does not declare its quietest motion static).  Runs shorter
than ``min_duration_s`` are dropped after trimming ``trim_s`` off both ends of every run.

Directions are compared in the ARRAY frame (sensor outputs rotated by R(q)ᵀ of the nominal
orientations, DESIGN §7.0), so IMUs mounted upside-down agree with the others.
"""
from __future__ import annotations

import numpy as np
import torch
from scipy.ndimage import uniform_filter1d

from ..errors import UserError
from ..physics.models import to_array_frame

__all__ = [
    "detect_static",
    "static_segments",
    "segment_labels",
    "mask_from_labels",
    "segment_means",
    "gravity_directions",
    "cluster_orientations",
    "estimate_noise_std",
    "difference_noise_std",
    "angle_deg",
    "StaticAnalysis",
    "analyse_static",
]


# ---------------------------------------------------------------------------------------- helpers
def _window_samples(time: np.ndarray, window_s: float) -> int:
    dt = float(np.median(np.diff(time))) if time.size > 1 else 1.0
    w = int(round(window_s / dt)) if dt > 0 else 1
    return max(3, w | 1)  # odd, so the window is centred on its sample


def _moving_spread(x: np.ndarray, w: int) -> tuple[np.ndarray, np.ndarray]:
    """Centred moving-window spread sqrt(trace(Cov)/3) of (T, K, 3) → (T, K), plus a (T, K)
    flag of windows that touched a non-finite sample (those are never static)."""
    bad = ~np.isfinite(x).all(-1)  # (T, K)
    xf = np.where(np.isfinite(x), x, 0.0)
    # Subtracting the per-channel median first keeps the running sums free of cancellation.
    xf = xf - np.median(xf, axis=0, keepdims=True)
    m = uniform_filter1d(xf, w, axis=0, mode="nearest")
    m2 = uniform_filter1d(xf * xf, w, axis=0, mode="nearest")
    var = np.maximum(m2 - m * m, 0.0).mean(-1)
    touched = uniform_filter1d(bad.astype(np.float64), w, axis=0, mode="nearest") > 0
    return np.sqrt(var), touched


def _present(x: np.ndarray) -> np.ndarray:
    """(K,) IMUs with at least one finite sample (absent triads are all-NaN, DESIGN §7.1)."""
    return np.isfinite(x).any(axis=(0, 2))


def _runs(mask: np.ndarray) -> np.ndarray:
    """(S, 2) half-open [start, stop) index pairs of the True runs of a 1-D bool mask."""
    m = np.concatenate(([False], np.asarray(mask, dtype=bool), [False]))
    d = np.diff(m.astype(np.int8))
    return np.stack((np.flatnonzero(d == 1), np.flatnonzero(d == -1)), axis=1)


# ---------------------------------------------------------------------------------------- detection
def detect_static(
    acc: np.ndarray,
    gyro: np.ndarray | None,
    time: np.ndarray,
    *,
    window_s: float = 0.5,
    factor: float = 3.0,
    floor_quantile: float = 0.1,
    acc_abs_max: float = 0.5,
    gyro_abs_max: float = 0.05,
    min_duration_s: float = 3.0,
    trim_s: float = 0.25,
    return_stats: bool = False,
):
    """Find the samples at which the array rests.

    Parameters
    ----------
    acc : (T, K, 3) m/s² — accelerometer outputs (any frame; the statistic is rotation invariant).
    gyro : (T, K, 3) rad/s or None — gyroscope outputs (NaN for IMUs without one).
    time : (T,) s — strictly increasing.
    window_s : moving-window length, s (rounded to an odd number of samples, at least 3).
    factor : a sample is static where the windowed spread is below ``factor`` × its noise floor.
    floor_quantile : the noise floor is this quantile of the windowed spread over the recording
        (valid while at least that fraction of the recording rests).
    acc_abs_max, gyro_abs_max : absolute caps on the thresholds, m/s² and rad/s (keep a
        recording with no rest from calling its quietest motion static).
    min_duration_s : shortest static run kept, s (after trimming).
    trim_s : removed from both ends of every static run, s (transients at the edges).
    return_stats : also return a dict with the statistics and thresholds used.

    Returns
    -------
    mask : (T,) bool — True where static.  With ``return_stats``: ``(mask, stats)``.
    """
    acc = np.asarray(acc, dtype=np.float64)
    time = np.asarray(time, dtype=np.float64)
    if acc.ndim != 3 or acc.shape[-1] != 3:
        raise UserError(f"acc: expected shape (T, K, 3), got {acc.shape}")
    T = acc.shape[0]
    if time.shape != (T,):
        raise UserError(f"time: expected shape ({T},), got {time.shape}")
    if gyro is not None:
        gyro = np.asarray(gyro, dtype=np.float64)
        if gyro.shape != acc.shape:
            raise UserError(f"gyro: expected shape {acc.shape} like acc, got {gyro.shape}")
    if not (0 < floor_quantile < 1) or factor <= 1:
        raise UserError("detect_static: expected 0 < floor_quantile < 1 and factor > 1")
    if T < 3:
        mask = np.zeros(T, dtype=bool)
        return (mask, {}) if return_stats else mask

    w = _window_samples(time, window_s)
    dt = float(np.median(np.diff(time)))
    stats = {"window_samples": w, "dt": dt}
    ok = np.ones(T, dtype=bool)
    for name, x, cap in (("acc", acc, acc_abs_max), ("gyro", gyro, gyro_abs_max)):
        if x is None:
            continue
        pres = _present(x)
        if not pres.any():
            continue
        spread, touched = _moving_spread(x[:, pres], w)
        s = spread.mean(1)
        valid = ~touched.any(1)
        floor = float(np.quantile(s[valid], floor_quantile)) if valid.any() else np.inf
        thr = min(factor * floor, cap)
        ok &= valid & (s < thr)
        stats[f"{name}_spread"] = s
        stats[f"{name}_floor"] = floor
        stats[f"{name}_threshold"] = thr

    # Trim both ends of every run, then drop short ones (both in samples of the median step).
    trim = int(round(trim_s / dt)) if dt > 0 else 0
    min_len = int(np.ceil(min_duration_s / dt)) if dt > 0 else 1
    mask = np.zeros(T, dtype=bool)
    for a, b in _runs(ok):  # one iteration per rest: a handful, not per sample
        a, b = a + trim, b - trim
        if b - a >= max(min_len, 1):
            mask[a:b] = True
    return (mask, stats) if return_stats else mask


def static_segments(mask: np.ndarray) -> list[tuple[int, int]]:
    """Half-open ``(start, stop)`` sample-index pairs of the static runs of a (T,) bool mask."""
    return [(int(a), int(b)) for a, b in _runs(mask)]


def segment_labels(mask: np.ndarray) -> np.ndarray:
    """(T,) str array: ``"static"`` where ``mask``, else ``"dynamic"`` (DESIGN §7.1 ``segment``)."""
    return np.where(np.asarray(mask, dtype=bool), "static", "dynamic").astype("<U7")


def mask_from_labels(segment: np.ndarray) -> np.ndarray:
    """(T,) bool from a §7.1 ``segment`` label array (True where ``"static"``)."""
    return np.asarray(segment).astype(str) == "static"


# ---------------------------------------------------------------------------------------- rests
def segment_means(x: np.ndarray, segments, orientations: np.ndarray | None = None) -> np.ndarray:
    """(S, K, 3) mean of (T, K, 3) outputs over each ``(start, stop)`` segment.

    With ``orientations`` (K, 4) the means are rotated into the ARRAY frame (R(q)ᵀ, DESIGN §7.0).
    """
    x = np.asarray(x, dtype=np.float64)
    segs = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    c = np.concatenate((np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)), axis=0)
    n = (segs[:, 1] - segs[:, 0]).astype(np.float64)
    means = (c[segs[:, 1]] - c[segs[:, 0]]) / n[:, None, None]
    if orientations is not None:
        q = torch.as_tensor(np.asarray(orientations, dtype=np.float64))
        means = to_array_frame(torch.as_tensor(means), q).numpy()
    return means


def gravity_directions(means_array: np.ndarray) -> np.ndarray:
    """(S, 3) unit "up" directions of each rest (the specific force at rest is −g, i.e. it points
    up), from (S, K, 3) array-frame means: each IMU's mean normalised, averaged over the IMUs
    present, normalised."""
    m = np.asarray(means_array, dtype=np.float64)
    u = m / np.linalg.norm(m, axis=-1, keepdims=True)
    d = np.nanmean(u, axis=1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors (..., 3), degrees (atan2 form: accurate near 0° and 180°)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), (a * b).sum(-1)))


def cluster_orientations(directions: np.ndarray, tol_deg: float = 2.0, *, neighbours_only: bool = False) -> np.ndarray:
    """Group rests into distinct orientations.

    directions : (S, 3) gravity directions of the rests, in time order.
    tol_deg : two rests whose directions agree within this angle are the same orientation.
    neighbours_only : False (default): single linkage over all pairs of rests, so rests whose
        directions agree within ``tol_deg`` — directly or through a chain of such rests — are
        one orientation, and a later return to an earlier orientation is not a new one (exp_2 of
        the MIMU data ends with a rest on the face it rested on at ~437 s).  True: only
        consecutive rests merge (a rest split by a bump); every return counts again.

    Returns (S,) int labels 0..n−1 in order of first appearance.
    """
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    S = d.shape[0]
    if S == 0:
        return np.zeros(0, dtype=np.int64)
    if neighbours_only:
        new = np.concatenate(([True], angle_deg(d[1:], d[:-1]) > tol_deg))
        return np.cumsum(new) - 1
    # Single linkage: connected components of the "within tol" graph (S is tens, so S² is fine).
    adj = angle_deg(d[:, None, :], d[None, :, :]) <= tol_deg
    lab = np.arange(S)
    while True:  # label propagation to the minimum label in each component; ≤ S rounds
        new = np.where(adj, lab[None, :], S).min(1)
        if np.array_equal(new, lab):
            break
        lab = new
    # Each component carries its smallest member index, so ascending order is first appearance.
    return np.searchsorted(np.unique(lab), lab).astype(np.int64)


def estimate_noise_std(x: np.ndarray, segments, *, min_segments: int = 1) -> np.ndarray:
    """White-noise std per IMU from rests, (K,) in the units of ``x``.

    For every IMU and axis the samples of each static segment have that segment's mean removed;
    the pooled variance is Σ r² / (N − S) (N samples in S segments: one degree of freedom per
    removed mean).  The per-axis variances are averaged and the square root taken (the RMS of the
    per-axis stds), the σ of an isotropic N(0, σ² I₃) noise model ([C21] eq. 5).
    NaN for IMUs with no finite data.
    """
    x = np.asarray(x, dtype=np.float64)
    segs = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    S = segs.shape[0]
    if S < min_segments:
        raise UserError(f"estimate_noise_std: expected at least {min_segments} static segment(s), got {S}")
    idx = np.concatenate([np.arange(a, b) for a, b in segs]) if S else np.zeros(0, dtype=np.int64)
    seg_id = np.repeat(np.arange(S), segs[:, 1] - segs[:, 0])
    means = segment_means(x, segs)  # (S, K, 3)
    r = x[idx] - means[seg_id]
    dof = idx.size - S
    if dof <= 0:
        raise UserError("estimate_noise_std: static segments too short to estimate a spread")
    var = (r * r).sum(0) / dof  # (K, 3)
    return np.sqrt(var.mean(-1))


def difference_noise_std(x: np.ndarray, segments) -> np.ndarray:
    """(K,) noise std from first differences within each rest: sqrt(mean over axes of
    Var(Δx)/2).  For white noise it equals :func:`estimate_noise_std`; a ratio
    pooled/difference far from 1 flags coloured or tonal noise (> 1: slow or low-frequency
    content; < 1: content near the Nyquist rate)."""
    x = np.asarray(x, dtype=np.float64)
    segs = np.asarray(segments, dtype=np.int64).reshape(-1, 2)
    d = np.concatenate([np.diff(x[a:b], axis=0) for a, b in segs if b - a >= 2]) if len(segs) else np.zeros((0,) + x.shape[1:])
    if d.shape[0] < 2:
        raise UserError("difference_noise_std: static segments too short to estimate a spread")
    return np.sqrt((d.var(0) / 2).mean(-1))


# ---------------------------------------------------------------------------------------- summary
class StaticAnalysis:
    """Everything the rests of a recording tell: segments, array-frame means, gravity
    directions, orientation labels and noise levels (see :func:`analyse_static`)."""

    def __init__(self, mask, segments, acc_means, gyro_means, directions, orientation_labels,
                 acc_noise_std, gyro_noise_std, stats):
        self.mask = mask
        self.segments = segments
        self.acc_means = acc_means  # (S, K, 3) array frame, m/s²
        self.gyro_means = gyro_means  # (S, K, 3) array frame, rad/s, or None
        self.directions = directions  # (S, 3)
        self.orientation_labels = orientation_labels  # (S,)
        self.acc_noise_std = acc_noise_std  # (K,)
        self.gyro_noise_std = gyro_noise_std  # (K,) or None
        self.stats = stats

    @property
    def n_segments(self) -> int:
        return len(self.segments)

    @property
    def n_orientations(self) -> int:
        return int(self.orientation_labels.max() + 1) if len(self.orientation_labels) else 0


def analyse_static(acc, gyro, time, orientations=None, *, tol_deg: float = 2.0,
                   neighbours_only: bool = False, mask=None, **static_kwargs) -> StaticAnalysis:
    """Detect rests (unless ``mask`` is given), then their array-frame means, gravity directions,
    orientation clusters (``tol_deg``) and the pooled noise std of acc and gyro per IMU.

    ``orientations`` (K, 4): nominal array → sensor quaternions; identity if None.
    ``static_kwargs`` go to :func:`detect_static`.
    """
    stats = {}
    if mask is None:
        mask, stats = detect_static(acc, gyro, time, return_stats=True, **static_kwargs)
    segs = static_segments(mask)
    K = np.asarray(acc).shape[1]
    if orientations is None:
        orientations = np.tile([1.0, 0.0, 0.0, 0.0], (K, 1))
    if segs:
        am = segment_means(acc, segs, orientations)
        gm = segment_means(gyro, segs, orientations) if gyro is not None else None
        dirs = gravity_directions(am)
        labels = cluster_orientations(dirs, tol_deg, neighbours_only=neighbours_only)
        an = estimate_noise_std(acc, segs)
        gn = estimate_noise_std(gyro, segs) if gyro is not None else None
    else:
        am = np.zeros((0, K, 3))
        gm = None if gyro is None else np.zeros((0, K, 3))
        dirs = np.zeros((0, 3))
        labels = np.zeros(0, dtype=np.int64)
        an = np.full(K, np.nan)
        gn = None if gyro is None else np.full(K, np.nan)
    return StaticAnalysis(np.asarray(mask, dtype=bool), segs, am, gm, dirs, labels, an, gn, stats)

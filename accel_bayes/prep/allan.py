"""Bias random walk from the rests: the Allan variance of static stretches, with its uncertainty.

What the VIO tools call ``*_random_walk`` (Kalibr, OpenVINS) is K, the density of the white
noise that drives the bias: b' = K w(t), units m s-3/√Hz (accelerometer) or rad s-2/√Hz (gyro).
Their ``*_noise_density`` is N, the white measurement noise, units m s-2/√Hz or rad s-1/√Hz.
For a static sensor the Allan variance of cluster means of length τ is

    AVAR(τ) = N²/τ + K² τ / 3

(IEEE Std 952-1997, Annex C).  The white part falls with τ, the random walk grows with it; they
cross at τ_c = √3 N / K.  K is only seen where τ well above τ_c still leaves several
independent clusters inside the static stretches: they must be many τ_c long in all.  Measured
with :func:`static_time_needed` (one stretch, doubling from 60 s): EuRoC's stated ADIS16448
gyro (N = 1.7e-4 rad/s/√Hz, K = 1.9e-5 rad/s²/√Hz, τ_c ≈ 15 s) needs 240 s; a MEMS gyro with
N = 5.8e-5 (0.2 °/√h) and K = 2e-6 (τ_c ≈ 50 s) 960 s; every halving of K doubles τ_c, so
better sensors need of the order of an hour.  Rests of seconds to a minute, as a calibration
recording has, give no random walk (two stretches of ≈ 10 τ_c in all just pass).

Estimator.  Within every static stretch (runs of the recording's ``segment == "static"``
samples; differences are never taken across two stretches, so orientation changes between
rests do not enter), non-overlapping clusters of m = 1, 2, 4, … samples give D(τ) squared
differences of adjacent cluster means over the three axes; their half-mean is the AVAR estimate.
(N², K²/3) are fitted by weighted least squares on the AVAR estimates with variances
2·AVAR(τ)²·c(τ)/D(τ) from the fitted model (iterated), c the inflation that the correlation of
adjacent differences brings (ρ = −½ for white noise, +¼ for a random walk; c = 1 + 2ρ²).  The
standard error of K̂ is a parametric bootstrap: the fit repeated on series simulated from
(N̂, K̂) with the recording's stretch lengths (the AVARs at neighbouring τ share data, so the
WLS standard error alone is ≈ 1.5× too small).

Criterion (:data:`RELATIVE_SE_MAX`).  The estimate is used when its standard error is at most
25 % of K̂ (50 % of K̂²).  That is the static-time criterion stated in terms the data decide:
how long the rests must be follows from N, K and the rate, and :func:`static_time_needed`
gives it; it is checked on simulated series with a known K in ``tests/test_allan.py`` and
``experiments/allan_criterion.md`` (RMS z 1.1–1.25 where the rests are long enough).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RELATIVE_SE_MAX", "AllanRandomWalk", "static_runs", "allan_random_walk", "static_time_needed"]

# se(K̂)/K̂ at most this; se(K̂²)/K̂² = 2× it (first order).
RELATIVE_SE_MAX = 0.25


@dataclass
class AllanRandomWalk:
    """A random-walk estimate from rests.

    k : K̂, units/s/√Hz (m s-3/√Hz or rad s-2/√Hz); NaN where the fit gives K̂² ≤ 0.
    k_se : its standard error (first order: se(K̂²) / 2K̂).
    n_density : N̂, units·√s (m s-2/√Hz or rad s-1/√Hz).
    static_s : total static time used, s; longest_s : the longest stretch, s.
    accepted : k_se ≤ RELATIVE_SE_MAX · k.
    """

    k: float
    k_se: float
    n_density: float
    static_s: float
    longest_s: float
    accepted: bool


def static_runs(segment, min_samples: int = 4) -> list[tuple[int, int]]:
    """(start, stop) index pairs of the runs of ``segment == "static"`` with at least
    ``min_samples`` samples (half-open, in sample order)."""
    st = np.asarray(segment).astype(str) == "static"
    if not st.any():
        return []
    edges = np.flatnonzero(np.diff(np.r_[0, st.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2]) if b - a >= min_samples]


def _avar_table(x: np.ndarray, runs, min_clusters: int = 3):
    """(τ in samples, AVAR estimate, D) over octave cluster lengths; x (T, 3).  Clusters of 2m
    samples are the means of adjacent pairs of clusters of m, so all octaves cost O(T)."""
    levels = [x[a:b] for a, b in runs]
    out = []
    m = 1
    while levels and max(len(c) for c in levels) >= min_clusters:
        ssq, D = 0.0, 0
        for c in levels:
            if len(c) >= 2:
                d = np.diff(c, axis=0)
                ssq += float((d * d).sum())
                D += d.size
        if D:
            out.append((m, 0.5 * ssq / D, D))
        levels = [0.5 * (c[0:len(c) // 2 * 2:2] + c[1:len(c) // 2 * 2:2]) for c in levels if len(c) >= 2]
        m *= 2
    return out


def _fit(x: np.ndarray, runs, rate: float, iterations: int = 4):
    """WLS (N², K²/3) on the AVAR table; None where it has fewer than two cluster lengths."""
    table = _avar_table(x, runs)
    if len(table) < 2:
        return None
    tau = np.array([t[0] for t in table], dtype=np.float64) / rate
    y = np.array([t[1] for t in table])
    D = np.array([t[2] for t in table], dtype=np.float64)
    A = np.stack([1.0 / tau, tau], -1)
    model = y.copy()
    theta = np.array([y[0] * tau[0], 0.0])
    for _ in range(iterations):
        white = np.clip(theta[0] / tau, 0.0, None)
        walk = np.clip(theta[1] * tau, 0.0, None)
        f = white / np.maximum(white + walk, 1e-300)
        rho = -0.5 * f + 0.25 * (1.0 - f)
        W = D / (2.0 * np.maximum(model, 1e-300) ** 2 * (1.0 + 2.0 * rho ** 2))
        cov = np.linalg.inv(A.T @ (W[:, None] * A))
        theta = cov @ (A.T @ (W * y))
        model = np.maximum(A @ theta, 0.1 * y.min())
    return theta, cov


def _simulate(n_density: float, k: float, lengths, rate: float, rng) -> np.ndarray:
    """Static stretches of white noise N plus a random walk K, three axes, one after another."""
    T = int(sum(lengths))
    x = n_density * math.sqrt(rate) * rng.standard_normal((T, 3))
    walk = k / math.sqrt(rate) * rng.standard_normal((T, 3))
    a = 0
    for n in lengths:
        x[a:a + n] += np.cumsum(walk[a:a + n], 0)
        a += n
    return x


def allan_random_walk(x, runs, rate: float, *, replicates: int = 30, seed: int = 0) -> AllanRandomWalk | None:
    """Fit N and K (module docstring) to one triad's static stretches.

    x : (T, 3) outputs, SI units, sampled at ``rate`` Hz within each run.
    runs : (start, stop) index pairs of the static stretches (:func:`static_runs`).
    replicates, seed : the standard error of K̂ is the spread of the estimate over ``replicates``
        series simulated from the fitted (N̂, K̂) with the same stretches (parametric bootstrap,
        seeded): the AVAR estimates at neighbouring τ share their data, and the WLS standard
        error, which treats them as independent, is ≈ 1.5× too small (measured).
    Returns None when no stretch allows three clusters of two samples.
    """
    x = np.asarray(x, dtype=np.float64)
    runs = [(a, b) for a, b in runs if b - a >= 6]
    if not runs or not (rate > 0):
        return None
    fit = _fit(x, runs, rate)
    if fit is None:
        return None
    theta, cov = fit
    lengths = [b - a for a, b in runs]
    secs = np.array(lengths) / rate
    n_hat = math.sqrt(max(theta[0], 0.0))
    k2 = 3.0 * theta[1]
    if not k2 > 0:
        return AllanRandomWalk(k=math.nan, k_se=math.inf, n_density=n_hat, static_s=float(secs.sum()),
                               longest_s=float(secs.max()), accepted=False)
    k = math.sqrt(k2)
    wls_se = 3.0 * math.sqrt(max(cov[1, 1], 0.0)) / (2.0 * k)
    if wls_se > RELATIVE_SE_MAX * k:
        # The bootstrap se is larger still (≈ 1.5×): refused without spending it.
        return AllanRandomWalk(k=k, k_se=wls_se, n_density=n_hat, static_s=float(secs.sum()),
                               longest_s=float(secs.max()), accepted=False)
    rng = np.random.default_rng(seed)
    sim_runs, a = [], 0
    for n in lengths:
        sim_runs.append((a, a + n))
        a += n
    boot = []
    for _ in range(replicates):
        boot.append(3.0 * _fit(_simulate(n_hat, k, lengths, rate, rng), sim_runs, rate)[0][1])
    k_se = float(np.std(boot, ddof=1)) / (2.0 * k)  # se(K̂²) → se(K̂), first order
    return AllanRandomWalk(k=k, k_se=k_se, n_density=n_hat, static_s=float(secs.sum()), longest_s=float(secs.max()),
                           accepted=bool(k_se <= RELATIVE_SE_MAX * k))


def static_time_needed(n_density: float, k: float, rate: float, *, seed: int = 0, max_s: float = 4 * 3600.0) -> float:
    """Shortest single static stretch, s (doubling from 60 s), whose :func:`allan_random_walk`
    meets :data:`RELATIVE_SE_MAX` on a simulated series with white noise ``n_density`` and random
    walk ``k`` at ``rate`` Hz (seeded); ``inf`` beyond ``max_s``.  For stating the criterion in
    seconds for a given sensor."""
    rng = np.random.default_rng(seed)
    L = 60.0
    while L <= max_s:
        T = int(L * rate)
        x = (n_density * math.sqrt(rate) * rng.standard_normal((T, 3))
             + np.cumsum(k / math.sqrt(rate) * rng.standard_normal((T, 3)), 0))
        est = allan_random_walk(x, [(0, T)], rate)
        if est is not None and est.accepted:
            return L
        L *= 2
    return math.inf

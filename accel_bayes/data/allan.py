"""Bias random walk from the rests: the Allan variance of static stretches, with its uncertainty.

What the VIO tools call ``*_random_walk`` (Kalibr, OpenVINS) is K, the density of the white
noise that drives the bias: b' = K w(t), units m s-3/√Hz (accelerometer) or rad s-2/√Hz (gyro).
Their ``*_noise_density`` is N, the white measurement noise, units m s-2/√Hz or rad s-1/√Hz.
For a static sensor the Allan variance of cluster means of length τ is

    AVAR(τ) = N²/τ + K² τ / 3

(IEEE Std 952-1997, Annex C).  The white part falls with τ, the random walk grows with it; they
cross at τ_c = √3 N / K.  K is only seen where τ well above τ_c still leaves several
independent clusters inside one static stretch: it must be many τ_c long (criterion below).
How long, for a given sensor, :func:`static_time_needed` measures (``experiments/allan_criterion.md``):
EuRoC's stated ADIS16448 gyro (N = 1.7e-4 rad/s/√Hz, K = 1.9e-5 rad/s²/√Hz, τ_c ≈ 15 s) needs
minutes; a MEMS gyro with N = 5.8e-5 (0.2 °/√h) and K = 2e-6 (τ_c ≈ 50 s) about a quarter of an
hour; τ_c grows as 1/K, so better sensors need an hour and more.  Rests of seconds to half a
minute, as a calibration recording has, give no random walk.

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

Criterion (:data:`RELATIVE_SE_MAX`, :data:`MIN_STRETCH_TAU_C`).  The estimate is used when its
standard error is at most 25 % of K̂ (50 % of K̂²) and the longest stretch is at least 20 τ̂_c
long (τ̂_c = √3 N̂/K̂).  The second condition puts the estimate on cluster lengths where the
random walk dominates: three clusters of a 20 τ_c stretch are 6.7 τ_c long, where K²τ/3 is 44×
N²/τ.  Many short rests meet the first condition alone through the small rise of the Allan
variance near τ_c, where any slow disturbance of a hand-placed rest (residual motion, tilt,
temperature) reads as a random walk: on MIMU4444 experiment 1 (20 rests, 460 s, the longest
28 s) the first condition alone accepts apparent random walks of ≈ 1e-3 m/s³/√Hz
(accelerometers) and 1e-4–2e-4 rad/s²/√Hz (two gyros) with τ̂_c of 2.5–11 s; the second
refuses them all (at 10 τ̂_c one gyro's would still pass).  The criterion is checked on
simulated series with a known K in ``tests/data/test_allan.py`` and
``experiments/allan_criterion.md`` (RMS z 1.1–1.25 where the rests are long enough).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RELATIVE_SE_MAX", "MIN_STRETCH_TAU_C", "AllanRandomWalk", "static_runs", "allan_random_walk", "static_time_needed"]

# se(K̂)/K̂ at most this; se(K̂²)/K̂² = 2× it (first order).
RELATIVE_SE_MAX = 0.25
# And the longest stretch at least this many crossover times τ̂_c = √3 N̂/K̂ (see the module docstring).
MIN_STRETCH_TAU_C = 20.0


@dataclass
class AllanRandomWalk:
    """A random-walk estimate from rests.

    k : K̂, units/s/√Hz (m s-3/√Hz or rad s-2/√Hz); NaN where the fit gives K̂² ≤ 0.
    k_se : its standard error (first order: se(K̂²) / 2K̂).
    n_density : N̂, units·√s (m s-2/√Hz or rad s-1/√Hz).
    static_s : total static time used, s; longest_s : the longest stretch, s.
    accepted : k_se ≤ RELATIVE_SE_MAX · k and longest_s ≥ MIN_STRETCH_TAU_C · √3 n_density / k.
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
    tau_c = math.sqrt(3.0) * n_hat / k
    if wls_se > RELATIVE_SE_MAX * k or secs.max() < MIN_STRETCH_TAU_C * tau_c:
        # Refused without the bootstrap (whose se is larger still, ≈ 1.5× the WLS one).
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
                           accepted=bool(k_se <= RELATIVE_SE_MAX * k and secs.max() >= MIN_STRETCH_TAU_C * tau_c))


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

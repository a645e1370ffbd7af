"""A timing error that wanders: the exact marginal likelihood of an AR(1) sampling-instant error on
one sensor triad, and its two parameters fitted by maximum marginal likelihood.

Model (linearised in the timing error, as ``time_offset`` and ``sampling_jitter`` are): per
sample t the triad's whitened residual is

    r̃_t = ũ_t δ_t + e_t,   e_t ~ N(0, I₃),

ũ_t the whitened output rate (the direction a timing error moves the output, s⁻¹ per unit noise)
and δ_t (s) a stationary Gauss–Markov process with standard deviation σ_δ and correlation
φ_t = ρ^(Δt_t/Δt₀) between consecutive samples (ρ the lag-one correlation at the median step Δt₀;
across a selection gap the correlation decays with the gap's length).  ρ = 0 is white jitter in
its Gaussian form; ρ → 1 a slowly drifting time offset.  Free-running sensor clocks sampled by a
host at a fixed rate give such a process (a beat between the two clocks that wanders with the
clocks' frequencies); on the real MIMU4444 recordings the gyroscope residuals of every IMU look
like it (``accel_bayes.mismatch.characterise``: lag-one autocorrelation 0.5–0.9, excess 3–5×
larger along the rate than across it; ``experiments/mimu_mismatch.md``).

Marginal over δ (Woodbury and the determinant lemma; U is block-diagonal with the columns ũ_t, so
UᵀU = diag(a)):

    log N(r̃; 0, I + U Σ Uᵀ) − log N(r̃; 0, I) = ½ bᵀ P⁻¹ b − ½ log|P| + ½ log|Q|,

a_t = ũ_tᵀũ_t, b_t = ũ_tᵀr̃_t, Q = Σ⁻¹ the tridiagonal precision of the AR(1) process and
P = Q + diag(a), also tridiagonal: O(T) with LAPACK's banded Cholesky (no loop over samples in
Python).  :func:`ar1_gain` is that difference; :func:`fit_wander` maximises it over (σ_δ, ρ).
``tests/mismatch/test_wander.py`` checks it against the dense Gaussian computation and against simulated
processes.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["ar1_precision_bands", "ar1_gain", "ar1_conditional_mean", "fit_wander", "sample_steps"]


def _phis(steps: np.ndarray, rho: float) -> np.ndarray:
    """(T−1,) correlation between consecutive samples, ρ^(step) (step in median sample steps)."""
    rho = min(max(float(rho), 0.0), 0.9999)  # the Hessian's finite differences may step outside
    return np.power(rho, np.asarray(steps, dtype=float)) if rho > 0 else np.zeros(len(steps))


def ar1_precision_bands(T: int, steps: np.ndarray, sigma: float, rho: float):
    """The AR(1) precision Q (T × T, tridiagonal) in LAPACK upper banded form (2, T), and log|Q|.

    δ_0 ~ N(0, σ²), δ_t = φ_t δ_{t−1} + √(1 − φ_t²)·σ·ε_t: Q = LᵀL/σ² with L bidiagonal."""
    phi = _phis(steps, rho)
    c = 1.0 / (1.0 - phi ** 2)  # (T−1,) 1/(1−φ²)
    diag = np.ones(T)
    diag[1:] = c
    diag[:-1] += phi ** 2 * c
    off = -phi * c
    ab = np.zeros((2, T))
    ab[0, 1:] = off / sigma ** 2
    ab[1] = diag / sigma ** 2
    logdet = -T * math.log(sigma ** 2) - float(np.log1p(-phi ** 2).sum())
    return ab, logdet


def _posterior(a, b, steps, sigma: float, rho: float, c2: float):
    """The posterior of δ given (a, b): P = Q + diag(a)/c², banded Cholesky; returns
    (P⁻¹ b/c² (T,), log|P|, log|Q|) — the conditional mean and the two determinants of the
    marginal (module docstring)."""
    from scipy.linalg import cho_solve_banded, cholesky_banded

    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    P, logdet_q = ar1_precision_bands(len(a), steps, sigma, rho)
    P[1] += a / c2
    cP = cholesky_banded(P, lower=False)
    return cho_solve_banded((cP, False), b / c2), 2.0 * float(np.log(cP[1]).sum()), logdet_q


def ar1_gain(a: np.ndarray, b: np.ndarray, steps: np.ndarray, sigma: float, rho: float, c: float = 1.0,
             rr: float | None = None, n: int | None = None) -> float:
    """Marginal log-likelihood gain (nats) of the AR(1) timing error, with white noise of
    variance c² (in units of the stated noise), over N(0, I) (module docstring; c = 1: the stated
    noise).  a (T,) s⁻², b (T,) s⁻¹ per sample; steps (T−1,) the time steps in units of the
    median step; sigma (s) > 0; 0 ≤ rho < 1; for c ≠ 1 also rr = Σ r̃ᵀr̃ and n = the number of
    residuals (3T for a complete triad)."""
    b = np.asarray(b, dtype=float)
    c2 = float(c) ** 2
    x, logdet_p, logdet_q = _posterior(a, b, steps, sigma, rho, c2)
    gain = 0.5 * float((b / c2) @ x) - 0.5 * logdet_p + 0.5 * logdet_q
    if c2 != 1.0:
        if rr is None or n is None:
            raise ValueError("ar1_gain: c != 1 needs rr and n")
        gain += -0.5 * rr / c2 + 0.5 * rr - 0.5 * n * math.log(c2)
    return gain


def ar1_conditional_mean(a, b, steps, sigma: float, rho: float, c: float = 1.0) -> np.ndarray:
    """E[δ | r] (T,) in s: the conditional mean (BLUP) of the AR(1) timing error given the
    residuals, (Q + diag(a)/c²)⁻¹ b/c² (module docstring; same arguments as :func:`ar1_gain`).
    With the restricted a, b of :func:`accel_bayes.mismatch.jitter.jitter_ab` it is the GLS
    estimate of δ with the per-sample motion states profiled out, so y − E[δ]·rate refitted by
    least squares gives the GLS mean of the motion (Henderson's mixed-model equations)."""
    if sigma <= 0:
        return np.zeros(len(a))
    return _posterior(a, b, steps, sigma, rho, float(c) ** 2)[0]


def _noise_only_gain(rr: float, n: int) -> tuple[float, float]:
    """(c, gain over N(0, I)) of the best white-noise-only model N(0, c² I)."""
    c2 = max(rr / n, 1e-300)
    return math.sqrt(c2), -0.5 * rr / c2 + 0.5 * rr - 0.5 * n * math.log(c2)


def fit_wander(a, b, steps, *, sigma_max: float, rho_max: float = 0.995, rr: float | None = None,
               n: int | None = None) -> dict:
    """Maximise :func:`ar1_gain` over σ_δ ∈ (0, sigma_max] s and ρ ∈ [0, rho_max] — and, given
    rr = Σ r̃ᵀr̃ and n, over the white-noise factor c too, so that a residual excess that does not
    lie along the rate is left to c instead of inflating σ_δ (a coarse grid, then L-BFGS-B in
    (log σ, ρ[, log c])).

    Returns {"sigma" s, "rho", "c" (1 when not fitted), "gain" nats over the noise-only model
    (N(0, I), or N(0, c₀² I) at its best c₀ when c is fitted), "evidence" = 2·gain (the likelihood
    ratio against no wander, σ = 0 on the boundary), "sigma_std", "rho_std" (approximate, from the
    inverse Hessian)}."""
    from scipy.optimize import minimize

    fit_c = rr is not None and n is not None
    c0, g0 = _noise_only_gain(rr, n) if fit_c else (1.0, 0.0)

    def gain(ls, r, lc):
        return ar1_gain(a, b, steps, math.exp(ls), r, math.exp(lc), rr, n) if fit_c else \
            ar1_gain(a, b, steps, math.exp(ls), r)

    sig_grid = sigma_max * np.logspace(-3, 0, 7)
    rho_grid = np.array([0.0, 0.5, 0.8, 0.95])
    rho_grid = rho_grid[rho_grid <= rho_max]
    c_grid = c0 * np.array([0.5, 1.0]) if fit_c else [1.0]
    best = (g0, None)
    for sg in sig_grid:
        for r in rho_grid:
            for cc in c_grid:
                g = gain(math.log(sg), r, math.log(cc))
                if g > best[0]:
                    best = (g, (math.log(sg), r, math.log(cc)))
    if best[1] is None:
        return {"sigma": 0.0, "rho": 0.0, "c": c0, "gain": 0.0, "evidence": 0.0, "sigma_std": None, "rho_std": None}
    npar = 3 if fit_c else 2

    def nll(p):
        return -gain(p[0], p[1], p[2] if fit_c else 0.0)

    x0 = np.array(best[1][:npar])
    bounds = [(math.log(sigma_max) - 12, math.log(sigma_max)), (0.0, rho_max)] + \
        ([(math.log(c0) - 5, math.log(c0) + 1)] if fit_c else [])
    res = minimize(nll, x0, method="L-BFGS-B", bounds=bounds)
    x = np.asarray(res.x, dtype=float) if -res.fun >= best[0] else x0
    g = -nll(x)
    sig_std = rho_std = None
    try:  # a finite-difference Hessian of the negative log-likelihood at the optimum
        h = 1e-3
        H = np.zeros((npar, npar))
        E = np.eye(npar) * h
        for i in range(npar):
            for j in range(npar):
                H[i, j] = (nll(x + E[i] + E[j]) - nll(x + E[i] - E[j]) - nll(x - E[i] + E[j]) + nll(x - E[i] - E[j])) / (4 * h * h)
        C = np.linalg.inv(H)
        if np.all(np.diag(C) > 0):
            sig_std = math.exp(x[0]) * math.sqrt(C[0, 0])
            rho_std = math.sqrt(C[1, 1])
    except (np.linalg.LinAlgError, ValueError):
        pass
    return {"sigma": math.exp(x[0]), "rho": float(x[1]), "c": math.exp(x[2]) if fit_c else 1.0, "gain": g - g0,
            "evidence": 2.0 * (g - g0), "sigma_std": sig_std, "rho_std": rho_std}


def sample_steps(time) -> np.ndarray:
    """(T−1,) the steps between consecutive sample times in units of the median step: the
    ``steps`` the AR(1) correlation decays over (ρ^step; a selection gap is a long step)."""
    t = np.asarray(time, dtype=float)
    dt = np.diff(t)
    return dt / float(np.median(dt)) if len(dt) else np.zeros(0)

"""Accelerometer noise as a hyperparameter, estimated from the data (issue #6 item 2).

Why
---
On real recordings the white-noise std measured at rest (σ_rest ≈ 0.04 m/s² on the MIMU4444)
does not describe what the [C21] model leaves unexplained during vigorous motion: uncalibrated
gyro scale factors and misalignments (errors growing with |ω|), sensor non-linearity, the
sample-time skew between IMUs.  With σ_rest the MAP residuals are ~25–35× the stated noise
(χ²/dof ≈ 800–1400 on the six MIMU experiments) and the posterior is far too narrow.

What is estimated (default of the real-data pipeline, :func:`accel_bayes.pipelines.calibrate.calibrate`)
---------------------------------------------------------------------------------------------
1. **A noise level per triad, σ_k, by type-II maximum likelihood at the MAP** (below).  On the
   MIMU data σ_k ≈ 1.3–2.0 m/s².
2. **A misspecification factor κ from the sandwich covariance** (:func:`~accel_bayes.inference.noise_fit.sandwich_inflation`):
   with σ_k fitted, the residuals are still not the model's white noise — their size grows
   ~6× from slow to fast samples and part of them is common to the triads of a sample (a gyro
   error moves every triad's centripetal term), so the Laplace covariance under-states the
   variability of the estimate.  The sandwich A⁻¹BA⁻¹ (scores with Newey–West lags) measures
   it: ~1.7× the Laplace std on every MIMU experiment (κ ≈ 2.8–3.1, stable across lags 0–40,
   i.e. not a time-correlation effect).  The likelihood is then tempered, p(y | θ)^(1/κ)
   (:class:`~accel_bayes.model.tempering.TemperedLikelihood`, a coarsened / generalised-Bayes posterior): the posterior
   widens by ≈ √κ and its mode stays where the fitted model puts it.  Tempering, not just
   σ·√κ: the Occam factor |M(θ)|^(−T/2) of the φ integral does not scale with σ, so inflating
   σ alone would let it pull the geometry inward (by 0.37 mm on exp_1, ~8 posterior std).

Optional rate-dependent model (``bins > 1``)
--------------------------------------------
e_t,k ~ N(0, σ_k² s_t² I₃), s_t = s_b(t) a factor per quantile bin b of the gyro rate |ω̄_t|
(mean of s_t² over the samples = 1).  Implemented without touching the likelihood: because
u(ω) is quadratic, u(ω)/s = u(ω/√s), and φ_t is free (flat prior), so

    y_t/s_t = G(θ) u(ω_t/√s_t) + H(θ) φ_t' + e_t/s_t

turns the heteroscedastic model into the homoscedastic one exactly, up to a θ-free constant
(:func:`scale_samples`).  It is NOT the default: on the MIMU data (8 bins, s_b ≈ 0.1–1.7) it
up-weights the slow samples, whose errors turned out to be just as systematic, and the spread
of the six experiments' estimates grew (e.g. IMU 4 x: 44 → 107 µm) while the posterior std
shrank — the sandwich then still said ×1.4–1.9.

Type-II ML of the levels
------------------------
The marginal likelihood of (σ, s), with φ_t integrated out exactly (flat prior, DESIGN §4) and
ω_t by a Laplace approximation about the MAP ω̂_t, is stationary where (REML-type fixed point)

    σ_k² = Σ_t ‖r_t,k‖²/s_t² / Σ_t d_t,k,      s_b² = Σ_{t∈b} Σ_k ‖r_t,k‖²/σ_k² / Σ_{t∈b} Σ_k d_t,k,

with r_t,k the residual of triad k (φ projected out) and d_t,k = 3 − h^φ_t,k − h^ω_t,k its
residual degrees of freedom: h^φ the leverage of triad k's rows in the φ projection (6 per
sample in all) and h^ω in the ω̂_t fit (≤ 3 per sample; ~0 when the gyros pin ω down).  With
one level for all triads and ω known this is the exact REML estimate of a Gaussian linear model
with 6 nuisance parameters per sample (tests/model/test_preprocess.py checks it against the
likelihood).  :func:`~accel_bayes.inference.noise_fit.fit_map_with_noise` alternates the MAP with this update until the levels
move by less than ``rtol``.  PmMH then samples with the noise fixed there (empirical Bayes):
with ~10⁵ residual degrees of freedom the uncertainty of the levels themselves (< 1 %) is
ignored.

What none of this fixes: errors that repeat from one experiment to the next (e.g. a gyro scale
error biases the spacing the same way every time) look like signal, not noise; only an
independent reference could reveal them.  ``experiments/mimu_repeatability.py`` checks what
can be checked: the scatter across experiments against the posterior std.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from ..constants import DEFAULT_RATE_BINS
from ..data.outputs import to_jsonable
from ..errors import UserError
from ..physics.jacobians import du_domega
from ..physics.models import G_matrix, H_matrix, u_of_omega

__all__ = ["NoiseModel", "residual_statistics", "update_noise", "scale_samples", "rate_bins", "std_per_triad",
           "NOISE_MODES", "DEFAULT_RATE_BINS"]

NOISE_MODES = ("auto", "stated", "estimate")


@dataclass
class NoiseModel:
    """The fitted noise model e_t,k ~ N(0, σ_k² s_t² I₃) (module docstring).

    std : (A,) m/s² — σ_k, rows of the likelihood (``imu_labels`` order).
    bin_edges : (B+1,) rad/s — |ω̄| bin edges (first 0, last inf).
    bin_scale : (B,) — s_b (sample-mean of s_t² is 1).
    stated : (A,) m/s² — the std the recording stated.
    chi2_per_dof_stated : float — χ²/dof of the first MAP with the stated std (1 if it was right).
    dof : (A,) — residual degrees of freedom per triad at the end.
    history : per round {"std", "bin_scale", "map_iterations"}.
    """

    std: np.ndarray
    bin_edges: np.ndarray
    bin_scale: np.ndarray
    stated: np.ndarray
    chi2_per_dof_stated: float = float("nan")
    dof: np.ndarray | None = None
    bin_counts: np.ndarray | None = None
    history: list = field(default_factory=list)
    converged: bool = True

    @property
    def bins(self) -> int:
        return int(len(self.bin_scale))

    @property
    def factor(self) -> np.ndarray:
        """(A,) σ_k / stated."""
        return self.std / self.stated

    def sample_scale(self, omega_norm) -> np.ndarray:
        """(T,) s_t for gyro rates |ω̄_t| (rad/s)."""
        w = np.asarray(omega_norm, dtype=np.float64)
        b = np.clip(np.searchsorted(self.bin_edges, w, side="right") - 1, 0, self.bins - 1)
        return np.asarray(self.bin_scale)[b]

    def to_dict(self) -> dict:
        def L(x):  # 1-D, as floats, null where not finite (strict JSON)
            return None if x is None else to_jsonable(np.asarray(x, dtype=np.float64), nonfinite="null")
        return {
            "model": "e_tk ~ N(0, (std_k * s_t)^2 I3), s_t = bin_scale[bin of |mean gyro_t|]; type-II ML at the MAP",
            "std": L(self.std), "stated": L(self.stated), "factor": L(self.factor),
            "bin_edges_rad_s": L(self.bin_edges), "bin_scale": L(self.bin_scale), "bin_counts": L(self.bin_counts),
            "chi2_per_dof_stated": float(self.chi2_per_dof_stated), "dof": L(self.dof),
            "rounds": self.history, "converged": bool(self.converged),
        }


def std_per_triad(acc_noise_std, A) -> np.ndarray:
    """(A,) m/s²: one noise std per triad from a scalar, (A,) or (A, 3) (per-axis stds are
    combined as the root mean square); refused unless finite and > 0."""
    s = np.asarray(acc_noise_std, dtype=np.float64)
    if s.ndim == 0:
        s = np.full(A, float(s))
    elif s.shape == (A, 3):
        s = np.sqrt((s**2).mean(-1))
    if s.shape != (A,):
        raise UserError(f"acc_noise_std: expected a scalar, ({A},) or ({A}, 3), got {s.shape}")
    if not np.isfinite(s).all() or (s <= 0).any():
        raise UserError("acc_noise_std: expected finite values > 0")
    return s


def scale_samples(acc, omega_mean, omega_cov, scale):
    """The heteroscedastic model as a homoscedastic one: (acc/s_t, ω̄_t/√s_t, P_t/s_t).

    acc (T, A, 3), omega_mean (T, 3), omega_cov (T, 3, 3), scale (T,) > 0.  Exact because u(ω)
    is quadratic and φ_t has a flat prior (module docstring).  Returns float64 tensors."""
    s = torch.as_tensor(np.asarray(scale, dtype=np.float64))
    if s.dim() != 1 or not bool((s > 0).all()):
        raise UserError("scale: expected a (T,) array of positive factors")
    acc = torch.as_tensor(acc, dtype=torch.float64)
    return (acc / s[:, None, None], torch.as_tensor(omega_mean, dtype=torch.float64) / s.sqrt()[:, None],
            torch.as_tensor(omega_cov, dtype=torch.float64) / s[:, None, None])


def residual_statistics(acc, positions, omega_hat, omega_cov, acc_noise_std, *, chunk: int = 4096) -> dict:
    """Residuals and their degrees of freedom at a mode (θ, ω̂), for the noise update.

    acc : (T, A, 3) m/s², array frame.  positions : (A, 3) m.  omega_hat : (T, 3) rad/s (ω at
    the mode).  omega_cov : (T, 3, 3) the gyro posterior covariance.  acc_noise_std : (A,) or
    scalar — the weights of the fit.
    Returns {"rss": (T, A) ‖r_t,k‖² (m/s²)², "dof": (T, A) d_t,k = 3 − h^φ_t,k − h^ω_t,k}.
    """
    acc = torch.as_tensor(acc, dtype=torch.float64)
    if acc.dim() != 3 or acc.shape[-1] != 3:
        raise UserError(f"acc: expected shape (T, A, 3), got {tuple(acc.shape)}")
    T, A, _ = acc.shape
    pos = torch.as_tensor(positions, dtype=torch.float64)
    if pos.shape != (A, 3):
        raise UserError(f"positions: expected shape ({A}, 3), got {tuple(pos.shape)}")
    w_hat = torch.as_tensor(omega_hat, dtype=torch.float64)
    P = torch.as_tensor(omega_cov, dtype=torch.float64)
    if w_hat.shape != (T, 3) or P.shape != (T, 3, 3):
        raise UserError(f"omega_hat/omega_cov: expected shapes ({T}, 3) and ({T}, 3, 3)")
    s = torch.as_tensor(std_per_triad(acc_noise_std, A))
    sl = s.repeat_interleave(3).reciprocal()  # Λ^{1/2}
    Hw = sl[:, None] * H_matrix(pos)
    Gw = sl[:, None] * G_matrix(pos)
    Minv = torch.linalg.inv(Hw.T @ Hw)
    h_phi = (Hw @ Minv * Hw).sum(-1)  # (3A,) leverage of each row in the φ projection
    Pperp = torch.eye(3 * A, dtype=torch.float64) - Hw @ Minv @ Hw.T
    Pinv = torch.linalg.inv(P)
    y = acc.reshape(T, 3 * A)
    rss = torch.empty(T, A, dtype=torch.float64)
    dof = torch.empty(T, A, dtype=torch.float64)
    for a in range(0, T, chunk):  # memory only: T / 4096 iterations
        b = min(T, a + chunk)
        z = y[a:b] * sl - u_of_omega(w_hat[a:b]) @ Gw.T  # Λ^{1/2}(y − G u(ω̂))
        r = (z @ Pperp) / sl  # φ projected out, back to m/s²
        rss[a:b] = (r * r).reshape(b - a, A, 3).sum(-1)
        J = Pperp @ (Gw @ du_domega(w_hat[a:b]))  # (n, 3A, 3) whitened, φ-projected ∂r/∂ω
        Hom = J.transpose(-1, -2) @ J + Pinv[a:b]
        lev = (J * torch.linalg.solve(Hom, J.transpose(-1, -2)).transpose(-1, -2)).sum(-1)  # (n, 3A)
        dof[a:b] = (1.0 - h_phi - lev).reshape(b - a, A, 3).sum(-1)
    return {"rss": rss.numpy(), "dof": dof.numpy()}


def update_noise(stats: dict, bin_index: np.ndarray, n_bins: int, sigma0, *, inner: int = 50,
                 tol: float = 1e-10):
    """Solve the REML fixed point for (σ_k, s_b) at fixed residuals (module docstring).

    stats : from :func:`residual_statistics` with the residuals in ORIGINAL units (rss of the
    unscaled model).  bin_index : (T,) bin of each sample.  Returns (σ (A,), s (B,)), s
    normalised so that the sample-mean of s_t² is 1."""
    rss, dof = np.asarray(stats["rss"]), np.asarray(stats["dof"])
    b = np.asarray(bin_index, dtype=np.int64)
    dof_k = dof.sum(0)
    if (dof_k <= 0).any():
        raise UserError("noise: too few samples to estimate the noise (non-positive residual dof)")
    dof_b = np.bincount(b, weights=dof.sum(1), minlength=n_bins)
    sig2 = np.asarray(sigma0, dtype=np.float64) ** 2
    s2 = np.ones(n_bins)
    for _ in range(inner):  # alternating exact updates of a concave problem: converges fast
        st2 = s2[b]
        sig2_new = (rss / st2[:, None]).sum(0) / dof_k
        num = np.bincount(b, weights=(rss / sig2_new).sum(1), minlength=n_bins)
        s2_new = np.where(dof_b > 0, num / np.where(dof_b > 0, dof_b, 1.0), 1.0)
        c = s2_new[b].mean()  # normalise: mean_t s_t² = 1, the level goes into σ
        s2_new, sig2_new = s2_new / c, sig2_new * c
        done = np.abs(sig2_new / sig2 - 1).max() < tol and np.abs(s2_new / s2 - 1).max() < tol
        sig2, s2 = sig2_new, s2_new
        if done:
            break
    return np.sqrt(sig2), np.sqrt(s2)


def rate_bins(omega_norm, n_bins: int) -> np.ndarray:
    """(B+1,) edges of ``n_bins`` quantile bins of the rates (first 0, last inf)."""
    n_bins = int(n_bins)
    if n_bins < 1:
        raise UserError(f"bins: expected an integer >= 1, got {n_bins}")
    w = np.asarray(omega_norm, dtype=np.float64)
    inner = np.quantile(w, np.linspace(0, 1, n_bins + 1)[1:-1]) if n_bins > 1 else np.zeros(0)
    return np.concatenate(([0.0], inner, [np.inf]))

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
2. **A misspecification factor κ from the sandwich covariance** (:func:`sandwich_inflation`):
   with σ_k fitted, the residuals are still not the model's white noise — their size grows
   ~6× from slow to fast samples and part of them is common to the triads of a sample (a gyro
   error moves every triad's centripetal term), so the Laplace covariance under-states the
   variability of the estimate.  The sandwich A⁻¹BA⁻¹ (scores with Newey–West lags) measures
   it: ~1.7× the Laplace std on every MIMU experiment (κ ≈ 2.8–3.1, stable across lags 0–40,
   i.e. not a time-correlation effect).  The likelihood is then tempered, p(y | θ)^(1/κ)
   (:class:`TemperedLikelihood`, a coarsened / generalised-Bayes posterior): the posterior
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
with 6 nuisance parameters per sample (tests/test_preprocess.py checks it against the
likelihood).  :func:`fit_map_with_noise` alternates the MAP with this update until the levels
move by less than ``rtol``.  PmMH then samples with the noise fixed there (empirical Bayes):
with ~10⁵ residual degrees of freedom the uncertainty of the levels themselves (< 1 %) is
ignored.

What none of this fixes: errors that repeat from one experiment to the next (e.g. a gyro scale
error biases the spacing the same way every time) look like signal, not noise; only an
independent reference could reveal them.  ``experiments/mimu_repeatability.py`` checks what
can be checked: the scatter across experiments against the posterior std.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..constants import DEFAULT_PRIOR_STD, DEFAULT_RATE_BINS
from ..data.outputs import to_jsonable
from ..errors import UserError
from .likelihood import RaoBlackwellLikelihood, positions_from_theta
from ..physics.models import G_matrix, H_matrix, acc_noise_std_per_axis, u_of_omega
from .phi_prior import PhiPrior
from ..physics.jacobians import du_domega

__all__ = ["NoiseModel", "residual_statistics", "update_noise", "scale_samples", "fit_map_with_noise",
           "sandwich_inflation", "rate_bins", "TemperedLikelihood", "fit_map_tempered", "NOISE_MODES",
           "DEFAULT_RATE_BINS"]

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


def _std_rows(acc_noise_std, A) -> np.ndarray:
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
    s = torch.as_tensor(_std_rows(acc_noise_std, A))
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


def fit_map_with_noise(acc, omega_mean, omega_cov, acc_noise_std, *, reference: int = 0, prior_mean=None,
                       prior_std=DEFAULT_PRIOR_STD, bins: int = DEFAULT_RATE_BINS, max_rounds: int = 8, rtol: float = 0.01,
                       fit_kwargs: dict | None = None, covariate=None):
    """Alternate the MAP and the type-II ML noise update until σ and s move by < ``rtol``.

    Arguments as :func:`accel_bayes.inference.map.fit_map` (array frame, m/s², rad/s, m);
    ``bins``: number of |ω̄| quantile bins of the rate-dependent factor (1: one σ per triad).
    ``covariate``: (T,) values whose quantile bins carry the factor instead of |ω̄_t| (e.g. |ω̇_t|,
    rad/s²); ``model.sample_scale`` must then be given the same values.
    Each round warm-starts the MAP from the previous mode.  Returns ``(map_result, model)``:
    the MAP of the SCALED data (:func:`scale_samples` with ``model.sample_scale(|ω̄|)``; its
    positions are those of the original problem, its ω is scaled by 1/√s_t) and the
    :class:`NoiseModel`.  A MAP that diverges is returned as it is (check ``converged``).
    """
    from ..inference.map import fit_map

    kw = dict(on_divergence="ignore")
    kw.update(fit_kwargs or {})
    acc = torch.as_tensor(acc, dtype=torch.float64)
    omega_mean = torch.as_tensor(omega_mean, dtype=torch.float64)
    omega_cov = torch.as_tensor(omega_cov, dtype=torch.float64)
    A = acc.shape[1]
    stated = _std_rows(acc_noise_std, A)
    wn = omega_mean.norm(dim=-1).numpy() if covariate is None else np.asarray(covariate, dtype=np.float64)
    if wn.shape != (acc.shape[0],) or not np.isfinite(wn).all():
        raise UserError(f"covariate: expected {acc.shape[0]} finite values, got shape {wn.shape}")
    edges = rate_bins(wn, bins)
    bidx = np.clip(np.searchsorted(edges, wn, side="right") - 1, 0, len(edges) - 2)
    counts = np.bincount(bidx, minlength=len(edges) - 1)
    sigma, sb = stated.copy(), np.ones(len(edges) - 1)
    res = fit_map(acc, omega_mean, omega_cov, sigma, reference=reference, prior_mean=prior_mean,
                  prior_std=prior_std, **kw)
    hist, chi2_0, converged = [], float("nan"), False
    st = None
    for _ in range(int(max_rounds)):
        if not bool(torch.isfinite(torch.as_tensor(res.theta)).all()):
            break
        s_t = sb[bidx]
        a_s, w_s, P_s = scale_samples(acc, omega_mean, omega_cov, s_t)
        st = residual_statistics(a_s, res.positions, res.omega, P_s, sigma)
        if not hist:
            chi2_0 = float((st["rss"] / sigma**2).sum() / st["dof"].sum())
        st["rss"] = st["rss"] * (s_t**2)[:, None]  # residuals of the unscaled model
        new_sigma, new_sb = update_noise(st, bidx, len(sb), sigma)
        change = max(float(np.abs(new_sigma / sigma - 1).max()), float(np.abs(new_sb / sb - 1).max()))
        hist.append({"std": [float(v) for v in new_sigma], "bin_scale": [float(v) for v in new_sb],
                     "map_iterations": int(res.n_iter)})
        # warm start: ω of the mode in the new scaling
        omega_orig = res.omega * torch.as_tensor(np.sqrt(s_t))[:, None]
        sigma, sb = new_sigma, new_sb
        s_t = sb[bidx]
        a_s, w_s, P_s = scale_samples(acc, omega_mean, omega_cov, s_t)
        res = fit_map(a_s, w_s, P_s, sigma, reference=reference, prior_mean=prior_mean, prior_std=prior_std,
                      init_positions=res.positions, init_omega=omega_orig / torch.as_tensor(np.sqrt(s_t))[:, None],
                      **kw)
        if change < rtol:
            converged = True
            break
    model = NoiseModel(std=sigma, bin_edges=edges, bin_scale=sb, stated=stated, chi2_per_dof_stated=chi2_0,
                       dof=None if st is None else st["dof"].sum(0), bin_counts=counts, history=hist,
                       converged=converged)
    return res, model


def newey_west_lags(T: int) -> int:
    """The usual automatic Bartlett bandwidth floor(4 (T/100)^(2/9)) (Newey & West 1994)."""
    return int(math.floor(4.0 * (max(int(T), 1) / 100.0) ** (2.0 / 9.0)))


def sandwich_inflation(acc, omega_mean, omega_cov, acc_noise_std, map_result, *, reference: int = 0,
                       prior_mean=None, prior_std=DEFAULT_PRIOR_STD, lags: int | None = None, phi_prior=None,
                       cluster: str = "sample") -> dict:
    """How much wider the misspecification-robust (sandwich) covariance of θ is than the Laplace one.

    At the MAP of the (scaled) problem, with per-sample scores g_t = J̃_tᵀ r_t (r_t the whitened,
    φ-projected residual; J̃_t its θ-Jacobian with ω_t profiled out: J_θ − J_ω (J_ωᵀJ_ω +
    P_t⁻¹)⁻¹ J_ωᵀJ_θ), B = Σ_t g_t g_tᵀ + Σ_{l=1..L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ) (Newey–West,
    Bartlett weights, Γ_l = Σ_t g_t g_{t+l}ᵀ over the samples in time order; L = ``lags`` or
    :func:`newey_west_lags`).  The sandwich is C = A⁻¹ B A⁻¹ with A⁻¹ the Laplace covariance.
    If the model were right, B ≈ A (data part) and C ≈ A⁻¹.  Returns {"kappa": mean over
    coordinates of diag(C)/diag(A⁻¹) (average variance inflation), "std_ratio": (n,)
    sqrt of the per-coordinate ratios, "lags": L}.

    ``cluster``: the unit whose scores are summed before the outer product — "sample" (default:
    all 3A channels of a sample, so errors shared by the triads of a sample count), "triad" (each
    triad's 3 channels; shared errors across triads ignored) or "channel" (each channel alone).
    Comparing them splits the misspecification: "channel" sees heteroscedasticity only, "triad"
    adds the correlation within a triad, "sample" the correlation between triads.  The lag terms
    pair each unit with itself ``l`` samples later.  A unit smaller than the sample drops the
    (negative) correlations the φ projection itself puts between channels, so it is not 1 under
    the model: "std_ratio_white" (flat φ prior only, else None) is what the same clustering gives
    in expectation under the model's white noise, r_t = P⊥ e_t (B_white = Σ_t Σ_u J̃_tuᵀ P⊥_uu J̃_tu,
    P⊥ = I − Hw M⁻¹ Hwᵀ), and "std_ratio_relative" = std_ratio / std_ratio_white the misfit
    that clustering sees.
    """
    from ..inference.map import build_map_problem

    prob = build_map_problem(acc, omega_mean, omega_cov, acc_noise_std, reference=reference, prior_mean=prior_mean,
                             prior_std=prior_std, init_positions=map_result.positions, init_omega=map_result.omega,
                             phi_prior=phi_prior)
    res_by_name = {r.name: r for r in prob.sample_residuals}
    accr, gyr = res_by_name["acc"], res_by_name["gyro"]
    g = {"theta": torch.as_tensor(map_result.theta, dtype=torch.float64)}
    x = torch.as_tensor(map_result.omega, dtype=torch.float64)
    r = accr.fn(g, x, accr.data)
    Jd, Jw = accr.jac(g, x, accr.data)
    Jt = Jd["theta"]
    Li = gyr.data[1]
    Hww = Jw.transpose(-1, -2) @ Jw + Li.transpose(-1, -2) @ Li
    Jp = Jt - Jw @ torch.linalg.solve(Hww, Jw.transpose(-1, -2) @ Jt)
    if cluster not in ("sample", "triad", "channel"):
        raise UserError(f"cluster: expected 'sample', 'triad' or 'channel', got {cluster!r}")
    T, m, n = Jp.shape
    A = int(torch.as_tensor(acc).shape[1])
    if cluster != "sample" and m != 3 * A:
        raise UserError(f"cluster: {cluster!r} needs the flat phi prior (the residual has {m} rows, not 3A = {3 * A})")
    per = {"sample": m, "triad": 3, "channel": 1}[cluster]
    if cluster == "sample":
        s = (Jp.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1)  # (T, n)
    else:  # rows are triad-major (3 per triad), as the likelihood stacks them
        s = (Jp * r.unsqueeze(-1)).reshape(T, m // per, per, n).sum(2).reshape(T * (m // per), n)  # (T·units, n)
    L = newey_west_lags(T) if lags is None else int(lags)
    B = s.T @ s
    u = m // per
    for lag in range(1, min(L, T - 1) + 1):  # L ≈ 10: a handful of (n × n) products
        Gm = s[:-lag * u].T @ s[lag * u:]  # unit c of sample t with unit c of sample t + lag
        B = B + (1.0 - lag / (L + 1.0)) * (Gm + Gm.T)
    Ainv = torch.as_tensor(map_result.laplace_cov, dtype=torch.float64)
    C = Ainv @ B @ Ainv
    ratio = torch.diagonal(C) / torch.diagonal(Ainv)
    out = {"kappa": float(ratio.mean()), "std_ratio": ratio.clamp_min(0).sqrt().numpy(), "lags": L}
    if m == 3 * A:  # flat φ prior: r_t = P⊥ z_t, P⊥ the same for every sample
        Hw = _sqrt_lam_rows(acc_noise_std, A)[:, None] * H_matrix(torch.as_tensor(map_result.positions, dtype=torch.float64))
        Pp = torch.eye(m, dtype=torch.float64) - Hw @ torch.linalg.solve(Hw.T @ Hw, Hw.T)
        mask = torch.block_diag(*[torch.ones(per, per, dtype=torch.float64)] * (m // per))
        Bw = torch.einsum("tci,cd,tdj->ij", Jp, Pp * mask, Jp)
        white = (torch.diagonal(Ainv @ Bw @ Ainv) / torch.diagonal(Ainv)).clamp_min(0).sqrt().numpy()
        out["std_ratio_white"] = white
        out["std_ratio_relative"] = out["std_ratio"] / white
    else:
        out["std_ratio_white"] = out["std_ratio_relative"] = None
    return out


def _sqrt_lam_rows(acc_noise_std, A: int) -> torch.Tensor:
    """(3A,) Λ^{1/2}: 1/σ per row, triad-major (the whitening of the likelihood's rows)."""
    return acc_noise_std_per_axis(acc_noise_std, A, dtype=torch.float64).reshape(3 * A).reciprocal()


# ---------------------------------------------------------------------------- tempering (coarsening)

class TemperedLikelihood(RaoBlackwellLikelihood):
    """The [C21] likelihood raised to the power 1/κ (a coarsened / generalised-Bayes posterior).

    Constructed like :class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood` with the noise
    std ALREADY scaled by √κ: that tempers the Gaussian exponent (and integrates ω under the
    correspondingly wider likelihood).  The Occam factor −(T/2) log|M(θ)| of the φ integral does
    not scale with σ (only shifts by a constant), so :meth:`log_phat` re-weights it to
    −(T/(2κ)) log|M(θ)| by adding the deterministic (1 − 1/κ)(T/2) log|M(θ)|.  p̂ times a
    deterministic function of θ is an unbiased estimator of that function × p, so PmMH stays
    exact for the tempered target.

    With a proper prior N(0, F) on φ (``phi_prior``, the UNtempered F) the sample's density is
    N(y; Gu, Q + HFHᵀ); its power 1/κ is the Gaussian with covariance κ(Q + HFHᵀ), i.e. noise
    std × √κ AND F × κ (done here), times |Q + HFHᵀ|^(−1/(2κ)), whose θ-part is
    |M + F⁻¹|^(−1/(2κ)) — unchanged under that joint scaling up to a constant, so the same Occam
    re-weighting applies with M + F⁻¹ in place of M.
    """

    def __init__(self, acc, omega, acc_noise_std, num_draws, kappa: float, reference: int = 0,
                 dtype=torch.float64, device=None, phi_prior=None):
        self.kappa = float(kappa)
        if not self.kappa >= 1.0:
            raise UserError(f"kappa: expected a factor >= 1, got {kappa!r}")
        prior = PhiPrior.coerce(phi_prior, dtype=dtype, device=device)
        super().__init__(acc, omega, acc_noise_std, num_draws, reference=reference, dtype=dtype, device=device,
                         phi_prior=None if prior is None else prior.scaled(self.kappa))

    def occam_correction(self, positions) -> torch.Tensor:
        """(1 − 1/κ)(T/2) log|M(θ) + F⁻¹| for positions (..., A, 3) (M alone for the flat prior);
        O(A) per θ and invariant to a common translation (H(r + c) = H(r)·E with det E = 1)."""
        r = self._positions(positions)
        H = H_matrix(r)
        M = self._with_phi_prior(H.transpose(-1, -2) @ (self.lam[:, None] * H))
        return (1.0 - 1.0 / self.kappa) * 0.5 * self.T * torch.linalg.slogdet(M)[1]

    def log_phat(self, positions, *args, **kwargs) -> torch.Tensor:
        """log p̂ of the [C21] estimator plus the Occam re-weighting (class docstring)."""
        out = super().log_phat(positions, *args, **kwargs)
        return out + self.occam_correction(positions).to(out.dtype).reshape(out.shape)


def fit_map_tempered(acc, omega_mean, omega_cov, acc_noise_std, kappa: float, *, reference: int = 0,
                     prior_mean=None, prior_std=DEFAULT_PRIOR_STD, init_positions=None, init_omega=None, max_iter: int = 100,
                     phi_prior=None):
    """MAP and Laplace covariance of the tempered posterior (:class:`TemperedLikelihood`):
    :func:`accel_bayes.inference.map.build_map_problem` with ``acc_noise_std`` (already × √κ)
    and its log|M| term weighted by 1/κ; solved by the same Levenberg–Marquardt.  Returns a
    :class:`~accel_bayes.inference.map.MAPResult` (``converged`` False and a NaN covariance when
    the Hessian is not positive definite).  ``phi_prior``: the untempered prior on φ (scaled by κ
    here, as in :class:`TemperedLikelihood`)."""
    from ..inference.lm.linear import NotPositiveDefinite
    from ..inference.lm import ExtraCost, LevenbergMarquardt
    from ..inference.map import MAPResult, build_map_problem

    prior = PhiPrior.coerce(phi_prior)
    prob = build_map_problem(acc, omega_mean, omega_cov, acc_noise_std, reference=reference, prior_mean=prior_mean,
                             prior_std=prior_std, init_positions=init_positions, init_omega=init_omega,
                             phi_prior=None if prior is None else prior.scaled(kappa))
    w = 1.0 / float(kappa)
    prob.extra = [ExtraCost(lambda g, e=e: w * e.fn(g), grad_hess=lambda g, e=e: tuple(w * v for v in e.grad_hess(g)),
                            step_hessian=e.step_hessian, name=e.name) for e in prob.extra]
    lm = LevenbergMarquardt(None, max_iter=max_iter, desc="MAP").solve(prob)
    converged, reason = lm.converged, lm.reason
    theta = lm.values["theta"]
    try:
        if not bool(torch.isfinite(theta).all()):
            raise NotPositiveDefinite("non-finite")
        cov = lm.covariance("exact")
    except NotPositiveDefinite:
        cov = torch.full((prob.n_free, prob.n_free), float("nan"), dtype=torch.float64)
        converged, reason = False, f"{reason}; Hessian not positive definite at the end point"
    ref = prob.map_info["reference"]
    pos = positions_from_theta(theta, ref, theta.shape[0] + 1)
    return MAPResult(positions=pos, theta=theta, omega=lm.locals, laplace_cov=cov, log_posterior=-lm.cost,
                     cost_terms=prob.cost_terms(lm.values, lm.locals), log=lm.log, converged=converged,
                     reason=reason, n_iter=lm.n_iter, reference=ref, lm=lm)

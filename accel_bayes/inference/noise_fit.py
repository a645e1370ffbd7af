"""MAP fits of the model with the noise levels estimated, the sandwich measure of misspecification
and the MAP of the tempered posterior (issue #6 item 2; the model, its estimators and why:
:mod:`accel_bayes.model.noise` and :mod:`accel_bayes.model.tempering`).  They run the MAP solver
(:mod:`.map`, :mod:`.lm`), hence their place in ``inference``.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..constants import DEFAULT_PRIOR_STD, DEFAULT_RATE_BINS
from ..errors import UserError
from ..model.likelihood import positions_from_theta
from ..model.noise import NoiseModel, rate_bins, residual_statistics, scale_samples, std_per_triad, update_noise
from ..model.phi_prior import PhiPrior
from ..model.unresolved_fit import per_sample_scores  # noqa: F401 (public here too; lives in the model layer)
from ..physics.models import H_matrix, acc_noise_std_per_axis
from .lm import ExtraCost, LevenbergMarquardt
from .lm.linear import NotPositiveDefinite
from .map import MAPResult, build_map_problem, fit_map

__all__ = ["fit_map_with_noise", "newey_west_lags", "newey_west_meat", "score_sandwich", "per_sample_scores",
           "sandwich_inflation", "fit_map_tempered"]


def fit_map_with_noise(acc, omega_mean, omega_cov, acc_noise_std, *, reference: int = 0, prior_mean=None,
                       prior_std=DEFAULT_PRIOR_STD, bins: int = DEFAULT_RATE_BINS, max_rounds: int = 8, rtol: float = 0.01,
                       fit_kwargs: dict | None = None, covariate=None):
    """Alternate the MAP and the type-II ML noise update until σ and s move by < ``rtol``.

    Arguments as :func:`accel_bayes.inference.map.fit_map` (array frame, m/s², rad/s, m);
    ``bins``: number of |ω̄| quantile bins of the rate-dependent factor (1: one σ per triad).
    ``covariate``: (T,) values whose quantile bins carry the factor instead of |ω̄_t| (e.g. |ω̇_t|,
    rad/s²); ``model.sample_scale`` must then be given the same values.
    Each round warm-starts the MAP from the previous mode.  Returns ``(map_result, model)``:
    the MAP of the SCALED data (:func:`~accel_bayes.model.noise.scale_samples` with ``model.sample_scale(|ω̄|)``; its
    positions are those of the original problem, its ω is scaled by 1/√s_t) and the
    :class:`~accel_bayes.model.noise.NoiseModel`.  A MAP that diverges is returned as it is (check ``converged``).
    """
    kw = dict(on_divergence="ignore")
    kw.update(fit_kwargs or {})
    acc = torch.as_tensor(acc, dtype=torch.float64)
    omega_mean = torch.as_tensor(omega_mean, dtype=torch.float64)
    omega_cov = torch.as_tensor(omega_cov, dtype=torch.float64)
    A = acc.shape[1]
    stated = std_per_triad(acc_noise_std, A)
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
    Ainv = torch.as_tensor(map_result.laplace_cov, dtype=torch.float64)
    out = score_sandwich(s, Ainv, units=m // per, lags=lags)
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


def newey_west_meat(scores: torch.Tensor, *, units: int = 1, lags: int | None = None) -> tuple[torch.Tensor, int]:
    """(B (n, n), L): Σ_t g_t g_tᵀ + Σ_{l=1..L} (1 − l/(L+1)) (Γ_l + Γ_lᵀ), Bartlett weights, of the
    scores ``scores`` (T·units, n) in time order, ``units`` consecutive rows per sample; Γ_l pairs
    each unit with itself ``l`` samples later.  L = ``lags`` or :func:`newey_west_lags` (T)."""
    s = torch.as_tensor(scores, dtype=torch.float64)
    u = int(units)
    T = s.shape[0] // u
    L = newey_west_lags(T) if lags is None else int(lags)
    B = s.T @ s
    for lag in range(1, min(L, T - 1) + 1):  # L ≈ 10: a handful of (n × n) products
        Gm = s[:-lag * u].T @ s[lag * u:]
        B = B + (1.0 - lag / (L + 1.0)) * (Gm + Gm.T)
    return B, L


def score_sandwich(scores, laplace_cov, *, units: int = 1, lags: int | None = None) -> dict:
    """The sandwich C = A⁻¹ B A⁻¹ (B: :func:`newey_west_meat` of ``scores``) against the Laplace
    covariance A⁻¹ = ``laplace_cov`` (n, n) (units of θ²).  Returns {"kappa": mean of the
    per-coordinate variance ratios, "std_ratio": (n,) their square roots, "lags": L, "cov": C}."""
    Ainv = torch.as_tensor(laplace_cov, dtype=torch.float64)
    B, L = newey_west_meat(scores, units=units, lags=lags)
    C = Ainv @ B @ Ainv
    ratio = torch.diagonal(C) / torch.diagonal(Ainv)
    return {"kappa": float(ratio.mean()), "std_ratio": ratio.clamp_min(0).sqrt().numpy(), "lags": L, "cov": C}


def _sqrt_lam_rows(acc_noise_std, A: int) -> torch.Tensor:
    """(3A,) Λ^{1/2}: 1/σ per row, triad-major (the whitening of the likelihood's rows)."""
    return acc_noise_std_per_axis(acc_noise_std, A, dtype=torch.float64).reshape(3 * A).reciprocal()


def fit_map_tempered(acc, omega_mean, omega_cov, acc_noise_std, kappa: float, *, reference: int = 0,
                     prior_mean=None, prior_std=DEFAULT_PRIOR_STD, init_positions=None, init_omega=None, max_iter: int = 100,
                     phi_prior=None):
    """MAP and Laplace covariance of the tempered posterior (:class:`~accel_bayes.model.tempering.TemperedLikelihood`):
    :func:`accel_bayes.inference.map.build_map_problem` with ``acc_noise_std`` (already × √κ)
    and its log|M| term weighted by 1/κ; solved by the same Levenberg–Marquardt.  Returns a
    :class:`~accel_bayes.inference.map.MAPResult` (``converged`` False and a NaN covariance when
    the Hessian is not positive definite).  ``phi_prior``: the untempered prior on φ (scaled by κ
    here, as in :class:`~accel_bayes.model.tempering.TemperedLikelihood`)."""
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

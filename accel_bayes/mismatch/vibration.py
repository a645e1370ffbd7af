"""Aliased jerk at the gyros' sampling instants: the accelerometer misfit that couples the IMUs
(issue #11; ``experiments/acc_timing_check.md``).

Physics.  Each IMU k reads its triads at t + δ_kt, with δ a sampling-instant error of about a
millisecond that its gyro reveals (``timing_wander``).  An accelerometer read late by δ is off by
δ times the board's jerk at that instant.  On the MIMU4444 recordings that jerk is not the one the
62.5 Hz outputs resolve: it is white from sample to sample, about 2.7× larger and unrelated in
direction, as vibration above the 31 Hz Nyquist frequency, aliased, would give.  So it cannot be
predicted; it is a per-sample nuisance shared by every IMU of the rigid board, and only its
*pattern* across the IMUs is known — proportional to each IMU's instant error.

Model.  For sample t in |ω| band b(t) (quantile bands of :data:`accel_bayes.mismatch.budget.BANDS`),
with a_kt = R_kᵀ r̃_kt the accelerometer residual of IMU k in the array frame (r̃ = r/√(1 − h),
leverage-corrected as in the budget) and the instant error the IMU's own gyro residual gives

    δ_kt = r_g,kt · ġ_kt / (|ġ_kt|² + λ_k)   (s; ġ the fitted gyro output's rate, rad/s²;
                                             λ_k an empirical-Bayes shrinkage, :func:`instant_errors`),
    d_kt = δ_kt − mean_k δ_kt          (a common instant error is absorbed by the motion states),

    a_kt = d_kt j_t + e_kt,   j_t ~ N(0, s²_b I₃) (m/s³),   e_kt ~ N(0, v_kb I₃) ((m/s²)²).

Per array axis the K residuals of a sample are N(0, V_t + s² d_t d_tᵀ), V_t = diag(v_{k,b(t)}):
a rank-one update, so the density is exact in O(K) per sample (matrix determinant lemma,
Sherman–Morrison):

    log N = −½ [Σ_k a_k²/v_k − s² (Σ_k d_k a_k / v_k)² / (1 + s² c) + Σ_k log v_k + log(1 + s² c)
                + K log 2π],   c = Σ_k d_k² / v_k.

This is the accelerometer half of ``unresolved_motion`` with the gyros' instant errors as the
loading: the density and its fit are :func:`accel_bayes.mismatch.unresolved.marginal_loglik` and
:func:`~accel_bayes.mismatch.unresolved.fit_scales` (``coupled_loglik`` / ``fit_arrays`` here are
those, under their old names).

The null model is s² = 0: a white variance per IMU and |ω| band, the physics-free baseline of
``experiments/mimu_mismatch.py``.  Both are fitted by maximum likelihood (j_t marginalised); the
likelihood ratio against the null is the ``evidence``.  It is *not* χ²-distributed on real fits:
the per-sample motion states make the residuals of a sample correlated (the leverage correction
fixes each residual's variance, not their covariance, and inflates the variance across the IMUs
by about K/(K − 1)), and a rank-one term soaks that up — 0–55 on clean twins of 2 500 samples
(``tests/mismatch/test_vibration.py``).  Its significance is therefore a **permutation test**.  The
statistic is the likelihood ratio with the white variances held at the null's (each sample then
enters through two numbers, so it costs O(T)).  Its null distribution is the same statistic with
the instant-error rows permuted among the samples of each |ω| band, which keeps every
distribution and breaks only the pairing of an IMU's accelerometer with its own gyro's instant.  The predicted variance of the coupled part, s² d_kt² per axis,
is what it adds to the budget; the conditional mean E[d j | a] is its realised part.

Measured (``experiments/mimu_mismatch.md``, 2026-11-26): on the six recordings the coupling
explains 42–47 % of the accelerometer excess (39–55 % in every |ω| band), with likelihood ratios
5.9–7.1·10⁴; the permutation statistic is 3.6–4.3·10⁴ against at most 1.2·10³ in 19 permutations.  Fitted on one recording and
held fixed on another (30 pairs, the instant errors from the target's own gyros), it predicts the
accelerometers better than the banded white variance by +4.9 to +6.3 nats per sample on every
pair; with the target's instants permuted across samples it loses by 1.2–11.6 nats per sample.
What it leaves lies partly along the fitted jerk (0.42–0.49 of the power against 1/3): each
accelerometer's own instant differs from its gyro's by about 0.1–0.2 ms rms — not modelled.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from .budget import band_edges
from .model import ModelFit
from .prepared import Prepared
# one implementation of the marginal and its fit: the aliased jerk is unresolved_motion's acc half on
# the gyros' instant errors
from .unresolved import fit_scales as fit_arrays, marginal_loglik as coupled_loglik  # noqa: F401

__all__ = ["AliasedJerk", "instant_errors", "array_residuals", "coupled_loglik", "fit_aliased_jerk",
           "omega_edges", "fit_arrays"]

_FLOOR_RATE2 = 1e-9  # (rad/s²)²: below it a gyro's rate gives no instant (δ = 0 there)


def omega_edges(fit: ModelFit) -> list[float]:
    """Inner |ω| band edges (rad/s) of ``fit``'s motion (:func:`accel_bayes.mismatch.budget.band_edges`)."""
    return band_edges(np.linalg.norm(fit.x[:, 0:3].detach().cpu().numpy(), axis=1))


def _bands(fit: ModelFit, edges) -> torch.Tensor:
    w = np.linalg.norm(fit.x[:, 0:3].detach().cpu().numpy(), axis=1)
    return torch.as_tensor(np.digitize(w, np.asarray(edges, dtype=float)), dtype=torch.long)


def instant_errors(prep: Prepared, fit: ModelFit, *, shrink: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
    """(δ (T, K) s, valid (T, K) bool): each IMU's per-sample sampling-instant error as its gyro
    residual r_g gives it along the fitted gyro output's rate ġ (rad/s²); 0 and invalid where the
    gyro triad is not fully observed or |ġ|² is below 1e-9 (rad/s²)².

    ``shrink=False``: the least-squares instant δ = r_g·ġ/|ġ|², unbounded where ġ is small.
    ``shrink=True`` (default): its posterior mean under δ ~ N(0, τ_k²) and a white gyro misfit of
    variance σ_k² per axis, δ = r_g·ġ/(|ġ|² + σ_k²/τ_k²), with σ_k² the IMU's residual variance
    across ġ (the two perpendicular directions) and τ_k² = mean of δ_LS² − σ_k²/|ġ|² over the
    samples where |ġ|² is above its median (empirical Bayes, per IMU)."""
    rate = fit.ctx.gyro_rate
    if rate is None:
        from ..physics.effects.base import output_rates

        rate = output_rates(prep.time, fit.ctx.acc, fit.ctx.gyro)[1]
    rate = rate.to(fit.res_gyro)
    r = fit.res_gyro
    n2 = (rate ** 2).sum(-1)
    ok = (prep.m_gyro > 0).all(-1) & (n2 > _FLOOR_RATE2)
    along = (r * rate).sum(-1)
    lam = torch.zeros(prep.K, dtype=r.dtype)
    if shrink:
        for k in range(prep.K):
            sel = ok[:, k]
            if int(sel.sum()) < 10:
                continue
            rk, nk, ak = r[sel, k], n2[sel, k], along[sel, k]
            perp = ((rk ** 2).sum(-1) - ak ** 2 / nk).clamp_min(0)
            sig2 = float(perp.mean()) / 2
            big = nk > nk.median()
            tau2 = float(((ak[big] / nk[big]) ** 2 - sig2 / nk[big]).mean())
            lam[k] = sig2 / tau2 if tau2 > 0 else float("inf")
    den = n2 + lam[None, :]
    delta = torch.where(ok & torch.isfinite(den), along / den.clamp_min(_FLOOR_RATE2), torch.zeros_like(n2))
    return delta, ok


def array_residuals(prep: Prepared, fit: ModelFit, sensor: str = "acc") -> tuple[torch.Tensor, torch.Tensor]:
    """(a (T, K, 3), valid (T, K) bool): the leverage-corrected residuals r/√(1 − h) of ``sensor``
    ("acc": m/s², "gyro": rad/s) rotated into the array frame (a = R_kᵀ r, R_k array → sensor); 0
    where the triad is not fully observed."""
    from ..physics.geometry import quat_to_matrix

    j = {"acc": 0, "gyro": 1}[sensor]
    h = fit.linear().h.reshape(prep.T, 2, prep.K, 3)[:, j]
    res, m = (fit.res_acc, prep.m_acc) if sensor == "acc" else (fit.res_gyro, prep.m_gyro)
    r = res / torch.sqrt((1 - h).clamp_min(1e-3))
    R = quat_to_matrix(torch.as_tensor(prep.q, dtype=r.dtype))  # (K, 3, 3): array → sensor
    ok = (m > 0).all(-1)
    a = torch.einsum("kji,tkj->tki", R, r) * ok[..., None]
    return a, ok


def _centred(delta: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    n = w.sum(1, keepdim=True).clamp_min(1)
    return (delta - (delta * w).sum(1, keepdim=True) / n) * w


def _pattern(delta: torch.Tensor, ok_g: torch.Tensor, ok_a: torch.Tensor) -> torch.Tensor:
    """d (T, K): the instant errors centred over the IMUs whose both triads enter the sample, 0
    elsewhere (an IMU without a gyro instant enters the white part only)."""
    w = (ok_a & ok_g).to(delta.dtype)
    return _centred(delta * w, w)


@dataclass
class AliasedJerk:
    """The fitted coupling (module docstring).  ``edges`` inner |ω| band edges (rad/s, B − 1);
    ``v`` (K, B) white variances ((m/s²)²); ``jerk_rms`` (B,) s_b (m/s³) with ``jerk_rms_std``
    (observed information); ``loglik`` / ``loglik_null`` (nats, the null refitted with s = 0);
    ``evidence`` = 2 (loglik − loglik_null) with ``df`` = B; ``v_null`` (K, B) the null's white
    variances; ``share`` and ``share_by_band`` the power of the conditional mean E[d j | a] (the
    part of the residual the coupling explains, as a mixed model's BLUP) over the accelerometer
    excess Σ(a² − σ²), overall and per |ω| band; ``share_predicted`` the model's predicted coupled
    variance Σ s² d² over the same excess — larger than ``share`` where the instant errors are
    heavy-tailed (a sample with a large d only discounts one direction, at a logarithmic cost, so
    the ML scale over-predicts there); ``n`` samples used; ``permutation`` {"n", "statistic",
    "statistic_max", "statistic_median", "p_value"}: the permutation test of the module docstring —
    its statistic is the likelihood ratio with the white variances held at the null's
    (:func:`_profile_lr`; below ``evidence``, which refits them), observed and with the instant
    errors permuted within |ω| bands, p = (1 + #{permuted ≥ observed}) / (1 + n); ``extra["remainder_along_jerk"]``
    whether what is left lies along the per-sample jerk (:func:`_remainder_along_jerk`)."""

    edges: list
    v: np.ndarray
    jerk_rms: np.ndarray
    jerk_rms_std: np.ndarray
    loglik: float
    loglik_null: float
    evidence: float
    df: int
    share: float
    share_by_band: list
    share_predicted: float
    v_null: np.ndarray
    n: int
    permutation: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"omega_edges": [float(e) for e in self.edges], "jerk_rms": [float(x) for x in self.jerk_rms],
                "jerk_rms_std": [float(x) for x in self.jerk_rms_std], "white_var": np.asarray(self.v).tolist(),
                "loglik": float(self.loglik), "loglik_null": float(self.loglik_null), "evidence": float(self.evidence),
                "df": int(self.df), "share": float(self.share), "share_by_band": [float(x) for x in self.share_by_band],
                "share_predicted": float(self.share_predicted), "white_var_null": np.asarray(self.v_null).tolist(),
                "n": int(self.n), "permutation": dict(self.permutation), **self.extra}

    def loglik_on(self, prep: Prepared, fit: ModelFit, *, shuffle_seed: int | None = None) -> tuple[float, float]:
        """(coupled, white) log density (nats) of another fit's accelerometer residuals with these
        parameters held — the white model with the null's variances ``v_null`` (bands by this fit's |ω| against the stored edges; the instant errors
        from this fit's own gyros).  ``shuffle_seed``: permute the instant-error rows across
        samples (the null that keeps their distribution and breaks the pairing)."""
        a, ok_a = array_residuals(prep, fit)
        delta, ok_g = instant_errors(prep, fit)
        if shuffle_seed is not None:
            g = torch.Generator().manual_seed(int(shuffle_seed))
            perm = torch.randperm(prep.T, generator=g)
            delta, ok_g = delta[perm], ok_g[perm]
        w = ok_a.to(a.dtype)
        d = _pattern(delta, ok_g, ok_a)
        lab = _bands(fit, self.edges)
        v = torch.as_tensor(self.v, dtype=a.dtype)[:, lab].T
        v0 = torch.as_tensor(self.v_null, dtype=a.dtype)[:, lab].T
        s2 = torch.as_tensor(self.jerk_rms, dtype=a.dtype)[lab] ** 2
        return float(coupled_loglik(a, d, w, v, s2).sum()), float(coupled_loglik(a, d, w, v0, torch.zeros_like(s2)).sum())


def _profile_lr(a, d, w, v, lab, B: int) -> float:
    """2 max over s_b² ≥ 0 of [log L(s²) − log L(0)] with the white variances v (T, K) held: per
    sample only c_t = Σ d²/v and P_t = Σ_i (Σ_k d_k a_ki / v_k)² enter,
    Δ log L_t = ½ [s² P_t / (1 + s² c_t) − 3 log(1 + s² c_t)]; maximised per band by Newton steps
    on log s² from a grid start (each band is independent)."""
    inv = w / v
    c = (d ** 2 * inv).sum(1)
    P = (torch.einsum("tk,tki->ti", d * inv, a) ** 2).sum(-1)
    total = 0.0
    for b in range(B):
        sel = lab == b
        cb, Pb = c[sel], P[sel]
        if cb.numel() == 0 or float(cb.max()) <= 0:
            continue

        def f(x):  # Δ log L of the band at s² = exp(x); x a 1-D tensor of candidates
            s2 = torch.exp(x)[:, None]
            return 0.5 * (s2 * Pb / (1 + s2 * cb) - 3 * torch.log1p(s2 * cb)).sum(1)

        scale = float((1 / cb[cb > 0]).median())
        grid = torch.linspace(-12, 12, 97, dtype=a.dtype) + math.log(scale)
        x = grid[torch.argmax(f(grid))].reshape(1)
        for _ in range(30):  # Newton on x with autograd derivatives, backtracking
            xr = x.clone().requires_grad_(True)
            y = f(xr).sum()
            g1, = torch.autograd.grad(y, xr, create_graph=True)
            g2, = torch.autograd.grad(g1.sum(), xr)
            step = -g1.detach() / g2 if float(g2) < 0 else torch.sign(g1.detach())
            step = step.clamp(-2, 2)
            while float(f(x + step)) < float(f(x)) and float(step.abs()) > 1e-8:
                step = step / 2
            x = x + step
            if float(step.abs()) < 1e-9:
                break
        total += max(0.0, 2 * float(f(x)))
    return total


def _remainder_along_jerk(a, d, w, s2_t, inv, c, proj, seed) -> dict:
    """Is what the coupling leaves still along the sample's jerk?  On the samples whose instant
    pattern is well determined (c = Σ d²/v above its median): the jerk's conditional mean
    ĵ_t = s² Σ_k d_k a_k / v_k / (1 + s² c), the remainder r_kt = a_kt − d_kt ĵ_t and the share of
    its power along ĵ_t (1/3 if isotropic; ``null``: the same along the ĵ of a permuted sample).
    An accelerometer whose own instant differs from its gyro's by ε_kt adds ε_kt j_t — along the
    jerk; ``acc_own_instant_rms_s`` is the ε that the excess along ĵ implies, from
    E[(r·û)² − |r_⊥|²/2] = τ² |ĵ|² fitted over the samples (s; 0 when the excess is not positive)."""
    j = (s2_t / (1 + s2_t * c))[:, None] * proj  # (T, 3)
    sel = (c > c.median()) & (w.sum(1) >= 3) & ((j ** 2).sum(-1) > 0)
    if int(sel.sum()) < 10:
        return {}
    js, ds, as_, ws = j[sel], d[sel], a[sel], w[sel]
    r = (as_ - ds[:, :, None] * js[:, None, :]) * ws[..., None]
    u = js / js.norm(dim=-1, keepdim=True)
    along = torch.einsum("tki,ti->tk", r, u) ** 2
    tot = (r ** 2).sum(-1)
    g = torch.Generator().manual_seed(int(seed) + 1)
    us = u[torch.randperm(len(u), generator=g)]
    null = torch.einsum("tki,ti->tk", r, us) ** 2
    j2 = (js ** 2).sum(-1)
    ex = ((along - (tot - along) / 2) * ws).sum(1) / ws.sum(1).clamp_min(1)
    tau2 = float((ex * j2).sum() / (j2 ** 2).sum())
    return {"fraction": float(along.sum() / tot.sum()), "null": float(null.sum() / tot.sum()),
            "acc_own_instant_rms_s": math.sqrt(tau2) if tau2 > 0 else 0.0, "samples": int(sel.sum())}


def fit_aliased_jerk(prep: Prepared, fit: ModelFit, *, edges=None, max_iter: int = 200, n_permutations: int = 19,
                     seed: int = 0) -> AliasedJerk | None:
    """Maximum-likelihood fit of the coupling (module docstring) to ``fit``'s accelerometer
    residuals, the instant errors from its gyro residuals.  ``edges``: inner |ω| band edges
    (rad/s; default :func:`omega_edges` of ``fit``).  ``n_permutations`` fits with the instant
    errors permuted within bands (seeded by ``seed``) give the p-value; 0 skips them.  About 1 s
    plus 0.3 s per permutation on 6 000 samples of 8 IMUs.  None when fewer than three IMUs have
    both triads observed (no pattern across IMUs to fit)."""
    a, ok_a = array_residuals(prep, fit)
    delta, ok_g = instant_errors(prep, fit)
    if int((ok_a & ok_g).any(0).sum()) < 3:
        return None
    # an IMU without a gyro instant still has an accelerometer residual: it enters the white part
    # only (d = 0), so the null and the coupled model see the same data
    w_all = ok_a.to(a.dtype)
    d = _pattern(delta, ok_g, ok_a)
    edges = omega_edges(fit) if edges is None else [float(e) for e in edges]
    lab = _bands(fit, edges)
    B, K = len(edges) + 1, prep.K
    v0, lv, ls, ll0, ll1, sd_ls = fit_arrays(a, d, w_all, lab, B, max_iter=max_iter)
    s = torch.exp(0.5 * ls)
    v = torch.exp(lv)
    # shares of the accelerometer excess: predicted coupled variance and the realised conditional mean
    s2_t = torch.exp(ls)[lab]
    vt = v[:, lab].T
    inv = w_all / vt
    c = (d ** 2 * inv).sum(1)
    proj = torch.einsum("tk,tki->ti", d * inv, a)
    m = (s2_t / (1 + s2_t * c))[:, None, None] * d[:, :, None] * proj[:, None, :]  # E[d j | a] (T, K, 3)
    sig2 = (prep.sigma_acc ** 2).to(a.dtype)[None, :] * w_all
    pred = 3 * s2_t[:, None] * d ** 2
    real = (m ** 2).sum(-1)
    excess_t = (a ** 2).sum(-1) * w_all - 3 * sig2  # (T, K)
    share_band = []
    for b in range(B):
        sel = lab == b
        ex = float(excess_t[sel].sum())
        share_band.append(float(real[sel].sum()) / ex if ex > 0 else float("nan"))
    ex_all = float(excess_t.sum())
    ev = max(0.0, 2 * (ll1 - ll0))
    remainder = _remainder_along_jerk(a, d, w_all, s2_t, inv, c, proj, seed)
    perm = {}
    if n_permutations > 0:
        # the test statistic: the likelihood ratio with the white variances held at the null's
        # (then each sample enters through two numbers, c_t and |p_t|², and a fit costs O(T));
        # the same statistic with the instants permuted within bands is its null distribution
        v0t = v0[:, lab].T
        stat = _profile_lr(a, d, w_all, v0t, lab, B)
        g = torch.Generator().manual_seed(int(seed))
        evs = []
        for _ in range(int(n_permutations)):
            idx = torch.arange(prep.T)
            for b in range(B):
                sel = torch.nonzero(lab == b).flatten()
                idx[sel] = sel[torch.randperm(len(sel), generator=g)]
            evs.append(_profile_lr(a, _pattern(delta[idx], ok_g[idx], ok_a), w_all, v0t, lab, B))
        evs = np.asarray(evs)
        perm = {"n": int(n_permutations), "statistic": stat, "statistic_max": float(evs.max()),
                "statistic_median": float(np.median(evs)), "p_value": float((1 + (evs >= stat).sum()) / (1 + len(evs)))}
    return AliasedJerk(edges=edges, v=v.numpy(), jerk_rms=s.numpy(), jerk_rms_std=(0.5 * s * sd_ls).numpy(),
                       loglik=ll1, loglik_null=ll0, evidence=ev, df=B,
                       share=float(real.sum()) / ex_all if ex_all > 0 else float("nan"), share_by_band=share_band,
                       share_predicted=float(pred.sum()) / ex_all if ex_all > 0 else float("nan"),
                       v_null=v0.numpy(), n=int((w_all.sum(1) > 0).sum()), permutation=perm,
                       extra={"remainder_along_jerk": remainder})

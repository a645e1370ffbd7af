"""Random effects in the mismatch model: the exact ``sampling_jitter`` marginal likelihood at a
mean fit, its width profiled in 1-D, and the predicted extra variance of random effects.

At a fit (:class:`~accel_bayes.mismatch.model.ModelFit`), per IMU k and sample t, the six whitened
residuals r̃ (acc xyz, gyro xyz; whitened by the model noise σ·factor) and the whitened output rate
ṽ = v/(σ·factor) enter the exact marginal of :mod:`accel_bayes.physics.effects.jitter`
(:func:`~accel_bayes.physics.effects.log_marginal_gain`, D = I in whitened units) through
a_t and b_t, formed as the *restricted* (REML) likelihood of the residuals, exact per sample:

* the per-sample motion states absorb part of every residual: with P = I − Jx (JxᵀJx)⁻¹ Jxᵀ the
  sample's residual-maker (all 6K rows) and ṽ the rate direction (non-zero on IMU k's rows
  only), the residual is r = P(ṽδ + e), so on the range of P its covariance is I + σ_δ² u uᵀ
  with u = Pṽ.  In any orthonormal basis Z of that range, Zᵀu and Zᵀr give
  a = uᵀu = ṽᵀPṽ = ṽ_kᵀu_k and b = uᵀr = ṽᵀr = ṽ_kᵀr_k (P r = r): only IMU k's rows are needed,
  and under the null b ~ N(0, a) exactly;
* no leverage correction enters a or b.  (Until 2026-11-26 they were ũᵀũ and ũᵀr̃ with u and r
  divided by √(1 − h): that made Var b ≠ a under the null — b grew faster than a where the
  rate was large — and a clean simulation gave acc timing evidences of 9–14 (median) instead of
  ≈ 0, the false alarms of ``experiments/mismatch_proof.md``'s re-check.)  The white-noise
  factor's residual power Σ r²/(1 − h) is leverage-corrected (REML-like, as ``noise_level``'s
  :func:`accel_bayes.mismatch.screens.noise_evidence`).

Evidence = 2·(max_w Σ_t gain_t(w) − 0): the likelihood ratio against w = 0, a hypothesis on the
boundary of the parameter space (w ≥ 0), so under the null it is distributed as the 50:50
mixture ½χ²₀ + ½χ²₁ (Self & Liang 1987) and its p-value is ½·P(χ²₁ > stat).  The detector's
threshold (χ²₃ Bonferroni quantile) is not lowered for it: conservative.  Uncertainty: the
profile-likelihood 95 % interval {w : 2(ℓ(ŵ) − ℓ(w)) ≤ χ²₁,0.95}, and a std = interval length /
3.92.

The mean is refitted with the random effects in the model (:func:`~accel_bayes.mismatch.fit.fit_model`),
alternating with their parameters until they settle:

* the first refit re-weights (IRLS-style): each channel gets 1/(σ² + predicted random variance),
  the diagonal of the moment-matched covariance D + (w²/12) v vᵀ;
* then each random timing effect is taken off the outputs (GLS): its conditional mean
  E[δ_t | r]·rate (:func:`random_offsets`, the banded solve of
  :func:`accel_bayes.mismatch.wander.ar1_conditional_mean`; ``sampling_jitter`` as the Gaussian of
  the uniform's variance, independent per sample, on both triads) is subtracted and the motion
  refitted; only a wander's white part stays in the weights.  With the
  restricted b = ṽᵀP y this is Henderson's mixed-model solution in one step (per-sample motion
  states; a few rounds for the positions).  Re-weighting alone left the wandering triad's mean
  in the motion fit: a first-order low-pass on one accelerometer (a nearly constant timing error)
  then leaked into the other IMUs' residuals and was named there (timing evidences up to 500 on
  IMUs without any effect; ``tests/mismatch/test_wander.py``), and a jittered IMU gave spurious jitter
  findings on two other IMUs in every concealed multi-effect jitter case.

The exact marginal is then evaluated at that mean, on the residuals of the recorded outputs
projected in the noise whitening D (:func:`_noise_projection`; the fit's diagnostic system, see
:func:`accel_bayes.mismatch.fit.fit_model`, is whitened by the full predicted variance).  Without the refit a jittered IMU keeps pulling the
per-sample motion states, and ``noise_level`` — whose refit does re-weight — would win on an
unequal footing.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..physics.effects.jitter import log_marginal_gain
from .model import project_off_states

__all__ = ["jitter_ab", "profile_width", "jitter_evidence", "random_variance", "variance_ratio", "fit_random_effects",
           "triad_wander", "wander_table", "random_offsets", "weight_effects",
           "CHI2_1_95"]

CHI2_1_95 = 3.841458820694124  # χ²₁ 95 % quantile: the profile-likelihood interval


def _rows(K: int, k: int) -> torch.Tensor:
    return torch.tensor([3 * k, 3 * k + 1, 3 * k + 2, 3 * K + 3 * k, 3 * K + 3 * k + 1, 3 * K + 3 * k + 2])


def _noise_projection(prep, fit):
    """The fit's per-sample linearisation in the **noise** whitening (σ·factor, no random-effect
    weights): (Jx (T, 6K, 9), (JxᵀJx)⁻¹ (T, 9, 9), r (T, 6K) the residuals of the recorded
    outputs, h (T, 6K) the leverage, o (T, 6K) or None the wanders' conditional means that the
    mean fit took off the outputs (``gls_offset``, same whitening)).  The fit's own system
    (:meth:`ModelFit.linear`) is whitened by its weights, which for a fit with random effects
    include their predicted variance; the restricted likelihood of a random effect does not (P y
    does not depend on how the motion was fitted).  Cached on the fit."""
    lin = fit.linear()
    model = getattr(fit.lm, "model", None)
    vr = getattr(model, "var_ratio", None)
    off = getattr(model, "gls_offset", None)
    if vr is None:
        return lin.Jx, lin.Vinv, lin.r, lin.h, None
    cached = getattr(fit, "_noise_projection", None)
    if cached is not None and cached[0] is lin:
        return cached[1]
    T, m = lin.r.shape
    back = torch.sqrt(vr.reshape(T, m))
    Jx = lin.Jx * back.unsqueeze(-1)
    r = lin.r * back
    Vinv = torch.linalg.inv(Jx.transpose(-1, -2) @ Jx)
    h = ((Jx @ Vinv) * Jx).sum(-1)
    o = None
    if off is not None:
        w = torch.stack((prep.m_acc / (prep.sigma_acc * fit.acc_factor)[None, :, None],
                         prep.m_gyro / (prep.sigma_gyro * fit.gyro_factor)[None, :, None]), 1)
        o = (off * w).reshape(T, m)
    out = (Jx, Vinv, r, h, o)
    try:
        fit._noise_projection = (lin, out)
    except AttributeError:  # pragma: no cover - a fit type without attributes: recompute each time
        pass
    return out


def jitter_ab(prep, fit, k: int, sensor: str | None = None, with_residual_power: bool = False,
              whitening: str = "noise"):
    """(a, b), each (T,), of IMU k at a fit (module docstring): a = ṽᵀPṽ in s⁻², b = ṽᵀP y in s⁻¹
    (restricted to IMU k's rows, exact per sample: Var b = a under the null).
    ``sensor`` "acc" or "gyro" restricts them to that triad's three channels (``timing_wander``);
    None uses all six (``sampling_jitter``).  ``with_residual_power`` (with a sensor): also
    Σ r̃ᵀr̃ (leverage-corrected) and the number of observed channels of the triad.  ``whitening``:
    "noise" (default: the model's noise σ·factor, the residuals projected in that whitening
    (:func:`_noise_projection`) — the restricted likelihood a random effect is fitted on, whatever
    weights the fit's mean used) or "model" (the fit's weights, random effects' predicted variance
    included — what the fit leaves, as the characteriser describes it)."""
    if whitening not in ("noise", "model"):
        raise ValueError(f"whitening: expected 'noise' or 'model', got {whitening!r}")
    K = prep.K
    rows = _rows(K, k)
    if whitening == "model":
        lin = fit.linear()
        model = getattr(fit.lm, "model", None)
        Jx_all, Vinv, r_all, h_all = lin.Jx, lin.Vinv, lin.r, lin.h
        vr = getattr(model, "var_ratio", None)
        back = torch.ones(prep.T, 6, dtype=torch.float64) if vr is None else \
            torch.sqrt(torch.cat((vr[:, 0, k], vr[:, 1, k]), -1))
    else:
        Jx_all, Vinv, r_all, h_all, o_all = _noise_projection(prep, fit)
        back = torch.ones(prep.T, 6, dtype=torch.float64)
        if o_all is not None:
            # the other IMUs' wanders are the model's (their conditional means off, as the mean fit
            # took them off); IMU k's own stays in: its effect is what is being fitted or tested.
            # Without this the projection spreads a wandering triad's error into every other IMU
            keep = torch.ones(o_all.shape[1], dtype=o_all.dtype)
            keep[rows] = 0.0
            r_all = r_all - o_all * keep
    wa = prep.m_acc[:, k] / (prep.sigma_acc[k] * fit.acc_factor[k])
    wg = prep.m_gyro[:, k] / (prep.sigma_gyro[k] * fit.gyro_factor[k])
    v = torch.cat((prep.acc_rate[:, k] * wa, prep.gyro_rate[:, k] * wg), -1) / back  # (T, 6), in the whitening
    sl = slice(0, 6) if sensor is None else slice(0, 3) if sensor == "acc" else slice(3, 6)
    if sensor is not None:  # a one-triad timing error moves only that triad's outputs
        keep = torch.zeros(6, dtype=v.dtype)
        keep[sl] = 1.0
        v = v * keep
    Jx = Jx_all[:, rows]  # (T, 6, 9)
    # u = P_kk v: the direction left in the residuals after the motion states took their share
    u = project_off_states(Jx, Vinv, v)
    # P y on IMU k's rows (the whole sample's residual projected: exact whatever x the fit has)
    r = project_off_states(Jx_all, Vinv, r_all)[:, rows]
    # back to the noise whitening (identity unless "model")
    vk, uk, rk = (v * back)[:, sl], (u * back)[:, sl], (r * back)[:, sl]
    a, b = (vk * uk).sum(-1), (vk * rk).sum(-1)
    if sensor is not None and with_residual_power:
        h = h_all[:, rows][:, sl]
        m = (prep.m_acc if sensor == "acc" else prep.m_gyro)[:, k]
        rt2 = rk * rk / (1 - h).clamp_min(1e-3)  # leverage-corrected residual power
        return a, b, float((rt2 * m).sum()), int(m.sum())
    return a, b


def triad_wander(prep, fit, k: int, sensor: str, sigma_max: float, whitening: str = "noise"):
    """:func:`accel_bayes.mismatch.wander.fit_wander` on IMU k's ``sensor`` triad at a fit, its
    white-noise factor fitted too: (the fit's dict, Σa (s⁻²), Σ r̃ᵀr̃, number of observed
    channels), a and r̃ from :func:`jitter_ab` (projected, leverage-corrected, noise-whitened).
    ``sigma_max`` bounds the instant std (s); ``whitening`` as in :func:`jitter_ab`.  The one fit
    behind ``timing_wander`` (noise whitening) and the characteriser's timing column (model
    whitening: what the fit leaves)."""
    from .wander import fit_wander, sample_steps

    a, b, rr, n = jitter_ab(prep, fit, k, sensor, with_residual_power=True, whitening=whitening)
    f = fit_wander(a.numpy(), b.numpy(), sample_steps(prep.time), sigma_max=sigma_max, rr=rr, n=n)
    return f, float(a.sum()), rr, n


def _wander_profile(prep, fit, effect) -> dict:
    """``timing_wander`` at a fit: (width, correlation) by maximum marginal likelihood of the AR(1)
    instant error on the effect's triad, fitted together with a white-noise factor c of the triad
    (:func:`accel_bayes.mismatch.wander.fit_wander`); the gain and the evidence are against the
    triad's best noise-only model (``gain``: what the timing term adds), and the inflation itself
    becomes the effect's ``excess_noise_var`` ((c² − 1)·σ², units², ≥ 0; ``noise_only_gain`` its
    log-likelihood gain over the model's noise).  The detector's evidence is the sum of the two
    gains (against the current model, like every variance candidate's): it beats ``noise_level``
    only by what the timing term adds.  A profile dict like :func:`profile_width`'s plus
    "correlation", "correlation_std", "excess_noise_var" and "noise_only_gain"."""
    from .wander import _noise_only_gain

    k = int(effect.imu)
    f, _, rr, n = triad_wander(prep, fit, k, effect.which, _max_width(prep) / math.sqrt(12.0))
    c = max(float(f["c"]), 1.0)  # no variance below the model's noise
    sig = float((prep.sigma_acc[k] * fit.acc_factor[k]) if effect.which == "acc" else
                (prep.sigma_gyro[k] * fit.gyro_factor[k]))
    w = math.sqrt(12.0) * f["sigma"]
    w_std = None if f["sigma_std"] is None else math.sqrt(12.0) * f["sigma_std"]
    iv = [max(0.0, w - 1.96 * w_std), w + 1.96 * w_std] if w_std is not None else [0.0, w]
    return {"width": w, "correlation": f["rho"], "gain": f["gain"], "interval": iv,
            "std": w_std if w_std is not None else float("nan"), "correlation_std": f["rho_std"],
            "excess_noise_var": (c * c - 1.0) * sig * sig,
            "noise_only_gain": _noise_only_gain(rr, n)[1]}


def _max_width(prep) -> float:
    """Upper bound of the width search: one median sample interval (a wider jitter would reorder
    samples, and the linearisation in δ would no longer hold)."""
    t = np.asarray(prep.time, dtype=float)
    return float(np.median(np.diff(t))) if len(t) > 1 else 1e-2


def profile_width(a: torch.Tensor, b: torch.Tensor, w_max: float) -> dict:
    """Maximise G(w) = Σ_t log_marginal_gain(a_t, b_t, w) over 0 ≤ w ≤ w_max (a log grid, then a
    bounded Brent refinement).  Returns {"width", "gain" (= G(ŵ) ≥ 0), "interval" [lo, hi]
    (profile 95 %, endpoints to 0.1 % of ŵ), "std"}."""
    from scipy.optimize import brentq, minimize_scalar

    def G(w):
        return float(log_marginal_gain(a, b, float(w)).sum()) if w > 0 else 0.0

    grid = np.r_[0.0, np.logspace(math.log10(w_max) - 4, math.log10(w_max), 41)]
    # the whole grid in one vectorised evaluation (T × 41)
    vals = np.r_[0.0, log_marginal_gain(a[:, None], b[:, None], torch.as_tensor(grid[None, 1:])).sum(0).numpy()]
    j = int(np.argmax(vals))
    if j == 0:
        w_hat, g_hat = 0.0, 0.0
    else:
        lo, hi = grid[j - 1], grid[min(j + 1, len(grid) - 1)]
        res = minimize_scalar(lambda w: -G(w), bounds=(lo, hi), method="bounded", options={"xatol": 1e-4 * grid[j]})
        w_hat, g_hat = (float(res.x), -float(res.fun)) if -res.fun >= vals[j] else (float(grid[j]), float(vals[j]))
    f = lambda w: 2 * (g_hat - G(w)) - CHI2_1_95  # noqa: E731
    lo = 0.0 if f(0.0) <= 0 or w_hat == 0 else brentq(f, 0.0, w_hat, xtol=1e-3 * w_hat)
    hi = w_max if f(w_max) <= 0 else brentq(f, w_hat, w_max, xtol=1e-3 * max(w_hat, 1e-4 * w_max))
    return {"width": w_hat, "gain": g_hat, "interval": [float(lo), float(hi)], "std": (hi - lo) / 3.92}


def jitter_evidence(prep, fit, effect) -> tuple[float, dict]:
    """(evidence, profile) of a ``sampling_jitter`` effect at a fit: evidence = 2·G(ŵ), the
    likelihood ratio against w = 0 (module docstring); profile from :func:`profile_width`."""
    if effect.name == "timing_wander":
        # against the current model (N(0, I) in its noise units), as every other variance
        # candidate's evidence: the wander's own white-noise part competes with noise_level's
        # inflation on equal terms, and the wander wins only by what the timing term adds
        prof = _wander_profile(prep, fit, effect)
        return 2.0 * (prof["gain"] + prof["noise_only_gain"]), prof
    a, b = jitter_ab(prep, fit, int(effect.imu))
    prof = profile_width(a, b, _max_width(prep))
    return 2.0 * prof["gain"], prof


def fit_random_effects(prep, fit) -> None:
    """Estimate the width of every random effect in ``fit`` (profile maximum at the fit's mean;
    writes ``params``, ``std`` and ``stats["width_interval_s"]``) and add their exact marginal
    gains to ``fit.loglik_t``/``fit.loglik`` (gains of the leverage-corrected residuals, as the
    evidence uses; the Gaussian part stays the plain one at the fitted mean); ``fit.chi2``
    becomes Σ r²/(noise variance + predicted random variance) (moment form, for χ²/dof).
    Downstream: ELPD by PSIS-LOO (:mod:`.compare`) starts from these per-sample values and
    perturbs them in the fit's (re-weighted) whitening — an approximation for random effects;
    :func:`~accel_bayes.mismatch.compare.corrected_recording` does not represent them."""
    rand = [e for e in fit.effects if e.kind == "random"]
    if not rand:
        return
    w_max = _max_width(prep)
    # the Gaussian part on the per-sample restricted residuals P y (noise whitening), as the gains
    # are: then log L = log N(P y; 0, I) + gains is the restricted likelihood whatever mean the
    # fit used (re-weighted or GLS), and a mean effect's evidence beside a random effect compares
    # like with like (with the fit's raw residuals a constant delay on a wandering triad was
    # credited with the wander's own mean: evidence ≈ 200 where ≈ 1 was due)
    Jx, Vinv, r_all, _, _ = _noise_projection(prep, fit)
    rp = project_off_states(Jx, Vinv, r_all)
    fit.loglik_t = fit.loglik_t + 0.5 * ((r_all * r_all).sum(-1) - (rp * rp).sum(-1))
    for e in rand:
        if e.name == "timing_wander":
            # the AR(1) gain is not a sum over samples: spread evenly over them (only the total
            # enters the evidence; the per-sample split matters for PSIS-LOO, approximate anyway)
            prof = _wander_profile(prep, fit, e)
            e.set_params({"width": prof["width"], "correlation": prof["correlation"],
                          "excess_noise_var": prof["excess_noise_var"]})
            e.std = {"width": torch.tensor(prof["std"], dtype=torch.float64)}
            if prof["correlation_std"] is not None:
                e.std["correlation"] = torch.tensor(prof["correlation_std"], dtype=torch.float64)
            e.stats["width_interval_s"] = prof["interval"]
            # the timing term's own likelihood ratio (against the triad's best noise-only model):
            # the detector accepts a wander only where this alone passes its threshold
            e.stats["timing_evidence"] = 2.0 * prof["gain"]
            fit.loglik_t = fit.loglik_t + (prof["gain"] + prof["noise_only_gain"]) / prep.T
            continue
        a, b = jitter_ab(prep, fit, int(e.imu))
        prof = profile_width(a, b, w_max)
        e.set_params({"width": prof["width"]})
        e.std = {"width": torch.tensor(prof["std"], dtype=torch.float64)}
        e.stats["width_interval_s"] = prof["interval"]
        fit.loglik_t = fit.loglik_t + log_marginal_gain(a, b, prof["width"])
    fit.loglik = float(fit.loglik_t.sum())
    ratio = variance_ratio(prep, fit)
    za = fit.res_acc / (prep.sigma_acc * fit.acc_factor)[None, :, None] * prep.m_acc
    zg = fit.res_gyro / (prep.sigma_gyro * fit.gyro_factor)[None, :, None] * prep.m_gyro
    fit.chi2 = float((za ** 2 / ratio[:, 0]).sum() + (zg ** 2 / ratio[:, 1]).sum())


def random_offsets(prep, fit, effects=None):
    """(T, 2, K, 3) sensor units, or None: the conditional mean of the random timing effects
    (``effects``, default those in ``fit``) given the fit's residuals, E[δ_t | r]·rate_t on each
    wander's triad (``sampling_jitter``: on both triads of its IMU, δ Gaussian with the uniform's
    variance, independent per sample) (:func:`accel_bayes.mismatch.wander.ar1_conditional_mean` with the restricted
    a, b of :func:`jitter_ab`, the effect's width, correlation and white-noise factor).  The
    refit takes it off the outputs (:class:`~accel_bayes.mismatch.model._Model` ``offset``), so
    the motion is fitted as by GLS under the wander's covariance instead of being pulled by the
    wandering triad — which, fitted by re-weighting alone, leaked into the other IMUs' residuals
    and was named there as timing errors of their own (``experiments/characterise_proof.md``)."""
    from .wander import ar1_conditional_mean, sample_steps

    effects = fit.effects if effects is None else effects
    rand = [e for e in effects if e.name in ("timing_wander", "sampling_jitter") and float(e.params["width"]) > 0]
    if not rand:
        return None
    off = torch.zeros(prep.T, 2, prep.K, 3, dtype=torch.float64)
    steps = sample_steps(prep.time)
    for e in rand:
        k = int(e.imu)
        wander = e.name == "timing_wander"
        sensor = e.which if wander else None  # sampling_jitter: one instant for both triads
        a, b = jitter_ab(prep, fit, k, sensor)
        c = 1.0
        if wander:
            sig = float((prep.sigma_acc[k] * fit.acc_factor[k]) if e.which == "acc" else
                        (prep.sigma_gyro[k] * fit.gyro_factor[k]))
            c = math.sqrt(1.0 + float(e.params["excess_noise_var"]) / sig ** 2)
        # sampling_jitter: the Gaussian of the same variance (w²/12), independent per sample (ρ = 0)
        d = ar1_conditional_mean(a.numpy(), b.numpy(), steps, float(e.params["width"]) / math.sqrt(12.0),
                                 float(e.params["correlation"]) if wander else 0.0, c)
        # what the instants do on average: a filter's group delay shows as a mean far from 0
        e.stats["instant_mean_s"] = float(d.mean())
        e.stats["instant_rms_s"] = float(math.sqrt((d * d).mean()))
        dt = torch.as_tensor(d, dtype=torch.float64)[:, None]
        if sensor in (None, "acc"):
            off[:, 0, k] += dt * prep.acc_rate[:, k]
        if sensor in (None, "gyro"):
            off[:, 1, k] += dt * prep.gyro_rate[:, k]
    return off


def weight_effects(effects) -> list:
    """The random effects as the mean fit's weights see them once their conditional means are
    taken off the outputs (:func:`random_offsets`): a ``timing_wander`` keeps only its white part
    (``excess_noise_var``) in the weights, a ``sampling_jitter`` nothing."""
    out = []
    for e in effects:
        if e.name in ("timing_wander", "sampling_jitter"):
            e = e.copy()
            e.set_params({"width": 0.0})
        out.append(e)
    return out


def random_variance(prep, fit=None, effects=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Predicted extra variance of the random effects (``effects``, default those in ``fit``) per
    sample and channel, (acc (T, K, 3) in (m/s²)², gyro (T, K, 3) in (rad/s)²): the diagonal of
    their moment-matched covariance ((w²/12)·rate² for ``sampling_jitter``, rates of the
    baseline fit, ``prep.acc_rate``/``prep.gyro_rate``).  The hook for variance budgets (DESIGN
    §7.2 ``budget``: the part of the excess a random effect predicts)."""
    from types import SimpleNamespace

    effects = fit.effects if effects is None else effects
    va = torch.zeros(prep.T, prep.K, 3, dtype=torch.float64)
    vg = torch.zeros_like(va)
    ctx = SimpleNamespace(acc=va, gyro=vg, K=prep.K, acc_rate=prep.acc_rate, gyro_rate=prep.gyro_rate)
    for e in effects:
        if e.kind == "random":
            da, dg = e.variance(None, ctx)
            va, vg = va + da * prep.m_acc, vg + dg * prep.m_gyro
    return va, vg


def variance_ratio(prep, fit=None, effects=None, acc_factor=None, gyro_factor=None) -> torch.Tensor:
    """(T, 2, K, 3): 1 + predicted random variance / noise variance (σ·factor)² per channel —
    what a squared noise-whitened residual is divided by to be ~1 under the full model.
    Effects and factors from ``fit`` unless given."""
    fa = fit.acc_factor if acc_factor is None else acc_factor
    fg = fit.gyro_factor if gyro_factor is None else gyro_factor
    va, vg = random_variance(prep, fit, effects)
    sa = (prep.sigma_acc * fa)[None, :, None] ** 2
    sg = (prep.sigma_gyro * fg)[None, :, None] ** 2
    return torch.stack((1 + va / sa, 1 + vg / sg), 1)


def wander_table(prep, fit, sensors=("gyro", "acc"), sigma_max: float | None = None) -> dict:
    """:func:`fit_wander` (noise factor c fitted too) on every IMU's triads at a fit: {sensor:
    [{imu, sigma_ms, rho, c, evidence, share}]}, ``share`` = the predicted timing variance σ²·Σa
    over the excess Σ(r̃² − 1) of the triad (the part of its excess power a wandering timing error
    of that size accounts for; the rest is white noise c² − 1).  ``evidence`` is against the
    best noise-only model of the triad, so a constant variance inflation earns nothing.  Residuals
    in the fit's own whitening (random effects already in the fit included): what the fit leaves."""
    t = prep.time.detach().cpu().double().numpy()
    sigma_max = float(np.median(np.diff(t))) if sigma_max is None else sigma_max
    out = {}
    for sensor in sensors:
        rows = []
        for k in range(prep.K):
            m = prep.m_acc[:, k] if sensor == "acc" else prep.m_gyro[:, k]
            if not bool(m.any()):
                continue
            f, a_sum, rr, n = triad_wander(prep, fit, k, sensor, sigma_max, whitening="model")
            excess = rr - n
            rows.append({"imu": k, "sigma_ms": 1e3 * f["sigma"], "rho": f["rho"], "c": f["c"], "evidence": f["evidence"],
                         "share": (f["sigma"] ** 2 * a_sum / excess) if excess > 0 else None})
        out[sensor] = rows
    return out

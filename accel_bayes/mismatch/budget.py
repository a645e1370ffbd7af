"""The residual budget of a mismatch report (DESIGN §7.2 vocabulary 1.1, top-level ``budget``):
how much excess variance the baseline leaves per sensor and motion regime, and how much of it
the refined model accounts for.

One row per sensor (``"acc"``, ``"gyro"``) and regime::

    {"sensor": "gyro", "regime": "|omega| 90-100%", "samples": n, "channel_samples": n_c,
     "excess_var_observed": a, "excess_var_explained": b, "stated_var": s2,
     "excess_var_observed_se": se}

Regimes (:func:`budget_regimes`): ``"all"``, and the quantile bands 0–25, 25–50, 50–75, 75–90 and
90–100 % of |ω| (``"|omega| 0-25%"`` …) and of |ω̇| (``"|omega_dot| 0-25%"`` …), from the
*baseline* fit's motion, so the rows of a and b cover the same samples.  ``samples`` counts the
time samples of the band, ``channel_samples`` the observed outputs of the sensor in it (every
IMU, every axis); a, b and ``stated_var`` are means over those channel-samples, in the sensor's
units² ((m/s²)² or (rad/s)²); ``excess_var_observed_se`` is a's standard error over blocks of
consecutive samples (:func:`_ratio_se`).

* ``a`` = mean of r̃² − σ², r the baseline residual, σ the stated noise std of the output's IMU.
  r̃² = r²/(1 − h) is the *leverage-corrected* squared residual (h the leverage of the sample's
  fitted motion state, :mod:`accel_bayes.mismatch.locate`): the per-sample motion [ω, ω̇, s] is
  fitted, which shrinks E[r²] to σ²(1 − h) — on a clean recording plain r² − σ² would be −σ²·h̄
  (−19 % of σ² with 8 IMUs) instead of 0.  Under the nominal model E[r̃²] = σ², so a ≈ 0 on clean
  data and a > 0 is the variance the model misses.
* ``b`` = (mean r̃²_baseline − mean r̃²_refined) + mean predicted extra variance, i.e. what the
  refined model's mean effects remove from the residuals plus what its variance effects predict
  on top of the stated noise.  Both r̃² are taken on **restricted** residuals
  (:func:`restricted_sq`): each fit's raw residual projected off the per-sample motion states in
  the stated-noise whitening, P_σ r, squared and leverage-corrected.  P_σ r = P_σ (y − mean
  effects) whatever motion the fit chose, so the removal term holds what the mean effects change
  and nothing of how the refined fit's weights (noise factors, random effects' predicted variance,
  their GLS offsets: :mod:`accel_bayes.mismatch.fit`) steered the motion — the same restricted
  residuals the random effects are profiled on (:mod:`accel_bayes.mismatch.jitter`).  For the
  baseline (stated noise, no weights) P_σ r = r and r̃² is :func:`leverage_corrected_sq`.  Until
  2026-11-28 the refined fit's own r̃² was used: a GLS refit that follows the IMUs without a
  random term (plate4: two accelerometer wanders, two reference IMUs with leverage 0.83) moves
  the references' excess into the termed IMUs' residuals, and that move counted as a negative
  removal (concealed clockgen clock-010: b = −0.032 (m/s²)² for a = 0.187;
  ``experiments/acc_budget_probe.md``).  The parts of b:

  - ``noise_level``: (c² − 1) σ², c the fitted noise factor of the output's IMU/sensor;
  - any other effect in the refined model that defines ``predicted_variance(params, ctx)``
    returning (acc_var, gyro_var), each (T, K, 3) in units² on top of the stated noise (the hook
    for random effects such as ``sampling_jitter``; ``ctx`` is the refined fit's
    :class:`~accel_bayes.physics.effects.SignalContext`, which carries the output rates);
  - the terms fitted beside the refined model and held out of its mean fit (``extra``: the
    detector's ``unresolved_motion``, :mod:`accel_bayes.mismatch.unresolved_stage`), through the
    same hook.

  A refined model that explains the misfit has b ≈ a in every row, not only in ``"all"``.  With
  no refined model (clean recording), b = 0.
"""
from __future__ import annotations

import numpy as np
import torch

from .model import ModelFit
from .prepared import Prepared

__all__ = ["BANDS", "band_edges", "budget_regimes", "leverage_corrected_sq", "stated_noise_system", "restricted_sq", "predicted_extra_variance", "residual_budget", "group_power"]

BANDS = ((0, 25), (25, 50), (50, 75), (75, 90), (90, 100))  # quantile bands, %


def band_edges(values) -> list[float]:
    """The inner edges of the :data:`BANDS` of ``values`` (any units): their 25, 50, 75 and 90 %
    quantiles, for ``np.digitize``."""
    return np.quantile(np.asarray(values, dtype=float), [b[0] / 100 for b in BANDS[1:]]).tolist()


def budget_regimes(fit: ModelFit) -> list[tuple[str, np.ndarray]]:
    """[(regime name, (T,) bool sample mask)]: "all", then the :data:`BANDS` of |ω| and of |ω̇|
    (rad/s, rad/s²) of ``fit``'s motion.  Band edges are quantiles; the top band includes its
    maximum, every other band its lower edge and not its upper one."""
    x = fit.x.detach().cpu().numpy()
    T = x.shape[0]
    out = [("all", np.ones(T, bool))]
    for name, v in (("|omega|", np.linalg.norm(x[:, 0:3], axis=1)), ("|omega_dot|", np.linalg.norm(x[:, 3:6], axis=1))):
        edges = band_edges(v)
        lab = np.digitize(v, edges, right=False)
        for j, (lo, hi) in enumerate(BANDS):
            out.append((f"{name} {lo}-{hi}%", lab == j))
    return out


def leverage_corrected_sq(prep: Prepared, fit: ModelFit) -> tuple[torch.Tensor, torch.Tensor]:
    """(acc, gyro) (T, K, 3): r²/(1 − h), raw residual r of ``fit`` (units²), h the leverage of
    the sample's motion state (module docstring); 0 where unobserved."""
    h = fit.linear().h.reshape(prep.T, 2, prep.K, 3)
    one_minus = (1 - h).clamp_min(1e-3)  # as in locate.standardized
    return (fit.res_acc ** 2 / one_minus[:, 0] * prep.m_acc, fit.res_gyro ** 2 / one_minus[:, 1] * prep.m_gyro)


def stated_noise_system(prep: Prepared, fit: ModelFit) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(Jx (T, 6K, 9), (JxᵀJx)⁻¹ (T, 9, 9), r (T, 6K)): ``fit``'s per-sample motion-state Jacobian and
    raw residual whitened by the **stated** noise σ alone.  The fit's linear system is whitened by
    its own weights (σ·factor·√(variance ratio)); its rows are scaled back to σ.  Rows are
    (acc, gyro) × IMU × axis, as ``fit.linear()``'s."""
    lin = fit.linear()
    T, K = prep.T, prep.K
    vr = getattr(getattr(fit.lm, "model", None), "var_ratio", None)
    back = torch.ones(T, 2, K, 3, dtype=torch.float64) if vr is None else torch.sqrt(vr)
    back = (back * torch.stack((fit.acc_factor, fit.gyro_factor))[None, :, :, None]).reshape(T, 6 * K)
    Jx = lin.Jx * back.unsqueeze(-1)
    return Jx, torch.linalg.inv(Jx.transpose(-1, -2) @ Jx), lin.r * back


def restricted_sq(prep: Prepared, fit: ModelFit) -> tuple[torch.Tensor, torch.Tensor]:
    """(acc, gyro) (T, K, 3) units²: (P_σ r)²/(1 − h_σ)·σ², r the raw residual of ``fit``, P_σ the
    per-sample residual-maker of the motion states and h_σ their leverage, both in the **stated**
    noise whitening (σ, no noise factors, no random-effect weights); 0 where unobserved (module
    docstring), in :func:`stated_noise_system`'s whitening.  Equals :func:`leverage_corrected_sq`
    for a fit without weights."""
    from .model import project_off_states

    T, K = prep.T, prep.K
    Jx, Vinv, r = stated_noise_system(prep, fit)
    h = ((Jx @ Vinv) * Jx).sum(-1)
    rp = project_off_states(Jx, Vinv, r)
    z2 = (rp * rp / (1 - h).clamp_min(1e-3)).reshape(T, 2, K, 3)  # as in locate.standardized
    return (z2[:, 0] * prep.sigma_acc[None, :, None] ** 2 * prep.m_acc,
            z2[:, 1] * prep.sigma_gyro[None, :, None] ** 2 * prep.m_gyro)


def predicted_extra_variance(prep: Prepared, fit: ModelFit, extra=()) -> tuple[torch.Tensor, torch.Tensor]:
    """(acc, gyro) (T, K, 3) the variance ``fit``'s model adds to the stated noise, units²: the
    noise factors' (c² − 1) σ² plus every effect's ``predicted_variance(params, ctx)`` where it
    has one, ``fit``'s effects and the terms ``extra`` (module docstring); 0 where unobserved."""
    va = ((fit.acc_factor ** 2 - 1) * prep.sigma_acc ** 2)[None, :, None].expand(prep.T, prep.K, 3).clone()
    vg = ((fit.gyro_factor ** 2 - 1) * prep.sigma_gyro ** 2)[None, :, None].expand(prep.T, prep.K, 3).clone()
    for e in list(fit.effects) + list(extra):
        fn = getattr(e, "predicted_variance", None)
        if fn is not None:
            a, g = fn(None, fit.ctx)
            va, vg = va + a, vg + g
    return va * prep.m_acc, vg * prep.m_gyro


def residual_budget(prep: Prepared, baseline: ModelFit, refined: ModelFit | None = None, *, extra=(),
                    predicted=None) -> list[dict]:
    """The budget rows of the module docstring for ``baseline`` and ``refined`` (None: b = 0),
    sensors acc then gyro, regimes in :func:`budget_regimes` order; ``extra``: terms fitted beside
    ``refined`` whose predicted variance is part of b; ``predicted``: (acc, gyro) (T, K, 3) units²
    to use instead of :func:`predicted_extra_variance` (e.g. with random-effect scales taken from
    another recording).  Sensors without any observed output are left out."""
    regs = budget_regimes(baseline)
    base_sq = restricted_sq(prep, baseline)
    if refined is not None:
        ref_sq = restricted_sq(prep, refined)
        pred = predicted_extra_variance(prep, refined, extra) if predicted is None else \
            (predicted[0] * prep.m_acc, predicted[1] * prep.m_gyro)
    rows = []
    for j, sensor in enumerate(("acc", "gyro")):
        mask = prep.m_acc if sensor == "acc" else prep.m_gyro
        sig2 = ((prep.sigma_acc if sensor == "acc" else prep.sigma_gyro) ** 2)[None, :, None] * mask
        # per time sample: (observed count, Σ r̃²_base, Σ σ², Σ r̃²_ref, Σ predicted extra)
        per_t = [mask.sum((1, 2)), base_sq[j].sum((1, 2)), sig2.sum((1, 2))]
        if refined is not None:
            per_t += [ref_sq[j].sum((1, 2)), pred[j].sum((1, 2))]
        per_t = np.stack([v.detach().cpu().numpy() for v in per_t], 1)
        if per_t[:, 0].sum() == 0:
            continue
        for name, sel in regs:
            s = per_t[sel].sum(0)
            n = float(s[0])
            if n == 0:
                a = b = s2 = se = float("nan")
            else:
                a = (s[1] - s[2]) / n
                s2 = s[2] / n
                b = ((s[1] - s[3]) + s[4]) / n if refined is not None else 0.0
                se = _ratio_se(per_t[sel, 1] - per_t[sel, 2], per_t[sel, 0], a)
            rows.append({"sensor": sensor, "regime": name, "samples": int(sel.sum()), "channel_samples": int(n),
                         "excess_var_observed": float(a), "excess_var_explained": float(b), "stated_var": float(s2),
                         "excess_var_observed_se": float(se)})
    return rows


#: consecutive samples of a regime per block of :func:`_ratio_se`: the excess comes in bursts
#: (impacts) that last several samples, so samples are not independent
SE_BLOCK = 16


def _ratio_se(x: np.ndarray, n: np.ndarray, ratio: float) -> float:
    """Standard error of Σx/Σn (the ratio estimator over blocks of :data:`SE_BLOCK` consecutive
    samples, taken as independent): x (T,) per-sample excess sums, n (T,) channel counts."""
    nb = max(len(x) // SE_BLOCK, 1)
    xb = np.array([v.sum() for v in np.array_split(x, nb)])
    cb = np.array([v.sum() for v in np.array_split(n, nb)])
    if nb < 2 or cb.sum() == 0:
        return float("nan")
    return float(np.sqrt(nb / (nb - 1) * ((xb - ratio * cb) ** 2).sum()) / cb.sum())


def group_power(prep: Prepared, fit: ModelFit, effect, h: torch.Tensor) -> float:
    """Mean leverage-corrected z² (model noise units) of the IMU/sensor group(s) an effect acts
    on, at a fit; ``h`` (T, m) the leverage of the per-sample motion states (from the fit the
    candidate extends: the leverage hardly moves when one effect is added)."""
    T, K = prep.T, prep.K
    which = getattr(effect, "which", None) or effect.sensor
    groups = ("acc", "gyro") if which == "both" else (which,)
    from .jitter import variance_ratio

    ratio = variance_ratio(prep, fit)  # random effects' predicted variance is not excess
    za = (fit.res_acc / (prep.sigma_acc * fit.acc_factor)[None, :, None]) ** 2 / ratio[:, 0]
    zg = (fit.res_gyro / (prep.sigma_gyro * fit.gyro_factor)[None, :, None]) ** 2 / ratio[:, 1]
    hh = h.reshape(T, 2, K, 3)
    num = den = 0.0
    for gname in groups:
        z2 = (za if gname == "acc" else zg) / (1 - hh[:, 0 if gname == "acc" else 1]).clamp_min(1e-3)
        m = prep.m_acc if gname == "acc" else prep.m_gyro
        if effect.imu is not None:
            z2, m = z2[:, effect.imu], m[:, effect.imu]
        num += float((z2 * m).sum())
        den += float(m.sum())
    return num / den if den > 0 else 1.0

"""The detector's gyro linear stage (:func:`accel_bayes.mismatch.detect`, step 3a): every
gyroscope's whole linear error, y_k = (I + M_k) g_k + b_k (sensor frame; g_k the true rate
R_k ω, M_k 3 × 3 relative, b_k rad/s; :class:`~accel_bayes.physics.effects.GyroLinear`), before
the rounds that name one effect at a time.

Why a stage of its own.  Raw MEMS gyros carry all twelve terms on every IMU (the MIMU4444's
reach 1.85 % per entry and repeat across recordings to ≤ 0.11 %, experiments/gyro_linear_check.md).
A round adds one 1-df term, leaving eleven per IMU in the residual, where a random timing
effect explains them better: with such errors on every IMU the detector named the concealed
effect right in 1 of 21 cases (experiments/mismatch_multi.md, before this stage).

How (block-coordinate maximum likelihood on the detector's own model):

1. **Relative blocks, closed form.**  Given the fitted rates ĝ_k (the nominal gyro outputs of
   the current fit), each IMU's [I + M_k | b_k] is the least-squares regression of its gyro
   outputs on [ĝ_k, 1] — the exact conditional maximum-likelihood estimate, since the block is
   linear and acts on that gyro alone.  The recording is corrected, y ← (I + M_k)⁻¹(y − b_k), the
   motion and geometry refitted (:func:`~accel_bayes.mismatch.fit.fit_model`, no effects), and
   the regression repeated on the original outputs (``passes``, default 2).  The fitted rate
   follows the gyros, so these blocks are relative to the array's mean gyro.
2. **The common part, through the lever arms.**  An error shared by all gyros moves the fitted
   rate with it and is only seen by the accelerometers' centripetal terms; it is fitted as
   one array-frame ``GyroLinear(imu=None)`` (12 parameters) by the LM solver on the corrected
   recording, kept when its heteroscedasticity-robust Wald statistic (:func:`robust_wald`, the
   trace-free matrix and the offset, 11 df; the isotropic part is the array's size, below) passes
   χ²_11 at 1 − α/m, and folded into every IMU's block: I + M_k ← (I + M_k)(I + R_k C R_kᵀ),
   b_k ← (I + M_k) R_k c + b_k.  Why robust: at this point of the detector the accelerometers still
   carry what the clock and unresolved-motion stages model later — the board's vibration read at
   each IMU's own data age — an excess that grows with the motion, i.e. where the centripetal terms
   that see the common part are large.  Judged by its likelihood ratio over the residual power (the
   rounds' F-type guard, which assumes the excess is spread evenly) the common part took it: on
   clockgen's clock-006 and clock-016 it kept entries of 0.22 and 0.12 where the gyros share ≤ 0.017
   (``experiments/gyro_common_stage_probe.md``); the robust statistic is 16–23 there (threshold 39;
   the model-based Wald statistic of the same estimate 1536–1925) and within 10 % of the model-based
   one where the accelerometers' misfit is white (the synchronised twins, no vibration: 31–125).
   What no test can tell apart is a systematic error: on accelerometers ``prep`` could not calibrate,
   the common part takes their errors (kept by either test); the accelerometer stage (opt-in)
   restages it on corrected triads (:mod:`accel_bayes.mismatch.acc_linear`).
3. **Tests.**  The errors must be spread over several gyros: the spread share
   (:func:`~accel_bayes.mismatch.linear_blocks.spread_share`) at least :data:`MIN_SPREAD_SHARE` and
   its statistic above χ²_{12(n−2)} at 1 − α/m; below the share, the others' relative blocks with
   the strongest gyro's block inverted (:func:`~accel_bayes.mismatch.linear_blocks.others_after_top`)
   above χ²_{12(n−1)} at 1 − α/m — on boards of few gyros the share of independent errors is itself
   near (n − 2)/(n − 1) (experiments/gyro_spread_check.md).  Before any
   refit, the group's conditional statistic Σ_k Σ_t |M_k ĝ_kt + b_k|²/σ_k²
   at the baseline (noise-robust: over max(1, P), P the mean z² left in the gyros after the
   regression) is held to χ²_{12n} at 1 − α/m; below it the stage stops (cost: n regressions).
   After the fit, each block's statistic (the same sum for its IMU, over max(1, P_k)) is held to
   χ²_12 at 1 − α/m, and at least two of its twelve terms must pass χ²_1 at 1 − α/m on their own
   (z² with the noise-robust standard deviations below): a gyro with a single scale, coupling or
   offset error is left to the rounds, which name that term on its axis.  Blocks that fail are
   dropped and the recording is corrected with the others.

The array-size gauge.  The same isotropic scale error on every gyro is a rescaling of the whole
array (the centripetal terms grow with ω², the tangential ones are free per sample, the
positions scale), so no data see it.  The stage holds the *median* gyro's isotropic scale at
zero: one badly scaled gyro then carries its own error instead of spreading a seventh of it
over the others (which the rounds would otherwise meet as eight small blocks).

The stage returns the corrected :class:`~accel_bayes.mismatch.prepared.Prepared` (the rounds
run on it, the blocks held at their estimates), the fit on it, and the kept blocks with their
statistics and standard deviations (the regression's, σ_k² (XᵀX)⁻¹ per output axis, rate
uncertainty neglected: the rate is pinned by all n gyros).  The data transform's Jacobian
(|I + M_k|⁻¹ per sample, ~1 ± 0.03) is left out of the log-likelihoods compared.

Measured: experiments/mismatch_multi.md (the 21 concealed multi-effect cases) and
experiments/mimu_mismatch.md (the six real recordings).
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..physics.effects import GyroLinear
from ..physics.geometry import quat_to_matrix
from .fit import fit_model
from .linear_blocks import (MIN_SPREAD_SHARE, LinearStage, block_sd, block_stat_t, corrected_outputs, design,
                            linear_stage, lstsq, power, relative_blocks, rows, set_block_std)
from .model import ModelFit
from .prepared import Prepared

__all__ = ["GyroLinearStage", "gyro_linear_stage", "relative_blocks", "corrected_gyro", "block_corrected_recording",
           "robust_wald", "MIN_SPREAD_SHARE", "COMMON_DF"]

#: what :func:`gyro_linear_stage` returns (the stage record both linear stages share)
GyroLinearStage = LinearStage


def corrected_gyro(prep: Prepared, A: torch.Tensor, b: torch.Tensor) -> Prepared:
    """``prep`` with every gyro output y_k replaced by A_k⁻¹(y_k − b_k) and its stated noise rescaled
    (:func:`accel_bayes.mismatch.linear_blocks.corrected_outputs` on the gyros)."""
    return corrected_outputs(prep, A, b, "gyro")


#: the common part's parameters tested (:func:`robust_wald`): the 3 × 3 matrix less its isotropic part
#: (the array's size, held at the gauge) and the offset
COMMON_DF = 11


def robust_wald(fit: ModelFit, n_eff: int, drop_isotropic: bool = True) -> tuple[float, float]:
    """(robust, model-based) Wald statistics of the last ``n_eff`` mean-effect parameters of ``fit`` (a
    ``GyroLinear``'s flattened matrix, 9, then offset, 3) against zero, the matrix's isotropic part left out
    (``drop_isotropic``: it trades with the array's size).

    Model-based: η̂ᵀ [S⁻¹]_ηη⁻¹ η̂ with S the reduced information (motion states eliminated sample by
    sample, :class:`~accel_bayes.mismatch.model.LinearSystem`).  Robust (HC0 sandwich, White 1980): the
    covariance S⁻¹ B S⁻¹ with B = Σ_t u_t u_tᵀ, u_t the sample's efficient score (Jg_t − Jx_t Z_t)ᵀ r_t in
    the stated noise's whitening — honest when the misfit's variance varies with the motion, not when it
    is correlated from sample to sample (blocks of samples would leave too few for the 12 + 3F globals on
    a 20 s recording)."""
    lin = fit.linear()
    r = lin.r[None]
    u = lin.jg_tmul(r, per_sample=True)[0] - torch.einsum("tdn,td->tn", lin.Z, lin.jx_tmul(r)[0])
    cov_rob = lin.Sinv @ (u.T @ u) @ lin.Sinv
    eta = torch.cat([e.flatten() for e in fit.effects if e.kind in ("mean", "clip")])[-n_eff:]
    Q = torch.eye(n_eff, dtype=torch.float64)
    if drop_isotropic:
        t = torch.zeros(n_eff, dtype=torch.float64)
        t[[0, 4, 8]] = 3 ** -0.5
        ev, U = torch.linalg.eigh(Q - torch.outer(t, t))
        Q = U[:, ev > 0.5]
    e = Q.T @ eta

    def stat(cov):
        return float(e @ torch.linalg.solve(Q.T @ cov[-n_eff:, -n_eff:] @ Q, e))

    return stat(cov_rob), stat(lin.Sinv)


def _common_part(prep_c: Prepared, fit: ModelFit, A: torch.Tensor, b: torch.Tensor, info: dict, level: float):
    """Step 2 (module docstring): one array-frame ``GyroLinear(imu=None)`` fitted through the lever
    arms on the corrected recording, kept when its heteroscedasticity-robust Wald statistic
    (:func:`robust_wald`) passes χ²_11 at 1 − ``level`` (α/m), and folded into every gyro's block.
    Returns (fit, A, b)."""
    from scipy.stats import chi2

    common = GyroLinear(imu=None)
    thr = float(chi2.isf(level, COMMON_DF))
    try:
        fc = fit_model(prep_c, [common], init=fit, laplace=False)
        lr = 2.0 * (fc.loglik - fit.loglik) / max(power(prep_c, fc, None, "acc"), 1.0)
        wald, wald_model = robust_wald(fc, 12)
    except Exception as exc:  # the common part is a refinement; without it the blocks are relative
        fc, lr, wald, wald_model = None, float("nan"), float("nan"), float("nan")
        info["common_error"] = f"{type(exc).__name__}: {exc}"
    info.update({"common_statistic_robust": wald, "common_threshold": thr, "common_df": COMMON_DF,
                 "common_statistic_kind": "heteroscedasticity-robust (HC0) Wald statistic of the trace-free matrix "
                                          "and the offset (gyro_linear.robust_wald)",
                 "common_wald_model": wald_model, "common_lr_over_acc_power": lr})
    if fc is not None and wald > thr:
        e = fc.effects[0]
        R = quat_to_matrix(prep_c.q)  # array → sensor
        C = R @ e.params["matrix"] @ R.transpose(1, 2)
        c = R @ e.params["bias"]
        hg = torch.as_tensor(prep_c.has_gyro)
        A_new = A @ (torch.eye(3, dtype=torch.float64) + C)
        b_new = torch.einsum("kij,kj->ki", A, c) + b
        A = torch.where(hg[:, None, None], A_new, A)
        b = torch.where(hg[:, None], b_new, b)
        info["common"] = {"matrix": e.params["matrix"].tolist(), "bias": e.params["bias"].tolist(), "kept": True}
        fit = fc
    return fit, A, b


def gyro_linear_stage(prep: Prepared, base: ModelFit, *, m: int, alpha: float, passes: int = 2,
                      common: bool = True) -> LinearStage:
    """Run step 3a (module docstring) from the baseline fit ``base`` of ``prep``; ``m`` and
    ``alpha`` are the detector's Bonferroni count and family-wise error rate.  ``common=False`` skips
    step 2 (the blocks stay relative): the detector's first pass when the accelerometer linear stage
    follows, since the common part is seen through the accelerometers (:mod:`accel_bayes.mismatch.acc_linear`)."""
    return linear_stage(prep, base, sensor="gyro", block=lambda k, p: GyroLinear(imu=k, params=p), m=m, alpha=alpha,
                        passes=passes, common=_common_part if common else None)


def block_corrected_recording(rec, blocks):
    """A :class:`~accel_bayes.data.recording.Recording` with the linear stages' blocks inverted on its
    outputs (each block on its own sensor, gyro or acc; every sample; a sample with a NaN channel stays
    NaN): what the rounds were run on, for the posterior comparison."""
    if not blocks:
        return rec
    out = {"gyro": np.array(rec.gyro, dtype=np.float64, copy=True)}
    if any(e.sensor == "acc" for e in blocks):
        out["acc"] = np.array(rec.acc, dtype=np.float64, copy=True)
    for e in blocks:
        y = out[e.sensor]
        y[:, e.imu] = e.invert(y[:, e.imu])
    return dataclasses.replace(rec, **out)


def refresh_blocks(prep0: Prepared, stage: GyroLinearStage, fit: ModelFit) -> ModelFit:
    """Re-estimate the kept blocks after a round has added a finding, and refit: the blocks were
    first fitted without it, and an effect on a gyro leaks into its block (a second-order response
    into the offset and scale, a timing error's large residual into the couplings — which the
    accelerometers then read as a rotated triad).  Each block is the regression of the original
    outputs of ``prep0`` on the model's predicted gyro outputs (``fit.pred_gyro``: rates plus the
    findings' mean gyro effects), weighted per sample and axis by 1/(1 + predicted random variance
    / noise variance) of the findings' random effects (:func:`~accel_bayes.mismatch.jitter.variance_ratio`).
    ``stage`` is updated in place (``prep``, ``fit``, the blocks' parameters, statistics and
    standard deviations); returns the refitted model on the re-corrected recording."""
    from .jitter import variance_ratio

    if not stage.blocks:
        return fit
    I3 = torch.eye(3, dtype=torch.float64)
    A = I3.repeat(prep0.K, 1, 1)
    b = torch.zeros(prep0.K, 3, dtype=torch.float64)
    ratio = variance_ratio(stage.prep, fit)[:, 1]  # (T, K, 3) gyro channels
    pred = fit.pred_gyro
    for e in stage.blocks:
        k = e.imu
        r = rows(prep0, k)
        X = design(pred[:, k], r)
        for i in range(3):
            sw = ratio[r, k, i].rsqrt()[:, None]
            beta = lstsq(X * sw, prep0.y_gyro[r, k, i:i + 1] * sw)[:, 0]
            A[k, i], b[k, i] = beta[:3], beta[3]
    prep_c = corrected_gyro(prep0, A, b)
    fit = fit_model(prep_c, [e.copy() for e in fit.effects], init=fit, laplace=False)
    gain_t = np.zeros(prep0.T)
    for e in stage.blocks:
        k = e.imu
        r, sigma = rows(prep0, k), float(prep0.sigma_gyro[k])
        st_t = block_stat_t(fit.pred_gyro[:, k], A[k], b[k], sigma, r)
        p_k = power(prep_c, fit, k)
        e.set_params({"matrix": A[k] - I3, "bias": b[k]})
        set_block_std(e, block_sd(fit.pred_gyro[:, k], r, sigma, p_k))
        e.stats.update({"statistic": float(st_t.sum()), "statistic_robust": float(st_t.sum()) / max(p_k, 1.0),
                        "gyro_power_after": p_k, "refreshed": e.stats.get("refreshed", 0) + 1})
        gain_t += st_t.numpy() / max(p_k, 1.0)
    stage.prep, stage.fit, stage.gain_t = prep_c, fit, gain_t
    return fit

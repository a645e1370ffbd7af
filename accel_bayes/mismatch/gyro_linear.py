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
   recording, kept when its likelihood ratio passes χ²_12 at 1 − α/m, and folded into every
   IMU's block: I + M_k ← (I + M_k)(I + R_k C R_kᵀ), b_k ← (I + M_k) R_k c + b_k.
3. **Tests.**  The errors must be spread over several gyros (:data:`MIN_SPREAD_SHARE`, and the
   spread statistic of :func:`_spread_share` above χ²_{12(n−2)} at 1 − α/m).  Before any
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

import math

import dataclasses
import time as _time
from types import SimpleNamespace

import numpy as np
import torch

from ..physics.effects import GyroLinear
from ..physics.geometry import quat_to_matrix
from .budget import group_power
from .fit import fit_model
from .model import ModelFit
from .prepared import Prepared

__all__ = ["GyroLinearStage", "gyro_linear_stage", "relative_blocks", "corrected_gyro", "block_corrected_recording"]


@dataclasses.dataclass
class GyroLinearStage:
    """What the stage found: ``prep`` (corrected, or the input when nothing was kept), ``fit``
    (on ``prep``), ``blocks`` (kept :class:`GyroLinear` effects, parameters and ``std`` set,
    ``stats`` with the statistic), ``gain_t`` (T,) the per-sample statistic of the kept blocks,
    ``info`` (the report's ``details.gyro_linear_stage``)."""

    prep: Prepared
    fit: ModelFit
    blocks: list
    gain_t: np.ndarray | None
    info: dict


#: the stage runs only when the gyro errors are spread over several IMUs (:func:`_spread_share`).
#: One erroneous gyro leaks 1/n of its error into every other through the fitted (mean) rate, the
#: same array-frame error on each: the others then differ from their common part by noise only
#: (share ≈ 0 for a strong error), while independent errors on every gyro give ≈ 1 (0.94–0.99 on the 42
#: concealed multi-effect recordings, 1.02 and 1.08 on MIMU exp_1 and exp_4; 0.003–0.49 on six
#: mismatch_proof cases with one erroneous gyro).
#: The share alone is not enough: where the others' blocks are noise (one gyro's error that is not
#: linear in the rate, e.g. a g-sensitivity, leaks no common linear pattern) the share of noise is
#: ≈ (n − 2)/(n − 1); the stage also needs the spread *statistic* above its χ²_{12(n−2)} quantile
#: (mismatch_proof's gyro_g_sensitivity-000 on mimu32: share 0.77, statistic 384 against 489).
#: A single gyro's scale, coupling or offset is named term by term, on its axis, by the rounds
#: (experiments/mismatch_proof.py).
MIN_SPREAD_SHARE = 0.7


def _spread_share(prep: Prepared, g_hat: torch.Tensor, rel: dict, imus) -> tuple[float, float]:
    """How much of the relative errors is *not* one gyro's error seen through the mean rate: with
    D_k(t) = R_kᵀ((A_k − I) ĝ_kt + b_k) (array frame) and top the IMU with the largest statistic,
    (share, statistic): the statistic Σ_{k≠top} Σ_t |D_k − D̄|²/σ_k² (≈ χ²_{12(n−2)} when the
    others carry only the common leak and noise) and its share of Σ_{k≠top} Σ_t |D_k|²/σ_k², D̄
    the mean over k ≠ top."""
    R = quat_to_matrix(prep.q)
    I3 = torch.eye(3, dtype=torch.float64)
    top = max(imus, key=lambda k: float(rel["stat"][k]))
    others = [k for k in imus if k != top]
    if len(others) < 2:
        return 1.0, math.inf
    D = torch.stack([(g_hat[:, k] @ (rel["A"][k] - I3).T + rel["b"][k]) @ R[k] for k in others], 1)  # (T, n-1, 3)
    w = torch.stack([prep.m_gyro[:, k].min(-1).values / float(prep.sigma_gyro[k]) ** 2 for k in others], 1)
    dev = D - D.mean(1, keepdim=True)
    num = float(((dev ** 2).sum(-1) * w).sum())
    den = float(((D ** 2).sum(-1) * w).sum())
    return (num / den if den > 0 else 1.0), num


def _rows(prep: Prepared, k: int) -> torch.Tensor:
    """(T,) bool: the samples where IMU k's three gyro channels are observed."""
    return prep.m_gyro[:, k].min(-1).values > 0


def _design(g_k: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """The regression design [g_k, 1] (n, 4) of one gyro's block on the given rows."""
    return torch.cat((g_k[rows], torch.ones(int(rows.sum()), 1, dtype=torch.float64)), 1)


def _lstsq(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """The least-squares solution β of X β ≈ Y (minimum norm if X is rank-deficient), by LAPACK's
    SVD driver ``gelsd``.  Not torch's CPU default ``gelsy``: with the MKL that torch ships, gelsy's
    result depends on the operands' memory alignment (2-7 different last bits over 16 offsets of the
    same (n, 4) design, n = 97-20000), so that the same recording and seed gave detect reports that
    differed run to run (tests/mismatch/test_detect_determinism.py); gelsd, gelss and gels gave one
    result over every offset, and gelsd keeps gelsy's treatment of a rank-deficient design (an IMU
    turned about one axis only) — the minimum-norm solution below the relative cut-off eps·max(n, 4)."""
    return torch.linalg.lstsq(X, Y, driver="gelsd").solution


def _block_stat_t(g_k: torch.Tensor, A_k: torch.Tensor, b_k: torch.Tensor, sigma: float, rows) -> torch.Tensor:
    """(T,) per-sample statistic |(A_k − I) g_kt + b_k|²/σ² of one block (0 off ``rows``)."""
    d = g_k @ (A_k - torch.eye(3, dtype=torch.float64)).T + b_k
    return (d ** 2).sum(-1) / sigma ** 2 * rows


def _block_sd(g_k: torch.Tensor, rows, sigma: float, power: float) -> torch.Tensor:
    """(4,) standard deviations of each output axis' row [A_k − I | b_k] of a block fitted on
    [g_k, 1]: σ √diag((XᵀX)⁻¹), inflated by √max(1, P) (P the gyro's leftover power)."""
    X = _design(g_k, rows)
    return (torch.linalg.inv(X.T @ X).diagonal().clamp_min(0) * sigma ** 2 * max(power, 1.0)).sqrt()


def relative_blocks(prep: Prepared, g_hat: torch.Tensor, imus) -> dict:
    """Step 1's regression: per IMU k in ``imus``, y_k ≈ A_k ĝ_k + b_k over its observed samples.

    g_hat (T, K, 3) fitted sensor-frame rates (rad/s).  Returns {"A": (K, 3, 3), "b": (K, 3)} (identity/zero
    for IMUs not in ``imus``), "stat" (K,) Σ_t |(A_k − I) ĝ_kt + b_k|²/σ_k², "stat_t" (T, K) and
    "rss_z2" (K,) the mean z² left.
    """
    T, K = prep.T, prep.K
    A = torch.eye(3, dtype=torch.float64).repeat(K, 1, 1)
    b = torch.zeros(K, 3, dtype=torch.float64)
    stat_t = torch.zeros(T, K, dtype=torch.float64)
    rss = torch.ones(K, dtype=torch.float64)
    for k in imus:
        rows = _rows(prep, k)
        if int(rows.sum()) < 12:
            continue
        X = _design(g_hat[:, k], rows)
        Y = prep.y_gyro[rows, k]
        beta = _lstsq(X, Y)  # (4, 3): Y ≈ X β
        A[k], b[k] = beta[:3].T, beta[3]
        sigma = float(prep.sigma_gyro[k])
        stat_t[:, k] = _block_stat_t(g_hat[:, k], A[k], b[k], sigma, rows)
        rss[k] = ((Y - X @ beta) ** 2).sum() / sigma ** 2 / max(int(rows.sum()) * 3 - 12, 1)
    return {"A": A, "b": b, "stat": stat_t.sum(0), "stat_t": stat_t, "rss_z2": rss}


def corrected_gyro(prep: Prepared, A: torch.Tensor, b: torch.Tensor) -> Prepared:
    """``prep`` with every gyro output y_k replaced by A_k⁻¹(y_k − b_k) (unobserved channels stay 0)
    and its stated noise σ_k by σ_k |det A_k|^(−1/3): the correction rescales the noise too, and a
    gyro read 2 % too high would otherwise look 2 % quieter than stated (a spurious noise_level)."""
    y = torch.einsum("kij,tkj->tki", torch.linalg.inv(A), prep.y_gyro - b[None])
    sg = prep.sigma_gyro * torch.linalg.det(A).abs().pow(-1.0 / 3.0)
    return dataclasses.replace(prep, y_gyro=y * prep.m_gyro, sigma_gyro=sg)


def _set_std(e: GyroLinear, sd: torch.Tensor) -> None:
    """A block's std from its rows' (4,) standard deviations: column j of the matrix, the offset."""
    e.std = {"matrix": sd[:3].expand(3, 3).clone(), "bias": sd[3].expand(3).clone()}


def _power(prep: Prepared, fit: ModelFit, imu) -> float:
    return group_power(prep, fit, SimpleNamespace(sensor="gyro", imu=imu), fit.linear().h)


def gyro_linear_stage(prep: Prepared, base: ModelFit, *, m: int, alpha: float, passes: int = 2) -> GyroLinearStage:
    """Run step 3a (module docstring) from the baseline fit ``base`` of ``prep``; ``m`` and
    ``alpha`` are the detector's Bonferroni count and family-wise error rate."""
    from scipy.stats import chi2

    t0 = _time.perf_counter()
    imus = [int(k) for k in np.flatnonzero(prep.has_gyro)]
    n = len(imus)
    thr_group = float(chi2.isf(alpha / m, 12 * n))
    thr_block = float(chi2.isf(alpha / m, 12))
    info = {"imus": imus, "group_df": 12 * n, "group_threshold": thr_group, "block_threshold": thr_block}

    def done(result, prep_=prep, fit_=base, blocks=(), gain_t=None):
        info["result"] = result
        info["seconds"] = _time.perf_counter() - t0
        return GyroLinearStage(prep_, fit_, list(blocks), gain_t, info)

    # 3 (first half): the cheap group test at the baseline
    rel = relative_blocks(prep, base.ctx.gyro, imus)
    p_left = float(rel["rss_z2"][imus].mean())
    g_stat = float(rel["stat"].sum()) / max(p_left, 1.0)
    info.update({"group_statistic": float(rel["stat"].sum()), "group_statistic_robust": g_stat,
                 "gyro_power_left": p_left})
    if g_stat <= thr_group:
        return done("group below its threshold: no gyro linear errors")
    spread, spread_stat = _spread_share(prep, base.ctx.gyro, rel, imus)
    spread_stat /= max(p_left, 1.0)
    thr_spread = float(chi2.isf(alpha / m, 12 * max(n - 2, 1)))
    info.update({"spread_share": spread, "spread_statistic_robust": spread_stat, "spread_threshold": thr_spread})
    if spread < MIN_SPREAD_SHARE:
        return done(f"the errors sit on one gyro (the others differ by a common leak only: spread share "
                    f"{spread:.3f} < {MIN_SPREAD_SHARE}): left to the rounds, term by term")
    if spread_stat <= thr_spread:
        # the others' blocks are noise: a share near 1 then says nothing (one gyro's error that is
        # not linear in the rate, e.g. a g-sensitivity, leaks no common pattern to compare with)
        return done(f"the errors sit on one gyro (the others' relative blocks are noise: spread statistic "
                    f"{spread_stat:.4g} <= {thr_spread:.4g}, χ²_{12 * max(n - 2, 1)}): left to the rounds, term by term")
    # 1: relative blocks, alternating with the motion
    fit = base
    for _ in range(int(passes)):
        rel = relative_blocks(prep, fit.ctx.gyro, imus)
        prep_c = corrected_gyro(prep, rel["A"], rel["b"])
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    A, b = rel["A"].clone(), rel["b"].clone()
    # 2: the common part, through the lever arms
    common = GyroLinear(imu=None)
    try:
        fc = fit_model(prep_c, [common], init=fit, laplace=False)
        lr = 2.0 * (fc.loglik - fit.loglik) / max(_power(prep_c, fc, None), 1.0)
    except Exception as exc:  # the common part is a refinement; without it the blocks are relative
        fc, lr = None, float("nan")
        info["common_error"] = f"{type(exc).__name__}: {exc}"
    info["common_statistic_robust"] = lr
    if fc is not None and lr > thr_block:
        e = fc.effects[0]
        R = quat_to_matrix(prep.q)  # array → sensor
        C = R @ e.params["matrix"] @ R.transpose(1, 2)
        c = R @ e.params["bias"]
        hg = torch.as_tensor(prep.has_gyro)
        A_new = A @ (torch.eye(3, dtype=torch.float64) + C)
        b_new = torch.einsum("kij,kj->ki", A, c) + b
        A = torch.where(hg[:, None, None], A_new, A)
        b = torch.where(hg[:, None], b_new, b)
        info["common"] = {"matrix": e.params["matrix"].tolist(), "bias": e.params["bias"].tolist(), "kept": True}
        fit = fc
    # the array-size gauge: the same scale error on every gyro is a rescaling of the whole array
    # (the rates' centripetal terms grow with ω², the tangential ones are free per sample), so it is
    # not seen by any data; hold the median gyro's isotropic scale at zero
    hg = torch.as_tensor(prep.has_gyro)
    iso = torch.stack([torch.diagonal(A[k]).sum() / 3 - 1 for k in imus])
    c = float(iso.median())
    A = torch.where(hg[:, None, None], A / (1 + c), A)
    b = torch.where(hg[:, None], b / (1 + c), b)
    info["isotropic_gauge"] = {"rule": "median gyro's isotropic scale error held at 0", "removed": c}
    # 3 (second half): each block's statistic at the fit and its terms' z-scores
    prep_c = corrected_gyro(prep, A, b)
    fit = fit_model(prep_c, (), init=fit, laplace=False)
    I3 = torch.eye(3, dtype=torch.float64)
    g_hat = fit.ctx.gyro
    thr_term = float(chi2.isf(alpha / m, 1))
    info["term_threshold"] = thr_term
    blocks_info, keep = {}, []
    for k in imus:
        rows, sigma = _rows(prep, k), float(prep.sigma_gyro[k])
        st_t = _block_stat_t(g_hat[:, k], A[k], b[k], sigma, rows)
        p_k = _power(prep_c, fit, k)
        st = float(st_t.sum()) / max(p_k, 1.0)
        sd = _block_sd(g_hat[:, k], rows, sigma, p_k)
        z2 = (torch.cat((A[k] - I3, b[k][:, None]), 1) / sd[None, :]) ** 2  # (3, 4): [M | b] rows
        n_terms = int((z2 > thr_term).sum())
        blocks_info[k] = {"statistic": float(st_t.sum()), "statistic_robust": st, "gyro_power_after": p_k,
                          "significant_terms": n_terms}
        # one significant term is the rounds' business: a single scale, coupling or offset is named
        # there on its own axis (and a second-order response is not mistaken for an offset block)
        if st > thr_block and n_terms >= 2:
            keep.append(k)
    info["blocks"] = blocks_info
    info["kept"] = keep
    if not keep:
        return done("no block above its threshold with two or more significant terms")
    if len(keep) < n:
        drop = torch.tensor([k not in keep for k in range(prep.K)])
        A = torch.where(drop[:, None, None], I3.expand_as(A), A)
        b = torch.where(drop[:, None], torch.zeros_like(b), b)
        prep_c = corrected_gyro(prep, A, b)
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    blocks, gain_t = [], np.zeros(prep.T)
    for k in keep:
        rows, sigma, p_k = _rows(prep, k), float(prep.sigma_gyro[k]), blocks_info[k]["gyro_power_after"]
        e = GyroLinear(imu=k, params={"matrix": A[k] - I3, "bias": b[k]})
        _set_std(e, _block_sd(fit.ctx.gyro[:, k], rows, sigma, p_k))
        e.stats = dict(blocks_info[k])
        blocks.append(e)
        # over every sample (unmasked, unlike the refresh's): it only says where the block acts
        gain_t += _block_stat_t(fit.ctx.gyro[:, k], A[k], b[k], sigma, True).numpy() / max(p_k, 1.0)
    info["evidence_group"] = 2.0 * (fit.loglik - base.loglik)
    return done(f"kept blocks on IMUs {keep}", prep_c, fit, blocks, gain_t)


def block_corrected_recording(rec, blocks):
    """A :class:`~accel_bayes.data.recording.Recording` with the stage's blocks inverted on its gyro
    outputs (every sample; a sample with a NaN channel stays NaN): what the rounds were run on, for the posterior comparison."""
    if not blocks:
        return rec
    g = np.array(rec.gyro, dtype=np.float64, copy=True)
    for e in blocks:
        g[:, e.imu] = e.invert(g[:, e.imu])
    return dataclasses.replace(rec, gyro=g)


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
        rows = _rows(prep0, k)
        X = _design(pred[:, k], rows)
        for i in range(3):
            sw = ratio[rows, k, i].rsqrt()[:, None]
            beta = _lstsq(X * sw, prep0.y_gyro[rows, k, i:i + 1] * sw)[:, 0]
            A[k, i], b[k, i] = beta[:3], beta[3]
    prep_c = corrected_gyro(prep0, A, b)
    fit = fit_model(prep_c, [e.copy() for e in fit.effects], init=fit, laplace=False)
    gain_t = np.zeros(prep0.T)
    for e in stage.blocks:
        k = e.imu
        rows, sigma = _rows(prep0, k), float(prep0.sigma_gyro[k])
        st_t = _block_stat_t(fit.pred_gyro[:, k], A[k], b[k], sigma, rows)
        p_k = _power(prep_c, fit, k)
        e.set_params({"matrix": A[k] - I3, "bias": b[k]})
        _set_std(e, _block_sd(fit.pred_gyro[:, k], rows, sigma, p_k))
        e.stats.update({"statistic": float(st_t.sum()), "statistic_robust": float(st_t.sum()) / max(p_k, 1.0),
                        "gyro_power_after": p_k, "refreshed": e.stats.get("refreshed", 0) + 1})
        gain_t += st_t.numpy() / max(p_k, 1.0)
    stage.prep, stage.fit, stage.gain_t = prep_c, fit, gain_t
    return fit

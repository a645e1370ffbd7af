"""One triad's whole linear error as a 12-parameter block, y_k = (I + M_k) x_k + b_k (sensor frame,
x_k the true output of IMU k's sensor), estimated for every triad of one sensor at once: the
machinery the detector's two linear stages share, the gyroscopes' (:mod:`accel_bayes.mismatch.gyro_linear`,
step 3a, where the method, its tests and the array-size gauge are explained) and the
accelerometers' (:mod:`accel_bayes.mismatch.acc_linear`, step 3a').

``sensor`` is ``"gyro"`` or ``"acc"`` throughout: the block regresses that sensor's outputs on the
current fit's nominal outputs of it (``fit.ctx.gyro`` rad/s, ``fit.ctx.acc`` m/s²), and corrects
that sensor's outputs and stated noise.  :func:`linear_stage` is the stage itself (relative blocks
alternating with the motion, the group and spread tests, the median isotropic gauge, the per-block
tests); the gyro stage adds its common part through the lever arms (``common``).
"""
from __future__ import annotations

import dataclasses
import math
import time as _time
from types import SimpleNamespace
from typing import Callable

import numpy as np
import torch

from ..physics.geometry import quat_to_matrix
from .budget import group_power
from .fit import fit_model
from .model import ModelFit
from .prepared import Prepared

__all__ = ["LinearStage", "linear_stage", "relative_blocks", "corrected_outputs", "block_arrays", "MIN_SPREAD_SHARE"]

#: the stage runs only when the errors are spread over several triads (:func:`spread_share`).
#: One erroneous triad leaks 1/n of its error into every other through the fitted (mean) motion, the
#: same array-frame error on each: the others then differ from their common part by noise only
#: (share ≈ 0 for a strong error), while independent errors on every triad give ≈ 1 (gyros: 0.94–0.99
#: on the 42 concealed multi-effect recordings, 1.02 and 1.08 on MIMU exp_1 and exp_4; 0.003–0.49 on
#: six mismatch_proof cases with one erroneous gyro).
#: The share alone is not enough: where the others' blocks are noise (one triad's error that is not
#: linear in its output, e.g. a g-sensitivity, leaks no common linear pattern) the share of noise is
#: ≈ (n − 2)/(n − 1); the stage also needs the spread *statistic* above its χ²_{12(n−2)} quantile
#: (mismatch_proof's gyro_g_sensitivity-000 on mimu32: share 0.77, statistic 384 against 489).
#: A single triad's scale, coupling or offset is named term by term, on its axis, by the rounds
#: (experiments/mismatch_proof.py).
#: Below the share the stage asks the question directly (:func:`others_after_top`) before refusing:
#: with few triads the share of independent errors is itself near (n − 2)/(n − 1), under this value
#: at n = 4 (experiments/gyro_spread_check.md).
MIN_SPREAD_SHARE = 0.7

_WORD = {"gyro": "gyro", "acc": "accelerometer"}


@dataclasses.dataclass
class LinearStage:
    """What a linear stage found: ``prep`` (corrected, or the input when nothing was kept), ``fit``
    (on ``prep``), ``blocks`` (kept block effects, parameters and ``std`` set, ``stats`` with the
    statistic), ``gain_t`` (T,) the per-sample statistic of the kept blocks, ``info`` (the report's
    ``details.gyro_linear_stage`` / ``details.acc_linear_stage``), ``sensor``."""

    prep: Prepared
    fit: ModelFit
    blocks: list
    gain_t: np.ndarray | None
    info: dict
    sensor: str = "gyro"


def _has(prep: Prepared, sensor: str) -> np.ndarray:
    return np.asarray(prep.has_gyro if sensor == "gyro" else prep.has_acc)


def _mask(prep: Prepared, sensor: str) -> torch.Tensor:
    return prep.m_gyro if sensor == "gyro" else prep.m_acc


def _y(prep: Prepared, sensor: str) -> torch.Tensor:
    return prep.y_gyro if sensor == "gyro" else prep.y_acc


def _sigma(prep: Prepared, sensor: str) -> torch.Tensor:
    return prep.sigma_gyro if sensor == "gyro" else prep.sigma_acc


def nominal(fit: ModelFit, sensor: str) -> torch.Tensor:
    """(T, K, 3) the fit's nominal sensor-frame outputs of ``sensor`` (the blocks' regressors)."""
    return fit.ctx.gyro if sensor == "gyro" else fit.ctx.acc


def rows(prep: Prepared, k: int, sensor: str = "gyro") -> torch.Tensor:
    """(T,) bool: the samples where IMU k's three channels of ``sensor`` are observed."""
    return _mask(prep, sensor)[:, k].min(-1).values > 0


def design(x_k: torch.Tensor, rows_: torch.Tensor) -> torch.Tensor:
    """The regression design [x_k, 1] (n, 4) of one triad's block on the given rows."""
    return torch.cat((x_k[rows_], torch.ones(int(rows_.sum()), 1, dtype=torch.float64)), 1)


def lstsq(X: torch.Tensor, Y: torch.Tensor) -> torch.Tensor:
    """The least-squares solution β of X β ≈ Y (minimum norm if X is rank-deficient), by LAPACK's
    SVD driver ``gelsd``.  Not torch's CPU default ``gelsy``: with the MKL that torch ships, gelsy's
    result depends on the operands' memory alignment (2-7 different last bits over 16 offsets of the
    same (n, 4) design, n = 97-20000), so that the same recording and seed gave detect reports that
    differed run to run (tests/mismatch/test_detect_determinism.py); gelsd, gelss and gels gave one
    result over every offset, and gelsd keeps gelsy's treatment of a rank-deficient design (an IMU
    turned about one axis only) — the minimum-norm solution below the relative cut-off eps·max(n, 4)."""
    return torch.linalg.lstsq(X, Y, driver="gelsd").solution


def block_stat_t(x_k: torch.Tensor, A_k: torch.Tensor, b_k: torch.Tensor, sigma: float, rows_) -> torch.Tensor:
    """(T,) per-sample statistic |(A_k − I) x_kt + b_k|²/σ² of one block (0 off ``rows_``)."""
    d = x_k @ (A_k - torch.eye(3, dtype=torch.float64)).T + b_k
    return (d ** 2).sum(-1) / sigma ** 2 * rows_


def block_sd(x_k: torch.Tensor, rows_, sigma: float, power: float) -> torch.Tensor:
    """(4,) standard deviations of each output axis' row [A_k − I | b_k] of a block fitted on
    [x_k, 1]: σ √diag((XᵀX)⁻¹), inflated by √max(1, P) (P the triad's leftover power)."""
    X = design(x_k, rows_)
    return (torch.linalg.inv(X.T @ X).diagonal().clamp_min(0) * sigma ** 2 * max(power, 1.0)).sqrt()


def relative_blocks(prep: Prepared, x_hat: torch.Tensor, imus, sensor: str = "gyro") -> dict:
    """The blocks' regression: per IMU k in ``imus``, y_k ≈ A_k x̂_k + b_k over its observed samples.

    x_hat (T, K, 3) fitted sensor-frame outputs of ``sensor`` (rad/s or m/s²).  Returns {"A": (K, 3, 3),
    "b": (K, 3)} (identity/zero for IMUs not in ``imus``), "stat" (K,) Σ_t |(A_k − I) x̂_kt + b_k|²/σ_k²,
    "stat_t" (T, K) and "rss_z2" (K,) the mean z² left.
    """
    T, K = prep.T, prep.K
    A = torch.eye(3, dtype=torch.float64).repeat(K, 1, 1)
    b = torch.zeros(K, 3, dtype=torch.float64)
    stat_t = torch.zeros(T, K, dtype=torch.float64)
    rss = torch.ones(K, dtype=torch.float64)
    y_all, sig = _y(prep, sensor), _sigma(prep, sensor)
    for k in imus:
        r = rows(prep, k, sensor)
        if int(r.sum()) < 12:
            continue
        X = design(x_hat[:, k], r)
        Y = y_all[r, k]
        beta = lstsq(X, Y)  # (4, 3): Y ≈ X β
        A[k], b[k] = beta[:3].T, beta[3]
        sigma = float(sig[k])
        stat_t[:, k] = block_stat_t(x_hat[:, k], A[k], b[k], sigma, r)
        rss[k] = ((Y - X @ beta) ** 2).sum() / sigma ** 2 / max(int(r.sum()) * 3 - 12, 1)
    return {"A": A, "b": b, "stat": stat_t.sum(0), "stat_t": stat_t, "rss_z2": rss}


def corrected_outputs(prep: Prepared, A: torch.Tensor, b: torch.Tensor, sensor: str = "gyro") -> Prepared:
    """``prep`` with every output y_k of ``sensor`` replaced by A_k⁻¹(y_k − b_k) (unobserved channels
    stay 0) and its stated noise σ_k by σ_k |det A_k|^(−1/3): the correction rescales the noise too,
    and a triad read 2 % too high would otherwise look 2 % quieter than stated (a spurious noise_level)."""
    y = torch.einsum("kij,tkj->tki", torch.linalg.inv(A), _y(prep, sensor) - b[None])
    s = _sigma(prep, sensor) * torch.linalg.det(A).abs().pow(-1.0 / 3.0)
    if sensor == "gyro":
        return dataclasses.replace(prep, y_gyro=y * prep.m_gyro, sigma_gyro=s)
    return dataclasses.replace(prep, y_acc=y * prep.m_acc, sigma_acc=s)


def block_arrays(blocks, K: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(A (K, 3, 3), b (K, 3)): I + matrix and bias of each block's IMU, identity and zero elsewhere
    (the form :func:`corrected_outputs` takes)."""
    A = torch.eye(3, dtype=torch.float64).repeat(K, 1, 1)
    b = torch.zeros(K, 3, dtype=torch.float64)
    for e in blocks:
        A[e.imu] = A[e.imu] + e.params["matrix"]
        b[e.imu] = e.params["bias"]
    return A, b


def spread_share(prep: Prepared, x_hat: torch.Tensor, rel: dict, imus, sensor: str = "gyro") -> tuple[float, float]:
    """How much of the relative errors is *not* one triad's error seen through the mean motion: with
    D_k(t) = R_kᵀ((A_k − I) x̂_kt + b_k) (array frame) and top the IMU with the largest statistic,
    (share, statistic): the statistic Σ_{k≠top} Σ_t |D_k − D̄|²/σ_k² (≈ χ²_{12(n−2)} when the
    others carry only the common leak and noise) and its share of Σ_{k≠top} Σ_t |D_k|²/σ_k², D̄
    the mean over k ≠ top."""
    R = quat_to_matrix(prep.q)
    I3 = torch.eye(3, dtype=torch.float64)
    top = max(imus, key=lambda k: float(rel["stat"][k]))
    others = [k for k in imus if k != top]
    if len(others) < 2:
        return 1.0, math.inf
    m, sig = _mask(prep, sensor), _sigma(prep, sensor)
    D = torch.stack([(x_hat[:, k] @ (rel["A"][k] - I3).T + rel["b"][k]) @ R[k] for k in others], 1)  # (T, n-1, 3)
    w = torch.stack([m[:, k].min(-1).values / float(sig[k]) ** 2 for k in others], 1)
    dev = D - D.mean(1, keepdim=True)
    num = float(((dev ** 2).sum(-1) * w).sum())
    den = float(((D ** 2).sum(-1) * w).sum())
    return (num / den if den > 0 else 1.0), num


def others_after_top(prep: Prepared, base: ModelFit, rel: dict, imus, sensor: str, passes: int = 3) -> tuple[int, float]:
    """Whether triads other than the strongest carry linear errors of their own: the strongest IMU's
    block is inverted on its outputs alone, alternating ``passes`` times with the motion refitted (its
    regression on the original outputs against the current fit), and the others' relative blocks are
    regressed again.  Returns (top, Σ_{k≠top} statistic_k / max(1, P)), P the
    mean z² the others' regressions leave; ≈ χ²_{12(n−1)} or below when only the top triad is in error.

    The accelerometers' spread test (the gyros keep :func:`spread_share`): one triad's error leaks into
    the others through the fitted motion, and for the accelerometers the leak is not common — the
    per-sample angular acceleration takes part of it and hands it on through each triad's lever arm
    (ω̇ × c_k), so that on mimu8 a single acc_scale, acc_bias, acc_misalignment or triad_orientation
    left a spread share of 0.44–0.69, close to :data:`MIN_SPREAD_SHARE`, and spread statistics far
    above their quantile.  Taking the top triad's error out and looking again asks the question directly."""
    top = max(imus, key=lambda k: float(rel["stat"][k]))
    others = [k for k in imus if k != top]
    K = prep.K
    A = torch.eye(3, dtype=torch.float64).repeat(K, 1, 1)
    b = torch.zeros(K, 3, dtype=torch.float64)
    fit = base
    for _ in range(int(passes)):
        # the top block alternating with the motion: at the baseline it is short by what the motion took
        # of it, and that part comes back at each refit (a geometric series, ratio about 1/n)
        one = relative_blocks(prep, nominal(fit, sensor), [top], sensor)
        A[top], b[top] = one["A"][top], one["b"][top]
        prep_c = corrected_outputs(prep, A, b, sensor)
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    again = relative_blocks(prep_c, nominal(fit, sensor), others, sensor)
    p_left = float(again["rss_z2"][others].mean()) if others else 1.0
    return top, float(again["stat"][others].sum()) / max(p_left, 1.0)


def set_block_std(e, sd: torch.Tensor) -> None:
    """A block's std from its rows' (4,) standard deviations: column j of the matrix, the offset."""
    e.std = {"matrix": sd[:3].expand(3, 3).clone(), "bias": sd[3].expand(3).clone()}


def power(prep: Prepared, fit: ModelFit, imu, sensor: str = "gyro") -> float:
    """The mean leverage-corrected z² left in ``sensor``'s outputs of ``imu`` (None: all)."""
    return group_power(prep, fit, SimpleNamespace(sensor=sensor, imu=imu), fit.linear().h)


def linear_stage(prep: Prepared, base: ModelFit, *, sensor: str, block: Callable, m: int, alpha: float,
                 passes: int = 2, common: Callable | None = None, spread_test: str = "share") -> LinearStage:
    """The linear stage of ``sensor`` (:mod:`accel_bayes.mismatch.gyro_linear`'s docstring, steps 1–3)
    from the fit ``base`` of ``prep``; ``m`` and ``alpha`` are the detector's Bonferroni count and
    family-wise error rate; ``block(imu, params)`` makes one block effect (:class:`GyroLinear`,
    :class:`AccLinear`).  ``common(prep_c, fit, A, b, info, level)`` → (fit, A, b), ``level`` = α/m: the gyro
    stage's step 2, between the relative blocks and the gauge (None: no common part).  ``spread_test``:
    ``"share"`` (:func:`spread_share` and its statistic, the gyros') or ``"others"``
    (:func:`others_after_top`, the accelerometers')."""
    from scipy.stats import chi2

    t0 = _time.perf_counter()
    word = _WORD[sensor]
    imus = [int(k) for k in np.flatnonzero(_has(prep, sensor))]
    n = len(imus)
    thr_group = float(chi2.isf(alpha / m, 12 * n))
    thr_block = float(chi2.isf(alpha / m, 12))
    info = {"imus": imus, "group_df": 12 * n, "group_threshold": thr_group, "block_threshold": thr_block}

    def done(result, prep_=prep, fit_=base, blocks=(), gain_t=None):
        info["result"] = result
        info["seconds"] = _time.perf_counter() - t0
        return LinearStage(prep_, fit_, list(blocks), gain_t, info, sensor)

    # 3 (first half): the cheap group test at the baseline
    rel = relative_blocks(prep, nominal(base, sensor), imus, sensor)
    p_left = float(rel["rss_z2"][imus].mean())
    g_stat = float(rel["stat"].sum()) / max(p_left, 1.0)
    info.update({"group_statistic": float(rel["stat"].sum()), "group_statistic_robust": g_stat,
                 f"{sensor}_power_left": p_left})
    if g_stat <= thr_group:
        return done(f"group below its threshold: no {word} linear errors")

    def direct(why):
        # the others' relative blocks with the strongest triad's block inverted (others_after_top)
        top, o_stat = others_after_top(prep, base, rel, imus, sensor)
        thr_o = float(chi2.isf(alpha / m, 12 * max(n - 1, 1)))
        info.update({"top_imu": top, "others_statistic_robust": o_stat, "others_threshold": thr_o})
        if o_stat <= thr_o:
            return done(f"the errors sit on one {word} ({why}with IMU {top}'s block inverted the others' relative "
                        f"blocks are noise: statistic {o_stat:.4g} <= {thr_o:.4g}, χ²_{12 * max(n - 1, 1)}): left to "
                        "the rounds, term by term")
        return _fit_blocks(prep, base, sensor, block, m, alpha, passes, common, imus, info, done)

    if spread_test == "others":
        return direct("")
    spread, spread_stat = spread_share(prep, nominal(base, sensor), rel, imus, sensor)
    spread_stat /= max(p_left, 1.0)
    thr_spread = float(chi2.isf(alpha / m, 12 * max(n - 2, 1)))
    info.update({"spread_share": spread, "spread_statistic_robust": spread_stat, "spread_threshold": thr_spread})
    if spread < MIN_SPREAD_SHARE:
        # a screen, not the answer: on a board of few gyros, each in error, the others' mean carries
        # about 1/(n − 1) of their own errors, so the share sits near (n − 2)/(n − 1) (0.67 at n = 4)
        # and falls under MIN_SPREAD_SHARE by chance (0.56–0.64 on clockgen's cube6 and plate4 cases
        # with 0.5–3 % errors on every gyro); the direct question decides
        return direct(f"the others differ by a common leak only: spread share {spread:.3f} < {MIN_SPREAD_SHARE}, and ")
    if spread_stat <= thr_spread:
        # the others' blocks are noise: a share near 1 then says nothing (one triad's error that is
        # not linear in its output, e.g. a g-sensitivity, leaks no common pattern to compare with)
        return done(f"the errors sit on one {word} (the others' relative blocks are noise: spread statistic "
                    f"{spread_stat:.4g} <= {thr_spread:.4g}, χ²_{12 * max(n - 2, 1)}): left to the rounds, term by term")
    return _fit_blocks(prep, base, sensor, block, m, alpha, passes, common, imus, info, done)


def _fit_blocks(prep, base, sensor, block, m, alpha, passes, common, imus, info, done) -> LinearStage:
    """:func:`linear_stage` past its group and spread tests: steps 1–3 (relative blocks alternating with
    the motion, the common part, the gauge, the per-block tests)."""
    from scipy.stats import chi2

    word, n = _WORD[sensor], len(imus)
    sig, has = _sigma(prep, sensor), torch.as_tensor(_has(prep, sensor))
    thr_block = info["block_threshold"]
    # 1: relative blocks, alternating with the motion
    fit = base
    for _ in range(int(passes)):
        rel = relative_blocks(prep, nominal(fit, sensor), imus, sensor)
        prep_c = corrected_outputs(prep, rel["A"], rel["b"], sensor)
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    A, b = rel["A"].clone(), rel["b"].clone()
    if common is not None:  # 2: the common part
        fit, A, b = common(prep_c, fit, A, b, info, alpha / m)
    # the array-size gauge: the same scale error on every triad is a rescaling of the whole array, so
    # it is not seen by any data; hold the median triad's isotropic scale at zero
    iso = torch.stack([torch.diagonal(A[k]).sum() / 3 - 1 for k in imus])
    c = float(iso.median())
    A = torch.where(has[:, None, None], A / (1 + c), A)
    b = torch.where(has[:, None], b / (1 + c), b)
    info["isotropic_gauge"] = {"rule": f"median {word}'s isotropic scale error held at 0", "removed": c}
    # 3 (second half): each block's statistic at the fit and its terms' z-scores
    prep_c = corrected_outputs(prep, A, b, sensor)
    fit = fit_model(prep_c, (), init=fit, laplace=False)
    I3 = torch.eye(3, dtype=torch.float64)
    x_hat = nominal(fit, sensor)
    thr_term = float(chi2.isf(alpha / m, 1))
    info["term_threshold"] = thr_term
    blocks_info, keep = {}, []
    for k in imus:
        r, sigma = rows(prep, k, sensor), float(sig[k])
        st_t = block_stat_t(x_hat[:, k], A[k], b[k], sigma, r)
        p_k = power(prep_c, fit, k, sensor)
        st = float(st_t.sum()) / max(p_k, 1.0)
        sd = block_sd(x_hat[:, k], r, sigma, p_k)
        z2 = (torch.cat((A[k] - I3, b[k][:, None]), 1) / sd[None, :]) ** 2  # (3, 4): [M | b] rows
        n_terms = int((z2 > thr_term).sum())
        blocks_info[k] = {"statistic": float(st_t.sum()), "statistic_robust": st, f"{sensor}_power_after": p_k,
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
        prep_c = corrected_outputs(prep, A, b, sensor)
        fit = fit_model(prep_c, (), init=fit, laplace=False)
    blocks, gain_t = [], np.zeros(prep.T)
    for k in keep:
        r, sigma, p_k = rows(prep, k, sensor), float(sig[k]), blocks_info[k][f"{sensor}_power_after"]
        e = block(k, {"matrix": A[k] - I3, "bias": b[k]})
        set_block_std(e, block_sd(nominal(fit, sensor)[:, k], r, sigma, p_k))
        e.stats = dict(blocks_info[k])
        blocks.append(e)
        # over every sample (unmasked, unlike the refresh's): it only says where the block acts
        gain_t += block_stat_t(nominal(fit, sensor)[:, k], A[k], b[k], sigma, True).numpy() / max(p_k, 1.0)
    info["evidence_group"] = 2.0 * (fit.loglik - base.loglik)
    return done(f"kept blocks on IMUs {keep}", prep_c, fit, blocks, gain_t)

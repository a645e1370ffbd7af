"""Estimation of the process-noise intensities q_a, q_ω of the continuous-time motion priors
(:mod:`.motion_priors`; ``process_noise="estimate"`` / ``"estimate-snap"``, issue #12).

A start from the raw outputs (:func:`initial_process_intensities`,
:func:`initial_smooth_process_intensities`), then the type-II ML fixed point
q_k ← q_k · rss_k / (n_k − h_k) (:func:`process_noise_statistics`,
:func:`update_process_intensities`) alternated with the joint LM (:func:`estimate_intensities`).
:class:`ProcessNoise` carries the current intensities, their whitening and the history across
the LM runs of one self-calibration.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable

import torch

from ...physics.geometry import quat_to_matrix
from .factors import motion_posterior, process_residuals
from .motion_priors import (
    _CHAIN_ORDERS,
    MotionPrior,
    _intensity_rows,
    bridged_process_whitening,
    continuous_process_whitening,
    process_sqrt_information,
)

__all__ = ["initial_process_intensities", "initial_smooth_process_intensities", "process_noise_statistics",
           "update_process_intensities", "ProcessNoise", "initial_process_noise", "estimate_intensities"]


def initial_process_intensities(acc: torch.Tensor, dt: torch.Tensor, positions: torch.Tensor,
                                orientations: torch.Tensor, fixed: int, inv_std: torch.Tensor) -> dict:
    """A start for the intensities from the raw outputs (the fixed point below refines it).

    q_a from the fixed triad's sample-to-sample changes (≈ Δa_lin: E|Δa|² = 3 q_a Δt), q_ω from
    the changes of the difference of each triad's output and the fixed one's, rotated into the
    array frame with the nominal orientations (≈ Δω̇ × Δr plus centripetal changes, an upper
    bound): E|Δω̇|² = 3 q_ω Δt.  Noise (2σ² per component) is subtracted.
    """
    R = quat_to_matrix(orientations)  # array → sensor
    f = (R.transpose(-1, -2).unsqueeze(0) @ acc.unsqueeze(-1)).squeeze(-1)  # (T, A, 3) array frame
    var_n = (1.0 / inv_std ** 2)  # (A, 3)
    d0 = torch.diff(f[:, fixed], dim=0)
    ms0 = (d0 ** 2).sum(-1) - 2 * var_n[fixed].sum()
    qa = float((ms0.clamp_min(0) / (3 * dt)).mean())
    others = [j for j in range(acc.shape[1]) if j != fixed]
    qws = []
    for j in others:
        dr2 = float(((positions[j] - positions[fixed]) ** 2).sum())
        dd = torch.diff(f[:, j] - f[:, fixed], dim=0)
        ms = (dd ** 2).sum(-1) - 2 * (var_n[j].sum() + var_n[fixed].sum())
        qws.append(float((ms.clamp_min(0) / (3 * dt)).mean()) / max(dr2, 1e-12))
    qw = float(torch.tensor(qws).median()) if qws else 1.0
    return {"acc": max(qa, 1e-6), "omega": max(qw, 1e-6)}


def initial_smooth_process_intensities(acc: torch.Tensor, dt: torch.Tensor, positions: torch.Tensor,
                                       orientations: torch.Tensor, fixed: int, inv_std: torch.Tensor,
                                       dim: int = 15) -> dict:
    """Start intensities of the smoother models (state width 12 or 15) from the raw outputs.

    As :func:`initial_process_intensities`, with second differences at a lag of k samples
    (h = kΔ ≈ 20 ms, Δ the median step: a smooth signal's second difference grows as h², its noise
    stays 6σ²): when ω̇ (or a_lin) is an integrated Brownian path of intensity q, its second
    difference at lag h has E|Δ²|² = 3 · (2/3) q h³ = 2 q h³ (three axes).  For the jerk-driven a_lin
    of width 12 the first-difference rule of :func:`initial_process_intensities` is kept.
    """
    pa, _ = _CHAIN_ORDERS[dim]
    step = float(dt.median())
    k = max(1, int(round(0.02 / step)))
    h = k * step
    R = quat_to_matrix(orientations)
    f = (R.transpose(-1, -2).unsqueeze(0) @ acc.unsqueeze(-1)).squeeze(-1)  # (T, A, 3) array frame
    var_n = 1.0 / inv_std ** 2

    def d2(y):
        return y[2 * k:] - 2 * y[k:-k] + y[:-2 * k]

    if acc.shape[0] <= 2 * k:
        k, h = 1, step
    base = initial_process_intensities(acc, dt, positions, orientations, fixed, inv_std)
    if pa == 2:
        ms0 = (d2(f[:, fixed]) ** 2).sum(-1) - 6 * var_n[fixed].sum()
        qa = float(ms0.clamp_min(0).mean()) / (2 * h ** 3)
    else:
        qa = base["acc"]
    qws = []
    for j in range(acc.shape[1]):
        if j == fixed:
            continue
        dr2 = float(((positions[j] - positions[fixed]) ** 2).sum())
        ms = (d2(f[:, j] - f[:, fixed]) ** 2).sum(-1) - 6 * (var_n[j].sum() + var_n[fixed].sum())
        qws.append(float(ms.clamp_min(0).mean()) / (2 * h ** 3) / max(dr2, 1e-12))
    qw = float(torch.tensor(qws).median()) if qws else 1.0
    return {"acc": max(qa, 1e-6), "omega": max(qw, 1e-6)}


# The estimated q_ω starts this much below the raw-output guess: a stiff motion model ties ω to ∫ω̇
# firmly in the first fit from zero motion (a loose one lets ω flip sign between segments and the
# poses run off), and the fixed point then loosens it, at most ×_MAX_FACTOR per step.
_START_STIFFNESS = 1e-3
_MAX_FACTOR = 10.0

# residual rows of each intensity in the whitened process residual
_INTENSITY_ROWS = {"acc": slice(0, 3), "omega": slice(3, 9)}  # width 9; _intensity_rows in general


def process_noise_statistics(states, positions, orientations, dt, W, inv_std, S=None) -> dict:
    """Per intensity: the sum of squared whitened process residuals at the estimate, their number
    and their leverage in the motion fit (poses held at the estimate).

    With H the Gauss–Newton matrix of the motion states (triad + process rows; block
    tridiagonal), a group k of whitened residual rows with Jacobian J_k has leverage
    h_k = tr(J_k H⁻¹ J_kᵀ), computed from the diagonal and first off-diagonal blocks of H⁻¹.
    Returns {"acc": (rss, n, h), "omega": (rss, n, h)}.  States (T, d) of any width of
    :data:`.motion_priors.MOTION_STATE_DIMS` (W (T−1, d, d) of the same width).
    """
    Jp, Jn, Sig, C = motion_posterior(states, positions, orientations, dt, W, inv_std, S)
    M = (Jp @ Sig[:-1] @ Jp.transpose(-1, -2) + Jp @ C @ Jn.transpose(-1, -2)
         + Jn @ C.transpose(-1, -2) @ Jp.transpose(-1, -2) + Jn @ Sig[1:] @ Jn.transpose(-1, -2))
    lev = torch.diagonal(M, dim1=-2, dim2=-1)  # (T−1, 9)
    r = process_residuals(states, dt, W)
    rows = _INTENSITY_ROWS if states.shape[-1] == 9 else _intensity_rows(states.shape[-1])
    return {k: (float((r[:, sl] ** 2).sum()), int(r[:, sl].numel()), float(lev[:, sl].sum()))
            for k, sl in rows.items()}


def update_process_intensities(intensities: dict, stats: dict, max_factor: float = _MAX_FACTOR) -> dict:
    """One step of the type-II ML fixed point q_k ← q_k · rss_k / (n_k − h_k).

    The marginal likelihood of the intensities in the model linearised at the estimate (motion
    integrated out by Laplace) is stationary where each group's whitened residual sum of squares
    equals its residual degrees of freedom n_k − h_k (as for the accelerometer noise in
    :mod:`accel_bayes.model.noise`); the factor is clamped to [1/max_factor, max_factor]."""
    out = {}
    for k, q in intensities.items():
        rss, n, h = stats[k]
        dof = max(n - h, 1e-3 * n)
        fac = min(max(rss / dof, 1.0 / max_factor), max_factor)
        out[k] = float(q) * fac
    return out


@dataclass
class ProcessNoise:
    """The process noise of the LM runs of one self-calibration, updated as they go.

    W : the whitening of the process factors now in use ((T−1, 9) diagonal or (T−1, d, d));
    q : the current intensities {"acc", "omega"} (None with the fixed eq. 8 variances);
    start : the intensities the first run started from; history : one entry per fixed-point step
    (run, intensities, statistics, change)."""

    W: torch.Tensor
    q: dict | None
    start: dict | None
    history: list = field(default_factory=list)


def initial_process_noise(acc, dt, steps, positions, orientations, fixed: int, inv_std,
                          prior: MotionPrior) -> ProcessNoise:
    """The process noise of the first LM run: eq. 8 (bridged over left-out samples, ``steps`` (T−1,)
    grid steps per fitted step, or None), or the continuous-time model of ``prior`` at its given
    intensities or at the raw-output start made stiff (×_START_STIFFNESS on q_ω).  acc (T, A, 3)
    m/s², dt (T−1,) s, start poses positions (A, 3) m / orientations (A, 4), inv_std (A, 3)."""
    intensities = prior.intensities
    if prior.mode == "s16":
        if steps is None or bool((torch.as_tensor(steps) == 1).all()):
            sqrt_info = process_sqrt_information(dt, prior.variances)
        else:
            sqrt_info = bridged_process_whitening(dt, steps, prior.variances)
    else:
        if intensities is None:
            if prior.dim == 9:
                intensities = initial_process_intensities(acc, dt, positions, orientations, fixed, inv_std)
            else:
                intensities = initial_smooth_process_intensities(acc, dt, positions, orientations, fixed, inv_std,
                                                                 prior.dim)
            intensities["omega"] *= _START_STIFFNESS
        sqrt_info = continuous_process_whitening(dt, intensities, prior.dim)
    return ProcessNoise(W=sqrt_info, q=intensities, start=intensities)


def estimate_intensities(res, log: list, label: str, noise: ProcessNoise, refit: Callable, dt: torch.Tensor,
                         inv_std: torch.Tensor, S, *, max_steps: int, rtol: float):
    """Type-II ML of the process intensities: alternate the fixed-point update with the joint LM
    (``refit(positions, orientations, states, k)`` → (LM result, cost log) of update k at the
    updated ``noise.W``, warm-started at the previous estimate) until the intensities move < ``rtol`` (relative) or ``max_steps`` updates.
    Updates ``noise`` and extends ``log``; returns the last LM result."""
    dim = noise.W.shape[-1]
    for k in range(max_steps):
        vals, x = res.values, res.locals
        if not (bool(torch.isfinite(x).all()) and bool(torch.isfinite(vals["position"]).all())):
            break
        stats = process_noise_statistics(x, vals["position"], vals["rotation"], dt, noise.W, inv_std, S)
        new = update_process_intensities(noise.q, stats)
        change = max(abs(math.log(new[c] / noise.q[c])) for c in new)
        noise.history.append({"run": label, "intensities": dict(noise.q), "stats": stats, "change": change})
        if change < rtol:
            break
        noise.q = new
        noise.W = continuous_process_whitening(dt, new, dim)
        res, log_k = refit(vals["position"], vals["rotation"], x, k + 1)
        off = log[-1]["iteration"]
        for e in log_k:
            e["stage"] = f"noise {k + 1}"
            e["iteration"] += off
        log.extend(log_k)  # its iteration 0 carries the cost at the new intensities
    return res

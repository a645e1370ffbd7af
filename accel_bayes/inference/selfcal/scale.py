"""The accelerometer-only scale symmetry of the [S16] self-calibration and the two corrections of
the joint MAP along it (issue #12).

Accelerometer-only data are unchanged under r → c·r, ω → ω/√c, ω̇ → ω̇/c (:func:`scale_orbit`);
only the motion prior ties c, so the joint MAP's scale is the prior's, and comes out too large.
The corrections move the MAP along the orbit to the maximum of the Laplace marginal likelihood of
the poses (motion integrated out): its value (:func:`laplace_scale_nll`; the default,
:func:`laplace_scale_correction`) or the root of its approximate derivative
(:func:`marginal_scale_score`, :func:`score_scale_correction`).  Both return a
:class:`ScaleCorrection` (poses and motion on the orbit, and the record of the evaluations); the
covariance stays the joint MAP's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from ...physics import jacobians as jac
from ...physics.geometry import skew
from ..lm.linear import NotPositiveDefinite, block_tridiagonal_logdet
from .factors import motion_hessian, motion_posterior, process_residuals
from .problem import _run_lm, build_problem
from .result import SelfCalResult

__all__ = ["scale_orbit", "marginal_scale_score", "laplace_scale_nll", "ScaleCorrection",
           "laplace_scale_correction", "score_scale_correction"]


def scale_orbit(positions, states, fixed: int, c: float):
    """The accelerometer-only symmetry: poses and motion that explain the outputs exactly as well.

    Free positions r_j → r_f + c (r_j − r_f) about the fixed triad f; ω → ω/√c, ω̇ → ω̇/c and
    a_lin → a_lin + (1 − 1/c) K with K = ω̇×r_f + ω×(ω×r_f) (keeps the fixed triad's specific force;
    zero when the fixed triad sits at the array origin).  Every triad's specific force is unchanged.
    With the smoother states (width 12, 15) ω̈ → ω̈/c (like ω̇, so the ω̇–ω̈ link keeps its
    consistency) and ȧ_lin is left as it is: neither enters the data, so any choice is an orbit."""
    rf = positions[fixed]
    p = rf + c * (positions - rf)
    a, w, wd = states[:, 0:3], states[:, 3:6], states[:, 6:9]
    K = torch.cross(wd, rf.expand_as(wd), dim=-1) + torch.cross(w, torch.cross(w, rf.expand_as(w), dim=-1), dim=-1)
    parts = [a + (1 - 1 / c) * K, w / math.sqrt(c), wd / c]
    if states.shape[-1] >= 12:
        parts.append(states[:, 9:12] / c)
        parts.append(states[:, 12:])
    x = torch.cat(parts, -1)
    return p, x


def marginal_scale_score(states, positions, orientations, dt, W, inv_std, fixed: int, S=None) -> float:
    """d/dc of −log p(z | poses on the scale orbit) at c = 1, motion integrated out (Laplace).

    The joint MAP over poses and motion is biased along the scale orbit (:func:`scale_orbit`): the
    data term is constant along it, so the MAP's scale is set by the motion prior alone, which
    prefers slower motion (a larger board).  Integrating the motion out adds the volume of the
    orbit map (det = c^(−9T/2)) and the posterior spread: with x = φ_c(x′),

        d/dc [−log p] = 9T/2 + Σ_i r_iᵀ (J_prev,i v_i + J_next,i v_{i+1}) + tr(Λ V Σ),

    r_i the whitened process residuals, v = dφ_c/dc at c = 1 (per sample (K, −ω/2, −ω̇)), V its
    Jacobian, Λ = J_pᵀJ_p the process information and Σ the motion's Laplace covariance (poses
    held).  The middle term vanishes at the joint MAP.  With the smoother states (width d = 12,
    15) v also carries −ω̈ (ȧ_lin: 0) and the volume term is 15T/2 (ω̈ → ω̈/c adds c^(−3) per sample).
    """
    T, d = states.shape
    Jp, Jn, Sig, C = motion_posterior(states, positions, orientations, dt, W, inv_std, S)
    rf = positions[fixed]
    w, wd = states[:, 3:6], states[:, 6:9]
    K = torch.cross(wd, rf.expand_as(wd), dim=-1) + torch.cross(w, torch.cross(w, rf.expand_as(w), dim=-1), dim=-1)
    v = torch.cat((K, -0.5 * w, -wd), -1)  # (T, 9)
    if d > 9:
        v = torch.cat((v, -states[:, 9:12], torch.zeros_like(states[:, 12:])), -1)
    V = torch.zeros(T, d, d, dtype=states.dtype, device=states.device)
    eye3 = torch.eye(3, dtype=states.dtype, device=states.device)
    V[:, 0:3, 3:6] = jac.df_domega(rf.expand(T, 1, 3), w)[:, 0]  # ∂(ω×(ω×r_f))/∂ω
    V[:, 0:3, 6:9] = -skew(rf).expand(T, 3, 3)
    V[:, 3:6, 3:6] = -0.5 * eye3
    V[:, 6:9, 6:9] = -eye3
    if d > 9:
        V[:, 9:12, 9:12] = -eye3
    r = process_residuals(states, dt, W)
    middle = float((r * ((Jp @ v[:-1].unsqueeze(-1)).squeeze(-1) + (Jn @ v[1:].unsqueeze(-1)).squeeze(-1))).sum())
    JpT, JnT = Jp.transpose(-1, -2), Jn.transpose(-1, -2)
    SL = torch.zeros_like(Sig)  # (Σ Λ)_ii
    SL[:-1] += Sig[:-1] @ (JpT @ Jp) + C @ (JnT @ Jp)       # Σ_ii Λ_ii(prev part) + Σ_{i,i+1} Λ_{i+1,i}
    SL[1:] += Sig[1:] @ (JnT @ Jn) + C.transpose(-1, -2) @ (JpT @ Jn)  # Σ_ii Λ_ii(next part) + Σ_{i,i−1} Λ_{i−1,i}
    trace = float(torch.einsum("tij,tji->", V, SL))
    volume = 4.5 * T if d == 9 else 7.5 * T
    return volume + middle + trace


def laplace_scale_nll(c: float, positions, states, orientations, fixed: int, acc, dt, W, inv_std, S=None,
                      offset=None, max_iter: int = 100):
    """Laplace −log p(z | poses on the scale orbit at c), motion integrated out, up to a constant.

    Poses and a start motion from :func:`scale_orbit` (positions (A, 3) m, states (T, d)); the
    motion-only MAP x̂_c at those poses by the structured LM; then ½F(x̂_c) + ½ log det H_xx(x̂_c)
    with H_xx the Gauss–Newton matrix of the motion (triad + process rows, block tridiagonal).
    Returns (value, positions_c, x̂_c).  Dimensionless (a negative log-likelihood)."""
    pc, xc = scale_orbit(positions, states, fixed, c)
    prob = build_problem(acc, dt, pc, orientations, xc, fixed, inv_std, W, S, offset, poses_fixed=True)
    r, _ = _run_lm(prob, max_iter=max_iter, ftol=1e-14, xtol=1e-14, gtol=1e-12, progress=False, desc="scale")
    x = r.locals
    _, _, D, B = motion_hessian(x, pc, orientations, dt, W, inv_std, S)
    logdet = block_tridiagonal_logdet(D, B)
    return float(r.cost) + 0.5 * logdet, pc, x


@dataclass(frozen=True)
class ScaleCorrection:
    """The joint MAP moved along the scale orbit: positions (A, 3) m, states (T, d) and the record
    for ``SelfCalResult.process_noise["scale_correction"]`` (method, factor c, evaluations)."""

    positions: torch.Tensor
    states: torch.Tensor
    record: dict


def _scale_orbit_start(out: SelfCalResult, res, A: int, fixed: int):
    """Where both scale corrections start: (positions, states and orientations of the joint MAP,
    copies; Var(c), the Laplace variance of the relative scale c along the fitted board, from the
    positions' joint covariance), or None when the MAP has no usable covariance."""
    free = [j for j in range(A) if j != fixed]
    if out.covariance is not None:
        Cp = out.covariance[:3 * len(free), :3 * len(free)]
    else:
        try:
            Cp = res.covariance()[:3 * len(free), :3 * len(free)]
        except NotPositiveDefinite:
            return None
    p0, x0, q = out.raw_positions.clone(), out.states.clone(), out.raw_orientations
    d = (p0 - p0[fixed])[free].reshape(-1)
    return p0, x0, q, float(d @ Cp @ d) / float(d @ d) ** 2


def laplace_scale_correction(out: SelfCalResult, res, A: int, fixed: int, acc, dt, W, inv_std, S, offset,
                             max_iter: int, max_steps: int = 10) -> ScaleCorrection | None:
    """Move the joint MAP along the scale orbit to the minimum of the Laplace marginal
    :func:`laplace_scale_nll` over c.  Start: c = 1, 1 ± sd (sd the Laplace std of the relative
    scale at the joint MAP); then parabolic steps through the three best points, each at most
    4 sd (and 5 %) from the best, until a step is below 0.02 sd.  Poses and motion become the
    orbit's poses at the best c and the motion-only MAP there; the covariance stays the joint
    MAP's.  ``out``/``res``: the joint MAP (:class:`SelfCalResult`, LM result); None when it has no
    usable covariance or no evaluation is finite."""
    start = _scale_orbit_start(out, res, A, fixed)
    if start is None:
        return None
    p0, x0, q, var_c = start
    sd = math.sqrt(max(var_c, 1e-16))
    evals = {}
    steps = []

    def f(c):
        c = float(c)
        if c not in evals:
            try:
                val, pc, xc = laplace_scale_nll(c, p0, x0, q, fixed, acc, dt, W, inv_std, S, offset, max_iter)
            except (np.linalg.LinAlgError, NotPositiveDefinite):
                val, pc, xc = math.inf, None, None
            evals[c] = (val, pc, xc)
            steps.append({"c": c, "nll": val})
        return evals[c][0]

    for c in (1.0, 1.0 - sd, 1.0 + sd):
        f(c)
    for _ in range(max_steps):
        finite = [c for c in evals if math.isfinite(evals[c][0])]
        if len(finite) < 3:
            break
        best3 = sorted(sorted(finite, key=lambda c: evals[c][0])[:3])
        cb = min(finite, key=lambda c: evals[c][0])
        ys = [evals[c][0] - evals[cb][0] for c in best3]
        a2, a1, _ = np.polyfit(np.array(best3) - cb, ys, 2)
        if a2 > 0:
            c_new = cb - a1 / (2 * a2)
        else:  # not convex through these points: walk downhill
            c_new = cb + (2 * sd if best3[-1] == cb else -2 * sd)
        c_new = min(max(c_new, cb - 4 * sd, 0.95), cb + 4 * sd, 1.05)
        if min(abs(c_new - c) for c in evals) < 0.02 * sd:
            break
        f(c_new)
    cb = min(evals, key=lambda c: evals[c][0])
    if not math.isfinite(evals[cb][0]):
        return None
    _, pc, xc = evals[cb]
    return ScaleCorrection(pc, xc.detach(), {"method": "laplace", "factor": cb, "steps": steps})


def score_scale_correction(out: SelfCalResult, res, A: int, fixed: int, dt, W, inv_std, S,
                           max_steps: int = 6) -> ScaleCorrection | None:
    """Move the joint MAP along the scale orbit to the maximum of the Laplace marginal likelihood
    of the poses (motion integrated out): the root of d(−log p)/dc (:func:`marginal_scale_score`),
    bracketed from the joint MAP by Newton steps with Var(c), the Laplace variance of the scale along
    the fitted board (positions' joint covariance, motion marginalised), then regula falsi.  The
    covariance is the joint MAP's.  None when the MAP has no usable covariance."""
    start = _scale_orbit_start(out, res, A, fixed)
    if start is None:
        return None
    p0, x0, q, var_c = start
    sd = math.sqrt(max(var_c, 1e-30))
    steps = []

    def g(c):  # d(−log p)/dc at the orbit point φ_c(MAP)
        pc, xc = scale_orbit(p0, x0, fixed, c)
        val = marginal_scale_score(xc, pc, q, dt, W, inv_std, fixed, S) / c
        steps.append({"c": c, "dnll_dc": val})
        return val

    # Root of g(c) = 0: first bracket it (Newton steps with the Laplace curvature 1/Var(c), then
    # secant extrapolation, at most 5 % per step), then the Illinois variant of regula falsi inside
    # the bracket.  The Laplace curvature can be several times off, so plain Newton may oscillate.
    a, ga = 1.0, g(1.0)
    b = 1.0 - max(min(ga * var_c, 0.05), -0.05)
    gb = g(b)
    for _ in range(max_steps):
        if (ga > 0) != (gb > 0):
            break
        slope = (gb - ga) / (b - a)
        step = -gb / slope if slope > 0 else (b - a)
        step = max(min(step, 0.05), -0.05)
        a, ga, b = b, gb, b + step
        gb = g(b)
    if (ga > 0) != (gb > 0):
        for _ in range(12):
            if abs(b - a) < 0.01 * sd:
                break
            c = b - gb * (b - a) / (gb - ga)
            gc = g(c)
            if (gc > 0) != (gb > 0):
                a, ga = b, gb
            else:
                ga = 0.5 * ga
            b, gb = c, gc
    c_b = b
    p, x = scale_orbit(p0, x0, fixed, c_b)
    total = c_b
    return ScaleCorrection(p, x, {"method": "score", "factor": total, "steps": steps})

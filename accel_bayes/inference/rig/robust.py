"""Misspecification-robust covariance of the rig posterior: the block sandwich H⁻¹ B H⁻¹
(issue #28, the MIMU pairs' z RMS 5.6 with Laplace stds 20–65× below a jackknife's).

Why: the Laplace std counts only the white noise of a model the data may reject (on the MIMU4444
the IMUs' relative timing changes by up to 1 ms between moves, ``experiments/rig_mimu_diagnose.md``).
The sandwich measures the spread of the estimate from the data's own scores instead.

What: the measurement residuals are cut into time blocks of fixed length L
(:data:`DEFAULT_SCORE_BLOCK`, by their motion interval's start).  The motion knots and every global
outside the reported set (bias knots, linear errors) are nuisances; each row's Jacobian is
*profiled*, P = J_I − J_N H_NN⁻¹ H_NI (H the information the Laplace uses, exact Hessian, priors
included), so a block's score Σ Pᵀr is blind to the knots it holds — without that, the per-block
scores of the 12 local numbers every 10 ms would dominate and the sum would mean nothing.  Block b's
influence on the reported parameters is a_b = C Σ_{m∈b} P_mᵀ r_m with C the Laplace covariance
(on the identified subspace, as reported), and B = Σ_b a_b a_bᵀ.  Priors are not data and give no
block score.  Under the model E[a_b a_bᵀ] = V_b − (the block's leverage), V_b = C P_bᵀP_b C; the
sandwich of a contrast w is divided by its expected shrink 1 − Σ_b wᵀV_b V⁻¹ V_b w / wᵀVw
(V = Σ V_b), which makes it unbiased when the model holds (the HC2 idea at block level).

Why L = 3 s, fixed before any MIMU z was computed: a block must be longer than the stretch over
which the misspecified residuals are correlated, or the sandwich splits it and undercounts; on
exp_1 that stretch is one hand move (1–3 s: the delete-one-block jackknife of
``rig_mimu_diagnose.md`` used the same 3 s blocks and saw 0.4–1.2 ms), and an IMU's timing wander
lives on that scale.  Longer blocks leave too few of them to estimate B: a 30 s window (the MIMU pair
study) keeps 10, a 15 s concealed rig 5.

Which std is reported (the rule, fixed in advance): per reported coordinate (or contrast w) the
misspecification test compares the corrected sandwich variance with the model's V; with
Satterthwaite's m = (Σ e_b)²/Σ e_b² blocks (e_b = E[(wᵀa_b)²] under the model, after the
leverage), the ratio is about χ²_m/m.  Where it exceeds that law's 1 − :data:`TEST_LEVEL` quantile the sandwich variance
is the reported one (the data reject the model's noise there), else the Laplace.  ``fit_rig`` then
warns in one line.  DESIGN §7.3's ``std``/``cov`` keep their meaning (Laplace); the robust and
reported ones are added keys.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.stats import chi2

from ..lm.linear import SchurComplementSolver, cholesky

__all__ = ["DEFAULT_SCORE_BLOCK", "TEST_LEVEL", "BlockScores", "block_scores", "contrast_variances", "robust_std",
           "robust_summary", "robust_warning"]

#: s, the sandwich's block length L (see the module docstring for why 3 s)
DEFAULT_SCORE_BLOCK = 3.0

#: false-alarm rate per coordinate of the misspecification test that picks the sandwich std
TEST_LEVEL = 0.01


@dataclass
class BlockScores:
    """Per time block b: edges (nb + 1,) s − t₀ of the recording; influence a_b (nb, p) on the
    reported free coordinates (their units: rad, m, s, 1); model_cov V_b (nb, p, p), the model's
    expectation of a_b a_bᵀ before the fit's own leverage."""

    edges: np.ndarray
    influence: np.ndarray
    model_cov: np.ndarray

    def robust_cov(self) -> np.ndarray:
        """The uncorrected sandwich Σ_b a_b a_bᵀ (p, p)."""
        return self.influence.T @ self.influence


def block_scores(problem, values: dict, x: torch.Tensor, lin, keep: np.ndarray, cov: np.ndarray,
                 block_s: float) -> BlockScores:
    """Block influences of the rig fit's measurement residuals on the ``keep`` free coordinates.

    problem : the LM :class:`~accel_bayes.inference.lm.Problem` of the last pass (its chain
    residual named "rig" holds the data), at (values, x); lin : the information blocks the Laplace
    used (exact Hessian or Gauss–Newton, priors included); keep : bool over the free coordinates,
    the reported ones; cov : their Laplace covariance (p, p), finite; block_s : L in s.
    """
    meas = next(r for r in problem.chain_residuals if r.name == "rig")
    U, W, V, V_off = lin.U, lin.W, lin.V, lin.V_off
    I = torch.as_tensor(np.flatnonzero(keep))
    N = torch.as_tensor(np.flatnonzero(~keep))
    # G = H_NN⁻¹ H_NI over N = (other globals, all knots): the arrow system with p right-hand sides
    F = SchurComplementSolver(problem.local_structure).factor(V, V_off)
    WN, WI = W[:, N, :], W[:, I, :]
    Y = F.solve_lower(WN.transpose(-1, -2))                           # (T, d, nN)
    yb = F.solve_lower(WI.transpose(-1, -2).contiguous())             # (T, d, p)
    Yf, ybf = Y.reshape(-1, Y.shape[-1]), yb.reshape(-1, yb.shape[-1])
    if len(N):
        S_NN = U[N][:, N] - Yf.T @ Yf
        Gg = torch.cholesky_solve(U[N][:, I] - Yf.T @ ybf, cholesky(0.5 * (S_NN + S_NN.T), "nuisance information"))
        Gx = F.solve_upper((ybf - Yf @ Gg).reshape(yb.shape))
    else:
        Gg = U.new_zeros(0, len(I))
        Gx = F.solve_upper(yb)
    r, Jg, A, B = problem.chain_jacobians(meas, values, x)
    P = Jg[..., I] - Jg[..., N] @ Gg - A @ Gx[:-1] - B @ Gx[1:]       # (J−1, m, p) profiled rows
    tau = meas.data.tau.numpy()
    span = float(tau[-1] - tau[0]) + meas.data.h
    nb = max(int(round(span / block_s)), 1)  # a trailing part shorter than L/2 joins its neighbour
    edges = tau[0] + block_s * np.arange(nb + 1)
    edges[-1] = tau[0] + span
    blk = np.minimum(((tau - tau[0]) // block_s).astype(int), nb - 1)
    C = torch.as_tensor(cov)
    infl, mcov = [], []
    for b in range(nb):
        sel = torch.as_tensor(blk == b)
        Pb = P[sel].reshape(-1, P.shape[-1])
        infl.append((C @ (Pb.T @ r[sel].reshape(-1))).numpy())
        mcov.append((C @ (Pb.T @ Pb) @ C).numpy())
    return BlockScores(edges=edges, influence=np.array(infl), model_cov=np.array(mcov))


def contrast_variances(scores: BlockScores, laplace_cov: np.ndarray, Wc: np.ndarray, level: float = TEST_LEVEL) -> dict:
    """Laplace, sandwich and reported variances of the contrasts Wc (n, p) of the free coordinates.

    Returns arrays (n,): "laplace", "robust" (leverage-corrected sandwich), "model" (wᵀVw),
    "dof" (Satterthwaite blocks), "fired" (the test of the module docstring), "reported".  NaN
    (unidentified) contrasts stay NaN and never fire.
    """
    Wc = np.atleast_2d(np.asarray(Wc, dtype=float))
    # unidentified coordinates (NaN rows) poison only the contrasts that touch them
    touched = (np.abs(Wc[:, ~np.isfinite(np.diag(laplace_cov))]) > 0).any(1)
    lap = np.einsum("ni,ij,nj->n", Wc, np.nan_to_num(laplace_cov), Wc)
    a = scores.influence @ Wc.T                                         # (nb, n)
    vb = np.einsum("ni,bij,nj->bn", Wc, scores.model_cov, Wc)           # (nb, n)
    Vt = scores.model_cov.sum(0)
    Vinv = np.linalg.pinv(0.5 * (Vt + Vt.T), rcond=1e-12, hermitian=True)
    VbW = np.einsum("bij,nj->bni", scores.model_cov, Wc)                # V_b w
    eb = vb - np.einsum("bni,ij,bnj->bn", VbW, Vinv, VbW)               # E[(wᵀa_b)²] under the model
    model = vb.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        shrink = np.clip(eb.sum(0) / model, 1e-3, 1.0)
        robust = (a ** 2).sum(0) / shrink
        # Satterthwaite: Σ_b (wᵀa_b)² as Σ_b e_b χ²_1 (blocks taken as independent)
        dof = np.maximum(eb.sum(0) ** 2 / (eb ** 2).sum(0), 1.0)
        q = np.where(np.isfinite(dof), chi2.ppf(1.0 - level, np.nan_to_num(dof, nan=1.0)) / np.nan_to_num(dof, nan=1.0), np.nan)
        fired = np.isfinite(robust) & np.isfinite(model) & (robust > q * model)
    fired &= ~touched
    lap, robust, model = (np.where(touched, np.nan, v) for v in (lap, robust, model))
    reported = np.where(fired, robust, lap)
    return {"laplace": lap, "robust": robust, "model": model, "dof": dof, "fired": fired, "reported": reported,
            "shrink": shrink}


def robust_std(v) -> np.ndarray:
    """√ of variances, NaN kept."""
    v = np.asarray(v, dtype=float)
    return np.sqrt(np.where(np.isfinite(v), np.clip(v, 0.0, None), np.nan))


#: reported blocks of :func:`robust_summary`: rig block name → the summary's key
_BLOCKS = {"q": "orientation", "r": "position", "o": "time_offset", "d": "clock_drift", "oa": "acc_delay"}


def robust_summary(res) -> dict:
    """Per non-reference IMU label k and reported parameter (orientation in the sensor frame, as
    ``orientation_cov``; position; time_offset; clock_drift and acc_delay where free): a dict with
    "std" (Laplace), "std_robust", "cov_robust", "ratio" (robust/Laplace std), "std_reported",
    "robust_used" (per coordinate) — units rad, m, s, 1.  {} when the fit kept no block scores."""
    from ...physics.geometry import quat_to_matrix
    if res.block_scores is None:
        return {}
    labels = res.free_labels
    out = {}
    for k in range(len(res.position)):
        if k == res.reference_imu:
            continue
        out[k] = {}
        for name, key in _BLOCKS.items():
            idx = [i for i, (kk, n, _) in enumerate(labels) if kk == k and n == name]
            if not idx:
                continue
            Wc = np.zeros((len(idx), len(labels)))
            Wc[np.arange(len(idx)), idx] = 1.0
            if name == "q":  # tangent in the array frame; reported in the sensor frame (R δ)
                Rk = quat_to_matrix(torch.as_tensor(np.asarray(res.orientation[k], dtype=float))).numpy()
                Wc[:, idx] = Rk
            v = contrast_variances(res.block_scores, res.free_cov, Wc)
            # the sandwich's block, scaled so that its diagonal is the leverage-corrected variance
            sc = 1.0 / np.sqrt(v["shrink"])
            Cr = (Wc @ res.block_scores.robust_cov() @ Wc.T) * sc[:, None] * sc[None, :]
            Cr[~np.isfinite(v["robust"]), :] = np.nan
            Cr[:, ~np.isfinite(v["robust"])] = np.nan
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = robust_std(v["robust"]) / robust_std(v["laplace"])
            out[k][key] = {"std": robust_std(v["laplace"]), "std_robust": robust_std(v["robust"]), "cov_robust": Cr,
                           "ratio": ratio, "std_reported": robust_std(v["reported"]), "robust_used": v["fired"]}
    return out


def robust_warning(summary: dict) -> str | None:
    """One line naming where the reported std is the sandwich, or None."""
    used = [(k, key, float(np.nanmax(e["ratio"][e["robust_used"]])))
            for k, blocks in summary.items() for key, e in blocks.items() if e["robust_used"].any()]
    if not used:
        return None
    worst = max(r for _, _, r in used)
    where = ", ".join(f"IMU {k} {key}" for k, key, _ in used)
    return (f"rig posterior: the data reject the model's white noise ({where}); the reported std there is the "
            f"block sandwich, up to {worst:.1f}× the Laplace std")

"""Comparing fits of the augmented model (DESIGN §2 "refit → compare").

:func:`compare_fits`: χ²/dof with the stated noise (or the refined noise when a noise_level
effect is in the model, and it says so), log-likelihood, ELPD by PSIS-LOO over time samples
(:func:`elpd_loo`: pointwise log-likelihood at Laplace draws of the globals, with each sample's
motion state re-profiled through the local linearisation; the ArviZ calls, ``az.loo`` and
``az.compare``, are :func:`accel_bayes.diagnostics.arviz_calls.psis_loo` / :func:`~accel_bayes.diagnostics.arviz_calls.compare_loo`)
and the geometry before/after.  :func:`posterior_comparison` additionally runs
:func:`accel_bayes.pipelines.calibrate.calibrate` (PmMH) on the recording before and after correction
(:func:`corrected_recording`).
"""
from __future__ import annotations

import warnings

import numpy as np
import torch

from ..physics.effects import model_outputs
from .model import ModelFit, project_off_states

__all__ = ["elpd_loo", "compare_fits", "corrected_recording", "posterior_comparison"]


def elpd_loo(fit: ModelFit, *, draws: int = 200, seed: int = 0):
    """PSIS-LOO over time samples (ArviZ ``az.loo``) of a fit, and the InferenceData used.

    Pointwise log-likelihood ℓ_t(g_s) at S Laplace draws g_s ~ N(ĝ, S⁻¹) of the globals
    (positions, effect parameters), each sample's motion state re-profiled through the local
    linearisation: ℓ_t(ĝ + δ) = ℓ_t(ĝ) − ½(‖P_t(r_t − J_t δ)‖² − ‖r_t‖²), P_t the projection off
    the motion-state Jacobian.  Returns (elpd dict, idata); the dict holds elpd_loo, se, p_loo
    and the count of Pareto k > 0.7.
    """
    elpd, idata, _ = _elpd_loo(fit, draws=draws, seed=seed)
    return elpd, idata


def _elpd_loo(fit: ModelFit, *, draws: int = 200, seed: int = 0):
    """:func:`elpd_loo` plus ArviZ's ``ELPDData`` (pointwise), which :func:`compare_fits` hands
    to :func:`accel_bayes.diagnostics.arviz_calls.compare_loo` so that PSIS-LOO is not recomputed there."""
    from ..diagnostics.arviz_calls import psis_loo  # lazy: ArviZ and matplotlib only when a comparison is made

    lin = fit.linear()
    n = lin.n
    g = torch.Generator().manual_seed(int(seed))
    base_t = fit.loglik_t
    if n:
        L = torch.linalg.cholesky(lin.Sinv)
        eps = torch.randn(draws, n, generator=g, dtype=torch.float64)
        dg = eps @ L.T  # (S, n)
        T = lin.r.shape[0]
        Pr = project_off_states(lin.Jx, lin.Vinv, lin.r)
        a = lin.jg_tmul(Pr.unsqueeze(0), per_sample=True)[0]  # (T, n) = J_tᵀ P_t r_t
        ll = base_t[None] - 0.5 * (_projected_quad(lin, dg) - 2 * dg @ a.T)
    else:
        ll = base_t[None].expand(draws, -1)
        dg = None
    post = (dg if dg is not None else torch.zeros(draws, 1, dtype=torch.float64)).numpy()
    elpd, idata, loo = psis_loo(ll.numpy(), post)
    elpd["draws"] = int(draws)
    return elpd, idata, loo


def _projected_quad(lin, dg: torch.Tensor) -> torch.Tensor:
    """‖P_t J_t δ_s‖² (S, T) for draws δ (S, n) of the globals, P_t the projection off sample t's
    motion-state Jacobian, as ‖J_t δ‖² − (W_tᵀδ)ᵀ V_t⁻¹ (W_tᵀδ) (P_t is idempotent and
    J_xᵀ J_t δ = W_tᵀ δ).  ‖J_t δ‖² comes from the per-sample Gram blocks of the structured global
    Jacobian (IMU k's rows see only its own position and the effects), contracted with the draws'
    outer products by one matrix product each: no (S, T, 6K) array of projected rows is formed
    (that was most of the time of PSIS-LOO on 32 IMUs)."""
    S, n = dg.shape
    T = lin.r.shape[0]
    free = lin.free
    F = len(free)
    p = lin.Je.shape[-1]
    quad = dg.new_zeros(S, T)
    if F:
        Jrf = lin.Jr[:, :, free]  # (T, 2, F, 3, 3)
        A = torch.einsum("tsfai,tsfaj->tfij", Jrf, Jrf).reshape(T, F * 9)
        dr = dg[:, :3 * F].reshape(S, F, 3)
        quad = quad + (dr[:, :, :, None] * dr[:, :, None, :]).reshape(S, F * 9) @ A.T
    if p:
        de = dg[:, 3 * F:]
        if F:
            B = torch.einsum("tsfai,tsfap->tfip", Jrf, lin.Je[:, :, free]).reshape(T, F * 3 * p)
            quad = quad + 2 * ((dr[:, :, :, None] * de[:, None, None, :]).reshape(S, F * 3 * p) @ B.T)
        C = torch.einsum("tskap,tskaq->tpq", lin.Je, lin.Je).reshape(T, p * p)
        quad = quad + (de[:, :, None] * de[:, None, :]).reshape(S, p * p) @ C.T
    Wd = (dg @ lin.W.permute(1, 0, 2).reshape(n, T * 9)).reshape(S, T, 9)  # W_tᵀ δ
    Zd = (dg @ lin.Z.reshape(T * 9, n).T).reshape(S, T, 9)  # V_t⁻¹ W_tᵀ δ
    return quad - (Wd * Zd).sum(-1)


def compare_fits(before: ModelFit, after: ModelFit, *, draws: int = 200, seed: int = 0, loo: bool = True) -> dict:
    """Before/after comparison of two fits of the same recording (module docstring)."""
    out = {
        "effects_before": [e.label() for e in before.effects],
        "effects_after": [e.label() for e in after.effects],
        "loglik": {"before": before.loglik, "after": after.loglik, "difference": after.loglik - before.loglik},
        "chi2_per_dof": {"before": before.chi2_per_dof, "after": after.chi2_per_dof,
                         "after_model_noise": after.chi2_per_dof_model,
                         "noise": "refined" if after.has_noise_effect else "stated"},
        "dof": {"before": before.dof, "after": after.dof},
        "positions_before": before.positions.tolist(),
        "positions_after": after.positions.tolist(),
        "position_change_m": (after.positions - before.positions).tolist(),
    }
    if loo:
        try:
            from ..diagnostics.arviz_calls import compare_loo  # lazy, as in _elpd_loo

            e0, _, loo0 = _elpd_loo(before, draws=draws, seed=seed)
            e1, _, loo1 = _elpd_loo(after, draws=draws, seed=seed + 1)
            out["elpd_loo"] = {"before": e0, "after": e1, "difference": e1["elpd_loo"] - e0["elpd_loo"],
                               "compare": compare_loo({"baseline": loo0, "refined": loo1})}
        except Exception as exc:  # pragma: no cover - report rather than fail the whole analysis
            out["elpd_loo"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def corrected_recording(rec, fit: ModelFit, index=None):
    """A copy of ``rec`` with the fitted mean effects subtracted (outputs − (model with effects −
    nominal model)), samples the fitted saturation clips removed from the noise accounting by
    flagging them in ``acc_clipped``/``gyro_clipped``, and the stated noise multiplied by the
    fitted noise factors.  What the posterior calibration is rerun on (``detect(posterior=calibrate)``).

    index : None — ``rec`` holds exactly the fitted samples (``Prepared.rec``); else the fitted
        samples' indices into ``rec`` (``Prepared.selection.index``, ``rec`` = ``Prepared.source``):
        only those samples are corrected (the others carry no fitted motion; the calibration's
        selection drops them again)."""
    out = rec.copy()
    mean_eff = [e for e in fit.effects if e.kind == "mean"]
    rows = slice(None) if index is None else np.asarray(index)
    if mean_eff:
        with torch.no_grad():
            ctx = fit.ctx
            acc, gyro = model_outputs(mean_eff, ctx)
            out.acc = np.array(rec.acc, dtype=np.float64)
            out.acc[rows] -= (acc - ctx.acc).numpy()
            if rec.gyro is not None:
                out.gyro = np.array(rec.gyro, dtype=np.float64)
                out.gyro[rows] -= (gyro - ctx.gyro).numpy()
    for e in fit.effects:
        if e.kind == "clip":
            L = float(e.params["limit"])
            y = np.asarray(rec.acc if e.which == "acc" else rec.gyro)
            sel = np.abs(y) >= L * (1 - 1e-9)
            if e.imu is not None:
                m = np.zeros_like(sel)
                m[:, e.imu, e.axis_index] = sel[:, e.imu, e.axis_index]
                sel = m
            flags = sel.any(-1)
            nm = "acc_clipped" if e.which == "acc" else "gyro_clipped"
            old = getattr(out, nm)
            setattr(out, nm, flags if old is None else (np.asarray(old) | flags))
    out.acc_noise_std = np.asarray(rec.acc_noise_std) * fit.acc_factor.numpy()
    out.gyro_noise_std = np.asarray(rec.gyro_noise_std) * fit.gyro_factor.numpy()
    out.source = (rec.source + "; " if rec.source else "") + "corrected for " + ", ".join(e.label() for e in fit.effects)
    return out


def posterior_comparison(rec, fit: ModelFit, calibrate, *, seed: int = 0, chains: int = 2, draws: int = 400,
                         warmup: int = 400, progress: bool = False, index=None, corrected_base=None) -> dict:
    """PmMH posterior of the positions (``calibrate``: :func:`accel_bayes.pipelines.calibrate.calibrate`,
    passed in by the caller because the pipelines stand above ``mismatch``; short chains)
    on the recording as given and on :func:`corrected_recording` (``index`` as there) — an
    adapter over the calibration pipeline, which itself knows no effects.  Given the whole
    prepared recording (``Prepared.source``, rests included) the calibration keeps its own
    protocol: the same selection, noise estimated as for a recording with rests.  ``corrected_base``:
    the recording ``fit`` was fitted to when that is not ``rec`` (the detector's gyro linear stage
    corrects the gyros first), the "after" run corrects it.  Returns both
    ``positions.json``-style documents' per-IMU means/stds and their R̂/ESS diagnostics, or an
    error note."""
    out = {"settings": {"chains": chains, "draws": draws, "warmup": warmup, "seed": int(seed)}}
    after = corrected_recording(rec if corrected_base is None else corrected_base, fit, index=index)
    for tag, r in (("before", rec), ("after", after)):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                res = calibrate(r, chains=chains, draws=draws, warmup=warmup, seed=int(seed), progress=progress)
            doc = res.positions
            out[tag] = {"imus": [{"imu": d["imu"], "mean": d["mean"], "std": d["std"]} for d in doc["imus"]],
                        "diagnostics": doc.get("diagnostics", {})}
        except Exception as exc:  # report, do not fail the mismatch analysis
            out[tag] = {"error": f"{type(exc).__name__}: {exc}"}
    return out

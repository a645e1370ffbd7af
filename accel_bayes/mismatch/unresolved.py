"""``unresolved_motion`` (DESIGN §7.2 vocabulary 1.2; issue #27 item 3): board motion faster than
the outputs resolve, seen through each IMU's data age, marginalised exactly.

Physics.  IMU k's output read at t is the sample its sensor took at t − age_kt (its clock's data
age, ``sampling_clock``).  The part of the board's motion between the outputs that the fitted
motion does not resolve — vibration and impacts above the host's Nyquist rate — is a per-sample
jerk j_t (m/s³) on the accelerometers and angular acceleration α_t (rad/s²) on the gyroscopes,
common to the rigid board.  To first order it adds −age_kt j_t (acc) and −age_kt α_t (gyro) to
IMU k's residual; a common age is absorbed by the motion states, so the loading is the centred
age d_kt = age_kt − mean_k age_kt (s).  Per sample and sensor, in the array frame,

    y_kt = d_kt m_t + e_kt,   m_t ~ N(0, s²_b(t) I₃),   e_kt ~ N(0, v_k,b(t) I₃),

s_b the scale of the unresolved motion in |ω| band b (``jerk_rms`` m/s³ for acc,
``angular_acc_rms`` rad/s² for gyro), v the white variance per IMU and band.  The 3K residuals of
a sample are Gaussian with covariance A + U S Uᵀ, U = d ⊗ I₃ (rank 3), which
:func:`lowrank_terms` evaluates exactly (Woodbury identity, matrix determinant lemma) for any
base A — diagonal (this model) or a full cross-IMU covariance (held-out remainders,
:mod:`accel_bayes.mismatch.heldout`) — batched over samples, O(T n r²).

Its contribution to the §7.2 budget is the predicted extra variance s²_b d²_kt per channel-sample
(:func:`predicted_variance`).  The accelerometer half on the gyros' instant errors is the aliased
jerk of :mod:`accel_bayes.mismatch.vibration`, which evaluates and fits it with the functions here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# The covariance algebra lives in the model layer (issue #30 item 5: one implementation, shared with
# the calibration likelihood); re-exported here for the detector's callers.
from ..model.unresolved_cov import gauss_logpdf, loadings, lowrank_terms, marginal_loglik, t_logpdf  # noqa: F401

__all__ = ["lowrank_terms", "gauss_logpdf", "t_logpdf", "loadings", "marginal_loglik", "fit_scales",
           "predicted_variance", "finding", "UnresolvedMotion"]


def fit_scales(a: torch.Tensor, d: torch.Tensor, w: torch.Tensor, lab: torch.Tensor, B: int, *, max_iter: int = 200,
               std: bool = True):
    """Maximum-likelihood fit of :func:`marginal_loglik` on arrays: a (T, K, 3), d (T, K) centred
    data ages or instant errors (s), w (T, K) weights 0/1, lab (T,) |ω| band index in [0, B).
    Returns (v_null (K, B), log v (K, B), log s² (B,), loglik_null, loglik, std of log s² (B,) —
    NaN with ``std=False``, which skips the Hessian); s in units/s per axis."""
    T, K = w.shape
    onehot = torch.nn.functional.one_hot(lab, B).to(a.dtype)  # (T, B)
    # null: the ML white variance per IMU and band in closed form
    num = torch.einsum("tb,tk->kb", onehot, (a ** 2).sum(-1) * w)
    den = 3 * torch.einsum("tb,tk->kb", onehot, w)
    v0 = (num / den.clamp_min(1)).clamp_min(1e-12)
    v0 = torch.where(den > 0, v0, v0[den > 0].mean() if (den > 0).any() else torch.ones_like(v0))
    ll0 = marginal_loglik(a, d, w, v0[:, lab].T, torch.zeros(T, dtype=a.dtype)).sum()

    # log-parameters, L-BFGS from the null plus a term of a tenth of the white variance (a fixed
    # start would sit where the gradient vanishes when d is tiny)
    lv = torch.log(v0).clone().requires_grad_(True)
    d2 = float((d ** 2 * w).sum() / w.sum().clamp_min(1))
    s2_0 = 0.1 * float(v0.mean()) / d2 if d2 > 0 else 1e6
    ls = torch.full((B,), math.log(s2_0), dtype=a.dtype, requires_grad=True)
    opt = torch.optim.LBFGS([lv, ls], max_iter=max_iter, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                            tolerance_change=1e-12)

    def nll(lv_, ls_):
        return -marginal_loglik(a, d, w, torch.exp(lv_)[:, lab].T, torch.exp(ls_)[lab]).sum()

    def closure():
        opt.zero_grad()
        loss = nll(lv, ls)
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    lv, ls = lv.detach(), ls.detach()
    ll1 = -nll(lv, ls)
    if not std:
        return v0, lv, ls, float(ll0), float(ll1), torch.full((B,), float("nan"), dtype=a.dtype)
    # the scales' standard errors from the observed information of all log-parameters; the bands
    # share no parameter and no sample, so the information is block-diagonal by band
    sd_ls = torch.full((B,), float("nan"), dtype=a.dtype)
    for b in range(B):
        sel = lab == b
        if not bool(sel.any()):
            continue
        ab, db, wb = a[sel], d[sel], w[sel]

        def nll_b(x):
            return -marginal_loglik(ab, db, wb, torch.exp(x[:K])[None, :].expand(len(ab), K),
                                    torch.exp(x[K]).expand(len(ab))).sum()

        H = torch.autograd.functional.hessian(nll_b, torch.cat((lv[:, b], ls[b:b + 1])), vectorize=True)
        try:
            sd_ls[b] = torch.sqrt(torch.linalg.inv(H)[K, K].clamp_min(0))
        except RuntimeError:  # singular (e.g. an IMU without samples in the band): no std
            pass
    return v0, lv, ls, float(ll0), float(ll1), sd_ls


def predicted_variance(d: torch.Tensor, w: torch.Tensor, s2: torch.Tensor) -> torch.Tensor:
    """(T, K): the extra variance per channel the term predicts, s²_b(t) d²_kt (units²) — its part
    b of the §7.2 budget, per channel-sample; 0 where the triad does not enter."""
    return s2[:, None] * d ** 2 * w


def finding(edges, jerk_rms, angular_acc_rms, *, evidence: float, jerk_rms_std=None, angular_acc_rms_std=None) -> dict:
    """The §7.2 finding (vocabulary 1.2) of fitted scales: ``jerk_rms`` (m/s³) and
    ``angular_acc_rms`` (rad/s²) per |ω| band, inner band edges ``edges`` (rad/s); imu and axis
    null (a per-sample error common to the board)."""
    params = {"omega_edges": [float(e) for e in edges], "jerk_rms": [float(x) for x in jerk_rms],
              "angular_acc_rms": [float(x) for x in angular_acc_rms]}
    if jerk_rms_std is not None:
        params["jerk_rms_std"] = [float(x) for x in jerk_rms_std]
    if angular_acc_rms_std is not None:
        params["angular_acc_rms_std"] = [float(x) for x in angular_acc_rms_std]
    return {"effect": "unresolved_motion", "imu": None, "axis": None, "evidence": float(evidence),
            "parameters": params, "where": {"regime": "all |omega| bands", "time_s": None},
            "explanation": "board motion faster than the outputs resolve (vibration, impacts), seen through each "
                           "IMU's data age as a per-sample error common to the board"}


@dataclass
class UnresolvedMotion:
    """The fitted term as the refit and the §7.2 budget take a random effect: ``d`` (T, K) the
    centred data ages (s) of the fit's samples, ``lab`` (T,) their |ω| band, ``edges`` the inner
    band edges (rad/s), ``jerk_rms`` (B,) m/s³ and ``angular_acc_rms`` (B,) rad/s² per axis.
    ``predicted_variance(params, ctx)`` is the budget's hook
    (:func:`accel_bayes.mismatch.budget.predicted_extra_variance`); :meth:`loglik` the term's
    contribution to a refit's log-likelihood given white variances."""

    d: torch.Tensor
    lab: torch.Tensor
    edges: list
    jerk_rms: torch.Tensor
    angular_acc_rms: torch.Tensor
    name: str = "unresolved_motion"
    kind: str = "random"

    def predicted_variance(self, params=None, ctx=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(acc, gyro) (T, K, 3): s²_b d² per channel (units²), the same on the three axes."""
        w = torch.ones_like(self.d)
        out = []
        for s in (self.jerk_rms, self.angular_acc_rms):
            out.append(predicted_variance(self.d, w, torch.as_tensor(s, dtype=self.d.dtype)[self.lab] ** 2)[..., None]
                       .expand(*self.d.shape, 3))
        return out[0], out[1]

    def loglik(self, y_acc, y_gyro, w, v_acc, v_gyro) -> torch.Tensor:
        """Per-sample log density (nats, (T,)) of both sensors' array-frame residuals (T, K, 3)
        with white variances v (T, K) and this term marginalised (:func:`marginal_loglik`)."""
        dt = self.d.dtype
        return (marginal_loglik(y_acc, self.d * w, w, v_acc, torch.as_tensor(self.jerk_rms, dtype=dt)[self.lab] ** 2)
                + marginal_loglik(y_gyro, self.d * w, w, v_gyro, torch.as_tensor(self.angular_acc_rms, dtype=dt)[self.lab] ** 2))

    def finding(self, evidence: float) -> dict:
        """The report's finding (:func:`finding`)."""
        return finding(self.edges, self.jerk_rms, self.angular_acc_rms, evidence=evidence)

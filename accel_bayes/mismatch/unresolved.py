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
(:func:`predicted_variance`).  The detector fits the richer form of :func:`fit_grid`: scales per
|ω| × |ω̇| cell, one white variance per IMU, and an age error ε_kt the clocks do not give, through
which the same m_t adds s² e² per channel (issue #27 budget).  The accelerometer half on the gyros' instant errors is the aliased
jerk of :mod:`accel_bayes.mismatch.vibration`, which evaluates and fits it with the functions here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch

# The covariance algebra lives in the model layer (issue #30 item 5: one implementation, shared with
# the calibration likelihood); re-exported here for the detector's callers.
from ..model.unresolved_cov import (gauss_logpdf, loadings, lowrank_terms, marginal_loglik,  # noqa: F401
                                    rotational_loadings, t_logpdf)

__all__ = ["lowrank_terms", "gauss_logpdf", "t_logpdf", "loadings", "marginal_loglik", "fit_scales", "fit_grid",
           "GridFit", "predicted_variance", "finding", "UnresolvedMotion"]


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


@dataclass
class GridFit:
    """:func:`fit_grid`'s result: ``v`` (K,) white variance per IMU (units²); ``s2`` (C,) the
    unresolved motion's variance per axis per cell ((units/s)², 0 in an empty cell); ``e2`` the age
    error's variance (s²); ``loglik`` (nats); ``loglik_no_age_error`` (nats, refitted with e2 = 0);
    ``sd_log_s2`` (C,) standard errors of log s2 (NaN where not computed); ``v_no_age_error``,
    ``s2_no_age_error`` the refit with e2 = 0; ``a2`` / ``a2_no_age_error`` (C,) the angular jerk's
    variance per axis per cell ((rad/s³)²) where it was fitted (``lever``), else None."""

    v: torch.Tensor
    s2: torch.Tensor
    e2: float
    loglik: float
    loglik_no_age_error: float
    sd_log_s2: torch.Tensor
    v_no_age_error: torch.Tensor
    s2_no_age_error: torch.Tensor
    a2: torch.Tensor | None = None
    a2_no_age_error: torch.Tensor | None = None


def _grid_lbfgs(a, d, w, cell, C, counts, lv, ls, le, free_e, v_known, v_floor, rot=None, la=None):
    """L-BFGS on the per-sample objective of :func:`fit_grid` (e fixed at exp(le) unless ``free_e``);
    with ``rot`` (:func:`_RotTerm`) and ``la`` (C,) log angular-jerk variances, the lever-arm term too."""
    T = a.shape[0]
    params = [lv, ls] + ([le] if free_e else []) + ([la] if rot is not None else [])
    opt = torch.optim.LBFGS(params, max_iter=300, line_search_fn="strong_wolfe", tolerance_grad=1e-9,
                            tolerance_change=1e-12)
    filled = (counts > 0)[cell]

    def nll(lv_, ls_, le_, la_=None):  # la_: the angular jerk's log-variances, used with ``rot`` only
        if rot is not None:
            # a line-search step may try e^(log-variance) that overflows; the rank-6 factorisation needs finite
            # variances (the jerk-only closed form does not), so the log-variances are capped at e^LOG_VAR_CAP
            ls_, la_ = ls_.clamp(max=LOG_VAR_CAP), la_.clamp(max=LOG_VAR_CAP)
        s2 = torch.where(filled, torch.exp(ls_)[cell], torch.zeros((), dtype=a.dtype))
        v = v_floor[None, :] + torch.exp(lv_)[None, :] + torch.exp(le_) * s2[:, None] + v_known
        if rot is None:
            return -marginal_loglik(a, d, w, v, s2).sum()
        sa2 = torch.where(filled, torch.exp(la_)[cell], torch.zeros((), dtype=a.dtype))
        return -rot.loglik(a, v, s2, sa2, torch.exp(le_)).sum()

    def closure():
        opt.zero_grad()
        loss = nll(lv, ls, le, la) / T  # per sample: keeps L-BFGS's tolerances meaningful
        loss.backward()
        return loss

    for _ in range(3):
        opt.step(closure)
    return nll


#: the largest log-variance the lever-arm fit evaluates (:func:`_grid_lbfgs`): e^60 ≈ (10¹³)², far above any jerk
#: (m/s³) or angular jerk (rad/s³) a board carries, far below overflow
LOG_VAR_CAP = 60.0


class _RotTerm:
    """The board's unresolved angular jerk ω̈_t on the accelerometers beside the jerk (:func:`fit_grid`'s
    ``lever``): triad k's residual gains −(d_kt + ε_kt)(ω̈_t × c_k), c_k its lever arm (m) about the
    clocked triads' centroid, ω̈_t ~ N(0, a²_c I₃) rad/s³ — the same loading the calibration's likelihood
    carries (:func:`~accel_bayes.model.unresolved_cov.rotational_loadings`).  Per sample the 3K residuals
    have covariance diag(v + e²s² + e²a² ρ_k) + s² (d ⊗ I₃)(…)ᵀ + a² R Rᵀ, ρ_ki = |c_k|² − c_ki² the
    squared row norms of [c_k]×; evaluated exactly by :func:`lowrank_terms` (rank 6)."""

    def __init__(self, d: torch.Tensor, w: torch.Tensor, lever: torch.Tensor, centred: bool = False):
        T, K = d.shape
        c = torch.as_tensor(lever, dtype=d.dtype)
        c = c if centred else c - c.mean(0, keepdim=True)  # ``centred``: lever arms given about their point
        self.rowsq = (c ** 2).sum(-1, keepdim=True) - c ** 2  # (K, 3)
        self.d, self.w, self.c = d, w, c
        self.ww = w[:, :, None].expand(T, K, 3).reshape(T, 3 * K)  # the channels' 0/1 weights
        self.T, self.K = T, K
        self._U = None  # the (T, 3K, 6) loadings, built on the first loglik (the budget's predicted variance needs none)

    @property
    def U(self) -> torch.Tensor:
        if self._U is None:
            self._U = torch.cat((loadings(self.d), rotational_loadings(self.d, self.c, about=torch.zeros(3, dtype=self.d.dtype))), -1)
        return self._U

    def loglik(self, a, v, s2, sa2, e2) -> torch.Tensor:
        """(T,) nats: a (T, K, 3) residuals, v (T, K) white variances (with e² s²), s2 / sa2 (T,) the jerk's
        and the angular jerk's variances per axis, e2 the age error's variance (s²)."""
        T, K = self.T, self.K
        vv = v[:, :, None] + e2 * sa2[:, None, None] * self.rowsq[None]
        S = torch.stack([s2] * 3 + [sa2] * 3, -1)
        q, ld = lowrank_terms(a.reshape(T, 3 * K), self.U, S, v=vv.reshape(T, 3 * K), w=self.ww)
        return gauss_logpdf(q, ld, self.ww.sum(-1))

    def predicted(self, sa2: torch.Tensor, e2: float) -> torch.Tensor:
        """(T, K) units²: the angular jerk's extra variance per channel, a² (d² + e²) |c_k|²·⅔ (the triad's
        mean over its three axes: the budget's channel mean does not depend on the frame)."""
        return sa2[:, None] * (self.d ** 2 + e2) * self.w * (self.rowsq.sum(-1) / 3.0)[None, :]


def fit_grid(a: torch.Tensor, d: torch.Tensor, w: torch.Tensor, cell: torch.Tensor, C: int, *,
             v_known: torch.Tensor | None = None, v_floor: torch.Tensor | None = None, std: bool = True,
             lever: torch.Tensor | None = None) -> GridFit:
    """Maximum-likelihood fit of the unresolved motion seen through the clocks' ages *and* an age
    error the clocks do not give (issue #27 budget):

        y_kt = (d_kt + ε_kt) m_t + e_kt,   m_t ~ N(0, s²_c(t) I₃),   ε_kt ~ (0, e²) iid,
        e_kt ~ N(0, v_k I₃),

    a (T, K, 3) array-frame residuals (units), d (T, K) centred clock ages (s), w (T, K) 0/1, cell
    (T,) in [0, C) the motion cell of each sample (the |ω| × |ω̇| bands).  ε m is not Gaussian; it
    enters by its first two moments — zero mean, variance e² s²_c per axis, uncorrelated across IMUs
    and with d m — so the per-sample covariance is (v_k + e² s²_c) I on the diagonal plus
    s²_c d dᵀ ⊗ I₃, evaluated exactly by :func:`marginal_loglik`.  The white part v_k is one
    constant per IMU (the sensor's own noise does not follow the motion); all that grows with the
    motion is loaded by the common unresolved m_t, through d or through ε.  ``v_known`` (T, K)
    units²: variance per channel the model already predicts (its random effects), added to the
    white part so that the term is fitted on top of it, not in its place.  ``v_floor`` (K,) units²:
    the least white variance per IMU (its stated noise): without it an IMU's white variance can
    collapse to 0 with its residual taken wholly by d_k m_t (a Heywood case of the factor model).

    ``lever`` (K, 3) m, accelerometers only: the triads' positions; the board's unresolved angular
    jerk is then fitted beside the jerk, y_kt += −(d_kt + ε_kt)(ω̈_t × c_k), ω̈_t ~ N(0, a²_c I₃) rad/s³
    per cell, c_k about the triads' centroid (:class:`_RotTerm`; ``GridFit.a2``).  A rigid board's
    triads read at different instants see its rotation's jerk through their lever arms, which the
    jerk m_t (the same on every triad) cannot carry."""
    T, K = w.shape
    v_known = torch.zeros_like(w) if v_known is None else v_known
    v_floor = torch.zeros(K, dtype=a.dtype) if v_floor is None else torch.as_tensor(v_floor, dtype=a.dtype)
    counts = torch.bincount(cell, minlength=C)
    p = (a ** 2).sum(-1) * w
    d2 = float((d ** 2 * w).sum() / w.sum().clamp_min(1))
    rot = None if lever is None else _RotTerm(d, w, lever)
    # start: a tenth of each IMU's power white, half the mean power on the term, ε of 0.1 ms; the angular
    # jerk (when fitted) starts with the same share through the mean squared lever arm
    lv_0 = torch.log((0.1 * p.sum(0) / (3 * w.sum(0)).clamp_min(1)).clamp_min(1e-12))
    s2_start = max(0.5 * float(p.sum() / (3 * w.sum().clamp_min(1))) / max(d2, 1e-30), 1e-12)
    ls_0 = torch.full((C,), math.log(s2_start), dtype=a.dtype)
    la_0 = None
    if rot is not None:
        c2 = max(float(rot.rowsq.sum(-1).mean()) / 3.0, 1e-12)
        la_0 = torch.full((C,), math.log(s2_start / c2), dtype=a.dtype)
    lv, ls = lv_0.clone().requires_grad_(True), ls_0.clone().requires_grad_(True)
    la = None if rot is None else la_0.clone().requires_grad_(True)
    le = torch.tensor(math.log(1e-8), dtype=a.dtype, requires_grad=True)
    nll = _grid_lbfgs(a, d, w, cell, C, counts, lv, ls, le, True, v_known, v_floor, rot, la)
    with torch.no_grad():
        ll = float(-nll(lv, ls, le, la))
    fit = (lv.detach().clone(), ls.detach().clone(), le.detach().clone(), None if la is None else la.detach().clone())
    # the same without the age error, from the same start (its evidence is the difference)
    lv0, ls0 = lv_0.clone().requires_grad_(True), ls_0.clone().requires_grad_(True)
    la0 = None if rot is None else la_0.clone().requires_grad_(True)
    le0 = torch.tensor(-200.0, dtype=a.dtype)
    nll0 = _grid_lbfgs(a, d, w, cell, C, counts, lv0, ls0, le0, False, v_known, v_floor, rot, la0)
    with torch.no_grad():
        ll0 = float(-nll0(lv0, ls0, le0, la0))
    if not math.isfinite(ll0):  # the line search left the domain from that start: from the fit instead
        lv0, ls0 = fit[0].clone().requires_grad_(True), fit[1].clone().requires_grad_(True)
        la0 = None if rot is None else fit[3].clone().requires_grad_(True)
        nll0 = _grid_lbfgs(a, d, w, cell, C, counts, lv0, ls0, le0, False, v_known, v_floor, rot, la0)
        with torch.no_grad():
            ll0 = float(-nll0(lv0, ls0, le0, la0))
    lv, ls, le, la = fit
    sd = torch.full((C,), float("nan"), dtype=a.dtype)
    if std:
        x = torch.cat((lv, ls, le[None]) + (() if la is None else (la,)))

        def f(x_):
            return nll(x_[:K], x_[K:K + C], x_[K + C], None if la is None else x_[K + C + 1:])

        H = torch.autograd.functional.hessian(f, x, vectorize=True)
        keep = torch.cat((torch.ones(K, dtype=torch.bool), counts > 0, torch.ones(1, dtype=torch.bool))
                         + (() if la is None else (counts > 0,)))
        try:
            cov = torch.linalg.inv(H[keep][:, keep])
            sd[counts > 0] = torch.sqrt(torch.diagonal(cov)[K:K + int((counts > 0).sum())].clamp_min(0))
        except RuntimeError:  # singular information: no standard errors
            pass
    zero = torch.zeros((), dtype=a.dtype)
    s2 = torch.where(counts > 0, torch.exp(ls), zero)
    s20 = torch.where(counts > 0, torch.exp(ls0.detach()), zero)
    a2 = a20 = None
    if rot is not None:  # the variances the fit evaluated (capped as in _grid_lbfgs)
        s2 = torch.where(counts > 0, torch.exp(ls.clamp(max=LOG_VAR_CAP)), zero)
        s20 = torch.where(counts > 0, torch.exp(ls0.detach().clamp(max=LOG_VAR_CAP)), zero)
        a2 = torch.where(counts > 0, torch.exp(la.clamp(max=LOG_VAR_CAP)), zero)
        a20 = torch.where(counts > 0, torch.exp(la0.detach().clamp(max=LOG_VAR_CAP)), zero)
    return GridFit(v_floor + torch.exp(lv), s2, float(torch.exp(le)), ll, ll0, sd, v_floor + torch.exp(lv0.detach()), s20,
                   a2, a20)


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

    With ``omega_dot_edges`` (inner |ω̇| band edges, rad/s², C − 1 of them) the scales are per
    motion cell instead: ``lab`` = b·C + c (|ω| band b, |ω̇| band c) and ``jerk_rms`` /
    ``angular_acc_rms`` have B·C entries (:func:`fit_grid`); ``age_error_rms`` (acc, gyro) s is the
    rms e of the age error ε the clocks do not give, which adds e² s² per channel on the clocked
    IMUs (those with a nonzero ``d``, or ``w`` (T, K) 0/1 when given).
    ``predicted_variance(params, ctx)`` is the budget's hook
    (:func:`accel_bayes.mismatch.budget.predicted_extra_variance`); :meth:`loglik` the term's
    contribution to a refit's log-likelihood given white variances.

    ``angular_jerk_rms`` (same shape as ``jerk_rms``, rad/s³) with ``lever`` (K, 3) m, the triads'
    lever arms about the clocked triads' centroid: the board's unresolved angular jerk on the
    accelerometers (:func:`fit_grid`'s ``lever``); None: not in the term (the default detector)."""

    d: torch.Tensor
    lab: torch.Tensor
    edges: list
    jerk_rms: torch.Tensor
    angular_acc_rms: torch.Tensor
    name: str = "unresolved_motion"
    kind: str = "random"
    omega_dot_edges: list | None = None
    age_error_rms: tuple = (0.0, 0.0)
    w: torch.Tensor | None = None
    angular_jerk_rms: torch.Tensor | None = None
    lever: torch.Tensor | None = None

    def _mask(self) -> torch.Tensor:
        return (self.d != 0).to(self.d.dtype) if self.w is None else self.w.to(self.d.dtype)

    def _s2(self, scales) -> torch.Tensor:
        return torch.as_tensor(scales, dtype=self.d.dtype)[self.lab] ** 2

    def _rot(self, w) -> "_RotTerm | None":
        return None if self.angular_jerk_rms is None else _RotTerm(self.d * w, w, self.lever, centred=True)

    def predicted_variance(self, params=None, ctx=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(acc, gyro) (T, K, 3): s² (d² + e²) per channel (units²), the same on the three axes; with
        the angular jerk, its a² (d² + e²) |c_k|²·⅔ on the accelerometers too."""
        w = self._mask()
        out = []
        for s, e in zip((self.jerk_rms, self.angular_acc_rms), self.age_error_rms):
            s2 = self._s2(s)
            out.append(predicted_variance(self.d, w, s2) + s2[:, None] * float(e) ** 2 * w)
        rot = self._rot(w)
        if rot is not None:
            out[0] = out[0] + rot.predicted(self._s2(self.angular_jerk_rms), float(self.age_error_rms[0]) ** 2)
        return out[0][..., None].expand(*self.d.shape, 3), out[1][..., None].expand(*self.d.shape, 3)

    def loglik(self, y_acc, y_gyro, w, v_acc, v_gyro) -> torch.Tensor:
        """Per-sample log density (nats, (T,)) of both sensors' array-frame residuals (T, K, 3)
        with white variances v (T, K) and this term marginalised (:func:`marginal_loglik`)."""
        out = 0.0
        rot = self._rot(w)
        for y, v, s, e, r in ((y_acc, v_acc, self.jerk_rms, self.age_error_rms[0], rot),
                              (y_gyro, v_gyro, self.angular_acc_rms, self.age_error_rms[1], None)):
            s2 = self._s2(s)
            if r is None:
                out = out + marginal_loglik(y, self.d * w, w, v + float(e) ** 2 * s2[:, None] * w, s2)
            else:
                out = out + r.loglik(y, v + float(e) ** 2 * s2[:, None] * w, s2, self._s2(self.angular_jerk_rms),
                                     float(e) ** 2)
        return out

    def band_rms(self, scales=None) -> tuple[list, list]:
        """(jerk m/s³, angular acceleration rad/s²) rms per |ω| band: the scales themselves, or with
        cells the root of their mean square over the band's samples.  ``scales``: other per-cell
        scales (e.g. ``angular_jerk_rms``) instead, returned as a one-element tuple."""
        pair = (self.jerk_rms, self.angular_acc_rms) if scales is None else (scales,)
        if self.omega_dot_edges is None:
            return tuple([float(x) for x in s] for s in pair)
        C = len(self.omega_dot_edges) + 1
        band = self.lab // C
        out = []
        for s in pair:
            s2 = self._s2(s)
            out.append([float(torch.sqrt(s2[band == b].mean())) if bool((band == b).any()) else 0.0
                        for b in range(len(self.edges) + 1)])
        return tuple(out)

    def finding(self, evidence: float) -> dict:
        """The report's finding (:func:`finding`)."""
        j, g = self.band_rms()
        return finding(self.edges, j, g, evidence=evidence)

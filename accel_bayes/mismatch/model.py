"""The augmented array model: nominal [C21] kinematics + effects, and its linear algebra
(DESIGN §2 "extend model → refit → compare").

Model (per sample t, IMU k, sensor frame; the one signal model of :mod:`accel_bayes.physics.models`)::

    y^a_tk = [outputs of effects ∘ R_k f(r_k; ω_t, ω̇_t, s_t)]_acc  + e^a,  e^a ~ N(0, (c^a_k σ^a_k)² I₃)
    y^g_tk = [outputs of effects ∘ R_k ω_t]_gyro                   + e^g,  e^g ~ N(0, (c^g_k σ^g_k)² I₃)

f the rigid-body specific force ([C21] eq. 4a), R_k the nominal orientation (§7.0), σ the noise
stated in the recording and c the noise factors (1 unless a ``noise_level`` effect is in the
model).  Unknowns: the positions r_k relative to the reference IMU (3-mm Gaussian prior around
the design, as :func:`accel_bayes.inference.map.fit_map`), the effect parameters η (weak
Gaussian priors, :attr:`Effect.parameters`), and per-sample motion x_t = [ω_t, ω̇_t, s_t].

This differs from the [C21] MAP in two documented ways, both needed to compare models by a
likelihood ratio: every gyroscope is a measurement of its own (the [C21] "calibrated" gyro
posterior is exactly this with ω_t's individual gyro residuals summed, so an offset on *one*
gyro becomes visible), and φ_t = [ω̇_t; s_t] is *profiled* (maximised per sample) rather than
integrated with a flat prior, so the log-likelihood carries no −(T/2)·log|M(θ)| term (DESIGN §4).

Structure-aware linearisation (:class:`_Model`): IMU k's rows depend on its own position only, so
the normal equations are assembled from per-IMU 3×3 blocks and the dense (T·6K × 3K) position
Jacobian is never formed (a 32-IMU, T = 3000 iteration costs well under a second and a few
hundred MB less).  The nominal part's Jacobians are closed-form; the effect part is
differentiated by forward-mode autodiff (``torch.func.jvp``, batched with ``vmap``) in p + 12
directions (its parameters, the 9 motion coordinates on every sample at once, and the 3 position
axes on every IMU at once — valid because an effect's perturbation of IMU k depends only on IMU
k's own position).  :class:`LinearSystem` keeps that linearisation at an optimum (motion states
eliminated by Schur complement) for leverages, Laplace draws and PSIS-LOO.

Fitting is :mod:`accel_bayes.mismatch.fit`; the data it fits, :mod:`accel_bayes.mismatch.prepared`.
"""
from __future__ import annotations

import copy as _copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch

from ..physics import jacobians as jac
from ..physics.effects import SignalContext, model_outputs
from ..physics.geometry import quat_to_matrix
from ..physics.models import G_matrix, H_matrix, to_array_frame, u_of_omega
from .prepared import Prepared

__all__ = ["LinearSystem", "ModelFit", "LOG2PI"]

LOG2PI = math.log(2 * math.pi)


# ============================================================================ results

@dataclass
class LinearSystem:
    """Gauss–Newton linearisation of a fit at its optimum (whitened residuals, rows ordered
    (sensor, IMU, axis): 3K accelerometer rows, then 3K gyroscope rows; m = 6K per sample).

    r (T, m) residuals; Jx (T, m, 9) ∂r/∂x_t; the global Jacobian is kept *structured*:
    Jr (T, 2, K, 3, 3) ∂r/∂r_k on IMU k's own rows (every other block is zero) and Je (T, 2, K, 3, p)
    ∂r/∂η; the free globals are the positions of ``free`` (IMU labels) then η, n = 3F + p.
    W (T, n, 9) = Jgᵀ Jx per sample; Vinv (T, 9, 9) = (JxᵀJx)⁻¹; Z = Vinv Wᵀ (T, 9, n);
    S (n, n) the reduced information (motion states eliminated, priors included) and Sinv; h (T, m)
    the leverage of the per-sample motion states (diag Jx Vinv Jxᵀ; the globals' leverage,
    ~n/(T·m) per residual, is neglected).
    """

    r: torch.Tensor
    Jx: torch.Tensor
    Jr: torch.Tensor
    Je: torch.Tensor
    free: list
    W: torch.Tensor
    Vinv: torch.Tensor
    Z: torch.Tensor
    S: torch.Tensor
    Sinv: torch.Tensor
    h: torch.Tensor

    @property
    def n(self) -> int:
        return int(self.S.shape[0])

    def jg_tmul(self, e: torch.Tensor, per_sample: bool = False) -> torch.Tensor:
        """Jgᵀ e for e (B, T, m): (B, n), or per sample (B, T, n) with ``per_sample``."""
        B, T, m = e.shape
        K = self.Jr.shape[2]
        e5 = e.reshape(B, T, 2, K, 3)
        if per_sample:
            gr = torch.einsum("btska,tskai->btki", e5, self.Jr)[:, :, self.free].reshape(B, T, -1)
            ge = torch.einsum("btska,tskap->btp", e5, self.Je)
        else:
            gr = torch.einsum("btska,tskai->bki", e5, self.Jr)[:, self.free].reshape(B, -1)
            ge = torch.einsum("btska,tskap->bp", e5, self.Je)
        return torch.cat((gr, ge), -1)

    def jg_mul(self, dg: torch.Tensor) -> torch.Tensor:
        """Jg dg for dg (B, n): (B, T, m)."""
        B = dg.shape[0]
        T, _, K = self.Jr.shape[:3]
        F = len(self.free)
        d_full = dg.new_zeros(B, K, 3)
        if F:
            d_full[:, self.free] = dg[:, :3 * F].reshape(B, F, 3)
        out = torch.einsum("tskai,bki->btska", self.Jr, d_full)
        if self.Je.shape[-1]:
            out = out + torch.einsum("tskap,bp->btska", self.Je, dg[:, 3 * F:])
        return out.reshape(B, T, -1)

    def jg_rows(self, k: int) -> torch.Tensor:
        """The dense rows of IMU k of Jg: (T, 6, n) [acc xyz, gyro xyz]."""
        T = self.Jr.shape[0]
        F = len(self.free)
        out = self.Jr.new_zeros(T, 6, self.n)
        if k in self.free:
            j = self.free.index(k)
            out[:, :, 3 * j:3 * j + 3] = self.Jr[:, :, k].reshape(T, 6, 3)
        if self.Je.shape[-1]:
            out[:, :, 3 * F:] = self.Je[:, :, k].reshape(T, 6, -1)
        return out

    def jx_mul(self, dx: torch.Tensor) -> torch.Tensor:
        """Jx dx for dx (B, T, 9): (B, T, m) — one batched matmul over the samples."""
        return torch.bmm(self.Jx, dx.permute(1, 2, 0)).permute(2, 0, 1)

    def jx_tmul(self, e: torch.Tensor) -> torch.Tensor:
        """Jxᵀ e for e (B, T, m): (B, T, 9)."""
        return torch.bmm(self.Jx.transpose(-1, -2), e.permute(1, 2, 0)).permute(2, 0, 1)

    def project(self, e: torch.Tensor) -> torch.Tensor:
        """Residuals e (B, T, m) after a linear least-squares refit of all nuisance parameters
        (one Gauss–Newton step from the optimum): what a twin recording's residuals would be."""
        B, T, m = e.shape
        n = self.n
        bx = self.jx_tmul(e)  # (B, T, 9)
        Z2 = self.Z.reshape(T * 9, n)
        rhs = self.jg_tmul(e) - bx.reshape(B, T * 9) @ Z2
        dg = rhs @ self.Sinv.T
        dx = torch.bmm(self.Vinv, bx.permute(1, 2, 0)).permute(2, 0, 1) - (dg @ Z2.T).reshape(B, T, 9)
        return e - self.jx_mul(dx) - self.jg_mul(dg)


@dataclass
class ModelFit:
    """One fitted (augmented) model.

    effects : the effects in the model (their ``params`` hold the estimates, ``std`` the Laplace
        standard deviations).  positions (K, 3) m relative to the reference IMU (array frame;
        IMUs without accelerometer keep their design position).  x (T, 9) = [ω, ω̇, s] per sample.
    acc_factor, gyro_factor (K,) noise factors (1 = stated).  loglik : Gaussian log-likelihood
    of every observed output (constants included) at the optimum, noise = stated × factors;
    loglik_t (T,) its per-sample split.  chi2_stated : Σ r²/σ²_stated; chi2 : Σ r²/(c σ)².
    n_obs, n_params, dof = n_obs − n_params.  pred_acc/pred_gyro, res_acc/res_gyro (T, K, 3)
    model outputs and raw residuals (0 where unobserved).  ctx : the signal context at the fit.
    """

    effects: list
    positions: torch.Tensor
    x: torch.Tensor
    acc_factor: torch.Tensor
    gyro_factor: torch.Tensor
    loglik: float
    loglik_t: torch.Tensor
    chi2_stated: float
    chi2: float
    n_obs: int
    n_params: int
    converged: bool
    reason: str
    n_iter: int
    seconds: float
    pred_acc: torch.Tensor
    pred_gyro: torch.Tensor
    res_acc: torch.Tensor
    res_gyro: torch.Tensor
    ctx: SignalContext = field(repr=False)
    lm: object = field(default=None, repr=False)
    _linear: LinearSystem | None = field(default=None, repr=False)
    _prep: Prepared | None = field(default=None, repr=False)

    @property
    def dof(self) -> int:
        return self.n_obs - self.n_params

    @property
    def chi2_per_dof(self) -> float:
        """χ²/dof with the noise stated in the recording."""
        return self.chi2_stated / max(self.dof, 1)

    @property
    def chi2_per_dof_model(self) -> float:
        """χ²/dof with the model's noise (stated × noise factors)."""
        return self.chi2 / max(self.dof, 1)

    @property
    def has_noise_effect(self) -> bool:
        """Whether the model's per-sample variance differs from the stated noise (a
        ``noise_level`` or a random effect such as ``sampling_jitter``)."""
        return any(e.kind in ("noise", "random") for e in self.effects)

    @property
    def effect_names(self) -> list[str]:
        return [e.name for e in self.effects]

    def linear(self) -> LinearSystem:
        """The :class:`LinearSystem` at the optimum (computed once, cached)."""
        if self._linear is None:
            self._linear = _linear_system(self._prep, self)
        return self._linear

    def drop_linear(self) -> None:
        self._linear = None
        self.__dict__.pop("_noise_projection", None)  # accel_bayes.mismatch.jitter's cache

    def summary(self) -> dict:
        return {"effects": [e.label() for e in self.effects], "loglik": self.loglik,
                "chi2_per_dof": self.chi2_per_dof, "chi2_per_dof_model_noise": self.chi2_per_dof_model,
                "dof": self.dof, "n_obs": self.n_obs, "converged": self.converged, "reason": self.reason,
                "seconds": self.seconds}


# ============================================================================ model pieces

def _positions(theta: torch.Tensor, prep: Prepared, base: torch.Tensor) -> torch.Tensor:
    """Full (K, 3) positions: the free rows from θ (F, 3), the others from ``base``
    (a selection matmul rather than an indexed write, so vmap/jvp can batch it)."""
    free = prep.free_imus
    if not free:
        return base
    P = torch.zeros(prep.K, len(free), dtype=base.dtype)
    P[torch.as_tensor(free), torch.arange(len(free))] = 1.0
    keep = 1.0 - P.sum(1, keepdim=True)
    return base * keep + P @ theta


def _mean_effects(effects):
    return [e for e in effects if e.kind in ("mean", "clip")]


def _split_eta(effects, eta):
    out, i = [], 0
    for e in effects:
        out.append(e.unflatten(eta[i:i + e.df]))
        i += e.df
    return out


class _Model:
    """Residuals, cost and structured Gauss–Newton blocks of the augmented model (module
    docstring).  Globals: θ (F, 3) positions of the free IMUs, η (p,) effect parameters;
    locals x (T, 9)."""

    def __init__(self, prep: Prepared, effects, acc_factor, gyro_factor, base_positions, prior_std, var_ratio=None,
                 offset=None):
        self.prep = prep
        # ``offset`` (T, 2, K, 3), sensor units: the random effects' conditional mean given the data
        # (E[δ_t | r]·rate), taken off the outputs so that the mean fit is the GLS one
        # (accel_bayes.mismatch.jitter.random_offsets); the residuals of the fit
        # (ModelFit.res_acc/res_gyro, the evidence) stay those of the recorded outputs
        self.y_acc = prep.y_acc if offset is None else prep.y_acc - offset[:, 0] * prep.m_acc
        self.y_gyro = prep.y_gyro if offset is None else prep.y_gyro - offset[:, 1] * prep.m_gyro
        self.effects = _mean_effects(effects)
        # effects act on few IMUs: evaluate them on the sub-context of the IMUs they touch
        # (IMU-separability), with their IMU labels re-indexed into it
        if any(e.imu is None for e in self.effects):
            self.touched = list(range(prep.K))
        else:
            self.touched = sorted({int(e.imu) for e in self.effects})
        self.sub_effects = []
        for e in self.effects:
            e2 = _copy.copy(e)
            if e.imu is not None:
                e2.imu = self.touched.index(int(e.imu))
            self.sub_effects.append(e2)
        self.tidx = torch.as_tensor(self.touched, dtype=torch.long)
        self.p = sum(e.df for e in self.effects)
        K, T = prep.K, prep.T
        self.R = quat_to_matrix(prep.q)  # (K, 3, 3)
        self.wa = prep.m_acc / (prep.sigma_acc * acc_factor)[None, :, None]
        self.wg = prep.m_gyro / (prep.sigma_gyro * gyro_factor)[None, :, None]
        self.var_ratio = var_ratio
        if var_ratio is not None:
            # random effects (sampling_jitter): per-sample weights 1/(noise + predicted random
            # variance), the IRLS re-weighting of the mean (accel_bayes.mismatch.jitter)
            self.wa = self.wa / torch.sqrt(var_ratio[:, 0])
            self.wg = self.wg / torch.sqrt(var_ratio[:, 1])
        self.base = base_positions
        self.free = prep.free_imus
        self.F = len(self.free)
        self.K, self.T = K, T
        self.mu = prep.nominal[torch.as_tensor(self.free)] if self.free else prep.nominal.new_zeros(0, 3)
        self.prior_std = float(prior_std)
        sc = torch.cat([e.prior_scales() for e in self.effects]) if self.effects else torch.zeros(0, dtype=torch.float64)
        self.eta_info = torch.where(torch.isfinite(sc), 1.0 / sc ** 2, torch.zeros_like(sc))

    @property
    def n(self) -> int:
        return 3 * self.F + self.p

    def ctx(self, pos, x):
        p = self.prep
        return SignalContext.from_motion(pos, p.q, x[:, 0:3], x[:, 3:6], x[:, 6:9], p.time, p.acc_rate, p.gyro_rate)

    def sub_ctx(self, ctx, acc=None, gyro=None, omega=None, omega_dot=None, s=None, positions=None):
        """The context restricted to the touched IMUs (fields may be replaced, e.g. by duals)."""
        t = self.tidx
        pick = lambda v: None if v is None else v[:, t]  # noqa: E731
        return SignalContext(ctx.time, ctx.omega if omega is None else omega,
                             ctx.omega_dot if omega_dot is None else omega_dot, ctx.s if s is None else s,
                             ctx.positions[t] if positions is None else positions, ctx.orientations[t],
                             ctx.acc[:, t] if acc is None else acc, ctx.gyro[:, t] if gyro is None else gyro,
                             pick(ctx.acc_rate), pick(ctx.gyro_rate))

    def outputs(self, theta, eta, x):
        pos = _positions(theta, self.prep, self.base)
        ctx = self.ctx(pos, x)
        if self.effects:
            a, g = model_outputs(self.sub_effects, self.sub_ctx(ctx), _split_eta(self.effects, eta))
            acc = ctx.acc.index_copy(1, self.tidx, a)
            gyro = ctx.gyro.index_copy(1, self.tidx, g)
        else:
            acc, gyro = ctx.acc, ctx.gyro
        return acc, gyro, ctx

    def residual(self, theta, eta, x) -> torch.Tensor:
        """Whitened residuals (T, 2, K, 3)."""
        acc, gyro, _ = self.outputs(theta, eta, x)
        return torch.stack(((self.y_acc - acc) * self.wa, (self.y_gyro - gyro) * self.wg), 1)

    def prior_cost(self, theta, eta) -> float:
        c = 0.5 * float((((theta - self.mu) / self.prior_std) ** 2).sum()) if self.F else 0.0
        if self.p:
            c += 0.5 * float((self.eta_info * eta ** 2).sum())
        return c

    def cost(self, theta, eta, x) -> float:
        with torch.no_grad():
            return 0.5 * float((self.residual(theta, eta, x) ** 2).sum()) + self.prior_cost(theta, eta)

    def jacobians(self, theta, eta, x):
        """(r (T,2,K,3), Jx (T,2,K,3,9), Jr (T,2,K,3,3), Je (T,2,K,3,p)): derivatives of the
        whitened residuals.  The nominal part in closed form; the effect part by forward-mode
        autodiff of the effects *given the signal context*, with the context's tangents taken
        from the closed-form nominal derivatives (p + 12 directions batched by vmap) — the
        kinematics are never pushed through the autodiff.  The sensor-major layout of
        :class:`LinearSystem`; :meth:`_blocks` gives the same numbers IMU-major."""
        T, K = self.T, self.K
        return tuple(A.reshape(T, K, 2, 3, *A.shape[3:]).transpose(1, 2).contiguous()
                     for A in self._blocks(theta, eta, x))

    def _blocks(self, theta, eta, x):
        """IMU-major (rows [acc xyz, gyro xyz] of IMU k contiguous) whitened residuals r (T, K, 6)
        and Jacobians Jx (T, K, 6, 9), Jr (T, K, 6, 3), Je (T, K, 6, p) (:meth:`jacobians`).  The
        normal equations are sums of per-IMU blocks, so :meth:`linearize` works in this layout:
        no permuted copies of the (T, K, 6, 9) Jacobian per iteration."""
        prep, K, T = self.prep, self.K, self.T
        pos = _positions(theta, prep, self.base)
        w, wd = x[:, 0:3], x[:, 3:6]
        R = self.R
        eye = torch.eye(3, dtype=x.dtype)
        # nominal kinematics, array frame: f = Ω(ω)²r + Ω(ω̇)r + s ([C21] eq. 4a)
        JxA = _rot(R, jac.df_dmotion(pos, w))  # (T, K, 3, 9) ∂f/∂[ω, ω̇, s], sensor frame
        # ∂f/∂r is the same matrix for every IMU: rotate the (T, 3, 3) once per IMU
        JrA = torch.einsum("kij,tjc->tkic", R, jac.df_dr(w, wd))  # (T, K, 3, 3)
        JxG, JrG = self._gyro_nominal(x.dtype)
        Je = torch.zeros(T, 2, K, 3, self.p, dtype=x.dtype)
        acc, gyro, ctx = self.outputs(theta, eta, x)
        if self.effects:
            sub_effects, effects = self.sub_effects, self.effects
            t = self.tidx
            nt = len(self.touched)

            def delta(eta_, acc_, gyro_, om_, omd_, s_, pos_):
                c = self.sub_ctx(ctx, acc_, gyro_, om_, omd_, s_, pos_)
                a_, g_ = model_outputs(sub_effects, c, _split_eta(effects, eta_))
                return torch.stack((a_ - acc_, g_ - gyro_), 1)  # (T, 2, nt, 3)

            p = self.p
            D = p + 9 + 3
            t_eta = torch.zeros(D, p, dtype=x.dtype)
            t_eta[torch.arange(p), torch.arange(p)] = 1.0
            JxAt, JrAt, JxGt = JxA[:, t], JrA[:, t], JxG[:, t]
            t_acc = torch.cat((x.new_zeros(p, T, nt, 3), JxAt.permute(3, 0, 1, 2), JrAt.permute(3, 0, 1, 2)), 0)
            t_gyro = torch.cat((x.new_zeros(p, T, nt, 3), JxGt.permute(3, 0, 1, 2), x.new_zeros(3, T, nt, 3)), 0)
            unit = eye[:, None, :].expand(3, T, 3)
            zz = x.new_zeros(3, T, 3)
            t_om = torch.cat((x.new_zeros(p, T, 3), unit, zz, zz, zz), 0)
            t_omd = torch.cat((x.new_zeros(p, T, 3), zz, unit, zz, zz), 0)
            t_s = torch.cat((x.new_zeros(p, T, 3), zz, zz, unit, zz), 0)
            t_pos = torch.cat((x.new_zeros(p + 9, nt, 3), eye[:, None, :].expand(3, nt, 3)), 0)
            primals = (eta, ctx.acc[:, t], ctx.gyro[:, t], ctx.omega, ctx.omega_dot, ctx.s, ctx.positions[t])
            cols = torch.func.vmap(lambda *tg: torch.func.jvp(delta, primals, tg)[1])(
                t_eta, t_acc, t_gyro, t_om, t_omd, t_s, t_pos)
            cols = cols.permute(1, 2, 3, 4, 0)  # (T, 2, nt, 3, D)
            Je = x.new_zeros(T, 2, K, 3, p)
            Je[:, :, t] = cols[..., :p]
            JxA = JxA.index_add(1, t, cols[:, 0, ..., p:p + 9])
            JxG = JxG.index_add(1, t, cols[:, 1, ..., p:p + 9])
            # IMU-separable effects: column a = ∂Δ_k/∂r_k,a
            JrA = JrA.index_add(1, t, cols[:, 0, ..., p + 9:])
            JrG = JrG.index_add(1, t, cols[:, 1, ..., p + 9:])
        # whitened, with the residual's minus sign folded into the weights (exact)
        wa, wg = -self.wa.unsqueeze(-1), -self.wg.unsqueeze(-1)
        r = torch.cat(((self.y_acc - acc) * self.wa, (self.y_gyro - gyro) * self.wg), 2)
        Jx = torch.cat((wa * JxA, wg * JxG), 2)
        Jr = torch.cat((wa * JrA, wg * JrG), 2)
        Je = torch.cat((wa * Je[:, 0], wg * Je[:, 1]), 2) if self.p else x.new_zeros(T, K, 6, 0)
        return r.detach(), Jx.detach(), Jr.detach(), Je.detach()

    def _gyro_nominal(self, dtype):
        """The gyroscopes' nominal Jacobians, constant: ∂(R_k ω)/∂[ω, ω̇, s] = [R_k, 0, 0] (T, K, 3, 9)
        and ∂/∂r_k = 0 (T, K, 3, 3), built once per model (read-only: the effect part is added
        out of place)."""
        if getattr(self, "_gyro_nom", None) is None:
            T, K, R = self.T, self.K, self.R
            self._gyro_nom = (torch.cat((R.expand(T, K, 3, 3), torch.zeros(T, K, 3, 6, dtype=dtype)), -1),
                              torch.zeros(T, K, 3, 3, dtype=dtype))
        return self._gyro_nom

    def linearize(self, theta, eta, x):
        """Normal-equation blocks (U, W, V, b_g, b_x) with the structure of the module docstring
        (per-IMU blocks contracted by batched matmuls, in the IMU-major layout of :meth:`_blocks`);
        r, Jx, Jr, Je are returned in the sensor-major layout of :meth:`jacobians` (views)."""
        r, Jx, Jr, Je = self._blocks(theta, eta, x)  # (T, K, 6[, ·])
        T, F, p, K = self.T, self.F, self.p, self.K
        fr = self.free
        m = 6 * K
        Jxf = Jx.reshape(T, m, 9)
        rf = r.reshape(T, m)
        V = Jxf.transpose(-1, -2) @ Jxf
        b_x = -(Jxf.transpose(-1, -2) @ rf.unsqueeze(-1)).squeeze(-1)
        n = self.n
        U = r.new_zeros(n, n)
        b_g = r.new_zeros(n)
        JrT = Jr.transpose(-1, -2)  # (T, K, 3, 6)
        # every IMU's block, then the free ones (cheaper than gathering the (T, F, 6, 9) rows first)
        Wr = (JrT @ Jx)[:, fr].reshape(T, 3 * F, 9)
        if F:
            Urr = (JrT @ Jr).sum(0)[fr]  # (F, 3, 3)
            U[:3 * F, :3 * F] = torch.block_diag(*Urr.unbind(0)) + torch.eye(3 * F, dtype=r.dtype) / self.prior_std ** 2
            b_g[:3 * F] = -(JrT @ r.unsqueeze(-1)).sum(0)[fr].reshape(-1) \
                - ((theta - self.mu) / self.prior_std ** 2).reshape(-1)
        W = Wr
        if p:
            Jef = Je.reshape(T, m, p)
            Ure = (JrT @ Je).sum(0)[fr].reshape(3 * F, p)
            U[:3 * F, 3 * F:] = Ure
            U[3 * F:, :3 * F] = Ure.T
            Jflat = Jef.reshape(T * m, p)
            U[3 * F:, 3 * F:] = Jflat.T @ Jflat + torch.diag(self.eta_info)
            b_g[3 * F:] = -(Jflat.T @ rf.reshape(-1)) - self.eta_info * eta
            W = torch.cat((Wr, Jef.transpose(-1, -2) @ Jxf), 1)
        cost = 0.5 * float((r ** 2).sum()) + self.prior_cost(theta, eta)
        sm = lambda A: A.reshape(T, K, 2, 3, *A.shape[3:]).transpose(1, 2)  # noqa: E731  sensor-major view
        return {"cost": cost, "r": sm(r), "Jx": sm(Jx), "Jr": sm(Jr), "Je": sm(Je), "U": 0.5 * (U + U.T), "W": W,
                "V": V, "b_g": b_g, "b_x": b_x}


def _rot(R: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """R_k M_tk for R (K, 3, 3) and M (T, K, 3, c): einsum batches it over the K IMUs, K products
    (3 × 3)(3 × T·c) — 5× faster than the elementwise broadcast-and-sum, which wrote a
    (T, K, 3, 3, c) intermediate, and far faster than T·K tiny matmuls."""
    return torch.einsum("kij,tkjc->tkic", R, M)


def _init_locals(prep: Prepared, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
    """x_t = [ω_t, φ̂_t] with φ̂_t = [ω̇; s] the weighted least-squares fit of the accelerometers
    given ω_t ([C21] eq. 5 linear in φ)."""
    ka = np.flatnonzero(prep.has_acc)
    r = positions[ka]
    q = prep.q[ka]
    y = to_array_frame(prep.y_acc[:, ka], q).reshape(prep.T, -1)  # (T, 3A)
    w2 = (1.0 / prep.sigma_acc[ka] ** 2).repeat_interleave(3)
    H = H_matrix(r)
    G = G_matrix(r)
    M = H.T @ (w2[:, None] * H)
    rhs = (y - u_of_omega(omega) @ G.T) * w2
    phi = torch.linalg.solve(M, (rhs @ H).T).T
    return torch.cat((omega, phi), -1)


def _gyro_mean(prep: Prepared) -> torch.Tensor:
    """Inverse-variance weighted mean of the gyros, array frame (T, 3)."""
    g = to_array_frame(prep.y_gyro, prep.q)  # (T, K, 3)
    w = prep.m_gyro / prep.sigma_gyro[None, :, None] ** 2
    return (g * w).sum(1) / w.sum(1).clamp_min(1e-300)



# ============================================================================ log-likelihood

def _loglik_terms(prep: Prepared, res_acc, res_gyro, fa, fg):
    sa = (prep.sigma_acc * fa)[None, :, None]
    sg = (prep.sigma_gyro * fg)[None, :, None]
    za = res_acc / sa * prep.m_acc
    zg = res_gyro / sg * prep.m_gyro
    quad_t = (za ** 2).sum((1, 2)) + (zg ** 2).sum((1, 2))
    logdet_t = (prep.m_acc * torch.log(sa)).sum((1, 2)) + (prep.m_gyro * torch.log(sg)).sum((1, 2))
    nobs_t = prep.m_acc.sum((1, 2)) + prep.m_gyro.sum((1, 2))
    ll_t = -0.5 * quad_t - logdet_t - 0.5 * nobs_t * LOG2PI
    return ll_t, float(quad_t.sum())


def _detach_ctx(ctx: SignalContext) -> SignalContext:
    d = lambda t: None if t is None else t.detach()  # noqa: E731
    return SignalContext(d(ctx.time), d(ctx.omega), d(ctx.omega_dot), d(ctx.s), d(ctx.positions),
                         d(ctx.orientations), d(ctx.acc), d(ctx.gyro), d(ctx.acc_rate), d(ctx.gyro_rate))


def project_off_states(Jx: torch.Tensor, Vinv: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
    """P_t X_t = X_t − Jx_t (Jx_tᵀJx_t)⁻¹ Jx_tᵀ X_t per sample: what the per-sample motion states
    leave of X (T, m) or (T, m, d), with Jx (T, m, 9) and Vinv = (JxᵀJx)⁻¹ (T, 9, 9) of the same
    whitening (the fit's :class:`LinearSystem`, or its noise-whitened twin in
    :mod:`accel_bayes.mismatch.jitter`)."""
    vec = X.dim() == 2
    Y = X.unsqueeze(-1) if vec else X
    out = Y - Jx @ (Vinv @ (Jx.transpose(-1, -2) @ Y))
    return out.squeeze(-1) if vec else out


def _local_leverage(Jx: torch.Tensor) -> torch.Tensor:
    V = Jx.transpose(-1, -2) @ Jx
    L = torch.linalg.cholesky(V)
    Y = torch.linalg.solve_triangular(L, Jx.transpose(-1, -2), upper=False)  # (T, 9, m)
    return (Y * Y).sum(-2)


def _linear_system(prep: Prepared, fit: ModelFit) -> LinearSystem:
    lm = fit.lm
    model = lm.model
    lin = model.linearize(lm.theta, lm.eta, lm.x)
    T, K = prep.T, prep.K
    Jx = lin["Jx"].reshape(T, 6 * K, 9)
    V = lin["V"]
    L = torch.linalg.cholesky(V)
    Vinv = torch.cholesky_solve(torch.eye(9, dtype=V.dtype).expand_as(V), L)
    W = lin["W"]  # (T, n, 9)
    Z = Vinv @ W.transpose(-1, -2)  # (T, 9, n)
    S = lin["U"] - torch.einsum("tnd,tdm->nm", W, Z)
    S = 0.5 * (S + S.T)
    Sinv = torch.linalg.inv(S) if S.shape[0] else S
    h = _local_leverage(Jx)
    return LinearSystem(r=lin["r"].reshape(T, 6 * K), Jx=Jx, Jr=lin["Jr"].contiguous(), Je=lin["Je"].contiguous(),
                        free=list(model.free), W=W,
                        Vinv=Vinv, Z=Z, S=S, Sinv=0.5 * (Sinv + Sinv.T), h=h)

"""The augmented array model: nominal [C21] kinematics + effects, fitted jointly with the
geometry and the motion (DESIGN §2 "extend model → refit → compare").

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
The baseline starts from the package's MAP (:func:`accel_bayes.inference.map.fit_map_recording`,
calibrated gyros) and is re-optimised under this objective, so "with" and "without" an effect are
always two optima of the same function.

Solver: Levenberg–Marquardt built from the package's LM pieces — Nielsen damping with Marquardt
scaling (:mod:`accel_bayes.inference.lm.damping`), the Schur-complement solver that eliminates the
per-sample motion states (:class:`accel_bayes.inference.lm.linear.SchurComplementSolver`, cost linear
in T) and the stopping rules of :class:`accel_bayes.inference.lm.StoppingRule` — driven by a
structure-aware linearisation: IMU k's rows depend on its own position only, so the normal
equations are assembled from per-IMU 3×3 blocks and the dense (T·6K × 3K) position Jacobian that
the generic :class:`~accel_bayes.inference.lm.Problem` interface needs is never formed (a 32-IMU,
T = 3000 iteration costs well under a second and a few hundred MB less).  The nominal part's
Jacobians are closed-form; the effect part is differentiated by forward-mode autodiff
(``torch.func.jvp``, batched with ``vmap``) in p + 12 directions (its parameters, the 9 motion
coordinates on every sample at once, and the 3 position axes on every IMU at once — valid
because an effect's perturbation of IMU k depends only on IMU k's own position).

Noise factors (``noise_level``) are not in the least-squares problem: after each fit they are
re-estimated in closed form, c² = mean of z² = r²/(σ²(1 − h)) over the IMU's (or all IMUs')
residuals of that sensor, with h the leverage of the per-sample motion states (REML-like: the
leverage correction keeps E[z²] = 1 under the stated noise), and the fit repeated (≤ 5 rounds).

Comparison (:func:`compare_fits`): χ²/dof with the stated noise (or the refined noise when a
noise_level effect is in the model, and it says so), log-likelihood, ELPD by PSIS-LOO over time
samples (:func:`elpd_loo`: pointwise log-likelihood at Laplace draws of the globals, with each
sample's motion state re-profiled through the local linearisation; ArviZ ``az.loo`` /
``az.compare``) and the geometry before/after.  ``posterior=True`` additionally runs
:func:`accel_bayes.calibrate.calibrate` on the recording before and after correction
(:func:`corrected_recording`).

Held-out transfer (:func:`heldout_fit`): effects estimated on one recording, their parameters
held fixed, added to the nominal model of another recording; both models re-fit the positions
and the motion, so their log-likelihoods compare directly (the real-data check of
``experiments/mimu_mismatch.py``).
"""
from __future__ import annotations

import copy as _copy
import math
import time as _time
import warnings
from dataclasses import dataclass, field

import numpy as np
import torch

from ..constants import DEFAULT_PRIOR_STD
from ..errors import UserError
from ..physics.geometry import quat_to_matrix
from ..inference.lm import LevenbergMarquardt, Linearization, StoppingRule
from ..physics.models import G_matrix, H_matrix, to_array_frame, u_of_omega
from ..physics import jacobians as jac
from ..physics.effects import CandidateLayout, SignalContext, model_outputs, noise_factors, output_rates

__all__ = [
    "Prepared",
    "ModelFit",
    "LinearSystem",
    "prepare",
    "fit_model",
    "baseline_fit",
    "compare_fits",
    "elpd_loo",
    "corrected_recording",
    "heldout_fit",
    "DEFAULT_PRIOR_STD",
]

LOG2PI = math.log(2 * math.pi)


# ============================================================================ data

@dataclass
class Prepared:
    """A recording in the form the fits use (torch, float64, sensor frame).

    y_acc, y_gyro (T, K, 3) outputs with NaN → 0; m_acc, m_gyro (T, K, 3) 1.0 where observed;
    sigma_acc, sigma_gyro (K,) stated noise; q (K, 4) nominal orientations; nominal (K, 3)
    design positions relative to the reference IMU ``ref``; has_acc/has_gyro (K,) bool;
    acc_rate/gyro_rate (T, K, 3) d/dt of the fitted nominal outputs (set after the baseline fit,
    used by time_offset).
    """

    rec: object
    time: torch.Tensor
    y_acc: torch.Tensor
    y_gyro: torch.Tensor
    m_acc: torch.Tensor
    m_gyro: torch.Tensor
    sigma_acc: torch.Tensor
    sigma_gyro: torch.Tensor
    q: torch.Tensor
    nominal: torch.Tensor
    ref: int
    has_acc: np.ndarray
    has_gyro: np.ndarray
    acc_rate: torch.Tensor | None = None
    gyro_rate: torch.Tensor | None = None
    n_dropped_clipped: int = 0

    @property
    def T(self) -> int:
        return int(self.y_acc.shape[0])

    @property
    def K(self) -> int:
        return int(self.y_acc.shape[1])

    @property
    def layout(self) -> CandidateLayout:
        return CandidateLayout(self.K, self.has_acc, self.has_gyro, self.ref)

    @property
    def free_imus(self) -> list[int]:
        """IMUs whose position is estimated: accelerometer IMUs except the reference."""
        return [k for k in range(self.K) if self.has_acc[k] and k != self.ref]

    @property
    def n_obs(self) -> int:
        return int(self.m_acc.sum() + self.m_gyro.sum())


def prepare(rec, *, drop_clipped: bool = True) -> Prepared:
    """Check a :class:`~accel_bayes.data.recording.Recording` for mismatch analysis and convert it.

    drop_clipped : drop the samples the recording flags as clipped
        (:func:`accel_bayes.prep.selection.select_samples`, reason ``clipped``), as
        :func:`accel_bayes.prep.preprocess.preprocess` does for the calibration.  A flagged output sits
        at the range while the true one is beyond it: its Gaussian residual would be a censored
        quantity treated as a measurement, the per-sample motion fitted to it is biased (every
        IMU sees the same ω, so all gyros clip together and ω is pulled to the range), and the
        resulting structured residuals get absorbed by whichever candidate effect fits them
        best.  Clipping the recording does *not* flag (an unstated range) stays in and is what
        the ``saturation`` effect explains.  The kept recording is ``Prepared.rec``; the number
        dropped is ``Prepared.n_dropped_clipped``.
    """
    if rec.gyro is None or not np.asarray(rec.has_gyro).any():
        raise UserError("gyro: mismatch detection needs gyroscope data (the motion is estimated from the gyros)")
    n_drop = 0
    if drop_clipped:
        from ..prep.selection import clipped_mask

        clip = clipped_mask(rec)
        n_drop = int(clip.sum())
        if n_drop:
            if n_drop > len(clip) - 10:
                raise UserError(f"acc_clipped/gyro_clipped: {n_drop} of {len(clip)} samples are flagged as clipped; "
                                "too few unclipped samples remain for mismatch detection")
            rec = rec.select(~clip)
    has_acc = np.asarray(rec.has_acc, bool)
    has_gyro = np.asarray(rec.has_gyro, bool)
    if has_acc.sum() < 3:
        raise UserError(f"acc: at least 3 IMUs with accelerometer data are needed, got {int(has_acc.sum())}")
    ref = int(rec.reference_imu)
    if not has_acc[ref]:
        raise UserError(f"reference_imu: IMU {ref} has no accelerometer data")
    f = lambda x: torch.as_tensor(np.asarray(x, dtype=np.float64))  # noqa: E731
    acc, gyro = f(rec.acc), f(rec.gyro)
    m_acc = torch.isfinite(acc).double() * f(has_acc)[None, :, None]
    m_gyro = torch.isfinite(gyro).double() * f(has_gyro)[None, :, None]
    nominal = f(rec.nominal_position)
    nominal = nominal - nominal[ref]
    from ..physics.arrays import check_triad_geometry

    try:
        check_triad_geometry(nominal[torch.as_tensor(has_acc)], labels=np.flatnonzero(has_acc).tolist())
    except ValueError as exc:
        raise UserError(f"nominal_position: {exc}") from None
    sa, sg = f(rec.acc_noise_std), f(rec.gyro_noise_std)
    if bool((sa[torch.as_tensor(has_acc)] <= 0).any()) or bool((sg[torch.as_tensor(has_gyro)] <= 0).any()):
        raise UserError("acc_noise_std/gyro_noise_std: expected > 0 for every IMU with data")
    sa = torch.where(sa > 0, sa, torch.ones_like(sa))
    sg = torch.where(sg > 0, sg, torch.ones_like(sg))
    return Prepared(rec=rec, time=f(rec.time), y_acc=torch.nan_to_num(acc), y_gyro=torch.nan_to_num(gyro),
                    m_acc=m_acc, m_gyro=m_gyro, sigma_acc=sa, sigma_gyro=sg, q=f(rec.nominal_orientation),
                    nominal=nominal, ref=ref, has_acc=has_acc, has_gyro=has_gyro, n_dropped_clipped=n_drop)


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
        return any(e.kind == "noise" for e in self.effects)

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

    def __init__(self, prep: Prepared, effects, acc_factor, gyro_factor, base_positions, prior_std):
        self.prep = prep
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
        return torch.stack(((self.prep.y_acc - acc) * self.wa, (self.prep.y_gyro - gyro) * self.wg), 1)

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
        kinematics are never pushed through the autodiff."""
        prep, K, T = self.prep, self.K, self.T
        pos = _positions(theta, prep, self.base)
        w, wd = x[:, 0:3], x[:, 3:6]
        R = self.R
        eye = torch.eye(3, dtype=x.dtype)
        # nominal kinematics, array frame: f = Ω(ω)²r + Ω(ω̇)r + s ([C21] eq. 4a)
        JxA = _rot(R, jac.df_dmotion(pos, w))  # (T, K, 3, 9) ∂f/∂[ω, ω̇, s], sensor frame
        JrA = _rot(R, jac.df_dr(w, wd)[:, None].expand(T, K, 3, 3))  # (T, K, 3, 3)
        JxG = torch.cat((R.expand(T, K, 3, 3), torch.zeros(T, K, 3, 6, dtype=x.dtype)), -1)
        JrG = torch.zeros(T, K, 3, 3, dtype=x.dtype)
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
        wa, wg = self.wa.unsqueeze(-1), self.wg.unsqueeze(-1)
        r = torch.stack(((prep.y_acc - acc) * self.wa, (prep.y_gyro - gyro) * self.wg), 1)
        Jx = -torch.stack((wa * JxA, wg * JxG), 1)
        Jr = -torch.stack((wa * JrA, wg * JrG), 1)
        Je = -torch.stack((wa * Je[:, 0], wg * Je[:, 1]), 1) if self.p else Je
        return r.detach(), Jx.detach(), Jr.detach(), Je.detach()

    def linearize(self, theta, eta, x):
        """Normal-equation blocks (U, W, V, b_g, b_x) with the structure of the module docstring
        (per-IMU blocks contracted by batched matmuls)."""
        r, Jx, Jr, Je = self.jacobians(theta, eta, x)
        T, F, p, K = self.T, self.F, self.p, self.K
        fr = self.free
        m = 6 * K
        Jxf = Jx.reshape(T, m, 9)
        rf = r.reshape(T, m)
        V = Jxf.transpose(-1, -2) @ Jxf
        b_x = -(Jxf.transpose(-1, -2) @ rf.unsqueeze(-1)).squeeze(-1)
        # per-IMU views (T, K, 6, ·): rows [acc xyz, gyro xyz] of IMU k
        Jxk = Jx.permute(0, 2, 1, 3, 4).reshape(T, K, 6, 9)
        Jrk = Jr.permute(0, 2, 1, 3, 4).reshape(T, K, 6, 3)[:, fr]
        rk = r.permute(0, 2, 1, 3).reshape(T, K, 6)[:, fr]
        n = self.n
        U = r.new_zeros(n, n)
        b_g = r.new_zeros(n)
        JrkT = Jrk.transpose(-1, -2)  # (T, F, 3, 6)
        Wr = (JrkT @ Jxk[:, fr]).reshape(T, 3 * F, 9)
        if F:
            Urr = (JrkT @ Jrk).sum(0)  # (F, 3, 3)
            U[:3 * F, :3 * F] = torch.block_diag(*Urr.unbind(0)) + torch.eye(3 * F, dtype=r.dtype) / self.prior_std ** 2
            b_g[:3 * F] = -(JrkT @ rk.unsqueeze(-1)).sum(0).reshape(-1) \
                - ((theta - self.mu) / self.prior_std ** 2).reshape(-1)
        W = Wr
        if p:
            Jef = Je.reshape(T, m, p)
            Jek = Je.permute(0, 2, 1, 3, 4).reshape(T, K, 6, p)[:, fr]
            Ure = (JrkT @ Jek).sum(0).reshape(3 * F, p)
            U[:3 * F, 3 * F:] = Ure
            U[3 * F:, :3 * F] = Ure.T
            Jflat = Jef.reshape(T * m, p)
            U[3 * F:, 3 * F:] = Jflat.T @ Jflat + torch.diag(self.eta_info)
            b_g[3 * F:] = -(Jflat.T @ rf.reshape(-1)) - self.eta_info * eta
            W = torch.cat((Wr, Jef.transpose(-1, -2) @ Jxf), 1)
        cost = 0.5 * float((r ** 2).sum()) + self.prior_cost(theta, eta)
        return {"cost": cost, "r": r, "Jx": Jx, "Jr": Jr, "Je": Je, "U": 0.5 * (U + U.T), "W": W, "V": V,
                "b_g": b_g, "b_x": b_x}


def _rot(R: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """R_k M_tk for R (K, 3, 3) and M (T, K, 3, c), elementwise (much faster than a broadcast
    matmul of T·K tiny matrices)."""
    return (R[None, :, :, :, None] * M[:, :, None, :, :]).sum(-2)


@dataclass
class _LMOut:
    theta: torch.Tensor
    eta: torch.Tensor
    x: torch.Tensor
    cost: float
    converged: bool
    reason: str
    n_iter: int
    log: list
    model: _Model = field(repr=False)


class _ModelProblem:
    """:class:`_Model` through the problem protocol of the package's structured LM
    (:class:`~accel_bayes.inference.lm.LevenbergMarquardt`): globals {"theta" (F, 3), "eta"
    (p,)}, both Euclidean; locals x (T, 9), block-diagonal."""

    local_structure = "diagonal"
    x0 = None

    def __init__(self, model: _Model):
        self.model = model
        self.n_free = model.n

    def linearize(self, values, x, *, step: bool = True) -> Linearization:
        lin = self.model.linearize(values["theta"], values["eta"], x)
        return Linearization(lin["cost"], lin["U"], lin["W"], lin["V"], None, lin["b_g"], lin["b_x"])

    def cost(self, values, x) -> float:
        return self.model.cost(values["theta"], values["eta"], x)

    def retract(self, values, delta):
        F, th, eta = self.model.F, values["theta"], values["eta"]
        return {"theta": th + delta[:3 * F].reshape(F, 3) if F else th,
                "eta": eta + delta[3 * F:] if self.model.p else eta}


def _lm_solve(model: _Model, theta, eta, x, *, max_iter: int = 60, ftol: float = 1e-11, xtol: float = 1e-12,
              gtol: float = 1e-12) -> _LMOut:
    """The package's structured Levenberg–Marquardt (Nielsen damping, Marquardt scaling, Schur
    solver, stopping rules: :class:`~accel_bayes.inference.lm.LevenbergMarquardt`) on the
    linearisation of :class:`_Model` (one iteration is O(T·K), no dense position Jacobian)."""
    lm = LevenbergMarquardt(stopping=StoppingRule(max_iter, ftol, xtol, gtol))
    res = lm.solve(_ModelProblem(model), {"theta": theta, "eta": eta}, x)
    return _LMOut(res.values["theta"], res.values["eta"], res.locals, res.cost, res.converged, str(res.reason),
                  res.n_iter, res.log, model)


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


# ============================================================================ fitting

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


def fit_model(prep: Prepared, effects=(), *, init: "ModelFit | None" = None, init_positions=None, init_x=None,
              prior_std: float = DEFAULT_PRIOR_STD, max_iter: int = 60, noise_rounds: int = 5,
              laplace: bool = True, progress: bool = False) -> ModelFit:
    """Fit the augmented model (module docstring) with ``effects`` (their current ``params`` are
    the starting values; estimates are written back into them, with Laplace ``std``).

    init : a previous :class:`ModelFit` to start from (positions, motion, shared effects'
        values); else ``init_positions`` (K, 3) and ``init_x`` (T, 9), else the design and the
        gyro mean with least-squares [ω̇; s].
    laplace : compute the effect parameters' Laplace standard deviations (one more
        linearisation; detection refits skip it).  ``progress`` is accepted for symmetry with
        the package's fitters; the structured LM prints nothing.
    """
    t0 = _time.perf_counter()
    effects = list(effects)
    for e in effects:
        if e.kind == "finding":
            raise UserError("unexplained: is a finding, not a model effect")
        if e.imu is not None and not 0 <= e.imu < prep.K:
            raise UserError(f"{e.label()}: imu out of range for K={prep.K}")
        if e.needs_rates and prep.acc_rate is None:
            raise UserError(f"{e.label()}: needs output rates; fit the baseline first (baseline_fit sets them)")
    K = prep.K
    if init is not None:
        pos0 = init.positions.clone()
        x0 = init.x.clone()
    else:
        pos0 = prep.nominal.clone() if init_positions is None else torch.as_tensor(init_positions, dtype=torch.float64)
        pos0 = pos0 - pos0[prep.ref]
        x0 = _init_locals(prep, pos0, _gyro_mean(prep)) if init_x is None else torch.as_tensor(init_x, dtype=torch.float64)
    noise_eff = [e for e in effects if e.kind == "noise"]
    fa, fg = noise_factors(noise_eff, K)  # each noise effect starts from its current factor
    mean_eff = _mean_effects(effects)
    eta0 = torch.cat([e.flatten() for e in mean_eff]) if mean_eff else torch.zeros(0, dtype=torch.float64)
    rounds = noise_rounds if noise_eff else 1
    lm = model = None
    free = prep.free_imus

    def solve(pos0, x0, eta0, fa, fg):
        model = _Model(prep, effects, fa, fg, pos0, prior_std)
        th0 = pos0[torch.as_tensor(free)].clone() if free else pos0.new_zeros(0, 3)
        lm = _lm_solve(model, th0, eta0.clone(), x0.clone(), max_iter=max_iter)
        return lm, model, _positions(lm.theta, prep, pos0), lm.x, lm.eta

    for rnd in range(rounds):
        lm, model, pos0, x0, eta0 = solve(pos0, x0, eta0, fa, fg)
        if not noise_eff:
            break
        # closed-form noise factors from leverage-corrected residuals (module docstring)
        z2a, z2g = _z2(prep, model, lm)
        changed = 0.0
        for e in noise_eff:
            z2 = z2a if e.which == "acc" else z2g
            mask = prep.m_acc if e.which == "acc" else prep.m_gyro
            sel = mask.clone()
            if e.imu is not None:
                keep = torch.zeros(K, dtype=torch.float64)
                keep[e.imu] = 1.0
                sel = sel * keep[None, :, None]
            # z2 is in the current model's noise units; take this effect's own factor out, so
            # overlapping noise effects (one IMU and all IMUs) multiply
            f_old = float(e.params["factor"])
            own = z2 * f_old ** 2
            f_new = math.sqrt(float((own * sel).sum() / sel.sum().clamp_min(1)))
            changed = max(changed, abs(f_new - f_old))
            e.set_params({"factor": f_new})
        fa_new, fg_new = noise_factors(noise_eff, K)
        fa, fg = fa_new, fg_new
        if changed < 1e-5:
            break
    if noise_eff and rounds > 1:
        lm, model, pos0, x0, eta0 = solve(pos0, x0, eta0, fa, fg)
    # write back and evaluate
    with torch.no_grad():
        acc, gyro, ctx = model.outputs(lm.theta, lm.eta, lm.x)
        if mean_eff:
            for e, pv in zip(mean_eff, _split_eta(mean_eff, eta0)):
                e.params = {k: v.detach().clone() for k, v in pv.items()}
            # clip effects' derived statistics on the unclipped outputs
            acc_u, gyro_u = model_outputs([e for e in mean_eff if e.kind == "mean"], ctx)
            for e in mean_eff:
                if e.kind == "clip":
                    e.update_stats(acc_u, gyro_u)
    res_acc = (prep.y_acc - acc) * prep.m_acc
    res_gyro = (prep.y_gyro - gyro) * prep.m_gyro
    ll_t, quad = _loglik_terms(prep, res_acc, res_gyro, fa, fg)
    _, quad_stated = _loglik_terms(prep, res_acc, res_gyro, torch.ones(K, dtype=torch.float64),
                                   torch.ones(K, dtype=torch.float64))
    n_params = 9 * prep.T + 3 * len(prep.free_imus) + sum(e.df for e in effects if e.kind != "finding")
    fit = ModelFit(effects=effects, positions=pos0.detach().clone(), x=x0.detach().clone(), acc_factor=fa.clone(),
                   gyro_factor=fg.clone(), loglik=float(ll_t.sum()), loglik_t=ll_t.detach(), chi2_stated=quad_stated,
                   chi2=quad, n_obs=prep.n_obs, n_params=n_params, converged=bool(lm.converged), reason=str(lm.reason),
                   n_iter=int(lm.n_iter), seconds=_time.perf_counter() - t0, pred_acc=acc.detach(),
                   pred_gyro=gyro.detach(), res_acc=res_acc.detach(), res_gyro=res_gyro.detach(),
                   ctx=_detach_ctx(ctx), lm=lm, _prep=prep)
    if mean_eff and laplace:
        _effect_std(fit, mean_eff)
    return fit


def _detach_ctx(ctx: SignalContext) -> SignalContext:
    d = lambda t: None if t is None else t.detach()  # noqa: E731
    return SignalContext(d(ctx.time), d(ctx.omega), d(ctx.omega_dot), d(ctx.s), d(ctx.positions),
                         d(ctx.orientations), d(ctx.acc), d(ctx.gyro), d(ctx.acc_rate), d(ctx.gyro_rate))


def _z2(prep, model: _Model, lm: _LMOut):
    """Leverage-corrected squared standardized residuals (T, K, 3) for acc and gyro at a fit
    (in the fit's own noise units)."""
    r, Jx, _, _ = model.jacobians(lm.theta, lm.eta, lm.x)
    T, K = prep.T, prep.K
    h = _local_leverage(Jx.reshape(T, 6 * K, 9)).reshape(T, 2, K, 3)
    z2 = r ** 2 / (1 - h).clamp_min(1e-3)
    return z2[:, 0], z2[:, 1]


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
    return LinearSystem(r=lin["r"].reshape(T, 6 * K), Jx=Jx, Jr=lin["Jr"], Je=lin["Je"], free=list(model.free), W=W,
                        Vinv=Vinv, Z=Z, S=S, Sinv=0.5 * (Sinv + Sinv.T), h=h)


def _effect_std(fit: ModelFit, mean_eff) -> None:
    """Laplace standard deviations of the effect parameters (Schur-reduced information)."""
    try:
        lin = fit.linear()
        F3 = 3 * len(fit._prep.free_imus)
        var = torch.diagonal(lin.Sinv)[F3:].clamp_min(0)
        i = 0
        for e in mean_eff:
            v = var[i:i + e.df].sqrt()
            e.std = e.unflatten(v)
            i += e.df
    except Exception as exc:  # pragma: no cover - a singular system leaves std unknown
        warnings.warn(f"effect standard deviations unavailable: {exc}", RuntimeWarning, stacklevel=2)


def baseline_fit(prep: Prepared, *, use_map: bool = True, prior_std: float = DEFAULT_PRIOR_STD,
                 progress: bool = False) -> tuple[ModelFit, dict]:
    """The nominal model's fit (no effects) and the output rates for ``time_offset``.

    Starts from the package's MAP (:func:`accel_bayes.inference.map.fit_map_recording` with the
    calibrated gyro posterior, Gauss–Newton Laplace) when ``use_map``; falls back to the design
    and the gyro mean if the MAP is unavailable or diverges (recorded in the returned info).
    Sets ``prep.acc_rate``/``prep.gyro_rate`` from the fitted nominal outputs
    (:func:`accel_bayes.physics.effects.output_rates`).  Returns (fit, info).
    """
    info = {"start": "design"}
    init_pos = init_x = None
    if use_map:
        try:
            from ..inference.map import fit_map_recording

            t0 = _time.perf_counter()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                mres = fit_map_recording(prep.rec, gyro_method="calibrated", prior_std=prior_std,
                                         hessian="gauss_newton", on_divergence="ignore")
            labels = list(mres.imu_labels)
            if mres.converged or not str(mres.reason).startswith("diverged"):
                pos = prep.nominal.clone()
                pos[torch.as_tensor(labels)] = torch.as_tensor(mres.positions, dtype=torch.float64)
                pos = pos - pos[prep.ref]
                idx = getattr(mres, "sample_index", None)
                if idx is None or len(idx) == prep.T:
                    init_pos = pos
                    init_x = _init_locals(prep, pos, torch.as_tensor(mres.omega, dtype=torch.float64))
                    info = {"start": "map", "map_seconds": _time.perf_counter() - t0, "map_reason": str(mres.reason),
                            "map_positions": pos.tolist()}
            if init_pos is None:
                info = {"start": "design", "map_failure": str(mres.reason)}
        except Exception as exc:  # the MAP is a starting point only; the fit below is the result
            info = {"start": "design", "map_failure": f"{type(exc).__name__}: {exc}"}
    fit = fit_model(prep, (), init_positions=init_pos, init_x=init_x, prior_std=prior_std, progress=progress)
    prep.acc_rate, prep.gyro_rate = output_rates(prep.time, fit.ctx.acc, fit.ctx.gyro)
    fit.ctx.acc_rate, fit.ctx.gyro_rate = prep.acc_rate, prep.gyro_rate
    return fit, info


# ============================================================================ comparison

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
    to ``az.compare`` so that PSIS-LOO is not recomputed there."""
    from .report import _arviz

    az = _arviz()
    lin = fit.linear()
    n = lin.n
    g = torch.Generator().manual_seed(int(seed))
    base_t = fit.loglik_t
    if n:
        L = torch.linalg.cholesky(lin.Sinv)
        eps = torch.randn(draws, n, generator=g, dtype=torch.float64)
        dg = eps @ L.T  # (S, n)
        T = lin.r.shape[0]
        Pr = lin.r - (lin.Jx @ (lin.Vinv @ (lin.Jx.transpose(-1, -2) @ lin.r.unsqueeze(-1)))).squeeze(-1)
        a = lin.jg_tmul(Pr.unsqueeze(0), per_sample=True)[0]  # (T, n) = J_tᵀ P_t r_t
        out = []
        for ch in torch.split(dg, 25):
            Zd = (ch @ lin.Z.reshape(T * 9, n).T).reshape(-1, T, 9)
            Jd = lin.jg_mul(ch) - lin.jx_mul(Zd)  # P_t J_t δ
            out.append(base_t[None] - 0.5 * ((Jd * Jd).sum(-1) - 2 * ch @ a.T))
        ll = torch.cat(out, 0)
    else:
        ll = base_t[None].expand(draws, -1)
        dg = None
    post = {"globals": (dg if dg is not None else torch.zeros(draws, 1, dtype=torch.float64)).numpy()[None]}
    idata = az.from_dict(posterior=post, log_likelihood={"y": ll.numpy()[None]}, dims={"y": ["time"]})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        loo = az.loo(idata, pointwise=True)
    k = np.asarray(loo.pareto_k)
    return {"elpd_loo": float(loo.elpd_loo), "se": float(loo.se), "p_loo": float(loo.p_loo),
            "pareto_k_over_0.7": int((k > 0.7).sum()), "draws": int(draws)}, idata, loo


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
            from .report import _arviz

            az = _arviz()
            e0, _, loo0 = _elpd_loo(before, draws=draws, seed=seed)
            e1, _, loo1 = _elpd_loo(after, draws=draws, seed=seed + 1)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                # the pointwise ELPDData, not the InferenceData: az.compare would redo PSIS-LOO
                cmp = az.compare({"baseline": loo0, "refined": loo1}, ic="loo")
            out["elpd_loo"] = {"before": e0, "after": e1, "difference": e1["elpd_loo"] - e0["elpd_loo"],
                               "compare": {str(ix): {"rank": int(row["rank"]), "elpd_diff": float(row["elpd_diff"]),
                                                     "dse": float(row["dse"]), "weight": float(row["weight"])}
                                           for ix, row in cmp.iterrows()}}
        except Exception as exc:  # pragma: no cover - report rather than fail the whole analysis
            out["elpd_loo"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def corrected_recording(rec, fit: ModelFit):
    """A copy of ``rec`` with the fitted mean effects subtracted (outputs − (model with effects −
    nominal model)), samples the fitted saturation clips removed from the noise accounting by
    flagging them in ``acc_clipped``/``gyro_clipped``, and the stated noise multiplied by the
    fitted noise factors.  What the posterior calibration is rerun on (``posterior=True``)."""
    out = rec.copy()
    mean_eff = [e for e in fit.effects if e.kind == "mean"]
    if mean_eff:
        with torch.no_grad():
            ctx = fit.ctx
            acc, gyro = model_outputs(mean_eff, ctx)
            out.acc = np.asarray(rec.acc) - (acc - ctx.acc).numpy()
            if rec.gyro is not None:
                out.gyro = np.asarray(rec.gyro) - (gyro - ctx.gyro).numpy()
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


def posterior_comparison(rec, fit: ModelFit, *, seed: int = 0, chains: int = 2, draws: int = 400,
                         warmup: int = 400, progress: bool = False) -> dict:
    """PmMH posterior of the positions (:func:`accel_bayes.calibrate.calibrate`, short chains)
    on the recording as given and on :func:`corrected_recording` — an adapter over the
    calibration pipeline, which itself knows no effects.  Returns both ``positions.json``-style
    documents' per-IMU means/stds and their R̂/ESS diagnostics, or an error note."""
    try:
        from ..calibrate import calibrate
    except ImportError as exc:  # pragma: no cover
        return {"error": f"accel_bayes.calibrate unavailable: {exc}"}
    out = {"settings": {"chains": chains, "draws": draws, "warmup": warmup, "seed": int(seed)}}
    for tag, r in (("before", rec), ("after", corrected_recording(rec, fit))):
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


# ============================================================================ held-out transfer

class _Fixed:
    """An effect whose parameters are held at given values (no free parameters, df = 0): it
    perturbs (``mean``) or clips (``clip``) the outputs exactly as the wrapped effect does, but
    the fit never moves it.  Used by :func:`heldout_fit`."""

    parameters = ()
    needs_rates = False

    def __init__(self, effect):
        if effect.kind not in ("mean", "clip"):
            raise UserError(f"{effect.label()}: only mean and clip effects can be held fixed in a fit")
        self.inner = effect.copy()
        self.name = effect.name
        self.kind = effect.kind
        self.imu = effect.imu
        self.needs_rates = effect.needs_rates
        self.params, self.std, self.stats = {}, {}, {}

    df = 0

    def flatten(self, params=None):
        return torch.zeros(0, dtype=torch.float64)

    def unflatten(self, vec):
        return {}

    def prior_scales(self):
        return torch.zeros(0, dtype=torch.float64)

    def _at(self):
        e = _copy.copy(self.inner)
        e.imu = self.imu  # the fit may re-index IMUs into a sub-context
        return e

    def perturbation(self, params, ctx):
        return self._at().perturbation(None, ctx)

    def transform(self, params, acc, gyro, ctx):
        return self._at().transform(None, acc, gyro, ctx)

    def update_stats(self, acc, gyro) -> None:
        pass

    def label(self) -> str:
        return "fixed:" + self.inner.label()


def heldout_fit(prep: Prepared, effects, *, base: "ModelFit | None" = None, prior_std: float = DEFAULT_PRIOR_STD) -> dict:
    """Log-likelihood of a recording under the nominal model and under the nominal model plus
    ``effects`` **held at their given parameter values** (e.g. estimated on another recording).

    Both models re-fit the same nuisance parameters on this recording — positions and the
    per-sample motion — so they have the same number of free parameters and their
    log-likelihoods compare directly (a held-out check: no parameter of the effects is fitted
    here).  ``mean``/``clip`` effects enter the signal model unchanged (:class:`_Fixed`);
    ``noise_level`` effects fix the noise factors (stated std × factor); ``unexplained``
    findings carry no model and are skipped.  ``time_offset`` uses this recording's output
    rates (from ``base``).

    base : the nominal fit of ``prep`` (:func:`baseline_fit`), computed if None.
    Returns {"loglik_nominal", "loglik_fixed", "difference" (fixed − nominal), "per_sample"
    (difference / T), "chi2_per_dof_nominal", "chi2_per_dof_fixed" (stated noise),
    "effects" (labels used), "skipped", "converged", "seconds"}.
    """
    t0 = _time.perf_counter()
    if base is None:
        base, _ = baseline_fit(prep, prior_std=prior_std)
    used, skipped, fixed, noise = [], [], [], []
    for e in effects:
        if e.kind in ("mean", "clip"):
            fixed.append(_Fixed(e))
            used.append(e.label())
        elif e.kind == "noise":
            noise.append(e)
            used.append(e.label())
        else:
            skipped.append(e.label())
    p2 = prep
    if noise:
        fa, fg = noise_factors(noise, prep.K)
        p2 = _copy.copy(prep)
        p2.sigma_acc = prep.sigma_acc * fa
        p2.sigma_gyro = prep.sigma_gyro * fg
    f = fit_model(p2, fixed, init=base, prior_std=prior_std, laplace=False)
    # χ² with the stated noise for both models
    _, quad_stated = _loglik_terms(prep, f.res_acc, f.res_gyro, torch.ones(prep.K, dtype=torch.float64),
                                   torch.ones(prep.K, dtype=torch.float64))
    return {"loglik_nominal": base.loglik, "loglik_fixed": f.loglik, "difference": f.loglik - base.loglik,
            "per_sample": (f.loglik - base.loglik) / prep.T,
            "chi2_per_dof_nominal": base.chi2_per_dof, "chi2_per_dof_fixed": quad_stated / max(base.dof, 1),
            "positions_nominal": base.positions.tolist(), "positions_fixed": f.positions.tolist(),
            "effects": used, "skipped": skipped, "converged": bool(f.converged) and bool(base.converged),
            "seconds": _time.perf_counter() - t0}

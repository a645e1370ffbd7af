"""The Rao-Blackwellized likelihood with a per-sample covariance: the board's unresolved jerk,
loaded on each IMU by its data age, projected out with φ_t; heavy tails as a scale mixture
(issue #30 item 1; the physics: issue #27 items 2–3, :mod:`accel_bayes.mismatch.unresolved`).

Model, per sample t, array frame, stacked over the A triads (3A numbers)::

    y_t = G(θ) u(ω_t) + H(θ) φ_t + D_t m_t + e_t,   e_t ~ N(0, Q/λ_t),  m_t ~ N(0, s_t² I₃/λ_t),
    D_t = d_t ⊗ I₃,   d_kt = age_kt − mean_k age_kt  (s),

age_kt the data age of triad k's output at t (its sampling clock's sawtooth, plus the acc − gyro
filter delay: :func:`ages_from_clocks`), m_t the board's jerk that the outputs do not resolve
(m/s³) with scale s_t (its |ω| band's ``jerk_rms``, :func:`band_scale`), φ_t = [ω̇_t; s_t] with
the prior of :class:`~.likelihood.RaoBlackwellLikelihood` (flat, or N(0, F/λ_t)), and λ_t a
per-sample precision scale: λ_t ≡ 1 (``nu=None``, Gaussian) or λ_t ~ Gamma(ν/2, rate ν/2) (mean
1), which makes y_t a multivariate t with ν degrees of freedom given ω_t: heavy tails as a scale
mixture, not a post-hoc inflation.  The loading is centred because a common age moves every triad
alike, which φ_t's s_t absorbs; with the flat prior centring changes nothing.

Integrating φ_t and m_t out (m first with its prior; the determinant lemma, DESIGN §4's −½
exponent for the φ part) gives, with S the flat likelihood's φ-projection, Ũ_t = s_t D_t,
r_t = y_t − G u(ω_t), N_t = I₃ + Ũ_tᵀSŨ_t (3×3) and, for λ_t = 1,

    log p(y_t | ω_t, θ) = −½ q̃_t − ½ log|M(θ)| − ½ log|N_t(θ)|,
    q̃_t = r_tᵀSr_t − ‖L_t⁻¹Ũ_tᵀSr_t‖²,   N_t = L_t L_tᵀ,

up to the base class's θ-free constants (:attr:`log_constant`; the same ones, so values compare
with the flat likelihood's).  |N_t| depends on θ through S: it is the per-sample determinant, with
exponent −½ like |M|.  With s_t d_t = 0, N_t = I and q̃ = q: the flat likelihood exactly.  With the
scale mixture, per sample and draw (closed form, exact; n = 3A − 6 flat prior, 3A proper)::

    log ∫ p(y_t | ω, θ, λ) Gamma(λ; ν/2, ν/2) dλ
        = lgamma(a + n/2) − lgamma(a) − (n/2) log a − (a + n/2) log1p(q̃/(2a)) − ½ log|M| − ½ log|N_t|,

a = ν/2 (λ scales Q, the jerk prior and a proper φ prior together; the determinants do not
depend on λ beyond λ^(n/2)).  The ω_t integral stays the [C21] Monte Carlo average over draws from
the gyro posterior, so p̂ is still unbiased (pseudo-marginal MH stays exact).

Cost.  Per θ on top of the flat projection: the 3×3 N_t and the 3×6 and 3-vector maps
V_t = L_t⁻¹Ũ_tᵀSG, v_t = L_t⁻¹Ũ_tᵀSr̄_t (r̄ centred at the gyro mean), all from the flat
projection's weighted residuals by sums over the A triads (O(T·A)), batched 3×3 Choleskys;
per draw q̃ = q − ‖V_t δ − v_t‖², δ = u(ω) − u(ω̄_t), on top of the flat path's shared 6×6 factor
(:mod:`.draw_sums`).  Samples with s_t d_t = 0 get zero corrections; a recording with none
takes the flat path unchanged.  ``experiments/bench_likelihood_percov.py`` times it on exp_1.
"""
from __future__ import annotations

import copy
import math

import numpy as np
import torch

from ..errors import UserError
from ..physics.models import u_of_omega
from .likelihood import RaoBlackwellLikelihood
from .unresolved_cov import centred_ages

__all__ = ["PerSampleCovLikelihood", "with_unresolved_motion", "ages_from_clocks", "band_scale"]


def band_scale(omega_norm, edges, rms) -> torch.Tensor:
    """s_t (T,) per sample from a per-|ω|-band scale: ``edges`` the B − 1 inner band edges
    (rad/s, ascending, as the ``unresolved_motion`` finding's ``omega_edges``), ``rms`` (B,) the
    band's scale (``jerk_rms``, m/s³), ``omega_norm`` (T,) rad/s.  Band b holds
    edges[b−1] ≤ |ω| < edges[b]."""
    w = torch.as_tensor(np.asarray(omega_norm, dtype=np.float64))
    e = torch.as_tensor(np.asarray(edges, dtype=np.float64)).reshape(-1)
    v = torch.as_tensor(np.asarray(rms, dtype=np.float64)).reshape(-1)
    if len(v) != len(e) + 1:
        raise UserError(f"jerk_rms: expected {len(e) + 1} values for {len(e)} band edges, got {len(v)}")
    if not bool(torch.isfinite(v).all()) or bool((v < 0).any()):
        raise UserError("jerk_rms: expected finite values >= 0")
    return v[torch.bucketize(w, e, right=True)]


def ages_from_clocks(time, clocks: dict, labels, sensor: str = "acc") -> torch.Tensor:
    """The data ages (T, len(labels)) s of the rows ``labels`` (IMU labels) at the read times
    ``time`` (T,) s (the recording's own time axis), from ``clocks`` {IMU label:
    :class:`~accel_bayes.physics.effects.clock.SamplingClock`}.  ``sensor="acc"`` adds each
    clock's acc − gyro filter delay.  IMUs without a clock get age 0 (read in step with the host)."""
    if sensor not in ("acc", "gyro"):
        raise UserError(f"sensor: expected 'acc' or 'gyro', got {sensor!r}")
    t = torch.as_tensor(np.asarray(time, dtype=np.float64))
    out = torch.zeros(len(t), len(labels), dtype=torch.float64)
    for j, k in enumerate(labels):
        clock = clocks.get(int(k))
        if clock is None:
            continue
        out[:, j] = clock.age(t)
        if sensor == "acc":
            out[:, j] += float(clock.params["filter_delay_acc_minus_gyro_s"])
    return out


def with_unresolved_motion(lik: RaoBlackwellLikelihood, age, jerk_std, nu=None) -> "PerSampleCovLikelihood":
    """The per-sample-covariance likelihood on ``lik``'s data (shared, not copied): ``age`` (T, A)
    s the rows' data ages, ``jerk_std`` scalar or (T,) m/s³, ``nu`` None or the degrees of
    freedom of the scale mixture (module docstring)."""
    new = copy.copy(lik)
    new.__class__ = PerSampleCovLikelihood
    new._set_terms(age, jerk_std, nu)
    return new


class PerSampleCovLikelihood(RaoBlackwellLikelihood):
    """:class:`~.likelihood.RaoBlackwellLikelihood` with the unresolved jerk loaded by the data
    ages and an optional scale mixture (module docstring).

    Extra parameters: ``age`` (T, A) s, the data age of each row's output (centred here);
    ``jerk_std`` scalar or (T,) m/s³, the jerk's scale per axis at each sample (0: absent);
    ``nu`` None (Gaussian) or ν > 0, the degrees of freedom of the per-sample scale mixture.
    The tempered likelihood (:mod:`.tempering`) does not combine with it.
    """

    def __init__(self, acc, omega, acc_noise_std, num_draws, age, jerk_std, nu=None, reference: int = 0,
                 dtype=torch.float64, device=None, phi_prior=None):
        super().__init__(acc, omega, acc_noise_std, num_draws, reference=reference, dtype=dtype, device=device,
                         phi_prior=phi_prior)
        self._set_terms(age, jerk_std, nu)

    def _set_terms(self, age, jerk_std, nu):
        age = torch.as_tensor(np.asarray(age, dtype=np.float64) if not torch.is_tensor(age) else age,
                              dtype=self.dtype, device=self.device)
        if age.shape != (self.T, self.A):
            raise UserError(f"age: expected shape (T, A) = ({self.T}, {self.A}) s, got {tuple(age.shape)}")
        if not bool(torch.isfinite(age).all()):
            raise UserError("age: expected finite data ages (s)")
        s = torch.as_tensor(jerk_std, dtype=self.dtype, device=self.device)
        s = s.expand(self.T) if s.dim() == 0 else s
        if s.shape != (self.T,) or not bool(torch.isfinite(s).all()) or bool((s < 0).any()):
            raise UserError(f"jerk_std: expected a finite scale >= 0 (m/s³), scalar or ({self.T},), got shape "
                            f"{tuple(s.shape)}")
        if nu is not None:
            nu = float(nu)
            if not (math.isfinite(nu) and nu > 0):
                raise UserError(f"nu: expected degrees of freedom > 0 or None, got {nu!r}")
        self.age = age
        self.jerk_std = s
        self.nu = nu
        # Ũ_t = s_t D_t only through the product u_kt = s_t d_kt (m/s² per unit-variance jerk)
        self.loading = centred_ages(age) * s[:, None]
        self.active = torch.nonzero((self.loading != 0).any(-1)).reshape(-1)

    # ------------------------------------------------------------------ per-θ terms
    def _percov_terms(self, r: torch.Tensor) -> dict:
        """The flat projection at r (B, A, 3) plus V (B, T, 3, 6), v (B, T, 3) and log|N_t|
        (B, T) of the module docstring (zero where the sample has no loading)."""
        proj = self._projection_hot(r, extras=True)
        B, A, T = r.shape[0], self.A, self.T
        idx = self.active
        u = self.loading[idx]  # (Ta, A)
        sl = self._sqrt_lam.view(A, 3)
        lam = self.lam.view(A, 3)
        Hs = proj["Hw"].view(B, A, 3, 6) * sl[..., None]  # rows of Λ H
        Gs = proj["Gt"].view(B, A, 3, 6) * sl[..., None]  # rows of Λ Ẽ = S G
        Y = torch.einsum("ta,baij->btji", u, Hs)  # HᵀΛŨ_t (B, Ta, 6, 3)
        Ta = len(idx)
        Yh = torch.linalg.solve_triangular(proj["L"], Y.permute(0, 2, 1, 3).reshape(B, 6, Ta * 3), upper=False)
        Yh = Yh.view(B, 6, Ta, 3)
        # N_t = I + ŨᵀΛŨ − (HᵀΛŨ)ᵀ(M + F⁻¹)⁻¹(HᵀΛŨ) = I + Ũ_tᵀ S Ũ_t
        Nt = -torch.einsum("bitj,bitk->btjk", Yh, Yh)
        diag = 1.0 + (u * u) @ lam  # (Ta, 3)
        Nt = Nt + torch.diag_embed(diag)
        Ln, info = torch.linalg.cholesky_ex(Nt)
        if bool((info != 0).any()):  # cannot happen for finite inputs: N_t ⪰ I
            raise UserError("age: the per-sample covariance is not positive definite (non-finite loading?)")
        E = torch.einsum("ta,baij->btij", u, Gs)  # Ũ_tᵀ S G (B, Ta, 3, 6)
        a = torch.einsum("ta,btai->bti", u, proj["e_w"][:, idx].view(B, Ta, A, 3) * sl)  # Ũ_tᵀ S r̄_t
        Vt = torch.linalg.solve_triangular(Ln, torch.cat((E, a[..., None]), -1), upper=False)  # (B, Ta, 3, 7)
        V = torch.zeros(B, T, 3, 6, dtype=self.dtype, device=self.device)
        v = torch.zeros(B, T, 3, dtype=self.dtype, device=self.device)
        logdetN = torch.zeros(B, T, dtype=self.dtype, device=self.device)
        V[:, idx] = Vt[..., :6]
        v[:, idx] = Vt[..., 6]
        logdetN[:, idx] = 2 * torch.diagonal(Ln, dim1=-2, dim2=-1).log().sum(-1)
        proj.update(V=V, v=v, logdetN=logdetN)
        return proj

    def _kernel(self, q: torch.Tensor) -> torch.Tensor:
        """Per-draw log weight from q̃ (any shape): −½ q̃ (Gaussian) or the scale mixture's
        closed form (module docstring)."""
        if self.nu is None:
            return -0.5 * q
        a = 0.5 * self.nu
        n = 3 * self.A - (0 if self.phi_prior_prec is not None else 6)
        const = math.lgamma(a + n / 2) - math.lgamma(a) - n / 2 * math.log(a)
        return const - (a + n / 2) * torch.log1p(q.clamp_min(0) / (2 * a))

    # ------------------------------------------------------------------ estimators
    def log_lik_given_omega(self, positions: torch.Tensor, omega: torch.Tensor) -> torch.Tensor:
        """log p(y^a | ω_{1:T}, θ) with φ_t, m_t (and λ_t) integrated out (module docstring), up to
        the base class's dropped constants.  positions (..., A, 3) m; omega (T, 3) or (..., T, 3)
        rad/s broadcasting against the positions' batch.  Returns (...); differentiable."""
        r = self._positions(positions)
        batch = r.shape[:-2]
        B = int(np.prod(batch)) if len(batch) else 1
        omega = torch.as_tensor(omega, dtype=self.dtype, device=self.device)
        delta = (u_of_omega(omega) - u_of_omega(self.omega.mean)).expand(*batch, self.T, 6).reshape(B, self.T, 6)
        p = self._percov_terms(r.reshape(B, self.A, 3))
        q = (p["c"] - 2 * (p["b"] * delta).sum(-1) + ((delta @ p["C"]) * delta).sum(-1)
             - ((p["V"] @ delta[..., None])[..., 0] - p["v"]).square().sum(-1))
        out = self._kernel(q).sum(-1) - 0.5 * self.T * p["logdetM"] - 0.5 * p["logdetN"].sum(-1)
        return out.reshape(batch)

    def log_phat(self, positions, generator=None, z=None, num_draws=None, independent_draws: bool = False):
        """log p̂(y^a | y^g, θ) with the per-sample covariance (module docstring); the arguments and
        the draws are :meth:`RaoBlackwellLikelihood.log_phat`'s (same z → the same ω draws).
        Without any loaded sample and with ``nu=None`` it is the flat estimator itself."""
        if len(self.active) == 0 and self.nu is None:
            return super().log_phat(positions, generator=generator, z=z, num_draws=num_draws,
                                    independent_draws=independent_draws)
        r = self._positions(positions)
        batch = r.shape[:-2]
        if z is None:
            z = self.sample_z(batch if independent_draws else (), num_draws, generator)
        else:
            z = torch.as_tensor(z, dtype=self.dtype, device=self.device)
            if z.dim() < 3 or z.shape[-3] != self.T or z.shape[-1] != 3:
                raise UserError(f"z: expected shape (..., T={self.T}, N, 3), got {tuple(z.shape)}")
        N = z.shape[-2]
        B = int(np.prod(batch)) if len(batch) else 1
        p = self._percov_terms(r.reshape(B, self.A, 3))
        zt = z.transpose(-1, -2)
        if len(zt.shape[:-3]):
            zt = zt.expand(*batch, *zt.shape[-3:]).reshape(B, self.T, 3, N)
        Rc, w, floor = self._factor_any(p["c"], p["b"], p["C"])
        V, v = p["V"], p["v"]

        def logw(s, d, t0, t1):
            # d (…, 6, τ, N): q̃ = s + floor − ‖V δ − v‖²
            Vc = V[:, t0:t1]
            Vd = torch.einsum("btij,jtn->bitn", Vc, d) if d.dim() == 3 else torch.einsum("btij,bjtn->bitn", Vc, d)
            corr = (Vd - v[:, t0:t1].transpose(1, 2)[..., None]).square().sum(1)  # (B, τ, N)
            return self._kernel(s + floor[:, t0:t1, None] - corr)

        inplace = not (torch.is_grad_enabled() and (Rc.requires_grad or zt.requires_grad))
        lse = self._lse_direct(zt, Rc, w, inplace, logw=logw)  # (B, T)
        out = lse.sum(-1) - self.T * math.log(N) - 0.5 * self.T * p["logdetM"] - 0.5 * p["logdetN"].sum(-1)
        return out.reshape(batch)

    def _factor_any(self, c, b, C):
        """(R_C, w, floor) with q = ‖R_C δ + w_t‖² + floor_t: :meth:`_factor` where it applies,
        else (C singular, A ≤ 4 rounding) a square root of C from its eigendecomposition and the
        pseudo-inverse (b_t lies in C's range, both being Ẽ_wᵀ times a vector); ``floor`` is then
        only c − ‖w‖², which the max-shifted log-sum-exp does not need to bound q."""
        fac = self._factor(c, b, C)
        if fac is not None:
            return fac
        ev, Vc = torch.linalg.eigh(C)
        tol = ev.amax(-1, keepdim=True) * 1e-12
        root = ev.clamp_min(0).sqrt()
        Rc = root[..., :, None] * Vc.transpose(-1, -2)  # C = RcᵀRc
        inv = torch.where(ev > tol, 1.0 / root.clamp_min(1e-300), torch.zeros_like(root))
        w = -(inv[..., :, None] * (Vc.transpose(-1, -2) @ b.transpose(-1, -2)))  # −Rc⁺ᵀ b (B, 6, T)
        return Rc, w, c - (w * w).sum(-2)

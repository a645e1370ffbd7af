"""The per-draw work of the likelihood's Monte Carlo estimator log p̂ (:meth:`~.likelihood.
RaoBlackwellLikelihood.log_phat`): the factor of the 7×7 quadratic form per sample and the
log-sum-exp over the draws, held in :class:`DrawSums`, which the likelihood class extends (it
needs the likelihood's data: the gyro posterior's Cholesky factors and means, T, dtype).

Cost and numerics
-----------------
Everything that touches the 3A-dimensional data is computed once per (θ, t), O(T·A) per θ
(:meth:`~.likelihood.RaoBlackwellLikelihood.projection`).  S is never formed: S r = Λ(r − Hφ̂) with
φ̂ = M⁻¹HᵀΛr the least-squares [ω̇; s], so with r_t = y_t − G u(ω̄_t) (centred at the gyro
posterior mean) and d = u(ω) − u(ω̄_t),

    q_tn = c_t − 2 b_tᵀ d_tn + d_tnᵀ C d_tn,  c_t = r_tᵀSr_t, b_t = GᵀSr_t, C = GᵀSG,

all three computed from φ-projected residuals (no cancellation between the large φ part of y
and the small remainder).  Let R_t be the upper-triangular factor of the 7×7 matrix
[[C, −b_t], [−b_tᵀ, c_t]]; C does not depend on t, so R_t = [[R_C, w_t], [0, R_77,t]] with
R_C the factor of C (one 6×6 Cholesky per θ), w_t = −R_C⁻ᵀb_t and R_77,t² = c_t − ‖w_t‖².  Then
q_tn − R_77² = ‖R_C d_tn + w_t‖², a sum of squares (never negative), whatever A is.  For a
few draws (N ≤ 32) d_tn is formed directly from v = L_t z_tn (d_ij = ω_i v_j + ω̄_j v_i, ω = ω̄ + v);
for many, per draw d_tn = D_t f(z_tn) with f = [z; u(z); 1] and q_tn − R_77² = ‖F_t f(z_tn)‖²
with F_t = R_t[:6] D_t (6×10).  R_77² = min_d q_t is a lower bound of every q_tn, so
exp(−½(q − R_77²)) ≤ 1 cannot overflow; samples where every term underflows fall back to a
max-shifted log-sum-exp.  (Where C is singular, A ≤ 3, or a remainder comes out negative by
rounding, R_t comes from a 7×7 Cholesky or eigendecomposition per sample instead.)

One log p̂ at N = 1 on exp_1 (T = 5885, A = 8) costs ≈ 0.9 ms on one core
(experiments/bench_iteration.py): the projection (two matrix products over the data, ≈ 0.45 ms)
and the per-draw work (≈ 0.2 ms).
"""
from __future__ import annotations

import math

import torch

__all__ = ["DrawSums", "DIRECT_MAX_DRAWS"]

# Budget (number of float64 elements) of one chunk of per-draw temporaries: keeps memory at
# ~tens of MB whatever T·N·batch is, without a Python loop per sample.
_CHUNK_ELEMS = 1 << 19

# Up to this many draws per sample, log_phat evaluates q directly from d = u(ω) − u(ω̄)
# (_lse_direct); above it the per-sample 6×10 maps F_t (_lse_shared) are cheaper per draw.
# The direct path works in smaller chunks (its temporaries then stay in cache).
DIRECT_MAX_DRAWS = 32
_DIRECT_CHUNK_ELEMS = 1 << 18


class DrawSums:
    """Mixin of :class:`~.likelihood.RaoBlackwellLikelihood`: the draw sums of log p̂ (module
    docstring).  Reads ``T``, ``dtype``, ``device``, ``omega`` and ``omega_chol`` of the likelihood
    and caches θ-free tensors in attributes named ``_*`` (dropped by its ``to``)."""

    def _factor(self, c, b, C):
        """(R_C, w, floor) with R_t = [[R_C, w_t], [0, √floor_t]] the upper-triangular factor of
        C'_t = [[C, −b_t], [−b_tᵀ, c_t]] (see :meth:`_draw_maps`), or None when C is singular or
        some remainder floor_t = c_t − ‖w_t‖² comes out negative by rounding (then the caller
        takes the general 7×7 path).  R_C (B, 6, 6), w (B, 6, T), floor (B, T) ≥ 0.

        C is the same at every t, so this is one 6×6 Cholesky and one triangular solve per θ: the
        same arithmetic as the last row of a 7×7 Cholesky, without T factorisations.
        """
        Lc, info = torch.linalg.cholesky_ex(C)  # C = Lc Lcᵀ, R_C = Lcᵀ
        if bool((info != 0).any()):
            return None
        w = torch.linalg.solve_triangular(Lc, b.transpose(-1, -2), upper=False).neg()  # −R_C⁻ᵀ b_t
        floor = c - (w * w).sum(-2)
        if not bool((floor >= 0).all()):
            return None
        return Lc.transpose(-1, -2), w, floor

    def _lse_direct(self, zt, Rc, w, inplace=True, logw=None):
        """log Σ_n exp(−½(q_tn − floor_t)) → (B, T), with q_tn − floor_t = ‖R_C d_tn + w_t‖².

        d_tn = u(ω_tn) − u(ω̄_t) is formed from v = L_t z_tn (ω = ω̄ + v) as
        d_ij = ω_i v_j + ω̄_j v_i (exact for the quadratic u, no cancellation), θ-free and so
        shared by all B positions when zt (T, 3, N) is; zt (B, T, 3, N) gives one per position.
        Per draw that is ~40 flops for d plus a 6×6 triangular product per θ (one matrix product
        over all t and n), instead of the 6×10 map F_t per (θ, t) of :meth:`_lse_shared`.
        For N = 1 the log-sum-exp is the term itself (no exp/log).

        ``logw`` (optional) turns each chunk's s = ‖R_C d + w‖² (B, τ, N) into per-draw log
        weights: called as ``logw(s, d, t0, t1)`` with d (…, 6, τ, N) the chunk's draws of
        u(ω) − u(ω̄) (a reused buffer: read it before returning); the result is log-sum-exp'ed
        with the max shift (the per-sample covariance of :mod:`.likelihood_percov` subtracts a
        further term per draw, so s − floor is no longer a lower bound).
        """
        B = Rc.shape[0]
        T, N = zt.shape[-3], zt.shape[-1]
        shared = zt.dim() == 3
        zb = () if shared else (B,)
        Lt, mt = self._chol_t, self._mean_t  # (3, 3, T), (3, T)
        pi, pj = self._pairs
        out = []
        step = max(1, _DIRECT_CHUNK_ELEMS // (16 * N * B))  # ~16 numbers per (draw, θ) in flight
        # Without autograd the temporaries live in buffers reused across chunks and calls (fresh
        # multi-100-kB allocations cost page faults comparable to the arithmetic).
        ws = self._workspace if inplace else (lambda name, shape: None)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            tau = t1 - t0
            zc = zt[..., t0:t1, :, :].transpose(-3, -2)  # (…, 3, τ, N) view
            m = mt[:, t0:t1, None]  # (3, τ, 1)
            # v_i = Σ_j L_ij z_j  (…, 3, τ, N)
            prod = torch.mul(Lt[:, :, t0:t1, None], zc.unsqueeze(-4), out=ws("prod", (*zb, 3, 3, tau, N)))
            v = torch.sum(prod, -3, out=ws("v", (*zb, 3, tau, N)))
            om = torch.add(v, m, out=ws("om", (*zb, 3, tau, N)))
            d = torch.index_select(om, -3, pi, out=ws("d", (*zb, 6, tau, N)))
            tmp = torch.index_select(v, -3, pj, out=ws("tmp", (*zb, 6, tau, N)))
            d = d.mul_(tmp) if inplace else d * tmp
            tmp = torch.index_select(v, -3, pi, out=ws("tmp", (*zb, 6, tau, N)))
            tmp = tmp.mul_(m.index_select(0, pj)) if inplace else tmp * m.index_select(0, pj)
            d = d.add_(tmp) if inplace else d + tmp  # d_ij = ω_i v_j + ω̄_j v_i
            y = torch.matmul(Rc, d.view(*zb, 6, tau * N), out=ws("y", (B, 6, tau * N)))
            y = y.view(B, 6, tau, N)
            y = y.add_(w[:, :, t0:t1, None]) if inplace else y + w[:, :, t0:t1, None]
            y = y.mul_(y) if inplace else y * y
            s = torch.sum(y, 1, out=ws("s", (B, tau, N)))  # (B, τ, N)
            if logw is not None:
                h = logw(s, d, t0, t1)
                out.append(h[..., 0] if N == 1 else torch.logsumexp(h, -1))
                continue
            out.append(s[..., 0] * -0.5 if N == 1 else self._log_mean_exp_shifted(s))
        return torch.cat(out, 1)

    def _workspace(self, name: str, shape: tuple) -> torch.Tensor:
        """A scratch tensor of ``shape`` named ``name``, reused across calls (grown as needed)."""
        cache = self.__dict__.setdefault("_ws_cache", {})
        n = math.prod(shape)
        buf = cache.get(name)
        if buf is None or buf.numel() < n:
            buf = cache[name] = torch.empty(n, dtype=self.dtype, device=self.device)
        return buf[:n].view(shape)

    @property
    def _chol_t(self) -> torch.Tensor:
        """chol(cov_t) stored (3, 3, T) (cached)."""
        if getattr(self, "_chol_t_cache", None) is None:
            self._chol_t_cache = self.omega_chol.permute(1, 2, 0).contiguous()
            self._mean_t_cache = self.omega.mean.T.contiguous()
        return self._chol_t_cache

    @property
    def _mean_t(self) -> torch.Tensor:
        """ω̄_t stored (3, T) (cached)."""
        self._chol_t
        return self._mean_t_cache

    @property
    def _pairs(self):
        if getattr(self, "_pairs_cache", None) is None:
            self._pairs_cache = (torch.tensor(_PAIRS_I, device=self.device), torch.tensor(_PAIRS_J, device=self.device))
        return self._pairs_cache

    def _draw_maps(self, c, b, C):
        """(F, floor): q_tn = ‖F_t f(z_tn)‖² + floor_t, F (B, T, 6, 10), floor (B, T) ≥ 0.

        R_t is an upper-triangular factor of C'_t = [[C, −b_t], [−b_tᵀ, c_t]] = R_tᵀR_t, so the
        last row of R_t D_t is (0, …, 0, R_77) and floor = R_77² = min_d q is a lower bound of
        every q_tn: exp(−½(q − floor)) ≤ 1 never overflows (see :meth:`_lse_shared`).
        R_t comes from :meth:`_factor` (one shared 6×6 Cholesky) or, where that declines, from
        :meth:`_draw_maps_eig` (a 7×7 factor per sample).
        """
        fac = self._factor(c, b, C)
        if fac is None:
            return self._draw_maps_eig(c, b, C)
        return self._maps_from_factor(*fac[:2]), fac[2]

    def _maps_from_factor(self, Rc, w):
        """F_t = R_t[:6] D_t = [R_C D_t[:6, :9], w_t] (D_t's last row is e_10 and its last column
        is zero above it) → (B, T, 6, 10), stored (T, B, 6, 10) so that :meth:`_lse_shared`'s
        (T, 6B, 10) view needs no copy."""
        B, T = w.shape[0], w.shape[-1]
        F = torch.empty(T, B, 6, 10, dtype=w.dtype, device=w.device)
        F[..., :9] = (Rc @ self._D6).view(B, 6, T, 9).permute(2, 0, 1, 3)
        F[..., 9] = w.permute(2, 0, 1)
        return F.permute(1, 0, 2, 3)

    @property
    def _D6(self) -> torch.Tensor:
        """D_t[:6, :9] stored (6, T·9) (θ-free, cached): R_C @ _D6 is one matrix product."""
        if getattr(self, "_D6_cache", None) is None:
            self._D6_cache = self._D[:, :6, :9].permute(1, 0, 2).reshape(6, self.T * 9)
        return self._D6_cache

    def _draw_maps_eig(self, c, b, C):
        """:meth:`_draw_maps` through a 7×7 factor per sample (the general path: Cholesky, and
        for singular or rounding-indefinite C'_t an eigendecomposition square root)."""
        B, T = c.shape
        Cp = torch.empty(B, T, 7, 7, dtype=self.dtype, device=self.device)
        Cp[..., :6, :6] = C.unsqueeze(1)
        Cp[..., :6, 6] = -b
        Cp[..., 6, :6] = -b
        Cp[..., 6, 6] = c
        Lc, info = torch.linalg.cholesky_ex(Cp)
        R = Lc.transpose(-1, -2)
        bad = info != 0
        if bool(bad.any()):
            # Singular (e.g. A ≤ 4: rank S = 3A − 6 < 7) or indefinite by rounding: a square root
            # from the eigendecomposition (negative rounding eigenvalues clipped to 0), made
            # upper-triangular by QR (RᵀR is unchanged).
            lam, V = torch.linalg.eigh(Cp[bad])
            R0 = lam.clamp_min(0).sqrt().unsqueeze(-1) * V.transpose(-1, -2)
            R = R.clone()
            R[bad] = torch.linalg.qr(R0).R
        F = R[..., :6, :] @ self._D  # (B, T, 6, 10)
        return F, R[..., 6, 6].square()

    @property
    def _D(self) -> torch.Tensor:
        """D_t (T, 7, 10): [u(ω̄_t + L_t z) − u(ω̄_t); 1] = D_t [z; u(z); 1] (θ-free, cached)."""
        if getattr(self, "_D_cache", None) is None:
            m, Lg = self.omega.mean, self.omega_chol
            T = self.T
            mx, my, mz = m.unbind(-1)
            o = torch.zeros_like(mx)
            J = torch.stack(  # ∂u/∂ω at the mean (T, 6, 3)
                (
                    torch.stack((2 * mx, o, o), -1),
                    torch.stack((o, 2 * my, o), -1),
                    torch.stack((o, o, 2 * mz), -1),
                    torch.stack((my, mx, o), -1),
                    torch.stack((mz, o, mx), -1),
                    torch.stack((o, mz, my), -1),
                ),
                -2,
            )
            pi = torch.tensor(_PAIRS_I, device=self.device)
            pj = torch.tensor(_PAIRS_J, device=self.device)
            fk = torch.tensor(_FEAT_I, device=self.device)
            fl = torch.tensor(_FEAT_J, device=self.device)
            # (Lz)_i (Lz)_j = Σ_(k≤l) P[(i,j),(k,l)] z_k z_l with P = L_ik L_jl (+ L_il L_jk if k ≠ l).
            Li, Lj = Lg[:, pi, :], Lg[:, pj, :]  # (T, 6, 3): rows i and j of L for each output pair
            P = Li[:, :, fk] * Lj[:, :, fl]  # (T, 6, 6) over feature pairs (k, l)
            cross = (fk != fl).to(self.dtype)
            P = P + cross * (Li[:, :, fl] * Lj[:, :, fk])
            D = torch.zeros(T, 7, 10, dtype=self.dtype, device=self.device)
            D[:, :6, :3] = J @ Lg
            D[:, :6, 3:9] = P
            D[:, 6, 9] = 1.0
            self._D_cache = D
        return self._D_cache

    @staticmethod
    def _features(zt: torch.Tensor, buf: torch.Tensor | None = None) -> torch.Tensor:
        """f = [z; zx², zy², zz², zx zy, zy zz, zx zz; 1] for zt (..., τ, 3, N) → (..., τ, 10, N).

        ``buf`` (a previous result of the same shape) is reused: its constant row is kept.
        """
        if buf is None or buf.shape[:-2] != zt.shape[:-2] or buf.shape[-1] != zt.shape[-1]:
            buf = torch.empty(*zt.shape[:-2], 10, zt.shape[-1], dtype=zt.dtype, device=zt.device)
            buf[..., 9, :] = 1.0
        buf[..., 0:3, :] = zt
        torch.mul(zt, zt, out=buf[..., 3:6, :])
        torch.mul(zt[..., 0:2, :], zt[..., 1:3, :], out=buf[..., 6:8, :])
        torch.mul(zt[..., 0, :], zt[..., 2, :], out=buf[..., 8, :])
        return buf

    def _chunk(self, N, per_draw):
        return max(1, _CHUNK_ELEMS // max(1, N * per_draw))

    @staticmethod
    def _log_mean_exp_shifted(s: torch.Tensor) -> torch.Tensor:
        """log Σ_n exp(−½ s_n) over the last dim for s ≥ 0 (q minus its floor).

        exp(−½ s) ≤ 1 cannot overflow, so the max-shift of a general logsumexp is skipped; rows
        where every term underflows (all s ≳ 1400: a θ or sample far from fitting) are redone
        with the shifted form.  ``s`` is overwritten.
        """
        h = s.mul_(-0.5) if not s.requires_grad else s * -0.5
        tot = torch.exp(h).sum(-1)
        out = tot.log()
        low = tot < 1e-280
        if bool(low.any()):
            out[low] = torch.logsumexp(h[low], -1)
        return out

    def _lse_shared(self, zt, F, inplace=True):
        """log Σ_n exp(−½(q_tn − floor_t)) with one zt (T, 3, N) for all B positions → (B, T)."""
        B = F.shape[0]
        T, _, N = zt.shape
        Fs = F.permute(1, 0, 2, 3).reshape(T, 6 * B, 10)  # one (6B × 10) map per t
        out, buf = [], None
        step = self._chunk(N, 10 + 6 * B)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            buf = self._features(zt[t0:t1], buf if inplace else None)  # (τ, 10, N)
            Y = torch.bmm(Fs[t0:t1], buf)  # (τ, 6B, N)
            Y = Y.mul_(Y) if inplace else Y * Y
            s = Y.reshape(t1 - t0, B, 6, N).sum(2)  # (τ, B, N)
            out.append(self._log_mean_exp_shifted(s))
        return torch.cat(out, 0).T

    def _lse_per_batch(self, zt, F, inplace=True):
        """As :meth:`_lse_shared` with its own zt (B, T, 3, N) per position → (B, T)."""
        B, T, _, N = zt.shape
        out, buf = [], None
        step = self._chunk(N * B, 16)
        for t0 in range(0, T, step):
            t1 = min(T, t0 + step)
            buf = self._features(zt[:, t0:t1], buf if inplace else None)  # (B, τ, 10, N)
            Y = F[:, t0:t1] @ buf  # (B, τ, 6, N)
            s = (Y.mul_(Y) if inplace else Y * Y).sum(-2)
            out.append(self._log_mean_exp_shifted(s))
        return torch.cat(out, 1)




# Index pairs (i, j) of u(ω) = [xx, yy, zz, xy, xz, yz] (models.u_of_omega order): the rows of D.
_PAIRS_I = (0, 1, 2, 0, 0, 1)
_PAIRS_J = (0, 1, 2, 1, 2, 2)
# Pairs (k, l) of the feature vector f[3:9] = [xx, yy, zz, xy, yz, xz] (the order _features
# computes them in, two vectorised products): the columns of D.
_FEAT_I = (0, 1, 2, 0, 1, 0)
_FEAT_J = (0, 1, 2, 1, 2, 2)

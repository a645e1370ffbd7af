"""Derivatives of the residual groups of a :class:`~accel_bayes.inference.lm.Problem`: analytic
Jacobian dicts mapped onto the free global columns, or forward-mode autodiff batched over the
samples (one ``jvp`` per direction, ``vmap`` over the directions), and the exact Hessian for
Laplace covariances (forward-over-reverse).  See the module docstring of
:mod:`accel_bayes.inference.lm` for the conventions."""
from __future__ import annotations

import torch
from torch.func import jvp, vmap

from .protocol import Linearization
from .residuals import ChainResidual, ExtraCost, GlobalResidual, SampleResidual

__all__ = ["ProblemDerivatives"]


class ProblemDerivatives:
    """The derivative half of :class:`~accel_bayes.inference.lm.Problem` (a mixin: it uses the
    problem's layout — ``variables``, ``offsets``, ``sizes``, ``free_idx``, ``n_free``, ``P`` — its
    ``chart`` and ``_total_cost_tensor``)."""

    def _cols_from_dict(self, jd: dict, lead: tuple, ref: torch.Tensor) -> torch.Tensor | None:
        """Analytic Jacobian dict (name → (*lead, size)) → (*lead, n_free); None if the dict is empty
        (the group does not depend on the globals)."""
        if not jd:
            return None
        for name in jd:
            if name not in self.offsets:
                raise ValueError(f"analytic Jacobian: unknown global block {name!r}")
        # Free columns of each block, taken block by block (a slice where they are contiguous,
        # e.g. all rows but the fixed triad's) and concatenated in layout order: one copy of the
        # free part, no scatter into the full tangent layout and gather back.
        parts = []
        for name, (sel, nf) in self._block_free_cols().items():
            if nf == 0:
                continue
            if name in jd:
                parts.append(jd[name].reshape(*lead, self.sizes[name])[..., sel])
            else:
                parts.append(ref.new_zeros(*lead, nf))
        if not parts:  # every global fixed
            return ref.new_zeros(*lead, 0)
        return torch.cat(parts, -1) if len(parts) > 1 else parts[0]

    def _block_free_cols(self) -> dict:
        """name → (selector of the block's free tangent columns (slice or index tensor), count)."""
        if getattr(self, "_free_cols_cache", None) is None:
            out = {}
            for name, v in self.variables.items():
                idx = torch.nonzero(v.free_mask().reshape(-1)).flatten()
                nf = int(idx.numel())
                if nf and int(idx[-1] - idx[0]) + 1 == nf:
                    sel = slice(int(idx[0]), int(idx[-1]) + 1)
                else:
                    sel = idx
                out[name] = (sel, nf)
            self._free_cols_cache = out
        return self._free_cols_cache

    def _vmap(self, f):
        return vmap(f, chunk_size=self.jac_chunk) if self.jac_chunk else vmap(f)

    def sample_jacobians(self, res: SampleResidual, values: dict, x):
        """(r (T, m), Jg (T, m, n_free), Jx (T, m, d) or None) of one per-sample group."""
        if res.jac is not None:
            r = res.fn(values, x, res.data)
            jd, jx = res.jac(values, x, res.data)
            return r, self._cols_from_dict(jd, tuple(r.shape), r), jx
        n = self.n_free
        z = self.P.new_zeros(n)
        if x is None:
            f = lambda dg: res.fn(self.chart(values, dg), None, res.data)  # noqa: E731
            r = res.fn(values, None, res.data)
            tang = self._vmap(lambda td: jvp(f, (z,), (td,))[1])(torch.eye(n, dtype=self.dtype, device=z.device))
            return r, tang.permute(1, 2, 0), None
        T, d = x.shape
        f = lambda dg, ex: res.fn(self.chart(values, dg), x + ex, res.data)  # noqa: E731
        td = torch.cat((torch.eye(n, dtype=x.dtype, device=x.device), x.new_zeros(d, n)), 0)
        tx = torch.cat((x.new_zeros(n, T, d), torch.eye(d, dtype=x.dtype, device=x.device)[:, None, :].expand(d, T, d)), 0)
        r = res.fn(values, x, res.data)
        tang = self._vmap(lambda a, b: jvp(f, (z, torch.zeros_like(x)), (a, b))[1])(td, tx)  # (n+d, T, m)
        return r, tang[:n].permute(1, 2, 0), tang[n:].permute(1, 2, 0)

    def chain_jacobians(self, res: ChainResidual, values: dict, x):
        """(r (T−1, m), Jg (T−1, m, n_free), A (T−1, m, d), B (T−1, m, d)) of one chain group."""
        xp, xn = x[:-1], x[1:]
        if res.jac is not None:
            r = res.fn(values, xp, xn, res.data)
            jd, A, B = res.jac(values, xp, xn, res.data)
            return r, self._cols_from_dict(jd, tuple(r.shape), r), A, B
        n, (Tm, d) = self.n_free, xp.shape
        z = self.P.new_zeros(n)
        f = lambda dg, ep, en: res.fn(self.chart(values, dg), xp + ep, xn + en, res.data)  # noqa: E731
        eye_d = torch.eye(d, dtype=x.dtype, device=x.device)[:, None, :].expand(d, Tm, d)
        zer = x.new_zeros(d, Tm, d)
        td = torch.cat((torch.eye(n, dtype=x.dtype, device=x.device), x.new_zeros(2 * d, n)), 0)
        tp = torch.cat((x.new_zeros(n, Tm, d), eye_d, zer), 0)
        tn = torch.cat((x.new_zeros(n, Tm, d), zer, eye_d), 0)
        r = res.fn(values, xp, xn, res.data)
        zp = torch.zeros_like(xp)
        tang = self._vmap(lambda a, b, c: jvp(f, (z, zp, zp), (a, b, c))[1])(td, tp, tn)
        return r, tang[:n].permute(1, 2, 0), tang[n:n + d].permute(1, 2, 0), tang[n + d:].permute(1, 2, 0)

    def global_jacobian(self, res: GlobalResidual, values: dict):
        """(r (m,), J (m, n_free)) of one global group."""
        r = res.fn(values)
        if res.jac is not None:
            return r, self._cols_from_dict(res.jac(values), tuple(r.shape), r)
        n = self.n_free
        z = self.P.new_zeros(n)
        f = lambda dg: res.fn(self.chart(values, dg))  # noqa: E731
        tang = self._vmap(lambda a: jvp(f, (z,), (a,))[1])(torch.eye(n, dtype=self.dtype, device=z.device))
        return r, tang.transpose(0, 1)

    def extra_derivatives(self, e: ExtraCost, values: dict):
        """(value, grad (n_free,), hess (n_free, n_free)) of one extra term."""
        if e.grad_hess is not None:
            v, gfull, hfull = e.grad_hess(values)
            i = self.free_idx
            return v, gfull[i], hfull[i][:, i]
        z = self.P.new_zeros(self.n_free)
        f = lambda dg: e.fn(self.chart(values, dg))  # noqa: E731
        g = torch.func.grad(f)(z)
        H = torch.func.jacfwd(torch.func.grad(f))(z)
        return e.fn(values), g, 0.5 * (H + H.T)


    def exact_hessian(self, values: dict, x) -> Linearization:
        """Exact second derivatives of F in the same block layout (forward-over-reverse autodiff).

        Directions: the n free global coordinates, then each local coordinate k set on every sample
        at once (colour classes t mod 3 when chain residuals couple neighbours, so the off-diagonal
        blocks separate).  Used for Laplace covariances; needs ``fn``s that reverse- and
        forward-differentiate (analytic ``jac``s are not used here).
        """
        n, T, d = self.n_free, self.T, self.d
        z = self.P.new_zeros(n)
        if x is None:
            f = lambda dg: self._total_cost_tensor(self.chart(values, dg), None)  # noqa: E731
            g = torch.func.grad(f)(z)
            H = torch.func.jacfwd(torch.func.grad(f))(z)
            return Linearization(float(f(z).detach()), 0.5 * (H + H.T), None, None, None, -g, None)
        f = lambda dg, ex: self._total_cost_tensor(self.chart(values, dg), x + ex)  # noqa: E731
        gf = torch.func.grad(f, argnums=(0, 1))
        ex0 = torch.zeros_like(x)
        ncol = 3 if self.local_structure == "tridiagonal" else 1
        td = torch.cat((torch.eye(n, dtype=x.dtype, device=x.device), x.new_zeros(ncol * d, n)), 0)
        tx = [x.new_zeros(n, T, d)]
        tsel = torch.arange(T, device=x.device)
        for c in range(ncol):
            on = (tsel % ncol == c).to(x.dtype)[:, None] if ncol > 1 else torch.ones(T, 1, dtype=x.dtype, device=x.device)
            tx.append(torch.eye(d, dtype=x.dtype, device=x.device)[:, None, :] * on[None])
        tx = torch.cat(tx, 0)
        (gd, gx), (hd, hx) = self._vmap(lambda a, b: jvp(gf, (z, ex0), (a, b)))(td, tx)
        gd, gx = gd[0], gx[0]
        U = hd[:n]  # (n, n)
        W = hx[:n].permute(1, 0, 2)  # (T, n, d)
        V = x.new_zeros(T, d, d)
        V_off = x.new_zeros(max(T - 1, 0), d, d) if ncol > 1 else None
        for c in range(ncol):
            blk = hx[n + c * d:n + (c + 1) * d]  # (d=k, T, d) : column k of the blocks
            sel = tsel % ncol == c
            V[sel] = blk.permute(1, 2, 0)[sel]
            if ncol > 1:
                nxt = (tsel % ncol == (c + 1) % ncol) & (tsel > 0)
                # ∂g_{t}/∂x_{t−1}[k] = V_{t,t−1}[:, k] = V_off_{t−1}[k, :]
                V_off[tsel[nxt] - 1] = blk.permute(1, 0, 2)[nxt]
        cost = float(f(z, ex0).detach())
        return Linearization(cost, 0.5 * (U + U.T), W, 0.5 * (V + V.transpose(-1, -2)), V_off, -gd, -gx)

"""The factor-graph least-squares problem of the structured LM (DESIGN §6): global blocks
(:class:`~accel_bayes.inference.lm.Variable`), optional locals x (T, d), residual groups
(:mod:`.residuals`) and extra terms — its layout, charts, cost and Gauss–Newton normal equations.
Its derivatives are in :mod:`.derivatives`."""
from __future__ import annotations

import math
from dataclasses import replace

import torch

from ...physics.geometry import boxplus, quat_mul
from .derivatives import ProblemDerivatives
from .protocol import Linearization
from .residuals import ChainResidual, ExtraCost, GlobalResidual, SampleResidual
from .robust import apply_robust, get_loss, robust_weights
from .variables import EUCLIDEAN, QUATERNION, Variable

__all__ = ["Problem"]

_CHAIN_CHUNK = 2048  # pairs per chunk when accumulating chain-residual blocks (cache-sized temporaries)


class Problem(ProblemDerivatives):
    """A factor-graph least-squares problem: global blocks, optional locals, residual groups.

    Parameters
    ----------
    globals : dict name → :class:`Variable` (or a tensor, taken as a free Euclidean block).
    locals : (T, d) tensor of initial local blocks, or None.
    residuals : list of :class:`SampleResidual`, :class:`ChainResidual`, :class:`GlobalResidual`.
    extra : :class:`ExtraCost`, a list of them, or None.
    local_structure : "auto" (tridiagonal iff a ChainResidual is present), "diagonal",
        "tridiagonal".
    dtype, device : cast every tensor (default: float64 on the device of the given tensors).
    jac_chunk : optional ``chunk_size`` for the vmap over Jacobian directions (memory bound).
    """

    def __init__(self, globals: dict, locals: torch.Tensor | None, residuals: list, extra=None, *,
                 local_structure: str = "auto", dtype=torch.float64, device=None, jac_chunk: int | None = None):
        if not isinstance(globals, dict):
            raise ValueError("globals: expected a dict name → Variable")
        self.dtype = dtype
        self.device = device
        self.variables: dict[str, Variable] = {}
        for name, v in globals.items():
            if not isinstance(v, Variable):
                v = Variable(torch.as_tensor(v))
            val = v.value.to(dtype=dtype, device=device if device is not None else v.value.device)
            fixed = v.fixed
            if isinstance(fixed, torch.Tensor):
                fixed = fixed.to(device=val.device)
            self.variables[name] = Variable(val, v.manifold, fixed)
        if locals is not None:
            locals = torch.as_tensor(locals)
            locals = locals.to(dtype=dtype, device=device if device is not None else locals.device)
            if locals.dim() != 2:
                raise ValueError(f"locals: expected shape (T, d), got {tuple(locals.shape)}")
        self.x0 = locals
        self.sample_residuals = [r for r in residuals if isinstance(r, SampleResidual)]
        self.chain_residuals = [r for r in residuals if isinstance(r, ChainResidual)]
        self.global_residuals = [r for r in residuals if isinstance(r, GlobalResidual)]
        unknown = [r for r in residuals if not isinstance(r, (SampleResidual, ChainResidual, GlobalResidual))]
        if unknown:
            raise ValueError(f"residuals: unknown residual type {type(unknown[0]).__name__}")
        if self.chain_residuals and locals is None:
            raise ValueError("a ChainResidual needs local variables")
        if extra is None:
            extra = []
        elif isinstance(extra, ExtraCost):
            extra = [extra]
        self.extra = list(extra)
        for r in self.sample_residuals + self.chain_residuals + self.global_residuals:
            r.loss = get_loss(r.loss)
        if local_structure not in ("auto", "diagonal", "tridiagonal"):
            raise ValueError(f"local_structure: expected 'auto', 'diagonal' or 'tridiagonal', got {local_structure!r}")
        if local_structure == "auto":
            local_structure = "tridiagonal" if self.chain_residuals else "diagonal"
        if local_structure == "diagonal" and self.chain_residuals:
            raise ValueError("local_structure='diagonal' is incompatible with chain residuals")
        self.local_structure = local_structure
        self.jac_chunk = jac_chunk
        self._build_layout()

    # ------------------------------------------------------------------ layout
    def _build_layout(self):
        self.offsets, self.sizes = {}, {}
        off = 0
        masks = []
        for name, v in self.variables.items():
            size = int(math.prod(v.tangent_shape))
            self.offsets[name], self.sizes[name] = off, size
            masks.append(v.free_mask().reshape(-1))
            off += size
        self.n_tangent = off
        dev = self.x0.device if self.x0 is not None else (
            next(iter(self.variables.values())).value.device if self.variables else self.device)
        mask = torch.cat(masks) if masks else torch.zeros(0, dtype=torch.bool, device=dev)
        self.free_idx = torch.nonzero(mask).flatten()
        self.n_free = int(self.free_idx.numel())
        # P maps free coordinates into the full tangent vector; a matmul keeps it vmap-friendly.
        self.P = torch.zeros(self.n_tangent, self.n_free, dtype=self.dtype, device=dev)
        self.P[self.free_idx, torch.arange(self.n_free, device=dev)] = 1.0
        self._device = dev

    @property
    def T(self) -> int:
        return 0 if self.x0 is None else int(self.x0.shape[0])

    @property
    def d(self) -> int:
        return 0 if self.x0 is None else int(self.x0.shape[1])

    def free_labels(self) -> list[tuple[str, tuple]]:
        """(block name, tangent index) of every free coordinate, in the order of the information matrix."""
        out = []
        for name, v in self.variables.items():
            idx = torch.nonzero(v.free_mask()).tolist()
            out.extend((name, tuple(i)) for i in idx)
        return out

    def initial_values(self) -> dict[str, torch.Tensor]:
        vals = {}
        for name, v in self.variables.items():
            if v.manifold == QUATERNION:
                free_any = v.free_mask().any(-1, keepdim=True)
                vals[name] = torch.where(free_any, v.value / v.value.norm(dim=-1, keepdim=True), v.value)
            else:
                vals[name] = v.value.clone()
        return vals

    # ------------------------------------------------------------------ charts
    def _split(self, full: torch.Tensor, name: str) -> torch.Tensor:
        o, s = self.offsets[name], self.sizes[name]
        return full[..., o:o + s].reshape(*full.shape[:-1], *self.variables[name].tangent_shape)

    def chart(self, values: dict, delta_free: torch.Tensor) -> dict:
        """Globals displaced by free tangent coordinates, through a smooth second-order chart
        (used for derivatives at δ = 0 only)."""
        full = self.P @ delta_free
        out = {}
        for name, v in self.variables.items():
            dv = self._split(full, name)
            if v.manifold == EUCLIDEAN:
                out[name] = values[name] + dv
            else:
                half = 0.5 * dv
                w = 1.0 - 0.5 * (half * half).sum(-1, keepdim=True)
                out[name] = quat_mul(values[name], torch.cat((w, half), -1))
        return out

    def retract(self, values: dict, delta_free: torch.Tensor) -> dict:
        """The update g ⊞ δ: Euclidean addition, quaternion ``boxplus`` (exact, re-normalised)."""
        full = self.P @ delta_free
        out = {}
        for name, v in self.variables.items():
            dv = self._split(full, name)
            if v.manifold == EUCLIDEAN:
                out[name] = values[name] + dv
            else:
                free_any = v.free_mask().any(-1, keepdim=True)
                out[name] = torch.where(free_any, boxplus(values[name], dv), values[name])
        return out

    # ------------------------------------------------------------------ cost
    def cost_terms(self, values: dict, x: torch.Tensor | None) -> dict[str, float]:
        """Cost of every residual group / extra term (by name; repeated names are summed)."""
        terms: dict[str, float] = {}

        def add(k, v):
            terms[k] = terms.get(k, 0.0) + float(v)

        for r in self.sample_residuals:
            add(r.name, apply_robust(r.fn(values, x, r.data), [], r.loss, r.group_size)[0])
        for r in self.chain_residuals:
            add(r.name, apply_robust(r.fn(values, x[:-1], x[1:], r.data), [], r.loss, r.group_size)[0])
        for r in self.global_residuals:
            add(r.name, apply_robust(r.fn(values).reshape(1, -1), [], r.loss, None)[0])
        for e in self.extra:
            add(e.name, e.fn(values))
        return terms

    def cost(self, values: dict, x: torch.Tensor | None) -> float:
        """F(g, x) = Σ ½ ρ(‖r‖²) + Σ extra."""
        with torch.no_grad():
            return float(sum(self.cost_terms(values, x).values()))

    def _total_cost_tensor(self, values, x):
        c = x.new_zeros(()) if x is not None else self.P.new_zeros(())
        for r in self.sample_residuals:
            c = c + apply_robust(r.fn(values, x, r.data), [], r.loss, r.group_size)[0]
        for r in self.chain_residuals:
            c = c + apply_robust(r.fn(values, x[:-1], x[1:], r.data), [], r.loss, r.group_size)[0]
        for r in self.global_residuals:
            c = c + apply_robust(r.fn(values).reshape(1, -1), [], r.loss, None)[0]
        for e in self.extra:
            c = c + e.fn(values)
        return c

    # ------------------------------------------------------------------ normal equations
    def linearize(self, values: dict, x, *, step: bool = True) -> Linearization:
        """Gauss–Newton normal-equation blocks at (values, x).

        step=True projects extra-term Hessians with ``step_hessian='psd'`` on the PSD cone (used
        inside LM); step=False keeps them exact (information matrices).
        """
        n, T, d = self.n_free, self.T, self.d
        ref = self.P
        U = ref.new_zeros(n, n)
        b_g = ref.new_zeros(n)
        # W and V are left unwritten until the first per-sample group that reaches them stores its
        # products there (no zeroing pass over the long blocks; zeroed below if no group does)
        W = ref.new_empty(T, n, d) if x is not None else None
        V = ref.new_empty(T, d, d) if x is not None else None
        fresh = [W is not None, V is not None]
        b_x = ref.new_zeros(T, d) if x is not None else None
        V_off = ref.new_zeros(max(T - 1, 0), d, d) if (x is not None and self.local_structure == "tridiagonal") else None
        cost = ref.new_zeros(())
        Vc = None
        for res in self.sample_residuals:
            for a, b, rc in self._sample_chunks(res, x):
                xs = None if x is None else x[a:b]
                r, Jg, Jx = self.sample_jacobians(rc, values, xs)
                if step and res.local_hessian is not None and x is not None:
                    w = robust_weights(r, res.loss, res.group_size)
                    C = res.local_hessian(values, xs, rc.data, r if w is None else r * w)
                    if Vc is None:
                        Vc = C.new_zeros(T, d, d)
                    Vc[a:b] += C
                c, r, (Jg, Jx) = apply_robust(r, [Jg, Jx], res.loss, res.group_size)
                cost = cost + c
                sl = slice(a, b)
                wrote = self._accumulate(U, b_g, None if W is None else W[sl], None if V is None else V[sl],
                                         None if b_x is None else b_x[sl], r, Jg, Jx, fresh)
            fresh = [f and not w for f, w in zip(fresh, wrote)]
        if fresh[0]:
            W.zero_()
        if fresh[1]:
            V.zero_()
        for res in self.chain_residuals:
            r, Jg, A, B = self.chain_jacobians(res, values, x)
            c, r, (Jg, A, B) = apply_robust(r, [Jg, A, B], res.loss, res.group_size)
            cost = cost + c
            # pairs in chunks: the (chunk, d, d) products stay in cache on long records
            Tm = r.shape[0]
            cs = max(1, min(Tm, _CHAIN_CHUNK))
            for a in range(0, Tm, cs):
                b = min(a + cs, Tm)
                ra, Aa, Ba = r[a:b], A[a:b], B[a:b]
                if Jg is not None and n:
                    Jga = Jg[a:b]
                    Jf = Jga.reshape(-1, n)
                    U += Jf.T @ Jf
                    b_g -= Jf.T @ ra.reshape(-1)
                    W[a:b] += Jga.transpose(-1, -2) @ Aa
                    W[a + 1:b + 1] += Jga.transpose(-1, -2) @ Ba
                At, Bt = Aa.transpose(-1, -2), Ba.transpose(-1, -2)
                V[a:b] += At @ Aa
                V[a + 1:b + 1] += Bt @ Ba
                V_off[a:b] += At @ Ba
                b_x[a:b] -= (At @ ra.unsqueeze(-1)).squeeze(-1)
                b_x[a + 1:b + 1] -= (Bt @ ra.unsqueeze(-1)).squeeze(-1)
        for res in self.global_residuals:
            r, J = self.global_jacobian(res, values)
            if J is None:
                J = r.new_zeros(r.numel(), n)
            c, r, (J,) = apply_robust(r.reshape(1, -1), [J.unsqueeze(0)], res.loss, None)
            cost = cost + c
            U += J[0].T @ J[0]
            b_g -= J[0].T @ r[0]
        for e in self.extra:
            v, g, H = self.extra_derivatives(e, values)
            cost = cost + v
            b_g -= g
            if step and e.step_hessian == "psd" and n:
                lam, Q = torch.linalg.eigh(H)
                H = (Q * lam.clamp_min(0)) @ Q.T
            U += H
        if Vc is not None:
            Vn = V + 0.5 * (Vc + Vc.transpose(-1, -2))
            lam, Q = torch.linalg.eigh(Vn)
            lam = torch.maximum(lam, 1e-6 * lam.abs().amax(-1, keepdim=True))
            V = (Q * lam.unsqueeze(-2)) @ Q.transpose(-1, -2)
        return Linearization(float(cost.detach()), 0.5 * (U + U.T), W, V, V_off, b_g, b_x)

    def _sample_chunks(self, res: SampleResidual, x):
        """(start, stop, group) per chunk of samples: the group itself over all samples unless it
        asks for ``chunk`` and has locals, else a copy with ``data`` sliced to the chunk."""
        T = 0 if x is None else x.shape[0]
        cs = res.chunk
        if x is None or not cs or T <= cs:
            yield 0, T, res
            return

        def cut(dd, a, b):
            if dd is None:
                return None
            if isinstance(dd, torch.Tensor):
                return dd[a:b]
            if isinstance(dd, tuple):
                return tuple(cut(e, a, b) for e in dd)
            raise TypeError(f"SampleResidual {res.name!r}: chunk needs data None, a tensor or a tuple "
                            f"of tensors, got {type(dd).__name__}")

        for a in range(0, T, cs):
            b = min(a + cs, T)
            yield a, b, replace(res, data=cut(res.data, a, b))

    def _accumulate(self, U, b_g, W, V, b_x, r, Jg, Jx, fresh=(False, False)):
        """Add one per-sample group's JᵀJ and −Jᵀr to the blocks (matmuls, no einsum paths).

        fresh = (W unwritten, V unwritten): store the products there instead of adding them.
        Returns (wrote W, wrote V)."""
        n = U.shape[-1]
        wrote = [False, False]
        if Jg is not None and n:
            Jf = Jg.reshape(-1, n)
            U += Jf.T @ Jf
            b_g -= Jf.T @ r.reshape(-1)
            if Jx is not None:
                if fresh[0]:
                    torch.matmul(Jg.transpose(-1, -2), Jx, out=W)
                else:
                    W += Jg.transpose(-1, -2) @ Jx
                wrote[0] = True
        if Jx is not None:
            Jxt = Jx.transpose(-1, -2)
            if fresh[1]:
                torch.matmul(Jxt, Jx, out=V)
            else:
                V += Jxt @ Jx
            wrote[1] = True
            b_x -= (Jxt @ r.unsqueeze(-1)).squeeze(-1)
        return wrote

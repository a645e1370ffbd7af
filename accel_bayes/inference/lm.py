"""One structured Levenberg–Marquardt solver for the factor graphs of the package (DESIGN §6).

The problems it solves — the [C21] MAP, the [S16] self-calibration (§IV, eq. 15), the [S16]
conventional calibration (eq. 19) — share one shape: a few **global** variable blocks (positions,
orientations on their manifold, sensor parameters) that touch every sample, and **local**
per-sample blocks x_t ∈ ℝ^d (motion states) that touch only their own sample and, with a process
model, their neighbours.  The cost is

    F = Σ_groups ½ Σ_blocks ρ(‖r_b‖²)  +  Σ extra(g)

with whitened residuals r (information matrices already applied through their square roots) and
optional smooth non-least-squares terms on the globals (the (T/2)·log|M(θ)| of DESIGN §4).

Pieces (PyPose ``optim`` split, STYLE.md), each swappable and testable alone:

* problem description — :class:`Variable`, :class:`SampleResidual`, :class:`ChainResidual`,
  :class:`GlobalResidual`, :class:`ExtraCost`, :class:`Problem` (this module);
* linear solver — :class:`~accel_bayes.inference.linear.SchurComplementSolver` (locals eliminated
  by the Schur complement; block-diagonal or block-tridiagonal; O(T) per iteration);
* damping — :mod:`~accel_bayes.inference.damping` (Nielsen's rule by default, Marquardt scaling);
* robust kernel — :mod:`~accel_bayes.inference.robust` (Huber, Cauchy; IRLS reweighting);
* stopping rules — :class:`StoppingRule` (ftol / xtol / gtol / max_iter, one place).

Two loops share these pieces: :class:`LevenbergMarquardt` (one structured problem, Schur
elimination of the locals) and :class:`BatchedLevenbergMarquardt` (many small independent dense
problems solved together — one λ, one stopping reason and one convergence flag per problem, no
Python loop over problems; used by motion estimation and the intrinsics fit).  Both see a
problem only through a small protocol: ``linearize`` (cost, gradient and Gauss–Newton blocks at a
point), ``cost`` and ``retract`` (apply a tangent step) — :class:`Problem` is one implementation,
``accel_bayes.mismatch.refine`` has another.

Variables
---------
Globals are named blocks. A Euclidean block is any tensor; its tangent is itself.  A quaternion
block holds unit quaternions (..., 4) (w, x, y, z) and is updated by
``geometry.boxplus(q, δ) = q ∘ exp(δ)`` with δ a rotation vector (rad) — the exponential-map
variant of [S16] eq. 17–18 — so its tangent shape is (..., 3).  Any part of a block can be
``fixed`` (a bool, or a bool mask over the tangent shape or a prefix of it, e.g. (A,) to fix whole
rows of (A, 3) positions).  The global tangent vector concatenates the blocks in insertion order
(each flattened, C order); the *free* coordinates are that vector with the fixed ones removed —
this is the ordering of :meth:`LMResult.information`.

Locals are one tensor x (T, d), Euclidean.

Residual functions
------------------
* ``SampleResidual.fn(g, x, data) -> (T, m)``: per-sample residuals; g is the dict of global
  values, x (T, d) the locals (None if the problem has none), data whatever the group was given
  (passed through unchanged; typically per-sample tensors with leading dim T).  Analytic
  Jacobians: ``jac(g, x, data) -> (Jg, Jx)`` with Jg a dict name → (T, m, tangent size of that
  block) (missing names: no dependence; an empty dict: none at all) and Jx (T, m, d).  Optional
  ``local_hessian(g, x, data, r) -> (T, d, d)`` gives LM a Newton model in the locals
  (large-residual problems; see :class:`SampleResidual`).
* ``ChainResidual.fn(g, x_prev, x_next, data) -> (T−1, m)``: residuals between x_t and x_{t+1}
  ([S16] eq. 14); ``jac -> (Jg dict of (T−1, m, ·), A (T−1, m, d), B (T−1, m, d))``.
* ``GlobalResidual.fn(g) -> (m,)``: priors; ``jac(g) -> dict name → (m, ·)``.
* ``ExtraCost.fn(g) -> ()``: a smooth term added to F; ``grad_hess(g) -> (value, grad (N,),
  hess (N, N))`` in the full global tangent layout, else autograd.

Without ``jac`` the Jacobians come from forward-mode autodiff batched over the samples: the
residual of sample t depends on x_t alone, so one ``torch.func.jvp`` with the tangent e_k on
every sample at once yields column k of all T Jacobians; ``torch.func.vmap`` runs the n + d
directions together.  The function must therefore be written batched over T (as it is anyway)
with ops that vmap supports.  Quaternion derivatives are taken through the second-order chart
q ∘ (1 − |δ|²/8, δ/2), which agrees with q ∘ exp(δ) to second order at δ = 0.  (The first use of
a ``torch.func`` transform in a process imports ``torch._dynamo``, a one-off of a few seconds;
problems with analytic ``jac``/``grad_hess`` everywhere never pay it in LM.)

Information matrices: :meth:`LMResult.information` gives the Schur-reduced information of the
free globals (locals marginalised) from the Gauss–Newton blocks or from the exact Hessian
(:meth:`Problem.exact_hessian`, forward-over-reverse autodiff, colour classes t mod 3 for chains).

Example
-------
>>> import torch
>>> from accel_bayes.inference.lm import Variable, SampleResidual, Problem, solve
>>> t = torch.linspace(0, 1, 20, dtype=torch.float64)
>>> y = 2.0 * torch.exp(-1.5 * t)
>>> prob = Problem({"p": Variable(torch.tensor([1.0, -1.0], dtype=torch.float64))}, None,
...                [SampleResidual(lambda g, x, d: (g["p"][0] * torch.exp(g["p"][1] * d[0]) - d[1]).unsqueeze(-1),
...                                data=(t, y))])
>>> res = solve(prob)
>>> [round(v, 6) for v in res.values["p"].tolist()], res.converged
([2.0, -1.5], True)
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import torch
from torch.func import jvp, vmap

from ..physics.geometry import boxplus, quat_mul
from .damping import DampingStrategy, get_damping
from .linear import NotPositiveDefinite, SchurComplementSolver, cholesky, damped_step
from .robust import RobustLoss, apply_robust, get_loss, robust_weights

__all__ = [
    "Variable",
    "SampleResidual",
    "ChainResidual",
    "GlobalResidual",
    "ExtraCost",
    "Problem",
    "Linearization",
    "StoppingRule",
    "LevenbergMarquardt",
    "LMResult",
    "BatchedLevenbergMarquardt",
    "BatchedLMResult",
    "solve",
]

_CHAIN_CHUNK = 2048  # pairs per chunk when accumulating chain-residual blocks (cache-sized temporaries)

EUCLIDEAN = "euclidean"
QUATERNION = "quaternion"


# ===================================================================== problem description

@dataclass
class Variable:
    """A global variable block.

    value : tensor — Euclidean (any shape) or unit quaternions (..., 4) (w, x, y, z).
    manifold : "euclidean" (default) or "quaternion" (tangent: rotation vectors (..., 3), rad).
    fixed : bool or bool tensor over the tangent shape (or a prefix of it) — True = held fixed.
    """

    value: torch.Tensor
    manifold: str = EUCLIDEAN
    fixed: Any = False

    def __post_init__(self):
        if self.manifold not in (EUCLIDEAN, QUATERNION):
            raise ValueError(f"Variable.manifold: expected 'euclidean' or 'quaternion', got {self.manifold!r}")
        if self.manifold == QUATERNION and (self.value.dim() == 0 or self.value.shape[-1] != 4):
            raise ValueError(f"Variable: a quaternion block needs shape (..., 4), got {tuple(self.value.shape)}")

    @property
    def tangent_shape(self) -> tuple:
        return tuple(self.value.shape) if self.manifold == EUCLIDEAN else tuple(self.value.shape[:-1]) + (3,)

    def free_mask(self) -> torch.Tensor:
        """(tangent_shape) bool, True where the coordinate is optimised."""
        shp = self.tangent_shape
        m = torch.as_tensor(self.fixed, dtype=torch.bool, device=self.value.device)
        if m.dim() > len(shp) or tuple(m.shape) != tuple(shp[: m.dim()]) and m.dim() > 0:
            raise ValueError(f"Variable.fixed: expected a bool or a mask of shape {shp} (or a prefix), "
                             f"got shape {tuple(m.shape)}")
        while m.dim() < len(shp):
            m = m.unsqueeze(-1)
        return ~m.expand(shp)


@dataclass
class SampleResidual:
    """Per-sample residual group r_t(g, x_t) (T, m); see the module docstring for ``fn``/``jac``.

    loss : robust loss (RobustLoss, "huber", "cauchy") or None; group_size : length of a robust
    block along m (None = the whole row of a sample).
    local_hessian : optional ``local_hessian(g, x, data, r) -> (T, d, d)``, the second-order term
        Σ_m r_tm ∂²r_tm/∂x_t² of the local blocks (r given with robust weights ρ' applied).  LM
        steps then use a Newton model in the locals: V_t ← PSD part of (J_xᵀJ_x + that term)
        (eigenvalues clamped at 1e-6 of the block's largest).  This pays off in large-residual
        problems, where Gauss–Newton converges only linearly (e.g. the [C21] MAP on real data
        with a wide gyroscope posterior: 41 instead of > 300 iterations).  Information matrices
        are not affected.
    """

    fn: Callable
    data: Any = None
    jac: Callable | None = None
    loss: Any = None
    group_size: int | None = None
    name: str = "sample"
    local_hessian: Callable | None = None
    chunk: int | None = None
    """Linearise in chunks of this many samples (None: all at once).  Requires ``data`` to be None,
    a tensor or a tuple of tensors with leading dim T (sliced along with x); the blocks of long
    records are then built with cache-sized intermediates (per-iteration time linear in T)."""


@dataclass
class ChainResidual:
    """Pairwise residual group r_t(g, x_t, x_{t+1}) (T−1, m) — e.g. the [S16] process model (eq. 14)."""

    fn: Callable
    data: Any = None
    jac: Callable | None = None
    loss: Any = None
    group_size: int | None = None
    name: str = "chain"


@dataclass
class GlobalResidual:
    """Residuals on the globals only, r(g) (m,) — e.g. Gaussian priors (θ − μ)/σ."""

    fn: Callable
    jac: Callable | None = None
    loss: Any = None
    name: str = "global"


@dataclass
class ExtraCost:
    """A smooth non-least-squares term c(g) added to the cost (e.g. (T/2)·log|M(θ)|, DESIGN §4).

    step_hessian : "exact" (default) uses its Hessian as is inside LM steps (Newton-like local
    convergence; an indefinite system is answered by raising λ); "psd" projects it on the PSD cone
    (always-PD steps, but only linear convergence where the term has negative curvature).
    Information matrices always use the exact Hessian.
    """

    fn: Callable
    grad_hess: Callable | None = None
    step_hessian: str = "exact"
    name: str = "extra"


@dataclass
class Linearization:
    """Normal-equation blocks at one point (see :mod:`accel_bayes.inference.linear`).

    cost: float; U (n, n); W (T, n, d) or None; V (T, d, d) or None; V_off (T−1, d, d) or None;
    b_g (n,) = −∂F/∂g; b_x (T, d) = −∂F/∂x (or None).
    """

    cost: float
    U: torch.Tensor
    W: torch.Tensor | None
    V: torch.Tensor | None
    V_off: torch.Tensor | None
    b_g: torch.Tensor
    b_x: torch.Tensor | None

    @property
    def grad_inf(self) -> float:
        g = self.b_g.abs().max() if self.b_g.numel() else self.b_g.new_zeros(())
        if self.b_x is not None and self.b_x.numel():
            g = torch.maximum(g, self.b_x.abs().max())
        return float(g)

    def diag(self) -> tuple[torch.Tensor, torch.Tensor | None]:
        dg = torch.diagonal(self.U)
        dx = None if self.V is None else torch.diagonal(self.V, dim1=-2, dim2=-1)
        return dg, dx


class Problem:
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

    # ------------------------------------------------------------------ Jacobians
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


# ===================================================================== stopping rules

class StoppingRule:
    """All stopping tests of the LM loop in one place.

    ftol : stop (converged) after an accepted step with F_old − F_new ≤ ftol·F_old.
    xtol : stop (converged) when ‖δ‖ ≤ xtol·(‖x‖ + xtol) (‖·‖ over free globals and locals; ‖x‖
        over all variable values), accepted or not — no step of that size can change anything.
    gtol : stop (converged) when ‖∇F‖∞ ≤ gtol at a linearisation point.
    max_iter : stop (not converged) after that many step attempts (accepted or rejected).
    flat_rejected : also stop (converged, "ftol") after a *rejected* step that changed F by at
        most ftol·F either way — at round-off level no step can make progress, and raising λ
        until the xtol test fires only costs iterations (default False).
    Beyond these, the loop stops unconverged with "damping_limit" when λ exceeds the strategy's
    lambda_max, and with "non_finite" when the linearisation is not finite.
    """

    CONVERGED = ("gtol", "ftol", "xtol")
    # reason codes of the batched mode (index into REASONS; "" = still running)
    REASONS = ("", "gtol", "ftol", "xtol", "max_iter", "damping_limit", "non_finite")

    def __init__(self, max_iter: int = 100, ftol: float = 1e-10, xtol: float = 1e-10, gtol: float = 1e-10, *,
                 flat_rejected: bool = False):
        if max_iter < 0:
            raise ValueError(f"max_iter must be ≥ 0, got {max_iter}")
        for nm, v in (("ftol", ftol), ("xtol", xtol), ("gtol", gtol)):
            if not v >= 0:
                raise ValueError(f"{nm} must be ≥ 0, got {v}")
        self.max_iter, self.ftol, self.xtol, self.gtol = int(max_iter), float(ftol), float(xtol), float(gtol)
        self.flat_rejected = bool(flat_rejected)

    # The tests themselves, each written once; they take floats (one problem) or (B,) tensors
    # (batched mode) alike.
    def _gtol(self, grad_inf):
        return grad_inf <= self.gtol

    def _ftol(self, accepted, cost_old, cost_new):
        hit = accepted & ((cost_old - cost_new) <= self.ftol * abs(cost_old))
        if self.flat_rejected:
            hit = hit | (~accepted & (abs(cost_old - cost_new) <= self.ftol * abs(cost_old)))
        return hit

    def _xtol(self, step_norm, x_norm):
        return step_norm <= self.xtol * (x_norm + self.xtol)

    def at_linearization(self, grad_inf: float, n_iter: int) -> str | None:
        if not math.isfinite(grad_inf):
            return "non_finite"
        if self._gtol(grad_inf):
            return "gtol"
        if n_iter >= self.max_iter:
            return "max_iter"
        return None

    def after_step(self, accepted: bool, cost_old: float, cost_new: float, step_norm: float, x_norm: float) -> str | None:
        if self._ftol(accepted, cost_old, cost_new):
            return "ftol"
        if self._xtol(step_norm, x_norm):
            return "xtol"
        return None

    def batched_at_linearization(self, grad_inf: torch.Tensor) -> torch.Tensor:
        """Reason codes (B,) (index into :attr:`REASONS`, 0 = go on) at a linearisation point;
        ``max_iter`` is the loop's to apply (one count for all problems)."""
        R = self.REASONS
        code = torch.where(self._gtol(grad_inf), R.index("gtol"), 0)
        return torch.where(torch.isfinite(grad_inf), code, R.index("non_finite"))

    def batched_after_step(self, accepted, cost_old, cost_new, step_norm, x_norm) -> torch.Tensor:
        """Reason codes (B,) after a step attempt, as :meth:`after_step` per problem."""
        R = self.REASONS
        return torch.where(self._ftol(accepted, cost_old, cost_new), R.index("ftol"),
                           torch.where(self._xtol(step_norm, x_norm), R.index("xtol"), 0))


# ===================================================================== result

@dataclass
class LMResult:
    """Outcome of :meth:`LevenbergMarquardt.solve`.

    values : dict name → optimised global tensors; locals : (T, d) or None; cost : final F;
    converged : bool; reason : "gtol" | "ftol" | "xtol" (converged) or "max_iter" |
    "damping_limit" | "non_finite"; n_iter : step attempts; log : one dict per attempt with keys
    iteration, cost (after the attempt), step_norm, lambda, rho, accepted, grad_inf.
    """

    values: dict
    locals: torch.Tensor | None
    cost: float
    converged: bool
    reason: str
    n_iter: int
    log: list
    problem: Problem = field(repr=False)

    @property
    def globals(self) -> dict:
        return self.values

    def free_labels(self):
        """(block, tangent index) per row of :meth:`information`."""
        return self.problem.free_labels()

    def information(self, hessian: str = "gauss_newton") -> torch.Tensor:
        """Reduced information matrix of the free global coordinates at the optimum, locals
        marginalised: S = U − W V⁻¹ Wᵀ (Schur complement).  Its inverse is the Laplace covariance.

        hessian : "gauss_newton" (JᵀJ with robust weights, exact Hessians of extra terms) or
            "exact" (full second derivatives by autodiff, see :meth:`Problem.exact_hessian`).
        """
        if hessian == "gauss_newton":
            lin = self.problem.linearize(self.values, self.locals, step=False)
        elif hessian == "exact":
            lin = self.problem.exact_hessian(self.values, self.locals)
        else:
            raise ValueError(f"hessian: expected 'gauss_newton' or 'exact', got {hessian!r}")
        S = SchurComplementSolver(self.problem.local_structure).reduce(lin.U, lin.W, lin.V, lin.V_off)
        return 0.5 * (S + S.T)

    def covariance(self, hessian: str = "gauss_newton") -> torch.Tensor:
        """Laplace covariance of the free globals (inverse of :meth:`information`)."""
        S = self.information(hessian)
        L = cholesky(S, "reduced information matrix")
        return torch.cholesky_inverse(L)


# ===================================================================== the solver

class LevenbergMarquardt:
    """Levenberg–Marquardt on a :class:`Problem` with Schur elimination of the locals.

    Parameters
    ----------
    damping : DampingStrategy | "nielsen" | "marquardt" | None (Nielsen, Marquardt scaling).
    linear_solver : SchurComplementSolver or None (built from the problem's local structure).
    stopping : StoppingRule or None; or pass max_iter/ftol/xtol/gtol.
    progress : show a tqdm bar (cost, λ) — off by default.
    callback : called as callback(iteration, values, locals, log_entry) after each attempt.

    Problem protocol (what :meth:`solve` uses; :class:`Problem` implements it): ``n_free`` and
    ``local_structure`` ("diagonal"/"tridiagonal"); ``linearize(values, x) -> Linearization``;
    ``cost(values, x) -> float``; ``retract(values, δ_free) -> values``; and, only when
    :meth:`solve` is not given start values, ``initial_values()`` and ``x0``.

    One iteration = one step attempt: solve (H + λD) δ = b through the Schur complement, try
    g ⊞ δ_g, x + δ_x, accept if the gain ratio ρ > 0, update λ; re-linearise after acceptance.
    Per-iteration cost is linear in T.  Deterministic: no random numbers anywhere.
    """

    def __init__(self, damping=None, linear_solver: SchurComplementSolver | None = None,
                 stopping: StoppingRule | None = None, *, max_iter: int = 100, ftol: float = 1e-10,
                 xtol: float = 1e-10, gtol: float = 1e-10, progress: bool = False, desc: str = "LM",
                 callback: Callable | None = None):
        self.damping_spec = damping
        self.linear_solver = linear_solver
        self.stopping = stopping if stopping is not None else StoppingRule(max_iter, ftol, xtol, gtol)
        self.progress = bool(progress)
        self.desc = desc
        self.callback = callback

    @staticmethod
    def _norm(values: dict, x) -> float:
        s = sum(float((v * v).sum()) for v in values.values())
        if x is not None:
            s += float((x * x).sum())
        return math.sqrt(s)

    def solve(self, problem: Problem, values: dict | None = None, locals: torch.Tensor | None = None) -> LMResult:
        """Minimise F from the problem's initial values (or the given ones)."""
        damping: DampingStrategy = get_damping(self.damping_spec)
        solver = self.linear_solver or SchurComplementSolver(problem.local_structure)
        stop = self.stopping
        values = problem.initial_values() if values is None else {k: v.clone() for k, v in values.items()}
        x = (problem.x0.clone() if problem.x0 is not None else None) if locals is None else locals.clone()

        lin = problem.linearize(values, x)
        if not math.isfinite(lin.cost):
            raise ValueError("LM: the cost is not finite at the initial point")
        cost = lin.cost
        dg_h, dx_h = lin.diag()
        diag_h = torch.cat((dg_h, dx_h.reshape(-1))) if dx_h is not None else dg_h
        D = damping.scale(diag_h)
        damping.init(diag_h, D)
        log: list[dict] = []
        n_iter = 0
        reason = None
        bar = None
        if self.progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=stop.max_iter, desc=self.desc, leave=False)
        n = problem.n_free
        try:
            while True:
                reason = stop.at_linearization(lin.grad_inf, n_iter)
                if reason is not None:
                    break
                n_iter += 1
                lam = damping.lam
                Dg = D[:n]
                Dx = D[n:].reshape(lin.V.shape[:-1]) if lin.V is not None else None
                Ud = lin.U + torch.diag(lam * Dg)
                Vd = lin.V + torch.diag_embed(lam * Dx) if lin.V is not None else None
                entry = {"iteration": n_iter, "lambda": lam, "grad_inf": lin.grad_inf}
                try:
                    dg, dx = solver.solve(Ud, lin.W, Vd, lin.b_g, lin.b_x, lin.V_off)
                except NotPositiveDefinite:
                    damping.update(-math.inf, False)
                    entry.update(cost=cost, step_norm=float("nan"), rho=-math.inf, accepted=False)
                    log.append(entry)
                    if bar is not None:
                        bar.update(1)
                    if damping.exhausted:
                        reason = "damping_limit"
                        break
                    continue
                step_sq = float((dg * dg).sum())
                pred = float(dg @ (lin.b_g + lam * Dg * dg))
                if dx is not None:
                    step_sq += float((dx * dx).sum())
                    pred += float((dx * (lin.b_x + lam * Dx * dx)).sum())
                pred *= 0.5
                step_norm = math.sqrt(step_sq)
                new_values = problem.retract(values, dg)
                new_x = x + dx if dx is not None else x
                new_cost = problem.cost(new_values, new_x)
                if pred > 0 and math.isfinite(new_cost):
                    rho = (cost - new_cost) / pred
                else:
                    rho = -math.inf
                accepted = rho > 0
                entry.update(cost=new_cost if accepted else cost, step_norm=step_norm, rho=rho, accepted=accepted)
                log.append(entry)
                damping.update(rho, accepted)
                x_norm = self._norm(values, x)
                old_cost = cost
                if accepted:
                    values, x, cost = new_values, new_x, new_cost
                if self.callback is not None:
                    self.callback(n_iter, values, x, entry)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(cost=f"{cost:.6g}", lam=f"{lam:.2g}")
                reason = stop.after_step(accepted, old_cost, new_cost, step_norm, x_norm)
                if reason is not None:
                    break
                if accepted:
                    lin = problem.linearize(values, x)
                    dg_h, dx_h = lin.diag()
                    diag_h = torch.cat((dg_h, dx_h.reshape(-1))) if dx_h is not None else dg_h
                    D = damping.scale(diag_h)
                elif damping.exhausted:
                    reason = "damping_limit"
                    break
        finally:
            if bar is not None:
                bar.close()
        return LMResult(values=values, locals=x, cost=cost, converged=reason in StoppingRule.CONVERGED,
                        reason=reason, n_iter=n_iter, log=log, problem=problem)


# ===================================================================== batched mode

@dataclass
class BatchedLMResult:
    """Outcome of :meth:`BatchedLevenbergMarquardt.solve`, one entry per problem (batch shape B).

    x : (*B, n) solutions; cost : (*B,) F at x; b : (*B, n) −∇F at x; H : (*B, n, n) the
    Gauss–Newton matrix at x (its inverse is the Laplace covariance); converged : (*B,) bool;
    reason : (*B,) int64 codes into :attr:`StoppingRule.REASONS`; n_iter : loop iterations
    (the same for all problems: the loop runs until every problem has stopped).
    """

    x: torch.Tensor
    cost: torch.Tensor
    b: torch.Tensor
    H: torch.Tensor
    converged: torch.Tensor
    reason: torch.Tensor
    n_iter: int

    def reasons(self) -> list:
        """The stopping reason of each problem as a string (flattened batch order)."""
        return [StoppingRule.REASONS[int(c)] for c in self.reason.reshape(-1)]


class BatchedLevenbergMarquardt:
    """Levenberg–Marquardt on many small independent problems at once (no loop over problems).

    The problems share one size n and one ``linearize`` that evaluates all of them together —
    e.g. the 9 motion unknowns of every sample (:mod:`accel_bayes.motion_estimation`, batched over
    samples and geometry draws) or the 9 rest-model parameters of every IMU
    (:mod:`accel_bayes.prep.intrinsics`).  The pieces are those of :class:`LevenbergMarquardt`: the
    damping strategy (:mod:`~accel_bayes.inference.damping`, one λ per problem), the stopping
    rule (:class:`StoppingRule`, one reason per problem) and a batched Cholesky solve of the
    damped n×n systems; a problem whose damped matrix is not positive definite has its step
    refused and its λ raised, as in the structured solver.  Problems that have stopped keep their
    values (per-problem convergence masks) while the others go on.

    Protocol: ``linearize(x) -> (F (*B,), b (*B, n), H (*B, n, n))`` with F the cost in the
    ½‖r‖² convention, b = −∇F and H the Gauss–Newton matrix JᵀJ; ``retract(x, δ)`` (default
    x + δ) for non-Euclidean parameters.  One ``linearize`` per iteration (at the trial point;
    accepted problems keep it).

    Parameters: damping (DampingStrategy, "nielsen", "marquardt" or None = Nielsen with
    Marquardt scaling), stopping (StoppingRule) or max_iter/ftol/xtol/gtol.
    """

    def __init__(self, damping=None, stopping: StoppingRule | None = None, *, max_iter: int = 100,
                 ftol: float = 1e-10, xtol: float = 1e-10, gtol: float = 1e-10):
        self.damping_spec = damping
        self.stopping = stopping if stopping is not None else StoppingRule(max_iter, ftol, xtol, gtol)

    def solve(self, linearize: Callable, x0: torch.Tensor, retract: Callable | None = None, *,
              subset: bool = False) -> BatchedLMResult:
        """Minimise every problem from x0 (*B, n).

        subset : the problem can evaluate a subset of itself: ``linearize(x_sub (k, n), idx (k,))``
            with idx the indices of the problems (x0 must then be (B, n)).  Each iteration then
            evaluates only the problems still running — most stop after a few iterations, so the
            later ones cost little.
        """
        damping: DampingStrategy = get_damping(self.damping_spec)
        stop = self.stopping
        R = StoppingRule.REASONS
        if subset and x0.dim() != 2:
            raise ValueError(f"BatchedLevenbergMarquardt: subset mode needs x0 of shape (B, n), got {tuple(x0.shape)}")
        x = x0.clone()
        F, b, H = linearize(x, torch.arange(x.shape[0], device=x.device)) if subset else linearize(x)
        n = x.shape[-1]
        diag = torch.diagonal(H, dim1=-2, dim2=-1)
        D = damping.scale(diag)
        damping.init(diag, D, batched=True)
        reason = torch.zeros(F.shape, dtype=torch.long, device=x.device)
        n_iter = 0
        while True:
            active = reason == 0
            code = stop.batched_at_linearization(b.abs().amax(-1) if n else torch.zeros_like(F))
            reason = torch.where(active & (code > 0), code, reason)
            active = reason == 0
            if not bool(active.any()):
                break
            if n_iter >= stop.max_iter:
                reason = torch.where(active, R.index("max_iter"), reason)
                break
            n_iter += 1
            # the running problems (all of them without subset; their own tensors then)
            idx = torch.nonzero(active).squeeze(-1) if subset else None
            sel = (lambda t: t[idx]) if subset else (lambda t: t)  # noqa: E731
            xs, Fs, bs, Hs, Ds, lam, act = sel(x), sel(F), sel(b), sel(H), sel(D), sel(damping.lam), sel(active)
            step, ok = damped_step(Hs, bs, lam.unsqueeze(-1) * Ds)
            ok = ok & act
            pred = 0.5 * (step * (bs + lam.unsqueeze(-1) * Ds * step)).sum(-1)
            x_new = xs + step if retract is None else retract(xs, step)
            F_new, b_new, H_new = linearize(x_new, idx) if subset else linearize(x_new)
            good = ok & (pred > 0) & torch.isfinite(F_new)
            rho = torch.where(good, (Fs - F_new) / torch.where(good, pred, 1.0), -math.inf)
            accepted = good & (rho > 0)
            after = stop.batched_after_step(accepted, Fs, F_new, step.norm(dim=-1), xs.norm(dim=-1))
            xs = torch.where(accepted[..., None], x_new, xs)
            Fs = torch.where(accepted, F_new, Fs)
            bs = torch.where(accepted[..., None], b_new, bs)
            Hs = torch.where(accepted[..., None, None], H_new, Hs)
            if subset:
                rho_all = torch.full_like(F, -math.inf).index_put_((idx,), rho)
                acc_all = torch.zeros_like(active).index_put_((idx,), accepted)
                damping.update(rho_all, acc_all, active)
                x[idx], F[idx], b[idx], H[idx] = xs, Fs, bs, Hs
                D[idx] = torch.where(accepted[..., None], damping.scale(torch.diagonal(Hs, dim1=-2, dim2=-1)), Ds)
            else:
                damping.update(rho, accepted, active)
                x, F, b, H = xs, Fs, bs, Hs
                D = torch.where(accepted[..., None], damping.scale(torch.diagonal(H, dim1=-2, dim2=-1)), D)
            code = torch.where(ok, after, 0)
            code = torch.where((code == 0) & ~accepted & sel(damping.exhausted), R.index("damping_limit"), code)
            if subset:
                reason[idx] = code
            else:
                reason = torch.where(active, code, reason)
        conv = torch.zeros_like(reason, dtype=torch.bool)
        for nm in StoppingRule.CONVERGED:
            conv |= reason == R.index(nm)
        return BatchedLMResult(x=x, cost=F, b=b, H=H, converged=conv, reason=reason, n_iter=n_iter)


def solve(problem: Problem, *, damping=None, max_iter: int = 100, ftol: float = 1e-10, xtol: float = 1e-10,
          gtol: float = 1e-10, progress: bool = False, callback: Callable | None = None) -> LMResult:
    """Convenience wrapper: ``LevenbergMarquardt(damping, max_iter=…, …).solve(problem)``."""
    return LevenbergMarquardt(damping, max_iter=max_iter, ftol=ftol, xtol=xtol, gtol=gtol,
                              progress=progress, callback=callback).solve(problem)

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

* the protocol — :mod:`.protocol` (:class:`Linearization`, what a solver asks of a problem);
* problem description — :mod:`.variables` (:class:`Variable`), :mod:`.residuals`
  (:class:`SampleResidual`, :class:`ChainResidual`, :class:`GlobalResidual`, :class:`ExtraCost`),
  :mod:`.problem` (:class:`Problem`: layout, charts, cost, normal equations) with its
  derivatives in :mod:`.derivatives` (analytic Jacobians or forward-mode autodiff, exact Hessian);
* linear solver — :class:`~accel_bayes.inference.lm.linear.SchurComplementSolver` (locals
  eliminated by the Schur complement; block-diagonal or block-tridiagonal; O(T) per iteration);
* damping — :mod:`~accel_bayes.inference.lm.damping` (Nielsen's rule by default, Marquardt scaling);
* robust kernel — :mod:`~accel_bayes.inference.lm.robust` (Huber, Cauchy; IRLS reweighting);
* stopping rules — :class:`StoppingRule` in :mod:`.stopping` (ftol / xtol / gtol / max_iter, one place).

Two loops share these pieces: :class:`LevenbergMarquardt` (:mod:`.solver`; one structured problem, Schur
elimination of the locals) and :class:`BatchedLevenbergMarquardt` (many small independent dense
problems solved together — one λ, one stopping reason and one convergence flag per problem, no
Python loop over problems; :mod:`.batched`; used by motion estimation and the intrinsics fit).  Both see a
problem only through a small protocol: ``linearize`` (cost, gradient and Gauss–Newton blocks at a
point), ``cost`` and ``retract`` (apply a tangent step) — :class:`Problem` is one implementation,
``accel_bayes.mismatch.fit`` has another.  The concrete problems are built where their
models live: the [C21] MAP in :mod:`accel_bayes.inference.map`, the [S16] self-calibration in
:mod:`accel_bayes.inference.selfcal`, the conventional calibration in
:mod:`accel_bayes.inference.conventional`.

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

from .batched import BatchedLevenbergMarquardt, BatchedLMResult
from .problem import Problem
from .protocol import Linearization
from .residuals import ChainResidual, ExtraCost, GlobalResidual, SampleResidual
from .solver import LevenbergMarquardt, LMResult, solve
from .stopping import StoppingRule
from .variables import EUCLIDEAN, QUATERNION, Variable  # noqa: F401 (the manifold names, as before)

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

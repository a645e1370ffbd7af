"""Pseudo-marginal Metropolis–Hastings for the array geometry ([C21] Alg. 1, §III-C; DESIGN §5).

:class:`PMMHKernel` is a :class:`pyro.infer.mcmc.mcmc_kernel.MCMCKernel`, so
``pyro.infer.MCMC(kernel, num_samples, warmup_steps, num_chains, initial_params=...)`` runs it
(site ``"r"``: θ, the (A−1, 3) positions of the non-reference triads relative to the reference,
metres, array frame).  :func:`run_pmmh` is a small driver around the same kernel that adds
what Pyro's loop cannot give: per-draw statistics (log p̂, acceptance), crash-safe checkpoints
and bit-exact resumption.

Exactness
---------
The accepted state's estimate log p̂(y | θ) is cached and **never re-estimated**: p̂ is an
unbiased estimator of p(y | θ) (:mod:`accel_bayes.likelihood`), and only then is the chain's
θ-marginal the exact posterior ([C21] §III-A, eq. 8).  Every tuning that looks at the chain
(step size, proposal covariance, independence proposal) happens during warm-up only and is
frozen afterwards, so the kept draws come from one fixed, exact kernel.

Proposals
---------
* Gaussian random walk θ' = θ + σ_q L ε, L Lᵀ = Σ ([C21] eq. 27 with Σ = I; here Σ defaults to
  the prior covariance, may be the Laplace covariance of the MAP, and is re-estimated from the
  warm-up draws in doubling windows when ``adapt_cov``).  σ_q follows a Robbins–Monro recursion
  on log σ_q towards ``target_accept_prob`` (default 15 %, inside [C21]'s 7–23 %), restarted at
  each covariance update; the value frozen at the end of warm-up is the average of log σ_q over
  the final adaptation window.
* Optional independence proposal θ' ~ N(μ, c² Σ_ind) mixed in with probability
  ``independence_prob`` (μ, Σ_ind: the MAP and its Laplace covariance, or the warm-up moments).
  Each move type is a valid MH kernel for the same target, so the random mixture is too.  In
  many dimensions (93 for the 32-IMU board) a random walk needs O(d) steps per independent draw,
  whereas a good independence proposal gives near-independent draws whenever it is accepted.

Randomness: each chain owns a ``torch.Generator`` seeded from (kernel seed, chain index, start
point), used for the proposals, the uniform of the MH test and the likelihood estimator's draws.
Same seed → same chains, bit for bit.
"""
from __future__ import annotations

import hashlib
import math
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from pyro.infer.mcmc.mcmc_kernel import MCMCKernel

from ..errors import UserError
from ..likelihood import positions_from_theta

__all__ = ["PMMHKernel", "PMMHRun", "run_pmmh", "read_checkpoint", "check_checkpoint_request", "CHECKPOINT_FORMAT",
           "warmup_windows", "regularized_cov"]

CHECKPOINT_FORMAT = "accel_bayes.pmmh-checkpoint/1"

# Robbins–Monro gain γ_k = RM_GAIN / (k + 1)^RM_DECAY on log σ_q; a large first gain lets one
# warm-up move σ_q by orders of magnitude (prior scale 3 mm → posterior scale ~10 µm).
RM_GAIN = 2.0
RM_DECAY = 0.6

# σ_q·√d after each covariance update (2.38 is optimal for a Gaussian target without estimator
# noise; pseudo-marginal noise lowers the optimum, Sherlock et al. 2015).
RESET_STEP = 0.8 * 2.38

MOVE_RW, MOVE_IND = 0, 1

# Fraction of warm-up spent before the first covariance window (step size adapts from the start).
INIT_BUFFER = 0.15

# Largest share of independence moves during warm-up (the rest adapt the random walk).
WARMUP_MAX_INDEPENDENCE = 0.5


def warmup_windows(warmup_steps: int, init_buffer: float | None = None, term_buffer: float = 0.20,
                   base_window: int = 25) -> list[int]:
    """Iterations (1-based counts of warm-up steps done) at which the proposal covariance is
    re-estimated: Stan-style doubling windows between an initial buffer (step size only, lets the
    chain reach the bulk) and a terminal buffer (step size only, for the final Σ).  Fewer than
    150 warm-up steps: no covariance windows."""
    W = int(warmup_steps)
    if W < 150:
        return []
    start = int((INIT_BUFFER if init_buffer is None else init_buffer) * W)
    end = W - int(term_buffer * W)
    ends = []
    w = base_window
    pos = start
    while pos + w < end:
        nxt = pos + w
        # a window that would leave less than twice its size before the end absorbs the rest
        if end - nxt < 2 * w:
            nxt = end
        ends.append(nxt)
        pos = nxt
        w *= 2
    if not ends or ends[-1] != end:
        ends.append(end)
    return ends


def regularized_cov(n: int, s: torch.Tensor, ss: torch.Tensor) -> torch.Tensor | None:
    """Sample covariance of n draws from their running sums (s = Σx, ss = Σxxᵀ), shrunk towards
    its diagonal with weight λ = min(1, max(0.05, d/n)) — a window shorter than the dimension only
    yields the variances.  None when it carries no scale (a chain stuck on one point)."""
    if n < 3:
        return None
    d = s.shape[0]
    mean = s / n
    S = (ss - n * torch.outer(mean, mean)) / (n - 1)
    S = 0.5 * (S + S.T)
    diag = torch.diagonal(S).clamp_min(0.0)
    if not bool(torch.isfinite(S).all()) or bool((diag <= 0).any()):
        return None
    lam = min(1.0, max(0.05, d / n))
    out = (1.0 - lam) * S + lam * torch.diag(diag)
    _, info = torch.linalg.cholesky_ex(out)
    return out if int(info) == 0 else torch.diag(diag)


def _chol(cov: torch.Tensor, name: str) -> torch.Tensor:
    L, info = torch.linalg.cholesky_ex(cov)
    if int(info) != 0:
        raise UserError(f"{name}: expected a symmetric positive-definite matrix")
    return L


def _chain_seed(seed: int, chain: int, theta0: torch.Tensor | None) -> int:
    """64-bit generator seed from (seed, chain index, start point).  The start point enters so
    that chains run by Pyro's multiprocess sampler (which calls setup() once per process, chain
    index 0 everywhere) still get distinct streams when their initial_params differ."""
    h = hashlib.sha256(f"accel_bayes.pmmh/{int(seed)}/{int(chain)}".encode())
    if theta0 is not None:
        h.update(theta0.detach().to(torch.float64).cpu().contiguous().numpy().tobytes())
    return int.from_bytes(h.digest()[:8], "little") & 0x7FFF_FFFF_FFFF_FFFF


class PMMHKernel(MCMCKernel):
    r"""Pseudo-marginal Metropolis–Hastings kernel for θ ([C21] Alg. 1), a Pyro ``MCMCKernel``.

    One :meth:`sample` call is one iteration of [C21] Alg. 1: propose θ', estimate
    log p̂(y | θ') with fresh draws, accept with probability
    min(1, p̂(y|θ') p(θ') q(θ|θ') / (p̂(y|θ) p(θ) q(θ'|θ))) ([C21] eq. 8), where p̂(y|θ) is the
    **cached** estimate of the current state.

    :param likelihood: object with ``A``, ``reference`` and
        ``log_phat(positions (..., A, 3), generator=...) -> (...)``, an unbiased estimator of
        the likelihood on the log scale, e.g.
        :class:`~accel_bayes.likelihood.RaoBlackwellLikelihood`.
    :param prior: object with ``log_prob(theta (..., A−1, 3))``, ``sample(shape, generator)``
        and ``covariance()`` (:mod:`accel_bayes.inference.priors`).
    :param int seed: base seed; chain c uses a generator derived from (seed, c, start point).
    :param float step_size: initial σ_q (dimensionless, multiplies the Cholesky factor of
        ``proposal_cov``).  Default 2.38/√d · 0.5.
    :param proposal_cov: (d, d) tensor, d = 3(A−1), covariance Σ of the random-walk step in
        m² (row-major vec θ).  Default: the prior covariance.
    :param float target_accept_prob: target of the warm-up step-size adaptation; within
        [0.07, 0.23] ([C21] §III-C).  Default 0.15.
    :param bool adapt_step_size: Robbins–Monro adaptation of σ_q during warm-up.  Default True.
    :param bool adapt_cov: re-estimate Σ (and the independence proposal when it has no fixed
        moments) from warm-up draws in doubling windows.  Default True.
    :param float independence_prob: probability of an independence move (0 ≤ p < 1).
        Default 0 (pure random walk, as in [C21]).
    :param independence_mean: (A−1, 3) centre μ of the independence proposal (e.g. the MAP).
    :param independence_cov: (d, d) covariance Σ_ind (e.g. the Laplace covariance).
    :param float independence_scale: c ≥ 1, the proposal is N(μ, c² Σ_ind).  Default
        √(1 + √(0.2/d)): slightly wider than Σ_ind at a fixed cost Var[log w] = 0.1 in any d.
    :param str site: name of the sample site.  Default ``"r"``.

    Example::

        >>> import torch, pyro
        >>> from accel_bayes.inference.priors import GaussianPrior
        >>> class Toy:  # exact Gaussian log-likelihood, A = 3 triads
        ...     A, reference = 3, 0
        ...     def log_phat(self, positions, generator=None):
        ...         return -0.5 * ((positions[..., 1:, :] - 0.01) / 1e-3).pow(2).sum((-1, -2))
        >>> prior = GaussianPrior(torch.zeros(3, 3), std=3e-3)
        >>> kernel = PMMHKernel(Toy(), prior, seed=1)
        >>> mcmc = pyro.infer.MCMC(kernel, num_samples=200, warmup_steps=200, disable_progbar=True)
        >>> mcmc.run()
        >>> mcmc.get_samples()["r"].shape
        torch.Size([200, 2, 3])
    """

    def __init__(
        self,
        likelihood,
        prior,
        *,
        seed: int = 0,
        step_size: float | None = None,
        proposal_cov: torch.Tensor | None = None,
        target_accept_prob: float = 0.15,
        adapt_step_size: bool = True,
        adapt_cov: bool = True,
        independence_prob: float = 0.0,
        independence_mean: torch.Tensor | None = None,
        independence_cov: torch.Tensor | None = None,
        independence_scale: float | None = None,
        site: str = "r",
    ):
        for nm in ("A", "reference", "log_phat"):
            if not hasattr(likelihood, nm):
                raise UserError(f"likelihood: expected an object with .{nm} (see RaoBlackwellLikelihood)")
        for nm in ("log_prob", "sample"):
            if not hasattr(prior, nm):
                raise UserError(f"prior: expected an object with .{nm} (see accel_bayes.inference.priors)")
        if not isinstance(target_accept_prob, (int, float)) or not 0.0 < float(target_accept_prob) < 1.0:
            raise UserError(f"target_accept_prob: expected a float in the interval (0, 1), got {target_accept_prob!r}")
        if not 0.0 <= float(independence_prob) < 1.0:
            raise UserError(f"independence_prob: expected a float in [0, 1), got {independence_prob!r}")
        d = 3 * (int(likelihood.A) - 1)
        if independence_scale is None:
            # c² − 1 = √(0.2/d): the importance weights of N(μ, c²Σ) against N(μ, Σ) then have
            # Var[log w] = (c² − 1)² d / 2 = 0.1 whatever the dimension (c = 1.1 would cost
            # Var 2 for the 93 coordinates of the 32-IMU board), while tails stay a little wider.
            independence_scale = math.sqrt(1.0 + math.sqrt(0.2 / d))
        if not float(independence_scale) > 0:
            raise UserError(f"independence_scale: expected a float > 0, got {independence_scale!r}")
        self.likelihood = likelihood
        self.prior = prior
        self.A = int(likelihood.A)
        self.reference = int(likelihood.reference)
        self.event_shape = (self.A - 1, 3)
        self.dim = d
        self.seed = int(seed)
        self.site = str(site)
        self.target_accept_prob = float(target_accept_prob)
        self.adapt_step_size = bool(adapt_step_size)
        self.adapt_cov = bool(adapt_cov)
        self.independence_prob = float(independence_prob)
        self.independence_scale = float(independence_scale)
        mean_like = getattr(prior, "mean", None)
        self.dtype = mean_like.dtype if isinstance(mean_like, torch.Tensor) else torch.float64
        self.device = mean_like.device if isinstance(mean_like, torch.Tensor) else torch.device("cpu")
        if proposal_cov is None:
            if not hasattr(prior, "covariance"):
                raise UserError("proposal_cov: required when the prior has no covariance()")
            proposal_cov = prior.covariance()
        self.proposal_cov0 = self._check_cov(proposal_cov, "proposal_cov")
        if step_size is None:
            step_size = 0.5 * 2.38 / math.sqrt(d)
        if not (isinstance(step_size, (int, float)) and float(step_size) > 0 and math.isfinite(float(step_size))):
            raise UserError(f"step_size: expected a positive float, got {step_size!r}")
        self.step_size0 = float(step_size)
        self.independence_mean0 = None
        self.independence_cov0 = None
        if independence_mean is not None or independence_cov is not None:
            if independence_mean is None or independence_cov is None:
                raise UserError("independence_mean/independence_cov: give both or neither")
            m = torch.as_tensor(independence_mean, dtype=self.dtype, device=self.device)
            if tuple(m.shape) != self.event_shape:
                raise UserError(f"independence_mean: expected shape {self.event_shape}, got {tuple(m.shape)}")
            self.independence_mean0 = m.clone()
            self.independence_cov0 = self._check_cov(independence_cov, "independence_cov")
        elif self.independence_prob > 0 and not self.adapt_cov:
            raise UserError("independence_prob > 0 needs independence_mean/independence_cov or adapt_cov=True")
        self.model = None  # no Pyro model: the target is given by likelihood and prior
        self.transforms = {}  # θ is unconstrained
        self._pending_init = None
        self._initial_params = None
        self.next_chain = 0  # chain index the next setup() uses unless told otherwise
        super().__init__()

    def _check_cov(self, cov, name):
        c = torch.as_tensor(cov, dtype=self.dtype, device=self.device)
        if tuple(c.shape) != (self.dim, self.dim):
            raise UserError(f"{name}: expected shape ({self.dim}, {self.dim}), got {tuple(c.shape)}")
        c = 0.5 * (c + c.T)
        _chol(c, name)
        return c.clone()

    # ------------------------------------------------------------------ Pyro interface
    @property
    def initial_params(self):
        """{site: θ₀} of the chain set up last (Pyro reads it after :meth:`setup`)."""
        return self._initial_params

    @initial_params.setter
    def initial_params(self, params):
        """Start point for the next chain (Pyro sets it before :meth:`setup`); without one the
        chain starts from a prior draw."""
        th = params[self.site] if isinstance(params, dict) else params
        th = torch.as_tensor(th, dtype=self.dtype, device=self.device)
        if tuple(th.shape) != self.event_shape:
            raise UserError(f"initial_params[{self.site!r}]: expected shape {self.event_shape}, got {tuple(th.shape)}")
        self._pending_init = th.clone()

    def setup(self, warmup_steps, *args, chain_id: int | None = None, **kwargs):
        """(Re)initialise every piece of state for a new chain: generator, start point and its
        log p̂, proposal, adaptation counters.  ``chain_id`` defaults to a counter of setup calls
        (Pyro's sequential sampler runs chain 0, 1, … on this one object)."""
        if chain_id is None:
            chain_id = self.next_chain
        self.chain = int(chain_id)
        self.next_chain = self.chain + 1
        self._warmup_steps = int(warmup_steps)
        theta0 = self._pending_init
        self._pending_init = None
        self._gen = torch.Generator(device=self.device)
        self._gen.manual_seed(_chain_seed(self.seed, self.chain, theta0))
        if theta0 is None:
            theta0 = self.prior.sample((), generator=self._gen).to(self.dtype)
        self._t = 0
        self._log_step = math.log(self.step_size0)
        self._rm_k = 0
        self._log_step_sum = 0.0
        self._log_step_n = 0
        self._prop_cov = self.proposal_cov0.clone()
        self._prop_chol = _chol(self._prop_cov, "proposal_cov")
        if self.independence_mean0 is not None:
            self._ind_mean = self.independence_mean0.clone()
            self._ind_cov = self.independence_cov0.clone()
        else:
            self._ind_mean = None
            self._ind_cov = None
        self._set_ind_chol()
        self._windows = warmup_windows(self._warmup_steps) if self.adapt_cov else []
        self._win_start = int(INIT_BUFFER * self._warmup_steps)
        self._avg_from = self._warmup_steps // 2
        self._win_n = 0
        self._win_s = torch.zeros(self.dim, dtype=self.dtype, device=self.device)
        self._win_ss = torch.zeros(self.dim, self.dim, dtype=self.dtype, device=self.device)
        self._n_accept = {"warmup": [0, 0], "sample": [0, 0]}  # [accepted, proposed]
        self._n_move = {MOVE_RW: [0, 0], MOVE_IND: [0, 0]}  # post-warm-up, by move type
        self._mean_accept_prob = 0.0
        self._divergences = []
        self._theta = theta0.clone()
        self._log_prior = self.prior.log_prob(self._theta)
        if not bool(torch.isfinite(self._log_prior)):
            raise UserError("initial_params: the start point has zero prior density")
        self._log_phat = self._estimate(self._theta)
        if not bool(torch.isfinite(self._log_phat)):
            raise UserError("initial_params: the likelihood estimate at the start point is not finite")
        self._initial_params = {self.site: self._theta.clone()}
        self.last_accepted = False
        self.last_accept_prob = 0.0
        self.last_move = MOVE_RW

    def _set_ind_chol(self):
        if self._ind_cov is None:
            self._ind_chol = None
            return
        self._ind_chol = _chol(self._ind_cov, "independence_cov") * self.independence_scale

    def _estimate(self, theta: torch.Tensor) -> torch.Tensor:
        pos = positions_from_theta(theta, self.reference, self.A)
        return torch.as_tensor(self.likelihood.log_phat(pos, generator=self._gen), dtype=self.dtype).reshape(())

    def _current_log_phat(self) -> torch.Tensor:
        """The accepted state's estimate — the cached value (exactness; [C21] Alg. 1 line 14)."""
        return self._log_phat

    def _ind_logq(self, theta: torch.Tensor) -> torch.Tensor:
        x = (theta - self._ind_mean).reshape(-1, 1)
        z = torch.linalg.solve_triangular(self._ind_chol, x, upper=False)
        return -0.5 * (z * z).sum()

    @property
    def warming_up(self) -> bool:
        return self._t < self._warmup_steps

    def sample(self, params):
        """One PmMH iteration ([C21] Alg. 1 lines 4–15); returns {site: θ}."""
        th = params.get(self.site) if isinstance(params, dict) else None
        if th is not None and not torch.equal(torch.as_tensor(th, dtype=self.dtype), self._theta):
            raise UserError(f"params[{self.site!r}]: differs from the kernel's current state; "
                            "a PMMHKernel continues its own chain (call setup() to start a new one)")
        warm = self.warming_up
        gen = self._gen
        d = self.dim
        use_ind = False
        if self.independence_prob > 0 and self._ind_chol is not None:
            # Warm-up keeps at least half of the moves random-walk ones, so σ_q gets enough
            # Robbins–Monro steps; after warm-up the mixture weight is the one asked for.
            p_ind = min(self.independence_prob, WARMUP_MAX_INDEPENDENCE) if warm else self.independence_prob
            use_ind = bool(torch.rand((), generator=gen, dtype=self.dtype) < p_ind)
        eps = torch.randn(d, generator=gen, dtype=self.dtype, device=self.device)
        if use_ind:
            prop = self._ind_mean + (self._ind_chol @ eps).reshape(self.event_shape)
            log_q_ratio = self._ind_logq(self._theta) - self._ind_logq(prop)
        else:
            prop = self._theta + math.exp(self._log_step) * (self._prop_chol @ eps).reshape(self.event_shape)
            log_q_ratio = 0.0
        lprior_p = self.prior.log_prob(prop)
        accepted = False
        alpha = 0.0
        if math.isfinite(float(lprior_p)):
            lphat_p = self._estimate(prop)
            if math.isfinite(float(lphat_p)):
                log_alpha = (float(lphat_p) + float(lprior_p) - float(self._current_log_phat())
                             - float(self._log_prior) + float(log_q_ratio))
                alpha = math.exp(min(0.0, log_alpha))
                u = float(torch.rand((), generator=gen, dtype=self.dtype))
                if u < alpha:
                    accepted = True
                    self._theta = prop
                    self._log_phat = lphat_p
                    self._log_prior = lprior_p
            else:
                self._divergences.append(self._t)
        self.last_accepted, self.last_accept_prob = accepted, alpha
        self.last_move = MOVE_IND if use_ind else MOVE_RW
        phase = "warmup" if warm else "sample"
        self._n_accept[phase][0] += int(accepted)
        self._n_accept[phase][1] += 1
        if not warm:
            self._n_move[self.last_move][0] += int(accepted)
            self._n_move[self.last_move][1] += 1
        n = self._n_accept[phase][1]
        self._mean_accept_prob += (alpha - self._mean_accept_prob) / n
        self._t += 1
        if warm:
            self._adapt(alpha, use_ind)
        return {self.site: self._theta.clone()}

    def _adapt(self, alpha: float, was_ind: bool):
        t = self._t  # warm-up steps done, including this one
        if self.adapt_step_size and not was_ind:
            self._rm_k += 1
            self._log_step += RM_GAIN / (self._rm_k ** RM_DECAY) * (alpha - self.target_accept_prob)
            if t > self._avg_from:
                self._log_step_sum += self._log_step
                self._log_step_n += 1
        if self._windows:
            if self._win_start < t <= self._windows[-1]:
                x = self._theta.reshape(-1)
                self._win_n += 1
                self._win_s += x
                self._win_ss += torch.outer(x, x)
            if t in self._windows:
                cov = regularized_cov(self._win_n, self._win_s, self._win_ss)
                if cov is not None:
                    self._prop_cov = cov
                    self._prop_chol = _chol(cov, "proposal_cov")
                    self._log_step = math.log(RESET_STEP / math.sqrt(self.dim))
                    if self.independence_mean0 is None:
                        self._ind_mean = (self._win_s / self._win_n).reshape(self.event_shape).clone()
                        self._ind_cov = cov.clone()
                        self._set_ind_chol()
                self._rm_k = 0
                self._avg_from = t + (self._warmup_steps - t) // 2
                self._log_step_sum, self._log_step_n = 0.0, 0
                self._win_n = 0
                self._win_s.zero_()
                self._win_ss.zero_()
        if t == self._warmup_steps and self.adapt_step_size and self._log_step_n > 0:
            # Freeze at the average of log σ_q over the second half of the last adaptation phase
            # (Polyak averaging: the last iterate alone still carries the Robbins–Monro noise).
            self._log_step = self._log_step_sum / self._log_step_n

    def end_warmup(self):
        """Pyro never calls it; warm-up ends after ``warmup_steps`` sample() calls."""

    def logging(self):
        phase = "warmup" if self.warming_up else "sample"
        out = OrderedDict([
            ("acc. rate", "{:.3f}".format(self._n_accept[phase][0] / max(1, self._n_accept[phase][1]))),
            ("step", "{:.2e}".format(math.exp(self._log_step))),
        ])
        if self.independence_prob > 0 and not self.warming_up:
            # The 7–23 % target of the step adaptation concerns the random-walk moves; the overall
            # rate above also counts the (mostly accepted) independence moves.
            a, m = self._n_move[MOVE_RW]
            out["rw acc."] = "{:.3f}".format(a / m if m else float("nan"))
        return out

    def diagnostics(self):
        acc, n = self._n_accept["sample"]
        out = {
            "divergences": list(self._divergences),
            "acceptance rate": acc / n if n else float("nan"),
            "step size": math.exp(self._log_step),
            "warmup acceptance rate": self._n_accept["warmup"][0] / max(1, self._n_accept["warmup"][1]),
        }
        for mv, nm in ((MOVE_RW, "random-walk acceptance rate"), (MOVE_IND, "independence acceptance rate")):
            a, m = self._n_move[mv]
            out[nm] = a / m if m else float("nan")
        return out

    # ------------------------------------------------------------------ state for checkpoints
    @property
    def current_log_phat(self) -> float:
        """Cached log p̂ of the current state."""
        return float(self._log_phat)

    @property
    def current_log_prior(self) -> float:
        return float(self._log_prior)

    @property
    def current_theta(self) -> torch.Tensor:
        return self._theta.clone()

    @property
    def proposal_cov(self) -> torch.Tensor:
        """Current random-walk covariance Σ (σ_q² Σ is the step covariance)."""
        return self._prop_cov.clone()

    @property
    def step_size(self) -> float:
        return math.exp(self._log_step)

    def state_dict(self) -> dict:
        """Everything :meth:`sample` depends on, for a bit-exact resume (tensors and plain types)."""
        return {
            "chain": self.chain, "t": self._t, "warmup_steps": self._warmup_steps,
            "theta": self._theta.clone(), "log_phat": self._log_phat.clone(), "log_prior": self._log_prior.clone(),
            "gen_state": self._gen.get_state(), "log_step": self._log_step, "rm_k": self._rm_k,
            "log_step_sum": self._log_step_sum, "log_step_n": self._log_step_n, "avg_from": self._avg_from,
            "prop_cov": self._prop_cov.clone(),
            "ind_mean": None if self._ind_mean is None else self._ind_mean.clone(),
            "ind_cov": None if self._ind_cov is None else self._ind_cov.clone(),
            "win_n": self._win_n, "win_s": self._win_s.clone(), "win_ss": self._win_ss.clone(),
            "n_accept": {k: list(v) for k, v in self._n_accept.items()},
            "n_move": {str(k): list(v) for k, v in self._n_move.items()},
            "mean_accept_prob": self._mean_accept_prob, "divergences": list(self._divergences),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a state saved by :meth:`state_dict` (after :meth:`setup` of the same chain)."""
        self.chain = int(state["chain"])
        self.next_chain = self.chain + 1
        self._t = int(state["t"])
        self._warmup_steps = int(state["warmup_steps"])
        self._theta = state["theta"].clone()
        self._log_phat = state["log_phat"].clone()
        self._log_prior = state["log_prior"].clone()
        self._gen = torch.Generator(device=self.device)
        self._gen.set_state(state["gen_state"])
        self._log_step = float(state["log_step"])
        self._rm_k = int(state["rm_k"])
        self._log_step_sum = float(state["log_step_sum"])
        self._log_step_n = int(state["log_step_n"])
        self._prop_cov = state["prop_cov"].clone()
        self._prop_chol = _chol(self._prop_cov, "proposal_cov")
        self._ind_mean = None if state["ind_mean"] is None else state["ind_mean"].clone()
        self._ind_cov = None if state["ind_cov"] is None else state["ind_cov"].clone()
        self._set_ind_chol()
        self._windows = warmup_windows(self._warmup_steps) if self.adapt_cov else []
        self._win_start = int(INIT_BUFFER * self._warmup_steps)
        self._avg_from = int(state["avg_from"])
        self._win_n = int(state["win_n"])
        self._win_s = state["win_s"].clone()
        self._win_ss = state["win_ss"].clone()
        self._n_accept = {k: list(v) for k, v in state["n_accept"].items()}
        self._n_move = {int(k): list(v) for k, v in state["n_move"].items()}
        self._mean_accept_prob = float(state["mean_accept_prob"])
        self._divergences = list(state["divergences"])
        self._initial_params = {self.site: self._theta.clone()}


# ---------------------------------------------------------------------------- driver

@dataclass
class PMMHRun:
    """Draws and per-draw statistics of :func:`run_pmmh` (C chains × D kept draws).

    theta (C, D, A−1, 3) m; log_phat (C, D) — cached log p̂ of each kept state; log_prior (C, D);
    accepted (C, D) bool — the move into this draw was accepted; accept_prob (C, D) — its MH
    probability min(1, α); move (C, D) int8 — 0 random walk, 1 independence; step_size (C,);
    proposal_cov (C, d, d); diagnostics — kernel.diagnostics() per chain; initial (C, A−1, 3);
    seconds — wall time of the sampling; resumed — whether a checkpoint was used.
    """

    theta: torch.Tensor
    log_phat: torch.Tensor
    log_prior: torch.Tensor
    accepted: torch.Tensor
    accept_prob: torch.Tensor
    move: torch.Tensor
    step_size: torch.Tensor
    proposal_cov: torch.Tensor
    initial: torch.Tensor
    diagnostics: list = field(default_factory=list)
    seconds: float = 0.0
    resumed: bool = False

    @property
    def num_chains(self) -> int:
        return int(self.theta.shape[0])

    @property
    def num_samples(self) -> int:
        return int(self.theta.shape[1])

    @property
    def acceptance_rate(self) -> torch.Tensor:
        """(C,) fraction of accepted moves after warm-up."""
        return self.accepted.to(torch.float64).mean(-1)


def _atomic_save(obj, path: Path) -> None:
    from ..data.outputs import atomic_path

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


# what a checkpoint must hold (keys and types) for run_pmmh to resume from it
_CHECKPOINT_KEYS = {"format": str, "fingerprint": dict, "chain": int, "iteration": int, "arrays": dict,
                    "diagnostics": list, "seconds": (int, float)}


def read_checkpoint(path: str | os.PathLike) -> dict:
    """Load and check a checkpoint written by :func:`run_pmmh`, before anything is computed.

    Loaded with ``torch.load(weights_only=True)``: a checkpoint holds only tensors, dicts, lists,
    strings and numbers, so nothing in it is executed.  Raises :class:`UserError` (one line naming
    ``checkpoint`` and the file) for an empty, truncated or corrupt file, a file that is not a
    torch file, a torch file that is not a PmMH checkpoint, another checkpoint format version, or
    a checkpoint with missing or mistyped parts.
    """
    p = Path(path)
    if p.is_dir():
        raise UserError(f"checkpoint: {p} is a directory; expected a checkpoint file")
    if p.stat().st_size == 0:
        raise UserError(f"checkpoint: {p} is empty (a run killed while creating it?); delete it or rerun without "
                        "--resume")
    try:
        saved = torch.load(p, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... by damage
        raise UserError(f"checkpoint: {p} is not a readable PmMH checkpoint (corrupt, truncated or not a torch "
                        f"file: {type(exc).__name__}); delete it or rerun without --resume") from None
    fmt = saved.get("format") if isinstance(saved, dict) else None
    if not isinstance(fmt, str) or not fmt.startswith(CHECKPOINT_FORMAT.rsplit("/", 1)[0] + "/"):
        raise UserError(f"checkpoint: {p} is a torch file but not a PmMH checkpoint (expected format "
                        f"{CHECKPOINT_FORMAT!r})")
    if fmt != CHECKPOINT_FORMAT:
        raise UserError(f"checkpoint: {p} has format {fmt!r}; this version reads {CHECKPOINT_FORMAT!r}; rerun without "
                        "--resume")
    bad = [k for k, t in _CHECKPOINT_KEYS.items() if not isinstance(saved.get(k), t) or isinstance(saved.get(k), bool)]
    if bad:
        raise UserError(f"checkpoint: {p} is incomplete or damaged (missing or mistyped: {', '.join(bad)}); delete it "
                        "or rerun without --resume")
    return saved


def check_checkpoint_request(saved: dict, request: dict, path) -> None:
    """Refuse (:class:`UserError`) a checkpoint written for another recording, other settings or by
    another package version: ``request`` is the caller's dict of plain values known before any
    computation (``version``, ``recording`` hash, the options), stored as ``fingerprint["request"]``."""
    old = saved["fingerprint"].get("request")
    if not isinstance(old, dict):
        raise UserError(f"checkpoint: {path} holds no settings fingerprint to check a resume against; rerun without "
                        "--resume")
    if old.get("version") != request.get("version"):
        raise UserError(f"resume: checkpoint {path} was written by accel_bayes {old.get('version')}, this is "
                        f"{request.get('version')}; rerun without --resume")
    if old.get("recording") != request.get("recording"):
        raise UserError(f"resume: checkpoint {path} was written for another recording; rerun with that recording or "
                        "without --resume")
    bad = _fingerprint_mismatch(old, request)
    if bad:
        raise UserError(f"resume: checkpoint {path} was written with different settings ({', '.join(bad)}); "
                        "rerun with the same options or without --resume")


def _fingerprint_mismatch(saved: dict, now: dict) -> list[str]:
    keys = sorted(set(saved) | set(now))
    return [k for k in keys if saved.get(k) != now.get(k)]


def run_pmmh(
    kernel: PMMHKernel,
    num_samples: int,
    warmup_steps: int,
    num_chains: int = 1,
    initial_params: torch.Tensor | None = None,
    *,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 0,
    resume: bool = False,
    fingerprint: dict | None = None,
    callback=None,
) -> PMMHRun:
    """Run ``num_chains`` chains of ``kernel`` one after another (the same transitions as
    ``pyro.infer.MCMC(kernel, num_samples, warmup_steps, num_chains)``, same draws for the same
    seed), keeping per-draw statistics, with optional crash-safe checkpoints.

    initial_params : (C, A−1, 3) start points, or None to start each chain from a prior draw.
    progress : a tqdm bar per chain (stderr) showing the acceptance rate and step size.
    checkpoint, checkpoint_every : save the whole sampler state (current θ, its cached log p̂,
        generator state, step size, proposal covariance, adaptation counters, draws so far) to
        ``checkpoint`` every ``checkpoint_every`` iterations and at the end, written atomically
        (temporary file + rename).
    resume : continue from ``checkpoint`` if it exists (otherwise start afresh).  The
        continuation is bit-exact: a killed-and-resumed run returns exactly the draws of an
        uninterrupted one.  ``fingerprint`` (a dict of plain values: settings, data hash) is
        stored in the checkpoint and must match on resume.  The file is checked by
        :func:`read_checkpoint`; callers with expensive set-up check it (and
        :func:`check_checkpoint_request`) before that set-up, as :func:`accel_bayes.calibrate.calibrate` does.
    callback : called as ``callback(chain, iteration, kernel)`` after every iteration
        (iteration counts warm-up and sampling, from 0).
    """
    for nm, v, lo in (("num_samples", num_samples, 1), ("warmup_steps", warmup_steps, 0),
                      ("num_chains", num_chains, 1), ("checkpoint_every", checkpoint_every, 0)):
        if not isinstance(v, (int, np.integer)) or int(v) < lo:
            raise UserError(f"{nm}: expected an integer >= {lo}, got {v!r}")
    C, D, W = int(num_chains), int(num_samples), int(warmup_steps)
    shape = kernel.event_shape
    dt, dev = kernel.dtype, kernel.device
    if initial_params is not None:
        initial_params = torch.as_tensor(initial_params, dtype=dt, device=dev)
        if tuple(initial_params.shape) != (C,) + shape:
            raise UserError(f"initial_params: expected shape {(C,) + shape}, got {tuple(initial_params.shape)}")
    if checkpoint_every and checkpoint is None:
        raise UserError("checkpoint_every: needs a checkpoint file")
    ckpt = Path(checkpoint) if checkpoint is not None else None
    fp = dict(fingerprint or {})
    fp.update({"num_chains": C, "num_samples": D, "warmup_steps": W, "seed": kernel.seed,
               "event_shape": list(shape)})

    st = {
        "theta": torch.zeros((C, D) + shape, dtype=dt, device=dev),
        "log_phat": torch.zeros(C, D, dtype=dt, device=dev),
        "log_prior": torch.zeros(C, D, dtype=dt, device=dev),
        "accepted": torch.zeros(C, D, dtype=torch.bool, device=dev),
        "accept_prob": torch.zeros(C, D, dtype=dt, device=dev),
        "move": torch.zeros(C, D, dtype=torch.int8, device=dev),
        "step_size": torch.zeros(C, dtype=dt, device=dev),
        "proposal_cov": torch.zeros(C, kernel.dim, kernel.dim, dtype=dt, device=dev),
        "initial": torch.zeros((C,) + shape, dtype=dt, device=dev),
    }
    diags: list = [None] * C
    chain0, it0, kstate, seconds0 = 0, 0, None, 0.0
    resumed = False
    if resume and ckpt is not None and ckpt.exists():
        saved = read_checkpoint(ckpt)
        bad = _fingerprint_mismatch(saved["fingerprint"], fp)
        if bad:
            raise UserError(f"resume: checkpoint {ckpt} was written with different settings ({', '.join(bad)}); "
                            "rerun with the same options or without --resume")
        st = saved["arrays"]
        diags = saved["diagnostics"]
        chain0, it0, kstate = saved["chain"], saved["iteration"], saved["kernel"]
        seconds0 = float(saved.get("seconds", 0.0))
        resumed = True

    def save(chain, iteration, kernel_state, seconds):
        if ckpt is None:
            return
        _atomic_save({"format": CHECKPOINT_FORMAT, "fingerprint": fp, "chain": chain, "iteration": iteration,
                      "kernel": kernel_state, "arrays": st, "diagnostics": diags, "seconds": seconds}, ckpt)

    t_start = time.perf_counter() - seconds0
    total = W + D
    bar_cls = None
    if progress:
        from tqdm.auto import tqdm as bar_cls
    for c in range(chain0, C):
        if c == chain0 and kstate is not None:
            kernel.load_state_dict(kstate)
            start = it0
        else:
            if initial_params is not None:
                kernel.initial_params = {kernel.site: initial_params[c]}
            kernel.setup(W, chain_id=c)
            st["initial"][c] = kernel.initial_params[kernel.site]
            start = 0
        bar = None
        if bar_cls is not None and start < total:
            bar = bar_cls(total=total, initial=start, desc=f"chain {c}", leave=True, dynamic_ncols=True)
        try:
            for i in range(start, total):
                kernel.sample({kernel.site: kernel._theta})
                if i >= W:
                    j = i - W
                    st["theta"][c, j] = kernel._theta
                    st["log_phat"][c, j] = kernel._log_phat
                    st["log_prior"][c, j] = kernel._log_prior
                    st["accepted"][c, j] = kernel.last_accepted
                    st["accept_prob"][c, j] = kernel.last_accept_prob
                    st["move"][c, j] = kernel.last_move
                if bar is not None:
                    bar.update(1)
                    if (i + 1) % 10 == 0 or i + 1 == total:
                        bar.set_postfix(kernel.logging(), refresh=False)
                if callback is not None:
                    callback(c, i, kernel)
                if checkpoint_every and (i + 1) % checkpoint_every == 0 and i + 1 < total:
                    save(c, i + 1, kernel.state_dict(), time.perf_counter() - t_start)
        finally:
            if bar is not None:
                bar.close()
        st["step_size"][c] = kernel.step_size
        st["proposal_cov"][c] = kernel.proposal_cov
        diags[c] = kernel.diagnostics()
        kstate = None
        if ckpt is not None and c + 1 < C:
            save(c + 1, 0, None, time.perf_counter() - t_start)
    seconds = time.perf_counter() - t_start
    if ckpt is not None:
        save(C, 0, None, seconds)
    return PMMHRun(diagnostics=diags, seconds=seconds, resumed=resumed, **st)

"""The PmMH kernel ([C21] Alg. 1, §III-C; DESIGN §5), a Pyro ``MCMCKernel``.

The state machine is a handful of private attributes — the chain's generator, the current θ with
its **cached** log p̂ and log prior, the iteration counter ``_t`` and the acceptance counters
(:class:`AcceptanceStats`, reporting only) — plus the proposals (:mod:`.proposals`) and the warm-up adaptation (:mod:`.adaptation`) it owns.
:meth:`PMMHKernel.setup` re-initialises all of them for a chain, :meth:`PMMHKernel.sample` does
exactly one transition, :meth:`PMMHKernel.logging` and :meth:`PMMHKernel.diagnostics` only
report, and :meth:`PMMHKernel.state_dict` / :meth:`PMMHKernel.load_state_dict` save and restore
everything a transition depends on (checkpoints, :mod:`.runner`).
"""
from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from typing import NamedTuple

import torch
from pyro.infer.mcmc.mcmc_kernel import MCMCKernel

from ...errors import UserError
from ...model.likelihood import positions_from_theta
from .adaptation import CovarianceAdapter, StepSizeAdapter, WarmupAdaptation
from .proposals import (MOVE_IND, MOVE_RW, IndependenceProposal, ProposalMixture, RandomWalkProposal,
                        cholesky_factor)

__all__ = ["PMMHKernel", "Transition", "AcceptanceStats", "chain_seed"]


def chain_seed(seed: int, chain: int, theta0: torch.Tensor | None) -> int:
    """64-bit generator seed from (seed, chain index, start point).  The start point enters so
    that chains run by Pyro's multiprocess sampler (which calls setup() once per process, chain
    index 0 everywhere) still get distinct streams when their initial_params differ."""
    h = hashlib.sha256(f"accel_bayes.pmmh/{int(seed)}/{int(chain)}".encode())
    if theta0 is not None:
        h.update(theta0.detach().to(torch.float64).cpu().contiguous().numpy().tobytes())
    return int.from_bytes(h.digest()[:8], "little") & 0x7FFF_FFFF_FFFF_FFFF


class AcceptanceStats:
    """Counters of one chain, for reporting only (they never influence a transition): accepted and
    proposed moves in warm-up and after it, post-warm-up counts by move type, the running mean of
    the MH probability in the current phase, and the iterations whose proposal gave a non-finite
    likelihood estimate ("divergences")."""

    def __init__(self):
        self.n_accept = {"warmup": [0, 0], "sample": [0, 0]}  # [accepted, proposed]
        self.n_move = {MOVE_RW: [0, 0], MOVE_IND: [0, 0]}  # post-warm-up, by move type
        self.mean_accept_prob = 0.0
        self.divergences = []

    def record(self, warm: bool, move: int, accepted: bool, alpha: float) -> None:
        phase = "warmup" if warm else "sample"
        self.n_accept[phase][0] += int(accepted)
        self.n_accept[phase][1] += 1
        if not warm:
            self.n_move[move][0] += int(accepted)
            self.n_move[move][1] += 1
        n = self.n_accept[phase][1]
        self.mean_accept_prob += (alpha - self.mean_accept_prob) / n

    def rate(self, phase: str) -> float:
        """Acceptance rate of ``phase`` ("warmup" or "sample"); 0 before any move."""
        return self.n_accept[phase][0] / max(1, self.n_accept[phase][1])

    def move_rate(self, move: int) -> float:
        """Post-warm-up acceptance rate of one move type; NaN before any."""
        a, m = self.n_move[move]
        return a / m if m else float("nan")

    def state_dict(self) -> dict:
        return {"n_accept": {k: list(v) for k, v in self.n_accept.items()},
                "n_move": {str(k): list(v) for k, v in self.n_move.items()},
                "mean_accept_prob": self.mean_accept_prob, "divergences": list(self.divergences)}

    def load_state_dict(self, state: dict) -> None:
        self.n_accept = {k: list(v) for k, v in state["n_accept"].items()}
        self.n_move = {int(k): list(v) for k, v in state["n_move"].items()}
        self.mean_accept_prob = float(state["mean_accept_prob"])
        self.divergences = list(state["divergences"])


class Transition(NamedTuple):
    """The outcome of the last :meth:`PMMHKernel.sample`: the state θ (A−1, 3) m after it, its
    cached log p̂ and log prior (0-d tensors), whether the move was accepted, its MH probability
    min(1, α) and the move type (0 random walk, 1 independence)."""

    theta: torch.Tensor
    log_phat: torch.Tensor
    log_prior: torch.Tensor
    accepted: bool
    accept_prob: float
    move: int


class PMMHKernel(MCMCKernel):
    r"""Pseudo-marginal Metropolis–Hastings kernel for θ ([C21] Alg. 1), a Pyro ``MCMCKernel``.

    One :meth:`sample` call is one iteration of [C21] Alg. 1: propose θ', estimate
    log p̂(y | θ') with fresh draws, accept with probability
    min(1, p̂(y|θ') p(θ') q(θ|θ') / (p̂(y|θ) p(θ) q(θ'|θ))) ([C21] eq. 8), where p̂(y|θ) is the
    **cached** estimate of the current state.

    :param likelihood: object with ``A``, ``reference`` and
        ``log_phat(positions (..., A, 3), generator=...) -> (...)``, an unbiased estimator of
        the likelihood on the log scale, e.g.
        :class:`~accel_bayes.model.likelihood.RaoBlackwellLikelihood`.
    :param prior: object with ``log_prob(theta (..., A−1, 3))``, ``sample(shape, generator)``
        and ``covariance()`` (:mod:`accel_bayes.inference.mcmc.priors`).
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
    :param float correlation: ρ in [0, 1) of the correlated pseudo-marginal method (Deligiannidis,
        Doucet & Pitt 2018): the standard normals z (T, N, 3) behind the estimate are part of the
        state, and each proposal moves them by the Crank–Nicolson step
        z' = ρ z + √(1 − ρ²) ε, ε ~ N(0, I) — reversible with respect to N(0, I), so the MH ratio
        keeps the form above with p̂(y|θ', z') and the cached p̂(y|θ, z), and the θ-marginal of the
        chain is still the posterior.  The estimates at θ and θ' then share most of their noise,
        so far fewer draws N suffice.  Needs ``likelihood.sample_z`` and a ``z=`` argument of
        ``log_phat``.  Default 0: fresh draws every iteration, the kernel of [C21] Alg. 1 (bit for
        bit the chains of earlier versions).

    Example::

        >>> import torch, pyro
        >>> from accel_bayes.inference.mcmc.priors import GaussianPrior
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
        correlation: float = 0.0,
    ):
        for nm in ("A", "reference", "log_phat"):
            if not hasattr(likelihood, nm):
                raise UserError(f"likelihood: expected an object with .{nm} (see RaoBlackwellLikelihood)")
        for nm in ("log_prob", "sample"):
            if not hasattr(prior, nm):
                raise UserError(f"prior: expected an object with .{nm} (see accel_bayes.inference.mcmc.priors)")
        if not isinstance(target_accept_prob, (int, float)) or not 0.0 < float(target_accept_prob) < 1.0:
            raise UserError(f"target_accept_prob: expected a float in the interval (0, 1), got {target_accept_prob!r}")
        if not 0.0 <= float(independence_prob) < 1.0:
            raise UserError(f"independence_prob: expected a float in [0, 1), got {independence_prob!r}")
        if isinstance(correlation, bool) or not isinstance(correlation, (int, float)) \
                or not 0.0 <= float(correlation) < 1.0:
            raise UserError(f"correlation: expected a float in [0, 1), got {correlation!r}")
        if float(correlation) > 0 and not hasattr(likelihood, "sample_z"):
            raise UserError("correlation: > 0 needs a likelihood with .sample_z and log_phat(..., z=...)")
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
        self.correlation = float(correlation)
        self._z = None  # the current state's standard normals (correlation > 0 only)
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
        # the pieces: proposals (parameters the adaptation moves) and the warm-up adaptation
        self._rw = RandomWalkProposal(self.proposal_cov0, math.log(self.step_size0))
        self._ind = IndependenceProposal(self.event_shape, self.independence_scale)
        self._proposal = ProposalMixture(self._rw, self._ind, self.independence_prob)
        self._adaptation = WarmupAdaptation(
            StepSizeAdapter(self.target_accept_prob, self.adapt_step_size),
            CovarianceAdapter(self.dim, self.dtype, self.device, self.adapt_cov),
            adapt_independence=self.independence_mean0 is None)
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
        cholesky_factor(c, name)
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
        log p̂, proposals, adaptation, counters.  ``chain_id`` defaults to a counter of setup calls
        (Pyro's sequential sampler runs chain 0, 1, … on this one object)."""
        if chain_id is None:
            chain_id = self.next_chain
        self.chain = int(chain_id)
        self.next_chain = self.chain + 1
        self._warmup_steps = int(warmup_steps)
        theta0 = self._pending_init
        self._pending_init = None
        self._gen = torch.Generator(device=self.device)
        self._gen.manual_seed(chain_seed(self.seed, self.chain, theta0))
        if theta0 is None:
            theta0 = self.prior.sample((), generator=self._gen).to(self.dtype)
        self._t = 0
        self._rw.set_cov(self.proposal_cov0.clone())
        self._rw.log_step = math.log(self.step_size0)
        if self.independence_mean0 is not None:
            self._ind.set(self.independence_mean0.clone(), self.independence_cov0.clone())
        else:
            self._ind.set(None, None)
        self._adaptation.setup(self._warmup_steps)
        self._stats = AcceptanceStats()
        self._theta = theta0.clone()
        self._log_prior = self.prior.log_prob(self._theta)
        if not bool(torch.isfinite(self._log_prior)):
            raise UserError("initial_params: the start point has zero prior density")
        if self.correlation > 0:
            # the same numbers log_phat(generator=...) would draw: ρ > 0 starts where ρ = 0 does
            self._z = self.likelihood.sample_z((), None, self._gen)
        self._log_phat = self._estimate(self._theta, self._z)
        if not bool(torch.isfinite(self._log_phat)):
            raise UserError("initial_params: the likelihood estimate at the start point is not finite")
        self._initial_params = {self.site: self._theta.clone()}
        self._last = (False, 0.0, MOVE_RW)

    def _estimate(self, theta: torch.Tensor, z: torch.Tensor | None = None) -> torch.Tensor:
        """log p̂(y | θ): with the given standard normals z, else fresh ones from the chain's generator."""
        pos = positions_from_theta(theta, self.reference, self.A)
        out = self.likelihood.log_phat(pos, generator=self._gen) if z is None else self.likelihood.log_phat(pos, z=z)
        return torch.as_tensor(out, dtype=self.dtype, device=self.device).reshape(())

    def _propose_z(self) -> torch.Tensor:
        """z' = ρ z + √(1 − ρ²) ε (Crank–Nicolson: leaves N(0, I) invariant and is reversible with
        respect to it, so no proposal density enters the MH ratio); ε drawn as sample_z draws."""
        eps = self.likelihood.sample_z((), self._z.shape[-2], self._gen)
        rho = self.correlation
        return rho * self._z + math.sqrt((1.0 - rho) * (1.0 + rho)) * eps

    def _current_log_phat(self) -> torch.Tensor:
        """The accepted state's estimate — the cached value (exactness; [C21] Alg. 1 line 14)."""
        return self._log_phat

    @property
    def warming_up(self) -> bool:
        return self._t < self._warmup_steps

    def sample(self, params):
        """One PmMH iteration ([C21] Alg. 1 lines 4–15); returns {site: θ}.  ``params`` is the
        current state (Pyro passes it back) or ``{}``."""
        th = params.get(self.site) if isinstance(params, dict) else None
        if th is not None and not torch.equal(torch.as_tensor(th, dtype=self.dtype), self._theta):
            raise UserError(f"params[{self.site!r}]: differs from the kernel's current state; "
                            "a PMMHKernel continues its own chain (call setup() to start a new one)")
        warm = self.warming_up
        prop, log_q_ratio, move = self._proposal.propose(self._theta, self._gen, warm)
        lprior_p = self.prior.log_prob(prop)
        accepted = False
        alpha = 0.0
        if math.isfinite(float(lprior_p)):
            z_p = self._propose_z() if self.correlation > 0 else None
            lphat_p = self._estimate(prop, z_p)
            if math.isfinite(float(lphat_p)):
                log_alpha = (float(lphat_p) + float(lprior_p) - float(self._current_log_phat())
                             - float(self._log_prior) + float(log_q_ratio))
                alpha = math.exp(min(0.0, log_alpha))
                u = float(torch.rand((), generator=self._gen, dtype=self.dtype, device=self.device))
                if u < alpha:
                    accepted = True
                    self._theta = prop
                    self._log_phat = lphat_p
                    self._log_prior = lprior_p
                    if z_p is not None:
                        self._z = z_p
            else:
                self._stats.divergences.append(self._t)
        self._last = (accepted, alpha, move)
        self._stats.record(warm, move, accepted, alpha)
        self._t += 1
        if warm:
            self._adaptation.step(self._t, alpha, move == MOVE_IND, self._theta, self._rw, self._ind)
        return {self.site: self._theta.clone()}

    def end_warmup(self):
        """Pyro never calls it; warm-up ends after ``warmup_steps`` sample() calls."""

    # ------------------------------------------------------------------ reporting only
    def logging(self):
        phase = "warmup" if self.warming_up else "sample"
        out = OrderedDict([
            ("acc. rate", "{:.3f}".format(self._stats.rate(phase))),
            ("step", "{:.2e}".format(self.step_size)),
        ])
        if self.independence_prob > 0 and not self.warming_up:
            # The 7–23 % target of the step adaptation concerns the random-walk moves; the overall
            # rate above also counts the (mostly accepted) independence moves.
            out["rw acc."] = "{:.3f}".format(self._stats.move_rate(MOVE_RW))
        return out

    def diagnostics(self):
        st = self._stats
        acc, n = st.n_accept["sample"]
        return {
            "divergences": list(st.divergences),
            "acceptance rate": acc / n if n else float("nan"),
            "step size": self.step_size,
            "warmup acceptance rate": st.rate("warmup"),
            "random-walk acceptance rate": st.move_rate(MOVE_RW),
            "independence acceptance rate": st.move_rate(MOVE_IND),
        }

    @property
    def last(self) -> Transition:
        """The state after the last :meth:`sample` and how it was reached (tensors not copied)."""
        accepted, alpha, move = self._last
        return Transition(self._theta, self._log_phat, self._log_prior, accepted, alpha, move)

    @property
    def last_accepted(self) -> bool:
        return self._last[0]

    @property
    def last_accept_prob(self) -> float:
        return self._last[1]

    @property
    def last_move(self) -> int:
        return self._last[2]

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
        return self._rw.cov.clone()

    @property
    def step_size(self) -> float:
        """Current σ_q."""
        return self._rw.step_size

    # ------------------------------------------------------------------ state for checkpoints
    def state_dict(self) -> dict:
        """Everything :meth:`sample` depends on, for a bit-exact resume (tensors and plain types).
        The keys are those of checkpoint format ``accel_bayes.pmmh-checkpoint/1``, plus ``"z"``
        (T, N, 3) when ``correlation`` > 0."""
        return {
            "chain": self.chain, "t": self._t, "warmup_steps": self._warmup_steps,
            "theta": self._theta.clone(), "log_phat": self._log_phat.clone(), "log_prior": self._log_prior.clone(),
            "gen_state": self._gen.get_state(), "log_step": self._rw.log_step,
            **self._adaptation.state_dict(),
            "prop_cov": self._rw.cov.clone(),
            "ind_mean": None if self._ind.mean is None else self._ind.mean.clone(),
            "ind_cov": None if self._ind.cov is None else self._ind.cov.clone(),
            **self._stats.state_dict(),
            # the correlated kernel's normals; absent at ρ = 0, whose keys stay those of format 1
            **({} if self._z is None else {"z": self._z.clone()}),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore a state saved by :meth:`state_dict`."""
        self.chain = int(state["chain"])
        self.next_chain = self.chain + 1
        self._t = int(state["t"])
        self._warmup_steps = int(state["warmup_steps"])
        self._theta = state["theta"].clone()
        self._log_phat = state["log_phat"].clone()
        self._log_prior = state["log_prior"].clone()
        self._gen = torch.Generator(device=self.device)
        self._gen.set_state(state["gen_state"])
        self._rw.set_cov(state["prop_cov"].clone())
        self._rw.log_step = float(state["log_step"])
        self._ind.set(None if state["ind_mean"] is None else state["ind_mean"].clone(),
                      None if state["ind_cov"] is None else state["ind_cov"].clone())
        self._adaptation.setup(self._warmup_steps)
        self._adaptation.load_state_dict(state)
        self._stats = AcceptanceStats()
        self._stats.load_state_dict(state)
        z = state.get("z")
        if (z is None) != (self.correlation == 0):
            raise UserError(f"state: saved with{'out' if z is None else ''} the correlated kernel's z; "
                            f"this kernel has correlation {self.correlation}")
        self._z = None if z is None else z.clone()
        self._initial_params = {self.site: self._theta.clone()}
        self._last = (False, 0.0, MOVE_RW)

"""Pseudo-marginal Metropolis–Hastings for the array geometry ([C21] Alg. 1, §III-C; DESIGN §5).

The package is split by concern: :mod:`.kernel` (:class:`PMMHKernel`, the state machine),
:mod:`.proposals` (random walk, independence, their mixture), :mod:`.adaptation` (warm-up step
size and covariance windows), :mod:`.runner` (:func:`run_pmmh`, fixed length;
:func:`run_pmmh_until`, extended block by block until a convergence check passes),
:mod:`.checkpoint` (format, loading, fingerprints) and :mod:`.priors` (p(θ)).

:class:`PMMHKernel` is a :class:`pyro.infer.mcmc.mcmc_kernel.MCMCKernel`, so
``pyro.infer.MCMC(kernel, num_samples, warmup_steps, num_chains, initial_params=...)`` runs it
(site ``"r"``: θ, the (A−1, 3) positions of the non-reference triads relative to the reference,
metres, array frame).  :func:`run_pmmh` is a small driver around the same kernel that adds
what Pyro's loop cannot give: per-draw statistics (log p̂, acceptance), crash-safe checkpoints
and bit-exact resumption.

Exactness
---------
The accepted state's estimate log p̂(y | θ) is cached and **never re-estimated**: p̂ is an
unbiased estimator of p(y | θ) (:mod:`accel_bayes.model.likelihood`), and only then is the chain's
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

from .adaptation import regularized_cov, warmup_windows
from .checkpoint import CHECKPOINT_FORMAT, check_checkpoint_request, read_checkpoint
from .kernel import PMMHKernel, Transition
from .runner import STOP_REASONS, PMMHRun, run_pmmh, run_pmmh_until

__all__ = ["PMMHKernel", "PMMHRun", "Transition", "run_pmmh", "run_pmmh_until", "STOP_REASONS", "read_checkpoint", "check_checkpoint_request",
           "CHECKPOINT_FORMAT", "warmup_windows", "regularized_cov"]

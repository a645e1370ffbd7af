"""Warm-up adaptation of the PmMH proposals ([C21] §III-C; DESIGN §5), kept apart from the kernel
as Pyro keeps HMC's in an adapter.

* :class:`StepSizeAdapter` — Robbins–Monro recursion on log σ_q towards the target acceptance
  probability, restarted at each covariance update, frozen at the end of warm-up at the average
  of log σ_q over the second half of the last adaptation phase (Polyak averaging).
* :class:`CovarianceAdapter` — running sums of the warm-up draws in Stan-style doubling windows
  (:func:`warmup_windows`); at each window end the regularised sample covariance
  (:func:`regularized_cov`) replaces the random-walk Σ (and, without fixed moments, the
  independence proposal's mean and covariance).
* :class:`WarmupAdaptation` — one warm-up step of both, applied to the kernel's proposals.

Adaptation only ever looks at the chain during warm-up; afterwards the proposals are frozen so the
kept draws come from one fixed, exact kernel.
"""
from __future__ import annotations

import math

import torch

from .proposals import IndependenceProposal, RandomWalkProposal

__all__ = ["warmup_windows", "regularized_cov", "StepSizeAdapter", "CovarianceAdapter", "WarmupAdaptation",
           "RM_GAIN", "RM_DECAY", "RESET_STEP", "INIT_BUFFER"]

# Robbins–Monro gain γ_k = RM_GAIN / (k + 1)^RM_DECAY on log σ_q; a large first gain lets one
# warm-up move σ_q by orders of magnitude (prior scale 3 mm → posterior scale ~10 µm).
RM_GAIN = 2.0
RM_DECAY = 0.6

# σ_q·√d after each covariance update (2.38 is optimal for a Gaussian target without estimator
# noise; pseudo-marginal noise lowers the optimum, Sherlock et al. 2015).
RESET_STEP = 0.8 * 2.38

# Fraction of warm-up spent before the first covariance window (step size adapts from the start).
INIT_BUFFER = 0.15


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


class StepSizeAdapter:
    """Robbins–Monro recursion log σ_q ← log σ_q + γ_k (α − α*), γ_k = RM_GAIN / k^RM_DECAY, on the
    random-walk moves of warm-up, with the running average of log σ_q over the second half of the
    current adaptation phase (the value frozen at the end of warm-up).

    :param float target_accept_prob: α*, in (0, 1).
    :param bool enabled: adapt at all (False: σ_q stays as given).
    """

    def __init__(self, target_accept_prob: float, enabled: bool = True):
        self.target_accept_prob = float(target_accept_prob)
        self.enabled = bool(enabled)

    def setup(self, warmup_steps: int) -> None:
        """Start a new chain's warm-up of ``warmup_steps`` iterations."""
        self._warmup_steps = int(warmup_steps)
        self._k = 0
        self._sum = 0.0
        self._n = 0
        self._avg_from = self._warmup_steps // 2

    def update(self, log_step: float, alpha: float, t: int) -> float:
        """log σ_q after a random-walk move with MH probability ``alpha`` at warm-up step t (1-based)."""
        if not self.enabled:
            return log_step
        self._k += 1
        log_step += RM_GAIN / (self._k ** RM_DECAY) * (alpha - self.target_accept_prob)
        if t > self._avg_from:
            self._sum += log_step
            self._n += 1
        return log_step

    def restart(self, t: int) -> None:
        """A new adaptation phase from warm-up step t (after a covariance update)."""
        self._k = 0
        self._avg_from = t + (self._warmup_steps - t) // 2
        self._sum, self._n = 0.0, 0

    def final(self, log_step: float) -> float:
        """log σ_q frozen at the end of warm-up: the phase average (the last iterate alone still
        carries the Robbins–Monro noise), or ``log_step`` when nothing was averaged."""
        if self.enabled and self._n > 0:
            return self._sum / self._n
        return log_step

    def state_dict(self) -> dict:
        return {"rm_k": self._k, "log_step_sum": self._sum, "log_step_n": self._n, "avg_from": self._avg_from}

    def load_state_dict(self, state: dict) -> None:
        self._k = int(state["rm_k"])
        self._sum = float(state["log_step_sum"])
        self._n = int(state["log_step_n"])
        self._avg_from = int(state["avg_from"])


class CovarianceAdapter:
    """Running sums Σx, Σxxᵀ of the warm-up draws in the doubling windows of
    :func:`warmup_windows`; :meth:`observe` says when a window closes and :meth:`take` returns its
    regularised covariance and mean and clears the sums.

    :param int dim: d = 3(A−1).
    :param bool enabled: False: no windows.
    """

    def __init__(self, dim: int, dtype=torch.float64, device=None, enabled: bool = True):
        self.dim = int(dim)
        self.dtype, self.device = dtype, device
        self.enabled = bool(enabled)

    def setup(self, warmup_steps: int) -> None:
        W = int(warmup_steps)
        self._windows = warmup_windows(W) if self.enabled else []
        self._start = int(INIT_BUFFER * W)
        self._n = 0
        self._s = torch.zeros(self.dim, dtype=self.dtype, device=self.device)
        self._ss = torch.zeros(self.dim, self.dim, dtype=self.dtype, device=self.device)

    def observe(self, t: int, theta: torch.Tensor) -> bool:
        """Add the state after warm-up step t (1-based) when t lies in a window; True when a
        window ends at t."""
        if not self._windows:
            return False
        if self._start < t <= self._windows[-1]:
            x = theta.reshape(-1)
            self._n += 1
            self._s += x
            self._ss += torch.outer(x, x)
        return t in self._windows

    def take(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """(covariance or None, mean or None) of the window just closed (m², m); clears the sums."""
        cov = regularized_cov(self._n, self._s, self._ss)
        mean = None if cov is None else self._s / self._n
        self._n = 0
        self._s.zero_()
        self._ss.zero_()
        return cov, mean

    def state_dict(self) -> dict:
        return {"win_n": self._n, "win_s": self._s.clone(), "win_ss": self._ss.clone()}

    def load_state_dict(self, state: dict) -> None:
        self._n = int(state["win_n"])
        self._s = state["win_s"].clone()
        self._ss = state["win_ss"].clone()


class WarmupAdaptation:
    """One warm-up step of the step size and the covariance windows, applied to the proposals.

    :param StepSizeAdapter step_size: the σ_q recursion.
    :param CovarianceAdapter covariance: the windows.
    :param bool adapt_independence: also move the independence proposal to each window's moments
        (when it has no fixed mean and covariance).
    """

    def __init__(self, step_size: StepSizeAdapter, covariance: CovarianceAdapter, adapt_independence: bool):
        self.step_size = step_size
        self.covariance = covariance
        self.adapt_independence = bool(adapt_independence)

    def setup(self, warmup_steps: int) -> None:
        self._warmup_steps = int(warmup_steps)
        self.step_size.setup(warmup_steps)
        self.covariance.setup(warmup_steps)

    def step(self, t: int, alpha: float, was_independence: bool, theta: torch.Tensor, rw: RandomWalkProposal,
             ind: IndependenceProposal) -> None:
        """After warm-up step t (1-based) with MH probability ``alpha`` and current state θ."""
        if not was_independence:
            rw.log_step = self.step_size.update(rw.log_step, alpha, t)
        if self.covariance.observe(t, theta):
            cov, mean = self.covariance.take()
            if cov is not None:
                rw.set_cov(cov)
                rw.log_step = math.log(RESET_STEP / math.sqrt(self.covariance.dim))
                if self.adapt_independence:
                    ind.set(mean.reshape(ind.event_shape).clone(), cov.clone())
            self.step_size.restart(t)
        if t == self._warmup_steps:
            rw.log_step = self.step_size.final(rw.log_step)

    def state_dict(self) -> dict:
        return {**self.step_size.state_dict(), **self.covariance.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.step_size.load_state_dict(state)
        self.covariance.load_state_dict(state)

"""The PmMH runner: chains one after another, warm-up counting, per-draw statistics, crash-safe
checkpoints and a progress bar, using only the kernel's public methods (``setup``, ``sample``,
``last``, ``logging``, ``diagnostics``, ``state_dict``/``load_state_dict``).

Two drivers share the per-iteration loop: :func:`run_pmmh` runs a fixed number of draws, and
:func:`run_pmmh_until` extends the chains block by block (keeping each chain's kernel state
between blocks) until a convergence check passes or a budget is spent.  Both give, for the same
kernel and seed, the same draws: a chain's transitions depend only on its own state.
"""
from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ... import interrupts
from ...errors import UserError
from .checkpoint import CHECKPOINT_FORMAT, fingerprint_mismatch, read_checkpoint, write_checkpoint
from .kernel import PMMHKernel

__all__ = ["PMMHRun", "run_pmmh", "run_pmmh_until", "STOP_REASONS"]

# why run_pmmh_until stopped: the check passed, the draw budget or the wall-clock budget was spent
STOP_REASONS = ("converged", "max_samples", "max_seconds")


@dataclass
class PMMHRun:
    """Draws and per-draw statistics of :func:`run_pmmh` (C chains × D kept draws).

    theta (C, D, A−1, 3) m; log_phat (C, D) — cached log p̂ of each kept state; log_prior (C, D);
    accepted (C, D) bool — the move into this draw was accepted; accept_prob (C, D) — its MH
    probability min(1, α); move (C, D) int8 — 0 random walk, 1 independence; step_size (C,);
    proposal_cov (C, d, d); diagnostics — kernel.diagnostics() per chain; initial (C, A−1, 3);
    seconds — wall time of the sampling; resumed — whether a checkpoint was used.
    :func:`run_pmmh_until` also fills checks — one plain dict per convergence check (its
    ``as_dict()`` plus ``seconds``, the sampler's wall time at the check) — and stopped — one of
    :data:`STOP_REASONS`; both stay empty / None for :func:`run_pmmh`.
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
    checks: list = field(default_factory=list)
    stopped: str | None = None

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


def _new_arrays(kernel, C: int, D: int) -> dict:
    """Zeroed per-draw arrays of C chains × D draws (the keys of :class:`PMMHRun`'s tensors)."""
    shape, dt, dev = kernel.event_shape, kernel.dtype, kernel.device
    return {
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


_PER_DRAW = ("theta", "log_phat", "log_prior", "accepted", "accept_prob", "move")


def _iterate(kernel, st, c, start, stop, W, bar, callback, checkpoint_every, save_at):
    """Iterations ``start`` … ``stop − 1`` of chain ``c`` (counted from its first warm-up
    iteration): one kernel transition each, the kept ones (i ≥ W) stored at draw i − W;
    ``save_at(i + 1)`` every ``checkpoint_every`` iterations except at ``stop``."""
    for i in range(start, stop):
        interrupts.check()  # SIGINT/SIGTERM: stop between transitions (accel_bayes.interrupts)
        kernel.sample({})
        if i >= W:
            j, tr = i - W, kernel.last
            st["theta"][c, j] = tr.theta
            st["log_phat"][c, j] = tr.log_phat
            st["log_prior"][c, j] = tr.log_prior
            st["accepted"][c, j] = tr.accepted
            st["accept_prob"][c, j] = tr.accept_prob
            st["move"][c, j] = tr.move
        if bar is not None:
            bar.update(1)
            if (i + 1) % 10 == 0 or i + 1 == stop:
                bar.set_postfix(kernel.logging(), refresh=False)
        if callback is not None:
            callback(c, i, kernel)
        if checkpoint_every and (i + 1) % checkpoint_every == 0 and i + 1 < stop:
            save_at(i + 1)



def _check_starts_and_checkpoint(kernel, C, initial_params, checkpoint, checkpoint_every):
    """The chain starts as a (C, *event_shape) tensor of the kernel's dtype/device (or None) and the
    checkpoint path (or None); one-line UserErrors for a wrong shape or checkpoint_every without a file."""
    shape = kernel.event_shape
    if initial_params is not None:
        initial_params = torch.as_tensor(initial_params, dtype=kernel.dtype, device=kernel.device)
        if tuple(initial_params.shape) != (C,) + shape:
            raise UserError(f"initial_params: expected shape {(C,) + shape}, got {tuple(initial_params.shape)}")
    if checkpoint_every and checkpoint is None:
        raise UserError("checkpoint_every: needs a checkpoint file")
    return initial_params, (Path(checkpoint) if checkpoint is not None else None)

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
        :func:`check_checkpoint_request`) before that set-up, as :func:`accel_bayes.pipelines.calibrate.calibrate` does.
    callback : called as ``callback(chain, iteration, kernel)`` after every iteration
        (iteration counts warm-up and sampling, from 0).
    """
    for nm, v, lo in (("num_samples", num_samples, 1), ("warmup_steps", warmup_steps, 0),
                      ("num_chains", num_chains, 1), ("checkpoint_every", checkpoint_every, 0)):
        if not isinstance(v, (int, np.integer)) or int(v) < lo:
            raise UserError(f"{nm}: expected an integer >= {lo}, got {v!r}")
    C, D, W = int(num_chains), int(num_samples), int(warmup_steps)
    shape = kernel.event_shape
    initial_params, ckpt = _check_starts_and_checkpoint(kernel, C, initial_params, checkpoint, checkpoint_every)
    fp = dict(fingerprint or {})
    fp.update({"num_chains": C, "num_samples": D, "warmup_steps": W, "seed": kernel.seed,
               "event_shape": list(shape)})

    st = _new_arrays(kernel, C, D)
    diags: list = [None] * C
    chain0, it0, kstate, seconds0 = 0, 0, None, 0.0
    resumed = False
    if resume and ckpt is not None and ckpt.exists():
        saved = read_checkpoint(ckpt)
        bad = fingerprint_mismatch(saved["fingerprint"], fp)
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
        write_checkpoint({"format": CHECKPOINT_FORMAT, "fingerprint": fp, "chain": chain, "iteration": iteration,
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
            _iterate(kernel, st, c, start, total, W, bar, callback, checkpoint_every,
                     lambda it: save(c, it, kernel.state_dict(), time.perf_counter() - t_start))
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


def run_pmmh_until(
    kernel: PMMHKernel,
    check,
    warmup_steps: int,
    num_chains: int = 1,
    initial_params: torch.Tensor | None = None,
    *,
    check_every: int = 500,
    max_samples: int = 20_000,
    max_seconds: float | None = None,
    progress: bool = True,
    checkpoint: str | os.PathLike | None = None,
    checkpoint_every: int = 0,
    resume: bool = False,
    fingerprint: dict | None = None,
    callback=None,
) -> PMMHRun:
    """Run ``num_chains`` chains of ``kernel`` until ``check`` says they have converged, checking
    at fixed draw counts, up to a draw budget and a wall-clock safety stop.

    The chains are extended block by block: block 0 is each chain's ``warmup_steps`` warm-up
    iterations and its first ``check_every`` kept draws (chains one after another, as
    :func:`run_pmmh`), and every later block continues each chain from its saved kernel state
    (:meth:`PMMHKernel.state_dict`) by ``check_every`` more draws.  After each block,
    ``check(theta)`` is called on the draws so far, theta (C, D, A−1, 3); it returns an object with
    ``.converged`` (bool), and optionally ``.as_dict()`` (plain values, kept in ``run.checks``) and
    ``.line()`` (shown with the progress bars).  Because a chain's transitions depend only on its own
    state, a run that stops at D draws per chain holds exactly the draws of ``run_pmmh(…, D, …)``
    with the same kernel and seed.

    check_every : kept draws per chain between checks (≥ 1): the checks happen at D = check_every,
        2·check_every, … — fixed draw counts, never wall time, so where the run stops does not
        depend on the machine (except through ``max_seconds``).
    max_samples : most kept draws per chain (≥ 1; the last block is shortened to end there).
    max_seconds : wall-clock budget of the sampling in seconds (warm-up included, resumed time
        counted), tested after each check; None: no limit.  A safety stop: a run that ends by it
        has a machine-dependent number of draws (``run.stopped == "max_seconds"``).
    The run stops at the first check that passes (``run.stopped == "converged"``), else when
    ``max_samples`` draws are reached ("max_samples") or ``max_seconds`` has passed ("max_seconds").

    checkpoint, checkpoint_every, resume, fingerprint, callback, progress : as in :func:`run_pmmh`;
    the checkpoint (same format) also holds every chain's kernel state between blocks and the
    checks so far, so a resume continues bit-exactly, also in the middle of a block.  Resuming a
    run that stopped on a budget continues it when the new ``max_samples``/``max_seconds`` allow
    more (neither is part of the fingerprint), and gives the draws the larger budget would have
    given in one run: the stop happened right after a check that failed.
    """
    for nm, v, lo in (("check_every", check_every, 1), ("max_samples", max_samples, 1),
                      ("warmup_steps", warmup_steps, 0), ("num_chains", num_chains, 1),
                      ("checkpoint_every", checkpoint_every, 0)):
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or int(v) < lo:
            raise UserError(f"{nm}: expected an integer >= {lo}, got {v!r}")
    if max_seconds is not None:
        try:
            ok = float(max_seconds) > 0 and np.isfinite(float(max_seconds))
        except (TypeError, ValueError):
            ok = False
        if not ok or isinstance(max_seconds, bool):
            raise UserError(f"max_seconds: expected a finite number > 0 (seconds) or None, got {max_seconds!r}")
    if not callable(check):
        raise UserError("check: expected a callable check(theta) -> object with .converged")
    C, B, W, Dmax = int(num_chains), int(check_every), int(warmup_steps), int(max_samples)
    shape = kernel.event_shape
    initial_params, ckpt = _check_starts_and_checkpoint(kernel, C, initial_params, checkpoint, checkpoint_every)
    fp = dict(fingerprint or {})
    fp.update({"mode": "until-converged", "num_chains": C, "check_every": B, "warmup_steps": W,
               "seed": kernel.seed, "event_shape": list(shape)})

    st = _new_arrays(kernel, C, 0)
    diags: list = [None] * C
    states: list = [None] * C  # each chain's kernel state at the end of its last finished block
    checks: list = []
    done = 0  # kept draws per chain of the finished blocks
    target = None  # draws per chain at the end of the block in progress (None between blocks)
    chain0, it0, kstate, seconds0, stopped, resumed = 0, 0, None, 0.0, None, False
    if resume and ckpt is not None and ckpt.exists():
        saved = read_checkpoint(ckpt)
        bad = fingerprint_mismatch(saved["fingerprint"], fp)
        if bad:
            raise UserError(f"resume: checkpoint {ckpt} was written with different settings ({', '.join(bad)}); "
                            "rerun with the same options or without --resume")
        until = saved.get("until")
        if not isinstance(until, dict):
            raise UserError(f"checkpoint: {ckpt} holds no run-until-converged state; rerun without --resume")
        st, diags = saved["arrays"], saved["diagnostics"]
        chain0, it0, kstate = saved["chain"], saved["iteration"], saved["kernel"]
        seconds0 = float(saved.get("seconds", 0.0))
        states, checks, done, stopped = list(until["states"]), list(until["checks"]), int(until["done"]), until["stopped"]
        target = until.get("target")
        resumed = True
        if stopped is not None and stopped != "converged":
            # stopped on a budget: continue if the budgets given now allow more
            stopped = "max_samples" if done >= Dmax else (
                "max_seconds" if max_seconds is not None and seconds0 >= float(max_seconds) else None)

    def save(chain, iteration, kernel_state, seconds):
        if ckpt is None:
            return
        write_checkpoint({"format": CHECKPOINT_FORMAT, "fingerprint": fp, "chain": chain, "iteration": iteration,
                          "kernel": kernel_state, "arrays": st, "diagnostics": diags, "seconds": seconds,
                          "until": {"states": states, "checks": checks, "done": done, "target": target,
                                    "stopped": stopped}}, ckpt)

    t_start = time.perf_counter() - seconds0
    bar_cls = None
    if progress:
        from tqdm.auto import tqdm as bar_cls
    last_line = ""  # the last check, shown with the bars
    if checks:  # resumed: the last check so far
        h = checks[-1]
        last_line = f"{h.get('draws')} draws/chain" + (
            f": max R-hat {h['rhat_max']:.4f}" if isinstance(h.get("rhat_max"), float) else "")
    while stopped is None:
        if target is None:  # a new block (a resumed one keeps the target it was started with)
            target = min((done // B + 1) * B, Dmax)
        have = int(st["theta"].shape[1])
        if have < target:  # extend the per-draw arrays (a resumed block may already have them)
            more = _new_arrays(kernel, C, target - have)
            for k in _PER_DRAW:
                st[k] = torch.cat([st[k], more[k]], dim=1)
        for c in range(chain0, C):
            stop_it = W + target
            if c == chain0 and kstate is not None:
                kernel.load_state_dict(kstate)
                start = it0
            elif states[c] is None:  # the chain's first block: warm-up from its start point
                if initial_params is not None:
                    kernel.initial_params = {kernel.site: initial_params[c]}
                kernel.setup(W, chain_id=c)
                st["initial"][c] = kernel.initial_params[kernel.site]
                start = 0
            else:
                kernel.load_state_dict(states[c])
                start = W + done
            bar = None
            if bar_cls is not None and start < stop_it:
                first = 0 if done == 0 else W + done
                desc = (f"chain {c} draws {done}-{target}" + (f" (+{W} warm-up)" if first == 0 and W else "")
                        + (f" [check {len(checks)}: {last_line}]" if last_line else ""))
                bar = bar_cls(total=stop_it - first, initial=start - first, desc=desc, leave=False,
                              dynamic_ncols=True)
            try:
                _iterate(kernel, st, c, start, stop_it, W, bar, callback, checkpoint_every,
                         lambda it, c=c: save(c, it, kernel.state_dict(), time.perf_counter() - t_start))
            finally:
                if bar is not None:
                    bar.close()
            states[c] = kernel.state_dict()
            st["step_size"][c] = kernel.step_size
            st["proposal_cov"][c] = kernel.proposal_cov
            diags[c] = kernel.diagnostics()
            kstate = None
            if ckpt is not None and c + 1 < C:
                save(c + 1, 0, None, time.perf_counter() - t_start)
        chain0, done, target = 0, target, None
        res = check(st["theta"][:, :done])
        rec = dict(res.as_dict()) if hasattr(res, "as_dict") else {"draws": done, "converged": bool(res.converged)}
        rec["seconds"] = time.perf_counter() - t_start
        checks.append(rec)
        if bool(res.converged):
            stopped = "converged"
        elif done >= Dmax:
            stopped = "max_samples"
        elif max_seconds is not None and rec["seconds"] >= float(max_seconds):
            stopped = "max_seconds"
        line = res.line() if hasattr(res, "line") else f"{done} draws/chain"
        last_line = line
        if bar_cls is not None:
            bar_cls.write(f"check {len(checks)}: {line} -> "
                          + ("continuing" if stopped is None else f"stopped ({stopped})"), file=sys.stderr)
        save(0, 0, None, rec["seconds"])
    seconds = time.perf_counter() - t_start
    st = {k: (v[:, :done] if k in _PER_DRAW else v) for k, v in st.items()}
    return PMMHRun(diagnostics=diags, seconds=seconds, resumed=resumed, checks=checks, stopped=stopped, **st)

"""The PmMH runner: chains one after another, warm-up counting, per-draw statistics, crash-safe
checkpoints and a progress bar, using only the kernel's public methods (``setup``, ``sample``,
``last``, ``logging``, ``diagnostics``, ``state_dict``/``load_state_dict``).
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from ...errors import UserError
from .checkpoint import CHECKPOINT_FORMAT, fingerprint_mismatch, read_checkpoint, write_checkpoint
from .kernel import PMMHKernel

__all__ = ["PMMHRun", "run_pmmh"]


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
            for i in range(start, total):
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

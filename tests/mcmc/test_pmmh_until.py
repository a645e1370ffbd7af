"""Run-until-converged PmMH (:func:`run_pmmh_until`, issue #15 item 1): the chains are extended
block by block from each chain's saved kernel state, so a run that stops at D draws per chain holds
exactly the draws of one fixed run of D draws with the same seed; checkpoints resume bit-exactly
in the middle of a block and between blocks; budgets stop the run and are recorded.
"""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from accel_bayes import diagnostics as dg
from accel_bayes.errors import UserError
from accel_bayes.inference.mcmc import PMMHKernel, run_pmmh, run_pmmh_until
from accel_bayes.inference.mcmc.priors import GaussianPrior

FIELDS = ("theta", "log_phat", "log_prior", "accepted", "accept_prob", "move", "step_size", "proposal_cov",
          "initial")


class _NoisyGaussian:
    """log p̂ = ℓ(θ) + s ε − s²/2, ε ~ N(0, 1) from the kernel's generator (A = 3, reference 0)."""

    A, reference = 3, 0

    def __init__(self, noise=0.8):
        self.noise = noise
        g = torch.Generator().manual_seed(0)
        B = torch.randn(6, 6, generator=g, dtype=torch.float64)
        self.prec = torch.linalg.inv((B @ B.T / 6 + 0.5 * torch.eye(6, dtype=torch.float64)) * 1e-6)
        self.mu = torch.full((2, 3), 1e-3, dtype=torch.float64)

    def log_phat(self, positions, generator=None):
        th = positions[..., 1:, :] - positions[..., :1, :]
        x = (th - self.mu).reshape(*th.shape[:-2], -1)
        e = torch.randn(th.shape[:-2], generator=generator, dtype=th.dtype)
        return -0.5 * ((x @ self.prec) * x).sum(-1) + self.noise * e - 0.5 * self.noise ** 2


def _kernel(seed=3, noise=0.8):
    prior = GaussianPrior(torch.zeros(3, 3, dtype=torch.float64), std=3e-3)
    return PMMHKernel(_NoisyGaussian(noise), prior, seed=seed, independence_prob=0.3)


def _converges_at(n):
    """A check that passes once the chains have n draws (records what it saw)."""
    seen = []

    def check(theta):
        seen.append(int(theta.shape[1]))
        return SimpleNamespace(converged=theta.shape[1] >= n)

    check.seen = seen
    return check


W, C = 160, 2  # W ≥ 150: covariance windows and independence moments adapt in warm-up


def _same(a, b):
    for f in FIELDS:
        assert torch.equal(getattr(a, f), getattr(b, f)), f


def test_continuation_equals_one_long_run():
    """Stopping after 3 blocks of 70 draws gives exactly the fixed run of 210 draws, and the
    shorter prefixes are those of the fixed runs of 70 and 140 draws."""
    check = _converges_at(210)
    run = run_pmmh_until(_kernel(), check, W, C, check_every=70, max_samples=1000, progress=False)
    assert check.seen == [70, 140, 210] and run.stopped == "converged" and run.num_samples == 210
    assert [c["draws"] for c in run.checks] == [70, 140, 210]
    fixed = run_pmmh(_kernel(), 210, W, C, progress=False)
    _same(run, fixed)
    assert run.diagnostics == fixed.diagnostics
    short = run_pmmh(_kernel(), 70, W, C, progress=False)
    assert torch.equal(short.theta, run.theta[:, :70]) and torch.equal(short.log_phat, run.log_phat[:, :70])


def test_budget_stops_and_last_block_is_shortened():
    check = _converges_at(10 ** 9)
    run = run_pmmh_until(_kernel(), check, W, C, check_every=40, max_samples=100, progress=False)
    assert check.seen == [40, 80, 100] and run.stopped == "max_samples" and run.num_samples == 100
    _same(run, run_pmmh(_kernel(), 100, W, C, progress=False))
    # the wall-clock safety stop is tested after a check (here the first one)
    run = run_pmmh_until(_kernel(), _converges_at(10 ** 9), W, C, check_every=40, max_samples=1000,
                         max_seconds=1e-9, progress=False)
    assert run.stopped == "max_seconds" and run.num_samples == 40 and len(run.checks) == 1


@pytest.mark.parametrize("stop", [(0, 100), (1, 185), (0, 230), (1, 265)],
                         ids=["chain0-warmup", "chain1-block0", "chain0-block1", "chain1-block2"])
def test_resume_is_bit_exact_inside_and_between_blocks(tmp_path, stop):
    ck = tmp_path / "until.ckpt"
    full = run_pmmh_until(_kernel(), _converges_at(150), W, C, check_every=50, max_samples=400, progress=False)
    assert full.num_samples == 150

    def kill(chain, i, kernel):
        if (chain, i) == stop:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_pmmh_until(_kernel(), _converges_at(150), W, C, check_every=50, max_samples=400, progress=False,
                       checkpoint=ck, checkpoint_every=20, callback=kill)
    check = _converges_at(150)
    resumed = run_pmmh_until(_kernel(), check, W, C, check_every=50, max_samples=400, progress=False,
                             checkpoint=ck, checkpoint_every=20, resume=True)
    assert resumed.resumed and resumed.stopped == "converged"
    _same(resumed, full)
    assert resumed.diagnostics == full.diagnostics
    assert [c["draws"] for c in resumed.checks] == [50, 100, 150]
    # a finished run resumes to itself without sampling
    again = run_pmmh_until(_kernel(), check, W, C, check_every=50, max_samples=400, progress=False,
                           checkpoint=ck, resume=True)
    _same(again, full)


def test_resume_with_a_larger_budget_continues_as_one_run(tmp_path):
    ck = tmp_path / "until.ckpt"
    kw = dict(check_every=50, progress=False, checkpoint=ck)
    first = run_pmmh_until(_kernel(), _converges_at(200), W, C, max_samples=120, **kw)
    assert first.stopped == "max_samples" and first.num_samples == 120
    more = run_pmmh_until(_kernel(), _converges_at(200), W, C, max_samples=1000, resume=True, **kw)
    assert more.stopped == "converged" and more.num_samples == 200
    _same(more, run_pmmh_until(_kernel(), _converges_at(200), W, C, check_every=50, max_samples=1000,
                               progress=False))
    # other settings (here: the check interval) are refused
    with pytest.raises(UserError, match="different settings.*check_every"):
        run_pmmh_until(_kernel(), _converges_at(200), W, C, check_every=60, max_samples=1000, progress=False,
                       checkpoint=ck, resume=True)
    # a fixed-length run does not resume a run-until-converged checkpoint, nor the reverse
    with pytest.raises(UserError, match="different settings"):
        run_pmmh(_kernel(), 200, W, C, progress=False, checkpoint=ck, resume=True)


def test_with_the_real_convergence_check():
    """dg.convergence_check as the check (what calibrate uses); the checks are recorded."""
    check = lambda th: dg.convergence_check(th, rhat_max=1.05, ess_min=100)  # noqa: E731
    g = torch.Generator().manual_seed(0)
    init = 1e-3 + 1e-3 * torch.randn(C, 2, 3, generator=g, dtype=torch.float64)  # around the posterior
    run = run_pmmh_until(_kernel(noise=0.1), check, 400, C, init, check_every=200, max_samples=4000,
                         progress=False)
    assert run.stopped == "converged" and run.checks[-1]["converged"] and len(run.checks) >= 2
    assert all(not c["converged"] and c["failed"] for c in run.checks[:-1])
    last = dg.convergence_check(run.theta, rhat_max=1.05, ess_min=100)
    assert last.converged and last.as_dict()["rhat_max"] == run.checks[-1]["rhat_max"]
    # the noisier chains do not get there within a small budget: stopped, with the reasons recorded
    run = run_pmmh_until(_kernel(), check, W, C, check_every=100, max_samples=300, progress=False)
    assert run.stopped == "max_samples" and not run.checks[-1]["converged"]
    assert any("ESS" in f for f in run.checks[-1]["failed"])


def test_progress_reports_each_check(capsys):
    run_pmmh_until(_kernel(), _converges_at(60), W, 1, check_every=30, max_samples=100, progress=True)
    err = capsys.readouterr().err
    assert "check 1:" in err and "continuing" in err and "check 2:" in err and "stopped (converged)" in err


def test_refuses_bad_settings():
    for kw, name in ((dict(check_every=0), "check_every"), (dict(max_samples=0), "max_samples"),
                     (dict(max_seconds=0.0), "max_seconds"), (dict(max_seconds=float("nan")), "max_seconds"),
                     (dict(checkpoint_every=5), "checkpoint_every")):
        with pytest.raises(UserError, match=name):
            run_pmmh_until(_kernel(), _converges_at(1), W, C, progress=False, **kw)
    with pytest.raises(UserError, match="check"):
        run_pmmh_until(_kernel(), None, W, C, progress=False)

"""The pieces of the PmMH package (accel_bayes.inference.mcmc), each alone: the step-size and
covariance adapters, the proposals and their mixture, the kernel's checkpoint state (format 1)."""
import math

import pytest
import torch

from accel_bayes.inference.mcmc.adaptation import (INIT_BUFFER, RM_DECAY, RM_GAIN, CovarianceAdapter,
                                                   StepSizeAdapter, regularized_cov, warmup_windows)
from accel_bayes.inference.mcmc.proposals import (MOVE_IND, MOVE_RW, IndependenceProposal, ProposalMixture,
                                                  RandomWalkProposal)

F64 = torch.float64


def test_step_size_adapter_robbins_monro_and_polyak_average():
    a = StepSizeAdapter(0.2)
    a.setup(10)  # averaging from step 6 (W // 2 = 5, strictly after)
    ls, seen = 0.0, []
    for t, alpha in enumerate([0.0, 1.0, 0.5, 0.2, 0.1, 0.3, 0.0, 0.9, 0.2, 0.4], start=1):
        new = a.update(ls, alpha, t)
        assert new == ls + RM_GAIN / (t ** RM_DECAY) * (alpha - 0.2)
        ls = new
        if t > 5:
            seen.append(ls)
    assert a.final(ls) == sum(seen) / len(seen)
    off = StepSizeAdapter(0.2, enabled=False)
    off.setup(10)
    assert off.update(-1.0, 0.9, 1) == -1.0 and off.final(-1.0) == -1.0


def test_step_size_adapter_restart_resets_gain_and_average():
    a = StepSizeAdapter(0.25)
    a.setup(100)
    for t in range(1, 61):
        a.update(0.0, 0.5, t)
    a.restart(60)  # new phase: gain from k = 1, averaging from 60 + 20
    assert a.update(0.0, 0.75, 61) == RM_GAIN / 2
    assert a.final(7.0) == 7.0  # nothing averaged yet in this phase
    assert a.state_dict()["avg_from"] == 80


def test_covariance_adapter_windows_and_moments():
    W = 200
    ends = warmup_windows(W)
    cov = CovarianceAdapter(2, F64)
    cov.setup(W)
    g = torch.Generator().manual_seed(0)
    draws = torch.randn(W, 2, generator=g, dtype=F64) * torch.tensor([1.0, 3.0], dtype=F64)
    start, got = int(INIT_BUFFER * W), []
    for t in range(1, W + 1):
        if cov.observe(t, draws[t - 1]):
            got.append((t, cov.take()))
    assert [t for t, _ in got] == ends
    # the first window holds the draws after the initial buffer up to its end
    x = draws[start:ends[0]]
    c0, m0 = got[0][1]
    assert torch.allclose(m0, x.mean(0))
    assert torch.allclose(c0, regularized_cov(len(x), x.sum(0), x.T @ x))
    assert cov.state_dict()["win_n"] == 0  # cleared


def test_independence_log_q_is_the_gaussian_log_density_up_to_a_constant():
    g = torch.Generator().manual_seed(1)
    B = torch.randn(6, 6, generator=g, dtype=F64)
    S = B @ B.T + torch.eye(6, dtype=F64)
    mean = torch.randn(2, 3, generator=g, dtype=F64)
    q = IndependenceProposal((2, 3), scale=1.3)
    assert not q.available
    q.set(mean, S)
    ref = torch.distributions.MultivariateNormal(mean.reshape(-1), covariance_matrix=1.3**2 * S)
    a, b = torch.randn(2, 2, 3, generator=g, dtype=F64)
    assert torch.allclose(q.log_q(a) - q.log_q(b), ref.log_prob(a.reshape(-1)) - ref.log_prob(b.reshape(-1)))


def test_mixture_draw_order_and_move_types():
    rw = RandomWalkProposal(torch.eye(6, dtype=F64) * 1e-6, math.log(0.5))
    ind = IndependenceProposal((2, 3), scale=1.0)
    mix = ProposalMixture(rw, ind, independence_prob=0.9)
    theta = torch.zeros(2, 3, dtype=F64)
    # no independence proposal yet: no uniform drawn, only ε
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    prop, lq, mv = mix.propose(theta, g1, warming_up=False)
    eps = torch.randn(6, generator=g2, dtype=F64)
    assert mv == MOVE_RW and lq == 0.0 and torch.equal(prop, rw.propose(theta, eps))
    ind.set(torch.ones(2, 3, dtype=F64), torch.eye(6, dtype=F64))
    moves = [mix.propose(theta, g1, warming_up=w)[2] for w in [True] * 400 + [False] * 400]
    share_warm = sum(m == MOVE_IND for m in moves[:400]) / 400
    share_after = sum(m == MOVE_IND for m in moves[400:]) / 400
    assert 0.4 < share_warm < 0.6 and share_after > 0.83  # capped at 1/2 during warm-up


def test_kernel_state_keys_are_those_of_checkpoint_format_1():
    from pathlib import Path

    from test_pmmh_reference import _kernels

    old = torch.load(Path(__file__).parent / "data" / "pmmh_checkpoint_v1.ckpt", weights_only=True)
    k = _kernels()["adapted"]()
    k.setup(200)
    assert set(k.state_dict()) == set(old["kernel"])

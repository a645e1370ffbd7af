"""The fast general path of the per-sample likelihood (issue #30 item 3, fastjerk): N_t from the
θ-free age pairs, the right-looking Cholesky over the samples, the reused buffers without autograd.

References: the same path with the pair products switched off (the elementwise Gram over the φ
components), one position at a time, central finite differences for the autograd path, and (slow)
the cost bar itself — one log p̂ with the angular jerk at most 4× the flat model's at exp_1's size.
"""
import statistics
import time

import pytest
import torch

import accel_bayes.model.likelihood_percov as lp
from accel_bayes.model.gyro_posterior import gyro_posterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood
from accel_bayes.physics.models import specific_force
from tests.model.test_angular_jerk import LEVER
from tests.model.test_instant_error import _rate
from tests.model.test_likelihood_percov import POS5, SIG, _case

DT = torch.float64


def _models(T=40, N=3, seed=5):
    acc, omega, age, s = _case(T=T, seed=seed)
    ang = torch.linspace(2e4, 9e4, T, dtype=DT)
    a = PerSampleCovLikelihood(acc, omega, SIG, N, age, s, angjerk_std=ang, lever=LEVER)
    e = PerSampleCovLikelihood(acc, omega, SIG, N, age, s, angjerk_std=ang, lever=LEVER, rate=_rate(T, 5),
                               instant_std=2e-4)
    return a, e


def test_the_age_pair_products_give_the_gram_path_values_and_a_batch_gives_each_position(monkeypatch):
    """N_t from the age pairs against the elementwise Gram (A = 5: 15 pairs, under the cap), at a
    batch of three positions and at each alone; the instant error's columns keep the Gram."""
    a, e = _models()
    assert a._theta_free[-1] is not None and e._theta_free[-1] is None
    pos = torch.stack((POS5, POS5 * 1.2, POS5 + 0.004))
    z = a.sample_z((), 3, torch.Generator().manual_seed(2))
    with torch.no_grad():
        fast = a.log_phat(pos, z=z).clone()
        one = torch.stack([a.log_phat(p, z=z) for p in pos])
        terms = {k: v.clone() for k, v in a._percov_terms(a._positions(pos)).items() if k in ("V", "logdetN")}
        monkeypatch.setattr(lp, "_MAX_AGE_PAIRS", 0)
        b = PerSampleCovLikelihood(a.acc, a.omega, SIG, 3, a.age, a.jerk_std, angjerk_std=a.angjerk_std, lever=LEVER)
        assert b._theta_free[-1] is None and b.W is not None and a.W is None
        gram = b.log_phat(pos, z=z)
        ref = b._percov_terms(b._positions(pos))
    torch.testing.assert_close(fast, gram, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(one, fast, rtol=1e-12, atol=1e-9)
    for k, v in terms.items():
        torch.testing.assert_close(v, ref[k], rtol=1e-10, atol=1e-10)
    # the term is there: without the angular jerk the value moves by nats
    plain = PerSampleCovLikelihood(a.acc, a.omega, SIG, 3, a.age, a.jerk_std)
    assert float((plain.log_phat(pos, z=z) - fast).abs().min()) > 1.0


@pytest.mark.parametrize("which", ["pairs", "instant"])
def test_log_phat_with_draws_per_position_and_with_autograd_gives_each_position_alone(which):
    """One z per position (the per-draw u of each position from its own draws) and positions that
    require grad (out-of-place per-draw path) give each position's own log p̂."""
    a, e = _models()
    lik = a if which == "pairs" else e
    pos = torch.stack((POS5, POS5 * 1.2, POS5 + 0.004))
    z = lik.sample_z((3,), 3, torch.Generator().manual_seed(4))
    with torch.no_grad():
        one = torch.stack([lik.log_phat(p, z=zz) for p, zz in zip(pos, z)])
        torch.testing.assert_close(lik.log_phat(pos, z=z), one, rtol=1e-12, atol=1e-9)
    torch.testing.assert_close(lik.log_phat(pos.clone().requires_grad_(True), z=z).detach(), one, rtol=1e-12,
                               atol=1e-9)


@pytest.mark.parametrize("which", ["pairs", "instant"])
def test_the_autograd_path_gives_the_in_place_values_and_their_gradient(which):
    """With positions that require grad the general path runs out of place (no reused buffers): the
    same values as the in-place path, and the gradient of log p(y | ω, θ) matches central finite
    differences of the in-place values; a call at another θ in between leaves no trace."""
    a, e = _models()
    lik = a if which == "pairs" else e
    w = lik.omega.mean + 0.1
    with torch.no_grad():
        v0 = lik.log_lik_given_omega(POS5, w).clone()
        lik.log_lik_given_omega(POS5 * 1.3, w)  # the reused buffers now hold another θ
        assert float(lik.log_lik_given_omega(POS5, w)) == float(v0)
    p = POS5.clone().requires_grad_(True)
    v = lik.log_lik_given_omega(p, w)
    (g,) = torch.autograd.grad(v, p)
    assert float(v.detach()) == pytest.approx(float(v0), rel=1e-12)
    h = 1e-6
    with torch.no_grad():
        for k, i in ((1, 0), (2, 1), (4, 2), (3, 2)):
            dp = torch.zeros_like(POS5)
            dp[k, i] = h
            fd = (lik.log_lik_given_omega(POS5 + dp, w) - lik.log_lik_given_omega(POS5 - dp, w)) / (2 * h)
            assert float(g[k, i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-3)


def _cpu_ms(fns: dict, rounds: int, block: int) -> dict:
    """10th percentile of the thread CPU time per call (ms), blocks alternating between the calls:
    robust to the other jobs on a shared machine."""
    times = {k: [] for k in fns}
    for _ in range(rounds):
        for k, fn in fns.items():
            for _ in range(block):
                t0 = time.thread_time()
                fn()
                times[k].append(time.thread_time() - t0)
    return {k: 1e3 * sorted(v)[len(v) // 10] for k, v in times.items()}


@pytest.mark.slow
def test_one_log_phat_with_the_angular_jerk_costs_at_most_four_flat_ones_at_exp1_size():
    """Issue #30 item 3 at exp_1's size (T = 5885, A = 8, N = 1, one thread), synthetic data: the
    angular jerk's log p̂ ≤ 4× the flat model's (the code before fastjerk: 4.8× on this case; after: 2.4×)."""
    T, A = 5885, 8
    g = torch.Generator().manual_seed(7)
    pos = 0.03 * torch.randn(A, 3, generator=g, dtype=DT)
    w = 20 * torch.randn(T, 3, generator=g, dtype=DT)
    acc = specific_force(pos, w, 50 * torch.randn(T, 3, generator=g, dtype=DT),
                         10 * torch.randn(T, 3, generator=g, dtype=DT)) + torch.randn(T, A, 3, generator=g, dtype=DT)
    omega = gyro_posterior(w[:, None, :] + 0.05 * torch.randn(T, 4, 3, generator=g, dtype=DT),
                           torch.full((4,), 0.05, dtype=DT), "calibrated")
    age = 1e-3 * torch.rand(T, A, generator=g, dtype=DT)
    flat = RaoBlackwellLikelihood(acc, omega, 1.5, 1)
    ang = PerSampleCovLikelihood(acc, omega, 1.5, 1, age, 3e3, angjerk_std=1e5, lever=pos)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with torch.no_grad():
            gen = torch.Generator().manual_seed(1)
            fns = {"flat": lambda: flat.log_phat(pos, generator=gen), "ang": lambda: ang.log_phat(pos, generator=gen)}
            for fn in fns.values():
                fn()
            ms = _cpu_ms(fns, rounds=8, block=10)
    finally:
        torch.set_num_threads(threads)
    assert ms["ang"] <= 4.0 * ms["flat"], ms
    print(f"angular jerk {ms['ang']:.3f} ms, flat {ms['flat']:.3f} ms, {ms['ang'] / ms['flat']:.2f}x")

"""The sandwich from a likelihood's own per-sample scores (issue #30, experiments/percov_honesty_probe.py).

``PerSampleCovLikelihood.log_lik_per_sample`` against the dense per-sample Gaussian of
test_likelihood_percov; ``per_sample_scores`` against central differences; and on a simulated flat
case, the score sandwich (``score_sandwich``) against ``sandwich_inflation``'s, computed by its own
residual/Jacobian route with ω pinned at ω̄ (the scores then differ only by the common
∂(−½ log|M|)/∂θ, which ``sandwich_inflation`` leaves out).
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from accel_bayes.inference.noise_fit import per_sample_scores, sandwich_inflation, score_sandwich
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import with_unresolved_motion

from .test_likelihood_percov import POS5, SIG, _case, _dense_sample_logpdfs

DT = torch.float64


def _full(th):
    return torch.cat((torch.zeros(1, 3, dtype=DT), th.reshape(-1, 3)))


def test_per_sample_terms_equal_the_dense_gaussian_per_sample():
    acc, omega, age, s = _case(T=9)
    lik = with_unresolved_motion(RaoBlackwellLikelihood(acc, omega, SIG, 1), age, s)
    w = omega.mean + 0.1
    got = lik.log_lik_per_sample(POS5 * 1.2, w).numpy()
    const = -(3 * 5 - 6) / 2 * math.log(2 * math.pi) - 15 * math.log(SIG)  # per sample, omitted by the class
    want = _dense_sample_logpdfs(POS5 * 1.2, acc, w, age, s)
    np.testing.assert_allclose(got + const, want, rtol=1e-10, atol=1e-8)
    assert float(lik.log_lik_given_omega(POS5 * 1.2, w)) == pytest.approx(got.sum(), rel=1e-12)


def test_per_sample_scores_match_central_differences():
    acc, omega, age, s = _case(T=6)
    lik = with_unresolved_motion(RaoBlackwellLikelihood(acc, omega, SIG, 1), age, s)
    th = POS5[1:].reshape(-1).clone()

    def ell(t):
        return lik.log_lik_per_sample(_full(t), omega.mean)

    got = per_sample_scores(ell, th)
    h = 1e-6
    want = torch.stack([(ell(th + h * e) - ell(th - h * e)) / (2 * h) for e in torch.eye(len(th), dtype=DT)], -1)
    assert got.shape == (6, len(th))
    torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("lags", [0, None, 3])
def test_score_sandwich_reproduces_sandwich_inflation_on_a_flat_case(lags):
    acc, omega, age, _ = _case(T=300, seed=11, jerk=0.0)
    g = torch.Generator().manual_seed(1)
    # heteroscedastic extra noise: a misfit the flat model does not know of
    acc = acc + 2 * SIG * torch.rand(acc.shape[0], 1, 1, generator=g, dtype=DT) * torch.randn(acc.shape, generator=g,
                                                                                            dtype=DT)
    flat = with_unresolved_motion(RaoBlackwellLikelihood(acc, omega, SIG, 1), age, 0.0)
    th = (POS5[1:] + 1e-3).reshape(-1)  # any point with a positive-definite Hessian: the identity is algebra
    wbar = omega.mean

    def ell(t):
        return flat.log_lik_per_sample(_full(t), wbar)

    def half_logdet_m(t):
        return -0.5 * flat._projection_hot(flat._positions(_full(t))[None])["logdetM"]

    S = per_sample_scores(ell, th) - per_sample_scores(half_logdet_m, th)[0]
    cov = torch.linalg.inv(torch.autograd.functional.hessian(lambda t: -ell(t).sum(), th))
    mine = score_sandwich(S, cov, lags=lags)
    mr = SimpleNamespace(positions=_full(th), theta=th.reshape(-1, 3), omega=wbar, laplace_cov=cov)
    pkg = sandwich_inflation(acc, wbar, 1e-12 * torch.eye(3, dtype=DT), SIG, mr, prior_mean=_full(th), lags=lags)
    assert mine["lags"] == pkg["lags"]
    np.testing.assert_allclose(mine["std_ratio"], pkg["std_ratio"], rtol=1e-6)
    # the misfit is real (heteroscedastic data): the ratios are far from 1, so agreement is not trivial
    assert np.max(pkg["std_ratio"]) > 1.2
    # with the determinant's gradient kept the sandwich differs: the comparison is sensitive to it
    full = score_sandwich(per_sample_scores(ell, th), cov, lags=lags)
    assert np.max(np.abs(full["std_ratio"] / pkg["std_ratio"] - 1)) > 1e-3

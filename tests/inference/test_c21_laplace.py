"""Two independent Laplace approximations of the [C21] geometry posterior check each other.

``experiments/_laplace.py`` (dense S, autograd Hessian, Newton, ω held at the gyro average; no
code shared with the package's likelihood/MAP) against :func:`accel_bayes.inference.map.fit_map`
(LM on the factor graph, φ by variable projection, ω marginalised by a Schur complement).  With
the calibrated 8-gyro posterior (std ≈ 4·10⁻⁴ rad/s against |ω| ≈ 30 rad/s) fixing ω changes
the covariance by far less than the 5 % tolerance, so a larger disagreement is a bug in one of
the two.
"""

import numpy as np
import pytest
import torch

from experiments._laplace import laplace_from_recording, log_posterior

from accel_bayes.physics.arrays import mimu4444_8  # noqa: E402
from accel_bayes.model.likelihood import RaoBlackwellLikelihood  # noqa: E402
from accel_bayes.simulate import simulate  # noqa: E402


def _case(T=20, seed=3, acc_std=0.04):
    arr = mimu4444_8()
    sim = simulate(arr, "iid", T=T, seed=seed, clip=False, acc_noise_std=acc_std)
    g = torch.Generator().manual_seed(seed)
    prior_mean = sim.true_positions + 1e-4 * torch.randn(arr.K, 3, generator=g, dtype=torch.float64)
    return sim, prior_mean


def test_log_posterior_matches_beta_limit():
    """The dense φ-projected density equals the β → ∞ limit of the exact Gaussian marginal
    N(y; h, Q + β H F Hᵀ) ([C21] eq. 18–23 with the −½ power): differences between two θ agree."""
    torch.manual_seed(0)
    A, T = 4, 3
    r0 = torch.tensor([[0.0, 0, 0], [0.01, 0, 0.001], [0, 0.012, -0.001], [0.011, 0.009, 0.0]], dtype=torch.float64)
    omega = torch.randn(T, 3, dtype=torch.float64) * 5
    acc = torch.randn(T, A, 3, dtype=torch.float64)
    std = torch.full((A,), 0.3, dtype=torch.float64)
    th1 = r0[1:]
    th2 = r0[1:] + 2e-3 * torch.randn(A - 1, 3, dtype=torch.float64)
    big = 1e30  # a flat prior on θ: compare the likelihood parts only
    ours = (log_posterior(th1, acc, omega, std, th1, big) - log_posterior(th2, acc, omega, std, th1, big)).item()

    def exact(theta, beta):
        r = torch.cat((torch.zeros(1, 3, dtype=torch.float64), theta), 0)
        out = 0.0
        for t in range(T):
            w = omega[t]
            h = torch.linalg.cross(w.expand(A, 3), torch.linalg.cross(w.expand(A, 3), r, dim=-1), dim=-1).reshape(-1)
            H = torch.zeros(3 * A, 6, dtype=torch.float64)
            for k in range(A):
                x, y, z = r[k]
                H[3 * k:3 * k + 3, :3] = -torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64)
                H[3 * k:3 * k + 3, 3:] = torch.eye(3, dtype=torch.float64)
            cov = torch.diag(std.repeat_interleave(3) ** 2) + beta * H @ H.T
            out += torch.distributions.MultivariateNormal(h, cov).log_prob(acc[t].reshape(-1)).item()
        return out

    # log N carries −½ log|βF| per sample, the same for both θ: it cancels in the difference.
    # The finite-β error is O(1/β): it shrinks from β = 10⁴ to 10⁸ and ends below 10⁻⁴.
    errs = [abs((exact(th1, beta) - exact(th2, beta)) - ours) for beta in (1e4, 1e8)]
    assert errs[1] < 1e-4 * max(1.0, abs(ours))
    assert errs[1] < errs[0]
    # The test can tell the powers apart: [C21] eq. 25 as printed (|M|⁻¹) differs from the limit
    # by (T/2)·Δlog|M|, far beyond the tolerance here.
    def logdet_M(theta):
        r = torch.cat((torch.zeros(1, 3, dtype=torch.float64), theta), 0)
        H = torch.cat([torch.cat((-torch.tensor([[0, -z, y], [z, 0, -x], [-y, x, 0]], dtype=torch.float64),
                                  torch.eye(3, dtype=torch.float64)), 1) for x, y, z in r.tolist()], 0)
        lam = std.repeat_interleave(3) ** -2
        return torch.linalg.slogdet(H.T @ (lam[:, None] * H))[1].item()

    printed = ours - 0.5 * T * (logdet_M(th1) - logdet_M(th2))
    assert abs((exact(th1, 1e8) - exact(th2, 1e8)) - printed) > 100 * errs[1]


def test_laplace_newton_finds_mode():
    """At the returned mode the gradient vanishes (relative to the prior scale) and the
    covariance is symmetric positive definite."""
    sim, prior_mean = _case(T=10)
    res = laplace_from_recording(sim.recording, prior_mean, 3e-3)
    assert res.grad_norm < 1e-6
    ev = torch.linalg.eigvalsh(res.cov)
    assert bool((ev > 0).all())
    # the posterior is much narrower than the 3 mm prior and centred within a few std of the truth
    assert res.std_mean_um < 300
    truth = (sim.true_positions - sim.true_positions[0])[1:]
    z = ((res.mode - truth) / res.std).abs().max().item()
    assert z < 5


def test_laplace_agrees_with_map_helper():
    """Average posterior std of the independent Laplace vs fit_map's laplace_cov: within 5 %,
    and coordinate by coordinate within 10 % (mimu8, T = 20, σ_a = 0.04 m/s²)."""
    fm = pytest.importorskip("accel_bayes.inference.map", reason="accel_bayes.inference.map (fit_map) not present")
    sim, prior_mean = _case(T=20)
    rec = sim.recording
    ours = laplace_from_recording(rec, prior_mean, 3e-3)
    lik = RaoBlackwellLikelihood.from_recording(rec, num_draws=1, gyro_method="calibrated")
    res = fm.fit_map(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, reference=lik.reference,
                     prior_mean=prior_mean, prior_std=3e-3)
    std_map = torch.diagonal(res.laplace_cov).sqrt()
    std_ours = ours.std.reshape(-1)
    ratio = float(std_map.mean() / std_ours.mean())
    assert ratio == pytest.approx(1.0, abs=0.05), f"mean std: map {std_map.mean():.3e} vs ours {std_ours.mean():.3e}"
    assert np.allclose(std_map.numpy(), std_ours.numpy(), rtol=0.10)
    # the modes agree to a small fraction of the posterior std
    assert float(((res.theta - ours.mode) / ours.std).abs().max()) < 0.1

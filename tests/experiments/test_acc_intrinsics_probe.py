"""The per-triad accelerometer-gain probe (``experiments/acc_intrinsics_probe.py``) on small synthetic
arrays: a 0.5 % gain put on one triad is recovered within its Laplace std (and nothing on the others),
none is found where none was put, and the two likelihood rewrites it rests on (corrected data with
their Jacobian; rescaled noise levels) equal likelihoods built from scratch."""
import numpy as np
import pytest
import torch

from accel_bayes.model.gyro_posterior import GyroPosterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.physics.models import G_matrix, H_matrix, u_of_omega
from experiments import acc_intrinsics_probe as ap

SIGMA = 0.01  # m/s², white accelerometer noise
R = torch.tensor([[0, 0, 0], [0.019, 0, 0], [0, -0.019, 0.001], [0.019, -0.019, -0.002]], dtype=torch.float64)


def _data(gain, seed=0, T=400):
    """(T, 4, 3) m/s² readings of a 4-triad array rotated hard (|ω| ~ 10 rad/s), triad k's readings
    × (1 + gain[k]), and the gyro posterior (ω known to 1e-4 rad/s)."""
    g = torch.Generator().manual_seed(seed)
    w = 6.0 * torch.randn(T, 3, generator=g, dtype=torch.float64)
    phi = torch.cat([50.0 * torch.randn(T, 3, generator=g, dtype=torch.float64),
                     5.0 * torch.randn(T, 3, generator=g, dtype=torch.float64)], -1)
    y = (u_of_omega(w) @ G_matrix(R).T + phi @ H_matrix(R).T).reshape(T, 4, 3)
    y = y * (1.0 + torch.as_tensor(gain, dtype=torch.float64))[None, :, None]
    y = y + SIGMA * torch.randn(y.shape, generator=g, dtype=torch.float64)
    post = GyroPosterior(w, 1e-8 * torch.eye(3, dtype=torch.float64).expand(T, 3, 3).clone(), "test")
    return y, post


def _lik(y, post, sigma=SIGMA):
    # the φ prior the data were drawn from: the model is then exactly right and its Laplace std honest
    return RaoBlackwellLikelihood(y, post, sigma, 1, phi_prior=(50.0, 5.0))


@pytest.mark.parametrize("kind", ["scale", "sym"])
def test_a_gain_on_one_triad_is_recovered(kind):
    e = 0.005
    lik = _lik(*_data([0.0, 0.0, e, 0.0]))
    f = ap.fit_acc_gain(lik, R + 5e-4, kind)
    K = torch.zeros(4, 3, 3, dtype=torch.float64)
    K[2] = (1 / (1 + e) - 1) * torch.eye(3, dtype=torch.float64)
    want = np.asarray(ap.params_of(K, kind, 0))
    z = (np.asarray(f["k"]) - want) / np.asarray(f["k_std"])
    assert np.abs(z).max() < 4, z
    # resolved: the gain is many std from zero on triad 2's scale entries
    n = ap.KINDS[kind]
    assert max(f["k_std"][n:n + 3 if kind == "sym" else n + 1]) < 1e-3
    assert f["gain_nats"] > 20


def test_no_gain_is_found_where_none_was_put():
    lik = _lik(*_data([0.0, 0.0, 0.0, 0.0], seed=1))
    f = ap.fit_acc_gain(lik, R, "sym")
    z = np.asarray(f["k"]) / np.asarray(f["k_std"])
    assert np.abs(z).max() < 4.5, z  # 18 parameters
    assert f["gain_nats"] < 25  # ~ chi²_18 / 2
    # the noise levels were right: α ≈ 1
    assert np.allclose(f["alpha"], 1.0, atol=0.1)


def test_corrected_data_and_rescaled_noise_equal_likelihoods_built_from_them():
    y, post = _data([0.0, 0.003, 0.0, -0.002], seed=2)
    lik = _lik(y, post)
    K = ap.k_matrices(torch.arange(1.0, 19.0, dtype=torch.float64) * 1e-3, "sym", 4, 0)
    a = torch.tensor([1.2, 0.8, 1.0, 0.5], dtype=torch.float64)
    got = ap.with_acc(ap.with_noise_scale(lik, a), K)
    ref = _lik(ap.corrected_acc(y, K), post, sigma=SIGMA * a[:, None].expand(4, 3))
    w = post.mean
    np.testing.assert_allclose(float(got.log_lik_given_omega(R, w)) + got.log_constant,
                               float(ref.log_lik_given_omega(R, w)) + ref.log_constant, rtol=1e-10)
    assert float(K[0].abs().max()) == 0.0  # the reference triad keeps K = 0


def test_params_invert_the_matrices():
    for kind, n in ap.KINDS.items():
        p = torch.arange(1.0, 3 * n + 1, dtype=torch.float64) * 1e-3
        K = ap.k_matrices(p, kind, 4, 1)
        np.testing.assert_allclose(ap.params_of(K, kind, 1), p.numpy())
        assert torch.allclose(K, K.transpose(-1, -2))


@pytest.mark.parametrize("blocks", [True, False])
def test_rescaled_noise_equals_a_per_sample_likelihood_built_from_scratch(blocks):
    from accel_bayes.model.likelihood_percov import with_unresolved_motion

    y, post = _data([0.0, 0.0, 0.0, 0.0], seed=3, T=50)
    g = torch.Generator().manual_seed(4)
    age = 1e-3 * torch.rand(50, 4, generator=g, dtype=torch.float64)
    rate = 100.0 * torch.randn(50, 4, 3, generator=g, dtype=torch.float64)
    # every path that whitens a loading by λ^½ at construction: angular jerk, instant errors, an unknown age
    kw = dict(rate=rate, instant_std=2e-4, angjerk_std=3e4, lever=R, age_var=torch.tensor([0.0, 0.0, 1e-7, 0.0]))
    if not blocks:  # the angular jerk alone: N_t from the age pairs, no whitened loading stored
        kw = dict(angjerk_std=3e4, lever=R)
    a = torch.tensor([1.3, 0.7, 1.0, 0.6], dtype=torch.float64)
    got = ap.with_noise_scale(with_unresolved_motion(_lik(y, post), age, 20.0, **kw), a)
    ref = with_unresolved_motion(_lik(y, post, sigma=SIGMA * a[:, None].expand(4, 3)), age, 20.0, **kw)
    w = post.mean + 0.01
    np.testing.assert_allclose(float(got.log_lik_given_omega(R, w)) + got.log_constant,
                               float(ref.log_lik_given_omega(R, w)) + ref.log_constant, rtol=1e-10)


@pytest.mark.parametrize("c", [0.01, 0.05])
def test_a_common_isotropic_gain_is_an_array_scale(c):
    """The probe's "Identifiability": with the Jacobian, (1 + c) on every triad is the array scaled by
    1/(1 + c) with the noise std scaled alike — exactly, up to the flat φ prior's measure of the specific
    force s (s' = (1 + c) s: 3 log(1 + c) nats per sample).  Without the Jacobian this fails by 3A T log(1 + c)."""
    T = 30
    y, post = _data([0.0, 0.0, 0.0, 0.0], seed=5, T=T)
    K = c * torch.eye(3, dtype=torch.float64).expand(4, 3, 3)
    got = ap.with_acc(RaoBlackwellLikelihood(y, post, SIGMA, 1), K)
    lhs = float(got.log_lik_given_omega(R, post.mean)) + got.log_constant + float(ap.log_jacobian(K, T))
    ref = RaoBlackwellLikelihood(y, post, SIGMA / (1 + c), 1)
    rhs = float(ref.log_lik_given_omega(R / (1 + c), post.mean)) + ref.log_constant
    assert lhs - rhs == pytest.approx(3 * T * np.log1p(c), rel=1e-9)

"""The common-gyro-error probe (``experiments/gyro_common_probe.py``) on small synthetic arrays: an
anisotropic error put into ω̄ is recovered within its Laplace std, none is found where none was put,
and a common SCALE is measurable only with the geometry known (free positions absorb it exactly)."""
import dataclasses

import numpy as np
import pytest
import torch

from accel_bayes.model.gyro_posterior import GyroPosterior
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.physics.models import G_matrix, H_matrix, u_of_omega
from experiments import gyro_common_probe as gp

SIGMA = 0.01  # m/s², white accelerometer noise


def _case(G_true, seed=0, T=400):
    """A 4-triad array (m) rotated hard (|ω| ~ 10 rad/s) whose gyros read ω̄ with ω_true = (I + G) ω̄."""
    g = torch.Generator().manual_seed(seed)
    r = torch.tensor([[0, 0, 0], [0.019, 0, 0], [0, -0.019, 0.001], [0.019, -0.019, -0.002]], dtype=torch.float64)
    w_bar = 6.0 * torch.randn(T, 3, generator=g, dtype=torch.float64)
    w = gp.corrected_omega(w_bar, torch.as_tensor(G_true, dtype=torch.float64))
    phi = torch.cat([50.0 * torch.randn(T, 3, generator=g, dtype=torch.float64),
                     5.0 * torch.randn(T, 3, generator=g, dtype=torch.float64)], -1)
    y = u_of_omega(w) @ G_matrix(r).T + phi @ H_matrix(r).T
    y = y + SIGMA * torch.randn(y.shape, generator=g, dtype=torch.float64)
    post = GyroPosterior(w_bar, 1e-8 * torch.eye(3, dtype=torch.float64).expand(T, 3, 3).clone(), "test")
    # the φ prior the data were drawn from: the model is then exactly right and its Laplace std honest
    return RaoBlackwellLikelihood(y.reshape(T, 4, 3), post, SIGMA, 1, phi_prior=(50.0, 5.0)), r


@pytest.mark.parametrize("kind", ["diag0", "full0"])
def test_an_injected_traceless_error_is_recovered_with_the_positions_free(kind):
    E = np.diag([0.003, -0.002, -0.001])
    lik, r = _case(E)
    f = gp.fit_common_gyro(lik, r + 5e-4, kind)
    want = np.diag(E)[:2] if kind == "diag0" else np.delete(E.reshape(-1), 8)
    z = (np.asarray(f["g"]) - want) / np.asarray(f["g_std"])
    assert np.abs(z).max() < 4, z
    assert max(f["g_std"]) < 5e-4  # resolved: the error is > 4 std from zero on the scaled axes
    assert f["gain_nats"] > 10


def test_no_error_is_found_where_none_was_put():
    lik, r = _case(np.zeros((3, 3)), seed=1)
    f = gp.fit_common_gyro(lik, r, "full0")
    z = np.asarray(f["g"]) / np.asarray(f["g_std"])
    assert np.abs(z).max() < 4, z
    assert f["gain_nats"] < 20  # ~ chi²_8 / 2


def test_params_invert_the_matrix():
    g = torch.arange(1.0, 10.0, dtype=torch.float64) * 1e-3
    for kind, n in gp.KINDS.items():
        G = gp.g_matrix(g[:n], kind)
        np.testing.assert_allclose(gp.params_of(G, kind), g[:n].numpy())
        if kind.endswith("0"):
            assert abs(float(torch.trace(G))) < 1e-15


def test_a_common_scale_is_an_array_scale_unless_the_geometry_is_known():
    lik, r = _case(0.003 * np.eye(3), seed=2)
    fixed = gp.fit_common_gyro(lik, r, "scalar", free_positions=False)
    assert abs(fixed["g"][0] - 0.003) < 4 * fixed["g_std"][0] and fixed["g_std"][0] < 3e-4
    free = gp.fit_common_gyro(lik, r, "scalar")
    # ω̇ free per sample: ((1+c)ω)×((1+c)ω×r) = ω×(ω×(1+c)²r); only the priors and log|M(θ)| are left
    assert free["g_std"][0] > 10 * fixed["g_std"][0]


def test_the_error_is_injected_into_every_gyro_in_the_array_frame():
    import experiments.clockgen as cg

    rec, _ = cg.draw_case("clock", 3, duration=2.0, noise=False)
    # general mounting rotations: the board's own (half turns) are their own inverses and would hide a transpose
    rng = np.random.default_rng(0)
    q = rng.normal(size=(rec.K, 4))
    # the generator's first seconds are a rest (zero rates): any rates exercise the map
    rec = dataclasses.replace(rec, nominal_orientation=q / np.linalg.norm(q, axis=1, keepdims=True),
                              gyro=rng.normal(size=rec.gyro.shape))
    E = np.array([[0.003, 0.001, 0.0], [0.0, 0.0, -0.002], [0.0005, 0.0, -0.001]])
    new = gp.inject_gyro_error(rec, E)
    a0, a1 = rec.gyro_tensor("array"), new.gyro_tensor("array")
    assert float(a0.abs().max()) > 1.0
    np.testing.assert_allclose(a1.numpy(), (a0 @ torch.as_tensor(np.eye(3) + E).T).numpy(), atol=1e-12)

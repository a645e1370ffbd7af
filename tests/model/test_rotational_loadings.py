"""The age-loaded unresolved angular jerk (``unresolved_cov.rotational_loadings``) against the
rigid-body cross product written independently with numpy."""
import numpy as np
import pytest
import torch

from accel_bayes.model.unresolved_cov import loadings, rotational_loadings


def test_rotational_loading_is_the_age_weighted_cross_product():
    rng = np.random.default_rng(3)
    T, K = 5, 4
    d = rng.normal(0, 1e-3, (T, K))
    r = rng.normal(0, 0.05, (K, 3))
    w = rng.normal(0, 1e4, (T, 3))  # angular jerk, rad/s³
    U = rotational_loadings(torch.tensor(d), torch.tensor(r))
    got = torch.einsum("tnr,tr->tn", U, torch.tensor(w)).numpy().reshape(T, K, 3)
    rc = r - r.mean(0)
    want = d[:, :, None] * np.cross(rc[None, :, :], w[:, None, :])
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-12)


def test_origin_shift_stays_in_the_jerk_span():
    # shifting every position by o changes nothing (positions are taken about their centroid); the
    # uncentred term d_k (r_k + o) × w differs from ours by d_k o × w, a common vector loaded by d
    rng = np.random.default_rng(4)
    d = torch.tensor(rng.normal(0, 1e-3, (6, 3)))
    r = torch.tensor(rng.normal(0, 0.05, (3, 3)))
    o = torch.tensor([0.3, -0.2, 0.1], dtype=torch.float64)
    torch.testing.assert_close(rotational_loadings(d, r + o), rotational_loadings(d, r))
    w = torch.tensor(rng.normal(0, 1.0, 3))
    uncentred = d[:, :, None] * torch.cross((r + o)[None].expand(6, 3, 3), w.expand(6, 3, 3), dim=-1)
    ours = (rotational_loadings(d, r) @ w).reshape(6, 3, 3)
    common = (loadings(d) @ torch.cross(o + r.mean(0), w, dim=0)).reshape(6, 3, 3)
    torch.testing.assert_close(uncentred, ours + common)


def test_rotational_loading_rejects_bad_positions():
    with pytest.raises(ValueError, match="r must be"):
        rotational_loadings(torch.zeros(2, 3, dtype=torch.float64), torch.zeros(4, 3, dtype=torch.float64))

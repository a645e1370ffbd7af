"""The rig model's analytic Jacobians against central finite differences (issue #28 item 1)."""
import numpy as np
import torch

from accel_bayes.inference.rig.model import (BiasGrid, bucket_samples, measurement_jacobian, measurement_residual,
                                             process_jacobian, process_residual, process_matrices, walk_residual)
from accel_bayes.physics.geometry import boxplus, quat_normalize


def _small_rig(seed=0, K=3):
    rng = np.random.default_rng(seed)
    samples = []
    for k, rate in zip(range(K), (100.0, 160.0, 250.0)):
        ds = np.arange(0.0, 0.2, 1.0 / rate) + rng.uniform(0, 1e-3)
        n = len(ds)
        samples.append({"ds": ds, "yg": rng.normal(size=(n, 3)), "ya": rng.normal(size=(n, 3)),
                        "wg": np.full(n, 1.0 / 0.01), "wa": np.full(n, 1.0 / 0.05)})
    h, lo = 0.01, -0.02
    n_knots = int(np.ceil(0.26 / h)) + 1
    o = np.r_[0.0, rng.uniform(-3e-3, 3e-3, K - 1)]
    d = np.r_[0.0, rng.uniform(-1e-4, 1e-4, K - 1)]
    # bias grids coarser than the motion's and of their own spacing per sensor kind
    grids = (BiasGrid(lo, 0.26 / 2, 3), BiasGrid(lo, 0.26 / 3, 4))
    data = bucket_samples(samples, o, d, lo, h, n_knots, grids)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    g = {"q": quat_normalize(t(rng.normal(size=(K - 1, 4)))), "r": t(rng.normal(0, 0.1, (K - 1, 3))),
         "o": t(o[1:]), "d": t(d[1:]), "bg": t(rng.normal(0, 0.01, (K - 1, 3, 3))),
         "ba": t(rng.normal(0, 0.1, (K - 1, 4, 3)))}
    x = t(rng.normal(size=(n_knots, 12)) * np.r_[[2.0] * 3, [20.0] * 3, [5.0] * 3, [50.0] * 3])
    R0 = torch.linalg.qr(t(rng.normal(size=(3, 3))))[0]
    R0 = R0 * torch.sign(torch.det(R0))
    return g, x, data, R0


def test_measurement_jacobian_matches_finite_differences():
    g, x, data, R0 = _small_rig()
    jac, A, B = measurement_jacobian(g, x[:-1], x[1:], data, R0)
    f = lambda gg, xx: measurement_residual(gg, xx[:-1], xx[1:], data, R0)  # noqa: E731
    eps = 1e-6
    for name in ("q", "r", "o", "d", "bg", "ba"):
        v = g[name]
        n_t = v.shape[0] * 3 if name in ("q", "r") else v.numel()
        for c in range(n_t):
            delta = torch.zeros(n_t, dtype=torch.float64)
            delta[c] = eps
            def moved(s):
                gg = dict(g)
                if name == "q":
                    gg["q"] = boxplus(v, (s * delta).reshape(-1, 3))
                else:
                    gg[name] = v + (s * delta).reshape(v.shape)
                return f(gg, x)
            fd = (moved(1) - moved(-1)) / (2 * eps)
            assert torch.allclose(jac[name][..., c], fd, rtol=1e-5, atol=1e-4 * (1 + fd.abs().max())), (name, c)
    # locals (the motion): x_j enters interval j through A and interval j−1 through B
    for c in range(x.shape[1]):
        for jj in (3, 10):
            dx = torch.zeros_like(x)
            dx[jj, c] = eps
            fd = (f(g, x + dx) - f(g, x - dx)) / (2 * eps)
            assert torch.allclose(A[jj, :, c], fd[jj], rtol=1e-5, atol=1e-4 * (1 + fd.abs().max())), ("A", c)
            assert torch.allclose(B[jj - 1, :, c], fd[jj - 1], rtol=1e-5, atol=1e-4 * (1 + fd.abs().max())), ("B", c)


def test_process_prior_is_whitened_white_jerk():
    """The prior increments have unit covariance under the white-noise-on-jerk model they claim."""
    h, qc = 0.005, 3.0
    AB = process_matrices(h, qc, qc)
    rng = np.random.default_rng(1)
    n = 20000
    # exact discretisation of the integrated white noise: x_{j+1} = Φ x_j + w, Cov(w) = Q
    Q = qc * np.array([[h ** 3 / 3, h ** 2 / 2], [h ** 2 / 2, h]])
    L = np.linalg.cholesky(Q)
    xp = rng.normal(size=(n, 12))
    xn = np.empty_like(xp)
    for off in (0, 6):
        w = rng.normal(size=(n, 2, 3))
        wq = np.einsum("ab,nbc->nac", L, w)
        xn[:, off:off + 3] = xp[:, off:off + 3] + h * xp[:, off + 3:off + 6] + wq[:, 0]
        xn[:, off + 3:off + 6] = xp[:, off + 3:off + 6] + wq[:, 1]
    e = process_residual(torch.as_tensor(xp), torch.as_tensor(xn), AB).numpy()
    C = np.cov(e.T)
    assert np.allclose(C, np.eye(12), atol=0.05)
    jd, A, B = process_jacobian(torch.as_tensor(xp[:3]), AB)
    assert jd == {} and torch.equal(A[0], AB[0]) and torch.equal(B[0], AB[1])


def test_bias_walk_prior_is_whitened_random_walk():
    """The bias knots' increments are whitened by the walk density over the bias spacing H: unit
    variance under a random walk of that density, each IMU by its own figure."""
    grid, walk = BiasGrid(0.0, 2.5, 5), np.array([2e-5, 5e-5])   # two non-reference IMUs
    rng = np.random.default_rng(2)
    n = 20000
    steps = rng.normal(size=(n, 2, grid.n - 1, 3)) * (walk * np.sqrt(grid.H))[None, :, None, None]
    b = np.concatenate((rng.normal(size=(n, 2, 1, 3)), steps), 2).cumsum(2)
    fn, J = walk_residual(grid, walk)
    e = np.stack([fn(torch.as_tensor(bi)).numpy() for bi in b[:2000]])
    assert np.allclose(np.cov(e.T), np.eye(e.shape[1]), atol=0.12)
    assert torch.allclose(J @ torch.as_tensor(b[0]).reshape(-1), fn(torch.as_tensor(b[0])))

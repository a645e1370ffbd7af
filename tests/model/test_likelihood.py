"""Tests of the Rao-Blackwellized likelihood (accel_bayes.model.likelihood, DESIGN §4).

Every reference here is computed independently of the estimator's code path: dense Gaussians
with a finite prior scale β ([C21] eq. 18–19), a dense projector built with torch.linalg.lstsq
from models.specific_force, tensor-product Gauss–Hermite quadrature, and numpy covariances.
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.draw_tuning import choose_num_draws
from accel_bayes.model.gyro_posterior import GyroPosterior, gyro_posterior
from accel_bayes.prep.prepared import prepare_recording
from accel_bayes.model.likelihood import RaoBlackwellLikelihood, positions_from_theta, theta_from_positions
from accel_bayes.physics.models import G_matrix, H_matrix, imu_outputs, specific_force, u_of_omega
from accel_bayes.data.recording import Recording

DT = torch.float64
DEG = math.pi / 180

# A small, well-spread 4-triad array (m); row 0 is the reference.
POS4 = torch.tensor([[0.0, 0.0, 0.0], [0.10, 0.01, 0.0], [0.02, 0.09, 0.01], [0.01, -0.02, 0.08]], dtype=DT)


def _gen(seed):
    return torch.Generator().manual_seed(seed)


def _simulate(pos, T, sigma_a, sigma_g, G, seed, w_std=4.0, wd_std=3.0, s_std=3.0):
    """Array-frame data: acc (T, A, 3), gyro (T, G, 3), true ω (T, 3)."""
    g = _gen(seed)
    w = w_std * torch.randn(T, 3, generator=g, dtype=DT)
    wd = wd_std * torch.randn(T, 3, generator=g, dtype=DT)
    s = s_std * torch.randn(T, 3, generator=g, dtype=DT)
    acc = specific_force(pos, w, wd, s) + sigma_a * torch.randn(T, pos.shape[0], 3, generator=g, dtype=DT)
    gyro = w.unsqueeze(-2) + sigma_g * torch.randn(T, G, 3, generator=g, dtype=DT)
    return acc, gyro, w


def _brute_loglik_given_omega(pos, y, omega, sigma_a):
    """log p(y | ω, θ) (β → ∞, same constant convention) from the kinematics and a dense
    weighted least-squares projector: −½ min_φ ‖y − f(ω, φ)‖²_Λ − ½ log|HᵀΛH|.

    pos (A, 3); y (A, 3); omega (..., 3).  H's columns are the specific forces of unit ω̇ and
    unit s (models.specific_force), not models.H_matrix.
    """
    r = pos - pos[0]
    A = r.shape[0]
    eye = torch.eye(3, dtype=DT)
    zero = torch.zeros(3, dtype=DT)
    cols = [specific_force(r, zero, eye[j], zero).reshape(3 * A) for j in range(3)]
    cols += [specific_force(r, zero, zero, eye[j]).reshape(3 * A) for j in range(3)]
    H = torch.stack(cols, -1)  # (3A, 6)
    w = 1.0 / sigma_a
    Hw = H * w
    zeros = torch.zeros_like(omega)
    h = specific_force(r, omega, zeros, zeros).reshape(*omega.shape[:-1], 3 * A)
    bw = ((y.reshape(3 * A) - h) * w).unsqueeze(-1)  # (..., 3A, 1)
    sol = torch.linalg.lstsq(Hw.expand(*bw.shape[:-2], 3 * A, 6), bw).solution
    res = (bw - Hw @ sol).squeeze(-1)
    logdet = torch.linalg.slogdet(Hw.T @ Hw)[1]
    return -0.5 * res.pow(2).sum(-1) - 0.5 * logdet


def _gauss_hermite_log_integral(pos, y, mean, cov, sigma_a, n):
    """log ∫ p(y | ω, θ) N(ω; mean, cov) dω by an n³-point tensor Gauss–Hermite rule in the
    whitened coordinates ω = mean + chol(cov) x, x ~ N(0, I)."""
    x, wts = np.polynomial.hermite_e.hermegauss(n)
    logw = np.log(wts / math.sqrt(2 * math.pi))
    X = torch.tensor(np.stack(np.meshgrid(x, x, x, indexing="ij"), -1).reshape(-1, 3), dtype=DT)
    LW = torch.tensor((logw[:, None, None] + logw[None, :, None] + logw[None, None, :]).reshape(-1), dtype=DT)
    L = torch.linalg.cholesky(cov)
    om = mean + X @ L.T
    return torch.logsumexp(LW + _brute_loglik_given_omega(pos, y, om, sigma_a), 0)


def _dense_log_phat(lik, pos, z):
    """[C21] eq. 26 (with the −½ power) the straightforward way: dense S, dense quadratic forms."""
    r = pos - pos[lik.reference]
    H, G = H_matrix(r), G_matrix(r)
    Lam = torch.diag(lik.lam)
    M = H.T @ Lam @ H
    S = Lam - Lam @ H @ torch.linalg.inv(M) @ H.T @ Lam
    om = lik.omega.mean[:, None, :] + (lik.omega_chol[:, None] @ z.unsqueeze(-1)).squeeze(-1)
    res = lik.y[:, None, :] - u_of_omega(om) @ G.T
    q = torch.einsum("tni,ij,tnj->tn", res, S, res)
    N = z.shape[-2]
    return (torch.logsumexp(-0.5 * q, -1) - math.log(N)).sum() - 0.5 * lik.T * torch.linalg.slogdet(M)[1]


@pytest.fixture(scope="module")
def small():
    """A 5-triad random problem: T = 12, 3 gyros, calibrated posterior."""
    g = _gen(11)
    pos = 0.05 * torch.randn(5, 3, generator=g, dtype=DT)
    pos[0] = 0
    acc, gyro, w = _simulate(pos, 12, 0.05, 0.02, 3, seed=12)
    om = gyro_posterior(gyro, torch.full((3,), 0.02, dtype=DT), "calibrated")
    return pos, RaoBlackwellLikelihood(acc, om, torch.full((5,), 0.05, dtype=DT), num_draws=64), w


# ---------------------------------------------------------------- 1. β → ∞ limit: −½ log|M|

def test_log_lik_given_omega_matches_beta_limit_not_eq25():
    """Differences between two θ of the exact log N(y; G u(ω), Q + β H Hᵀ) ([C21] eq. 18–19,
    f = 0, F = I) converge, as β grows, to ours (power −½ of |M|) and not to eq. 25 (power −1)."""
    T, sigma = 3, 0.1
    acc, gyro, w = _simulate(POS4, T, sigma, 0.01, 2, seed=1, w_std=3.0, wd_std=1.0, s_std=1.0)
    om = gyro_posterior(gyro, torch.full((2,), 0.01, dtype=DT), "calibrated")
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma, dtype=DT), num_draws=1)
    th1 = POS4
    th2 = POS4 * 1.6 + 0.01 * torch.randn(4, 3, generator=_gen(2), dtype=DT)  # |M| very different

    def exact(pos, beta):
        """Plain dense: slogdet and solve of M_β = Q + β H Hᵀ (loses accuracy for β ≳ 1e7)."""
        r = pos - pos[0]
        H = H_matrix(r)
        Mb = sigma**2 * torch.eye(12, dtype=DT) + beta * H @ H.T
        tot = 0.0
        for t in range(T):
            dy = acc[t].reshape(12) - G_matrix(r) @ u_of_omega(w[t])
            tot = tot - 0.5 * dy @ torch.linalg.solve(Mb, dy) - 0.5 * torch.linalg.slogdet(2 * math.pi * Mb)[1]
        return float(tot)

    def exact_scaled(pos, beta):
        """The same Gaussian in the orthonormal basis [U, U⊥] of range(H) (full QR of H): with
        Q = σ²I, M_β = blockdiag(σ²I₆ + β R Rᵀ, σ² I) exactly, and each block is well conditioned."""
        r = pos - pos[0]
        H = H_matrix(r)
        Qf, Rf = torch.linalg.qr(H, mode="complete")
        R6 = Rf[:6]
        Bk = sigma**2 * torch.eye(6, dtype=DT) + beta * R6 @ R6.T
        tot = 0.0
        for t in range(T):
            dy = Qf.T @ (acc[t].reshape(12) - G_matrix(r) @ u_of_omega(w[t]))
            quad = dy[:6] @ torch.linalg.solve(Bk, dy[:6]) + dy[6:].pow(2).sum() / sigma**2
            logdet = torch.linalg.slogdet(Bk)[1] + 6 * math.log(sigma**2)
            tot = tot - 0.5 * quad - 0.5 * (12 * math.log(2 * math.pi) + logdet)
        return float(tot)

    ours = float(lik.log_lik_given_omega(th1, w) - lik.log_lik_given_omega(th2, w))
    paper = float(lik.log_lik_paper_eq25(th1, w) - lik.log_lik_paper_eq25(th2, w))
    err = {b: abs(exact(th1, b) - exact(th2, b) - ours) for b in (1e2, 1e4, 1e6)}
    errs = {b: abs(exact_scaled(th1, b) - exact_scaled(th2, b) - ours) for b in (1e2, 1e4, 1e6, 1e8, 1e10)}
    # plain dense form: the error falls like 1/β
    assert err[1e2] > 1e-3
    assert 30 < err[1e2] / err[1e4] < 300 and 30 < err[1e4] / err[1e6] < 300, err
    # Richardson extrapolation of the plain form to β = ∞ lands on ours
    d4, d6 = exact(th1, 1e4) - exact(th2, 1e4), exact(th1, 1e6) - exact(th2, 1e6)
    assert abs((1e6 * d6 - 1e4 * d4) / (1e6 - 1e4) - ours) < 1e-6
    # well-conditioned form: agrees with the plain one, keeps falling like 1/β down to ~1e-10
    assert abs(errs[1e4] - err[1e4]) < 1e-6
    assert errs[1e10] < 1e-8 and errs[1e8] < 1e-6, errs
    # ... and the printed eq. 25 is off by (T/2)(log|M1| − log|M2|), far more than that
    assert abs(paper - ours) > 1.0
    d_exact = exact_scaled(th1, 1e10) - exact_scaled(th2, 1e10)
    assert abs(d_exact - paper) > 1.0


def test_eq25_differs_by_half_T_logdet(small):
    pos, lik, w = small
    p = pos + 0.01
    logdet = lik.projection(p)["logdetM"]
    diff = lik.log_lik_paper_eq25(p, w) - lik.log_lik_given_omega(p, w)
    assert torch.allclose(diff, -0.5 * lik.T * logdet, rtol=0, atol=1e-9)


def test_log_lik_given_omega_matches_bruteforce_projector(small):
    pos, lik, w = small
    p = pos + 0.003 * torch.randn(5, 3, generator=_gen(3), dtype=DT)
    om = w + 0.05 * torch.randn(w.shape, generator=_gen(4), dtype=DT)
    ref = sum(_brute_loglik_given_omega(p, lik.acc[t], om[t], 0.05) for t in range(lik.T))
    assert abs(float(lik.log_lik_given_omega(p, om) - ref)) < 1e-8
    # batched: (2, A, 3) positions × (2, T, 3) ω
    P = torch.stack((p, pos))
    O = torch.stack((om, w))
    got = lik.log_lik_given_omega(P, O)
    assert torch.allclose(got, torch.stack([lik.log_lik_given_omega(P[i], O[i]) for i in range(2)]), atol=1e-10)


def test_log_lik_given_omega_is_differentiable(small):
    pos, lik, w = small
    p = (pos + 0.002).clone().requires_grad_(True)
    val = lik.log_lik_given_omega(p, w)
    (grad,) = torch.autograd.grad(val, p)
    # central finite differences on two coordinates
    for k, j in ((1, 0), (3, 2)):
        e = torch.zeros_like(pos)
        e[k, j] = 1e-6
        fd = (lik.log_lik_given_omega(p.detach() + e, w) - lik.log_lik_given_omega(p.detach() - e, w)) / 2e-6
        assert abs(float(grad[k, j] - fd)) < 1e-4 * (1 + abs(float(fd)))


# ---------------------------------------------------------------- 2. against quadrature

def test_log_phat_matches_gauss_hermite_quadrature():
    """One sample, 2 gyros at σ_g = 8 °/s (ω posterior std 5.7 °/s): the integrand varies by a
    factor of several over the posterior.  N = 2·10⁵ draws vs a 40³-point Gauss–Hermite rule."""
    sigma_a, sigma_g = 0.05, 8 * DEG
    acc, gyro, w = _simulate(POS4, 1, sigma_a, sigma_g, 2, seed=5, w_std=5.0)
    om = gyro_posterior(gyro, torch.full((2,), sigma_g, dtype=DT), "calibrated")
    N = 200_000
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma_a, dtype=DT), num_draws=N)
    th = POS4 + 0.002 * torch.randn(4, 3, generator=_gen(6), dtype=DT)
    z = lik.sample_z(generator=_gen(7))
    est = float(lik.log_phat(th, z=z))
    # MC standard error of log p̂ from the same draws, integrand evaluated independently
    omn = om.mean[0] + z[0, :20_000] @ torch.linalg.cholesky(om.cov[0]).T  # 20000 draws suffice for the sd
    lw = _brute_loglik_given_omega(th, acc[0], omn, sigma_a)
    wts = torch.exp(lw - lw.max())
    rel_sd = float(wts.std() / wts.mean())
    assert rel_sd > 0.5, "integrand too flat for a meaningful test"
    se = rel_sd / math.sqrt(N)
    q40 = float(_gauss_hermite_log_integral(th, acc[0], om.mean[0], om.cov[0], sigma_a, 40))
    q30 = float(_gauss_hermite_log_integral(th, acc[0], om.mean[0], om.cov[0], sigma_a, 30))
    quad_err = abs(q30 - q40)  # a bound on the 40-point error (the rule converges fast here)
    assert quad_err < 1e-6
    assert abs(est - q40) < 4 * se + quad_err, (est, q40, se)
    # the check is sharp: a 3 mm change of one position moves the value by many tolerances
    th2 = th.clone()
    th2[1, 0] += 0.003
    est2 = float(lik.log_phat(th2, z=z))
    assert abs(est2 - est) > 10 * (4 * se + quad_err)


# ---------------------------------------------------------------- 3. unbiased in p

def test_phat_is_unbiased_in_p_not_in_log_p():
    """E[p̂/p] = 1 ([C21] §III-A: what PmMH needs), while E[log p̂] < log p (Jensen).

    T = 4 samples, N = 4 draws, R = 20000 independent replicates; σ_g = 2 °/s (2 gyros), so
    Var[p̂/p] ≈ 1.2: large enough to matter, small enough for the replicate mean to be
    reliable.  p from a 20³-point Gauss–Hermite rule per sample (accurate to 1e-11 here).
    Tolerance: 4 standard errors of the replicate mean."""
    sigma_a, sigma_g = 0.05, 2 * DEG
    T, N, R = 4, 4, 20_000
    acc, gyro, w = _simulate(POS4, T, sigma_a, sigma_g, 2, seed=8, w_std=5.0)
    om = gyro_posterior(gyro, torch.full((2,), sigma_g, dtype=DT), "calibrated")
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma_a, dtype=DT), num_draws=N)
    th = POS4
    logp = sum(float(_gauss_hermite_log_integral(th, acc[t], om.mean[t], om.cov[t], sigma_a, 20)) for t in range(T))
    vals = lik.log_phat(th.expand(R, 4, 3), generator=_gen(9), independent_draws=True)
    ratio = torch.exp(vals - logp)
    mean, se = float(ratio.mean()), float(ratio.std() / math.sqrt(R))
    assert float(ratio.var()) > 0.5, "estimator variance too small for a meaningful test"
    assert abs(mean - 1.0) < 4 * se, (mean, se)
    # log p̂ itself is biased low (≈ −Var/2 per sample): a test on E[log p̂] would reject
    log_se = float(vals.std() / math.sqrt(R))
    assert float(vals.mean()) - logp < -20 * log_se


# ---------------------------------------------------------------- 4. implementation checks

def test_log_phat_equals_dense_form(small):
    pos, lik, _ = small
    p = pos + 0.004 * torch.randn(5, 3, generator=_gen(21), dtype=DT)
    z = lik.sample_z(generator=_gen(22))
    ours = float(lik.log_phat(p, z=z))
    dense = float(_dense_log_phat(lik, p, z))
    assert abs(ours - dense) < 1e-9, (ours, dense)


def test_log_phat_dense_form_sample_cov_and_singular_quadratic():
    """A = 4 (rank S = 6 < 7: the singular-factor path) and the wide eq. 30 posterior."""
    acc, gyro, w = _simulate(POS4, 6, 0.05, 0.05, 3, seed=23)
    om = gyro_posterior(gyro, torch.full((3,), 0.05, dtype=DT), "sample_cov")
    lik = RaoBlackwellLikelihood(acc, om, torch.tensor([0.05, 0.04, 0.06, 0.05], dtype=DT), num_draws=50)
    z = lik.sample_z(generator=_gen(24))
    assert abs(float(lik.log_phat(POS4, z=z)) - float(_dense_log_phat(lik, POS4, z))) < 1e-9


def test_projection_quantities_reproduce_quadratic_form(small):
    pos, lik, w = small
    pr = lik.projection(pos)
    r = pos - pos[0]
    H, G = H_matrix(r), G_matrix(r)
    Lam = torch.diag(lik.lam)
    M = H.T @ Lam @ H
    S = Lam - Lam @ H @ torch.linalg.solve(M, H.T @ Lam)
    assert torch.allclose(pr["M"], M, atol=1e-9)
    assert torch.allclose(pr["L"] @ pr["L"].T, M, atol=1e-9)
    assert abs(float(pr["logdetM"] - torch.logdet(M))) < 1e-10
    assert torch.allclose(pr["C"], G.T @ S @ G, rtol=1e-9, atol=1e-7)
    assert torch.allclose(pr["c"], torch.einsum("ti,ij,tj->t", lik.y, S, lik.y), rtol=1e-8)
    assert torch.allclose(pr["b"], lik.y @ S @ G, rtol=1e-8, atol=1e-6)
    u = u_of_omega(w)
    q = pr["c"] - 2 * (pr["b"] * u).sum(-1) + torch.einsum("ti,ij,tj->t", u, pr["C"], u)
    res = lik.y - u @ G.T
    assert torch.allclose(q, torch.einsum("ti,ij,tj->t", res, S, res), rtol=1e-7, atol=1e-7)


def test_batched_positions_equal_loop_and_seeds(small):
    pos, lik, _ = small
    P = pos + 0.003 * torch.randn(2, 3, 5, 3, generator=_gen(31), dtype=DT)
    z = lik.sample_z(generator=_gen(32))
    got = lik.log_phat(P, z=z)
    assert got.shape == (2, 3)
    loop = torch.stack([torch.stack([lik.log_phat(P[i, j], z=z) for j in range(3)]) for i in range(2)])
    assert torch.allclose(got, loop, rtol=0, atol=1e-10)
    # generator path ≡ sample_z with the same seed ≡ a contiguous (T, N, 3) copy of z
    a = lik.log_phat(pos, generator=_gen(5))
    b = lik.log_phat(pos, generator=_gen(5))
    c = lik.log_phat(pos, z=lik.sample_z(generator=_gen(5)).contiguous())
    d = lik.log_phat(pos, generator=_gen(6))
    assert float(a) == float(b)
    assert abs(float(a - c)) < 1e-12
    assert float(a) != float(d)
    # independent draws: a per-element z, equal to the loop over its slices
    ind = lik.log_phat(P, generator=_gen(7), independent_draws=True)
    zs = lik.sample_z((2, 3), generator=_gen(7))
    loop = torch.stack([torch.stack([lik.log_phat(P[i, j], z=zs[i, j]) for j in range(3)]) for i in range(2)])
    assert torch.allclose(ind, loop, rtol=0, atol=1e-10)
    assert len(set(float(v) for v in (ind - got).flatten())) == 6  # not one shared z
    # num_draws override and N from z
    assert lik.log_phat(pos, generator=_gen(8), num_draws=7).shape == ()
    with pytest.raises(UserError):
        lik.log_phat(pos[:4])


def test_reference_row_and_theta_roundtrip(small):
    pos, lik, _ = small
    z = lik.sample_z(generator=_gen(41))
    base = float(lik.log_phat(pos, z=z))
    shift = torch.tensor([0.3, -0.2, 0.1], dtype=DT)
    assert abs(float(lik.log_phat(pos + shift, z=z)) - base) < 1e-9  # only relative positions matter
    lik2 = RaoBlackwellLikelihood(lik.acc, lik.omega, lik.acc_noise_std, 64, reference=2)
    assert abs(float(lik2.log_phat(pos, z=z)) - base) < 1e-9  # translation invariance of the model
    theta = theta_from_positions(pos + shift, 2)
    assert theta.shape == (4, 3)
    back = positions_from_theta(theta, 2, 5)
    assert torch.allclose(back, pos - pos[2], atol=1e-15)
    assert torch.equal(back[2], torch.zeros(3, dtype=DT))
    th = torch.randn(7, 4, 3, generator=_gen(42), dtype=DT)
    for ref in (0, 4):
        assert torch.equal(theta_from_positions(positions_from_theta(th, ref, 5), ref), th)
    with pytest.raises(UserError):
        positions_from_theta(th, 0, 4)


def test_gyro_posterior_methods():
    g = _gen(51)
    T, G = 6, 4
    gyro = torch.randn(T, G, 3, generator=g, dtype=DT)
    std = torch.full((G,), 0.01, dtype=DT)
    sc = gyro_posterior(gyro, std, "sample_cov")
    for t in range(T):
        ref = np.cov(gyro[t].numpy().T, ddof=1)  # 1/(G−1), not divided by G
        assert np.allclose(sc.cov[t].numpy(), ref, atol=1e-12)
        assert np.allclose(sc.mean[t].numpy(), gyro[t].numpy().mean(0))
    scm = gyro_posterior(gyro, std, "sample_cov_mean")
    assert torch.allclose(scm.cov, sc.cov / G, atol=1e-12)
    cal = gyro_posterior(gyro, std, "calibrated")
    assert torch.allclose(cal.cov, (0.01**2 / G) * torch.eye(3, dtype=DT).expand(T, 3, 3))
    # unequal noise: inverse-variance weighting
    std2 = torch.tensor([0.01, 0.02, 0.02, 0.04], dtype=DT)
    cal2 = gyro_posterior(gyro, std2, "calibrated")
    wts = std2.pow(-2)
    assert torch.allclose(cal2.mean, (gyro * wts[:, None]).sum(1) / wts.sum())
    assert torch.allclose(cal2.cov[0], torch.eye(3, dtype=DT) / wts.sum())
    # floor: with 2 gyros the sample covariance has rank 1; eigenvalues are raised to σ²/G
    two = gyro[:, :2]
    fl = gyro_posterior(two, std[:2], "sample_cov")
    ev = torch.linalg.eigvalsh(fl.cov)
    assert torch.allclose(ev[:, :2], torch.full((T, 2), 0.01**2 / 2, dtype=DT), rtol=1e-9)
    raw = torch.linalg.eigvalsh(torch.stack([torch.tensor(np.cov(two[t].numpy().T, ddof=1)) for t in range(T)]))
    assert torch.allclose(ev[:, 2], raw[:, 2], rtol=1e-9)
    with pytest.raises(UserError):
        gyro_posterior(gyro[:, :1], std[:1], "sample_cov")
    with pytest.raises(UserError):
        gyro_posterior(gyro, std, "nope")


def test_from_recording_rotates_selects_and_labels():
    """Rotated IMUs (MIMU bottom side), one IMU without gyro, one without accelerometer."""
    from accel_bayes.physics.arrays import mimu4444_8

    arr = mimu4444_8()
    K, T = arr.K, 40
    g = _gen(61)
    w = 3.0 * torch.randn(T, 3, generator=g, dtype=DT)
    w[:10] *= 0.01  # ten samples nearly without rotation
    wd = torch.randn(T, 3, generator=g, dtype=DT)
    s = torch.randn(T, 3, generator=g, dtype=DT)
    acc, gyro = imu_outputs(arr.positions, arr.orientations, w, wd, s)
    acc, gyro = acc.numpy().copy(), gyro.numpy().copy()
    gyro[:, 3] = np.nan
    acc[:, 5] = np.nan
    clipped = np.zeros((T, K), dtype=bool)
    clipped[12, 1] = True
    rec = Recording(time=np.arange(T) / 100.0, acc=acc, gyro=gyro, nominal_position=arr.positions.numpy(),
                    nominal_orientation=arr.orientations.numpy(), acc_noise_std=np.full(K, 0.04),
                    gyro_noise_std=np.full(K, 0.001), acc_clipped=clipped, reference_imu=2)
    lik = RaoBlackwellLikelihood.from_recording(rec, num_draws=16, gyro_method="calibrated")
    assert lik.imu_labels == (0, 1, 2, 3, 4, 6, 7) and lik.gyro_labels == (0, 1, 2, 4, 5, 6, 7)
    assert lik.reference == 2 and lik.T == T and lik.A == 7
    assert torch.equal(lik.nominal_positions, arr.positions[[0, 1, 2, 3, 4, 6, 7]])
    keep = list(lik.imu_labels)
    f = specific_force(arr.positions[keep], w, wd, s)
    assert torch.allclose(lik.acc, f, atol=1e-12)  # back in the array frame
    assert torch.allclose(lik.omega.mean, w, atol=1e-12)
    lr = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, select="rotation", drop_clipped=True),
                                               num_draws=16)
    expect = [t for t in range(T) if float(w[t].norm()) >= 0.5 and t != 12]
    assert lr.sample_index.tolist() == expect and lr.T == len(expect)
    lm = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, select=np.arange(T) % 2 == 0), num_draws=16)
    assert lm.T == T // 2
    with pytest.raises(UserError):
        prepare_recording(rec, select="everything")


# ---------------------------------------------------------------- 5. choosing N

def test_choose_num_draws_hits_the_target_range():
    sigma_a, sigma_g = 0.05, 3 * DEG
    acc, gyro, w = _simulate(POS4, 30, sigma_a, sigma_g, 2, seed=71, w_std=5.0)
    om = gyro_posterior(gyro, torch.full((2,), sigma_g, dtype=DT), "calibrated")
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma_a, dtype=DT), num_draws=1)
    N, table = choose_num_draws(lik, POS4, target=1.0, accept=(0.1, 3.0), repeats=40, start=2, seed=1)
    assert table[0]["num_draws"] == 2 and table[0]["var"] > 3.0  # start is too small: it had to grow N
    row = [r for r in table if r["num_draws"] == N]
    assert len(row) == 1 and 0.1 <= row[0]["var"] <= 3.0, table
    # an independent re-measurement agrees (R = 60: relative sd of a variance estimate ≈ 0.18)
    g = _gen(72)
    vals = torch.stack([lik.log_phat(POS4, generator=g, num_draws=N) for _ in range(60)])
    assert 0.05 <= float(vals.var()) <= 5.0


def test_log_phat_gradient_matches_finite_differences(small):
    pos, lik, _ = small
    z = lik.sample_z(generator=_gen(81))
    p = (pos + 0.001).clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(lik.log_phat(p, z=z), p)
    e = torch.zeros_like(pos)
    e[2, 1] = 1e-6
    fd = (lik.log_phat(pos + 0.001 + e, z=z) - lik.log_phat(pos + 0.001 - e, z=z)) / 2e-6
    assert abs(float(grad[2, 1] - fd)) < 1e-4 * (1 + abs(float(fd)))


def test_far_off_theta_does_not_underflow(small):
    """At a θ that fits nothing every exp(−½q) underflows; the value stays finite and equals
    the dense form."""
    pos, lik, _ = small
    z = lik.sample_z(generator=_gen(82))
    bad = pos * 3.0 + 0.05
    v = lik.log_phat(bad, z=z)
    assert torch.isfinite(v)
    assert abs(float(v - _dense_log_phat(lik, bad, z))) < 1e-7 * abs(float(v))


def test_user_gyro_posterior_correlated_cov_and_validation(small):
    pos, lik, w = small
    g = _gen(91)
    X = 0.05 * torch.randn(lik.T, 3, 3, generator=g, dtype=DT)
    cov = X @ X.transpose(-1, -2) + 1e-4 * torch.eye(3, dtype=DT)
    post = GyroPosterior(w + 0.01, cov, "custom")
    lk = RaoBlackwellLikelihood(lik.acc, post, lik.acc_noise_std, num_draws=40)
    z = lk.sample_z(generator=_gen(92))
    assert abs(float(lk.log_phat(pos, z=z) - _dense_log_phat(lk, pos, z))) < 1e-9
    sub = post.select(torch.arange(lik.T) < 5)
    assert sub.T == 5 and torch.equal(sub.cov, cov[:5])
    with pytest.raises(UserError):
        RaoBlackwellLikelihood(lik.acc, GyroPosterior(w, -cov, "bad"), lik.acc_noise_std, 4)
    with pytest.raises(UserError):
        RaoBlackwellLikelihood(lik.acc, post, torch.zeros(5, dtype=DT), 4)
    with pytest.raises(UserError):
        RaoBlackwellLikelihood(lik.acc, post.select(torch.arange(3)), lik.acc_noise_std, 4)
    # collinear triads: M(θ) singular → a clear error, not NaN
    line = torch.zeros(5, 3, dtype=DT)
    line[:, 0] = torch.arange(5, dtype=DT) * 0.01
    with pytest.raises(UserError):
        lk.log_phat(line, z=z)


# ---------------------------------------------------------------- 5. proper Gaussian prior on φ

def test_phi_prior_matches_dense_gaussian_marginal():
    """With φ_t ~ N(0, F), log p(y_t | ω_t, θ) = log N(y_t; G u(ω_t), Q + H F Hᵀ) exactly
    (dense covariance, torch.distributions, built from models.H_matrix only): differences
    between two θ agree with ours to round-off; the flat default differs from it."""
    T, sigma = 4, 0.1
    acc, gyro, w = _simulate(POS4, T, sigma, 0.01, 2, seed=31)
    om = gyro_posterior(gyro, torch.full((2,), 0.01, dtype=DT), "calibrated")
    sd = (3.0, 2.0)  # σ_ω̇ rad/s², σ_s m/s²
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma, dtype=DT), num_draws=1, phi_prior=sd)
    flat = RaoBlackwellLikelihood(acc, om, torch.full((4,), sigma, dtype=DT), num_draws=1)
    F = torch.diag(torch.tensor([sd[0]] * 3 + [sd[1]] * 3, dtype=DT) ** 2)
    th = [POS4, POS4 * 1.3 + 0.005 * torch.randn(4, 3, generator=_gen(32), dtype=DT)]

    def dense(pos):
        r = pos - pos[0]
        H, G = H_matrix(r), G_matrix(r)
        cov = sigma**2 * torch.eye(12, dtype=DT) + H @ F @ H.T
        mean = u_of_omega(w) @ G.T
        return float(torch.distributions.MultivariateNormal(mean, cov).log_prob(acc.reshape(T, 12)).sum())

    d_exact = dense(th[0]) - dense(th[1])
    d_ours = float(lik.log_lik_given_omega(th[0], w) - lik.log_lik_given_omega(th[1], w))
    d_flat = float(flat.log_lik_given_omega(th[0], w) - flat.log_lik_given_omega(th[1], w))
    assert abs(d_ours - d_exact) < 1e-8 * max(1.0, abs(d_exact)), (d_ours, d_exact)
    assert abs(d_flat - d_exact) > 0.1  # the prior on φ matters at this scale

    # The O(1)-per-draw path (projection → c, b, C) gives the same quadratic form under the prior.
    pr = lik.projection(th[1])
    u = u_of_omega(w)
    q = pr["c"] - 2 * (pr["b"] * u).sum(-1) + torch.einsum("ti,ij,tj->t", u, pr["C"], u)
    quad, logdet = lik._quad_given_omega(th[1], w)
    assert abs(float(q.sum() - quad)) < 1e-7 * float(quad)
    assert abs(float(pr["logdetM"] - logdet)) < 1e-10


def test_phi_prior_log_phat_equals_dense_form():
    """log p̂ under the prior equals eq. 26 done densely with S_F = Λ − ΛH(M + F⁻¹)⁻¹HᵀΛ."""
    acc, gyro, w = _simulate(POS4, 6, 0.05, 0.05, 3, seed=33)
    om = gyro_posterior(gyro, torch.full((3,), 0.05, dtype=DT), "calibrated")
    sd = torch.tensor([2.0, 3.0, 4.0, 1.0, 2.0, 5.0], dtype=DT)
    lik = RaoBlackwellLikelihood(acc, om, torch.full((4,), 0.05, dtype=DT), num_draws=40, phi_prior=sd)
    z = lik.sample_z(generator=_gen(34))
    r = POS4 - POS4[0]
    H, G = H_matrix(r), G_matrix(r)
    Lam = torch.diag(lik.lam)
    MF = H.T @ Lam @ H + torch.diag(sd ** -2)
    S = Lam - Lam @ H @ torch.linalg.inv(MF) @ H.T @ Lam
    omg = lik.omega.mean[:, None, :] + (lik.omega_chol[:, None] @ z.unsqueeze(-1)).squeeze(-1)
    res = lik.y[:, None, :] - u_of_omega(omg) @ G.T
    q = torch.einsum("tni,ij,tnj->tn", res, S, res)
    dense = (torch.logsumexp(-0.5 * q, -1) - math.log(40)).sum() - 0.5 * lik.T * torch.linalg.slogdet(MF)[1]
    assert abs(float(lik.log_phat(POS4, z=z)) - float(dense)) < 1e-9
    with pytest.raises(UserError, match="phi_prior"):
        RaoBlackwellLikelihood(acc, om, 0.05, num_draws=4, phi_prior=(1.0, 0.0))


# ---------------------------------------------------------------- 5. the hot-path variants (issue #15)

def _dense_phi_prior_log_phat(lik, pos, z, prec):
    """Eq. 26 densely with S_F = Λ − ΛH(M + F⁻¹)⁻¹HᵀΛ (``prec`` = F⁻¹, None for the flat prior)."""
    r = pos - pos[lik.reference]
    H, G = H_matrix(r), G_matrix(r)
    Lam = torch.diag(lik.lam)
    MF = H.T @ Lam @ H + (0 if prec is None else prec)
    S = Lam - Lam @ H @ torch.linalg.inv(MF) @ H.T @ Lam
    om = lik.omega.mean[:, None, :] + (lik.omega_chol[:, None] @ z.unsqueeze(-1)).squeeze(-1)
    res = lik.y[:, None, :] - u_of_omega(om) @ G.T
    q = torch.einsum("tni,ij,tnj->tn", res, S, res)
    N = z.shape[-2]
    return (torch.logsumexp(-0.5 * q, -1) - math.log(N)).sum() - 0.5 * lik.T * torch.linalg.slogdet(MF)[1]


@pytest.mark.parametrize("N", [1, 3, 32, 33])
def test_every_draw_path_equals_dense_form(small, N):
    """N ≤ 32: q from d = u(ω) − u(ω̄) and the shared factor (direct path, N = 1 without exp/log);
    N = 33: the 6×10 maps from the shared factor.  Shared z over a batch of θ and a z per θ."""
    pos, lik, _ = small
    P = pos + 0.004 * torch.randn(3, 5, 3, generator=_gen(101 + N), dtype=DT)
    z = lik.sample_z(num_draws=N, generator=_gen(102 + N))
    got = lik.log_phat(P, z=z)
    for i in range(3):
        dense = float(_dense_log_phat(lik, P[i], z))
        assert abs(float(got[i]) - dense) < 1e-9 * abs(dense), (N, i, float(got[i]), dense)
    zb = lik.sample_z((3,), num_draws=N, generator=_gen(103 + N))
    got = lik.log_phat(P, z=zb)
    for i in range(3):
        dense = float(_dense_log_phat(lik, P[i], zb[i]))
        assert abs(float(got[i]) - dense) < 1e-9 * abs(dense), (N, i, float(got[i]), dense)


def test_direct_path_far_off_theta_and_chunks(small, monkeypatch):
    """Direct path: a θ far from the data (every exp(−½q) underflows without the floor) and
    several t-chunks give the dense value."""
    import accel_bayes.model.draw_sums as draw_sums

    pos, lik, _ = small
    z = lik.sample_z(num_draws=5, generator=_gen(111))
    bad = pos * 3.0 + 0.05
    want = float(_dense_log_phat(lik, bad, z))
    assert abs(float(lik.log_phat(bad, z=z)) - want) < 1e-9 * abs(want)
    monkeypatch.setattr(draw_sums, "_DIRECT_CHUNK_ELEMS", 5 * 16 * 2)  # 2 samples per chunk
    assert abs(float(lik.log_phat(bad, z=z)) - want) < 1e-9 * abs(want)
    P = pos + 0.002 * torch.randn(2, 5, 3, generator=_gen(112), dtype=DT)
    got = lik.log_phat(P, z=z)
    for i in range(2):
        dense = float(_dense_log_phat(lik, P[i], z))
        assert abs(float(got[i]) - dense) < 1e-9 * abs(dense)


def test_direct_path_gradient_matches_finite_differences(small):
    pos, lik, _ = small
    for N in (1, 4):
        z = lik.sample_z(num_draws=N, generator=_gen(121 + N))
        p = (pos + 0.001).clone().requires_grad_(True)
        (grad,) = torch.autograd.grad(lik.log_phat(p, z=z), p)
        e = torch.zeros_like(pos)
        e[3, 2] = 1e-6
        fd = (lik.log_phat(pos + 0.001 + e, z=z) - lik.log_phat(pos + 0.001 - e, z=z)) / 2e-6
        assert abs(float(grad[3, 2] - fd)) < 1e-4 * (1 + abs(float(fd)))


def test_singular_factor_path_with_few_draws():
    """A = 4 (rank S = 6 < 7): the shared factor declines and the 7×7/eigendecomposition path
    is taken also for N within the direct range."""
    acc, gyro, w = _simulate(POS4, 6, 0.05, 0.05, 3, seed=23)
    om = gyro_posterior(gyro, torch.full((3,), 0.05, dtype=DT), "sample_cov")
    lik = RaoBlackwellLikelihood(acc, om, torch.tensor([0.05, 0.04, 0.06, 0.05], dtype=DT), num_draws=3)
    z = lik.sample_z(generator=_gen(131))
    want = float(_dense_log_phat(lik, POS4, z))
    assert abs(float(lik.log_phat(POS4, z=z)) - want) < 1e-9 * max(1.0, abs(want))


@pytest.mark.parametrize("N", [1, 6, 40])
def test_phi_prior_every_draw_path_equals_dense_form(N):
    g = _gen(141)
    pos = 0.05 * torch.randn(6, 3, generator=g, dtype=DT)
    pos[0] = 0
    acc, gyro, w = _simulate(pos, 9, 0.05, 0.03, 3, seed=142)
    om = gyro_posterior(gyro, torch.full((3,), 0.03, dtype=DT), "calibrated")
    B = torch.randn(6, 6, generator=g, dtype=DT)
    Fcov = B @ B.T + 0.5 * torch.eye(6, dtype=DT)  # a full 6×6 F
    lik = RaoBlackwellLikelihood(acc, om, torch.full((6,), 0.05, dtype=DT), num_draws=N, phi_prior=Fcov)
    z = lik.sample_z(generator=_gen(143))
    p = pos + 0.003 * torch.randn(6, 3, generator=g, dtype=DT)
    want = float(_dense_phi_prior_log_phat(lik, p, z, torch.linalg.inv(Fcov)))
    assert abs(float(lik.log_phat(p, z=z)) - want) < 1e-9 * abs(want), N


@pytest.mark.parametrize("prior", [None, (3.0, 2.0)])
def test_hot_projection_equals_projection(small, prior):
    pos, lik0, _ = small
    lik = RaoBlackwellLikelihood(lik0.acc, lik0.omega, lik0.acc_noise_std, num_draws=1, phi_prior=prior)
    P = pos + 0.003 * torch.randn(2, 5, 3, generator=_gen(151), dtype=DT)
    hot = lik._projection_hot(lik._positions(P))
    ref = lik.projection(P, center=lik.omega.mean)
    for k in ("c", "b", "C", "logdetM"):
        assert torch.allclose(hot[k], ref[k], rtol=1e-10, atol=1e-10 * float(ref[k].abs().max())), k

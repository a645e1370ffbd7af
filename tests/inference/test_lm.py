"""Tests of the structured LM solver (accel_bayes.inference.lm / linear / damping / robust).

Independent references: finite differences (Jacobians), dense torch.linalg.solve (Schur solves),
scipy.optimize.least_squares on the stacked problem (LM optimum), closed forms (robust losses).
"""
import math

import numpy as np
import pytest
import scipy.optimize
import torch

from accel_bayes.physics.geometry import boxplus, quat_exp, quat_mul, quat_to_matrix, random_quaternion
from accel_bayes.inference.lm.damping import MarquardtDamping, NielsenDamping
from accel_bayes.inference.lm import (ChainResidual, ExtraCost, GlobalResidual, LevenbergMarquardt, Problem,
                                      SampleResidual, Variable, solve)
from accel_bayes.inference.lm.linear import (NotPositiveDefinite, SchurComplementSolver, block_tridiagonal_factor,
                                          block_tridiagonal_solve, dense_from_blocks)
from accel_bayes.inference.lm.robust import CauchyLoss, HuberLoss

DT = torch.float64


# ---------------------------------------------------------------- a small nonlinear problem
# Errors-in-variables exponential fit: y_t = a·exp(b·u_t) + c·v_t, with the regressors (u_t, v_t)
# observed with noise; globals p = (a, b, c), locals x_t = (u_t, v_t).
SY, SZ = 0.05, 0.02


def _eiv_data(T=40, seed=0, noise=True):
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, T)
    v = rng.uniform(-1, 1, T)
    a, b, c = 1.5, -0.8, 0.7
    y = a * np.exp(b * u) + c * v + (SY * rng.standard_normal(T) if noise else 0)
    zu = u + (SZ * rng.standard_normal(T) if noise else 0)
    zv = v + (SZ * rng.standard_normal(T) if noise else 0)
    data = torch.tensor(np.stack([y, zu, zv], 1), dtype=DT)
    return data, np.array([a, b, c]), np.stack([u, v], 1)


def eiv_fn(g, x, data):
    p = g["p"]
    u, v = x[..., 0], x[..., 1]
    y, zu, zv = data[..., 0], data[..., 1], data[..., 2]
    pred = p[0] * torch.exp(p[1] * u) + p[2] * v
    return torch.stack(((y - pred) / SY, (zu - u) / SZ, (zv - v) / SZ), -1)


def eiv_jac(g, x, data):
    p = g["p"]
    u, v = x[..., 0], x[..., 1]
    e = torch.exp(p[1] * u)
    T = x.shape[0]
    Jp = torch.zeros(T, 3, 3, dtype=DT)
    Jp[:, 0, 0] = -e / SY
    Jp[:, 0, 1] = -p[0] * u * e / SY
    Jp[:, 0, 2] = -v / SY
    Jx = torch.zeros(T, 3, 2, dtype=DT)
    Jx[:, 0, 0] = -p[0] * p[1] * e / SY
    Jx[:, 0, 1] = -p[2] / SY
    Jx[:, 1, 0] = -1 / SZ
    Jx[:, 2, 1] = -1 / SZ
    return {"p": Jp}, Jx


def _eiv_problem(data, p0, x0, jac=None, **kw):
    return Problem({"p": Variable(torch.tensor(p0, dtype=DT))}, torch.tensor(x0, dtype=DT),
                   [SampleResidual(eiv_fn, data=data, jac=jac)], **kw)


def _scipy_eiv(data, p0, x0):
    T = data.shape[0]
    d = data.numpy()

    def fun(z):
        p, x = z[:3], z[3:].reshape(T, 2)
        pred = p[0] * np.exp(p[1] * x[:, 0]) + p[2] * x[:, 1]
        return np.concatenate([(d[:, 0] - pred) / SY, (d[:, 1] - x[:, 0]) / SZ, (d[:, 2] - x[:, 1]) / SZ])

    z0 = np.concatenate([p0, x0.reshape(-1)])
    ref = scipy.optimize.least_squares(fun, z0, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15, max_nfev=20000)
    # SciPy >= 1.17's MINPACK run stops on ftol about 1e-9 short of the optimum here (its Gauss-Newton
    # step there is still 1.2e-9), so finish with a few plain Gauss-Newton steps on central-difference
    # Jacobians: numpy only, independent of the solver under test.
    z, eye, h = ref.x.copy(), np.eye(ref.x.size), 1e-7
    for _ in range(5):
        J = np.stack([(fun(z + h * e) - fun(z - h * e)) / (2 * h) for e in eye], axis=1)
        step = np.linalg.solve(J.T @ J, -J.T @ fun(z))
        z = z + step
        if np.abs(step).max() < 1e-13:
            break
    ref.x, ref.cost = z, 0.5 * float(fun(z) @ fun(z))
    return ref


def _fd_jacobian(f, z0, eps=1e-6):
    cols = []
    for i in range(z0.numel()):
        e = torch.zeros_like(z0)
        e[i] = eps
        cols.append((f(z0 + e) - f(z0 - e)) / (2 * eps))
    return torch.stack(cols, -1)


def test_jacobians_analytic_autograd_and_finite_differences_agree():
    data, p, x = _eiv_data(T=7)
    prob = _eiv_problem(data, p + 0.1, x + 0.05)
    vals = prob.initial_values()
    xx = prob.x0
    r, Jg, Jx = prob.sample_jacobians(prob.sample_residuals[0], vals, xx)
    r2, Jg2, Jx2 = _eiv_problem(data, p + 0.1, x + 0.05, jac=eiv_jac).sample_jacobians(
        SampleResidual(eiv_fn, data=data, jac=eiv_jac), vals, xx)
    # finite differences of the full stacked residual w.r.t. (p, x)
    def full(z):
        return eiv_fn({"p": z[:3]}, z[3:].reshape(-1, 2), data).reshape(-1)
    z0 = torch.cat((vals["p"], xx.reshape(-1)))
    Jfd = _fd_jacobian(full, z0).reshape(7, 3, -1)
    Jg_fd = Jfd[..., :3]
    Jx_fd = torch.stack([Jfd[t, :, 3 + 2 * t:5 + 2 * t] for t in range(7)])
    for J, Jref in ((Jg, Jg_fd), (Jx, Jx_fd), (Jg2, Jg_fd), (Jx2, Jx_fd)):
        assert torch.allclose(J, Jref, rtol=1e-7, atol=1e-6)
    assert torch.allclose(Jg, Jg2, rtol=1e-12, atol=1e-10) and torch.allclose(Jx, Jx2, rtol=1e-12, atol=1e-10)
    # the block structure is real: x_s does not enter r_t for s ≠ t
    off = torch.stack([Jfd[t, :, 3 + 2 * ((t + 1) % 7):5 + 2 * ((t + 1) % 7)] for t in range(7)])
    assert float(off.abs().max()) < 1e-8


def test_chain_and_quaternion_jacobians_match_finite_differences():
    torch.manual_seed(1)
    T, d = 6, 2
    x = torch.randn(T, d, dtype=DT)
    q0 = random_quaternion(generator=torch.Generator().manual_seed(3))
    k = torch.randn(3, dtype=DT)

    def chain(g, xp, xn, data):
        # a nonlinear chain factor that also depends on the orientation
        R = quat_to_matrix(g["q"])
        a = torch.cat((xp, xn[..., :1]), -1)
        return (a @ R.T) * torch.sin(xn[..., 1:2]) + g["k"]

    prob = Problem({"q": Variable(q0, "quaternion"), "k": Variable(k)}, x, [ChainResidual(chain)])
    vals = prob.initial_values()
    r, Jg, A, B = prob.chain_jacobians(prob.chain_residuals[0], vals, x)

    def full(z):
        g = {"q": quat_mul(q0, quat_exp(z[:3])) if z[:3].abs().max() > 0 else q0, "k": k + z[3:6]}
        xx = x + z[6:].reshape(T, d)
        return chain(g, xx[:-1], xx[1:], None).reshape(-1)

    z0 = torch.zeros(6 + T * d, dtype=DT)
    Jfd = _fd_jacobian(full, z0).reshape(T - 1, 3, -1)
    assert torch.allclose(Jg, Jfd[..., :6], rtol=1e-7, atol=1e-7)
    A_fd = torch.stack([Jfd[t, :, 6 + d * t:6 + d * (t + 1)] for t in range(T - 1)])
    B_fd = torch.stack([Jfd[t, :, 6 + d * (t + 1):6 + d * (t + 2)] for t in range(T - 1)])
    assert torch.allclose(A, A_fd, rtol=1e-7, atol=1e-7) and torch.allclose(B, B_fd, rtol=1e-7, atol=1e-7)


# ---------------------------------------------------------------- linear solvers

def _random_arrow(T, n, d, tri, seed):
    g = torch.Generator().manual_seed(seed)
    m = d + 2
    Jg = torch.randn(T, m, n, generator=g, dtype=DT)
    Jx = torch.randn(T, m, d, generator=g, dtype=DT)
    U = torch.einsum("tmi,tmj->ij", Jg, Jg) + torch.eye(n, dtype=DT)
    W = torch.einsum("tmi,tmj->tij", Jg, Jx)
    V = torch.einsum("tmi,tmj->tij", Jx, Jx) + 0.1 * torch.eye(d, dtype=DT)
    V_off = None
    if tri:
        A = torch.randn(T - 1, d, d, generator=g, dtype=DT)
        B = torch.randn(T - 1, d, d, generator=g, dtype=DT)
        V = V.clone()
        V[:-1] += A.transpose(-1, -2) @ A
        V[1:] += B.transpose(-1, -2) @ B
        V_off = A.transpose(-1, -2) @ B
    b_g = torch.randn(n, generator=g, dtype=DT)
    b_x = torch.randn(T, d, generator=g, dtype=DT)
    return U, W, V, V_off, b_g, b_x


@pytest.mark.parametrize("tri,T", [(False, 9), (True, 9), (True, 16), (True, 2)])
def test_schur_solve_equals_dense_solve(tri, T):
    n, d = 5, 3
    U, W, V, V_off, b_g, b_x = _random_arrow(T, n, d, tri, seed=4 + tri + T)
    solver = SchurComplementSolver("tridiagonal") if tri else SchurComplementSolver("diagonal")
    dg, dx, S = solver.solve(U, W, V, b_g, b_x, V_off, return_reduced=True)
    A = dense_from_blocks(U, W, V, V_off)
    ref = torch.linalg.solve(A, torch.cat((b_g, b_x.reshape(-1))))
    got = torch.cat((dg, dx.reshape(-1)))
    assert float((got - ref).abs().max() / ref.abs().max()) < 1e-10
    # reduced matrix = inverse of the globals' block of A⁻¹
    Sinv_ref = torch.linalg.inv(A)[:n, :n]
    assert torch.allclose(torch.linalg.inv(S), Sinv_ref, rtol=1e-10, atol=1e-12)
    assert torch.allclose(solver.reduce(U, W, V, V_off), S, rtol=1e-10, atol=1e-10)


@pytest.mark.parametrize("T", [1, 2, 3, 7, 8, 13])
def test_block_tridiagonal_batched_and_not_pd(T):
    d = 4
    _, _, V, V_off, _, _ = _random_arrow(T, 2, d, True, seed=11 + T)
    Vb = torch.stack((V, 2 * V))
    Eb = torch.stack((V_off, 2 * V_off))
    B = torch.randn(2, T, d, 3, generator=torch.Generator().manual_seed(0), dtype=DT)
    X = block_tridiagonal_factor(Vb, Eb).solve(B)
    X2 = block_tridiagonal_solve(Vb, Eb, B)
    for i in range(2):
        A = dense_from_blocks(torch.zeros(0, 0, dtype=DT), torch.zeros(T, 0, d, dtype=DT), Vb[i], Eb[i])
        ref = torch.linalg.solve(A, B[i].reshape(T * d, 3))
        for XX in (X, X2):
            assert float((XX[i].reshape(T * d, 3) - ref).abs().max()) < 1e-10 * float(ref.abs().max())
    with pytest.raises(NotPositiveDefinite):
        block_tridiagonal_factor(-Vb, Eb)
    with pytest.raises(NotPositiveDefinite):
        block_tridiagonal_solve(-Vb, Eb, B)


# ---------------------------------------------------------------- LM on the EIV problem

def test_lm_matches_scipy_least_squares():
    data, p, x = _eiv_data(T=40, seed=2)
    p0 = np.array([1.0, -0.3, 0.3])
    x0 = data[:, 1:].numpy().copy()  # start the latents at their observations
    ref = _scipy_eiv(data, p0, x0)
    for jac in (None, eiv_jac):
        res = solve(_eiv_problem(data, p0, x0, jac=jac), max_iter=200, ftol=1e-15, xtol=1e-14, gtol=1e-12)
        assert res.converged, res.reason
        assert np.allclose(res.values["p"].numpy(), ref.x[:3], rtol=0, atol=1e-9)
        assert np.allclose(res.locals.numpy().reshape(-1), ref.x[3:], rtol=0, atol=1e-9)
        assert abs(res.cost - ref.cost) <= 1e-10 * ref.cost
    # log: costs never increase over accepted steps
    costs = [e["cost"] for e in res.log]
    assert all(c2 <= c1 + 1e-12 for c1, c2 in zip(costs, costs[1:]))


def test_local_hessian_hook_keeps_the_optimum():
    data, p, x = _eiv_data(T=40, seed=2)
    p0 = np.array([1.0, -0.3, 0.3])
    x0 = data[:, 1:].numpy().copy()
    ref = _scipy_eiv(data, p0, x0)

    def local_hess(g, xx, d, r):  # Σ_m r_m ∂²r_m/∂x²: only ∂²r_0/∂u² = −a b² e^{bu}/σ_y
        a, b = g["p"][0], g["p"][1]
        H = torch.zeros(xx.shape[0], 2, 2, dtype=DT)
        H[:, 0, 0] = r[:, 0] * (-a * b * b * torch.exp(b * xx[:, 0]) / SY)
        return H

    prob = Problem({"p": Variable(torch.tensor(p0, dtype=DT))}, torch.tensor(x0, dtype=DT),
                   [SampleResidual(eiv_fn, data=data, jac=eiv_jac, local_hessian=local_hess)])
    # the hook's term equals the exact local Hessian minus Gauss-Newton
    vals = prob.initial_values()
    ex = prob.exact_hessian(vals, prob.x0).V
    gn = prob.linearize(vals, prob.x0, step=False).V
    r = eiv_fn(vals, prob.x0, data)
    assert torch.allclose(gn + local_hess(vals, prob.x0, data, r), ex, rtol=1e-10, atol=1e-8)
    res = solve(prob, max_iter=200, ftol=1e-15, xtol=1e-14, gtol=1e-12)
    assert res.converged
    assert np.allclose(res.values["p"].numpy(), ref.x[:3], atol=1e-9)
    assert np.allclose(res.locals.numpy().reshape(-1), ref.x[3:], atol=1e-9)


def test_noise_free_problem_recovers_truth_and_both_damping_rules():
    data, p, x = _eiv_data(T=30, seed=5, noise=False)
    for damping in (NielsenDamping(), MarquardtDamping(), NielsenDamping(scaling="levenberg")):
        res = solve(_eiv_problem(data, p * 0.7, x + 0.1), damping=damping, max_iter=300)
        assert res.converged, (damping, res.reason)
        assert np.allclose(res.values["p"].numpy(), p, atol=1e-8)
        assert np.allclose(res.locals.numpy(), x, atol=1e-8)


def test_information_matches_dense_gauss_newton_and_scipy_covariance():
    data, p, x = _eiv_data(T=25, seed=3)
    res = solve(_eiv_problem(data, p, data[:, 1:].numpy()), max_iter=200, ftol=1e-15)
    S = res.information()
    # dense GN information from the scipy Jacobian at the same optimum, marginalised by inversion
    ref = _scipy_eiv(data, res.values["p"].numpy(), res.locals.numpy())
    H = ref.jac.T @ ref.jac
    cov_ref = np.linalg.inv(H)[:3, :3]
    assert np.allclose(np.linalg.inv(S.numpy()), cov_ref, rtol=1e-7)
    assert np.allclose(res.covariance().numpy(), cov_ref, rtol=1e-7)
    # the exact-Hessian variant differs only by the (small) second-order residual term
    Se = res.information("exact")
    assert float(torch.linalg.norm(Se - S) / torch.linalg.norm(S)) < 0.05


# ---------------------------------------------------------------- manifold, fixed, chain

def _rotation_problem(T=30, seed=0, fixed_k=False):
    g = torch.Generator().manual_seed(seed)
    q_true = random_quaternion(generator=g)
    v = torch.randn(T, 3, generator=g, dtype=DT)
    k_true = torch.tensor([0.3, -0.2, 0.1], dtype=DT)
    y = v @ quat_to_matrix(q_true).T + k_true
    data = torch.cat((y, v + 0.01 * torch.randn(T, 3, generator=g, dtype=DT)), -1)

    def fn(gl, x, d):
        return torch.cat(((d[..., :3] - x @ quat_to_matrix(gl["q"]).T - gl["k"]) / 0.01,
                          (d[..., 3:] - x) / 0.01), -1)

    q0 = boxplus(q_true, torch.tensor([0.5, -0.4, 0.3], dtype=DT))
    k0 = k_true.clone() if fixed_k else torch.zeros(3, dtype=DT)
    prob = Problem({"q": Variable(q0, "quaternion"), "k": Variable(k0, fixed=fixed_k)}, data[:, 3:].clone(),
                   [SampleResidual(fn, data=data)])
    return prob, q_true, k_true


def test_boxplus_keeps_quaternions_unit_over_many_iterations():
    prob, q_true, _ = _rotation_problem()
    norms = []
    res = LevenbergMarquardt(max_iter=150, ftol=0, xtol=0, gtol=0,
                             callback=lambda i, v, x, e: norms.append(float(v["q"].norm()))).solve(prob)
    assert len(norms) >= 20
    assert max(abs(nq - 1) for nq in norms) < 1e-12
    from accel_bayes.physics.geometry import rotation_angle
    assert float(rotation_angle(res.values["q"], q_true)) < 1e-2  # noise-limited (σ_v = 0.01, T = 30)


def test_fixed_variables_stay_fixed():
    prob, q_true, k_true = _rotation_problem(fixed_k=True)
    res = solve(prob, max_iter=100)
    assert torch.equal(res.values["k"], k_true)
    # partially fixed block: row mask on a (2, 3) block
    data, p, x = _eiv_data(T=20, seed=1)

    def fn(g, xx, d):
        gg = {"p": torch.stack((g["P"][0, 0], g["P"][1, 1], g["P"][1, 2]))}
        return eiv_fn(gg, xx, d)

    P0 = torch.tensor([[1.5, 9.0, 9.0], [0.0, -0.5, 0.5]], dtype=DT)
    prob = Problem({"P": Variable(P0, fixed=torch.tensor([True, False]))}, data[:, 1:].clone(),
                   [SampleResidual(fn, data=data)])
    res = solve(prob)
    assert torch.equal(res.values["P"][0], P0[0])
    assert prob.n_free == 3 and res.information().shape == (3, 3)


def test_chain_problem_matches_scipy():
    # smoothing with a nonlinear observation and an unknown global gain:
    # y_t = k·sin(x_t) + e,   x_{t+1} − x_t ~ N(0, s²)
    T = 30
    rng = np.random.default_rng(7)
    xs = np.cumsum(0.2 * rng.standard_normal((T, 2)), 0)
    k_true = np.array([1.3, 0.7])
    y = k_true * np.sin(xs) + 0.05 * rng.standard_normal((T, 2))
    z = xs + 0.1 * rng.standard_normal((T, 2))
    data = torch.tensor(np.concatenate([y, z], 1))

    def obs(g, x, d):
        return torch.cat(((d[..., :2] - g["k"] * torch.sin(x)) / 0.05, (d[..., 2:] - x) / 0.1), -1)

    def proc(g, xp, xn, d):
        return (xn - xp) / 0.2

    prob = Problem({"k": Variable(torch.ones(2, dtype=DT))}, torch.tensor(z), [SampleResidual(obs, data=data),
                                                                                 ChainResidual(proc)])
    assert prob.local_structure == "tridiagonal"
    res = solve(prob, max_iter=200, ftol=1e-15, xtol=1e-14)
    assert res.converged

    def fun(w):
        k, x = w[:2], w[2:].reshape(T, 2)
        return np.concatenate([((y - k * np.sin(x)) / 0.05).ravel(), ((z - x) / 0.1).ravel(),
                               (np.diff(x, axis=0) / 0.2).ravel()])

    ref = scipy.optimize.least_squares(fun, np.concatenate([[1, 1], z.ravel()]), method="lm",
                                       xtol=1e-15, ftol=1e-15, gtol=1e-15)
    assert np.allclose(res.values["k"].numpy(), ref.x[:2], atol=1e-9)
    assert np.allclose(res.locals.numpy().ravel(), ref.x[2:], atol=1e-8)
    # information: Schur with the tridiagonal locals equals the dense marginal
    cov_ref = np.linalg.inv(ref.jac.T @ ref.jac)[:2, :2]
    assert np.allclose(res.covariance().numpy(), cov_ref, rtol=1e-6)
    # exact Hessian with 3-colouring equals a dense autograd Hessian
    He = res.information("exact")

    def F(w):
        k, x = w[:2], w[2:].reshape(T, 2)
        g = {"k": k}
        return 0.5 * ((obs(g, x, data) ** 2).sum() + (proc(g, x[:-1], x[1:], None) ** 2).sum())

    w = torch.cat((res.values["k"], res.locals.reshape(-1)))
    Hd = torch.autograd.functional.hessian(F, w)
    Sd = Hd[:2, :2] - Hd[:2, 2:] @ torch.linalg.solve(Hd[2:, 2:], Hd[2:, :2])
    assert torch.allclose(He, Sd, rtol=1e-9)


# ---------------------------------------------------------------- robust losses, extra costs

def test_robust_losses_closed_forms():
    s = torch.tensor([0.0, 0.5, 4.0, 100.0], dtype=DT)
    rho, rho1 = HuberLoss(1.0).rho(s)
    assert torch.allclose(rho, torch.tensor([0.0, 0.5, 3.0, 19.0], dtype=DT))
    assert torch.allclose(rho1, torch.tensor([1.0, 1.0, 0.5, 0.1], dtype=DT))
    rho, rho1 = CauchyLoss(2.0).rho(s)
    assert torch.allclose(rho, 4 * torch.log1p(s / 4))
    # ρ' is the derivative of ρ
    ss = s.clone().requires_grad_(True)
    for loss in (HuberLoss(1.0), CauchyLoss(2.0)):
        r, r1 = loss.rho(ss)
        (gr,) = torch.autograd.grad(r.sum(), ss)
        assert torch.allclose(gr, r1)


def test_robust_loss_downweights_outlier():
    t = torch.linspace(0, 1, 30, dtype=DT)
    y = 1.0 + 2.0 * t
    y[10] += 5.0  # one gross outlier (100 σ)

    def fn(g, x, d):
        return ((d[1] - g["c"][0] - g["c"][1] * d[0]) / 0.05).unsqueeze(-1)

    est = {}
    for loss in (None, "huber", CauchyLoss()):
        prob = Problem({"c": Variable(torch.zeros(2, dtype=DT))}, None, [SampleResidual(fn, data=(t, y), loss=loss)])
        est[str(loss)[:6]] = solve(prob, max_iter=300).values["c"]
    truth = torch.tensor([1.0, 2.0], dtype=DT)
    err_ls = float((est["None"] - truth).abs().max())
    err_hu = float((est["huber"] - truth).abs().max())
    err_ca = float((est["Cauchy"] - truth).abs().max())
    assert err_ls > 0.1
    assert err_hu < 0.3 * err_ls
    assert err_ca < 1e-3 < err_hu  # redescending: the outlier keeps only ~ρ'(100²) ≈ 6e-4 of its pull


def test_extra_cost_term_and_global_residual():
    # minimise ½‖(p − m)/s‖² + log(1 + p0²) + p1⁴ : gradient zero at the optimum (checked by autograd)
    m = torch.tensor([2.0, 1.0], dtype=DT)
    prob = Problem({"p": Variable(torch.zeros(2, dtype=DT))}, None,
                   [GlobalResidual(lambda g: (g["p"] - m) / 0.7)],
                   ExtraCost(lambda g: torch.log1p(g["p"][0] ** 2) + g["p"][1] ** 4))
    res = solve(prob, max_iter=200, gtol=1e-12)
    assert res.converged
    p = res.values["p"].clone().requires_grad_(True)
    F = 0.5 * (((p - m) / 0.7) ** 2).sum() + torch.log1p(p[0] ** 2) + p[1] ** 4
    (g,) = torch.autograd.grad(F, p)
    assert float(g.abs().max()) < 1e-9
    Hd = torch.autograd.functional.hessian(
        lambda q: 0.5 * (((q - m) / 0.7) ** 2).sum() + torch.log1p(q[0] ** 2) + q[1] ** 4, res.values["p"])
    assert torch.allclose(res.information(), Hd, rtol=1e-10)
    assert torch.allclose(res.information("exact"), Hd, rtol=1e-10)


# ---------------------------------------------------------------- stopping rules

def test_stopping_reasons():
    data, p, x = _eiv_data(T=20, seed=9)
    mk = lambda: _eiv_problem(data, p * 0.5, data[:, 1:].numpy())  # noqa: E731
    r = solve(mk(), max_iter=2, ftol=0, xtol=0, gtol=0)
    assert (r.reason, r.converged, r.n_iter, len(r.log)) == ("max_iter", False, 2, 2)
    r = solve(mk(), gtol=1e30)
    assert (r.reason, r.converged, r.n_iter) == ("gtol", True, 0)
    r = solve(mk(), ftol=1e-2, xtol=0, gtol=0, max_iter=500)
    assert r.reason == "ftol" and r.converged and r.n_iter < 500
    r = solve(mk(), ftol=0, xtol=1e-6, gtol=0, max_iter=500)
    assert r.reason == "xtol" and r.converged
    assert set(r.log[0]) >= {"iteration", "cost", "step_norm", "lambda", "accepted", "rho"}
    with pytest.raises(ValueError):
        solve(mk(), max_iter=-1)


def test_progress_bar_and_determinism(capsys):
    data, p, x = _eiv_data(T=15, seed=4)
    r1 = solve(_eiv_problem(data, p * 0.5, data[:, 1:].numpy()), progress=True)
    r2 = solve(_eiv_problem(data, p * 0.5, data[:, 1:].numpy()))
    assert torch.equal(r1.values["p"], r2.values["p"]) and r1.log == r2.log


# ---------------------------------------------------------------- batched mode (many small problems)
def _exp_batch(B=24, S=25, seed=5):
    """B independent fits y = a·exp(b·u) + c (3 unknowns each, S points each, noisy)."""
    rng = np.random.default_rng(seed)
    u = rng.uniform(-1, 1, (B, S))
    # |b| ≥ 0.7: near b = 0, a·exp(b·u) + c ≈ (a + c) + a·b·u and the problem degenerates
    b = rng.choice([-1.0, 1.0], B) * rng.uniform(0.7, 1.5, B)
    truth = np.stack([rng.uniform(0.5, 2, B), b, rng.uniform(-1, 1, B)], 1)
    y = truth[:, :1] * np.exp(truth[:, 1:2] * u) + truth[:, 2:] + 0.05 * rng.standard_normal((B, S))
    return torch.tensor(u, dtype=DT), torch.tensor(y, dtype=DT), truth


def _exp_linearize(u, y):
    def lin(p, idx=None):
        uu, yy = (u, y) if idx is None else (u[idx], y[idx])
        e = torch.exp(p[..., 1:2] * uu)
        r = p[..., 0:1] * e + p[..., 2:3] - yy
        J = torch.stack((e, p[..., 0:1] * uu * e, torch.ones_like(e)), -1)
        return 0.5 * (r * r).sum(-1), -(J.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1), J.transpose(-1, -2) @ J
    return lin


def _scipy_polished(u, y, p0):
    """SciPy's MINPACK LM, then Gauss–Newton steps (numpy) to the optimum's round-off level."""
    f = lambda p: p[0] * np.exp(p[1] * u) + p[2] - y  # noqa: E731
    jac = lambda p: np.stack((np.exp(p[1] * u), p[0] * u * np.exp(p[1] * u), np.ones_like(u)), 1)  # noqa: E731
    p = scipy.optimize.least_squares(f, p0, jac=jac, method="lm", xtol=1e-15, ftol=1e-15, gtol=1e-15).x
    for _ in range(5):
        J = jac(p)
        p = p - np.linalg.solve(J.T @ J, J.T @ f(p))
    return p


def test_batched_lm_matches_scipy_on_every_problem():
    """Each of B small problems solved together equals SciPy's per-problem optimum; the subset
    mode (only running problems evaluated) and a (2, B/2) batch shape give the same answer."""
    from accel_bayes.inference.lm import BatchedLevenbergMarquardt, StoppingRule

    u, y, _ = _exp_batch()
    B = u.shape[0]
    p0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT).expand(B, 3)
    lm = BatchedLevenbergMarquardt(max_iter=200, ftol=1e-15, xtol=1e-14, gtol=1e-12)
    res = lm.solve(_exp_linearize(u, y), p0)
    assert bool(res.converged.all()), res.reasons()
    assert set(res.reasons()) <= set(StoppingRule.CONVERGED)
    # An LM that accepts steps on cost decreases resolves the optimum to about √ε of the
    # parameters' scale: within 1e-8 here (2.5e-9 observed; the ½‖r‖² ≈ 0.03 of these problems
    # carries ~1e-17 of round-off).  The gradient is tested directly as well.
    for i in range(B):
        ref = _scipy_polished(u[i].numpy(), y[i].numpy(), p0[i].numpy())
        assert np.allclose(res.x[i].numpy(), ref, rtol=0, atol=1e-8), (i, res.x[i], ref)
    assert float(res.b.abs().max()) < 1e-8
    sub = lm.solve(_exp_linearize(u, y), p0, subset=True)
    torch.testing.assert_close(sub.x, res.x, rtol=0, atol=1e-12)
    assert torch.equal(sub.reason, res.reason)
    shaped = lm.solve(_exp_linearize(u.reshape(2, B // 2, -1), y.reshape(2, B // 2, -1)), p0.reshape(2, B // 2, 3))
    torch.testing.assert_close(shaped.x.reshape(B, 3), res.x, rtol=0, atol=1e-12)
    # the returned Gauss–Newton matrix is the one at the solution
    _, _, H = _exp_linearize(u, y)(res.x)
    torch.testing.assert_close(res.H, H, rtol=1e-12, atol=0)


def test_batched_lm_per_problem_masks():
    """A problem that starts at its (noise-free) optimum stops at once with its value untouched,
    while the others run on; a problem cut off by max_iter is reported as not converged."""
    from accel_bayes.inference.lm import BatchedLevenbergMarquardt, StoppingRule

    u, y, truth = _exp_batch(B=6, seed=6)
    t = torch.tensor(truth, dtype=DT)
    y[0] = t[0, 0] * torch.exp(t[0, 1] * u[0]) + t[0, 2]  # noise-free: r = 0 at the truth
    p0 = torch.tensor([1.0, 0.0, 0.0], dtype=DT).repeat(6, 1)
    p0[0] = t[0]
    res = BatchedLevenbergMarquardt(max_iter=200, ftol=1e-15, xtol=1e-14, gtol=1e-12).solve(
        _exp_linearize(u, y), p0, subset=True)
    assert torch.equal(res.x[0], t[0]) and res.reasons()[0] == "gtol"
    assert bool(res.converged.all()) and res.n_iter > 3
    short = BatchedLevenbergMarquardt(max_iter=2, ftol=1e-15, xtol=1e-14, gtol=1e-12).solve(_exp_linearize(u, y), p0)
    assert short.reasons()[0] == "gtol" and short.reasons()[1:] == ["max_iter"] * 5
    assert short.converged.tolist() == [True] + [False] * 5
    assert StoppingRule.REASONS[int(short.reason[1])] == "max_iter"


@pytest.mark.parametrize("cls", [NielsenDamping, MarquardtDamping])
def test_damping_rules_agree_between_scalar_and_batched_mode(cls):
    """The same rule drives the structured solver (floats) and the batched one (one λ per
    problem): feeding each problem's (ρ, accepted) sequence to a scalar strategy gives the same λ."""
    rng = np.random.default_rng(0)
    B, steps = 5, 12
    diag = torch.tensor(rng.uniform(0.1, 10, (B, 4)), dtype=DT)
    rho = rng.uniform(-0.5, 1.2, (steps, B))
    acc = rho > 0
    rho[~acc & (rng.uniform(size=(steps, B)) < 0.3)] = -math.inf
    active = rng.uniform(size=(steps, B)) < 0.8
    bat = cls()
    bat.init(diag, bat.scale(diag), batched=True)
    for s in range(steps):
        bat.update(torch.tensor(rho[s], dtype=DT), torch.tensor(acc[s]), torch.tensor(active[s]))
    for i in range(B):
        one = cls()
        one.init(diag[i], one.scale(diag[i]))
        for s in range(steps):
            if active[s, i]:
                one.update(float(rho[s, i]), bool(acc[s, i]))
        assert math.isclose(one.lam, float(bat.lam[i]), rel_tol=1e-15), (i, one.lam, float(bat.lam[i]))


def test_structured_lm_needs_only_the_problem_protocol():
    """LevenbergMarquardt.solve uses a problem only through linearize / cost / retract (plus
    n_free and local_structure): a minimal object forwarding those gives the same result."""
    data, _, _ = _eiv_data(T=30, seed=4)
    prob = _eiv_problem(data, np.array([1.0, -0.3, 0.3]), data[:, 1:].numpy().copy(), jac=eiv_jac)

    class Minimal:
        local_structure = prob.local_structure
        n_free = prob.n_free
        x0 = None

        def linearize(self, values, x, *, step=True):
            return prob.linearize(values, x, step=step)

        def cost(self, values, x):
            return prob.cost(values, x)

        def retract(self, values, delta):
            return prob.retract(values, delta)

    ref = LevenbergMarquardt(max_iter=100).solve(prob)
    res = LevenbergMarquardt(max_iter=100).solve(Minimal(), prob.initial_values(), prob.x0)
    assert torch.equal(res.values["p"], ref.values["p"]) and torch.equal(res.locals, ref.locals)
    assert res.reason == ref.reason and res.n_iter == ref.n_iter

"""The accelerometers' linear errors integrated out of the likelihood (accel_bayes.model.acc_block_marginal).

References independent of the module's algebra: every sample's dense covariance (noise and the
per-sample loading built with numpy cross products, as tests/model/test_angular_jerk.py does), its
flat-φ projected precision and GLS fit by numpy, the blocks' design with numpy's kron, and the
Gaussian integral over the blocks in closed form (and by a brute-force 2-D grid for ``evidence``).  The tolerance τ
recovered from data simulated with it (type-II ML, fixed seeds, stated tolerance).
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.model.acc_block_marginal import (block_prior_mean, build_block_marginal, evidence,
                                                  with_block_marginal, _prior_var)
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood
from accel_bayes.physics.effects import AccLinear
from accel_bayes.physics.models import specific_force
from tests.model.test_likelihood_percov import POS5, SIG, _case, _kinematic_H

DT = torch.float64
LEVER = POS5 + torch.tensor([0.003, -0.002, 0.001], dtype=DT)
F6 = np.diag([30.0, 20.0, 25.0, 9.0, 16.0, 4.0])


def _sample_covs(acc, age, jerk_std, ang_std, lever):
    """Σ_t (T, 3A, 3A): σ²I + the jerk's and the angular jerk's age-loaded columns (numpy)."""
    T, A, _ = acc.shape
    lev = lever.numpy() - lever.numpy().mean(0)
    out = []
    for t in range(T):
        d = (age[t] - age[t].mean()).numpy()
        S = SIG ** 2 * np.eye(3 * A) + float(jerk_std[t]) ** 2 * np.kron(np.outer(d, d), np.eye(3))
        for j in range(3):
            col = (d[:, None] * np.cross(np.eye(3)[j], lev)).reshape(-1)
            S += float(ang_std[t]) ** 2 * np.outer(col, col)
        out.append(S)
    return np.array(out)


def _X(f, scale):
    """(T, 3A, 12A): rows of sample t, triad k = [I₃ ⊗ f_ktᵀ, I₃/s_t] on triad k's 12 columns (numpy)."""
    T, A, _ = f.shape
    X = np.zeros((T, 3 * A, 12 * A))
    for t in range(T):
        for k in range(A):
            X[t, 3 * k:3 * k + 3, 12 * k:12 * k + 9] = np.kron(np.eye(3), f[t, k][None, :])
            X[t, 3 * k:3 * k + 3, 12 * k + 9:12 * k + 12] = np.eye(3) / scale[t]
    return X


def _reference(pos, ref_pos, acc, omega_mean, Sig, mu, pvar, scale, F=None, exact_weights=False):
    """Δ at ``pos`` by dense algebra (numpy): per sample the flat-φ projected precision
    P_t = Σ_t⁻¹ − Σ_t⁻¹H(HᵀΣ_t⁻¹H)⁻¹HᵀΣ_t⁻¹ and the GLS fit f̂_t = m_t + Hφ̂_t at ``ref_pos`` (the
    regressor), then the Gaussian integral over β ~ N(μ, diag(pvar)) of Π_t exp(−½‖r_t − X_tβ‖²_{P_t})
    against β = 0 (K, P_t and X held at ``ref_pos``).  ``exact_weights``: the P_t of K and g at ``pos``
    instead (H of the positions themselves), X still at ``ref_pos`` — the exact integral whose value,
    gradient and Hessian at θ₀ the module keeps."""
    T, A, _ = acc.shape
    H = _kinematic_H(ref_pos)
    Hp = _kinematic_H(pos) if exact_weights else H
    zero = torch.zeros(T, 3, dtype=DT)
    m0 = specific_force(ref_pos, omega_mean, zero, zero).reshape(T, -1).numpy()
    m = specific_force(pos, omega_mean, zero, zero).reshape(T, -1).numpy()
    y = acc.reshape(T, -1).numpy()
    f = np.zeros_like(y)
    Ps, Pg = [], []
    for t in range(T):
        Si = np.linalg.inv(Sig[t])
        Mt = H.T @ Si @ H + (0 if F is None else np.linalg.inv(F))  # the MAP of φ under N(0, F)
        f[t] = m0[t] + H @ np.linalg.solve(Mt, H.T @ Si @ (y[t] - m0[t]))
        # the precision of y_t with φ integrated out: (Σ_t + HFHᵀ)⁻¹, or the flat limit's projection
        Ps.append(np.linalg.inv(Sig[t] + H @ F @ H.T) if F is not None
                  else Si - Si @ H @ np.linalg.solve(Mt, H.T @ Si))
        Mp = Hp.T @ Si @ Hp
        Pg.append(np.linalg.inv(Sig[t] + Hp @ F @ Hp.T) if F is not None
                  else Si - Si @ Hp @ np.linalg.solve(Mp, Hp.T @ Si))
    X = _X(f.reshape(T, A, 3), scale)
    r = y - m
    K = sum(X[t].T @ Pg[t] @ X[t] for t in range(T))
    g = sum(X[t].T @ Pg[t] @ r[t] for t in range(T))
    md, Pd = _deviations(mu, pvar)
    # the Gaussian integral over β ~ N(md, Pd) (singular: the sums over the triads are fixed at zero)
    a = g - K @ md
    Q = np.eye(len(mu)) + Pd @ K
    return float(g @ md - 0.5 * md @ K @ md + 0.5 * a @ np.linalg.solve(Q, Pd @ a) - 0.5 * np.linalg.slogdet(Q)[1])


def _deviations(mu, pvar):
    """(mean, covariance) of the iid prior N(μ, diag(pvar)) on the A×12 blocks conditioned on every entry
    summing to zero over the triads (the module's deviations), by the Gaussian conditioning formula."""
    A = len(mu) // 12
    C = np.kron(np.ones((1, A)), np.eye(12))  # the sums over the triads, entry by entry
    P = np.diag(pvar)
    Kc = P @ C.T @ np.linalg.inv(C @ P @ C.T)
    return mu - Kc @ (C @ mu), P - Kc @ C @ P


def _lik(T=8, seed=4, F=F6):
    acc, omega, age, s = _case(T=T, seed=seed)
    ang = torch.linspace(2e4, 9e4, T, dtype=DT)
    lik = PerSampleCovLikelihood(acc, omega, SIG, 3, age, s, phi_prior=None if F is None else torch.as_tensor(F),
                                 angjerk_std=ang, lever=LEVER)
    return lik, acc, omega, age, s, ang


@pytest.mark.parametrize("scaled", [False, True])
def test_delta_equals_the_dense_gaussian_at_the_reference_geometry(scaled):
    lik, acc, omega, age, s, ang = _lik()
    A, T = 5, lik.T
    scale = np.linspace(0.8, 1.6, T) if scaled else np.ones(T)
    g = torch.Generator().manual_seed(2)
    mu = 0.01 * torch.randn(12 * A, generator=g, dtype=DT)
    tau = (0.02, 0.3)
    term = build_block_marginal(lik, POS5, mu, tau=tau, sample_scale=scale)
    Sig = _sample_covs(acc, age, s, ang, LEVER)
    want = _reference(POS5, POS5, acc, omega.mean, Sig, mu.numpy(), _prior_var(tau, A).numpy(), scale, F6)
    got = float(term(lik._positions(POS5)))
    assert abs(got - want) < 1e-7 * max(1.0, abs(want))
    assert abs(want) > 1.0  # not a vacuous comparison: the blocks change the density by nats
    # and the likelihood carries it: log_lik_given_omega and log_phat gain exactly Δ
    new = with_block_marginal(lik, term)
    diff = float(new.log_lik_given_omega(POS5, omega.mean) - lik.log_lik_given_omega(POS5, omega.mean))
    assert abs(diff - got) < 1e-9
    z = lik.sample_z((), 3, torch.Generator().manual_seed(0))
    assert abs(float(new.log_phat(POS5, z=z) - lik.log_phat(POS5, z=z)) - got) < 1e-9
    assert lik.block_marginal is None  # the original is left alone
    # and with the flat φ prior, the projection's limit
    flat, *_ = _lik(F=None)
    want = _reference(POS5, POS5, acc, omega.mean, Sig, mu.numpy(), _prior_var(tau, A).numpy(), scale)
    got = float(build_block_marginal(flat, POS5, mu, tau=tau, sample_scale=scale)(flat._positions(POS5)))
    assert abs(got - want) < 1e-7 * max(1.0, abs(want))


def _fast_rotation(T, seed, wd_scale):
    """_case's recording with the angular acceleration ``wd_scale`` rad/s² rms (vibrating boards: 10²–10³)."""
    from accel_bayes.model.gyro_posterior import gyro_posterior

    g = torch.Generator().manual_seed(seed)
    w = 4 * torch.randn(T, 3, generator=g, dtype=DT)
    wd = wd_scale * torch.randn(T, 3, generator=g, dtype=DT)
    sf = 3 * torch.randn(T, 3, generator=g, dtype=DT)
    acc = specific_force(POS5, w, wd, sf) + SIG * torch.randn(T, 5, 3, generator=g, dtype=DT)
    gyro = w[:, None, :] + 0.05 * torch.randn(T, 4, 3, generator=g, dtype=DT)
    return acc, gyro_posterior(gyro, torch.full((4,), 0.05, dtype=DT), "calibrated")


@pytest.mark.parametrize("phi_prior", [None, "proper"])
def test_delta_is_expanded_in_the_positions_with_the_projections_weights(phi_prior):
    """Away from θ₀ the module keeps X_t at θ₀ and expands the exact Δ(θ) — K(θ) and
    g(θ) = Σ X_tᵀW_t(θ)(y_t − m_t(θ)), W_t moving with the positions through φ's lever arms (module
    docstring) — to second order: its directional derivative at θ₀ equals the dense reference's
    (central differences, 1e-5 relative), and at 0.3 mm it agrees to 1 % of how much Δ moved (third
    order).  Not vacuous: with W_t held at θ₀ (the module before 2026-11-29) the derivative is off by
    more than half, since the angular acceleration (200 rad/s² rms here) is what W_t's motion carries."""
    acc, omega = _fast_rotation(40, 7, 200.0)
    A = 5
    F = None if phi_prior is None else np.diag([4e4, 4e4, 4e4, 9.0, 9.0, 9.0])
    lik = RaoBlackwellLikelihood(acc, omega, SIG, 1, phi_prior=None if F is None else torch.as_tensor(F))
    mu = 0.004 * torch.randn(12 * A, generator=torch.Generator().manual_seed(3), dtype=DT)
    tau = (0.01, 0.1)
    term = build_block_marginal(lik, POS5, mu, tau=tau)
    Sig = np.array([SIG ** 2 * np.eye(3 * A)] * lik.T)
    pv, one = _prior_var(tau, A).numpy(), np.ones(lik.T)
    step = torch.zeros_like(POS5)
    step[1:] = 1e-4 * torch.tensor([[1.0, -0.5, 0.3], [0.2, 0.8, -0.6], [-0.7, 0.1, 0.9], [0.4, -0.9, 0.2]])

    def ref(frac, exact=True):
        return _reference(POS5 + frac * step, POS5, acc, omega.mean, Sig, mu.numpy(), pv, one, F, exact_weights=exact)

    def mod(frac):
        return float(term(lik._positions(POS5 + frac * step)))

    eps = 1e-2
    d_ref = (ref(eps) - ref(-eps)) / (2 * eps)
    d_mod = (mod(eps) - mod(-eps)) / (2 * eps)
    d_held = (ref(eps, False) - ref(-eps, False)) / (2 * eps)
    assert abs(d_mod - d_ref) < 1e-5 * abs(d_ref), (d_mod, d_ref)
    assert abs(d_held - d_ref) > 0.5 * abs(d_ref), (d_held, d_ref)
    moved = ref(3.0) - ref(0.0)
    assert abs(moved) > 0.1  # nats: the positions matter to Δ
    assert abs((mod(3.0) - mod(0.0)) - moved) < 1e-2 * abs(moved), (mod(3.0) - mod(0.0), moved)
    assert abs(mod(0.0) - ref(0.0)) < 1e-7 * max(1.0, abs(ref(0.0)))


def test_flat_phi_prior_and_the_plain_likelihood():
    """Without a per-sample loading (the flat likelihood): the same dense reference with Σ_t = σ²I."""
    acc, omega, age, s = _case(T=9, seed=5)
    lik = RaoBlackwellLikelihood(acc, omega, SIG, 3)
    A, T = 5, 9
    mu = 0.005 * torch.ones(12 * A, dtype=DT)
    tau = (0.01, 0.2)
    term = build_block_marginal(lik, POS5, mu, tau=tau)
    Sig = np.array([SIG ** 2 * np.eye(3 * A)] * T)
    want = _reference(POS5, POS5, acc, omega.mean, Sig, mu.numpy(), _prior_var(tau, A).numpy(), np.ones(T))
    assert abs(float(term(lik._positions(POS5))) - want) < 1e-8 * max(1, abs(want))


def test_type2_ml_recovers_the_tolerance_it_was_simulated_with():
    """Blocks drawn with τ_M = 1 % (every triad, 8 triads, 600 samples of strong motion): the fitted
    τ_M within ±35 % over three seeds (72 identifiable entries: the evidence's relative std of τ̂² is
    about √(2/72) ≈ 17 %, so ±35 % is two of its std on τ̂); τ_M → 0 data give τ̂_M < 0.3 %."""
    pos = torch.tensor([[0, 0, 0], [0.05, 0, 0], [0, 0.05, 0], [0.05, 0.05, 0], [0, 0, 0.03], [0.05, 0, 0.03],
                        [0, 0.05, 0.03], [0.05, 0.05, 0.03]], dtype=DT)
    A, T = 8, 600
    from accel_bayes.model.gyro_posterior import gyro_posterior

    for seed, tau_true in ((0, 0.01), (1, 0.01), (2, 0.01), (3, 1e-5)):
        g = torch.Generator().manual_seed(seed)
        w = 5 * torch.randn(T, 3, generator=g, dtype=DT)
        wd = 20 * torch.randn(T, 3, generator=g, dtype=DT)
        sf = 9.8 * torch.randn(T, 3, generator=g, dtype=DT)
        f = specific_force(pos, w, wd, sf)  # (T, A, 3)
        E = tau_true * torch.randn(A, 3, 3, generator=g, dtype=DT)
        b = 0.1 * torch.randn(A, 3, generator=g, dtype=DT)
        acc = f + torch.einsum("kij,tkj->tki", E, f) + b + 0.02 * torch.randn(T, A, 3, generator=g, dtype=DT)
        gyro = w[:, None, :] + 0.002 * torch.randn(T, 2, 3, generator=g, dtype=DT)
        omega = gyro_posterior(gyro, torch.full((2,), 0.002, dtype=DT), "calibrated")
        lik = RaoBlackwellLikelihood(acc, omega, 0.02, 1)
        term = build_block_marginal(lik, pos, torch.zeros(12 * A, dtype=DT))
        tm = term.tau[0]
        if tau_true > 1e-3:
            assert 0.65 * tau_true < tm < 1.35 * tau_true, (seed, tm)
        else:
            assert tm < 3e-3, tm
        assert term.record["tau_from"] == "type-II ML"


def test_prior_mean_is_the_reports_blocks_in_the_array_frame():
    """μ_k = −[vec(RᵀÊR); Rᵀb̂] with R the nominal orientation (array → sensor): a block on a triad
    rotated 90° about z reads, in the array frame, with its rows and columns permuted."""
    e = AccLinear(imu=1)
    e.params = {"matrix": torch.tensor([[0.01, 0.002, 0.0], [0.0, -0.02, 0.0], [0.0, 0.0, 0.005]], dtype=DT),
                "bias": torch.tensor([0.1, -0.2, 0.3], dtype=DT)}
    q = np.array([[1.0, 0, 0, 0], [math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4)]])
    mu = block_prior_mean([(1, e)], q, [0, 1]).view(2, 12)
    assert torch.all(mu[0] == 0)
    from accel_bayes.physics.geometry import quat_to_matrix

    R = quat_to_matrix(torch.as_tensor(q[1]))
    Ma = -(R.T @ e.params["matrix"] @ R)
    assert torch.allclose(mu[1, :9], Ma.reshape(9), atol=1e-15)
    assert torch.allclose(mu[1, 9:], -(R.T @ e.params["bias"]), atol=1e-15)
    # a rotation by 90° about z swaps the x and y scale errors: −(−0.02) lands on the array's x
    assert abs(abs(float(mu[1, 0])) - 0.02) < 1e-12 and abs(abs(float(mu[1, 4])) - 0.01) < 1e-12


def test_bad_input_is_refused_with_one_line():
    lik, *_ = _lik(T=4)
    with pytest.raises(UserError, match="mu: expected"):
        build_block_marginal(lik, POS5, torch.zeros(7, dtype=DT))
    with pytest.raises(UserError, match="acc_blocks: expected tolerances"):
        build_block_marginal(lik, POS5, torch.zeros(60, dtype=DT), tau=(0.0, 0.1))
    with pytest.raises(UserError, match="sample_scale"):
        build_block_marginal(lik, POS5, torch.zeros(60, dtype=DT), sample_scale=np.zeros(lik.T))


def test_evidence_is_the_gaussian_integral_at_one_point():
    """``evidence`` against a brute-force 2-D integral when β has two entries (trapezoid on a grid)."""
    K = torch.tensor([[4.0, 1.0], [1.0, 3.0]], dtype=DT)
    g = torch.tensor([0.7, -0.4], dtype=DT)
    mu = torch.tensor([0.1, 0.2], dtype=DT)
    pv = torch.tensor([0.5, 0.3], dtype=DT)
    x = np.linspace(-6, 6, 1201)
    B1, B2 = np.meshgrid(x, x, indexing="ij")
    Kn, gn, mn, pn = K.numpy(), g.numpy(), mu.numpy(), pv.numpy()
    quad = Kn[0, 0] * B1 ** 2 + 2 * Kn[0, 1] * B1 * B2 + Kn[1, 1] * B2 ** 2
    logf = gn[0] * B1 + gn[1] * B2 - 0.5 * quad - 0.5 * ((B1 - mn[0]) ** 2 / pn[0] + (B2 - mn[1]) ** 2 / pn[1])
    val = np.trapezoid(np.trapezoid(np.exp(logf), x, axis=1), x) / (2 * math.pi * math.sqrt(pn.prod()))
    assert abs(float(evidence(K, g, mu, pv)) - math.log(val)) < 1e-8


@pytest.mark.parametrize("phi_prior,wd_scale", [(None, 3.0), ("proper", 3.0), (None, 150.0), ("proper", 150.0)])
def test_common_shift_is_the_modes_response_to_a_common_error(phi_prior, wd_scale):
    """:func:`common_shifts` against refitting: the outputs corrected by a common 3×3 error and offset
    (the same on every triad), the mode of the likelihood found again by L-BFGS; the linear response
    predicts the move within 10 % (measured 5–7 %: the test's own regressor, the noisy outputs, differs
    from the module's fitted f̂ by the noise), with slow rotation (ω̇ 3 rad/s² rms: the centripetal terms
    carry the response) and fast (150 rad/s²: the angular acceleration's lever arms carry it, through the
    projection's weights; the module without them predicted a fifth of the move on concealed clock
    recordings, 2026-11-29)."""
    from accel_bayes.model.acc_block_marginal import common_shifts
    from accel_bayes.model.unresolved_fit import fixed_omega_mode

    if wd_scale == 3.0:
        acc, omega, age, s = _case(T=400, seed=11)
    else:
        acc, omega = _fast_rotation(400, 11, wd_scale)
    F = None if phi_prior is None else torch.diag(torch.tensor([wd_scale ** 2] * 3 + [9.0] * 3, dtype=DT))
    lik = RaoBlackwellLikelihood(acc, omega, SIG, 1, phi_prior=F)
    P0, cov0 = fixed_omega_mode(lik, POS5)
    term = build_block_marginal(lik, P0, torch.zeros(60, dtype=DT), tau=(0.01, 0.1))
    C = torch.tensor([[0.02, -0.01, 0.005], [0.01, -0.015, 0.0], [-0.004, 0.008, 0.01]], dtype=DT)
    beta = torch.cat((C.reshape(9), torch.tensor([0.05, -0.02, 0.03], dtype=DT)))
    term.common_center, term.common_std = -beta, torch.zeros(12, dtype=DT)  # draws = β exactly
    free = [c for c in range(15) if c // 3 != lik.reference]
    pred = common_shifts(term, cov0, free, 1, torch.Generator().manual_seed(0))[0]
    # the data as they would be with that common error taken off: y − (C f̂ + b), f̂ ≈ y to first order
    corrected = acc - (torch.einsum("ij,tkj->tki", C, acc) + beta[9:])
    P1, _ = fixed_omega_mode(RaoBlackwellLikelihood(corrected, omega, SIG, 1, phi_prior=F), P0)
    move = (P1 - P0).reshape(-1)[free]
    assert float(move.norm()) > 0.5 * float(cov0.diagonal().sqrt().mean())  # not a vacuous comparison
    assert float((pred - move).norm()) < 0.1 * float(move.norm()), float((pred - move).norm() / move.norm())


def test_newton_mode_agrees_with_lbfgs_and_survives_a_steep_start():
    """``fixed_omega_mode(newton=True)`` (the block step's mode search): on the plain likelihood it finds
    L-BFGS's mode and Laplace covariance (1e-9 m, 1e-6 relative); with the block term added at a
    fast-rotation geometry, whose gradient there is ~10⁴ nats/m, it lands on the combined target's
    stationary point (the Newton step left < 1e-9 m) with a positive definite covariance."""
    from accel_bayes.model.unresolved_fit import fixed_omega_mode

    acc, omega = _fast_rotation(300, 5, 150.0)
    lik = RaoBlackwellLikelihood(acc, omega, SIG, 1)
    P_l, C_l = fixed_omega_mode(lik, POS5)
    P_n, C_n = fixed_omega_mode(lik, POS5, newton=True)
    assert float((P_l - P_n).abs().max()) < 1e-9
    assert float(((C_l - C_n).abs() / C_l.diagonal().sqrt().outer(C_l.diagonal().sqrt())).max()) < 1e-6
    mu = 0.006 * torch.randn(60, generator=torch.Generator().manual_seed(8), dtype=DT)
    term = build_block_marginal(lik, P_n, mu, tau=(0.01, 0.1))
    free = [c for c in range(15) if c // 3 != lik.reference]
    assert float(term.grad[free].abs().max()) > 1e3  # a steep start (the reason for Newton)
    new = with_block_marginal(lik, term)
    P, C = fixed_omega_mode(new, P_n, newton=True)
    th = P.reshape(-1)[free].clone().requires_grad_(True)

    def ll(t):
        full = torch.zeros(15, dtype=DT)
        full[free] = t
        return new.log_lik_given_omega(full.view(5, 3), omega.mean)

    grad = torch.autograd.grad(ll(th), th)[0]
    assert float((C @ grad).abs().max()) < 1e-9  # m (the posterior std is ~1e-4 m): the Newton step left
    assert bool((torch.linalg.eigvalsh(C) > 0).all())
    assert float((P - P_n).abs().max()) > 1e-6  # the term moved the mode


def test_tolerance_fit_survives_its_line_search_and_large_recordings_recompute():
    """A prior centre of 0.6 % blocks on data without any (fast rotation): the type-II ML's line search
    tries tolerances ≫ 1, where I + PK loses its definiteness to round-off; the fit stays inside
    [1e-6, 1] and returns (it raised before the clamp).  And the term built without keeping the per-sample
    products between evaluations (what recordings too large for memory get) is the same to the bit."""
    import accel_bayes.model.acc_block_marginal as abm

    acc, omega = _fast_rotation(300, 5, 150.0)
    lik = RaoBlackwellLikelihood(acc, omega, SIG, 1)
    mu = 0.006 * torch.randn(60, generator=torch.Generator().manual_seed(8), dtype=DT)
    a = build_block_marginal(lik, POS5, mu)
    assert 1e-6 <= a.tau[0] <= 1 and 1e-6 <= a.tau[1] <= 1
    keep = abm._STORE_BYTES
    try:
        abm._STORE_BYTES = 0
        b = build_block_marginal(lik, POS5, mu)
    finally:
        abm._STORE_BYTES = keep
    assert a.value == b.value and torch.equal(a.grad, b.grad) and torch.equal(a.hess, b.hess)


@pytest.mark.parametrize("phi_prior,flat", [(None, False), ("proper", False), ("proper", True), ("proper", "kappa1")])
def test_marginal_scores_sum_to_the_targets_gradient(phi_prior, flat):
    """Fisher's identity (marginal_scores' docstring): the per-sample scores of the target with the
    deviations integrated out sum to ∇(ℓ + Δ) — ℓ's gradient by autograd of log_lik_given_omega, Δ's
    the exact gradient the term keeps at θ₀ — to 1e-7 of their size; the corrected outputs' part alone
    (the trace term dropped) misses by more than 1e-4 of it (what the trace term carries).  With a tiny
    tolerance and the prior centred at zero the scores are ℓ's own (nothing to integrate)."""
    import accel_bayes.model.acc_block_marginal as abm
    from accel_bayes.inference.noise_fit import per_sample_scores

    lik, acc, omega, age, s, ang = _lik(T=40, F=None if phi_prior is None else F6)
    if flat is True:  # the plain likelihood (no per-sample terms, no log_lik_per_sample of its own)
        lik = RaoBlackwellLikelihood(acc, omega, SIG, 3, phi_prior=torch.as_tensor(F6))
    elif flat == "kappa1":  # what calibrate --model hands over without per-sample terms: tempered by κ = 1
        from accel_bayes.model.tempering import TemperedLikelihood

        lik = TemperedLikelihood(acc, omega, SIG, 3, 1.0, phi_prior=torch.as_tensor(F6))
    A = lik.A
    scale = np.linspace(0.8, 1.6, lik.T)
    mu = 0.01 * torch.randn(12 * A, generator=torch.Generator().manual_seed(2), dtype=DT)
    term = build_block_marginal(lik, POS5, mu, tau=(0.02, 0.3), sample_scale=scale)
    free = list(range(3, 3 * A))
    r0 = lik._positions(POS5).reshape(-1)
    S = abm.marginal_scores(lik, term, POS5, free)
    assert S.shape == (lik.T, len(free))

    def ell(th):
        rv = r0.clone().index_put((torch.as_tensor(free),), th)
        return lik.log_lik_given_omega(rv.view(A, 3), omega.mean)

    th = r0[free].clone().requires_grad_(True)
    want = torch.autograd.grad(ell(th), th)[0] + term.grad[free]
    got = S.sum(0)
    assert float((got - want).norm()) < 1e-7 * float(want.norm()), (got, want)

    # without the trace term the sum misses: the check can fail
    saved = abm._ExactDelta.posterior_vv
    try:
        abm._ExactDelta.posterior_vv = lambda self, rv, R: (rv * 0).sum() * torch.ones(lik.T, dtype=DT)
        partial = abm.marginal_scores(lik, term, POS5, free).sum(0)
    finally:
        abm._ExactDelta.posterior_vv = saved
    assert float((partial - want).norm()) > 1e-4 * float(want.norm())

    if flat == "kappa1":  # a target tempered by κ ≠ 1 has no per-sample scores of its own: refused
        from accel_bayes.model.tempering import TemperedLikelihood

        hot = TemperedLikelihood(acc, omega, SIG, 3, 2.0, phi_prior=torch.as_tensor(F6))
        with pytest.raises(UserError, match="kappa"):
            abm.marginal_scores(hot, term, POS5, free)
    tiny = build_block_marginal(lik, POS5, torch.zeros(12 * A, dtype=DT), tau=(1e-9, 1e-9), sample_scale=scale)
    per = lik if hasattr(lik, "log_lik_per_sample") else PerSampleCovLikelihood(
        acc, omega, SIG, 3, torch.zeros(lik.T, A, dtype=DT), 0.0, phi_prior=torch.as_tensor(F6))
    plain = per_sample_scores(lambda t: per.log_lik_per_sample(
        r0.clone().index_put((torch.as_tensor(free),), t).view(A, 3), omega.mean), r0[free].clone())
    S0 = abm.marginal_scores(lik, tiny, POS5, free)
    assert float((S0 - plain).abs().max()) < 1e-8 * float(plain.abs().max())


def _simulated_blocks(seed, T=1500, sig=0.05, tau=(0.01, 0.1)):
    """Data from the block model itself: five triads at POS5 with deviations γ ~ N(0, τ²) (zero common part),
    outputs (I + E_k) f + b_k + N(0, σ²), gyros almost exact (the sandwich is taken at ω̄)."""
    import accel_bayes.model.acc_block_marginal as abm
    from accel_bayes.model.gyro_posterior import gyro_posterior

    g = torch.Generator().manual_seed(seed)
    w = 4 * torch.randn(T, 3, generator=g, dtype=DT)
    f = specific_force(POS5, w, 30 * torch.randn(T, 3, generator=g, dtype=DT), 3 * torch.randn(T, 3, generator=g,
                                                                                                 dtype=DT))
    A = 5
    gam = torch.randn(12 * (A - 1), generator=g, dtype=DT) * _prior_var(tau, A - 1).sqrt()
    beta = (abm.deviation_basis(A) @ gam).view(A, 12)
    E, b = beta[:, :9].reshape(A, 3, 3), beta[:, 9:]
    acc = f + torch.einsum("kij,tkj->tki", E, f) + b + sig * torch.randn(T, A, 3, generator=g, dtype=DT)
    gyro = w[:, None, :] + 1e-5 * torch.randn(T, 4, 3, generator=g, dtype=DT)
    om = gyro_posterior(gyro, torch.full((4,), 1e-5, dtype=DT), "calibrated")
    return RaoBlackwellLikelihood(acc, om, sig, 1), tau


@pytest.mark.parametrize("seed", [0, 1])
def test_efficient_scores_give_an_honest_sandwich_on_data_from_the_model(seed):
    """On data simulated from the model (a correctly specified target) the sandwich of the efficient
    scores at the mode of ℓ + Δ matches its Laplace covariance: mean variance ratio κ within 0.9–1.1
    (measured 0.98–1.04 over four seeds; the meat's sampling error at T = 1500 is a few %), every
    coordinate's std ratio within 0.8–1.25.  The scores before their projection on γ's own scores
    (the nuisance fitted to the same samples) give κ > 2 (measured 2.6–2.8): the check can fail."""
    import accel_bayes.model.acc_block_marginal as abm
    from accel_bayes.inference.noise_fit import score_sandwich
    from accel_bayes.model.unresolved_fit import fixed_omega_mode

    lik, tau = _simulated_blocks(seed)
    term = build_block_marginal(lik, POS5, torch.zeros(60, dtype=DT), tau=tau)
    P, cov = fixed_omega_mode(with_block_marginal(lik, term), POS5, prior_mean=POS5, prior_std=1.0, newton=True)
    free = list(range(3, 15))
    sw = score_sandwich(abm.marginal_scores(lik, term, P - P[0], free), cov)
    assert 0.9 < sw["kappa"] < 1.1, sw["kappa"]
    assert ((sw["std_ratio"] > 0.8) & (sw["std_ratio"] < 1.25)).all(), sw["std_ratio"]
    saved = abm._ExactDelta.g_per_sample
    try:
        abm._ExactDelta.g_per_sample = lambda self, rv, dy: torch.zeros(self.lik.T, self.Z.shape[1], dtype=DT)
        naive = score_sandwich(abm.marginal_scores(lik, term, P - P[0], free), cov)
    finally:
        abm._ExactDelta.g_per_sample = saved
    assert naive["kappa"] > 2.0, naive["kappa"]

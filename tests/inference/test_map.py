"""Tests of the [C21] MAP and its Laplace covariance (accel_bayes.inference.map).

Independent references: the true geometry (noise-free data), a dense autograd Hessian of the
negative log posterior written with the likelihood helper (accel_bayes.model.likelihood), and the
Cramér–Rao bound (slow statistical study).
"""
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.errors import UserError
from accel_bayes.inference.crb import crb_theta
from accel_bayes.inference.map import MAPDivergence, build_map_problem, fit_map, fit_map_recording
from accel_bayes.physics.models import imu_outputs, to_array_frame
from accel_bayes.physics.motion_generators import iid_motion

DT = torch.float64
DEG = math.pi / 180
SA, SG = 0.04, 0.06 * DEG


def make_data(T=200, seed=0, noise=True, pos_err=1e-4, array=None):
    """A [C21] data set: mimu8 board, i.i.d. motion, true positions = nominal + N(0, pos_err²)."""
    arr = mimu4444_8() if array is None else array
    g = torch.Generator().manual_seed(seed)
    m = iid_motion(T, generator=g)
    K = arr.K
    true = arr.positions + pos_err * torch.randn(K, 3, generator=g, dtype=DT)
    true[0] = arr.positions[0]
    acc, gyro = imu_outputs(true, arr.orientations, m.omega, m.omega_dot, m.s)
    if noise:
        acc = acc + SA * torch.randn(acc.shape, generator=g, dtype=DT)
        gyro = gyro + SG * torch.randn(gyro.shape, generator=g, dtype=DT)
    acc_a = to_array_frame(acc, arr.orientations)
    gyro_a = to_array_frame(gyro, arr.orientations)
    wbar = gyro_a.mean(1)  # calibrated gyros: the mean is sufficient, covariance σ_g²/K
    P = torch.eye(3, dtype=DT) * SG**2 / K
    return dict(arr=arr, motion=m, true=true, acc=acc_a, wbar=wbar, P=P)


def _full_phi_prior(seed=7):
    """A proper prior on φ with a full (correlated) 6×6 covariance, ω̇ ~ 30 rad/s², s ~ 6 m/s²."""
    g = torch.Generator().manual_seed(seed)
    B = torch.randn(6, 6, generator=g, dtype=DT)
    sd = torch.tensor([30.0, 30.0, 30.0, 6.0, 6.0, 6.0], dtype=DT)
    C = B @ B.T + 6 * torch.eye(6, dtype=DT)
    C = C / torch.outer(C.diagonal().sqrt(), C.diagonal().sqrt())
    return sd[:, None] * C * sd[None, :]


PHI_PRIORS = [None, "full"]


def _phi(p):
    return None if p is None else _full_phi_prior()


def test_noise_free_map_recovers_true_positions():
    d = make_data(T=200, seed=1, noise=False)
    res = fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, prior_std=3e-3)
    assert res.converged, res.reason
    rel = d["true"] - d["true"][0]
    err = float((res.positions - rel).abs().max())
    assert err < 1e-6, err
    assert torch.equal(res.positions[0], torch.zeros(3, dtype=DT))
    assert res.theta.shape == (7, 3) and res.omega.shape == (200, 3) and res.laplace_cov.shape == (21, 21)
    # ω at the mode equals the true ω (the gyro data were exact)
    assert float((res.omega - d["motion"].omega).abs().max()) < 1e-6


def _dense_neg_log_post(d, lik, prior_mean, prior_std, reference=0):
    """−log p(θ, ω | y) written independently with the likelihood helper."""
    A = d["acc"].shape[1]
    T = d["acc"].shape[0]
    keep = [k for k in range(A) if k != reference]
    mu = (prior_mean - prior_mean[reference])[keep].reshape(-1)
    Pinv = torch.linalg.inv(d["P"])
    n = 3 * (A - 1)

    def f(z):
        th = z[:n].reshape(A - 1, 3)
        pos = torch.zeros(A, 3, dtype=DT)
        pos = pos.index_put((torch.tensor(keep),), th)
        w = z[n:].reshape(T, 3)
        dw = w - d["wbar"]
        return (-lik.log_lik_given_omega(pos, w) + 0.5 * torch.einsum("ti,ij,tj->", dw, Pinv, dw)
                + 0.5 * (((z[:n] - mu) / prior_std) ** 2).sum())

    return f


def _small_problem(seed=3, T=10):
    arr = mimu4444_8()
    sub = arr.with_(positions=arr.positions[:4], orientations=arr.orientations[:4], has_acc=arr.has_acc[:4],
                    has_gyro=arr.has_gyro[:4], acc_noise_std=arr.acc_noise_std[:4],
                    gyro_noise_std=arr.gyro_noise_std[:4])
    d = make_data(T=T, seed=seed, noise=True, array=sub)
    # add larger noise so second-order (residual × curvature) Hessian terms matter
    g = torch.Generator().manual_seed(seed + 100)
    d["acc"] = d["acc"] + 0.3 * torch.randn(d["acc"].shape, generator=g, dtype=DT)
    return d


@pytest.mark.parametrize("phi_prior", PHI_PRIORS)
def test_laplace_covariance_matches_dense_autograd_hessian(phi_prior):
    likelihood = pytest.importorskip("accel_bayes.model.likelihood")
    d = _small_problem()
    A, T = 4, d["acc"].shape[0]
    sa = 0.34
    prior_std = 3e-3
    res = fit_map(d["acc"], d["wbar"], d["P"], sa, prior_mean=d["arr"].positions, prior_std=prior_std,
                  max_iter=200, phi_prior=_phi(phi_prior))
    assert res.converged, res.reason
    lik = likelihood.RaoBlackwellLikelihood(d["acc"], likelihood.GyroPosterior(d["wbar"], d["P"].expand(T, 3, 3), "given"),
                                            torch.full((A,), sa, dtype=DT), num_draws=1, phi_prior=_phi(phi_prior))
    f = _dense_neg_log_post(d, lik, d["arr"].positions, prior_std)
    z = torch.cat((res.theta.reshape(-1), res.omega.reshape(-1)))
    # the mode is a stationary point of the independent objective
    zz = z.clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(f(zz), zz)
    Hd = torch.autograd.functional.hessian(f, z)
    step = torch.linalg.solve(Hd, grad)  # Newton step left at the mode
    cov_d = torch.linalg.inv(Hd)[:9, :9]
    assert float((step[:9] / cov_d.diagonal().sqrt()).abs().max()) < 1e-5
    rel = float(torch.linalg.norm(res.laplace_cov - cov_d) / torch.linalg.norm(cov_d))
    assert rel < 1e-6, rel
    # the MAP's log posterior is −f up to a constant: compare differences between two points
    prob = build_map_problem(d["acc"], d["wbar"], d["P"], sa, prior_mean=d["arr"].positions, prior_std=prior_std,
                             phi_prior=_phi(phi_prior))
    z2 = z + 1e-4 * torch.randn(z.shape, generator=torch.Generator().manual_seed(0), dtype=DT)
    c1 = prob.cost({"theta": z[:9].reshape(3, 3)}, z[9:].reshape(T, 3))
    c2 = prob.cost({"theta": z2[:9].reshape(3, 3)}, z2[9:].reshape(T, 3))
    assert abs((c2 - c1) - float(f(z2) - f(z))) < 1e-8 * abs(float(f(z)))
    # the Gauss–Newton Laplace differs (second-order terms matter at this noise level)
    S_gn = res.lm.information("gauss_newton")
    rel_gn = float(torch.linalg.norm(torch.linalg.inv(S_gn) - cov_d) / torch.linalg.norm(cov_d))
    assert rel_gn > 1e-4


@pytest.mark.parametrize("phi_prior", PHI_PRIORS)
def test_map_objective_theta_part_is_the_likelihood_helper(phi_prior):
    likelihood = pytest.importorskip("accel_bayes.model.likelihood")
    d = make_data(T=50, seed=4)
    T = 50
    prob = build_map_problem(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, phi_prior=_phi(phi_prior))
    lik = likelihood.RaoBlackwellLikelihood(d["acc"], likelihood.GyroPosterior(d["wbar"], d["P"].expand(T, 3, 3), "given"),
                                            SA, num_draws=1, phi_prior=_phi(phi_prior))
    g = torch.Generator().manual_seed(1)
    for _ in range(3):
        pos = d["arr"].positions + 1e-3 * torch.randn(8, 3, generator=g, dtype=DT)
        pos = pos - pos[0]
        w = d["wbar"] + 0.05 * torch.randn(T, 3, generator=g, dtype=DT)
        terms = prob.cost_terms({"theta": pos[1:]}, w)
        ref = -float(lik.log_lik_given_omega(pos, w))
        assert abs(terms["acc"] + terms["logdetM"] - ref) < 1e-9 * abs(ref)
        # the log|M| term is the corrected (T/2)·log|M|, not the paper's T·log|M|
        paper = -float(lik.log_lik_paper_eq25(pos, w))
        assert abs(terms["acc"] + 2 * terms["logdetM"] - paper) < 1e-9 * abs(paper)
        if phi_prior is not None:  # the prior matters: the flat objective differs
            flat = build_map_problem(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions)
            ft = flat.cost_terms({"theta": pos[1:]}, w)
            assert abs(ft["acc"] + ft["logdetM"] - ref) > 1.0


@pytest.mark.parametrize("reference,phi_prior", [(0, None), (3, None), (3, "full")])
def test_analytic_derivatives_match_autodiff_and_finite_differences(reference, phi_prior):
    d = make_data(T=25, seed=8)
    g = torch.Generator().manual_seed(2)
    kw = dict(prior_mean=d["arr"].positions, reference=reference, phi_prior=_phi(phi_prior),
              init_positions=d["arr"].positions + 1e-3 * torch.randn(8, 3, generator=g, dtype=DT))
    pa = build_map_problem(d["acc"], d["wbar"], d["P"], SA, analytic=True, **kw)
    pb = build_map_problem(d["acc"], d["wbar"], d["P"], SA, analytic=False, **kw)
    v = pa.initial_values()
    x = pa.x0 + 0.1 * torch.randn(25, 3, generator=g, dtype=DT)
    for ra, rb in zip(pa.sample_residuals, pb.sample_residuals):
        _, Jga, Jxa = pa.sample_jacobians(ra, v, x)
        _, Jgb, Jxb = pb.sample_jacobians(rb, v, x)
        assert torch.allclose(Jxa, Jxb, rtol=1e-10, atol=1e-10 * float(Jxb.abs().max()))
        if Jga is not None:
            assert torch.allclose(Jga, Jgb, rtol=1e-10, atol=1e-10 * float(Jgb.abs().max()))
        else:
            assert float(Jgb.abs().max()) == 0.0
    va, ga, Ha = pa.extra_derivatives(pa.extra[0], v)
    vb, gb, Hb = pb.extra_derivatives(pb.extra[0], v)
    assert torch.allclose(ga, gb, rtol=1e-10) and torch.allclose(Ha, Hb, rtol=1e-9, atol=1e-9 * float(Hb.abs().max()))
    # finite differences of the acc residual w.r.t. θ (central, h = 1e-7 m)
    r0 = pa.sample_residuals[0]
    _, Jg, _ = pa.sample_jacobians(r0, v, x)
    h = 1e-7
    for j in (0, 7, 20):
        e = torch.zeros(21, dtype=DT)
        e[j] = h
        rp = r0.fn({"theta": v["theta"] + e.reshape(7, 3)}, x, r0.data)
        rm = r0.fn({"theta": v["theta"] - e.reshape(7, 3)}, x, r0.data)
        fd = (rp - rm) / (2 * h)
        assert torch.allclose(Jg[..., j], fd, rtol=1e-5, atol=1e-5 * float(fd.abs().max()))


@pytest.mark.parametrize("phi_prior", PHI_PRIORS)
def test_local_newton_blocks_are_the_exact_omega_hessian(phi_prior):
    d = make_data(T=30, seed=9)
    g = torch.Generator().manual_seed(4)
    prob = build_map_problem(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, phi_prior=_phi(phi_prior))
    v = {"theta": prob.initial_values()["theta"] + 1e-3 * torch.randn(7, 3, generator=g, dtype=DT)}
    x = prob.x0 + 0.3 * torch.randn(30, 3, generator=g, dtype=DT)  # far from the mode: large residuals
    gn = prob.linearize(v, x, step=False).V
    ex = prob.exact_hessian(v, x).V
    res = prob.sample_residuals[0]
    corr = res.local_hessian(v, x, res.data, res.fn(v, x, res.data))
    assert torch.allclose(gn + corr, ex, rtol=1e-9, atol=1e-9 * float(ex.abs().max()))
    # the MAP does not depend on the local model, only the path to it
    fa = fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, local_newton=True)
    fb = fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, local_newton=False)
    assert float((fa.theta - fb.theta).abs().max()) < 1e-3 * float(fa.position_std().max())


def test_fit_map_recording_on_simulated_recording():
    simulate = pytest.importorskip("accel_bayes.simulate")
    sim = simulate.simulate(mimu4444_8(), "iid", T=150, seed=7, clip=False, position_error_std=1e-4)
    res = fit_map_recording(sim.recording, gyro_method="calibrated")
    assert res.converged, res.reason
    assert res.imu_labels == tuple(range(8))
    rel = sim.true_positions - sim.true_positions[0]
    z = ((res.positions - rel)[1:] / res.position_std()[1:]).abs()
    assert float(z.max()) < 5.0, z
    cov = res.position_cov()
    assert cov.shape == (8, 3, 3) and torch.equal(cov[0], torch.zeros(3, 3, dtype=DT))


def test_divergence_is_reported_not_returned():
    d = make_data(T=40, seed=5)
    far = d["arr"].positions * 30.0
    with pytest.raises(MAPDivergence):
        fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, init_positions=far, max_iter=0)
    res = fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, init_positions=far, max_iter=0,
                  on_divergence="ignore")
    assert not res.converged and res.reason.startswith("diverged")
    assert bool(torch.isnan(res.laplace_cov).all())


def test_bad_input_is_refused():
    d = make_data(T=20, seed=6)
    with pytest.raises(UserError):
        fit_map(d["acc"][:, :2], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions[:2])
    with pytest.raises(UserError):
        fit_map(d["acc"], d["wbar"][:5], d["P"], SA, prior_mean=d["arr"].positions)
    with pytest.raises(UserError):
        fit_map(d["acc"], d["wbar"], d["P"], SA)  # no prior mean and no start
    with pytest.raises(UserError):
        fit_map(d["acc"], d["wbar"], d["P"], torch.ones(5), prior_mean=d["arr"].positions)


def test_map_errors_attain_the_crb():
    """MUST-SHOW: 50 simulated sets of one configuration — mimu8, T = 200, σ_a = 0.04 m/s²,
    σ_g = 0.06 °/s (8 calibrated gyros), [C21] i.i.d. motion, prior N(nominal, (3 mm)²), truth =
    nominal + N(0, (0.1 mm)²) — the MAP errors in units of the CRB standard deviation (Bayesian
    bound, prior information included) have RMS in [0.8, 1.2]."""
    z_all, maha = [], []
    for rep in range(50):
        d = make_data(T=200, seed=1000 + rep)
        res = fit_map(d["acc"], d["wbar"], d["P"], SA, prior_mean=d["arr"].positions, prior_std=3e-3,
                      hessian="gauss_newton")
        assert res.converged, res.reason
        m = d["motion"]
        C = crb_theta(d["true"], m.omega, m.omega_dot, m.s, SA, torch.full((8,), SG, dtype=DT), prior_std=3e-3)
        err = (res.theta - (d["true"] - d["true"][0])[1:]).reshape(-1)
        z_all.append(err / C.diagonal().sqrt())
        maha.append(float(err @ torch.linalg.solve(C, err)) / err.numel())
    z = torch.cat(z_all)
    rms = float(z.pow(2).mean().sqrt())
    print(f"MAP error RMS in CRB std units over 50 sets × 21 coordinates: {rms:.3f}; "
          f"mean Mahalanobis/n: {np.mean(maha):.3f}; mean error: {float(z.mean()):+.3f} CRB std")
    assert 0.8 <= rms <= 1.2

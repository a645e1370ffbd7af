"""The detector's speed-ups keep its numbers (issue #11 item 3): the IMU-major linearisation equals
the normal equations formed from the sensor-major Jacobians, PSIS-LOO's projected quadratic form
equals the explicit projection, the χ² tail is SciPy's, noise_level refits are only skipped where
they cannot change the verdict, and ``detect`` runs with one torch thread and restores the count."""
import math

import numpy as np
import pytest
import torch

from accel_bayes.errors import UserError
from accel_bayes.mismatch import baseline_fit, detect, fit_model, make_effect, prepare
from accel_bayes.mismatch.compare import _projected_quad
from accel_bayes.mismatch.locate import _chi2_logsf
from accel_bayes.mismatch.model import _Model
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.simulate import simulate

DEG = math.pi / 180
# the simulation of these numerics checks (shorter than test_detect's: they compare two computations)
NUMERICS_SIM = dict(T=300, rate=200.0, acc_noise_std=0.02, gyro_noise_std=0.1 * DEG)


@pytest.fixture(scope="module")
def prepared():
    eff = make_effect("acc_scale", imu=3, axis="y", parameters={"scale": 0.02})
    prep = prepare(simulate(mimu4444_8(), "smooth", seed=31, effects=[eff], **NUMERICS_SIM).recording)
    base, _ = baseline_fit(prep)
    return prep, base


def _effects():
    return [make_effect("acc_scale", imu=3, axis="y"), make_effect("triad_orientation", imu=2),
            make_effect("gyro_bias", imu=5, axis="x")]


def test_imu_major_linearize_equals_normal_equations_of_the_jacobians(prepared):
    prep, base = prepared
    model = _Model(prep, _effects(), base.acc_factor, base.gyro_factor, base.positions, 3e-3)
    theta = base.positions[torch.as_tensor(prep.free_imus)] + 1e-4
    eta = torch.full((model.p,), 1e-3, dtype=torch.float64)
    lin = model.linearize(theta, eta, base.x)
    r, Jx, Jr, Je = model.jacobians(theta, eta, base.x)  # sensor-major (T, 2, K, 3, ·)
    T, K, F = prep.T, prep.K, model.F
    # the dense global Jacobian, columns [free positions, η], rows (T, 6K)
    Jg = torch.zeros(T, 2, K, 3, model.n, dtype=torch.float64)
    for j, k in enumerate(prep.free_imus):
        Jg[:, :, k, :, 3 * j:3 * j + 3] = Jr[:, :, k]
    Jg[..., 3 * F:] = Je
    Jg, Jx, r = Jg.reshape(T, 6 * K, -1), Jx.reshape(T, 6 * K, 9), r.reshape(T, 6 * K)
    prior = torch.cat((torch.full((3 * F,), 1 / 3e-3 ** 2, dtype=torch.float64), model.eta_info))
    U = torch.einsum("tmi,tmj->ij", Jg, Jg) + torch.diag(prior)
    b_g = -torch.einsum("tmi,tm->i", Jg, r) - prior * torch.cat(((theta - model.mu).reshape(-1), eta))
    tol = dict(rtol=1e-10, atol=1e-9)
    torch.testing.assert_close(lin["U"], U, **tol)
    torch.testing.assert_close(lin["W"], Jg.transpose(-1, -2) @ Jx, **tol)
    torch.testing.assert_close(lin["V"], Jx.transpose(-1, -2) @ Jx, **tol)
    torch.testing.assert_close(lin["b_g"], b_g, **tol)
    torch.testing.assert_close(lin["b_x"], -(Jx.transpose(-1, -2) @ r.unsqueeze(-1)).squeeze(-1), **tol)
    torch.testing.assert_close(lin["Jx"].reshape(T, 6 * K, 9), Jx, rtol=0, atol=0)
    assert lin["cost"] == pytest.approx(0.5 * float((r ** 2).sum()) + model.prior_cost(theta, eta), rel=1e-12)


def test_projected_quadratic_form_equals_the_explicit_projection(prepared):
    prep, base = prepared
    fit = fit_model(prep, _effects(), init=base, laplace=False)
    lin = fit.linear()
    g = torch.Generator().manual_seed(3)
    dg = torch.randn(7, lin.n, generator=g, dtype=torch.float64) @ torch.linalg.cholesky(lin.Sinv).T
    T = lin.r.shape[0]
    Zd = (dg @ lin.Z.reshape(T * 9, lin.n).T).reshape(-1, T, 9)
    Pd = lin.jg_mul(dg) - lin.jx_mul(Zd)  # P_t J_t δ, formed explicitly
    torch.testing.assert_close(_projected_quad(lin, dg), (Pd * Pd).sum(-1), rtol=1e-9, atol=1e-12)


def test_chi2_log_tail_is_scipys():
    from scipy.stats import chi2

    for df in (1, 2, 3, 5, 12):
        for x in np.concatenate(([0.0, 1e-12], np.linspace(0.01, 400, 97))):
            assert _chi2_logsf(float(x), df) == float(chi2.logsf(x, df))


def test_noise_level_refits_only_in_rounds_without_an_acceptable_mean_effect():
    eff = make_effect("acc_scale", imu=3, axis="x", parameters={"scale": 0.03})
    rep = detect(simulate(mimu4444_8(), "smooth", seed=32, effects=[eff], **NUMERICS_SIM).recording, seed=0,
                 n_twins=10, loo_draws=20, refine=False)
    assert rep.findings and rep.findings[0].effect == "acc_scale"
    skipped = 0
    for rnd in rep.rounds:
        mean_ok = any(x.get("evidence_robust", -1) > rep.threshold for x in rnd["refits"]
                      if not x["candidate"].startswith("noise_level"))
        for x in rnd["refits"]:
            if x["candidate"].startswith("noise_level"):
                assert ("skipped" in x) == mean_ok
                assert ("evidence" in x) != mean_ok
                skipped += "skipped" in x
    assert skipped, "the case is meant to exercise a skipped noise_level refit"


def test_detect_runs_with_one_thread_and_restores_the_count(monkeypatch):
    import importlib

    det = importlib.import_module("accel_bayes.mismatch.detector")  # the driver module

    seen = []

    def fake_load(*args, **kwargs):
        seen.append(torch.get_num_threads())
        raise UserError("stop here")

    before = torch.get_num_threads()
    monkeypatch.setattr(det, "load_recording", fake_load)
    try:
        torch.set_num_threads(2)
        with pytest.raises(UserError, match="stop here"):
            detect("unused.nc")
        assert seen == [1] and torch.get_num_threads() == 2
        with pytest.raises(UserError, match="threads"):
            detect("unused.nc", threads=0)
    finally:
        torch.set_num_threads(before)

"""The gyro linear stage's common part is judged by a heteroscedasticity-robust Wald statistic
(``gyro_linear.robust_wald``; issue #27/#30, experiments/gyro_common_stage_probe.md).

Checked against (1) a dense computation written independently here: the full Gauss–Newton
information of every parameter (positions, the common block, every sample's motion states) by
autograd on the model's residual function, and the textbook sandwich H⁻¹ (Σ_t g_t g_tᵀ) H⁻¹; and
(2) data from the independent generator ``experiments/_conceal.py``: with white noise as stated both
statistics follow χ²_11, with an accelerometer excess that grows with |ω|² (where the centripetal
terms that see the common part are large) the model-based statistic is inflated by 10²–10³ while the
robust one stays near 11.
"""

import dataclasses
import warnings

import numpy as np
import pytest
import torch

from accel_bayes.mismatch.fit import baseline_fit, fit_model
from accel_bayes.mismatch.gyro_linear import COMMON_DF, robust_wald
from accel_bayes.mismatch.prepared import prepare
from accel_bayes.physics.effects import GyroLinear

from experiments import _conceal as C


def _fit(seed, T, excess=0.0):
    """(prep, baseline, fit with one common GyroLinear) on a clean irregular6 recording; ``excess`` (m/s²)
    adds accelerometer noise of std excess·|ω|²/mean|ω|² per sample (seeded)."""
    rec = C.make_case("irregular6", "none", seed, T=T).recording
    if excess:
        rng = np.random.default_rng(seed)
        w2 = (np.asarray(rec.gyro)[:, 0] ** 2).sum(-1)
        sd = excess * w2 / w2.mean()
        rec = dataclasses.replace(rec, acc=np.asarray(rec.acc) + rng.standard_normal(np.shape(rec.acc)) * sd[:, None, None])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        prep = prepare(rec)
        base = baseline_fit(prep)[0]
        fc = fit_model(prep, [GyroLinear(imu=None)], init=base, laplace=False)
    return prep, base, fc


def _dense_sandwich(fc):
    """(robust, model-based) covariance of the common block's 12 parameters, dense (module docstring)."""
    lm = fc.lm
    model = lm.model
    th, eta, x = lm.theta.detach(), lm.eta.detach(), lm.x.detach()
    F, p, T = th.shape[0], eta.numel(), x.shape[0]
    z0 = torch.cat((th.reshape(-1), eta, x.reshape(-1)))

    def res(z):
        return model.residual(z[:3 * F].reshape(F, 3), z[3 * F:3 * F + p], z[3 * F + p:].reshape(T, 9)).reshape(T, -1)

    r = res(z0)
    J = torch.autograd.functional.jacobian(res, z0)  # (T, m, N)
    Jf = J.reshape(-1, z0.numel())
    prior = torch.cat((torch.full((3 * F,), model.prior_std ** -2.0, dtype=torch.float64), model.eta_info,
                       torch.zeros(9 * T, dtype=torch.float64)))
    H = Jf.T @ Jf + torch.diag(prior)
    g = torch.einsum("tmn,tm->tn", J, r)  # every sample's score on every parameter
    Hinv = torch.linalg.inv(H)
    sl = slice(3 * F, 3 * F + p)
    return (Hinv @ (g.T @ g) @ Hinv)[sl, sl], Hinv[sl, sl]


def test_robust_wald_equals_the_dense_sandwich():
    _, _, fc = _fit(seed=11, T=40, excess=0.05)
    rob, mod = robust_wald(fc, 12)
    V_rob, V_mod = _dense_sandwich(fc)
    eta = fc.effects[0].flatten()
    t = torch.zeros(12, dtype=torch.float64)
    t[[0, 4, 8]] = 3 ** -0.5
    ev, U = torch.linalg.eigh(torch.eye(12, dtype=torch.float64) - torch.outer(t, t))
    Q = U[:, ev > 0.5]
    assert Q.shape[1] == COMMON_DF
    e = Q.T @ eta
    w = lambda V: float(e @ torch.linalg.solve(Q.T @ V @ Q, e))  # noqa: E731
    assert rob == pytest.approx(w(V_rob), rel=1e-5)
    assert mod == pytest.approx(w(V_mod), rel=1e-5)


def test_robust_wald_follows_chi2_with_stated_noise_and_resists_a_motion_dependent_excess():
    # six seeds each (fixed); χ²_11 has mean 11 and the mean of six has sd 1.9
    clean = [robust_wald(_fit(s, 1200)[2], 12) for s in range(6)]
    het = [robust_wald(_fit(s, 1200, excess=0.3)[2], 12) for s in range(6)]
    rob_c, mod_c = np.mean([c[0] for c in clean]), np.mean([c[1] for c in clean])
    assert 6.0 < rob_c < 16.0 and 6.0 < mod_c < 16.0
    assert all(abs(r - m) < 0.15 * m + 1.0 for r, m in clean)  # white noise: the two agree
    rob_h, mod_h = np.mean([h[0] for h in het]), np.mean([h[1] for h in het])
    assert 6.0 < rob_h < 18.0  # measured 12.7
    assert min(h[1] for h in het) > 300.0  # measured 802–7712: the excess read as a common gyro error

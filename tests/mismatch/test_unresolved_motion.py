"""unresolved_motion (accel_bayes/mismatch/unresolved.py): the exact low-rank marginal against a
dense Gaussian computation, and on the first-principles generator (experiments/clockgen) the
fitted scales against the generator's true unresolved jerk / angular acceleration on a short clock
case, and ~zero on its synchronised twin."""
from __future__ import annotations


import numpy as np
import pytest
import torch
from scipy.stats import multivariate_normal

from accel_bayes.mismatch.unresolved import gauss_logpdf, loadings, lowrank_terms, marginal_loglik



def test_lowrank_terms_equal_the_dense_gaussian_for_diagonal_masked_and_full_bases():
    g = np.random.default_rng(11)
    T, n, r, B = 6, 9, 3, 2
    y = g.normal(size=(T, n))
    U = g.normal(size=(T, n, r))
    s2 = g.uniform(0, 2, size=(T, r))
    s2[0] = 0.0
    v = g.uniform(0.2, 2, size=(T, n))
    w = (g.uniform(size=(T, n)) > 0.3).astype(float)
    A = g.normal(size=(B, n, n))
    cov = A @ A.transpose(0, 2, 1) + np.eye(n)
    lab = g.integers(0, B, size=T)
    tt = torch.as_tensor
    q, ld = lowrank_terms(tt(y * w), tt(U), tt(s2), v=tt(v), w=tt(w))
    got_diag = gauss_logpdf(q, ld, tt(w.sum(1))).numpy()
    q, ld = lowrank_terms(tt(y), tt(U), tt(s2), prec=torch.linalg.inv(tt(cov)), lab=tt(lab))
    got_full = gauss_logpdf(q, ld, n).numpy()
    for t in range(T):
        i = np.flatnonzero(w[t])
        C = np.diag(v[t]) + U[t] @ np.diag(s2[t]) @ U[t].T
        assert got_diag[t] == pytest.approx(multivariate_normal(np.zeros(len(i)), C[np.ix_(i, i)]).logpdf(y[t, i]), rel=1e-10)
        C = cov[lab[t]] + U[t] @ np.diag(s2[t]) @ U[t].T
        assert got_full[t] == pytest.approx(multivariate_normal(np.zeros(n), C).logpdf(y[t]), rel=1e-10)


def test_marginal_loglik_is_the_rank_three_gaussian_over_all_triads():
    """Per sample the 3K residuals are N(0, diag(v ⊗ 1₃) + s² (d dᵀ ⊗ I₃)) over the triads that enter."""
    g = np.random.default_rng(5)
    T, K = 5, 7
    y = g.normal(size=(T, K, 3))
    d = g.normal(scale=3e-4, size=(T, K))
    w = (g.uniform(size=(T, K)) > 0.2).astype(float)
    v = g.uniform(0.1, 1, size=(T, K))
    s2 = g.uniform(0, 5e6, size=T)
    got = marginal_loglik(*(torch.as_tensor(x) for x in (y * w[..., None], d * w, w, v, s2))).numpy()
    U = loadings(torch.as_tensor(d)).numpy()
    for t in range(T):
        i = np.flatnonzero(np.repeat(w[t], 3))
        C = np.diag(np.repeat(v[t], 3)) + s2[t] * U[t] @ U[t].T
        want = multivariate_normal(np.zeros(len(i)), C[np.ix_(i, i)]).logpdf(y[t].ravel()[i])
        assert got[t] == pytest.approx(want, rel=1e-10)


def _case_scales(kind, lateness=None):
    """Fit the physics model (clock-age mean + unresolved motion) to a 10 s clockgen case (seed 3,
    MIMU4444 board, 62.5 Hz, every generator effect on) with the clock case's true per-IMU
    lateness; returns (fitted scales per sensor (B,), true rms per axis per band, lateness)."""
    from experiments.clockgen import draw_case
    from experiments.clockgen.cases import motion_of

    from accel_bayes.mismatch import baseline_fit, prepare
    from accel_bayes.mismatch.budget import band_edges
    from accel_bayes.mismatch.generic import BandedWhite
    from accel_bayes.mismatch.heldout import _mean_coeff, centred, residuals_of
    from accel_bayes.physics.effects.base import output_rates

    rec, truth = draw_case(kind, 3, duration=10.0, f_host=62.5, board_name="mimu4444")
    prep = prepare(rec)
    fit, _ = baseline_fit(prep)
    res = residuals_of(prep, fit)
    t = prep.time.numpy()
    idx = np.searchsorted(truth["pose"]["time"], t)
    if lateness is None:
        # how late each IMU's sample is against its stamp: data age plus read skew and jitter
        lateness = truth["data_age"] + (truth["pose"]["time"][:, None] - truth["read_time"])
    d = centred(torch.as_tensor(lateness[idx]))
    # the true unresolved motion: the exact jerk / angular acceleration at the board's centre
    # less what the sampled outputs resolve (their finite-difference rate)
    mot, h = motion_of(truth), 1e-4
    cen = np.asarray(truth["position"]).mean(0, keepdims=True)
    (fp, wp), (fm, wm), (f0, w0) = (mot.specific_force(t + o, cen) for o in (h, -h, 0.0))
    ra, rg = output_rates(torch.as_tensor(t), torch.as_tensor(f0), torch.as_tensor(w0[:, None, :]))
    u = {"acc": (fp - fm)[:, 0] / (2 * h) - ra[:, 0].numpy(), "gyro": (wp - wm) / (2 * h) - rg[:, 0].numpy()}
    edges = band_edges(res.omega.numpy())
    lab = np.digitize(res.omega.numpy(), edges)
    out = {}
    for s in ("acc", "gyro"):
        ok = res.ok[s].numpy()
        y, dd, rate = res.y[s][ok], d[ok], res.rate[s][ok]
        c = _mean_coeff(y, rate, dd, torch.ones(len(y), dtype=torch.bool))
        m = BandedWhite.fit(y + c * dd[:, :, None] * rate, torch.as_tensor(lab[ok]), len(edges) + 1, d=dd)
        true = np.array([np.sqrt((u[s][lab == b] ** 2).mean() / 3) for b in range(len(edges) + 1)])
        out[s] = (m.s.numpy(), true)
    return out, lateness


@pytest.mark.slow
@pytest.mark.parametrize("sensor", [
    "acc",
    pytest.param("gyro", marks=pytest.mark.xfail(strict=True, reason=(
        "since the held-out residuals take the detector's board-rate regressor R_k ω̇ (heldout2), the "
        "gyro's fitted scale is 0.33–0.39× this truth, which is defined against the finite-difference "
        "output rate; against 'exact − fitted ω̇' it is 0.24–0.33×: not yet explained (issue #27)"))),
])
def test_fitted_scales_recover_clockgen_truth_and_vanish_on_the_twin(sensor):
    """Clock case: every band's fitted scale within a factor [0.8, 2.2] of the true rms (measured
    2026-11-27 on this case with the finite-difference regressor: 1.2–1.9× for acc, 1.6–1.9× for
    gyro).  Twin (same motion, errors and noise, every tick locked to the read): loaded with the
    clock case's lateness, every band's scale below 15 % of the clock case's."""
    clock, late = _case_scales("clock")
    twin, _ = _case_scales("twin", lateness=late)
    fitted, true = clock[sensor]
    assert np.all(fitted / true > 0.8) and np.all(fitted / true < 2.2), (sensor, fitted, true)
    assert np.all(twin[sensor][0] < 0.15 * fitted), (sensor, twin[sensor][0], fitted)


def test_unresolved_motion_term_budget_hook_and_finding():
    """The budget's predicted variance is s²_b d² per channel on both sensors; the finding carries
    jerk_rms / angular_acc_rms per band with imu and axis null (vocabulary 1.2); the term's
    log-likelihood is the sum of the two sensors' marginals."""
    from accel_bayes.mismatch.unresolved import UnresolvedMotion

    g = np.random.default_rng(2)
    T, K = 8, 4
    d = torch.as_tensor(g.normal(scale=3e-4, size=(T, K)))
    lab = torch.as_tensor(g.integers(0, 2, size=T))
    term = UnresolvedMotion(d, lab, [1.0], torch.tensor([300.0, 500.0], dtype=torch.float64),
                            torch.tensor([40.0, 90.0], dtype=torch.float64))
    va, vg = term.predicted_variance()
    np.testing.assert_allclose(va[:, :, 1].numpy(), (np.array([300.0, 500.0])[lab.numpy()][:, None] * d.numpy()) ** 2)
    np.testing.assert_allclose(vg[:, :, 2].numpy(), (np.array([40.0, 90.0])[lab.numpy()][:, None] * d.numpy()) ** 2)
    f = term.finding(evidence=12.5)
    assert (f["effect"], f["imu"], f["axis"]) == ("unresolved_motion", None, None)
    assert f["parameters"]["jerk_rms"] == [300.0, 500.0] and f["parameters"]["angular_acc_rms"] == [40.0, 90.0]
    ya, yg = (torch.as_tensor(g.normal(size=(T, K, 3))) for _ in range(2))
    w, v = torch.ones(T, K, dtype=torch.float64), torch.full((T, K), 0.5, dtype=torch.float64)
    want = (marginal_loglik(ya, d, w, v, torch.tensor([300.0, 500.0], dtype=torch.float64)[lab] ** 2)
            + marginal_loglik(yg, d, w, v, torch.tensor([40.0, 90.0], dtype=torch.float64)[lab] ** 2))
    np.testing.assert_allclose(term.loglik(ya, yg, w, v, v).numpy(), want.numpy())

"""Mismatch report vocabulary 1.1 (DESIGN §7.2): the ``gyro_nonlinearity`` effect found on
recordings of the independent generator ``experiments/_conceal.py`` (its own k2·ω² code), the
``refined.chi2_per_dof_stated`` key and the top-level residual ``budget`` — its numbers against
a direct numpy recomputation from the fits' residuals, b ≈ a on a concealed mean-effect case,
a ≈ 0 and b = 0 on a clean one, the noise/random-effect hook, and the JSON round trip."""
import json
import math

import numpy as np
import pytest

from accel_bayes.mismatch import detect, fit_model, make_effect, prepare, validate_report, baseline_fit
from accel_bayes.mismatch.budget import BANDS, residual_budget

from experiments import _conceal as C

# detect's quick settings (fewer twins and LOO draws than its defaults), at most two findings
BUDGET_DETECT = dict(n_twins=20, loo_draws=40, n_refit=3, max_findings=2)
T = 800
# seed 2 hides k2 = −6.4e-5 (rad/s)⁻¹ on IMU 3 x (peak k2·ω² ≈ 6 σ_g),
# seed 5 −7.4e-5 on IMU 4 x (≈ 2 σ_g at the peaks: the weakest of the three), seed 3 −1.9e-4 on
# IMU 6 z (≈ 16 σ_g)
SEEDS = (2, 5, 3)


def _case(effect, seed):
    return C.make_case("mimu8", effect, seed=seed, T=T)


@pytest.fixture(scope="module")
def reports():
    out = {}
    for seed in SEEDS:
        case = _case("gyro_nonlinearity", seed)
        out[seed] = (case, detect(case.recording, seed=0, **BUDGET_DETECT))
    return out


@pytest.fixture(scope="module")
def clean():
    case = _case("none", SEEDS[0])  # the exact clean twin of the first case
    return case, detect(case.recording, seed=0, **BUDGET_DETECT)


@pytest.mark.parametrize("seed", SEEDS)
def test_concealed_gyro_nonlinearity_is_named_with_imu_axis_and_k2(reports, seed):
    case, rep = reports[seed]
    tr, d = case.truth, rep.to_dict()
    assert d["mismatch_detected"]
    top = d["findings"][0]
    assert (top["effect"], top["imu"], top["axis"]) == ("gyro_nonlinearity", tr["imu"], tr["axis"])
    assert top["evidence"] > d["threshold"]
    k2, sd = top["parameters"]["k2"], top["std"]["k2"]
    assert 0 < sd < 0.2 * abs(tr["parameters"]["k2"])  # a real uncertainty, not a vacuous one
    assert abs(k2 - tr["parameters"]["k2"]) < 3 * sd  # 3 sigma
    assert "quadratically" in top["explanation"]
    # no other finding names a second mean effect on the recording (one concealed effect)
    assert [f["effect"] for f in d["findings"]].count("gyro_nonlinearity") == 1


def test_clean_twin_gets_no_gyro_nonlinearity_and_a_null_refined(clean):
    case, rep = clean
    d = rep.to_dict()
    assert "gyro_nonlinearity" not in [f["effect"] for f in d["findings"]]
    assert d["mismatch_detected"] is False and d["refined"] is None
    # budget still present: a ≈ 0 within its sampling noise (σ²·√(2/n) per row), b = 0
    rows = d["budget"]
    assert {r["sensor"] for r in rows} == {"acc", "gyro"} and len(rows) == 2 * (1 + 2 * len(BANDS))
    for r in rows:
        assert r["excess_var_explained"] == 0.0
        noise = r["stated_var"] * math.sqrt(2 / r["channel_samples"])
        assert abs(r["excess_var_observed"]) < 4 * noise, r


def _numpy_budget(prep, base, ref):
    """Independent recomputation of the budget rows from the fits' raw residuals and their motion-state
    Jacobians (numpy only; regimes by explicit percentile comparisons): r̃² = (P r)²/(1 − h)·σ², P and h
    the per-sample projection off the motion states in the stated-noise whitening (budget.restricted_sq)."""
    Tn, K = prep.T, prep.K
    x = base.x.numpy()
    speeds = {"|omega|": np.sqrt((x[:, 0:3] ** 2).sum(1)), "|omega_dot|": np.sqrt((x[:, 3:6] ** 2).sum(1))}
    sel = {"all": np.ones(Tn, bool)}
    for name, v in speeds.items():
        for lo, hi in ((0, 25), (25, 50), (50, 75), (75, 90), (90, 100)):
            a = -np.inf if lo == 0 else np.percentile(v, lo)
            b = np.inf if hi == 100 else np.percentile(v, hi)
            sel[f"{name} {lo}-{hi}%"] = (v >= a) & (v < b)

    def sq(fit):
        sig = np.stack((prep.sigma_acc.numpy(), prep.sigma_gyro.numpy()))[None, :, :, None]  # (1, 2, K, 1)
        r = np.stack((fit.res_acc.numpy(), fit.res_gyro.numpy()), 1) / sig  # (T, 2, K, 3), stated whitening
        vr = getattr(fit.lm.model, "var_ratio", None)
        back = np.ones((Tn, 2, K, 3)) if vr is None else np.sqrt(vr.numpy())
        back = back * np.stack((fit.acc_factor.numpy(), fit.gyro_factor.numpy()))[None, :, :, None]
        J = fit.linear().Jx.numpy() * back.reshape(Tn, 6 * K)[:, :, None]  # the fit's whitening → stated
        G = np.linalg.inv(np.einsum("tmi,tmj->tij", J, J))
        rv = r.reshape(Tn, 6 * K)
        pr = rv - np.einsum("tmi,tij,tnj,tn->tm", J, G, J, rv)
        h = np.einsum("tmi,tij,tmj->tm", J, G, J)
        z2 = (pr ** 2 / np.maximum(1 - h, 1e-3)).reshape(Tn, 2, K, 3) * sig ** 2
        m = np.stack((prep.m_acc.numpy(), prep.m_gyro.numpy()), 1)
        return z2[:, 0] * m[:, 0], z2[:, 1] * m[:, 1]

    sb, sr = sq(base), sq(ref)
    out = {}
    for j, sensor in enumerate(("acc", "gyro")):
        m = (prep.m_acc if j == 0 else prep.m_gyro).numpy() > 0
        s2 = np.broadcast_to(((prep.sigma_acc if j == 0 else prep.sigma_gyro).numpy() ** 2)[None, :, None], m.shape)
        for name, t in sel.items():
            mm = m & t[:, None, None]
            a = (sb[j][mm] - s2[mm]).mean()
            b = (sb[j][mm] - sr[j][mm]).mean()  # no variance effect in this model
            out[(sensor, name)] = (int(t.sum()), int(mm.sum()), a, b)
    return out


def test_budget_matches_a_numpy_recomputation_and_b_matches_a(reports):
    case, rep = reports[SEEDS[0]]
    d = rep.to_dict()
    ref = _numpy_budget(rep.prep, rep.baseline_fit, rep.refined_fit)
    assert len(d["budget"]) == len(ref) == 22
    for r in d["budget"]:
        n, nc, a, b = ref[(r["sensor"], r["regime"])]
        assert (r["samples"], r["channel_samples"]) == (n, nc), r
        assert r["excess_var_observed"] == pytest.approx(a, rel=1e-9, abs=1e-20)
        assert r["excess_var_explained"] == pytest.approx(b, rel=1e-9, abs=1e-20)
    # the gyro axis' k2·ω² is the misfit; the refined model explains it in every regime: a − b is
    # the refined residual's excess, zero up to its sampling noise σ²·√(2/n) (4 of them allowed)
    for r in d["budget"]:
        noise = r["stated_var"] * math.sqrt(2 / r["channel_samples"])
        assert abs(r["excess_var_observed"] - r["excess_var_explained"]) < 4 * noise, r
    g = {r["regime"]: r for r in d["budget"] if r["sensor"] == "gyro"}
    top = g["|omega| 90-100%"]
    assert top["excess_var_observed"] > 5 * top["stated_var"] * math.sqrt(2 / top["channel_samples"])  # a real excess
    assert top["excess_var_explained"] / top["excess_var_observed"] == pytest.approx(1, abs=0.25)
    assert g["all"]["excess_var_explained"] / g["all"]["excess_var_observed"] == pytest.approx(1, abs=0.25)
    # the excess grows with |ω| (ω² law): the top band carries more than the bottom one
    assert top["excess_var_observed"] > g["|omega| 0-25%"]["excess_var_observed"] + 0.1 * top["stated_var"]


def test_chi2_stated_and_json_round_trip(reports, tmp_path):
    case, rep = reports[SEEDS[0]]
    d = rep.to_dict()
    r = d["refined"]
    assert r["chi2_noise"] == "stated"  # no noise effect in the model
    assert r["chi2_per_dof_stated"] == r["chi2_per_dof"] == pytest.approx(rep.refined_fit.chi2_stated / rep.refined_fit.dof)
    assert r["chi2_per_dof_stated"] < d["baseline"]["chi2_per_dof"]
    rep.write(tmp_path, figures=False)
    back = json.loads((tmp_path / "report.json").read_text())
    validate_report(back)
    assert back["budget"] == json.loads(json.dumps(d["budget"]))
    assert back["refined"]["chi2_per_dof_stated"] == pytest.approx(r["chi2_per_dof_stated"], rel=1e-15)
    md = (tmp_path / "report.md").read_text()
    assert "## Residual budget" in md and "| regime | samples | a | a / σ² | b | b / a |" in md
    assert "\\|omega\\| 90-100%" in md  # regime names escaped inside the table
    bad = dict(back, budget=[{"sensor": "mag", "regime": "all", "samples": 1, "excess_var_observed": 0.0,
                              "excess_var_explained": 0.0}])
    with pytest.raises(ValueError):
        validate_report(bad)


def test_budget_noise_level_and_variance_hook():
    """Variance effects enter b as predicted variance: noise_level by (c² − 1)σ² (b ≈ a on a
    concealed noise_level case, its accelerometer rows), and any effect's
    ``predicted_variance(params, ctx)`` adds its mean exactly."""
    case = C.make_case("mimu8", "noise_level", seed=4, T=600)
    k = case.truth["imu"]
    prep = prepare(case.recording)
    base, _ = baseline_fit(prep)
    ref = fit_model(prep, [make_effect("noise_level", imu=k, sensor="acc")], init=base, laplace=False)
    rows = {(r["sensor"], r["regime"]): r for r in residual_budget(prep, base, ref)}
    a = rows[("acc", "all")]
    assert a["excess_var_observed"] > 0.05 * a["stated_var"]  # one IMU of 8 with 1.2–2 × the noise
    for (sensor, _), r in rows.items():
        noise = r["stated_var"] * math.sqrt(2 / r["channel_samples"])
        assert abs(r["excess_var_observed"] - r["excess_var_explained"]) < 4 * noise, r
    # the hook: a constant predicted variance v on IMU 2's gyro adds v·(3 of 24 channels) to b
    import torch

    v = 1e-6
    e = ref.effects[0]

    def predicted_variance(params, ctx):
        va = torch.zeros_like(ctx.acc)
        vg = torch.zeros_like(ctx.gyro)
        vg[:, 2] = v
        return va, vg

    e.predicted_variance = predicted_variance
    rows2 = {(r["sensor"], r["regime"]): r for r in residual_budget(prep, base, ref)}
    for key, r in rows2.items():
        add = v * 3 / 24 if key[0] == "gyro" else 0.0
        assert r["excess_var_explained"] == pytest.approx(rows[key]["excess_var_explained"] + add, rel=1e-9, abs=1e-15)


def test_model_jacobians_of_gyro_nonlinearity_match_finite_differences():
    """The augmented model's forward-mode Jacobian (mismatch/model.py: the effect pushed through
    ``torch.func.jvp`` with the context's closed-form tangents) against central differences of
    its own residual function, for k2 ≠ 0: ∂r/∂k2 and ∂r/∂ω (the effect's k2·ω² adds 2 k2 ω_a R
    to the gyro rows of its IMU)."""
    import torch

    case = C.make_case("mimu8", "gyro_nonlinearity", seed=2, T=120)
    prep = prepare(case.recording)
    e = make_effect("gyro_nonlinearity", imu=3, axis="x", parameters={"k2": 5e-3})
    fit = fit_model(prep, [e], max_iter=2, laplace=False)
    model, th, eta, x = fit.lm.model, fit.lm.theta, fit.lm.eta.clone(), fit.lm.x.clone()
    eta = eta + 5e-3  # well away from 0, so the ω-derivative of the effect is large
    r, Jx, _, Je = model.jacobians(th, eta, x)
    h = 1e-6
    fd = (model.residual(th, eta + h, x) - model.residual(th, eta - h, x)) / (2 * h)
    np.testing.assert_allclose(Je[..., 0].numpy(), fd.numpy(), rtol=1e-6, atol=1e-6)
    assert float(Je[:, 1, 3, 0].abs().max()) > 0 and float(Je[:, 1, [0, 1, 2, 4, 5, 6, 7]].abs().max()) == 0
    for j in range(3):  # ω components
        dx = torch.zeros_like(x)
        dx[:, j] = h
        fd = (model.residual(th, eta, x + dx) - model.residual(th, eta, x - dx)) / (2 * h)
        np.testing.assert_allclose(Jx[..., j].numpy(), fd.numpy(), rtol=1e-6, atol=1e-5)
    # the effect's share of ∂r/∂ω is there: without it the gyro row of IMU 3 axis x differs
    nominal = fit_model(prep, [], max_iter=1, laplace=False).lm.model
    _, Jx0, _, _ = nominal.jacobians(th, torch.zeros(0, dtype=torch.float64), x)
    assert float((Jx[:, 1, 3, 0, 0:3] - Jx0[:, 1, 3, 0, 0:3]).abs().max()) > 1e-3 * float(Jx0[:, 1, 3, 0, 0:3].abs().max())

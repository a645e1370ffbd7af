"""``calibrate(..., model=report)`` (issue #11 item 5): a mismatch report's random gyro effects in
the likelihood (:mod:`accel_bayes.model.report_terms`)."""
import copy
import json
import warnings

import numpy as np
import pytest
import torch

from experiments import _conceal as C
from experiments._reports import minimal_report, wander_calibration_case
from accel_bayes.errors import UserError  # noqa: E402
from accel_bayes.model.gyro_posterior import gyro_posterior  # noqa: E402
from accel_bayes.physics.effects import make_effect  # noqa: E402
from accel_bayes.pipelines.calibrate import calibrate  # noqa: E402
from accel_bayes.model.report_terms import fused_gyro_posterior, load_model  # noqa: E402

SHORT = dict(chains=1, draws=20, warmup=20, seed=0, progress=False)


def _report(rec, findings):
    """A minimal valid DESIGN §7.2 report of ``rec`` with ``findings`` (parameters as the detector writes them)."""
    return minimal_report(findings, rec, explanation="test finding")


@pytest.fixture(scope="module")
def wander_case():
    """mimu8 at 100 Hz with a concealed gyro timing wander (2 ms) on one IMU
    (:func:`experiments._reports.wander_calibration_case`): (recording, the wander's report, a clean report)."""
    rec, _, reports = wander_calibration_case()
    return rec, reports["found"], reports["clean"]


def test_fused_posterior_is_generalized_least_squares():
    """Against an independent per-sample GLS with numpy: stacked design [I; …; I], block-diagonal
    weights C_k⁻¹ with C_k = σ_k² I + (w²/12) ω̇ω̇ᵀ + v I on the gyros with a finding."""
    rng = np.random.default_rng(0)
    T, G = 7, 4
    t = np.arange(T) * 0.01
    y = rng.normal(0, 3.0, (T, G, 3))
    std = np.array([0.01, 0.02, 0.015, 0.03])
    labels = [0, 2, 5, 6]
    e1 = make_effect("timing_wander", imu=2, parameters={"width": 2e-3, "correlation": 0.8, "excess_noise_var": 0.04,
                                                          "sensor": "gyro"})
    e2 = make_effect("sampling_jitter", imu=6, parameters={"width": 5e-3})
    post, wdot = fused_gyro_posterior(torch.as_tensor(y), std, labels, t, [(2, e1), (6, e2)])
    w = std**-2
    mean0 = (y * w[None, :, None]).sum(1) / w.sum()
    wd = np.gradient(mean0, t, axis=0, edge_order=2)  # uniform steps, no gaps: one run
    np.testing.assert_allclose(wdot.numpy(), wd, rtol=1e-12, atol=1e-9)
    A = np.tile(np.eye(3), (G, 1))
    for i in range(T):
        blocks = [std[g] ** 2 * np.eye(3) for g in range(G)]
        blocks[1] = blocks[1] + (2e-3) ** 2 / 12 * np.outer(wd[i], wd[i]) + 0.04 * np.eye(3)
        blocks[3] = blocks[3] + (5e-3) ** 2 / 12 * np.outer(wd[i], wd[i])
        W = np.zeros((3 * G, 3 * G))
        for g, B in enumerate(blocks):
            W[3 * g:3 * g + 3, 3 * g:3 * g + 3] = np.linalg.inv(B)
        cov = np.linalg.inv(A.T @ W @ A)
        mean = cov @ A.T @ W @ y[i].reshape(-1)
        np.testing.assert_allclose(post.mean[i].numpy(), mean, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(post.cov[i].numpy(), cov, rtol=1e-10, atol=1e-16)


def test_fused_posterior_without_findings_is_the_calibrated_one():
    rng = np.random.default_rng(1)
    y = torch.as_tensor(rng.normal(0, 2.0, (9, 3, 3)))
    std = np.array([0.01, 0.02, 0.03])
    post, _ = fused_gyro_posterior(y, std, [0, 1, 2], np.arange(9) * 0.02, [])
    ref = gyro_posterior(y, torch.as_tensor(std), "calibrated")
    np.testing.assert_allclose(post.mean.numpy(), ref.mean.numpy(), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(post.cov.numpy(), ref.cov.numpy(), rtol=1e-12)


def test_model_brings_the_sandwich_ratio_to_one(wander_case):
    """The same pipeline with a report without findings (the "calibrated" gyro posterior) and with
    the wander: the sandwich-to-Laplace std ratio at the MAP drops from ≥ 2 to ≤ 1.3."""
    rec, found, clean = wander_case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r0 = calibrate(rec, model=clean, **SHORT)
        r1 = calibrate(rec, model=found, **SHORT)
    s0, s1 = r0.settings["model"]["sandwich"], r1.settings["model"]["sandwich"]
    assert s0["std_ratio_max"] > 2.0 and s0["kappa"] > 3.0
    assert s1["std_ratio_max"] < 1.3 and abs(s1["kappa"] - 1) < 0.2
    m = r1.settings["model"]
    assert [u["effect"] for u in m["used"]] == ["timing_wander"] and m["skipped"][0]["effect"] == "unexplained"
    assert r1.settings["gyro_method"] == "model" and len(m["sha256"]) == 64
    assert m["gyro_posterior"]["omega_shift_rms_rad_s"] > 0.05
    assert len(s1["std_ratio"]) == len(s1["coordinates"]) == 3 * (rec.K - 1)
    prov = r1.positions["provenance"]["settings"]["model"]
    assert prov["sha256"] == m["sha256"] and prov["sandwich"]["std_ratio_max"] == s1["std_ratio_max"]


def test_model_none_is_the_default_pipeline(wander_case):
    """model=None: no model record, the request of the run unchanged, the same draws as the explicit
    defaults (noise_inflation None resolves to True without a model)."""
    rec, _, _ = wander_case
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a = calibrate(rec, **SHORT)
        b = calibrate(rec, model=None, noise_inflation=True, **SHORT)
    assert "model" not in a.settings and a.settings["gyro_method"] == "sample_cov"
    np.testing.assert_array_equal(a.run.theta, b.run.theta)


def test_report_file_sha_and_bad_reports(wander_case, tmp_path):
    rec, found, _ = wander_case
    p = tmp_path / "report.json"
    p.write_text(json.dumps(found))
    import hashlib

    m = load_model(p)
    assert m.sha256 == hashlib.sha256(p.read_bytes()).hexdigest() and m.source == str(p)
    m.check_recording(rec)
    bad = copy.deepcopy(found)
    bad["details"]["recording"]["K"] = rec.K + 1
    with pytest.raises(UserError, match=r"details\.recording\.K"):
        calibrate(rec, model=bad, **SHORT)
    bad = copy.deepcopy(found)
    bad["details"]["recording"]["T_given"] = rec.T - 1
    with pytest.raises(UserError, match=r"details\.recording\.T_given"):
        load_model(bad).check_recording(rec)
    bad = copy.deepcopy(found)
    bad["schema"] = "accel_bayes.mismatch/0"
    with pytest.raises(UserError, match="schema"):
        load_model(bad)
    bad = copy.deepcopy(found)
    bad["findings"][0]["effect"] = "gyro_wobble"
    with pytest.raises(UserError, match="unknown effect"):
        load_model(bad)
    bad = copy.deepcopy(found)
    bad["findings"][0]["parameters"]["correlation"] = 1.5
    with pytest.raises(UserError, match=r"findings\[0\]"):
        load_model(bad)
    (tmp_path / "no.json").write_text("{not json")
    with pytest.raises(UserError, match="not JSON"):
        load_model(tmp_path / "no.json")
    with pytest.raises(UserError, match="cannot read"):
        load_model(tmp_path / "missing.json")
    with pytest.raises(UserError, match="gyro_method"):
        calibrate(rec, model=found, gyro_method="sample_cov", **SHORT)


def test_cli_model_refuses_a_report_of_another_recording(wander_case, tmp_path, capsys):
    from accel_bayes.cli import main
    from accel_bayes.data.io import write_recording

    rec, found, _ = wander_case
    path = tmp_path / "rec.nc"
    write_recording(rec, path)
    bad = copy.deepcopy(found)
    bad["details"]["recording"]["K"] = 3
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    rc = main(["calibrate", str(path), "--out", str(tmp_path / "out"), "--model", str(tmp_path / "bad.json"),
               "--quiet", "--no-plots", "--draws", "5", "--warmup", "5", "--chains", "1"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "details.recording.K" in err[0]


def test_noise_bins_on_a_given_covariate(wander_case):
    """fit_map_with_noise(covariate=|ω̄|) is the default rate binning; a wrong shape is refused."""
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.inference.noise_fit import fit_map_with_noise

    rec, _, _ = wander_case
    lik = RaoBlackwellLikelihood.from_recording(rec, num_draws=1, gyro_method="calibrated")
    nominal = torch.as_tensor(np.asarray(rec.nominal_position), dtype=torch.float64)
    kw = dict(reference=lik.reference, prior_mean=nominal, bins=3, max_rounds=2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, na = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, **kw)
        b, nb = fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std,
                                   covariate=lik.omega.mean.norm(dim=-1).numpy(), **kw)
    np.testing.assert_array_equal(na.bin_scale, nb.bin_scale)
    np.testing.assert_array_equal(np.asarray(a.theta), np.asarray(b.theta))
    with pytest.raises(UserError, match="covariate"):
        fit_map_with_noise(lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std, covariate=np.ones(3), **kw)


def test_sandwich_clusters_and_their_white_reference():
    """On a correctly specified simulation (stated noise, no effect, flat φ prior) every clustering of
    the sandwich, divided by its white-noise reference, is near 1; the per-sample reference is 1 by
    construction (J̃ lies in the range of P⊥); "sample" is the default and unchanged."""
    from accel_bayes.inference.map import fit_map
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.inference.noise_fit import sandwich_inflation

    rec = C.make_case("mimu8", "none", seed=2, T=1500, rate=100.0).recording
    lik = RaoBlackwellLikelihood.from_recording(rec, num_draws=1, gyro_method="calibrated")
    nominal = torch.as_tensor(np.asarray(rec.nominal_position), dtype=torch.float64)
    args = (lik.acc, lik.omega.mean, lik.omega.cov, lik.acc_noise_std)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        res = fit_map(*args, reference=lik.reference, prior_mean=nominal)
    d = sandwich_inflation(*args, res, reference=lik.reference, prior_mean=nominal)
    s = sandwich_inflation(*args, res, reference=lik.reference, prior_mean=nominal, cluster="sample")
    np.testing.assert_array_equal(d["std_ratio"], s["std_ratio"])
    np.testing.assert_allclose(s["std_ratio_white"], 1.0, atol=0.02)
    for unit in ("channel", "triad", "sample"):
        c = sandwich_inflation(*args, res, reference=lik.reference, prior_mean=nominal, cluster=unit, lags=0)
        assert 0.8 < np.median(c["std_ratio_relative"]) < 1.2, unit
        assert np.max(c["std_ratio_relative"]) < 1.4, unit
    with pytest.raises(UserError, match="cluster"):
        sandwich_inflation(*args, res, reference=lik.reference, prior_mean=nominal, cluster="imu")


def test_acc_blocks_of_the_report_are_integrated_out_or_fixed(wander_case):
    """A report with accelerometer blocks (``acc_scale``) on three triads: by default the calibration
    integrates every triad's deviation out (tolerance by type-II ML) and cuts the part they share
    (the draws moved by it, recorded); ``acc_blocks="fixed"`` inverts the blocks as exact; given
    tolerances are used as given.  The record says which (settings.model.acc_blocks)."""
    rec, _, _ = wander_case
    g = np.random.default_rng(5)
    blocks = [("acc_scale", k, {"scale": (0.004 * g.standard_normal((3, 3))).tolist(),
                                "bias": (0.02 * g.standard_normal(3)).tolist()}) for k in (1, 4, 6)]
    rep = _report(rec, blocks)
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for ab in ("fit", "fixed", (0.01, 0.1)):
            out[str(ab)] = calibrate(rec, model=rep, intrinsics="none", acc_blocks=ab, **SHORT)
    fit = out["fit"].settings["model"]["acc_blocks"]
    assert fit["tau_from"] == "type-II ML" and 0 < fit["tau_matrix"] < 1 and fit["triads"] == rec.K
    assert fit["report_blocks"] == [1, 4, 6]
    assert len(fit["common_shift_mean_m"]) == 3 * (rec.K - 1) and fit["common_shift_std_median_m"] >= 0
    assert out["fixed"].settings["model"]["acc_blocks"]["how"].startswith("fixed")
    # the sandwich is the integrated target's (its Laplace std is the block step's), the one before kept
    m = out["fit"].settings["model"]
    lap = np.sqrt(np.diagonal(np.asarray(out["fit"].map_result.laplace_cov)))
    np.testing.assert_allclose(m["sandwich"]["laplace_std_m"], lap, rtol=1e-12)
    assert m["sandwich_before_blocks"]["laplace_std_m"] != m["sandwich"]["laplace_std_m"]
    r = np.asarray(m["sandwich"]["std_ratio"])
    assert np.isfinite(r).all() and (r > 0).all()
    # integrating the errors widens the Laplace std (this wander case: ratios 6.8 → 3.8 median, unmodelled wander)
    assert np.median(m["sandwich"]["laplace_std_m"]) > np.median(m["sandwich_before_blocks"]["laplace_std_m"])
    assert "sandwich_before_blocks" not in out["fixed"].settings["model"]
    from accel_bayes.cli.calibrate import format_table  # the CLI says what was integrated, and which sandwich

    fit_lines = [ln for ln in format_table(out["fit"]).splitlines() if ln.startswith("model: accelerometer blocks")]
    assert len(fit_lines) == 1 and "IMU(s) 1, 4, 6 integrated out" in fit_lines[0] and "type-II ML" in fit_lines[0]
    assert any(ln.startswith("model: accelerometer blocks fixed") for ln in format_table(out["fixed"]).splitlines())
    # with the noise estimated (the real-data path) the flat likelihood is handed over as tempered by κ = 1
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        est = calibrate(rec, model=rep, intrinsics="none", noise="estimate", **SHORT)
    m = est.settings["model"]
    assert m["sandwich"]["tempering_applied"] == 1.0 and np.isfinite(m["sandwich"]["std_ratio_max"])
    assert "sandwich_before_blocks" in m
    given = out["(0.01, 0.1)"].settings["model"]["acc_blocks"]
    assert given["tau_from"] == "given" and given["tau_matrix"] == 0.01 and given["tau_bias_m_s2"] == 0.1
    mean = lambda r: np.array([e["mean"] for e in r.positions["imus"]])  # noqa: E731
    assert np.abs(mean(out["fit"]) - mean(out["fixed"])).max() > 0  # the term changes the posterior
    # the same seed gives the same draws (the cut's draws are seeded too)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        again = calibrate(rec, model=rep, intrinsics="none", **SHORT)
    np.testing.assert_array_equal(mean(again), mean(out["fit"]))


def test_accelerometer_blocks_are_used_only_on_the_outputs_they_were_estimated_on(wander_case):
    """``details.acc_linear_stage.outputs`` says which outputs a report's accelerometer blocks act on: blocks of
    the rest-calibrated outputs are kept after the rests' intrinsics and dropped without them, blocks of the
    outputs as recorded the other way round (a report without the key: as recorded, as every report before
    the key); the reason is recorded; any other value is refused naming the field."""
    from accel_bayes.errors import UserError
    from accel_bayes.model.report_terms import load_model

    rec, _, _ = wander_case
    blocks = [("acc_scale", 1, {"scale": (0.004 * np.eye(3)).tolist(), "bias": [0.02, 0.0, -0.01]})]
    for outputs, rest, kept in (("rest-calibrated", True, True), ("rest-calibrated", False, False),
                                ("as recorded", True, False), ("as recorded", False, True), (None, True, False)):
        rep = _report(rec, blocks)
        if outputs is not None:
            rep["details"]["acc_linear_stage"] = {"result": "test", "outputs": outputs}
        m = load_model(rep)
        assert m.acc_outputs == (outputs or "as recorded")
        m.match_acc_outputs(rest)
        assert bool(m.acc_linear) is kept, (outputs, rest)
        if not kept:
            why = [s["why"] for s in m.skipped if s["effect"] == "acc_scale"]
            assert why and (outputs or "as recorded") in why[0]
    rep = _report(rec, blocks)
    rep["details"]["acc_linear_stage"] = {"outputs": "corrected"}
    with pytest.raises(UserError, match="details.acc_linear_stage.outputs"):
        load_model(rep)

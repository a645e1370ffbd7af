"""Model-mismatch discovery end to end (accel_bayes.mismatch): clean recordings stay clean, a
recording with one effect of clear magnitude gets that effect ranked first at the right IMU/axis,
the report keeps the DESIGN §7.2 contract, the CLI's exit codes; plus independent checks of the
machinery (score statistic vs refitted likelihood ratio, linearised PPC twins vs an actual refit,
the noise-level evidence)."""
import json
import math

import numpy as np
import pytest
import torch

from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.cli import main
from accel_bayes.data.io import write_recording
from accel_bayes.mismatch import SCHEMA, detect, make_effect, validate_report
from accel_bayes.mismatch.screens import candidate_effects, noise_evidence, screen
from accel_bayes.mismatch import Prepared, baseline_fit, fit_model, prepare
from accel_bayes.simulate import simulate

DEG = math.pi / 180
KW = dict(T=400, rate=200.0, acc_noise_std=0.02, gyro_noise_std=0.1 * DEG)
FAST = dict(n_twins=20, loo_draws=40, n_refit=3)


def _sim(seed, effects=()):
    return simulate(mimu4444_8(), "smooth", seed=seed, effects=list(effects), **KW)


@pytest.fixture(scope="module")
def clean_rec():
    return _sim(21).recording


@pytest.fixture(scope="module")
def clean_report(clean_rec):
    return detect(clean_rec, seed=0, **FAST)


DISP = [0.0, 2e-4, 8e-4]  # m, sensor frame of IMU 6, axis z


@pytest.fixture(scope="module")
def disp_report():
    eff = make_effect("axis_displacement", imu=6, axis="z", parameters={"displacement": DISP})
    return detect(_sim(22, [eff]).recording, seed=0, **FAST)


def test_clean_recording_has_no_mismatch(clean_report):
    d = clean_report.to_dict()
    assert d["mismatch_detected"] is False
    assert d["findings"] == [] and d["refined"] is None
    assert clean_report.refined is None and not clean_report.mismatch_detected
    assert 0.95 < d["baseline"]["chi2_per_dof"] < 1.05
    # the threshold is the documented Bonferroni rule
    from scipy.stats import chi2

    m = d["details"]["n_candidates"]
    assert d["threshold"] == pytest.approx(chi2.isf(0.01 / m, 3), rel=1e-9)
    assert clean_report.location.ppc["chi2"]["p_value"] > 0.01


def test_one_effect_is_ranked_first_at_its_imu_and_axis(disp_report):
    d = disp_report.to_dict()
    assert d["mismatch_detected"]
    top = d["findings"][0]
    assert (top["effect"], top["imu"], top["axis"]) == ("axis_displacement", 6, "z")
    assert top["evidence"] > d["threshold"]
    est = np.array(top["parameters"]["displacement"])
    std = np.array(top["std"]["displacement"])
    assert np.all(np.abs(est - np.array(DISP)) < 5 * std + 1e-5)
    r = d["refined"]
    assert r["effects"][0] == "axis_displacement"
    assert r["loglik"] > d["baseline"]["loglik"] + top["evidence"] / 2 - 1e-6
    assert abs(r["chi2_per_dof"] - 1) < 0.05 < d["baseline"]["chi2_per_dof"] - 1 + 0.05
    assert r["elpd_loo"] > r["elpd_loo_baseline"]
    # the located excess sat at IMU 6's accelerometer z axis
    worst = max(disp_report.location.cells, key=lambda c: c["excess_z"])
    assert (worst["imu"], worst["sensor"], worst["axis"]) == (6, "acc", "z")


def test_report_contract_and_files(clean_report, disp_report, tmp_path):
    for rep, name in ((clean_report, "clean"), (disp_report, "disp")):
        paths = rep.write(tmp_path / name, figures=name == "disp")
        doc = json.loads((tmp_path / name / "report.json").read_text())
        validate_report(doc)
        assert doc["schema"] == SCHEMA
        assert set(doc) >= {"schema", "mismatch_detected", "threshold", "baseline", "findings", "refined"}
        assert set(doc["baseline"]) >= {"loglik", "chi2_per_dof", "dof"}
        for f in doc["findings"]:
            assert set(f) >= {"effect", "imu", "axis", "evidence", "parameters", "where", "explanation"}
            assert set(f["where"]) >= {"regime", "time_s"}
        evid = [f["evidence"] for f in doc["findings"] if f["effect"] != "unexplained"]
        assert evid == sorted(evid, reverse=True)
        assert (tmp_path / name / "report.md").read_text().startswith("# Model-mismatch report")
        # the preparation is the calibration's, and the report says so (issue #10 items 3, 5)
        prep = doc["details"]["recording"]["preparation"]
        assert prep["intrinsics"]["applied"] is False and "no static segments" in prep["intrinsics"]["why"]
        sel = prep["selection"]
        assert sel["kept"] == doc["details"]["recording"]["T"] == sel["recording"] - sum(sel["dropped"].values())
        assert sel["min_rotation"] == 0.5 and set(sel["dropped"]) == {"static", "clipped", "flagged", "non_finite", "slow", "user"}
        md = (tmp_path / name / "report.md").read_text().splitlines()
        assert sum(line.startswith("Preparation (as `calibrate`): intrinsics not applied") for line in md) == 1
    assert paths["heatmap"].exists() and paths["regimes"].exists() and paths["before_after"].exists()
    assert "![" in (tmp_path / "disp" / "report.md").read_text()
    bad = dict(json.loads((tmp_path / "clean" / "report.json").read_text()), mismatch_detected=True)
    with pytest.raises(ValueError):
        validate_report(bad)


@pytest.fixture(scope="module")
def gyro_case():
    eff = make_effect("gyro_bias", imu=4, axis="x", parameters={"bias": 0.2 * DEG})
    prep = prepare(_sim(23, [eff]).recording)
    base, _ = baseline_fit(prep)
    return prep, base


def test_score_statistic_matches_refitted_likelihood_ratio(gyro_case):
    """The screening statistic (efficient score test at the baseline) against the independent
    likelihood ratio of two LM optima: equal to first order."""
    prep, base = gyro_case
    cands = [c for c in candidate_effects(prep, ["gyro_bias"])]
    sc = screen(prep, base, cands)
    top = sc[0]
    assert (top.effect.imu, top.effect.axis) == (4, "x")
    fit = fit_model(prep, [make_effect("gyro_bias", imu=4, axis="x")], init=base)
    lr = 2 * (fit.loglik - base.loglik)
    assert lr > 50
    assert top.statistic == pytest.approx(lr, rel=0.02)
    assert fit.effects[0].params["bias"].item() == pytest.approx(0.2 * DEG, abs=4 * fit.effects[0].std["bias"].item())


def test_linearised_twins_match_an_actual_refit(gyro_case):
    """PPC twins are residuals after a one-step linear refit; compare with refitting a twin
    recording by the full LM."""
    prep, base = gyro_case
    lin = base.linear()
    T, K = prep.T, prep.K
    g = torch.Generator().manual_seed(7)
    e = torch.randn(T, 6 * K, generator=g, dtype=torch.float64)
    ea = e[:, :3 * K].reshape(T, K, 3) * prep.sigma_acc[None, :, None]
    eg = e[:, 3 * K:].reshape(T, K, 3) * prep.sigma_gyro[None, :, None]
    twin = Prepared(**{**prep.__dict__, "y_acc": base.pred_acc + ea, "y_gyro": base.pred_gyro + eg})
    refit = fit_model(twin, (), init=base)
    r_full = torch.cat(((refit.res_acc / prep.sigma_acc[None, :, None]).reshape(T, -1),
                        (refit.res_gyro / prep.sigma_gyro[None, :, None]).reshape(T, -1)), -1)
    r_lin = lin.project(e.unsqueeze(0))[0]
    assert float((r_full - r_lin).norm() / r_full.norm()) < 0.02
    assert float(((r_full - e).norm() / e.norm())) > 0.1  # the refit really absorbs part of the noise


def test_noise_level_evidence(clean_rec):
    eff = make_effect("noise_level", imu=4, sensor="acc", parameters={"factor": 1.5})
    prep = prepare(_sim(24, [eff]).recording)
    base, _ = baseline_fit(prep)
    ev, fac, n = noise_evidence(prep, base, make_effect("noise_level", imu=4, sensor="acc"))
    assert n == 3 * KW["T"] and ev > 100 and fac > 1.25  # the screen: a one-step, downward-biased estimate
    ev_other, fac_other, _ = noise_evidence(prep, base, make_effect("noise_level", imu=2, sensor="acc"))
    assert ev_other < 15 and fac_other == pytest.approx(1.0, abs=0.08)
    # the refit re-weights IMU 4 and re-estimates the factor until it is consistent
    e = make_effect("noise_level", imu=4, sensor="acc")
    fit = fit_model(prep, [e], init=base)
    sd = 1.5 / math.sqrt(2 * n)
    assert float(e.params["factor"]) == pytest.approx(1.5, abs=4 * sd)
    assert float(fit.acc_factor[4]) == float(e.params["factor"]) and float(fit.acc_factor[3]) == 1.0
    assert noise_evidence(prep, fit, e)[0] > 100
    assert fit.chi2_per_dof_model < fit.chi2_per_dof


def test_unexplained_mismatch_is_located(clean_rec):
    """A disturbance outside the vocabulary (a 25 Hz vibration burst on IMU 2's accelerometer x
    between 1.0 s and 1.5 s) with only acc_bias as candidate: reported as unexplained, there."""
    rec = clean_rec.copy()
    t = rec.time
    burst = (t >= 1.0) & (t < 1.5)
    rec.acc[:, 2, 0] += 0.15 * np.sin(2 * np.pi * 25 * t) * burst
    rep = detect(rec, effects=["acc_bias"], seed=0, refine=False, **FAST)
    d = rep.to_dict()
    assert d["mismatch_detected"] and d["refined"] is None
    u = [f for f in d["findings"] if f["effect"] == "unexplained"]
    assert u, d["findings"]
    f = u[0]
    assert (f["imu"], f["axis"], f["sensor"]) == (2, "x", "acc")
    ts = f["where"]["time_s"]
    assert ts is not None and ts[0] < 1.5 and ts[1] > 1.0


def test_cli_exit_codes(clean_rec, tmp_path, capsys):
    path = tmp_path / "rec.nc"
    write_recording(clean_rec, path)
    assert main(["mismatch", str(tmp_path / "missing.nc"), "--out", str(tmp_path / "o0")]) == 2
    assert main(["mismatch", str(path), "--out", str(tmp_path / "o1"), "--effects", "acc_wobble"]) == 2
    with pytest.raises(SystemExit) as exc:  # refused by the option's type, at parse time
        main(["mismatch", str(path), "--out", str(tmp_path / "o2"), "--alpha", "1.5"])
    assert exc.value.code == 2
    (tmp_path / "afile").write_text("x")
    assert main(["mismatch", str(path), "--out", str(tmp_path / "afile")]) == 2
    err = capsys.readouterr().err
    assert "acc_wobble" in err and "alpha" in err
    rc = main(["mismatch", str(path), "--out", str(tmp_path / "ok"), "--effects", "acc_bias,gyro_bias",
               "--twins", "10", "--no-figures", "--seed", "3"])
    assert rc == 0
    doc = json.loads((tmp_path / "ok" / "report.json").read_text())
    validate_report(doc)
    assert doc["mismatch_detected"] is False
    assert "no mismatch detected" in capsys.readouterr().out


def test_log_tail_probability_is_finite_and_accurate():
    """Ranking uses log10 P(χ²_df > x); SciPy's logsf underflows past x ≈ 1400 (all huge
    evidences would tie).  The asymptotic branch must agree with SciPy where both work."""
    from scipy.stats import chi2

    from accel_bayes.mismatch.locate import log10_chi2_sf as _log10_sf

    for df in (1, 3, 20):
        for x in (600.0, 900.0, 1200.0):
            assert _log10_sf(x, df) == pytest.approx(chi2.logsf(x, df) / math.log(10), rel=1e-6)
        vals = [_log10_sf(x, df) for x in (2e3, 2e4, 2e5)]
        assert all(math.isfinite(v) for v in vals) and vals[0] > vals[1] > vals[2]
    assert _log10_sf(5e4, 1) < _log10_sf(5e4, 3)  # more parameters, less support for the same evidence


def test_heldout_fit_with_fixed_effects(gyro_case, clean_rec):
    """Held-out transfer (effect parameters fixed, positions and motion re-fitted): at the refitted
    estimate it reproduces the refitted log-likelihood; the estimate raises the log-likelihood of
    an independent recording with the same effect, its negative lowers it; a fixed noise factor
    agrees with the closed form at the nominal optimum (a lower bound, the re-weighted fit can
    only gain a little)."""
    from accel_bayes.mismatch.transfer import heldout_fit

    prep, base = gyro_case
    fit = fit_model(prep, [make_effect("gyro_bias", imu=4, axis="x")], init=base)
    same = heldout_fit(prep, fit.effects, base=base)
    assert same["difference"] == pytest.approx(fit.loglik - base.loglik, rel=1e-6)
    assert fit.effects[0].params["bias"].item() != 0  # the input effect is not modified
    other = prepare(_sim(24, [make_effect("gyro_bias", imu=4, axis="x", parameters={"bias": 0.2 * DEG})]).recording)
    base2, _ = baseline_fit(other)
    h = heldout_fit(other, fit.effects, base=base2)
    assert h["difference"] > 50 and h["chi2_per_dof_fixed"] < h["chi2_per_dof_nominal"]
    neg = fit.effects[0].copy().set_params({"bias": -fit.effects[0].params["bias"]})
    assert heldout_fit(other, [neg], base=base2)["difference"] < -50
    # noise factor f on IMU 2's accelerometer of a clean recording: Δ = −n log f − ½ (1/f² − 1) Σ r²/σ²
    # at the nominal optimum
    pc = prepare(clean_rec)
    bc, _ = baseline_fit(pc)
    f = 1.3
    nz = make_effect("noise_level", imu=2, sensor="acc", parameters={"factor": f})
    hn = heldout_fit(pc, [nz], base=bc)
    r2 = float(((bc.res_acc[:, 2] / pc.sigma_acc[2]) ** 2 * pc.m_acc[:, 2]).sum())
    n = float(pc.m_acc[:, 2].sum())
    closed = -n * math.log(f) - 0.5 * (1 / f ** 2 - 1) * r2
    # re-weighting lets each sample's motion state move: the expected gain over the closed form is
    # ½ (1 − 1/f²)² Σ h (h the leverage of those rows) to second order; allow twice that
    h = bc.linear().h.reshape(pc.T, 2, pc.K, 3)[:, 0, 2]
    gain = 0.5 * (1 - 1 / f ** 2) ** 2 * float(h.sum())
    assert closed - 1e-6 <= hn["difference"] <= closed + 2 * gain
    assert hn["difference"] - closed == pytest.approx(gain, rel=0.5)
    assert heldout_fit(pc, [make_effect("unexplained", imu=1)], base=bc)["skipped"]


def test_regressor_on_one_imu_context_equals_full_context(gyro_case):
    """The score test's regressors are computed on a one-IMU sub-context (IMU-separability);
    check against differencing the full-context perturbation for one candidate of every class."""
    from accel_bayes.mismatch.screens import _regressor

    prep, base = gyro_case
    ctx = base.ctx
    seen = set()
    for c in candidate_effects(prep):
        if c.kind != "mean" or c.name in seen or c.imu != 5:
            continue
        seen.add(c.name)
        D = _regressor(c, ctx, 5)
        v0, sc = c.flatten(c.null_params()), c.prior_scales()
        for j in range(c.df):
            h = 1e-3 * (float(sc[j]) if math.isfinite(float(sc[j])) else 1.0)
            vp, vm = v0.clone(), v0.clone()
            vp[j] += h
            vm[j] -= h
            (ap, gp), (am, gm) = c.perturbation(c.unflatten(vp), ctx), c.perturbation(c.unflatten(vm), ctx)
            ref = torch.cat(((ap - am)[:, 5], (gp - gm)[:, 5]), -1) / (2 * h)
            assert torch.allclose(D[..., j], ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()) + 1e-300)
    assert len(seen) >= 9


# ------------------------------------------------------------------ reference IMU, clipping, ranking

def test_gyro_misalignment_at_the_reference_imu_is_named_first():
    """IMU 0 is the reference (origin, position fixed).  A 0.5 % cross-axis coupling of its gyro z
    axis to the x-axis rate is found and ranked first *as* gyro_misalignment at IMU 0, z ← x (reported
    under the DESIGN §7.2 name gyro_scale, the scale/misalignment error, with from_axis), with
    its coupling recovered — not as a mounting rotation of IMU 0, the nearest effect without it
    (a rotation would also turn gyro x and the accelerometer, which the data contradict)."""
    eff = make_effect("gyro_misalignment", imu=0, axis="z", from_axis="x", parameters={"coupling": 0.005})
    rec = _sim(25, [eff]).recording
    assert rec.reference_imu == 0
    d = detect(rec, seed=0, max_findings=1, **FAST).to_dict()
    top = d["findings"][0]
    assert (top["effect"], top["imu"], top["axis"], top["parameters"]["from_axis"]) == ("gyro_scale", 0, "z", "x")
    assert top["evidence"] > d["threshold"]
    assert abs(top["parameters"]["scale"] - 0.005) < 5 * top["std"]["coupling"] + 1e-5


def test_axis_displacement_at_the_reference_imu_is_identifiable():
    """A displaced x sensing element of the reference IMU (1.5 mm along x) reads ω×(ω×d) + ω̇×d on
    its x axis only.  Shifting the whole reference triad is a shift of the origin (absorbed by
    the other IMUs' free positions), but one axis' displacement is not: the score test keeps the
    candidate (non-singular efficient information) and ranks it first among all mean candidates."""
    eff = make_effect("axis_displacement", imu=0, axis="x", parameters={"displacement": [1.5e-3, 0.0, 0.0]})
    prep = prepare(_sim(26, [eff]).recording)
    base, _ = baseline_fit(prep)
    sc = [s for s in screen(prep, base, candidate_effects(prep)) if s.effect.kind == "mean"]
    ref = [s for s in sc if s.effect.imu == 0 and s.effect.name == "axis_displacement"]
    assert len(ref) == 3 and all(s.identifiable for s in ref)
    top = max(sc, key=lambda s: s.statistic)
    assert top.effect.label() == "axis_displacement[imu=0,axis=x]"
    assert top.estimate["displacement"][0].item() == pytest.approx(1.5e-3, rel=0.3)


def test_prepare_drops_flagged_clipped_samples(clean_rec):
    """Samples the recording flags as clipped are censored, not measurements: prepare() drops them
    (as the calibration's preprocess does) unless asked not to."""
    rec = clean_rec.copy()
    flags = np.zeros((len(rec.time), rec.K), dtype=bool)
    flags[10:30, 3] = True
    flags[50, 6] = True
    rec.gyro_clipped = flags
    p = prepare(rec, min_rotation=0)  # the clip test alone (no rests in this simulation)
    assert p.T == len(rec.time) - 21 and p.n_dropped_clipped == 21
    np.testing.assert_array_equal(p.time.numpy(), rec.time[~flags.any(1)])
    assert prepare(rec, drop_clipped=False, min_rotation=0).T == len(rec.time)
    # by default the calibration's whole selection: the same samples as preprocess keeps
    from accel_bayes.prep.preprocess import preprocess

    p = prepare(rec)
    np.testing.assert_array_equal(p.time.numpy(), rec.time[preprocess(rec).keep])
    assert p.preparation["selection"]["dropped"]["clipped"] == 21 == p.n_dropped_clipped


def test_excess_cells_rank_by_evidence_when_p_values_underflow(clean_rec):
    """Two located excesses far beyond SciPy's logsf range (statistics ≫ 1400): the larger one
    (IMU 5 gyro z) must rank first even though IMU 0's acc x comes first in enumeration order —
    with p-values underflowing to −inf a stable sort would report IMU 0 acc x whatever the data."""
    from accel_bayes.mismatch.locate import excess_cells

    rec = clean_rec.copy()
    t = rec.time
    rec.acc[:, 0, 0] += 0.2 * np.sin(2 * np.pi * 3 * t)
    rec.gyro[:, 5, 2] += 0.05 * np.sin(2 * np.pi * 2 * t)
    prep = prepare(rec)
    base, _ = baseline_fit(prep)
    tests = excess_cells(prep, base)
    assert all(math.isfinite(d["log10_p"]) for d in tests)
    assert [d["log10_p"] for d in tests] == sorted(d["log10_p"] for d in tests)
    by_cell = {(d["imu"], d["sensor"], d["axis"]): d["statistic"] for d in tests if d["scheme"] == "|omega|"}
    assert by_cell[(0, "acc", "x")] > 1e4 and by_cell[(5, "gyro", "z")] > by_cell[(0, "acc", "x")]
    assert (tests[0]["imu"], tests[0]["sensor"], tests[0]["axis"]) == (5, "gyro", "z")


def test_alternatives_are_the_candidates_with_akaike_weight_above_five_percent():
    """alternatives(): relative likelihood exp(((e_alt − 2 df_alt) − (e_best − 2 df_best)) / 2)
    computed by hand for three rivals of a 1-df finding with robust evidence 100."""
    from accel_bayes.mismatch.choose import ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD, alternatives

    def res(name, axis, ev, **kw):
        return {"effect": make_effect(name, imu=2, axis=axis, **kw), "evidence": ev + 1.0, "evidence_robust": ev}

    best = res("acc_scale", "x", 100.0)
    close = res("acc_nonlinearity", "x", 98.0)          # Δ = 2 → exp(−1) = 0.368
    far = res("acc_bias", "x", 93.0)                    # Δ = 7 → exp(−3.5) = 0.030 < 0.05
    wide = res("triad_orientation", None, 103.5)        # 3 df: Δ = −3.5 + 4 = 0.5 → exp(−0.25)
    out = alternatives(best, [best, close, far, wide])
    assert ALTERNATIVE_MIN_RELATIVE_LIKELIHOOD == 0.05
    assert [a["effect"] for a in out] == ["triad_orientation", "acc_nonlinearity"]
    assert out[0]["relative_likelihood"] == pytest.approx(math.exp(-0.25))
    assert out[1]["relative_likelihood"] == pytest.approx(math.exp(-1.0))
    assert out[1]["evidence"] == 99.0 and out[1]["imu"] == 2 and out[1]["axis"] == "x"


def _recording_with_rests(K=4, n_orient=12, n=60, dyn=40, sigma=0.04, sigma_g=0.003):
    """Raw outputs a = T⁻¹ g u + b + noise in n_orient rests (labelled), between dynamic
    stretches of random outputs (some slow, some clipped-free fast)."""
    from accel_bayes.data.recording import Recording

    g0 = 9.80665
    rng = np.random.default_rng(11)
    b = rng.normal(0, 0.3, (K, 3))
    Tm = np.zeros((K, 3, 3))
    for k in range(K):
        Tm[k] = np.diag(1 + rng.normal(0, 0.01, 3))
        Tm[k][np.tril_indices(3, -1)] = rng.normal(0, 0.005, 3)
    dirs = rng.normal(size=(n_orient, K, 3))
    dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
    Tinv = np.linalg.inv(Tm)
    acc, gyro, seg = [], [], []
    for s in range(n_orient):
        raw = np.einsum("kij,kj->ki", Tinv, g0 * dirs[s]) + b
        acc += [rng.normal(0, 20, (dyn, K, 3)), raw + sigma * rng.normal(size=(n, K, 3))]
        w = rng.normal(0, 1, (dyn, 1, 3)) * rng.uniform(0, 3, (dyn, 1, 1))  # one ω for the rigid board
        gyro += [w + sigma_g * rng.normal(size=(dyn, K, 3)), sigma_g * rng.normal(size=(n, K, 3))]
        seg += ["dynamic"] * dyn + ["static"] * n
    acc = np.concatenate(acc)
    pos = np.array([[0, 0, 0], [0.02, 0, 0], [0, 0.02, 0], [0, 0, 0.02]], dtype=float)[:K]
    return Recording(time=np.arange(acc.shape[0]) / 100.0, acc=acc, gyro=np.concatenate(gyro),
                     nominal_position=pos, acc_noise_std=np.full(K, sigma), gyro_noise_std=np.full(K, sigma_g),
                     segment=np.array(seg), description="rests")


def test_mismatch_prepares_a_recording_with_rests_as_calibrate_does():
    """On a recording with rests, prepare() applies the intrinsics calibrate estimates and keeps
    exactly calibrate's samples (issue #10: one prepared object)."""
    from accel_bayes.pipelines.calibrate import DEFAULTS
    from accel_bayes.prep.preprocess import preprocess
    rec = _recording_with_rests()
    pre = preprocess(rec, intrinsics=DEFAULTS["intrinsics"], drop_static=DEFAULTS["drop_static"],
                     drop_clipped=DEFAULTS["drop_clipped"], min_rotation=DEFAULTS["min_rotation"])
    assert pre.intrinsics is not None and pre.selection.dropped["static"] > 0
    p = prepare(rec)
    assert p.preparation["intrinsics"]["applied"] is True
    np.testing.assert_array_equal(p.selection.keep, pre.selection.keep)
    np.testing.assert_array_equal(p.rec.acc, pre.recording.acc[pre.keep])  # corrected, selected
    np.testing.assert_array_equal(p.time.numpy(), rec.time[pre.keep])


def test_corrected_recording_of_the_whole_prepared_recording(disp_report):
    """posterior=True reruns calibrate on the whole prepared recording (rests included, so the
    calibration keeps its protocol): only the fitted samples are corrected."""
    from accel_bayes.mismatch.compare import corrected_recording

    prep, fit = disp_report.prep, disp_report.refined_fit
    assert fit is not None and any(e.kind == "mean" for e in fit.effects)
    idx = prep.selection.index
    a = corrected_recording(prep.rec, fit)
    b = corrected_recording(prep.source, fit, index=idx)
    assert b.T == prep.source.T and a.T == prep.T == len(idx)
    np.testing.assert_allclose(b.acc[idx], a.acc, rtol=0, atol=1e-12)
    np.testing.assert_allclose(b.gyro[idx], a.gyro, rtol=0, atol=1e-12)
    assert not np.array_equal(a.acc, prep.rec.acc)  # something was corrected
    drop = ~prep.selection.keep
    np.testing.assert_array_equal(b.acc[drop], prep.source.acc[drop])


def test_acc_stage_runs_after_the_rests_intrinsics_and_says_on_which_outputs():
    """``acc_linear=True`` on a recording whose rests calibrate the triads: the stage runs on the
    rest-calibrated outputs (what the rests leave; before 2026-11-29 it was skipped there) and the report
    says so (``details.acc_linear_stage.outputs``), which ``calibrate --model`` matches against its own
    preparation (tests/model/test_calibrate_model.py)."""
    from accel_bayes.mismatch import DetectOptions, detect

    rep = detect(_recording_with_rests(n_orient=10, n=40, dyn=20), DetectOptions(seed=0, acc_linear=True,
                                                                                 effects=("acc_linear",))).to_dict()
    st = rep["details"]["acc_linear_stage"]
    assert st["outputs"] == "rest-calibrated"
    assert not str(st["result"]).startswith("not run")


def test_report_says_when_the_rests_leave_the_triads_rotation_unestimated():
    """report.md names the opt-in accelerometer stage when the rests calibrated the triads and it did not run;
    not when it ran, nor when there were no rests (tests/mismatch/test_detect.py's clean report)."""
    from accel_bayes.mismatch import DetectOptions, detect

    rec = _recording_with_rests(n_orient=10, n=40, dyn=20)
    hint = "Accelerometer linear stage not run"
    off = detect(rec, DetectOptions(seed=0, effects=("acc_linear",)))
    on = detect(rec, DetectOptions(seed=0, acc_linear=True, effects=("acc_linear",)))
    assert off.to_dict()["details"]["recording"]["preparation"]["intrinsics"]["applied"] is True
    assert sum(line.startswith(hint) for line in off.markdown().splitlines()) == 1
    assert hint not in on.markdown()

"""``calibrate --model`` with a report's ``sampling_clock`` and ``unresolved_motion`` findings (issue #30
Deliver 2): the per-sample unresolved-motion covariance in the chains' likelihood and the matching
angular-acceleration term in the gyro posterior (:mod:`accel_bayes.pipelines.calibrate_model`)."""
import copy
import hashlib
import json
import warnings

import numpy as np
import pytest
import torch

from experiments import _conceal as C
from accel_bayes.errors import UserError
from accel_bayes.model.gyro_posterior import gyro_posterior_timing
from accel_bayes.model.likelihood_percov import PerSampleCovLikelihood
from accel_bayes.model.report_terms import clock_corrected, fused_gyro_posterior, load_model, unresolved_terms
from accel_bayes.physics.effects import make_effect
from accel_bayes.pipelines.calibrate import calibrate

SHORT = dict(chains=1, draws=20, warmup=20, seed=0, progress=False)


def _clock(imu, beat, phase, delay=-1.5e-4):
    return ("sampling_clock", imu, {"internal_rate_hz": 1000.0 + beat, "beat_hz": beat, "phase": phase,
                                    "drift_hz_per_s": 0.0, "age_rms_s": 2.5e-4,
                                    "filter_delay_acc_minus_gyro_s": delay})


def _report(rec, findings):
    rows = [{"effect": name, "imu": imu, "axis": None, "evidence": 100.0, "parameters": dict(params),
             "where": {"regime": "all", "time_s": None}, "explanation": "test finding"}
            for name, imu, params in findings]
    return {"schema": "accel_bayes.mismatch/1", "mismatch_detected": True, "threshold": 20.0,
            "baseline": {"loglik": 0.0, "chi2_per_dof": 1.0, "dof": 1},
            "refined": {"effects": [r["effect"] for r in rows], "loglik": 0.0, "chi2_per_dof": 1.0},
            "findings": rows, "details": {"recording": {"K": int(rec.K), "T_given": int(rec.T), "T": int(rec.T)}}}


UNRESOLVED = ("unresolved_motion", None, {"omega_edges": [3.0, 6.0], "jerk_rms": [100.0, 500.0, 2000.0],
                                          "angular_acc_rms": [20.0, 50.0, 100.0]})


@pytest.fixture(scope="module")
def case():
    """mimu8 at 100 Hz, 800 samples (no clock in the data: the test is of the wiring, not the physics),
    and a report with clocks on three IMUs and the unresolved motion's band scales."""
    rec = C.make_case("mimu8", "timing_wander", seed=4, T=800, rate=100.0, magnitude=1e-3, sigma_a=0.02).recording
    clocks = [_clock(1, 0.8, 0.1), _clock(3, -2.3, 0.6), _clock(6, 1.2, 0.35, delay=None)]
    return rec, _report(rec, clocks + [UNRESOLVED]), _report(rec, clocks)


def test_fused_posterior_with_angular_acceleration_is_the_dense_gls():
    """Against numpy on the stacked 3G × 3G covariance blockdiag(C_k) + s² (d dᵀ) ⊗ I₃ (d the centred
    ages), one gyro with a timing finding; without findings it is gyro_posterior_timing."""
    rng = np.random.default_rng(2)
    T, G = 6, 4
    t = np.arange(T) * 0.01
    y = rng.normal(0, 3.0, (T, G, 3))
    std = np.array([0.01, 0.02, 0.015, 0.03])
    age = rng.uniform(0, 1e-3, (T, G))
    s = rng.uniform(50, 200, T)
    e = make_effect("sampling_jitter", imu=5, parameters={"width": 4e-3})
    post, wdot = fused_gyro_posterior(torch.as_tensor(y), std, [0, 2, 5, 6], t, [(5, e)], age=age, angular_acc_std=s)
    W = wdot.numpy()
    for i in range(T):
        C_ = np.zeros((3 * G, 3 * G))
        for g in range(G):
            C_[3 * g:3 * g + 3, 3 * g:3 * g + 3] = std[g] ** 2 * np.eye(3)
        C_[6:9, 6:9] += (4e-3 ** 2 / 12) * np.outer(W[i], W[i])
        d = age[i] - age[i].mean()
        C_ += s[i] ** 2 * np.kron(np.outer(d, d), np.eye(3))
        X = np.tile(np.eye(3), (G, 1))
        Ci = np.linalg.inv(C_)
        P = np.linalg.inv(X.T @ Ci @ X)
        np.testing.assert_allclose(post.cov[i].numpy(), P, rtol=1e-9)
        np.testing.assert_allclose(post.mean[i].numpy(), P @ X.T @ Ci @ y[i].reshape(-1), rtol=1e-9, atol=1e-12)
    plain, _ = fused_gyro_posterior(torch.as_tensor(y), std, [0, 2, 5, 6], t, [], age=age, angular_acc_std=s)
    ref = gyro_posterior_timing(torch.as_tensor(y), torch.as_tensor(std), torch.as_tensor(age), torch.as_tensor(s))
    np.testing.assert_allclose(plain.mean.numpy(), ref.mean.numpy(), rtol=1e-10, atol=1e-13)
    np.testing.assert_allclose(plain.cov.numpy(), ref.cov.numpy(), rtol=1e-10)
    with pytest.raises(UserError, match="age, angular_acc_std"):
        fused_gyro_posterior(torch.as_tensor(y), std, [0, 2, 5, 6], t, [], age=age)


def test_clocks_and_unresolved_motion_are_used_and_listed(case):
    """Used with the unresolved motion (each with how); without it the clocks are skipped with the reason."""
    rec, rep, rep_clocks = case
    m = load_model(rep)
    assert m.unresolved and [u["effect"] for u in m.used] == ["sampling_clock"] * 3 + ["unresolved_motion"]
    assert all(u["how"] for u in m.used) and not m.skipped
    m2 = load_model(rep_clocks)
    assert not m2.unresolved and not m2.used
    assert [s["effect"] for s in m2.skipped] == ["sampling_clock"] * 3
    assert all("unresolved_motion" in s["why"] for s in m2.skipped)


def test_clock_mean_effect_is_taken_off():
    """Outputs read late by a sawtooth age (y(t − age), a smooth motion, two runs with a gap): the
    correction y + age·ẏ removes the age·ẏ error but for the rate's own error where the age jumps
    (the read outputs' differences see the jump: a few % of ẏ at those samples)."""
    t = np.r_[np.arange(200), np.arange(260, 500)] / 62.5
    clock = make_effect("sampling_clock", imu=0, parameters=dict(_clock(0, 2.3, 0.4)[2]))
    age = clock.age(torch.as_tensor(t)).numpy()
    f = lambda tt: np.stack([np.sin(3 * tt), np.cos(2 * tt), tt ** 2], -1) * 40.0  # noqa: E731
    true = f(t)[:, None]
    read = f(t - age)[:, None]
    acc, gyro = clock_corrected(read, read / 10, t, age[:, None], age[:, None])
    rms = lambda e: float(np.sqrt(np.mean(e ** 2)))  # noqa: E731
    before, after = rms(read - true), rms(acc.numpy() - true)
    assert before > 0.1 and after < 0.05 * before and np.abs(acc.numpy() - true).max() < 0.1 * np.abs(read - true).max()
    np.testing.assert_allclose(gyro.numpy(), acc.numpy() / 10, rtol=1e-12)


def test_unidentified_filter_delay_is_no_difference(case):
    """The detector writes an unidentified acc − gyro filter delay as null (clockgen reports): read as
    0 — acc age = gyro age on that IMU — not a traceback."""
    rec, rep, _ = case
    t = np.asarray(rec.time)
    terms = unresolved_terms(rep, t, list(range(8)), list(range(8)), np.full(len(t), 4.0))
    np.testing.assert_array_equal(terms.age_acc[:, 6].numpy(), terms.age_gyro[:, 6].numpy())
    np.testing.assert_allclose((terms.age_acc[:, 1] - terms.age_gyro[:, 1]).numpy(), -1.5e-4, rtol=1e-12)
    assert terms.parameters["omega_edges"] == [3.0, 6.0]


@pytest.mark.parametrize("instant, angjerk", [(False, None), (True, None), (False, False)],
                         ids=["default", "instant_error", "no_angular_jerk"])
def test_calibrate_uses_the_per_sample_likelihood(case, monkeypatch, instant, angjerk):
    """The chains' likelihood is the per-sample one (the scales fitted per report band, untempered),
    provenance records the sha256, what was used and both sandwiches; tempering is refused.  The
    triads' instant-error term only when asked (``instant_error``), named as skipped otherwise; the
    board's angular jerk by default, named as skipped when switched off (``angular_jerk=False``)."""
    import accel_bayes.pipelines.calibrate as cal

    rec, rep, _ = case
    seen = []
    real = cal._chains_step
    monkeypatch.setattr(cal, "_chains_step", lambda lik, pri, draws, *a, **k: (seen.append((lik, draws)),
                                                                               real(lik, pri, draws, *a, **k))[1])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        r = calibrate(rec, model=rep, instant_error=instant, **({} if angjerk is None else {"angular_jerk": angjerk}),
                      **SHORT)
    lik, draws = seen[0]
    assert isinstance(lik, PerSampleCovLikelihood) and getattr(lik, "kappa", 1.0) == 1.0
    m = r.settings["model"]
    u = m["unresolved_motion"]
    # the chains are centred on this likelihood's own mode (on the flat MAP they did not mix on exp_1: R-hat 1.9)
    np.testing.assert_allclose(draws.theta.numpy(), np.asarray(u["mode_positions_m"])[1:], rtol=1e-12)
    assert sum(u["band_samples"]) == r.settings["T"] and len(u["jerk_rms_fitted_m_s3"]) == 3
    assert u["jerk_rms_report_m_s3"] == [100.0, 500.0, 2000.0]
    if instant:
        # the triads' own instant error on their output rates is in the chains' likelihood, e by type-II ML
        assert lik.W is not None and lik.rate.shape == (lik.T, lik.A, 3) and u["instant_error"] == "used"
        assert float(lik.instant_std) == u["instant_error_rms_fitted_s"] and 0 <= u["instant_error_rms_fitted_s"] < 1e-2
        assert u["triad_rate_rms_m_s3"] > 0 and np.isfinite(u["instant_error_gain_nats"])
    else:
        assert lik.rate is None and u["instant_error_rms_fitted_s"] is None
        assert u["instant_error"].startswith("skipped: not asked")
    # the board's angular jerk (default on): loaded by the nominal lever arms, its scale per band fitted;
    # switched off it is left out and named as skipped
    if angjerk is None:
        assert lik.loading_rot is not None and u["angular_jerk"] == "used"
        np.testing.assert_allclose(lik.lever.numpy(), np.asarray(rec.nominal_position)[list(lik.imu_labels)])
        assert len(u["angular_jerk_rms_fitted_rad_s3"]) == 3 and np.isfinite(u["angular_jerk_gain_nats"])
    else:
        assert lik.loading_rot is None and u["angular_jerk"].startswith("skipped: switched off")
    assert m["gyro_posterior"]["clock_mean_correction_rms"]["acc_m_s2"] > 0
    # IMUs 0, 2, 4, 5, 7 have no clock in the report: their random age is in the chains' likelihood,
    # listed in the record and said in one line of the table
    from accel_bayes.cli.calibrate import format_table

    assert [x["imu"] for x in u["unclocked"]] == [0, 2, 4, 5, 7]
    assert (lik.age_var > 0).tolist() == [k in (0, 2, 4, 5, 7) for k in lik.imu_labels]
    assert sum("IMU(s) 0, 2, 4, 5, 7 without a sampling clock" in line for line in format_table(r).splitlines()) == 1
    for key in ("sandwich", "sandwich_flat"):
        assert len(m[key]["std_ratio"]) == 3 * (rec.K - 1) and np.isfinite(m[key]["std_ratio"]).all()
    prov = r.positions["provenance"]["settings"]["model"]
    assert prov["sha256"] == m["sha256"] == load_model(rep).sha256 and len(m["sha256"]) == 64
    assert "unresolved_motion" in [x["effect"] for x in prov["used"]]
    with pytest.raises(UserError, match="noise_inflation"):
        calibrate(rec, model=rep, noise_inflation=True, **SHORT)


def test_cli_calibrate_model_writes_the_provenance(case, tmp_path):
    """``accel-bayes calibrate REC --model report.json`` end to end: exit 0, positions.json names the
    report's file sha256 and the per-sample covariance it used."""
    from accel_bayes.cli import main
    from accel_bayes.data.io import write_recording

    rec, rep, _ = case
    write_recording(rec, tmp_path / "rec.nc")
    (tmp_path / "report.json").write_text(json.dumps(rep))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rc = main(["calibrate", str(tmp_path / "rec.nc"), "--out", str(tmp_path / "out"), "--model",
                   str(tmp_path / "report.json"), "--quiet", "--no-plots", "--draws", "20", "--warmup", "20",
                   "--chains", "1"])
    doc = json.loads((tmp_path / "out" / "positions.json").read_text())
    # 20 draws cannot converge: the set is written and marked (DESIGN §7.5 status 4), not refused
    assert rc == 4 and doc["diagnostics"]["converged"] is False
    m = doc["provenance"]["settings"]["model"]
    assert m["sha256"] == hashlib.sha256((tmp_path / "report.json").read_bytes()).hexdigest()
    assert [u["effect"] for u in m["used"]][-1] == "unresolved_motion" and "unresolved_motion" in m
    assert m["sandwich"]["std_ratio_max"] > 0 and m["sandwich_flat"]["std_ratio_max"] > 0


@pytest.mark.slow
def test_cli_with_the_detectors_own_report_on_a_concealed_clock_recording(tmp_path):
    """The loop end to end on a concealed clock recording (experiments/clockgen, plate4, 30 s at
    62.5 Hz): ``mismatch`` writes the report, ``calibrate --model`` reads its sampling_clock and
    unresolved_motion findings through the per-sample likelihood."""
    from accel_bayes.cli import main
    from accel_bayes.data.io import write_recording
    from experiments.clockgen import draw_case

    rec, _ = draw_case("clock", 5, duration=30.0, board_name="plate4", f_host=62.5)
    write_recording(rec, tmp_path / "rec.nc")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert main(["mismatch", str(tmp_path / "rec.nc"), "--out", str(tmp_path / "mm")]) == 0
        rep = json.loads((tmp_path / "mm" / "report.json").read_text())
        assert {"sampling_clock", "unresolved_motion"} <= {f["effect"] for f in rep["findings"]}
        rc = main(["calibrate", str(tmp_path / "rec.nc"), "--out", str(tmp_path / "out"), "--model",
                   str(tmp_path / "mm" / "report.json"), "--quiet", "--no-plots", "--draws", "50", "--warmup", "50",
                   "--chains", "1"])
    doc = json.loads((tmp_path / "out" / "positions.json").read_text())
    assert rc == (0 if doc["diagnostics"]["converged"] else 4)  # 50 draws: written, marked if unconverged
    m = doc["provenance"]["settings"]["model"]
    assert "unresolved_motion" in m and {"sampling_clock", "unresolved_motion"} <= {u["effect"] for u in m["used"]}


def test_instant_error_option_needs_a_model_and_enters_the_fingerprint():
    """``instant_error`` without a model is refused naming the option; with one it changes what a
    resumed checkpoint must match, and leaves a model run without it unchanged."""
    from accel_bayes.errors import UserError
    from accel_bayes.pipelines.calibrate_options import CalibrateOptions

    with pytest.raises(UserError, match="^instant_error: .*needs a model"):
        CalibrateOptions(instant_error=True)
    on = CalibrateOptions(model="r.json", instant_error=True).fingerprint("rec", model_sha256="m")["options"]
    off = CalibrateOptions(model="r.json").fingerprint("rec", model_sha256="m")["options"]
    assert on["instant_error"] is True and "instant_error" not in off
    assert {k: v for k, v in on.items() if k != "instant_error"} == off

"""The concealed-clock calibration study (issue #30 item 4, ``experiments/percov_conceal.py``): what
it hands the pipeline and how it scores.  The study itself runs from the script (minutes a case)."""
import numpy as np
import pytest

import experiments.clockgen as cg
from experiments import percov_conceal as pc


def test_known_acc_intrinsics_recover_the_error_free_outputs():
    # the same case with and without the generator's linear errors (noise and rounding off, so that
    # only M and b differ): inverting M, b on the accelerometers must give the error-free outputs
    kw = dict(duration=1.0, noise=False, quantised=False, gyro_linear=False)
    rec, truth = cg.draw_case("clock", 4, **kw)
    ref, _ = cg.draw_case("clock", 4, errors=False, **kw)
    before = np.abs(np.asarray(rec.acc) - np.asarray(ref.acc)).max()
    fixed = pc.known_acc_intrinsics(rec, truth)
    assert before > 0.01  # m/s²: the errors are there to undo
    np.testing.assert_allclose(fixed.acc, ref.acc, atol=1e-9)
    np.testing.assert_array_equal(fixed.gyro, rec.gyro)  # gyro errors are left to the detector


def test_mounted_moves_the_nominal_positions_not_the_truth():
    rec, truth = cg.draw_case("clock", 2, duration=1.0, noise=False)
    moved, pos = pc.mounted(rec, truth, 5e-4, 2)
    np.testing.assert_array_equal(pos, np.asarray(truth["position"]))
    d = np.asarray(moved.nominal_position) - pos
    assert 1e-4 < d.std() < 1e-3  # m, a seeded draw at 0.5 mm
    again, _ = pc.mounted(rec, truth, 5e-4, 2)
    np.testing.assert_array_equal(again.nominal_position, moved.nominal_position)
    np.testing.assert_array_equal(rec.nominal_position, pos)  # the input recording is not changed


def test_score_is_error_over_std_relative_to_the_reference():
    pos = np.array([[0.01, 0.0, 0.0], [0.03, 0.0, 0.0], [0.01, 0.02, 0.0]])
    doc = {"reference_imu": 0, "imus": [
        {"imu": 0, "mean": [0, 0, 0], "std": [0, 0, 0]},
        {"imu": 1, "mean": [0.0201, 0.0, 0.0], "std": [1e-4, 1e-4, 1e-4]},
        {"imu": 2, "mean": [0.0, 0.0196, 0.0002], "std": [1e-4, 2e-4, 1e-4]}]}
    s = pc.score(doc, pos)
    np.testing.assert_allclose(s["z"], [1.0, 0.0, 0.0, 0.0, -2.0, 2.0], atol=1e-9)
    assert s["coordinates"][4] == "r[2, y]"


def _raw(truth, mean, std):
    """A cached calibration as run_case writes it: positions document and score."""
    doc = {"reference_imu": 0, "imus": [{"imu": k, "mean": list(m), "std": list(sd)}
                                        for k, (m, sd) in enumerate(zip(mean, std))]}
    return {"positions": doc, "score": pc.score(doc, np.asarray(truth)), "seconds": 1.0, "T_used": 100,
            "noise": "estimate", "kappa_applied": 1.0,
            "settings": {"chains": 1, "draws": 1, "warmup": 1, "seed": 0}}


def test_variant_record_states_the_geometry_scale():
    truth = np.array([[0.0, 0, 0], [0.04, 0, 0], [0, 0.03, 0.01]])
    sd = np.full((3, 3), 1e-4)
    assert pc.variant_record(_raw(truth, truth, sd))["scale"] == pytest.approx(1.0)
    assert pc.variant_record(_raw(truth, -0.7 * truth, sd))["scale"] == pytest.approx(-0.7)


def test_summary_flags_the_band():
    truth = np.array([[0.0, 0, 0], [0.04, 0, 0], [0, 0.03, 0.01]])
    sd = np.full((3, 3), 1e-4)

    def case(seed, dz):
        c = {"seed": seed, "board": "plate4", "f_host": 100.0, "duration": 20.0, "mount_std_m": 5e-4,
             "detect_seconds": 1.0, "findings": [], "acc_intrinsics": "known"}
        for v in pc.VARIANTS:
            c[v] = pc.variant_record(_raw(truth, truth + 1e-4 * np.asarray(dz), sd))
        return c
    good = [case(0, [[0, 0, 0], [1.0, -1.0, 0.5], [-0.8, 1.2, 1.1]])]
    summ = pc.summarise(good)
    assert 0.8 <= summ["with"]["all"]["rms"] <= 1.25 and summ["with"]["all"]["beyond4"] == 0
    bad = [case(0, [[0, 0, 0], [1.0, -5.0, 0.5], [0.0, 0.0, 0.0]])]
    text = pc.markdown(bad, pc.summarise(bad), "cmd", 2, 1.0)
    assert "**Met with the model, jerk only: NO**" in text and "**partial**" in text
    assert "with the angular jerk (the default): **NO**" in text


@pytest.mark.slow
def test_one_case_runs_end_to_end(tmp_path):
    import argparse

    args = argparse.Namespace(out=tmp_path, duration=8.0, mount_std=5e-4, acc_intrinsics="known", chains=2,
                              draws=100, warmup=100, seed=0)
    c = pc.run_case(1, args)
    assert c["with"]["score"]["z"] and c["without"]["score"]["z"]
    assert pc.cached(1, tmp_path) is not None


def test_probe_table_lists_every_piece():
    rows = [{"pieces": k, "scale": 1.0, "z_rms": 1.0, "noise_std": [0.03, 0.05], "noise": "estimate"} for k in pc.PROBE]
    text = "\n".join(pc.probe_markdown([{"seed": 1, "board": "plate4", "f_host": 250.0, "rows": rows,
                                         "chains_warmup_draws": list(pc.PROBE_CHAINS)}]))
    assert all(k in text for k in pc.PROBE) and "0.030–0.050" in text
    assert pc.probe_markdown([]) == []


@pytest.mark.parametrize("variant, model, angular_jerk, inflation", [
    ("with", True, False, None), ("with_angjerk", True, True, None),
    ("untempered", False, False, False), ("without", False, False, None)])
def test_each_variant_calls_calibrate_with_its_own_settings(monkeypatch, tmp_path, variant, model, angular_jerk,
                                                            inflation):
    """"without" is the default pipeline with no report: until 2026-11-28 a prefix test ("with…") gave it
    the report, so a rerun from an empty cache scored the model twice and never the default."""
    import accel_bayes.pipelines.calibrate as cal

    seen = {}

    class _Stop(Exception):
        pass

    def fake(rec, **kw):
        seen.update(kw)
        raise _Stop

    monkeypatch.setattr(cal, "calibrate", fake)
    report = tmp_path / "report.json"
    with pytest.raises(_Stop):
        pc.run_variant(object(), variant, report, chains=1, draws=1, warmup=1, seed=0)
    assert (seen["model"] == report) is model and (seen["model"] is None) is (not model)
    assert seen["angular_jerk"] is angular_jerk
    assert seen["noise_inflation"] is inflation

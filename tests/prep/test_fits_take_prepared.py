"""Every fit takes one PreparedRecording (issue #26 item 1): the likelihood, the MAP, motion
estimation, self-calibration and the mismatch fits accept the record ``prepare_recording`` makes,
refuse the sample-selection keywords they took before 0.2.0 with a TypeError that says where they
went, and leave the IMU/reference/geometry/noise checks to ``prepare_recording``, which runs them
once per fit and names the field."""
import dataclasses

import numpy as np
import pytest
import torch

import accel_bayes.prep.prepared as prepared_mod
from accel_bayes.errors import UserError
from accel_bayes.inference.map import fit_map_recording
from accel_bayes.inference.motion_estimate import estimate_motion
from accel_bayes.mismatch.prepared import prepare as mismatch_prepare
from accel_bayes.model.likelihood import RaoBlackwellLikelihood
from accel_bayes.physics.arrays import mimu4444_8
from accel_bayes.pipelines.selfcal import prepare as selfcal_prepare
from accel_bayes.prep.prepared import PreparedRecording, prepare_recording
from accel_bayes.simulate import simulate


@pytest.fixture(scope="module")
def sim():
    return simulate(mimu4444_8(), "iid", T=120, rate=100.0, seed=5, position_error_std=1e-4)


def _calibration(sim):
    return (sim.true_positions - sim.true_positions[0]).numpy()


def test_every_fit_accepts_a_prepared_recording(sim):
    rec = sim.recording
    p = prepare_recording(rec, select=np.arange(rec.T) % 3 != 1)
    assert 0 < p.T < rec.T
    lik = RaoBlackwellLikelihood.from_recording(p, num_draws=2)
    assert lik.prepared is p and lik.selection is p.selection and np.array_equal(lik.sample_index, p.sample_index)
    res = fit_map_recording(p, max_iter=3, on_divergence="ignore")
    assert res.selection is p.selection and res.imu_labels == p.imu_labels and res.omega.shape == (p.T, 3)
    ds = estimate_motion(p, _calibration(sim), draws=0)
    np.testing.assert_array_equal(ds["time"].values, p.time)  # one estimate per kept sample
    mm = mismatch_prepare(p)
    assert mm.prepared is p and mm.T == p.T and mm.selection is p.selection
    ps = prepare_recording(rec, select="all", gyro="ignored", reference=3, reference_field="--fixed")
    inp = selfcal_prepare(ps)
    assert inp.prepared is ps and inp.fixed_label == 3 and inp.acc.shape == (rec.T, rec.K, 3)
    np.testing.assert_array_equal(inp.acc, np.asarray(rec.acc))  # sensor frame, every sample


def test_a_recording_is_prepared_with_the_defaults(sim):
    """A plain Recording is the same fit as prepare_recording(rec) with the fit's defaults."""
    rec = sim.recording
    a = RaoBlackwellLikelihood.from_recording(rec, num_draws=2)
    b = RaoBlackwellLikelihood.from_recording(prepare_recording(rec), num_draws=2)
    assert torch.equal(a.acc, b.acc) and torch.equal(a.omega.cov, b.omega.cov)
    np.testing.assert_array_equal(a.sample_index, b.sample_index)


@pytest.mark.parametrize("keyword, value", [("select", "rotation"), ("min_rotation", 0.5), ("drop_clipped", True),
                                            ("selection", None), ("acc_imus", [0, 1, 2])])
def test_the_old_selection_keywords_are_a_type_error(sim, keyword, value):
    rec = sim.recording
    fits = (lambda **kw: RaoBlackwellLikelihood.from_recording(rec, num_draws=1, **kw),
            lambda **kw: fit_map_recording(rec, max_iter=1, **kw),
            lambda **kw: estimate_motion(rec, _calibration(sim), draws=0, **kw))
    for fit in fits:
        with pytest.raises(TypeError, match=f"{keyword}= removed in 0.2.0.*prepare_recording"):
            fit(**{keyword: value})


def test_motion_intrinsics_keyword_is_a_type_error(sim):
    with pytest.raises(TypeError, match="intrinsics= removed in 0.2.0"):
        estimate_motion(sim.recording, _calibration(sim), intrinsics=None)


def test_the_checks_run_once_in_prepare_recording_and_name_the_field(sim, monkeypatch):
    rec = sim.recording
    calls = []
    real = prepared_mod.check_triad_geometry
    monkeypatch.setattr(prepared_mod, "check_triad_geometry", lambda *a, **k: calls.append(1) or real(*a, **k))
    fits = {"likelihood": lambda r: RaoBlackwellLikelihood.from_recording(r, num_draws=1),
            "map": lambda r: fit_map_recording(r, max_iter=1, on_divergence="ignore"),
            "motion": lambda r: estimate_motion(r, _calibration(sim), draws=0),
            "selfcal": lambda r: selfcal_prepare(r),
            "mismatch": lambda r: mismatch_prepare(r, intrinsics="none")}
    for name, fit in fits.items():
        calls.clear()
        fit(rec)
        assert len(calls) == 1, f"{name}: the geometry check ran {len(calls)} times"
    bad = dataclasses.replace(rec, acc_noise_std=np.where(np.arange(rec.K) == 4, 0.0, rec.acc_noise_std))
    for name, fit in fits.items():
        if name == "motion":
            continue  # motion estimation may be given its own noise (stated_noise=False)
        with pytest.raises(UserError, match=r"^acc_noise_std: expected > 0 for every IMU used \[0, 1, 2, 3, 4"):
            fit(bad)
    with pytest.raises(UserError, match="^--fixed: IMU 0 is not among the accelerometer IMUs used"):
        prepare_recording(rec, gyro="ignored", reference=0, reference_field="--fixed", acc_imus=range(1, rec.K))


def test_prepared_recording_of_a_fit_that_ignores_the_gyros(sim):
    p = prepare_recording(sim.recording, select="all", gyro="ignored")
    assert isinstance(p, PreparedRecording) and p.gyro is None and p.gyro_labels == ()
    assert p.T == sim.recording.T
    with pytest.raises(UserError, match="^gyro: expected one of"):
        prepare_recording(sim.recording, gyro="sometimes")

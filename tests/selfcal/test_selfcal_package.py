"""inference/selfcal/ as a package (issue #26 item 4): the public names of the old module still
import from the package, each from its one home; the solver's options are a frozen record that
refuses a bad option before any computation; the modules stay small."""
import dataclasses
from pathlib import Path

import pytest
import torch

import accel_bayes.inference.selfcal as sc
from accel_bayes.inference.selfcal import motion_priors, solve
from accel_bayes.physics import models
from accel_bayes.physics.arrays import s16_plate

PKG = Path(sc.__file__).parent

# the public names of accel_bayes/inference/selfcal.py at 9279a3c (its __all__ and the names that
# experiments/ imported), less simulate_process_motion, now a motion generator (physics.motion_generators)
OLD_PUBLIC = [
    "triad_residuals", "triad_jacobians", "process_residuals", "process_jacobians", "process_sqrt_information",
    "bridged_process_whitening", "PROCESS_NOISE_MODES", "wnoj_process_covariance", "wnoj_process_whitening",
    "MOTION_MODEL_DIMS", "integrated_wiener_covariance", "continuous_process_covariance",
    "continuous_process_whitening", "initial_process_intensities", "process_noise_statistics",
    "update_process_intensities", "scale_orbit", "marginal_scale_score", "laplace_scale_nll", "SelfCalResult",
    "SelfCalDiverged", "check_divergence", "self_calibrate", "FitCheck", "fit_check", "build_problem",
    "initial_smooth_process_intensities", "MISFIT_RMS", "UNIDENTIFIED_SCALE_STD",
]


def test_old_public_names_import_from_the_package():
    missing = [n for n in OLD_PUBLIC if not hasattr(sc, n)]
    assert not missing
    assert set(sc.__all__) >= set(OLD_PUBLIC)
    assert all(hasattr(sc, n) for n in sc.__all__)


def test_every_motion_prior_has_one_home():
    """The [S16] process model (eq. 7–8) left physics/models.py for motion_priors.py: one
    definition, re-exported by the package, none left behind under the old name."""
    for name in ("process_model", "process_transition", "process_covariance", "process_variances",
                 "S16_PROCESS_VARIANCES", "MOTION_STATE_DIMS"):
        assert not hasattr(models, name), name
        assert getattr(sc, name) is getattr(motion_priors, name)
    for name in ("wnoj_process_covariance", "continuous_process_covariance", "bridged_process_whitening"):
        assert getattr(sc, name).__module__ == motion_priors.__name__


def test_modules_stay_small():
    sizes = {p.name: len(p.read_text(encoding="utf-8").splitlines()) for p in PKG.glob("*.py")}
    assert len(sizes) >= 9
    assert max(sizes.values()) < 400, sizes


def _case():
    arr = s16_plate()
    g = torch.Generator().manual_seed(3)
    z = torch.randn(20, arr.K, 3, generator=g, dtype=torch.float64)
    return arr, z


def test_a_bad_option_is_refused_before_any_lm_run(monkeypatch):
    """Before the split, ``rerun_from_estimate`` was checked only after the first LM run (seconds
    to minutes of work on a real recording): the trap below was hit before the refusal."""
    def trap(*a, **k):
        raise AssertionError("an LM run started before the options were checked")

    monkeypatch.setattr(solve, "_run_lm", trap)
    arr, z = _case()
    with pytest.raises(ValueError, match="rerun_from_estimate"):
        sc.self_calibrate(z, 0.01, nominal_positions=arr.positions, rerun_from_estimate="sometimes")
    with pytest.raises(ValueError, match="process_noise"):
        sc.self_calibrate(z, 0.01, nominal_positions=arr.positions, process_noise="jerk")
    with pytest.raises(ValueError, match="process_variances"):
        sc.self_calibrate(z, 0.01, nominal_positions=arr.positions, process_noise="estimate",
                          process_variances={"acc": 1.0})


def test_solve_options_are_frozen_and_carry_the_motion_prior():
    o = sc.SelfcalSolveOptions(process_noise={"acc": 2.0, "omega": 3.0, "dim": 15})
    assert (o.prior.mode, o.prior.dim, o.prior.intensities) == ("fixed", 15, {"acc": 2.0, "omega": 3.0})
    assert not o.prior.estimated and sc.SelfcalSolveOptions(process_noise="estimate-snap").prior.estimated
    assert sc.SelfcalSolveOptions().prior == motion_priors.MotionPrior("s16", 9)
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.max_iter = 3
    with pytest.raises(ValueError, match="'dim'"):
        sc.SelfcalSolveOptions(process_noise={"acc": 2.0, "omega": 3.0, "dim": 10})


def test_a_rerun_that_is_not_kept_leaves_the_kept_runs_process_noise(monkeypatch):
    """With an estimated process noise, a re-run that is not kept must not lend its intensities
    to the result, nor its whitening to the scale correction of the kept estimate.  Before the
    fix both were the last run's (the re-run's).  The re-run is made "worse" by inflating its
    reported cost after it ran, so that the first run is kept."""
    from accel_bayes.physics.geometry import boxplus
    from accel_bayes.physics.motion_generators import simulate_process_motion

    arr = s16_plate()
    g = torch.Generator().manual_seed(8)
    x = simulate_process_motion(160, 1 / 125.0, seed=8, segment_length=20, omega_dot_std=8.0, omega0_std=3.0)
    q_true = boxplus(arr.orientations, 0.05 * torch.randn(arr.K, 3, generator=g, dtype=torch.float64))
    p_true = arr.positions + 2e-3 * torch.randn(arr.K, 3, generator=g, dtype=torch.float64)
    z = models.triad_output(x, q_true, p_true) + 0.01 * torch.randn(160, arr.K, 3, generator=g, dtype=torch.float64)

    seen = {}
    run = solve._Solver.run

    def run_and_record(self, p, q, x0, label):
        out = run(self, p, q, x0, label)
        seen[label] = (dict(self.noise.q), self.noise.W.clone())
        return dataclasses.replace(out, F=out.F * 10) if label == "rerun" else out

    scale = solve.laplace_scale_correction

    def scale_and_record(out, res, A, fixed, acc, dt, W, *a, **k):
        seen["scale_W"] = W
        return scale(out, res, A, fixed, acc, dt, W, *a, **k)

    monkeypatch.setattr(solve._Solver, "run", run_and_record)
    monkeypatch.setattr(solve, "laplace_scale_correction", scale_and_record)
    res = sc.self_calibrate(z, 1 / 125.0, nominal_positions=arr.positions, nominal_orientations=arr.orientations,
                            acc_noise_std=0.01, process_noise="estimate-snap", max_iter=60)
    assert res.ok and [r["label"] for r in res.runs] == ["first", "rerun"] and res.runs[1]["kept"] is False
    q_first, W_first = seen["first"]
    assert seen["rerun"][0] != q_first  # the re-run did move the intensities: the check can fail
    assert res.process_noise["intensities"] == q_first
    assert torch.equal(seen["scale_W"], W_first)

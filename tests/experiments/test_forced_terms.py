"""The report with the model's clock and unresolved-motion terms forced on
(``experiments/forced_terms.py``, the coverage must-show of issue #30): ``calibrate --model`` must
read it as a report whose terms are all used, on a clean recording where the detector keeps none."""
import numpy as np
import pytest

from accel_bayes.model.report_terms import load_model, unresolved_terms
from accel_bayes.simulate import simulate
from experiments import c21_coverage as cov
from experiments.forced_terms import forced_report


@pytest.fixture(scope="module")
def clean():
    return simulate(cov.square_board(0.03), "smooth", 300, 100.0, seed=5, clip=False).recording


@pytest.fixture(scope="module")
def report(clean):
    return forced_report(clean)


def test_every_imu_gets_a_clock_and_the_motion_term_is_there(clean, report):
    clocks = [f for f in report["findings"] if f["effect"] == "sampling_clock"]
    assert sorted(f["imu"] for f in clocks) == [k for k in range(clean.K) if bool(np.asarray(clean.has_gyro)[k])]
    um = [f for f in report["findings"] if f["effect"] == "unresolved_motion"]
    assert len(um) == 1
    p = um[0]["parameters"]
    B = len(p["omega_edges"]) + 1
    assert len(p["jerk_rms"]) == B and len(p["angular_acc_rms"]) == B
    assert np.all(np.isfinite(p["jerk_rms"])) and np.all(np.isfinite(p["angular_acc_rms"]))


def test_calibrate_reads_it_with_every_term_used(clean, report):
    m = load_model(report)
    m.check_recording(clean)
    assert m.unresolved and not m.skipped
    assert sorted(u["effect"] for u in m.used) == ["sampling_clock"] * 4 + ["unresolved_motion"]
    t = np.asarray(clean.time)
    terms = unresolved_terms(report, t, [0, 1, 2, 3], [0, 1, 2, 3], np.full(t.size, 5.0))
    # the clocks load something: a forced clock is a sawtooth of its fitted width, not zero
    assert float(terms.age_acc.abs().max()) > 0


def test_c21_coverage_refuses_forced_terms_on_iid_data(capsys):
    with pytest.raises(SystemExit) as e:
        cov.main(["--model-terms", "forced", "--n", "1"])
    assert e.value.code == 2
    assert "--model-terms" in capsys.readouterr().err


@pytest.mark.slow
def test_a_forced_replicate_runs_through_calibrate():
    r = cov.replicate_pipeline(0, T=300, chains=2, draws=100, warmup=100, model_terms="forced")
    assert sorted(r["ranks"]) == sorted(f"{k}{a}" for k, a in cov.COORDS)
    assert "unresolved_motion" in r["forced"]["used"] and not r["forced"]["skipped"]

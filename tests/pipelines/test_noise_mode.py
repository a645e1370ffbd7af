"""calibrate's noise mode (``calibrate_steps.noise_mode_for``): with a mismatch report "auto" estimates the
noise levels even without rests (issue #30 item 4: the stated white σ left ``--model`` overconfident by
6–10× on the concealed recordings without rests, ``experiments/vibgeom_probe.md``)."""
import pytest

from accel_bayes.pipelines.calibrate_steps import noise_mode_for


@pytest.mark.parametrize("rests, model, mode", [(True, False, "estimate"), (True, True, "estimate"),
                                                (False, True, "estimate"), (False, False, "stated")])
def test_auto_estimates_with_rests_or_a_report(rests, model, mode):
    assert noise_mode_for("auto", rests, model) == mode


@pytest.mark.parametrize("asked", ["stated", "estimate"])
def test_an_explicit_mode_is_kept(asked):
    for rests in (True, False):
        for model in (True, False):
            assert noise_mode_for(asked, rests, model) == asked

"""The angular-jerk probe (``experiments/angjerk_probe.py``): the generator's truth it compares the
fitted scales with.  The probe itself runs from the script (seconds a case after calibrate's MAP)."""
import numpy as np

import experiments.clockgen as cg
from experiments import angjerk_probe as ap


def test_the_truth_is_the_vibrations_angular_jerk_and_nothing_without_it():
    t = np.linspace(2.0, 8.0, 400)
    _, truth = cg.draw_case("clock", 3, duration=10.0, noise=False)
    wdd = ap.vibration_omega_ddot(truth)(t)
    # rotational vibration 0.05–0.3 rad/s at 30–95 Hz (plus impacts): ω̈ ~ A(2πf)² = 2e3–1e5 rad/s³
    rms = np.sqrt((wdd ** 2).mean())
    assert wdd.shape == (400, 3) and 1e3 < rms < 3e5
    _, calm = cg.draw_case("clock", 3, duration=10.0, noise=False, vibration=False)
    np.testing.assert_array_equal(ap.vibration_omega_ddot(calm)(t), 0.0)

"""The clock search where board vibration aliases (issue #27, recall): on a 125 Hz read the
vibration above the read's Nyquist rate (clockgen: 30–95 Hz) folds, and the finite difference of
the sampled gyro outputs — the data age's regressor until the recall fix — flips sign and shrinks
there, so the sawtooth fitted on it had the wrong beat or none.  The regressor is now the board's
angular acceleration R_k ω̇_t (:func:`accel_bayes.physics.effects.board_gyro_rate`)."""
import numpy as np

from accel_bayes.mismatch.clock import clock_ages, estimate_clock
from accel_bayes.mismatch.fit import baseline_fit
from accel_bayes.mismatch.prepared import prepare
from experiments.clock_proof import truth_beat_mid
from experiments.clockgen import draw_case

# plate4 read at 125 Hz, 10 s, beats −13.5 to +13.7 Hz: at c03e6a6 all four clocks were accepted
# with wrong beats (−6.10, −3.01, 6.09, 3.08 Hz: the folded lines, widths 1.1–2.3 ms)
SEED, DURATION = 2, 10.0


def test_beats_found_on_a_125hz_read_with_aliased_vibration():
    rec, truth = draw_case("clock", SEED, board_name="plate4", f_host=125.0, duration=DURATION)
    prep = prepare(rec)
    base, _ = baseline_fit(prep)
    _, st = clock_ages(prep, base)
    t = prep.time.numpy()
    t_mid = 0.5 * float(t[0] + t[-1])
    assert sorted(c.imu for c in st.clocks) == [0, 1, 2, 3]
    for c in st.clocks:
        beat_mid = c.params["beat_hz"] + c.params["drift_hz_per_s"] * t_mid
        assert abs(float(beat_mid) - truth_beat_mid(truth, c.imu, t_mid)) <= 0.05


def test_search_is_not_led_by_a_constant_offset():
    """A constant time offset (read skew) gives b = −a·const: the spectrum of the motion's
    envelope in a_t.  At c03e6a6 it outranked a −2.3 Hz beat (62.4 Hz, width 0.11 ms found)."""
    rng = np.random.default_rng(3)
    t = np.arange(0, 20, 0.008)
    env = ((t % 6.0) > 2.0).astype(float)  # moves of 4 s between rests of 2 s
    a = 1e7 * (0.05 + env * (1 + 0.5 * np.sin(2 * np.pi * 0.7 * t)))
    age = 1e-3 * ((0.3 - 2.3 * t) % 1.0)
    b = -a * (age + 0.4e-3) + np.sqrt(a) * rng.standard_normal(t.size)
    c = estimate_clock(t, a, b, 125.0)
    assert abs(c["beat_hz"] + c["drift_hz_per_s"] * 10.0 - (-2.3)) < 0.01
    assert 0.85e-3 < c["width_s"] < 1.15e-3

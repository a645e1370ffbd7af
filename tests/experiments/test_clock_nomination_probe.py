"""``experiments/clock_nomination_probe.py``: its wider-apart nomination on a synthetic ranking, and the table."""
import numpy as np

from experiments import clock_nomination_probe as cn


def _sp(Q):
    L = Q.size
    freqs = np.linspace(-50.0, 50.0, L, endpoint=False)
    return {"freqs": freqs, "L": L, "step": 1.0, "f_read": 100.0, "drifts": np.array([0.0]), "P": Q[None], "Pn": Q[None]}


def test_local_maxima_kept_apart():
    L = 1000  # 0.1 Hz a bin
    Q = np.zeros(L)
    Q[700], Q[702] = 10.0, 9.5  # one line, two maxima two bins apart (+20.0 / +20.2 Hz)
    Q[701] = 9.0
    Q[300] = 5.0  # a weaker line at −20 Hz: the same |β|, one peak of the real input's spectrum
    Q[550] = 4.0  # +5 Hz
    beats2 = sorted(round(p[1], 2) for p in cn.nominate_apart(_sp(Q), 1))
    assert 20.0 in beats2 and 20.2 in beats2 and 5.0 in beats2 and -20.0 not in beats2
    beats3 = sorted(round(p[1], 2) for p in cn.nominate_apart(_sp(Q), 3))
    assert beats3 == [5.0, 20.0]  # the line's second maximum is within 3 bins


def test_markdown_says_whether_the_true_beat_is_nominated():
    r = {"seed": 29, "imu": 1, "board": "cube6", "f_read": 62.5, "kept": 433, "span_s": 10.2, "true_beat": -16.449,
         "threshold": 33.6, "true": {"beat": -16.452, "evidence": 2738.6, "evw": 634.7, "width_ms": 2.66},
         "pick": {"beat": 13.022, "evidence": 822.0, "evw": 135.5, "width_ms": 0.4}, "height_ratio": 0.85, "rank": 80, "floor_between": 0.64, "f_top": 13.08,
         "top": [13.08, -13.08], "nominated": [13.08, -7.16], "screened": [-16.45, 11.48], "n_screen": 100, "apart": {4: [16.45, 13.08]}, "bins_per_resolution": 6.4}
    text = "\n".join(cn.markdown(r, "cmd"))
    assert "| the true clock as a candidate (refined) | -16.452 | 2738.6 | 634.7 | 2.66 |" in text
    assert "+13.08, -7.16 — true beat **not in**" in text
    assert "Between the top (±13.08 Hz) and the true beat the ranking never falls below 0.64 of the top." in text
    assert "next 100 distinct local maxima, best first): -16.45, +11.48 — true beat in." in text
    assert "Local maxima kept 4 bins apart: +16.45, +13.08 — true beat in." in text

"""``calibrate --model`` is untempered: where the model's own sandwich at its mode says the Laplace std
is too narrow (ratio above issue #30's 1.3 bar), the user is told in one line instead of reading it
from settings.model.sandwich (concealed clock-020: ratio 9, z up to 5.4, no warning before)."""
import warnings

import pytest

from accel_bayes.pipelines.calibrate_model import HONEST_STD_RATIO, warn_if_misfit


def _record(ratios):
    return {"std_ratio": ratios, "coordinates": [f"r[{k}, x]" for k in range(len(ratios))]}


def test_warns_once_naming_the_worst_coordinate_and_the_count():
    with pytest.warns(RuntimeWarning) as rec:
        msg = warn_if_misfit(_record([1.0, 8.95, 1.4, 0.9]))
    assert len(rec) == 1 and str(rec[0].message) == msg
    assert "8.95x" in msg and "r[1, x]" in msg and "2 of 4 coordinates" in msg and "\n" not in msg


@pytest.mark.parametrize("ratios", [[1.0, HONEST_STD_RATIO, 0.8], []])
def test_silent_at_or_below_the_bar_and_without_a_record(ratios):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert warn_if_misfit(_record(ratios)) is None
    assert warn_if_misfit({"kappa": None, "why": "no usable MAP"}) is None

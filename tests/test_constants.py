"""accel_bayes.constants: one definition of g, the degree conversions and the default prior std."""
import math
import re
from pathlib import Path

import accel_bayes
from accel_bayes import constants


def test_values_and_directions():
    assert constants.G0 == 9.80665
    assert math.isclose(90 * constants.DEG_TO_RAD, math.pi / 2, rel_tol=1e-15)
    assert math.isclose(math.pi * constants.RAD_TO_DEG, 180.0, rel_tol=1e-15)
    assert constants.DEFAULT_PRIOR_STD == 3e-3


def test_no_module_defines_its_own_degree_constant_or_gravity():
    """A bare ``DEG`` meant π/180 in some modules and 180/π in others; the package now takes
    both directions (and g) from accel_bayes.constants only."""
    root = Path(accel_bayes.__file__).parent
    pat = re.compile(r"^\s*\w+\s*=\s*(math\.pi\s*/\s*180|180(\.0)?\s*/\s*(math|np)\.pi|9\.80665)\b", re.M)
    offenders = [str(p.relative_to(root)) for p in root.rglob("*.py")
                 if p.name != "constants.py" and pat.search(p.read_text(encoding="utf-8"))]
    assert offenders == []

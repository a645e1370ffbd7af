"""accel_bayes.constants: one definition of g, the degree conversions and the default prior std."""
import math
import re
from pathlib import Path

import accel_bayes
from accel_bayes import constants
from tests.paths import STORED


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


def test_file_format_strings_are_the_contracts_not_module_paths():
    """The schema and format strings name file formats, not modules: moving a module (issue #10)
    must not change them, or every file written before the move is refused.  Literal values
    from DESIGN §7 and the files written by 7adf109."""
    from accel_bayes.data.positions import POSITIONS_SCHEMA
    from accel_bayes.data.format_v1 import FORMAT
    from accel_bayes.data.io import TRUTH_SCHEMA
    from accel_bayes.data.mismatch_report import SCHEMA as MISMATCH_SCHEMA
    from accel_bayes.prep.intrinsics import SCHEMA as INTRINSICS_SCHEMA
    from accel_bayes.inference.mcmc.checkpoint import CHECKPOINT_FORMAT
    import accel_bayes.inference.motion_estimate as me

    assert FORMAT == "accel_bayes.recording/1"
    assert POSITIONS_SCHEMA == "accel_bayes.positions/1"
    assert MISMATCH_SCHEMA == "accel_bayes.mismatch/1"
    assert INTRINSICS_SCHEMA == "accel_bayes.intrinsics/1"
    assert me.MOTION_SCHEMA == "accel_bayes.motion/1"
    assert TRUTH_SCHEMA == "accel_bayes.truth/1"
    assert CHECKPOINT_FORMAT == "accel_bayes.pmmh-checkpoint/1"


def test_files_written_before_the_layout_move_still_load():
    """A recording and a positions.json written by 7adf109 (``accel-bayes simulate --preset mimu8
    -T 60 --seed 3`` and ``accel-bayes map`` on it) load with today's readers."""
    from pathlib import Path

    import numpy as np

    from accel_bayes.data.io import read_recording
    from accel_bayes.data.positions import read_positions

    rec = read_recording(STORED / "rec_7adf109.nc")
    assert rec.acc.shape == (60, 8, 3) and np.isfinite(rec.acc).all()
    doc = read_positions(STORED / "positions_7adf109.json")
    assert doc["schema"] == "accel_bayes.positions/1" and len(doc["imus"]) == 8
    assert doc["means"].shape == (8, 3) and np.isfinite(doc["means"]).all()

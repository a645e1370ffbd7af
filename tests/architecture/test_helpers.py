"""One copy of each helper (issue #10 item 7): the JSON cleaner, the recording loader, the
constants and the experiments' shared pieces."""
import ast
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import torch

from accel_bayes.data.outputs import to_jsonable
from accel_bayes.errors import UserError

from tests.paths import REPO


def test_to_jsonable_keeps_or_nulls_nonfinite():
    x = {"a": np.array([1.0, np.nan]), "b": torch.tensor([np.inf]), "c": np.float64(np.nan), "d": (1, 2.5)}
    kept = to_jsonable(x)
    assert math.isnan(kept["a"][1]) and kept["b"] == [math.inf] and math.isnan(kept["c"]) and kept["d"] == [1, 2.5]
    assert to_jsonable(x, nonfinite="null") == {"a": [1.0, None], "b": [None], "c": None, "d": [1, 2.5]}
    assert to_jsonable(np.array([[1, 2]]), nonfinite="null") == [[1, 2]]  # ints stay ints
    assert to_jsonable({"p": Path("a/b"), "n": np.int64(3), "t": np.bool_(True)}) == {"p": "a/b", "n": 3, "t": True}


def test_to_jsonable_unknown_objects():
    @dataclass
    class D:
        x: float

    assert to_jsonable(D(np.float64(1.5))) == {"x": 1.5}
    obj = object()
    with pytest.raises(UserError, match=r"attrs\['k'\]\.z: cannot store a object"):
        to_jsonable({"z": obj}, where="attrs['k']")
    assert to_jsonable({"z": obj}, unknown="repr")["z"].startswith("<object")
    assert to_jsonable({"z": obj}, unknown="keep")["z"] is obj
    with pytest.raises(UserError, match="dictionary keys"):
        to_jsonable({(1, 2): 3})
    assert to_jsonable({(1, 2): 3}, unknown="keep") == {"(1, 2)": 3}


def _defs(path, name):
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return [n for n in ast.walk(tree) if isinstance(n, ast.FunctionDef) and n.name == name]


@pytest.mark.parametrize("name", ["_clean", "_jsonable", "_json_float", "_load_recording", "_load", "load_any",
                                  "make_client", "run_tasks"])
def test_no_second_copy_in_the_package(name):
    files = list((REPO / "accel_bayes").rglob("*.py")) + list((REPO / "experiments").glob("s16_*.py"))
    hits = [str(p.relative_to(REPO)) for p in files if _defs(p, name)]
    assert not hits, f"{name} defined again in {hits}"


def test_one_data_dir_in_experiments():
    hits = [p.name for p in (REPO / "experiments").glob("*.py") if _defs(p, "data_dir")]
    assert hits == ["_data.py"]

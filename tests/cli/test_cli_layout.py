"""``accel_bayes.cli`` parses arguments, calls a pipeline and prints (issue #10 item 6): no module
in it imports a numerical library, at module level or inside a function (AST check)."""
import ast
from pathlib import Path

import pytest

import accel_bayes

CLI = Path(accel_bayes.__file__).parent / "cli"
NUMERICAL = {"torch", "numpy", "scipy", "pandas", "xarray", "arviz", "matplotlib"}


def _imports(tree):
    """Every (line, top-level package) imported anywhere in a module, functions included."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield node.lineno, a.name.split(".")[0]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            yield node.lineno, node.module.split(".")[0]


@pytest.mark.parametrize("path", sorted(CLI.glob("*.py")), ids=lambda p: p.name)
def test_cli_module_imports_no_numerical_library(path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    bad = [f"{path.name}:{line} imports {mod}" for line, mod in _imports(tree) if mod in NUMERICAL]
    assert not bad, "; ".join(bad)


def test_the_check_sees_function_level_imports():
    tree = ast.parse("def f():\n    import numpy as np\n    from torch import nn\n")
    assert {m for _, m in _imports(tree)} == {"numpy", "torch"}


def test_every_command_module_is_checked():
    names = {p.stem for p in CLI.glob("*.py")}
    assert {"calibrate", "map", "selfcal", "motion", "intrinsics", "info", "simulate", "demo"} <= names

"""The package's layers and the size of its files (issue #26, "Must show: the layering test").

* A folder imports only from itself and the folders before it in :data:`LAYERS` (DESIGN §8's
  order, refined below), counting the imports inside functions and resolving relative ones: the
  import graph is :func:`test_import_graph.graph` (``lazy=True``), the one AST scan of the package.
  ``inference/lm`` is its own layer, below ``prep``: the solvers import nothing of the package
  but ``physics.geometry`` and ``interrupts``, and ``prep``'s intrinsics fit runs the batched LM.
  The root ``accel_bayes/__init__.py`` (the version, and public names loaded on first use by
  ``importlib``, which no AST scan sees) counts as the bottom layer.
* No module over :data:`MAX_LINES` lines except at most three listed in :data:`ALLOWED_LARGE`, each
  saying why in its module docstring (none is needed today: every module is under the limit).
"""
import ast

import pytest

from tests.architecture.test_import_graph import ROOT, graph

# Bottom first.  A module belongs to the longest entry that is its dotted path or a prefix of it.
LAYERS = (
    ("", "constants", "errors", "threads", "interrupts"),  # "" is the root package
    ("physics",),
    ("data",),
    ("inference.lm",),
    ("prep",),
    ("model",),
    ("simulate",),
    ("inference",),
    ("diagnostics",),
    ("mismatch",),
    ("pipelines",),
    ("cli", "__main__"),
)

MAX_LINES = 600
# Modules allowed over MAX_LINES (at most 3), each with the reason in its docstring, which must
# contain the phrase below.
ALLOWED_LARGE: dict = {}
REASON_PHRASE = "over 600 lines"


def layer_of(module: str):
    """Index in LAYERS of an ``accel_bayes…`` module, or None when no entry covers it."""
    rel = module[len("accel_bayes."):] if module.startswith("accel_bayes.") else ""
    best, depth = None, -1
    for i, names in enumerate(LAYERS):
        for name in names:
            covers = rel == name or (name and rel.startswith(name + "."))
            if covers and len(name) > depth:
                best, depth = i, len(name)
    return best


def upward_imports(g: dict) -> list:
    """'a -> b' for every edge of the import graph from a lower layer to a higher one."""
    return sorted(f"{m} -> {d}" for m, deps in g.items() for d in deps
                  if layer_of(m) is not None and layer_of(d) is not None and layer_of(d) > layer_of(m))


@pytest.fixture(scope="module")
def g():
    return graph(lazy=True)


def test_every_module_has_a_layer(g):
    assert "accel_bayes.model.likelihood" in g and "accel_bayes.inference.lm.solver" in g
    loose = sorted(m for m in g if layer_of(m) is None)
    assert not loose, f"modules in no layer (add their folder to LAYERS and the README layout): {loose}"


def test_no_import_from_a_later_folder(g):
    bad = upward_imports(g)
    assert not bad, "imports from a later folder:\n" + "\n".join(bad)


def test_the_check_sees_lazy_imports_and_the_order_both_ways(g):
    """An import inside a function is an edge (pipelines/map.py imports the MAP in its function
    only), and the order flags an upward edge and passes a downward one."""
    assert "accel_bayes.inference.map" in g["accel_bayes.pipelines.map"]
    assert "accel_bayes.inference.map" not in graph(lazy=False)["accel_bayes.pipelines.map"]
    fake = {"accel_bayes.mismatch.compare": ["accel_bayes.pipelines.calibrate", "accel_bayes.physics.geometry"],
            "accel_bayes.prep.intrinsics": ["accel_bayes.inference.lm.batched"],
            "accel_bayes.prep.selection": ["accel_bayes.inference.map"],
            "accel_bayes.data.outputs": ["accel_bayes"]}
    assert upward_imports(fake) == ["accel_bayes.mismatch.compare -> accel_bayes.pipelines.calibrate",
                                    "accel_bayes.prep.selection -> accel_bayes.inference.map"]
    assert layer_of("accel_bayes.inference.lm.batched") < layer_of("accel_bayes.prep.intrinsics") \
        < layer_of("accel_bayes.model.likelihood") < layer_of("accel_bayes.inference.map")


def _line_counts() -> dict:
    return {p.relative_to(ROOT).as_posix(): len(p.read_text(encoding="utf-8").splitlines())
            for p in ROOT.rglob("*.py")}


def test_allowed_large_files_say_why():
    assert len(ALLOWED_LARGE) <= 3
    for rel in ALLOWED_LARGE:
        doc = ast.get_docstring(ast.parse((ROOT / rel).read_text(encoding="utf-8"))) or ""
        assert REASON_PHRASE in doc.lower(), f"{rel}: its docstring must say why it is {REASON_PHRASE}"


def test_no_module_over_600_lines_but_the_allowed():
    over = sorted(rel for rel, n in _line_counts().items() if n > MAX_LINES and rel not in ALLOWED_LARGE)
    assert not over, f"modules over {MAX_LINES} lines: {over}"

"""The package's import graph (issue #10 items 4–5):

* no import cycle, counting imports inside functions too (deliberately lazy imports are still
  dependencies: the old ``mismatch`` cycle locate → refine → report → locate ran through them,
  which the module-level check, :func:`test_no_import_cycle` below, cannot see);
* ``accel_bayes.simulate`` does not import ``accel_bayes.mismatch`` (the simulator is physics);
* only ``accel_bayes/diagnostics/`` imports ArviZ or matplotlib (every plot in that package), and
  ArviZ only in ``diagnostics/arviz_calls.py`` (every ArviZ call in one module).
"""
import ast
import subprocess
import sys
from pathlib import Path
from tests.paths import REPO

ROOT = REPO / "accel_bayes"

# Modules still allowed to import arviz/matplotlib outside diagnostics/: none since the [S16]
# convergence plot moved from cli/selfcal.py to diagnostics (issue #10 item 6).
PENDING_PLOTTING: set = set()
PLOTTING = ("arviz", "matplotlib")


def _modules() -> dict:
    mods = {}
    for p in ROOT.rglob("*.py"):
        parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    return mods


def _imports(p: Path, lazy: bool):
    """(module name, level) of every import statement; ``lazy``: also those inside functions."""
    tree = ast.parse(p.read_text(encoding="utf-8"))
    nodes = ast.walk(tree) if lazy else tree.body
    for node in nodes:
        if isinstance(node, ast.ImportFrom):
            yield node
        elif isinstance(node, ast.Import):
            yield node


def graph(lazy: bool = True) -> dict:
    """{module: [accel_bayes modules it imports]}; a ``from pkg import name`` counts as an edge to
    ``pkg.name`` when that is a module, else to ``pkg``."""
    mods = _modules()
    out = {}
    for m, p in mods.items():
        pkg = m.split(".") if p.name == "__init__.py" else m.split(".")[:-1]
        deps = set()
        for node in _imports(p, lazy):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = pkg[:len(pkg) - node.level + 1]
                    name = ".".join(base + ([node.module] if node.module else []))
                else:
                    name = node.module
                for a in node.names:
                    full = f"{name}.{a.name}"
                    deps.add(full if full in mods else name)
            else:
                deps.update(a.name for a in node.names)
        out[m] = sorted(d for d in deps if d in mods and d != m)
    return out


def cycles(g: dict) -> list:
    state, found = {}, []

    def visit(u, stack):
        state[u] = 1
        stack.append(u)
        for v in g[u]:
            if state.get(v) == 1:
                found.append(" -> ".join(stack[stack.index(v):] + [v]))
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 2

    for m in sorted(g):
        if m not in state:
            visit(m, [])
    return found


def _reach(g: dict, start: str) -> set:
    seen, todo = set(), [start]
    while todo:
        u = todo.pop()
        for v in g.get(u, ()):
            if v not in seen:
                seen.add(v)
                todo.append(v)
    return seen


def test_no_import_cycle_even_through_lazy_imports():
    g = graph(lazy=True)
    assert "accel_bayes.mismatch.prepared" in g and "accel_bayes.mismatch.compare" in g
    found = cycles(g)
    assert not found, found


def test_simulate_does_not_import_mismatch():
    g = graph(lazy=True)
    bad = sorted(m for m in _reach(g, "accel_bayes.simulate") if m.startswith("accel_bayes.mismatch"))
    assert not bad, bad
    code = ("import sys, accel_bayes.simulate; "
            "print(sorted(m for m in sys.modules if m.startswith('accel_bayes.mismatch')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


ARVIZ_MODULE = "diagnostics/arviz_calls.py"


def _plotting_imports(p: Path) -> set:
    names = set()
    for node in _imports(p, lazy=True):
        mods = [node.module or ""] if isinstance(node, ast.ImportFrom) else [a.name for a in node.names]
        names.update(n for n in mods if n.split(".")[0] in PLOTTING)
    return names


def test_only_diagnostics_imports_arviz_or_matplotlib():
    offenders, arviz = {}, set()
    for p in ROOT.rglob("*.py"):
        rel = p.relative_to(ROOT).as_posix()
        names = _plotting_imports(p)
        if any(n.split(".")[0] == "arviz" for n in names):
            arviz.add(rel)
        if rel.startswith("diagnostics/") or rel in PENDING_PLOTTING:
            continue
        if names:
            offenders[rel] = sorted(names)
    assert not offenders, offenders
    assert arviz == {ARVIZ_MODULE}, f"ArviZ imported outside {ARVIZ_MODULE}: {sorted(arviz - {ARVIZ_MODULE})}"
    for rel in PENDING_PLOTTING:  # the exception must not outlive its reason
        assert (ROOT / rel).exists(), f"{rel} is gone: remove it from PENDING_PLOTTING"


def test_importing_mismatch_loads_neither_arviz_nor_matplotlib():
    """The mismatch package reaches diagnostics/ only inside functions (a comparison, a figure)."""
    code = ("import sys, accel_bayes.mismatch; "
            "print(sorted({m.split('.')[0] for m in sys.modules} & {'arviz', 'matplotlib'}))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]", out


def test_no_import_cycle():
    """The graph of module-level imports between accel_bayes modules is acyclic (a package's
    ``__init__`` importing its own submodules is the usual re-export)."""
    g = graph(lazy=False)
    assert "accel_bayes.inference.lm.solver" in g and "accel_bayes.inference.mcmc.kernel" in g
    found = cycles(g)
    assert not found, found

"""No import cycle in the package (issue #10): the graph of module-level ``import``/``from … import``
statements between accel_bayes modules is acyclic.  Imports inside functions (deliberately lazy)
are not edges; a package's ``__init__`` importing its own submodules is the usual re-export."""
import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "accel_bayes"


def _graph() -> dict:
    mods = {}
    for p in ROOT.rglob("*.py"):
        parts = list(p.relative_to(ROOT.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        mods[".".join(parts)] = p
    graph = {}
    for m, p in mods.items():
        pkg = m.split(".") if p.name == "__init__.py" else m.split(".")[:-1]
        deps = set()
        for node in ast.parse(p.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.ImportFrom):
                base = pkg[:len(pkg) - node.level + 1] if node.level else []
                name = ".".join(base + ([node.module] if node.module else [])) if node.level else node.module
                for a in node.names:
                    full = f"{name}.{a.name}"
                    deps.add(full if full in mods else name)
            elif isinstance(node, ast.Import):
                deps.update(a.name for a in node.names)
        graph[m] = sorted(d for d in deps if d in mods and d != m)
    return graph


def test_no_import_cycle():
    graph = _graph()
    assert "accel_bayes.inference.lm.solver" in graph and "accel_bayes.inference.mcmc.kernel" in graph
    state, cycles = {}, []

    def visit(u, stack):
        state[u] = 1
        stack.append(u)
        for v in graph[u]:
            if state.get(v) == 1:
                cycles.append(" -> ".join(stack[stack.index(v):] + [v]))
            elif v not in state:
                visit(v, stack)
        stack.pop()
        state[u] = 2

    for m in graph:
        if m not in state:
            visit(m, [])
    assert not cycles, cycles

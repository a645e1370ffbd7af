"""The test suite's own layout (issue #26 item 7): test files sit in subject folders that are
packages, and no test file edits ``sys.path`` — the concealed generators and the experiment
scripts are imported as ``experiments.*`` and shared helpers as ``tests.<subject>.*``, which
pytest's ``pythonpath = ["."]`` (pyproject.toml) makes importable from the repository root."""
import ast
from pathlib import Path

from tests.paths import REPO


def sys_path_edits(folder: Path) -> list[str]:
    """``file:line`` of every use of ``sys.path`` or ``monkeypatch.syspath_prepend`` in the Python
    files under ``folder`` (a read of ``sys.path`` counts too: a test has no reason to look)."""
    found = []
    for path in sorted(folder.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if (isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name)
                    and node.value.id == "sys") or (isinstance(node, ast.Attribute) and node.attr == "syspath_prepend"):
                found.append(f"{path.relative_to(folder.parent)}:{node.lineno}")
    return found


def misplaced_test_files(folder: Path) -> list[str]:
    """Test files outside a subject folder, and subject folders that are not packages (without
    ``__init__.py`` pytest would import their files by bare name, where two subjects may clash)."""
    bad = [f"{p.relative_to(folder.parent)}: not in a subject folder" for p in sorted(folder.glob("test_*.py"))]
    for d in sorted(p for p in folder.iterdir() if p.is_dir() and any(p.rglob("test_*.py"))):
        if not (d / "__init__.py").is_file():
            bad.append(f"{d.relative_to(folder.parent)}: no __init__.py")
    return bad


def conflicting_constants(folder: Path) -> list[str]:
    """``NAME: file = value; file = value`` for every module-level UPPER_CASE name that two test
    modules of ``folder`` bind to different expressions (source text compared): a reader of one
    subject must not meet ``FAST`` meaning two things, as after the ``test_mismatch`` /
    ``_fast`` / ``_v11`` split by history."""
    seen: dict = {}
    for path in sorted(folder.glob("*.py")):
        for node in ast.parse(path.read_text(encoding="utf-8")).body:
            if isinstance(node, ast.Assign):
                for t in node.targets:
                    if isinstance(t, ast.Name) and t.id.lstrip("_").isupper():
                        seen.setdefault(t.id, {})[path.name] = ast.unparse(node.value)
    return [f"{name}: " + "; ".join(f"{f} = {v}" for f, v in by_file.items())
            for name, by_file in sorted(seen.items()) if len(set(by_file.values())) > 1]


# Subjects whose test files were split by history (issue #26 item 7)
SPLIT_BY_HISTORY = ("mismatch", "pipelines", "mcmc")


def test_one_meaning_per_constant_name_in_a_subject():
    bad = [f"tests/{s}: {c}" for s in SPLIT_BY_HISTORY for c in conflicting_constants(REPO / "tests" / s)]
    assert not bad, "\n".join(bad)


def test_no_test_file_edits_sys_path():
    found = sys_path_edits(REPO / "tests")
    assert not found, found


def test_test_files_are_grouped_in_subject_packages():
    bad = misplaced_test_files(REPO / "tests")
    assert not bad, bad
    assert (REPO / "tests" / "__init__.py").is_file()


def test_checks_see_what_they_look_for(tmp_path):
    """Both checks find a planted offence (the checks cannot pass vacuously)."""
    t = tmp_path / "tests"
    (t / "cli").mkdir(parents=True)
    (t / "cli" / "test_a.py").write_text("import sys\nsys.path.insert(0, 'x')\n")
    (t / "test_b.py").write_text("def test_b(monkeypatch):\n    monkeypatch.syspath_prepend('x')\n")
    assert sys_path_edits(t) == ["tests/cli/test_a.py:2", "tests/test_b.py:2"]
    assert misplaced_test_files(t) == ["tests/test_b.py: not in a subject folder", "tests/cli: no __init__.py"]
    (t / "cli" / "test_c.py").write_text("FAST = dict(n=1)\nDEG = 0.5\n")
    (t / "cli" / "test_d.py").write_text("FAST = dict(n=2)\nDEG = 0.5\n")
    assert conflicting_constants(t / "cli") == ["FAST: test_c.py = dict(n=1); test_d.py = dict(n=2)"]

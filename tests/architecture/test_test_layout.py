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

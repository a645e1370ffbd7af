"""Every study is reachable (issue #26 item 7): ``experiments/README.md`` links every report
``experiments/*.md`` and names every script, every file it names exists, and each line of the
README's "What was measured" section links a report and the script that regenerates it."""
import re
from pathlib import Path

from tests.paths import REPO

EXPERIMENTS = REPO / "experiments"
_LINK = re.compile(r"\]\(([^)#\s]+)\)")
_NAMED = re.compile(r"`((?:tests|experiments)/[\w./]+\.py|[\w.]+\.py)")


def index_problems(folder: Path) -> list[str]:
    """What ``folder/README.md`` misses (a report not linked, a script not named) or names
    wrongly (a link or a ``….py`` that does not exist, relative to ``folder`` or, for
    ``tests/…`` and ``experiments/…``, to the repository above it)."""
    text = (folder / "README.md").read_text(encoding="utf-8")
    links = set(_LINK.findall(text))
    named = links | set(_NAMED.findall(text))
    bad = [f"{md.name}: not linked" for md in sorted(folder.glob("*.md"))
           if md.name != "README.md" and md.name not in links]
    bad += [f"{py.name}: not named" for py in sorted(folder.glob("*.py"))
            if not py.name.startswith("_") and py.name not in named]
    for name in sorted(named):
        where = folder.parent / name if name.startswith(("tests/", "experiments/")) else folder / name
        if not where.exists():
            bad.append(f"{name}: does not exist")
    return bad


def measured_problems(readme: Path) -> list[str]:
    """Lines of the README's "What was measured" section that do not link both an existing
    ``experiments/*.md`` report and an existing ``experiments/*.py`` script."""
    text = readme.read_text(encoding="utf-8")
    section = text[text.index("## What was measured"):]
    section = section[:section.index("\n## ", 5)]
    lines = [ln for ln in section.splitlines() if ln.startswith("- ")]
    bad = [] if lines else ["no claims"]
    for ln in lines:
        targets = _LINK.findall(ln)
        reports = [t for t in targets if re.fullmatch(r"experiments/[\w.]+\.md", t)]
        scripts = [t for t in targets if re.fullmatch(r"experiments/[\w.]+\.py", t)]
        missing = [t for t in reports + scripts if not (readme.parent / t).exists()]
        if not reports or not scripts or missing:
            bad.append(ln[:80] + ("" if not missing else f" (missing: {missing})"))
    return bad


def test_experiments_index_links_every_report_and_names_only_existing_files():
    bad = index_problems(EXPERIMENTS)
    assert not bad, bad


def test_every_readme_claim_links_its_report_and_script():
    bad = measured_problems(REPO / "README.md")
    assert not bad, bad


def test_the_checks_find_planted_gaps(tmp_path):
    """An unlinked report, an unnamed script, a link to nothing and a claim without its script
    are each reported (the checks cannot pass vacuously)."""
    ex = tmp_path / "experiments"
    ex.mkdir()
    for name in ("a.md", "b.md", "a.py", "c.py", "_helper.py"):
        (ex / name).write_text("")
    (ex / "README.md").write_text("| claim | [`a.py`](a.py) | [a.md](a.md) | `tests/x/test_gone.py` |\n"
                                  "see [gone.md](gone.md)\n")
    assert index_problems(ex) == ["b.md: not linked", "c.py: not named", "gone.md: does not exist",
                                  "tests/x/test_gone.py: does not exist"]
    (tmp_path / "README.md").write_text("## What was measured\n\n"
                                        "- ok ([a.md](experiments/a.md), [a.py](experiments/a.py))\n"
                                        "- no script ([a.md](experiments/a.md))\n\n## Next\n")
    assert measured_problems(tmp_path / "README.md") == ["- no script ([a.md](experiments/a.md))"]

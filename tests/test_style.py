"""Habits the suite holds: the tree passes ``ruff check`` with the rules of pyproject.toml and is in
``ruff format``'s layout, and the public modules' docstring examples are there to run (pytest collects
them: ``--doctest-modules``)."""

from __future__ import annotations

import doctest
import importlib
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def ruff(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    try:
        import ruff as _  # noqa: F401  (installed with the test extras)
    except ImportError:
        pytest.fail("ruff is not installed: pip install -e '.[test]' (it is one of the test extras)")
    return subprocess.run([sys.executable, "-m", "ruff", *args], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_ruff_check_passes_on_the_tree() -> None:
    done = ruff("check", "--no-cache", "--output-format", "concise", ".")
    assert done.returncode == 0, (
        f"ruff check found problems (fix them, or `ruff check --fix` for import order):\n{done.stdout}{done.stderr}"
    )


def test_ruff_format_holds_on_the_tree() -> None:
    done = ruff("format", "--check", "--no-cache", ".")
    assert done.returncode == 0, f"files not in ruff's format (run `ruff format .`):\n{done.stdout}{done.stderr}"


def test_ruff_format_check_finds_an_unformatted_file(tmp_path: Path) -> None:
    """The format check can fail: a planted file in another layout is reported."""
    bad = tmp_path / "planted.py"
    bad.write_text("x = {  'a':1,'b' :2 }\n", encoding="utf-8")
    done = ruff("format", "--check", "--no-cache", "--config", str(REPO / "pyproject.toml"), str(bad), cwd=tmp_path)
    assert done.returncode == 1 and "planted.py" in done.stdout, done.stdout


def test_ruff_rules_catch_what_they_are_chosen_for(tmp_path: Path) -> None:
    """The configured rules fail on a planted unused import, an unsorted import block, a mutable
    default and an undefined name: the style test can fail."""
    bad = tmp_path / "planted.py"
    bad.write_text("import sys\nimport os\n\n\ndef f(x=[]):\n    return undefined_name\n", encoding="utf-8")
    done = ruff(
        "check",
        "--no-cache",
        "--output-format",
        "concise",
        "--config",
        str(REPO / "pyproject.toml"),
        str(bad),
        cwd=tmp_path,
    )
    assert done.returncode == 1
    for code in ("F401", "I001", "B006", "F821"):
        assert code in done.stdout, (code, done.stdout)


@pytest.mark.parametrize("module", ["labelaudit.core.posterior", "labelaudit.results", "labelaudit.training"])
def test_public_modules_have_examples_that_run(module: str) -> None:
    """Each has docstring examples, none of them skipped (pytest runs them as doctests)."""
    tests = doctest.DocTestFinder().find(importlib.import_module(module))
    examples = [ex for t in tests for ex in t.examples]
    assert examples, f"{module}: no docstring example"
    assert not [ex.source for ex in examples if ex.options.get(doctest.SKIP)], f"{module}: a skipped example"


ISSUE_NUMBER = re.compile(r"\bissues? ?#?\d+|\bissue-\d+", re.IGNORECASE)


def test_code_names_no_issue_numbers() -> None:
    """Comments and docstrings say why, not which ticket: an issue number in code is history that the
    reader cannot follow (the git log keeps it)."""
    hits = []
    for folder in ("labelaudit", "scripts", "tests"):
        for path in sorted((REPO / folder).rglob("*")):
            if path.suffix not in (".py", ".toml", ".j2", ".sh") or path == Path(__file__).resolve():
                continue
            for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
                if ISSUE_NUMBER.search(line):
                    hits.append(f"{path.relative_to(REPO)}:{n}: {line.strip()}")
    assert not hits, "issue numbers in code (say what the code holds instead):\n" + "\n".join(hits)


def test_the_issue_number_pattern_finds_them() -> None:
    found = [
        t
        for t in ("# issue 15: a NaN box", "(issues 4 and 13)", "the issue-6 benchmark", "see Issue #12")
        if ISSUE_NUMBER.search(t)
    ]
    assert len(found) == 4
    assert not ISSUE_NUMBER.search("# an issue with 3 frames") and not ISSUE_NUMBER.search("tissue 5")

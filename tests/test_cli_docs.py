"""Every command has help with examples and a section in docs/cli.md, and docs/cli.md is current."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest
import typer
from typer.testing import CliRunner

from labelaudit.cli import app

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("gen_cli_docs", ROOT / "scripts" / "gen_cli_docs.py")
gen = importlib.util.module_from_spec(spec)
spec.loader.exec_module(gen)  # type: ignore[union-attr]

COMMANDS = list(typer.main.get_command(app).commands)  # type: ignore[attr-defined]


def test_the_known_commands_are_registered():
    assert {"infer", "rank", "check", "simulate", "demo"} <= set(COMMANDS)


@pytest.mark.parametrize("name", COMMANDS)
def test_command_has_help_examples_and_a_docs_section(name):
    cmd = typer.main.get_command(app).commands[name]  # type: ignore[attr-defined]
    paragraphs, examples = gen.split_help(cmd.help or "")
    assert paragraphs and len(paragraphs[0]) > 20, f"{name}: no help text"
    assert examples and all(e.startswith(f"labelaudit {name}") for e in examples), (
        f"{name}: no Examples block of `labelaudit {name} …` lines"
    )
    for p in cmd.params:
        assert (getattr(p, "help", None) or "").strip(), f"{name}: parameter {p.name} has no help"
    assert f"## `labelaudit {name}" in (ROOT / "docs" / "cli.md").read_text(), f"docs/cli.md has no section for {name}"
    r = CliRunner().invoke(app, [name, "--help"])
    assert r.exit_code == 0 and "Examples" in r.stdout


def test_docs_cli_md_is_generated_from_the_help():
    assert (ROOT / "docs" / "cli.md").read_text() == gen.render(), (
        "docs/cli.md is stale: run python scripts/gen_cli_docs.py"
    )


def test_split_help_finds_examples():
    assert gen.split_help("Do X.\n\nMore.\n\n[bold]Examples[/bold]\n\n  labelaudit x a\n\n  labelaudit x b") == (
        ["Do X.", "More."],
        ["labelaudit x a", "labelaudit x b"],
    )
    assert gen.split_help("Only text.") == (["Only text."], [])

"""``labelaudit check``: evaluate a gate file against a results folder; the exit code is the verdict."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Optional

import typer

from labelaudit.cli.app import app, handle_errors, out
from labelaudit.errors import UsageError


@app.command()
def check(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    config: Optional[Path] = typer.Option(
        None, "--config", help="Gate thresholds TOML (default: the built-in configs/gate.toml)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the rule outcomes as JSON on stdout instead of a table."),
    junit: Optional[Path] = typer.Option(None, "--junit", help="Also write the outcomes as JUnit XML to this file."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """CI gate: evaluate label-quality thresholds per class; exit 0 pass, 1 fail, 2 cannot evaluate.

    Rules (docs/ci-gate.md): minimum median JIoU-GT, maximum fraction below a JIoU-GT threshold, maximum fraction/count of boxes without points, maximum fraction over a label_error threshold, maximum failed objects and frames, per class with [class.X] overrides; and, dataset-wide, at most max_missing_per_frame missing-label candidates (objects nobody labelled) with a score of at least missing_score_threshold per frame (skipped for results of infer --no-missing). Exit 2 for unreadable, empty or incomplete results, unknown config keys or a rule that could not be evaluated: never 0 when nothing was evaluated.

    [bold]Examples[/bold]

      labelaudit check results/

      labelaudit check results/ --config ci/gate.toml --junit gate-report.xml

      labelaudit check results/ --json | jq .verdict
    """
    from labelaudit.cli.display import print_gate_table
    from labelaudit.gate import evaluate_gate, load_gate
    from labelaudit.results import open_results

    with handle_errors(debug):
        gate = load_gate(config)
        report = evaluate_gate(open_results(results), gate)
        if junit is not None:
            try:
                junit.parent.mkdir(parents=True, exist_ok=True)
                junit.write_text(report.to_junit())
            except OSError as exc:
                raise UsageError(f"{junit}: cannot write the JUnit report ({exc.strerror})") from None
        if as_json:
            sys.stdout.write(report.to_json() + "\n")
        else:
            print_gate_table(out(), report)
    raise typer.Exit(report.exit_code)

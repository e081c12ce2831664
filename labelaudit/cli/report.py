"""``labelaudit report``: one self-contained HTML review page of a results folder.

Parses the options, shows a progress bar on stderr while the gallery renders, calls
:func:`labelaudit.viz.report.build_report` and prints the written path on stdout (docs/review.md).
"""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)

from labelaudit import constants as C
from labelaudit.cli.app import EXIT_USAGE, app, err, handle_errors
from labelaudit.errors import UsageError


@app.command()
def report(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    output: Path = typer.Option(Path("labelaudit-report.html"), "-o", "--output", help="HTML file to write."),
    gate: Optional[str] = typer.Option(
        None, "--gate", help="Gate TOML whose verdict the page shows ('default': the built-in configs/gate.toml)."
    ),
    top: int = typer.Option(
        C.REPORT_TOP, "--top", help="Gallery size: the worst N by label_error and the worst N by JIoU-GT."
    ),
    eval_dir: Optional[Path] = typer.Option(
        None, "--eval", help="Output folder of `labelaudit eval` to include (summary.json and its plots)."
    ),
    dataset: Optional[Path] = typer.Option(
        None,
        "--dataset",
        help="The dataset's current location, when it moved since `infer` (for the gallery pictures).",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write one self-contained HTML review page: run summary, gate verdict, the paper's Fig. 7 plots and a gallery of the worst labels.

    Every image is embedded (no network, no JavaScript), so the file can be attached to a ticket or a dataset release. Each gallery entry has a stable anchor #<frame>-<object_index> (e.g. report.html#000123-4). Prints the path on stdout; exits 2 (after writing the page, which says so) when the results hold no evaluated object.

    [bold]Examples[/bold]

      labelaudit report results/ -o report.html

      labelaudit report results/ -o release/labels.html --gate ci/gate.toml --top 25

      labelaudit report results/ --eval eval-out/ --dataset /mnt/moved/kitti
    """
    from labelaudit.viz.report import build_report

    with handle_errors(debug):
        bar: Progress | None = None
        task = None

        def progress(done: int, total: int) -> None:
            nonlocal bar, task
            if quiet:
                return
            if bar is None:
                bar = Progress(
                    TextColumn("[bold]report[/bold] gallery"),
                    BarColumn(),
                    MofNCompleteColumn(),
                    TimeElapsedColumn(),
                    console=err(),
                )
                task = bar.add_task("gallery", total=total)
                bar.start()
            bar.update(
                task, completed=done, total=total
            )  # the candidates' pictures follow the galleries' and extend the total

        try:
            summary = build_report(
                results, output, gate=gate, top=top, eval_dir=eval_dir, dataset=dataset, progress=progress
            )
        except OSError as exc:
            raise UsageError(f"{output}: cannot write the report ({exc.strerror})") from None
        finally:
            if bar is not None:
                bar.stop()
        if not quiet:
            verdict = f", gate {summary.gate_verdict}" if summary.gate_verdict else ""
            missing = (
                ""
                if summary.missing_counted is None
                else f", {summary.missing_counted} possibly missing labels ({summary.missing_pictures} pictured)"
            )
            err().print(
                f"report: {summary.objects} objects ({summary.evaluated} evaluated), {summary.pictures} pictures{verdict}{missing}, "
                f"{summary.size_bytes / 1e6:.1f} MB in {summary.seconds:.1f} s → {escape(str(summary.path))}",
                soft_wrap=True,
            )
        typer.echo(str(summary.path))
        if summary.evaluated == 0:
            err().print("[red]error:[/red] the results hold no evaluated object; the report says so", soft_wrap=True)
            raise typer.Exit(EXIT_USAGE)

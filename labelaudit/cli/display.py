"""Everything the CLI prints with Rich: the infer progress bar and summary, the rank and gate tables.

Display only: values come from library results (:class:`~labelaudit.rank.RankResult`,
:class:`~labelaudit.gate.GateReport`, :class:`~labelaudit.infer.run.RunSummary`); every string that
comes from the data is escaped, so a class name like ``[/]`` prints as itself.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

import pyarrow as pa
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

if TYPE_CHECKING:
    from labelaudit.gate import GateReport
    from labelaudit.infer.run import ChunkResult, RunSummary
    from labelaudit.rank import MissingResult, RankResult


class RichProgress:
    """Progress bar of ``infer`` on stderr with frames/s and objects/s."""

    def __init__(self, console: Console):
        self.console = console
        self.frames = self.objects = 0

    def start(self, total_units: int, done_units: int) -> None:
        self.t0 = time.perf_counter()
        self.bar = Progress(
            TextColumn("[bold]infer[/bold]"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[rate]}"),
            TimeElapsedColumn(),
            TimeRemainingColumn(),
            console=self.console,
        )
        self.task = self.bar.add_task("infer", total=total_units, completed=done_units, rate="")
        self.bar.start()

    def advance(self, result: ChunkResult) -> None:
        self.frames += result.frames
        self.objects += result.objects
        dt = max(time.perf_counter() - self.t0, 1e-9)
        self.bar.update(
            self.task, advance=result.units, rate=f"{self.frames / dt:.1f} frames/s  {self.objects / dt:.0f} objects/s"
        )

    def stop(self) -> None:
        self.bar.stop()


def print_run_summary(console: Console, summary: RunSummary, stats: dict[str, Any]) -> None:
    """The end-of-run table of ``infer``: objects and median JIoU-GT per class, statuses, frames."""
    console.print(f"[bold]labelaudit infer[/bold] → {escape(str(summary.output))}")
    table = Table()
    table.add_column("class")
    table.add_column("objects", justify="right")
    table.add_column("median JIoU-GT", justify="right")
    for name, c in stats["classes"].items():
        med = "–" if c["median_jiou_gt"] is None else f"{c['median_jiou_gt']:.3f}"
        table.add_row(escape(name), str(c["objects"]), med)
    console.print(table)
    statuses = ", ".join(f"{escape(str(k))} {v}" for k, v in stats["by_status"].items()) or "none"
    resumed = f" ({summary.chunks_skipped} of {summary.chunks} shards already done)" if summary.chunks_skipped else ""
    retried = getattr(summary, "chunks_retried", 0)
    if retried:
        resumed += f" ({retried} shard{'s' if retried > 1 else ''} of an earlier run re-tried: they had failed frames or objects)"
    console.print(f"objects by status: {statuses}")
    console.print(
        f"frames this run: {summary.frames}{resumed}; failed frames: {summary.failed_frames}; warnings: {summary.warnings}; "
        f"wall time {summary.wall_seconds:.1f} s"
    )
    if summary.failed_frames or summary.warnings:
        console.print(f"failed frames and warnings are listed in {escape(str(summary.output / 'errors.parquet'))}")


def display_columns(table: pa.Table, by: str) -> list[str]:
    """Columns shown in the Rich table of ``rank`` (``by`` always included; empty optional ones dropped)."""
    base = [
        "frame_id",
        "object_index",
        "class_name",
        "status",
        "num_points",
        "distance",
        "jiou_gt",
        "label_error",
        "sigma_hat",
    ]
    cols = [c for c in base if c in table.schema.names]
    cols = [
        c
        for c in cols
        if c in ("frame_id", "object_index", "class_name", "status")
        or c == by
        or table.column(c).null_count < table.num_rows
    ]
    if by not in cols:
        cols.append(by)
    if by == "track_error":  # which track, and what the label contradicts in it
        cols.insert(cols.index("object_index") + 1, "object_id")
        cols.append("track_issue")
    return cols


def format_cell(value: Any) -> str:
    """Short text for a table cell."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.3f}"
    return str(value)


def print_rank_table(console: Console, result: RankResult, extra: dict[str, list[str]] | None = None) -> None:
    """Rich table of a :class:`~labelaudit.rank.RankResult`; ``extra`` adds display-only columns."""
    q = result.query
    table = result.table
    for name, values in (extra or {}).items():
        table = table.append_column(name, pa.array(values, pa.string()))
    cols = display_columns(table, q.by) + list(extra or {})
    order = "highest" if q.is_descending else "lowest"
    scope = f" with ≥ {q.min_points} points" if q.min_points else ""
    t = Table(
        title=f"worst {table.num_rows} of {result.matched} objects{scope} by {escape(q.by)} ({order} first)",
        title_justify="left",
    )
    t.add_column("#", justify="right")
    for c in cols:
        t.add_column(
            escape(c), justify="left" if c in ("frame_id", "class_name", "status") or c in (extra or {}) else "right"
        )
    for i, row in enumerate(table.select(cols).to_pylist(), start=1):
        t.add_row(str(i), *(escape(format_cell(row[c])) for c in cols))
    console.print(t)


MISSING_DISPLAY_COLUMNS = (
    "frame_id",
    "candidate_index",
    "class_name",
    "source",
    "score",
    "num_points",
    "distance",
    "cx",
    "cy",
    "length",
    "width",
    "yaw",
)
"""Columns of the Rich table of ``rank --missing`` (JSON and CSV carry every column)."""


def print_missing_table(console: Console, result: MissingResult) -> None:
    """Rich table of a :class:`~labelaudit.rank.MissingResult`: the likeliest missed labels first."""
    q = result.query
    table = result.table
    cols = [c for c in MISSING_DISPLAY_COLUMNS if c in table.schema.names]
    if q.by not in cols:
        cols.append(q.by)
    order = "highest" if q.is_descending else "lowest"
    floor = f" with score ≥ {q.min_score:g}" if q.min_score is not None else ""
    t = Table(
        title=f"{table.num_rows} of {result.matched} missing-label candidates{floor} by {escape(q.by)} ({order} first; {result.total} in the results)",
        title_justify="left",
    )
    t.add_column("#", justify="right")
    for c in cols:
        t.add_column(escape(c), justify="left" if c in ("frame_id", "class_name", "source") else "right")
    for i, row in enumerate(table.select(cols).to_pylist(), start=1):
        t.add_row(str(i), *(escape(format_cell(row[c])) for c in cols))
    console.print(t)


def print_gate_table(console: Console, report: GateReport) -> None:
    """Rich table of the gate's rule outcomes, then the verdict."""
    from labelaudit.gate import format_number

    colour = {"pass": "green", "fail": "red", "skip": "yellow", "error": "magenta"}
    t = Table(title=f"labelaudit check — gate {escape(str(report.source))}", title_justify="left")
    for c in ("scope", "rule", "value", "threshold", "objects", "result", "note"):
        t.add_column(c, justify="right" if c in ("value", "threshold", "objects") else "left", no_wrap=c != "note")
    for r in report.results:
        t.add_row(
            escape(r.scope),
            escape(r.rule),
            format_number(r.value),
            f"{r.comparison} {format_number(r.threshold)}",
            str(r.objects),
            f"[{colour[r.status]}]{r.status}[/]",
            escape(r.note),
        )
    console.print(t)
    if report.absent_classes:
        console.print(f"not in the results, not evaluated: {escape(', '.join(report.absent_classes))}")
    v = report.verdict
    console.print(
        f"[bold {'green' if v == 'PASS' else 'red'}]{v}[/] ({report.total_objects} objects; exit {report.exit_code})"
    )

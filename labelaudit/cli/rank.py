"""``labelaudit rank``: a :class:`~labelaudit.rank.RankQuery` from the options, printed as a table, JSON or CSV."""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors, out, split_list


class OutputFormat(str, Enum):
    table = "table"
    json = "json"
    csv = "csv"


@app.command()
def rank(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    by: str = typer.Option("jiou_gt", "--by", help="Numeric column to rank by (jiou_gt, label_error, track_error, sigma_hat, num_points …)."),
    top: int = typer.Option(C.DEFAULT_RANK_TOP, "--top", help="Number of rows."),
    descending: Optional[bool] = typer.Option(None, "--desc/--asc", help="Sort order (default: worst first — ascending for jiou_gt, num_points, hull_iou; descending otherwise)."),
    class_: Optional[list[str]] = typer.Option(None, "--class", help="Only these classes (repeat or comma-separate)."),
    status: Optional[list[str]] = typer.Option(None, "--status", help="Only these statuses: ok, few_points, no_points, skipped, error."),
    min_points: Optional[int] = typer.Option(None, "--min-points", help="Only objects with at least this many points."),
    max_distance: Optional[float] = typer.Option(None, "--max-distance", help="Only objects at most this far from the sensor (m)."),
    where: Optional[list[str]] = typer.Option(None, "--where", help="Extra condition COLUMN OP VALUE, e.g. 'occluded<=1' (repeat: all must hold)."),
    out_format: OutputFormat = typer.Option(OutputFormat.table, "--format", help="table (Rich), json (array of row objects) or csv."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """List the worst labels first, by JIoU-GT (lowest first) or any numeric column.

    json and csv print every column of the matching rows to stdout, for pipes (csv: list columns as JSON arrays). Rows whose --by value is null (skipped or failed objects) are left out; --where takes any column with ==, !=, >=, <=, > or <. Only the needed columns are read to sort; full rows are fetched for the top N only.

    [bold]Examples[/bold]

      labelaudit rank results/

      labelaudit rank results/ --by label_error --top 50 --class Car

      labelaudit rank results/ --status few_points --max-distance 40 --format csv > worst.csv

      labelaudit rank results/ --where 'difficulty==Easy' --where 'num_points>=50'

      labelaudit rank results/ --by track_error --where 'track_issue==size'
    """
    from labelaudit.cli.display import print_rank_table
    from labelaudit.rank import RankQuery, rank_results, to_csv, to_json
    from labelaudit.results import STATUSES, open_results

    with handle_errors(debug):
        statuses = split_list(status)
        bad = [s for s in statuses if s not in STATUSES]
        if bad:
            raise typer.BadParameter(f"unknown status {', '.join(bad)}; expected {', '.join(STATUSES)}", param_hint="--status")
        query = RankQuery(by, top, descending, split_list(class_), statuses, min_points, max_distance, tuple(where or ()))
        opened = open_results(results)
        if not opened.complete:
            err().print(f"note: {escape(str(results))} is incomplete (a run is in progress or stopped); rerun infer to finish it", soft_wrap=True)
        result = rank_results(opened, query)
        if out_format is OutputFormat.json:
            sys.stdout.write(to_json(result.table) + "\n")
        elif out_format is OutputFormat.csv:
            sys.stdout.write(to_csv(result.table))
        else:
            print_rank_table(out(), result)
        if result.matched == 0:
            err().print("no objects match the filters")

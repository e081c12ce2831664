"""``labelaudit rank``: a :class:`~labelaudit.rank.RankQuery` from the options, printed as a table, JSON or CSV."""

from __future__ import annotations

import sys
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors, out, split_list

if TYPE_CHECKING:
    import pyarrow as pa

    from labelaudit.results import Results


class OutputFormat(str, Enum):
    table = "table"
    json = "json"
    csv = "csv"


@app.command()
def rank(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    by: Optional[str] = typer.Option(
        None,
        "--by",
        help="Numeric column to rank by (default jiou_gt; label_error, track_error, sigma_hat, num_points …; with --missing: score).",
    ),
    missing: bool = typer.Option(
        False,
        "--missing",
        help="Rank the missing-label candidates (objects nobody labelled, the missing/ table) instead of the labels, highest score first.",
    ),
    top: int = typer.Option(C.DEFAULT_RANK_TOP, "--top", help="Number of rows."),
    descending: Optional[bool] = typer.Option(
        None,
        "--desc/--asc",
        help="Sort order (default: worst first — ascending for jiou_gt, num_points, hull_iou; descending otherwise).",
    ),
    class_: Optional[list[str]] = typer.Option(None, "--class", help="Only these classes (repeat or comma-separate)."),
    status: Optional[list[str]] = typer.Option(
        None, "--status", help="Only these statuses: ok, few_points, no_points, skipped, error."
    ),
    min_points: Optional[int] = typer.Option(None, "--min-points", help="Only objects with at least this many points."),
    max_distance: Optional[float] = typer.Option(
        None, "--max-distance", help="Only objects at most this far from the sensor (m)."
    ),
    where: Optional[list[str]] = typer.Option(
        None, "--where", help="Extra condition COLUMN OP VALUE, e.g. 'occluded<=1' (repeat: all must hold)."
    ),
    min_score: Optional[float] = typer.Option(
        None, "--min-score", help="With --missing: only candidates with at least this score (in [0, 1])."
    ),
    source: Optional[list[str]] = typer.Option(
        None,
        "--source",
        help="With --missing: only candidates found this way: points, detections or both (repeat or comma-separate).",
    ),
    out_format: OutputFormat = typer.Option(
        OutputFormat.table, "--format", help="table (Rich), json (array of row objects) or csv."
    ),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """List the worst labels first, by JIoU-GT (lowest first) or any numeric column; with --missing, the objects nobody labelled.

    json and csv print every column of the matching rows to stdout, for pipes (csv: list columns as JSON arrays). Rows whose --by value is null (skipped or failed objects; label_error of classes it is not validated for, with a note on stderr) are left out; --where takes any column with ==, !=, >=, <=, > or <. Only the needed columns are read to sort; full rows are fetched for the top N only.

    --missing lists the candidates of the missing/ table (docs/results-schema.md), highest score first: frame_id and candidate_index name one (`labelaudit show RESULTS FRAME --candidate K` draws it); --class, --min-score, --source, --min-points, --max-distance and --where filter them. Exit 2 when the run did not search (infer --no-missing).

    [bold]Examples[/bold]

      labelaudit rank results/

      labelaudit rank results/ --by label_error --top 50 --class Car

      labelaudit rank results/ --status few_points --max-distance 40 --format csv > worst.csv

      labelaudit rank results/ --where 'difficulty==Easy' --where 'num_points>=50'

      labelaudit rank results/ --by track_error --where 'track_issue==size'

      labelaudit rank results/ --missing --min-score 0.5 --class Car --format json
    """
    from labelaudit.cli.display import print_missing_table, print_rank_table
    from labelaudit.rank import MissingQuery, RankQuery, rank_missing, rank_results
    from labelaudit.results import STATUSES

    with handle_errors(debug):
        if missing:
            if status:
                raise typer.BadParameter(
                    "candidates have no status; filter them with --min-score, --source or --where",
                    param_hint="--status",
                )
            mquery = MissingQuery(
                by or "score",
                top,
                descending,
                split_list(class_),
                split_list(source),
                min_score,
                min_points,
                max_distance,
                tuple(where or ()),
            )
            mresult = rank_missing(_open(results), mquery)
            _print(out_format, mresult.table, lambda: print_missing_table(out(), mresult))
            if mresult.matched == 0:
                err().print(f"no candidates match the filters ({mresult.total} in the results)")
            return
        for option, value in (("--min-score", min_score), ("--source", source)):
            if value:
                raise typer.BadParameter("only with --missing (labels: use --where)", param_hint=option)
        by = by or "jiou_gt"
        statuses = split_list(status)
        bad = [s for s in statuses if s not in STATUSES]
        if bad:
            raise typer.BadParameter(
                f"unknown status {', '.join(bad)}; expected {', '.join(STATUSES)}", param_hint="--status"
            )
        query = RankQuery(
            by, top, descending, split_list(class_), statuses, min_points, max_distance, tuple(where or ())
        )
        result = rank_results(_open(results), query)
        _print(out_format, result.table, lambda: print_rank_table(out(), result))
        if result.unscored:
            listed = ", ".join(f"{c}: {n}" for c, n in result.unscored.items())
            err().print(
                f"note: label_error is null for {listed} (a class the score is not validated for, docs/label-error.md): not ranked",
                soft_wrap=True,
            )
        if result.matched == 0:
            err().print("no objects match the filters")


def _open(results: Path) -> Results:
    """Open the results folder; a run that did not finish is noted on stderr (its rows are still listed)."""
    from labelaudit.results import open_results

    opened = open_results(results)
    if not opened.complete:
        err().print(
            f"note: {escape(str(results))} is incomplete (a run is in progress or stopped); rerun infer to finish it",
            soft_wrap=True,
        )
    return opened


def _print(out_format: OutputFormat, table: pa.Table, rich_table: Callable[[], None]) -> None:
    """The ranked rows on stdout: JSON, CSV, or the Rich table ``rich_table`` prints."""
    from labelaudit.rank import to_csv, to_json

    if out_format is OutputFormat.json:
        sys.stdout.write(to_json(table) + "\n")
    elif out_format is OutputFormat.csv:
        sys.stdout.write(to_csv(table))
    else:
        rich_table()

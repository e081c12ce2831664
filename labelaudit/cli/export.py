"""``labelaudit export``: options → :func:`labelaudit.export.export_results`, its summary as a table (stderr) or JSON.

It computes nothing: the targets are :mod:`labelaudit.training`'s, the files :mod:`labelaudit.export`'s.
"""

from __future__ import annotations

import json
import sys
from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape
from rich.table import Table

from labelaudit.cli.app import app, err, handle_errors


class Encoding(str, Enum):
    box = "box"
    log_size = "log-size"
    centerpoint = "centerpoint"
    pixor = "pixor"
    residual = "residual"


class ExportFormat(str, Enum):
    parquet = "parquet"
    openpcdet = "openpcdet"
    mmdet3d = "mmdet3d"


@app.command()
def export(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer` (or one Parquet file of rows)."),
    output: Path = typer.Option(..., "-o", "--output", help="File to write: the Parquet table, or the copy of the infos pickle."),
    encoding: Encoding = typer.Option(Encoding.box, "--encoding", help="Targets: box (x,y,z,l,w,h,yaw), log-size = centerpoint (x,y,z,log l/w/h,sin,cos), pixor (dx,dy,log l,log w,sin,cos), residual (the anchor coder of OpenPCDet/mmdet3d)."),
    source: str = typer.Option("model", "--source", help="Where σ_p comes from: model (posterior covariance), num_points, hull_iou, or fixed:VAR."),
    out_format: ExportFormat = typer.Option(ExportFormat.parquet, "--format", help="parquet (keyed by frame_id, object_index, object_id), openpcdet or mmdet3d (a copy of --infos with the targets added)."),
    infos: Optional[Path] = typer.Option(None, "--infos", help="OpenPCDet kitti_infos_*.pkl / Waymo infos, or mmdet3d v2 info file to copy."),
    anchor_size: Optional[list[str]] = typer.Option(None, "--anchor-size", help="CLASS=l,w,h anchor size for --encoding residual (repeat; adds to/overrides the KITTI or Waymo defaults)."),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write per-object label uncertainty σ_p as training targets in a detector's encoding.

    Variances and covariances of the encoded targets come from the posterior covariance of each label (first-order propagation with the exact Jacobian at the label) or from a heuristic; formulas, sources and file formats: docs/training.md. The Parquet output is keyed by (frame_id, object_index, object_id); openpcdet and mmdet3d write a copy of --infos with label_std, label_cov and label_std_valid added to every object, in that file's own object order.

    Objects without targets (DontCare, classes not audited, rows without a posterior, frames missing from the results) get NaN and a False mask, never a neighbour's values; the summary (stderr, or --json on stdout) counts them by reason. Exit 2 for bad options, unreadable results, a pickle with a disallowed global, an infos file that does not match the results (the message names the first mismatching frame), or when no object got targets; nothing is written then.

    [bold]Examples[/bold]

      labelaudit export results/ -o sigma_p.parquet --encoding log-size

      labelaudit export results/ -o kitti_infos_train_sigma.pkl --format openpcdet --infos kitti_infos_train.pkl --encoding residual

      labelaudit export results/ -o kitti_infos_train_sigma.pkl --format mmdet3d --infos kitti_infos_train.pkl --source num_points

      labelaudit export results/ -o fixed.parquet --source fixed:0.01 --json
    """
    from labelaudit.export import export_results, parse_anchor_sizes

    with handle_errors(debug):
        summary = export_results(
            results,
            output,
            encoding=encoding.value,
            source=source,
            fmt=out_format.value,  # type: ignore[arg-type]
            infos=infos,
            anchor_sizes=parse_anchor_sizes(anchor_size or ()),
        )
        if as_json:
            sys.stdout.write(json.dumps(summary.to_dict(), indent=2, sort_keys=True) + "\n")
        console = err()
        t = Table(title=f"labelaudit export — {summary.encoding}, source {escape(summary.source)}", title_justify="left")
        t.add_column("what")
        t.add_column("count", justify="right")
        t.add_row("result rows", str(summary.results_rows))
        t.add_row("  with targets", str(summary.rows_with_targets))
        for reason, n in sorted(summary.rows_without_targets.items()):
            t.add_row(f"  without: {escape(reason)}", str(n))
        if summary.infos is not None:
            t.add_row("infos frames", str(summary.infos_frames))
            t.add_row("  without result rows", str(summary.infos_frames_without_results))
            t.add_row("infos objects", str(summary.infos_objects))
            t.add_row("  with targets", str(summary.infos_objects_with_targets))
            for reason, n in sorted(summary.infos_objects_without_targets.items()):
                t.add_row(f"  NaN: {escape(reason)}", str(n))
            t.add_row("result rows not in the infos", str(summary.results_rows_not_in_infos))
            t.add_row("result frames not in the infos", str(summary.results_frames_not_in_infos))
        console.print(t)
        for note in summary.notes:
            console.print(f"note: {escape(note)}", soft_wrap=True)
        console.print(f"wrote {escape(summary.output)} ({summary.format})", soft_wrap=True)

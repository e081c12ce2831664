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

from labelaudit import constants as C
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
    glenet = "glenet"
    kitti_labels = "kitti-labels"


@app.command()
def export(
    results: Path = typer.Argument(
        ..., help="Results folder written by `labelaudit infer` (or one Parquet file of rows)."
    ),
    output: Path = typer.Option(
        ...,
        "-o",
        "--output",
        help="File to write: the Parquet table, or the copy of the infos pickle; for --format glenet the folder of the copies; kitti-labels: the review folder.",
    ),
    encoding: Optional[Encoding] = typer.Option(
        None,
        "--encoding",
        help="Targets: box (x,y,z,l,w,h,yaw; the default), log-size = centerpoint (x,y,z,log l/w/h,sin,cos), pixor (dx,dy,log l,log w,sin,cos), residual (the anchor coder of OpenPCDet/mmdet3d). Not with --format glenet (it has its own).",
    ),
    source: str = typer.Option(
        "model",
        "--source",
        help="Where σ_p comes from: model (posterior covariance), num_points, hull_iou, or fixed:VAR.",
    ),
    out_format: ExportFormat = typer.Option(
        ExportFormat.parquet,
        "--format",
        help="parquet (keyed by frame_id, object_index, object_id), openpcdet or mmdet3d (a copy of --infos with the targets added), glenet (copies of --infos and --dbinfos with GLENet's 'uncertainty' added, in folder -o).",
    ),
    infos: Optional[Path] = typer.Option(
        None,
        "--infos",
        help="OpenPCDet kitti_infos_*.pkl / Waymo infos, or mmdet3d v2 info file to copy; for glenet also a folder of OpenPCDet's per-sequence Waymo infos (<seq>/<seq>.pkl).",
    ),
    dbinfos: Optional[Path] = typer.Option(
        None,
        "--dbinfos",
        help="OpenPCDet gt-database infos to copy with --format glenet (kitti_dbinfos_train.pkl, Waymo's …_waymo_dbinfos_train_sampled_1.pkl).",
    ),
    anchor_size: Optional[list[str]] = typer.Option(
        None,
        "--anchor-size",
        help="CLASS=l,w,h anchor size for --encoding residual and --format glenet (repeat; adds to/overrides the KITTI or Waymo defaults).",
    ),
    min_label_error: float = typer.Option(
        C.EXPORT_REVIEW_LABEL_ERROR,
        "--min-label-error",
        help="kitti-labels: add the suggested box (the label-error fit) of labels whose label_error is above this.",
    ),
    min_score: float = typer.Option(
        C.EXPORT_REVIEW_MIN_SCORE,
        "--min-score",
        help="kitti-labels: add the missing-label candidates whose score is at least this.",
    ),
    min_track_error: float = typer.Option(
        C.EXPORT_REVIEW_TRACK_ERROR,
        "--min-track-error",
        help="kitti-labels on Waymo / Argoverse 2 results: add the box its track expects (source track) for labels whose track_error is above this.",
    ),
    dataset: Optional[Path] = typer.Option(
        None, "--dataset", help="kitti-labels: the dataset's current location, when it moved since `infer`."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the summary as JSON on stdout."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write per-object label uncertainty σ_p as training targets in a detector's encoding; or, with --format kitti-labels, the labels to review in a labelling tool.

    Variances and covariances of the encoded targets come from the posterior covariance of each label (first-order propagation with the exact Jacobian at the label) or from a heuristic; formulas, sources and file formats: docs/training.md. The Parquet output is keyed by (frame_id, object_index, object_id); openpcdet and mmdet3d write a copy of --infos with label_std, label_cov and label_std_valid added to every object, in that file's own object order.

    --format glenet writes what GLENet's training reads instead of its CVAE's output: annos['uncertainty'] (K, 7) of every infos frame, DontCare included, and 'uncertainty' (7,) of every gt-database entry — variances of OpenPCDet's ResidualCoder targets at the class anchor (x, y, z, log l, log w, log h, sin of the heading difference), all > 0; objects without a posterior get -1, as GLENet writes them. A BEV posterior takes z and h from the class prior (counted; --model 3d infers them). How to train with them: docs/training.md.

    --format kitti-labels writes the review loop into the folder -o (docs/review.md): per frame a KITTI label_2 file with the original lines unchanged, then the suggested box of every label whose label_error is above --min-label-error and every missing-label candidate whose score is at least --min-score, the score in the 16th column; changes.csv lists each added box, review.json the counts. Boxes are converted back to the rectified camera frame exactly (they read back to the same LiDAR boxes). Other datasets (Waymo, Argoverse 2 …): the same boxes as boxes.parquet in the LiDAR frame, plus, for every tracked label whose track_error is above --min-track-error, the box the rest of its track expects in that frame (predicted centre and heading, the track's fused size): a suggestion with source track and its track_issue, beside the fit's suggestion (source fit) when the label has both.

    Objects without targets (DontCare, classes not audited, rows without a posterior, frames missing from the results) get NaN and a False mask (-1 for glenet), never a neighbour's values; the summary (stderr, or --json on stdout) counts them by reason. Exit 2 for bad options, unreadable results, a pickle with a disallowed global, an infos file that does not match the results (the message names the first mismatching frame), or when no object got targets; nothing is written then.

    [bold]Examples[/bold]

      labelaudit export results/ -o sigma_p.parquet --encoding log-size

      labelaudit export results/ -o kitti_infos_train_sigma.pkl --format openpcdet --infos kitti_infos_train.pkl --encoding residual

      labelaudit export results/ -o kitti_infos_train_sigma.pkl --format mmdet3d --infos kitti_infos_train.pkl --source num_points

      labelaudit export results/ -o fixed.parquet --source fixed:0.01 --json

      labelaudit export results/ --format glenet --infos kitti_infos_train.pkl --dbinfos kitti_dbinfos_train.pkl -o glenet/

      labelaudit export results/ --format glenet --infos waymo_processed_data_v0_5_0/ --dbinfos waymo_processed_data_v0_5_0_waymo_dbinfos_train_sampled_1.pkl -o glenet/

      labelaudit export results/ --format kitti-labels -o review/ --min-score 0.6

      labelaudit export av2-results/ --format kitti-labels -o review/ --min-track-error 0.9
    """
    from labelaudit.export import export_results, parse_anchor_sizes

    with handle_errors(debug):
        if out_format is ExportFormat.kitti_labels:
            given = (
                ("--infos", infos is not None),
                ("--dbinfos", dbinfos is not None),
                ("--anchor-size", bool(anchor_size)),
                ("--encoding", encoding is not None),
                ("--source", source != "model"),
            )
            for option, used in given:
                if used:
                    raise typer.BadParameter(
                        "is for the training targets (parquet, openpcdet, mmdet3d, glenet), not --format kitti-labels",
                        param_hint=option,
                    )
            _export_review(results, output, min_label_error, min_score, min_track_error, dataset, as_json)
            return
        for option, given in (("--min-label-error", min_label_error != C.EXPORT_REVIEW_LABEL_ERROR), ("--min-score", min_score != C.EXPORT_REVIEW_MIN_SCORE),
                              ("--min-track-error", min_track_error != C.EXPORT_REVIEW_TRACK_ERROR), ("--dataset", dataset is not None)):  # fmt: skip
            if given:
                raise typer.BadParameter("only with --format kitti-labels", param_hint=option)
        summary = export_results(
            results,
            output,
            encoding=None if encoding is None else encoding.value,
            source=source,
            fmt=out_format.value,  # type: ignore[arg-type]
            infos=infos,
            anchor_sizes=parse_anchor_sizes(anchor_size or ()),
            dbinfos=dbinfos,
        )
        if as_json:
            sys.stdout.write(json.dumps(summary.to_dict(), indent=2, sort_keys=True) + "\n")
        console = err()
        t = Table(
            title=f"labelaudit export — {summary.encoding}, source {escape(summary.source)}", title_justify="left"
        )
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
                t.add_row(f"  {'-1' if summary.format == 'glenet' else 'NaN'}: {escape(reason)}", str(n))
            t.add_row("result rows not in the infos", str(summary.results_rows_not_in_infos))
            t.add_row("result frames not in the infos", str(summary.results_frames_not_in_infos))
        if summary.dbinfos is not None:
            t.add_row("gt-database objects", str(summary.dbinfos_objects))
            t.add_row("  with values", str(summary.dbinfos_objects_with_targets))
            for reason, n in sorted(summary.dbinfos_objects_without_targets.items()):
                t.add_row(f"  -1: {escape(reason)}", str(n))
        if summary.format == "glenet":
            t.add_row("z, h from the class prior", str(summary.objects_z_h_from_prior))
        console.print(t)
        for note in summary.notes:
            console.print(f"note: {escape(note)}", soft_wrap=True)
        for path in summary.outputs or [summary.output]:
            console.print(f"wrote {escape(path)} ({summary.format})", soft_wrap=True)


def _export_review(
    results: Path,
    output: Path,
    min_label_error: float,
    min_score: float,
    min_track_error: float,
    dataset: Optional[Path],
    as_json: bool,
) -> None:
    """``--format kitti-labels``: :func:`labelaudit.review.export_review`, its counts on stderr (or JSON on stdout)."""
    from labelaudit.review import export_review

    summary = export_review(
        results,
        output,
        min_label_error=min_label_error,
        min_score=min_score,
        dataset=dataset,
        min_track_error=min_track_error,
    )
    if as_json:
        sys.stdout.write(json.dumps(summary.to_dict(), indent=2, sort_keys=True) + "\n")
    console = err()
    what = "label_2 files" if summary.format == "kitti-labels" else "frames in boxes.parquet"
    console.print(
        f"review: {summary.frames_written} {what} ({summary.frames_changed} changed): {summary.labels} labels, "
        f"{summary.suggested} suggested boxes (label_error > {summary.min_label_error:g}), "
        + (
            f"{summary.track_suggested} boxes from tracks (track_error > {summary.min_track_error:g}), "
            if summary.format == "parquet"
            else ""
        )
        + f"{summary.missing} missing-label candidates (score ≥ {summary.min_score:g})",
        soft_wrap=True,
    )
    if not summary.missing_searched:
        console.print(
            "note: the results have no missing-label table (infer --no-missing): no candidates added", soft_wrap=True
        )
    for fid, why in list(summary.unreviewed_frames.items())[:10]:
        console.print(f"warning: frame {escape(fid)} not reviewed: {escape(why)}", soft_wrap=True)
    if len(summary.unreviewed_frames) > 10:
        console.print(
            f"warning: … {len(summary.unreviewed_frames) - 10} more frames not reviewed (review.json lists them)",
            soft_wrap=True,
        )
    console.print(f"wrote {escape(summary.output)} (changes.csv lists every added box)", soft_wrap=True)

"""``labelaudit show``: a bird's-eye-view picture of one label (or of a whole frame) as PNG.

Parses the options, calls :mod:`labelaudit.viz` and prints the written path on stdout; the
picture is recomputed from the dataset with the run's own configuration (docs/review.md).
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors
from labelaudit.errors import UsageError


class ShowBy(str, Enum):
    jiou_gt = "jiou_gt"
    label_error = "label_error"


@app.command()
def show(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    frame: str = typer.Argument(
        ...,
        help="Frame id as in the results (KITTI '000123', Waymo '<segment>:<timestamp>', Argoverse 2 '<log_id>:<timestamp_ns>').",
    ),
    object_index: Optional[int] = typer.Argument(
        None, metavar="[OBJECT]", help="object_index of the label in the frame; omit it for the whole frame."
    ),
    output: Optional[Path] = typer.Option(
        None, "-o", "--output", help="PNG file to write (default: show-<frame>[-<object>].png)."
    ),
    dataset: Optional[Path] = typer.Option(
        None, "--dataset", help="The dataset's current location, when it moved since `infer` (default: the manifest's)."
    ),
    size: Optional[str] = typer.Option(
        None,
        "--size",
        help=f"Picture size WIDTHxHEIGHT in pixels (default {C.SHOW_SIZE[0]}x{C.SHOW_SIZE[1]}; a frame {C.SHOW_FRAME_SIZE[0]}x{C.SHOW_FRAME_SIZE[1]}).",
    ),
    by: ShowBy = typer.Option(ShowBy.jiou_gt, "--by", help="Whole frame: colour the boxes by this score."),
    worst: int = typer.Option(C.SHOW_FRAME_WORST, "--worst", help="Whole frame: number this many worst boxes."),
    candidate: Optional[int] = typer.Option(
        None,
        "--candidate",
        help="Draw this missing-label candidate of the frame (candidate_index, as `rank --missing` prints it) close up, instead of a label.",
    ),
    min_score: float = typer.Option(
        C.SHOW_MISSING_MIN_SCORE,
        "--min-score",
        help="Whole frame: draw the missing-label candidates with at least this score.",
    ),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Draw one label with its spatial distribution p_G, a whole frame's boxes coloured by a score, or one missing-label candidate.

    A whole frame also draws its missing-label candidates (objects nobody labelled, the missing/ table) with a score of at least --min-score: magenta, dashed, tagged M<candidate_index> and their score, with a legend; the labels of classes not audited (thin, blue) and, for an Argoverse 2 log with its map, the drivable area its labels stay within 5 m of (orange, dashed). --candidate K draws candidate K close up: the points inside it coloured by height, the labels around it, its score and evidence.

    One object: its crop's points coloured by height, the labeled box, p_G as a heatmap, the 1-σ ellipses of its corners (C1 nearest the sensor), the suggested box of the label-error fit, the direction to the sensor, a scale bar and the row's numbers; for a tracked object (Waymo, Argoverse 2) also its labels in the 3 frames before and after, moved into this frame through the world frame (blue earlier, red later), with its track_error and the track's fused size. Everything is recomputed from the dataset with the run's parameters, so the picture matches the row. Prints the PNG's path on stdout.

    [bold]Examples[/bold]

      labelaudit show results/ 000123 4 -o worst.png

      labelaudit show results/ 000123 --by label_error -o frame.png

      labelaudit show results/ 000123 4 --dataset /mnt/new/kitti --size 900x800

      labelaudit show results/ 000123 --candidate 0 -o missing.png
    """
    from labelaudit.results import open_results
    from labelaudit.viz.objects import (
        ViewError,
        candidate_row,
        frame_candidates,
        frame_label_rows,
        frame_rows,
        load_frame,
        object_row,
        open_source,
        recompute,
        track_view,
    )
    from labelaudit.viz.show import parse_size, render_candidate, render_frame, render_object

    with handle_errors(debug):
        if worst < 0:
            raise typer.BadParameter(f"must be ≥ 0, got {worst}", param_hint="--worst")
        try:
            px = (
                parse_size(size)
                if size
                else (C.SHOW_SIZE if object_index is not None or candidate is not None else C.SHOW_FRAME_SIZE)
            )
        except ValueError as exc:
            raise typer.BadParameter(str(exc), param_hint="--size") from None
        if candidate is not None and object_index is not None:
            raise typer.BadParameter("draw either an OBJECT or a --candidate, not both", param_hint="--candidate")
        if not 0.0 <= min_score <= 1.0:
            raise typer.BadParameter(f"must be in [0, 1], got {min_score}", param_hint="--min-score")
        opened = open_results(results)
        cand = candidate_row(opened, frame, candidate) if candidate is not None else None
        try:
            rows = frame_rows(opened, frame)
        except ViewError:
            if object_index is not None or (cand is None and not frame_candidates(opened, frame)):
                raise
            rows = opened.dataset.schema.empty_table()  # a frame without labels, with candidates
        row = object_row(rows, object_index) if object_index is not None else None
        source = open_source(opened, dataset)
        for note in source.notes:
            err().print(f"warning: {escape(note)}", soft_wrap=True)
        if cand is not None:
            fr = load_frame(source, frame)
            png = render_candidate(frame, fr.points, cand, frame_label_rows(fr), px, fr.sensor_origin).png
        elif row is not None:
            audit = recompute(source, row)
            for col, (want, got) in audit.mismatches(rtol=1e-6).items():
                err().print(
                    f"warning: recomputed {col} = {got} but the row says {want} (dataset or labelaudit changed since infer)",
                    soft_wrap=True,
                )
            png = render_object(audit, px, track=track_view(opened, row)).png
        else:
            fr = load_frame(source, frame)
            shown = [c for c in frame_candidates(opened, frame) if c["score"] >= min_score]
            listed = rows.to_pylist()
            with_row = {int(r["object_index"]) for r in listed}
            others = fr.boxes[[i for i in range(len(fr.boxes)) if i not in with_row]]
            png = render_frame(
                frame, fr.points, listed, by.value, px, worst, fr.sensor_origin, shown, other_labels=others, roi=fr.roi
            ).png
        safe = frame.replace("/", "_").replace(":", "_")
        which = (
            f"-{object_index}" if object_index is not None else f"-missing-{candidate}" if candidate is not None else ""
        )
        out = output or Path(f"show-{safe}{which}.png")
        _write_png(png, out)
        typer.echo(str(out))


def _write_png(png: bytes, path: Path) -> None:
    """Atomic write (temporary dot-file, then rename)."""
    import os

    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        tmp.write_bytes(png)
        os.replace(tmp, path)
    except OSError as exc:
        raise UsageError(f"{path}: cannot write the picture ({exc.strerror})") from None

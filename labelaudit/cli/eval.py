"""``labelaudit eval``: the Typer command and its Rich tables (the library is :mod:`labelaudit.evaluate`).

Parses the options, calls :func:`labelaudit.evaluate.run.run_eval`, prints the AP table (or the
JSON summary) on stdout and progress on stderr, writes EVAL_DIR. Exit 0 when something was
evaluated, 2 for bad input or when nothing could be evaluated.
"""

from __future__ import annotations

import json
import sys
from enum import Enum
from pathlib import Path
from typing import Any, Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from labelaudit import constants as C
from labelaudit.cli.app import EXIT_USAGE, DatasetFormat, app, err, handle_errors, out, split_list
from labelaudit.errors import UsageError
from labelaudit.evaluate.cells import LET_INTERP, LET_METRICS, METRIC_NAMES


class View(str, Enum):
    bev = "bev"
    three_d = "3d"


class DetFormat(str, Enum):
    auto = "auto"
    kitti = "kitti"
    waymo = "waymo"
    parquet = "parquet"
    av2 = "av2"


class EvalOutput(str, Enum):
    table = "table"
    json = "json"


class Interp(str, Enum):
    r40 = "R40"
    r11 = "R11"


class StderrProgress:
    """Stage messages and a JIoU pair counter on stderr."""

    def __init__(self, console: Console, quiet: bool):
        self.console = console
        self.quiet = quiet
        self._last = -1

    def stage(self, message: str) -> None:
        if not self.quiet:
            self.console.print(f"[dim]eval:[/dim] {escape(message)}", soft_wrap=True)

    def pairs(self, done: int, total: int) -> None:
        pct = int(100 * done / max(total, 1))
        if not self.quiet and total > 2000 and pct // 25 != self._last:
            self._last = pct // 25
            self.console.print(f"[dim]eval:[/dim] JIoU {done}/{total} pairs")

    def infer_progress(self) -> Any:
        if self.quiet:
            return None
        from labelaudit.cli.display import RichProgress

        return RichProgress(self.console)


def _fmt(v: Any, digits: int = 1) -> str:
    return "–" if v is None else f"{v:.{digits}f}"


def print_eval_tables(console: Console, summary: dict[str, Any], interp: str = "R40", brief: bool = False) -> None:
    """AP per class × difficulty × metric at the usual threshold and mAP 0.5:0.9; mean overlaps by distance.

    ``brief``: the AP table and the notes only (the demo).
    """
    meta = summary["metric"]
    ap_all = summary["ap"] + (summary.get("probabilistic_ap") or [])
    metrics = [m for m in METRIC_NAMES if m not in LET_METRICS and any(r["metric"] == m for r in ap_all)]
    let = {
        (r["class"], r["difficulty"], r["metric"]): r
        for r in ap_all
        if r["metric"] in LET_METRICS and r["interp"] == LET_INTERP
    }
    ap = {(r["class"], r["difficulty"], r["metric"], r["threshold"], r["interp"]): r for r in ap_all}
    mp = {(r["class"], r["difficulty"], r["metric"], r["interp"]): r for r in summary["map"]}
    lo, hi = meta["map_thresholds"][0], meta["map_thresholds"][-1]
    t = Table(
        title=f"AP|{interp} (%), {meta['view'].upper()} — at the usual threshold and mean over {lo:g}:{meta['map_thresholds'][1] - lo:.2g}:{hi:g}",
        title_justify="left",
    )
    for c in ("class", "difficulty", "GT", "det"):
        t.add_column(c, justify="left" if c in ("class", "difficulty") else "right")
    for m in metrics:
        t.add_column(f"{METRIC_NAMES[m]}@t", justify="right")
    for m in metrics:
        t.add_column(f"mAP {METRIC_NAMES[m]}", justify="right")
    let_metrics = [m for m in LET_METRICS if any(k[2] == m for k in let)]
    for m in let_metrics:
        t.add_column(METRIC_NAMES[m], justify="right")
    for cls in summary["classes"]:
        th = meta["usual_thresholds"][cls]
        for diff in meta["difficulties"]:
            first = ap.get((cls, diff, "iou", th, interp), {})
            row = [escape(cls) + f" (t={th:g})", diff, str(first.get("num_gt", 0)), str(first.get("num_det", 0))]
            row += [_fmt(ap.get((cls, diff, m, th, interp), {}).get("ap")) for m in metrics]
            row += [_fmt(mp.get((cls, diff, m, interp), {}).get("map")) for m in metrics]
            row += [_fmt(let.get((cls, diff, m), {}).get("ap")) for m in let_metrics]
            t.add_row(*row)
    console.print(t)
    if let_metrics:
        lm = meta.get("let", {})
        iou = ", ".join(f"{escape(c)} {v:g}" for c, v in lm.get("min_let_iou", {}).items())
        console.print(
            f"LET-AP / LET-APL: Waymo's longitudinal-error-tolerant AP (3D, LET-IoU ≥ {iou}; range from the camera, tolerance "
            f"max({lm.get('tolerance_fraction', C.EVAL_LET_TOLERANCE_FRACTION):g}·r, {lm.get('min_tolerance_m', C.EVAL_LET_MIN_TOLERANCE):g} m); "
            "Waymo's AP integration, not R40/R11; docs/eval.md)",
            soft_wrap=True,
        )
    few = sorted(
        {(r["class"], r["difficulty"]) for r in summary["ap"] if r["num_gt"] and r["num_gt"] < C.EVAL_RECALL_POINTS - 1}
    )
    if few:
        cells = ", ".join(f"{c} {d}" for c, d in few)
        console.print(
            f"note: fewer than {C.EVAL_RECALL_POINTS - 1} GT boxes in {escape(cells)}: the devkit then samples recall per true positive, so AP there is coarse (docs/eval.md)",
            soft_wrap=True,
        )
    if brief:
        for note in summary["notes"]:
            console.print(f"note: {escape(note)}", soft_wrap=True)
        return

    bins = ["all", *meta["distance_bins"]]
    mo = {(r["class"], r["difficulty"], r["distance_bin"], r["metric"]): r for r in summary["mean_overlap_by_class"]}
    metrics = [m for m in metrics if any(r["metric"] == m for r in summary["mean_overlap_by_class"])]
    t2 = Table(
        title=f"mean overlap of matched detections (IoU > {meta['association_min_iou']:g}) by GT distance (m)",
        title_justify="left",
    )
    for c in ("class", "difficulty", "metric", *bins):
        t2.add_column(c, justify="left" if c in ("class", "difficulty", "metric") else "right")
    for cls in summary["classes"]:
        for diff in meta["difficulties"]:
            for m in metrics:
                cells = []
                for b in bins:
                    r = mo.get((cls, diff, b, m))
                    cells.append("–" if not r or r["mean"] is None else f"{r['mean']:.3f} ({r['count']})")
                t2.add_row(escape(cls), diff, METRIC_NAMES[m], *cells)
    console.print(t2)

    if summary.get("probabilistic"):
        t3 = Table(
            title="probabilistic detections: recall at JIoU thresholds, own distribution vs as deterministic",
            title_justify="left",
        )
        for c in ("class", "difficulty", "threshold", "recall (own)", "recall (det.)", "gain", "AP (own)", "AP (det.)"):
            t3.add_column(c, justify="left" if c in ("class", "difficulty") else "right")
        for r in summary["probabilistic"]:
            if r["difficulty"] != meta["headline_difficulty"]:
                continue
            t3.add_row(
                escape(r["class"]),
                r["difficulty"],
                f"{r['threshold']:g}",
                f"{r['recall_probabilistic']:.3f}",
                f"{r['recall_deterministic']:.3f}",
                f"{r['recall_gain']:+.3f}",
                _fmt(r["ap_probabilistic"]),
                _fmt(r["ap_deterministic"]),
            )
        console.print(t3)
    c = summary["counts"]
    console.print(
        f"{c['frames']} frames, {c['gt']} GT boxes, {c['detections']} detections; labels: {escape(summary['labels']['source'])} "
        f"({c['labels_used']} used, {c['labels_without_covariance']} without covariance); JIoU pairs {c['jiou_pairs']}",
        soft_wrap=True,
    )
    for note in summary["notes"]:
        console.print(f"note: {escape(note)}", soft_wrap=True)


@app.command("eval")
def eval_command(
    dataset: Path = typer.Argument(
        ...,
        help="Labelled dataset as `infer` reads it (KITTI root, Waymo v2 folder, Waymo v1 .tfrecord, Argoverse 2 folder).",
    ),
    detections: Path = typer.Argument(
        ...,
        help="Detections: KITTI result folder (<frame>.txt), Waymo Objects .bin, Argoverse 2 .feather, or labelaudit Parquet.",
    ),
    results: Optional[Path] = typer.Option(
        None, "--results", help="`infer` results folder with the labels' covariances (default: infer them now)."
    ),
    output: Optional[Path] = typer.Option(
        None, "-o", "--output", help="EVAL_DIR: summary.json, detections.parquet, PNG plots."
    ),
    classes: Optional[list[str]] = typer.Option(
        None,
        "--classes",
        help="Classes to evaluate (comma-separate or repeat; default: Car, Pedestrian, Cyclist — Waymo Vehicle, …; AV2 REGULAR_VEHICLE, … — those detected at least once).",
    ),
    view: View = typer.Option(
        View.bev,
        "--metric",
        help="Overlap in bird's-eye view (bev) or 3D; the label covariances must come from the same model.",
    ),
    out_format: EvalOutput = typer.Option(
        EvalOutput.table, "--format", help="table (Rich) or json (the summary document, one flat record per AP cell)."
    ),
    interp: Interp = typer.Option(
        Interp.r40, "--interp", help="AP interpolation shown in the table (JSON always has both)."
    ),
    dataset_format: DatasetFormat = typer.Option(
        DatasetFormat.auto, "--dataset-format", help="Dataset format; auto detects it."
    ),
    detections_format: DetFormat = typer.Option(
        DetFormat.auto, "--detections-format", help="Detections format; auto detects it."
    ),
    config: Optional[Path] = typer.Option(
        None, "--config", help="Model config TOML (as for infer; default: the built-in one of the format)."
    ),
    split: Optional[str] = typer.Option(
        None, "--split", help="KITTI ImageSets split (val, …) / Waymo or Argoverse 2 split folder."
    ),
    limit: Optional[int] = typer.Option(
        None, "--limit", help="Only the first N frames (KITTI) / segments (Waymo) / logs (Argoverse 2)."
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Worker processes for JIoU and label inference (default: all cores)."
    ),
    let: bool = typer.Option(
        False,
        "--let",
        help="Also Waymo's LET-3D-AP and LET-3D-APL (longitudinal-error-tolerant: depth errors along the camera's line of sight forgiven up to max(10 % of range, 0.5 m); APL charges them); records with metric let / let_apl.",
    ),
    lenient: bool = typer.Option(
        False,
        "--lenient",
        help="Leave out (and report) frames with an unreadable label or detection, instead of stopping.",
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress messages."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Evaluate a detector with IoU, JIoU and JIoU-ratio: AP that respects label uncertainty.

    Matching and AP follow the official KITTI object devkit (difficulties, DontCare, neighbouring classes, greedy matching by score, R40 and R11; KITTI overlaps in the camera frame as the devkit takes them); the same procedure then runs with the overlap replaced by JIoU (detection vs the uncertain label) and JIoU-ratio (JIoU / JIoU-GT). --let adds Waymo's LET-3D-AP and LET-3D-APL, which forgive depth errors along the camera's line of sight. See docs/eval.md.

    [bold]Examples[/bold]

      labelaudit eval /data/kitti pointgnn/data --split val --results kitti-results/ -o eval-out/

      labelaudit eval sim/ sim/detections --results sim-results/ --format json | jq '.map[] | select(.metric=="jiou")'

      labelaudit eval /data/waymo_v2/validation preds.bin --metric 3d --classes Vehicle -o eval-waymo/

      labelaudit eval /data/av2/sensor detections.feather --split val -o eval-av2/
    """
    from labelaudit.evaluate.output import write_eval_dir
    from labelaudit.evaluate.run import EvalRequest, nothing_evaluated, run_eval

    with handle_errors(debug):
        if workers is not None and workers < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {workers}", param_hint="--workers")
        if limit is not None and limit < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {limit}", param_hint="--limit")
        request = EvalRequest(
            dataset=dataset,
            detections=detections,
            results=results,
            output=output,
            dataset_format=dataset_format.value,
            detections_format=detections_format.value,
            classes=split_list(classes) or None,
            view=view.value,
            config=config,
            split=split,
            limit=limit,
            workers=workers,
            strict=not lenient,
            debug=debug,
            let=let,
        )
        console = err()
        result = run_eval(request, StderrProgress(console, quiet))
        summary = result.summary
        if output is not None:
            try:
                files = write_eval_dir(result, output)
            except OSError as exc:
                raise UsageError(f"{output}: cannot write the evaluation ({exc.strerror})") from None
            if not quiet:
                console.print(
                    f"wrote {len(files)} files to {escape(str(output))}: " + ", ".join(escape(p.name) for p in files),
                    soft_wrap=True,
                )
        if out_format is EvalOutput.json:
            sys.stdout.write(json.dumps(summary, indent=2, sort_keys=True) + "\n")
        else:
            print_eval_tables(out(), summary, interp.value)
        if nothing_evaluated(summary):
            console.print(
                "[red]error:[/red] nothing was evaluated: no ground-truth box of the evaluated classes counts at any difficulty",
                soft_wrap=True,
            )
            raise typer.Exit(EXIT_USAGE)

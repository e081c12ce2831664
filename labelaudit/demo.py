"""The demo loop on simulated data: simulate → infer → rank → check → eval → report, with the simulator's ground truth.

:func:`run_demo` does the work and returns what a caller shows (the ranked tables with an
``injected`` column from the simulator's manifest, the gate report, the evaluation of a synthetic
detector); it reports its steps through a callback and prints nothing itself (``labelaudit demo``
prints, :mod:`labelaudit.cli.demo`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable

import pyarrow as pa
import pyarrow.parquet as pq
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.evaluate.output import write_eval_dir
from labelaudit.evaluate.run import EvalRequest, run_eval
from labelaudit.gate import GateReport, evaluate_gate, load_gate
from labelaudit.infer.run import InferRequest, Progress, RunSummary, infer_dataset
from labelaudit.rank import RankQuery, RankResult, rank_results
from labelaudit.results import open_results
from labelaudit.sim.dataset import simulate_dataset
from labelaudit.sim.detector import DetectorSpec, simulate_detections
from labelaudit.sim.noise import NoiseSpec
from labelaudit.viz.report import build_report

DEMO_NOISE = NoiseSpec(
    fraction=0.2,
    center_std=C.SIM_BENCH_NOISE[0],
    size_std=C.SIM_BENCH_NOISE[1],
    yaw_std=C.SIM_BENCH_NOISE[2],
    gross_fraction=0.05,
)
"""The demo's label noise: the label-error benchmark's jitter on 20 % of vehicles, gross errors on 5 %."""

DEMO_QUERIES = (RankQuery(top=10, min_points=1), RankQuery(by="label_error", top=10))
"""Lowest JIoU-GT among boxes with points (all point-less boxes are equally uncertain), highest label_error."""


@dataclass
class DemoRun:
    """What the demo produced: where the data and results are, the ranked tables, the gate verdict."""

    data: Path
    results: Path
    ranked: list[tuple[RankResult, list[str]]] = field(default_factory=list)  # (ranking, injected kind per row)
    gate: GateReport | None = None
    evaluation: dict[str, Any] | None = None  # summary of the synthetic detector's evaluation (labelaudit eval)
    eval_dir: Path | None = None  # its EVAL_DIR
    report: Path | None = None  # the HTML review page
    missing: list[dict[str, Any]] = field(
        default_factory=list
    )  # missing-label candidates (score ≥ DEMO_MISSING_SCORE), each with the dropped label it found (or None)
    dropped: int = 0  # vehicle labels the simulator left out (DEMO_DROP_FRACTION)


def injected_by_object(manifest: Path) -> dict[str, str]:
    """object_id → perturbation kind from a simulator manifest (empty when unreadable)."""
    try:
        t = pq.read_table(manifest, columns=["object_id", "perturbation"])
    except (OSError, pa.ArrowInvalid, KeyError):
        return {}
    return dict(zip(t.column("object_id").to_pylist(), t.column("perturbation").to_pylist()))


def missing_found(results: Path, manifest: Path) -> tuple[list[dict[str, Any]], int]:
    """The missing-label candidates of ``results`` with score ≥ ``DEMO_MISSING_SCORE`` (nearest first),
    each with ``found``: the object id of the label the simulator dropped within 1 m of it (None
    when it is no dropped label), and how many vehicle labels the simulator dropped."""
    import math

    from labelaudit.results import read_missing

    try:
        man = pq.read_table(
            manifest, columns=["frame_id", "scene_index", "class_name", "dropped", "true_cx", "true_cy"]
        ).to_pylist()
    except (OSError, pa.ArrowInvalid, KeyError):
        man = []
    dropped = [m for m in man if m["dropped"]]
    rows = [r for r in read_missing(results).to_pylist() if r["score"] >= C.DEMO_MISSING_SCORE]
    for r in rows:
        hit = [
            m
            for m in dropped
            if m["frame_id"] == r["frame_id"] and math.hypot(m["true_cx"] - r["cx"], m["true_cy"] - r["cy"]) <= 1.0
        ]
        r["found"] = f"{hit[0]['class_name']} (scene object {hit[0]['scene_index']})" if hit else None
    return rows, len(dropped)


def run_demo(
    folder: Path,
    frames: int = C.DEMO_FRAMES,
    workers: int | None = None,
    *,
    say: Callable[[str], Any] = lambda message: None,
    progress: Progress | None = None,
    after_infer: Callable[[RunSummary], Any] = lambda summary: None,
    report: Path | None = None,
    debug: bool = False,
) -> DemoRun:
    """Simulate ``frames`` frames with injected label errors into ``folder``, audit, rank and gate them,
    evaluate a synthetic detector on them and write the review page.

    ``say`` receives one line per step (Rich markup; paths in it are escaped); ``progress`` is the infer progress sink;
    ``after_infer`` gets the infer run summary before the ranking starts; the HTML review page goes
    to ``report`` (default ``folder/report.html``).
    """
    data, results = folder / "sim-kitti", folder / "results"
    say(f"[bold]1/6 simulate[/bold] {frames} frames with injected label errors → {escape(str(data))}")
    simulate_dataset(
        data,
        frames=frames,
        seed=0,
        noise=DEMO_NOISE,
        progress=progress is not None,
        workers=workers or os.cpu_count() or 1,
        overwrite=True,
        drop_fraction=C.DEMO_DROP_FRACTION,
    )
    say(f"[bold]2/6 infer[/bold] {escape(str(data))} → {escape(str(results))}")
    after_infer(
        infer_dataset(InferRequest(data, results, "kitti", workers=workers, overwrite=True, debug=debug), progress)
    )
    run = DemoRun(data, results)
    run.missing, run.dropped = missing_found(results, data / "manifest.parquet")
    opened = open_results(results)
    say(
        "[bold]3/6 rank[/bold] the worst labels; 'injected' is the simulator's ground truth "
        "(none = exact label). Boxes without points are all equally uncertain (prior only), so they are left out here."
    )
    truth = injected_by_object(data / "manifest.parquet")
    for query in DEMO_QUERIES:
        if (
            query.by not in opened.columns
            or opened.read([query.by]).column(query.by).null_count == opened.dataset.count_rows()
        ):
            continue
        ranked = rank_results(opened, query)
        run.ranked.append((ranked, [truth.get(o, "?") for o in ranked.table.column("object_id").to_pylist()]))
    say("[bold]4/6 check[/bold] the built-in gate (configs/gate.toml)")
    run.gate = evaluate_gate(opened, load_gate(None))
    run.eval_dir = folder / "eval"
    det = simulate_detections(data, DetectorSpec(), seed=0)
    say(
        f"[bold]5/6 eval[/bold] a synthetic detector ({det.detections} detections: localisation noise, misses, false positives) "
        f"against the labels and their uncertainty — IoU, JIoU and JIoU-ratio AP → {escape(str(run.eval_dir))}"
    )
    evaluated = run_eval(
        EvalRequest(
            dataset=data,
            detections=det.folder,
            results=results,
            output=run.eval_dir,
            classes=("Car",),
            workers=workers,
            debug=debug,
        )
    )
    write_eval_dir(evaluated, run.eval_dir)
    run.evaluation = evaluated.summary
    run.report = Path(report) if report is not None else folder / "report.html"
    say(
        f"[bold]6/6 report[/bold] the HTML review page (plots, the worst labels' pictures, the evaluation) → {escape(str(run.report))}"
    )
    build_report(results, run.report, gate="default", eval_dir=run.eval_dir)
    return run

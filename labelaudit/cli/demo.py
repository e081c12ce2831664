"""``labelaudit demo``: run :func:`labelaudit.demo.run_demo` and print its tables."""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from labelaudit import constants as C
from labelaudit.cli.app import app, err, handle_errors, out


def print_missing_found(run: object) -> None:
    """The demo's missing-label candidates and which dropped labels they found, on stdout."""
    rows, dropped = getattr(run, "missing", []), getattr(run, "dropped", 0)
    found = sum(1 for r in rows if r["found"])
    o = out()
    o.print(
        f"missing labels: the simulator dropped {dropped} vehicle label(s); {len(rows)} candidate(s) with score ≥ {C.DEMO_MISSING_SCORE:g}, "
        f"{found} of them at a dropped label (RESULTS/missing/, docs/missing.md)",
        soft_wrap=True,
    )
    for r in rows[:10]:
        what = f"the dropped {r['found']}" if r["found"] else "no dropped label"
        o.print(
            f"  frame {escape(r['frame_id'])} candidate {r['candidate_index']}: {r['class_name']} at ({r['cx']:.1f}, {r['cy']:.1f}) m, "
            f"{r['num_points']} points, score {r['score']:.2f}, source {r['source']} → {what}",
            soft_wrap=True,
        )


@app.command()
def demo(
    folder: Optional[Path] = typer.Argument(
        None, help="Where to put the simulated data and results (default: a temporary folder)."
    ),
    frames: int = typer.Option(C.DEMO_FRAMES, "--frames", help="Simulated frames."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (default: all cores)."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Simulate a small dataset with injected label errors, audit it, rank the worst, run the gate, evaluate a detector.

    Shows the whole loop in seconds: simulate (12 frames, 20 % jittered and 5 % grossly wrong vehicle labels, 10 % left out) → infer → rank (the worst boxes with points, and by label_error, with the simulator's ground truth `injected`: none, jitter, shift, swap_lw, yaw90) → check with the built-in gate → eval (a synthetic detector scored with IoU, JIoU and JIoU-ratio AP, docs/eval.md) → missing labels (the candidates the search found, and which left-out labels they are) → report (an HTML review page: FOLDER/report.html, or ./labelaudit-demo-report.html without FOLDER). Exits 0 when the loop ran (whatever the gate verdict); pass FOLDER to keep the data and results (default: a temporary folder, deleted afterwards).

    [bold]Examples[/bold]

      labelaudit demo

      labelaudit demo demo-out/ --frames 30
    """
    from labelaudit.cli.display import RichProgress, print_gate_table, print_rank_table, print_run_summary
    from labelaudit.cli.eval import print_eval_tables
    from labelaudit.demo import run_demo
    from labelaudit.results import open_results
    from labelaudit.summary import summarize

    with handle_errors(debug):
        if frames < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {frames}", param_hint="--frames")
        tmp = tempfile.TemporaryDirectory(prefix="labelaudit-demo-") if folder is None else None
        root = Path(tmp.name) if tmp is not None else folder
        assert root is not None
        console = err()
        try:
            # A temporary folder is deleted at the end: its report goes to the current folder instead.
            page = Path(C.DEMO_REPORT_NAME).resolve() if tmp is not None else None
            run = run_demo(
                root,
                frames,
                workers,
                say=console.print,
                progress=RichProgress(console),
                debug=debug,
                report=page,
                after_infer=lambda summary: print_run_summary(
                    console, summary, summarize(open_results(summary.output))
                ),
            )
            for ranked, injected in run.ranked:
                print_rank_table(out(), ranked, {"injected": injected})
            assert run.gate is not None
            print_gate_table(out(), run.gate)
            if run.evaluation is not None:
                print_eval_tables(out(), run.evaluation, brief=True)
            print_missing_found(run)
            console.print(f"report: {escape(str(run.report))} (open it in a browser)", soft_wrap=True)
            if tmp is None:
                console.print(
                    f"kept: results in {escape(str(run.results))} (try `labelaudit rank {escape(str(run.results))} --by sigma_hat`), "
                    f"the simulator's ground truth in {escape(str(run.data / 'manifest.parquet'))}",
                    soft_wrap=True,
                )
            else:
                console.print(
                    "run `labelaudit demo DIR` to keep the data, the results and the simulator's ground truth",
                    soft_wrap=True,
                )
        finally:
            if tmp is not None:
                tmp.cleanup()

"""The ``labelaudit`` command line: a thin Typer layer over the library (DESIGN.md §8).

Data goes to stdout, progress and logs to stderr. Exit codes: 0 success / gate passed, 1 gate
failed, 2 usage, config or input error (a one-line message naming the file and the fix), 3 an
internal error (a bug; ``--debug`` shows the traceback).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from contextlib import contextmanager
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator, Optional

import pyarrow as pa
import typer
from typer.exceptions import TyperException
from rich.console import Console
from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit.config import ConfigError
from labelaudit.datasets import DatasetError
from labelaudit.results import ResultsError

if TYPE_CHECKING:  # heavy modules are imported inside the commands, so `--help` stays fast
    from labelaudit.gate import GateReport
    from labelaudit.pipeline import ChunkResult, RunSummary
    from labelaudit.rank import RankResult
    from labelaudit.sim.noise import NoiseSpec

app = typer.Typer(
    name="labelaudit",
    help=(
        "Audit 3D LiDAR box labels (KITTI, Waymo) from the point cloud itself: per-label spatial "
        "uncertainty (JIoU-GT), ranking of the worst labels and a CI gate.\n\n"
        "[bold]Examples[/bold]\n\n"
        "  labelaudit demo\n\n"
        "  labelaudit infer /data/kitti -o results/ && labelaudit rank results/ && labelaudit check results/"
    ),
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
)

EXIT_OK, EXIT_GATE_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3


class CliError(ValueError):
    """A usage or input problem found by the CLI itself; shown as one line, exit 2."""


class Format(str, Enum):
    auto = "auto"
    kitti = "kitti"
    waymo_v2 = "waymo-v2"
    waymo_v1 = "waymo-v1"


class ModelKind(str, Enum):
    bev = "bev"
    three_d = "3d"


class OutputFormat(str, Enum):
    table = "table"
    json = "json"
    csv = "csv"


def _out() -> Console:
    # Built per call: Typer's test runner swaps sys.stdout between invocations.
    # Not a terminal (pipe, CI log): wide enough that tables do not wrap.
    return Console(file=sys.stdout, highlight=False, width=None if sys.stdout.isatty() else 140)


def _err() -> Console:
    return Console(file=sys.stderr, stderr=True, highlight=False)


@contextmanager
def _handle_errors(debug: bool) -> Iterator[None]:
    """Turn library errors into a one-line message and exit code 2 (bugs: 3, traceback with --debug)."""
    from labelaudit.pipeline import InferError, StrictError, WorkerCrashed

    try:
        yield
    except (typer.Exit, TyperException):
        raise
    except (ConfigError, ResultsError, InferError, StrictError, WorkerCrashed, DatasetError, CliError) as exc:
        if debug:
            raise
        _err().print(f"[red]error:[/red] {escape(str(exc))}", markup=True, highlight=False, soft_wrap=True)
        raise typer.Exit(EXIT_USAGE) from None
    except KeyboardInterrupt:
        _err().print("interrupted; rerun the same command to resume")
        raise typer.Exit(130) from None
    except Exception as exc:
        if debug:
            raise
        _err().print(f"[red]internal error:[/red] {type(exc).__name__}: {escape(str(exc))} (rerun with --debug for the traceback)", soft_wrap=True)
        raise typer.Exit(EXIT_INTERNAL) from None


def _version(value: bool) -> None:
    if value:
        typer.echo(f"labelaudit {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """Audit 3D LiDAR box labels from the point cloud itself."""


# --------------------------------------------------------------------------- infer


class RichProgress:
    """Progress bar on stderr with frames/s and objects/s."""

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
        self.bar.update(self.task, advance=result.units, rate=f"{self.frames / dt:.1f} frames/s  {self.objects / dt:.0f} objects/s")

    def stop(self) -> None:
        self.bar.stop()


def _print_run_summary(console: Console, summary: RunSummary, stats: dict[str, Any]) -> None:
    console.print(f"[bold]labelaudit infer[/bold] → {escape(str(summary.output))}")
    table = Table()
    table.add_column("class")
    table.add_column("objects", justify="right")
    table.add_column("median JIoU-GT", justify="right")
    for name, c in stats["classes"].items():
        med = "–" if c["median_jiou_gt"] is None else f"{c['median_jiou_gt']:.3f}"
        table.add_row(name, str(c["objects"]), med)
    console.print(table)
    statuses = ", ".join(f"{k} {v}" for k, v in stats["by_status"].items()) or "none"
    resumed = f" ({summary.chunks_skipped} of {summary.chunks} shards already done)" if summary.chunks_skipped else ""
    console.print(f"objects by status: {statuses}")
    console.print(
        f"frames this run: {summary.frames}{resumed}; failed frames: {summary.failed_frames}; warnings: {summary.warnings}; "
        f"wall time {summary.wall_seconds:.1f} s"
    )
    if summary.failed_frames or summary.warnings:
        console.print(f"failed frames and warnings are listed in {escape(str(summary.output / 'errors.parquet'))}")


def run_infer_command(
    dataset: Path,
    output: Path,
    fmt: str = "auto",
    config: Optional[Path] = None,
    classes: Optional[str] = None,
    model: Optional[str] = None,
    split: Optional[str] = None,
    workers: Optional[int] = None,
    limit: Optional[int] = None,
    overwrite: bool = False,
    strict: bool = False,
    quiet: bool = False,
    debug: bool = False,
) -> RunSummary:
    """Library-level body of ``infer`` (also used by ``demo``); returns the run summary."""
    from labelaudit.pipeline import InferRequest, NoProgress, resolve_config, resolve_format, run_infer
    from labelaudit.rank import summarize
    from labelaudit.results import open_results

    if workers is not None and workers < 1:
        raise typer.BadParameter(f"must be ≥ 1, got {workers}", param_hint="--workers")
    resolved = resolve_format(dataset, fmt)
    class_list = None if classes is None else [c for c in classes.split(",")]
    cfg = resolve_config(config, resolved, class_list, model)
    request = InferRequest(dataset, output, resolved, split, workers, limit, overwrite, strict, debug)
    console = _err()
    progress = NoProgress() if quiet else RichProgress(console)
    summary = run_infer(request, cfg, progress)
    stats = summarize(open_results(output))
    if not quiet:
        _print_run_summary(console, summary, stats)
    if stats["objects"] == 0:
        wanted = ", ".join(cfg.classes)
        raise ResultsError(f"{output}: no objects audited (classes {wanted}); check --classes (or pass --classes all) and {output / 'errors.parquet'}")
    return summary


@app.command()
def infer(
    dataset: Path = typer.Argument(..., help="Dataset folder (KITTI root or training/, Waymo v2 folder) or a Waymo v1 .tfrecord."),
    output: Path = typer.Option(Path(C.DEFAULT_RESULTS_DIR), "-o", "--output", help="Results folder (Parquet shards + manifest)."),
    fmt: Format = typer.Option(Format.auto, "--format", help="Dataset format; auto detects it."),
    config: Optional[Path] = typer.Option(None, "--config", help="Model config TOML (default: the built-in one of the format)."),
    classes: Optional[str] = typer.Option(None, "--classes", help="Comma-separated classes to audit, or 'all' (default: the config's, vehicles)."),
    model: Optional[ModelKind] = typer.Option(None, "--model", help="bev (default) or 3d."),
    split: Optional[str] = typer.Option(None, "--split", help="KITTI ImageSets split (train, val, …)."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (default: all cores)."),
    limit: Optional[int] = typer.Option(None, "--limit", help="Only the first N frames (KITTI) / segments (Waymo)."),
    resume: bool = typer.Option(True, "--resume/--overwrite", help="Skip shards already written with the same parameters, or start over."),
    strict: bool = typer.Option(False, "--strict", help="Stop at the first frame or object that fails."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and summary."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Audit every labeled box of a dataset: crop its points, infer its spatial uncertainty, write Parquet.

    Results go to a folder of Parquet shards with a manifest (see docs/results-schema.md). A stopped run resumes where it left off when started again with the same options.

    [bold]Examples[/bold]

      labelaudit infer /data/kitti -o results/

      labelaudit infer /data/kitti --split val --classes Car,Van --workers 8

      labelaudit infer /data/waymo_v2/validation --format waymo-v2 --model 3d -o waymo-results/
    """
    with _handle_errors(debug):
        run_infer_command(dataset, output, fmt.value, config, classes, model.value if model else None, split, workers, limit, not resume, strict, quiet, debug)


# --------------------------------------------------------------------------- rank


def _split_list(values: Optional[list[str]]) -> tuple[str, ...]:
    out: list[str] = []
    for v in values or []:
        out.extend(s.strip() for s in v.split(",") if s.strip())
    return tuple(out)


def print_rank_table(console: Console, result: RankResult, extra: dict[str, list[str]] | None = None) -> None:
    """Rich table of a :class:`~labelaudit.rank.RankResult`; ``extra`` adds display-only columns."""
    from labelaudit.rank import display_columns, format_cell

    q = result.query
    table = result.table
    for name, values in (extra or {}).items():
        table = table.append_column(name, pa.array(values, pa.string()))
    cols = display_columns(table, q.by) + list(extra or {})
    order = "highest" if q.is_descending else "lowest"
    scope = f" with ≥ {q.min_points} points" if q.min_points else ""
    t = Table(title=f"worst {table.num_rows} of {result.matched} objects{scope} by {q.by} ({order} first)", title_justify="left")
    t.add_column("#", justify="right")
    for c in cols:
        t.add_column(c, justify="left" if c in ("frame_id", "class_name", "status") or c in (extra or {}) else "right")
    for i, row in enumerate(table.select(cols).to_pylist(), start=1):
        t.add_row(str(i), *(format_cell(row[c]) for c in cols))
    console.print(t)


@app.command()
def rank(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    by: str = typer.Option("jiou_gt", "--by", help="Numeric column to rank by (jiou_gt, label_error, sigma_hat, num_points …)."),
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

    json and csv print every column of the matching rows to stdout, for pipes.

    [bold]Examples[/bold]

      labelaudit rank results/

      labelaudit rank results/ --by label_error --top 50 --class Car

      labelaudit rank results/ --status few_points --max-distance 40 --format csv > worst.csv

      labelaudit rank results/ --where 'difficulty==Easy' --where 'num_points>=50'
    """
    from labelaudit.rank import RankQuery, rank_results, to_csv, to_json
    from labelaudit.results import STATUSES, open_results

    with _handle_errors(debug):
        statuses = _split_list(status)
        bad = [s for s in statuses if s not in STATUSES]
        if bad:
            raise typer.BadParameter(f"unknown status {', '.join(bad)}; expected {', '.join(STATUSES)}", param_hint="--status")
        query = RankQuery(by, top, descending, _split_list(class_), statuses, min_points, max_distance, tuple(where or ()))
        opened = open_results(results)
        if not opened.complete:
            _err().print(f"note: {escape(str(results))} is incomplete (a run is in progress or stopped); rerun infer to finish it", soft_wrap=True)
        result = rank_results(opened, query)
        if out_format is OutputFormat.json:
            sys.stdout.write(to_json(result.table) + "\n")
        elif out_format is OutputFormat.csv:
            sys.stdout.write(to_csv(result.table))
        else:
            print_rank_table(_out(), result)
        if result.matched == 0:
            _err().print("no objects match the filters")


# --------------------------------------------------------------------------- check


def print_gate_table(console: Console, report: GateReport) -> None:
    from labelaudit.gate import _fmt

    colour = {"pass": "green", "fail": "red", "skip": "yellow", "error": "magenta"}
    t = Table(title=f"labelaudit check — gate {report.source}", title_justify="left")
    for c in ("scope", "rule", "value", "threshold", "objects", "result", "note"):
        t.add_column(c, justify="right" if c in ("value", "threshold", "objects") else "left", no_wrap=c != "note")
    for r in report.results:
        t.add_row(r.scope, r.rule, _fmt(r.value), f"{r.comparison} {_fmt(r.threshold)}", str(r.objects), f"[{colour[r.status]}]{r.status}[/]", r.note)
    console.print(t)
    if report.absent_classes:
        console.print(f"not in the results, not evaluated: {escape(', '.join(report.absent_classes))}")
    v = report.verdict
    console.print(f"[bold {'green' if v == 'PASS' else 'red'}]{v}[/] ({report.total_objects} objects; exit {report.exit_code})")


@app.command()
def check(
    results: Path = typer.Argument(..., help="Results folder written by `labelaudit infer`."),
    config: Optional[Path] = typer.Option(None, "--config", help="Gate thresholds TOML (default: the built-in configs/gate.toml)."),
    as_json: bool = typer.Option(False, "--json", help="Print the rule outcomes as JSON on stdout instead of a table."),
    junit: Optional[Path] = typer.Option(None, "--junit", help="Also write the outcomes as JUnit XML to this file."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """CI gate: evaluate label-quality thresholds per class; exit 0 pass, 1 fail, 2 cannot evaluate.

    Rules (docs/ci-gate.md): minimum median JIoU-GT, maximum fraction below a JIoU-GT threshold, maximum fraction/count of boxes without points, maximum fraction over a label_error threshold, maximum failed objects and frames. Never exits 0 when nothing was evaluated.

    [bold]Examples[/bold]

      labelaudit check results/

      labelaudit check results/ --config ci/gate.toml --junit gate-report.xml

      labelaudit check results/ --json | jq .verdict
    """
    from labelaudit.gate import evaluate_gate, load_gate
    from labelaudit.results import open_results

    with _handle_errors(debug):
        gate = load_gate(config)
        report = evaluate_gate(open_results(results), gate)
        if junit is not None:
            try:
                junit.parent.mkdir(parents=True, exist_ok=True)
                junit.write_text(report.to_junit())
            except OSError as exc:
                raise CliError(f"{junit}: cannot write the JUnit report ({exc.strerror})") from None
        if as_json:
            sys.stdout.write(report.to_json() + "\n")
        else:
            print_gate_table(_out(), report)
    raise typer.Exit(report.exit_code)


# --------------------------------------------------------------------------- simulate & demo


def _noise_spec(fraction: float, center_std: float, size_std: float, yaw_std: float, gross_fraction: float) -> NoiseSpec:
    from labelaudit.sim.noise import NoiseSpec

    try:
        return NoiseSpec(fraction=fraction, center_std=center_std, size_std=size_std, yaw_std=yaw_std, gross_fraction=gross_fraction)
    except ValueError as exc:
        raise typer.BadParameter(str(exc), param_hint="--noise-*/--gross-fraction") from None


@app.command()
def simulate(
    out: Path = typer.Argument(..., help="Folder to write the KITTI-format dataset to."),
    frames: int = typer.Option(20, "--frames", help="Number of frames."),
    seed: int = typer.Option(0, "--seed", help="Random seed (same seed, same dataset)."),
    noise_fraction: float = typer.Option(0.2, "--noise-fraction", help="Share of vehicle labels with Gaussian jitter."),
    noise_center_std: float = typer.Option(C.SIM_BENCH_NOISE[0], "--noise-center-std", help="Jitter std of the centre (m)."),
    noise_size_std: float = typer.Option(C.SIM_BENCH_NOISE[1], "--noise-size-std", help="Jitter std of length and width (m)."),
    noise_yaw_std: float = typer.Option(C.SIM_BENCH_NOISE[2], "--noise-yaw-std", help="Jitter std of the yaw (rad)."),
    gross_fraction: float = typer.Option(0.02, "--gross-fraction", help="Share of vehicle labels with a gross error (shifted 1 m, swapped l/w, turned 90°)."),
    workers: int = typer.Option(1, "--workers", help="Worker processes (same files for any count)."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace a simulated dataset already in OUT."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Write a synthetic LiDAR dataset in KITTI layout with known, injected label noise.

    manifest.parquet in OUT records every object's true box, written box and perturbation.

    [bold]Examples[/bold]

      labelaudit simulate sim/ --frames 100 --seed 1

      labelaudit simulate sim/ --noise-fraction 0.3 --noise-center-std 0.2 --gross-fraction 0.05
    """
    with _handle_errors(debug):
        if frames < 1:
            raise typer.BadParameter(f"must be ≥ 1, got {frames}", param_hint="--frames")
        spec = _noise_spec(noise_fraction, noise_center_std, noise_size_std, noise_yaw_std, gross_fraction)
        _simulate(out, frames, seed, spec, quiet, workers=workers, overwrite=overwrite)
        _err().print(f"wrote {frames} frames to {out} (next: labelaudit infer {out})")


def _simulate(out: Path, frames: int, seed: int, spec: NoiseSpec, quiet: bool, workers: int = 1, overwrite: bool = False) -> None:
    from labelaudit.simulate import simulate_dataset

    if workers < 1:
        raise typer.BadParameter(f"must be ≥ 1, got {workers}", param_hint="--workers")
    try:
        simulate_dataset(out, frames=frames, seed=seed, noise=spec, progress=not quiet, workers=workers, overwrite=overwrite)
    except FileExistsError as exc:
        raise CliError(f"{exc} (--overwrite replaces it)") from None


@app.command()
def demo(
    folder: Optional[Path] = typer.Argument(None, help="Where to put the simulated data and results (default: a temporary folder)."),
    frames: int = typer.Option(C.DEMO_FRAMES, "--frames", help="Simulated frames."),
    workers: Optional[int] = typer.Option(None, "--workers", help="Worker processes (default: all cores)."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Simulate a small dataset with injected label errors, audit it, rank the worst and run the gate.

    Shows the whole loop in seconds: simulate → infer → rank → check. Exits 0 when the loop ran (whatever the gate verdict); pass FOLDER to keep the data and results.

    [bold]Examples[/bold]

      labelaudit demo

      labelaudit demo demo-out/ --frames 30
    """
    from labelaudit.gate import evaluate_gate, load_gate
    from labelaudit.rank import RankQuery, rank_results
    from labelaudit.results import open_results

    with _handle_errors(debug):
        tmp = None
        if folder is None:
            tmp = tempfile.TemporaryDirectory(prefix="labelaudit-demo-")
            folder = Path(tmp.name)
        try:
            data, results = folder / "sim-kitti", folder / "results"
            console = _err()
            console.print(f"[bold]1/4 simulate[/bold] {frames} frames with injected label errors → {data}")
            spec = _noise_spec(0.2, C.SIM_BENCH_NOISE[0], C.SIM_BENCH_NOISE[1], C.SIM_BENCH_NOISE[2], 0.05)
            _simulate(data, frames, 0, spec, quiet=False, workers=workers or os.cpu_count() or 1, overwrite=True)
            console.print(f"[bold]2/4 infer[/bold] {data} → {results}")
            run_infer_command(data, results, "kitti", workers=workers, overwrite=True, debug=debug)
            opened = open_results(results)
            console.print(
                "[bold]3/4 rank[/bold] the worst labels; 'injected' is the simulator's ground truth "
                "(none = exact label). Boxes without points are all equally uncertain (prior only), so they are left out here."
            )
            truth = _injected_by_object(data / "manifest.parquet")
            for query in (RankQuery(top=10, min_points=1), RankQuery(by="label_error", top=10)):
                if query.by not in opened.columns or opened.read([query.by]).column(query.by).null_count == opened.dataset.count_rows():
                    continue
                ranked = rank_results(opened, query)
                injected = [truth.get(o, "?") for o in ranked.table.column("object_id").to_pylist()]
                print_rank_table(_out(), ranked, {"injected": injected})
            console.print("[bold]4/4 check[/bold] the built-in gate (configs/gate.toml)")
            report = evaluate_gate(opened, load_gate(None))
            print_gate_table(_out(), report)
            if tmp is None:
                console.print(
                    f"kept: results in {escape(str(results))} (try `labelaudit rank {escape(str(results))} --by sigma_hat`), "
                    f"the simulator's ground truth in {escape(str(data / 'manifest.parquet'))}",
                    soft_wrap=True,
                )
            else:
                console.print("run `labelaudit demo DIR` to keep the data, the results and the simulator's ground truth", soft_wrap=True)
        finally:
            if tmp is not None:
                tmp.cleanup()


def _injected_by_object(manifest: Path) -> dict[str, str]:
    """object_id → perturbation kind from a simulator manifest (empty when unreadable)."""
    import pyarrow.parquet as pq

    try:
        t = pq.read_table(manifest, columns=["object_id", "perturbation"])
    except (OSError, pa.ArrowInvalid, KeyError):
        return {}
    return dict(zip(t.column("object_id").to_pylist(), t.column("perturbation").to_pylist()))


def main() -> None:
    """Console-script entry point."""
    app(prog_name="labelaudit")


if __name__ == "__main__":
    main()

"""``labelaudit infer``: parse the options into an :class:`~labelaudit.infer.run.InferRequest`, run, print the summary."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

from labelaudit import constants as C
from labelaudit.cli.app import DatasetFormat, app, err, handle_errors
from labelaudit.errors import UsageError


class ModelChoice(str, Enum):
    bev = "bev"
    three_d = "3d"


@app.command()
def infer(
    dataset: Path = typer.Argument(
        ...,
        help="Dataset folder (KITTI root or training/, Waymo v2 folder, Argoverse 2 root, split or log folder) or a Waymo v1 .tfrecord.",
    ),
    output: str = typer.Option(
        C.DEFAULT_RESULTS_DIR,
        "-o",
        "--output",
        help="Results folder (Parquet shards + manifest); '-o .' for the current folder.",
    ),
    dataset_format: DatasetFormat = typer.Option(
        DatasetFormat.auto, "--dataset-format", help="Dataset format; auto detects it."
    ),
    config: Optional[Path] = typer.Option(
        None,
        "--config",
        help="Model config TOML, or 'paper' for the authors' published KITTI setting (default: the built-in one of the format).",
    ),
    classes: Optional[str] = typer.Option(
        None, "--classes", help="Comma-separated classes to audit, or 'all' (default: the config's, vehicles)."
    ),
    model: Optional[ModelChoice] = typer.Option(None, "--model", help="bev (default) or 3d."),
    split: Optional[str] = typer.Option(
        None,
        "--split",
        help="KITTI ImageSets split (train, val, …); Waymo v2 and Argoverse 2: the split folder under DATASET.",
    ),
    workers: Optional[int] = typer.Option(
        None, "--workers", help="Worker processes (default: all cores); with --scheduler local, the cluster's size."
    ),
    scheduler: Optional[str] = typer.Option(
        None,
        "--scheduler",
        metavar="ADDR",
        help="Run on a Dask cluster: tcp://HOST:PORT of a running scheduler, or local[:N] for a local cluster of N processes (docs/scale.md).",
    ),
    limit: Optional[int] = typer.Option(
        None, "--limit", help="Only the first N frames (KITTI) / segments (Waymo) / logs (Argoverse 2)."
    ),
    resume: bool = typer.Option(
        True,
        "--resume/--overwrite",
        help="Skip shards already written with the same parameters (re-trying those with failures), or start over (also replaces a damaged folder).",
    ),
    missing: bool = typer.Option(
        True,
        "--missing/--no-missing",
        help="Search the point clouds for objects of the audited classes that have no label (RESULTS/missing/, docs/missing.md); --no-missing skips it.",
    ),
    detections: Optional[Path] = typer.Option(
        None,
        "--detections",
        metavar="PATH",
        help="A detector's output (KITTI result files, Waymo Objects .bin or labelaudit Parquet, as `eval` reads): confident detections no label overlaps become missing-label candidates too.",
    ),
    strict: bool = typer.Option(
        False, "--strict", help="Stop at the first frame or object that fails (exit 2, one line naming the file)."
    ),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and summary."),
    debug: bool = typer.Option(False, "--debug", help="Show tracebacks."),
) -> None:
    """Audit every labeled box of a dataset: crop its points, infer its spatial uncertainty, write Parquet.

    Results go to a folder of Parquet shards with a manifest (see docs/results-schema.md). A stopped run resumes where it left off when started again with the same options.

    [bold]Examples[/bold]

      labelaudit infer /data/kitti -o results/

      labelaudit infer /data/kitti --split val --classes Car,Van --workers 8

      labelaudit infer /data/kitti --config paper -o paper-results/

      labelaudit infer /data/kitti --detections pointgnn/data -o results/

      labelaudit infer /data/kitti --no-missing -o results/

      labelaudit infer /data/waymo_v2/validation --dataset-format waymo-v2 --model 3d -o waymo-results/

      labelaudit infer /data/av2/sensor --split val -o av2-results/

      labelaudit infer /shared/waymo_v2/training --scheduler tcp://scheduler:8786 -o /shared/results/
    """
    with handle_errors(debug):
        if not output.strip():  # Path("") would be the current folder
            raise UsageError("-o/--output is empty; name the results folder (`-o .` for the current one)")
        executor = start_pool_early(workers, scheduler)
        from labelaudit.infer.run import InferRequest

        request = InferRequest(
            dataset,
            Path(output),
            dataset_format.value,
            split,
            workers,
            limit,
            overwrite=not resume,
            strict=strict,
            debug=debug,
            scheduler=scheduler,
            config=config,
            classes=None if classes is None else tuple(classes.split(",")),
            model=model.value if model else None,
            missing=missing,
            detections=detections,
        )
        run_and_report(request, quiet, executor)


def start_pool_early(workers: int | None, scheduler: str | None) -> object | None:
    """The worker pool of ``--workers``, its fork server already starting (None: serial, Dask or a bad count).

    Started before anything else, so the server's imports and warm-up (the core and its compiled
    kernels, about a second) overlap with this process' own (Arrow, the dataset listing, the
    output folder). A run that then stops on bad input only leaves an idle server, which exits with
    this process. With ``--scheduler local[:N]`` the same server is started for the LocalCluster's
    workers; a cluster itself is left to :func:`~labelaudit.infer.run.run_infer`, which contacts it
    only once the input is known to be good.
    """
    from labelaudit.executors import PoolExecutor, fork_server_preload, make_executor, start_fork_server

    preload = fork_server_preload(workers, scheduler)
    if preload is None:
        return None  # serial, a tcp:// cluster, or a bad value that run_infer reports after the input checks
    if scheduler is not None:
        start_fork_server(preload)  # the LocalCluster's workers fork from it; the cluster starts in run_infer
        return None
    executor = make_executor(workers)
    assert isinstance(executor, PoolExecutor)
    executor.start()
    return executor


def run_and_report(request: object, quiet: bool, executor: object | None = None) -> None:
    """Run ``infer`` for a request with the progress bar and the end-of-run summary on stderr (also used by ``demo``)."""
    from labelaudit.cli.display import RichProgress, print_run_summary
    from labelaudit.infer.run import NoProgress, infer_dataset
    from labelaudit.results import open_results
    from labelaudit.summary import summarize, summarize_columns

    console = err()
    summary = infer_dataset(request, NoProgress() if quiet else RichProgress(console), executor)  # type: ignore[arg-type]
    if not quiet:  # a run that wrote every row has their columns; a resumed one reads the folder (~0.1 s)
        c = summary.columns
        stats = (
            summarize(open_results(summary.output))
            if c is None
            else summarize_columns(c["class_name"], c["status"], c["jiou_gt"], summary.failed_frames)
        )
        print_run_summary(console, summary, stats)

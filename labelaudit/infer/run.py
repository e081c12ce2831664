"""The ``labelaudit infer`` run: resolve format and config, plan chunks, resume, hand chunks to an executor.

:func:`run_infer` plans fixed chunks of units (independent of the worker count), skips those already
written (``--resume``), hands the rest to an :class:`~labelaudit.executors.Executor` and writes each
returned chunk as atomic shards. :func:`process_chunk` is the pure function a worker runs: a
:class:`ChunkTask` (a few :class:`~labelaudit.datasets.FrameRef` s, the config and the run's shard
metadata) in, a :class:`ChunkResult` (the chunk's shards as Parquet bytes, :func:`encode_chunk`, and
its errors) out; it loads its own frames, so it runs in any process or cluster node. Rows are built
by :mod:`labelaudit.infer.rows`; the folder layout, lock and resume checks belong to
:mod:`labelaudit.results`. Nothing here prints.
"""

from __future__ import annotations

import hashlib
import math
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import pyarrow as pa

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.config import RunConfig, hash_inputs, resolve_config, validate_config
from labelaudit.datasets import DatasetError, FrameFailure, FrameRef, open_dataset, resolve_format
from labelaudit.errors import InferError, ResultsError, StrictError, one_line
from labelaudit.executors import Executor, make_executor
from labelaudit.summary import SUMMARY_COLUMNS

# labelaudit.infer.rows (the core: numba kernels) is imported where a chunk is processed, so the
# process that only plans, writes and reports (the main process, a Dask client) never loads it.


def missing_of_frame(frame: Any, cfg: RunConfig, detections: Any = None) -> list[dict[str, Any]]:
    """:func:`labelaudit.infer.missing.find_missing` (imported on first use)."""
    from labelaudit.infer.missing import find_missing

    return find_missing(frame, cfg, detections)


def process_frame(frame: Any, cfg: RunConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """:func:`labelaudit.infer.rows.process_frame` (imported on first use)."""
    from labelaudit.infer.rows import process_frame as rows_of_frame

    return rows_of_frame(frame, cfg)


# --------------------------------------------------------------------------- layer 2: one chunk


@dataclass(frozen=True)
class ChunkTask:
    """Everything a worker needs to produce one shard: picklable, no open files."""

    name: str  # shard file name (derived from the unit keys)
    refs: tuple[FrameRef, ...]
    cfg: RunConfig
    reader_options: tuple[tuple[str, Any], ...] = ()
    max_frames_per_unit: int | None = None
    debug: bool = False
    detections: Mapping[str, Any] = field(default_factory=dict)  # frame id → the frame's detections (--detections)
    metadata: Mapping[str, Any] | None = None  # the run's shard metadata: the worker encodes the shards (encode_chunk)


@dataclass
class ChunkResult:
    """What a worker returns for one chunk."""

    name: str
    table: pa.Table | None  # None once encoded (shards)
    errors: list[dict[str, Any]]
    units: int
    frames: int
    objects: int
    seconds: float
    sources: dict[str, str] = field(default_factory=dict)  # frame id → the file its labels came from
    missing: pa.Table | None = None  # missing-label candidates of the chunk (None: the search is off)
    shards: dict[str, bytes] | None = None  # folder → the chunk's Parquet file there, once encoded (encode_chunk)
    failure: str | None = None  # once encoded: --strict's message for the chunk's first failure (None: none)
    summary: dict[str, list[Any]] | None = None  # once encoded: the rows' SUMMARY_COLUMNS, for the end-of-run summary

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Frame-level errors (warnings excluded)."""
        return [e for e in self.errors if e["level"] == "error"]


_READERS = (
    threading.local()
)  # per thread: a Dask worker may run several tasks at once (--nthreads > 1), and readers keep open files


def _reader(ref: FrameRef, options: tuple[tuple[str, Any], ...]) -> Any:
    """One reader per thread and dataset: opening a reader lists folders, so reuse it."""
    key = (ref.dataset_format, ref.root, options)
    readers = _READERS.__dict__.setdefault("by_key", {})
    if key not in readers:
        readers[key] = open_dataset(ref.root, ref.dataset_format, **dict(options))
    return readers[key]


def process_chunk(task: ChunkTask) -> ChunkResult:
    """Load and audit every frame of a chunk of units; never raises for bad input.

    A unit that cannot be read (or a frame that cannot be read or whose crop fails) becomes an
    error row naming its file; objects whose inference fails become rows with status ``error``.
    With ``task.debug`` unexpected exceptions (bugs, not bad input) propagate so their traceback
    is visible.
    """
    from labelaudit.executors import tune_allocator
    from labelaudit.infer.rows import frame_note

    tune_allocator()
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    candidates: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    sources: dict[str, str] = {}
    search = task.cfg.missing.enabled
    frames = 0
    for ref in task.refs:
        try:
            reader = _reader(ref, task.reader_options)
            for n, frame in enumerate(reader.load_unit(ref)):
                if task.max_frames_per_unit is not None and n >= task.max_frames_per_unit:
                    break
                if isinstance(frame, FrameFailure):  # the reader goes on with the unit's next frame
                    exc = frame.error
                    errors.append(frame_note(frame.frame_id, ref.key, one_line(str(exc)), file=exc.path, line=exc.line))
                    continue
                source = frame.source or ref.key
                try:  # a frame that fails (e.g. in the crop) never takes the rest of its unit along
                    frame_rows, notes = process_frame(frame, task.cfg)
                except Exception as exc:
                    if task.debug:
                        raise
                    errors.append(
                        frame_note(
                            frame.frame_id,
                            ref.key,
                            one_line(f"{type(exc).__name__} in frame {frame.frame_id} of {source}: {exc}"),
                            file=source,
                        )
                    )
                    continue
                for note in notes:
                    note["unit"] = ref.key
                    note["file"] = note["file"] or source
                sources[R.safe_text(frame.frame_id)] = source
                rows.extend(frame_rows)
                errors.extend(notes)
                frames += 1
                if search:  # after the frame's rows: a failing search never costs the frame its objects
                    try:
                        candidates.extend(missing_of_frame(frame, task.cfg, task.detections.get(frame.frame_id)))
                    except Exception as exc:
                        if task.debug:
                            raise
                        errors.append(
                            frame_note(
                                frame.frame_id,
                                ref.key,
                                one_line(
                                    f"missing-label search failed in frame {frame.frame_id} of {source}: {type(exc).__name__}: {exc} (its objects are kept)"
                                ),
                                file=source,
                            )
                        )
        except DatasetError as exc:  # the reader gave up on the unit (or on the rest of it)
            errors.append(frame_note(None, ref.key, one_line(str(exc)), file=exc.path, line=exc.line))
        except Exception as exc:
            if task.debug:
                raise
            detail = f": {exc}" if str(exc) else ""
            errors.append(
                frame_note(
                    None, ref.key, one_line(f"{type(exc).__name__} while reading {ref.key}{detail}"), file=ref.key
                )
            )
    table = R.rows_to_table(rows, normalized=True)  # process_frame's rows are normalised
    missing = R.missing_rows_to_table(candidates) if search else None
    result = ChunkResult(
        task.name, table, errors, len(task.refs), frames, table.num_rows, time.perf_counter() - start, sources, missing
    )
    return result if task.metadata is None else encode_chunk(result, task.metadata)


def encode_chunk(result: ChunkResult, metadata: Mapping[str, Any]) -> ChunkResult:
    """``result`` with its shards encoded as Parquet bytes (:attr:`ChunkResult.shards`, by folder:
    the objects shard with its :func:`~labelaudit.results.chunk_record`, the missing-label shard
    when the chunk was searched, the errors part when it has notes), its ``--strict`` message
    (:attr:`ChunkResult.failure`), the columns of the end-of-run summary (:attr:`ChunkResult.summary`),
    and no tables.

    Run by the worker (:attr:`ChunkTask.metadata`): the process that writes the shards then only
    stores bytes, and the bytes cost less to send than the tables. The files are the ones
    :func:`~labelaudit.results.write_parquet_atomic` writes from the tables, byte for byte.
    """
    if result.shards is not None:
        return result
    shards = {
        R.OBJECTS_DIR: R.parquet_bytes(
            R.with_metadata(result.table, {**metadata, "chunk": R.chunk_record(result.table, result.errors)})
        )
    }
    if result.missing is not None:  # an empty shard too: it says the chunk was searched
        shards[R.MISSING_DIR] = R.parquet_bytes(R.with_metadata(result.missing, metadata))
    if result.errors:
        shards[R.ERRORS_DIR] = R.parquet_bytes(R.errors_to_table(result.errors, metadata))
    summary = {c: result.table.column(c).to_pylist() for c in SUMMARY_COLUMNS}
    return replace(result, table=None, missing=None, shards=shards, failure=chunk_failure(result), summary=summary)


# --------------------------------------------------------------------------- layer 3: a run


@dataclass(frozen=True)
class InferRequest:
    """The options of ``labelaudit infer``: input, output, run options and the config overrides.

    ``config``, ``classes`` and ``model`` are used by :func:`infer_dataset` to resolve the
    :class:`~labelaudit.config.RunConfig` (:func:`resolve_config`); :func:`run_infer` takes a
    resolved config instead and ignores them.
    """

    dataset: Path
    output: Path = Path(C.DEFAULT_RESULTS_DIR)
    dataset_format: str = "auto"
    split: str | None = None
    workers: int | None = None
    limit: int | None = None
    overwrite: bool = False
    strict: bool = False
    debug: bool = False
    chunk_units: int | None = None  # None: chunk_size_for(format, number of units)
    config: Path | None = None  # model config TOML; None: the built-in one of the format
    classes: tuple[str, ...] | None = None  # None: the config's; ("all",): every class
    model: str | None = None  # "bev" / "3d" override of the config's [model] kind
    scheduler: str | None = None  # Dask scheduler address (tcp://HOST:PORT) or local[:N]; None: the pool of ``workers``
    missing: bool = True  # search for objects without a label (missing/); False: --no-missing
    detections: Path | None = (
        None  # a detector's output (the formats `eval` reads): its unlabelled detections are candidates too
    )


@dataclass
class RunSummary:
    """What a run did (the shards themselves are on disk)."""

    output: Path
    manifest: dict[str, Any]
    units: int
    chunks: int
    chunks_skipped: int
    frames: int
    objects: int
    failed_frames: int
    warnings: int
    wall_seconds: float
    chunks_retried: int = 0  # shards of an earlier run run again: they had failed frames or objects
    columns: dict[str, list[Any]] | None = None  # every row's SUMMARY_COLUMNS, this run wrote them all (else None)


class Progress(Protocol):
    """Receives progress events (the CLI shows a Rich bar; the library default shows nothing)."""

    def start(self, total_units: int, done_units: int) -> None: ...

    def advance(self, result: ChunkResult) -> None: ...

    def stop(self) -> None: ...


class NoProgress:
    def start(self, total_units: int, done_units: int) -> None:
        pass

    def advance(self, result: ChunkResult) -> None:
        pass

    def stop(self) -> None:
        pass


def chunk_name(refs: Sequence[FrameRef]) -> str:
    """Shard file name of a chunk: a hash of its unit keys, so a resumed run finds it again."""
    # surrogateescape: a key from a non-UTF-8 file name hashes as its bytes
    digest = hashlib.sha256("\n".join(r.key for r in refs).encode("utf-8", "surrogateescape")).hexdigest()[:20]
    return f"part-{digest}.parquet"


def chunk_size_for(dataset_format: str, num_units: int) -> int:
    """Units per chunk: about :data:`~labelaudit.constants.TARGET_CHUNKS` chunks, at most the
    format's :data:`~labelaudit.constants.CHUNK_UNITS`. Depends only on the unit list, never on
    the worker count, so a run resumed with other ``--workers`` finds its shards again."""
    cap = C.CHUNK_UNITS.get(dataset_format, 1)
    return int(min(cap, max(1, math.ceil(num_units / C.TARGET_CHUNKS))))


def plan_chunks(refs: Sequence[FrameRef], chunk_units: int) -> list[tuple[str, tuple[FrameRef, ...]]]:
    """Split units into chunks in list order, independent of the worker count: chunks of
    ``chunk_units`` while at least twice that many units are left, then the rest (``chunk_units``
    to twice that) in chunks that halve (25 → 13, 6, 3, 2, 1; 4 → 2, 1, 1).

    Workers take chunks in plan order as they finish; with equal chunks to the end, the first
    worker out of work waits for the others' last chunk, half a chunk on average (~80 ms of a
    480-frame run on two cores). With the last chunks halving, the last one to finish is a unit or
    two. A chunk size of 1 (Waymo segments, Argoverse 2 logs, small runs) plans as before.
    """
    chunks: list[tuple[FrameRef, ...]] = []
    i, n = 0, len(refs)
    while n - i >= 2 * chunk_units:
        chunks.append(tuple(refs[i : i + chunk_units]))
        i += chunk_units
    while i < n:
        k = (n - i + 1) // 2  # half of what is left, rounded up
        chunks.append(tuple(refs[i : i + k]))
        i += k
    return [(chunk_name(c), c) for c in chunks]


def run_infer(
    request: InferRequest, cfg: RunConfig, progress: Progress | None = None, executor: Executor | None = None
) -> RunSummary:
    """Audit a dataset folder into a results folder (``labelaudit infer``).

    Parameters
    ----------
    request : input, output and run options
    cfg : model configuration (its ``dataset_format`` must be the resolved format)
    progress : progress sink (default: silent)
    executor : default :func:`make_executor` of ``request.workers`` and ``request.scheduler``

    Raises
    ------
    DatasetError
        Missing dataset path or undetectable format.
    InferError
        Unreadable dataset, no frames, output folder of another run.
    StrictError
        ``request.strict`` and a frame or an object failed.
    """
    start = time.perf_counter()
    progress = progress or NoProgress()
    dataset = Path(request.dataset).absolute()  # units name absolute paths: workers of a cluster do not share our cwd
    validate_config(cfg, "the run configuration")
    if request.split is not None and (not request.split.strip() or any(c in request.split for c in "/\\\0")):
        raise InferError(
            f"--split {request.split!r}: expected a split name such as train or val (ImageSets/<split>.txt)"
        )
    fmt = resolve_format(dataset, request.dataset_format)
    if cfg.dataset_format != fmt:
        cfg = cfg.with_overrides(dataset_format=fmt)
    reader_options: tuple[tuple[str, Any], ...] = (("split", request.split),) if request.split else ()
    try:
        reader = open_dataset(dataset, fmt, **dict(reader_options))
        refs = reader.list_units()
    except DatasetError as exc:
        raise InferError(str(exc)) from None
    except TypeError as exc:  # a reader without a split option
        raise InferError(f"{dataset}: option not supported by the {fmt} reader ({exc})") from None
    except OSError as exc:  # e.g. a --split name too long for the file system
        raise InferError(f"{exc.filename or dataset}: cannot list the dataset ({exc.strerror or exc})") from None
    if request.limit is not None:
        if request.limit < 1:
            raise InferError(f"--limit must be ≥ 1, got {request.limit}")
        refs = refs[: request.limit]
    if not refs:
        raise InferError(
            f"{dataset}: no frames found (format {fmt}{', split ' + request.split if request.split else ''})"
        )

    # Start the executor now that the input is known to be good: the pool's fork server imports
    # the core while this process hashes and prepares the folder; an unreachable cluster fails
    # before the folder is touched.
    executor = executor or make_executor(request.workers, scheduler=request.scheduler)
    try:
        executor.start()
        return _run_checked(request, cfg, fmt, dataset, refs, reader_options, progress, executor, start)
    except BaseException:
        executor.close()
        raise


def _run_checked(
    request: InferRequest,
    cfg: RunConfig,
    fmt: str,
    dataset: Path,
    refs: Sequence[FrameRef],
    reader_options: tuple[tuple[str, Any], ...],
    progress: Progress,
    executor: Executor,
    start: float,
) -> RunSummary:
    inputs = hash_inputs(cfg)
    metadata = R.run_metadata(
        inputs["params"],
        cfg.param_hash(),
        str(dataset.resolve()),
        fmt,
        constants_digest=inputs["constants_digest"],
        split=request.split,
        limit=request.limit,
    )
    output = Path(request.output)
    R.check_output_folder(output)
    with R.output_lock(output, request.overwrite):
        return _run_locked(request, cfg, fmt, refs, reader_options, metadata, output, progress, executor, start)


def _run_locked(
    request: InferRequest,
    cfg: RunConfig,
    fmt: str,
    refs: Sequence[FrameRef],
    reader_options: tuple[tuple[str, Any], ...],
    metadata: dict[str, Any],
    output: Path,
    progress: Progress,
    executor: Executor,
    start: float,
) -> RunSummary:
    R.prepare_output(output, metadata, request.overwrite)

    chunk_units = request.chunk_units or chunk_size_for(fmt, len(refs))
    chunks = plan_chunks(refs, chunk_units)
    shard_dir, err_dir, missing_dir = output / R.OBJECTS_DIR, output / R.ERRORS_DIR, output / R.MISSING_DIR
    search = cfg.missing.enabled
    # A chunk without its object shard is to run; only written shards are looked into (and a new
    # folder's first look at a footer, importing pyarrow.parquet, waits until the workers compute).
    written = {p.name for p in shard_dir.glob("*.parquet")} if shard_dir.is_dir() else set()
    state = {
        name: R.chunk_state(shard_dir / name, err_dir / name, missing_dir / name if search else None)
        if name in written
        else "missing"
        for name, _ in chunks
    }
    done = {name for name, s in state.items() if s == "done"}
    retried = sum(1 for s in state.values() if s == "retry")
    R.write_json_atomic(
        {**metadata, "complete": False, "units": len(refs), "chunks": len(chunks)}, output / R.MANIFEST_NAME
    )

    detections = (
        read_missing_detections(cfg, fmt, refs[0].root, request.split, request.limit) if cfg.missing.detections else {}
    )
    tasks = [
        ChunkTask(
            name,
            c,
            cfg,
            reader_options,
            request.limit if fmt != "kitti" else None,
            request.debug,
            detections_of_chunk(detections, c, fmt),
            metadata,
        )
        for name, c in chunks
        if name not in done
    ]
    frames = objects = 0
    columns: dict[str, list[Any]] = {c: [] for c in SUMMARY_COLUMNS}  # for the end-of-run summary
    progress.start(len(refs), sum(len(c) for name, c in chunks if name in done))
    try:  # the executor is closed after the end below: a pool's workers stop meanwhile
        for k, result in enumerate(executor.run(tasks, process_chunk)):
            result = encode_chunk(result, metadata)  # the worker has (ChunkTask.metadata): then a no-op
            if request.strict and result.failure is not None:
                raise StrictError(result.failure)
            shards = result.shards or {}  # encoded: never empty
            if R.ERRORS_DIR in shards:
                R.write_bytes_atomic(shards[R.ERRORS_DIR], err_dir / result.name)
            else:
                (err_dir / result.name).unlink(missing_ok=True)
            if R.MISSING_DIR in shards:
                R.write_bytes_atomic(shards[R.MISSING_DIR], missing_dir / result.name)
            # The object shard is written last: its presence marks the chunk complete for --resume,
            # and it records what the chunk's errors part must hold (R.chunk_state).
            R.write_bytes_atomic(shards[R.OBJECTS_DIR], shard_dir / result.name)
            if k == 0:
                _import_for_the_end(fmt)
            for c, values in (result.summary or {}).items():
                columns[c].extend(values)
            frames += result.frames
            objects += result.objects
            progress.advance(result)
    except BaseException:
        executor.close()
        raise
    finally:
        progress.stop()

    # Shards of an earlier plan (e.g. another --limit) would mix into the results: remove them.
    planned = {name for name, _ in chunks}
    for d, keep in ((shard_dir, planned), (err_dir, planned), (missing_dir, planned if search else set())):
        if d.is_dir():
            for p in d.glob("*.parquet"):
                if p.name not in keep:
                    p.unlink()
    # Tracks span chunks: judged once, over every written row (labelaudit/infer/tracks.py). For a
    # format without tracks the pass only removes an older run's tracks file: not imported otherwise.
    if metadata.get("format") in C.TRACK_FORMATS or (output / R.TRACKS_FILE).exists():
        from labelaudit.infer.tracks import run_tracks_pass

        run_tracks_pass(output, cfg, metadata)
    error_parts = sorted(err_dir.glob("*.parquet")) if err_dir.is_dir() else []
    errors = R.read_error_tables(error_parts)
    R.write_parquet_atomic(R.with_metadata(errors, metadata), output / R.ERRORS_FILE)
    failed = sum(1 for v in errors.column("level").to_pylist() if v == "error")
    wall = time.perf_counter() - start
    manifest = {
        **metadata,
        "complete": True,
        "units": len(refs),
        "chunks": len(chunks),
        "failed_frames": failed,
        "wall_seconds_last_run": round(wall, 3),
    }
    R.write_json_atomic(manifest, output / R.MANIFEST_NAME)
    executor.close()
    return RunSummary(
        output,
        manifest,
        len(refs),
        len(chunks),
        len(done),
        frames,
        objects,
        failed,
        errors.num_rows - failed,
        wall,
        retried,
        columns if not done else None,  # resumed chunks' rows are only in the folder
    )


def _import_for_the_end(fmt: str) -> None:
    """Import what the end of a run needs (the tracks pass of a format with tracks; Parquet's
    writer for ``errors.parquet``) once the first chunk is back: while the workers compute, not on
    the run's tail, where the writing process is all that runs (~20 ms)."""
    import pyarrow.parquet  # noqa: F401

    if fmt in C.TRACK_FORMATS:
        import labelaudit.infer.tracks  # noqa: F401


def chunk_failure(result: ChunkResult) -> str | None:
    """``--strict``'s one-line message for the first failed frame or object of a chunk (naming its
    file), or None when nothing failed; from the chunk's tables (:func:`encode_chunk` keeps it)."""
    if result.table is None:
        return result.failure
    failed = result.failed
    if failed:
        e = failed[0]
        where = "" if not e["file"] or str(e["file"]) in e["message"] else f"{e['file']}: "
        return one_line(f"--strict: unit {e['unit']} failed: {where}{e['message']}")
    if result.table.num_rows:
        status = result.table.column("status").to_pylist()
        if "error" in status:
            i = status.index("error")
            row = result.table.slice(i, 1).to_pylist()[0]
            source = result.sources.get(row["frame_id"], "")
            line = f" (line {row['label_line']})" if row.get("label_line") is not None else ""
            where = "" if not source or source in (row["message"] or "") else f"{source}{line}: "
            return one_line(
                f"--strict: frame {row['frame_id']} object {row['object_index']} failed: {where}{row['message']}"
            )
    return None


def read_missing_detections(
    cfg: RunConfig, fmt: str, dataset: str, split: str | None, limit: int | None
) -> dict[str, Any]:
    """A detector's output for the missing-label search (``--detections``): frame id →
    :class:`~labelaudit.infer.missing.FrameDetections` of the detections at or above
    ``cfg.missing.detection_min_score``, in the dataset's LiDAR/vehicle frame.

    Read once here, with the readers of ``eval`` (KITTI result files, Waymo ``Objects``, Parquet;
    KITTI boxes converted with each frame's calibration); a frame whose detections cannot be read
    is an error of the whole run (:class:`InferError` naming the file), as a wrong path is.
    """
    from labelaudit.datasets.detections import read_detections
    from labelaudit.datasets.gt import load_ground_truth
    from labelaudit.infer.missing import FrameDetections

    path = Path(str(cfg.missing.detections))
    try:
        gt = load_ground_truth(dataset, fmt, split=split, limit=limit, strict=False)
        det = read_detections(path, gt, cfg.missing.detections_format, strict=True)
    except (DatasetError, ValueError) as exc:
        raise InferError(f"--detections: {one_line(str(exc))}") from None
    out: dict[str, Any] = {}
    threshold = cfg.missing.detection_min_score
    for f, fid in enumerate(gt.frame_ids):
        lo, hi = int(det.det_off[f]), int(det.det_off[f + 1])
        keep = [k for k in range(lo, hi) if det.scores[k] >= threshold]
        if keep:
            out[fid] = FrameDetections(
                det.boxes[keep].copy(),
                det.scores[keep].copy(),
                [det.class_names[k] for k in keep],
                [det.source[k] for k in keep],
            )
    return out


def detections_of_chunk(detections: Mapping[str, Any], refs: Sequence[FrameRef], fmt: str) -> dict[str, Any]:
    """The detections a chunk's frames need (KITTI: a unit is a frame; Waymo: a segment's frame ids
    start with its name)."""
    if not detections:
        return {}
    if fmt == "kitti":
        keys = {r.key for r in refs}
        return {k: v for k, v in detections.items() if k in keys}
    names = tuple(Path(r.key).name.split(".")[0] for r in refs)
    return {k: v for k, v in detections.items() if any(n and n in k for n in names)} or dict(detections)


def with_missing_options(cfg: RunConfig, request: InferRequest) -> RunConfig:
    """``cfg`` with the missing-label options of ``request`` (``--no-missing``, ``--detections``)."""
    if request.detections is not None:
        if not request.missing:
            raise InferError(
                "--detections and --no-missing exclude each other: the detections are used by the missing-label search"
            )
        path = Path(request.detections)
        if not path.exists():
            raise InferError(f"{path}: --detections path does not exist")
        return cfg.with_overrides(missing=replace(cfg.missing, detections=str(path.absolute())))
    if not request.missing:
        return cfg.with_overrides(missing=replace(cfg.missing, enabled=False))
    return cfg


def infer_dataset(
    request: InferRequest, progress: Progress | None = None, executor: Executor | None = None
) -> RunSummary:
    """``labelaudit infer``: resolve the format and config of ``request``, run, check something was audited.

    Raises
    ------
    InferError, DatasetError, ConfigError
        Unreadable dataset or config, bad options, output folder of another run.
    ResultsError
        The run audited no object at all (e.g. ``--classes`` names no class of the dataset).
    """
    if request.workers is not None and request.workers < 1:
        raise InferError(f"--workers must be ≥ 1, got {request.workers}")
    fmt = resolve_format(Path(request.dataset), request.dataset_format)
    cfg = resolve_config(request.config, fmt, request.classes, request.model)
    cfg = with_missing_options(cfg, request)
    summary = run_infer(replace(request, dataset_format=fmt), cfg, progress, executor)
    # Rows written by this run settle it; only a run that wrote none (everything resumed, or nothing
    # audited) opens the folder to count (pyarrow.dataset: ~0.05 s at the end of every run).
    if summary.objects == 0 and R.open_results(summary.output).dataset.count_rows() == 0:
        raise ResultsError(
            f"{summary.output}: no objects audited (classes {', '.join(cfg.classes)}); check --classes "
            f"(or pass --classes all) and {summary.output / R.ERRORS_FILE}"
        )
    return summary

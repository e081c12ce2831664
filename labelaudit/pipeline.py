"""Frames → result rows → Parquet shards: the ``labelaudit infer`` engine (DESIGN.md §2, §7, §9).

Three layers, each testable alone:

1. :func:`process_frame` — pure: one :class:`~labelaudit.datasets.Frame` and a
   :class:`~labelaudit.config.RunConfig` in, result rows and frame notes out.
2. :func:`process_chunk` — pure: a :class:`ChunkTask` (a few :class:`FrameRef` s plus the config)
   in, a :class:`ChunkResult` (an Arrow table and the errors) out. It loads its own frames, so it
   can run in any worker process or on any cluster node.
3. :func:`run_infer` — plans chunks, skips those already written (``--resume``), hands the rest to
   an :class:`Executor` and writes each returned table as an atomic shard.

The :class:`Executor` seam is ``run(units, fn) -> iterator of fn(unit)`` in any order;
:class:`SerialExecutor` and :class:`PoolExecutor` (multiprocessing) live here, a Dask executor
plugs in the same way.
"""

from __future__ import annotations

import hashlib
import math
import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
import os
import shutil
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Protocol, Sequence, TypeVar

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from labelaudit import constants as C
from labelaudit.config import CONFIG_DIR, ConfigError, RunConfig, hash_inputs, load_config
from labelaudit.datasets import DatasetError, FORMATS, Frame, FrameRef, detect_format, open_dataset
from labelaudit import results as R

T = TypeVar("T")
U = TypeVar("U")

ALL_CLASSES = "all"
"""Put this alone in ``classes`` to audit every class (``--classes all``)."""

DIFFICULTY_NAMES = {0: "Easy", 1: "Moderate", 2: "Hard"}


class InferError(ValueError):
    """Bad input, output folder or options for ``infer``; the message names the path and the fix."""


class StrictError(RuntimeError):
    """``--strict``: a frame or an object failed; the message says which and why."""


# --------------------------------------------------------------------------- layer 1: one frame


def _frame_note(frame_id: str | None, unit: str, message: str, level: str = "error", file: str | None = None, line: int | None = None) -> dict[str, Any]:
    return {"unit": unit, "frame_id": frame_id, "file": file, "line": line, "level": level, "message": message}


def _extras_for(frame: Frame, i: int) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for name in R.EXTRA_COLUMNS:
        if name not in frame.extras:
            continue
        value = frame.extras[name][i]
        if name == "difficulty" and not isinstance(value, str):
            value = DIFFICULTY_NAMES.get(int(value), "unknown")
        out[name] = value
    return out


def wants_class(cfg: RunConfig, class_name: str) -> bool:
    """Whether objects of ``class_name`` are audited under ``cfg`` (``classes = ["all"]`` = every class)."""
    return ALL_CLASSES in cfg.classes or class_name in cfg.classes


def process_frame(frame: Frame, cfg: RunConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Audit every selected box of one frame.

    Parameters
    ----------
    frame : points (N, 4) and boxes (K, 7) in the LiDAR frame
    cfg : run configuration (classes, length range, crop and model parameters)

    Returns
    -------
    rows : one dict per audited box, normalised (:func:`labelaudit.results.normalize_row`: every
        column of :data:`labelaudit.results.SCHEMA`, plain Python values, NaN as None); boxes of
        other classes are left out, boxes outside the length range get status ``skipped``, a
        box whose inference raised gets status ``error`` and the exception in ``message``.
    notes : frame warnings (level ``warning``) as rows of the errors table
    """
    from labelaudit.audit import audit_object
    from labelaudit.crop import crop_frame_pair
    from labelaudit.geometry import validate_box

    notes = [_frame_note(frame.frame_id, frame.frame_id, w, level="warning") for w in frame.warnings]
    origin = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    selected = [i for i, name in enumerate(frame.class_names) if wants_class(cfg, name)]
    rows: dict[int, dict[str, Any]] = {}
    final: set[int] = set()  # indices whose row is already normalised
    to_audit: list[int] = []
    for i in selected:
        box = frame.boxes[i]
        row: dict[str, Any] = {
            "dataset": cfg.dataset_format,
            "frame_id": frame.frame_id,
            "object_index": i,
            "object_id": frame.object_ids[i],
            "class_name": frame.class_names[i],
            **dict(zip(R.BOX_COLUMNS, (float(v) for v in box))),
            "distance": float(math.hypot(box[0] - origin[0], box[1] - origin[1])),
            "model": cfg.model.model,
            "sigma": cfg.model.sigma,
            **_extras_for(frame, i),
        }
        rows[i] = row
        try:
            validate_box(box)
        except ValueError as exc:
            row.update(status="error", message=f"invalid box: {exc}")
            continue
        length = float(box[3])
        if not (cfg.min_length <= length <= cfg.max_length):
            row.update(status="skipped", message=f"length {length:.2f} m outside [{cfg.min_length:g}, {cfg.max_length:g}] m")
            continue
        to_audit.append(i)

    if to_audit:
        boxes = np.ascontiguousarray(frame.boxes[to_audit], dtype=float)
        # The label-error fit gets a wider crop (a box shifted off its object must still see it);
        # one Open3D pass gives both crops, the narrow one refined from the wide one exactly.
        indices, fit_indices = crop_frame_pair(frame.points, boxes, cfg.crop)
        for i, idx, fit_idx in zip(to_audit, indices, fit_indices):
            row = rows[i]
            points = frame.points[idx]
            try:
                result = audit_object(frame.boxes[i], points, frame.class_names[i], cfg, origin, fit_points=frame.points[fit_idx])
                # values the schema cannot hold fail here, per object; the row is final after this
                rows[i] = R.normalize_row({**row, **result})
                final.add(i)
            except Exception as exc:  # one bad object never sinks the frame (DESIGN.md §9)
                row.update(status="error", message=f"{type(exc).__name__}: {exc}", num_points=len(idx))
    return [rows[i] if i in final else R.normalize_row(rows[i]) for i in selected], notes


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


@dataclass
class ChunkResult:
    """What a worker returns for one chunk."""

    name: str
    table: pa.Table
    errors: list[dict[str, Any]]
    units: int
    frames: int
    objects: int
    seconds: float

    @property
    def failed(self) -> list[dict[str, Any]]:
        """Frame-level errors (warnings excluded)."""
        return [e for e in self.errors if e["level"] == "error"]


_READERS: dict[tuple[Any, ...], Any] = {}


def _reader(ref: FrameRef, options: tuple[tuple[str, Any], ...]) -> Any:
    """One reader per process and dataset: opening a reader lists folders, so reuse it."""
    key = (ref.dataset_format, ref.root, options)
    if key not in _READERS:
        _READERS[key] = open_dataset(ref.root, ref.dataset_format, **dict(options))
    return _READERS[key]


def process_chunk(task: ChunkTask) -> ChunkResult:
    """Load and audit every frame of a chunk of units; never raises for bad input.

    A unit that cannot be read (or a frame whose crop fails) becomes an error row; objects whose
    inference fails become rows with status ``error``. With ``task.debug`` unexpected exceptions
    (bugs, not bad input) propagate so their traceback is visible.
    """
    start = time.perf_counter()
    rows: list[dict[str, Any]] = []
    errors: list[dict[str, Any]] = []
    frames = 0
    for ref in task.refs:
        try:
            reader = _reader(ref, task.reader_options)
            for n, frame in enumerate(reader.load_unit(ref)):
                if task.max_frames_per_unit is not None and n >= task.max_frames_per_unit:
                    break
                try:  # a frame that fails (e.g. in the crop) never takes the rest of its unit along
                    frame_rows, notes = process_frame(frame, task.cfg)
                except Exception as exc:
                    if task.debug:
                        raise
                    errors.append(_frame_note(frame.frame_id, ref.key, f"{type(exc).__name__} in frame {frame.frame_id}: {exc}"))
                    continue
                for note in notes:
                    note["unit"] = ref.key
                rows.extend(frame_rows)
                errors.extend(notes)
                frames += 1
        except DatasetError as exc:  # the reader gave up on the unit (or on the rest of it)
            errors.append(_frame_note(None, ref.key, str(exc), file=exc.path, line=exc.line))
        except Exception as exc:
            if task.debug:
                raise
            errors.append(_frame_note(None, ref.key, f"{type(exc).__name__} while reading {ref.key}: {exc}"))
    table = R.rows_to_table(rows, normalized=True)  # process_frame's rows are normalised
    return ChunkResult(task.name, table, errors, len(task.refs), frames, table.num_rows, time.perf_counter() - start)


# --------------------------------------------------------------------------- executors


class Executor(Protocol):
    """Runs a pure function over units of work; results may come back in any order."""

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        ...

    def close(self) -> None:
        """Stop workers early (after an error); a no-op when nothing runs."""
        ...


class SerialExecutor:
    """In-process, one unit after the other (``--workers 1``, tests, debugging)."""

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        for unit in units:
            yield fn(unit)

    def close(self) -> None:
        pass


_SINGLE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Workers inherit 1 BLAS/OpenMP thread each: the pool already uses every core."""
    saved = {k: os.environ.get(k) for k in _SINGLE_THREAD_ENV}
    for k in _SINGLE_THREAD_ENV:
        os.environ.setdefault(k, "1")
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


class WorkerCrashed(RuntimeError):
    """A worker process died (killed, out of memory, a crash in native code)."""


class PoolExecutor:
    """A pool of ``workers`` processes.

    Workers fork from a ``forkserver`` that has imported the heavy modules once
    (:data:`~labelaudit.constants.WORKER_PRELOAD`: Open3D, SciPy, the core), so they start warm;
    the server is single-threaded, so forking it is safe with Open3D/BLAS (forking the main
    process, which may run Arrow threads, is not).

    Built on :class:`concurrent.futures.ProcessPoolExecutor`, so a worker that dies raises
    :class:`WorkerCrashed` instead of hanging the run; finished shards are kept for ``--resume``.
    """

    def __init__(self, workers: int, start_method: str = C.POOL_START_METHOD):
        if workers < 1:
            raise ValueError(f"workers must be ≥ 1, got {workers}")
        self.workers = workers
        self.start_method = start_method
        self._pool: ProcessPoolExecutor | None = None

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        if not units:
            return
        method = self.start_method if self.start_method in multiprocessing.get_all_start_methods() else "spawn"  # Windows
        ctx = multiprocessing.get_context(method)
        if method == "forkserver":
            ctx.set_forkserver_preload(list(C.WORKER_PRELOAD))  # missing modules are skipped
        with _single_threaded_children():
            self._pool = ProcessPoolExecutor(max_workers=min(self.workers, len(units)), mp_context=ctx)
            futures = [self._pool.submit(fn, u) for u in units]
        try:
            for future in as_completed(futures):
                try:
                    yield future.result()
                except BrokenProcessPool:
                    raise WorkerCrashed(
                        "a worker process died (killed, out of memory or a native crash); finished shards are kept — "
                        "rerun the same command to resume, with fewer --workers if memory is short"
                    ) from None
        finally:
            self.close()

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None


def make_executor(workers: int | None) -> Executor:
    """Serial for one worker, else a process pool (``None`` = every core)."""
    n = workers if workers is not None else (os.cpu_count() or 1)
    return SerialExecutor() if n <= 1 else PoolExecutor(n)


# --------------------------------------------------------------------------- layer 3: a run


@dataclass(frozen=True)
class InferRequest:
    """The options of ``labelaudit infer`` (everything but the model parameters)."""

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


def resolve_format(dataset: Path, fmt: str) -> str:
    """``auto`` → the detected format; raises :class:`InferError` with the reason."""
    if fmt != "auto" and fmt not in FORMATS:
        raise InferError(f"--format {fmt!r}: expected auto or one of {', '.join(FORMATS)}")
    if not dataset.exists():
        raise InferError(f"{dataset}: dataset path does not exist")
    if fmt == "auto":
        try:
            return detect_format(dataset)
        except DatasetError as exc:
            raise InferError(str(exc)) from None
    return fmt


def resolve_config(config_path: Path | None, dataset_format: str, classes: Sequence[str] | None = None, model: str | None = None) -> RunConfig:
    """Load the TOML config (or the built-in one of the format) and apply CLI overrides.

    Raises
    ------
    ConfigError
        Unreadable file, unknown key, bad value.
    """
    if config_path is None:
        name = "waymo.toml" if dataset_format.startswith("waymo") else "kitti.toml"
        cfg = load_config(None, dataset_format) if (CONFIG_DIR / name).is_file() else RunConfig(dataset_format=dataset_format)
    else:
        cfg = load_config(config_path, dataset_format)
    if classes is not None:
        classes = tuple(c.strip() for c in classes if c.strip())
        if not classes:
            raise ConfigError("--classes: expected a comma-separated list of class names or 'all'")
        cfg = cfg.with_overrides(classes=(ALL_CLASSES,) if ALL_CLASSES in classes else classes)
    if model is not None:
        if model not in ("bev", "3d"):
            raise ConfigError(f"--model: expected bev or 3d, got {model!r}")
        cfg = cfg.with_overrides(model=replace(cfg.model, model=model))
    return cfg


def chunk_name(refs: Sequence[FrameRef]) -> str:
    """Shard file name of a chunk: a hash of its unit keys, so a resumed run finds it again."""
    digest = hashlib.sha256("\n".join(r.key for r in refs).encode()).hexdigest()[:20]
    return f"part-{digest}.parquet"


def chunk_size_for(dataset_format: str, num_units: int) -> int:
    """Units per chunk: about :data:`~labelaudit.constants.TARGET_CHUNKS` chunks, at most the
    format's :data:`~labelaudit.constants.CHUNK_UNITS`. Depends only on the unit list, never on
    the worker count, so a run resumed with other ``--workers`` finds its shards again."""
    cap = C.CHUNK_UNITS.get(dataset_format, 1)
    return int(min(cap, max(1, math.ceil(num_units / C.TARGET_CHUNKS))))


def plan_chunks(refs: Sequence[FrameRef], chunk_units: int) -> list[tuple[str, tuple[FrameRef, ...]]]:
    """Split units into fixed-size chunks in list order (independent of the worker count)."""
    chunks = [tuple(refs[i : i + chunk_units]) for i in range(0, len(refs), chunk_units)]
    return [(chunk_name(c), c) for c in chunks]


def _is_whole_parquet(path: Path) -> bool:
    try:
        pq.read_metadata(path)
        return True
    except Exception:
        return False


LOCK_NAME = ".labelaudit.lock"
"""Lock file of a results folder while ``infer`` writes to it (holds the writer's pid)."""


def check_output_folder(output: Path) -> None:
    """Refuse a path that is a file, or a non-empty folder that is not a results folder."""
    if output.exists() and not output.is_dir():
        raise InferError(f"{output}: exists and is not a folder; choose another -o/--output")
    if output.is_dir() and not (output / R.MANIFEST_NAME).exists() and any(p.name != LOCK_NAME for p in output.iterdir()):
        raise InferError(
            f"{output}: folder is not empty and has no {R.MANIFEST_NAME} (not a labelaudit results folder); "
            "choose a new or empty -o/--output"
        )


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


@contextmanager
def output_lock(output: Path) -> Iterator[None]:
    """Hold ``output/.labelaudit.lock`` for the duration of a run.

    A second ``infer`` on the same folder stops with :class:`InferError` instead of interleaving
    shards; a lock left by a killed run (its pid is gone) is taken over. Same-machine only.
    """
    output.mkdir(parents=True, exist_ok=True)
    path = output / LOCK_NAME
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(path.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _pid_alive(pid):
                raise InferError(f"{output}: another labelaudit infer (pid {pid}) is writing to this folder; wait for it or choose another -o/--output") from None
            path.unlink(missing_ok=True)  # stale: its writer is gone
            continue
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        break
    else:
        raise InferError(f"{output}: cannot take the lock {path}")
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def prepare_output(output: Path, metadata: Mapping[str, Any], overwrite: bool) -> None:
    """Create, reset (``--overwrite``) or check for resume a results folder.

    Raises
    ------
    InferError
        The folder is not a results folder, or holds results of other parameters / another input
        (unless ``overwrite``).
    """
    check_output_folder(output)
    manifest = R.read_manifest(output) if output.is_dir() else None
    if manifest is not None and overwrite:
        for sub in (R.OBJECTS_DIR, R.ERRORS_DIR):
            if (output / sub).is_dir():
                shutil.rmtree(output / sub)
        for name in (R.ERRORS_FILE, R.MANIFEST_NAME):
            (output / name).unlink(missing_ok=True)
    elif manifest is not None:
        why = R.resume_mismatch(manifest, metadata)
        if why is not None:
            raise InferError(f"{output}: cannot resume: {why}; pass --overwrite to replace these results, or choose another -o/--output")
    output.mkdir(parents=True, exist_ok=True)
    R.remove_temp_files(output)


def run_infer(request: InferRequest, cfg: RunConfig, progress: Progress | None = None, executor: Executor | None = None) -> RunSummary:
    """Audit a dataset folder into a results folder (``labelaudit infer``).

    Parameters
    ----------
    request : input, output and run options
    cfg : model configuration (its ``dataset_format`` must be the resolved format)
    progress : progress sink (default: silent)
    executor : default :func:`make_executor` of ``request.workers``

    Raises
    ------
    InferError
        Unreadable dataset, no frames, output folder of another run.
    StrictError
        ``request.strict`` and a frame or an object failed.
    """
    start = time.perf_counter()
    progress = progress or NoProgress()
    dataset = Path(request.dataset)
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
    if request.limit is not None:
        if request.limit < 1:
            raise InferError(f"--limit must be ≥ 1, got {request.limit}")
        refs = refs[: request.limit]
    if not refs:
        raise InferError(f"{dataset}: no frames found (format {fmt}{', split ' + request.split if request.split else ''})")

    inputs = hash_inputs(cfg)
    metadata = R.run_metadata(
        inputs["params"], cfg.param_hash(), str(dataset.resolve()), fmt, constants_digest=inputs["constants_digest"], split=request.split, limit=request.limit
    )
    output = Path(request.output)
    check_output_folder(output)
    with output_lock(output):
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
    executor: Executor | None,
    start: float,
) -> RunSummary:
    prepare_output(output, metadata, request.overwrite)

    chunk_units = request.chunk_units or chunk_size_for(fmt, len(refs))
    chunks = plan_chunks(refs, chunk_units)
    shard_dir, err_dir = output / R.OBJECTS_DIR, output / R.ERRORS_DIR
    done = {name for name, _ in chunks if (shard_dir / name).is_file() and _is_whole_parquet(shard_dir / name)}
    R.write_json_atomic({**metadata, "complete": False, "units": len(refs), "chunks": len(chunks)}, output / R.MANIFEST_NAME)

    tasks = [
        ChunkTask(name, c, cfg, reader_options, request.limit if fmt != "kitti" else None, request.debug)
        for name, c in chunks
        if name not in done
    ]
    executor = executor or make_executor(request.workers)
    frames = objects = 0
    progress.start(len(refs), sum(len(c) for name, c in chunks if name in done))
    try:
        for result in executor.run(tasks, process_chunk):
            if request.strict:
                _raise_if_failed(result)
            if result.errors:
                R.write_parquet_atomic(R.errors_to_table(result.errors, metadata), err_dir / result.name)
            else:
                (err_dir / result.name).unlink(missing_ok=True)
            # The object shard is written last: its presence marks the chunk complete for --resume.
            R.write_parquet_atomic(R.with_metadata(result.table, metadata), shard_dir / result.name)
            frames += result.frames
            objects += result.objects
            progress.advance(result)
    finally:
        executor.close()
        progress.stop()

    # Shards of an earlier plan (e.g. another --limit) would mix into the results: remove them.
    planned = {name for name, _ in chunks}
    for d in (shard_dir, err_dir):
        if d.is_dir():
            for p in d.glob("*.parquet"):
                if p.name not in planned:
                    p.unlink()
    error_parts = sorted(err_dir.glob("*.parquet")) if err_dir.is_dir() else []
    errors = pa.concat_tables([pq.read_table(p) for p in error_parts]).cast(R.ERRORS_SCHEMA) if error_parts else R.ERRORS_SCHEMA.empty_table()
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
    return RunSummary(output, manifest, len(refs), len(chunks), len(done), frames, objects, failed, errors.num_rows - failed, wall)


def _raise_if_failed(result: ChunkResult) -> None:
    failed = result.failed
    if failed:
        e = failed[0]
        raise StrictError(f"--strict: unit {e['unit']} failed: {e['message']}")
    if result.table.num_rows:
        status = result.table.column("status").to_pylist()
        if "error" in status:
            i = status.index("error")
            row = result.table.slice(i, 1).to_pylist()[0]
            raise StrictError(f"--strict: frame {row['frame_id']} object {row['object_index']} failed: {row['message']}")

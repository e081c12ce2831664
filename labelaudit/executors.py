"""Executors: run a pure function over units of work, serially, in a process pool, (later) on Dask.

The seam is ``run(units, fn) -> iterator of fn(unit)`` in any order, plus ``close()``. ``infer`` and
``simulate`` use the same implementations. Executors know nothing about labels, rows or files.
"""

from __future__ import annotations

import multiprocessing
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
import os
from contextlib import contextmanager
from typing import Callable, Iterator, Protocol, Sequence, TypeVar


from labelaudit import constants as C
from labelaudit.errors import WorkerCrashed

T = TypeVar("T")
U = TypeVar("U")


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


class PoolExecutor:
    """A pool of ``workers`` processes.

    Workers fork from a ``forkserver`` that has imported the heavy modules once
    (:data:`~labelaudit.constants.WORKER_PRELOAD`: Open3D, SciPy, the core), so they start warm;
    the server is single-threaded, so forking it is safe with Open3D/BLAS (forking the main
    process, which may run Arrow threads, is not).

    Built on :class:`concurrent.futures.ProcessPoolExecutor`, so a worker that dies raises
    :class:`WorkerCrashed` instead of hanging the run; finished shards are kept for ``--resume``.
    """

    def __init__(self, workers: int, start_method: str = C.POOL_START_METHOD, preload: Sequence[str] = C.WORKER_PRELOAD):
        if workers < 1:
            raise ValueError(f"workers must be ≥ 1, got {workers}")
        self.workers = workers
        self.start_method = start_method
        self.preload = tuple(preload)  # modules the fork server imports (only the first pool of a process starts it)
        self._pool: ProcessPoolExecutor | None = None

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        if not units:
            return
        method = self.start_method if self.start_method in multiprocessing.get_all_start_methods() else "spawn"  # Windows
        ctx = multiprocessing.get_context(method)
        if method == "forkserver":
            ctx.set_forkserver_preload(list(self.preload))  # missing modules are skipped
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


def make_executor(workers: int | None, preload: Sequence[str] = C.WORKER_PRELOAD) -> Executor:
    """Serial for one worker, else a process pool (``None`` = every core) whose fork server imports ``preload``."""
    n = workers if workers is not None else (os.cpu_count() or 1)
    return SerialExecutor() if n <= 1 else PoolExecutor(n, preload=preload)

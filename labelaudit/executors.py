"""Executors: run a pure function over units of work, serially, in a process pool, or on a Dask cluster.

The seam is ``start()`` (optional early start-up: fork server, cluster connection), ``run(units, fn)
-> iterator of fn(unit)`` in any order, each result exactly once, plus ``close()``. ``infer`` and
``simulate`` use the same implementations (:func:`make_executor`). Executors know nothing about
labels, rows or files: the caller writes what comes back. Dask is imported only by
:class:`DaskExecutor` (``infer --scheduler``).
"""

from __future__ import annotations

import functools
import logging
import multiprocessing
import os
import re
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from typing import Any, Callable, Iterator, Protocol, Sequence, TypeVar

from labelaudit import constants as C
from labelaudit.errors import ClusterError, UsageError, WorkerCrashed

T = TypeVar("T")
U = TypeVar("U")


# --------------------------------------------------------------------------- executors


class Executor(Protocol):
    """Runs a pure function over units of work; results may come back in any order."""

    def start(self) -> None:
        """Begin start-up work early (optional; :func:`run` starts whatever is not running)."""
        ...

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]: ...

    def close(self) -> None:
        """Stop workers early (after an error), or wait for those of a finished run to exit (a
        pool stops them once every result is back); a no-op when nothing runs."""
        ...


_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameter numbers (malloc.h)


@functools.lru_cache(maxsize=1)
def tune_allocator() -> bool:
    """Keep freed memory for reuse in the process that audits (glibc only; elsewhere a no-op, False).

    A box's arrays (responsibilities, rasters: a few MB for a box of 10⁴ points) are allocated and
    freed once per box; with glibc's defaults each such block is a fresh ``mmap`` whose pages fault
    in again on every box. Blocks below :data:`~labelaudit.constants.MALLOC_MMAP_THRESHOLD` come
    from the heap instead, and up to :data:`~labelaudit.constants.MALLOC_TRIM_THRESHOLD` of free
    heap is kept (minor page faults 220 → 4 per frame, ~0.5–1 ms; a worker's memory may stay that much
    higher). Results are
    unchanged: only where memory comes from. Called once per process, where chunks are processed.
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process' own symbols: libc's, without find_library's `ldconfig -p`
    except (OSError, AttributeError, TypeError):  # not glibc (macOS, Windows, musl without mallopt)
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, C.MALLOC_MMAP_THRESHOLD)) and bool(
        mallopt(_M_TRIM_THRESHOLD, C.MALLOC_TRIM_THRESHOLD)
    )


class SerialExecutor:
    """In-process, one unit after the other (``--workers 1``, tests, debugging)."""

    def start(self) -> None:
        pass

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        for unit in units:
            yield fn(unit)

    def close(self) -> None:
        pass


_SINGLE_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
FORK_SERVER_ENV = "LABELAUDIT_FORK_SERVER"
"""Set (to the parent's pid) while the fork server starts: :mod:`labelaudit.infer.warmup` then makes
the server skip its interpreter teardown when it exits (up to a second with numba and Arrow loaded,
during which it still holds the caller's stdout/stderr pipes)."""


def single_threaded_blas() -> None:
    """One BLAS/OpenMP thread in this process and its children, unless the caller's environment
    sets a number.

    For a process whose work is elsewhere: ``infer``'s main process plans, writes and reports
    while its workers audit with one thread each. OpenBLAS starts a thread per core when NumPy
    loads, and those threads spin while the process imports Arrow and Typer (~0.1 s of CPU on two
    cores, taken from the fork server that imports beside it). Takes effect only before NumPy is
    imported; results are unchanged (the audit's matrices are far below BLAS's threading sizes,
    and the workers already run with one thread).
    """
    for k in _SINGLE_THREAD_ENV:
        os.environ.setdefault(k, "1")


@contextmanager
def _single_threaded_children() -> Iterator[None]:
    """Workers inherit 1 BLAS/OpenMP thread each: the pool already uses every core."""
    saved = {k: os.environ.get(k) for k in (*_SINGLE_THREAD_ENV, FORK_SERVER_ENV)}
    for k in _SINGLE_THREAD_ENV:
        os.environ.setdefault(k, "1")
    os.environ[FORK_SERVER_ENV] = str(os.getpid())
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def start_fork_server(preload: Sequence[str], fork: bool = False) -> bool:
    """Launch this process' ``multiprocessing`` fork server, importing ``preload``; False where
    there is none (Windows). Returns at once: the server imports while the caller goes on.

    There is one server per process, and its preload is fixed when it starts: a server already
    running keeps its own (its children then import what they miss). The pool's workers and a
    LocalCluster's Dask workers both fork from it, so they start with the core and its compiled
    kernels loaded.

    ``fork``: start the server as a fork of this process (:func:`fork_the_fork_server`) where that
    is safe, so it inherits the interpreter and whatever this process has imported; for a process
    that knows itself small and clean (the console script, before its command's imports). Otherwise,
    and by default, a new interpreter, as ``multiprocessing`` starts it.
    """
    if "forkserver" not in multiprocessing.get_all_start_methods():
        return False
    from multiprocessing import forkserver

    multiprocessing.get_context("forkserver").set_forkserver_preload(list(preload))  # missing modules are skipped
    with _single_threaded_children():
        if not (fork and fork_the_fork_server(preload)):
            forkserver.ensure_running()
    return True


def single_threaded() -> bool:
    """True when this process runs one thread, native ones included (Linux's /proc; else False)."""
    try:
        return len(os.listdir(f"/proc/{os.getpid()}/task")) == 1
    except OSError:
        return False


FORKED_SERVER_NAME, FORKED_TRACKER_NAME = "la-forkserver", "la-rtracker"
"""Process names (``/proc/PID/comm``: ``ps -o comm``, ``top``) of a fork server and a resource tracker
forked from the console script (:func:`fork_the_fork_server`), whose command line is the main process'
own: the benchmarks tell them apart by these."""


def _name_this_process(name: str) -> None:
    """Set this process' name as ``ps``/``top`` show it (Linux; elsewhere nothing happens)."""
    try:
        with open("/proc/self/comm", "w") as f:
            f.write(name)
    except OSError:
        pass


def _fork_the_resource_tracker() -> bool:
    """Start ``multiprocessing``'s resource tracker (which unlinks the pool's semaphores if a process
    dies holding them) as a fork of this single-threaded process, as :func:`fork_the_fork_server`
    does the server: the stdlib's ``resource_tracker.main`` on a pipe whose write end only this
    process holds (and passes to its children). False where one runs already."""
    import signal
    import sys
    from multiprocessing import resource_tracker

    tracker = resource_tracker._resource_tracker
    with tracker._lock:
        if tracker._fd is not None:
            return False
        blocked = (signal.SIGINT, signal.SIGTERM)  # as the stdlib's start: ignored once main() runs
        r, w = os.pipe()
        signal.pthread_sigmask(signal.SIG_BLOCK, blocked)
        pid = -1
        try:
            pid = os.fork()
        finally:
            if pid != 0:
                signal.pthread_sigmask(signal.SIG_UNBLOCK, blocked)
        if pid == 0:  # the tracker
            code = 1
            try:
                os.close(w)
                _name_this_process(FORKED_TRACKER_NAME)
                resource_tracker.main(r)
                code = 0
            except BaseException:
                sys.excepthook(*sys.exc_info())
            finally:
                os._exit(code)
        os.close(r)
        tracker._fd, tracker._pid = w, pid
    return True


def _preload_then_collect(preload: Sequence[str]) -> None:
    """In a fork server forked from the console script: import ``preload`` as the stdlib's
    ``forkserver.main`` does (a module that is not there is skipped), with the garbage collector
    off, then freeze what exists and turn the collector on for the workers.

    The console script runs its start-up with the collector off (:mod:`labelaudit.__main__`), so
    every object the server inherits is still in the youngest generation: with the collector on,
    the first collections walked them all and the preload's ~10⁵ new ones again (~10 ms of the
    server's ~0.15 s of CPU before it can fork a worker, the start-up's critical path). What the
    preload and warm-up make lives as long as the server and its workers; frozen, no worker's
    collection walks it either (Python's advice for a process that forks workers:
    :func:`gc.freeze` before the fork).
    """
    import gc

    gc.disable()  # (the console script's is off already)
    for name in preload:
        try:
            __import__(name)
        except ImportError:
            pass
    gc.freeze()
    gc.enable()


def fork_the_fork_server(preload: Sequence[str]) -> bool:
    """Start this process' ``multiprocessing`` fork server as a fork of this process instead of a new
    interpreter; False (nothing done) where that is not safe or not known to work, and the caller
    then starts it the usual way.

    What the usual start does again in a new interpreter (~30 ms of CPU: the interpreter, ``site``,
    ``multiprocessing``; ~15 ms for the resource tracker, forked the same way), the fork inherits;
    the server then imports ``preload`` exactly as the usual one does, speaks the same protocol on
    the same kind of socket (the stdlib's ``forkserver.main``) and forks the workers the same way,
    so they run the same code on the same modules. Only while this process runs a single thread (a fork of a process with other threads,
    e.g. Arrow's or BLAS's, may inherit a held lock) and on the CPython versions whose fork-server
    protocol this follows (3.11–3.13; 3.14 adds an authentication key).
    """
    import sys

    if not ((3, 11) <= sys.version_info[:2] <= (3, 13)) or not single_threaded():
        return False
    import socket
    import threading
    from multiprocessing import connection, forkserver, resource_tracker, util

    server = forkserver._forkserver
    with server._lock:
        if server._forkserver_pid is not None:
            return False  # one already started (the stdlib checks that it still runs)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()  # nothing buffered here is written again by a child
            except (AttributeError, OSError, ValueError):
                pass
        if not _fork_the_resource_tracker():
            resource_tracker.ensure_running()  # the workers share it, as with the usual start
        with socket.socket(socket.AF_UNIX) as listener:
            address = connection.arbitrary_address("AF_UNIX")
            listener.bind(address)
            if not util.is_abstract_socket_namespace(address):
                os.chmod(address, 0o600)
            listener.listen()
            alive_r, alive_w = os.pipe()  # every client holds the write end; EOF ends the server
            pid = os.fork()
            if pid == 0:  # the server
                code = 1
                try:
                    os.close(alive_w)
                    _name_this_process(FORKED_SERVER_NAME)
                    server._lock = threading.Lock()  # held by the parent at the fork
                    _preload_then_collect(preload)
                    forkserver.main(listener.fileno(), alive_r, [])  # preloaded: its own loop only
                except SystemExit:  # its clients are gone
                    code = 0
                except BaseException:
                    sys.excepthook(*sys.exc_info())
                finally:
                    os._exit(code)
            os.close(alive_r)
        server._forkserver_address = address
        server._forkserver_alive_fd = alive_w
        server._forkserver_pid = pid
    return True


def fork_server_preload(workers: int | None, scheduler: str | None = None) -> tuple[str, ...] | None:
    """What the fork server of ``--workers`` / ``--scheduler`` imports, or None where the run has none
    (one worker: serial; a ``tcp://`` cluster; a bad value, which the run itself reports)."""
    if workers is not None and workers < 1:
        return None
    if scheduler is not None:
        try:
            _, local_workers = parse_scheduler(scheduler, workers)
        except UsageError:
            return None
        return local_cluster_preload() if local_workers is not None else None
    n = workers if workers is not None else (os.cpu_count() or 1)
    return tuple(C.WORKER_PRELOAD) if n > 1 else None


class PoolExecutor:
    """A pool of ``workers`` processes.

    Workers fork from a ``forkserver`` that has imported the heavy modules once
    (:data:`~labelaudit.constants.WORKER_PRELOAD`: the core and its compiled kernels), so they
    start warm; the server is single-threaded, so forking it is safe with numba/BLAS (forking the
    main process, which may run Arrow threads, is not). :meth:`start` launches the server at once,
    so its imports overlap with the main process' own work (listing the dataset, the output folder).

    Built on :class:`concurrent.futures.ProcessPoolExecutor`, so a worker that dies raises
    :class:`WorkerCrashed` instead of hanging the run; finished shards are kept for ``--resume``.
    """

    def __init__(
        self, workers: int, start_method: str = C.POOL_START_METHOD, preload: Sequence[str] = C.WORKER_PRELOAD
    ):
        if workers < 1:
            raise ValueError(f"workers must be ≥ 1, got {workers}")
        self.workers = workers
        self.start_method = start_method
        self.preload = tuple(preload)  # modules the fork server imports (only the first pool of a process starts it)
        self._pool: ProcessPoolExecutor | None = None
        self._stopping: threading.Thread | None = None  # stops the workers of a finished run (_stop_in_background)

    def _context(self) -> Any:
        method = (
            self.start_method if self.start_method in multiprocessing.get_all_start_methods() else "spawn"
        )  # Windows
        ctx = multiprocessing.get_context(method)
        if method == "forkserver":
            ctx.set_forkserver_preload(list(self.preload))  # missing modules are skipped
        return ctx

    def start(self) -> None:
        """Launch the fork server now (it imports the preload modules while the caller goes on)."""
        if self.start_method == "forkserver":
            start_fork_server(self.preload)  # no-op where there is no fork server (Windows: spawn)

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        if not units:
            return
        self.close()  # a pool of an earlier run, still stopping, is waited for
        ctx = self._context()
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
        except BaseException:  # an error, or the caller stopped early (GeneratorExit)
            self.close()
            raise
        self._stop_in_background()

    def _stop_in_background(self) -> None:
        """Every result is back: stop the workers (each exits once it reads its stop message, its
        exit status comes back through the fork server) in a thread, while the caller finishes its
        own work (``infer``: the end of the run, ~10 ms, on the run's critical path either way);
        :meth:`close` waits for it."""
        pool, self._pool = self._pool, None
        if pool is not None:
            self._stopping = threading.Thread(target=pool.shutdown, name="labelaudit-pool-stop")
            self._stopping.start()

    def close(self) -> None:
        """Stop the workers (pending chunks cancelled) and wait until they have exited."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None
        if self._stopping is not None:
            self._stopping.join()
            self._stopping = None


# --------------------------------------------------------------------------- Dask


@functools.lru_cache(maxsize=1)
def code_fingerprint() -> dict[str, str]:
    """What must be equal on the client and every worker for equal rows: the labelaudit version and
    the digest of its fixed numbers (:func:`labelaudit.config.constants_digest`)."""
    from labelaudit import __version__
    from labelaudit.config import constants_digest

    return {"version": __version__, "constants": constants_digest()}


def _describe(fp: dict[str, str]) -> str:
    return f"labelaudit {fp.get('version')} (constants {fp.get('constants')})"


def _mismatch_message(where: str, expected: dict[str, str], got: dict[str, str]) -> str:
    return (
        f"{where} runs {_describe(got)}, this client {_describe(expected)}; install the same labelaudit on the "
        "client and every worker (docs/scale.md)"
    )


def _checked_call(unit: Any, *, fn: Callable[[Any], Any], expected: dict[str, str]) -> Any:
    """A task on a Dask worker: refuse to compute under other code than the client's (a worker
    that joined after the connect-time check), else ``fn(unit)``."""
    got = code_fingerprint()
    if got != expected:
        raise ClusterError(_mismatch_message(f"Dask worker (pid {os.getpid()})", expected, got))
    return fn(unit)


async def _probe(address: str, timeout: float) -> None:
    """Connect to a scheduler and ask its identity, within ``timeout`` seconds (raises otherwise)."""
    import asyncio

    from distributed.core import rpc

    r = rpc(address, timeout=timeout)
    try:
        await asyncio.wait_for(r.identity(), timeout)
    finally:
        await r.close_rpc()


_LOCAL = re.compile(r"^local(?::(\d+))?$")


def parse_scheduler(address: str, workers: int | None = None) -> tuple[str | None, int | None]:
    """``(scheduler address, None)`` for ``tcp://HOST:PORT`` (or another Dask protocol), ``(None, N)``
    for ``local[:N]`` (a LocalCluster of N worker processes; N = ``workers``, else every core).

    Raises
    ------
    UsageError
        A malformed address, ``local:0``, or ``--workers`` that contradicts it.
    """
    address = address.strip()
    m = _LOCAL.match(address)
    if m:
        n = int(m.group(1)) if m.group(1) else workers if workers is not None else (os.cpu_count() or 1)
        if n < 1:
            raise UsageError(f"--scheduler {address}: a local cluster needs ≥ 1 worker")
        if workers is not None and m.group(1) and workers != n:
            raise UsageError(f"--scheduler {address} and --workers {workers} disagree; give the worker count once")
        return None, n
    if workers is not None:
        raise UsageError(
            f"--workers {workers} with --scheduler {address}: a cluster's workers are set where they start "
            "(dask worker … --nworkers N); drop --workers"
        )
    if not re.match(r"^([a-z][a-z0-9+]*://)?[^\s:/]+:\d+$", address):
        raise UsageError(f"--scheduler {address!r}: expected tcp://HOST:PORT (a running Dask scheduler) or local[:N]")
    return (address if "://" in address else f"tcp://{address}"), None


class DaskExecutor:
    """Units as tasks on a Dask ``distributed`` cluster: an existing one (``tcp://HOST:PORT``) or a
    LocalCluster of processes started for the run (``local[:N]``).

    - **Connect** (:meth:`start`): an unreachable scheduler raises :class:`ClusterError` naming the
      address after :data:`~labelaudit.constants.DASK_CONNECT_TIMEOUT` s; then every worker's
      labelaudit version and constants digest must equal the client's (:func:`code_fingerprint`),
      else :class:`ClusterError` naming both. Tasks check it again (workers that join later).
    - **Run**: one task per unit, results (the chunks' Parquet shards as bytes) streamed back as
      tasks complete, each yielded exactly once and released on the cluster at once. A worker lost
      mid-run has its tasks rescheduled by Dask; a task present at more worker deaths than the
      scheduler's ``allowed-failures`` raises :class:`WorkerCrashed`.
    - Workers must see the same dataset paths as the client (docs/scale.md); nothing is written
      by them.
    """

    def __init__(
        self,
        scheduler: str | None = None,
        local_workers: int | None = None,
        connect_timeout: float = C.DASK_CONNECT_TIMEOUT,
        preload: Sequence[str] = C.WORKER_PRELOAD,
    ):
        if (scheduler is None) == (local_workers is None):
            raise ValueError("give exactly one of scheduler (an address) and local_workers (a LocalCluster size)")
        self.preload = tuple(preload)  # what the LocalCluster's workers import when they start
        self.scheduler = scheduler
        self.local_workers = local_workers
        self.connect_timeout = connect_timeout
        self._client: Any = None
        self._cluster: Any = None
        self._futures: list[Any] = []

    @property
    def address(self) -> str:
        return self.scheduler if self.scheduler is not None else f"local:{self.local_workers}"

    def start(self) -> None:
        """Connect (or start the LocalCluster) and check the workers' labelaudit; idempotent."""
        if self._client is not None:
            return
        try:
            import distributed
        except ImportError:
            raise ClusterError("--scheduler needs Dask: pip install 'dask[distributed]'") from None
        try:
            if self.scheduler is None:
                self._cluster = self._local_cluster(distributed)
                self._client = distributed.Client(self._cluster, set_as_default=False)
            else:
                self._connect(distributed)
            self._check_workers()
        except BaseException:
            self.close()
            raise

    def _local_cluster(self, distributed: Any) -> Any:
        """The LocalCluster of ``local[:N]``: its worker processes fork from the fork server
        (:func:`start_fork_server`, preloaded with Dask and the core) instead of each starting a
        new interpreter that imports them (about a second per worker, and as much again to stop)."""
        import dask

        method = "forkserver" if start_fork_server(local_cluster_preload(self.preload)) else "spawn"
        with dask.config.set({"distributed.worker.multiprocessing-method": method, **C.DASK_LOCAL_CONFIG}):
            return distributed.LocalCluster(
                n_workers=self.local_workers,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",  # any free port: never a clash with 8787
                silence_logs=logging.ERROR,
                preload=list(self.preload),  # a killed worker is handled, not news
            )

    def _connect(self, distributed: Any) -> None:
        import asyncio

        try:
            asyncio.run(_probe(self.scheduler, self.connect_timeout))
        except Exception as exc:  # refused, timed out (TimeoutError), or not a Dask scheduler
            reason = str(exc) or type(exc).__name__
            if isinstance(exc, MemoryError):
                reason = "the server there does not speak the Dask protocol"
            raise ClusterError(
                f"cannot reach the Dask scheduler at {self.scheduler} within {self.connect_timeout:g} s ({reason}); "
                "start it with `dask scheduler` and check the address, or use --scheduler local"
            ) from None
        self._client = distributed.Client(self.scheduler, timeout=self.connect_timeout, set_as_default=False)

    def _check_workers(self) -> None:
        client = self._client
        try:
            client.wait_for_workers(1, timeout=C.DASK_WORKER_WAIT)
        except Exception:
            raise ClusterError(
                f"the Dask scheduler at {self.address} has no workers after {C.DASK_WORKER_WAIT:g} s; start some with `dask worker {self.address}`"
            ) from None
        expected = code_fingerprint()
        try:
            found = client.run(code_fingerprint)
        except Exception as exc:
            raise ClusterError(
                f"the Dask workers of {self.address} cannot run labelaudit ({type(exc).__name__}: {exc}); "
                f"install {_describe(expected)} on every worker (docs/scale.md)"
            ) from None
        for worker, got in sorted(found.items()):
            if got != expected:
                raise ClusterError(_mismatch_message(f"Dask worker {worker}", expected, got))

    def run(self, units: Sequence[T], fn: Callable[[T], U]) -> Iterator[U]:
        if not units:
            return
        self.start()
        from uuid import uuid4

        import distributed

        token = uuid4().hex[:12]
        keys = [f"labelaudit-{i}-{token}" for i in range(len(units))]
        index = {k: i for i, k in enumerate(keys)}
        self._futures = self._client.map(
            _checked_call, list(units), key=keys, pure=False, fn=fn, expected=code_fingerprint()
        )
        returned: set[int] = set()
        try:
            for future in distributed.as_completed(self._futures, loop=self._client.loop):
                i = index[future.key]
                if i in returned:  # never twice, whatever the cluster reports
                    continue
                try:
                    result = future.result()
                except distributed.KilledWorker:
                    raise WorkerCrashed(
                        "a task was running on each Dask worker that died, too often to retry (out of memory or a native crash; "
                        "distributed.scheduler.allowed-failures); "
                        "finished shards are kept — rerun the same command to resume"
                    ) from None
                except distributed.client.FutureCancelledError:
                    raise ClusterError(
                        f"the Dask scheduler at {self.address} cancelled the run (restarted or lost); rerun the same command to resume"
                    ) from None
                returned.add(i)
                future.release()
                yield result
            if len(returned) != len(units):
                raise WorkerCrashed(
                    f"{len(units) - len(returned)} of {len(units)} tasks never came back from {self.address}; rerun the same command to resume"
                )
        finally:
            self.close()

    def close(self) -> None:
        client, cluster, self._client, self._cluster = self._client, self._cluster, None, None
        futures, self._futures = self._futures, []
        if client is not None:
            try:
                if futures:
                    client.cancel(futures)
                client.close()
            except Exception:  # a scheduler already gone: nothing left to stop
                pass
        if cluster is not None:
            cluster.close()


def local_cluster_preload(preload: Sequence[str] = C.WORKER_PRELOAD) -> tuple[str, ...]:
    """What the fork server of a ``local[:N]`` cluster imports: Dask's worker, then ``preload``."""
    return ("distributed", *preload)


def make_executor(
    workers: int | None, preload: Sequence[str] = C.WORKER_PRELOAD, scheduler: str | None = None
) -> Executor:
    """The executor of ``--workers N`` / ``--scheduler ADDR``.

    No scheduler: serial for one worker, else a process pool (``None`` = every core) whose fork
    server imports ``preload``. A scheduler address (``tcp://HOST:PORT``) or ``local[:N]``:
    :class:`DaskExecutor` (not connected yet; its LocalCluster workers import ``preload``).

    Raises
    ------
    UsageError
        A malformed scheduler address, or ``--workers`` together with a ``tcp://`` scheduler.
    """
    if scheduler is not None:
        address, local = parse_scheduler(scheduler, workers)
        return DaskExecutor(address, local, preload=preload)
    n = workers if workers is not None else (os.cpu_count() or 1)
    return SerialExecutor() if n <= 1 else PoolExecutor(n, preload=preload)

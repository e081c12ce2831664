"""The ``labelaudit`` console script (and ``python -m labelaudit``): starts ``infer``'s fork server, then runs the Typer app.

Kept outside :mod:`labelaudit.cli` (whose import loads Typer and every command): for ``labelaudit infer`` the worker pool's fork server is started
before Typer and the commands are imported, so its imports and warm-up overlap with theirs
(about 0.3 s of a short run), and the main process runs with one BLAS thread
(:func:`labelaudit.executors.single_threaded_blas`: OpenBLAS's idle threads would spin through
those imports). The garbage collector is off during the start-up (:func:`main`), and ``infer`` ends
without the interpreter's teardown (:func:`exit_without_teardown`).
"""

from __future__ import annotations

import gc
import sys


def start_infer_fork_server(argv: list[str]) -> bool:
    """For ``infer`` with a worker pool or ``--scheduler local``: start its fork server now; True if started.

    Reads only ``--workers`` and ``--scheduler``: anything unclear is left to the command, which
    starts the server itself (a second start is a no-op), and reports bad values.
    """
    if len(argv) < 2 or argv[1] != "infer" or any(a in ("--help", "-h") for a in argv):
        return False
    seen: dict[str, str] = {}
    args = iter(argv[2:])
    for a in args:
        name, eq, value = a.partition("=")
        if name in ("--workers", "--scheduler"):
            seen[name] = value if eq else next(args, "")
    try:
        workers = int(seen["--workers"]) if "--workers" in seen else None
    except ValueError:
        return False
    from labelaudit.executors import fork_server_preload, start_fork_server

    preload = fork_server_preload(workers, seen.get("--scheduler"))
    if preload is None:
        return False
    # The server is forked from this process, which has imported nothing of the command yet: it
    # inherits the interpreter and NumPy instead of starting its own (~70 ms less CPU in the start-up,
    # where both cores are busy). NumPy comes first because this process imports it anyway (the plan);
    # with one BLAS thread (main) it starts no thread, and a fork needs a single-threaded process.
    import numpy  # noqa: F401

    return start_fork_server(preload, fork=True)


def main() -> None:
    """Console-script entry point (``labelaudit``)."""
    # The start-up (Typer, Rich, pydantic, Arrow, NumPy) makes ~10⁵ objects that live as long as the
    # process: the collector's passes over them were ~15 % of infer's main-process CPU. It stays
    # off until the command group's callback, which freezes them and turns it back on.
    gc.disable()
    if len(sys.argv) > 1 and sys.argv[1] == "infer":  # before NumPy loads: the main process only plans and writes
        from labelaudit.executors import single_threaded_blas

        single_threaded_blas()
    start_infer_fork_server(sys.argv)
    from labelaudit.cli import main as run

    if len(sys.argv) < 2 or sys.argv[1] != "infer":
        run()
        return
    try:
        run()
    except SystemExit as exc:
        exit_without_teardown(exc.code)
        raise
    exit_without_teardown(0)


def exit_without_teardown(code: object) -> None:
    """End the process now, skipping the interpreter's teardown of its modules; returns instead
    (the caller then exits the usual way) when that could lose anything.

    For ``infer``, whose main process has written and closed every file when its command returns:
    tearing down NumPy, Arrow, Typer and the rest took 0.1–0.17 s of CPU after the last shard
    (measured at load 5), on the critical path of every run. The exit handlers still run (multiprocessing's finalizers, which
    release the pool's semaphores; logging) and the standard streams are flushed. Returns when
    ``code`` is not an int (Python prints a text code), another non-daemon thread still runs
    (the interpreter would wait for it), a child process started by this one still runs (a
    ``--scheduler local`` worker that is still stopping), or a stream cannot be flushed (a closed
    pipe, which the interpreter reports).
    """
    import atexit
    import os
    import threading

    code = 0 if code is None else code
    if not isinstance(code, int) or any(
        t is not threading.main_thread() and not t.daemon and t.is_alive() for t in threading.enumerate()
    ):
        return
    # A child still running (a LocalCluster's worker still stopping) would find its scheduler, in
    # this process, gone and log a traceback.
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.active_children():
        return
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except (OSError, ValueError, AttributeError):  # a closed pipe or stream, or none at all
        return
    atexit._run_exitfuncs()  # the exit handlers, last registered first, as at a normal exit
    try:
        sys.stdout.flush()  # whatever the handlers printed
        sys.stderr.flush()
    except (OSError, ValueError, AttributeError):
        code = code or 120  # as the interpreter exits when its final flush fails
    os._exit(code)


if __name__ == "__main__":
    main()

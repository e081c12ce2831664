"""The ``labelaudit`` console script (and ``python -m labelaudit``): starts ``infer``'s fork server, then runs the Typer app.

Kept outside :mod:`labelaudit.cli` (whose import loads Typer and every command): for ``labelaudit infer`` the worker pool's fork server is started
before Typer and the commands are imported, so its imports and warm-up overlap with theirs
(about 0.3 s of a short run), and the main process runs with one BLAS thread
(:func:`labelaudit.executors.single_threaded_blas`: OpenBLAS's idle threads would spin through
those imports). The garbage collector is off during the start-up (:func:`main`).
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
    return preload is not None and start_fork_server(preload)


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

    run()


if __name__ == "__main__":
    main()

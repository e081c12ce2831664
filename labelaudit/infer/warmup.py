"""Imported by the worker pool's fork server and by Dask workers (:data:`~labelaudit.constants.WORKER_PRELOAD`):
runs one synthetic object through the per-object audit, so the compiled kernels (numba, loaded
from its on-disk cache on first call, ~0.5 s) and lazy imports are loaded once in the server and
every forked worker starts warm. Importing it anywhere else only costs that half second.

In the pool's fork server it also makes the server's exit immediate (:func:`fast_exit_in_fork_server`).
"""

from __future__ import annotations

import atexit
import os
import sys


def fast_exit_in_fork_server() -> bool:
    """In the fork server of a :class:`~labelaudit.executors.PoolExecutor` (marked by
    :data:`~labelaudit.executors.FORK_SERVER_ENV` = its parent's pid), skip the interpreter
    teardown at exit.

    The server exits when its parent does; tearing down numba and Arrow then takes up to a
    second, during which it still holds the parent's stdout/stderr, so a caller that reads them to
    the end (CI logs, ``subprocess.run(capture_output=True)``) waits for it. The server holds no
    data and writes no file; its forked workers end with ``os._exit`` anyway.
    """
    marker = os.environ.pop("LABELAUDIT_FORK_SERVER", None)
    if marker != str(os.getppid()) or "multiprocessing.forkserver" not in sys.modules:
        return False

    def _exit_now() -> None:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)

    atexit.register(_exit_now)  # registered last, so it runs first
    return True


def warm_up(strict: bool = False) -> None:
    """Audit a synthetic frame of two boxes (crops, ground, rays, covariance, JIoU-GT, box fit, hull IoU)
    in the BEV model, every format's default (and in the 3D one too where the kernels run by numba's
    JIT), search it for missing labels (with the exact overlap the search takes against labels), and
    encode the rows and candidates as a chunk's shards.

    Never raises unless ``strict`` (tests): a failed warm-up only means workers load lazily.
    """
    try:
        from dataclasses import replace

        import numpy as np

        from labelaudit.config import load_config
        from labelaudit.executors import tune_allocator

        tune_allocator()  # the forked workers inherit it
        from labelaudit.datasets import Frame
        from labelaudit.infer.rows import process_frame

        box = np.array([15.0, 3.0, 0.75, 4.2, 1.7, 1.5, 0.3])
        rng = np.random.default_rng(0)
        road = np.c_[rng.uniform(5, 25, (256, 2)) - [0, 10], np.full(256, -0.1)]  # ground and rays behind the box
        pts = np.c_[np.vstack([box[:3] + rng.normal(0.0, 1.0, (64, 3)), road]), np.zeros(320)].astype(np.float32)
        base = load_config(None, "kitti")
        rows: list = []
        from labelaudit.kernels import kernel_mode

        # Ahead of time, a 3D run's first chunk only generates the dispatch of the few kernels the BEV
        # model does not call, in each worker beside the other; the 3D frame here (~4 ms) would sit on
        # every run's start-up. On numba's JIT each such kernel loads its compiled code (~0.1 s).
        models = ("bev",) if kernel_mode()[0] == "aot" else ("bev", "3d")
        for model in models:  # crops, ground, rays, neighbours, the fit with rays, counts: every kernel
            cfg = base.with_overrides(model=replace(base.model, kind=model))
            rows += process_frame(
                Frame("warm-up", pts, np.stack([box, box + [0, 2.5, 0, 0, 0, 0, 0]]), ["Car", "Car"], ["a", "b"]), cfg
            )[0]
        # the crops' cleaning passes (geometry loads them on first use): the audit above hands its
        # crops cleaned already, the search's fits still clean theirs
        from labelaudit.core import pointops  # noqa: F401
        from labelaudit.infer.missing import find_missing

        # the missing-label search: the same returns with no label, so a cluster is boxed and its rays counted
        candidates = find_missing(Frame("warm-up", pts, np.zeros((0, 7)), [], []), base)
        from labelaudit.core.iou import bev_iou_exact

        bev_iou_exact(box, box + [0.5, 0, 0, 0, 0, 0, 0])  # the search's overlap with a frame's labels (shapely)
        from labelaudit import results as R

        # a chunk's shards, as the worker encodes them (Arrow tables, pyarrow.parquet's writer)
        R.parquet_bytes(R.rows_to_table(rows, normalized=True))
        R.parquet_bytes(R.missing_rows_to_table(candidates))
    except Exception:  # a warm-up must never stop the fork server; workers then load lazily
        if strict:
            raise


fast_exit_in_fork_server()
warm_up()

"""Imported by ``eval``'s worker fork server (:data:`~labelaudit.constants.EVAL_WORKER_PRELOAD`): loads the
compiled kernels the workers run (label samples and raster, exact cell areas, Jaccard, box clipping)
once in the server by computing one BEV JIoU pair, so forked workers start warm (3D pairs, rare,
load their extra kernels lazily). Importing it anywhere else only costs that fraction of a second.
"""

from __future__ import annotations


def warm_up(strict: bool = False) -> None:
    """One BEV JIoU pair; never raises unless ``strict`` (tests)."""
    try:
        import numpy as np

        from labelaudit.config import SpatialParams
        from labelaudit.evaluate.jiou import pair_jious
        from labelaudit.evaluate.overlap import pair_overlaps

        box = np.array([[15.0, 3.0, -0.8, 4.2, 1.7, 1.5, 0.3]])
        det = box + np.array([[0.2, 0.1, 0.0, 0.1, 0.0, 0.0, 0.05]])
        _, iou, _ = pair_overlaps(det, box, [0], [0], "bev")
        pair_jious("bev", SpatialParams(), box, np.eye(6)[None] * 0.01, det, None, "phi", [0], [0], iou, workers=1)
    except Exception:  # a warm-up must never stop the fork server; workers then load lazily
        if strict:
            raise


warm_up()

"""labelaudit: audit 3D LiDAR box labels with the generative label-uncertainty model of
"Labels Are Not Perfect: Inferring Spatial Uncertainty in Object Detection" (Feng, Wang et al.).

The public API is listed in ``__all__`` and imported on first use (so ``import labelaudit`` and the
CLI's ``--help`` stay fast); scripts and tests use these names, not the private modules.

Examples
--------
>>> import numpy as np
>>> from labelaudit import BoxDistribution, jiou
>>> from labelaudit.config import SpatialParams
>>> box = np.array([10.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
>>> a = BoxDistribution.deterministic(box, "bev")
>>> b = BoxDistribution.deterministic(box + [1.0, 0, 0, 0, 0, 0, 0], "bev")
>>> round(jiou(a, b, SpatialParams()), 2)  # deterministic boxes: JIoU = IoU = 3/5
0.6
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"
SCHEMA_VERSION = "1"

# public name → the module that owns it
_EXPORTS: dict[str, str] = {
    # the model (core/: no I/O)
    "infer_label": "labelaudit.core.posterior",
    "LabelPosterior": "labelaudit.core.posterior",
    "fit_label": "labelaudit.core.fit",
    "LabelFit": "labelaudit.core.fit",
    "hull_iou": "labelaudit.core.iou",
    "bev_iou_exact": "labelaudit.core.iou",
    "iou_3d_exact": "labelaudit.core.iou",
    "BoxDistribution": "labelaudit.core.spatial",
    "Grid": "labelaudit.core.spatial",
    "jaccard": "labelaudit.core.spatial",
    "jiou": "labelaudit.core.spatial",
    "jiou_gt": "labelaudit.core.spatial",
    "spatial_distribution": "labelaudit.core.spatial",
    # configuration
    "RunConfig": "labelaudit.config",
    "load_config": "labelaudit.config",
    # data in
    "Frame": "labelaudit.datasets",
    "FrameRef": "labelaudit.datasets",
    "open_dataset": "labelaudit.datasets",
    "detect_format": "labelaudit.datasets",
    # infer
    "audit_object": "labelaudit.infer.rows",
    "process_frame": "labelaudit.infer.rows",
    "InferRequest": "labelaudit.infer.run",
    "run_infer": "labelaudit.infer.run",
    # results and the queries over them
    "Results": "labelaudit.results",
    "open_results": "labelaudit.results",
    "read_results": "labelaudit.results",
    "read_missing": "labelaudit.results",
    "RankQuery": "labelaudit.rank",
    "rank_results": "labelaudit.rank",
    "MissingQuery": "labelaudit.rank",
    "rank_missing": "labelaudit.rank",
    "summarize": "labelaudit.summary",
    "load_gate": "labelaudit.gate",
    "evaluate_gate": "labelaudit.gate",
    # training targets (σ_p) and the KLD loss
    "export_results": "labelaudit.export",
    "export_review": "labelaudit.review",
    "kld_loss": "labelaudit.training",
    # simulation
    "NoiseSpec": "labelaudit.sim.noise",
    "simulate_dataset": "labelaudit.sim.dataset",
    # errors
    "LabelAuditError": "labelaudit.errors",
    "ConfigError": "labelaudit.errors",
    "DatasetError": "labelaudit.errors",
    "ResultsError": "labelaudit.errors",
    "InferError": "labelaudit.errors",
    "ExportError": "labelaudit.errors",
}

__all__ = sorted(_EXPORTS) + ["SCHEMA_VERSION", "__version__"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'labelaudit' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # next access is a plain lookup
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))

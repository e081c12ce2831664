"""The names of an evaluation cell, in one place: overlap metrics, AP interpolations, difficulty
levels and each class's usual overlap threshold.

Imported by the evaluation (:mod:`labelaudit.evaluate.run`) and by what reads its output (the
report's evaluation section), so it holds names and constants only — no I/O, no Arrow.
"""

from __future__ import annotations

from labelaudit import constants as C

__all__ = [
    "DIFFICULTIES",
    "INTERPS",
    "LET_INTERP",
    "LET_METRICS",
    "METRIC_NAMES",
    "METRICS",
    "family",
    "usual_threshold",
]

METRICS = ("iou", "jiou", "jiou_ratio")  # overlap measures the devkit matching runs with
LET_METRICS = ("let", "let_apl")  # Waymo's LET-3D-AP and LET-3D-APL (``eval --let``)
INTERPS = ("R40", "R11")  # the devkit's AP interpolations
LET_INTERP = "waymo"  # LET records' interpolation: Waymo's (recall points every 0.05, trapezoids)
METRIC_NAMES = {
    "iou": "IoU",
    "jiou": "JIoU",
    "jiou_ratio": "JIoU-ratio",
    "jiou_deterministic": "JIoU (det.)",
    "let": "LET-AP",
    "let_apl": "LET-APL",
}
DIFFICULTIES = {"kitti": ("easy", "moderate", "hard"), "waymo": ("level_1", "level_2"), "av2": ("all",)}


def family(dataset_format: str) -> str:
    """ "kitti", "waymo" (both Waymo versions share classes and difficulty levels) or "av2" (one
    level: every box with a LiDAR point counts, like Waymo's LEVEL_2 without the level labels)."""
    if dataset_format == "av2":
        return "av2"
    return "waymo" if dataset_format.startswith("waymo") else "kitti"


def usual_threshold(class_name: str) -> float:
    """The class's customary minimum overlap (Car/Vehicle 0.7, Pedestrian/Cyclist 0.5), case-insensitive."""
    for k, v in C.EVAL_MIN_OVERLAP.items():
        if k.lower() == class_name.lower():
            return float(v)
    return float(C.EVAL_DEFAULT_MIN_OVERLAP)

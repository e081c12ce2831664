"""Summaries of a results folder: counts by status and class, median JIoU-GT, failed frames.

What ``infer`` prints at the end of a run (and what a report opens with). Reads columns through
:class:`labelaudit.results.Results`; no printing, no ranking (that is :mod:`labelaudit.rank`).
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from labelaudit import results as R
from labelaudit.results import Results

SUMMARY_COLUMNS = ("class_name", "status", "jiou_gt")
"""The objects columns a summary is made of (:func:`summarize_columns`)."""


def summarize(results: Results) -> dict[str, Any]:
    """Counts by status, median JIoU-GT per class and failed frames (for the end-of-run summary)."""
    t = results.read(list(SUMMARY_COLUMNS))
    return summarize_columns(*(t.column(c).to_pylist() for c in SUMMARY_COLUMNS), results.failed_frames())


def summarize_columns(
    class_name: Sequence[str], status: Sequence[str], jiou_gt: Sequence[float | None], failed_frames: int
) -> dict[str, Any]:
    """:func:`summarize` of the rows' :data:`SUMMARY_COLUMNS` (any row order; a null JIoU-GT is
    None) and the number of failed frames: what a run that wrote every row itself summarises
    without reading them back."""
    status = np.asarray(status, dtype=object)
    classes = np.asarray(class_name, dtype=object)
    jiou = np.array([np.nan if v is None else v for v in jiou_gt], dtype=float)
    by_status = {s: int(np.sum(status == s)) for s in R.STATUSES if np.any(status == s)}
    per_class = {}
    for name in sorted(set(classes.tolist())):
        v = jiou[(classes == name) & np.isfinite(jiou)]
        per_class[name] = {
            "objects": int(np.sum(classes == name)),
            "median_jiou_gt": float(np.median(v)) if len(v) else None,
        }
    return {
        "objects": len(status),
        "by_status": by_status,
        "classes": per_class,
        "failed_frames": failed_frames,
    }

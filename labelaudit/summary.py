"""Summaries of a results folder: counts by status and class, median JIoU-GT, failed frames.

What ``infer`` prints at the end of a run (and what a report opens with). Reads columns through
:class:`labelaudit.results.Results`; no printing, no ranking (that is :mod:`labelaudit.rank`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from labelaudit import results as R
from labelaudit.results import Results


def summarize(results: Results) -> dict[str, Any]:
    """Counts by status, median JIoU-GT per class and failed frames (for the end-of-run summary)."""
    t = results.read(["class_name", "status", "jiou_gt"])
    status = np.asarray(t.column("status").to_pylist(), dtype=object)
    classes = np.asarray(t.column("class_name").to_pylist(), dtype=object)
    jiou = t.column("jiou_gt").to_numpy(zero_copy_only=False).astype(float)
    by_status = {s: int(np.sum(status == s)) for s in R.STATUSES if np.any(status == s)}
    per_class = {}
    for name in sorted(set(classes.tolist())):
        v = jiou[(classes == name) & np.isfinite(jiou)]
        per_class[name] = {
            "objects": int(np.sum(classes == name)),
            "median_jiou_gt": float(np.median(v)) if len(v) else None,
        }
    return {
        "objects": t.num_rows,
        "by_status": by_status,
        "classes": per_class,
        "failed_frames": results.failed_frames(),
    }

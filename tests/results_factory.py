"""Hand-built results folders (real Parquet files) for the rank / check / results tests."""

from __future__ import annotations

from pathlib import Path
from typing import Any, Sequence

from labelaudit import results as R


def make_row(
    frame_id: str, index: int, class_name: str = "Car", status: str = "ok", jiou_gt: float | None = 0.8, **kw: Any
) -> dict[str, Any]:
    """One plausible result row; ``kw`` overrides any column."""
    row: dict[str, Any] = {
        "dataset": "kitti",
        "frame_id": frame_id,
        "object_index": index,
        "object_id": f"{frame_id}:{index}",
        "class_name": class_name,
        "cx": 10.0 + index,
        "cy": 2.0,
        "cz": -0.8,
        "length": 4.0,
        "width": 1.7,
        "height": 1.5,
        "yaw": 0.1,
        "distance": 10.2 + index,
        "num_points": 0 if status == "no_points" else 120,
        "status": status,
        "sigma": 0.2,
        "jiou_gt": None if status in ("skipped", "error") else jiou_gt,
        "corner_tv": [0.01, 0.02, 0.03, 0.04],
        "std_cx": 0.05,
        "std_cy": 0.05,
        "std_cz": float("nan"),
        "std_length": 0.1,
        "std_width": 0.05,
        "std_height": float("nan"),
        "std_yaw": 0.02,
        "cov": [0.0025] * 36,
        "cov_dim": 6,
        "model": "bev",
    }
    row.update(kw)
    return row


def make_results(
    root: Path,
    shards: Sequence[Sequence[dict[str, Any]]],
    errors: Sequence[dict[str, Any]] = (),
    complete: bool = True,
    param_hash: str = "0123456789abcdef",
) -> Path:
    """Write a results folder: one shard per row list, ``errors.parquet`` and a manifest."""
    meta = R.run_metadata({"model": "bev"}, param_hash, "/data/kitti", "kitti")
    for i, rows in enumerate(shards):
        R.write_parquet_atomic(R.rows_to_table(rows, meta), root / R.OBJECTS_DIR / f"part-{i:04d}.parquet")
    R.write_parquet_atomic(R.errors_to_table(errors, meta), root / R.ERRORS_FILE)
    R.write_json_atomic({**meta, "complete": complete}, root / R.MANIFEST_NAME)
    return root


# --------------------------------------------------------------------------- the missing-label table


def make_candidate(
    frame_id: str, index: int, score: float = 0.8, class_name: str = "Car", source: str = "points", **kw: Any
) -> dict[str, Any]:
    """One plausible missing-label candidate row; ``kw`` overrides any column."""
    cx, cy = 15.0 + 3.0 * index, -4.0
    row: dict[str, Any] = {
        "frame_id": frame_id,
        "candidate_index": index,
        "class_name": class_name,
        "cx": cx,
        "cy": cy,
        "cz": -0.9,
        "length": 4.2,
        "width": 1.8,
        "height": 1.5,
        "yaw": 0.3,
        "num_points": 150,
        "distance": float((cx**2 + cy**2) ** 0.5),
        "score": score,
        "source": source,
        "dataset": "kitti",
        "size_score": 0.9,
        "shape_score": 0.8,
        "free_rays": 0,
        "max_label_iou": 0.0,
        "detection_score": 0.7 if source != "points" else None,
    }
    row.update(kw)
    return row


def add_missing(root: Path, shards: Sequence[Sequence[dict[str, Any]]]) -> Path:
    """Add a ``missing/`` table (one shard per row list, empty lists give empty shards) to a results folder."""
    for i, rows in enumerate(shards):
        R.write_parquet_atomic(R.missing_rows_to_table(rows), root / R.MISSING_DIR / f"part-{i:04d}.parquet")
    return root

"""The result rows an export needs, read into NumPy arrays (:class:`ResultArrays`).

One pass over the results folder (or a Parquet file, or an in-memory table) with the columns the
targets and the infos alignment use; the flattened φ covariances stay one flat array with per-row
offsets. It checks that every (frame_id, object_index) key is unique and computes nothing else.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from labelaudit import results as R
from labelaudit.errors import ExportError

FloatArray = NDArray[np.float64]

__all__ = ["ResultArrays", "read_result_arrays"]

_RESULT_COLUMNS = (
    "dataset", "frame_id", "object_index", "object_id", "class_name", "status",
    *R.BOX_COLUMNS, "num_points", "hull_iou", "cov", "cov_dim", "model", "label_line",
)  # fmt: skip


@dataclass
class ResultArrays:
    """The columns of a results table the export needs, as NumPy arrays (N rows).

    ``cov`` holds each row's flattened φ covariance start offset and length in ``cov_values``
    (null lists have length 0); ``num_points`` / ``hull_iou`` are NaN where null.
    """

    dataset: NDArray[np.object_]
    frame_id: NDArray[np.object_]
    object_index: NDArray[np.int64]
    object_id: NDArray[np.object_]
    class_name: NDArray[np.object_]
    status: NDArray[np.object_]
    boxes: FloatArray
    num_points: FloatArray
    hull_iou: FloatArray
    cov_dim: NDArray[np.int64]
    cov_start: NDArray[np.int64]
    cov_len: NDArray[np.int64]
    cov_values: FloatArray
    model: NDArray[np.object_]
    label_line: NDArray[np.int64]
    manifest: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame_id)

    def cov_phi(self, rows: NDArray[np.int64], p: int) -> FloatArray:
        """(len(rows), p, p) covariances of rows whose list has p² entries."""
        idx = self.cov_start[rows, None] + np.arange(p * p)[None, :]
        return self.cov_values[idx].reshape(len(rows), p, p)


def _np(col: pa.ChunkedArray, fill: Any = None) -> np.ndarray:
    if fill is not None:
        col = col.fill_null(fill)
    return col.to_numpy(zero_copy_only=False)


def read_result_arrays(results: str | Path | pa.Table) -> ResultArrays:
    """Read the rows of a results folder (or one Parquet file, or a table) into :class:`ResultArrays`.

    Raises
    ------
    labelaudit.results.ResultsError
        Unreadable or missing results.
    ExportError
        No rows, or a (frame_id, object_index) key that appears twice.
    """
    manifest: dict[str, Any] = {}
    if isinstance(results, pa.Table):
        missing = [c for c in _RESULT_COLUMNS if c not in results.column_names]
        table = results
        for c in missing:
            table = table.append_column(c, pa.nulls(table.num_rows, R.SCHEMA.field(c).type))
        table = table.select(list(_RESULT_COLUMNS))
        where = "<table>"
    else:
        opened = R.open_results(results)
        manifest = opened.manifest
        table = opened.read(list(_RESULT_COLUMNS))
        where = str(results)
    if table.num_rows == 0:
        raise ExportError(f"{where}: the results hold no objects; nothing to export")
    cov = table.column("cov").combine_chunks()
    lengths = pc.list_value_length(cov).fill_null(0).to_numpy(zero_copy_only=False).astype(np.int64)
    values = pc.list_flatten(cov).to_numpy(zero_copy_only=False).astype(float)  # null entries → NaN
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    arrays = ResultArrays(
        dataset=_np(table.column("dataset"), ""),
        frame_id=_np(table.column("frame_id")),
        object_index=_np(table.column("object_index"), -1).astype(np.int64),
        object_id=_np(table.column("object_id"), ""),
        class_name=_np(table.column("class_name"), ""),
        status=_np(table.column("status"), ""),
        boxes=np.stack([_np(table.column(c).cast(pa.float64())).astype(float) for c in R.BOX_COLUMNS], axis=1),
        num_points=_np(table.column("num_points").cast(pa.float64())).astype(float),
        hull_iou=_np(table.column("hull_iou").cast(pa.float64())).astype(float),
        cov_dim=_np(table.column("cov_dim"), -1).astype(np.int64),
        cov_start=starts,
        cov_len=lengths,
        cov_values=values if len(values) else np.zeros(1),
        model=_np(table.column("model"), ""),
        label_line=_np(table.column("label_line"), -1).astype(np.int64),
        manifest=manifest,
    )
    keys = Counter(zip(arrays.frame_id.tolist(), arrays.object_index.tolist()))
    dup = next((k for k, n in keys.items() if n > 1), None)
    if dup is not None:
        raise ExportError(
            f"{where}: frame {dup[0]} object_index {dup[1]} appears {keys[dup]} times; results must have one row per object"
        )
    return arrays

"""The Parquet table of σ_p targets (``--format parquet``), keyed by frame_id, object_index and object_id."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa

from labelaudit.export.arrays import ResultArrays
from labelaudit.export.targets import ExportTargets

__all__ = ["targets_to_table"]


def targets_to_table(arrays: ResultArrays, targets: ExportTargets) -> pa.Table:
    """The Parquet table: keys, validity, ``std_<target>`` columns and the covariance (row-major T×T).

    NaN std become null (Parquet's "not applicable"); the covariance list keeps NaN entries for the
    targets a valid row lacks (z and h of a BEV model) and is null for rows without targets.
    """
    n, Tn = len(arrays), targets.encoding.size
    cols: dict[str, pa.Array] = {
        "frame_id": pa.array(arrays.frame_id.tolist(), pa.string()),
        "object_index": pa.array(arrays.object_index, pa.int32()),
        "object_id": pa.array(arrays.object_id.tolist(), pa.string()),
        "class_name": pa.array(arrays.class_name.tolist(), pa.string()),
        "status": pa.array(arrays.status.tolist(), pa.string()),
        "label_line": pa.array(arrays.label_line, pa.int32(), mask=arrays.label_line < 0),
        "valid": pa.array(targets.valid, pa.bool_()),
        "reason": pa.array([r or None for r in targets.reason.tolist()], pa.string()),
    }
    for t, name in enumerate(targets.encoding.targets):
        v = targets.std[:, t]
        cols[f"std_{name}"] = pa.array(v, pa.float64(), mask=np.isnan(v))
    flat = pa.array(targets.cov.reshape(-1), pa.float64())
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * (Tn * Tn), pa.int32())
    cov = pa.ListArray.from_arrays(offsets, flat, mask=pa.array(~targets.valid))
    cols["cov"] = cov
    cols["cov_dim"] = pa.array(np.full(n, Tn, dtype=np.int32), pa.int32())
    table = pa.table(cols)
    order = np.lexsort((arrays.object_index, arrays.frame_id.astype(str)))
    table = table.take(pa.array(order))
    meta = {
        **targets.metadata(),
        "results_param_hash": arrays.manifest.get("param_hash"),
        "results_input": arrays.manifest.get("input"),
    }
    return table.replace_schema_metadata({b"labelaudit_export": json.dumps(meta, sort_keys=True).encode()})

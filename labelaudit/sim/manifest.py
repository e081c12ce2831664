"""The simulator's manifest file: its name and its reader.

``labelaudit simulate`` writes ``manifest.parquet`` beside the data (:mod:`labelaudit.sim.dataset`
owns its schema and writes it); what reads it back — the synthetic detector, the demo, tests — reads
it here, without importing the writers.
"""

from __future__ import annotations

import os
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

MANIFEST_NAME = "manifest.parquet"
SEQUENCE_MANIFEST_COLUMNS = (
    "frame_id",
    "object_id",
    "class_name",
    "sim_class",
    "true_box",
    "written_box",
    "perturbation",
    "track_error_kind",
    "track_error_size",
)  # the manifest of simulated sequences (Waymo segments, Argoverse 2 logs): one row per object and frame


def write_manifest_table(table: pa.Table, path: str | Path) -> Path:
    """Write a manifest table to ``path`` atomically (a temporary name, then a rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path


def read_manifest(path: str | Path) -> pa.Table:
    """Read a simulator manifest (a dataset folder or the parquet file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: simulator manifest not found (written by `labelaudit simulate`)")
    return pq.read_table(path)

"""The simulator's manifest file: its name and its reader.

``labelaudit simulate`` writes ``manifest.parquet`` beside the data (:mod:`labelaudit.sim.dataset`
owns its schema and writes it); what reads it back — the synthetic detector, the demo, tests — reads
it here, without importing the writers.
"""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

MANIFEST_NAME = "manifest.parquet"


def read_manifest(path: str | Path) -> pa.Table:
    """Read a simulator manifest (a dataset folder or the parquet file itself)."""
    path = Path(path)
    if path.is_dir():
        path = path / MANIFEST_NAME
    if not path.is_file():
        raise FileNotFoundError(f"{path}: simulator manifest not found (written by `labelaudit simulate`)")
    return pq.read_table(path)

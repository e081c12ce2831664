"""Frame → missing-label candidates: objects of the audited classes that no label explains.

:func:`find_missing` returns the rows of the ``missing/`` table (:data:`labelaudit.results.MISSING_SCHEMA`)
for one frame. Pure function: no files, no printing.
"""

from __future__ import annotations

from typing import Any

from labelaudit.config import RunConfig
from labelaudit.datasets import Frame


def find_missing(frame: Frame, cfg: RunConfig, detections: Any = None) -> list[dict[str, Any]]:
    """Candidate objects without a label in ``frame`` (rows of the ``missing/`` table).

    The point-cloud search is not wired in yet: no candidates.
    """
    return []

"""What an export did (:class:`ExportSummary`), for the CLI's table and ``--json``."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

__all__ = ["ExportSummary", "reasons_text"]


@dataclass
class ExportSummary:
    """What an export did (printed by the CLI; ``--json`` prints :meth:`to_dict`)."""

    output: str
    format: str
    encoding: str
    source: str
    results_rows: int
    rows_with_targets: int
    rows_without_targets: dict[str, int]
    infos: str | None = None
    infos_frames: int = 0
    infos_frames_without_results: int = 0
    infos_objects: int = 0
    infos_objects_with_targets: int = 0
    infos_objects_without_targets: dict[str, int] = field(default_factory=dict)
    results_frames_not_in_infos: int = 0
    results_rows_not_in_infos: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def reasons_text(reasons: Mapping[str, int]) -> str:
    """``3 DontCare, 1 no cov``: counts by reason, largest first (error messages)."""
    return ", ".join(f"{n} {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])) or "no objects"

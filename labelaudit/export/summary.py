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
    dbinfos: str | None = None
    dbinfos_objects: int = 0
    dbinfos_objects_with_targets: int = 0
    dbinfos_objects_without_targets: dict[str, int] = field(default_factory=dict)
    objects_z_h_from_prior: int = 0
    outputs: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    def add_infos_stats(self, stats: Mapping[str, Any]) -> None:
        """Take the counts of an infos alignment (:func:`labelaudit.export.infos.align_frames` and the attach step)."""
        self.infos_frames = stats["frames"]
        self.infos_frames_without_results = stats["frames_without_results"]
        self.infos_objects = stats["objects"]
        self.infos_objects_with_targets = stats["objects_with_targets"]
        self.infos_objects_without_targets = dict(stats["reasons"])
        self.results_frames_not_in_infos = stats["results_frames_not_in_infos"]
        self.results_rows_not_in_infos = stats["results_rows_not_in_infos"]


def reasons_text(reasons: Mapping[str, int]) -> str:
    """``3 DontCare, 1 no cov``: counts by reason, largest first (error messages)."""
    return ", ".join(f"{n} {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])) or "no objects"

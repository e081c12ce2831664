"""Read an ``EVAL_DIR`` written by ``labelaudit eval`` for the report: summary.json and its PNG plots.

The contract (docs/review.md): ``EVAL_DIR/summary.json`` is an object with

- ``ap``: records ``{class, difficulty, view, metric, threshold, interp, ap, num_gt, num_det}``,
  ``metric`` one of iou / jiou / jiou_ratio with ``interp`` R40 or R11, or let / let_apl (``eval
  --let``: Waymo's LET-3D-AP / APL) with ``interp`` waymo and its LET-IoU as the threshold;
- ``mean_overlap``: records ``{difficulty, distance_bin, metric, mean, count}``;
- ``counts``, ``dataset``, ``metric``: shown as given;

plus any number of ``EVAL_DIR/*.png`` plots, embedded in file-name order. Validation names the file,
the record and the field. The report shows AP at the usual thresholds only, and LET at its own
(:func:`labelaudit.evaluate.cells.usual_threshold`; R40). This module reads and
reshapes; it evaluates nothing.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

from labelaudit import constants as C
from labelaudit.evaluate.cells import INTERPS, LET_INTERP, LET_METRICS, METRICS, usual_threshold
from labelaudit.viz.objects import ViewError

__all__ = ["EvalSection", "read_eval_dir", "usual_threshold", "METRICS"]

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_AP_FIELDS: dict[str, tuple[type | tuple[type, ...], bool]] = {  # field → (types, may be null)
    "class": (str, False),
    "difficulty": ((str, int), False),
    "view": (str, False),
    "metric": (str, False),
    "threshold": ((int, float), False),
    "interp": (str, False),
    "ap": ((int, float), True),
    "num_gt": (int, False),
    "num_det": (int, False),
}
_OVERLAP_FIELDS: dict[str, tuple[type | tuple[type, ...], bool]] = {
    "difficulty": ((str, int), False),
    "distance_bin": ((str, int, float), False),
    "metric": (str, False),
    "mean": ((int, float), True),
    "count": (int, False),
}


@dataclass
class EvalSection:
    """What the report shows of an eval folder.

    Attributes
    ----------
    root : the folder
    dataset, metric : as given in summary.json
    counts : summary.json's ``counts`` as (key, value text) pairs
    ap_columns : difficulties (table columns, in order of appearance)
    ap_rows : one dict per (class, view, metric): class, view, metric, threshold, cells (one per
        difficulty: {"ap", "num_gt", "num_det"} or None), note
    overlap_columns : distance bins; overlap_rows : one dict per (metric, difficulty): cells {mean, count} or None
    plots : (file name, PNG bytes), sorted by name
    """

    root: Path
    dataset: str
    metric: str
    counts: list[tuple[str, str]]
    ap_columns: list[str]
    ap_rows: list[dict[str, Any]]
    overlap_columns: list[str]
    overlap_rows: list[dict[str, Any]]
    plots: list[tuple[str, bytes]] = field(default_factory=list)


def _check_records(records: Any, key: str, fields: Mapping[str, tuple[Any, bool]], where: Path) -> list[dict[str, Any]]:
    if not isinstance(records, list):
        raise ViewError(f"{where}: {key} must be a list of records, got {type(records).__name__}")
    for i, rec in enumerate(records):
        if not isinstance(rec, dict):
            raise ViewError(f"{where}: {key}[{i}] must be an object, got {type(rec).__name__}")
        for name, (types, nullable) in fields.items():
            if name not in rec:
                raise ViewError(f"{where}: {key}[{i}] has no field {name!r} (expected {', '.join(fields)})")
            v = rec[name]
            if v is None and nullable:
                continue
            if isinstance(v, bool) or not isinstance(v, types) or (isinstance(v, float) and not math.isfinite(v)):
                want = " or ".join(t.__name__ for t in (types if isinstance(types, tuple) else (types,)))
                raise ViewError(f"{where}: {key}[{i}].{name} must be {want}{' or null' if nullable else ''}, got {v!r}")
        metrics = METRICS + LET_METRICS if "interp" in fields else METRICS
        if rec["metric"] not in metrics:
            raise ViewError(f"{where}: {key}[{i}].metric must be one of {', '.join(metrics)}, got {rec['metric']!r}")
        if "interp" in fields:
            interps = (LET_INTERP,) if rec["metric"] in LET_METRICS else INTERPS
            if rec["interp"] not in interps:
                raise ViewError(
                    f"{where}: {key}[{i}].interp must be {' or '.join(interps)} for metric {rec['metric']}, got {rec['interp']!r}"
                )
    return records


def _text(v: Any) -> str:
    return v if isinstance(v, str) else json.dumps(v, sort_keys=True)


def _ordered(values: list[Any]) -> list[str]:
    out: list[str] = []
    for v in values:
        s = str(v)
        if s not in out:
            out.append(s)
    return out


def _ap_table(records: list[dict[str, Any]]) -> tuple[list[str], list[dict[str, Any]]]:
    columns = _ordered([r["difficulty"] for r in records])
    rows: dict[tuple[str, str, str], dict[str, Any]] = {}
    for cls in _ordered([r["class"] for r in records]):
        thr = usual_threshold(cls)
        mine = [r for r in records if r["class"] == cls and r["metric"] not in LET_METRICS]
        picked = [r for r in mine if r["interp"] == C.REPORT_AP_INTERP and abs(float(r["threshold"]) - thr) < 1e-9]
        if not picked:
            have = ", ".join(f"{t:g}" for t in sorted({float(r["threshold"]) for r in mine}))
            interps = ", ".join(sorted({r["interp"] for r in mine}))
            rows[(cls, "", "")] = {
                "class": cls,
                "view": "",
                "metric": "",
                "threshold": thr,
                "cells": [None] * len(columns),
                "note": f"no {C.REPORT_AP_INTERP} AP at {thr:g} in summary.json (thresholds {have}; {interps})",
            }
            continue
        for view in _ordered([r["view"] for r in picked]):
            for metric in METRICS:
                sel = [r for r in picked if r["view"] == view and r["metric"] == metric]
                if not sel:
                    continue
                cells: list[dict[str, Any] | None] = [None] * len(columns)
                for r in sel:
                    cells[columns.index(str(r["difficulty"]))] = {
                        "ap": r["ap"],
                        "num_gt": r["num_gt"],
                        "num_det": r["num_det"],
                    }
                rows[(cls, view, metric)] = {
                    "class": cls,
                    "view": view,
                    "metric": metric,
                    "threshold": thr,
                    "cells": cells,
                    "note": "",
                }
        for metric in LET_METRICS:  # LET: its own LET-IoU threshold and Waymo's integration
            sel = [r for r in records if r["class"] == cls and r["metric"] == metric]
            if not sel:
                continue
            cells = [None] * len(columns)
            for r in sel:
                cells[columns.index(str(r["difficulty"]))] = {
                    "ap": r["ap"],
                    "num_gt": r["num_gt"],
                    "num_det": r["num_det"],
                }
            rows[(cls, "3d", metric)] = {
                "class": cls,
                "view": sel[0]["view"],
                "metric": metric,
                "threshold": float(sel[0]["threshold"]),
                "cells": cells,
                "note": "",
            }
    return columns, list(rows.values())


def _overlap_table(records: list[dict[str, Any]]) -> tuple[list[str], list[dict[str, Any]]]:
    columns = _ordered([r["distance_bin"] for r in records])
    rows: dict[tuple[str, str], dict[str, Any]] = {}
    for metric in METRICS:
        for diff in _ordered([r["difficulty"] for r in records if r["metric"] == metric]):
            cells: list[dict[str, Any] | None] = [None] * len(columns)
            for r in records:
                if r["metric"] == metric and str(r["difficulty"]) == diff:
                    cells[columns.index(str(r["distance_bin"]))] = {"mean": r["mean"], "count": r["count"]}
            rows[(metric, diff)] = {"metric": metric, "difficulty": diff, "cells": cells}
    return columns, list(rows.values())


def read_eval_dir(root: str | Path) -> EvalSection:
    """Read and check an eval folder.

    Raises
    ------
    ViewError
        Missing folder or summary.json, invalid JSON (with line and column), a missing key, a
        record with a missing or mistyped field, or a ``*.png`` that is not a PNG.
    """
    root = Path(root)
    path = root / "summary.json"
    if not root.is_dir():
        raise ViewError(f"--eval {root}: no such folder (expected the output folder of `labelaudit eval`)")
    if not path.is_file():
        raise ViewError(f"{path}: not found; --eval expects the output folder of `labelaudit eval`")
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ViewError(f"{path}:{exc.lineno}:{exc.colno}: not valid JSON ({exc.msg})") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ViewError(f"{path}: unreadable ({exc})") from None
    if not isinstance(data, dict):
        raise ViewError(f"{path}: expected a JSON object at the top level, got {type(data).__name__}")
    missing = [k for k in ("ap", "mean_overlap", "counts", "dataset", "metric") if k not in data]
    if missing:
        raise ViewError(f"{path}: missing top-level key(s) {', '.join(missing)}")
    ap = _check_records(data["ap"], "ap", _AP_FIELDS, path)
    overlap = _check_records(data["mean_overlap"], "mean_overlap", _OVERLAP_FIELDS, path)
    counts = data["counts"]
    pairs = [(str(k), _text(v)) for k, v in counts.items()] if isinstance(counts, dict) else [("counts", _text(counts))]
    plots = []
    for png in sorted(root.glob("*.png")):
        blob = png.read_bytes()
        if not blob.startswith(PNG_SIGNATURE):
            raise ViewError(f"{png}: not a PNG file (bad signature)")
        plots.append((png.name, blob))
    ap_columns, ap_rows = _ap_table(ap)
    ov_columns, ov_rows = _overlap_table(overlap)
    return EvalSection(
        root, _text(data["dataset"]), _text(data["metric"]), pairs, ap_columns, ap_rows, ov_columns, ov_rows, plots
    )

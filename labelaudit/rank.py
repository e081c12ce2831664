"""Ranking queries for ``labelaudit rank``: the worst labels first, filtered, as rows, JSON or CSV.

Reads only the columns a query needs through :mod:`pyarrow.dataset`, sorts, keeps the top N and
only then fetches their full rows, so it stays fast on millions of objects. Machine formats (JSON,
CSV) are made here; the Rich table is the CLI's (:mod:`labelaudit.cli.tables`). No printing.
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
from dataclasses import dataclass
from typing import Any, Sequence

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads

from labelaudit import results as R
from labelaudit.results import Results, ResultsError

ASCENDING_BY_DEFAULT = frozenset({"jiou_gt", "num_points", "hull_iou"})
"""Columns where *low* is bad (sorted ascending by default); every other column sorts descending
(higher = worse: label_error, sigma_hat, fit_offset_m, std_*, distance …)."""


def default_descending(by: str) -> bool:
    """Whether ``--by`` sorts descending when neither ``--desc`` nor ``--asc`` is given."""
    return by not in ASCENDING_BY_DEFAULT


@dataclass(frozen=True)
class RankQuery:
    """Which rows to rank and how."""

    by: str = "jiou_gt"
    top: int = 20
    descending: bool | None = None  # None: default_descending(by)
    classes: tuple[str, ...] = ()
    statuses: tuple[str, ...] = ()
    min_points: int | None = None
    max_distance: float | None = None
    where: tuple[str, ...] = ()  # conditions like "num_points>=10", "difficulty==Hard" (all must hold)

    @property
    def is_descending(self) -> bool:
        return default_descending(self.by) if self.descending is None else self.descending


@dataclass
class RankResult:
    """The top rows (every column, worst first) and how many rows matched the filters."""

    table: pa.Table
    matched: int
    query: RankQuery


def _numeric_columns(schema: pa.Schema) -> list[str]:
    return [f.name for f in schema if pa.types.is_integer(f.type) or pa.types.is_floating(f.type)]


_OPS = {">=": pc.greater_equal, "<=": pc.less_equal, "!=": pc.not_equal, "==": pc.equal, ">": pc.greater, "<": pc.less, "=": pc.equal}
_WHERE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(>=|<=|!=|==|>|<|=)\s*(.+?)\s*$")


def parse_where(condition: str, schema: pa.Schema) -> tuple[str, Any, Any]:
    """Parse ``"column OP value"`` (OP one of == != >= <= > <) against the results schema.

    Returns
    -------
    (column, compute function, typed value)

    Raises
    ------
    ResultsError
        Malformed condition, unknown column or a value of the wrong type.
    """
    m = _WHERE.match(condition)
    if not m:
        raise ResultsError(f"--where {condition!r}: expected COLUMN OP VALUE with OP one of ==, !=, >=, <=, >, < (e.g. 'num_points>=10')")
    column, op, raw = m.groups()
    if column not in schema.names:
        raise ResultsError(f"--where {condition!r}: unknown column {column!r}; columns: {', '.join(schema.names)}")
    typ = schema.field(column).type
    value: Any = raw.strip("'\"")
    if pa.types.is_integer(typ) or pa.types.is_floating(typ):
        try:
            value = float(value)
        except ValueError:
            raise ResultsError(f"--where {condition!r}: {column} is numeric, got {raw!r}") from None
    elif not pa.types.is_string(typ):
        raise ResultsError(f"--where {condition!r}: cannot compare the {typ} column {column!r}")
    return column, _OPS[op], value


def rank_results(results: Results, query: RankQuery) -> RankResult:
    """Rank objects by a numeric column, worst first.

    Rows whose ``by`` value is null or NaN (e.g. skipped objects) are left out.

    Raises
    ------
    ResultsError
        ``by`` is not a numeric column of the results, or ``top`` < 1.
    """
    schema = results.dataset.schema
    numeric = _numeric_columns(schema)
    if query.by not in numeric:
        raise ResultsError(f"--by {query.by!r}: not a numeric column of {results.root}; choose one of {', '.join(numeric)}")
    if query.top < 1:
        raise ResultsError(f"--top must be ≥ 1, got {query.top}")

    conditions = [parse_where(w, schema) for w in query.where]
    needed = ["frame_id", "object_index", query.by]
    for c, used in (("class_name", query.classes), ("status", query.statuses), ("num_points", query.min_points is not None), ("distance", query.max_distance is not None)):
        if used and c not in needed:
            needed.append(c)
    needed += [c for c, _, _ in conditions if c not in needed]
    table = results.read(needed)
    by = table.column(query.by)
    mask = pc.is_valid(by)
    if pa.types.is_floating(by.type):
        mask = pc.and_(mask, pc.invert(pc.is_nan(by)))
    if query.classes:
        mask = pc.and_(mask, pc.is_in(table.column("class_name"), value_set=pa.array(list(query.classes))))
    if query.statuses:
        mask = pc.and_(mask, pc.is_in(table.column("status"), value_set=pa.array(list(query.statuses))))
    if query.min_points is not None:
        mask = pc.and_(mask, pc.greater_equal(table.column("num_points"), query.min_points))
    if query.max_distance is not None:
        mask = pc.and_(mask, pc.less_equal(table.column("distance"), query.max_distance))
    for column, op, value in conditions:
        mask = pc.and_(mask, op(table.column(column), value))
    mask = pc.fill_null(mask, False)
    kept = table.filter(mask)
    order = "descending" if query.is_descending else "ascending"
    idx = pc.sort_indices(kept, sort_keys=[(query.by, order), ("frame_id", "ascending"), ("object_index", "ascending")])
    top = kept.take(idx[: query.top])
    keys = list(zip(top.column("frame_id").to_pylist(), top.column("object_index").to_pylist()))

    # Fetch full rows of the winners only: frames are few, rows are matched on (frame_id, object_index).
    if keys:
        frames = pa.array(sorted({f for f, _ in keys}))
        full = results.dataset.to_table(filter=pads.field("frame_id").isin(frames))
        pos = {k: i for i, k in enumerate(zip(full.column("frame_id").to_pylist(), full.column("object_index").to_pylist()))}
        full = full.take(pa.array([pos[k] for k in keys], type=pa.int64()))
    else:
        full = schema.empty_table()
    return RankResult(full, kept.num_rows, query)


# --------------------------------------------------------------------------- output


def ordered_columns(table: pa.Table) -> list[str]:
    """Schema columns first (in schema order), then any extra columns of the file."""
    names = table.schema.names
    return [c for c in R.COLUMN_NAMES if c in names] + [c for c in names if c not in R.COLUMN_NAMES]


def _plain(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def to_records(table: pa.Table) -> list[dict[str, Any]]:
    """Rows as dicts keyed by column name (NaN → None), schema columns first."""
    cols = ordered_columns(table)
    return [{c: _plain(row[c]) for c in cols} for row in table.select(cols).to_pylist()]


def to_json(table: pa.Table) -> str:
    """A JSON array, one object per row, every column by its name."""
    return json.dumps(to_records(table), indent=1)


def to_csv(table: pa.Table) -> str:
    """CSV with a header; list columns (corner_tv, cov) as JSON arrays, nulls as empty fields."""
    cols = ordered_columns(table)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    for rec in to_records(table):
        writer.writerow(["" if rec[c] is None else json.dumps(rec[c]) if isinstance(rec[c], list) else rec[c] for c in cols])
    return buf.getvalue()


__all__: Sequence[str] = [
    "RankQuery",
    "RankResult",
    "rank_results",
    "to_json",
    "to_csv",
    "to_records",
    "default_descending",
]

"""Ranking queries for ``labelaudit rank``: the worst labels first (or the likeliest missing labels,
``--missing``), filtered, as rows, JSON or CSV.

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
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads

from labelaudit import results as R
from labelaudit.results import Results, ResultsError

ASCENDING_BY_DEFAULT = frozenset({"jiou_gt", "num_points", "hull_iou"})
"""Columns where *low* is bad (sorted ascending by default); every other column sorts descending
(higher = worse: label_error, sigma_hat, fit_offset_m, std_*, distance …; for missing-label
candidates: score, higher = more likely a missed label)."""


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
    unscored: dict[str, int] = field(default_factory=dict)
    """Sorting by ``label_error``: audited objects matching the filters whose score is null, per
    class — classes the score is not validated for (docs/label-error.md); they are not ranked."""


def _numeric_columns(schema: pa.Schema) -> list[str]:
    return [f.name for f in schema if pa.types.is_integer(f.type) or pa.types.is_floating(f.type)]


_AUDITED = ("ok", "few_points", "no_points")  # statuses whose rows carry the model's columns

_OPS = {
    ">=": pc.greater_equal,
    "<=": pc.less_equal,
    "!=": pc.not_equal,
    "==": pc.equal,
    ">": pc.greater,
    "<": pc.less,
    "=": pc.equal,
}
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
        raise ResultsError(
            f"--where {condition!r}: expected COLUMN OP VALUE with OP one of ==, !=, >=, <=, >, < (e.g. 'num_points>=10')"
        )
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


def _mask(
    table: pa.Table,
    by: str,
    one_of: Mapping[str, Sequence[str]],
    at_least: Mapping[str, float | None],
    at_most: Mapping[str, float | None],
    conditions: Sequence[tuple[str, Any, Any]],
) -> pa.Array:
    """Rows with a finite ``by`` value that pass every filter (an empty ``one_of`` list or a None
    bound is no filter; :func:`parse_where` conditions must all hold; null never passes)."""
    col = table.column(by)
    mask = pc.is_valid(col)
    if pa.types.is_floating(col.type):
        mask = pc.and_(mask, pc.invert(pc.is_nan(col)))
    for name, values in one_of.items():
        if values:
            mask = pc.and_(mask, pc.is_in(table.column(name), value_set=pa.array(list(values))))
    for bounds, op in ((at_least, pc.greater_equal), (at_most, pc.less_equal)):
        for name, bound in bounds.items():
            if bound is not None:
                mask = pc.and_(mask, op(table.column(name), bound))
    for column, op, value in conditions:
        mask = pc.and_(mask, op(table.column(column), value))
    return pc.fill_null(mask, False)


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
        raise ResultsError(
            f"--by {query.by!r}: not a numeric column of {results.root}; choose one of {', '.join(numeric)}"
        )
    if query.top < 1:
        raise ResultsError(f"--top must be ≥ 1, got {query.top}")

    conditions = [parse_where(w, schema) for w in query.where]
    needed = ["frame_id", "object_index", query.by]
    scored_only = query.by == "label_error" and {"class_name", "status"} <= set(schema.names)
    for c, used in (
        ("class_name", query.classes or scored_only),
        ("status", query.statuses or scored_only),
        ("num_points", query.min_points is not None),
        ("distance", query.max_distance is not None),
    ):
        if used and c not in needed:
            needed.append(c)
    needed += [c for c, _, _ in conditions if c not in needed]
    table = results.read(needed)
    one_of = {"class_name": query.classes, "status": query.statuses}
    bounds = ({"num_points": query.min_points}, {"distance": query.max_distance})
    kept = table.filter(_mask(table, query.by, one_of, *bounds, conditions))
    unscored: dict[str, int] = {}
    if scored_only:  # audited rows that pass every filter but have no score: their class is not validated
        passing = _mask(
            table, "object_index", one_of, *bounds, conditions
        )  # the filters alone (object_index is never null)
        missing = pc.invert(_mask(table, query.by, {}, {}, {}, []))
        audited = pc.is_in(table.column("status"), value_set=pa.array(list(_AUDITED)))
        for name in table.filter(pc.and_(pc.and_(missing, audited), passing)).column("class_name").to_pylist():
            unscored[name] = unscored.get(name, 0) + 1
    order = "descending" if query.is_descending else "ascending"
    idx = pc.sort_indices(kept, sort_keys=[(query.by, order), ("frame_id", "ascending"), ("object_index", "ascending")])
    top = kept.take(idx[: query.top])
    keys = list(zip(top.column("frame_id").to_pylist(), top.column("object_index").to_pylist()))

    # Fetch full rows of the winners only: frames are few, rows are matched on (frame_id, object_index).
    if keys:
        frames = pa.array(sorted({f for f, _ in keys}))
        full = results.dataset.to_table(filter=pads.field("frame_id").isin(frames))
        pos = {
            k: i
            for i, k in enumerate(zip(full.column("frame_id").to_pylist(), full.column("object_index").to_pylist()))
        }
        full = full.take(pa.array([pos[k] for k in keys], type=pa.int64()))
    else:
        full = schema.empty_table()
    return RankResult(full, kept.num_rows, query, dict(sorted(unscored.items())))


# --------------------------------------------------------------------------- missing labels

MISSING_SOURCES = R.MISSING_SOURCES
"""Values of the candidates' ``source`` column."""


def read_candidates(results: Results) -> pa.Table | None:
    """The ``missing/`` table of a results folder (every candidate row, :func:`labelaudit.results.read_missing`),
    or None when the run did not search for missing labels (``infer --no-missing``, or results of
    an older labelaudit): an empty table means the search ran and found nothing.

    Raises
    ------
    ResultsError
        A shard of the table cannot be read (the message names it).
    """
    params = results.manifest.get("params")
    search = params.get("missing") if isinstance(params, dict) else None
    enabled = bool(search.get("enabled")) if isinstance(search, dict) else False
    if results.root.is_file() or not (enabled or (results.root / R.MISSING_DIR).is_dir()):
        return None
    return R.read_missing(results.root)


def require_candidates(results: Results) -> pa.Table:
    """:func:`read_candidates`, with a :class:`ResultsError` naming the fix when the search did not run."""
    table = read_candidates(results)
    if table is None:
        raise ResultsError(
            f"{results.root}: no missing-label table (missing/); the run skipped the search (--no-missing) or is "
            "from an older labelaudit: rerun `labelaudit infer` without --no-missing"
        )
    return table


@dataclass(frozen=True)
class MissingQuery:
    """Which missing-label candidates to list and how (default: highest ``score`` first)."""

    by: str = "score"
    top: int = 20
    descending: bool | None = None  # None: highest first (score, num_points: more evidence of an object)
    classes: tuple[str, ...] = ()
    sources: tuple[str, ...] = ()
    min_score: float | None = None
    min_points: int | None = None
    max_distance: float | None = None
    where: tuple[str, ...] = ()

    @property
    def is_descending(self) -> bool:
        return True if self.descending is None else self.descending


@dataclass
class MissingResult:
    """The top candidates (every column, first = most likely a missed label), how many matched, how many there are."""

    table: pa.Table
    matched: int
    total: int
    query: MissingQuery


def rank_missing(results: Results, query: MissingQuery) -> MissingResult:
    """Rank missing-label candidates by a numeric column (``score`` by default, highest first).

    Raises
    ------
    ResultsError
        No missing-label table, an unknown ``by`` or ``--where`` column, ``top`` < 1, a ``min_score``
        outside [0, 1] or an unknown source.
    """
    if query.top < 1:
        raise ResultsError(f"--top must be ≥ 1, got {query.top}")
    if query.min_score is not None and not 0.0 <= query.min_score <= 1.0:
        raise ResultsError(f"--min-score must be in [0, 1], got {query.min_score}")
    bad = [s for s in query.sources if s not in MISSING_SOURCES]
    if bad:
        raise ResultsError(f"--source {', '.join(bad)}: expected one of {', '.join(MISSING_SOURCES)}")
    table = require_candidates(results)
    table = table.select(missing_column_order(table))
    numeric = _numeric_columns(table.schema)
    if query.by not in numeric:
        raise ResultsError(
            f"--by {query.by!r}: not a numeric column of the missing-label table; choose one of {', '.join(numeric)}"
        )
    conditions = [parse_where(w, table.schema) for w in query.where]
    one_of = {"class_name": query.classes, "source": query.sources}
    at_least = {"score": query.min_score, "num_points": query.min_points}
    kept = table.filter(_mask(table, query.by, one_of, at_least, {"distance": query.max_distance}, conditions))
    order = "descending" if query.is_descending else "ascending"
    idx = pc.sort_indices(
        kept, sort_keys=[(query.by, order), ("frame_id", "ascending"), ("candidate_index", "ascending")]
    )
    return MissingResult(kept.take(idx[: query.top]), kept.num_rows, table.num_rows, query)


def missing_column_order(table: pa.Table) -> list[str]:
    """The columns of a candidates table in the order of :data:`labelaudit.results.MISSING_SCHEMA`, then any others."""
    names = table.schema.names
    return [c for c in R.MISSING_COLUMN_NAMES if c in names] + [c for c in names if c not in R.MISSING_COLUMN_NAMES]


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
    cols = missing_column_order(table) if "candidate_index" in table.schema.names else ordered_columns(table)
    return [{c: _plain(row[c]) for c in cols} for row in table.select(cols).to_pylist()]


def to_json(table: pa.Table) -> str:
    """A JSON array, one object per row, every column by its name."""
    return json.dumps(to_records(table), indent=1)


def to_csv(table: pa.Table) -> str:
    """CSV with a header; list columns (corner_tv, cov) as JSON arrays, nulls as empty fields."""
    cols = missing_column_order(table) if "candidate_index" in table.schema.names else ordered_columns(table)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(cols)
    for rec in to_records(table):
        writer.writerow(
            ["" if rec[c] is None else json.dumps(rec[c]) if isinstance(rec[c], list) else rec[c] for c in cols]
        )
    return buf.getvalue()


__all__: Sequence[str] = [
    "RankQuery",
    "RankResult",
    "rank_results",
    "MissingQuery",
    "MissingResult",
    "rank_missing",
    "read_candidates",
    "require_candidates",
    "missing_column_order",
    "to_json",
    "to_csv",
    "to_records",
    "default_descending",
]

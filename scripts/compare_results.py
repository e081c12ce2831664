"""Compare the rows of two results folders, bit for bit or within tolerances.

The object rows (``objects/``) and the missing-label candidates (``missing/``, when either folder
has any) are compared. Prints the number of rows, and every column that differs (with the largest
difference and the first differing row); exits 1 when anything differs, 0 when the rows are
identical. Used to check that a change on the ``infer`` path leaves the rows untouched:

    python scripts/compare_results.py before/ after/

``--tolerant``: a change that may move the last bits (compiled code replacing NumPy/LAPACK
arithmetic) passes when every float column is within 1e-9 relative or 1e-12 absolute,
``jiou_gt`` within 1e-7 and ``label_error`` within 1e-6 (absolute), and every other column
(status, integers, strings) is identical; it prints the largest absolute and relative difference
of every column that moved:

    python scripts/compare_results.py --tolerant before/ after/ [more pairs …]
"""

from __future__ import annotations

import argparse
import math
import sys

import pyarrow as pa

from labelaudit import open_results
from labelaudit.results import KEY_COLUMNS, read_missing

MISSING_KEYS = ("frame_id", "candidate_index")  # a candidate row's key


def _same(a: object, b: object) -> bool:
    if isinstance(a, float) and isinstance(b, float):
        return a == b or (math.isnan(a) and math.isnan(b))
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return a == b


def _gap(a: object, b: object) -> float:
    try:
        if isinstance(a, list):
            return max((_gap(x, y) for x, y in zip(a, b)), default=0.0)
        return abs(float(a) - float(b))  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.inf


TOLERANCES = {"jiou_gt": 1e-7, "label_error": 1e-6}  # absolute; other floats: FLOAT_REL or FLOAT_ABS
FLOAT_REL, FLOAT_ABS = 1e-9, 1e-12


def _floats(value: object) -> list[float] | None:
    """The float(s) of a cell (a list column flattened), None when it holds something else."""
    if isinstance(value, float):
        return [value]
    if isinstance(value, list) and all(isinstance(x, float) for x in value):
        return list(value)
    return None


def _tables(before: str, after: str, table: str) -> tuple[pa.Table, pa.Table, tuple[str, ...]]:
    """The ``table`` ("objects" or "missing") of both folders, each sorted by its key, and that key."""
    keys = tuple(KEY_COLUMNS) if table == "objects" else MISSING_KEYS
    read = (lambda path: open_results(path).read()) if table == "objects" else read_missing
    return (
        read(before).sort_by([(k, "ascending") for k in keys]),
        read(after).sort_by([(k, "ascending") for k in keys]),
        keys,
    )


def _has_missing(*folders: str) -> bool:
    return any(read_missing(f).num_rows for f in folders)


def moved(before: str, after: str, table: str = "objects") -> tuple[dict[str, tuple[int, float, float]], list[str]]:
    """Per float column that differs: (rows, largest absolute, largest relative difference); and the
    violations of the tolerances (module docstring), including any other column that differs."""
    ta, tb, keys = _tables(before, after, table)
    if ta.num_rows != tb.num_rows or ta.column_names != tb.column_names:
        return {}, [f"rows {ta.num_rows} vs {tb.num_rows}, columns equal: {ta.column_names == tb.column_names}"]
    stats: dict[str, tuple[int, float, float]] = {}
    bad: list[str] = []
    for name in ta.column_names:
        va, vb = ta.column(name).to_pylist(), tb.column(name).to_pylist()
        rows, worst_abs, worst_rel = 0, 0.0, 0.0
        for i, (x, y) in enumerate(zip(va, vb)):
            if _same(x, y):
                continue
            fx, fy = _floats(x), _floats(y)
            if (
                fx is None
                or fy is None
                or len(fx) != len(fy)
                or any(math.isnan(a) != math.isnan(b) for a, b in zip(fx, fy))
            ):
                key = {k: ta.column(k)[i].as_py() for k in keys}
                bad.append(f"{name}: {x!r} vs {y!r} at {key}")
                break
            rows += 1
            for a, b in zip(fx, fy):
                if math.isnan(a) or a == b:
                    continue
                gap, rel = abs(a - b), abs(a - b) / max(abs(a), abs(b))
                worst_abs, worst_rel = max(worst_abs, gap), max(worst_rel, rel)
                limit = TOLERANCES.get(name)
                ok = gap <= limit if limit is not None else (rel <= FLOAT_REL or gap <= FLOAT_ABS)
                if not ok:
                    key = {k: ta.column(k)[i].as_py() for k in keys}
                    bad.append(f"{name}: {a!r} vs {b!r} (difference {gap:.3g}, relative {rel:.3g}) at {key}")
        if rows:
            stats[name] = (rows, worst_abs, worst_rel)
    return stats, bad


def compare(before: str, after: str, table: str = "objects") -> list[str]:
    """Differences between the rows of ``table`` ("objects" or "missing") of two results folders
    (empty when identical)."""
    ta, tb, keys = _tables(before, after, table)
    if ta.num_rows != tb.num_rows:
        return [f"row count {ta.num_rows} vs {tb.num_rows}"]
    out = []
    for name in sorted(set(ta.column_names) | set(tb.column_names)):
        if name not in ta.column_names or name not in tb.column_names:
            out.append(f"{name}: only in {'after' if name in tb.column_names else 'before'}")
            continue
        va, vb = ta.column(name).to_pylist(), tb.column(name).to_pylist()
        bad = [i for i, (x, y) in enumerate(zip(va, vb)) if not _same(x, y)]
        if bad:
            worst = max(_gap(va[i], vb[i]) for i in bad)
            key = {k: ta.column(k)[bad[0]].as_py() for k in keys}
            out.append(f"{name}: {len(bad)} rows differ, largest difference {worst:.3g}, first at {key}")
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tolerant", action="store_true", help="last-bit changes within the tolerances pass")
    parser.add_argument("before")
    parser.add_argument("after")
    parser.add_argument("pairs", nargs="*", help="more before/after folders (with --tolerant)")
    args = parser.parse_args()
    if args.tolerant:
        folders = [args.before, args.after, *args.pairs]
        if len(folders) % 2:
            parser.error("give folders in before/after pairs")
        failed = False
        for before, after in zip(folders[::2], folders[1::2]):
            for table in ("objects", "missing") if _has_missing(before, after) else ("objects",):
                stats, bad = moved(before, after, table)
                rows = (open_results(before).read() if table == "objects" else read_missing(before)).num_rows
                verdict = "OUTSIDE THE TOLERANCES" if bad else ("within the tolerances" if stats else "bit-identical")
                print(f"{before} → {after}: {table}, {rows} rows, {verdict}")
                for name, (n, gap, rel) in sorted(stats.items()):
                    print(f"  {name:18s} {n:5d} rows moved, largest difference {gap:.3g} (relative {rel:.3g})")
                for line in bad[:20]:
                    print(f"  ! {line}")
                failed |= bool(bad)
        return 1 if failed else 0
    failed = False
    for table in ("objects", "missing") if _has_missing(args.before, args.after) else ("objects",):
        diffs = compare(args.before, args.after, table)
        rows = (open_results(args.before).read() if table == "objects" else read_missing(args.before)).num_rows
        if diffs:
            print(f"{table}: {rows} rows; DIFFERENT:\n  " + "\n  ".join(diffs))
            failed = True
        else:
            print(f"{table}: {rows} rows, every column bit-identical")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

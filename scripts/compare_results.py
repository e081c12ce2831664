"""Compare the object rows of two results folders, bit for bit.

Prints the number of rows, and every column that differs (with the largest difference and the
first differing row); exits 1 when anything differs, 0 when the rows are identical. Used to check
that a change on the ``infer`` path leaves the rows untouched:

    python scripts/compare_results.py before/ after/
"""

from __future__ import annotations

import argparse
import math
import sys

from labelaudit import open_results
from labelaudit.results import KEY_COLUMNS


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


def compare(before: str, after: str) -> list[str]:
    """Differences between the rows of two results folders (empty when identical)."""
    ta = open_results(before).read().sort_by([(k, "ascending") for k in KEY_COLUMNS])
    tb = open_results(after).read().sort_by([(k, "ascending") for k in KEY_COLUMNS])
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
            key = {k: ta.column(k)[bad[0]].as_py() for k in KEY_COLUMNS}
            out.append(f"{name}: {len(bad)} rows differ, largest difference {worst:.3g}, first at {key}")
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("before")
    parser.add_argument("after")
    args = parser.parse_args()
    diffs = compare(args.before, args.after)
    rows = open_results(args.before).dataset.count_rows()
    if diffs:
        print(f"{rows} rows; DIFFERENT:\n  " + "\n  ".join(diffs))
        return 1
    print(f"{rows} rows, every column bit-identical")
    return 0


if __name__ == "__main__":
    sys.exit(main())

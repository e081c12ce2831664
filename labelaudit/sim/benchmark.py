"""Ranking metrics for label-error detection: AUROC, precision at the top k %, binning.
Pure functions over score arrays, used by the label-error benchmark (scripts/bench_label_error.py); no I/O.

Vectorised NumPy, no scikit-learn. Used by ``scripts/bench_label_error.py`` to compare
``label_error`` with the baselines; ties are handled exactly (average ranks for AUROC, expected
value under random tie-breaking for precision at k), so a constant score gets AUROC 0.5 and the
base rate as precision.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]


def _check(scores: ArrayLike, labels: ArrayLike) -> tuple[FloatArray, NDArray[np.bool_]]:
    s = np.asarray(scores, dtype=float).ravel()
    y = np.asarray(labels).ravel()
    if s.shape != y.shape:
        raise ValueError(f"scores and labels must have the same length, got {s.shape[0]} and {y.shape[0]}")
    if not np.all(np.isfinite(s)):
        bad = np.flatnonzero(~np.isfinite(s))
        raise ValueError(f"scores must be finite; {bad.size} are not (first at index {bad[0]}: {s[bad[0]]})")
    if y.dtype != bool:
        if not np.all(np.isin(y, (0, 1))):
            raise ValueError(f"labels must be boolean or 0/1, got values {np.unique(y)[:5]}")
        y = y.astype(bool)
    return s, y


def average_ranks(values: ArrayLike) -> FloatArray:
    """1-based ranks of ``values`` (N,), ties sharing their average rank (as scipy.stats.rankdata)."""
    v = np.asarray(values, dtype=float).ravel()
    order = np.argsort(v, kind="mergesort")
    sv = v[order]
    # Start of every run of equal values, and the average of the 1-based positions in the run.
    starts = np.flatnonzero(np.r_[True, sv[1:] != sv[:-1]])
    ends = np.r_[starts[1:], sv.size]  # exclusive
    run_rank = 0.5 * (starts + 1 + ends)
    ranks = np.empty(v.size)
    ranks[order] = np.repeat(run_rank, ends - starts)
    return ranks


def auroc(scores: ArrayLike, labels: ArrayLike) -> float:
    """Area under the ROC curve: P(score of a random positive > score of a random negative), ties ½.

    Parameters
    ----------
    scores : (N,) higher = more likely positive
    labels : (N,) bool or 0/1

    Returns
    -------
    AUROC in [0, 1]; NaN when there is no positive or no negative.
    """
    s, y = _check(scores, labels)
    n_pos = int(y.sum())
    n_neg = y.size - n_pos
    if n_pos == 0 or n_neg == 0:
        return float("nan")
    r = average_ranks(s)  # Mann–Whitney U from the rank sum of the positives
    u = float(r[y].sum()) - n_pos * (n_pos + 1) / 2.0
    return u / (n_pos * n_neg)


def precision_at_fraction(scores: ArrayLike, labels: ArrayLike, fraction: float = 0.05) -> float:
    """Share of positives among the ``ceil(fraction · N)`` highest scores.

    Ties at the cut-off are broken at random in expectation: the tied group contributes its share
    of positives times the number of places left. NaN for an empty input.
    """
    if not 0.0 < fraction <= 1.0:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    s, y = _check(scores, labels)
    n = s.size
    if n == 0:
        return float("nan")
    m = int(np.ceil(fraction * n - 1e-9))
    m = min(max(m, 1), n)
    threshold = np.sort(s)[::-1][m - 1]
    above = s > threshold
    tied = s == threshold
    left = m - int(above.sum())
    expected = float(y[above].sum()) + left * float(y[tied].sum()) / float(tied.sum())
    return expected / m


def bin_index(values: ArrayLike, edges: Sequence[float]) -> NDArray[np.int64]:
    """Bin of each value for bins ``[edges[i], edges[i+1])``; the last edge may be ``inf``.

    Returns (N,) indices 0 … len(edges) − 2, or −1 for values outside all bins (or NaN).
    """
    v = np.asarray(values, dtype=float).ravel()
    e = np.asarray(edges, dtype=float)
    if e.ndim != 1 or e.size < 2 or np.any(np.diff(e) <= 0):
        raise ValueError(f"edges must be ≥ 2 strictly increasing values, got {list(edges)}")
    idx = np.searchsorted(e, v, side="right") - 1
    idx[(idx < 0) | (idx >= e.size - 1) | ~np.isfinite(v)] = -1
    return idx.astype(np.int64)


def bin_names(edges: Sequence[float], unit: str = "") -> list[str]:
    """Readable names of the bins of :func:`bin_index` for integer-like counts or ranges."""
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        if np.isinf(hi):
            out.append(f"≥ {lo:g}{unit}")
        else:
            out.append(f"{lo:g}–{hi:g}{unit}")
    return out


@dataclass(frozen=True)
class RankingRow:
    """Metrics of several scores on one subset of objects."""

    name: str
    n: int
    n_pos: int
    auroc: dict[str, float]
    precision: dict[str, float]


def ranking_table(
    scores: Mapping[str, ArrayLike],
    labels: ArrayLike,
    subsets: Mapping[str, ArrayLike],
    fraction: float = 0.05,
) -> list[RankingRow]:
    """AUROC and precision at the top ``fraction`` of every score on every subset.

    Parameters
    ----------
    scores : name → (N,) score, higher = more likely positive
    labels : (N,) positives
    subsets : row name → (N,) boolean mask of the objects in that row
    fraction : share of the subset taken as "top" for the precision
    """
    y = np.asarray(labels).astype(bool).ravel()
    rows = []
    for row_name, mask in subsets.items():
        m = np.asarray(mask, dtype=bool).ravel()
        if m.shape != y.shape:
            raise ValueError(f"subset {row_name!r}: mask length {m.size} != {y.size} labels")
        au = {k: auroc(np.asarray(v, dtype=float)[m], y[m]) for k, v in scores.items()}
        pr = {
            k: precision_at_fraction(np.asarray(v, dtype=float)[m], y[m], fraction) if m.any() else float("nan")
            for k, v in scores.items()
        }
        rows.append(RankingRow(row_name, int(m.sum()), int(y[m].sum()), au, pr))
    return rows

"""Ranking metrics of labelaudit.sim.benchmark against known answers and brute force."""

from __future__ import annotations

import math

import numpy as np
import pytest

from labelaudit.sim.benchmark import (
    auroc,
    average_ranks,
    bin_index,
    bin_names,
    precision_at_fraction,
    ranking_table,
)


def brute_auroc(scores: np.ndarray, labels: np.ndarray) -> float:
    """All positive/negative pairs: 1 if the positive scores higher, ½ on a tie."""
    pos = scores[labels]
    neg = scores[~labels]
    diff = pos[:, None] - neg[None, :]
    return float(np.mean((diff > 0) + 0.5 * (diff == 0)))


def test_auroc_known_answers() -> None:
    assert auroc([0.1, 0.2, 0.8, 0.9], [0, 0, 1, 1]) == 1.0
    assert auroc([0.9, 0.8, 0.2, 0.1], [0, 0, 1, 1]) == 0.0
    assert auroc([0.5, 0.5, 0.5, 0.5], [0, 1, 0, 1]) == 0.5
    # positives 0.35, 0.8 vs negatives 0.1, 0.4: pairs won 1 + 0 + 1 + 1 = 3 of 4
    assert auroc([0.1, 0.4, 0.35, 0.8], [0, 0, 1, 1]) == pytest.approx(0.75)
    assert math.isnan(auroc([0.1, 0.2], [1, 1]))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_auroc_equals_pairwise_brute_force_with_ties(seed: int) -> None:
    rng = np.random.default_rng(seed)
    s = rng.integers(0, 6, size=200).astype(float)  # many ties
    y = rng.random(200) < 0.3
    assert auroc(s, y) == pytest.approx(brute_auroc(s, y), abs=1e-12)
    s2 = rng.normal(size=150)
    y2 = rng.random(150) < 0.1
    assert auroc(s2, y2) == pytest.approx(brute_auroc(s2, y2), abs=1e-12)


def test_average_ranks_share_ties() -> None:
    np.testing.assert_allclose(average_ranks([3.0, 1.0, 3.0, 2.0]), [3.5, 1.0, 3.5, 2.0])


def test_precision_at_fraction() -> None:
    s = np.arange(20, dtype=float)  # top 5 % of 20 = 1 object: the 19
    y = np.zeros(20, bool)
    y[19] = True
    assert precision_at_fraction(s, y, 0.05) == 1.0
    assert precision_at_fraction(s, y, 0.10) == 0.5  # 19 and 18
    assert precision_at_fraction(-s, y, 0.05) == 0.0
    # a constant score: expectation under random tie-breaking = the base rate
    assert precision_at_fraction(np.ones(20), y, 0.25) == pytest.approx(1 / 20)
    # ties at the cut-off: top 2 of [5, 3, 3, 3] → the 5 (positive) + 1 of three 3s (one positive)
    assert precision_at_fraction([5, 3, 3, 3], [1, 1, 0, 0], 0.5) == pytest.approx((1 + 1 / 3) / 2)


def test_inputs_are_validated() -> None:
    with pytest.raises(ValueError, match="same length"):
        auroc([1.0, 2.0], [0, 1, 1])
    with pytest.raises(ValueError, match="finite"):
        auroc([1.0, float("nan")], [0, 1])
    with pytest.raises(ValueError, match="0/1"):
        auroc([1.0, 2.0], [0, 2])
    with pytest.raises(ValueError, match="fraction"):
        precision_at_fraction([1.0], [1], 0.0)


def test_bins() -> None:
    edges = [1, 10, 50, np.inf]
    np.testing.assert_array_equal(bin_index([0, 1, 9, 10, 49, 50, 1e6, np.nan], edges), [-1, 0, 0, 1, 1, 2, 2, -1])
    assert bin_names(edges) == ["1–10", "10–50", "≥ 50"]
    with pytest.raises(ValueError, match="increasing"):
        bin_index([1.0], [0, 0, 1])


def test_ranking_table_rows() -> None:
    y = np.array([0, 0, 1, 1, 0, 1], bool)
    good = np.array([0.1, 0.2, 0.9, 0.8, 0.3, 0.7])
    rows = ranking_table({"good": good, "bad": -good}, y, {"all": np.ones(6, bool), "first4": np.arange(6) < 4})
    assert [r.name for r in rows] == ["all", "first4"]
    assert rows[0].n == 6 and rows[0].n_pos == 3 and rows[1].n == 4 and rows[1].n_pos == 2
    assert rows[0].auroc["good"] == 1.0 and rows[0].auroc["bad"] == 0.0
    assert rows[0].precision["good"] == 1.0

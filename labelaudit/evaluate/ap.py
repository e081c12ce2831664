"""Average precision from the devkit's precision samples: the 41-point curve, R40 and R11.

The devkit stores, for each of its (at most 41) score thresholds, precision = TP / (TP + FP) and
recall = TP / (TP + FN); the precision curve is then made monotone by taking, at each sample, the
largest precision at this or any later sample. Unused samples stay 0.

* **R40** (the KITTI benchmark since 2019): the mean of samples 1 … 40 (recall 1/40 … 1; recall 0
  left out), × 100.
* **R11** (the original PASCAL-style KITTI metric): the mean of samples 0, 4, 8, …, 40 (recall
  0, 0.1, …, 1), × 100.

This module only turns counts into numbers; the matching that produces the counts is
:mod:`labelaudit.evaluate.matching`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C

FloatArray = NDArray[np.float64]

__all__ = ["PrecisionCurve", "ap_r11", "ap_r40", "precision_curve"]


@dataclass(frozen=True)
class PrecisionCurve:
    """The devkit's sampled PR curve of one evaluation cell.

    Attributes
    ----------
    precision : (41,) interpolated (monotone) precision per recall sample; 0 beyond the used samples
    recall : (T,) recall at each used sample (T ≤ 41 score thresholds)
    raw_precision : (T,) precision before interpolation
    thresholds : (T,) the score thresholds
    tp, fp, fn : (T,) counts per threshold
    """

    precision: FloatArray
    recall: FloatArray
    raw_precision: FloatArray
    thresholds: FloatArray
    tp: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    fp: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))
    fn: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, np.int64))

    @property
    def ap_r40(self) -> float:
        return ap_r40(self.precision)

    @property
    def ap_r11(self) -> float:
        return ap_r11(self.precision)

    @property
    def max_recall(self) -> float:
        """Recall with every detection counted (the lowest score threshold); 0 when none."""
        return float(self.recall[-1]) if len(self.recall) else 0.0


def precision_curve(
    tp: ArrayLike, fp: ArrayLike, fn: ArrayLike, thresholds: ArrayLike, n_points: int = C.EVAL_RECALL_POINTS
) -> PrecisionCurve:
    """Precision samples from TP/FP/FN per threshold, as the devkit's ``eval_class``.

    A threshold with TP + FP = 0 (possible only in degenerate matchings) gets precision 0 where the
    devkit would divide by zero.
    """
    tp = np.asarray(tp, dtype=np.int64)
    fp = np.asarray(fp, dtype=np.int64)
    fn = np.asarray(fn, dtype=np.int64)
    t = len(tp)
    if t > n_points:
        raise ValueError(f"at most {n_points} thresholds, got {t}")
    with np.errstate(divide="ignore", invalid="ignore"):
        raw = np.where(tp + fp > 0, tp / np.maximum(tp + fp, 1), 0.0)
        recall = np.where(tp + fn > 0, tp / np.maximum(tp + fn, 1), 0.0)
    prec = np.zeros(n_points)
    prec[:t] = raw
    # max over this and every later sample (the zeros beyond t do not change it)
    prec[:t] = np.maximum.accumulate(prec[:t][::-1])[::-1]
    return PrecisionCurve(
        prec, recall.astype(float), raw.astype(float), np.asarray(thresholds, dtype=float), tp, fp, fn
    )


def ap_r40(precision: ArrayLike) -> float:
    """AP|R40 in percent: mean of the precision samples at recall 1/40 … 1 (sample 0 excluded)."""
    p = np.asarray(precision, dtype=float)
    return float(np.sum(p[1:41]) / 40.0 * 100.0)


def ap_r11(precision: ArrayLike) -> float:
    """AP|R11 in percent: mean of the precision samples at recall 0, 0.1, …, 1 (every 4th of 41)."""
    p = np.asarray(precision, dtype=float)
    return float(np.sum(p[0:41:4]) / 11.0 * 100.0)

"""Compiled per-point passes behind :mod:`labelaudit.core.geometry` (numba), kept apart so that
importing the geometry (the CLI does) never imports numba. No I/O, no model.
"""

from __future__ import annotations

import math

import numpy as np

from labelaudit.kernels import kernel


@kernel
def finite_keep(pts, d, keep):  # pragma: no cover - compiled
    """Marks in ``keep`` (N,) the rows of ``pts`` (N, ≥d) whose first ``d`` values are finite;
    returns how many."""
    m = 0
    for k in range(pts.shape[0]):
        ok = True
        for j in range(d):
            if not math.isfinite(pts[k, j]):
                ok = False
        keep[k] = ok
        m += ok
    return m


@kernel
def finite_rows_f64(pts, d):  # pragma: no cover - compiled
    """The rows of ``pts`` (N, ≥d), float32 or float64, whose first ``d`` values are finite, as a
    float64 (M, d) C-contiguous copy (converted exactly): :func:`~labelaudit.core.geometry.clean_points`
    in two passes over the crop instead of NumPy's strided test, cut and cast."""
    keep = np.empty(pts.shape[0], dtype=np.bool_)
    out = np.empty((finite_keep(pts, d, keep), d))
    q = 0
    for k in range(pts.shape[0]):
        if keep[k]:
            for j in range(d):
                out[q, j] = pts[k, j]
            q += 1
    return out


@kernel
def finite_columns_f64(pts, d):  # pragma: no cover - compiled
    """:func:`finite_rows_f64` transposed: the finite rows' first ``d`` values as a float64 (d, M)
    C-contiguous array (converted exactly), the layout of the label-error fit's point passes,
    without the (M, d) copy and its transposed copy."""
    keep = np.empty(pts.shape[0], dtype=np.bool_)
    out = np.empty((d, finite_keep(pts, d, keep)))
    q = 0
    for k in range(pts.shape[0]):
        if keep[k]:
            for j in range(d):
                out[j, q] = pts[k, j]
            q += 1
    return out

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


@kernel
def range_image_points(ri, dirs, t, rot, trans, posed):  # pragma: no cover - compiled
    """Points (M, 4) float32 of a range image ``ri`` (H, W, ≥2) float32: every pixel with range > 0,
    in row-major order, at ``dirs[i, j] · range + t`` (dirs (H, W, 3), t (3,), float64); with
    ``posed``, then moved by its column's rigid transform ``rot[j] · p + trans[j]`` (rot (W, 3, 3),
    trans (W, 3)); the pixel's channel 1 as the fourth value. The float64 operations of
    :func:`~labelaudit.datasets.waymo_common.range_image_to_points`' NumPy passes, in their order
    (no fast-math), without their per-point gathers and temporaries."""
    h, w = ri.shape[0], ri.shape[1]
    n = 0
    for i in range(h):
        for j in range(w):
            n += ri[i, j, 0] > 0  # NaN compares False: dropped too
    out = np.empty((n, 4), dtype=np.float32)
    q = 0
    for i in range(h):
        for j in range(w):
            if not ri[i, j, 0] > 0:
                continue
            r = np.float64(ri[i, j, 0])
            x = dirs[i, j, 0] * r + t[0]
            y = dirs[i, j, 1] * r + t[1]
            z = dirs[i, j, 2] * r + t[2]
            if posed:
                x, y, z = (
                    rot[j, 0, 0] * x + rot[j, 0, 1] * y + rot[j, 0, 2] * z + trans[j, 0],
                    rot[j, 1, 0] * x + rot[j, 1, 1] * y + rot[j, 1, 2] * z + trans[j, 1],
                    rot[j, 2, 0] * x + rot[j, 2, 1] * y + rot[j, 2, 2] * z + trans[j, 2],
                )
            out[q, 0] = x
            out[q, 1] = y
            out[q, 2] = z
            out[q, 3] = ri[i, j, 1]
            q += 1
    return out


@kernel
def rows_equal_first(a):  # pragma: no cover - compiled
    """Whether every row of ``a`` (H, W, C) equals its first row (NaN equals nothing): NumPy's
    ``(a == a[:1]).all()`` without the (H, W, C) comparison array, stopping at the first difference."""
    for i in range(1, a.shape[0]):
        for j in range(a.shape[1]):
            for c in range(a.shape[2]):
                if not a[i, j, c] == a[0, j, c]:
                    return False
    for j in range(a.shape[1]):  # the first row against itself: False where it holds a NaN
        for c in range(a.shape[2]):
            if not a[0, j, c] == a[0, j, c]:
                return False
    return True

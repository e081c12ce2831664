"""Geometric overlap of many box pairs at once: BEV / 3D IoU and the devkit's "overlap over the detection".

One compiled pass clips every requested pair of rotated rectangles (Sutherland–Hodgman against
the four edges of the other, convex, counter-clockwise box) and takes the shoelace area; a bounding
circle test skips pairs that cannot touch. 3D multiplies the BEV intersection by the overlap of
the z-intervals (boxes turn about z only), exactly what ``evaluate_object.cpp`` does with the
camera-frame y interval. This module owns only geometry on boxes in the dataset's LiDAR/vehicle
frame; it knows nothing about classes, scores or files.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["bev_corners", "pair_overlaps", "box_areas", "clip_area"]


def bev_corners(boxes: ArrayLike) -> FloatArray:
    """BEV corners of boxes, counter-clockwise from front-left (+l/2, +w/2), shape (N, 4, 2).

    Same order as :func:`labelaudit.core.geometry.box_corners` with ``"bev"``.
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    c, s = np.cos(b[:, 6]), np.sin(b[:, 6])
    ux, uy = np.array([0.5, -0.5, -0.5, 0.5]), np.array([0.5, 0.5, -0.5, -0.5])
    lx = ux[None, :] * b[:, 3:4]
    ly = uy[None, :] * b[:, 4:5]
    x = b[:, 0:1] + lx * c[:, None] - ly * s[:, None]
    y = b[:, 1:2] + lx * s[:, None] + ly * c[:, None]
    return np.ascontiguousarray(np.stack([x, y], axis=-1))


def box_areas(boxes: ArrayLike, view: str) -> FloatArray:
    """BEV area l·w, or volume l·w·h for ``view == "3d"``, shape (N,)."""
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    area = b[:, 3] * b[:, 4]
    return area * b[:, 5] if view == "3d" else area


@kernel
def clip_area(P, Q):  # pragma: no cover - compiled
    """Area of the intersection of two convex counter-clockwise quadrilaterals P, Q (4, 2)."""
    # The intersection of two convex quadrilaterals has at most 8 vertices.
    bx = np.empty(16)
    by = np.empty(16)
    cx = np.empty(16)
    cy = np.empty(16)
    n = 4
    for k in range(4):
        bx[k] = P[k, 0]
        by[k] = P[k, 1]
    for e in range(4):
        ax0, ay0 = Q[e, 0], Q[e, 1]
        ax1, ay1 = Q[(e + 1) % 4, 0], Q[(e + 1) % 4, 1]
        ex, ey = ax1 - ax0, ay1 - ay0
        m = 0
        for k in range(n):
            px, py = bx[k], by[k]
            qx, qy = bx[(k + 1) % n], by[(k + 1) % n]
            sp = ex * (py - ay0) - ey * (px - ax0)  # > 0: left of the edge (inside)
            sq = ex * (qy - ay0) - ey * (qx - ax0)
            if sp >= 0.0:
                cx[m] = px
                cy[m] = py
                m += 1
                if sq < 0.0:
                    t = sp / (sp - sq)
                    cx[m] = px + t * (qx - px)
                    cy[m] = py + t * (qy - py)
                    m += 1
            elif sq >= 0.0:
                t = sp / (sp - sq)
                cx[m] = px + t * (qx - px)
                cy[m] = py + t * (qy - py)
                m += 1
        n = m
        if n < 3:
            return 0.0
        for k in range(n):
            bx[k] = cx[k]
            by[k] = cy[k]
    area = 0.0
    for k in range(n):
        area += bx[k] * by[(k + 1) % n] - bx[(k + 1) % n] * by[k]
    return max(0.5 * area, 0.0)


@kernel
def _pairs_kernel(ca, cb, centre_a, centre_b, radius_a, radius_b, za, zb, ia, ib, three_d):  # pragma: no cover - compiled
    n = ia.shape[0]
    inter = np.zeros(n)
    for k in range(n):
        i, j = ia[k], ib[k]
        dx = centre_a[i, 0] - centre_b[j, 0]
        dy = centre_a[i, 1] - centre_b[j, 1]
        r = radius_a[i] + radius_b[j]
        if dx * dx + dy * dy >= r * r:
            continue
        dz = 1.0
        if three_d:
            dz = min(za[i, 1], zb[j, 1]) - max(za[i, 0], zb[j, 0])
            if dz <= 0.0:
                continue
        inter[k] = clip_area(ca[i], cb[j]) * dz
    return inter


def pair_overlaps(
    boxes_a: ArrayLike,
    boxes_b: ArrayLike,
    ia: ArrayLike,
    ib: ArrayLike,
    view: str = "bev",
    grow_a: ArrayLike | None = None,
    grow_b: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Intersection, IoU and intersection over the area of ``a`` for the pairs (ia[k], ib[k]).

    Parameters
    ----------
    boxes_a : (Na, 7), boxes_b : (Nb, 7) boxes (cx, cy, cz, l, w, h, yaw)
    ia, ib : (P,) indices into ``boxes_a`` and ``boxes_b``
    view : "bev" (areas of the ground-plane rectangles) or "3d" (volumes: BEV intersection times
        the overlap of the z-intervals)
    grow_a, grow_b : optional (Na,), (Nb,) margins (m) added to each half length and half width
        before intersecting — a cheap "could these supports touch" test; the IoU returned is then
        that of the grown boxes

    Returns
    -------
    inter : (P,) intersection area (BEV) or volume (3D)
    iou : (P,) inter / (|a| + |b| − inter)
    over_a : (P,) inter / |a| — the devkit's criterion 0 (detection vs DontCare region)
    """
    a = np.asarray(boxes_a, dtype=float).reshape(-1, 7).copy()
    b = np.asarray(boxes_b, dtype=float).reshape(-1, 7).copy()
    if grow_a is not None:
        a[:, 3:5] += 2.0 * np.asarray(grow_a, dtype=float)[:, None]
    if grow_b is not None:
        b[:, 3:5] += 2.0 * np.asarray(grow_b, dtype=float)[:, None]
    ia = np.ascontiguousarray(ia, dtype=np.int64).reshape(-1)
    ib = np.ascontiguousarray(ib, dtype=np.int64).reshape(-1)
    if view not in ("bev", "3d"):
        raise ValueError(f"view must be 'bev' or '3d', got {view!r}")
    three_d = view == "3d"
    za = np.ascontiguousarray(np.c_[a[:, 2] - a[:, 5] / 2, a[:, 2] + a[:, 5] / 2])
    zb = np.ascontiguousarray(np.c_[b[:, 2] - b[:, 5] / 2, b[:, 2] + b[:, 5] / 2])
    inter = _pairs_kernel(
        bev_corners(a), bev_corners(b), np.ascontiguousarray(a[:, :2]), np.ascontiguousarray(b[:, :2]),
        0.5 * np.hypot(a[:, 3], a[:, 4]), 0.5 * np.hypot(b[:, 3], b[:, 4]), za, zb, ia, ib, three_d,
    )
    area_a, area_b = box_areas(a, view)[ia], box_areas(b, view)[ib]
    union = area_a + area_b - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
        over_a = np.where(area_a > 0, inter / area_a, 0.0)
    return inter, np.clip(iou, 0.0, 1.0), np.clip(over_a, 0.0, 1.0)

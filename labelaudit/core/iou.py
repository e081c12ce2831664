"""Overlaps of boxes: exact BEV and 3D IoU of two boxes, and the hull-IoU baseline score.

``hull_iou`` (BEV IoU between a box and the convex hull of its points) is the simple label-quality
baseline of docs/label-error.md; ``bev_iou_exact`` / ``iou_3d_exact`` are the reference overlaps
(Shapely polygons) that the probabilistic JIoU of :mod:`labelaudit.core.spatial` reduces to for
deterministic boxes. No I/O.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from labelaudit.core import geometry as g
from labelaudit.core.geometry import FloatArray
from labelaudit.kernels import kernel


def hull_iou(box: ArrayLike, points: ArrayLike | None) -> float:
    """BEV IoU between a box and the convex hull of its points (a baseline label-quality score).

    0.0 when the hull has no area (fewer than 3 points, or all on a line). The hull (monotone
    chain), its clipping by the box (Sutherland–Hodgman) and the areas (shoelace) are one compiled
    call, :func:`_hull_iou_kernel`; coordinates are taken relative to the box centre.
    """
    return hull_iou_valid(g.validate_box(box), points)


def hull_iou_valid(y: FloatArray, points: ArrayLike | None) -> float:
    """:func:`hull_iou` of a box (7,) float64 known to be valid (after :func:`~labelaudit.core.geometry.validate_box`).

    float32/float64 points (N, ≥2) are read as they are (converted exactly): the finite rows,
    the hull candidates (:func:`_hull_candidates`) and their order by x, then y, relative to the
    box centre come from one compiled pass (:func:`_sorted_candidates_kernel`) instead of a float64
    copy of the crop and a dozen NumPy passes.
    """
    arr = None if points is None else np.asarray(points)
    if arr is None or arr.dtype not in _KERNEL_DTYPES or arr.ndim != 2 or arr.shape[1] < 2 or arr.size == 0:
        pts = _hull_candidates(g.clean_points(points, 2))  # other input: the reference path (and its errors)
        if len(pts) < 3:
            return 0.0
        local = pts - y[:2]
        local = np.ascontiguousarray(local[np.lexsort((local[:, 1], local[:, 0]))])  # by x, then y
    else:
        local = _sorted_candidates_kernel(arr, float(y[0]), float(y[1]))
        if len(local) < 3:
            return 0.0
    # the box's corners relative to its centre, counter-clockwise, formed in the kernel
    return float(_hull_iou_kernel(local, _BEV_CORNER_J, g.phi_of_valid_box(y, "bev"), float(y[0]), float(y[1])))


_KERNEL_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))  # native floats: what the compiled pass reads as is
_BEV_CORNER_J = g.design_matrix(g.BEV_CORNERS_UNIT, "bev")  # (4, 2, 6): the corners are J·φ (geometry.box_corners)


@kernel
def _cross(o0, o1, a0, a1, b0, b1):  # pragma: no cover - compiled
    """z of (a − o) × (b − o): > 0 when o → a → b turns left."""
    return (a0 - o0) * (b1 - o1) - (a1 - o1) * (b0 - o0)


@kernel
def _shoelace(poly, m):  # pragma: no cover - compiled
    s = 0.0
    for i in range(m):
        j = (i + 1) % m
        s += poly[i, 0] * poly[j, 1] - poly[j, 0] * poly[i, 1]
    return 0.5 * s


@kernel(inline="always")
def _local_corners(J, phi, cx, cy):  # pragma: no cover - compiled
    """``J · φ − (cx, cy)`` (4, 2) for J (4, 2, p), φ (p,): each corner's products added left to
    right from 0, as NumPy's ``J @ φ`` adds them for these sizes (tested bit for bit)."""
    corners = np.empty((J.shape[0], 2))
    for c in range(J.shape[0]):
        for d in range(2):
            acc = 0.0
            for k in range(J.shape[2]):
                acc += J[c, d, k] * phi[k]
            corners[c, d] = acc - (cx if d == 0 else cy)
    return corners


@kernel
def _hull_iou_kernel(pts, J, phi, cx, cy):  # pragma: no cover - compiled
    """IoU of the convex hull of ``pts`` (N, 2), sorted by x then y, and the box whose corners are
    ``J · φ − (cx, cy)`` (J (4, 2, 6), φ (6,): :func:`~labelaudit.core.geometry.box_corners` relative
    to the centre, counter-clockwise, :func:`_local_corners`); 0.0 when the hull has no area."""
    corners = _local_corners(J, phi, cx, cy)
    n = pts.shape[0]
    hull = np.empty((2 * n + 1, 2))
    k = 0
    for i in range(n):  # lower hull; collinear and repeated points are dropped (≤ 0)
        while (
            k >= 2
            and _cross(hull[k - 2, 0], hull[k - 2, 1], hull[k - 1, 0], hull[k - 1, 1], pts[i, 0], pts[i, 1]) <= 0.0
        ):
            k -= 1
        hull[k, 0], hull[k, 1] = pts[i, 0], pts[i, 1]
        k += 1
    lower = k + 1
    for i in range(n - 2, -1, -1):  # upper hull
        while (
            k >= lower
            and _cross(hull[k - 2, 0], hull[k - 2, 1], hull[k - 1, 0], hull[k - 1, 1], pts[i, 0], pts[i, 1]) <= 0.0
        ):
            k -= 1
        hull[k, 0], hull[k, 1] = pts[i, 0], pts[i, 1]
        k += 1
    m = k - 1  # the last point repeats the first
    if m < 3:
        return 0.0
    hull_area = _shoelace(hull, m)
    if not hull_area > 0.0:
        return 0.0
    poly = hull[:m].copy()
    for e in range(4):  # clip by each edge of the box: keep the left side (inside, on the edge)
        a0, a1 = corners[e, 0], corners[e, 1]
        b0, b1 = corners[(e + 1) % 4, 0], corners[(e + 1) % 4, 1]
        out = np.empty((2 * m + 2, 2))
        q = 0
        for i in range(m):
            p0, p1 = poly[i - 1, 0], poly[i - 1, 1]  # i − 1 = −1: the last vertex
            c0, c1 = poly[i, 0], poly[i, 1]
            sp = _cross(a0, a1, b0, b1, p0, p1)
            sc = _cross(a0, a1, b0, b1, c0, c1)
            if (sc >= 0.0) != (sp >= 0.0):  # the edge p → c crosses the line: add the crossing
                t = sp / (sp - sc)
                out[q, 0], out[q, 1] = p0 + t * (c0 - p0), p1 + t * (c1 - p1)
                q += 1
            if sc >= 0.0:
                out[q, 0], out[q, 1] = c0, c1
                q += 1
        poly = out[:q].copy()
        m = q
        if m < 3:
            return 0.0
    inter = max(_shoelace(poly, m), 0.0)
    union = hull_area + _shoelace(corners, 4) - inter
    return inter / union if union > 0.0 else 0.0


def _hull_candidates(pts: FloatArray) -> FloatArray:
    """The points (N, 2) that can be convex-hull vertices (Akl–Toussaint): a point strictly inside
    the octagon of the extreme points along x, x + y, y and x − y (both ways) is inside the hull and
    is dropped. Exact; the points of a simulated car keep an eighth of their number (79 of 637 on
    average; 202 with the quadrilateral of the x and y extremes alone), so the sort and the hull
    get little to do."""
    if len(pts) < 8:
        return pts
    x, y = pts[:, 0], pts[:, 1]
    s, d = x + y, x - y
    octagon = pts[  # counter-clockwise
        [x.argmin(), s.argmin(), y.argmin(), d.argmax(), x.argmax(), s.argmax(), y.argmax(), d.argmin()]
    ]
    keep = np.zeros(len(pts), dtype=bool)
    edges = 0
    for (qx, qy), (rx, ry) in zip(octagon, np.roll(octagon, -1, axis=0)):
        ex, ey = rx - qx, ry - qy
        if ex == 0.0 and ey == 0.0:
            continue  # two extremes are the same point: the polygon has fewer sides
        edges += 1
        keep |= ex * (y - qy) - ey * (x - qx) <= 0.0  # not strictly left of this edge (on it: kept)
    return pts[keep] if edges else pts


@kernel
def _sorted_candidates_kernel(pts, cx, cy):  # pragma: no cover - compiled
    """The hull candidates of :func:`_hull_candidates` among the finite rows of ``pts`` (N, ≥2)
    (x, y of :func:`~labelaudit.core.geometry.clean_points`), relative to (cx, cy) and sorted by x,
    then y (M, 2) float64: the same float64 operations as the NumPy form, element by element (no
    fast-math). Equal keys are equal points, so the order is unique whatever the sort."""
    n = pts.shape[0]
    xs = np.empty(n)
    ys = np.empty(n)
    m = 0
    for k in range(n):
        x, y = np.float64(pts[k, 0]), np.float64(pts[k, 1])
        if math.isfinite(x) and math.isfinite(y):
            xs[m], ys[m] = x, y
            m += 1
    keep = np.ones(m, dtype=np.bool_)
    if m >= 8:
        # the extreme points along x, x + y, y, x − y and their opposites (first occurrence), in
        # counter-clockwise order: :func:`_hull_candidates`' octagon
        ext = np.zeros(8, dtype=np.int64)  # min x, min x+y, min y, max x−y, max x, max x+y, max y, min x−y
        for k in range(1, m):
            x, y = xs[k], ys[k]
            if x < xs[ext[0]]:
                ext[0] = k
            if x + y < xs[ext[1]] + ys[ext[1]]:
                ext[1] = k
            if y < ys[ext[2]]:
                ext[2] = k
            if x - y > xs[ext[3]] - ys[ext[3]]:
                ext[3] = k
            if x > xs[ext[4]]:
                ext[4] = k
            if x + y > xs[ext[5]] + ys[ext[5]]:
                ext[5] = k
            if y > ys[ext[6]]:
                ext[6] = k
            if x - y < xs[ext[7]] - ys[ext[7]]:
                ext[7] = k
        keep[:] = False
        edges = 0
        for e in range(8):
            qx, qy = xs[ext[e]], ys[ext[e]]
            rx, ry = xs[ext[(e + 1) % 8]], ys[ext[(e + 1) % 8]]
            ex, ey = rx - qx, ry - qy
            if ex == 0.0 and ey == 0.0:
                continue
            edges += 1
            for k in range(m):  # not strictly left of this side (on it: kept)
                if not keep[k] and ex * (ys[k] - qy) - ey * (xs[k] - qx) <= 0.0:
                    keep[k] = True
        if edges == 0:
            keep[:] = True
    q = 0
    lx = np.empty(m)
    ly = np.empty(m)
    for k in range(m):
        if keep[k]:
            lx[q], ly[q] = xs[k] - cx, ys[k] - cy
            q += 1
    lx, ly = lx[:q], ly[:q]
    order = np.argsort(lx, kind="mergesort")
    out = np.empty((q, 2))
    for i in range(q):
        out[i, 0], out[i, 1] = lx[order[i]], ly[order[i]]
    i = 0
    while i < q:  # runs of equal x: by y, stable (insertion sort; runs are short) — np.lexsort's order, ±0 included
        j = i + 1
        while j < q and out[j, 0] == out[i, 0]:
            j += 1
        for a in range(i + 1, j):
            vx, vy = out[a, 0], out[a, 1]
            b = a - 1
            while b >= i and out[b, 1] > vy:
                out[b + 1, 0], out[b + 1, 1] = out[b, 0], out[b, 1]
                b -= 1
            out[b + 1, 0], out[b + 1, 1] = vx, vy
        i = j
    return out


def bev_iou_exact(box_a: ArrayLike, box_b: ArrayLike) -> float:
    """Exact BEV IoU of two rotated boxes (shapely polygon intersection)."""
    from shapely.geometry import Polygon

    pa, pb = Polygon(g.box_corners(box_a, "bev")), Polygon(g.box_corners(box_b, "bev"))
    inter = pa.intersection(pb).area
    union = pa.area + pb.area - inter
    return float(inter / union) if union > 0 else 0.0


def iou_3d_exact(box_a: ArrayLike, box_b: ArrayLike) -> float:
    """Exact 3D IoU of two yaw-only boxes (BEV intersection × z overlap)."""
    from shapely.geometry import Polygon

    a, b = g.validate_box(box_a), g.validate_box(box_b)
    pa, pb = Polygon(g.box_corners(a, "bev")), Polygon(g.box_corners(b, "bev"))
    z_lo = max(a[2] - a[5] / 2, b[2] - b[5] / 2)
    z_hi = min(a[2] + a[5] / 2, b[2] + b[5] / 2)
    inter = pa.intersection(pb).area * max(0.0, z_hi - z_lo)
    union = a[3] * a[4] * a[5] + b[3] * b[4] * b[5] - inter
    return float(inter / union) if union > 0 else 0.0


# public for labelaudit.core.posterior.bev_label_scores, which calls them from its own compiled pass
# (hull_iou_valid's steps for float64 points: the sorted candidates, then the clipped hull's IoU)
hull_candidates_sorted = _sorted_candidates_kernel
hull_iou_sorted = _hull_iou_kernel
BEV_CORNER_J = _BEV_CORNER_J

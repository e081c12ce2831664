"""Geometric overlap of many box pairs at once: BEV / 3D IoU and the devkit's "overlap over the detection".

One compiled pass clips every requested pair of rotated rectangles (Sutherland–Hodgman against
the four edges of the other, convex, counter-clockwise box) and takes the shoelace area; a bounding
circle test skips pairs that cannot touch. 3D multiplies the BEV intersection by the overlap of
the third coordinate's intervals (boxes turn about that axis only).

Boxes are given as (c1, c2, c3, l, w, h, yaw): the ground-plane rectangle in (c1, c2), the height
interval c3 ± h/2. For Waymo (and every LiDAR/vehicle-frame box) that is the box itself. The KITTI
devkit measures overlap in the rectified camera frame instead: the rectangle in the camera's
(x, z) plane and the height interval along camera y, from the label's bottom y up to y − h. Camera
y is not exactly the LiDAR's −z (R0_rect · Tr_velo_to_cam tilts it by a few mrad), so 3D overlaps
taken on LiDAR z differ from the devkit's by up to ~10⁻² for boxes a few millimetres apart in
camera y. :func:`camera_frame_boxes` lays KITTI boxes out in the devkit's geometry, so the same
kernel gives the devkit's numbers. This module knows nothing about classes, scores or files.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = ["bev_corners", "box_areas", "camera_frame_boxes", "clip_area", "kitti_devkit_boxes", "pair_overlaps"]


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


def camera_frame_boxes(locations: ArrayLike, dims_hwl: ArrayLike, rotation_y: ArrayLike) -> FloatArray:
    """KITTI boxes in the devkit's geometry, laid out for :func:`pair_overlaps`, shape (N, 7).

    The devkit intersects the rectangles in the rectified camera's (x, z) plane and the height
    intervals [y − h, y] along camera y (y points down, ``location`` is the bottom centre). A box
    turned by ``rotation_y`` about camera y has its length along (cos ry, −sin ry) in (x, z), so in
    the (c1, c2, c3, l, w, h, yaw) layout it is (x, z, y − h/2, l, w, h, −ry): the ground-plane
    rectangle is exact and c3 ± h/2 is the devkit's height interval.

    Parameters
    ----------
    locations : (N, 3) bottom centres (x, y, z) in the rectified camera frame
    dims_hwl : (N, 3) height, width, length
    rotation_y : (N,) rotation about camera y (rad)
    """
    loc = np.asarray(locations, dtype=float).reshape(-1, 3)
    dims = np.asarray(dims_hwl, dtype=float).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=float).reshape(-1)
    h = dims[:, 0]
    return np.ascontiguousarray(np.c_[loc[:, 0], loc[:, 2], loc[:, 1] - h / 2.0, dims[:, 2], dims[:, 1], h, -ry])


def kitti_devkit_boxes(boxes: ArrayLike, frame_of_row: ArrayLike, calibs: Sequence[Any]) -> FloatArray:
    """LiDAR-frame KITTI boxes of many frames in the devkit's geometry (:func:`camera_frame_boxes`).

    Each box goes back to the rectified camera frame with its own frame's calibration (the exact
    inverse of how labels and KITTI detection files were brought to the LiDAR frame).

    Parameters
    ----------
    boxes : (N, 7) LiDAR-frame boxes
    frame_of_row : (N,) frame index of each box
    calibs : per frame a :class:`~labelaudit.datasets.kitti.Calibration`

    Returns
    -------
    (N, 7) boxes for :func:`pair_overlaps`

    Raises
    ------
    ValueError
        A frame holding boxes has no calibration.
    """
    from labelaudit.datasets.kitti import boxes_lidar_to_camera

    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    fr = np.asarray(frame_of_row, dtype=np.int64).reshape(-1)
    out = np.empty_like(b)
    if not len(b):
        return out
    order = np.argsort(fr, kind="stable")
    cut = np.flatnonzero(np.diff(fr[order])) + 1
    for rows in np.split(order, cut):
        calib = calibs[int(fr[rows[0]])]
        if calib is None:
            raise ValueError(f"frame {int(fr[rows[0]])} has boxes but no KITTI calibration")
        loc, dims, ry = boxes_lidar_to_camera(b[rows], calib)
        out[rows] = camera_frame_boxes(loc, dims, ry)
    return out


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
def _pairs_kernel(
    ca, cb, centre_a, centre_b, radius_a, radius_b, za, zb, ia, ib, three_d
):  # pragma: no cover - compiled
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
        bev_corners(a),
        bev_corners(b),
        np.ascontiguousarray(a[:, :2]),
        np.ascontiguousarray(b[:, :2]),
        0.5 * np.hypot(a[:, 3], a[:, 4]),
        0.5 * np.hypot(b[:, 3], b[:, 4]),
        za,
        zb,
        ia,
        ib,
        three_d,
    )
    area_a, area_b = box_areas(a, view)[ia], box_areas(b, view)[ib]
    union = area_a + area_b - inter
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = np.where(union > 0, inter / union, 0.0)
        over_a = np.where(area_a > 0, inter / area_a, 0.0)
    return inter, np.clip(iou, 0.0, 1.0), np.clip(over_a, 0.0, 1.0)

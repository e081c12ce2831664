"""Points of each labelled box: Open3D oriented-box selection with a BEV margin and a ground cut.
It selects point indices only; the model and the rows are elsewhere.

The selection region of a box ``(cx, cy, cz, l, w, h, yaw)`` is the box

- widened by ``margin`` on every side in bird's-eye view (length and width grow by 2·margin; the
  height does not), so points a few centimetres outside a tight label still count;
- cut from below at ``bottom + ground_cut`` (bottom = cz − h/2), so ground returns under the
  object are dropped; the top stays at cz + h/2.

Boundaries are inclusive. :func:`crop_frame` builds **one** Open3D point cloud per frame and asks
each box's ``OrientedBoundingBox`` for its indices; :func:`points_in_boxes_numpy` is the plain
NumPy reference. They agree except for points within floating-point rounding of a face.

:func:`crop_frame_pair` serves the pipeline, which needs two nested crops per box (the model's and
the wider one of the label-error fit): Open3D crops once with the wide margin and the narrow crop
is taken from those points by :func:`refine_crop`, which repeats Open3D's arithmetic exactly.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import open3d as o3d
from numpy.typing import ArrayLike, NDArray

from labelaudit.config import CropParams
from labelaudit.core.geometry import rotation_z

IndexArray = NDArray[np.int64]

__all__ = ["crop_frame", "crop_frame_pair", "points_in_boxes_numpy", "refine_crop", "selection_boxes"]


def _check_inputs(points: ArrayLike, boxes: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] < 3:
        raise ValueError(f"points must be (N, ≥3), got shape {pts.shape}")
    b = np.asarray(boxes, dtype=float)
    if b.size == 0:
        b = b.reshape(0, 7)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"boxes must be (K, 7), got shape {b.shape}")
    return pts, b


def selection_boxes(boxes: ArrayLike, margin: float, ground_cut: float) -> NDArray[np.float64]:
    """The regions actually selected, as boxes (K, 7): BEV margin added, bottom raised by ``ground_cut``.

    A box whose ground cut reaches its top gets height ≤ 0 (it selects nothing).
    """
    b = np.array(boxes, dtype=float).reshape(-1, 7)
    if margin < 0 or ground_cut < 0:
        raise ValueError(f"margin and ground_cut must be ≥ 0, got margin={margin}, ground_cut={ground_cut}")
    out = b.copy()
    out[:, 3] += 2.0 * margin
    out[:, 4] += 2.0 * margin
    out[:, 5] -= ground_cut
    out[:, 2] += ground_cut / 2.0  # bottom goes up by ground_cut, the top stays
    return out


def points_in_boxes_numpy(
    points: ArrayLike, boxes: ArrayLike, margin: float = 0.0, ground_cut: float = 0.0
) -> list[IndexArray]:
    """Reference point selection (NumPy, float64).

    Parameters
    ----------
    points : (N, ≥3) — only x, y, z are used
    boxes : (K, 7) cx, cy, cz, l, w, h, yaw
    margin : BEV margin in metres, added on every side of length and width
    ground_cut : metres above the box bottom below which points are dropped

    Returns
    -------
    indices : K sorted int64 arrays of row indices into ``points``
    """
    pts, b = _check_inputs(points, boxes)
    xyz = pts[:, :3].astype(np.float64)
    sel = selection_boxes(b, margin, ground_cut)
    out: list[IndexArray] = []
    for cx, cy, cz, l, w, h, yaw in sel:
        if h <= 0:
            out.append(np.empty(0, dtype=np.int64))
            continue
        c, s = np.cos(yaw), np.sin(yaw)
        dx, dy, dz = xyz[:, 0] - cx, xyz[:, 1] - cy, xyz[:, 2] - cz
        # Rotate by −yaw into the box frame.
        lx = c * dx + s * dy
        ly = -s * dx + c * dy
        inside = (np.abs(lx) <= l / 2.0) & (np.abs(ly) <= w / 2.0) & (np.abs(dz) <= h / 2.0)
        out.append(np.flatnonzero(inside).astype(np.int64))
    return out


def crop_frame(points: ArrayLike, boxes: ArrayLike, params: CropParams) -> list[IndexArray]:
    """Indices of the points inside each box, with the margin and ground cut of ``params``.

    One Open3D point cloud is built for the frame; every box is an ``OrientedBoundingBox`` queried
    against it.

    Parameters
    ----------
    points : (N, ≥3) x, y, z, … in the boxes' frame (float32 or float64)
    boxes : (K, 7) cx, cy, cz, l, w, h, yaw
    params : margin and ground cut

    Returns
    -------
    indices : K sorted int64 arrays of row indices into ``points`` (the order of ``points``)
    """
    pts, b = _check_inputs(points, boxes)
    if len(b) == 0:
        return []
    sel = selection_boxes(b, params.margin, params.ground_cut)
    # float32 input converts to float64 exactly, so Open3D sees the same coordinates as the reference.
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.ascontiguousarray(pts[:, :3], dtype=np.float64)))
    rotations = rotation_z(sel[:, 6])
    out: list[IndexArray] = []
    for box, R in zip(sel, rotations):
        if box[5] <= 0 or len(pts) == 0:
            out.append(np.empty(0, dtype=np.int64))
            continue
        obb = o3d.geometry.OrientedBoundingBox(box[:3], R, box[3:6])
        idx = np.asarray(obb.get_point_indices_within_bounding_box(cloud.points), dtype=np.int64)
        out.append(np.sort(idx))
    return out


def refine_crop(points: ArrayLike, boxes: ArrayLike, candidates: list[IndexArray], params: CropParams) -> list[IndexArray]:
    """The indices :func:`crop_frame` ``(points, boxes, params)`` returns, taken from a superset.

    Open3D's ``OrientedBoundingBox`` keeps a point p when ``|(p − c)·R[:, a]| ≤ extent_a / 2`` for
    a = x, y, z. The same float64 operations in the same order are done here on the candidate
    points only, so the result is identical (tested against Open3D on random and real frames) at
    the cost of the candidates, not the frame.

    Parameters
    ----------
    points : (N, ≥3) the frame's points
    boxes : (K, 7) cx, cy, cz, l, w, h, yaw
    candidates : K sorted index arrays, each a superset of the crop by ``params`` (e.g. a crop
        with a larger margin and the same ground cut)
    params : margin and ground cut of the wanted crop

    Returns
    -------
    indices : K sorted int64 arrays, each a subset of its candidates
    """
    pts, b = _check_inputs(points, boxes)
    if len(candidates) != len(b):
        raise ValueError(f"need one candidate array per box: {len(candidates)} arrays for {len(b)} boxes")
    sel = selection_boxes(b, params.margin, params.ground_cut)
    rotations = rotation_z(sel[:, 6])
    out: list[IndexArray] = []
    for box, R, cand in zip(sel, rotations, candidates):
        if box[5] <= 0 or len(cand) == 0:
            out.append(np.empty(0, dtype=np.int64))
            continue
        d = pts[cand, :3].astype(np.float64) - box[:3]
        half = box[3:6] / 2.0
        inside = np.ones(len(cand), dtype=bool)
        for a in range(3):  # d·R[:, a] summed left to right, as Eigen's 3-vector dot
            proj = d[:, 0] * R[0, a] + d[:, 1] * R[1, a] + d[:, 2] * R[2, a]
            inside &= np.abs(proj) <= half[a]
        out.append(np.asarray(cand, dtype=np.int64)[inside])
    return out


def crop_frame_pair(points: ArrayLike, boxes: ArrayLike, params: CropParams) -> tuple[list[IndexArray], list[IndexArray]]:
    """The model's crop (``params.margin``) and the label-error fit's wider crop (``params.fit_margin``).

    One Open3D pass with the wide margin; the narrow crop is refined from it
    (:func:`refine_crop`), equal to ``crop_frame(points, boxes, params)``.

    Returns
    -------
    indices : K sorted int64 arrays, the crop with ``params.margin``
    fit_indices : K sorted int64 arrays, the crop with ``max(params.margin, params.fit_margin)``
        (the same list as ``indices`` when the fit margin is not wider)
    """
    if params.fit_margin <= params.margin:
        indices = crop_frame(points, boxes, params)
        return indices, indices
    fit_indices = crop_frame(points, boxes, replace(params, margin=params.fit_margin))
    return refine_crop(points, boxes, fit_indices, params), fit_indices

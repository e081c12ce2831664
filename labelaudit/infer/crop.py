"""Points of each labelled box: Open3D oriented-box selection with a BEV margin and a ground cut.
It selects point indices only; the model and the rows are elsewhere.

The selection region of a box ``(cx, cy, cz, l, w, h, yaw)`` is the box

- widened by ``margin`` on every side in bird's-eye view (length and width grow by 2·margin; the
  height does not), so points a few centimetres outside a tight label still count;
- cut from below at ``bottom + ground_cut`` (bottom = cz − h/2), so ground returns under the
  object are dropped; the top stays at cz + h/2.

Boundaries are inclusive. :func:`crop_frame` asks each box's Open3D ``OrientedBoundingBox`` for
its indices; :func:`points_in_boxes_numpy` is the plain
NumPy reference. They agree except for points within floating-point rounding of a face.

:func:`crop_frame_pair` serves the pipeline, which needs two nested crops per box (the model's and
the wider one of the label-error fit): Open3D crops once with the wide margin and the narrow crop
is taken from those points by :func:`refine_crop`, which repeats Open3D's arithmetic exactly.

Open3D tests every point it is given against a box, so each box is asked only about the points
of the BEV grid cells its footprint touches (:class:`_BevIndex`, built once per frame by a
compiled counting sort): the same indices as asking about the whole frame, at the cost of the
candidates instead of K·N. A frame with many boxes (≥ :data:`~labelaudit.constants.CROP_GRID_MIN_BOXES`,
e.g. a 10,000-line label file) skips Open3D altogether: its candidates are tested with Open3D's
exact arithmetic, vectorised over the boxes (:func:`_crop_pair_by_grid`), so the indices are
identical whichever way is taken.
"""

from __future__ import annotations

import functools
import sys
import types
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.config import CropParams
from labelaudit.core.geometry import rotation_z
from labelaudit.kernels import kernel

IndexArray = NDArray[np.int64]


def _import_open3d() -> types.ModuleType:
    """``import open3d`` without its plotting chain.

    ``open3d.visualization`` imports ``draw_plotly``, which imports Plotly and Dash (about half of
    Open3D's import time, in every worker) although a crop never plots. When Open3D is not loaded
    yet, that one module is replaced by a stand-in whose three functions load the real module on
    first call, so ``open3d.visualization.draw_plotly(...)`` still works for whoever wants it.
    """
    name = "open3d.visualization.draw_plotly"
    if "open3d" not in sys.modules and name not in sys.modules:
        stub = types.ModuleType(name, "Stand-in of labelaudit.infer.crop: the real module loads on first call.")

        def _real() -> types.ModuleType:
            import importlib.util

            spec = importlib.util.find_spec("open3d.visualization")
            path = next(iter(spec.submodule_search_locations)) if spec and spec.submodule_search_locations else None
            real_spec = importlib.util.spec_from_file_location(name, f"{path}/draw_plotly.py")
            module = importlib.util.module_from_spec(real_spec)  # type: ignore[arg-type]
            real_spec.loader.exec_module(module)  # type: ignore[union-attr]
            sys.modules[name] = module
            return module

        def _lazy(attr: str):  # noqa: ANN202
            def call(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
                return getattr(_real(), attr)(*args, **kwargs)

            call.__name__ = attr
            return call

        for attr in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
            setattr(stub, attr, _lazy(attr))
        sys.modules[name] = stub
    import open3d

    return open3d


@functools.lru_cache(maxsize=1)
def open3d() -> types.ModuleType:
    """Open3D, imported on first use (:func:`_import_open3d`).

    The pipeline's crops (:mod:`labelaudit.infer.evidence`) repeat Open3D's selection arithmetic in
    a compiled pass and never call Open3D, so a worker that only audits does not pay its import
    (~0.5 s and ~100 MiB per process); :func:`crop_frame`, ``show`` and the tests that compare the
    two selections load it here.
    """
    return _import_open3d()


__all__ = ["bev_candidates", "crop_frame", "crop_frame_pair", "points_in_boxes_numpy", "refine_crop", "selection_boxes"]


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

    Every box is an Open3D ``OrientedBoundingBox`` queried against the frame's points — only
    against the points of the BEV grid cells its footprint touches (:class:`_BevIndex`, one compiled
    counting sort per frame): Open3D tests each point on its own, so a superset of the box's points
    gives the indices a query of the whole frame gives (a test checks), at the cost of the
    candidates instead of K·N.

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
    empty = np.empty(0, dtype=np.int64)
    if len(pts) == 0:
        return [empty for _ in sel]
    o3d = open3d()
    rotations = rotation_z(sel[:, 6])
    own, idx = _BevIndex(pts, sel, C.CROP_GRID_CELL).candidates(slice(None))
    starts = np.searchsorted(own, np.arange(len(sel) + 1))  # candidates come grouped by box
    out: list[IndexArray] = []
    for k, (box, R) in enumerate(zip(sel, rotations)):
        cand = idx[starts[k] : starts[k + 1]]
        if box[5] <= 0 or len(cand) == 0:
            out.append(empty)
            continue
        obb = o3d.geometry.OrientedBoundingBox(box[:3], R, box[3:6])
        hit = np.asarray(obb.get_point_indices_within_bounding_box(_open3d_points(pts, cand)), dtype=np.int64)
        out.append(np.sort(cand[hit]))
    return out


def _open3d_points(pts: NDArray, rows: IndexArray) -> "types.ModuleType":
    """x, y, z of the points ``pts[rows]`` as the Open3D vector a box query reads.

    float32 converts to float64 exactly, so Open3D sees the same coordinates as the reference. The
    gather and conversion are one compiled pass (NumPy's strided float32 → float64 cast takes ~8×
    longer), and no ``PointCloud`` is built around the vector: its constructor copies every point
    again, for nothing a bounding-box query needs.
    """
    if pts.dtype == np.float32 or pts.dtype == np.float64:
        xyz = _xyz_float64(pts, np.ascontiguousarray(rows, dtype=np.int64))
    else:
        xyz = np.ascontiguousarray(pts[rows, :3], dtype=np.float64)
    return open3d().utility.Vector3dVector(xyz)


@kernel
def _xyz_float64(pts, rows):  # pragma: no cover - compiled
    out = np.empty((rows.shape[0], 3))
    for j in range(rows.shape[0]):
        i = rows[j]
        out[j, 0] = pts[i, 0]
        out[j, 1] = pts[i, 1]
        out[j, 2] = pts[i, 2]
    return out


def refine_crop(
    points: ArrayLike, boxes: ArrayLike, candidates: list[IndexArray], params: CropParams
) -> list[IndexArray]:
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


class _BevIndex:
    """The frame's points sorted by BEV grid cell, inside the rectangle that holds every box.

    ``keys`` are the sorted cell keys (column · ny + row) and ``index`` the point indices in that
    order (ascending within a cell). A compiled counting sort (two passes over the frame) builds
    them when the grid has at most :data:`~labelaudit.constants.CROP_GRID_DENSE_CELLS` cells per
    point, else a stable NumPy sort of the kept points (boxes spread far apart); both give the
    same arrays.
    """

    def __init__(self, pts: NDArray, sel: NDArray[np.float64], cell: float):
        self.pts, self.cell = pts, cell
        self.lo, self.hi = _footprints(sel)
        (self.x0, self.y0), (x1, y1) = self.lo.min(axis=0), self.hi.max(axis=0)
        self.ny = int(np.floor((y1 - self.y0) / cell)) + 1
        nx = int(np.floor((x1 - self.x0) / cell)) + 1
        if pts.dtype in (np.float32, np.float64) and nx * self.ny <= C.CROP_GRID_DENSE_CELLS * max(len(pts), 1024):
            self.keys, self.index = _counting_sort_cells(
                pts, float(self.x0), float(self.y0), float(x1), float(y1), float(cell), nx, self.ny
            )
            return
        xy = pts[:, :2].astype(np.float64)
        with np.errstate(invalid="ignore"):
            keep = np.flatnonzero(
                (xy[:, 0] >= self.x0) & (xy[:, 0] <= x1) & (xy[:, 1] >= self.y0) & (xy[:, 1] <= y1)
            )  # NaN: out
        key = self._cells(xy[keep, 0], self.x0) * self.ny + self._cells(xy[keep, 1], self.y0)
        order = np.argsort(key, kind="stable")
        self.keys, self.index = key[order], keep[order]

    def _cells(self, v: NDArray[np.float64], origin: float) -> NDArray[np.int64]:
        return np.floor((v - origin) / self.cell).astype(np.int64)

    def candidates(self, boxes: slice) -> tuple[IndexArray, IndexArray]:
        """(box, point index) pairs of the cells the footprints of ``boxes`` touch (box numbers
        relative to the slice start; not sorted)."""
        lo, hi = self.lo[boxes], self.hi[boxes]
        bx = np.c_[self._cells(lo[:, 0], self.x0), self._cells(hi[:, 0], self.x0)]
        by = np.c_[self._cells(lo[:, 1], self.y0), self._cells(hi[:, 1], self.y0)]
        # one run of sorted keys per (box, column of cells): cells (col, by0) … (col, by1)
        counts = bx[:, 1] - bx[:, 0] + 1
        owner = np.repeat(np.arange(len(lo)), counts)
        col = bx[owner, 0] + np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
        start = np.searchsorted(self.keys, col * self.ny + by[owner, 0], side="left")
        length = np.searchsorted(self.keys, col * self.ny + by[owner, 1], side="right") - start
        pos = np.repeat(start - (np.cumsum(length) - length), length) + np.arange(length.sum())
        return np.repeat(owner, length), self.index[pos]


@kernel
def _counting_sort_cells(pts, x0, y0, x1, y1, cell, nx, ny):  # pragma: no cover - compiled
    """:class:`_BevIndex`'s sorted (keys, index) by a counting sort: the same keep test and cell
    keys as its NumPy form (float64 x, y; floor((v − origin) / cell)), stable by point index."""
    n = pts.shape[0]
    ncell = nx * ny
    key = np.empty(n, dtype=np.int64)
    start = np.zeros(ncell + 1, dtype=np.int64)
    for i in range(n):
        x = np.float64(pts[i, 0])
        y = np.float64(pts[i, 1])
        if x >= x0 and x <= x1 and y >= y0 and y <= y1:  # False for NaN
            k = np.int64(np.floor((x - x0) / cell)) * ny + np.int64(np.floor((y - y0) / cell))
            key[i] = k
            start[k + 1] += 1
        else:
            key[i] = -1
    for c in range(ncell):
        start[c + 1] += start[c]
    fill = start[:ncell].copy()
    keys = np.empty(start[ncell], dtype=np.int64)
    index = np.empty(start[ncell], dtype=np.int64)
    for i in range(n):
        k = key[i]
        if k >= 0:
            keys[fill[k]] = k
            index[fill[k]] = i
            fill[k] += 1
    return keys, index


def _footprints(sel: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(K, 2) low and high corners of the boxes' axis-aligned BEV rectangles, padded by far more
    than the rounding of the oriented test (so a point inside a box is inside its rectangle)."""
    c, s = np.abs(np.cos(sel[:, 6])), np.abs(np.sin(sel[:, 6]))
    half = np.c_[c * sel[:, 3] + s * sel[:, 4], s * sel[:, 3] + c * sel[:, 4]] / 2.0
    pad = 1e-9 * (1.0 + np.abs(sel[:, :2]).max(axis=1) + sel[:, 3:5].max(axis=1))
    return sel[:, :2] - half - pad[:, None], sel[:, :2] + half + pad[:, None]


def _split_by_box(own: IndexArray, idx: IndexArray, k: int) -> list[IndexArray]:
    """(box, index) pairs → K sorted index arrays."""
    o = np.lexsort((idx, own))
    own, idx = own[o], idx[o]
    return np.split(idx, np.searchsorted(own, np.arange(1, k)))


def bev_candidates(points: ArrayLike, boxes: ArrayLike, cell: float = C.CROP_GRID_CELL) -> list[IndexArray]:
    """For each box, the sorted indices of the points in the BEV grid cells its footprint touches.

    A superset of the points inside each box (as :func:`crop_frame` and :func:`refine_crop` test
    them): a point inside a box lies inside the box's axis-aligned BEV rectangle (padded by far
    more than the rounding of the oriented test), and its cell index, a monotone function of x and
    y, lies between those of the rectangle's corners. Non-finite points are in no box.

    Parameters
    ----------
    points : (N, ≥3) the frame's points
    boxes : (K, 7) the selection boxes (margin and ground cut already applied)
    cell : grid cell side (m)

    Returns
    -------
    candidates : K sorted int64 index arrays
    """
    pts, b = _check_inputs(points, boxes)
    if len(b) == 0:
        return []
    own, idx = _BevIndex(pts, b, cell).candidates(slice(None))
    return _split_by_box(own, idx, len(b))


def _inside(
    pts: NDArray, sel: NDArray[np.float64], rot: NDArray[np.float64], own: IndexArray, idx: IndexArray
) -> NDArray[np.bool_]:
    """Which (box, point) pairs are inside the box, as :func:`refine_crop` decides, on many boxes at once.

    The same float64 operations element for element, except the terms with the zero entries of
    a z rotation (R[2, 0], R[2, 1], R[0, 2], R[1, 2] = 0; R[2, 2] = 1): for the finite x, y of a
    candidate they add ±0, which leaves |projection| and so the decision unchanged (a NaN or inf
    z fails the z test either way).
    """
    d = pts[idx, :3].astype(np.float64) - sel[own, :3]
    half = sel[:, 3:6] / 2.0
    inside = np.abs(d[:, 2]) <= half[own, 2]
    inside &= np.abs(d[:, 0] * rot[own, 0, 0] + d[:, 1] * rot[own, 1, 0]) <= half[own, 0]
    inside &= np.abs(d[:, 0] * rot[own, 0, 1] + d[:, 1] * rot[own, 1, 1]) <= half[own, 1]
    return inside & (sel[own, 5] > 0)


def _crop_pair_by_grid(
    pts: NDArray, b: NDArray[np.float64], params: CropParams
) -> tuple[list[IndexArray], list[IndexArray]]:
    """:func:`crop_frame_pair` through the BEV grid: O(N log N + candidates), identical indices.

    Boxes go in batches of :data:`~labelaudit.constants.CROP_GRID_BATCH`, so the candidate
    arrays stay a few MB however many boxes a frame has.
    """
    wide = replace(params, margin=max(params.margin, params.fit_margin))
    sel_w, sel_n = (
        selection_boxes(b, wide.margin, wide.ground_cut),
        selection_boxes(b, params.margin, params.ground_cut),
    )
    rot_w, rot_n = rotation_z(sel_w[:, 6]), rotation_z(sel_n[:, 6])
    grid = _BevIndex(pts, sel_w, C.CROP_GRID_CELL)
    owners_w, points_w, owners_n, points_n = [], [], [], []
    for first in range(0, len(b), C.CROP_GRID_BATCH):
        own, idx = grid.candidates(slice(first, first + C.CROP_GRID_BATCH))
        own = own + first
        ok = _inside(pts, sel_w, rot_w, own, idx)
        own, idx = own[ok], idx[ok]
        owners_w.append(own)
        points_w.append(idx)
        if params.fit_margin > params.margin:
            ok = _inside(pts, sel_n, rot_n, own, idx)
            owners_n.append(own[ok])
            points_n.append(idx[ok])
    fit_indices = _split_by_box(np.concatenate(owners_w), np.concatenate(points_w), len(b))
    if params.fit_margin <= params.margin:
        return fit_indices, fit_indices
    return _split_by_box(np.concatenate(owners_n), np.concatenate(points_n), len(b)), fit_indices


def crop_frame_pair(
    points: ArrayLike, boxes: ArrayLike, params: CropParams
) -> tuple[list[IndexArray], list[IndexArray]]:
    """The model's crop (``params.margin``) and the label-error fit's wider crop (``params.fit_margin``).

    One Open3D pass with the wide margin; the narrow crop is refined from it
    (:func:`refine_crop`), equal to ``crop_frame(points, boxes, params)``.

    Returns
    -------
    indices : K sorted int64 arrays, the crop with ``params.margin``
    fit_indices : K sorted int64 arrays, the crop with ``max(params.margin, params.fit_margin)``
        (the same list as ``indices`` when the fit margin is not wider)
    """
    pts, b = _check_inputs(points, boxes)
    if len(b) >= C.CROP_GRID_MIN_BOXES and len(pts):  # many boxes: through the BEV grid (Open3D costs K·N)
        return _crop_pair_by_grid(pts, b, params)
    if params.fit_margin <= params.margin:
        indices = crop_frame(points, boxes, params)
        return indices, indices
    fit_indices = crop_frame(points, boxes, replace(params, margin=params.fit_margin))
    return refine_crop(points, boxes, fit_indices, params), fit_indices

"""JIoU of many (detection, label) pairs, each computed once and reused for every threshold.

JIoU(detection, label) is the probabilistic Jaccard index of the detection's spatial distribution
(uniform on its box, or p_G of its own covariance) and the label's p_G (docs/method.md), as
:func:`labelaudit.core.spatial.jiou` defines it, with spatial's samples, grid and rasteriser. Here
the pairs are grouped by label: the label's samples and grid are built once and shared by all its
candidate detections. The grid covers the supports of the label and of those detections, its cells
as fine as the smallest box and the sharpest boundary among them require.

For a *deterministic* detection (the common case) the pair is one compiled call
(:func:`_jiou_uniform_bev_kernel`): the label is rasterised only on the window of cells the
detection covers (its mass elsewhere enters through its total), the detection's share of each cell
is exact (polygon clipping) and partly covered cells are split between the box and the rest. That
makes the cell-level Jaccard of two uniform boxes their IoU, where rasterising the detection into
whole cells (as ``spatial.jiou`` does for "the other box") biases it by up to 0.02 at 64 cells per
side; against a 3× finer grid the result is within 0.01 (tested).

Labels without a covariance (their inference failed or was skipped) are deterministic boxes: a
deterministic detection then gets its exact IoU. Large batches are split over worker processes.
This module owns the pairing, batching and the compiled pair kernel; p_G sampling and the Jaccard
index are :mod:`labelaudit.core.spatial`'s.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.config import SpatialParams
from labelaudit.core import spatial as S
from labelaudit.evaluate.overlap import bev_corners, clip_area
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]

__all__ = ["PairTask", "pair_jious"]

_MIN_PAIRS_FOR_POOL = 4000  # below this many pairs a worker pool costs more than it saves


@dataclass(frozen=True)
class PairTask:
    """One batch: labels with their candidate detections (picklable, for worker processes).

    ``gt_cov[g]`` is NaN-filled when label g has no covariance; ``det_cov`` is None when no
    detection has one, else NaN-filled rows for deterministic detections.
    """

    model: str
    params: SpatialParams
    gt_boxes: FloatArray  # (G, 7)
    gt_cov: FloatArray  # (G, p, p)
    det_boxes: FloatArray  # (D, 7)
    det_cov: FloatArray | None  # (D, k, k)
    det_cov_on: str
    pair_gt: NDArray[np.int64]  # (P,) into gt_boxes, sorted
    pair_det: NDArray[np.int64]  # (P,) into det_boxes
    pair_iou: FloatArray  # (P,) exact IoU of the mean boxes
    deterministic: bool = False  # treat every detection as deterministic (the Fig. 12 baseline)
    batch: int = 0  # position of the batch, so results coming back from workers find their pairs


def _dist(box: FloatArray, model: str, cov: FloatArray | None, cov_on: str) -> S.BoxDistribution:
    if cov is None or np.isnan(cov).any():
        return S.BoxDistribution(box, model)  # type: ignore[arg-type]
    return S.BoxDistribution(box, model, cov, cov_on)  # type: ignore[arg-type]


@kernel
def _chord(quad, y):  # pragma: no cover - compiled
    """x-interval (lo, hi) of a convex quadrilateral on the line at height y (lo > hi when it misses)."""
    lo, hi = np.inf, -np.inf
    for e in range(4):
        ax, ay = quad[e, 0], quad[e, 1]
        bx, by = quad[(e + 1) % 4, 0], quad[(e + 1) % 4, 1]
        if (ay - y) * (by - y) <= 0.0 and ay != by:
            x = ax + (y - ay) / (by - ay) * (bx - ax)
            lo, hi = min(lo, x), max(hi, x)
        elif ay == by == y:
            lo, hi = min(lo, ax, bx), max(hi, ax, bx)
    return lo, hi


@kernel
def _cell_areas(quad, xe, ye):  # pragma: no cover - compiled
    """Exact area of a convex counter-clockwise quadrilateral (4, 2) inside every cell, (ny, nx).

    Per row band only the cells at the ends of the quad's span are clipped: the quad's left
    boundary is convex in y and its right boundary concave, so the cells between the larger left
    and the smaller right end of the two edge chords are covered completely.
    """
    nx, ny = xe.shape[0] - 1, ye.shape[0] - 1
    out = np.zeros((ny, nx))
    y0, y1 = quad[:, 1].min(), quad[:, 1].max()
    j0 = max(0, np.searchsorted(ye, y0, side="right") - 1)
    j1 = min(ny, np.searchsorted(ye, y1, side="left"))
    cell = np.empty((4, 2))
    for j in range(j0, j1):
        ya, yb = ye[j], ye[j + 1]
        la, ra = _chord(quad, ya)
        lb, rb = _chord(quad, yb)
        # the span of the quad within the band: its chords and any vertex inside the band
        xmin, xmax = min(la, lb), max(ra, rb)
        for k in range(4):
            if ya < quad[k, 1] < yb:
                xmin, xmax = min(xmin, quad[k, 0]), max(xmax, quad[k, 0])
        if xmin >= xmax:
            continue
        full_lo, full_hi = (max(la, lb), min(ra, rb)) if (la <= ra and lb <= rb) else (np.inf, -np.inf)
        i0 = max(0, np.searchsorted(xe, xmin, side="right") - 1)
        i1 = min(nx, np.searchsorted(xe, xmax, side="left"))
        for i in range(i0, i1):
            if xe[i] >= full_lo and xe[i + 1] <= full_hi:
                out[j, i] = (xe[i + 1] - xe[i]) * (yb - ya)
                continue
            cell[0, 0], cell[0, 1] = xe[i], ya
            cell[1, 0], cell[1, 1] = xe[i + 1], ya
            cell[2, 0], cell[2, 1] = xe[i + 1], yb
            cell[3, 0], cell[3, 1] = xe[i], yb
            out[j, i] = clip_area(cell, quad)
    return out


@kernel
def _jiou_uniform_bev_kernel(A, centres, weights, xe, ye, quad, box_area, q_total, nsub):  # pragma: no cover - compiled
    """BEV JIoU of a uniform box (quad, area) and label samples rasterised on the window (xe, ye).

    The label raster is spatial's (row centre-line intervals, :func:`labelaudit.core.spatial.events_kernel`);
    the box's cell shares are exact and partly covered cells are split (see :func:`_uniform_jaccard`).
    Cells outside the window hold no box mass, so the label's mass there enters through
    ``q_total`` minus what the window holds.
    """
    nx, ny = xe.shape[0] - 1, ye.shape[0] - 1
    dx, dy = xe[1] - xe[0], ye[1] - ye[0]
    i_lo, i_hi, f_lo, f_hi, _ = S.events_kernel(A, centres, xe[0], xe[-1], ye[0], dx, dy, nx, ny, nsub)
    nb = ny * (nx + 1)
    steps = np.zeros(nb)
    direct = np.zeros(nb)
    for k in range(i_lo.shape[0]):
        w = weights[k]
        for r in range(i_lo.shape[1]):
            a, b = i_lo[k, r], i_hi[k, r]
            steps[a] += w * dx
            steps[b] -= w * dx
            direct[b] += w * f_hi[k, r]
            direct[a] -= w * f_lo[k, r]
    q = np.empty((ny, nx))
    sub = dy / nsub
    qmax = 0.0
    for j in range(ny):
        acc = 0.0
        for i in range(nx + 1):
            acc += steps[j * (nx + 1) + i]
            if i < nx:
                v = (acc + direct[j * (nx + 1) + i]) * sub
                q[j, i] = v
                if v > qmax:
                    qmax = v
    tiny = 1e-12 * qmax
    area = _cell_areas(quad, xe, ye)
    cell = dx * dy
    n_all = 2 * nx * ny
    P = np.empty(n_all)
    Q = np.empty(n_all)
    m = 0
    p_only = 0.0
    q_only = 0.0
    q_in = 0.0
    for j in range(ny):
        for i in range(nx):
            qv = q[j, i]
            if qv <= tiny:
                qv = 0.0
            q_in += qv
            pv = area[j, i] / box_area
            if pv <= 0.0:
                q_only += qv
                continue
            if qv == 0.0:
                p_only += pv
                continue
            frac = min(max(area[j, i] / cell, 0.0), 1.0)
            if frac < 1.0 - 1e-12:
                P[m] = pv
                Q[m] = qv * frac
                m += 1
                q_only += qv * (1.0 - frac)
            else:
                P[m] = pv
                Q[m] = qv
                m += 1
    q_only += max(0.0, q_total - q_in)
    if m == 0:
        return 0.0
    ratio = np.empty(m)
    for k in range(m):
        ratio[k] = P[k] / Q[k]
    order = np.argsort(ratio)
    suffix = np.empty(m)
    acc = p_only
    for t in range(m - 1, -1, -1):
        acc += P[order[t]]
        suffix[t] = acc
    prefix = q_only
    out = 0.0
    for t in range(m):
        k = order[t]
        out += 1.0 / (suffix[t] / P[k] + prefix / Q[k])
        prefix += Q[k]
    return out


def _grid_quad(box: FloatArray, ref: FloatArray) -> FloatArray:
    """BEV corners (4, 2) of ``box`` in the frame of the grid of ``ref`` (origin at its centre, x along its length)."""
    c, s = np.cos(ref[6]), np.sin(ref[6])
    corners = bev_corners(box)[0] - ref[:2]
    return np.ascontiguousarray(corners @ np.array([[c, -s], [s, c]]))


def _uniform_jaccard(
    box: FloatArray,
    ref: FloatArray,
    grid: S.Grid,
    q: FloatArray,
    q_full: NDArray[np.bool_] | None,
    q_total: float = 1.0,
) -> float:
    """Jaccard of the uniform distribution on a deterministic ``box`` and the label mass ``q`` on ``grid``.

    The box's share of every cell is exact (polygon clipping), and each partly covered cell is
    split into its covered part (all of the box's mass there) and the rest, the label's mass shared
    between them by area: the cell-level Jaccard of two uniform boxes is then their IoU, where
    averaging the box over whole cells would bias it by up to ~0.02 at 64 cells per side. 3D: the
    same per voxel, with the box's z-interval; layers both cover completely are merged
    (``q_full``: the label's completely covered layers) and layers without box mass enter through
    the label's total only. ``grid`` may be a window of the label's grid that holds the whole box:
    the label's mass outside it (``q_total`` minus what ``q`` holds) only enters through its total.
    """
    xe, ye = grid.x_edges, grid.y_edges
    area = _cell_areas(_grid_quad(box, ref), xe, ye)  # (ny, nx) m²
    cell_area = np.outer(np.diff(ye), np.diff(xe))
    if grid.z_edges is None:
        p = area / (box[3] * box[4])
        frac = np.clip(area / cell_area, 0.0, 1.0).ravel()
        qv = q.ravel()
        part = (frac > 1e-12) & (frac < 1.0 - 1e-12) & (qv > 0)
        P = np.concatenate([p.ravel(), np.zeros(int(part.sum()))])
        Q = np.concatenate([np.where(part, qv * frac, qv), qv[part] * (1.0 - frac[part])])
        return S.jaccard(P, Q, q_outside=max(0.0, q_total - float(qv.sum())))
    ze = grid.z_edges - (box[2] - ref[2])  # layer edges relative to the box centre
    dz = np.diff(ze)
    zc = np.clip(np.minimum(0.5 * box[5], ze[1:]) - np.maximum(-0.5 * box[5], ze[:-1]), 0.0, None)  # (nz,)
    vol = box[3] * box[4] * box[5]
    has_p = zc > 0
    has_q = q.reshape(-1, q.shape[-1]).sum(axis=0) > 0
    det_full = zc >= dz * (1 - 1e-9)
    both_full = det_full & (q_full if q_full is not None else np.zeros_like(det_full))
    explicit = np.flatnonzero(has_p & has_q & ~both_full)
    full = np.flatnonzero(both_full & has_q)
    layers = list(explicit) + ([int(full[0])] if len(full) else [])
    counts_l = [1.0] * len(explicit) + ([float(len(full))] if len(full) else [])
    Ps, Qs, Cs = [], [], []
    p_in = 0.0
    q_in = 0.0
    for z, cnt in zip(layers, counts_l):
        pz = (area * zc[z] / vol).ravel()
        frac = np.clip(area * zc[z] / (cell_area * dz[z]), 0.0, 1.0).ravel()
        qz = q[:, :, z].ravel()
        part = (frac > 1e-12) & (frac < 1.0 - 1e-12) & (qz > 0)
        Ps += [pz, np.zeros(int(part.sum()))]
        Qs += [np.where(part, qz * frac, qz), qz[part] * (1.0 - frac[part])]
        Cs += [np.full(len(pz), cnt), np.full(int(part.sum()), cnt)]
        p_in += cnt * float(pz.sum())
        q_in += cnt * float(qz.sum())
    if not Ps:
        return 0.0
    return S.jaccard(
        np.concatenate(Ps),
        np.concatenate(Qs),
        np.concatenate(Cs),
        p_outside=max(0.0, 1.0 - p_in),
        q_outside=max(0.0, q_total - q_in),
    )


def _box_samples(box: FloatArray, ref: FloatArray, quad: FloatArray, three_d: bool) -> "S.Samples":
    """A deterministic box as spatial's one-sample description (only its support is used: the grid)."""
    dz = box[2] - ref[2]
    z = np.array([[dz - box[5] / 2, dz + box[5] / 2]]) if three_d else None
    return S.Samples.single(np.zeros((1, 2)), np.zeros((1, 2, 2)), z, np.ones(1), quad)


def _window(grid: S.Grid, quads: list[FloatArray]) -> S.Grid:
    """The part of ``grid`` (same cell edges) covering every quad: the rows and columns their boxes touch."""
    pts = np.concatenate(quads)
    xe, ye = grid.x_edges, grid.y_edges
    i0 = max(0, int(np.searchsorted(xe, pts[:, 0].min(), side="right")) - 1)
    i1 = min(len(xe) - 1, int(np.searchsorted(xe, pts[:, 0].max(), side="left")))
    j0 = max(0, int(np.searchsorted(ye, pts[:, 1].min(), side="right")) - 1)
    j1 = min(len(ye) - 1, int(np.searchsorted(ye, pts[:, 1].max(), side="left")))
    return S.Grid(grid.ref, xe[i0 : i1 + 1], ye[j0 : j1 + 1], grid.z_edges)


_UNIT8 = np.array(
    [[0.5, -0.5, -0.5, 0.5, 0.5, -0.5, 0.0, 0.0], [0.5, 0.5, -0.5, -0.5, 0.0, 0.0, 0.5, -0.5]]
)  # BEV corners, then face midpoints


def _label_samples_bev(
    box: FloatArray, cov: FloatArray, params: SpatialParams
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The label's p_G samples in its own frame, as ``spatial.sample_boxes`` draws them (BEV, φ covariance).

    Returns axes (S, 2, 2), centres (S, 2), weights (S,) and the support bounds lo, hi (2,) — the mean
    corners ± ``support_std`` times the largest corner std; without the boundary statistics
    ``sample_boxes`` adds (a grid for deterministic detections does not need them).
    """
    c0, s0 = np.cos(box[6]), np.sin(box[6])
    Rt = np.array([[c0, s0], [-s0, c0]])
    T = np.zeros((6, 6))
    T[0:2, 0:2] = T[2:4, 2:4] = T[4:6, 4:6] = Rt
    z = S.normal_samples(6, params.num_samples, params.seed)
    phis = np.array([0.0, 0.0, box[3], 0.0, box[4], 0.0]) + z @ S.sqrt_psd(T @ cov @ T.T)
    n = len(phis)
    A = np.empty((n, 2, 2))
    A[:, 0, 0], A[:, 1, 0] = phis[:, 2], phis[:, 3]
    A[:, 0, 1], A[:, 1, 1] = -phis[:, 5], phis[:, 4]
    centres = np.ascontiguousarray(phis[:, :2])
    size = np.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
    ok = size > 1e-12 * max(float(np.max(size)), 1e-300)
    weights = np.where(ok, 1.0 / np.where(ok, size, 1.0), 0.0) / np.count_nonzero(ok)
    pts = np.matmul(A, _UNIT8[:, :4]) + centres[:, :, None]  # (S, 2, 4)
    mean = pts.mean(axis=0)
    dev = pts - mean
    corner_std = float(np.sqrt(np.max(np.einsum("sdk,sdk->k", dev, dev) / n)))
    lo = mean.min(axis=1) - params.support_std * corner_std
    hi = mean.max(axis=1) + params.support_std * corner_std
    return A, centres, weights, lo, hi


def _fast_bev_group(task: PairTask, g: int, rows: NDArray[np.int64], out: FloatArray) -> bool:
    """BEV label with a covariance and only deterministic detections (none equal to the label): the
    compiled path. Same samples and grid as :func:`_label_group`'s general path; False when it does not apply."""
    ref = task.gt_boxes[g]
    boxes = task.det_boxes[task.pair_det[rows]]
    if np.any(np.all(boxes == ref, axis=1)):
        return False  # the label box itself: its edges lie on the cell boundaries (spatial's special case)
    p = task.params
    A, cen, w, lo, hi = _label_samples_bev(ref, task.gt_cov[g], p)
    quads = [_grid_quad(b, ref) for b in boxes]
    pts = np.concatenate(quads)
    lo = np.minimum(lo, pts.min(axis=0))
    hi = np.maximum(hi, pts.max(axis=0))
    cell = min(max(ref[3], ref[4]), float(np.min(np.maximum(boxes[:, 3], boxes[:, 4])))) / max(
        float(p.cells_per_side), 1.0
    )
    grid = S.Grid(ref, S.axis_edges(ref[3] / 2, lo[0], hi[0], cell), S.axis_edges(ref[4] / 2, lo[1], hi[1], cell))
    win = _window(grid, quads)
    for k, (b, qd) in enumerate(zip(boxes, quads)):
        out[k] = _jiou_uniform_bev_kernel(A, cen, w, win.x_edges, win.y_edges, qd, b[3] * b[4], 1.0, C.SUBROWS_PER_CELL)
    return True


def _label_group(task: PairTask, g: int, rows: NDArray[np.int64]) -> FloatArray:
    """JIoU of label g with the detections of ``rows`` (indices into the task's pairs)."""
    p = task.params
    three_d = task.model == "3d"
    gcov = task.gt_cov[g]
    label_det = bool(np.isnan(gcov).any())
    out = np.empty(len(rows))
    if not label_det and not three_d and (task.det_cov is None or task.deterministic):
        if _fast_bev_group(task, g, rows, out):
            return out
    uniform: list[tuple[int, FloatArray]] = []  # (position, box) of deterministic detections
    spread: list[tuple[int, S.BoxDistribution]] = []  # probabilistic ones
    for k, r in enumerate(rows):
        j = task.pair_det[r]
        dcov = None if (task.det_cov is None or task.deterministic) else task.det_cov[j]
        if dcov is None or bool(np.isnan(dcov).any()):
            if label_det:
                out[k] = task.pair_iou[r]  # two uniform boxes: the Jaccard index is their IoU
            else:
                uniform.append((k, task.det_boxes[j]))
        else:
            spread.append((k, _dist(task.det_boxes[j], task.model, dcov, task.det_cov_on)))
    if not uniform and not spread:
        return out
    label = _dist(task.gt_boxes[g], task.model, None if label_det else gcov, "phi")
    ref = label.box
    sb = S.sample_boxes(label, ref, p)
    quads = [_grid_quad(b, ref) for _, b in uniform]
    s_uniform = [_box_samples(b, ref, qd, three_d) for (_, b), qd in zip(uniform, quads)]
    s_spread = [S.sample_boxes(d, ref, p) for _, d in spread]
    # as spatial.jiou: a deterministic box counts as sharp (blur 0) unless it is the reference itself
    blurs = [s.blur for s, (_, b) in zip(s_uniform, uniform) if not np.array_equal(b, ref)] + [s.blur for s in s_spread]
    if not label_det:
        blurs.append(sb.blur)
    blur = np.min(blurs, axis=0) if blurs else None
    boxes = [ref, *(b for _, b in uniform), *(d.box for _, d in spread)]
    grid = S.make_grid(ref, label.model, [sb, *s_uniform, *s_spread], p, boxes, blur)
    q_full = None
    if three_d and sb.z is not None:
        q_full = np.all(S.z_coverage(sb, grid.z_edges) >= np.diff(grid.z_edges) * (1 - 1e-9), axis=0)
    if uniform:
        # deterministic detections have no mass outside their boxes: the label is rasterised on
        # the window they cover only; the rest of its mass (total 1) enters through its sum
        win = _window(grid, quads)
        if not three_d:
            A = np.ascontiguousarray(sb.axes, dtype=np.float64)
            cen = np.ascontiguousarray(sb.centres, dtype=np.float64)
            w = np.ascontiguousarray(sb.weights, dtype=np.float64)
            for (k, b), qd in zip(uniform, quads):
                out[k] = _jiou_uniform_bev_kernel(
                    A, cen, w, win.x_edges, win.y_edges, qd, b[3] * b[4], 1.0, C.SUBROWS_PER_CELL
                )
        else:
            q = S.rasterise(sb, win)
            for k, b in uniform:
                out[k] = _uniform_jaccard(b, ref, win, q, q_full)
    if spread:
        q = S.rasterise(sb, grid)
        for (k, _d), sa in zip(spread, s_spread):
            if not three_d:
                out[k] = S.jaccard(S.rasterise(sa, grid), q)
            else:  # spatial's own pair rasteriser (merges the z-layers both cover completely)
                out[k] = S.jaccard(*S.pair_masses(sa, sb, grid))
    return out


def run_task(task: PairTask) -> FloatArray:
    """JIoU of every pair of a :class:`PairTask` (in the task's pair order)."""
    out = np.empty(len(task.pair_gt))
    if not len(out):
        return out
    starts = np.flatnonzero(np.r_[True, task.pair_gt[1:] != task.pair_gt[:-1]])
    ends = np.r_[starts[1:], len(out)]
    for a, b in zip(starts, ends):
        rows = np.arange(a, b)
        out[rows] = _label_group(task, int(task.pair_gt[a]), rows)
    return out


def pair_jious(
    model: str,
    params: SpatialParams,
    gt_boxes: FloatArray,
    gt_cov: FloatArray,
    det_boxes: FloatArray,
    det_cov: FloatArray | None,
    det_cov_on: str,
    pair_gt: Sequence[int],
    pair_det: Sequence[int],
    pair_iou: Sequence[float],
    *,
    deterministic: bool = False,
    workers: int | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> FloatArray:
    """JIoU of the pairs (pair_gt[k], pair_det[k]), computed once each.

    Parameters
    ----------
    model : "bev" or "3d"
    params : grid and sampling of p_G (the config's ``[spatial]``)
    gt_boxes : (G, 7) labels; gt_cov : (G, p, p) their φ covariances (NaN rows: none)
    det_boxes : (D, 7) detections; det_cov : (D, k, k) or None; det_cov_on : "phi" or "box"
    pair_gt, pair_det : (P,) indices; pair_iou : (P,) exact IoU of each pair's mean boxes
    deterministic : ignore the detections' covariances
    workers : processes (None: all cores; small batches always run in-process)
    progress : callback (pairs done, pairs total)

    Returns
    -------
    (P,) JIoU in [0, 1]
    """
    pg = np.asarray(pair_gt, dtype=np.int64)
    pd = np.asarray(pair_det, dtype=np.int64)
    piou = np.asarray(pair_iou, dtype=float)
    order = np.argsort(pg, kind="stable")
    out = np.empty(len(pg))
    if not len(pg):
        return out
    n_workers = workers if workers is not None else (os.cpu_count() or 1)
    n_chunks = 1 if (n_workers <= 1 or len(pg) < _MIN_PAIRS_FOR_POOL) else 8 * n_workers
    # cut at label boundaries so a label's raster is built once
    sg = pg[order]
    cuts = [0]
    for c in range(1, n_chunks):
        pos = int(np.searchsorted(sg, sg[min(len(sg) - 1, c * len(sg) // n_chunks)], side="left"))
        if pos > cuts[-1]:
            cuts.append(pos)
    cuts.append(len(sg))
    tasks = []
    for a, b in zip(cuts[:-1], cuts[1:]):
        idx = order[a:b]
        gsel, ginv = np.unique(pg[idx], return_inverse=True)
        dsel, dinv = np.unique(pd[idx], return_inverse=True)
        tasks.append(
            (
                idx,
                PairTask(
                    model,
                    params,
                    np.ascontiguousarray(gt_boxes[gsel]),
                    np.ascontiguousarray(gt_cov[gsel]),
                    np.ascontiguousarray(det_boxes[dsel]),
                    None if det_cov is None else np.ascontiguousarray(det_cov[dsel]),
                    det_cov_on,
                    ginv.astype(np.int64),
                    dinv.astype(np.int64),
                    piou[idx],
                    deterministic,
                    len(tasks),
                ),
            )
        )
    done = 0
    if len(tasks) == 1:
        out[tasks[0][0]] = run_task(tasks[0][1])
        if progress:
            progress(len(pg), len(pg))
        return out
    from labelaudit.executors import make_executor

    executor = make_executor(n_workers, C.EVAL_WORKER_PRELOAD)
    try:
        for batch, values in executor.run([t for _, t in tasks], _run_batch):
            out[tasks[batch][0]] = values
            done += len(values)
            if progress:
                progress(done, len(pg))
    finally:
        executor.close()
    return out


def _run_batch(task: PairTask) -> tuple[int, FloatArray]:
    return task.batch, run_task(task)

"""What the frame around each labelled box says: its crops, local ground, neighbours and rays.

For the boxes of one frame (docs/label-error.md, "Ground, neighbours and free space"):

- **crops.** One compiled pass sorts the frame's points by azimuth
  (:func:`labelaudit.core.freespace.azimuth_buckets`); each box's *neighbourhood* (the box grown in
  bird's-eye view by the largest margin used below, from ``GROUND_WINDOW`` under its bottom to τ
  over its top) is taken from its azimuth window. The model's crop (``[crop] margin`` and the fixed
  ``ground_cut`` above the box bottom, what the covariance and JIoU-GT see) is taken from it with
  Open3D's own arithmetic (:func:`_open3d_inside`, the operations of
  :func:`labelaudit.infer.crop.refine_crop`: the indices of Open3D's ``OrientedBoundingBox``
  selection, bit for bit); the label-error fit's crop (``[crop]
  fit_margin``) is cut at ``ground_cut`` above the *local ground*.
- **ground.** A plane fitted to the neighbourhood's points near the box bottom by RANSAC with a
  fixed seed and a least-squares refit (:func:`ground_plane`); when too few points support one,
  the box bottom (the fixed cut). Sloped roads and labels with a wrong bottom then neither feed
  ground returns into the fit nor cut the vehicle's lower body.
- **neighbours.** Points inside another label of the frame (grown by ``NEIGHBOUR_MARGIN``) and
  outside the box itself are that label's evidence: they are dropped from the fit's crop and
  from the model's crop where its margin reaches them.
- **unlabelled surfaces.** A wall, hedge or fence beside a vehicle is not its evidence either: the
  points of a connected surface (BEV cells of ``SCENERY_VOXEL``) that lies wholly outside the label
  (more than ``NEIGHBOUR_MARGIN`` from it) and runs out of the fit's crop are dropped from the
  fit's crop (:func:`scenery_mask`). An object's own points always reach into its label unless
  the label misses it entirely.
- **rays.** The rays of the frame that can pass through each box's solid lower body
  (:func:`labelaudit.core.freespace.ray_candidates`), with the ground they are measured from.

Pure functions of arrays: no files, no printing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.config import CropParams
from labelaudit.core.freespace import (
    FreeSpace,
    azimuth_buckets,
    behind_other_returns,
    neighbourhood_parts,
    passing_parts,
    ray_candidate_parts,
    through_own_returns,
)
from labelaudit.core.geometry import rotation_z
from labelaudit.infer.crop import selection_boxes
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

__all__ = [
    "BoxEvidence",
    "ObjectEvidence",
    "fit_free_space",
    "frame_evidence",
    "ground_plane",
    "label_boxes",
    "scenery_mask",
]


def fit_free_space(class_name: str, free_space: FreeSpace | None) -> FreeSpace | None:
    """The rays the label-error fit of a ``class_name`` box uses: vehicles' (:data:`~labelaudit.constants.FREE_SPACE_CLASSES`)
    only — a pedestrian's, a bike's or a Misc box is mostly open space (their rays are only counted)."""
    return free_space if class_name in C.FREE_SPACE_CLASSES else None


def label_boxes(boxes: NDArray) -> FloatArray:
    """The labels of a frame that can own points (finite, positive sizes), whatever their class:
    the ``others`` of :func:`frame_evidence`."""
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    ok = np.all(np.isfinite(b), axis=1) & np.all(b[:, 3:6] > 0, axis=1)
    return b[ok]


@dataclass(frozen=True)
class ObjectEvidence:
    """What :func:`labelaudit.infer.rows.audit_object` needs beyond the crops: the rays, the
    neighbourhood's points (N, ≥3) for the "ends on or in" counts, and two diagnostics."""

    free_space: FreeSpace
    near_points: NDArray
    neighbour_points: int = 0
    ground_z: float = float("nan")
    scenery_points: int = 0
    through_rays: int = 0


@dataclass(frozen=True)
class BoxEvidence:
    """One box's crops and surroundings, as indices into the frame's points.

    Attributes
    ----------
    model_idx : the model's crop (``margin``, fixed ground cut), neighbours' points dropped
    fit_idx : the label-error fit's crop (``fit_margin``, cut above the local ground), neighbours dropped
    near_idx : the neighbourhood (every point that can end on or in the box or its fit)
    free_space : the rays that may cross the box, and its local ground
    ground_z : local ground height under the box centre (m); NaN when the fixed cut was used
    neighbour_points : points dropped from the fit's crop because they lie in another label
    scenery_points : points dropped from the fit's crop because they belong to an unlabelled
        surface outside the label that runs out of the crop
    through_rays : rays through the box's slab that passed beyond its own returns (see-through:
        under a chassis, through glass), left out of ``free_space``
    near_xyz : the neighbourhood's points (n, 3) float64, ``points[near_idx, :3]`` converted
        exactly (gathered once for the crops); None: gathered from the frame when needed
    model_pts : the model's crop as the posterior takes it, ``clean_points(points[model_idx],
        model_dim)`` (m, model_dim) float64, from the same pass; None: not made
    fit_cols : the fit's crop as the fit takes it, ``clean_columns(points[fit_idx], 3)`` (3, f)
        float64, from the same pass; None: not made
    """

    model_idx: IndexArray
    fit_idx: IndexArray
    near_idx: IndexArray
    free_space: FreeSpace
    ground_z: float
    neighbour_points: int
    scenery_points: int = 0
    through_rays: int = 0
    near_xyz: FloatArray | None = None
    model_pts: FloatArray | None = None
    fit_cols: FloatArray | None = None

    def for_object(self, points: NDArray) -> ObjectEvidence:
        """The :class:`ObjectEvidence` of this box, given the frame's points (its neighbourhood's
        xyz when :func:`frame_evidence` kept them: the counts read x, y, z only)."""
        return ObjectEvidence(
            self.free_space,
            points[self.near_idx] if self.near_xyz is None else self.near_xyz,
            self.neighbour_points,
            self.ground_z,
            self.scenery_points,
            self.through_rays,
        )


def _box_evidence(*values: object) -> BoxEvidence:
    """A :class:`BoxEvidence` of its fields in order, made in one step: the frozen dataclass'
    ``__init__`` sets each field through ``object.__setattr__`` (a few µs per box)."""
    ev = object.__new__(BoxEvidence)
    ev.__dict__.update(zip(_BOX_EVIDENCE_FIELDS, values))
    return ev


_BOX_EVIDENCE_FIELDS = tuple(f.name for f in fields(BoxEvidence))


def frame_evidence(
    points: NDArray,
    boxes: NDArray,
    origin: NDArray,
    crop: CropParams,
    others: NDArray | None = None,
    ray_mask: NDArray | None = None,
    model_dim: int = 3,
) -> list[BoxEvidence]:
    """Crops, local ground, neighbours and candidate rays of every box of a frame.

    Parameters
    ----------
    points : (N, ≥3) the frame's points
    boxes : (K, 7) the boxes to audit (valid boxes)
    origin : (3,) the sensor
    crop : margins and ground cut
    others : (J, 7) every label of the frame whose points are not this box's evidence (default:
        ``boxes``); a box is never its own neighbour (rows equal to it are skipped)
    ray_mask : (N,) bool, the points that end an empty ray from ``origin``
        (:attr:`~labelaudit.datasets.Frame.ray_mask`); None = all. Only they count as rays; every
        point is still in the crops
    model_dim : the point dimension of the model's crop rows handed out
        (:attr:`BoxEvidence.model_pts`): 2 for a BEV model, 3 for a 3D one

    Returns
    -------
    one :class:`BoxEvidence` per box
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    if len(b) == 0:
        return []
    others = b if others is None else np.asarray(others, dtype=float).reshape(-1, 7)
    # a copy of a label adds nothing to "inside another label" (label files with repeated lines);
    # which copy is kept, and in which order, changes no flag (a point is foreign when any label holds it)
    others = np.array(list(dict.fromkeys(map(tuple, others.tolist()))), dtype=float).reshape(-1, 7)
    tau = C.FREE_SPACE_TOLERANCE
    tau_in = C.FREE_SPACE_INSIDE_TOLERANCE
    wide = max(crop.fit_margin, crop.margin, C.GROUND_MARGIN, tau)
    # one pass sorts the frame's points by azimuth; every box's neighbourhood and rays come from its window
    buckets = azimuth_buckets(points, origin, b, max(wide, C.FREE_SPACE_REACH))
    sel = selection_boxes(b, crop.margin, crop.ground_cut)  # the model's crop regions, as Open3D sees them
    rotations = rotation_z(sel[:, 6])
    slabs = np.stack([np.full(len(b), C.FREE_SPACE_SLAB[0]), C.FREE_SPACE_SLAB[1] * b[:, 5]], 1)
    o = np.asarray(origin, dtype=float).reshape(3)
    mask = None if ray_mask is None else np.asarray(ray_mask, dtype=bool)
    ox, oy = float(o[0]), float(o[1])
    out: list[BoxEvidence] = []
    for j0 in range(0, len(b), _BATCH):  # batches bound the buffers in frames of thousands of boxes
        bb = b[j0 : j0 + _BATCH]
        # each neighbourhood's indices and its points as float64 (converted exactly), gathered once
        near = neighbourhood_parts(buckets, bb, wide, C.GROUND_WINDOW, tau, first=j0)
        # the other labels the fit margins of these boxes can reach (never the box itself)
        reach = (
            np.hypot(bb[:, 3], bb[:, 4])[:, None] / 2
            + np.hypot(others[:, 3], others[:, 4])[None, :] / 2
            + crop.fit_margin
            + C.NEIGHBOUR_MARGIN
        )
        close = np.hypot(bb[:, None, 0] - others[None, :, 0], bb[:, None, 1] - others[None, :, 1]) <= reach
        close &= ~np.all(bb[:, None, :] == others[None, :, :], axis=2)
        # every box's local ground and both crops, in one compiled call
        grounds = np.empty((len(bb), 3))
        found = np.zeros(len(bb), dtype=np.bool_)
        counts = np.zeros((len(bb), 6), dtype=np.int64)
        model_flat, fit_flat, model_rows, fit_cols = _crops_kernel(
            near.xyz,
            near.idx,
            near.starts,
            bb,
            others,
            close,
            crop.fit_margin,
            crop.ground_cut,
            C.NEIGHBOUR_MARGIN,
            C.SCENERY_VOXEL,
            sel[j0 : j0 + _BATCH],
            rotations[j0 : j0 + _BATCH],
            *_ground_args(),
            grounds,
            found,
            counts,
            model_dim,
        )
        rays = ray_candidate_parts(buckets, bb, grounds, slabs[j0 : j0 + _BATCH], o, C.FREE_SPACE_REACH, first=j0)
        ends, starts = rays.xyz, rays.starts
        if mask is not None:  # e.g. Waymo: other lidars and second returns are no rays from the origin
            keep = mask[rays.idx]
            ends = ends[keep]
            starts = np.concatenate([[0], np.cumsum(keep)])[starts]
        # every box's rays in the kernels' layout, and the ones that pass through its slab
        crossing = passing_parts(bb, ends, starts, grounds, slabs[j0 : j0 + _BATCH], o, tau, crop.ground_cut)
        ground_z = np.where(found, grounds[:, 0], np.nan).tolist()
        planes = np.zeros((len(bb), 4))  # (g0, gx, gy, unused)
        planes[:, :3] = grounds
        # where each box's crops start in the flat outputs: model, fit, model rows, fit columns
        at = np.zeros((len(bb) + 1, 4), dtype=np.int64)
        np.cumsum(counts[:, :4], axis=0, out=at[1:])
        s_near, s_ray, at_l = near.starts.tolist(), starts.tolist(), at.tolist()
        ends_t, hz = crossing.ends_t, crossing.hz
        for j, (box, slab, (n_foreign, n_scenery), seen) in enumerate(
            zip(bb, slabs[j0 : j0 + _BATCH].tolist(), counts[:, 4:].tolist(), crossing.any_passing.tolist())
        ):
            r0, r1 = s_ray[j], s_ray[j + 1]
            fs = FreeSpace.with_kernel_inputs(
                o,
                ends[r0:r1],
                planes[j],
                box[:2].copy(),
                (slab[0], slab[1]),
                tau,
                tau_in,
                crop.ground_cut,
                (ends_t[3 * r0 : 3 * r1].reshape(3, r1 - r0), ox, oy, hz[j]),
            )
            near_xyz = near.xyz[s_near[j] : s_near[j + 1]]
            # rays that passed beyond the box's own returns saw through the object (under its chassis,
            # through glass), and second returns went on through something nearer: not empty space inside the box
            n_through = 0
            if seen:  # most right labels have no ray through them at all
                own = _own_returns(near_xyz, box, planes[j], tau, crop.ground_cut)
                passing = (crossing.passing[r0:r1], crossing.reach[r0:r1])
                through = through_own_returns(box, fs, own, C.FREE_SPACE_SIGHT_ANGLE, passing) | behind_other_returns(
                    box, fs, buckets, C.FREE_SPACE_SAME_RAY_ANGLE, passing
                )
                n_through = int(np.count_nonzero(through))
                if n_through:
                    fs = replace(fs, ends=fs.ends[~through])
            m0, f0, mr0, fc0 = at_l[j]
            m1, f1, mr1, fc1 = at_l[j + 1]
            out.append(
                _box_evidence(
                    model_flat[m0:m1],
                    fit_flat[f0:f1],
                    near.idx[s_near[j] : s_near[j + 1]],
                    fs,
                    ground_z[j],
                    n_foreign,
                    n_scenery,
                    n_through,
                    near_xyz,
                    model_rows[mr0:mr1],
                    fit_cols[3 * fc0 : 3 * fc1].reshape(3, fc1 - fc0),
                )
            )
    return out


@kernel
def _crops_kernel(
    xyz,
    idx,
    starts,
    boxes,
    others,
    close,
    fit_margin,
    cut,
    nb_margin,
    cell,
    sel,
    R,
    draws,
    scored,
    g_margin,
    g_window,
    g_inlier,
    g_min_points,
    g_max_slope,
    grounds,
    found,
    counts,
    dim,
):  # pragma: no cover - compiled
    """Every box's local ground (:func:`ground_plane`; the box bottom where none is found) and crops
    (:func:`_box_crops` against the other labels ``close`` to it) from its neighbourhood, the part
    ``starts[j]:starts[j + 1]`` of ``xyz`` (n, 3) and ``idx`` (n,): the grounds (B, 3), whether
    each was found (B,), per box (model crop size, fit crop size, the model crop's rows with ``dim``
    finite coordinates, the fit crop's rows with 3, foreign points, scenery points) (B, 6), the
    model's and the fit's crops, box after box (flat), and the same crops as the model's passes
    take them: the model crop's finite rows' first ``dim`` coordinates (flat (·, dim)) and the fit
    crop's finite rows as (3, f) columns, box after box (flat)
    (:func:`~labelaudit.core.geometry.clean_points` and ``clean_columns`` of the gathered rows)."""
    n_all = xyz.shape[0]
    model_flat = np.empty(n_all, dtype=np.int64)
    fit_flat = np.empty(n_all, dtype=np.int64)
    model_rows = np.empty((n_all, dim))
    fit_cols = np.empty(3 * n_all)
    r = q = 0
    near = np.empty((others.shape[0], 7))
    plane = np.empty(3)
    a = c = 0
    for j in range(boxes.shape[0]):
        box = boxes[j]
        s, e = starts[j], starts[j + 1]
        pts = xyz[s:e]
        if _ground_kernel(pts, box, draws, scored, g_margin, g_window, g_inlier, g_min_points, g_max_slope, plane):
            grounds[j, 0], grounds[j, 1], grounds[j, 2] = plane[0], plane[1], plane[2]
            found[j] = True
        else:
            grounds[j, 0], grounds[j, 1], grounds[j, 2] = box[2] - box[5] / 2, 0.0, 0.0
        m = 0
        for i in range(others.shape[0]):
            if close[j, i]:
                for f in range(7):
                    near[m, f] = others[i, f]
                m += 1
        model_idx, fit_idx, n_foreign, n_scenery, model_k, fit_k = _box_crops(
            pts,
            idx[s:e],
            box,
            grounds[j],
            near[:m],
            fit_margin,
            cut,
            nb_margin,
            cell,
            sel[j],
            R[j],
            sel[j, 5] > 0,
        )
        model_flat[a : a + model_idx.shape[0]] = model_idx
        fit_flat[c : c + fit_idx.shape[0]] = fit_idx
        a += model_idx.shape[0]
        c += fit_idx.shape[0]
        r0 = r
        for k in model_k:  # the crop's rows in its order, the finite ones (clean_points)
            ok = True
            for t in range(dim):
                ok = ok and math.isfinite(pts[k, t])
            if ok:
                for t in range(dim):
                    model_rows[r, t] = pts[k, t]
                r += 1
        f = 0
        for k in fit_k:  # clean_columns: the finite rows' x, y, z as columns
            if math.isfinite(pts[k, 0]) and math.isfinite(pts[k, 1]) and math.isfinite(pts[k, 2]):
                f += 1
        i = 0
        for k in fit_k:
            if math.isfinite(pts[k, 0]) and math.isfinite(pts[k, 1]) and math.isfinite(pts[k, 2]):
                fit_cols[q + i], fit_cols[q + f + i], fit_cols[q + 2 * f + i] = pts[k, 0], pts[k, 1], pts[k, 2]
                i += 1
        q += 3 * f
        counts[j, 0], counts[j, 1], counts[j, 2], counts[j, 3], counts[j, 4], counts[j, 5] = (
            model_idx.shape[0],
            fit_idx.shape[0],
            r - r0,
            f,
            n_foreign,
            n_scenery,
        )
    return model_flat[:a], fit_flat[:c], model_rows[:r], fit_cols[:q]


def _own_returns(xyz: FloatArray, box: FloatArray, plane: FloatArray, tau: float, cut: float) -> FloatArray:
    """The box's own returns among its neighbourhood's points (n, 3): within τ of its rectangle in
    bird's-eye view, at least ``cut`` above its ground plane, at most τ over its top (the returns
    ``ray_counts`` takes for ending on or in it)."""
    return _own_returns_kernel(xyz, box, plane, math.cos(box[6]), math.sin(box[6]), tau, cut)


@kernel
def _own_returns_kernel(xyz, box, plane, c, s, tau, cut):  # pragma: no cover - compiled
    """:func:`_own_returns` in one pass: the same float64 operations per point as its NumPy form
    (the rotated offsets, :func:`~labelaudit.core.freespace.ground_heights`), no temporaries."""
    n = xyz.shape[0]
    keep = np.zeros(n, dtype=np.bool_)
    hl, hw, top = box[3] / 2 + tau, box[4] / 2 + tau, box[2] + box[5] / 2 + tau
    m = 0
    for k in range(n):
        x, y, z = xyz[k, 0], xyz[k, 1], xyz[k, 2]
        qx, qy = x - box[0], y - box[1]
        h = z - (plane[0] + plane[1] * (x - box[0]) + plane[2] * (y - box[1]))
        if abs(c * qx + s * qy) <= hl and abs(-s * qx + c * qy) <= hw and h >= cut and z <= top:
            keep[k] = True
            m += 1
    out = np.empty((m, 3))
    i = 0
    for k in range(n):
        if keep[k]:
            out[i, 0], out[i, 1], out[i, 2] = xyz[k, 0], xyz[k, 1], xyz[k, 2]
            i += 1
    return out


@kernel
def _box_crops(
    xyz, idx, box, plane, others, fit_margin, cut, nb_margin, cell, sel, R, with_model
):  # pragma: no cover - compiled
    """One box's crops from its neighbourhood (n, 3) and indices ``idx`` (n,): the model's crop
    (:func:`_open3d_inside` of the selection box ``sel``, rotation ``R``; none unless ``with_model``)
    without other labels' points, the fit's crop (:func:`_box_kernel`), the number of points
    dropped from the fit's crop as another label's and as unlabelled surfaces, and both crops'
    positions in the neighbourhood."""
    n = xyz.shape[0]
    flags = np.zeros(n, dtype=np.uint8)
    _box_kernel(xyz, box, plane, others, fit_margin, cut, nb_margin, cell, flags)
    inside = _open3d_inside(xyz, sel, R) if with_model else np.zeros(n, dtype=np.bool_)
    n_model = n_fit = n_foreign = n_scenery = 0
    for k in range(n):
        f = flags[k]
        if inside[k] and not (f & 2):
            n_model += 1
        if f & 1:
            n_fit += 1
        if f & 4:
            n_foreign += 1
        if f & 8:
            n_scenery += 1
    model_idx = np.empty(n_model, dtype=np.int64)
    fit_idx = np.empty(n_fit, dtype=np.int64)
    model_k = np.empty(n_model, dtype=np.int64)
    fit_k = np.empty(n_fit, dtype=np.int64)
    a = c = 0
    for k in range(n):
        f = flags[k]
        if inside[k] and not (f & 2):
            model_idx[a] = idx[k]
            model_k[a] = k
            a += 1
        if f & 1:
            fit_idx[c] = idx[k]
            fit_k[c] = k
            c += 1
    return model_idx, fit_idx, n_foreign, n_scenery, model_k, fit_k


_FIT, _FOREIGN, _FIT_FOREIGN, _FIT_SCENERY = 1, 2, 4, 8  # flags of _box_kernel


@kernel
def _open3d_inside(xyz, sel, R):  # pragma: no cover - compiled
    """Open3D's ``OrientedBoundingBox`` test of points (n, 3) float64 against the selection box
    ``sel`` (7,) with rotation ``R`` (3, 3): ``|(p − c)·R[:, a]| ≤ extent_a / 2``, the dot summed
    left to right — the float64 operations of :func:`labelaudit.infer.crop.refine_crop` in the same
    order (no fast-math), so the same indices as Open3D (tested), in one pass."""
    n = xyz.shape[0]
    out = np.empty(n, dtype=np.bool_)
    for k in range(n):
        d0, d1, d2 = xyz[k, 0] - sel[0], xyz[k, 1] - sel[1], xyz[k, 2] - sel[2]
        ok = True
        for a in range(3):
            proj = d0 * R[0, a] + d1 * R[1, a] + d2 * R[2, a]
            if not abs(proj) <= sel[3 + a] / 2.0:
                ok = False
                break
        out[k] = ok
    return out


_BATCH = (
    256  # boxes per batch of the neighbour search (bounds its (batch, labels) arrays in frames of thousands of boxes)
)


@kernel
def _box_kernel(xyz, box, plane, others, fit_margin, cut, nb_margin, cell, flags):  # pragma: no cover - compiled
    """One box's pass over its neighbourhood (n, 3): the fit's crop (in the fit margin, ``cut``
    above the local ground, under the box top), points of other labels (grown by ``nb_margin``)
    outside the box itself, and unlabelled surfaces (:func:`scenery_mask`); flags (n,) of
    _FIT / _FOREIGN / _FIT_FOREIGN / _FIT_SCENERY. Compiled: per box a dozen NumPy passes over the
    neighbourhood cost more than the rest of the frame's evidence."""
    n = xyz.shape[0]
    c, s = math.cos(box[6]), math.sin(box[6])
    hl, hw, top = 0.5 * box[3], 0.5 * box[4], box[2] + 0.5 * box[5]
    lx = np.empty(n)
    ly = np.empty(n)
    above = np.zeros(n, dtype=np.bool_)
    # cos/sin of each other label, computed on first use (the same scalar calls, once per label, not per point)
    o_cos = np.empty(others.shape[0])
    o_sin = np.empty(others.shape[0])
    o_have = np.zeros(others.shape[0], dtype=np.bool_)
    m = 0
    for k in range(n):
        dx, dy = xyz[k, 0] - box[0], xyz[k, 1] - box[1]
        x, y, z = c * dx + s * dy, -s * dx + c * dy, xyz[k, 2]
        lx[k], ly[k] = x, y
        h = z - (plane[0] + plane[1] * dx + plane[2] * dy)
        above[k] = h >= cut and z <= top
        in_fit = above[k] and abs(x) <= hl + fit_margin and abs(y) <= hw + fit_margin
        own = abs(x) <= hl and abs(y) <= hw and abs(z - box[2]) <= 0.5 * box[5]
        foreign = False
        if not own:
            for j in range(others.shape[0]):
                o = others[j]
                if not o_have[j]:
                    o_cos[j], o_sin[j] = math.cos(o[6]), math.sin(o[6])
                    o_have[j] = True
                co, so = o_cos[j], o_sin[j]
                ex, ey = xyz[k, 0] - o[0], xyz[k, 1] - o[1]
                if (
                    abs(co * ex + so * ey) <= 0.5 * o[3] + nb_margin
                    and abs(-so * ex + co * ey) <= 0.5 * o[4] + nb_margin
                    and abs(z - o[2]) <= 0.5 * o[5]
                ):
                    foreign = True
                    break
        f = 0
        if foreign:
            f |= 2
            if in_fit:
                f |= 4
        elif in_fit:
            f |= 1
        flags[k] = f
        if above[k]:
            m += 1
    # unlabelled surfaces among the points above the ground
    sel = np.empty(m, dtype=np.int64)
    q = 0
    for k in range(n):
        if above[k]:
            sel[q] = k
            q += 1
    sc = _scenery(lx[sel], ly[sel], hl, hw, fit_margin, nb_margin, cell)
    for q in range(m):
        k = sel[q]
        if sc[q] and (flags[k] & 1):
            flags[k] = (flags[k] & ~1) | 8


@kernel
def _scenery(lx, ly, hl, hw, fit_margin, nb_margin, cell):  # pragma: no cover - compiled
    """The rule of :func:`scenery_mask` on box-frame BEV coordinates (n,)."""
    n = lx.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    if n == 0:
        return out
    lab = _cell_labels(lx, ly, cell)
    k = lab.max() + 1
    touches = np.zeros(k, dtype=np.bool_)
    for i in range(n):
        if abs(lx[i]) <= hl + nb_margin and abs(ly[i]) <= hw + nb_margin:
            touches[lab[i]] = True
    free = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if not touches[lab[i]]:
            free[m] = i
            m += 1
    if m == 0:
        return out
    fx, fy = lx[free[:m]], ly[free[:m]]
    grp = _cell_labels(fx, fy, 4.0 * cell)
    escapes = np.zeros(grp.max() + 1, dtype=np.bool_)
    for i in range(m):
        if abs(fx[i]) > hl + fit_margin or abs(fy[i]) > hw + fit_margin:
            escapes[grp[i]] = True
    for i in range(m):
        out[free[i]] = escapes[grp[i]]
    return out


@kernel
def _cell_labels(lx, ly, cell):  # pragma: no cover - compiled
    n = lx.shape[0]
    ijk = np.zeros((n, 3), dtype=np.int64)
    for i in range(n):
        ijk[i, 0] = int(math.floor(lx[i] / cell))
        ijk[i, 1] = int(math.floor(ly[i] / cell))
    i0, j0 = ijk[:, 0].min(), ijk[:, 1].min()
    for i in range(n):
        ijk[i, 0] -= i0
        ijk[i, 1] -= j0
    dims = np.array([ijk[:, 0].max() + 1, ijk[:, 1].max() + 1, 1])
    return _voxel_components(ijk, dims)


def _local(xyz: FloatArray, box: FloatArray) -> tuple[FloatArray, FloatArray]:
    c, s = math.cos(box[6]), math.sin(box[6])
    dx, dy = xyz[:, 0] - box[0], xyz[:, 1] - box[1]
    return c * dx + s * dy, -s * dx + c * dy


def ground_plane(xyz: FloatArray, box: FloatArray) -> FloatArray | None:
    """The local ground under a box: (g0, gx, gy) of ``z = g0 + gx (x − cx) + gy (y − cy)``, or None.

    Candidates are the points within ``GROUND_MARGIN`` of the box in BEV but outside its footprint
    (the vehicle's own lower body is not ground), between ``GROUND_WINDOW`` under its bottom and
    half that over it. RANSAC: ``GROUND_HYPOTHESES`` planes through three candidates drawn from a
    fixed table of uniform numbers (so a box always gets the same plane) plus as many level planes
    through single candidates, slopes above ``GROUND_MAX_SLOPE`` rejected; the plane with the most
    candidates within ``GROUND_INLIER`` wins and is refitted to its inliers by least squares (the
    slope only when they span ≥ 1 m both ways, else a level plane at their median), then once more
    to the points within half that distance (the foot of a wall or a wheel is not ground). None
    when fewer than ``GROUND_MIN_POINTS`` points support it (the caller falls back to the box
    bottom).

    Open3D's ``segment_plane`` was measured first: ~3.5 ms per box (more than the rest of the
    per-object audit) and not reproducible from call to call (its RANSAC draws are not fixed by
    ``open3d.utility.random.seed``), and rows must be identical run to run. This is one compiled
    call (:func:`_ground_kernel`), ~0.05 ms.
    """
    out = np.empty(3)
    ok = _ground_kernel(
        np.ascontiguousarray(xyz, dtype=np.float64),
        np.asarray(box, dtype=float),
        *_ground_args(),
        out,
    )
    return out if ok else None


_GROUND_DRAWS = np.random.default_rng(0).random((C.GROUND_HYPOTHESES, 4))
"""Fixed uniform numbers of the RANSAC draws: three points and one level plane per hypothesis."""


def _ground_args() -> tuple:
    """The ground fit's fixed inputs, in the order its kernels take them (read at call time)."""
    return (
        _GROUND_DRAWS,
        C.GROUND_SCORED,
        C.GROUND_MARGIN,
        C.GROUND_WINDOW,
        C.GROUND_INLIER,
        C.GROUND_MIN_POINTS,
        C.GROUND_MAX_SLOPE,
    )


@kernel
def _ground_kernel(
    xyz, box, draws, scored, margin, window, inlier, min_points, max_slope, out
):  # pragma: no cover - compiled
    c, s = math.cos(box[6]), math.sin(box[6])
    hl, hw = 0.5 * box[3], 0.5 * box[4]
    bottom = box[2] - 0.5 * box[5]
    n_all = xyz.shape[0]
    cand = np.empty((n_all, 3))
    n = 0
    for k in range(n_all):
        dx, dy = xyz[k, 0] - box[0], xyz[k, 1] - box[1]
        lx, ly = abs(c * dx + s * dy), abs(-s * dx + c * dy)
        z = xyz[k, 2]
        if (
            lx > hl + margin
            or ly > hw + margin
            or (lx <= hl and ly <= hw)
            or z < bottom - window
            or z > bottom + 0.5 * window
        ):
            continue
        cand[n, 0], cand[n, 1], cand[n, 2] = dx, dy, z
        n += 1
    if n < min_points:
        return False
    stride = max(1, n // scored)
    ns = (
        n + stride - 1
    ) // stride  # the scored candidates, copied contiguous so the count loops vectorise (integer counts: exact)
    sx, sy, sz = np.empty(ns), np.empty(ns), np.empty(ns)
    for t in range(ns):
        sx[t], sy[t], sz[t] = cand[t * stride, 0], cand[t * stride, 1], cand[t * stride, 2]
    best_count, bg0, bgx, bgy = -1, 0.0, 0.0, 0.0
    for h in range(draws.shape[0]):
        for level in range(2):
            if level == 0:
                i0, i1, i2 = int(draws[h, 0] * n), int(draws[h, 1] * n), int(draws[h, 2] * n)
                ux, uy, uz = cand[i1, 0] - cand[i0, 0], cand[i1, 1] - cand[i0, 1], cand[i1, 2] - cand[i0, 2]
                vx, vy, vz = cand[i2, 0] - cand[i0, 0], cand[i2, 1] - cand[i0, 1], cand[i2, 2] - cand[i0, 2]
                nx, ny, nz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx
                if nz == 0.0:
                    continue
                gx, gy = -nx / nz, -ny / nz
                if math.hypot(gx, gy) > max_slope:
                    continue
                g0 = cand[i0, 2] - gx * cand[i0, 0] - gy * cand[i0, 1]
            else:
                i0 = int(draws[h, 3] * n)
                gx = gy = 0.0
                g0 = cand[i0, 2]
            count = 0
            for t in range(ns):
                if abs(sz[t] - (g0 + gx * sx[t] + gy * sy[t])) < inlier:
                    count += 1
            if count > best_count:
                best_count, bg0, bgx, bgy = count, g0, gx, gy
    plane = np.array([bg0, bgx, bgy])
    for rnd in range(2):
        thr = inlier if rnd == 0 else 0.5 * inlier
        # inlier moments for the least-squares plane z = g0 + gx·x + gy·y
        m = 0
        sx = sy = sz = sxx = sxy = syy = sxz = syz = 0.0
        zs = np.empty(n)
        for k in range(n):
            x, y, z = cand[k, 0], cand[k, 1], cand[k, 2]
            if abs(z - (plane[0] + plane[1] * x + plane[2] * y)) < thr:
                zs[m] = z
                m += 1
                sx += x
                sy += y
                sz += z
                sxx += x * x
                sxy += x * y
                syy += y * y
                sxz += x * z
                syz += y * z
        if m < min_points:
            return False
        mx, my, mz = sx / m, sy / m, sz / m
        cxx, cxy, cyy = sxx / m - mx * mx, sxy / m - mx * my, syy / m - my * my
        cxz, cyz = sxz / m - mx * mz, syz / m - my * mz
        det = cxx * cyy - cxy * cxy
        tr = cxx + cyy
        lam_min = 0.5 * tr - math.sqrt(max(0.25 * tr * tr - det, 0.0))  # smaller eigenvalue of the xy covariance
        solved = False
        if lam_min >= 0.25 and det > 0.0:  # the inliers span ≥ ~1 m both ways: the slope is observable
            gx = (cyy * cxz - cxy * cyz) / det
            gy = (cxx * cyz - cxy * cxz) / det
            if math.hypot(gx, gy) <= max_slope:
                plane[0], plane[1], plane[2] = mz - gx * mx - gy * my, gx, gy
                solved = True
        if not solved:
            plane[0], plane[1], plane[2] = np.median(zs[:m]), 0.0, 0.0
    out[0], out[1], out[2] = plane[0], plane[1], plane[2]
    return True


def scenery_mask(xyz: FloatArray, box: FloatArray, fit_margin: float) -> NDArray[np.bool_]:
    """Points (N, 3) of the neighbourhood (above the ground) that belong to an unlabelled surface.

    The points are grouped into connected components of occupied ``SCENERY_VOXEL`` cells of the
    bird's-eye view (8 neighbours, in the box frame; the points are those between the local ground
    cut and the box top, so the ground does not connect everything). A component *touches* the
    label when one of its points lies within ``NEIGHBOUR_MARGIN`` of it in BEV. The components that
    do not touch are grouped again with cells four times as large (a wall seen at a grazing angle
    returns points ~0.7 m apart), and a
    group is scenery when one of its points lies outside the fit's crop (the label grown by
    ``fit_margin``): a surface that passes beside the label and runs on beyond the crop. Points of
    touching components are never scenery, whatever lies near them.
    """
    lx, ly = _local(np.asarray(xyz, dtype=float), box)
    return _scenery(lx, ly, box[3] / 2, box[4] / 2, fit_margin, C.NEIGHBOUR_MARGIN, C.SCENERY_VOXEL)


@kernel
def _voxel_components(ijk, dims):  # pragma: no cover - compiled
    """Connected-component label (N,) of every point's voxel (26-connectivity; 8 in a single layer), by flood fill on a
    dense grid of the points' bounding voxels (a BFS has no NumPy form; scipy.ndimage would be one
    more import in every worker)."""
    nx, ny, nz = dims[0], dims[1], dims[2]
    grid = np.full(nx * ny * nz, -2, dtype=np.int64)  # −2 empty, −1 occupied, ≥ 0 component
    flat = np.empty(ijk.shape[0], dtype=np.int64)
    for k in range(ijk.shape[0]):
        f = (ijk[k, 0] * ny + ijk[k, 1]) * nz + ijk[k, 2]
        flat[k] = f
        grid[f] = -1
    stack = np.empty(nx * ny * nz, dtype=np.int64)
    comp = 0
    for k in range(ijk.shape[0]):
        if grid[flat[k]] != -1:
            continue
        top = 0
        stack[top] = flat[k]
        top += 1
        grid[flat[k]] = comp
        while top > 0:
            top -= 1
            f = stack[top]
            i, rem = f // (ny * nz), f % (ny * nz)
            j, l = rem // nz, rem % nz
            for di in (-1, 0, 1):
                ii = i + di
                if ii < 0 or ii >= nx:
                    continue
                for dj in (-1, 0, 1):
                    jj = j + dj
                    if jj < 0 or jj >= ny:
                        continue
                    for dl in (-1, 0, 1):
                        ll = l + dl
                        if ll < 0 or ll >= nz:
                            continue
                        g = (ii * ny + jj) * nz + ll
                        if grid[g] == -1:
                            grid[g] = comp
                            stack[top] = g
                            top += 1
        comp += 1
    out = np.empty(ijk.shape[0], dtype=np.int64)
    for k in range(ijk.shape[0]):
        out[k] = grid[flat[k]]
    return out

"""Spatial distribution p_G of an uncertain box on a grid, probabilistic Jaccard, JIoU and JIoU-GT.

p_G (DESIGN.md §5, form (b)) is the density of "a point drawn uniformly from the random box":

    p_G(u) = E_φ[ 1{u ∈ B(φ)} / size(B(φ)) ],    φ ~ N(φ̄, Σ),

estimated with a fixed set of scrambled-Sobol normal samples φ_s. Each sample box (a parallelogram
``c + A v*``, in 3D times a z-interval) is rasterised *exactly along x* on the centre line of every
row: for a horizontal line y = const, {x : |v*₁| ≤ ½, |v*₂| ≤ ½} is an interval (two slabs
intersected in closed form), and the exact length of its overlap with every cell of the row is
accumulated with a difference array — O(samples × rows) work, no per-cell loop. 3D multiplies each
sample's BEV raster by its z-interval coverage and contracts over samples with one sparse matrix
product; z-layers every sample covers completely are merged (the Jaccard takes cell counts).
Method, choices and measured accuracy: docs/method.md.

The grid lives in the frame of a reference box (the label): origin at its centre, x along its
length, so that the label itself is rasterised exactly (its edges fall on cell boundaries). A
deterministic box is the one-sample case with Σ = 0, so JIoU of two deterministic boxes is their IoU
up to the rasterisation of the other box's edges, and JIoU-GT → 1 as Σ → 0.
"""

from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit import geometry as g
from labelaudit.config import SpatialParams
from labelaudit.geometry import ModelKind

FloatArray = NDArray[np.float64]

__all__ = ["BoxDistribution", "Grid", "jaccard", "spatial_distribution", "jiou", "jiou_gt", "normal_samples"]


# ----------------------------------------------------------------------------------------------
# Box distributions
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class BoxDistribution:
    """A box with optional Gaussian uncertainty.

    Attributes
    ----------
    box : (7,) mean box (cx, cy, cz, l, w, h, yaw).
    model : "bev" or "3d".
    cov : None (deterministic box), or a covariance on φ ((6, 6) BEV, (8, 8) 3D) when
        ``cov_on == "phi"``, or on the box parameters when ``cov_on == "box"``: BEV (5, 5) over
        (cx, cy, l, w, yaw) or (7, 7) over all 7 (cz, h ignored); 3D (7, 7).
    cov_on : "phi" or "box".
    """

    box: FloatArray
    model: ModelKind
    cov: FloatArray | None = None
    cov_on: Literal["phi", "box"] = "phi"

    def __post_init__(self) -> None:
        object.__setattr__(self, "box", g.validate_box(self.box))
        d, p = g.point_dim(self.model), g.phi_dim(self.model)
        if self.cov is None:
            return
        cov = np.asarray(self.cov, dtype=float)
        if self.cov_on == "phi":
            want = [(p, p)]
        elif self.cov_on == "box":
            want = [(5, 5), (7, 7)] if d == 2 else [(7, 7)]
        else:
            raise ValueError(f"cov_on must be 'phi' or 'box', got {self.cov_on!r}")
        if cov.shape not in want or not np.all(np.isfinite(cov)):
            raise ValueError(f"covariance on {self.cov_on} for model {self.model!r} must be finite with shape {want}, got {cov.shape}")
        if self.cov_on == "box" and d == 2 and cov.shape == (7, 7):
            keep = [0, 1, 3, 4, 6]
            cov = cov[np.ix_(keep, keep)]
        object.__setattr__(self, "cov", 0.5 * (cov + cov.T))

    @classmethod
    def deterministic(cls, box: ArrayLike, model: ModelKind) -> "BoxDistribution":
        """A box without uncertainty (uniform distribution on the box)."""
        return cls(np.asarray(box, dtype=float), model)

    @classmethod
    def from_posterior(cls, post: "object") -> "BoxDistribution":
        """The label distribution of a :class:`labelaudit.model.LabelPosterior` (covariance on φ)."""
        return cls(np.asarray(post.box), post.model, np.asarray(post.cov), "phi")  # type: ignore[attr-defined]


@functools.lru_cache(maxsize=32)
def _normal_samples_cached(dim: int, num: int, seed: int) -> FloatArray:
    from scipy.stats import norm, qmc

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Sobol balance warning when num is not a power of two
        u = qmc.Sobol(d=dim, scramble=True, seed=seed).random(num)
    z = norm.ppf(np.clip(u, 1e-12, 1 - 1e-12))
    z.setflags(write=False)
    return z


def normal_samples(dim: int, num: int, seed: int) -> FloatArray:
    """Scrambled-Sobol standard normal samples (num, dim); cached, read-only, reproducible."""
    return _normal_samples_cached(int(dim), int(num), int(seed))


def _sqrt_psd(cov: FloatArray) -> FloatArray:
    """The symmetric square root of a PSD matrix (L Lᵀ = cov, L = Lᵀ).

    Unlike a Cholesky factor or V·√Λ it is unique and continuous in ``cov`` and commutes with
    rotations, so equal covariances always give equal samples (also when singular).
    """
    lam, V = np.linalg.eigh(cov)
    return (V * np.sqrt(np.clip(lam, 0.0, None))) @ V.T


@dataclass(frozen=True)
class _Samples:
    """Sample boxes in the grid frame and statistics of their boundary.

    centres (S, 2), in-plane axes (S, 2, 2) (columns: length and width edge vectors), z-intervals
    (S, 2) for 3D, weights (S,) = 1 / (size · number of valid samples); corner_mean (4, 2) and
    corner_std (largest corner total std), blur (d,): per grid axis, the smallest std of the
    coordinate along that axis of the points (corners, face midpoints) of the faces most normal to
    it — how sharp the distribution's boundary is across that axis (zeros for one sample);
    of the bottom/top), z_mean/z_std (2,) of the z-interval ends.
    """

    centres: FloatArray
    axes: FloatArray
    z: FloatArray | None
    weights: FloatArray
    corner_mean: FloatArray
    corner_std: float
    blur: FloatArray
    z_mean: FloatArray | None
    z_std: FloatArray | None


def _cos_sin(angle: float) -> tuple[float, float]:
    return math.cos(angle), math.sin(angle)


_IDX_3D_PLANAR = np.ix_([0, 1, 3, 4, 5, 6], [0, 1, 3, 4, 5, 6])  # the three in-plane 2-vectors of a 3D φ
# Unit coordinates (2, 8) of the 4 BEV corners (box_corners' order) and of the ±length, ±width face midpoints.
_FACE_POINTS_UNIT = np.array([[0.5, -0.5, -0.5, 0.5, 0.5, -0.5, 0.0, 0.0], [0.5, 0.5, -0.5, -0.5, 0.0, 0.0, 0.5, -0.5]])


def _sample_boxes(dist: BoxDistribution, ref: FloatArray, params: SpatialParams) -> _Samples:
    """Samples of ``dist`` expressed in the frame of ``ref`` (deterministic: one sample)."""
    d = g.point_dim(dist.model)
    box = dist.box
    c0, s0 = _cos_sin(ref[6])
    Rt = np.array([[c0, s0], [-s0, c0]])
    yl = box.copy()
    yl[0:2] = Rt @ (box[0:2] - ref[0:2])
    yl[2] = box[2] - ref[2]
    yl[6] = box[6] - ref[6]
    cl, sl = _cos_sin(yl[6])
    if dist.cov is None or dist.cov_on == "phi":
        phi = np.array([yl[0], yl[1], yl[3] * cl, yl[3] * sl, yl[4] * cl, yl[4] * sl])
        if d == 3:
            phi = np.array([yl[0], yl[1], yl[2], *phi[2:], yl[5]])
        if dist.cov is None:
            phis = phi[None, :]
        else:
            # φ in the grid frame is a linear map of φ: rotate the three in-plane 2-vectors.
            T6 = np.zeros((6, 6))
            T6[0:2, 0:2] = T6[2:4, 2:4] = T6[4:6, 4:6] = Rt
            if d == 2:
                T = T6
            else:
                T = np.eye(8)
                T[_IDX_3D_PLANAR] = T6
            z = normal_samples(phi.size, params.num_samples, params.seed)
            phis = phi + z @ _sqrt_psd(T @ dist.cov @ T.T)
        o = d - 2
        centre = phis[:, :d]
        A = np.empty((len(phis), 2, 2))
        A[:, 0, 0], A[:, 1, 0] = phis[:, 2 + o], phis[:, 3 + o]  # length edge (l cos, l sin)
        A[:, 0, 1], A[:, 1, 1] = -phis[:, 5 + o], phis[:, 4 + o]  # width edge (−w sin, w cos)
        height = phis[:, 7] if d == 3 else None
    else:
        k = dist.cov.shape[0]
        T = np.eye(k)
        T[:2, :2] = Rt
        z = normal_samples(k, params.num_samples, params.seed)
        mean = yl[[0, 1, 3, 4, 6]] if k == 5 else yl
        ys = mean + z @ _sqrt_psd(T @ dist.cov @ T.T)
        if k == 5:
            ys = np.c_[ys[:, 0:2], np.full(len(ys), yl[2]), ys[:, 2:4], np.full(len(ys), yl[5]), ys[:, 4]]
        c, sn = np.cos(ys[:, 6]), np.sin(ys[:, 6])
        A = np.empty((len(ys), 2, 2))
        A[:, 0, 0], A[:, 1, 0] = ys[:, 3] * c, ys[:, 3] * sn
        A[:, 0, 1], A[:, 1, 1] = -ys[:, 4] * sn, ys[:, 4] * c
        centre = ys[:, :d]
        height = ys[:, 5] if d == 3 else None
    size = np.abs(A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0])
    zint = None
    if height is not None:
        hh = 0.5 * np.abs(height)
        zint = np.stack([centre[:, 2] - hh, centre[:, 2] + hh], axis=1)
        size = size * 2.0 * hh
    S = len(A)
    if S == 1:
        weights = 1.0 / size if size[0] > 0 else np.zeros(1)
        a0, a1 = 0.5 * A[0, :, 0], 0.5 * A[0, :, 1]
        corners = centre[0, :2] + np.stack([a0 + a1, a1 - a0, -a0 - a1, a0 - a1])
        return _Samples(centre[:, :2], A, zint, weights, corners, 0.0, np.zeros(d), None if zint is None else zint[0], None if zint is None else np.zeros(2))
    ok = size > 1e-12 * max(float(np.max(size)), 1e-300)  # degenerate samples carry no area: drop
    weights = np.where(ok, 1.0 / np.where(ok, size, 1.0), 0.0) / np.count_nonzero(ok)
    # Corners in box_corners' BEV order ((+,+), (−,+), (−,−), (+,−) in unit coordinates), then the
    # midpoints of the ±length and ±width faces.
    pts = np.matmul(A, _FACE_POINTS_UNIT) + centre[:, :2, None]  # (S, 2, 8)
    mean = pts.mean(axis=0)  # (2, 8)
    dev = (pts - mean).reshape(S, 16)
    var = (np.einsum("ij,ij->j", dev, dev) / S).reshape(2, 8).T  # (8, 2)
    corner_mean = mean[:, :4].T
    corner_std = float(np.sqrt(np.max(var[:4].sum(axis=1))))
    # Blur across axis x: the faces most normal to x are the ±length faces when the length edge
    # points along x (corners and those faces' midpoints); likewise y.
    along_x = abs(A[:, 0, 0].sum()) >= abs(A[:, 1, 0].sum())
    x_mid, y_mid = (var[4:6], var[6:8]) if along_x else (var[6:8], var[4:6])
    blur = np.zeros(d)
    blur[0] = np.sqrt(min(float(var[:4, 0].min()), float(x_mid[:, 0].min())))
    blur[1] = np.sqrt(min(float(var[:4, 1].min()), float(y_mid[:, 1].min())))
    z_mean = z_std = None
    if zint is not None:
        z_mean, z_std = zint.mean(axis=0), zint.std(axis=0)
        blur[2] = float(z_std.min())
    return _Samples(centre[:, :2], A, zint, weights, corner_mean, corner_std, blur, z_mean, z_std)


# ----------------------------------------------------------------------------------------------
# Grid
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Grid:
    """A regular grid in the frame of a reference box (origin at its centre, x along its length).

    Attributes
    ----------
    ref : (7,) reference box (world frame)
    x_edges, y_edges : (nx+1,), (ny+1,) cell edges (metres, grid frame)
    z_edges : (nz+1,) for 3D (relative to the reference centre), None for BEV
    """

    ref: FloatArray
    x_edges: FloatArray
    y_edges: FloatArray
    z_edges: FloatArray | None = None

    @property
    def shape(self) -> tuple[int, ...]:
        s = (len(self.y_edges) - 1, len(self.x_edges) - 1)
        return s if self.z_edges is None else s + (len(self.z_edges) - 1,)

    def cell_centres_world(self) -> FloatArray:
        """World (x, y) of the BEV cell centres, shape (ny, nx, 2)."""
        xc = 0.5 * (self.x_edges[1:] + self.x_edges[:-1])
        yc = 0.5 * (self.y_edges[1:] + self.y_edges[:-1])
        X, Y = np.meshgrid(xc, yc)
        R = g.rotation_2d(self.ref[6])
        return np.stack([X, Y], -1) @ R.T + self.ref[:2]


def _axis_edges(half: float, lo: float, hi: float, cell: float) -> FloatArray:
    """Edges with the reference box's faces (±half) on cell boundaries, covering [lo, hi]."""
    n_box = max(1, int(round(2 * half / cell)))
    step = 2 * half / n_box
    n_lo = max(0, math.ceil((-half - lo) / step - 1e-9))
    n_hi = max(0, math.ceil((hi - half) / step - 1e-9))
    total = n_lo + n_box + n_hi
    if total > C.MAX_CELLS_PER_AXIS:  # wide support around a tiny box: coarser cells, box no longer on edges
        lo, hi = min(lo, -half), max(hi, half)
        return np.linspace(lo, hi, C.MAX_CELLS_PER_AXIS + 1)
    return -half - n_lo * step + step * np.arange(total + 1)


def _support(s: _Samples, support_std: float) -> tuple[FloatArray, FloatArray]:
    """Bounds (lo (k,), hi (k,)) of x, y [, z] covering the mean box ± support_std × largest corner std."""
    lo = np.min(s.corner_mean, axis=0) - support_std * s.corner_std
    hi = np.max(s.corner_mean, axis=0) + support_std * s.corner_std
    if s.z_mean is not None:
        lo = np.r_[lo, s.z_mean[0] - support_std * s.z_std[0]]
        hi = np.r_[hi, s.z_mean[1] + support_std * s.z_std[1]]
    return lo, hi


def _make_grid(
    ref: FloatArray,
    model: ModelKind,
    samples: list[_Samples],
    params: SpatialParams,
    boxes: list[FloatArray] | None = None,
    blur: FloatArray | None = None,
) -> Grid:
    """Grid in the frame of ``ref``.

    Cell size along axis a = max(longer BEV side of the smallest of ``boxes`` (default ``ref``),
    CELL_STD_SPAN × ``blur[a]``) / cells_per_side: the smaller box sets the accuracy, and a
    distribution whose boundary is blurred by ``blur[a]`` (m) across axis a needs no cells much
    finer than that along a.
    """
    d = g.point_dim(model)
    lo = np.full(d, np.inf)
    hi = np.full(d, -np.inf)
    for s in samples:
        a, b = _support(s, params.support_std)
        lo, hi = np.minimum(lo, a), np.maximum(hi, b)
    cells = params.cells_per_side * (1.0 if d == 2 else C.CELLS_PER_SIDE_3D_FACTOR)
    size = min(max(b[3], b[4]) for b in (boxes or [ref]))
    blur = np.zeros(d) if blur is None else blur
    cell = np.maximum(size, C.CELL_STD_SPAN * blur) / max(cells, 1.0)
    xe = _axis_edges(ref[3] / 2, lo[0], hi[0], cell[0])
    ye = _axis_edges(ref[4] / 2, lo[1], hi[1], cell[1])
    ze = _axis_edges(ref[5] / 2, lo[2], hi[2], cell[2]) if d == 3 else None
    return Grid(ref, xe, ye, ze)


# ----------------------------------------------------------------------------------------------
# Rasteriser
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Events:
    """Per (sample, row) x-interval of each sample box, as cell indices and offsets into the cells."""

    i_lo: NDArray[np.int64]  # (S, R) flat bin index (row·(nx+1) + k) of the interval start
    i_hi: NDArray[np.int64]  # (S, R) same for the end
    f_lo: FloatArray  # (S, R) offset of the start inside its cell (m)
    f_hi: FloatArray  # (S, R)
    valid: NDArray[np.bool_]  # (S, R) non-empty intervals
    ny: int
    nx: int
    dx: float
    dy: float  # height of one sub-row


def _events(s: _Samples, xe: FloatArray, ye: FloatArray) -> _Events:
    """Intersect every sample box with every (sub-)row centre line: O(S × rows), closed form."""
    nx, ny = len(xe) - 1, len(ye) - 1
    nsub = C.SUBROWS_PER_CELL
    dx, dy = xe[1] - xe[0], ye[1] - ye[0]
    ys = ye[0] + (np.arange(ny * nsub) + 0.5) * (dy / nsub)  # sub-row centres (R,)
    row = np.arange(ny * nsub) // nsub
    A = s.axes
    det = A[:, 0, 0] * A[:, 1, 1] - A[:, 0, 1] * A[:, 1, 0]
    # v* = A⁻¹ (u − c); row i of A⁻¹ is (bx_i, by_i)/det. On the line y = c_y + t the slab |v*_i| ≤ ½
    # is x − c_x ∈ [−h_i − m_i t, h_i − m_i t] with h_i = ½/|A⁻¹[i,0]|, m_i = by_i/bx_i.
    bx = np.stack([A[:, 1, 1], -A[:, 1, 0]], -1)
    by = np.stack([-A[:, 0, 1], A[:, 0, 0]], -1)
    scale = np.maximum(np.abs(bx), np.abs(by))
    flat = np.abs(bx) <= 1e-12 * scale  # slab parallel to x: it only limits y (see the y-extent below)
    safe_bx = np.where(flat, 1.0, bx)
    h = np.where(flat, np.inf, 0.5 * np.abs(det)[:, None] / np.abs(safe_bx))
    m = np.where(flat, 0.0, by / safe_bx)
    half_y = 0.5 * (np.abs(A[:, 1, 0]) + np.abs(A[:, 1, 1]))  # y-extent of the parallelogram
    t = ys[None, :] - s.centres[:, 1:2]  # (S, R)
    mt0, mt1 = m[:, 0:1] * t, m[:, 1:2] * t
    cx = s.centres[:, 0:1]
    lo = cx + np.maximum(-h[:, 0:1] - mt0, -h[:, 1:2] - mt1)
    hi = cx + np.minimum(h[:, 0:1] - mt0, h[:, 1:2] - mt1)
    np.clip(lo, xe[0], xe[-1], out=lo)
    np.clip(hi, xe[0], xe[-1], out=hi)
    valid = (np.abs(t) < half_y[:, None]) & (det[:, None] != 0) & (hi > lo)
    hi = np.where(valid, hi, lo)  # empty rows: zero-length interval, contributes exactly 0
    k_lo = np.minimum(((lo - xe[0]) * (1.0 / dx)).astype(np.int64), nx)
    k_hi = np.minimum(((hi - xe[0]) * (1.0 / dx)).astype(np.int64), nx)
    f_lo = lo - (xe[0] + k_lo * dx)
    f_hi = hi - (xe[0] + k_hi * dx)
    base = (row * (nx + 1))[None, :]
    return _Events(base + k_lo, base + k_hi, f_lo, f_hi, valid, ny, nx, dx, dy / nsub)


def _overlap(lo: float, hi: float, edges: FloatArray) -> FloatArray:
    """Length of [lo, hi] inside each cell of ``edges``."""
    return np.clip(np.minimum(hi, edges[1:]) - np.maximum(lo, edges[:-1]), 0.0, None)


def _aligned_single(s: _Samples, xe: FloatArray, ye: FloatArray) -> FloatArray | None:
    """Exact separable area per cell for a single axis-aligned box (the label in its own frame), else None."""
    A = s.axes
    if len(A) != 1 or A[0, 0, 1] != 0.0 or A[0, 1, 0] != 0.0:
        return None
    (cx, cy), hx, hy = s.centres[0], 0.5 * abs(A[0, 0, 0]), 0.5 * abs(A[0, 1, 1])
    return np.outer(_overlap(cy - hy, cy + hy, ye), _overlap(cx - hx, cx + hx, xe))


def _raster_bev(s: _Samples, xe: FloatArray, ye: FloatArray) -> FloatArray:
    """Weighted area of the sample boxes in every BEV cell, (ny, nx).

    Per interval, coverage(j) = dx·[k_lo ≤ j < k_hi] + f_hi·[j = k_hi] − f_lo·[j = k_lo]: the first
    term goes into a difference array (cumulative sum along x), the others directly.
    """
    aligned = _aligned_single(s, xe, ye)
    if aligned is not None:
        return aligned * s.weights[0]
    e = _events(s, xe, ye)
    nb = e.ny * (e.nx + 1)
    w = np.broadcast_to(s.weights[:, None], e.i_lo.shape)
    i_lo, i_hi = e.i_lo.ravel(), e.i_hi.ravel()
    wdx = (w * e.dx).ravel()
    steps = np.bincount(i_lo, weights=wdx, minlength=nb) - np.bincount(i_hi, weights=wdx, minlength=nb)
    direct = np.bincount(i_hi, weights=(w * e.f_hi).ravel(), minlength=nb) - np.bincount(
        i_lo, weights=(w * e.f_lo).ravel(), minlength=nb
    )
    cov = np.cumsum(steps.reshape(e.ny, e.nx + 1), axis=-1) + direct.reshape(e.ny, e.nx + 1)
    return cov[:, : e.nx] * e.dy


def _raster_3d(s: _Samples, xe: FloatArray, ye: FloatArray, zw: FloatArray) -> FloatArray:
    """Σ_s B_s(x, y) · zw[s, j]: BEV raster of each sample times a per-sample column weight, (ny, nx, ncols).

    The per-sample rasters are never formed densely: the interval events make a sparse
    (bins × samples) matrix, multiplied by ``zw`` (S × ncols), then summed along x per row.
    """
    from scipy.sparse import coo_matrix

    aligned = _aligned_single(s, xe, ye)
    if aligned is not None:
        return aligned[:, :, None] * zw[0]
    e = _events(s, xe, ye)
    nb = e.ny * (e.nx + 1)
    S = e.i_lo.shape[0]
    sidx = np.broadcast_to(np.arange(S)[:, None], e.i_lo.shape)[e.valid]
    i_lo, i_hi = e.i_lo[e.valid], e.i_hi[e.valid]
    rows = np.concatenate([i_lo, i_hi, i_hi + nb, i_lo + nb])
    cols = np.concatenate([sidx, sidx, sidx, sidx])
    n = len(i_lo)
    vals = np.concatenate([np.full(n, e.dx), np.full(n, -e.dx), e.f_hi[e.valid], -e.f_lo[e.valid]])
    M = coo_matrix((vals, (rows, cols)), shape=(2 * nb, S)).tocsr()
    out = np.asarray(M @ zw).reshape(2, e.ny, e.nx + 1, zw.shape[1])
    cov = np.cumsum(out[0], axis=1) + out[1]
    return cov[:, : e.nx] * e.dy


def _z_coverage(s: _Samples, ze: FloatArray) -> FloatArray:
    """Length of each sample's z-interval inside each z cell, (S, nz)."""
    return np.clip(np.minimum(s.z[:, 1:2], ze[None, 1:]) - np.maximum(s.z[:, 0:1], ze[None, :-1]), 0.0, None)


def _clean(mass: FloatArray) -> FloatArray:
    tiny = 1e-12 * float(np.max(mass)) if mass.size else 0.0
    mass[mass <= tiny] = 0.0  # round-off of the cumulative sums
    return mass


def _pair_masses(sa: _Samples, sb: _Samples, grid: Grid) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Masses of two distributions on the grid, as (p, q, counts) for :func:`jaccard`.

    3D: z-layers that every sample of both distributions covers completely are identical
    (p(x, y, z) = Σ_s w_s B_s(x, y)·dz); they are merged into one layer with a count, so only the
    layers near the top and bottom faces are formed and sorted one by one.
    """
    if grid.z_edges is None:
        return _clean(_raster_bev(sa, grid.x_edges, grid.y_edges)), _clean(_raster_bev(sb, grid.x_edges, grid.y_edges)), None
    ze = grid.z_edges
    dz = np.diff(ze)
    za, zb = _z_coverage(sa, ze), _z_coverage(sb, ze)
    full = np.all(za >= dz * (1 - 1e-9), axis=0) & np.all(zb >= dz * (1 - 1e-9), axis=0)
    empty = ~np.any(za > 0, axis=0) & ~np.any(zb > 0, axis=0)
    rest = ~full & ~empty
    n_full = int(np.count_nonzero(full))
    keep = np.r_[np.flatnonzero(rest), np.flatnonzero(full)[:1]]
    out = []
    for s, zc in ((sa, za), (sb, zb)):
        vox = _raster_3d(s, grid.x_edges, grid.y_edges, s.weights[:, None] * zc[:, keep])
        out.append(_clean(vox.reshape(-1, len(keep))))
    ncell = out[0].shape[0]
    counts = np.concatenate([np.ones((ncell, int(np.count_nonzero(rest)))), np.full((ncell, 1 if n_full else 0), float(n_full))], axis=1)
    return out[0], out[1], counts


def _rasterise(s: _Samples, grid: Grid) -> FloatArray:
    """Probability mass of p_G in every cell of the grid: (ny, nx) or (ny, nx, nz)."""
    if grid.z_edges is None:
        return _clean(_raster_bev(s, grid.x_edges, grid.y_edges))
    zw = s.weights[:, None] * _z_coverage(s, grid.z_edges)
    return _clean(_raster_3d(s, grid.x_edges, grid.y_edges, zw))


# ----------------------------------------------------------------------------------------------
# Probabilistic Jaccard, JIoU
# ----------------------------------------------------------------------------------------------


def jaccard(
    p: ArrayLike, q: ArrayLike, counts: ArrayLike | None = None, p_outside: float = 0.0, q_outside: float = 0.0
) -> float:
    """Probabilistic Jaccard index of two non-negative weight arrays on the same cells (Moulton & Jiang).

    J(p, q) = Σ_{i: p_i>0, q_i>0} 1 / Σ_j max(p_j/p_i, q_j/q_i), in O(N log N): with the cells sorted
    by r = p/q, max(·) is p_j/p_i for r_j ≥ r_i and q_j/q_i otherwise (ties give equal values), so
    the inner sum is a suffix sum of p over p_i plus a prefix sum of q over q_i. Invariant to the
    scale of p and of q; for two uniform distributions it is their IoU.

    ``counts`` (optional, same shape) says that entry i stands for ``counts[i]`` identical cells:
    a group of c equal cells contributes c / (P_after/p + Q_before/q + c) whatever their order, so
    identical cells can be merged before sorting. ``p_outside`` is mass of p on cells not listed
    where q = 0: such cells only ever enter through their total (they are in every p-suffix);
    likewise ``q_outside`` for q where p = 0 (in every q-prefix).
    """
    p = np.asarray(p, dtype=float).ravel()
    q = np.asarray(q, dtype=float).ravel()
    c = np.ones_like(p) if counts is None else np.asarray(counts, dtype=float).ravel()
    if p.shape != q.shape or c.shape != p.shape:
        raise ValueError(f"p, q (and counts) must have the same number of cells, got {p.size}, {q.size}, {c.size}")
    if np.any(p < 0) or np.any(q < 0):
        raise ValueError("p and q must be non-negative")
    both = (p > 0) & (q > 0)
    if not np.any(both):
        return 0.0
    # Cells with q = 0 (r = ∞) are in every p-suffix, cells with p = 0 (r = 0) in every q-prefix:
    # only the cells where both are positive need sorting.
    p_only = float(np.sum((c * p)[q == 0])) + float(p_outside)
    q_only = float(np.sum((c * q)[p == 0])) + float(q_outside)
    pb, qb, cb = p[both], q[both], c[both]
    order = np.argsort(pb / qb)
    ps, qs, cs = pb[order], qb[order], cb[order]
    suffix_p = np.cumsum((cs * ps)[::-1])[::-1] + p_only
    prefix_q = np.cumsum(cs * qs) - cs * qs + q_only
    return float(np.sum(cs / (suffix_p / ps + prefix_q / qs)))


def spatial_distribution(
    dist: BoxDistribution, params: SpatialParams, grid: Grid | None = None
) -> tuple[Grid, FloatArray]:
    """p_G of a box distribution on a grid (by default one in its own box frame).

    Returns
    -------
    grid : the :class:`Grid`
    mass : (ny, nx) BEV or (ny, nx, nz) 3D probability mass per cell (sums to ≈ 1; the part
        beyond ``support_std`` is cut off)
    """
    ref = dist.box if grid is None else grid.ref
    s = _sample_boxes(dist, ref, params)
    if grid is None:
        grid = _make_grid(ref, dist.model, [s], params, blur=s.blur)
    return grid, _rasterise(s, grid)


def jiou(a: BoxDistribution, b: BoxDistribution, params: SpatialParams) -> float:
    """JIoU of two box distributions: probabilistic Jaccard of their p_G on a common grid.

    The grid is built in the frame of ``b`` (pass the label as ``b``) and covers the support of both.
    """
    if a.model != b.model:
        raise ValueError(f"both distributions need the same model, got {a.model!r} and {b.model!r}")
    ref = b.box
    sa, sb = _sample_boxes(a, ref, params), _sample_boxes(b, ref, params)
    # The boundary blur sets the cell size; a deterministic box counts as sharp (blur 0) unless it
    # is the reference box itself, whose edges lie on cell boundaries and are rasterised exactly.
    blurs = [s.blur for s, dist in ((sa, a), (sb, b)) if not (dist.cov is None and np.array_equal(dist.box, ref))]
    blur = np.min(blurs, axis=0) if blurs else None
    grid = _make_grid(ref, b.model, [sa, sb], params, [a.box, b.box], blur)
    return jaccard(*_pair_masses(sa, sb, grid))


def _reference_samples(ref: FloatArray, model: ModelKind) -> _Samples:
    """The uniform distribution on the reference box itself, in its own frame (one aligned sample)."""
    d = g.point_dim(model)
    hl, hw = 0.5 * ref[3], 0.5 * ref[4]
    A = np.array([[[ref[3], 0.0], [0.0, ref[4]]]])
    corners = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    size = ref[3] * ref[4] * (ref[5] if d == 3 else 1.0)
    z = np.array([[-0.5 * ref[5], 0.5 * ref[5]]]) if d == 3 else None
    return _Samples(np.zeros((1, 2)), A, z, np.array([1.0 / size]), corners, 0.0, np.zeros(d), None if z is None else z[0], None if z is None else np.zeros(2))


def jiou_gt(post: "object", params: SpatialParams) -> float:
    """JIoU-GT of a label posterior: J(uniform on the labeled box, p_G of its posterior); 1 = certain.

    Same as ``jiou(BoxDistribution.deterministic(box), BoxDistribution.from_posterior(post))``
    (a test checks it) but faster: no re-validation, and since the uniform distribution is 0
    outside the box, p_G is only rasterised inside it (the rest is 1 − its mass there).
    """
    ref = np.asarray(post.box, dtype=float)  # type: ignore[attr-defined]
    model = post.model  # type: ignore[attr-defined]
    label = BoxDistribution.__new__(BoxDistribution)  # validated box and SPD covariance from the model
    object.__setattr__(label, "box", ref)
    object.__setattr__(label, "model", model)
    object.__setattr__(label, "cov", np.asarray(post.cov, dtype=float))  # type: ignore[attr-defined]
    object.__setattr__(label, "cov_on", "phi")
    sa, sb = _reference_samples(ref, model), _sample_boxes(label, ref, params)
    # q = 0 outside the labeled box, so p there only enters through its total, 1 − (p inside):
    # the grid covers the box alone (no truncated tails either).
    d = g.point_dim(model)
    cells = params.cells_per_side * (1.0 if d == 2 else C.CELLS_PER_SIDE_3D_FACTOR)
    cell = np.maximum(max(ref[3], ref[4]), C.CELL_STD_SPAN * sb.blur) / max(cells, 1.0)
    edges = [_axis_edges(0.5 * ref[3 + i], -0.5 * ref[3 + i], 0.5 * ref[3 + i], cell[i]) for i in range(d)]
    grid = Grid(ref, edges[0], edges[1], edges[2] if d == 3 else None)
    uniform, p_g, counts = _pair_masses(sa, sb, grid)
    inside = float(np.sum(p_g if counts is None else p_g * counts))
    return jaccard(uniform, p_g, counts, q_outside=max(0.0, 1.0 - inside))

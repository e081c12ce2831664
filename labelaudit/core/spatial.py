"""Spatial distribution p_G of an uncertain box on a grid, probabilistic Jaccard, JIoU and JIoU-GT.
No I/O; it reads only the stored Sobol samples shipped in ``labelaudit/data``.

p_G (docs/method.md §6, form (b)) is the density of "a point drawn uniformly from the random box":

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
from labelaudit.core import geometry as g
from labelaudit.core import linalg
from labelaudit.core.params import SAMPLE_TABLE, ModelKind, SpatialParams
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]

__all__ = [
    "BoxDistribution",
    "Grid",
    "jaccard",
    "spatial_distribution",
    "jiou",
    "jiou_gt",
    "jiou_gt_generic",
    "normal_samples",
    # the building blocks evaluate.jiou shares: samples, grid, rasteriser
    "Samples",
    "sample_boxes",
    "make_grid",
    "axis_edges",
    "sqrt_psd",
    "rasterise",
    "pair_masses",
    "z_coverage",
    "events_kernel",
]


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
            raise ValueError(
                f"covariance on {self.cov_on} for model {self.model!r} must be finite with shape {want}, got {cov.shape}"
            )
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
        """The label distribution of a :class:`labelaudit.core.posterior.LabelPosterior` (covariance on φ)."""
        return cls(np.asarray(post.box), post.model, np.asarray(post.cov), "phi")  # type: ignore[attr-defined]


def generate_normal_samples(dim: int, num: int, seed: int) -> FloatArray:
    """Scrambled-Sobol standard normal samples (num, dim) from scipy.stats.qmc."""
    from scipy.stats import norm, qmc

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Sobol balance warning when num is not a power of two
        u = qmc.Sobol(d=dim, scramble=True, seed=seed).random(num)
    return norm.ppf(np.clip(u, 1e-12, 1 - 1e-12))


@functools.lru_cache(maxsize=32)
def _normal_samples_cached(dim: int, num: int, seed: int) -> FloatArray:
    key = f"d{dim}_n{num}_s{seed}"
    z = None
    if SAMPLE_TABLE.is_file():
        with np.load(SAMPLE_TABLE) as table:
            if key in table.files:
                z = np.array(table[key], dtype=float)
    if z is None:
        z = generate_normal_samples(dim, num, seed)
    z.setflags(write=False)
    return z


def normal_samples(dim: int, num: int, seed: int) -> FloatArray:
    """Scrambled-Sobol standard normal samples (num, dim); cached, read-only, reproducible."""
    return _normal_samples_cached(int(dim), int(num), int(seed))


def sqrt_psd(cov: FloatArray) -> FloatArray:
    """The symmetric square root of a PSD matrix (L Lᵀ = cov, L = Lᵀ).

    Unlike a Cholesky factor or V·√Λ it is unique and continuous in ``cov`` and commutes with
    rotations, so equal covariances always give equal samples (also when singular). Compiled
    (:func:`labelaudit.core.linalg.sqrt_psd_kernel`); a non-finite matrix goes to LAPACK, which
    raises as ``np.linalg.eigh`` does.
    """
    a = np.ascontiguousarray(cov, dtype=np.float64)
    if not np.isfinite(a).all():
        lam, V = linalg.eigh(a)
        return (V * np.sqrt(np.maximum(lam, 0.0))) @ V.T
    return linalg.sqrt_psd_kernel(a)


@dataclass(frozen=True)
class Samples:
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

    @classmethod
    def single(
        cls, centres: FloatArray, axes: FloatArray, z: FloatArray | None, weights: FloatArray, corners: FloatArray
    ) -> "Samples":
        """One sample box (a deterministic distribution, or only its support): a sharp boundary
        (corner std and blur 0); ``centres`` (1, 2), ``axes`` (1, 2, 2), ``z`` (1, 2) or None (BEV),
        ``weights`` (1,), ``corners`` (4, 2)."""
        d = 2 if z is None else 3
        return cls(
            centres,
            axes,
            z,
            weights,
            corners,
            0.0,
            np.zeros(d),
            None if z is None else z[0],
            None if z is None else np.zeros(2),
        )


def _cos_sin(angle: float) -> tuple[float, float]:
    return math.cos(angle), math.sin(angle)


_IDX_3D_PLANAR = np.ix_([0, 1, 3, 4, 5, 6], [0, 1, 3, 4, 5, 6])  # the three in-plane 2-vectors of a 3D φ
# Unit coordinates (2, 8) of the 4 BEV corners (box_corners' order) and of the ±length, ±width face midpoints.
_FACE_POINTS_UNIT = np.array([[0.5, -0.5, -0.5, 0.5, 0.5, -0.5, 0.0, 0.0], [0.5, 0.5, -0.5, -0.5, 0.0, 0.0, 0.5, -0.5]])


def sample_boxes(dist: BoxDistribution, ref: FloatArray, params: SpatialParams) -> Samples:
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
            phis = phi + z @ sqrt_psd(T @ dist.cov @ T.T)
    else:
        k = dist.cov.shape[0]
        T = np.eye(k)
        T[:2, :2] = Rt
        z = normal_samples(k, params.num_samples, params.seed)
        mean = yl[[0, 1, 3, 4, 6]] if k == 5 else yl
        ys = mean + z @ sqrt_psd(T @ dist.cov @ T.T)
        if k == 5:
            ys = np.c_[ys[:, 0:2], np.full(len(ys), yl[2]), ys[:, 2:4], np.full(len(ys), yl[5]), ys[:, 4]]
        # The same φ layout: centre, length edge (l cos, l sin), width edge (w cos, w sin) [, height].
        c, sn = np.cos(ys[:, 6]), np.sin(ys[:, 6])
        edges = np.stack([ys[:, 3] * c, ys[:, 3] * sn, ys[:, 4] * c, ys[:, 4] * sn], axis=1)
        phis = np.concatenate([ys[:, :d], edges, ys[:, 5:6]] if d == 3 else [ys[:, :d], edges], axis=1)
    centres, A, zint, size, weights, corner_mean, corner_std, blur, z_mean, z_std = _sample_kernel(
        np.ascontiguousarray(phis, dtype=np.float64), d
    )
    if d == 2:
        zint = z_mean = z_std = None
    if len(A) == 1:
        weights = 1.0 / size if size[0] > 0 else np.zeros(1)
        a0, a1 = 0.5 * A[0, :, 0], 0.5 * A[0, :, 1]
        corners = centres[0] + np.stack([a0 + a1, a1 - a0, -a0 - a1, a0 - a1])
        return Samples.single(centres, A, zint, weights, corners)
    return Samples(centres, A, zint, weights, corner_mean, corner_std, blur, z_mean, z_std)


@kernel(error_model="numpy")
def _sample_kernel(phis, d):  # pragma: no cover - compiled
    """Sample boxes from φ samples (S, p) and the statistics of their boundary, in one pass.

    Returns centres (S, 2), axes A (S, 2, 2), z-intervals (S, 2) (zeros in BEV), sizes (S,), and for
    S > 1 the weights, corner_mean (4, 2), corner_std, blur (d,), z_mean, z_std (2,) of
    :class:`Samples`. Element by element the float64 operations of the NumPy form it replaced, in
    the same order (sums over samples run sequentially as NumPy's reductions along axis 0 do; the
    two edge sums that pick the blur axes are pairwise like ``ndarray.sum``), so the results are
    bit-identical (tests/test_spatial.py keeps the NumPy form).
    """
    S = phis.shape[0]
    o = d - 2
    centres = np.empty((S, 2))
    A = np.empty((S, 2, 2))
    zint = np.zeros((S, 2))
    size = np.empty(S)
    top = -np.inf
    for k in range(S):
        centres[k, 0], centres[k, 1] = phis[k, 0], phis[k, 1]
        A[k, 0, 0], A[k, 1, 0] = phis[k, 2 + o], phis[k, 3 + o]  # length edge (l cos, l sin)
        A[k, 0, 1], A[k, 1, 1] = -phis[k, 5 + o], phis[k, 4 + o]  # width edge (−w sin, w cos)
        v = abs(A[k, 0, 0] * A[k, 1, 1] - A[k, 0, 1] * A[k, 1, 0])
        if d == 3:
            hh = 0.5 * abs(phis[k, 7])
            zint[k, 0] = phis[k, 2] - hh
            zint[k, 1] = phis[k, 2] + hh
            v = v * 2.0 * hh
        size[k] = v
        top = linalg.nan_max(top, v)
    weights = np.zeros(S)
    corner_mean = np.zeros((4, 2))
    blur = np.zeros(d)
    z_mean = np.zeros(2)
    z_std = np.zeros(2)
    if S == 1:
        return centres, A, zint, size, weights, corner_mean, 0.0, blur, z_mean, z_std
    # Degenerate samples carry no area: drop them.
    floor = 1e-12 * (top if top != top or top > 1e-300 else 1e-300)
    n_ok = 0
    for k in range(S):
        if size[k] > floor:
            n_ok += 1
    for k in range(S):
        weights[k] = (1.0 / size[k] if size[k] > floor else 0.0) / n_ok
    # Corners in box_corners' BEV order ((+,+), (−,+), (−,−), (+,−) in unit coordinates), then the
    # midpoints of the ±length and ±width faces: (S, 2, 8), their mean and variance over samples.
    pts = np.empty((S, 2, 8))
    mean = np.zeros((2, 8))
    for k in range(S):
        for i in range(2):
            for j in range(8):
                pts[k, i, j] = (A[k, i, 0] * _FACE_POINTS_UNIT[0, j] + A[k, i, 1] * _FACE_POINTS_UNIT[1, j]) + centres[
                    k, i
                ]
                mean[i, j] += pts[k, i, j]
    for i in range(2):
        for j in range(8):
            mean[i, j] /= S
    var = np.zeros((8, 2))
    for k in range(S):
        for i in range(2):
            for j in range(8):
                dev = pts[k, i, j] - mean[i, j]
                var[j, i] += dev * dev
    for j in range(8):
        for i in range(2):
            var[j, i] /= S
    top = -np.inf
    for c in range(4):
        corner_mean[c, 0], corner_mean[c, 1] = mean[0, c], mean[1, c]
        top = linalg.nan_max(top, var[c, 0] + var[c, 1])
    corner_std = math.sqrt(top)
    # Blur across axis x: the faces most normal to x are the ±length faces when the length edge
    # points along x (corners and those faces' midpoints); likewise y.
    along_x = abs(linalg.pairwise_sum(A[:, 0, 0])) >= abs(linalg.pairwise_sum(A[:, 1, 0]))
    x_mid, y_mid = (4, 6) if along_x else (6, 4)
    for a, mid in ((0, x_mid), (1, y_mid)):
        lo = np.inf
        for c in range(4):
            lo = linalg.nan_min(lo, var[c, a])
        lo_mid = linalg.nan_min(var[mid, a], var[mid + 1, a])
        blur[a] = math.sqrt(lo_mid if lo_mid < lo else lo)  # Python's min(lo, lo_mid)
    if d == 3:
        for k in range(S):
            z_mean[0] += zint[k, 0]
            z_mean[1] += zint[k, 1]
        z_mean[0] /= S
        z_mean[1] /= S
        for k in range(S):
            for i in range(2):
                dev = zint[k, i] - z_mean[i]
                z_std[i] += dev * dev
        for i in range(2):
            z_std[i] = math.sqrt(z_std[i] / S)
        blur[2] = linalg.nan_min(z_std[0], z_std[1])
    return centres, A, zint, size, weights, corner_mean, corner_std, blur, z_mean, z_std


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


def axis_edges(half: float, lo: float, hi: float, cell: float) -> FloatArray:
    """Edges with the reference box's faces (±half) on cell boundaries, covering [lo, hi]."""
    half, lo, hi, cell = float(half), float(lo), float(hi), float(cell)
    if not (math.isfinite(half) and math.isfinite(lo) and math.isfinite(hi) and cell > 0 and math.isfinite(cell)):
        raise ValueError(f"grid axis: half {half}, bounds [{lo}, {hi}] and cell {cell} must be finite, cell > 0")
    return _axis_edges_kernel(half, lo, hi, cell, C.MAX_CELLS_PER_AXIS)


@kernel
def _axis_edges_kernel(half, lo, hi, cell, max_cells):  # pragma: no cover - compiled
    """:func:`axis_edges` of finite floats: ``round`` is Python's (half to even, as ``np.rint``) and a
    capped axis is NumPy's ``linspace`` (k · step + lo, the last edge = hi)."""
    n_box = max(1, np.int64(np.rint(2 * half / cell)))
    step = 2 * half / n_box
    n_lo = max(0, math.ceil((-half - lo) / step - 1e-9))
    n_hi = max(0, math.ceil((hi - half) / step - 1e-9))
    total = n_lo + n_box + n_hi
    if total > max_cells:  # wide support around a tiny box: coarser cells, box no longer on edges
        lo, hi = min(lo, -half), max(hi, half)
        out = np.empty(max_cells + 1)
        lin = (hi - lo) / max_cells
        for k in range(max_cells + 1):
            out[k] = k * lin + lo
        out[max_cells] = hi
        return out
    out = np.empty(total + 1)
    base = -half - n_lo * step
    for k in range(total + 1):
        out[k] = base + step * k
    return out


def _support(s: Samples, support_std: float) -> tuple[FloatArray, FloatArray]:
    """Bounds (lo (k,), hi (k,)) of x, y [, z] covering the mean box ± support_std × largest corner std."""
    lo = np.min(s.corner_mean, axis=0) - support_std * s.corner_std
    hi = np.max(s.corner_mean, axis=0) + support_std * s.corner_std
    if s.z_mean is not None:
        lo = np.r_[lo, s.z_mean[0] - support_std * s.z_std[0]]
        hi = np.r_[hi, s.z_mean[1] + support_std * s.z_std[1]]
    return lo, hi


def make_grid(
    ref: FloatArray,
    model: ModelKind,
    samples: list[Samples],
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
    size = min(max(b[3], b[4]) for b in (boxes or [ref]))
    blur = np.zeros(d) if blur is None else blur
    cell = np.maximum(size, C.CELL_STD_SPAN * blur) / grid_cells_per_side(params, d)
    xe = axis_edges(ref[3] / 2, lo[0], hi[0], cell[0])
    ye = axis_edges(ref[4] / 2, lo[1], hi[1], cell[1])
    ze = axis_edges(ref[5] / 2, lo[2], hi[2], cell[2]) if d == 3 else None
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


def _events(s: Samples, xe: FloatArray, ye: FloatArray) -> _Events:
    """Intersect every sample box with every (sub-)row centre line: O(S × rows), closed form.

    One compiled pass (:func:`events_kernel`): as NumPy array code this was ~30 calls on (S, R)
    arrays per JIoU-GT, whose call overhead cost more than the arithmetic.
    """
    nx, ny = len(xe) - 1, len(ye) - 1
    nsub = C.SUBROWS_PER_CELL
    dx, dy = xe[1] - xe[0], ye[1] - ye[0]
    i_lo, i_hi, f_lo, f_hi, valid = events_kernel(
        np.ascontiguousarray(s.axes, dtype=np.float64),
        np.ascontiguousarray(s.centres, dtype=np.float64),
        float(xe[0]),
        float(xe[-1]),
        float(ye[0]),
        float(dx),
        float(dy),
        nx,
        ny,
        nsub,
    )
    return _Events(i_lo, i_hi, f_lo, f_hi, valid, ny, nx, dx, dy / nsub)


@kernel
def events_kernel(A, centres, x0, x1, y0, dx, dy, nx, ny, nsub):  # pragma: no cover - compiled
    """Per (sample, sub-row): the x-interval of the sample box on the row's centre line.

    v* = A⁻¹ (u − c); row i of A⁻¹ is (bx_i, by_i)/det. On the line y = c_y + t the slab |v*_i| ≤ ½
    is x − c_x ∈ [−h_i − m_i t, h_i − m_i t] with h_i = ½/|A⁻¹[i,0]|, m_i = by_i/bx_i; a slab
    parallel to x (bx_i ≈ 0) only limits y, through the y-extent of the parallelogram. Empty
    intervals get zero length (hi = lo), so they add exactly 0 to the raster. Element by element
    the same float64 operations as the NumPy expressions they replaced (results are bit-identical).
    """
    S = A.shape[0]
    R = ny * nsub
    i_lo = np.empty((S, R), dtype=np.int64)
    i_hi = np.empty((S, R), dtype=np.int64)
    f_lo = np.empty((S, R))
    f_hi = np.empty((S, R))
    valid = np.empty((S, R), dtype=np.bool_)
    sub = dy / nsub
    inv_dx = 1.0 / dx
    for k in range(S):
        det, h0, h1, m0, m1, half_y = _sample_slabs(A, k)
        cx, cy = centres[k, 0], centres[k, 1]
        for r in range(R):
            k_lo, k_hi, lo_off, hi_off, ok = _row_interval(
                (y0 + (r + 0.5) * sub) - cy, cx, det, h0, h1, m0, m1, half_y, x0, x1, dx, inv_dx, nx
            )
            base = (r // nsub) * (nx + 1)
            i_lo[k, r] = base + k_lo
            i_hi[k, r] = base + k_hi
            f_lo[k, r] = lo_off
            f_hi[k, r] = hi_off
            valid[k, r] = ok
    return i_lo, i_hi, f_lo, f_hi, valid


@kernel
def _sample_slabs(A, k):  # pragma: no cover - compiled
    """det A, the slab half-widths h_i and slopes m_i along x, and the y half-extent of sample k."""
    a00, a01, a10, a11 = A[k, 0, 0], A[k, 0, 1], A[k, 1, 0], A[k, 1, 1]
    det = a00 * a11 - a01 * a10
    h0 = h1 = m0 = m1 = 0.0
    for i in range(2):
        bx, by = (a11, -a01) if i == 0 else (-a10, a00)
        scale = linalg.nan_max(abs(bx), abs(by))
        if abs(bx) <= 1e-12 * scale:
            h, m = np.inf, 0.0
        else:
            h, m = 0.5 * abs(det) / abs(bx), by / bx
        if i == 0:
            h0, m0 = h, m
        else:
            h1, m1 = h, m
    return det, h0, h1, m0, m1, 0.5 * (abs(a10) + abs(a11))


@kernel
def _row_interval(t, cx, det, h0, h1, m0, m1, half_y, x0, x1, dx, inv_dx, nx):  # pragma: no cover - compiled
    """The x-interval of one sample on the row line y = c_y + t: start and end cells (k_lo, k_hi),
    offsets into them, and whether it is non-empty. Plain comparisons, not NaN-propagating ones
    (a NaN bound is clamped to x0: a finite sample has none), which are several times dearer here:
    this runs once per sample and row of every raster."""
    mt0, mt1 = m0 * t, m1 * t
    a, b = -h0 - mt0, -h1 - mt1
    lo = cx + (a if a >= b else b)
    a, b = h0 - mt0, h1 - mt1
    hi = cx + (a if a <= b else b)
    lo = x0 if not lo >= x0 else lo
    lo = lo if lo <= x1 else x1
    hi = x0 if not hi >= x0 else hi
    hi = hi if hi <= x1 else x1
    ok = (abs(t) < half_y) and (det != 0) and (hi > lo)
    if not ok:
        hi = lo
    k_lo = min(np.int64((lo - x0) * inv_dx), nx)
    k_hi = min(np.int64((hi - x0) * inv_dx), nx)
    return k_lo, k_hi, lo - (x0 + k_lo * dx), hi - (x0 + k_hi * dx), ok


def _aligned_single(s: Samples, xe: FloatArray, ye: FloatArray, weight: float = 1.0) -> FloatArray | None:
    """Exact separable area per cell (times ``weight``) for a single axis-aligned box (the label in
    its own frame), else None."""
    A = s.axes
    if len(A) != 1 or A[0, 0, 1] != 0.0 or A[0, 1, 0] != 0.0:
        return None
    (cx, cy), hx, hy = s.centres[0], 0.5 * abs(A[0, 0, 0]), 0.5 * abs(A[0, 1, 1])
    return _aligned_kernel(float(cx), float(cy), float(hx), float(hy), xe, ye, float(weight))


@kernel
def _overlap_kernel(lo, hi, edges):  # pragma: no cover - compiled
    """Length of [lo, hi] inside each cell of ``edges``: clip(min(hi, right) − max(lo, left), 0)."""
    n = edges.size - 1
    out = np.empty(n)
    for j in range(n):
        out[j] = linalg.nan_max(linalg.nan_min(hi, edges[j + 1]) - linalg.nan_max(lo, edges[j]), 0.0)
    return out


@kernel
def _aligned_kernel(cx, cy, hx, hy, xe, ye, weight):  # pragma: no cover - compiled
    """outer(overlap along y, overlap along x) · weight, (ny, nx)."""
    ox = _overlap_kernel(cx - hx, cx + hx, xe)
    oy = _overlap_kernel(cy - hy, cy + hy, ye)
    out = np.empty((oy.size, ox.size))
    for i in range(oy.size):
        for j in range(ox.size):
            out[i, j] = oy[i] * ox[j] * weight
    return out


def _raster_bev(s: Samples, xe: FloatArray, ye: FloatArray) -> FloatArray:
    """Weighted area of the sample boxes in every BEV cell, (ny, nx).

    Per interval, coverage(j) = dx·[k_lo ≤ j < k_hi] + f_hi·[j = k_hi] − f_lo·[j = k_lo]: the first
    term goes into a difference array (cumulative sum along x), the others directly.
    """
    aligned = _aligned_single(s, xe, ye, s.weights[0])
    if aligned is not None:
        return aligned
    nx, ny = len(xe) - 1, len(ye) - 1
    return _raster_bev_events_kernel(
        np.ascontiguousarray(s.axes, dtype=np.float64),
        np.ascontiguousarray(s.centres, dtype=np.float64),
        np.ascontiguousarray(s.weights, dtype=np.float64),
        float(xe[0]),
        float(xe[-1]),
        float(ye[0]),
        float(xe[1] - xe[0]),
        float(ye[1] - ye[0]),
        nx,
        ny,
        C.SUBROWS_PER_CELL,
    )


@kernel
def _raster_bev_events_kernel(A, centres, weights, x0, x1, y0, dx, dy, nx, ny, nsub):  # pragma: no cover - compiled
    """:func:`events_kernel` and :func:`_raster_bev_kernel` in one pass (the same sums in the same
    order, no (S, R) event arrays): per sample, its intervals on every row in one loop (no stores
    into the raster: the compiler vectorises it), then their additions to the difference arrays."""
    nb = ny * (nx + 1)
    lo_dx = np.zeros(nb)
    hi_dx = np.zeros(nb)
    hi_f = np.zeros(nb)
    lo_f = np.zeros(nb)
    R = ny * nsub
    sub = dy / nsub
    inv_dx = 1.0 / dx
    i_lo = np.empty(R, dtype=np.int64)
    i_hi = np.empty(R, dtype=np.int64)
    f_lo = np.empty(R)
    f_hi = np.empty(R)
    for k in range(A.shape[0]):
        det, h0, h1, m0, m1, half_y = _sample_slabs(A, k)
        cx, cy = centres[k, 0], centres[k, 1]
        w = weights[k]
        wdx = w * dx
        for r in range(R):
            k_lo, k_hi, lo_off, hi_off, _ = _row_interval(
                (y0 + (r + 0.5) * sub) - cy, cx, det, h0, h1, m0, m1, half_y, x0, x1, dx, inv_dx, nx
            )
            base = (r if nsub == 1 else r // nsub) * (nx + 1)
            i_lo[r] = base + k_lo
            i_hi[r] = base + k_hi
            f_lo[r] = w * lo_off
            f_hi[r] = w * hi_off
        for r in range(R):
            lo_dx[i_lo[r]] += wdx
            hi_dx[i_hi[r]] += wdx
            hi_f[i_hi[r]] += f_hi[r]
            lo_f[i_lo[r]] += f_lo[r]
    return _raster_rows(lo_dx, hi_dx, hi_f, lo_f, dy / nsub, ny, nx)


@kernel
def _raster_bev_kernel(i_lo, i_hi, f_lo, f_hi, weights, dx, dy, ny, nx):  # pragma: no cover - compiled
    """The difference-array raster of :func:`_raster_bev` in one pass: the same sums in the same
    order as the NumPy form it replaced (four weighted ``bincount`` s over the (S, R) events in C
    order, differences, a running sum along each row, times dy), so the masses are bit-identical."""
    nb = ny * (nx + 1)
    lo_dx = np.zeros(nb)
    hi_dx = np.zeros(nb)
    hi_f = np.zeros(nb)
    lo_f = np.zeros(nb)
    S, R = i_lo.shape
    for k in range(S):
        w = weights[k]
        wdx = w * dx
        for r in range(R):
            lo_dx[i_lo[k, r]] += wdx
            hi_dx[i_hi[k, r]] += wdx
            hi_f[i_hi[k, r]] += w * f_hi[k, r]
            lo_f[i_lo[k, r]] += w * f_lo[k, r]
    return _raster_rows(lo_dx, hi_dx, hi_f, lo_f, dy, ny, nx)


@kernel
def _raster_rows(lo_dx, hi_dx, hi_f, lo_f, dy, ny, nx):  # pragma: no cover - compiled
    """The raster (ny, nx) from the per-bin sums: differences, a running sum along each row, times dy."""
    out = np.empty((ny, nx))
    for row in range(ny):
        base = row * (nx + 1)
        run = 0.0
        for j in range(nx):
            step = lo_dx[base + j] - hi_dx[base + j]
            run = step if j == 0 else run + step
            out[row, j] = (run + (hi_f[base + j] - lo_f[base + j])) * dy
    return out


def _raster_3d(s: Samples, xe: FloatArray, ye: FloatArray, zw: FloatArray) -> FloatArray:
    """Σ_s B_s(x, y) · zw[s, j]: BEV raster of each sample times a per-sample column weight, (ny, nx, ncols).

    The per-sample rasters are never formed densely: the interval events make a sparse
    (bins × samples) matrix, multiplied by ``zw`` (S × ncols), then summed along x per row. With
    one sub-row per cell that product is one compiled pass (:func:`_raster_3d_kernel`).
    """
    aligned = _aligned_single(s, xe, ye)
    if aligned is not None:
        return aligned[:, :, None] * zw[0]
    if C.SUBROWS_PER_CELL == 1:
        return _raster_3d_kernel(
            np.ascontiguousarray(s.axes, dtype=np.float64),
            np.ascontiguousarray(s.centres, dtype=np.float64),
            np.ascontiguousarray(zw, dtype=np.float64),
            float(xe[0]),
            float(xe[-1]),
            float(ye[0]),
            float(xe[1] - xe[0]),
            float(ye[1] - ye[0]),
            len(xe) - 1,
            len(ye) - 1,
        )
    from scipy.sparse import coo_matrix

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


@kernel
def _raster_3d_kernel(A, centres, zw, x0, x1, y0, dx, dy, nx, ny):  # pragma: no cover - compiled
    """The sparse product of :func:`_raster_3d` for one sub-row per cell, with SciPy's arithmetic:
    CSR rows (bins) hold their samples in ascending order, the entries of one (bin, sample) merged
    by a sum (an interval inside one cell: dx − dx and f_hi − f_lo; two terms, so their order does
    not matter), each row of ``M @ zw`` summed from 0 in that order; then the running sum along x."""
    i_lo, i_hi, f_lo, f_hi, valid = events_kernel(A, centres, x0, x1, y0, dx, dy, nx, ny, 1)
    S, R = i_lo.shape
    ncol = zw.shape[1]
    nb = ny * (nx + 1)
    acc = np.zeros((2 * nb, ncol))  # rows: the dx steps per bin, then the offsets per bin
    for k in range(S):  # ascending samples: each bin's entries arrive in CSR order
        for r in range(R):
            if not valid[k, r]:
                continue
            lo, hi = i_lo[k, r], i_hi[k, r]
            if lo == hi:
                step, off = dx + (-dx), f_hi[k, r] + (-f_lo[k, r])
                for c in range(ncol):
                    acc[lo, c] += step * zw[k, c]
                    acc[nb + lo, c] += off * zw[k, c]
            else:
                for c in range(ncol):
                    acc[lo, c] += dx * zw[k, c]
                    acc[hi, c] += -dx * zw[k, c]
                    acc[nb + hi, c] += f_hi[k, r] * zw[k, c]
                    acc[nb + lo, c] += -f_lo[k, r] * zw[k, c]
    out = np.empty((ny, nx, ncol))
    for row in range(ny):
        base = row * (nx + 1)
        for c in range(ncol):
            run = 0.0
            for j in range(nx):
                run = acc[base, c] if j == 0 else run + acc[base + j, c]
                out[row, j, c] = (run + acc[nb + base + j, c]) * dy
    return out


def z_coverage(s: Samples, ze: FloatArray) -> FloatArray:
    """Length of each sample's z-interval inside each z cell, (S, nz)."""
    return np.clip(np.minimum(s.z[:, 1:2], ze[None, 1:]) - np.maximum(s.z[:, 0:1], ze[None, :-1]), 0.0, None)


def _clean(mass: FloatArray) -> FloatArray:
    """``mass`` with the cells ≤ 1e-12 × its maximum set to 0 (round-off of the cumulative sums), in place."""
    mass = np.ascontiguousarray(mass)  # the rasters are: a copy would not be cleaned in place
    _clean_kernel(mass.reshape(-1))
    return mass


@kernel
def _clean_kernel(flat):  # pragma: no cover - compiled
    """The NumPy form ``tiny = 1e-12 · max; mass[mass <= tiny] = 0`` (a NaN maximum cleans nothing)."""
    if flat.size == 0:
        return
    top = flat[0]
    for i in range(1, flat.size):
        top = linalg.nan_max(top, flat[i])
    tiny = 1e-12 * top
    for i in range(flat.size):
        if flat[i] <= tiny:
            flat[i] = 0.0


def pair_masses(sa: Samples, sb: Samples, grid: Grid) -> tuple[FloatArray, FloatArray, FloatArray | None]:
    """Masses of two distributions on the grid, as (p, q, counts) for :func:`jaccard`.

    3D: z-layers that every sample of both distributions covers completely are identical
    (p(x, y, z) = Σ_s w_s B_s(x, y)·dz); they are merged into one layer with a count, so only the
    layers near the top and bottom faces are formed and sorted one by one.
    """
    if grid.z_edges is None:
        return (
            _clean(_raster_bev(sa, grid.x_edges, grid.y_edges)),
            _clean(_raster_bev(sb, grid.x_edges, grid.y_edges)),
            None,
        )
    ze = grid.z_edges
    dz = np.diff(ze)
    za, zb = z_coverage(sa, ze), z_coverage(sb, ze)
    full = (za >= dz * (1 - 1e-9)).all(axis=0) & (zb >= dz * (1 - 1e-9)).all(axis=0)
    empty = ~(za > 0).any(axis=0) & ~(zb > 0).any(axis=0)
    rest = ~full & ~empty
    n_full = int(np.count_nonzero(full))
    keep = np.r_[np.flatnonzero(rest), np.flatnonzero(full)[:1]]
    out = []
    for s, zc in ((sa, za), (sb, zb)):
        vox = _raster_3d(s, grid.x_edges, grid.y_edges, s.weights[:, None] * zc[:, keep])
        out.append(_clean(vox.reshape(-1, len(keep))))
    ncell = out[0].shape[0]
    counts = np.concatenate(
        [np.ones((ncell, int(np.count_nonzero(rest)))), np.full((ncell, 1 if n_full else 0), float(n_full))], axis=1
    )
    return out[0], out[1], counts


def rasterise(s: Samples, grid: Grid) -> FloatArray:
    """Probability mass of p_G in every cell of the grid: (ny, nx) or (ny, nx, nz)."""
    if grid.z_edges is None:
        return _clean(_raster_bev(s, grid.x_edges, grid.y_edges))
    zw = s.weights[:, None] * z_coverage(s, grid.z_edges)
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
    p = np.ascontiguousarray(p, dtype=np.float64).ravel()
    q = np.ascontiguousarray(q, dtype=np.float64).ravel()
    c = np.ones_like(p) if counts is None else np.ascontiguousarray(counts, dtype=np.float64).ravel()
    if p.shape != q.shape or c.shape != p.shape:
        raise ValueError(f"p, q (and counts) must have the same number of cells, got {p.size}, {q.size}, {c.size}")
    # Cells with q = 0 (r = ∞) are in every p-suffix, cells with p = 0 (r = 0) in every q-prefix:
    # only the cells where both are positive need sorting.
    negative, pb, qb, cb, ratio, p_only, q_only = _jaccard_split(p, q, c, float(p_outside), float(q_outside), 0)
    if negative:
        raise ValueError("p and q must be non-negative")
    if not pb.size:
        return 0.0
    # NumPy's sort, not numba's: the cells are mostly tied (the interior), 10³ in BEV and 10⁴–10⁵ in
    # 3D, and NumPy's vectorised sort takes a third to a half of the time numba's quicksort does
    return float(_jaccard_sum(pb, qb, cb, ratio.argsort(), p_only, q_only))


@kernel(error_model="numpy")
def _jaccard_split(p, q, c, p_outside, q_outside, row):  # pragma: no cover - compiled
    """The cells of :func:`jaccard` where both masses are positive (p, q, counts, r = p/q), and the
    totals p_only = Σ_{q=0} c·p + p_outside, q_only = Σ_{p=0} c·q + q_outside, summed in NumPy's
    (pairwise) order over the same arrays as the NumPy form; the flag says a mass is negative.

    ``row`` > 0: the cells are a raster, row-major with rows of ``row`` cells, and consecutive equal
    cells of a row are merged into one cell with their counts added. The interior of a JIoU-GT
    raster is such a run (every sample covers it, the running sum does not move), and
    :func:`_jaccard_sum` makes c equal cells in one entry the same term as c cells in a row (only
    the rounding of the sums moves), so fewer cells are sorted and summed; the totals are the
    unmerged cells' all the same. 0: every cell is kept."""
    n = p.size
    negative = False
    for i in range(n):
        if p[i] < 0 or q[i] < 0:
            negative = True
    pb = np.empty(n)
    qb = np.empty(n)
    cb = np.empty(n)
    ratio = np.empty(n)
    p_rest = np.empty(n)
    q_rest = np.empty(n)
    nb = n_p = n_q = 0
    last = -2  # the cell of the last entry
    for i in range(n):
        if q[i] == 0:
            p_rest[n_p] = c[i] * p[i]
            n_p += 1
        if p[i] == 0:
            q_rest[n_q] = c[i] * q[i]
            n_q += 1
        if p[i] > 0 and q[i] > 0:
            if row > 0 and last == i - 1 and i % row != 0 and p[i] == pb[nb - 1] and q[i] == qb[nb - 1]:
                cb[nb - 1] += c[i]
            else:
                pb[nb], qb[nb], cb[nb], ratio[nb] = p[i], q[i], c[i], p[i] / q[i]
                nb += 1
            last = i
    p_only = linalg.pairwise_sum(p_rest[:n_p]) + p_outside
    q_only = linalg.pairwise_sum(q_rest[:n_q]) + q_outside
    return negative, pb[:nb], qb[:nb], cb[:nb], ratio[:nb], p_only, q_only


@kernel(error_model="numpy")
def _jaccard_sum(pb, qb, cb, order, p_only, q_only):  # pragma: no cover - compiled
    """Σ_i c_i / (P_suffix/p_i + Q_prefix/q_i) over the cells sorted by r (``order``): the running
    sums sequential like ``np.cumsum``, the total pairwise like ``ndarray.sum``."""
    n = order.size
    cp = np.empty(n)  # c·p and c·q in sorted order
    cq = np.empty(n)
    for j in range(n):
        i = order[j]
        cp[j] = cb[i] * pb[i]
        cq[j] = cb[i] * qb[i]
    suffix = np.empty(n)
    run = 0.0
    for j in range(n - 1, -1, -1):
        run = cp[j] if j == n - 1 else run + cp[j]
        suffix[j] = run
    terms = np.empty(n)
    run = 0.0
    for j in range(n):
        run = cq[j] if j == 0 else run + cq[j]
        i = order[j]
        terms[j] = cb[i] / ((suffix[j] + p_only) / pb[i] + ((run - cq[j]) + q_only) / qb[i])
    return linalg.pairwise_sum(terms)


@kernel
def _ratio_keys(ratio):  # pragma: no cover - compiled
    """Sort keys of the Jaccard's cells (n,): each ratio r_i > 0 with its last ``shift`` bits
    replaced by the cell's index i (2^shift ≥ n), as float64 — for positive floats the order of
    the bits is the order of the values, so sorting the keys orders the cells by r (ratios within
    2^(shift − 52) of each other, ≤ 1.5e-11 relative for the 256² cells of the largest raster, in
    the order of their index: they give nearly equal terms, the sum moves in its last bits), and
    the index comes back from the sorted keys (:func:`_jaccard_sum_keys`). Returns (keys, shift)."""
    n = ratio.size
    shift = 0
    while (1 << shift) < n:
        shift += 1
    keys = np.empty(n)
    for i in range(n):
        keys[i] = ratio[i]
    bits = keys.view(np.int64)
    low = (np.int64(1) << shift) - 1
    for i in range(n):
        bits[i] = (bits[i] & ~low) | i
    return keys, shift


@kernel(error_model="numpy")
def _jaccard_sum_keys(pb, qb, cb, keys, shift, p_only, q_only):  # pragma: no cover - compiled
    """:func:`_jaccard_sum` of the cells in the order of their sorted keys (:func:`_ratio_keys`)."""
    order = keys.view(np.int64) & ((np.int64(1) << shift) - 1)
    return _jaccard_sum(pb, qb, cb, order, p_only, q_only)


jaccard_sum_sorted_keys = _jaccard_sum_keys
"""The Jaccard sum of :func:`jiou_gt_bev_cells`' cells once their keys are sorted (compiled; public
for :func:`labelaudit.core.posterior.bev_label_scores`, which calls it from its own compiled pass)."""


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
    s = sample_boxes(dist, ref, params)
    if grid is None:
        grid = make_grid(ref, dist.model, [s], params, blur=s.blur)
    return grid, rasterise(s, grid)


def jiou(a: BoxDistribution, b: BoxDistribution, params: SpatialParams) -> float:
    """JIoU of two box distributions: probabilistic Jaccard of their p_G on a common grid.

    The grid is built in the frame of ``b`` (pass the label as ``b``) and covers the support of both.
    """
    if a.model != b.model:
        raise ValueError(f"both distributions need the same model, got {a.model!r} and {b.model!r}")
    ref = b.box
    sa, sb = sample_boxes(a, ref, params), sample_boxes(b, ref, params)
    # The boundary blur sets the cell size; a deterministic box counts as sharp (blur 0) unless it
    # is the reference box itself, whose edges lie on cell boundaries and are rasterised exactly.
    blurs = [s.blur for s, dist in ((sa, a), (sb, b)) if not (dist.cov is None and np.array_equal(dist.box, ref))]
    blur = np.min(blurs, axis=0) if blurs else None
    grid = make_grid(ref, b.model, [sa, sb], params, [a.box, b.box], blur)
    return jaccard(*pair_masses(sa, sb, grid))


def _reference_samples(ref: FloatArray, model: ModelKind) -> Samples:
    """The uniform distribution on the reference box itself, in its own frame (one aligned sample)."""
    d = g.point_dim(model)
    hl, hw = 0.5 * ref[3], 0.5 * ref[4]
    A = np.array([[[ref[3], 0.0], [0.0, ref[4]]]])
    corners = np.array([[hl, hw], [-hl, hw], [-hl, -hw], [hl, -hw]])
    size = ref[3] * ref[4] * (ref[5] if d == 3 else 1.0)
    z = np.array([[-0.5 * ref[5], 0.5 * ref[5]]]) if d == 3 else None
    return Samples.single(np.zeros((1, 2)), A, z, np.array([1.0 / size]), corners)


def grid_cells_per_side(params: SpatialParams, d: int) -> float:
    """The JIoU rasters' cells across the (smaller) box's longer side, at least 1:
    ``params.cells_per_side`` in BEV (``d`` = 2), times CELLS_PER_SIDE_3D_FACTOR in 3D (a voxel
    grid's cost grows with the cube).

    Examples
    --------
    >>> from labelaudit.core.params import SpatialParams
    >>> grid_cells_per_side(SpatialParams(cells_per_side=64), 2)
    64.0
    >>> grid_cells_per_side(SpatialParams(cells_per_side=0), 2)
    1.0
    """
    return max(params.cells_per_side * (1.0 if d == 2 else C.CELLS_PER_SIDE_3D_FACTOR), 1.0)


def jiou_gt(post: "object", params: SpatialParams) -> float:
    """JIoU-GT of a label posterior: J(uniform on the labeled box, p_G of its posterior); 1 = certain.

    Same as ``jiou(BoxDistribution.deterministic(box), BoxDistribution.from_posterior(post))``
    (a test checks it) but faster: no re-validation, and since the uniform distribution is 0
    outside the box, p_G is only rasterised inside it (the rest is 1 − its mass there). A BEV
    posterior's cells come from one compiled pass (:func:`_jiou_gt_bev_kernel`), then are sorted
    by NumPy and summed by :func:`_jaccard_sum` as in :func:`jaccard`.
    """
    ref = np.asarray(post.box, dtype=float)  # type: ignore[attr-defined]
    model = post.model  # type: ignore[attr-defined]
    cov = np.ascontiguousarray(post.cov, dtype=np.float64)  # type: ignore[attr-defined]
    d = g.point_dim(model)
    if d == 2 and params.num_samples > 1:
        ok, pb, qb, cb, keys, shift, p_only, q_only = _jiou_gt_bev_kernel(
            ref,
            cov,
            normal_samples(6, params.num_samples, params.seed),
            grid_cells_per_side(params, d),
            C.CELL_STD_SPAN,
            C.MAX_CELLS_PER_AXIS,
            C.SUBROWS_PER_CELL,
        )
        if ok:
            # NumPy's sort of the cells' keys (ratio and cell together, _ratio_keys) between the two
            # compiled passes: a third of the time of its argsort of the ratios; in place (the
            # kernel's own array), without np.sort's copy
            keys.sort()
            return float(_jaccard_sum_keys(pb, qb, cb, keys, shift, p_only, q_only)) if pb.size else 0.0
    return jiou_gt_generic(ref, model, cov, params)


def jiou_gt_generic(ref: FloatArray, model: ModelKind, cov: FloatArray, params: SpatialParams) -> float:
    """:func:`jiou_gt` of box ``ref`` (7,) with φ covariance ``cov`` by the general steps (samples,
    grid, :func:`pair_masses`, :func:`jaccard`): the 3D path, and what the BEV kernel is tested against."""
    d = g.point_dim(model)
    label = BoxDistribution.__new__(BoxDistribution)  # validated box and SPD covariance from the model
    object.__setattr__(label, "box", ref)
    object.__setattr__(label, "model", model)
    object.__setattr__(label, "cov", cov)
    object.__setattr__(label, "cov_on", "phi")
    sa, sb = _reference_samples(ref, model), sample_boxes(label, ref, params)
    # q = 0 outside the labeled box, so p there only enters through its total, 1 − (p inside):
    # the grid covers the box alone (no truncated tails either).
    cell = np.maximum(max(ref[3], ref[4]), C.CELL_STD_SPAN * sb.blur) / grid_cells_per_side(params, d)
    edges = [axis_edges(0.5 * ref[3 + i], -0.5 * ref[3 + i], 0.5 * ref[3 + i], cell[i]) for i in range(d)]
    grid = Grid(ref, edges[0], edges[1], edges[2] if d == 3 else None)
    uniform, p_g, counts = pair_masses(sa, sb, grid)
    inside = float((p_g if counts is None else p_g * counts).sum())
    return jaccard(uniform, p_g, counts, q_outside=max(0.0, 1.0 - inside))


@kernel(error_model="numpy")
def _jiou_gt_bev_kernel(ref, cov, z, cells, span, max_cells, nsub):  # pragma: no cover - compiled
    """The cells of the Jaccard of a BEV posterior's JIoU-GT (box ``ref`` (7,), φ covariance ``cov``
    (6, 6)) from the normal samples ``z`` (S, 6), S > 1: the steps of :func:`jiou_gt`'s generic
    form in one pass — φ samples in the label's frame (φ̄ + z √(T Σ Tᵀ)), their boxes and blur, the
    grid over the label, both rasters cleaned, and :func:`_jaccard_split` with p_G's mass outside
    the label. Returns (ok, p, q, counts, r, p_only, q_only), what :func:`_jaccard_sum` takes once
    r is sorted; ``ok`` is False for a non-finite covariance (the generic form then raises as
    before) or a negative mass."""
    empty = np.zeros(0)
    for i in range(6):
        for j in range(6):
            if not math.isfinite(cov[i, j]):
                return False, empty, empty, empty, empty, 0, 0.0, 0.0
    length, width = ref[3], ref[4]
    # φ in the label's own frame: the three in-plane 2-vectors turned by −yaw (T Σ Tᵀ, T = diag(Rᵀ, Rᵀ, Rᵀ))
    c0, s0 = math.cos(ref[6]), math.sin(ref[6])
    tc = np.empty((6, 6))
    for i in range(6):
        b = i - i % 2
        for j in range(6):
            tc[i, j] = (c0 * cov[b, j] + s0 * cov[b + 1, j]) if i % 2 == 0 else (-s0 * cov[b, j] + c0 * cov[b + 1, j])
    m = np.empty((6, 6))
    for i in range(6):
        for j in range(6):
            b = j - j % 2
            m[i, j] = (tc[i, b] * c0 + tc[i, b + 1] * s0) if j % 2 == 0 else (-tc[i, b] * s0 + tc[i, b + 1] * c0)
    root = linalg.sqrt_psd_kernel(m)
    mean = (0.0, 0.0, length, 0.0, width, 0.0)
    S = z.shape[0]
    phis = np.empty((S, 6))
    for k in range(S):
        for j in range(6):
            acc = 0.0
            for i in range(6):
                acc += z[k, i] * root[i, j]
            phis[k, j] = mean[j] + acc
    centres, A, _, _, weights, _, _, blur, _, _ = _sample_kernel(phis, 2)
    top = max(length, width)
    xe = _axis_edges_kernel(0.5 * length, -0.5 * length, 0.5 * length, max(top, span * blur[0]) / cells, max_cells)
    ye = _axis_edges_kernel(0.5 * width, -0.5 * width, 0.5 * width, max(top, span * blur[1]) / cells, max_cells)
    nx, ny = xe.size - 1, ye.size - 1
    uniform = _aligned_kernel(0.0, 0.0, 0.5 * length, 0.5 * width, xe, ye, 1.0 / (length * width * 1.0))
    p_g = _raster_bev_events_kernel(
        A, centres, weights, xe[0], xe[nx], ye[0], xe[1] - xe[0], ye[1] - ye[0], nx, ny, nsub
    )
    u, q = uniform.reshape(-1), p_g.reshape(-1)
    _clean_kernel(u)
    _clean_kernel(q)
    inside = linalg.pairwise_sum(q)
    negative, pb, qb, cb, ratio, p_only, q_only = _jaccard_split(u, q, np.ones(u.size), 0.0, max(0.0, 1.0 - inside), nx)
    keys, shift = _ratio_keys(ratio)
    return not negative, pb, qb, cb, keys, shift, p_only, q_only


jiou_gt_bev_cells = _jiou_gt_bev_kernel
"""A BEV posterior's JIoU-GT cells before their sort (compiled: :func:`jiou_gt`'s first pass; public
for :func:`labelaudit.core.posterior.bev_label_scores`, which calls it from its own compiled pass)."""

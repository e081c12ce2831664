"""Box parametrisations, rotations, the feature map φ(y) and its Jacobians, frame transforms.

This module owns the geometry every other part shares; it does no I/O and holds no model.

Conventions (docs/method.md): everything is computed in the LiDAR/vehicle frame, x forward, y left,
z up, yaw about +z, box centre at the geometric centre.

A box is ``y = (cx, cy, cz, l, w, h, yaw)``. A point of the box with unit coordinates
``v* ∈ [-½, ½]^d`` is ``v = R(yaw) · diag(l, w, h) · v* + c``, which is linear in the feature vector

- BEV (``model="bev"``, d = 2, p = 6): ``φ = (c1, c2, l·cos, l·sin, w·cos, w·sin)``
- 3D  (``model="3d"``,  d = 3, p = 8): ``φ = (c1, c2, c3, l·cos, l·sin, w·cos, w·sin, h)``

so that ``v = J(v*) · φ`` with ``J`` depending on ``v*`` only.

φ has one degree of freedom more than the box: the length and width axes may turn independently
(a parallelogram). To make the prior on φ full rank we use the *extended* parameters

- BEV: ``ỹ = (cx, cy, l, w, a, b)``, 3D: ``ỹ = (cx, cy, cz, l, w, h, a, b)``

where ``a`` is the direction of the length axis and ``b`` that of the width axis turned back by
90°; at a rectangular box ``a = b = yaw``. The reported yaw of a parallelogram is ``(a + b) / 2``.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit.core.params import BOX_FIELDS, ModelKind

FloatArray = NDArray[np.float64]

BEV_OF_3D = np.array([0, 1, 3, 4, 5, 6])  # entries of φ_3d that make φ_bev: cx, cy, l·cos, l·sin, w·cos, w·sin


def point_dim(model: ModelKind) -> int:
    """Dimension d of a point: 2 for BEV, 3 for 3D."""
    return _check_model(model)[0]


def phi_dim(model: ModelKind) -> int:
    """Dimension p of the feature vector φ: 6 for BEV, 8 for 3D."""
    return _check_model(model)[1]


def _check_model(model: str) -> tuple[int, int]:
    if model == "bev":
        return 2, 6
    if model == "3d":
        return 3, 8
    raise ValueError(f"model must be 'bev' or '3d', got {model!r}")


def normalize_angle(angle: ArrayLike) -> FloatArray | float:
    """Wrap angles to [-π, π)."""
    if isinstance(
        angle, float
    ):  # a scalar: Python's float % is NumPy's remainder (same fmod-based rule), at a tenth of the cost
        return (float(angle) + math.pi) % (2.0 * math.pi) - math.pi
    wrapped = (np.asarray(angle, dtype=float) + np.pi) % (2.0 * np.pi) - np.pi
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def rotation_z(yaw: ArrayLike) -> FloatArray:
    """Rotation matrix about +z.

    Parameters
    ----------
    yaw : float or array of shape (...,)

    Returns
    -------
    R : array of shape (..., 3, 3)
    """
    yaw = np.asarray(yaw, dtype=float)
    c, s = np.cos(yaw), np.sin(yaw)
    R = np.zeros(yaw.shape + (3, 3))
    R[..., 0, 0], R[..., 0, 1] = c, -s
    R[..., 1, 0], R[..., 1, 1] = s, c
    R[..., 2, 2] = 1.0
    return R


def rotation_2d(yaw: ArrayLike) -> FloatArray:
    """2×2 rotation matrix (or a stack of them, shape (..., 2, 2))."""
    return rotation_z(yaw)[..., :2, :2]


def validate_box(box: ArrayLike) -> FloatArray:
    """Return ``box`` as a float array of shape (7,), or raise ``ValueError`` naming the bad values.

    A valid box has 7 finite numbers and strictly positive length, width and height.
    """
    y = np.asarray(box, dtype=float)
    if y.shape != (7,):
        raise ValueError(f"a box is 7 numbers (cx, cy, cz, l, w, h, yaw); got shape {y.shape}")
    v = y.tolist()  # 7 Python floats: scalar tests cost a tenth of array ones (this runs per box, often)
    if all(map(math.isfinite, v)) and v[3] > 0 and v[4] > 0 and v[5] > 0:
        return y
    if not np.all(np.isfinite(y)):
        bad = [f"{n}={v}" for n, v in zip(BOX_FIELDS, y) if not np.isfinite(v)]
        raise ValueError(f"box has non-finite values: {', '.join(bad)}")
    if np.any(y[3:6] <= 0):
        bad = [f"{n}={v:g}" for n, v in zip(BOX_FIELDS[3:6], y[3:6]) if v <= 0]
        raise ValueError(f"box sizes must be > 0: {', '.join(bad)}")
    return y


def box_to_phi(box: ArrayLike, model: ModelKind) -> FloatArray:
    """Feature vector φ(y) of a box.

    Parameters
    ----------
    box : array of shape (7,)
        (cx, cy, cz, l, w, h, yaw).
    model : "bev" or "3d"

    Returns
    -------
    phi : array of shape (6,) for BEV or (8,) for 3D
    """
    cx, cy, cz, length, width, height, yaw = validate_box(box)
    c, s = np.cos(yaw), np.sin(yaw)
    if _check_model(model)[0] == 2:
        return np.array([cx, cy, length * c, length * s, width * c, width * s])
    return np.array([cx, cy, cz, length * c, length * s, width * c, width * s, height])


def phi_axes(phi: ArrayLike, model: ModelKind) -> tuple[FloatArray, FloatArray]:
    """Centre and edge matrix of the (parallelogram) box described by φ.

    Parameters
    ----------
    phi : array of shape (..., p)

    Returns
    -------
    centre : array of shape (..., d)
    axes : array of shape (..., d, d)
        Columns are the length-edge, width-edge (and height-edge) vectors, so that a point of the
        box is ``centre + axes @ v*``.
    """
    phi = np.asarray(phi, dtype=float)
    d, p = _check_model(model)
    if phi.shape[-1] != p:
        raise ValueError(f"φ for model {model!r} has {p} entries, got shape {phi.shape}")
    # length edge = (l cos, l sin); width edge = (-w sin, w cos) — see J(v*).
    if d == 2:
        centre = phi[..., 0:2]
        axes = np.stack([np.stack([phi[..., 2], -phi[..., 5]], -1), np.stack([phi[..., 3], phi[..., 4]], -1)], -2)
        return centre, axes
    zeros = np.zeros_like(phi[..., 0])
    centre = phi[..., 0:3]
    axes = np.stack(
        [
            np.stack([phi[..., 3], -phi[..., 6], zeros], -1),
            np.stack([phi[..., 4], phi[..., 5], zeros], -1),
            np.stack([zeros, zeros, phi[..., 7]], -1),
        ],
        -2,
    )
    return centre, axes


def phi_to_box(phi: ArrayLike, model: ModelKind, *, cz: float = 0.0, height: float = 1.0) -> FloatArray:
    """Box (7,) of a feature vector; a parallelogram gets yaw = mean direction of its two axes.

    For BEV, ``cz`` and ``height`` are not part of φ and are taken from the arguments.
    """
    ext = phi_to_extended(phi, model)
    if model == "bev":
        cx, cy, length, width, a, b = ext
        return np.array([cx, cy, cz, length, width, height, _mean_angle(a, b)])
    cx, cy, cz3, length, width, h, a, b = ext
    return np.array([cx, cy, cz3, length, width, h, _mean_angle(a, b)])


def _mean_angle(a: float, b: float) -> float:
    return float(normalize_angle(a + 0.5 * normalize_angle(b - a)))


def box_to_extended(box: ArrayLike, model: ModelKind) -> FloatArray:
    """Extended parameters ỹ of a rectangular box: BEV (cx, cy, l, w, a, b), 3D (cx, cy, cz, l, w, h, a, b)."""
    cx, cy, cz, length, width, height, yaw = validate_box(box)
    if _check_model(model)[0] == 2:
        return np.array([cx, cy, length, width, yaw, yaw])
    return np.array([cx, cy, cz, length, width, height, yaw, yaw])


def extended_to_phi(ext: ArrayLike, model: ModelKind) -> FloatArray:
    """φ of extended parameters ỹ (inverse of :func:`phi_to_extended`)."""
    e = np.asarray(ext, dtype=float)
    if _check_model(model)[0] == 2:
        cx, cy, length, width, a, b = e
        return np.array([cx, cy, length * np.cos(a), length * np.sin(a), width * np.cos(b), width * np.sin(b)])
    cx, cy, cz, length, width, height, a, b = e
    return np.array([cx, cy, cz, length * np.cos(a), length * np.sin(a), width * np.cos(b), width * np.sin(b), height])


def phi_to_extended(phi: ArrayLike, model: ModelKind) -> FloatArray:
    """Extended parameters ỹ of a feature vector φ."""
    f = np.asarray(phi, dtype=float)
    d, p = _check_model(model)
    if f.shape != (p,):
        raise ValueError(f"φ for model {model!r} has {p} entries, got shape {f.shape}")
    o = d - 2  # offset of the in-plane terms: 0 for BEV, 1 for 3D
    lc, ls, wc, ws = f[2 + o : 6 + o]
    length, width = np.hypot(lc, ls), np.hypot(wc, ws)
    a, b = np.arctan2(ls, lc), np.arctan2(ws, wc)
    if d == 2:
        return np.array([f[0], f[1], length, width, a, b])
    return np.array([f[0], f[1], f[2], length, width, f[7], a, b])


def dphi_dext(box: ArrayLike, model: ModelKind) -> FloatArray:
    """Jacobian ∂φ/∂ỹ at a rectangular box (p×p, invertible for l, w > 0).

    Used to carry a covariance on the box parameters to φ: ``Σ_φ = G Σ_ỹ Gᵀ``.
    """
    return dphi_dext_valid(validate_box(box), model)


def sensor_xy(origin: ArrayLike) -> tuple[float, float]:
    """A sensor position's x, y as Python floats: the values ``np.asarray(origin, dtype=float)``
    holds, without the conversion when it is a float64 vector already."""
    if type(origin) is np.ndarray and origin.dtype == np.float64 and origin.ndim == 1:
        ox, oy = origin[:2].tolist()
        return ox, oy
    o = np.asarray(origin, dtype=float).reshape(-1)
    return float(o[0]), float(o[1])


def cos_sin(yaw: float) -> tuple[float, float]:
    """NumPy's ``np.cos(yaw)``, ``np.sin(yaw)`` as Python floats (NumPy's, not math's: NumPy may
    use SIMD kernels, and a label's φ, Jacobians and prior terms must agree bit for bit)."""
    return float(np.cos(yaw)), float(np.sin(yaw))


def dphi_dext_valid(y: FloatArray, model: ModelKind) -> FloatArray:
    """:func:`dphi_dext` of a box (7,) float64 known to be valid (after :func:`validate_box`)."""
    c, s = cos_sin(y[6])
    length, width = float(y[3]), float(y[4])
    d, p = _check_model(model)
    G = np.zeros(p * p)
    # the entries of the centre, l, w (then h for 3D), a and b columns (_DPHI_DEXT_ENTRIES), at once
    G[_DPHI_DEXT_ENTRIES[d]] = (
        (1.0, 1.0, c, s, c, s, -length * s, length * c, -width * s, width * c)
        if d == 2
        else (1.0, 1.0, 1.0, c, s, c, s, -length * s, length * c, -width * s, width * c, 1.0)
    )
    return G.reshape(p, p)


def _dphi_dext_entries(d: int) -> NDArray[np.int64]:
    """Flat indices into the p × p ∂φ/∂ỹ of its non-zero entries, in the order :func:`dphi_dext_valid` writes them."""
    p = 2 * d + 2
    o = d - 2
    il, iw, ia, ib = d, d + 1, p - 2, p - 1
    cells = [(i, i) for i in range(d)]
    cells += [(2 + o, il), (3 + o, il), (4 + o, iw), (5 + o, iw), (2 + o, ia), (3 + o, ia), (4 + o, ib), (5 + o, ib)]
    if d == 3:
        cells.append((7, 5))
    return np.array([i * p + j for i, j in cells])


_DPHI_DEXT_ENTRIES = {2: _dphi_dext_entries(2), 3: _dphi_dext_entries(3)}


def dext_dphi(box: ArrayLike, model: ModelKind) -> FloatArray:
    """Jacobian ∂ỹ/∂φ at a rectangular box: the inverse of :func:`dphi_dext`."""
    return np.linalg.inv(dphi_dext(box, model))


def box_param_jacobian(box: ArrayLike, model: ModelKind) -> tuple[FloatArray, tuple[str, ...]]:
    """Jacobian of the reported box parameters with respect to φ, at a rectangular box.

    The reported parameters are BEV (cx, cy, l, w, yaw) or 3D (cx, cy, cz, l, w, h, yaw), with
    yaw = (a + b) / 2. Propagate a φ covariance with ``K Σ Kᵀ`` to get per-parameter variances.

    Returns
    -------
    K : array of shape (5, 6) or (7, 8)
    names : names of the rows (subset of :data:`BOX_FIELDS`)
    """
    d, p = _check_model(model)
    E = dext_dphi(box, model)
    K = np.vstack([E[: p - 2], 0.5 * (E[p - 2] + E[p - 1])])
    names = ("cx", "cy", "length", "width", "yaw") if d == 2 else BOX_FIELDS
    return K, names


def design_matrix(vstar: ArrayLike, model: ModelKind) -> FloatArray:
    """J(v*) for unit-box coordinates: ``v = J(v*) @ φ``.

    Parameters
    ----------
    vstar : array of shape (..., d)
        Unit-box coordinates in [-½, ½]^d (values outside are allowed: the map is linear).

    Returns
    -------
    J : array of shape (..., d, p)
    """
    v = np.asarray(vstar, dtype=float)
    d, p = _check_model(model)
    if v.shape[-1] != d:
        raise ValueError(f"v* for model {model!r} has {d} coordinates, got shape {v.shape}")
    J = np.zeros(v.shape[:-1] + (d, p))
    o = d - 2
    J[..., 0, 0] = 1.0
    J[..., 1, 1] = 1.0
    J[..., 0, 2 + o] = v[..., 0]
    J[..., 0, 5 + o] = -v[..., 1]
    J[..., 1, 3 + o] = v[..., 0]
    J[..., 1, 4 + o] = v[..., 1]
    if d == 3:
        J[..., 2, 2] = 1.0
        J[..., 2, 7] = v[..., 2]
    return J


def unit_to_world(vstar: ArrayLike, box: ArrayLike, model: ModelKind) -> FloatArray:
    """Map unit-box coordinates (..., d) to points (..., d) of a box."""
    return design_matrix(vstar, model) @ box_to_phi(box, model)


def world_to_unit(points: ArrayLike, box: ArrayLike, model: ModelKind) -> FloatArray:
    """Map points (N, ≥d) to unit-box coordinates (N, d) of a box (inverse of :func:`unit_to_world`)."""
    y = validate_box(box)
    d = point_dim(model)
    pts = np.asarray(points, dtype=float)[..., :d]
    local = (pts - y[:d]) @ rotation_z(y[6])[:d, :d]  # R^T (x - c), written row-wise
    return local / y[3 : 3 + d]


def box_corners(box: ArrayLike, model: ModelKind = "3d") -> FloatArray:
    """Corners of a box.

    Returns
    -------
    corners : array of shape (4, 2) for BEV (counter-clockwise, starting at front-left
        (+l/2, +w/2)) or (8, 3) for 3D (the BEV order at the bottom, then at the top).
    """
    bev = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
    if _check_model(model)[0] == 2:
        return unit_to_world(bev, box, "bev")
    v = np.vstack([np.c_[bev, -0.5 * np.ones(4)], np.c_[bev, 0.5 * np.ones(4)]])
    return unit_to_world(v, box, "3d")


BEV_CORNERS_UNIT: FloatArray = np.array([[0.5, 0.5], [-0.5, 0.5], [-0.5, -0.5], [0.5, -0.5]])
"""Unit coordinates of the 4 BEV corners, in the order of :func:`box_corners`."""


def near_polygons(
    xy: ArrayLike, polygons: list[FloatArray] | tuple[FloatArray, ...], margin: float
) -> NDArray[np.bool_]:
    """Whether each point lies inside one of the polygons or within ``margin`` of its boundary.

    Parameters
    ----------
    xy : (M, 2) points
    polygons : each (P, 2) vertices, P ≥ 3, in order (either orientation; concave allowed); the last
        vertex joins the first (a repeated first vertex is harmless)
    margin : m, ≥ 0; the Euclidean distance to the nearest boundary segment: the polygon grown by a
        disc (rounded at convex corners), as a distance transform of its raster would be

    Returns
    -------
    (M,) bool. Inside is the even-odd rule, so where two polygons of one list overlap an odd number
    of times counts; pass the pieces of a union as separate polygons.
    """
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    out = np.zeros(len(pts), dtype=bool)
    for poly in polygons:
        v = np.asarray(poly, dtype=float).reshape(-1, 2)
        if len(v) < 3 or out.all():
            continue
        lo, hi = v.min(axis=0) - margin, v.max(axis=0) + margin
        cand = np.flatnonzero(~out & np.all((pts >= lo) & (pts <= hi), axis=1))
        if not len(cand):
            continue
        # the points (m, 1) against the edges a → b (P,), x and y apart (no (m, P, 2) temporaries)
        px, py = pts[cand, 0:1], pts[cand, 1:2]
        ax, ay = v[:, 0], v[:, 1]
        by = np.roll(ay, -1)
        dx, dy = np.roll(ax, -1) - ax, by - ay
        # even-odd crossings of the ray from p towards +x
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = ax + (py - ay) * (dx / dy)
        inside = np.count_nonzero(((ay > py) != (by > py)) & (px < x_cross), axis=1) % 2 == 1
        # distance to the nearest edge (a degenerate edge is its point)
        len2 = dx * dx + dy * dy
        inv = np.where(len2 > 0, 1.0 / np.where(len2 > 0, len2, 1.0), 0.0)
        rx, ry = px - ax, py - ay
        t = np.clip((rx * dx + ry * dy) * inv, 0.0, 1.0)
        ex, ey = rx - t * dx, ry - t * dy
        d2 = ex * ex + ey * ey
        out[cand] = inside | (d2.min(axis=1) <= margin * margin)
    return out


def transform_points(T_dst_src: ArrayLike, points_src: ArrayLike) -> FloatArray:
    """Apply a 4×4 homogeneous transform to points (N, 3); extra columns are kept unchanged."""
    T = np.asarray(T_dst_src, dtype=float)
    if T.shape != (4, 4):
        raise ValueError(f"a transform is 4×4, got shape {T.shape}")
    pts = np.asarray(points_src, dtype=float)
    out = pts.copy()
    out[..., :3] = pts[..., :3] @ T[:3, :3].T + T[:3, 3]
    return out


def invert_transform(T_dst_src: ArrayLike) -> FloatArray:
    """Inverse of a rigid 4×4 transform: returns ``T_src_dst``."""
    T = np.asarray(T_dst_src, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def quaternion_to_matrix(q: ArrayLike) -> FloatArray:
    """Rotation matrices of quaternions given as (w, x, y, z) (Hamilton convention, as Argoverse 2 writes them).

    Parameters
    ----------
    q : (..., 4) quaternions; they are normalised here, so only their direction matters

    Returns
    -------
    (..., 3, 3) rotations; NaN where a quaternion has zero or non-finite norm
    """
    q = np.asarray(q, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def quaternion_yaw(q: ArrayLike) -> FloatArray:
    """Heading about +z of quaternions (w, x, y, z): the direction of the rotated x axis in the xy plane.

    For a rotation about z alone (a cuboid label) this is the rotation angle; with roll or pitch
    it is still the direction the box's length axis points to, seen from above. (..., 4) → (...,)
    in [-π, π]; the norm of ``q`` does not matter.
    """
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.arctan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)


def yaw_quaternion(yaw: ArrayLike) -> FloatArray:
    """(..., 4) unit quaternions (w, x, y, z) of rotations by ``yaw`` about +z (the inverse of :func:`quaternion_yaw`)."""
    half = 0.5 * np.asarray(yaw, dtype=float)
    zero = np.zeros_like(half)
    return np.stack([np.cos(half), zero, zero, np.sin(half)], axis=-1)


def make_transform(R: ArrayLike, t: ArrayLike) -> FloatArray:
    """4×4 homogeneous transform from a 3×3 rotation and a translation."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=float)
    T[:3, 3] = np.asarray(t, dtype=float)
    return T


def clean_points(points: ArrayLike | None, d: int) -> FloatArray:
    """The first ``d`` coordinates of ``points`` (N, ≥d) as float64, rows with non-finite values dropped
    (None or empty → (0, d)); raises ValueError for another shape."""
    if points is None:
        return np.zeros((0, d))
    pts = np.asarray(points)
    if pts.dtype.kind != "f":
        pts = np.asarray(points, dtype=float)
    if pts.size == 0:
        return np.zeros((0, d))
    if pts.ndim != 2 or pts.shape[1] < d:
        raise ValueError(f"points must be an (N, ≥{d}) array, got shape {pts.shape}")
    if pts.dtype == np.float32 or pts.dtype == np.float64:  # the pipeline's crops: one compiled pass
        return _pointops().finite_rows_f64(pts, d)
    pts = pts[:, :d]  # other float types are converted after the cut (exactly): d columns, not all of them
    if np.isfinite(pts).all():  # the usual case: one test, a contiguous copy (as the masked copy below)
        return pts.astype(np.float64, order="C")
    return pts[np.all(np.isfinite(pts), axis=1)].astype(
        np.float64, order="C"
    )  # non-finite returns cannot be registered


def clean_columns(points: ArrayLike | None, d: int) -> FloatArray:
    """:func:`clean_points` transposed: a float64 (d, M) C-contiguous array, the finite rows' first
    ``d`` coordinates as columns; float32/float64 crops in one compiled pass."""
    pts = None if points is None else np.asarray(points)
    if pts is not None and pts.ndim == 2 and pts.shape[1] >= d and pts.size and pts.dtype in _NATIVE_FLOATS:
        return _pointops().finite_columns_f64(pts, d)
    return np.ascontiguousarray(clean_points(points, d).T)


_NATIVE_FLOATS = (np.dtype(np.float32), np.dtype(np.float64))  # what the compiled passes read as they are
_POINTOPS: list = []  # labelaudit.core.pointops once imported


def _pointops():  # noqa: ANN202 - a module
    """:mod:`labelaudit.core.pointops`, imported on first use (importing the geometry, as the CLI
    does, never loads the compiled kernels) and kept: an import statement costs ~1 µs per call."""
    if not _POINTOPS:
        from labelaudit.core import pointops

        _POINTOPS.append(pointops)
    return _POINTOPS[0]


def phi_of_valid_box(y: FloatArray, model: ModelKind) -> FloatArray:
    """:func:`box_to_phi` of a box (7,) float64 known to be valid (labels
    after ``validate_box``, the fit's own rectangles: finite, sizes floored above 0): the same arithmetic without the checks, which cost
    more than φ itself at a dozen calls per fit."""
    c, s = cos_sin(y[6])  # NumPy's cos/sin (not math's: NumPy may use SIMD kernels)
    cx, cy, cz, length, width, height, _ = (
        y.tolist()
    )  # Python floats: the same IEEE products, at a fraction of the cost
    if model == "bev":
        return np.array([cx, cy, length * c, length * s, width * c, width * s])
    return np.array([cx, cy, cz, length * c, length * s, width * c, width * s, height])

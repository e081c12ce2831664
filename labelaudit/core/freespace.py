"""Free-space evidence of LiDAR rays (docs/label-error.md, "Free space"): what a box must not contain.

A LiDAR return at ``p`` says the straight line from the sensor to ``p`` was empty before ``p``. A
vehicle's lower body — the slab from ``FREE_SPACE_SLAB[0]`` above the local ground up to
``FREE_SPACE_SLAB[1]`` × its height — is solid all over its footprint (no windows, no gap above
the hood), so a ray whose empty part passes through that slab more than a tolerance τ inside the
box's rectangle shows that the box covers empty space: it is shifted, turned or too large. A ray
stopped by an occluder in front of the box never reaches it and says nothing, so an occluded
correct box pays nothing.

This module owns

- the selection of the rays of a frame that can matter to each box (:func:`ray_candidates`: one
  compiled pass over the frame's points, bucketed by azimuth, then an exact segment test on the
  boxes' azimuth windows only);
- a box's evidence (:class:`FreeSpace`) and its counts (:func:`ray_counts`: rays through the slab
  that end behind the box, rays that end on or in it);
- the hinge rows the label-error fit adds per ray (:func:`free_rows_kernel`, called inside the
  compiled fit loop of :mod:`labelaudit.core.fit`).

No I/O; the ground plane under a box comes from the caller (:mod:`labelaudit.infer.evidence`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.int64]

__all__ = [
    "AzimuthBuckets",
    "FreeSpace",
    "PassingParts",
    "PointParts",
    "azimuth_buckets",
    "behind_other_returns",
    "ground_heights",
    "label_ray_terms",
    "neighbourhood_parts",
    "passing_parts",
    "passing_rays",
    "ray_candidate_parts",
    "ray_candidates",
    "ray_counts",
    "ray_depths",
    "through_own_returns",
]


@dataclass(frozen=True)
class FreeSpace:
    """The rays of a frame that may cross one box, and the ground they are measured from.

    Attributes
    ----------
    origin : (3,) sensor position (the start of every ray)
    ends : (M, 3) returns of the candidate rays (world frame)
    ground : (4,) local ground plane ``z = g0 + gx (x − x0) + gy (y − y0)`` as (g0, gx, gy, *unused*)
        with (x0, y0) = ``ref``
    ref : (2,) the point the plane is written about (the label's BEV centre)
    slab : (2,) heights above the ground of the solid slab's bottom and top (m)
    tolerance : τ (m): a ray counts only where it passes deeper than this inside the rectangle
    inside_tolerance : τ for rays that end inside the rectangle on the object (the box fit; m)
    object_height : a return this high above the ground (m) or higher is on the object, not the road
    """

    origin: FloatArray
    ends: FloatArray
    ground: FloatArray
    ref: FloatArray
    slab: tuple[float, float]
    tolerance: float
    inside_tolerance: float = C.FREE_SPACE_INSIDE_TOLERANCE
    object_height: float = C.DEFAULT_GROUND_CUT

    @property
    def num_rays(self) -> int:
        return len(self.ends)

    def heights(self) -> tuple[float, FloatArray]:
        """Height above the ground plane of the sensor and of every return (M,)."""
        h = ground_heights(np.vstack([self.origin[None, :], self.ends]), self.ground, self.ref)
        return float(h[0]), h[1:]

    @functools.cached_property
    def _inputs(self) -> tuple[FloatArray, float, float, FloatArray]:
        ends_t, _ = height_layout(self.ends, self.ground, self.ref)  # the rows of heights(), in one compiled pass
        ox, oy, oz = _floats(self.origin, 3)
        g0, gx, gy = _floats(self.ground, 3)
        x0, y0 = _floats(self.ref, 2)
        h0 = oz - (
            g0 + gx * (ox - x0) + gy * (oy - y0)
        )  # ground_heights of the sensor, in Python floats (the same IEEE operations)
        return (
            ends_t,
            float(self.origin[0]),
            float(self.origin[1]),
            np.array([h0, self.slab[0], self.slab[1], self.object_height]),
        )

    def kernel_inputs(self) -> tuple[FloatArray, float, float, FloatArray]:
        """The kernels' layout: ends_t (3, M) = x, y and height above the ground of the returns;
        the sensor's x, y; hz = (sensor height above the ground, slab bottom, slab top, object
        height). Computed once per box (the fit and both counts use it)."""
        return self._inputs

    @classmethod
    def with_kernel_inputs(
        cls,
        origin: FloatArray,
        ends: FloatArray,
        ground: FloatArray,
        ref: FloatArray,
        slab: tuple[float, float],
        tolerance: float,
        inside_tolerance: float,
        object_height: float,
        inputs: tuple[FloatArray, float, float, FloatArray],
    ) -> FreeSpace:
        """A :class:`FreeSpace` of these fields whose :meth:`kernel_inputs` are ``inputs`` (ends_t,
        the sensor's x and y as floats, hz: computed elsewhere with the same operations, as
        :meth:`set_kernel_inputs` takes them), made in one step: the frozen dataclass' ``__init__``
        sets each field through ``object.__setattr__`` (a few µs, per box of every frame)."""
        fs = object.__new__(cls)
        fs.__dict__.update(
            origin=origin,
            ends=ends,
            ground=ground,
            ref=ref,
            slab=slab,
            tolerance=tolerance,
            inside_tolerance=inside_tolerance,
            object_height=object_height,
            _inputs=inputs,
        )
        return fs

    def set_kernel_inputs(self, ends_t: FloatArray, hz: FloatArray) -> None:
        """Hand over :meth:`kernel_inputs`' ``ends_t`` (3, M) and ``hz`` (4,) computed elsewhere with
        the same operations (:func:`passing_parts`), instead of computing them on first use."""
        self.__dict__["_inputs"] = (ends_t, float(self.origin[0]), float(self.origin[1]), hz)


def _floats(v: ArrayLike, k: int) -> list[float]:
    """The first ``k`` values of a vector as Python floats (converted exactly)."""
    if type(v) is np.ndarray and v.ndim == 1 and (v.dtype == np.float64 or v.dtype == np.float32):
        return v[:k].tolist()
    return np.asarray(v, dtype=float)[:k].tolist()


def ground_heights(points: ArrayLike, ground: ArrayLike, ref: ArrayLike) -> FloatArray:
    """Height of points (N, ≥3) above the plane ``z = g0 + gx (x − x0) + gy (y − y0)`` (vertical, m)."""
    p = np.asarray(points, dtype=float)
    g = np.asarray(ground, dtype=float)
    r = np.asarray(ref, dtype=float)
    return p[:, 2] - (g[0] + g[1] * (p[:, 0] - r[0]) + g[2] * (p[:, 1] - r[1]))


def height_layout(points: NDArray, ground: ArrayLike, ref: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The kernels' layout of points (N, ≥3), float32 or float64: (3, N) rows x, y and
    :func:`ground_heights`, and z (N,), all float64 — the same operations, one compiled pass, no
    float64 copy of the rows."""
    g = np.asarray(ground, dtype=float)
    r = np.asarray(ref, dtype=float)
    p = np.asarray(points)
    if p.dtype != np.float32 and p.dtype != np.float64:  # the kernel reads native float32/float64 as they are
        p = np.asarray(p, dtype=np.float64)
    return _height_layout_kernel(p, float(g[0]), float(g[1]), float(g[2]), float(r[0]), float(r[1]))


@kernel
def _height_layout_kernel(p, g0, gx, gy, x0, y0):  # pragma: no cover - compiled
    """x, y, height above the plane (3, N) and z (N,) of points (N, ≥3): the float64 operations of
    :func:`ground_heights` in its order (no fast-math)."""
    n = p.shape[0]
    out = np.empty((3, n))
    z = np.empty(n)
    for k in range(n):
        x, y, zk = np.float64(p[k, 0]), np.float64(p[k, 1]), np.float64(p[k, 2])
        out[0, k] = x
        out[1, k] = y
        out[2, k] = zk - (g0 + gx * (x - x0) + gy * (y - y0))
        z[k] = zk
    return out, z


# ----------------------------------------------------------------------------------------------
# One ray against one rectangle: the deepest point of its empty part inside the slab
# ----------------------------------------------------------------------------------------------


@kernel(inline="always")
def _interval(o, d, lo, hi):  # pragma: no cover - compiled
    """t-interval where lo ≤ o + t·d ≤ hi (empty: t0 > t1)."""
    if d == 0.0:
        if lo <= o <= hi:
            return -math.inf, math.inf
        return math.inf, -math.inf
    a, b = (lo - o) / d, (hi - o) / d
    return (a, b) if a <= b else (b, a)


@kernel(inline="always")
def _try(t, t0, t1, ox, oy, dx, dy, hl, hw, best, tb):  # pragma: no cover - compiled
    """Depth at ray parameter t if t ∈ [t0, t1] and deeper than ``best``: the new (best, t)."""
    if t < t0 or t > t1:
        return best, tb
    dep = min(hl - abs(ox + t * dx), hw - abs(oy + t * dy))
    return (dep, t) if dep > best else (best, tb)


@kernel
def _deepest(ox, oy, oh, px, py, ph, hl, hw, zlo, zhi):  # pragma: no cover - compiled
    """Deepest point of the segment o → p (box frame; h = height above the ground) inside the prism
    |x| ≤ hl, |y| ≤ hw, zlo ≤ h ≤ zhi, in the BEV depth min(hl − |x|, hw − |y|).

    Returns (depth, t): depth −inf when the segment misses the prism. The depth is concave along
    the segment (a minimum of affine functions), so its maximum is at an end of the interval or
    where two of the four affine pieces cross: at most eight candidates, no allocation.
    """
    dx, dy, dh = px - ox, py - oy, ph - oh
    a0, a1 = _interval(ox, dx, -hl, hl)
    b0, b1 = _interval(oy, dy, -hw, hw)
    c0, c1 = _interval(oh, dh, zlo, zhi)
    t0 = max(0.0, a0, b0, c0)
    t1 = min(1.0, a1, b1, c1)
    if not t0 < t1:
        return -math.inf, 0.0
    return _deepest_between(t0, t1, ox, oy, dx, dy, hl, hw)


@kernel
def _deepest_between(t0, t1, ox, oy, dx, dy, hl, hw):  # pragma: no cover - compiled
    """(max, t) of m(t) = min(hl − |x(t)|, hw − |y(t)|) over t0 ≤ t ≤ t1 of the segment o + t·d:
    m is concave (a minimum of affine pieces), so the maximum is at an end or where two pieces
    cross — at most eight candidates."""
    best, tb = _try(t0, t0, t1, ox, oy, dx, dy, hl, hw, -math.inf, t0)
    best, tb = _try(t1, t0, t1, ox, oy, dx, dy, hl, hw, best, tb)
    if dx != 0.0:
        best, tb = _try(-ox / dx, t0, t1, ox, oy, dx, dy, hl, hw, best, tb)
    if dy != 0.0:
        best, tb = _try(-oy / dy, t0, t1, ox, oy, dx, dy, hl, hw, best, tb)
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            den = sx * dx - sy * dy  # hl − sx·x(t) = hw − sy·y(t)
            if den != 0.0:
                best, tb = _try((hl - hw - sx * ox + sy * oy) / den, t0, t1, ox, oy, dx, dy, hl, hw, best, tb)
    return best, tb


@kernel
def _signed_deepest(ox, oy, oh, px, py, ph, hl, hw, reach, zlo, zhi):  # pragma: no cover - compiled
    """Largest m(t) = min(hl − |x|, hw − |y|) (negative outside the rectangle) over the part of the
    segment inside the slab and within the rectangle grown by ``reach``; −inf when it misses that."""
    dx, dy, dh = px - ox, py - oy, ph - oh
    a0, a1 = _interval(ox, dx, -hl - reach, hl + reach)
    b0, b1 = _interval(oy, dy, -hw - reach, hw + reach)
    c0, c1 = _interval(oh, dh, zlo, zhi)
    t0 = max(0.0, a0, b0, c0)
    t1 = min(1.0, a1, b1, c1)
    if not t0 <= t1:
        return -math.inf
    return _deepest_between(t0, t1, ox, oy, dx, dy, hl, hw)[0]


@kernel
def displacement(y, y0, reach):  # pragma: no cover - compiled
    """Upper bound on how far any point's m moves between rectangles y0 and y, for points within
    ``reach`` of y0: centre shift + half the size changes + turn × (distance of such points from the
    centre); inf when that reaches ``reach`` (the bound no longer holds there)."""
    dyaw = abs((y[6] - y0[6] + math.pi) % (2.0 * math.pi) - math.pi)
    r = 0.5 * math.hypot(y0[3], y0[4]) + 1.5 * reach
    h = math.hypot(y[0] - y0[0], y[1] - y0[1]) + 0.5 * abs(y[3] - y0[3]) + 0.5 * abs(y[4] - y0[4]) + dyaw * r + 1e-9
    return h if h < reach else math.inf


@kernel
def _depths_kernel(y, ends_t, ox, oy, hz, out_depth, out_t):  # pragma: no cover - compiled
    """Deepest free depth (M,) and its ray parameter (M,) of every ray in the slab of box ``y``."""
    c, s = math.cos(y[6]), math.sin(y[6])
    rx, ry = ox - y[0], oy - y[1]
    bx, by = c * rx + s * ry, -s * rx + c * ry
    hl, hw = 0.5 * y[3], 0.5 * y[4]
    for k in range(ends_t.shape[1]):
        qx, qy = ends_t[0, k] - y[0], ends_t[1, k] - y[1]
        px, py = c * qx + s * qy, -s * qx + c * qy
        dep, t = _deepest(bx, by, hz[0], px, py, ends_t[2, k], hl, hw, hz[1], hz[2])
        out_depth[k] = dep
        out_t[k] = t


_ROW_MARGIN = (
    1e-9  # m; the rays' early skips keep this far from the depth they test (far above the rounding of depths in metres)
)


@kernel(inline="always")
def _axis_depth_bound(bx, by, px, py, hl, hw):  # pragma: no cover - compiled
    """An upper bound on the BEV depth min(hl − |x|, hw − |y|) all along the segment b → p (box
    frame), without its deepest point: with both ends on one side of an axis, |x| ≥ min(|bx|, |px|)
    all along it (likewise y). Exact up to the rounding of the points :func:`_deepest` evaluates
    (~1e-13 m): a test against it keeps a margin (``_ROW_MARGIN``)."""
    mx = min(abs(bx), abs(px)) if (bx > 0.0 and px > 0.0) or (bx < 0.0 and px < 0.0) else 0.0
    my = min(abs(by), abs(py)) if (by > 0.0 and py > 0.0) or (by < 0.0 and py < 0.0) else 0.0
    return min(hl - mx, hw - my)


@kernel
def free_rows_kernel(
    y, ends_t, ox, oy, hz, tau, tau_in, weight, slit, smooth, three_d, a, b, bounds, slack, floor
):  # pragma: no cover - compiled
    """Hinge rows of the box fit, one per ray: a (p, M) transposed like the point rows, b (M,).

    A ray whose empty part reaches depth d* > τ inside the slab of the current box ``y`` gives the
    row "the face nearest its deepest point q lies τ beyond q": ``nᵀ J(v*) φ = nᵀ q + τ`` with n the
    outward normal of that face and v* the unit coordinates of q's projection on it — the residual
    is d* − τ. A ray that *ends inside* the rectangle (at least the slab bottom above the ground:
    on the object, not on the road under it) proves less — real surfaces lie up to a few decimetres
    inside a correct label (bumpers, rounded corners, loose annotation) — and gets the looser
    ``tau_in``. The rows of the active rays are written to the first columns of a and b; returns
    their number. Rays whose bound (:func:`label_ray_terms`) plus ``slack`` stays below the smaller
    tolerance less 1.5 ``smooth`` are not evaluated (``slack`` = inf evaluates all): exact, a row
    needs a blended depth (below) more than τ − w/2, and that depth is less than w beyond d*. Two
    further skips are as exact (``_ROW_MARGIN`` above the rounding): a ray whose ends lie on one
    side of an axis far enough out that no point between them is deeper than that least depth (no
    deepest point computed), and one whose d* + w stays below its own tolerance less w/2 (no blend).

    The rows are continuous in the box (``smooth`` = w > 0, metres), so that the fit's result is a
    continuous function of its inputs and a last-bit change of them moves it by as little:

    - the faces within w of the nearest one at q share the row, face f with weight
      u_f ∝ 1 − (d_f − d*)/w (normalised), and the depth is their mean Σ u_f d_f — a ray whose
      deepest point lies on the diagonal between two faces (through a corner region) pulls both,
      where a hard choice of the nearest face flipped on the input's last bit;
    - the tolerance goes from τ to ``tau_in`` as the ray's end goes from the rectangle's edge to
      w inside it (it jumped by ``tau_in`` − τ there);
    - the hinge is rounded: with r = Σ u_f d_f − τ the residual is h(r) = (r + w/2)² / 2w for
      |r| < w/2, r beyond (0 below), and the row is the Gauss–Newton row of h: h′(r) × the linear
      row, whose residual at the box is r (the row switched on at full weight at r = 0 before).

    What stays discontinuous: a ray exactly parallel to a face has a flat deepest stretch, and
    which end of it is q (its position along the face) jumps as the box turns through parallel.

    Robust: a ray through the slab of a *right* box is possible — a gap between a truck's cab and
    its cargo box, open structure, a return through glass — and no box can exclude it (the ray
    crosses it from side to side). Each ray is therefore a mixture of the Gaussian hinge (σ) and a
    "slit" of prior probability ``slit``; its row is weighted by the responsibility of the hinge,
    (1 − slit)·e^(−h²/2σ²) / ((1 − slit)·e^(−h²/2σ²) + slit) with h = h(r) and σ = ``hz[4]``
    (iteratively reweighted: as the fit moves, deep rays become shallow and count again). A ray's
    weight is never below ``floor[k]``, its weight at the label (:func:`label_ray_terms`): a ray
    the label respects is no slit, and the fit cannot slide through it (without the floor a fit
    that had jumped past a ray, into free space, stopped counting it).
    """
    c, s = math.cos(y[6]), math.sin(y[6])
    rx, ry = ox - y[0], oy - y[1]
    bx, by = c * rx + s * ry, -s * rx + c * ry
    hl, hw = 0.5 * y[3], 0.5 * y[4]
    d = 3 if three_d else 2
    p = a.shape[0]
    tmin = min(tau, tau_in) - 1.5 * smooth  # the least depth of a ray with a row (below)
    half = 0.5 * smooth
    active = 0
    for k in range(ends_t.shape[1]):
        if bounds[k] + slack < tmin:
            continue
        qx, qy = ends_t[0, k] - y[0], ends_t[1, k] - y[1]
        px, py = c * qx + s * qy, -s * qx + c * qy
        # below the least depth with a row (by more than the rounding of _deepest's points) all along
        # the segment: no row, without the deepest point
        if _axis_depth_bound(bx, by, px, py, hl, hw) < tmin - _ROW_MARGIN:
            continue
        dep, t = _deepest(bx, by, hz[0], px, py, ends_t[2, k], hl, hw, hz[1], hz[2])
        if not dep > tmin:
            continue
        tk = tau
        if ends_t[2, k] >= hz[3]:  # an end on the object, not on the road: τ → τ_in within w of the edge
            inside = min(hl - abs(px), hw - abs(py))
            if inside > 0.0:
                tk = tau + (tau_in - tau) * min(inside / smooth, 1.0)
        lx, ly = bx + t * (px - bx), by + t * (py - by)  # deepest point, box frame
        d0, d1, d2, d3 = hl + lx, hl - lx, hw + ly, hw - ly  # its depth inside the −l, +l, −w, +w face
        dmin = min(d0, d1, d2, d3)
        if dmin + smooth - tk < -half - _ROW_MARGIN:  # r < dmin + w − τ_k (below): no row, without the blend
            continue
        u0 = max(0.0, 1.0 - (d0 - dmin) / smooth)
        u1 = max(0.0, 1.0 - (d1 - dmin) / smooth)
        u2 = max(0.0, 1.0 - (d2 - dmin) / smooth)
        u3 = max(0.0, 1.0 - (d3 - dmin) / smooth)
        su = u0 + u1 + u2 + u3
        u0, u1, u2, u3 = u0 / su, u1 / su, u2 / su, u3 / su
        r = u0 * d0 + u1 * d1 + u2 * d2 + u3 * d3 - tk
        if not r > -half:
            continue
        if r < half:  # the smoothed hinge h(r) and its slope h′(r)
            hr, dh = (r + half) * (r + half) / (2.0 * smooth), (r + half) / smooth
        else:
            hr, dh = r, 1.0
        j = active
        active += 1
        g = (1.0 - slit) * math.exp(-0.5 * hr * hr / (hz[4] * hz[4]))
        wk = weight * math.sqrt(g / (g + slit)) if slit > 0.0 else weight
        if floor.shape[0] and floor[k] > wk:
            wk = floor[k]
        # Σ u_f n_f, Σ u_f v0_f n_f, Σ u_f v1_f n_f in the box frame (n_f: the face's outward normal,
        # (v0_f, v1_f): the unit coordinates of q's projection on it), then turned to the world
        nx, ny = u1 - u0, u3 - u2
        lx_, ly_ = 0.5 * (u0 + u1), lx / y[3] * ny
        wx_, wy_ = ly / y[4] * nx, 0.5 * (u2 + u3)
        n0, n1 = c * nx - s * ny, s * nx + c * ny
        l0, l1 = c * lx_ - s * ly_, s * lx_ + c * ly_
        w0, w1 = c * wx_ - s * wy_, s * wx_ + c * wy_
        qwx = y[0] + c * lx - s * ly  # deepest point, world
        qwy = y[1] + s * lx + c * ly
        # Gauss–Newton row of the residual h(r): slope h′ times the linear row, whose residual is r
        ws = wk * dh
        for i in range(p):
            a[i, j] = 0.0
        a[0, j] = ws * n0
        a[1, j] = ws * n1
        a[d, j] = ws * l0
        a[d + 1, j] = ws * l1
        a[d + 2, j] = ws * w1
        a[d + 3, j] = -ws * w0
        b[j] = ws * (n0 * qwx + n1 * qwy + tk + r) - wk * hr
    return active


@kernel
def label_ray_terms(
    y, ends_t, ox, oy, hz, tau, tau_in, weight, slit, reach, bounds, floor
):  # pragma: no cover - compiled
    """What the fit needs of every ray (M,) at the label ``y``, in one pass: its bound into
    ``bounds``, and into ``floor`` the √weight the fit's hinge row (:func:`free_rows_kernel`) has
    at the label: the slit mixture's responsibility of the hinge at the ray's depth in the label's
    slab beyond its tolerance (0 beyond: the full ``weight`` (1 − slit)^½ at the surface,
    ``weight`` when the slit is off).

    The depth and tolerance are the plain ones (nearest face, τ or τ inside by where the ray ends):
    the fit's floor, fixed by the label and the rays, never by the fit's path.

    The bound is the largest signed depth m of the ray's empty part in the slab of ``y`` (−inf
    beyond ``reach``). m moves by at most the boundary displacement H of the rectangle
    (:func:`displacement`), so a ray with m + H below the least depth that gives a row
    (:func:`free_rows_kernel`) cannot be active for a box within H of ``y``: the fit skips it,
    exactly. A ray's depth at ``y`` is at most its bound (the bound's prism holds the depth's), so a
    ray whose bound stays below both tolerances — most rays — has the weight at the surface without
    its depth being computed: the same value (the 1e-6 m margin is far above the rounding of either
    maximum).
    """
    c, s = math.cos(y[6]), math.sin(y[6])
    rx, ry = ox - y[0], oy - y[1]
    bx, by = c * rx + s * ry, -s * rx + c * ry
    hl, hw = 0.5 * y[3], 0.5 * y[4]
    shallow = min(tau, tau_in) - 1e-6  # a bound below this: r = 0 below
    g0 = 1.0 - slit  # the mixture below at r = 0 (its exponential is exactly 1)
    at_surface = weight * math.sqrt(g0 / (g0 + slit)) if slit > 0.0 else weight
    for k in range(ends_t.shape[1]):
        qx, qy = ends_t[0, k] - y[0], ends_t[1, k] - y[1]
        px, py = c * qx + s * qy, -s * qx + c * qy
        bounds[k] = _signed_deepest(bx, by, hz[0], px, py, ends_t[2, k], hl, hw, reach, hz[1], hz[2])
        if slit <= 0.0 or not bounds[k] > shallow:
            floor[k] = at_surface
            continue
        dep = _deepest(bx, by, hz[0], px, py, ends_t[2, k], hl, hw, hz[1], hz[2])[0]
        ends_in = abs(px) <= hl and abs(py) <= hw and ends_t[2, k] >= hz[3]
        r = max(dep - (tau_in if ends_in else tau), 0.0)
        g = (1.0 - slit) * math.exp(-0.5 * r * r / (hz[4] * hz[4]))
        floor[k] = weight * math.sqrt(g / (g + slit))


def ray_depths(box: ArrayLike, fs: FreeSpace) -> tuple[FloatArray, FloatArray]:
    """Deepest free depth (M,) of every candidate ray inside the slab of ``box``, and its ray
    parameter t ∈ [0, 1] (M,) (−inf / 0 for rays that miss the slab).

    The depth is measured in bird's-eye view from the nearest side of the box rectangle; only the
    empty part of a ray (before its return) counts.
    """
    y = np.asarray(box, dtype=float)
    m = fs.num_rays
    dep, t = np.empty(m), np.empty(m)
    if m:
        ends_t, ox, oy, hz = fs.kernel_inputs()
        _depths_kernel(y, ends_t, ox, oy, hz, dep, t)
    return dep, t


def passing_rays(box: ArrayLike, fs: FreeSpace) -> tuple[NDArray[np.bool_], FloatArray]:
    """The rays (M,) whose empty part passes through the slab of ``box`` deeper than τ and that end
    behind or under it (not on or in it: the rule of ``free_rays``), and the distance (M,) from the
    sensor to each one's deepest point in the slab (3-D, m; NaN for the others)."""
    y = np.asarray(box, dtype=float)
    m = fs.num_rays
    passing = np.zeros(m, dtype=np.bool_)
    reach = np.full(m, np.nan)
    if m:
        dep, t = ray_depths(y, fs)
        _passing_kernel(
            y,
            fs.ends,
            fs.origin,
            dep,
            t,
            fs.tolerance,
            fs.kernel_inputs()[0][2],
            fs.object_height,
            passing,
            reach,
        )
    return passing, reach


@kernel
def _passing_kernel(y, ends, o, dep, t, tau, h_end, object_height, passing, reach):  # pragma: no cover - compiled
    """:func:`passing_rays` per ray; ``h_end`` the rays' end heights above the ground."""
    c, s = math.cos(y[6]), math.sin(y[6])
    hl, hw, top = 0.5 * y[3], 0.5 * y[4], y[2] + 0.5 * y[5]
    for k in range(ends.shape[0]):
        if not dep[k] > tau:
            continue
        qx, qy = ends[k, 0] - y[0], ends[k, 1] - y[1]
        px, py = c * qx + s * qy, -s * qx + c * qy
        if abs(px) <= hl + tau and abs(py) <= hw + tau and h_end[k] >= object_height and ends[k, 2] <= top + tau:
            continue  # ends on or in the box: not a ray through it
        dx, dy, dz = ends[k, 0] - o[0], ends[k, 1] - o[1], ends[k, 2] - o[2]
        passing[k] = True
        reach[k] = t[k] * math.sqrt(dx * dx + dy * dy + dz * dz)


class PassingParts(NamedTuple):
    """:func:`passing_parts` of B boxes whose rays are the parts ``starts`` of a flat (M, 3) array.

    Attributes
    ----------
    ends_t : (3 M,) box j's :meth:`FreeSpace.kernel_inputs` ``ends_t`` is ``ends_t[3 s:3 e]`` as (3, e − s),
        with s, e = starts[j], starts[j + 1]
    hz : (B, 4) each box's ``hz`` of :meth:`FreeSpace.kernel_inputs`
    passing, reach : (M,) :func:`passing_rays` of every box's rays, in the rays' order
    any_passing : (B,) whether a ray of the box passes
    """

    ends_t: FloatArray
    hz: FloatArray
    passing: NDArray[np.bool_]
    reach: FloatArray
    any_passing: NDArray[np.bool_]


def passing_parts(
    boxes: ArrayLike,
    ends: FloatArray,
    starts: IndexArray,
    grounds: ArrayLike,
    slabs: ArrayLike,
    origin: ArrayLike,
    tolerance: float,
    object_height: float,
) -> PassingParts:
    """:func:`passing_rays` and the kernels' layout (:meth:`FreeSpace.kernel_inputs`) of B boxes in
    one compiled call: box j's rays are ``ends[starts[j]:starts[j + 1]]`` (float64), its
    :class:`FreeSpace` has the ground ``grounds[j]`` (g0, gx, gy) about its BEV centre, the slab
    ``slabs[j]``, the sensor ``origin`` and τ = ``tolerance``. The same operations, in the same
    order, as those functions box by box."""
    b = np.ascontiguousarray(boxes, dtype=float).reshape(-1, 7)
    e = np.ascontiguousarray(ends, dtype=float).reshape(-1, 3)
    m = len(e)
    out = PassingParts(
        np.empty(3 * m),
        np.empty((len(b), 4)),
        np.zeros(m, dtype=np.bool_),
        np.full(m, np.nan),
        np.zeros(len(b), dtype=np.bool_),
    )
    _passing_parts_kernel(
        b,
        e,
        np.ascontiguousarray(starts, dtype=np.int64),
        np.ascontiguousarray(np.asarray(grounds, dtype=float)[:, :3]),
        np.ascontiguousarray(slabs, dtype=float),
        np.asarray(origin, dtype=float).reshape(3),
        float(tolerance),
        float(object_height),
        *out,
    )
    return out


@kernel
def _passing_parts_kernel(
    boxes, ends, starts, grounds, slabs, o, tau, object_height, ends_t, hz, passing, reach, any_passing
):  # pragma: no cover - compiled
    """:func:`passing_parts`: per box, :func:`height_layout` of its rays and the sensor's height
    about its centre (as :meth:`FreeSpace.kernel_inputs`), then :func:`ray_depths` and
    :func:`passing_rays`."""
    for j in range(boxes.shape[0]):
        y = boxes[j]
        s, e = starts[j], starts[j + 1]
        m = e - s
        g0, gx, gy = grounds[j, 0], grounds[j, 1], grounds[j, 2]
        hz[j, 0] = o[2] - (g0 + gx * (o[0] - y[0]) + gy * (o[1] - y[1]))
        hz[j, 1], hz[j, 2], hz[j, 3] = slabs[j, 0], slabs[j, 1], object_height
        if m == 0:
            continue
        lay = np.empty((3, m))
        for k in range(m):
            x, yk, zk = ends[s + k, 0], ends[s + k, 1], ends[s + k, 2]
            lay[0, k] = x
            lay[1, k] = yk
            lay[2, k] = zk - (g0 + gx * (x - y[0]) + gy * (yk - y[1]))
        for r in range(3):
            for k in range(m):
                ends_t[3 * s + r * m + k] = lay[r, k]
        dep = np.empty(m)
        t = np.empty(m)
        _depths_kernel(y, lay, o[0], o[1], hz[j], dep, t)
        _passing_kernel(y, ends[s:e], o, dep, t, tau, lay[2], object_height, passing[s:e], reach[s:e])
        for k in range(s, e):
            if passing[k]:
                any_passing[j] = True
                break


def through_own_returns(
    box: ArrayLike,
    fs: FreeSpace,
    own: ArrayLike,
    angle: float = C.FREE_SPACE_SIGHT_ANGLE,
    passing: tuple[NDArray[np.bool_], FloatArray] | None = None,
) -> NDArray[np.bool_]:
    """Rays (M,) that pass through the slab of ``box`` deeper than τ *beyond its own returns*: the
    object is see-through there, it is not empty space inside the box.

    A ray whose empty part crosses the slab and that ends behind or under the box
    (:func:`passing_rays`) is flagged when the box's own returns ``own`` (the points of the object:
    inside its rectangle, above the ground cut) lie on both sides of its azimuth within ``angle``,
    seen from the sensor, more than τ nearer than the ray's deepest point in the slab. Rays in the
    same direction stopped on the object in front of where this one went: this one passed under its
    chassis, through its glass or an open structure (the real KITTI truck 000019:0 has 1,106 such
    rays under its chassis). A label shifted, turned or grown into empty space covers road *beside*
    its object, where no return of it lies in the rays' direction, so its free rays stay; "both
    sides" keeps the rays just past the object's outline, which have its returns on one side only.
    The window is a little more than one column of the scanner (KITTI's HDL-64E 0.17°, Waymo's top
    lidar 0.14°, Argoverse 2's 0.2°), so a ray inside the outline has the neighbouring columns' returns.

    Parameters
    ----------
    box : (7,) the box
    fs : its rays (``fs.ends``, M) and ground
    own : (N, ≥3) the box's own returns
    angle : half-width of the azimuth window (rad): about one column of the sensor
    passing : :func:`passing_rays` of ``box`` and ``fs``, when the caller has it

    Returns
    -------
    (M,) bool
    """
    y = np.asarray(box, dtype=float)
    m = fs.num_rays
    pts = np.asarray(own, dtype=float)
    if m == 0 or len(pts) == 0:
        return np.zeros(m, dtype=bool)
    crossing, reach = passing_rays(y, fs) if passing is None else passing
    o = fs.origin
    centre = math.atan2(y[1] - o[1], y[0] - o[0])
    az = np.angle(np.exp(1j * (np.arctan2(pts[:, 1] - o[1], pts[:, 0] - o[0]) - centre)))
    # any sort will do: the kernel's answer for a ray depends on the set of returns in its window, not
    # on the order of equal azimuths (NumPy's default sort is ~2.5x faster than the stable one here)
    order = np.argsort(az)
    near = pts.take(order, axis=0)  # take: a fraction of fancy indexing's cost on 2-D arrays
    out = np.zeros(m, dtype=np.bool_)
    _through_kernel(
        fs.ends,
        o,
        centre,
        crossing,
        reach,
        fs.tolerance,
        az.take(order),
        np.hypot(near[:, 0] - o[0], near[:, 1] - o[1]),
        float(angle),
        out,
    )
    return out


@kernel
def _through_kernel(ends, o, centre, passing, reach, tau, own_az, own_r, angle, out):  # pragma: no cover - compiled
    """:func:`through_own_returns` per ray: ``own_az`` sorted azimuths of the own returns relative
    to ``centre``, ``own_r`` their BEV ranges."""
    n = own_az.shape[0]
    for k in range(ends.shape[0]):
        if not passing[k]:
            continue
        ex, ey, ez = ends[k, 0] - o[0], ends[k, 1] - o[1], ends[k, 2] - o[2]
        a = math.atan2(ey, ex) - centre
        a = (a + math.pi) % (2.0 * math.pi) - math.pi
        deepest = reach[k] * math.sqrt(ex * ex + ey * ey) / math.sqrt(ex * ex + ey * ey + ez * ez) - tau  # BEV
        left = right = False  # a nearer return on each side: the ray is inside the object's outline, not past its edge
        i = np.searchsorted(own_az, a - angle)
        while i < n and own_az[i] <= a + angle and not (left and right):
            if own_r[i] < deepest:
                if own_az[i] <= a:
                    left = True
                if own_az[i] >= a:
                    right = True
            i += 1
        out[k] = left and right


def behind_other_returns(
    box: ArrayLike,
    fs: FreeSpace,
    buckets: AzimuthBuckets,
    angle: float = C.FREE_SPACE_SAME_RAY_ANGLE,
    passing: tuple[NDArray[np.bool_], FloatArray] | None = None,
) -> NDArray[np.bool_]:
    """Rays (M,) through the slab of ``box`` (:func:`passing_rays`) that are *second returns*: another
    point of the frame lies in the same direction from the sensor (within ``angle``) more than τ
    nearer than the ray's deepest point in the slab. That point is on the ray: the ray went on
    through something that returned — glass, foliage, a dual-return sensor's first return, the
    road seen through a vehicle — so it is not an empty ray up to its end. Two returns of a
    single-return spinning lidar are never this close in direction (its beams are ≥ 0.33° apart in
    elevation, its columns 0.14–0.2° apart in azimuth). ``buckets`` must hold the frame's points
    around the box (:func:`azimuth_buckets`); points nearer than every box of the frame are not in
    them (they cannot be compared). ``passing``: :func:`passing_rays` of ``box`` and ``fs``, when the
    caller has it.
    """
    y = np.asarray(box, dtype=float)
    m = fs.num_rays
    out = np.zeros(m, dtype=np.bool_)
    if m == 0 or len(buckets.kept) == 0:
        return out
    crossing, reach = passing_rays(y, fs) if passing is None else passing
    nbins = len(buckets.starts) - 1
    _same_ray_kernel(
        fs.ends,
        fs.origin,
        crossing,
        reach,
        fs.tolerance,
        buckets.xyz,
        buckets.kept,
        buckets.bins,
        nbins,
        float(angle),
        out,
    )
    return out


@kernel
def _same_ray_kernel(ends, o, passing, reach, tau, pts, kept, bins, nbins, angle, out):  # pragma: no cover - compiled
    """:func:`behind_other_returns` per ray: the bucketed points (``kept`` indices into ``pts``, in
    point order, ``bins`` their azimuth bins) of the ray's azimuth bin and its two neighbours. The
    answer of a ray is whether *any* such point is on it, so the points are visited once, in point
    order, each against the passing rays of its bin and the two neighbouring bins."""
    m = ends.shape[0]
    scale = nbins / 4.0
    sin2 = math.sin(angle) ** 2
    u = np.empty((m, 3))
    near2 = np.empty(m)
    ray_bin = np.empty(m, dtype=np.int64)
    at = np.zeros(nbins + 1, dtype=np.int64)  # the passing rays by bin: at[q]:at[q + 1] of by_bin
    left = 0
    for k in range(m):
        if not passing[k]:
            continue
        ux, uy, uz = ends[k, 0] - o[0], ends[k, 1] - o[1], ends[k, 2] - o[2]
        un = math.sqrt(ux * ux + uy * uy + uz * uz)
        u[k, 0], u[k, 1], u[k, 2] = ux / un, uy / un, uz / un
        near2[k] = (reach[k] - tau) ** 2
        q = min(max(int(_pseudo_angle(ends[k, 0] - o[0], ends[k, 1] - o[1]) * scale), 0), nbins - 1)
        ray_bin[k] = q
        at[q + 1] += 1
        left += 1
    if left == 0:
        return
    for q in range(nbins):
        at[q + 1] += at[q]
    by_bin = np.empty(left, dtype=np.int64)
    fill = at[:nbins].copy()
    seen = np.zeros(nbins, dtype=np.bool_)  # a passing ray in the bin or one of its two neighbours
    for k in range(m):
        if passing[k]:
            q = ray_bin[k]
            by_bin[fill[q]] = k
            fill[q] += 1
            for dq in (-1, 0, 1):
                seen[(q + dq) % nbins] = True
    for t in range(kept.shape[0]):
        b = bins[t]
        if not seen[b]:
            continue
        i = kept[t]
        vx, vy, vz = np.float64(pts[i, 0]) - o[0], np.float64(pts[i, 1]) - o[1], np.float64(pts[i, 2]) - o[2]
        v2 = vx * vx + vy * vy + vz * vz
        if v2 == 0.0:
            continue
        for dq in (-1, 0, 1):  # the rays whose bin's neighbourhood holds bin b
            q = (b + dq) % nbins
            for a in range(at[q], at[q + 1]):
                k = by_bin[a]
                if out[k] or v2 >= near2[k]:
                    continue
                ux, uy, uz = u[k, 0], u[k, 1], u[k, 2]
                cx, cy, cz = uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx  # |u × v|² = sin² · |v|²
                if cx * cx + cy * cy + cz * cz <= sin2 * v2 and ux * vx + uy * vy + uz * vz > 0.0:
                    out[k] = True
                    left -= 1
        if left == 0:
            return


def ray_counts(box: ArrayLike, fs: FreeSpace, points: ArrayLike | None) -> tuple[int, int] | list[tuple[int, int]]:
    """(free, end) ray counts of ``box``: rays through its slab deeper than τ that end *behind* it,
    and rays that end on or in it.

    A return is "on or in" the box when it lies within τ of the box rectangle in bird's-eye view,
    at least ``fs.object_height`` above the local ground and at most τ above the box top. ``points`` are
    the returns near the box (a crop containing the box grown by τ); None counts none. ``box`` may
    be (B, 7) (a label and its suggested box): a list of B pairs, the returns' layout built once.
    """
    y = np.asarray(box, dtype=float)
    many = y.ndim == 2
    ys = y.reshape(-1, 7)
    ends_t, ox, oy, hz = fs.kernel_inputs() if fs.num_rays else (None, 0.0, 0.0, None)
    p = None if points is None else np.asarray(points)
    if (
        ends_t is not None and p is not None and len(p) and p.dtype in (np.float32, np.float64)
    ):  # the usual case: one compiled call
        g, r = fs.ground, fs.ref
        counts = np.empty((len(ys), 2), dtype=np.int64)
        _counts_kernel(
            ys,
            ends_t,
            ox,
            oy,
            hz,
            fs.tolerance,
            fs.ends[:, 2],
            p,
            float(g[0]),
            float(g[1]),
            float(g[2]),
            float(r[0]),
            float(r[1]),
            float(fs.object_height),
            counts,
        )
        out = [(int(f), int(e)) for f, e in counts.tolist()]
        return out if many else out[0]
    near = None
    if points is not None and len(points):
        near = height_layout(points, fs.ground, fs.ref)
        hz_end = np.array([0.0, 0.0, 0.0, fs.object_height])
    out = []
    for yb in ys:
        free = (
            int(_count_kernel(yb, ends_t, ox, oy, hz, fs.tolerance, True, fs.ends[:, 2])) if ends_t is not None else 0
        )
        end = int(_count_kernel(yb, near[0], 0.0, 0.0, hz_end, fs.tolerance, False, near[1])) if near is not None else 0
        out.append((free, end))
    return out if many else out[0]


@kernel
def _counts_kernel(
    ys, ends_t, ox, oy, hz, tau, ends_z, p, g0, gx, gy, x0, y0, object_height, out
):  # pragma: no cover - compiled
    """:func:`ray_counts` of the boxes ``ys`` (B, 7) into ``out`` (B, 2) in one call: the returns'
    layout (:func:`height_layout` of ``p``), then the free and the end count of every box."""
    near_t, near_z = _height_layout_kernel(p, g0, gx, gy, x0, y0)
    hz_end = np.zeros(4)
    hz_end[3] = object_height
    for j in range(ys.shape[0]):
        out[j, 0] = _count_kernel(ys[j], ends_t, ox, oy, hz, tau, True, ends_z)
        out[j, 1] = _count_kernel(ys[j], near_t, 0.0, 0.0, hz_end, tau, False, near_z)


@kernel
def _count_kernel(y, ends_t, ox, oy, hz, tau, free, z):  # pragma: no cover - compiled
    """``free``: rays deeper than τ in the slab of ``y`` whose return is not on or in it; else the
    returns on or in it (within τ of the rectangle, ≥ hz[3] above the ground, ≤ τ over the top). A
    ray that :func:`_axis_depth_bound` keeps short of τ is not counted without its deepest point."""
    c, s = math.cos(y[6]), math.sin(y[6])
    rx, ry = ox - y[0], oy - y[1]
    bx, by = c * rx + s * ry, -s * rx + c * ry
    hl, hw, top = 0.5 * y[3], 0.5 * y[4], y[2] + 0.5 * y[5]
    count = 0
    for k in range(ends_t.shape[1]):
        qx, qy = ends_t[0, k] - y[0], ends_t[1, k] - y[1]
        px, py = c * qx + s * qy, -s * qx + c * qy
        on = abs(px) <= hl + tau and abs(py) <= hw + tau and ends_t[2, k] >= hz[3] and z[k] <= top + tau
        if not free:
            count += on
            continue
        if on:
            continue
        if _axis_depth_bound(bx, by, px, py, hl, hw) < tau - _ROW_MARGIN:  # not deeper than τ anywhere
            continue
        dep, _ = _deepest(bx, by, hz[0], px, py, ends_t[2, k], hl, hw, hz[1], hz[2])
        count += dep > tau
    return count


# ----------------------------------------------------------------------------------------------
# The frame pass: which rays can reach which box
# ----------------------------------------------------------------------------------------------


@kernel
def _pseudo_angle(x, y):  # pragma: no cover - compiled
    """A monotone stand-in for atan2 in [0, 4) (the "diamond angle"): no transcendental call."""
    ax, ay = abs(x), abs(y)
    if ax + ay == 0.0:
        return 0.0
    if y >= 0.0:
        return y / (ax + ay) if x >= 0.0 else 2.0 - y / (ax + ay)
    return 2.0 - y / (ax + ay) if x < 0.0 else 4.0 + y / (ax + ay)


@kernel
def _bucket_kernel(pts, ox, oy, nbins, min_r2, ranges):  # pragma: no cover - compiled
    """The points at least √min_r2 from the sensor (nearer ones cannot reach any box) whose azimuth
    bin (seen from the sensor) some box's window covers (``ranges`` (K, 4), two inclusive bin ranges
    per box): their indices (M,) in point order, their bins (M,), and the number of them before
    each bin (nbins + 1,)."""
    wanted = np.zeros(nbins, dtype=np.bool_)
    for j in range(ranges.shape[0]):
        for r in range(2):
            for q in range(ranges[j, 2 * r], ranges[j, 2 * r + 1] + 1):
                wanted[q] = True
    n = pts.shape[0]
    kept = np.empty(n, dtype=np.int64)
    kept_bin = np.empty(n, dtype=np.int64)
    counts = np.zeros(nbins + 1, dtype=np.int64)
    scale = nbins / 4.0
    m = 0
    for k in range(n):
        x, y = pts[k, 0] - ox, pts[k, 1] - oy
        if x * x + y * y < min_r2:
            continue
        q = min(max(int(_pseudo_angle(x, y) * scale), 0), nbins - 1)
        if not wanted[q]:
            continue
        kept[m], kept_bin[m] = k, q
        m += 1
        counts[q + 1] += 1
    for q in range(nbins):
        counts[q + 1] += counts[q]
    return kept[:m].copy(), kept_bin[:m].copy(), counts


@kernel
def _windows_kernel(ranges, starts):  # pragma: no cover - compiled
    """The boxes' windows by bin: the boxes (B,) whose window covers bin q are
    ``boxes_of[at[q]:at[q + 1]]``, in box order; and each box's part (B + 1,) of a buffer that can
    hold every bucketed point of its window (``starts``: bucketed points before each bin)."""
    nbins = starts.shape[0] - 1
    b = ranges.shape[0]
    at = np.zeros(nbins + 1, dtype=np.int64)
    part = np.zeros(b + 1, dtype=np.int64)
    for j in range(b):
        w = 0
        for r in range(2):
            q0, q1 = ranges[j, 2 * r], ranges[j, 2 * r + 1]
            if q0 > q1:
                continue
            w += starts[q1 + 1] - starts[q0]
            for q in range(q0, q1 + 1):
                at[q + 1] += 1
        part[j + 1] = part[j] + w
    for q in range(nbins):
        at[q + 1] += at[q]
    fill = at[:nbins].copy()
    boxes_of = np.empty(at[nbins], dtype=np.int64)
    for j in range(b):
        for r in range(2):
            q0, q1 = ranges[j, 2 * r], ranges[j, 2 * r + 1]
            if q0 > q1:
                continue
            for q in range(q0, q1 + 1):
                boxes_of[fill[q]] = j
                fill[q] += 1
    return at, boxes_of, part


@kernel
def _compact_parts(idx, xyz, part, end):  # pragma: no cover - compiled
    """Box j's entries are ``part[j]:end[j]`` of ``idx`` (n,) and ``xyz`` (n, 3): moved down in place
    so that they follow each other; the parts' starts (B + 1,)."""
    b = part.shape[0] - 1
    starts = np.zeros(b + 1, dtype=np.int64)
    d = 0
    for j in range(b):
        for p in range(part[j], end[j]):  # d ≤ p: a forward copy in place
            idx[d] = idx[p]
            xyz[d, 0], xyz[d, 1], xyz[d, 2] = xyz[p, 0], xyz[p, 1], xyz[p, 2]
            d += 1
        starts[j + 1] = d
    return starts


@kernel(inline="always")
def _hits(ox, oy, oh, px, py, ph, hl, hw, zlo, zhi):  # pragma: no cover - compiled
    """Whether the segment o → p (box frame, heights above the ground) meets the prism."""
    a0, a1 = _interval(ox, px - ox, -hl, hl)
    b0, b1 = _interval(oy, py - oy, -hw, hw)
    c0, c1 = _interval(oh, ph - oh, zlo, zhi)
    return max(0.0, a0, b0, c0) < min(1.0, a1, b1, c1)


@kernel
def _select_kernel(
    pts, kept, bins, starts, ranges, near2, boxes, ground, ox, oy, oz, reach, slabs
):  # pragma: no cover - compiled
    """For each box, the bucketed points of its azimuth window whose ray from the sensor passes
    through its reach prism (rectangle grown by ``reach``, slab heights above its ground plane):
    indices (sorted per box), their xyz as float64 and each box's start (B + 1,), box after box.
    The bucketed points (``kept``, ``bins``) are visited once in point order, each against the
    boxes whose window holds its bin, so each box's part comes out sorted."""
    b = boxes.shape[0]
    at, boxes_of, part = _windows_kernel(ranges, starts)
    cs = np.empty((b, 6))  # per box: cos, sin, the sensor in its frame (x, y, height), the ground's g0
    for j in range(b):
        y = boxes[j]
        c, s = math.cos(y[6]), math.sin(y[6])
        rx, ry = ox - y[0], oy - y[1]
        cs[j, 0], cs[j, 1] = c, s
        cs[j, 2], cs[j, 3] = c * rx + s * ry, -s * rx + c * ry
        cs[j, 4] = oz - ground[j, 0] - ground[j, 1] * (ox - y[0]) - ground[j, 2] * (oy - y[1])
    idx = np.empty(part[b], dtype=np.int64)
    xyz = np.empty((part[b], 3))
    end = part[:b].copy()
    for t in range(kept.shape[0]):
        q = bins[t]
        if at[q] == at[q + 1]:
            continue
        i = kept[t]
        ex, ey = pts[i, 0] - ox, pts[i, 1] - oy
        e2 = ex * ex + ey * ey
        for a in range(at[q], at[q + 1]):
            j = boxes_of[a]
            if e2 < near2[j]:  # ends before the grown rectangle
                continue
            y = boxes[j]
            c, s = cs[j, 0], cs[j, 1]
            qx, qy = pts[i, 0] - y[0], pts[i, 1] - y[1]
            px, py = c * qx + s * qy, -s * qx + c * qy
            ph = pts[i, 2] - ground[j, 0] - ground[j, 1] * qx - ground[j, 2] * qy
            hl, hw = 0.5 * y[3] + reach, 0.5 * y[4] + reach
            if _hits(cs[j, 2], cs[j, 3], cs[j, 4], px, py, ph, hl, hw, slabs[j, 0], slabs[j, 1]):
                p = end[j]
                idx[p] = i
                xyz[p, 0], xyz[p, 1], xyz[p, 2] = np.float64(pts[i, 0]), np.float64(pts[i, 1]), np.float64(pts[i, 2])
                end[j] = p + 1
    part_starts = _compact_parts(idx, xyz, part, end)
    return idx[: part_starts[b]], xyz[: part_starts[b]], part_starts


def _bin_of_angle(angle: FloatArray, nbins: int) -> NDArray[np.int64]:
    a = np.mod(angle, 2.0 * np.pi)
    x, y = np.cos(a), np.sin(a)
    t = y / (np.abs(x) + np.abs(y))
    pa = np.where(x < 0, 2.0 - t, np.where(y >= 0, t, 4.0 + t))  # _pseudo_angle's quadrants
    return np.clip((pa * (nbins / 4.0)).astype(np.int64), 0, nbins - 1)


@dataclass(frozen=True)
class AzimuthBuckets:
    """The frame's points that can matter to some box, with their azimuth bins (seen from the
    sensor), and each box's bin window.

    Attributes
    ----------
    xyz : (N, 3) the frame's points (a float32 or float64 view; the kernels compute in float64)
    kept : (M,) indices of the bucketed points, ascending (point order)
    bins : (M,) the azimuth bin of each
    starts : (nbins + 1,) number of bucketed points in the bins before each bin
    ranges : (K, 4) up to two inclusive bin ranges per box
    near2 : (K,) squared BEV distance from the sensor to each box's grown rectangle
    reach : how far the windows reach beyond the boxes (m)
    """

    xyz: FloatArray
    kept: IndexArray
    bins: IndexArray
    starts: IndexArray
    ranges: IndexArray
    near2: FloatArray
    reach: float

    def window_sizes(self) -> IndexArray:
        """Points in each box's window (K,)."""
        sizes = np.zeros(len(self.ranges), dtype=np.int64)
        for r in range(2):
            lo, hi = self.ranges[:, 2 * r], self.ranges[:, 2 * r + 1]
            ok = lo <= hi
            sizes[ok] += self.starts[hi[ok] + 1] - self.starts[lo[ok]]
        return sizes


def azimuth_buckets(
    points: ArrayLike, origin: ArrayLike, boxes: ArrayLike, reach: float, nbins: int = C.FREE_SPACE_AZIMUTH_BINS
) -> AzimuthBuckets:
    """One compiled pass over the frame: the points that can matter to the boxes (not nearer than
    every box, in some box's azimuth window) and their bins among ``nbins`` azimuth bins (of a
    pseudo-angle), and every box's window: its rectangle grown by ``reach`` seen from the sensor.
    The later passes visit the kept points once, in point order, each against the boxes whose
    window holds its bin: every box's selection comes out in point order, with no sort."""
    pts = np.asarray(points)
    xyz = (
        pts[:, :3] if pts.dtype in (np.float32, np.float64) else pts[:, :3].astype(np.float64)
    )  # no copy of the frame: the kernels read float32 exactly
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    o = np.asarray(origin, dtype=float).reshape(3)
    ranges, near2 = _azimuth_ranges(b, o, reach, nbins)
    min_r2 = float(near2.min()) if len(b) else 0.0
    kept, bins, starts = _bucket_kernel(xyz, o[0], o[1], nbins, min_r2, ranges)
    return AzimuthBuckets(xyz, kept, bins, starts, ranges, near2, float(reach))


def ray_candidates(
    points: ArrayLike,
    origin: ArrayLike,
    boxes: ArrayLike,
    ground: ArrayLike,
    slabs: ArrayLike,
    reach: float,
    nbins: int = C.FREE_SPACE_AZIMUTH_BINS,
    buckets: AzimuthBuckets | None = None,
) -> tuple[list[IndexArray], list[FloatArray]]:
    """Indices of the points whose ray (sensor → point) passes through each box's reach prism.

    The reach prism of a box is its rectangle grown by ``reach`` on every side, between the heights
    ``slabs[j]`` above the box's ground plane: every ray the box fit can meet while it moves by up
    to ``reach``. The points are bucketed by azimuth (:func:`azimuth_buckets`, or ``buckets`` made
    with at least this reach); each box then tests only the points of its window, exactly (a
    segment–prism test).

    Parameters
    ----------
    points : (N, ≥3) the frame's points
    origin : (3,) the sensor
    boxes : (K, 7) boxes
    ground : (K, ≥3) ground planes (g0, gx, gy) about each box's BEV centre
    slabs : (K, 2) slab heights above the ground (m)
    reach : BEV growth of the rectangles (m)

    Returns
    -------
    K sorted int64 index arrays into ``points`` (views of one buffer: copy one to keep it alone),
    and the xyz (M_j, 3) float64 of each box's candidates
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    o = np.asarray(origin, dtype=float).reshape(3)
    k = len(b)
    if k == 0:
        return [], []
    if len(points) == 0:
        return [np.empty(0, dtype=np.int64) for _ in range(k)], [np.empty((0, 3)) for _ in range(k)]
    if buckets is None or buckets.reach < reach:
        buckets = azimuth_buckets(points, o, b, reach, nbins)
    g = np.ascontiguousarray(np.asarray(ground, dtype=float)[:, :3])
    sl = np.ascontiguousarray(slabs, dtype=float)
    result: list[IndexArray] = []
    ends: list[FloatArray] = []
    for j0 in range(0, k, _BATCH):  # batches bound the buffer in frames of thousands of boxes
        j1 = min(k, j0 + _BATCH)
        parts = ray_candidate_parts(buckets, b[j0:j1], g[j0:j1], sl[j0:j1], o, reach, first=j0)
        result.extend(parts.index_list())
        ends.extend(parts.xyz_list())
    return result, ends


@dataclass(frozen=True)
class PointParts:
    """A selection of the frame's points for each of B boxes, in one flat buffer: box j's part is
    ``idx[starts[j]:starts[j + 1]]`` (sorted indices into the frame) and the same rows of ``xyz``
    (their x, y, z as float64, converted exactly)."""

    idx: IndexArray
    xyz: FloatArray
    starts: IndexArray

    def index_list(self) -> list[IndexArray]:
        """Each box's indices (views of ``idx``)."""
        s = self.starts.tolist()
        return [self.idx[a:b] for a, b in zip(s, s[1:])]

    def xyz_list(self) -> list[FloatArray]:
        """Each box's points (n_j, 3) (views of ``xyz``)."""
        s = self.starts.tolist()
        return [self.xyz[a:b] for a, b in zip(s, s[1:])]


def ray_candidate_parts(
    buckets: AzimuthBuckets,
    boxes: ArrayLike,
    ground: ArrayLike,
    slabs: ArrayLike,
    origin: ArrayLike,
    reach: float,
    first: int = 0,
) -> PointParts:
    """:func:`ray_candidates` of the boxes (B, 7) that are boxes ``first`` … ``first + B − 1`` of
    ``buckets`` (made with at least this reach), as one :class:`PointParts` (B bounds its buffer)."""
    b = np.ascontiguousarray(boxes, dtype=float).reshape(-1, 7)
    o = np.asarray(origin, dtype=float).reshape(3)
    if buckets.reach < reach:
        raise ValueError(f"buckets reach {buckets.reach} m, the ray candidates need {reach} m")
    j0, j1 = first, first + len(b)
    bk = buckets
    return PointParts(
        *_select_kernel(
            bk.xyz,
            bk.kept,
            bk.bins,
            bk.starts,
            np.ascontiguousarray(bk.ranges[j0:j1]),
            np.ascontiguousarray(bk.near2[j0:j1]),
            b,
            np.ascontiguousarray(np.asarray(ground, dtype=float)[:, :3]),
            o[0],
            o[1],
            o[2],
            float(reach),
            np.ascontiguousarray(slabs, dtype=float),
        )
    )


def neighbourhood_parts(
    buckets: AzimuthBuckets, boxes: ArrayLike, margin: float, below: float, above: float, first: int = 0
) -> PointParts:
    """Indices (sorted per box) of the points in each box grown by ``margin`` in BEV, from ``below``
    under its bottom to ``above`` over its top, for the boxes (B, 7) that are boxes ``first`` …
    ``first + B − 1`` of ``buckets`` (which must reach at least ``margin``), as one
    :class:`PointParts` (B bounds its buffer): one compiled pass over the points of the boxes'
    azimuth windows instead of a test of every point of the frame per box."""
    b = np.ascontiguousarray(boxes, dtype=float).reshape(-1, 7)
    if buckets.reach < margin:
        raise ValueError(f"buckets reach {buckets.reach} m, the neighbourhoods need {margin} m")
    j0, j1 = first, first + len(b)
    return PointParts(
        *_region_kernel(
            buckets.xyz,
            buckets.kept,
            buckets.bins,
            buckets.starts,
            np.ascontiguousarray(buckets.ranges[j0:j1]),
            b,
            float(margin),
            float(below),
            float(above),
        )
    )


_BATCH = 256  # boxes per call of the selection kernels: bounds their buffers (frames of thousands of boxes)


@kernel
def _region_kernel(pts, kept, bins, starts, ranges, boxes, margin, below, above):  # pragma: no cover - compiled
    """For each box, the bucketed points of its azimuth window inside the grown box of
    :func:`neighbourhood_parts`: indices (sorted per box), their xyz as float64 and each box's
    start (B + 1,), box after box. The bucketed points are visited once in point order, each
    against the boxes whose window holds its bin (as :func:`_select_kernel`)."""
    b = boxes.shape[0]
    at, boxes_of, part = _windows_kernel(ranges, starts)
    cs = np.empty((b, 6))  # per box: cos, sin, the grown half length and width, the bottom and top
    for j in range(b):
        y = boxes[j]
        cs[j, 0], cs[j, 1] = math.cos(y[6]), math.sin(y[6])
        cs[j, 2], cs[j, 3] = 0.5 * y[3] + margin, 0.5 * y[4] + margin
        cs[j, 4], cs[j, 5] = y[2] - 0.5 * y[5] - below, y[2] + 0.5 * y[5] + above
    idx = np.empty(part[b], dtype=np.int64)
    xyz = np.empty((part[b], 3))
    end = part[:b].copy()
    for t in range(kept.shape[0]):
        q = bins[t]
        if at[q] == at[q + 1]:
            continue
        i = kept[t]
        z = pts[i, 2]
        for a in range(at[q], at[q + 1]):
            j = boxes_of[a]
            if z < cs[j, 4] or z > cs[j, 5]:
                continue
            qx, qy = pts[i, 0] - boxes[j, 0], pts[i, 1] - boxes[j, 1]
            c, s = cs[j, 0], cs[j, 1]
            if abs(c * qx + s * qy) <= cs[j, 2] and abs(-s * qx + c * qy) <= cs[j, 3]:
                p = end[j]
                idx[p] = i
                xyz[p, 0], xyz[p, 1], xyz[p, 2] = np.float64(pts[i, 0]), np.float64(pts[i, 1]), np.float64(z)
                end[j] = p + 1
    part_starts = _compact_parts(idx, xyz, part, end)
    return idx[: part_starts[b]], xyz[: part_starts[b]], part_starts


def _azimuth_ranges(
    boxes: FloatArray, origin: FloatArray, reach: float, nbins: int
) -> tuple[NDArray[np.int64], FloatArray]:
    """Bin ranges (K, 4): up to two inclusive [lo, hi] bin ranges per box (the second when the
    azimuth window wraps past 0; all bins when the sensor lies inside the grown rectangle), and the
    squared BEV distance (K,) from the sensor to each grown rectangle (0 inside).

    The angles are NumPy's (``cos``, ``sin``, ``arctan2``, the complex ``exp``, ``mod``: SIMD
    forms here, whose last bits a compiled pass would not reproduce, and the bins must not move),
    each called on the same values in the same layout as :func:`_azimuth_ranges_numpy`; the
    arithmetic between them is three compiled passes (the same operations) instead of ~40 NumPy
    calls on (K, 4) arrays."""
    c, s = np.cos(boxes[:, 6]), np.sin(boxes[:, 6])
    ox, oy = float(origin[0]), float(origin[1])
    cx, cy, dx, dy = _window_corners(boxes, c, s, ox, oy, float(reach))
    centre = np.arctan2(dy, dx)
    rel = np.angle(np.exp(1j * (np.arctan2(cy, cx) - centre[:, None])))
    a = np.mod(_window_edges(centre, rel), 2.0 * np.pi)  # the windows' first angles (K,), then their last (K,)
    return _window_ranges(boxes, c, s, ox, oy, float(reach), np.cos(a), np.sin(a), nbins)


@kernel
def _window_corners(boxes, c, s, ox, oy, reach):  # pragma: no cover - compiled
    """The grown rectangles' corners (K, 4) relative to the sensor, x and y, and the boxes' centres
    relative to it (K,), x and y: :func:`_azimuth_ranges_numpy`'s operations in its order."""
    k = boxes.shape[0]
    cx, cy = np.empty((k, 4)), np.empty((k, 4))
    dx, dy = np.empty(k), np.empty(k)
    for j in range(k):
        hl, hw = boxes[j, 3] / 2 + reach, boxes[j, 4] / 2 + reach
        for q in range(4):
            lx = (1.0 if q == 0 or q == 3 else -1.0) * hl  # _CORNER_SX, _CORNER_SY
            ly = (1.0 if q < 2 else -1.0) * hw
            cx[j, q] = boxes[j, 0] + c[j] * lx - s[j] * ly - ox
            cy[j, q] = boxes[j, 1] + s[j] * lx + c[j] * ly - oy
        dy[j] = boxes[j, 1] - oy
        dx[j] = boxes[j, 0] - ox
    return cx, cy, dx, dy


@kernel
def _window_edges(centre, rel):  # pragma: no cover - compiled
    """(2K,): centre + the smallest relative angle of each box's corners, then centre + the largest."""
    k = centre.shape[0]
    out = np.empty(2 * k)
    for j in range(k):
        lo = hi = rel[j, 0]
        for q in range(1, rel.shape[1]):
            v = rel[j, q]
            if v < lo or v != v:  # a NaN stays (as NumPy's min and max)
                lo = v
            if v > hi or v != v:
                hi = v
        out[j] = centre[j] + lo
        out[k + j] = centre[j] + hi
    return out


@kernel
def _window_ranges(boxes, c, s, ox, oy, reach, x, y, nbins):  # pragma: no cover - compiled
    """The bins of the windows' edge angles (their cos ``x`` and sin ``y``, (2K,): a pseudo-angle,
    truncated and clipped), the ranges (K, 4) they make, and the squared distance (K,) from the
    sensor to each grown rectangle: :func:`_azimuth_ranges_numpy`'s operations."""
    k = boxes.shape[0]
    bins = np.empty(2 * k, dtype=np.int64)
    scale = nbins / 4.0
    for i in range(2 * k):
        t = y[i] / (abs(x[i]) + abs(y[i]))
        pa = (2.0 - t) if x[i] < 0 else (t if y[i] >= 0 else 4.0 + t)
        bins[i] = min(max(np.int64(pa * scale), 0), nbins - 1)
    ranges = np.empty((k, 4), dtype=np.int64)
    near2 = np.empty(k)
    for j in range(k):
        hl, hw = boxes[j, 3] / 2 + reach, boxes[j, 4] / 2 + reach
        bx, by = (
            c[j] * (ox - boxes[j, 0]) + s[j] * (oy - boxes[j, 1]),
            -s[j] * (ox - boxes[j, 0]) + c[j] * (oy - boxes[j, 1]),
        )
        lo, hi = bins[j], bins[k + j]
        if abs(bx) <= hl and abs(by) <= hw:  # the sensor inside the grown rectangle: every direction
            ranges[j, 0], ranges[j, 1], ranges[j, 2], ranges[j, 3] = 0, nbins - 1, 1, 0
        elif lo > hi:  # wraps past 0
            ranges[j, 0], ranges[j, 1], ranges[j, 2], ranges[j, 3] = 0, hi, lo, nbins - 1
        else:
            ranges[j, 0], ranges[j, 1], ranges[j, 2], ranges[j, 3] = lo, hi, 1, 0
        gx, gy = abs(bx) - hl, abs(by) - hw
        gx = gx if gx > 0.0 or gx != gx else 0.0  # np.maximum(·, 0.0)
        gy = gy if gy > 0.0 or gy != gy else 0.0
        near2[j] = (gx * gx + gy * gy) * (1.0 - 1e-9)  # a hair nearer: rounding never drops a ray
    return ranges, near2


def _azimuth_ranges_numpy(
    boxes: FloatArray, origin: FloatArray, reach: float, nbins: int
) -> tuple[NDArray[np.int64], FloatArray]:
    """:func:`_azimuth_ranges` in NumPy alone (the reference its compiled passes are tested against)."""
    k = len(boxes)
    half = boxes[:, 3:5] / 2 + reach
    c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
    lx, ly = _CORNER_SX * half[:, :1], _CORNER_SY * half[:, 1:]
    cx = boxes[:, :1] + c * lx - s * ly - origin[0]
    cy = boxes[:, 1:2] + s * lx + c * ly - origin[1]
    centre = np.arctan2(boxes[:, 1] - origin[1], boxes[:, 0] - origin[0])
    rel = np.angle(np.exp(1j * (np.arctan2(cy, cx) - centre[:, None])))
    lo_a, hi_a = centre + rel.min(1), centre + rel.max(1)
    ranges = np.empty((k, 4), dtype=np.int64)
    ranges[:, 2], ranges[:, 3] = 1, 0  # empty second range
    # the sensor inside the grown rectangle: every direction
    ox = c[:, 0] * (origin[0] - boxes[:, 0]) + s[:, 0] * (origin[1] - boxes[:, 1])
    oy = -s[:, 0] * (origin[0] - boxes[:, 0]) + c[:, 0] * (origin[1] - boxes[:, 1])
    inside = (np.abs(ox) <= half[:, 0]) & (np.abs(oy) <= half[:, 1])
    bins = _bin_of_angle(np.concatenate([lo_a, hi_a]), nbins)
    b_lo, b_hi = bins[:k], bins[k:]
    wraps = b_lo > b_hi
    ranges[:, 0], ranges[:, 1] = np.where(wraps, 0, b_lo), b_hi
    ranges[wraps, 2], ranges[wraps, 3] = b_lo[wraps], nbins - 1
    ranges[inside, 0], ranges[inside, 1] = 0, nbins - 1
    ranges[inside, 2], ranges[inside, 3] = 1, 0
    gap_x = np.maximum(np.abs(ox) - half[:, 0], 0.0)
    gap_y = np.maximum(np.abs(oy) - half[:, 1], 0.0)
    near2 = (gap_x**2 + gap_y**2) * (1.0 - 1e-9)  # a hair nearer: rounding never drops a ray
    return ranges, near2


_CORNER_SX = np.array([[1.0, -1.0, -1.0, 1.0]])  # the rectangle's corners (1, 4): signs of the half length …
_CORNER_SY = np.array([[1.0, 1.0, -1.0, -1.0]])  # … and of the half width

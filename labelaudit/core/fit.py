"""The label-error model (docs/label-error.md): the box the points support and how far the label is from it.

An EM fit of the box to its points (point-to-surface residuals, regularised by the same prior as
:mod:`labelaudit.core.posterior`, with an l/w-swapped start) gives the suggested box, the label's
offset to it in metres and in Mahalanobis units, and ``label_error`` = χ² CDF of that offset under a
tolerance covariance. It tells "wrong" labels from merely uncertain ones. No I/O; the compiled
kernels (numba) are the per-point passes a profile showed to be the cost.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.core import geometry as g
from labelaudit.core import linalg
from labelaudit.core.freespace import (
    FreeSpace,
    displacement,
    free_rows_kernel,
    label_ray_terms,
)
from labelaudit.core.geometry import FloatArray
from labelaudit.core.params import ClassPrior, ModelKind, ModelParams
from labelaudit.core.posterior import (
    BoxPriorTerms,
    box_prior_terms,
    em_sigma,
    outlier_log_density,
    prior_cov_extended_cached,
    register_validated,
    spd_inverse,
)
from labelaudit.kernels import kernel

# ----------------------------------------------------------------------------------------------
# Label error: the model's suggested box and how far the label is from it (docs/label-error.md)
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LabelFit:
    """The box the points support (EM fit regularised by the prior) and the label's distance to it.

    Attributes
    ----------
    model : "3d" when the points had z (always, from the pipeline), else "bev"
    box : (7,) suggested box, written in the equivalent form (yaw + kπ/2, l/w swapped for odd k)
        closest to the label; a BEV fit keeps the label's cz and height.
    phi : (p,) φ of ``box``
    cov : (p, p) posterior covariance of φ at the fit
    offsets : fit − label per box field (yaw wrapped to [−π, π)); NaN for cz/height in BEV
    offset_m : centre offset (BEV: in x, y; 3D: x, y, z), metres
    mahalanobis : √(Δφᵀ Σ_fit⁻¹ Δφ), Δφ = φ_label − φ_fit
    tolerance_distance : √(Δφᵀ (Σ_fit + Σ_tol)⁻¹ Δφ), Σ_tol from :data:`~labelaudit.constants.LABEL_TOLERANCE`
    label_error : chi2.cdf(tolerance_distance², k), k = 7 box parameters (5 when the run's model is
        BEV or the points have no z: then only the BEV marginal of Δφ is scored, here and in mahalanobis)
    sigma_hat : EM noise estimate at the fit (NaN below 2 points); computed on first access (the
        pipeline reports σ̂ at the label, from :func:`infer_label`, and never pays for this one)
    iterations : EM iterations of the chosen start
    converged : whether the chosen start converged within the iteration cap
    swapped_start : the chosen fit started from the label with length and width swapped
    face_gaps : (−length, +length, −width, +width) depth (m) inside the label's side face of the outer
        surface its points show (:func:`face_gaps`); NaN for a face the sensor does not see, with too
        few points, or when the sensor position is unknown
    face_gap_distance : √Σ (gap − FACE_GAP)² / FACE_GAP_STD² over the seen faces: how far the
        label's seen faces are from where a right label's lie, in their own standard deviations;
        ``label_error`` = chi2.cdf(tolerance_distance² + face_gap_distance², k + faces)
    """

    model: ModelKind
    box: FloatArray
    phi: FloatArray
    cov: FloatArray
    offsets: dict[str, float]
    offset_m: float
    mahalanobis: float
    tolerance_distance: float
    label_error: float
    iterations: int
    converged: bool
    swapped_start: bool
    face_gaps: tuple[float, float, float, float] = (math.nan,) * 4
    face_gap_distance: float = 0.0
    _residual_inputs: tuple = field(default=(), repr=False, compare=False)  # (box, points, d, params, σ)

    @property
    def face_gap(self) -> float:
        """Of the seen faces' gaps, the one furthest from FACE_GAP (m; NaN when no side face is seen)."""
        best, far = math.nan, -1.0  # the first of the furthest, as max(seen, key=…) takes it
        for v in self.face_gaps:
            if v == v and abs(v - C.FACE_GAP) > far:
                best, far = v, abs(v - C.FACE_GAP)
        return best

    @functools.cached_property
    def sigma_hat(self) -> float:
        """EM noise estimate σ̂ of the points at the suggested box (NaN below 2 points)."""
        if not self._residual_inputs:
            return float("nan")
        y_fit, pts, d, params, sigma = self._residual_inputs
        reg = register_validated(y_fit, np.ascontiguousarray(pts), d, params.num_nearest, sigma, params.outlier_prob)
        return em_sigma([(reg.sqdist, outlier_log_density(y_fit, d))], d, sigma, params.outlier_prob)


def _equivalent_boxes(y: FloatArray) -> list[FloatArray]:
    """The four (l, w, yaw) forms of the same rectangle: yaw + kπ/2, l and w swapped for odd k."""
    out = []
    for k in range(4):
        b = y.copy()
        if k % 2:
            b[3], b[4] = y[4], y[3]
        b[6] = float(g.normalize_angle(y[6] + k * np.pi / 2))
        out.append(b)
    return out


def _closest_form(y: FloatArray, phi_ref: FloatArray, W: FloatArray, model: ModelKind) -> FloatArray:
    """Of the equivalent forms of rectangle ``y``, the one whose φ is nearest ``phi_ref`` in metric W."""
    return _closest_form_phi(y, phi_ref, W, model)[0]


def _closest_form_phi(
    y: FloatArray, phi_ref: FloatArray, W: FloatArray, model: ModelKind
) -> tuple[FloatArray, FloatArray]:
    """:func:`_closest_form` and its φ (the first of the least costs — a later one must be lower by more than
    1e-9 relative, so that a tie in exact arithmetic is not decided by rounding — or of the NaN ones).

    The forms and their φ are those of :func:`_equivalent_boxes` and
    :func:`~labelaudit.core.geometry.phi_of_valid_box`, written out in one compiled call
    (:func:`_closest_form_kernel`).
    """
    phi = np.empty(len(phi_ref))
    k, yaw = _closest_form_kernel(y, phi_ref, W, model == "3d", phi)
    return _form(y, k, yaw), phi


def _form(y: FloatArray, k: int, yaw: float) -> FloatArray:
    """The equivalent form k of rectangle ``y`` (7,) (:func:`_equivalent_boxes`), its yaw ``yaw``."""
    form = y.copy()
    if k % 2:
        form[3], form[4] = y[4], y[3]
    form[6] = yaw
    return form


@kernel
def _closest_form_kernel(y, phi_ref, W, three_d, phi_out):  # pragma: no cover - compiled
    """(k, yaw_k) of the equivalent form yaw + kπ/2 (l, w swapped for odd k) of rectangle ``y``
    whose φ is nearest ``phi_ref`` in metric W (p, p), its φ written to ``phi_out`` (p,).
    Ties within 1e-9 relative go to the first form; the first NaN cost ends the search (np.argmin's)."""
    p = phi_ref.shape[0]
    f = np.empty(p)
    wf = np.empty(p)
    best_cost, best_k, best_yaw = 0.0, -1, 0.0
    for k in range(4):
        yaw = (y[6] + k * (math.pi / 2) + math.pi) % (2.0 * math.pi) - math.pi  # normalize_angle
        lk, wk = (y[4], y[3]) if k % 2 else (y[3], y[4])
        c, s = math.cos(yaw), math.sin(yaw)
        if three_d:
            f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7] = y[0], y[1], y[2], lk * c, lk * s, wk * c, wk * s, y[5]
        else:
            f[0], f[1], f[2], f[3], f[4], f[5] = y[0], y[1], lk * c, lk * s, wk * c, wk * s
        for i in range(p):
            acc = 0.0
            for j in range(p):
                acc += W[i, j] * (f[j] - phi_ref[j])
            wf[i] = acc
        cost = 0.0
        for i in range(p):
            cost += (f[i] - phi_ref[i]) * wf[i]
        # a later form wins only by more than the rounding of the costs: two forms can be exactly as
        # near (a rectangle turned by 90°: yaw + π/2 and yaw − π/2), and the last bit must not choose
        if best_k < 0 or cost < best_cost - 1e-9 * abs(best_cost) or (cost != cost and best_cost == best_cost):
            best_cost, best_k, best_yaw = cost, k, yaw
            phi_out[:] = f
        if cost != cost:
            break
    return best_k, best_yaw


@kernel
def _rect_from_phi(phi, three_d, label, floor):  # pragma: no cover - compiled
    """Rectangle (7,) of a φ (mean axis direction); sizes kept ≥ ``floor`` × the label's.

    Equals ``geometry.phi_to_box`` (then the size floor), in scalar arithmetic: it runs once per
    fit iteration on 8 numbers, inside the compiled fit loop (:func:`_fit_iterate_kernel`).
    """
    out = np.empty(7)
    _rect_from_phi_into(phi, three_d, label, floor, out)
    return out


@kernel
def _rect_from_phi_into(phi, three_d, label, floor, out):  # pragma: no cover - compiled
    """:func:`_rect_from_phi` written into ``out`` (7,) (the fit's loop reuses one rectangle)."""
    o = 1 if three_d else 0
    lc, ls, wc, ws = phi[2 + o], phi[3 + o], phi[4 + o], phi[5 + o]
    a, b = math.atan2(ls, lc), math.atan2(ws, wc)
    two_pi = 2.0 * math.pi
    yaw = (a + 0.5 * ((b - a + math.pi) % two_pi - math.pi) + math.pi) % two_pi - math.pi
    cz, height = (phi[2], phi[7]) if three_d else (label[2], label[5])
    out[0], out[1], out[2] = phi[0], phi[1], cz
    out[3] = max(math.hypot(lc, ls), floor * label[3])
    out[4] = max(math.hypot(wc, ws), floor * label[4])
    out[5] = max(height, floor * label[5])
    out[6] = yaw


def _plane_rows(y: FloatArray, pts: FloatArray, model: ModelKind) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Point-to-surface rows for a box fit: a_k = J(v*_k)ᵀ n_k (N, p) and b_k = n_kᵀ x_k (N,),
    scaled by 1/FIT_INSIDE_SIGMA_RATIO for points deep inside the box; plus the squared distances
    (N,) of the points to the surface.

    Each point is registered to its single nearest surface point v̄_k, and only the residual along
    n_k (the face normal, or the direction to the nearest edge/corner when the point lies beyond
    one) is used. Unlike the full J rows, the position *along* the face then carries no information,
    so a face can slide while the box is fitted (no anchoring to the current box, no pull of the
    second-nearest face at corners). Computed by the compiled :func:`_rows_kernel`, which the fit
    calls through :func:`_normal_eq_work`.
    """
    d = g.point_dim(model)
    pts_t = np.ascontiguousarray(np.asarray(pts, dtype=float)[:, :d].T)
    n = pts_t.shape[1]
    a = np.empty((2 * d + 2, n))
    b = np.empty(n)
    sqd = np.empty(n)
    _rows_kernel(
        np.asarray(y, dtype=float),
        pts_t,
        d,
        C.FIT_INSIDE_FREE_DEPTH,
        1.0 / C.FIT_INSIDE_SIGMA_RATIO,
        0.0,
        1.0,
        a,
        b,
        sqd,
    )
    return a.T, b, sqd


@kernel
def _rows_kernel(
    y, pts_t, d, free_depth, deep_weight, outlier, sigma, a, b, sqd, centre_deep=False
):  # pragma: no cover - compiled
    """Rows a — transposed, (p, N) — b (N,) and squared distances (N,) of :func:`_plane_rows` for
    points (d, N).

    Nearest surface point: a point outside the box projects to its clamped position; a point
    inside to its nearest face (ties: the lower face index — axis first, the − face before the +
    face — as :func:`_nearest_faces` with m = 1). One pass, scalars only.

    ``outlier`` > 0: a point outside the box (or within ``free_depth`` of its surface) is a
    mixture of the Gaussian (σ = ``sigma``) and a uniform outlier of that prior probability, and
    its row is weighted by the Gaussian's responsibility (iteratively reweighted).

    ``centre_deep``: the rows of the points deeper than ``free_depth`` inside the box are centred
    per face (their mean over the deep points registered to the same face is subtracted), i.e. the
    face gets a free offset for them: a visible surface lies parallel to its face at an unknown
    depth inside it (a loose label, a bumper, a cabin), so deep points constrain the orientation
    of the faces and never pull them in. Their squared distance is then reported as 0.
    """
    c, s = math.cos(y[6]), math.sin(y[6])
    h0, h1 = 0.5 * y[3], 0.5 * y[4]
    h2 = 0.5 * y[5] if d == 3 else 0.0
    big = max(y[3], y[4], y[5]) if d == 3 else max(y[3], y[4])
    face = np.full(pts_t.shape[1], -1, dtype=np.int64)  # face of a deep point: axis·2 + (side > 0)
    n_deep = 0
    for k in range(pts_t.shape[1]):
        rx, ry = pts_t[0, k] - y[0], pts_t[1, k] - y[1]
        l0 = c * rx + s * ry  # box frame, metres: Rᵀ (x − c)
        l1 = -s * rx + c * ry
        m0 = min(max(l0, -h0), h0)
        m1 = min(max(l1, -h1), h1)
        inside = m0 == l0 and m1 == l1
        strict = abs(l0) < h0 and abs(l1) < h1
        l2 = m2 = 0.0
        if d == 3:
            l2 = pts_t[2, k] - y[2]
            m2 = min(max(l2, -h2), h2)
            inside = inside and m2 == l2
            strict = strict and abs(l2) < h2
        f_in = -1
        if inside:  # nearest face: the smallest (x ∓ half)² of each axis' nearer face
            e0, e1 = (h0 - abs(l0)) ** 2, (h1 - abs(l1)) ** 2
            e2 = (h2 - abs(l2)) ** 2 if d == 3 else math.inf
            if e0 <= e1 and e0 <= e2:
                m0 = h0 if l0 > 0 else -h0
                f_in = 1 if l0 > 0 else 0
            elif e1 <= e2:
                m1 = h1 if l1 > 0 else -h1
                f_in = 3 if l1 > 0 else 2
            else:
                m2 = h2 if l2 > 0 else -h2
                f_in = 5 if l2 > 0 else 4
        r0, r1, r2 = l0 - m0, l1 - m1, l2 - m2
        sq = r0 * r0 + r1 * r1 + r2 * r2
        norm = math.sqrt(sq)
        v0, v1 = m0 / y[3], m1 / y[4]  # unit coordinates of the nearest surface point
        v2 = m2 / y[5] if d == 3 else 0.0
        # n: the direction point − surface (face normal, or towards the nearest edge/corner beyond
        # one); on the surface (zero residual): the normal of the face the point lies on.
        if norm > 1e-9 * big:
            q0, q1, q2 = r0 / norm, r1 / norm, r2 / norm
        else:
            q0 = q1 = q2 = 0.0
            if abs(v1) > abs(v0) and (d == 2 or abs(v1) >= abs(v2)):
                q1 = math.copysign(1.0, v1) if v1 != 0 else 0.0
            elif d == 3 and abs(v2) > abs(v0) and abs(v2) > abs(v1):
                q2 = math.copysign(1.0, v2) if v2 != 0 else 0.0
            else:
                q0 = math.copysign(1.0, v0) if v0 != 0 else 0.0
        n0 = c * q0 - s * q1  # to the world frame (z unchanged)
        n1 = s * q0 + c * q1
        if strict and norm > free_depth:
            w = deep_weight  # √weight = σ / σ_inside
            face[k] = f_in
            n_deep += 1
        elif outlier > 0.0:
            gk = (1.0 - outlier) * math.exp(-0.5 * sq / (sigma * sigma))
            w = math.sqrt(gk / (gk + outlier))
        else:
            w = 1.0
        # a = J(v*)ᵀ n, written out from geometry.design_matrix
        a[0, k] = w * n0
        a[1, k] = w * n1
        bk = n0 * pts_t[0, k] + n1 * pts_t[1, k]
        if d == 3:
            a[2, k] = w * q2
            a[7, k] = w * v2 * q2
            bk += q2 * pts_t[2, k]
        a[d, k] = w * v0 * n0
        a[d + 1, k] = w * v0 * n1
        a[d + 2, k] = w * v1 * n1
        a[d + 3, k] = -w * v1 * n0
        b[k] = w * bk
        sqd[k] = sq
    if centre_deep and n_deep:
        p = a.shape[0]
        sa = np.zeros((6, p))
        sb = np.zeros(6)
        cnt = np.zeros(6)
        for k in range(pts_t.shape[1]):
            f = face[k]
            if f >= 0:
                cnt[f] += 1.0
                sb[f] += b[k]
                for i in range(p):
                    sa[f, i] += a[i, k]
        for k in range(pts_t.shape[1]):
            f = face[k]
            if f >= 0:
                b[k] -= sb[f] / cnt[f]
                for i in range(p):
                    a[i, k] -= sa[f, i] / cnt[f]
                sqd[k] = -1.0  # marks a centred deep point for the callers


@kernel(fastmath={"reassoc", "contract"})
def _gram_kernel(a, b, phi, with_residual):  # pragma: no cover - compiled
    """a aᵀ (p, p), a b (p,) and ‖aᵀφ − b‖² (0 unless ``with_residual``: the fit's iterations do
    not need it) for rows a (p, N): dot products of contiguous rows.
    Reassociation only (no other fast-math), so the sums vectorise; the result differs from the
    sequential sums by rounding alone. No BLAS: its threads oversubscribe the cores of a worker pool."""
    p, n = a.shape
    ata = np.empty((p, p))
    atb = np.empty(p)
    for i in range(p):
        for j in range(i, p):
            acc = 0.0
            for k in range(n):
                acc += a[i, k] * a[j, k]
            ata[i, j] = acc
            ata[j, i] = acc
        acc = 0.0
        for k in range(n):
            acc += a[i, k] * b[k]
        atb[i] = acc
    rr = 0.0
    if not with_residual:
        return ata, atb, rr
    for k in range(n):
        r = -b[k]
        for i in range(p):
            r += a[i, k] * phi[i]
        rr += r * r
    return ata, atb, rr


@kernel
def _normal_eq_work(
    y, pts_t, d, free_depth, deep_weight, outlier, sigma, phi, face, along, bs, rs
):  # pragma: no cover - compiled
    """Σ a_kᵀa_k (p, p), Σ a_k b_k (p,), Σ (a_k·φ − b_k)², Σ w_k² ‖x_k − v̄_k‖² and Σ w_k² of the rows of
    :func:`_plane_rows` for points (d, N), deep points centred per face (the last two over the
    points that are not deep inside; weight² = |the row's normal part|², a unit vector).

    Without outliers (``outlier`` = 0, the default) the sums are taken in one vectorised pass that
    never writes the rows (:func:`_point_sums_kernel`), and the deep points' centring is applied to
    the sums: Σ (a − ā)(a − ā)ᵀ = Σ a aᵀ − n ā āᵀ per face (a deep point's row is its face's normal
    and its coordinate along the face), the residuals' Σ (r − r̄)² from r. The pass works about the
    box's centre (b and the residuals from small numbers, then Σ a b = Σ a b̃ + Σ a aᵀ o), which
    rounds less than the rows' world coordinates. The same sums as the rows' (:func:`_rows_kernel`,
    :func:`_gram_kernel`), which outlier weights (an exponential per point) still take, up to rounding.

    The per-point work arrays (N,) are given: ``face`` (int64), ``along``, ``bs``, ``rs`` (the fit's
    passes over one set of points share them)."""
    n = pts_t.shape[1]
    if outlier > 0.0:
        a = np.empty((2 * d + 2, n))
        b = np.empty(n)
        sqd = np.empty(n)
        _rows_kernel(y, pts_t, d, free_depth, deep_weight, outlier, sigma, a, b, sqd, True)
        ata, atb, rr = _gram_kernel(a, b, phi, True)
        ss = sw = 0.0
        for k in range(n):
            if sqd[k] < 0.0:
                continue
            w2 = a[0, k] * a[0, k] + a[1, k] * a[1, k] + (a[2, k] * a[2, k] if d == 3 else 0.0)
            ss += w2 * sqd[k]
            sw += w2
        return ata, atb, rr, ss, sw
    three = d == 3
    ata, atb, rr, ss, sw = _point_sums_kernel(y, pts_t, three, free_depth, deep_weight, phi, face, along, bs, rs)
    cnt = np.zeros(6)
    s_along = np.zeros(6)
    sb = np.zeros(6)
    sr = np.zeros(6)
    deep = 0
    for k in range(n):
        f = face[k]
        if f >= 0:
            cnt[f] += 1.0
            s_along[f] += along[k]
            sb[f] += bs[k]
            sr[f] += rs[k]
            deep += 1
    c, s = math.cos(y[6]), math.sin(y[6])
    w = deep_weight
    u = np.empty(8)  # a face's mean deep row ā (3D layout)
    for f in range(6):
        if cnt[f] == 0.0:
            continue
        sg = 1.0 if f % 2 else -1.0  # the face's side; a deep point's normal points inside: −sg
        vm = s_along[f] / cnt[f]
        u[:] = 0.0
        if f < 2:
            n0, n1 = -c * sg, -s * sg
            u[0], u[1], u[3], u[4] = w * n0, w * n1, w * 0.5 * sg * n0, w * 0.5 * sg * n1
            u[5], u[6] = w * vm * n1, -w * vm * n0
        elif f < 4:
            n0, n1 = s * sg, -c * sg
            u[0], u[1], u[3], u[4] = w * n0, w * n1, w * vm * n0, w * vm * n1
            u[5], u[6] = w * 0.5 * sg * n1, -w * 0.5 * sg * n0
        else:
            u[2], u[7] = -w * sg, -w * 0.5
        for i in range(8):
            atb[i] -= u[i] * sb[f]
            for j in range(8):
                ata[i, j] -= cnt[f] * u[i] * u[j]
    for k in range(n if deep else 0):  # no deep point: nothing to centre
        f = face[k]
        if f >= 0:
            r = rs[k] - sr[f] / cnt[f]
            rr += r * r
    o = (y[0], y[1], y[2] if three else 0.0)
    for i in range(8):  # Σ a b = Σ a b̃ + (Σ a aᵀ) (o, 0, …), the centred sums alike
        atb[i] += ata[i, 0] * o[0] + ata[i, 1] * o[1] + ata[i, 2] * o[2]
    if three:
        return ata, atb, rr, ss, sw
    ata2, atb2 = np.empty((6, 6)), np.empty(6)  # the 2D layout: no z, no height
    for i in range(6):
        ii = i if i < 2 else i + 1
        atb2[i] = atb[ii]
        for j in range(6):
            ata2[i, j] = ata[ii, j if j < 2 else j + 1]
    return ata2, atb2, rr, ss, sw


@kernel(error_model="numpy", fastmath={"reassoc"})
def _point_sums_kernel(
    y, pts_t, three, free_depth, deep_weight, phi, face, along, bs, rs
):  # pragma: no cover - compiled
    """Σ a aᵀ (8, 8) and Σ a b̃ (8,) — the 3D layout, zero z and height in 2D — of the point rows of
    :func:`_rows_kernel` (without outliers, deep points not centred) about the box's centre o,
    b̃ = b − a·(o, 0, …) = w nᵀ(x − o), and over the points that are not deep inside Σ (a·φ − b)²,
    Σ w²‖x − v̄‖², Σ w²; per point into ``face`` the face of a deep point (else −1), into ``along``
    its unit coordinate along the face (that of the first tangent axis), ``bs`` b̃ and ``rs``
    a·φ − b.

    The same arithmetic per point as :func:`_rows_kernel`, written without branches and with the
    sums in scalars (reassociation only), so that the loop vectorises: ~2× the rows and their Gram
    product, which write and read back p + 2 arrays per point."""
    n = pts_t.shape[1]
    c, s = math.cos(y[6]), math.sin(y[6])
    h0, h1 = 0.5 * y[3], 0.5 * y[4]
    h2 = 0.5 * y[5] if three else 0.0
    big = max(y[3], y[4], y[5]) if three else max(y[3], y[4])
    thr = 1e-9 * big
    y0, y1, y2, y3, y4, y5 = y[0], y[1], y[2], y[3], y[4], y[5]
    # φ about the box's centre o, in the 3D layout's places (2D: no z, no height)
    if three:
        f0, f1, f2, f3, f4, f5, f6, f7 = phi[0] - y0, phi[1] - y1, phi[2] - y2, phi[3], phi[4], phi[5], phi[6], phi[7]
    else:
        f0, f1, f2, f3, f4, f5, f6, f7 = phi[0] - y0, phi[1] - y1, 0.0, phi[2], phi[3], phi[4], phi[5], 0.0
    s00 = s01 = s02 = s03 = s04 = s05 = s06 = s07 = s11 = s12 = s13 = s14 = s15 = s16 = s17 = s22 = s23 = s24 = 0.0
    s25 = s26 = s27 = s33 = s34 = s35 = s36 = s37 = s44 = s45 = s46 = s47 = s55 = s56 = s57 = s66 = s67 = s77 = 0.0
    ab0 = ab1 = ab2 = ab3 = ab4 = ab5 = ab6 = ab7 = 0.0
    rr = ss = sw = 0.0
    for k in range(n):
        xk, yk = pts_t[0, k], pts_t[1, k]
        zk = pts_t[2, k] if three else 0.0
        rx, ry = xk - y0, yk - y1
        l0 = c * rx + s * ry  # box frame, metres: Rᵀ (x − c)
        l1 = -s * rx + c * ry
        l2 = zk - y2 if three else 0.0
        m0 = min(max(l0, -h0), h0)
        m1 = min(max(l1, -h1), h1)
        m2 = min(max(l2, -h2), h2)
        inside = (m0 == l0) & (m1 == l1) & (m2 == l2)
        strict = (abs(l0) < h0) & (abs(l1) < h1) & ((abs(l2) < h2) | (not three))
        # inside: the nearest face, the smallest (x ∓ half)² of each axis' nearer face (ties: the lower axis)
        t0, t1, t2 = h0 - abs(l0), h1 - abs(l1), h2 - abs(l2)
        g0, g1 = t0 * t0, t1 * t1
        g2 = t2 * t2 if three else math.inf
        p0 = inside & (g0 <= g1) & (g0 <= g2)
        p1 = inside & (not p0) & (g1 <= g2)
        p2 = inside & (not p0) & (not p1)
        m0 = (h0 if l0 > 0 else -h0) if p0 else m0
        m1 = (h1 if l1 > 0 else -h1) if p1 else m1
        m2 = (h2 if l2 > 0 else -h2) if p2 else m2
        f_in = (1 if l0 > 0 else 0) if p0 else ((3 if l1 > 0 else 2) if p1 else (5 if l2 > 0 else 4))
        r0, r1, r2 = l0 - m0, l1 - m1, l2 - m2
        sq = r0 * r0 + r1 * r1 + r2 * r2
        norm = math.sqrt(sq)
        v0, v1 = m0 / y3, m1 / y4  # unit coordinates of the nearest surface point
        v2 = m2 / y5 if three else 0.0
        # n: the direction point − surface; on the surface (zero residual): the normal of the face
        # the point lies on (the largest unit coordinate; ties: y before z before x)
        av0, av1, av2 = abs(v0), abs(v1), abs(v2)
        fb1 = (av1 > av0) & ((not three) | (av1 >= av2))
        fb2 = (not fb1) & three & (av2 > av0) & (av2 > av1)
        fb0 = (not fb1) & (not fb2)
        on = not norm > thr
        q0 = (math.copysign(1.0, v0) if (fb0 & (v0 != 0)) else 0.0) if on else r0 / norm
        q1 = (math.copysign(1.0, v1) if (fb1 & (v1 != 0)) else 0.0) if on else r1 / norm
        q2 = (math.copysign(1.0, v2) if (fb2 & (v2 != 0)) else 0.0) if on else r2 / norm
        n0 = c * q0 - s * q1  # to the world frame (z unchanged)
        n1 = s * q0 + c * q1
        deep = strict & (norm > free_depth)
        w = deep_weight if deep else 1.0
        # a = J(v*)ᵀ n (geometry.design_matrix), 3D layout; b = w nᵀx
        u0 = w * n0
        u1 = w * n1
        u2 = w * q2
        u3 = w * v0 * n0
        u4 = w * v0 * n1
        u5 = w * v1 * n1
        u6 = -w * v1 * n0
        u7 = w * v2 * q2
        bk = w * (q0 * l0 + q1 * l1 + q2 * l2)  # b − a·(o, 0…) = w nᵀ(x − o): small numbers, no cancellation
        rk = u0 * f0 + u1 * f1 + u2 * f2 + u3 * f3 + u4 * f4 + u5 * f5 + u6 * f6 + u7 * f7 - bk
        face[k] = f_in if deep else -1
        along[k] = v1 if f_in < 2 else v0  # a deep point's row: its face and this coordinate
        bs[k] = bk
        rs[k] = rk
        s00 += u0 * u0
        s01 += u0 * u1
        s02 += u0 * u2
        s03 += u0 * u3
        s04 += u0 * u4
        s05 += u0 * u5
        s06 += u0 * u6
        s07 += u0 * u7
        s11 += u1 * u1
        s12 += u1 * u2
        s13 += u1 * u3
        s14 += u1 * u4
        s15 += u1 * u5
        s16 += u1 * u6
        s17 += u1 * u7
        s22 += u2 * u2
        s23 += u2 * u3
        s24 += u2 * u4
        s25 += u2 * u5
        s26 += u2 * u6
        s27 += u2 * u7
        s33 += u3 * u3
        s34 += u3 * u4
        s35 += u3 * u5
        s36 += u3 * u6
        s37 += u3 * u7
        s44 += u4 * u4
        s45 += u4 * u5
        s46 += u4 * u6
        s47 += u4 * u7
        s55 += u5 * u5
        s56 += u5 * u6
        s57 += u5 * u7
        s66 += u6 * u6
        s67 += u6 * u7
        s77 += u7 * u7
        ab0 += u0 * bk
        ab1 += u1 * bk
        ab2 += u2 * bk
        ab3 += u3 * bk
        ab4 += u4 * bk
        ab5 += u5 * bk
        ab6 += u6 * bk
        ab7 += u7 * bk
        rr += 0.0 if deep else rk * rk
        w2 = 0.0 if deep else u0 * u0 + u1 * u1 + u2 * u2
        ss += w2 * sq
        sw += w2
    ata = np.empty((8, 8))
    atb = np.empty(8)
    ata[0, 0] = ata[0, 0] = s00
    ata[0, 1] = ata[1, 0] = s01
    ata[0, 2] = ata[2, 0] = s02
    ata[0, 3] = ata[3, 0] = s03
    ata[0, 4] = ata[4, 0] = s04
    ata[0, 5] = ata[5, 0] = s05
    ata[0, 6] = ata[6, 0] = s06
    ata[0, 7] = ata[7, 0] = s07
    ata[1, 1] = ata[1, 1] = s11
    ata[1, 2] = ata[2, 1] = s12
    ata[1, 3] = ata[3, 1] = s13
    ata[1, 4] = ata[4, 1] = s14
    ata[1, 5] = ata[5, 1] = s15
    ata[1, 6] = ata[6, 1] = s16
    ata[1, 7] = ata[7, 1] = s17
    ata[2, 2] = ata[2, 2] = s22
    ata[2, 3] = ata[3, 2] = s23
    ata[2, 4] = ata[4, 2] = s24
    ata[2, 5] = ata[5, 2] = s25
    ata[2, 6] = ata[6, 2] = s26
    ata[2, 7] = ata[7, 2] = s27
    ata[3, 3] = ata[3, 3] = s33
    ata[3, 4] = ata[4, 3] = s34
    ata[3, 5] = ata[5, 3] = s35
    ata[3, 6] = ata[6, 3] = s36
    ata[3, 7] = ata[7, 3] = s37
    ata[4, 4] = ata[4, 4] = s44
    ata[4, 5] = ata[5, 4] = s45
    ata[4, 6] = ata[6, 4] = s46
    ata[4, 7] = ata[7, 4] = s47
    ata[5, 5] = ata[5, 5] = s55
    ata[5, 6] = ata[6, 5] = s56
    ata[5, 7] = ata[7, 5] = s57
    ata[6, 6] = ata[6, 6] = s66
    ata[6, 7] = ata[7, 6] = s67
    ata[7, 7] = ata[7, 7] = s77
    atb[0] = ab0
    atb[1] = ab1
    atb[2] = ab2
    atb[3] = ab3
    atb[4] = ab4
    atb[5] = ab5
    atb[6] = ab6
    atb[7] = ab7
    return ata, atb, rr, ss, sw


@kernel
def _face_gaps_kernel(y, pts_t, d, sx, sy, slab, quantile, min_points, gaps, counts):  # pragma: no cover - compiled
    """Per side face of box ``y`` (−length, +length, −width, +width), the depth inside the face of its
    outer surface — the ``quantile`` of the depths (m, negative outside) of the points (d, N)
    registered to it — into ``gaps`` (4,), NaN for a face the sensor at (``sx``, ``sy``) does not
    see (it is not beyond the face's plane in BEV) or with fewer than ``min_points`` points; the
    points registered to each face into ``counts`` (4,).

    With z (d = 3) only the points of the solid lower body count: height above the plane
    ``z = g0 + gx (x − x0) + gy (y − y0)`` within [lo, hi], ``slab`` = (g0, gx, gy, x0, y0, lo, hi)
    (the operations of :func:`~labelaudit.core.freespace.ground_heights`). A point is registered
    to the side face it lies furthest beyond, or, inside, nearest under (its largest signed
    distance |x| − l/2 or |y| − w/2); a point nearer the top or bottom face (3D) is no side's. The
    quantile is the order statistic of rank ⌊q (n − 1)⌋ (0-based, ascending), found by selection.
    """
    c, s = math.cos(y[6]), math.sin(y[6])
    h0, h1 = 0.5 * y[3], 0.5 * y[4]
    h2 = 0.5 * y[5] if d == 3 else math.inf
    rx, ry = sx - y[0], sy - y[1]
    bx, by = c * rx + s * ry, -s * rx + c * ry  # the sensor in the box frame
    n = pts_t.shape[1]
    face = np.empty(n, dtype=np.int64)
    depth = np.empty(n)
    for f in range(4):
        counts[f] = 0
    for k in range(n):
        face[k] = -1
        if d == 3:
            h = pts_t[2, k] - (slab[0] + slab[1] * (pts_t[0, k] - slab[3]) + slab[2] * (pts_t[1, k] - slab[4]))
            if not (h >= slab[5] and h <= slab[6]):
                continue
        qx, qy = pts_t[0, k] - y[0], pts_t[1, k] - y[1]
        l0, l1 = c * qx + s * qy, -s * qx + c * qy
        e0, e1 = abs(l0) - h0, abs(l1) - h1
        if e0 >= e1:
            f, e = (1 if l0 > 0.0 else 0), e0
        else:
            f, e = (3 if l1 > 0.0 else 2), e1
        if d == 3 and abs(pts_t[2, k] - y[2]) - h2 > e:
            continue
        face[k] = f
        depth[k] = -e
        counts[f] += 1
    for f in range(4):
        gaps[f] = math.nan
        sign = 1.0 if f % 2 else -1.0
        seen = sign * bx > h0 if f < 2 else sign * by > h1
        m = counts[f]
        if not seen or m == 0 or m < min_points:
            continue
        dep = np.empty(m)
        j = 0
        for k in range(n):
            if face[k] == f:
                dep[j] = depth[k]
                j += 1
        rank = int(quantile * (m - 1))
        gaps[f] = np.partition(dep, rank)[rank]  # the order statistic alone: a sort's value, without the sort


@kernel
def _solve_spd(M, rhs):  # pragma: no cover - compiled
    """x with M x = rhs for a small symmetric positive definite M (p, p): Cholesky, two
    triangular substitutions (scalars only; a LAPACK call from here would need scipy). NaN when M
    is not positive definite: the fit then reports NaN."""
    p = M.shape[0]
    x = np.empty(p)
    _solve_spd_into(M, rhs, np.zeros((p, p)), np.empty(p), x)
    return x


@kernel
def _solve_spd_into(M, rhs, L, z, x):  # pragma: no cover - compiled
    """:func:`_solve_spd` into ``x`` (p,), with its work arrays given: L (p, p; zeros above the
    diagonal, the rest written before it is read), z (p,)."""
    p = M.shape[0]
    if not linalg.cholesky_kernel(M, L):
        x[:] = np.nan
        return
    for i in range(p):
        acc = rhs[i]
        for k in range(i):
            acc -= L[i, k] * z[k]
        z[i] = acc / L[i, i]
    for i in range(p - 1, -1, -1):
        acc = z[i]
        for k in range(i + 1, p):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]


@kernel
def _scored_metrics_kernel(cov, S_tol, scored, w_tol, w):  # pragma: no cover - compiled
    """The two metrics of the label-error distances (:func:`_scored_metric`): ``w_tol`` = that of
    cov + S_tol, ``w`` = that of cov, both (p, p): the inverse of the ``scored`` entries' block
    (int indices, ascending), zero elsewhere. Returns False (outputs undefined) when a block is
    not positive definite."""
    k = scored.shape[0]
    a = np.empty((k, k))
    inv = np.empty((k, k))
    w_tol[:, :] = 0.0
    w[:, :] = 0.0
    for with_tol in (True, False):
        for i in range(k):
            for j in range(k):
                a[i, j] = (
                    cov[scored[i], scored[j]] + S_tol[scored[i], scored[j]] if with_tol else cov[scored[i], scored[j]]
                )
        if not linalg.spd_inverse_kernel(a, inv):
            return False
        out = w_tol if with_tol else w
        for i in range(k):
            for j in range(k):
                out[scored[i], scored[j]] = inv[i, j]
    return True


@kernel
def _label_distances_kernel(
    cov, G, tol_cov, scored, y_rect, phi_label, three_d, phi_out
):  # pragma: no cover - compiled
    """The label-error distances of a fit, in one call: S_tol = G tol_cov Gᵀ (the tolerance in φ),
    the two metrics of :func:`_scored_metrics_kernel` (of cov + S_tol and of cov; ``scored``: the
    scored φ entries), the form of ``y_rect`` closest to ``phi_label`` in the first
    (:func:`_closest_form_kernel`, its φ into ``phi_out``) and the squared distances
    δᵀ W δ of δ = φ_label − φ_form in both. Returns (ok, k, yaw_k, d² with the tolerance, d²);
    ok False when a block is not positive definite (the rest undefined)."""
    p = cov.shape[0]
    gt = np.empty((p, p))  # tol_cov Gᵀ
    linalg.matmul_kernel(tol_cov, G.T, gt)
    s_tol = np.empty((p, p))
    linalg.matmul_kernel(G, gt, s_tol)
    w_tol, w = np.empty((p, p)), np.empty((p, p))
    if not _scored_metrics_kernel(cov, s_tol, scored, w_tol, w):
        return False, 0, 0.0, 0.0, 0.0
    k, yaw = _closest_form_kernel(y_rect, phi_label, w_tol, three_d, phi_out)
    d2_tol = d2 = 0.0
    for i in range(p):
        acc_tol = acc = 0.0
        for j in range(p):
            acc_tol += w_tol[i, j] * (phi_label[j] - phi_out[j])
            acc += w[i, j] * (phi_label[j] - phi_out[j])
        d2_tol += (phi_label[i] - phi_out[i]) * acc_tol
        d2 += (phi_label[i] - phi_out[i]) * acc
    return True, k, yaw, d2_tol, d2


_RAY_REACH = (
    2.0  # m; rays further outside the label than this are not tracked (the candidates reach 1 m); the skip is exact
)


@kernel
def _max_abs_diff(a, b):  # pragma: no cover - compiled
    """``np.max(np.abs(a − b))`` of two vectors (p,) without the temporaries: NaN when a difference is NaN."""
    out = abs(a[0] - b[0])
    if out != out:
        return out
    for i in range(1, a.shape[0]):
        v = abs(a[i] - b[i])
        if v != v:
            return v
        if v > out:
            out = v
    return out


@kernel
def _all_equal(a, b):  # pragma: no cover - compiled
    """``np.all(a == b)`` of two vectors (p,) without the temporary."""
    for i in range(a.shape[0]):
        if not a[i] == b[i]:
            return False
    return True


@kernel
def _fit_iterate_kernel(
    y_cur,
    phi,
    pts_t,
    three_d,
    free_depth,
    deep_weight,
    outlier,
    tol,
    P0,
    prior_eta,
    label,
    inv_s2,
    floor,
    max_iter,
    halvings,
    stall,
    ends_t,
    ox,
    oy,
    hz,
    tau,
    tau_in,
    ray_weight,
    slit,
    smooth,
    wfloor,
    bounds,
    face,
    along,
    bs,
    rs,
    ray_a,
    ray_b,
):  # pragma: no cover - compiled
    """EM iterations of the box fit on (d, N) points from rectangle ``y_cur`` (φ ``phi``) until φ
    moves by less than ``tol`` (at most ``max_iter``). Returns (φ, rectangle, iterations, converged,
    stopped, precision, Σ w²‖x − v̄‖², Σ w²): ``stopped`` when a descent ended on the last box it
    accepted, whose pass is then the fitted box's — the symmetrised precision P0 + Σ aᵀa / σ² of its
    point and ray rows and its points' RMS sums (:func:`_fit_precision_work`'s, the same operations
    on the same rows) are returned with it (otherwise undefined).

    With free-space rays the iteration is a descent (docs/label-error.md, "The suggested box"): a
    step that raises the cost is halved back (up to ``halvings`` times), and when a step shorter
    than ``stall`` still raises it, the fit is the last box the descent accepted (converged).

    The iterations only need the mean (a linear solve). When the iteration has entered an exact
    2-cycle (a point flipping between two faces, so that φ repeats bit for bit), it can never
    converge: the state the iteration cap would end on is known, and is returned without running
    the remaining iterations. Point pass, free-space ray rows, Gram product, the p × p solve and
    the rectangle of φ are all compiled: per iteration, NumPy calls around the point pass would
    cost as much as the pass itself. The work arrays — the point pass's ``face``, ``along``,
    ``bs``, ``rs`` (N,), the ray rows' ``ray_a`` (p, M), ``ray_b`` (M,) — are given, and the
    iteration's own vectors and matrices are made once: the element-wise operations are NumPy's
    expressions written as loops (the same operations in the same order).
    """
    d = 3 if three_d else 2
    p = phi.shape[0]
    m = ends_t.shape[1]
    phi = phi.copy()  # the caller's φ (the label's) is never written: halving steps work in place
    phi_prev = phi.copy()
    new = np.empty(p)
    y_cur = y_cur.copy()
    prec = np.empty((p, p))
    sym = np.empty((p, p))
    rhs = np.empty(p)
    chol = np.zeros((p, p))
    z = np.empty(p)
    sigma = 1.0 / math.sqrt(inv_s2)
    kept = np.empty((p, p))  # the last accepted box's symmetrised precision (a descent's stop returns that box)
    kept_ss = kept_sw = 0.0
    kept_ok = False  # whether ``kept`` is the last accepted box's: the first pass is at ``y_cur`` as given, not rect(φ)
    descent = halvings > 0 and m > 0  # only rays made plain steps overshoot (points alone: EM converges)
    e_prev = math.inf
    halved = 0
    it = 0
    for it in range(1, max_iter + 1):
        ata, atb, rr, ss, sw = _normal_eq_work(
            y_cur, pts_t, d, free_depth, deep_weight, outlier, sigma, phi, face, along, bs, rs
        )
        if m:
            ata_r, atb_r, rr_r, k = _ray_normal_eq_work(
                y_cur,
                ends_t,
                ox,
                oy,
                hz,
                tau,
                tau_in,
                ray_weight,
                slit,
                smooth,
                three_d,
                phi,
                wfloor,
                bounds,
                label,
                ray_a,
                ray_b,
            )
            if k:
                for i in range(p):
                    for j in range(p):
                        ata[i, j] += ata_r[i, j]
                    atb[i] += atb_r[i]
                rr += rr_r
        if descent:
            # the cost at this box (rows and robust weights of this box, prior); a step that raised it
            # overshot (into free space the rays forbid, past the points): go half way back instead
            e_cur = rr * inv_s2
            for i in range(p):  # + φᵀP0φ − 2φᵀη, in scalars (a BLAS dot would load scipy.linalg in the workers)
                acc = -2.0 * prior_eta[i]
                for j in range(p):
                    acc += P0[i, j] * phi[j]
                e_cur += phi[i] * acc
            if e_cur > e_prev * (1.0 + 1e-12) + 1e-12:
                if halved >= halvings or _max_abs_diff(phi, phi_prev) < stall:
                    # a step shorter than ``stall`` still raises the cost: the descent has stopped at
                    # the last point it accepted, which is returned as it is (not the trial point:
                    # where the halving ended depends on the path, the accepted point on the data)
                    _rect_from_phi_into(phi_prev, three_d, label, floor, y_cur)
                    return phi_prev, y_cur, it, True, kept_ok, kept, kept_ss, kept_sw
                halved += 1
                for i in range(p):
                    phi[i] = 0.5 * (phi_prev[i] + phi[i])
                _rect_from_phi_into(phi, three_d, label, floor, y_cur)
                continue
            halved = 0
            e_prev = e_cur
        for i in range(p):  # P0 + ata σ⁻², symmetrised; η + atb σ⁻²
            for j in range(p):
                prec[i, j] = P0[i, j] + ata[i, j] * inv_s2
        for i in range(p):
            for j in range(p):
                sym[i, j] = 0.5 * (prec[i, j] + prec[j, i])
            rhs[i] = prior_eta[i] + atb[i] * inv_s2
        if descent:
            kept_ok = it > 1
            if kept_ok:
                kept[:, :] = sym
                kept_ss, kept_sw = ss, sw
        _solve_spd_into(sym, rhs, chol, z, new)
        step = _max_abs_diff(new, phi)
        if it >= 3 and step >= tol and _all_equal(new, phi_prev):
            # φ_it = φ_(it−2): the states alternate up to the cap. End on the cap's state.
            if (max_iter - it) % 2 == 0:
                phi = new
            _rect_from_phi_into(phi, three_d, label, floor, y_cur)
            return phi, y_cur, max_iter, False, False, kept, kept_ss, kept_sw
        phi_prev, phi, new = phi, new, phi_prev
        _rect_from_phi_into(phi, three_d, label, floor, y_cur)
        if step < tol:
            return phi, y_cur, it, True, False, kept, kept_ss, kept_sw
    return phi, y_cur, it, False, False, kept, kept_ss, kept_sw


@kernel
def _ray_normal_eq_work(
    y, ends_t, ox, oy, hz, tau, tau_in, ray_weight, slit, smooth, three_d, phi, wfloor, bounds, label, a, b
):  # pragma: no cover - compiled
    """Σ aᵀa (p, p), Σ a b (p,), Σ (a·φ − b)² and the number of the ray rows of box ``y``
    (:func:`~labelaudit.core.freespace.free_rows_kernel`), skipping the rays whose ``bounds`` at
    the ``label`` (:func:`~labelaudit.core.freespace.label_ray_terms`) rule them out — exact (bounds
    of +inf evaluate every ray). The rows' work arrays are given: ``a`` (p, M), ``b`` (M,)."""
    slack = displacement(y, label, _RAY_REACH)
    active = free_rows_kernel(
        y, ends_t, ox, oy, hz, tau, tau_in, ray_weight, slit, smooth, three_d, a, b, bounds, slack, wfloor
    )
    ata, atb, rr = _gram_kernel(a[:, :active], b[:active], phi, True)
    return ata, atb, rr, active


@kernel
def _fit_precision_work(
    y,
    pts_t,
    three_d,
    free_depth,
    deep_weight,
    outlier,
    sigma,
    phi,
    P0,
    inv_s2,
    ends_t,
    ox,
    oy,
    hz,
    tau,
    tau_in,
    ray_weight,
    slit,
    smooth,
    wfloor,
    bounds,
    label,
    face,
    along,
    bs,
    rs,
    ray_a,
    ray_b,
):  # pragma: no cover - compiled
    """The posterior precision (p, p) at the fitted rectangle ``y`` — P0 + (Σ aᵀa of the point rows
    + of the ray rows) / σ², symmetrised —, Σ (a·φ − b)² of both and the point rows' Σ w²‖x − v̄‖²,
    Σ w² (:func:`_normal_eq_work`, :func:`_ray_normal_eq_work`): one call, the element-wise
    operations in NumPy's order (no fast-math). The rays skipped by their bounds at the ``label``
    (as in the descent) give no row: the same rows as evaluating every ray.
    The work arrays of the point pass (``face`` … ``rs``) and of the ray rows (``ray_a``, ``ray_b``)
    are given."""
    ata, _, rr, ss, sw = _normal_eq_work(
        y, pts_t, 3 if three_d else 2, free_depth, deep_weight, outlier, sigma, phi, face, along, bs, rs
    )
    if ends_t.shape[1]:
        ata_r, _, rr_r, _ = _ray_normal_eq_work(
            y,
            ends_t,
            ox,
            oy,
            hz,
            tau,
            tau_in,
            ray_weight,
            slit,
            smooth,
            three_d,
            phi,
            wfloor,
            bounds,
            label,
            ray_a,
            ray_b,
        )
        ata = ata + ata_r
        rr += rr_r
    p = ata.shape[0]
    prec = P0 + ata * inv_s2
    out = np.empty((p, p))
    for i in range(p):
        for j in range(p):
            out[i, j] = 0.5 * (prec[i, j] + prec[j, i])
    return out, rr, ss, sw


@kernel
def _phi_of_rect(y, three_d):  # pragma: no cover - compiled
    """φ (p,) of a rectangle (7,) known to be valid: :func:`~labelaudit.core.geometry.phi_of_valid_box`."""
    c, s = math.cos(y[6]), math.sin(y[6])
    if three_d:
        return np.array([y[0], y[1], y[2], y[3] * c, y[3] * s, y[4] * c, y[4] * s, y[5]])
    return np.array([y[0], y[1], y[3] * c, y[3] * s, y[4] * c, y[4] * s])


@kernel
def _fit_em_kernel(
    start,
    phi,
    pts_t,
    three_d,
    free_depth,
    deep_weight,
    outlier,
    tol,
    P0,
    prior_eta,
    phi_label,
    label,
    sigma,
    inv_s2,
    floor,
    max_iter,
    halvings,
    stall,
    ends_t,
    ox,
    oy,
    hz,
    tau,
    tau_in,
    ray_weight,
    slit,
    smooth,
    wfloor,
    bounds,
    cov,
    post_above,
):  # pragma: no cover - compiled
    """One start of the box fit (:func:`_fit_em`): the descent from rectangle ``start`` (φ ``phi``),
    the precision at the fitted rectangle, its inverse into ``cov`` (p, p). Returns (φ, fitted
    rectangle, iterations, converged, log posterior, RMS of the points that count, whether the
    precision was positive definite, the precision). The passes share one set of work arrays.

    The log posterior is wanted only when the RMS is above ``post_above`` (−inf: always): a descent
    that stopped on the last box it accepted then hands back that box's pass (its precision and
    RMS, the same numbers a further pass would give) and the log posterior is NaN — its residuals
    at φ of the fitted rectangle would take a further pass."""
    n, p, m = pts_t.shape[1], phi.shape[0], ends_t.shape[1]
    face, along, bs, rs = np.empty(n, dtype=np.int64), np.empty(n), np.empty(n), np.empty(n)
    ray_a, ray_b = np.empty((p, m)), np.empty(m)
    phi, y_cur, it, converged, stopped, kept, kept_ss, kept_sw = _fit_iterate_kernel(
        start,
        phi,
        pts_t,
        three_d,
        free_depth,
        deep_weight,
        outlier,
        tol,
        P0,
        prior_eta,
        label,
        inv_s2,
        floor,
        max_iter,
        halvings,
        stall,
        ends_t,
        ox,
        oy,
        hz,
        tau,
        tau_in,
        ray_weight,
        slit,
        smooth,
        wfloor,
        bounds,
        face,
        along,
        bs,
        rs,
        ray_a,
        ray_b,
    )
    phi_rect = _phi_of_rect(y_cur, three_d)
    if stopped and kept_sw > 0 and math.sqrt(kept_ss / kept_sw) <= post_above:
        # the descent's stop: the fitted box is the last accepted one, whose precision and RMS the
        # descent kept; the log posterior (a pass for its residuals at φ_rect) is not wanted
        ok = linalg.spd_inverse_kernel(kept, cov)
        return phi, y_cur, it, converged, math.nan, math.sqrt(kept_ss / kept_sw), ok, kept
    precision, rr, ss, sw = _fit_precision_work(
        y_cur,
        pts_t,
        three_d,
        free_depth,
        deep_weight,
        outlier,
        sigma,
        phi_rect,
        P0,
        inv_s2,
        ends_t,
        ox,
        oy,
        hz,
        tau,
        tau_in,
        ray_weight,
        slit,
        smooth,
        wfloor,
        bounds,
        label,
        face,
        along,
        bs,
        rs,
        ray_a,
        ray_b,
    )
    ok = linalg.spd_inverse_kernel(precision, cov)
    p = phi_rect.shape[0]
    quad = 0.0  # (φ_rect − φ_label)ᵀ P0 (φ_rect − φ_label)
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += P0[i, j] * (phi_rect[j] - phi_label[j])
        quad += (phi_rect[i] - phi_label[i]) * acc
    log_post = -0.5 * rr * inv_s2 - 0.5 * quad
    rms = math.sqrt(ss / sw) if sw > 0 else 0.0  # distance to the surface of the points that count (not deep ones)
    return phi, y_cur, it, converged, log_post, rms, ok, precision


_NO_FACE_GAPS = np.full(4, np.nan)

_NO_RAYS = (np.empty((3, 0)), 0.0, 0.0, np.zeros(5), 0.0, 0.0, 0.0, 0.0, 1.0, np.empty(0), np.empty(0))
"""Ray inputs of a fit without free-space evidence (the kernels' layout, see :func:`_ray_inputs`)."""


def _ray_inputs(free_space: FreeSpace | None, sigma: float, label: FloatArray) -> tuple:
    """(ends_t (3, M), sensor x, sensor y, hz (5,) = (sensor height, slab bottom, slab top, object height, σ), τ,
    τ inside, √weight, slit probability, smoothing, the rays' √weight at the label (M,), their bounds at
    the label (M,)) of the fit's ray rows (:func:`~labelaudit.core.freespace.free_rows_kernel`), for the
    fits of one ``label`` (7,)."""
    if free_space is None or free_space.num_rays == 0:
        return _NO_RAYS
    ends_t, ox, oy, hz = free_space.kernel_inputs()
    hz5 = np.empty(5)
    hz5[:4] = hz
    hz5[4] = sigma
    tau, tau_in, weight, slit = (
        float(free_space.tolerance),
        float(free_space.inside_tolerance),
        float(C.FREE_SPACE_WEIGHT),
        float(C.FREE_SPACE_SLIT_PROB),
    )
    m = ends_t.shape[1]
    floor, bounds = np.empty(m), np.empty(m)
    label_ray_terms(label, ends_t, ox, oy, hz5, tau, tau_in, weight, slit, _RAY_REACH, bounds, floor)
    return (ends_t, ox, oy, hz5, tau, tau_in, weight, slit, float(C.FIT_SMOOTHING), floor, bounds)


def _fit_point_constants() -> tuple[float, float, float]:
    """(free depth, deep-point √weight, outlier probability) of the fit's point rows (:func:`_rows_kernel`),
    read from the constants at each call (the real-data benchmark chooses some of them by leave-one-frame-out)."""
    return (C.FIT_INSIDE_FREE_DEPTH, 1.0 / C.FIT_INSIDE_SIGMA_RATIO, C.FIT_OUTLIER_PROB)


def _fit_em(
    start: FloatArray,
    pts: FloatArray,
    phi_label: FloatArray,
    P0: FloatArray,
    label: FloatArray,
    sigma: float,
    params: ModelParams,
    rays: tuple = _NO_RAYS,
    prior_eta: FloatArray | None = None,
    phi_start: FloatArray | None = None,
    post_above: float = -math.inf,
) -> tuple[FloatArray, FloatArray, int, bool, float, FloatArray, float]:
    """Box fit from ``start`` (a rectangle): register each point to its nearest surface point of the
    current box, add a row per free-space ray through the box's slab, take the Gaussian mean with
    the prior centred on the label, repeat (Gauss–Newton / EM). Returns (φ, Σ, iterations,
    converged, log posterior, fitted rectangle, RMS distance to its surface of the points that
    count — weighted, so points deep inside the box, which the fit ignores, do not call for the
    swapped start).

    ``pts`` is (d, N) (transposed). The covariance is formed once, at the fitted box, with the ray
    rows active there. ``prior_eta`` = P0 φ_label and ``phi_start`` = φ(start) when the caller has
    them (a fit runs up to two starts; the first is the label). The log posterior is wanted only
    when the RMS is above ``post_above`` (the swapped start's test): below, it may be NaN.
    """
    model = params.kind
    phi = g.phi_of_valid_box(start, model) if phi_start is None else phi_start
    if prior_eta is None:
        prior_eta = P0 @ phi_label
    cov = np.empty(P0.shape)
    phi, y_cur, it, converged, log_post, rms, ok, precision = _fit_em_kernel(
        start,
        phi,
        pts,
        model == "3d",
        *_fit_point_constants(),
        float(C.FIT_TOLERANCE),
        P0,
        prior_eta,
        phi_label,
        label,
        float(sigma),
        1.0 / sigma**2,
        C.FIT_MIN_SIZE_FRACTION,
        C.FIT_MAX_ITERATIONS,
        int(C.FIT_STEP_HALVINGS),
        float(C.FIT_STALL_STEP),
        *rays,
        cov,
        post_above,
    )
    if not ok:
        cov = spd_inverse(precision)  # LAPACK's verdict, or the error naming the eigenvalues
    return phi, cov, int(it), bool(converged), float(log_post), y_cur, float(rms)


def _scored_metric(S: FloatArray, fit_model: ModelKind, scored: ModelKind) -> FloatArray:
    """Metric (p, p) of the label-error distance: S⁻¹ for the scored φ entries, zero elsewhere.

    A BEV run (``scored == "bev"``) of a 3D fit scores the BEV marginal of the Gaussian, i.e. the
    inverse of the (cx, cy, l·cos, l·sin, w·cos, w·sin) block of S: the fit is 3D so roof points
    register to the top face, but its cz and height are not what a BEV audit judges, and they are
    the least reliable parameters of the fit (the ground cut removes every point of the bottom
    face; near the sensor the roof of tall vehicles is above the top beam). On the label-error
    benchmark scoring them raised false alarms on correct labels (docs/label-error.md).
    """
    if fit_model == scored:
        return linalg.inv(S)
    W = np.zeros(S.shape)
    if S.flags.c_contiguous:  # the fit's matrices: flat take/put, the same entries as the ix_ indexing below
        W.ravel()[_BEV_BLOCK_FLAT] = linalg.inv(S.take(_BEV_BLOCK_FLAT).reshape(len(g.BEV_OF_3D), -1)).ravel()
    else:
        W[_BEV_BLOCK] = linalg.inv(S[_BEV_BLOCK])
    return W


def _scored_metrics(
    cov: FloatArray, S_tol: FloatArray, fit_model: ModelKind, scored: ModelKind
) -> tuple[FloatArray, FloatArray]:
    """(:func:`_scored_metric` of cov + S_tol, of cov), both (p, p), in one compiled call (Cholesky
    inverses of the scored block); NumPy's general inverse when a block is not positive definite."""
    p = cov.shape[0]
    w_tol, w = np.empty((p, p)), np.empty((p, p))
    idx = _SCORED_ALL[p] if fit_model == scored else g.BEV_OF_3D
    if _scored_metrics_kernel(cov, S_tol, idx, w_tol, w):
        return w_tol, w
    return _scored_metric(cov + S_tol, fit_model, scored), _scored_metric(cov, fit_model, scored)


_SCORED_ALL = {p: np.arange(p) for p in (6, 8)}  # every φ entry scored (the fit's model is the run's)
_BEV_BLOCK = np.ix_(g.BEV_OF_3D, g.BEV_OF_3D)
_BEV_BLOCK_FLAT = (
    g.BEV_OF_3D[:, None] * 8 + g.BEV_OF_3D[None, :]
).ravel()  # _BEV_BLOCK as flat indices into a C-ordered (8, 8)
_TOLERANCE: list[tuple[dict[str, float], ClassPrior]] = []  # (the constants' dict, its ClassPrior)


def _tolerance_prior() -> ClassPrior:
    """:data:`~labelaudit.constants.LABEL_TOLERANCE` as a ClassPrior, made again only when the constant changes."""
    last = _TOLERANCE[-1] if _TOLERANCE else None
    if last is not None and last[0] == C.LABEL_TOLERANCE:
        return last[1]
    out = ClassPrior(**C.LABEL_TOLERANCE)
    _TOLERANCE[:] = [(dict(C.LABEL_TOLERANCE), out)]
    return out


_AS_KIND: list[tuple[ModelParams, ModelKind, ModelParams]] = []  # the last params → params of another kind


def _params_of_kind(params: ModelParams, kind: ModelKind) -> ModelParams:
    """``dataclasses.replace(params, kind=kind)``, reused while the same params object comes back
    (every box of a run: the copy costs more than a BEV box's whole prior)."""
    last = _AS_KIND[-1] if _AS_KIND else None  # one read: safe with threads
    if last is not None and last[0] is params and last[1] == kind:
        return last[2]
    out = dataclasses.replace(params, kind=kind)
    _AS_KIND[:] = [(params, kind, out)]
    return out


def face_gaps(
    box: ArrayLike, points: ArrayLike, sensor_origin: ArrayLike, free_space: FreeSpace | None = None
) -> tuple[FloatArray, NDArray[np.int64]]:
    """How deep inside each side face of ``box`` (7,) the outer surface of its lower body lies.

    Returns ``(gaps, counts)``, both (4,), in the order −length, +length, −width, +width face:
    :data:`~labelaudit.constants.FACE_GAP_QUANTILE` of the depths inside the face (m; negative
    outside) of the points (N, ≥2) registered to it, NaN for a face the sensor at
    ``sensor_origin`` does not see (it is not beyond the face's plane, bird's-eye view) or with
    fewer than :data:`~labelaudit.constants.FACE_GAP_MIN_POINTS` points; and the number of points
    registered to each face. With z, only points of the solid lower body count —
    ``free_space.slab`` above its local ground, or FREE_SPACE_SLAB above the box bottom without
    ``free_space`` — and a point nearer the top or bottom face belongs to no side. A point belongs
    to the side face it lies furthest beyond (outside the box) or nearest under (inside).

    Above the lower body the surface is the cabin, windscreen and hood, inside a right label by
    the vehicle's shape; a face whose lower body is hidden, or that the sensor never sees, has no
    gap: nothing in the points says where it is.
    """
    y = g.validate_box(box)
    pts = np.asarray(points, dtype=float)
    d = 3 if pts.ndim == 2 and pts.shape[1] >= 3 else 2
    return _slab_face_gaps(y, g.clean_columns(pts, d), sensor_origin, free_space)


def _slab_face_gaps(
    y: FloatArray, pts_t: FloatArray, origin: ArrayLike, free_space: FreeSpace | None
) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`face_gaps` of a valid box (7,) and clean points (d, N) (the fit's layout)."""
    slab = np.empty(7)  # (g0, gx, gy, x0, y0, lo, hi)
    if free_space is not None:
        slab[:3] = free_space.ground[:3]
        slab[3:5] = free_space.ref[:2]
        slab[5:] = free_space.slab
    else:  # above the box bottom
        slab[:] = (y[2] - 0.5 * y[5], 0.0, 0.0, 0.0, 0.0, C.FREE_SPACE_SLAB[0], C.FREE_SPACE_SLAB[1] * y[5])
    sx, sy = g.sensor_xy(origin)
    gaps, counts = np.empty(4), np.empty(4, dtype=np.int64)
    _face_gaps_kernel(
        y, pts_t, pts_t.shape[0], sx, sy, slab, C.FACE_GAP_QUANTILE, int(C.FACE_GAP_MIN_POINTS), gaps, counts
    )
    return gaps, counts


def _face_gap_d2(gaps: FloatArray) -> tuple[float, int]:
    """(Σ (gap − FACE_GAP)² / FACE_GAP_STD², number of seen faces) over the faces with a gap.

    The quantile's own noise (the LiDAR's range noise, 1–3 cm, over at least FACE_GAP_MIN_POINTS
    points) is small against the annotation's looseness and is not added: with the fit's σ̂²/n added
    (σ̂ holds the object's shape, not only noise) the real held-out AUROC was lower (0.920 → 0.927
    without, pooled)."""
    d2, m = 0.0, 0
    for gap in gaps.tolist():
        if gap == gap:
            d2 += (gap - C.FACE_GAP) ** 2 / C.FACE_GAP_STD**2
            m += 1
    return d2, m


def fit_label(
    box: ArrayLike,
    points: ArrayLike | None,
    class_name: str,
    params: ModelParams,
    free_space: FreeSpace | None = None,
    sensor_origin: ArrayLike | None = None,
) -> LabelFit:
    """The model's suggested box for a label, and scores of how far the label is from it.

    The posterior mean of φ is no longer pinned to the label: EM alternates registration to the
    current box with the Gaussian mean ``Σ(Σ0⁻¹φ̄ + σ⁻² Σ r Jᵀx)`` — the prior, centred on the label,
    keeps sparse boxes from running away. Registration is to the single nearest surface point and
    only the residual across the surface counts (point-to-plane), so faces slide freely while
    fitting. When the fit from the label leaves the points far from its surface, a second start
    with length and width swapped is tried (a gross error nearest-face registration cannot climb
    out of); the one with the higher log posterior wins. Symmetries are handled honestly: the suggested box is
    written in the equivalent form (yaw + kπ/2, l/w swapped for odd k) nearest the label, so a label
    whose box is right but whose heading is reversed (or described with l/w swapped and yaw turned
    by 90°) is the same rectangle and is not called an error — points cannot tell heading.

    ``label_error`` = chi2.cdf(d², k): d² is the squared Mahalanobis distance between label and fit
    with the fit's covariance plus a tolerance covariance (LABEL_TOLERANCE: offsets of ~10 cm /
    2° are annotation noise, not errors), k the number of box parameters. It is near 0 when the
    points agree with the label *or cannot tell* (few points: wide posterior), and near 1 when the
    points put the box clearly elsewhere. Rough reading: 0.5 ≈ two tolerances off in one parameter
    (≈ 20 cm), 0.9 ≈ three, 0.99 ≈ four.

    With the sensor's position (``sensor_origin``, else ``free_space.origin``) the side faces the
    sensor sees add one χ² term each to d² and one degree of freedom each to k: how far each lies
    beyond its lower body's outer surface, against a right label's looseness
    (:func:`face_gaps`; FACE_GAP ± FACE_GAP_STD) — what shows a label too long or too wide on a
    seen face, whose points the fit treats as a loose label's. Vehicles only (a solid lower body).
    """
    return fit_label_valid(g.validate_box(box), points, class_name, params, free_space, sensor_origin=sensor_origin)


def fit_label_valid(
    y: FloatArray,
    points: ArrayLike | None,
    class_name: str,
    params: ModelParams,
    free_space: FreeSpace | None = None,
    *,
    prior_terms: BoxPriorTerms | None = None,
    sensor_origin: ArrayLike | None = None,
    columns: FloatArray | None = None,
) -> LabelFit:
    """:func:`fit_label` of a box (7,) float64 known to be valid (after
    :func:`~labelaudit.core.geometry.validate_box`): the pipeline validates each label once.

    ``columns``: the points already as the fit takes them, ``clean_columns(points, d)`` (d, N)
    float64 C-contiguous (d = 3: a 3D fit), when the caller made them (the pipeline's crop pass);
    ``points`` is then not read.

    ``prior_terms``: the label's :class:`~labelaudit.core.posterior.BoxPriorTerms` of the fit's
    model (3D when the points have z) when the caller has them, e.g. from a 3D run's posterior
    (:func:`~labelaudit.core.posterior.infer_label_valid`); terms of another model, prior or
    weight (a BEV run's) are not used, and None: computed here."""
    # The fit is 3D whenever the points have a z: in BEV, roof and hood points lie *inside* the
    # rectangle and would pull its edges inwards; in 3D they register to the top face.
    arr = None if points is None or columns is not None else np.asarray(points)
    if arr is not None and arr.dtype.kind != "f":
        arr = np.asarray(points, dtype=float)
    if columns is not None:
        model: ModelKind = "3d" if columns.shape[0] == 3 else "bev"
    else:
        model = "3d" if arr is not None and arr.ndim == 2 and arr.shape[1] >= 3 else "bev"
    # The run's model decides what is scored: a BEV run scores the BEV marginal of the 3D fit.
    scored: ModelKind = "bev" if model == "bev" or params.kind == "bev" else "3d"
    if model != params.kind:
        params = _params_of_kind(params, model)
    d = 3 if model == "3d" else 2
    pts_t = (
        columns if columns is not None else g.clean_columns(arr, d)
    )  # (d, N), the fit's layout (_normal_eq_work): float crops in one pass
    pts = pts_t.T  # (N, d), a view
    n = pts.shape[0]
    prior = params.prior_for(class_name)
    terms = prior_terms
    if terms is None or not terms.matches(model, prior, params.prior_weight):  # e.g. a BEV run's, or points without z
        terms = box_prior_terms(y, prior, params.prior_weight, model)
    phi_label, P0 = terms.phi, terms.P0
    sigma = float(params.sigma)
    if params.estimate_sigma and n >= max(params.min_points, 2):
        # estimate_sigma(y, pts, model, …) on points already clean: the same registration and EM
        reg = register_validated(y, np.ascontiguousarray(pts), d, params.num_nearest, sigma, params.outlier_prob)
        s_hat = em_sigma([(reg.sqdist, outlier_log_density(y, d))], d, sigma, params.outlier_prob)
        if np.isfinite(s_hat):
            sigma = max(s_hat, C.SIGMA_FLOOR)

    rays = _ray_inputs(free_space, sigma, y)
    prior_eta = terms.eta0  # P0 φ_label
    # A second start with length and width swapped, when the first fit leaves the points far from
    # its surface (RMS > FIT_SWAP_RESIDUAL × σ): the nearest-face registration cannot turn a box by
    # 90° on its own. The start with the higher log posterior wins (the first start's is wanted only then).
    can_swap = n >= max(params.min_points, 1) and abs(y[3] - y[4]) > 1e-9
    swap_rms = C.FIT_SWAP_RESIDUAL * sigma
    first = _fit_em(
        y, pts_t, phi_label, P0, y, sigma, params, rays, prior_eta, phi_label, swap_rms if can_swap else math.inf
    )
    best = (first, False)
    if can_swap and first[6] > swap_rms:
        swapped = y.copy()
        swapped[3], swapped[4] = y[4], y[3]
        alt = _fit_em(
            _closest_form(swapped, phi_label, P0, model), pts_t, phi_label, P0, y, sigma, params, rays, prior_eta
        )
        if alt[4] > best[0][4] + 1e-9:
            best = (alt, True)
    (phi_fit, cov, iterations, converged, _, y_rect, _), is_swapped = best

    tol_cov = prior_cov_extended_cached(_tolerance_prior(), model)
    phi_rect = np.empty(len(phi_label))
    ok, k_form, yaw, d2_tol, d2 = _label_distances_kernel(
        cov,
        terms.G,
        tol_cov,
        _SCORED_ALL[len(phi_label)] if model == scored else g.BEV_OF_3D,
        y_rect,
        phi_label,
        d == 3,
        phi_rect,
    )
    if ok:
        y_fit = _form(y_rect, k_form, yaw)
    else:  # a block not positive definite: NumPy's general inverses (or LAPACK's error)
        S_tol = terms.G.dot(tol_cov).dot(terms.G.T)
        W, W_fit = _scored_metrics(cov, S_tol, model, scored)
        y_fit, phi_rect = _closest_form_phi(y_rect, phi_label, W, model)
        delta = phi_label - phi_rect
        d2_tol, d2 = float(delta.dot(W).dot(delta)), float(delta.dot(W_fit).dot(delta))
    k = 5 if scored == "bev" else 7
    # The seen faces' gaps, at the label: the points say where a seen face's outer surface is, and a
    # right label's face lies FACE_GAP ± FACE_GAP_STD beyond it. The fit cannot say this (points deep
    # inside never pull a face in: a label too long or too wide there looks loose, not wrong).
    origin = sensor_origin if sensor_origin is not None else (None if free_space is None else free_space.origin)
    gaps, d2_gap, m = _NO_FACE_GAPS, 0.0, 0
    if origin is not None and n and class_name in C.FREE_SPACE_CLASSES:
        gaps, _ = _slab_face_gaps(y, pts_t, origin, free_space)
        d2_gap, m = _face_gap_d2(gaps)

    fit_v, label_v = y_fit.tolist(), y.tolist()  # Python floats: the same IEEE differences as y_fit − y
    diffs = [a - b for a, b in zip(fit_v, label_v)]
    offsets = dict(zip(g.BOX_FIELDS, diffs))
    offsets["yaw"] = (fit_v[6] - label_v[6] + math.pi) % (2.0 * math.pi) - math.pi  # g.normalize_angle of a float
    y_fit[6] = label_v[6] + offsets["yaw"]  # same branch as the label's yaw, so fit_yaw − yaw is the offset
    if d == 2:
        offsets["cz"] = offsets["height"] = float("nan")
    dc = np.array(diffs[:d])  # = y_fit[:d] − y[:d] (the yaw line above leaves the centre alone)
    return LabelFit(
        model=model,
        box=y_fit,
        phi=phi_rect,
        cov=cov,
        offsets=offsets,
        offset_m=math.sqrt(dc.dot(dc)),  # = np.linalg.norm(dc)
        mahalanobis=math.sqrt(max(d2, 0.0)),
        tolerance_distance=math.sqrt(max(d2_tol, 0.0)),
        label_error=_chi2_cdf(max(d2_tol, 0.0) + d2_gap, k + m),
        iterations=iterations,
        converged=converged,
        swapped_start=is_swapped,
        face_gaps=tuple(gaps.tolist()),
        face_gap_distance=math.sqrt(d2_gap),
        _residual_inputs=(y_fit.copy(), pts, d, params, sigma) if n >= 2 else (),
    )


def _chi2_cdf(x: float, k: int) -> float:
    """CDF of the χ² distribution with an integer number of degrees of freedom k ≥ 1, closed form
    (equals ``scipy.stats.chi2.cdf`` to ~1e-15; scipy.stats costs a second to import per worker).

    Even k: 1 − e^(−x/2) Σ_(j<k/2) (x/2)^j / j!.  Odd k: erf(√(x/2)) − e^(−x/2) Σ_(j=1..(k−1)/2)
    x^(j−½) √(2/π) / (1·3·…·(2j−1)).
    """
    if x <= 0.0:
        return 0.0
    if k % 2 == 0:
        term = total = 1.0
        for j in range(1, k // 2):
            term *= 0.5 * x / j
            total += term
        return float(max(0.0, 1.0 - math.exp(-0.5 * x) * total))
    term = math.sqrt(2.0 * x / math.pi)
    total = 0.0
    for j in range(1, (k - 1) // 2 + 1):
        total += term
        term *= x / (2 * j + 1)
    return float(min(1.0, max(0.0, math.erf(math.sqrt(0.5 * x)) - math.exp(-0.5 * x) * total)))

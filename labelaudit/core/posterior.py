"""The paper's generative label model (docs/method.md): registration, posterior covariance, noise EM.

Each LiDAR point x_k of a box is explained by one of the M nearest points v̄_km = J(v*_km)·φ̄ on the
surface of the *labeled* box, with isotropic Gaussian noise σ. With the mean fixed at the label the
posterior of the feature vector φ (see :mod:`labelaudit.core.geometry`) is Gaussian with precision

    Λ = Σ0⁻¹ + σ⁻² Σ_k Σ_m r_km J(v*_km)ᵀ J(v*_km)

where r_km are the registration responsibilities and Σ0 is the per-class prior. This module owns
that posterior and its summaries (per-parameter std, corner variances, σ̂); the label-error box fit
lives in :mod:`labelaudit.core.fit`. Like all of ``core/`` it does no I/O and knows no file format.
Everything is vectorised over points; a box costs a few hundred microseconds.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Iterable, NamedTuple, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.core import geometry as g
from labelaudit.core import linalg
from labelaudit.core.iou import BEV_CORNER_J, hull_candidates_sorted, hull_iou_sorted
from labelaudit.core.params import ClassPrior, ModelKind, ModelParams, SpatialParams
from labelaudit.core.spatial import grid_cells_per_side, jaccard_sum_sorted_keys, jiou_gt_bev_cells, normal_samples
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]


# ----------------------------------------------------------------------------------------------
# Generic linear-Gaussian posterior
# ----------------------------------------------------------------------------------------------


def linear_gaussian_posterior(
    J: ArrayLike,
    x: ArrayLike,
    sigma: float,
    prior_mean: ArrayLike,
    *,
    prior_cov: ArrayLike | None = None,
    prior_precision: ArrayLike | None = None,
    weights: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Posterior of θ for observations ``x_k = J_k θ + ε``, ``ε ~ N(0, σ² I / w_k)``, prior N(μ0, Σ0).

    Information form: ``Λ = Σ0⁻¹ + σ⁻² Σ_k w_k J_kᵀ J_k``, ``η = Σ0⁻¹ μ0 + σ⁻² Σ_k w_k J_kᵀ x_k``,
    posterior ``N(Λ⁻¹ η, Λ⁻¹)``. Solved with a Cholesky factor; the covariance is symmetrised.

    Parameters
    ----------
    J : array of shape (n, d, p)
        Design matrices (n observations of dimension d).
    x : array of shape (n, d)
    sigma : float
        Observation noise std.
    prior_mean : array of shape (p,)
    prior_cov, prior_precision : array of shape (p, p), optional
        Give one of them. A zero ``prior_precision`` is a flat prior (then the data must determine θ).
    weights : array of shape (n,), optional
        Per-observation weights (responsibilities); default 1.

    Returns
    -------
    mean : (p,)
    cov : (p, p)
    precision : (p, p)

    Raises
    ------
    ValueError
        When the precision is not positive definite (flat prior and too little data).
    """
    J = np.asarray(J, dtype=float)
    x = np.asarray(x, dtype=float)
    n, d, p = J.shape
    mu0 = np.asarray(prior_mean, dtype=float)
    if (prior_cov is None) == (prior_precision is None):
        raise ValueError("give exactly one of prior_cov and prior_precision")
    P0 = (
        np.linalg.inv(np.asarray(prior_cov, dtype=float))
        if prior_precision is None
        else np.asarray(prior_precision, dtype=float)
    )
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    # Stack rows of sqrt(w)·J so that one matmul gives Σ w JᵀJ.
    sw = np.sqrt(w)[:, None, None]
    A = (J * sw).reshape(n * d, p)
    b = (x[..., None] * sw[..., 0][:, :, None]).reshape(n * d) if n else np.zeros(0)
    precision = P0 + (A.T @ A) / sigma**2
    eta = P0 @ mu0 + (A.T @ b) / sigma**2
    precision = 0.5 * (precision + precision.T)
    cov = spd_inverse(precision)
    return cov @ eta, cov, precision


_EYE = {n: np.eye(n) for n in (6, 8)}  # read-only identities of the φ sizes
for _e in _EYE.values():
    _e.setflags(write=False)


def spd_inverse(P: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive definite matrix via Cholesky, symmetrised."""
    try:
        L = linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ValueError(
            f"posterior precision is not positive definite (eigenvalues {np.linalg.eigvalsh(P)})"
        ) from None
    Linv = linalg.solve(
        L, _EYE[P.shape[0]] if P.shape[0] in _EYE else np.eye(P.shape[0])
    )  # L is tiny (≤ 8×8): a generic solve is fine
    cov = Linv.T @ Linv
    return 0.5 * (cov + cov.T)


# ----------------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Registration:
    """Points registered to their nearest surface points of a box.

    Attributes
    ----------
    vstar : (N, M, d) unit-box coordinates of the M candidate surface points per point.
    sqdist : (N, M) squared distances (m²) point → candidate; ``inf`` marks a missing candidate.
    resp : (N, M) responsibilities r_km (rows sum to ≤ 1; < 1 when the outlier term takes weight).
    points : (N, d) the points used.
    """

    vstar: FloatArray
    sqdist: FloatArray
    resp: FloatArray
    points: FloatArray


def _responsibilities(
    sqdist: FloatArray, sigma: float, d: int, outlier_prob: float, outlier_log_density: float
) -> FloatArray:
    """r_km ∝ exp(−d²/2σ²) over the M candidates, plus an optional uniform outlier component."""
    if sqdist.size == 0:
        return np.zeros_like(sqdist)
    if not outlier_prob > 0:
        # Without outliers: the exponents and the row normalisation compiled, the exp NumPy's
        # (in place: the same values without two more (N, M) arrays).
        x = _resp_exponents(sqdist, 2.0 * sigma**2)
        return _normalise_rows(np.exp(x, out=x))
    m = sqdist.shape[1]
    logw = -sqdist / (2.0 * sigma**2)  # -inf for missing candidates
    top = logw.max(axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    e = np.exp(logw - top)
    norm = e.sum(axis=1, keepdims=True)
    # Mixture: (1-p)/M · N(x | v̄, σ²I) per candidate, p · uniform. Compare in log space.
    log_gauss_const = np.log((1.0 - outlier_prob) / m) - 0.5 * d * np.log(2.0 * np.pi * sigma**2)
    log_out = np.log(outlier_prob) + outlier_log_density - log_gauss_const
    norm = norm + np.exp(np.minimum(log_out - top, 700.0))
    return e / norm


@kernel
def _resp_exponents(sqdist, two_var):  # pragma: no cover - compiled
    """logw − max_m logw per point with logw = −d²/(2σ²) (a row without a finite maximum keeps
    logw): the NumPy form's element operations, so ``np.exp`` of it is the same array."""
    n, m = sqdist.shape
    out = np.empty((n, m))
    for k in range(n):
        top = -np.inf
        for j in range(m):
            out[k, j] = -sqdist[k, j] / two_var
            top = linalg.nan_max(top, out[k, j])
        if not math.isfinite(top):
            top = 0.0
        for j in range(m):
            out[k, j] = out[k, j] - top
    return out


@kernel
def _normalise_rows(e):  # pragma: no cover - compiled
    """e / e.sum(axis=1, keepdims=True), in place; a row has M ≤ 6 < 8 entries, which NumPy sums
    sequentially."""
    n, m = e.shape
    for k in range(n):
        norm = 0.0
        for j in range(m):
            norm += e[k, j]
        for j in range(m):
            e[k, j] = e[k, j] / norm
    return e


def register(
    box: ArrayLike,
    points: ArrayLike,
    model: ModelKind,
    *,
    num_nearest: int = C.DEFAULT_NUM_NEAREST,
    sigma: float = C.DEFAULT_SIGMA,
    outlier_prob: float = 0.0,
) -> Registration:
    """Register points to the ``num_nearest`` nearest distinct points of the labeled box surface.

    For every point the nearest point on each face (BEV: 4 edges, 3D: 6 faces) is computed in
    closed form; the M nearest distinct ones are kept (M is capped at the number of faces).

    Parameters
    ----------
    box : (7,) labeled box.
    points : (N, ≥d) points; only the first d columns are used.
    """
    y = g.validate_box(box)
    d = g.point_dim(model)
    return register_validated(y, g.clean_points(points, d), d, num_nearest, sigma, outlier_prob)


def register_validated(
    y: FloatArray, pts: FloatArray, d: int, num_nearest: int, sigma: float, outlier_prob: float
) -> Registration:
    """:func:`register` for a validated box and clean (N, d) points."""
    half = 0.5 * y[3 : 3 + d]
    c, s = g.cos_sin(y[6])
    m = min(int(num_nearest), 2 * d)
    tol = 1e-9 * max(half.tolist())
    vstar, sqd, x = _register_kernel(pts, float(y[0]), float(y[1]), float(y[2]), c, s, half, m, tol, 2.0 * sigma**2)
    if not outlier_prob > 0:  # _responsibilities without outliers, from the kernel's exponents
        resp = _normalise_rows(np.exp(x, out=x)) if sqd.size else np.zeros_like(sqd)
    else:
        log_density = -float(np.sum(np.log(2.0 * (half + C.OUTLIER_REGION_MARGIN))))
        resp = _responsibilities(sqd, sigma, d, outlier_prob, log_density)
    return Registration(vstar=vstar, sqdist=sqd, resp=resp, points=pts)


def _nearest_faces(local: FloatArray, half: FloatArray, m: int) -> tuple[FloatArray, FloatArray]:
    """The m nearest distinct face candidates of every point, as unit coordinates (N, m, d) and
    squared distances (N, m), nearest first, without forming the (N, 2d, d) array of all face
    candidates (tests/test_model.py keeps that plain form as the reference).

    The nearest point on face (a, ±) is the clamped point with coordinate a set to ±half_a, so its
    squared distance is Σ_{j≠a} excess_j² + (x_a ∓ half_a)², excess = x − clamp(x). Faces a point
    lies outside of (or on) all clamp to the same edge/corner point: only the first is kept. One
    compiled pass over the points (:func:`_nearest_faces_kernel`; as NumPy array code it was ~20
    calls per registration).
    """
    local = np.ascontiguousarray(local, dtype=np.float64)
    half = np.ascontiguousarray(half, dtype=np.float64)
    return _nearest_faces_kernel(local, half, int(m), 1e-9 * float(half.max()))


@kernel
def _register_kernel(pts, cx, cy, cz, c, s, half, m, tol, two_var):  # pragma: no cover - compiled
    """The points (N, d) in the box frame, Rᵀ (x − c) (the NumPy form's element operations), then
    :func:`_nearest_faces_kernel` and the responsibility exponents (:func:`_resp_exponents`)."""
    n, d = pts.shape
    local = np.empty((n, d))
    for k in range(n):
        r0, r1 = pts[k, 0] - cx, pts[k, 1] - cy
        local[k, 0] = c * r0 + s * r1
        local[k, 1] = -s * r0 + c * r1
        if d == 3:
            local[k, 2] = pts[k, 2] - cz
    vstar, sqd = _nearest_faces_kernel(local, half, m, tol)
    return vstar, sqd, _resp_exponents(sqd, two_var)


@kernel(inline="always")
def _order2(ka, ia, kb, ib):  # pragma: no cover - compiled
    """Two (distance, face) pairs in lexicographic order: a stable sort's order, branch-free."""
    swap = (ka > kb) | ((ka == kb) & (ia > ib))
    return (kb if swap else ka), (ib if swap else ia), (ka if swap else kb), (ia if swap else ib)


@kernel
def _nearest_edges_kernel(local, half, m, tol):  # pragma: no cover - compiled
    """:func:`_nearest_faces_kernel` of BEV points (d = 2, four edges), without branches: the same
    distances, and the same order of the edges — a sorting network on (distance, edge) pairs, whose
    lexicographic order is the stable insertion sort's — so the same arrays bit for bit."""
    n = local.shape[0]
    vstar = np.empty((n, m, 2))
    sqd = np.empty((n, m))
    h0, h1 = half[0], half[1]
    w0, w1 = 2.0 * h0, 2.0 * h1
    inf = np.inf
    for k in range(n):
        x0, x1 = local[k, 0], local[k, 1]
        c0 = min(max(x0, -h0), h0)
        c1 = min(max(x1, -h1), h1)
        e0 = (x0 - c0) * (x0 - c0)
        e1 = (x1 - c1) * (x1 - c1)
        total = 0.0 + e0 + e1
        b0, b1 = total - e0, total - e1
        lo0, hi0, lo1, hi1 = x0 + h0, x0 - h0, x1 + h1, x1 - h1
        s0 = x0 <= -h0 + tol  # the point is outside of (or on) this edge; only the first such counts
        s1 = x0 >= h0 - tol
        s2 = x1 <= -h1 + tol
        s3 = x1 >= h1 - tol
        n1 = np.int64(s0) + np.int64(s1)
        n2 = n1 + np.int64(s2)
        n3 = n2 + np.int64(s3)
        q0 = b0 + lo0 * lo0
        q1 = inf if (s1 and n1 > 1) else b0 + hi0 * hi0
        q2 = inf if (s2 and n2 > 1) else b1 + lo1 * lo1
        q3 = inf if (s3 and n3 > 1) else b1 + hi1 * hi1
        k0, i0, k1, i1 = _order2(q0, 0, q1, 1)
        k2, i2, k3, i3 = _order2(q2, 2, q3, 3)
        k0, i0, k2, i2 = _order2(k0, i0, k2, i2)
        k1, i1, k3, i3 = _order2(k1, i1, k3, i3)
        k1, i1, k2, i2 = _order2(k1, i1, k2, i2)
        u0, u1 = c0 / w0, c1 / w1
        for j in range(m):
            face = i0 if j == 0 else (i1 if j == 1 else (i2 if j == 2 else i3))
            sqd[k, j] = k0 if j == 0 else (k1 if j == 1 else (k2 if j == 2 else k3))
            side = 0.5 if face % 2 == 1 else -0.5
            vstar[k, j, 0] = side if face < 2 else u0
            vstar[k, j, 1] = side if face >= 2 else u1
    return vstar, sqd


@kernel
def _nearest_faces_kernel(local, half, m, tol):  # pragma: no cover - compiled
    """:func:`_nearest_faces`' pass: BEV points by :func:`_nearest_edges_kernel`, 3D ones by
    :func:`_nearest_faces_loop` (the same arrays either way)."""
    if local.shape[1] == 2 and m <= 4:
        return _nearest_edges_kernel(local, half, m, tol)
    return _nearest_faces_loop(local, half, m, tol)


@kernel
def _nearest_faces_loop(local, half, m, tol):  # pragma: no cover - compiled
    """Point by point: the 2d faces' squared distances, a stable insertion sort of them, the m
    nearest (:func:`_nearest_faces`)."""
    n, d = local.shape
    f = 2 * d
    vstar = np.empty((n, m, d))
    sqd = np.empty((n, m))
    clamped = np.empty(d)
    excess = np.empty(d)
    sq = np.empty(f)
    order = np.empty(f, dtype=np.int64)
    for k in range(n):
        total = 0.0
        for a in range(d):
            x = local[k, a]
            c = min(max(x, -half[a]), half[a])
            clamped[a] = c
            excess[a] = (x - c) * (x - c)
            total += excess[a]
        seen = 0  # faces the point is outside of (or on), so far
        for a in range(d):
            x = local[k, a]
            base = total - excess[a]
            lo_d, hi_d = x + half[a], x - half[a]
            sq[2 * a] = base + lo_d * lo_d
            sq[2 * a + 1] = base + hi_d * hi_d
            if x <= -half[a] + tol:
                seen += 1
                if seen > 1:
                    sq[2 * a] = np.inf
            if x >= half[a] - tol:
                seen += 1
                if seen > 1:
                    sq[2 * a + 1] = np.inf
        # Stable insertion sort of the 2d faces by distance (ties: lower face index first).
        for i in range(f):
            order[i] = i
        for i in range(1, f):
            j = i
            while j > 0 and sq[order[j - 1]] > sq[order[j]]:
                order[j - 1], order[j] = order[j], order[j - 1]
                j -= 1
        for j in range(m):
            face = order[j]
            sqd[k, j] = sq[face]
            axis = face // 2
            for a in range(d):
                if a == axis:
                    vstar[k, j, a] = 0.5 if face % 2 == 1 else -0.5
                else:
                    vstar[k, j, a] = clamped[a] / (2.0 * half[a])
    return vstar, sqd


def _design_basis(model: ModelKind) -> tuple[FloatArray, FloatArray]:
    """J(v*) = B_0 + Σ_i v*_i B_i: the basis B (d+1, d, p) and the products B_aᵀB_b (d+1, d+1, p, p)."""
    d = g.point_dim(model)
    B0 = g.design_matrix(np.zeros(d), model)
    B = np.stack([B0] + [g.design_matrix(np.eye(d)[i], model) - B0 for i in range(d)])
    return B, np.einsum("adp,bdq->abpq", B, B)


_BASIS = {m: _design_basis(m) for m in ("bev", "3d")}


def registration_information(reg: Registration, model: ModelKind) -> tuple[FloatArray, FloatArray]:
    """Σ_km r_km J_kmᵀJ_km (p, p) and Σ_km r_km J_kmᵀ x_k (p,) of a registration (σ not applied).

    J is linear in v*, so both follow from the weighted moments of ṽ = (1, v*): no per-point
    design matrices are formed. Equals the sums over :func:`labelaudit.core.geometry.design_matrix`
    up to rounding (one compiled pass; the products are summed in its own order, not BLAS's).
    """
    B, BB = _BASIS[model]
    return _information_kernel(reg.vstar, reg.resp, reg.points, B, BB)


@kernel
def _information_kernel(vstar, resp, points, B, BB):  # pragma: no cover - compiled
    """With ṽ = (1, v*): moments Σ_km r ṽ ṽᵀ (d+1, d+1) and cross Σ_k (Σ_m r ṽ) x_kᵀ (d+1, d),
    then contracted with the design basis: info = Σ_ab moments_ab BB_ab (p, p), eta = Σ_ab
    cross_ab B_ab (p,) (:func:`_contract_basis`). Sums run in point, candidate order."""
    n, m, d = vstar.shape
    moments = np.zeros((d + 1, d + 1))
    cross = np.zeros((d + 1, d))
    vt = np.empty(d + 1)
    rsum = np.empty(d + 1)
    for k in range(n):
        for a in range(d + 1):
            rsum[a] = 0.0
        for j in range(m):
            r = resp[k, j]
            vt[0] = 1.0
            for a in range(d):
                vt[a + 1] = vstar[k, j, a]
            for a in range(d + 1):
                ra = vt[a] * r
                rsum[a] += ra
                for b in range(d + 1):
                    moments[a, b] += ra * vt[b]
        for a in range(d + 1):
            for b in range(d):
                cross[a, b] += rsum[a] * points[k, b]
    return _contract_basis(moments, cross, B, BB)


@kernel
def _contract_basis(moments, cross, B, BB):  # pragma: no cover - compiled
    """info = Σ_ab moments_ab BB_ab (p, p) and eta = Σ_ab cross_ab B_ab (p,): the moments of ṽ
    ((d+1, d+1) and (d+1, d)) contracted with the design basis, in a, b order."""
    d = cross.shape[1]
    p = B.shape[2]
    info = np.zeros((p, p))
    eta = np.zeros(p)
    for a in range(d + 1):
        for b in range(d + 1):
            w = moments[a, b]
            for i in range(p):
                for j in range(p):
                    info[i, j] += w * BB[a, b, i, j]
        for b in range(d):
            w = cross[a, b]
            for i in range(p):
                eta[i] += w * B[a, b, i]
    return info, eta


@kernel
def _exp_information_kernel(vstar, x, points, B, BB):  # pragma: no cover - compiled
    """:func:`_information_kernel` of the responsibilities exp(x) / Σ_m exp(x) (x: the exponents of
    :func:`_resp_exponents`, N × M), formed point by point as the moments are summed: the same
    operations in the same order as the exponentials, :func:`_normalise_rows` and
    :func:`_information_kernel` one after the other, without the (N, M) responsibilities. The
    exponentials are taken first, all in one vectorised pass (:func:`~labelaudit.core.linalg.exp_kernel`,
    within 1 ulp of ``math.exp``). The moments of ṽ₀ = 1 are the responsibilities themselves
    (1 · r = r exactly)."""
    n, m, d = vstar.shape
    moments = np.zeros((d + 1, d + 1))
    cross = np.zeros((d + 1, d))
    xf = np.empty(n * m)
    for k in range(n):
        for j in range(m):
            xf[k * m + j] = x[k, j]
    ex = np.empty(n * m)
    linalg.exp_kernel(xf, ex, np.empty(n * m, dtype=np.int64))
    rsum = np.empty(d + 1)
    for k in range(n):
        norm = 0.0
        for j in range(m):
            norm += ex[k * m + j]
        for a in range(d + 1):
            rsum[a] = 0.0
        for j in range(m):
            r = ex[k * m + j] / norm
            rsum[0] += r
            moments[0, 0] += r
            for b in range(d):
                moments[0, b + 1] += r * vstar[k, j, b]
            for a in range(d):
                ra = vstar[k, j, a] * r
                rsum[a + 1] += ra
                moments[a + 1, 0] += ra
                for b in range(d):
                    moments[a + 1, b + 1] += ra * vstar[k, j, b]
        for a in range(d + 1):
            for b in range(d):
                cross[a, b] += rsum[a] * points[k, b]
    return _contract_basis(moments, cross, B, BB)


# ----------------------------------------------------------------------------------------------
# Prior
# ----------------------------------------------------------------------------------------------


def prior_cov_extended(prior: ClassPrior, model: ModelKind) -> FloatArray:
    """Prior covariance of the extended parameters ỹ, before the weight w.

    Centre, sizes: independent with the class std. The two axis angles are written
    ``a = yaw + s/2``, ``b = yaw − s/2`` with independent yaw ~ N(0, σ_yaw²) and shear
    s ~ N(0, (r·σ_yaw)²), r = :data:`~labelaudit.constants.PRIOR_SHEAR_STD_RATIO`. The reported yaw
    (a + b)/2 then has exactly the class yaw std, and the prior stays full rank.
    """
    d = g.point_dim(model)
    if d == 2:
        diag = [prior.center, prior.center, prior.length, prior.width]
    else:
        diag = [prior.center, prior.center, prior.center, prior.length, prior.width, prior.height]
    k = len(diag)
    S = np.zeros((k + 2, k + 2))
    S[:k, :k] = np.diag(np.square(diag))
    var_yaw = prior.yaw**2
    var_shear = (C.PRIOR_SHEAR_STD_RATIO * prior.yaw) ** 2
    S[k:, k:] = [[var_yaw + var_shear / 4, var_yaw - var_shear / 4], [var_yaw - var_shear / 4, var_yaw + var_shear / 4]]
    return S


@functools.lru_cache(maxsize=64)
def _prior_info_extended(prior: ClassPrior, model: ModelKind) -> FloatArray:
    """Σ_ỹ⁻¹ (cached per class prior: it does not depend on the box)."""
    info = np.linalg.inv(prior_cov_extended(prior, model))
    info.setflags(write=False)
    return info


@functools.lru_cache(maxsize=64)
def prior_cov_extended_cached(prior: ClassPrior, model: ModelKind) -> FloatArray:
    """:func:`prior_cov_extended`, cached per class prior and model (read-only)."""
    S = prior_cov_extended(prior, model)
    S.setflags(write=False)
    return S


def prior_covariance(box: ArrayLike, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    """Σ0 = G · Σ_ỹ / w · Gᵀ with G = ∂φ/∂ỹ at the label (full rank).

    The weight divides the prior *variance* (it multiplies the prior precision), as the authors'
    code does with its ``prior_scaler``.
    """
    G = g.dphi_dext(box, model)
    S = G @ (prior_cov_extended(prior, model) / weight) @ G.T
    return 0.5 * (S + S.T)


def prior_precision_from(E: FloatArray, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    P = E.T @ (_prior_info_extended(prior, model) * weight) @ E
    return 0.5 * (P + P.T)


def prior_precision(box: ArrayLike, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    """Σ0⁻¹ = Eᵀ · w Σ_ỹ⁻¹ · E with E = ∂ỹ/∂φ (Σ_ỹ is well conditioned; Σ0 need not be)."""
    return prior_precision_from(g.dext_dphi(box, model), prior, weight, model)


# ----------------------------------------------------------------------------------------------
# Noise σ by EM
# ----------------------------------------------------------------------------------------------


def em_sigma_step(sqdist: FloatArray, resp: FloatArray, dof: float = C.EM_RESIDUAL_DOF) -> tuple[float, float]:
    """Sufficient statistics of the σ update: (Σ r·‖x−v̄‖², dof·Σ r); σ² = first / second.

    ``dof`` is the number of noise components a residual keeps. The candidates are the *nearest*
    surface points, so the surface absorbs the tangential noise and a residual keeps only its
    normal component: dof = 1 (the surface's codimension) gives an unbiased per-axis σ, where the
    point dimension D (the authors' code; docs/method.md §5) would return σ/√D.
    Missing candidates (``sqdist = inf``) carry r = 0 and are skipped.
    """
    num = float(np.sum(resp * np.where(np.isfinite(sqdist), sqdist, 0.0)))
    return num, float(dof * np.sum(resp))


def outlier_log_density(y: FloatArray, d: int) -> float:
    """log of the uniform outlier density: 1 / size of the box grown by the outlier margin."""
    return -float(np.sum(np.log(y[3 : 3 + d] + 2.0 * C.OUTLIER_REGION_MARGIN)))


def em_sigma(regs: Sequence[tuple[FloatArray, float]], d: int, sigma0: float, outlier_prob: float) -> float:
    """Pooled EM for σ over registrations given as (sqdist (N, M), outlier log density)."""
    if len(regs) == 1 and outlier_prob == 0:
        sqd = regs[0][0]
        if len(sqd) and sqd.shape[1]:
            one = _em_sigma_one(sqd)
            if one is not None:
                return one
    regs = [(sqd, np.where(np.isfinite(sqd), sqd, 0.0), ld) for sqd, ld in regs]
    # Start at the nearest-candidate residual (the small-σ limit): EM then needs few iterations.
    n_pts = sum(len(sqd) for sqd, _, _ in regs)
    if n_pts == 0:
        return float("nan")
    start = np.sqrt(sum(float(np.sum(sqd0[:, 0])) for _, sqd0, _ in regs) / (C.EM_RESIDUAL_DOF * n_pts))
    sigma = max(float(start) if outlier_prob == 0 else float(sigma0), C.SIGMA_FLOOR)
    # With one-hot responsibilities the first M-step returns the start: then one step suffices.
    estimate = float(start) if outlier_prob == 0 else np.nan
    fast = (
        outlier_prob == 0
        and all(np.all(np.isfinite(sqd[:, 0])) for sqd, _, _ in regs)
        and all(sqd.shape[1] for sqd, _, _ in regs)
        and len({sqd.shape[1] for sqd, _, _ in regs}) == 1
    )
    if fast:
        # Without outliers the responsibilities of a point sum to 1 and only exp(−(d² − min d²)/2σ²)
        # changes with σ: the squared distances of all points go to one compiled loop.
        sqd_all = np.ascontiguousarray(np.concatenate([sqd for sqd, _, _ in regs], axis=0), dtype=np.float64)
        return float(
            _em_fast_kernel(
                sqd_all, sigma, estimate, C.SIGMA_FLOOR, C.EM_TOLERANCE, C.EM_MAX_ITERATIONS, float(C.EM_RESIDUAL_DOF)
            )
        )
    for _ in range(C.EM_MAX_ITERATIONS):
        num = den = 0.0
        for sqd, sqd0, log_density in regs:
            r = _responsibilities(sqd, sigma, d, outlier_prob, log_density)
            num += float(np.sum(r * sqd0))
            den += C.EM_RESIDUAL_DOF * float(np.sum(r))
        if den <= 0:
            return float("nan")
        new = float(np.sqrt(num / den))
        converged = np.isfinite(estimate) and abs(new - estimate) <= C.EM_TOLERANCE * max(estimate, C.SIGMA_FLOOR)
        estimate = new
        if converged or num == 0.0:
            break
        sigma = max(new, C.SIGMA_FLOOR)
    return estimate


def _em_sigma_one(sqd: FloatArray) -> float | None:
    """:func:`em_sigma` of one registration (N ≥ 1 points) without outliers: the same operations
    on the same arrays as the pooled form, without the pooling (this is the per-object σ̂ of every
    label); None when a nearest candidate is not finite (the pooled form handles that)."""
    ok, estimate = _em_one_kernel(sqd, C.SIGMA_FLOOR, C.EM_TOLERANCE, C.EM_MAX_ITERATIONS, float(C.EM_RESIDUAL_DOF))
    return float(estimate) if ok else None


@kernel
def _em_one_kernel(sqd, floor, tol, max_iter, dof):  # pragma: no cover - compiled
    """The start of :func:`_em_fast_kernel` for one registration (N, M) whose nearest candidates
    are finite (else (False, NaN)): √(Σ nearest d² / (dof·N)), summed in NumPy's pairwise order."""
    n = sqd.shape[0]
    for k in range(n):
        if not math.isfinite(sqd[k, 0]):
            return False, math.nan
    start = math.sqrt(linalg.pairwise_sum(sqd[:, 0]) / (dof * n))
    sigma = floor if floor > start else start  # Python's max(start, floor)
    return True, _em_fast_kernel(sqd, sigma, start, floor, tol, max_iter, dof)


@kernel(error_model="numpy")
def _em_fast_kernel(sqd, sigma, estimate, floor, tol, max_iter, dof):  # pragma: no cover - compiled
    """The EM of :func:`em_sigma` without outliers over squared distances (N, M): per point the
    responsibility-weighted d² over its candidates, the weights exp(−(d² − min d²)/2σ²) (missing
    candidates, d² = inf, weigh 0 and count as 0).

    Each iteration is a few passes over the (M, N) candidates that the compiler vectorises: the
    exponents, their exponentials (:func:`~labelaudit.core.linalg.exp_kernel`, within 1 ulp of
    ``math.exp``; a weight below e^−708 is 0), each point's Σ e and Σ e·d² in the candidates' order,
    and the points' Σ (Σ e·d²)/(Σ e) in NumPy's pairwise order. When every point's first candidate
    is its nearest, its weight exp(0) = 1 is not computed."""
    n, m = sqd.shape
    if m == 0:  # no candidates: 0/0 per point
        return math.nan
    lo = np.empty(n)  # np.min per point (NaN propagates)
    for k in range(n):
        v = np.inf
        for j in range(m):
            v = linalg.nan_min(v, sqd[k, j])
        lo[k] = v
    dif = np.empty(m * n)  # candidate-major: d² − min d², and d² where finite (else 0)
    fin = np.empty(m * n)
    nearest = 0
    for k in range(n):
        nearest += sqd[k, 0] == lo[k]
    first_nearest = 1 if nearest == n else 0
    for j in range(m):
        for k in range(n):
            v = sqd[k, j]
            dif[j * n + k] = v - lo[k]
            fin[j * n + k] = v if math.isfinite(v) else 0.0
    t = np.empty(m * n)  # exponents, then weights (apart: in place, exp_kernel's loops would not vectorise)
    e = np.empty(m * n)
    bits = np.empty(m * n, dtype=np.int64)
    se = np.empty(n)
    sw = np.empty(n)
    den = dof * n
    for _ in range(max_iter):
        scale = -0.5 / sigma**2
        j0 = first_nearest if math.isfinite(scale) else 0  # else 0 · scale is not 0
        lo_i = j0 * n
        for i in range(lo_i, m * n):
            t[i] = dif[i] * scale
        linalg.exp_kernel(t[lo_i:], e[lo_i:], bits[lo_i:])
        if j0:
            for k in range(n):
                se[k] = 1.0
                sw[k] = 0.0 + fin[k]
        else:
            for k in range(n):
                se[k] = 0.0 + e[k]
                sw[k] = 0.0 + e[k] * fin[k]
        for j in range(1, m):
            for k in range(n):
                se[k] += e[j * n + k]
                sw[k] += e[j * n + k] * fin[j * n + k]
        for k in range(n):
            sw[k] = sw[k] / se[k]
        num = linalg.pairwise_sum(sw)
        if den <= 0:
            return math.nan
        new = math.sqrt(num / den)
        converged = math.isfinite(estimate) and abs(new - estimate) <= tol * max(estimate, floor)
        estimate = new
        if converged or num == 0.0:
            break
        sigma = max(new, floor)
    return estimate


def estimate_sigma(
    box: ArrayLike,
    points: ArrayLike,
    model: ModelKind,
    *,
    num_nearest: int = C.DEFAULT_NUM_NEAREST,
    sigma_init: float = C.DEFAULT_SIGMA,
    outlier_prob: float = 0.0,
) -> float:
    """Per-object noise σ̂ by EM: σ² = Σ r‖x − v̄‖² / (dof · Σ r), responsibilities re-computed with σ̂
    (dof: see :func:`em_sigma_step`).

    With the box fixed at the label this is the RMS fit residual of the points to the box surface:
    large when the label does not fit its points. NaN for fewer than 2 points.
    """
    y = g.validate_box(box)
    reg = register(y, points, model, num_nearest=num_nearest, sigma=sigma_init, outlier_prob=outlier_prob)
    if reg.points.shape[0] < 2:
        return float("nan")
    d = g.point_dim(model)
    return em_sigma([(reg.sqdist, outlier_log_density(y, d))], d, sigma_init, outlier_prob)


def estimate_sigma_dataset(
    objects: Iterable[tuple[ArrayLike, ArrayLike]],
    model: ModelKind,
    *,
    num_nearest: int = C.DEFAULT_NUM_NEAREST,
    sigma_init: float = C.DEFAULT_SIGMA,
    outlier_prob: float = 0.0,
) -> float:
    """Dataset-level σ̂ by EM with sums pooled over many (box, points) pairs; use it to calibrate a config."""
    d = g.point_dim(model)
    regs = []
    for box, points in objects:
        y = g.validate_box(box)
        reg = register(y, points, model, num_nearest=num_nearest, sigma=sigma_init, outlier_prob=outlier_prob)
        if reg.points.shape[0]:
            regs.append((reg.sqdist, outlier_log_density(y, d)))
    if not regs:
        return float("nan")
    return em_sigma(regs, d, sigma_init, outlier_prob)


# ----------------------------------------------------------------------------------------------
# Derived quantities
# ----------------------------------------------------------------------------------------------


def corner_unit_coords(model: ModelKind) -> FloatArray:
    """Unit coordinates of the 4 BEV corners (3D: at mid-height, v*₃ = 0), order of box_corners."""
    if g.point_dim(model) == 2:
        return g.BEV_CORNERS_UNIT.copy()
    return np.c_[g.BEV_CORNERS_UNIT, np.zeros(4)]


def corner_total_variance(
    box: ArrayLike, cov: ArrayLike, model: ModelKind, sensor_origin: ArrayLike = (0.0, 0.0, 0.0)
) -> tuple[FloatArray, NDArray[np.int64]]:
    """Total variance trace(J(v*_c) Σ J(v*_c)ᵀ) at the 4 BEV corners, nearest-to-sensor first.

    Returns
    -------
    tv : (4,) total variances (m²), C1 = corner nearest to the sensor (BEV distance).
    order : (4,) indices into :func:`labelaudit.core.geometry.box_corners` (BEV order) of C1..C4.
    """
    return _corner_tv(g.validate_box(box), np.asarray(cov, dtype=float), model, sensor_origin)


_CORNER_J = {m: g.design_matrix(corner_unit_coords(m), m) for m in ("bev", "3d")}  # (4, d, p), box-independent
_CORNERS_UNIT = [tuple(u) for u in g.BEV_CORNERS_UNIT.tolist()]


def corner_covariances(cov: ArrayLike, model: ModelKind) -> FloatArray:
    """Covariances J(v*_c) Σ J(v*_c)ᵀ (4, d, d) of the 4 BEV corners (order of
    :func:`labelaudit.core.geometry.box_corners`, box frame axes = world axes) for a φ covariance Σ
    (p, p); their traces are :func:`corner_total_variance`'s, their x–y blocks the ellipses ``show`` draws.
    """
    J = _CORNER_J[model]
    return np.einsum("cdp,pq,ceq->cde", J, np.asarray(cov, dtype=float), J)


def corner_variances(covs: ArrayLike, model: ModelKind) -> FloatArray:
    """Total variances trace(J(v*_c) Σ_n J(v*_c)ᵀ) (n, 4) of the 4 BEV corners for a stack of φ
    covariances (n, p, p), in the order of :func:`labelaudit.core.geometry.box_corners`."""
    J = _CORNER_J[model]
    return np.einsum("cdp,npq,cdq->nc", J, np.asarray(covs, dtype=float), J)


def _corner_tv(
    y: FloatArray, cov: FloatArray, model: ModelKind, sensor_origin: ArrayLike
) -> tuple[FloatArray, NDArray[np.int64]]:
    tv = _corner_quad_forms(_CORNER_J[model], cov)  # = np.einsum("cdp,pq,cdq->c", J, cov, J)
    order = _corner_order(y, sensor_origin)
    return tv[order], order


def _corner_order(y: FloatArray, sensor_origin: ArrayLike) -> NDArray[np.int64]:
    """The 4 BEV corners of box ``y`` (box_corners' order), nearest to the sensor first."""
    c, s = math.cos(y[6]), math.sin(y[6])
    o = np.asarray(sensor_origin, dtype=float)
    # Corners − sensor in Python floats: the same IEEE operations as on (4,) arrays, without the calls.
    x0, y0, ox, oy = float(y[0]), float(y[1]), float(o[0]), float(o[1])
    dx, dy = [], []
    for ux, uy in _CORNERS_UNIT:
        ux, uy = ux * float(y[3]), uy * float(y[4])
        dx.append((c * ux - s * uy + x0) - ox)
        dy.append((s * ux + c * uy + y0) - oy)
    return np.hypot(dx, dy).argsort(kind="stable")


def box_std(box: ArrayLike, cov: ArrayLike, model: ModelKind) -> dict[str, float]:
    """Std of (cx, cy, cz, length, width, height, yaw) from K Σ Kᵀ; NaN for cz/height in BEV."""
    K, _ = g.box_param_jacobian(box, model)
    return _std_from_K(K, cov, model)


def _std_from_K(K: FloatArray, cov: ArrayLike, model: ModelKind) -> dict[str, float]:
    return _std_of(_quad_forms(K, np.asarray(cov, dtype=float)), model)  # = np.einsum("ip,pq,iq->i", K, cov, K)


def _std_of(var: FloatArray, model: ModelKind) -> dict[str, float]:
    """The std per box field from the variances K Σ Kᵀ of the model's parameters (NaN for cz, height in BEV)."""
    out = dict.fromkeys(g.BOX_FIELDS, math.nan)
    for name, v in zip(_STD_NAMES[model], var.tolist()):
        out[name] = math.sqrt(max(v, 0.0))  # IEEE square roots are exact-rounded: = np.sqrt
    return out


_STD_NAMES = {"bev": ("cx", "cy", "length", "width", "yaw"), "3d": g.BOX_FIELDS}  # the fields K Σ Kᵀ holds, in order


@kernel
def _quad_forms(K, cov):  # pragma: no cover - compiled
    """K_i Σ K_iᵀ per row i, summed as ``np.einsum("ip,pq,iq->i", K, cov, K)`` does: the products
    (K_ip·Σ_pq)·K_iq added one by one from 0, p outer, q inner (tests/test_model.py checks the bits)."""
    n, p = K.shape
    out = np.empty(n)
    for i in range(n):
        acc = 0.0
        for a in range(p):
            for b in range(p):
                acc += K[i, a] * cov[a, b] * K[i, b]
        out[i] = acc
    return out


@kernel
def _corner_quad_forms(J, cov):  # pragma: no cover - compiled
    """trace(J_c Σ J_cᵀ) per corner c in the order of ``np.einsum("cdp,pq,cdq->c", J, cov, J)``:
    (J_cdp·Σ_pq)·J_cdq added one by one from 0 over d, p, q (tests/test_model.py checks the bits)."""
    nc, nd, p = J.shape
    out = np.empty(nc)
    for c in range(nc):
        acc = 0.0
        for d in range(nd):
            for a in range(p):
                for b in range(p):
                    acc += J[c, d, a] * cov[a, b] * J[c, d, b]
        out[c] = acc
    return out


# ----------------------------------------------------------------------------------------------
# Inference for one label
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LabelPosterior:
    """Posterior of one label's feature vector φ (mean fixed at the label).

    Attributes
    ----------
    model : "bev" or "3d"
    box : (7,) the labeled box
    phi : (p,) φ of the label (the posterior mean)
    cov : (p, p) posterior covariance of φ
    sigma : noise std used (m)
    num_points : points used
    std_box : per-parameter std, keys cx, cy, cz, length, width, height, yaw (NaN for cz, height in BEV)
    corner_tv : (4,) corner total variance, C1 (nearest the sensor) first
    sigma_hat : per-object EM noise estimate (NaN when < 2 points)
    prior_cov : (p, p) prior covariance Σ0
    corner_order : (4,) indices of C1..C4 in box_corners' BEV order
    class_name : class the prior came from
    fit_mean : (p,) Gaussian mean with the registration held fixed (one step of the box fit)
    """

    model: ModelKind
    box: FloatArray
    phi: FloatArray
    cov: FloatArray
    sigma: float
    num_points: int
    std_box: dict[str, float]
    corner_tv: FloatArray
    sigma_hat: float
    prior_cov: FloatArray
    corner_order: NDArray[np.int64]
    class_name: str = ""
    fit_mean: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class BoxPriorTerms:
    """The label-box set-up shared by :func:`infer_label_valid` and
    :func:`labelaudit.core.fit.fit_label_valid`: φ of the label, the Jacobian G = ∂φ/∂ỹ, its
    inverse E = ∂ỹ/∂φ and the prior precision P0 = Eᵀ · w Σ_ỹ⁻¹ · E (docs/method.md §4).

    Computed once per object by :func:`box_prior_terms`; a consumer checks ``model``, ``prior``
    and ``weight`` against its own (a BEV run's posterior and the always-3D fit do not share one).

    Attributes
    ----------
    model : "bev" or "3d"
    prior : the class prior the precision is of
    weight : prior weight w (multiplies the precision)
    phi : (p,) φ of the label
    G : (p, p) ∂φ/∂ỹ at the label
    Ginv : (p, p) its inverse E
    P0 : (p, p) prior precision Σ0⁻¹ (symmetrised)
    eta0 : (p,) P0 φ, the prior's information vector centred on the label
    """

    model: ModelKind
    prior: ClassPrior
    weight: float
    phi: FloatArray
    G: FloatArray
    Ginv: FloatArray
    P0: FloatArray
    eta0: FloatArray

    def matches(self, model: ModelKind, prior: ClassPrior, weight: float) -> bool:
        """Whether these terms are those of ``model``, ``prior`` and ``weight``."""
        return self.model == model and self.weight == weight and (self.prior is prior or self.prior == prior)


def box_prior_terms(y: FloatArray, prior: ClassPrior, weight: float, model: ModelKind) -> BoxPriorTerms:
    """:class:`BoxPriorTerms` of a box (7,) float64 known to be valid (after
    :func:`~labelaudit.core.geometry.validate_box`).

    Examples
    --------
    >>> from labelaudit.core.params import ModelParams
    >>> params = ModelParams(kind="3d")
    >>> y = g.validate_box([10.0, 2.0, -1.0, 4.0, 1.8, 1.5, 0.3])
    >>> box_prior_terms(y, params.prior_for("Car"), params.prior_weight, "3d").P0.shape
    (8, 8)
    """
    d = g.point_dim(model)
    c, s = g.cos_sin(y[6])  # NumPy's, as phi_of_valid_box and dphi_dext_valid
    phi, G, E, P0, eta0 = _prior_terms_kernel(y, c, s, d, _weighted_prior_info(prior, model, float(weight)))
    return BoxPriorTerms(model=model, prior=prior, weight=weight, phi=phi, G=G, Ginv=E, P0=P0, eta0=eta0)


def box_prior_terms_bev_3d(y: FloatArray, prior: ClassPrior, weight: float) -> tuple[BoxPriorTerms, BoxPriorTerms]:
    """The BEV and the 3D :class:`BoxPriorTerms` of a box (7,) float64 known to be valid, in one
    compiled call: a BEV run's posterior takes the first, the label-error fit (3D whenever the
    points have z) the second. Each is :func:`box_prior_terms`'s of its model bit for bit (the same
    kernel body on the same values); one call instead of two spares a dispatch and its glue per box.
    """
    c, s = g.cos_sin(y[6])  # NumPy's, as phi_of_valid_box and dphi_dext_valid
    w = float(weight)
    b, t = _prior_terms_bev_3d_kernel(
        y, c, s, _weighted_prior_info(prior, "bev", w), _weighted_prior_info(prior, "3d", w)
    )
    return (
        BoxPriorTerms(model="bev", prior=prior, weight=weight, phi=b[0], G=b[1], Ginv=b[2], P0=b[3], eta0=b[4]),
        BoxPriorTerms(model="3d", prior=prior, weight=weight, phi=t[0], G=t[1], Ginv=t[2], P0=t[3], eta0=t[4]),
    )


@functools.lru_cache(maxsize=64)
def _weighted_prior_info(prior: ClassPrior, model: ModelKind, weight: float) -> FloatArray:
    """w Σ_ỹ⁻¹ of a class prior (read-only; cached: it does not depend on the box)."""
    W = _prior_info_extended(prior, model) * weight
    W.setflags(write=False)
    return W


@kernel
def _prior_terms_kernel(y, c, s, d, W):  # pragma: no cover - compiled
    """φ (p,), G = ∂φ/∂ỹ (p, p), its inverse E, P0 = sym(Eᵀ W E) and P0 φ of a valid box (7,), with
    c, s its yaw's cosine and sine and W = w Σ_ỹ⁻¹ (p, p), p = 2d + 2, in one pass. φ and G are
    :func:`~labelaudit.core.geometry.phi_of_valid_box` and :func:`~labelaudit.core.geometry.dphi_dext_valid`
    bit for bit (the same products); E is G's closed-form inverse (the identity on the centre and
    height, a 2 × 2 inverse per edge) instead of LAPACK's LU, and the products are sums in loops
    instead of BLAS: E, P0 and P0 φ differ from :func:`prior_precision_from`'s in the last bits."""
    p = 2 * d + 2
    o = d - 2
    length, width = y[3], y[4]
    il, iw, ia, ib = d, d + 1, p - 2, p - 1
    phi = np.empty(p)
    for i in range(d):
        phi[i] = y[i]
    phi[2 + o], phi[3 + o], phi[4 + o], phi[5 + o] = length * c, length * s, width * c, width * s
    G = np.zeros((p, p))
    E = np.zeros((p, p))
    for i in range(d):
        G[i, i] = 1.0
        E[i, i] = 1.0
    if d == 3:
        phi[7] = y[5]
        G[7, 5] = 1.0
        E[5, 7] = 1.0
    for row, col, angle, size in ((2 + o, il, ia, length), (4 + o, iw, ib, width)):
        # the edge (size·cos, size·sin) against (size, angle): [[c, −size·s], [s, size·c]]
        G[row, col], G[row + 1, col] = c, s
        G[row, angle], G[row + 1, angle] = -size * s, size * c
        det = c * (size * c) - (-size * s) * s
        E[col, row], E[col, row + 1] = (size * c) / det, (size * s) / det
        E[angle, row], E[angle, row + 1] = -s / det, c / det
    B = np.zeros((p, p))  # Eᵀ W
    linalg.matmul_kernel(E.T, W, B)
    P = np.zeros((p, p))
    linalg.matmul_kernel(B, E, P)
    P0 = np.empty((p, p))
    for i in range(p):
        for j in range(p):
            P0[i, j] = 0.5 * (P[i, j] + P[j, i])
    eta0 = np.empty(p)
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += P0[i, j] * phi[j]
        eta0[i] = acc
    return phi, G, E, P0, eta0


@kernel
def _prior_terms_bev_3d_kernel(y, c, s, W2, W3):  # pragma: no cover - compiled
    """:func:`_prior_terms_kernel` of the box for d = 2 (W2, 6 × 6) and d = 3 (W3, 8 × 8): two tuples
    (φ, G, E, P0, P0 φ)."""
    return _prior_terms_kernel(y, c, s, 2, W2), _prior_terms_kernel(y, c, s, 3, W3)


def checked_prior_terms(
    terms: BoxPriorTerms | None, y: FloatArray, prior: ClassPrior, weight: float, model: ModelKind
) -> BoxPriorTerms:
    """``terms`` when given (raising ValueError when they are of another model, prior or weight),
    else :func:`box_prior_terms` of the box."""
    if terms is None:
        return box_prior_terms(y, prior, weight, model)
    if not terms.matches(model, prior, weight):
        raise ValueError(
            f"prior terms of model {terms.model!r} (weight {terms.weight:g}) do not match model {model!r} (weight {weight:g}) and this class prior"
        )
    return terms


def infer_label(
    box: ArrayLike,
    points: ArrayLike | None,
    class_name: str,
    params: ModelParams,
    sensor_origin: ArrayLike = (0.0, 0.0, 0.0),
) -> LabelPosterior:
    """Posterior covariance of a label given its LiDAR points.

    Parameters
    ----------
    box : (7,) labeled box (cx, cy, cz, l, w, h, yaw), LiDAR frame.
    points : (N, ≥3) points of the box (x, y, z, ...); rows with non-finite values are dropped.
    class_name : selects the prior (``params.priors``; unknown classes use ``default``).
    params : model parameters.
    sensor_origin : (3,) sensor position, used to order the corners (C1 nearest).

    Raises
    ------
    ValueError
        Invalid box (non-positive size, non-finite values) or malformed points.

    See Also
    --------
    infer_label_valid : the same for a validated box and clean points (the pipeline's call).
    """
    y = g.validate_box(box)
    return infer_label_valid(y, g.clean_points(points, g.point_dim(params.kind)), class_name, params, sensor_origin)


def _no_outlier_settings(params: ModelParams, d: int) -> tuple[int, float, bool, int, tuple[float, float, float], int]:
    """The scalar settings of the posterior's compiled pass without the outlier component, in its
    argument order: M nearest surface points (at most 2d), σ, whether σ̂ is estimated, the points
    that estimate it (≥ 2), (σ floor, EM tolerance, residual dof) and the EM's iteration cap."""
    return (
        min(int(params.num_nearest), 2 * d),
        float(params.sigma),
        bool(params.estimate_sigma),
        int(max(params.min_points, 2)),
        (C.SIGMA_FLOOR, C.EM_TOLERANCE, float(C.EM_RESIDUAL_DOF)),
        C.EM_MAX_ITERATIONS,
    )


def infer_label_valid(
    y: FloatArray,
    pts: FloatArray,
    class_name: str,
    params: ModelParams,
    sensor_origin: ArrayLike = (0.0, 0.0, 0.0),
    *,
    prior_terms: BoxPriorTerms | None = None,
) -> LabelPosterior:
    """:func:`infer_label` of a box (7,) float64 known to be valid (after
    :func:`~labelaudit.core.geometry.validate_box`) and clean points (N, d) float64, d = 2 (BEV)
    or 3 (after :func:`~labelaudit.core.geometry.clean_points`): the pipeline validates once.

    ``prior_terms``: the box's :class:`BoxPriorTerms` of ``params.kind`` when the caller has them
    (shared with the label-error fit); default: computed here.
    """
    model = params.kind
    d = g.point_dim(model)
    n = pts.shape[0]
    prior = params.prior_for(class_name)
    terms = checked_prior_terms(prior_terms, y, prior, params.prior_weight, model)
    phi, G, E, P0 = terms.phi, terms.G, terms.Ginv, terms.P0

    if not params.outlier_prob > 0:
        c, s = g.cos_sin(y[6])
        B, BB = _BASIS[model]
        ox, oy = g.sensor_xy(sensor_origin)
        ok, sigma, sigma_hat, cov, fit_mean, S0, tv, var, order = _posterior_no_outliers_kernel(
            pts,
            y,
            c,
            s,
            *_no_outlier_settings(params, d),
            B,
            BB,
            P0,
            terms.eta0,
            G,
            prior_cov_extended_cached(prior, model),
            float(params.prior_weight),
            _CORNER_J[model],
            E,
            ox,
            oy,
        )
        if ok:
            return LabelPosterior(
                model=model,
                box=y,
                phi=phi,
                cov=cov,
                sigma=float(sigma),
                num_points=n,
                std_box=_std_of(var, model),
                corner_tv=tv,
                sigma_hat=float(sigma_hat),
                prior_cov=S0,
                corner_order=order,
                class_name=class_name,
                fit_mean=fit_mean,
            )
    sigma_hat = float("nan")
    sigma = float(params.sigma)
    reg = register_validated(y, pts, d, params.num_nearest, sigma, params.outlier_prob)
    if n >= 2:
        log_density = outlier_log_density(y, d) if params.outlier_prob > 0 else 0.0  # only read with outliers
        sigma_hat = em_sigma([(reg.sqdist, log_density)], d, sigma, params.outlier_prob)
        if params.estimate_sigma and n >= max(params.min_points, 2) and np.isfinite(sigma_hat):
            sigma = max(sigma_hat, C.SIGMA_FLOOR)
            reg = register_validated(y, pts, d, params.num_nearest, sigma, params.outlier_prob)

    data_precision, data_eta = registration_information(reg, model)
    ok, cov, fit_mean, S0 = _posterior_kernel(
        P0,
        terms.eta0,
        data_precision,
        data_eta,
        sigma,
        G,
        prior_cov_extended_cached(prior, model),
        float(params.prior_weight),
    )
    if not ok:  # not positive definite to the compiled factorisation: LAPACK's verdict and message
        precision = P0 + data_precision / sigma**2
        cov = spd_inverse(0.5 * (precision + precision.T))
        fit_mean = cov @ (terms.eta0 + data_eta / sigma**2)
    tv, order = _corner_tv(y, cov, model, sensor_origin)
    p = phi.size
    K = np.empty((p - 1, p))  # as geometry.box_param_jacobian
    K[: p - 2] = E[: p - 2]
    K[p - 2] = 0.5 * (E[p - 2] + E[p - 1])
    return LabelPosterior(
        model=model,
        box=y,
        phi=phi,
        cov=cov,
        sigma=sigma,
        num_points=n,
        std_box=_std_from_K(K, cov, model),
        corner_tv=tv,
        sigma_hat=sigma_hat,
        prior_cov=S0,
        corner_order=order,
        class_name=class_name,
        fit_mean=fit_mean,
    )


@kernel
def _posterior_no_outliers_kernel(
    pts, y, c, s, m, sigma, estimate, min_points, em, max_iter, B, BB, P0, eta0, G, S_ext, weight, J, E, ox, oy
):  # pragma: no cover - compiled
    """:func:`infer_label_valid` without the outlier component, in one pass: the registration
    (:func:`_register_kernel`), σ̂ (:func:`_em_one_kernel`; σ = max(σ̂, floor) with ``estimate``
    and ≥ ``min_points`` points, the responsibilities re-weighted with it: the nearest faces do not
    depend on σ), the information (:func:`_information_kernel`), the posterior
    (:func:`_posterior_kernel`), the corners' total variances (box_corners' order) and the variances
    K Σ Kᵀ of the box parameters (K: :func:`_box_jacobian_of` E = ∂ỹ/∂φ, as
    :func:`~labelaudit.core.geometry.box_param_jacobian`). ``em`` = (σ floor, tolerance, residual dof). The exponentials are
    :func:`~labelaudit.core.linalg.exp_kernel`'s, not NumPy's SIMD ``np.exp``: the
    responsibilities, and so Σ, differ in the last bits. Returns (ok, σ, σ̂, Σ, mean, Σ0, tv, var,
    order): tv in the corners' order from the sensor at (``ox``, ``oy``) (:func:`_corner_order_kernel`),
    nearest first; ok is False when σ̂ cannot be formed this way or Σ's factorisation fails (the
    caller then takes the general steps)."""
    n, d = pts.shape
    floor, tol, dof = em
    none = np.zeros(0, dtype=np.int64)
    if m < 1:  # no candidates: the general steps
        return False, sigma, math.nan, np.zeros((0, 0)), np.zeros(0), np.zeros((0, 0)), np.zeros(0), np.zeros(0), none
    half = np.empty(d)
    for a in range(d):
        half[a] = 0.5 * y[3 + a]
    top = half[0]
    for a in range(1, d):
        top = max(top, half[a])
    vstar, sqd, x = _register_kernel(pts, y[0], y[1], y[2], c, s, half, m, 1e-9 * top, 2.0 * sigma**2)
    sigma_hat = math.nan
    if n >= 2:
        ok, sigma_hat = _em_one_kernel(sqd, floor, tol, max_iter, dof)
        if not ok:
            return (
                False,
                sigma,
                sigma_hat,
                np.zeros((0, 0)),
                np.zeros(0),
                np.zeros((0, 0)),
                np.zeros(0),
                np.zeros(0),
                none,
            )
        if estimate and n >= min_points and math.isfinite(sigma_hat):
            sigma = max(sigma_hat, floor)
            x = _resp_exponents(sqd, 2.0 * sigma**2)
    info, eta = _exp_information_kernel(vstar, x, pts, B, BB)
    ok, cov, mean, S0 = _posterior_kernel(P0, eta0, info, eta, sigma, G, S_ext, weight)
    if not ok:
        return False, sigma, sigma_hat, cov, mean, S0, np.zeros(0), np.zeros(0), none
    tv = _corner_quad_forms(J, cov)
    order = _corner_order_kernel(y, ox, oy)
    tv_ordered = np.empty(4)
    for i in range(4):
        tv_ordered[i] = tv[order[i]]
    return True, sigma, sigma_hat, cov, mean, S0, tv_ordered, _quad_forms(_box_jacobian_of(E), cov), order


@kernel(inline="always")
def _box_jacobian_of(E):  # pragma: no cover - compiled
    """K (p − 1, p), the box parameters' rows of E = ∂ỹ/∂φ (p, p) with its two angle rows averaged
    (0.5 (a + b), the yaw): what :func:`infer_label_valid`'s general steps build with NumPy."""
    p = E.shape[0]
    K = np.empty((p - 1, p))
    for i in range(p - 2):
        for j in range(p):
            K[i, j] = E[i, j]
    for j in range(p):
        K[p - 2, j] = 0.5 * (E[p - 2, j] + E[p - 1, j])
    return K


@kernel(inline="always")
def _corner_order_kernel(y, ox, oy):  # pragma: no cover - compiled
    """:func:`_corner_order` of box ``y`` (7,) seen from (``ox``, ``oy``): the same operations (libm's
    cos, sin and hypot, as Python's math and NumPy's ``np.hypot`` call), and the stable order by
    an insertion sort (equal distances keep the corners' order)."""
    c, s = math.cos(y[6]), math.sin(y[6])
    dist = np.empty(4)
    for k in range(4):
        ux = (0.5 if k == 0 or k == 3 else -0.5) * y[3]
        uy = (0.5 if k < 2 else -0.5) * y[4]
        dist[k] = math.hypot((c * ux - s * uy + y[0]) - ox, (s * ux + c * uy + y[1]) - oy)
    order = np.arange(4)
    for i in range(1, 4):
        k = order[i]
        j = i - 1
        while j >= 0 and dist[order[j]] > dist[k]:
            order[j + 1] = order[j]
            j -= 1
        order[j + 1] = k
    return order


@kernel
def _posterior_kernel(P0, eta0, info, eta, sigma, G, S_ext, weight):  # pragma: no cover - compiled
    """The posterior of :func:`infer_label_valid` from the prior and data terms, in one pass:
    Λ = sym(P0 + info/σ²), its inverse Σ by Cholesky (Λ = L Lᵀ, Σ = L⁻ᵀ L⁻¹, symmetrised), the
    mean Σ (η0 + η/σ²) and the prior covariance sym(G (Σ_ỹ / w) Gᵀ). Returns (ok, Σ, mean, Σ0);
    ok is False when a Cholesky pivot is not positive (the caller then asks LAPACK, which raises)."""
    p = P0.shape[0]
    s2 = sigma * sigma
    lam = np.empty((p, p))
    for i in range(p):
        for j in range(p):
            lam[i, j] = 0.5 * ((P0[i, j] + info[i, j] / s2) + (P0[j, i] + info[j, i] / s2))
    cov = np.zeros((p, p))
    mean = np.zeros(p)
    S0 = np.zeros((p, p))
    if not linalg.spd_inverse_kernel(lam, cov):
        return False, cov, mean, S0
    rhs = np.empty(p)
    for i in range(p):
        rhs[i] = eta0[i] + eta[i] / s2
    for i in range(p):
        acc = 0.0
        for j in range(p):
            acc += cov[i, j] * rhs[j]
        mean[i] = acc
    GS = np.zeros((p, p))
    for i in range(p):
        for j in range(p):
            acc = 0.0
            for k in range(p):
                acc += G[i, k] * (S_ext[k, j] / weight)
            GS[i, j] = acc
    for i in range(p):
        for j in range(i, p):
            acc = 0.0
            for k in range(p):
                acc += GS[i, k] * G[j, k]
            S0[i, j] = acc
            S0[j, i] = acc
    return True, cov, mean, S0


# ----------------------------------------------------------------------------------------------
# A BEV label's scores in two compiled calls (the pipeline's path)
# ----------------------------------------------------------------------------------------------


class BevLabelScores(NamedTuple):
    """What a result row takes of a BEV label's posterior, JIoU-GT and hull IoU
    (:func:`bev_label_scores`): :class:`LabelPosterior`'s ``sigma``, ``sigma_hat``, ``num_points``,
    ``cov`` (6, 6), ``corner_tv`` (4,) C1 first and ``std_box``; :func:`~labelaudit.core.spatial.jiou_gt`'s
    ``jiou_gt``; :func:`~labelaudit.core.iou.hull_iou_valid`'s ``hull_iou``; and the label's 3D
    :class:`BoxPriorTerms` for the label-error fit (``fit_terms``)."""

    sigma: float
    sigma_hat: float
    num_points: int
    cov: FloatArray
    corner_tv: FloatArray
    std_box: dict[str, float]
    jiou_gt: float
    hull_iou: float
    fit_terms: BoxPriorTerms


def bev_label_scores(
    y: FloatArray,
    pts: FloatArray,
    prior: ClassPrior,
    params: ModelParams,
    spatial: SpatialParams,
    ox: float,
    oy: float,
) -> BevLabelScores | None:
    """A BEV label's posterior, JIoU-GT and hull IoU, and its 3D prior terms, in two compiled calls
    with NumPy's sort of the JIoU-GT cells between them: the values of :func:`box_prior_terms_bev_3d`,
    :func:`infer_label_valid`, :func:`~labelaudit.core.spatial.jiou_gt` and
    :func:`~labelaudit.core.iou.hull_iou_valid` bit for bit (the same kernels on the same values),
    without their six dispatches and the Python between them (~25 µs per box).

    ``y``: a box (7,) float64 known to be valid; ``pts``: clean points (N, 2) float64, C-contiguous;
    ``params``: a BEV model without the outlier component, ``spatial.num_samples`` > 1; (``ox``,
    ``oy``): the sensor. None when the one pass cannot answer (σ̂ or Σ not formed that way, or a
    non-finite Σ): the caller then takes the general steps, which give the same values or the error.
    """
    c, s = g.cos_sin(y[6])  # NumPy's, as box_prior_terms_bev_3d
    w = float(params.prior_weight)
    B, BB = _BASIS["bev"]
    W2, W3, S_ext, z = _bev_scores_inputs(prior, w, spatial.num_samples, spatial.seed)
    ok, sigma, sigma_hat, cov, tv, var, phi, t, pb, qb, cb, keys, shift, p_only, q_only = _bev_scores_kernel(
        y,
        c,
        s,
        W2,
        W3,
        pts,
        *_no_outlier_settings(params, 2),
        B,
        BB,
        S_ext,
        w,
        _CORNER_J["bev"],
        ox,
        oy,
        z,
        grid_cells_per_side(spatial, 2),
        C.CELL_STD_SPAN,
        C.MAX_CELLS_PER_AXIS,
        C.SUBROWS_PER_CELL,
    )
    if not ok:
        return None
    keys.sort()  # NumPy's sort, in place, as jiou_gt sorts them (the keys are distinct)
    jiou, hull = _bev_jaccard_hull_kernel(
        pb, qb, cb, keys, shift, p_only, q_only, pts, float(y[0]), float(y[1]), BEV_CORNER_J, phi
    )
    fit_terms = BoxPriorTerms(
        model="3d", prior=prior, weight=params.prior_weight, phi=t[0], G=t[1], Ginv=t[2], P0=t[3], eta0=t[4]
    )
    return BevLabelScores(
        float(sigma), float(sigma_hat), pts.shape[0], cov, tv, _std_of(var, "bev"), float(jiou), float(hull), fit_terms
    )


@functools.lru_cache(maxsize=64)
def _bev_scores_inputs(
    prior: ClassPrior, weight: float, num_samples: int, seed: int
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The box-independent inputs of :func:`bev_label_scores`, looked up once per box instead of
    four caches: w Σ_ỹ⁻¹ of the BEV and 3D models, the BEV Σ_ỹ and JIoU-GT's normal samples.
    Read-only arrays."""
    return (
        _weighted_prior_info(prior, "bev", weight),
        _weighted_prior_info(prior, "3d", weight),
        prior_cov_extended_cached(prior, "bev"),
        normal_samples(6, num_samples, seed),
    )


@kernel
def _bev_scores_kernel(
    y,
    c,
    s,
    W2,
    W3,
    pts,
    m,
    sigma,
    estimate,
    min_points,
    em,
    max_iter,
    B,
    BB,
    S_ext,
    weight,
    J,
    ox,
    oy,
    z,
    cells,
    span,
    max_cells,
    nsub,
):  # pragma: no cover - compiled
    """:func:`bev_label_scores`' first pass: the BEV and 3D prior terms (:func:`_prior_terms_bev_3d_kernel`),
    the posterior (:func:`_posterior_no_outliers_kernel` with the BEV terms) and, when it is formed,
    JIoU-GT's cells (:func:`~labelaudit.core.spatial.jiou_gt_bev_cells`). Returns (ok, σ, σ̂, Σ, tv,
    var, φ, the 3D terms, then the cells: p, q, counts, keys, shift, p_only, q_only)."""
    b, t = _prior_terms_bev_3d_kernel(y, c, s, W2, W3)
    phi, G, E, P0, eta0 = b
    ok, sigma, sigma_hat, cov, _, _, tv, var, _ = _posterior_no_outliers_kernel(
        pts, y, c, s, m, sigma, estimate, min_points, em, max_iter, B, BB, P0, eta0, G, S_ext, weight, J, E, ox, oy
    )
    empty = np.zeros(0)
    if not ok:
        return False, sigma, sigma_hat, cov, tv, var, phi, t, empty, empty, empty, empty, 0, 0.0, 0.0
    jok, pb, qb, cb, keys, shift, p_only, q_only = jiou_gt_bev_cells(y, cov, z, cells, span, max_cells, nsub)
    return jok, sigma, sigma_hat, cov, tv, var, phi, t, pb, qb, cb, keys, shift, p_only, q_only


@kernel
def _bev_jaccard_hull_kernel(
    pb, qb, cb, keys, shift, p_only, q_only, pts, cx, cy, J, phi
):  # pragma: no cover - compiled
    """:func:`bev_label_scores`' second pass: JIoU-GT's sum over the sorted cells (0 without cells,
    as :func:`~labelaudit.core.spatial.jiou_gt`) and the hull IoU of the points (N, 2) float64
    (:func:`~labelaudit.core.iou.hull_iou_valid`'s steps: 0 below three hull candidates)."""
    jiou = jaccard_sum_sorted_keys(pb, qb, cb, keys, shift, p_only, q_only) if pb.size else 0.0
    local = hull_candidates_sorted(pts, cx, cy)
    hull = hull_iou_sorted(local, J, phi, cx, cy) if local.shape[0] >= 3 else 0.0
    return jiou, hull

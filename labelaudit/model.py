"""The generative label model (DESIGN.md §4): registration, posterior covariance, noise EM, scores.

Each LiDAR point x_k of a box is explained by one of the M nearest points v̄_km = J(v*_km)·φ̄ on the
surface of the *labeled* box, with isotropic Gaussian noise σ. With the mean fixed at the label the
posterior of the feature vector φ (see :mod:`labelaudit.geometry`) is Gaussian with precision

    Λ = Σ0⁻¹ + σ⁻² Σ_k Σ_m r_km J(v*_km)ᵀ J(v*_km)

where r_km are the registration responsibilities and Σ0 is the per-class prior. Everything here is
vectorised over points; a box costs a few hundred microseconds.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit import geometry as g
from labelaudit.config import ClassPrior, ModelParams
from labelaudit.geometry import ModelKind

FloatArray = NDArray[np.float64]

__all__ = [
    "LabelPosterior",
    "Registration",
    "linear_gaussian_posterior",
    "register",
    "registration_information",
    "prior_cov_extended",
    "prior_covariance",
    "prior_precision",
    "em_sigma_step",
    "estimate_sigma",
    "estimate_sigma_dataset",
    "corner_total_variance",
    "box_std",
    "infer_label",
    "LabelFit",
    "fit_label",
    "hull_iou",
]


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
    P0 = np.linalg.inv(np.asarray(prior_cov, dtype=float)) if prior_precision is None else np.asarray(prior_precision, dtype=float)
    w = np.ones(n) if weights is None else np.asarray(weights, dtype=float)
    # Stack rows of sqrt(w)·J so that one matmul gives Σ w JᵀJ.
    sw = np.sqrt(w)[:, None, None]
    A = (J * sw).reshape(n * d, p)
    b = (x[..., None] * sw[..., 0][:, :, None]).reshape(n * d) if n else np.zeros(0)
    precision = P0 + (A.T @ A) / sigma**2
    eta = P0 @ mu0 + (A.T @ b) / sigma**2
    precision = 0.5 * (precision + precision.T)
    cov = _spd_inverse(precision)
    return cov @ eta, cov, precision


def _spd_inverse(P: FloatArray) -> FloatArray:
    """Inverse of a symmetric positive definite matrix via Cholesky, symmetrised."""
    try:
        L = np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        raise ValueError(f"posterior precision is not positive definite (eigenvalues {np.linalg.eigvalsh(P)})") from None
    Linv = np.linalg.solve(L, np.eye(P.shape[0]))  # L is tiny (≤ 8×8): a generic solve is fine
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


def _responsibilities(sqdist: FloatArray, sigma: float, d: int, outlier_prob: float, outlier_log_density: float) -> FloatArray:
    """r_km ∝ exp(−d²/2σ²) over the M candidates, plus an optional uniform outlier component."""
    if sqdist.size == 0:
        return np.zeros_like(sqdist)
    m = sqdist.shape[1]
    logw = -sqdist / (2.0 * sigma**2)  # -inf for missing candidates
    top = np.max(logw, axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    e = np.exp(logw - top)
    norm = np.sum(e, axis=1, keepdims=True)
    if outlier_prob > 0:
        # Mixture: (1-p)/M · N(x | v̄, σ²I) per candidate, p · uniform. Compare in log space.
        log_gauss_const = np.log((1.0 - outlier_prob) / m) - 0.5 * d * np.log(2.0 * np.pi * sigma**2)
        log_out = np.log(outlier_prob) + outlier_log_density - log_gauss_const
        norm = norm + np.exp(np.minimum(log_out - top, 700.0))
    return e / norm


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
    return _register(y, _clean_points(points, d), d, num_nearest, sigma, outlier_prob)


def _register(y: FloatArray, pts: FloatArray, d: int, num_nearest: int, sigma: float, outlier_prob: float) -> Registration:
    """:func:`register` for a validated box and clean (N, d) points."""
    half = 0.5 * y[3 : 3 + d]
    c, s = np.cos(y[6]), np.sin(y[6])
    rel = pts[:, :2] - y[:2]
    local = np.empty_like(pts)  # box frame, metres: Rᵀ (x − c)
    local[:, 0] = c * rel[:, 0] + s * rel[:, 1]
    local[:, 1] = -s * rel[:, 0] + c * rel[:, 1]
    if d == 3:
        local[:, 2] = pts[:, 2] - y[2]
    m = min(int(num_nearest), 2 * d)
    vstar, sqd = _nearest_faces(local, half, m)
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
    return _nearest_faces_kernel(local, half, int(m), 1e-9 * float(np.max(half)))


@numba.njit(cache=True)
def _nearest_faces_kernel(local, half, m, tol):  # pragma: no cover - compiled
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
    design matrices are formed. Equals the sums over :func:`labelaudit.geometry.design_matrix`.
    """
    B, BB = _BASIS[model]
    n, m, d = reg.vstar.shape
    vt = np.empty((n, m, d + 1))
    vt[..., 0] = 1.0
    vt[..., 1:] = reg.vstar
    rv = vt * reg.resp[..., None]
    rv2 = rv.reshape(n * m, d + 1)
    moments = rv2.T @ vt.reshape(n * m, d + 1)  # (d+1, d+1)
    cross = rv.sum(axis=1).T @ reg.points  # (d+1, d): Σ_k (Σ_m r ṽ_a) x — x does not depend on m
    p = B.shape[-1]
    return (moments.reshape(-1) @ BB.reshape(-1, p * p)).reshape(p, p), cross.reshape(-1) @ B.reshape(-1, p)


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


def prior_covariance(box: ArrayLike, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    """Σ0 = G · Σ_ỹ / w · Gᵀ with G = ∂φ/∂ỹ at the label (full rank).

    The weight divides the prior *variance* (it multiplies the prior precision), as the authors'
    code does with its ``prior_scaler``.
    """
    G = g.dphi_dext(box, model)
    S = G @ (prior_cov_extended(prior, model) / weight) @ G.T
    return 0.5 * (S + S.T)


def _prior_precision_from(E: FloatArray, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    P = E.T @ (_prior_info_extended(prior, model) * weight) @ E
    return 0.5 * (P + P.T)


def prior_precision(box: ArrayLike, prior: ClassPrior, weight: float, model: ModelKind) -> FloatArray:
    """Σ0⁻¹ = Eᵀ · w Σ_ỹ⁻¹ · E with E = ∂ỹ/∂φ (Σ_ỹ is well conditioned; Σ0 need not be)."""
    return _prior_precision_from(g.dext_dphi(box, model), prior, weight, model)


# ----------------------------------------------------------------------------------------------
# Noise σ by EM
# ----------------------------------------------------------------------------------------------


def em_sigma_step(sqdist: FloatArray, resp: FloatArray, dof: float = C.EM_RESIDUAL_DOF) -> tuple[float, float]:
    """Sufficient statistics of the σ update: (Σ r·‖x−v̄‖², dof·Σ r); σ² = first / second.

    ``dof`` is the number of noise components a residual keeps. The candidates are the *nearest*
    surface points, so the surface absorbs the tangential noise and a residual keeps only its
    normal component: dof = 1 (the surface's codimension) gives an unbiased per-axis σ, where the
    point dimension D (DESIGN.md §4, the authors' code) would return σ/√D.
    Missing candidates (``sqdist = inf``) carry r = 0 and are skipped.
    """
    num = float(np.sum(resp * np.where(np.isfinite(sqdist), sqdist, 0.0)))
    return num, float(dof * np.sum(resp))


def _outlier_log_density(y: FloatArray, d: int) -> float:
    """log of the uniform outlier density: 1 / size of the box grown by the outlier margin."""
    return -float(np.sum(np.log(y[3 : 3 + d] + 2.0 * C.OUTLIER_REGION_MARGIN)))


def _em(regs: Sequence[tuple[FloatArray, float]], d: int, sigma0: float, outlier_prob: float) -> float:
    """Pooled EM for σ over registrations given as (sqdist (N, M), outlier log density)."""
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
        # changes with σ: the candidate differences, as rows (M, N), go to one compiled loop.
        diff = np.concatenate([(sqd - np.min(sqd, axis=1, keepdims=True)).T for sqd, _, _ in regs], axis=1)
        sq = np.concatenate([sqd0.T for _, sqd0, _ in regs], axis=1)
        return float(_em_fast_kernel(diff, sq, sigma, estimate, C.SIGMA_FLOOR, C.EM_TOLERANCE, C.EM_MAX_ITERATIONS, float(C.EM_RESIDUAL_DOF)))
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


@numba.njit(cache=True)
def _em_fast_kernel(diff, sq, sigma, estimate, floor, tol, max_iter, dof):  # pragma: no cover - compiled
    """The EM of :func:`_em` without outliers: candidate differences d² − min d² and squared
    distances as rows (M, N); per point the responsibility-weighted d² over its candidates."""
    m, n = diff.shape
    den = dof * n
    for _ in range(max_iter):
        scale = -0.5 / sigma**2
        num = 0.0
        for k in range(n):
            se = 0.0
            s = 0.0
            for j in range(m):
                e = math.exp(diff[j, k] * scale)  # missing candidates (inf) give 0
                se += e
                s += e * sq[j, k]
            num += s / se
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
    return _em([(reg.sqdist, _outlier_log_density(y, d))], d, sigma_init, outlier_prob)


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
            regs.append((reg.sqdist, _outlier_log_density(y, d)))
    if not regs:
        return float("nan")
    return _em(regs, d, sigma_init, outlier_prob)


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
    order : (4,) indices into :func:`labelaudit.geometry.box_corners` (BEV order) of C1..C4.
    """
    return _corner_tv(g.validate_box(box), np.asarray(cov, dtype=float), model, sensor_origin)


_CORNER_J = {m: g.design_matrix(corner_unit_coords(m), m) for m in ("bev", "3d")}  # (4, d, p), box-independent


def _corner_tv(y: FloatArray, cov: FloatArray, model: ModelKind, sensor_origin: ArrayLike) -> tuple[FloatArray, NDArray[np.int64]]:
    J = _CORNER_J[model]
    tv = np.einsum("cdp,pq,cdq->c", J, cov, J)
    c, s = math.cos(y[6]), math.sin(y[6])
    u = g.BEV_CORNERS_UNIT * y[3:5]
    o = np.asarray(sensor_origin, dtype=float)
    dist = np.hypot((c * u[:, 0] - s * u[:, 1] + y[0]) - o[0], (s * u[:, 0] + c * u[:, 1] + y[1]) - o[1])  # corners − sensor
    order = np.argsort(dist, kind="stable")
    return tv[order], order


def box_std(box: ArrayLike, cov: ArrayLike, model: ModelKind) -> dict[str, float]:
    """Std of (cx, cy, cz, length, width, height, yaw) from K Σ Kᵀ; NaN for cz/height in BEV."""
    K, _ = g.box_param_jacobian(box, model)
    return _std_from_K(K, cov, model)


def _std_from_K(K: FloatArray, cov: ArrayLike, model: ModelKind) -> dict[str, float]:
    names = ("cx", "cy", "length", "width", "yaw") if g.point_dim(model) == 2 else g.BOX_FIELDS
    var = np.einsum("ip,pq,iq->i", K, np.asarray(cov, dtype=float), K)
    out = {name: float("nan") for name in g.BOX_FIELDS}
    for name, v in zip(names, var):
        out[name] = float(np.sqrt(max(v, 0.0)))
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


def _clean_points(points: ArrayLike | None, d: int) -> FloatArray:
    if points is None:
        return np.zeros((0, d))
    pts = np.asarray(points, dtype=float)
    if pts.size == 0:
        return np.zeros((0, d))
    if pts.ndim != 2 or pts.shape[1] < d:
        raise ValueError(f"points must be an (N, ≥{d}) array, got shape {pts.shape}")
    pts = pts[:, :d]
    return pts[np.all(np.isfinite(pts), axis=1)]  # non-finite returns cannot be registered


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
    """
    y = g.validate_box(box)
    model = params.model
    d = g.point_dim(model)
    pts = _clean_points(points, d)
    n = pts.shape[0]
    prior = params.prior_for(class_name)
    phi = _box_to_phi_valid(y, model)
    G = g.dphi_dext(y, model)
    E = np.linalg.inv(G)
    P0 = _prior_precision_from(E, prior, params.prior_weight, model)

    sigma_hat = float("nan")
    sigma = float(params.sigma)
    reg = _register(y, pts, d, params.num_nearest, sigma, params.outlier_prob)
    if n >= 2:
        sigma_hat = _em([(reg.sqdist, _outlier_log_density(y, d))], d, sigma, params.outlier_prob)
        if params.estimate_sigma and n >= max(params.min_points, 2) and np.isfinite(sigma_hat):
            sigma = max(sigma_hat, C.SIGMA_FLOOR)
            reg = _register(y, pts, d, params.num_nearest, sigma, params.outlier_prob)

    data_precision, data_eta = registration_information(reg, model)
    precision = P0 + data_precision / sigma**2
    cov = _spd_inverse(0.5 * (precision + precision.T))
    fit_mean = cov @ (P0 @ phi + data_eta / sigma**2)
    tv, order = _corner_tv(y, cov, model, sensor_origin)
    p = phi.size
    K = np.vstack([E[: p - 2], 0.5 * (E[p - 2] + E[p - 1])])  # as geometry.box_param_jacobian
    S0 = G @ (prior_cov_extended(prior, model) / params.prior_weight) @ G.T
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
        prior_cov=0.5 * (S0 + S0.T),
        corner_order=order,
        class_name=class_name,
        fit_mean=fit_mean,
    )


# ----------------------------------------------------------------------------------------------
# Label error: the model's suggested box and how far the label is from it (DESIGN.md §6)
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
    _residual_inputs: tuple = field(default=(), repr=False, compare=False)  # (box, points, d, params, σ)

    @functools.cached_property
    def sigma_hat(self) -> float:
        """EM noise estimate σ̂ of the points at the suggested box (NaN below 2 points)."""
        if not self._residual_inputs:
            return float("nan")
        y_fit, pts, d, params, sigma = self._residual_inputs
        reg = _register(y_fit, pts, d, params.num_nearest, sigma, params.outlier_prob)
        return _em([(reg.sqdist, _outlier_log_density(y_fit, d))], d, sigma, params.outlier_prob)


def _box_to_phi_valid(y: FloatArray, model: ModelKind) -> FloatArray:
    """:func:`geometry.box_to_phi` of a box (7,) float64 known to be valid (labels
    after ``validate_box``, the fit's own rectangles: finite, sizes floored above 0): the same arithmetic without the checks, which cost
    more than φ itself at a dozen calls per fit."""
    cx, cy, cz, length, width, height, yaw = y
    c, s = np.cos(yaw), np.sin(yaw)
    if model == "bev":
        return np.array([cx, cy, length * c, length * s, width * c, width * s])
    return np.array([cx, cy, cz, length * c, length * s, width * c, width * s, height])


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
    forms = _equivalent_boxes(y)
    cost = [float((f := _box_to_phi_valid(b, model) - phi_ref) @ W @ f) for b in forms]
    return forms[int(np.argmin(cost))]


@numba.njit(cache=True)
def _rect_from_phi(phi, three_d, label, floor):  # pragma: no cover - compiled
    """Rectangle (7,) of a φ (mean axis direction); sizes kept ≥ ``floor`` × the label's.

    Equals ``geometry.phi_to_box`` (then the size floor), in scalar arithmetic: it runs once per
    fit iteration on 8 numbers, inside the compiled fit loop (:func:`_fit_iterate_kernel`).
    """
    o = 1 if three_d else 0
    lc, ls, wc, ws = phi[2 + o], phi[3 + o], phi[4 + o], phi[5 + o]
    a, b = math.atan2(ls, lc), math.atan2(ws, wc)
    two_pi = 2.0 * math.pi
    yaw = (a + 0.5 * ((b - a + math.pi) % two_pi - math.pi) + math.pi) % two_pi - math.pi
    cz, height = (phi[2], phi[7]) if three_d else (label[2], label[5])
    out = np.empty(7)
    out[0], out[1], out[2] = phi[0], phi[1], cz
    out[3] = max(math.hypot(lc, ls), floor * label[3])
    out[4] = max(math.hypot(wc, ws), floor * label[4])
    out[5] = max(height, floor * label[5])
    out[6] = yaw
    return out


def _plane_rows(y: FloatArray, pts: FloatArray, model: ModelKind) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Point-to-surface rows for a box fit: a_k = J(v*_k)ᵀ n_k (N, p) and b_k = n_kᵀ x_k (N,),
    scaled by 1/FIT_INSIDE_SIGMA_RATIO for points deep inside the box; plus the squared distances
    (N,) of the points to the surface.

    Each point is registered to its single nearest surface point v̄_k, and only the residual along
    n_k (the face normal, or the direction to the nearest edge/corner when the point lies beyond
    one) is used. Unlike the full J rows, the position *along* the face then carries no information,
    so a face can slide while the box is fitted (no anchoring to the current box, no pull of the
    second-nearest face at corners). Computed by the compiled :func:`_rows_kernel`, which the fit
    calls through :func:`_fit_normal_eq`.
    """
    d = g.point_dim(model)
    pts_t = np.ascontiguousarray(np.asarray(pts, dtype=float)[:, :d].T)
    n = pts_t.shape[1]
    a = np.empty((2 * d + 2, n))
    b = np.empty(n)
    sqd = np.empty(n)
    _rows_kernel(np.asarray(y, dtype=float), pts_t, d, C.FIT_INSIDE_FREE_DEPTH, 1.0 / C.FIT_INSIDE_SIGMA_RATIO, a, b, sqd)
    return a.T, b, sqd


@numba.njit(cache=True)
def _rows_kernel(y, pts_t, d, free_depth, deep_weight, a, b, sqd):  # pragma: no cover - compiled
    """Rows a — transposed, (p, N) — b (N,) and squared distances (N,) of :func:`_plane_rows` for
    points (d, N).

    Nearest surface point: a point outside the box projects to its clamped position; a point
    inside to its nearest face (ties: the lower face index — axis first, the − face before the +
    face — as :func:`_nearest_faces` with m = 1). One pass, scalars only.
    """
    c, s = math.cos(y[6]), math.sin(y[6])
    h0, h1 = 0.5 * y[3], 0.5 * y[4]
    h2 = 0.5 * y[5] if d == 3 else 0.0
    big = max(y[3], y[4], y[5]) if d == 3 else max(y[3], y[4])
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
        if inside:  # nearest face: the smallest (x ∓ half)² of each axis' nearer face
            e0, e1 = (h0 - abs(l0)) ** 2, (h1 - abs(l1)) ** 2
            e2 = (h2 - abs(l2)) ** 2 if d == 3 else math.inf
            if e0 <= e1 and e0 <= e2:
                m0 = h0 if l0 > 0 else -h0
            elif e1 <= e2:
                m1 = h1 if l1 > 0 else -h1
            else:
                m2 = h2 if l2 > 0 else -h2
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
        w = deep_weight if strict and norm > free_depth else 1.0  # √weight = σ / σ_inside
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


@numba.njit(cache=True, fastmath={"reassoc", "contract"})
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


@numba.njit(cache=True)
def _normal_eq_kernel(y, pts_t, d, free_depth, deep_weight, phi):  # pragma: no cover - compiled
    n = pts_t.shape[1]
    a = np.empty((2 * d + 2, n))
    b = np.empty(n)
    sqd = np.empty(n)
    _rows_kernel(y, pts_t, d, free_depth, deep_weight, a, b, sqd)
    ata, atb, rr = _gram_kernel(a, b, phi, True)
    return ata, atb, rr, sqd.sum()


def _fit_normal_eq(y: FloatArray, pts_t: FloatArray, d: int, phi: FloatArray) -> tuple[FloatArray, FloatArray, float, float]:
    """Σ a_kᵀa_k (p, p), Σ a_k b_k (p,), Σ (a_k·φ − b_k)² and Σ ‖x_k − v̄_k‖² of the rows of
    :func:`_plane_rows` for points (d, N): one compiled call per fit iteration (as NumPy array code
    it took ~40 calls, and a fit runs 5–30 iterations)."""
    return _normal_eq_kernel(y, pts_t, d, C.FIT_INSIDE_FREE_DEPTH, 1.0 / C.FIT_INSIDE_SIGMA_RATIO, phi)


@numba.njit(cache=True)
def _solve_spd(M, rhs):  # pragma: no cover - compiled
    """x with M x = rhs for a small symmetric positive definite M (p, p): Cholesky, two
    triangular substitutions (scalars only; a LAPACK call from here would need scipy)."""
    p = M.shape[0]
    L = np.zeros((p, p))
    for j in range(p):
        acc = M[j, j]
        for k in range(j):
            acc -= L[j, k] * L[j, k]
        L[j, j] = math.sqrt(acc)  # NaN when M is not positive definite: the fit then reports NaN
        for i in range(j + 1, p):
            acc = M[i, j]
            for k in range(j):
                acc -= L[i, k] * L[j, k]
            L[i, j] = acc / L[j, j]
    z = np.empty(p)
    for i in range(p):
        acc = rhs[i]
        for k in range(i):
            acc -= L[i, k] * z[k]
        z[i] = acc / L[i, i]
    x = np.empty(p)
    for i in range(p - 1, -1, -1):
        acc = z[i]
        for k in range(i + 1, p):
            acc -= L[k, i] * x[k]
        x[i] = acc / L[i, i]
    return x


@numba.njit(cache=True)
def _fit_iterate_kernel(y_cur, phi, pts_t, three_d, free_depth, deep_weight, tol, P0, prior_eta, label, inv_s2, floor, max_iter):  # pragma: no cover - compiled
    d = 3 if three_d else 2
    p, n = phi.shape[0], pts_t.shape[1]
    a = np.empty((p, n))
    b = np.empty(n)
    sqd = np.empty(n)
    phi_prev = phi.copy()
    it = 0
    for it in range(1, max_iter + 1):
        _rows_kernel(y_cur, pts_t, d, free_depth, deep_weight, a, b, sqd)
        ata, atb, _ = _gram_kernel(a, b, phi, False)
        precision = P0 + ata * inv_s2
        new = _solve_spd(0.5 * (precision + precision.T), prior_eta + atb * inv_s2)
        step = np.max(np.abs(new - phi))
        if it >= 3 and step >= tol and np.all(new == phi_prev):
            # φ_it = φ_(it−2): the states alternate up to the cap. End on the cap's state.
            if (max_iter - it) % 2 == 0:
                phi = new
            return phi, _rect_from_phi(phi, three_d, label, floor), max_iter, False
        phi_prev, phi = phi, new
        y_cur = _rect_from_phi(phi, three_d, label, floor)
        if step < tol:
            return phi, y_cur, it, True
    return phi, y_cur, it, False


def _fit_iterate(
    y_cur: FloatArray,
    phi: FloatArray,
    pts: FloatArray,
    tol: float,
    P0: FloatArray,
    prior_eta: FloatArray,
    label: FloatArray,
    inv_s2: float,
    model: ModelKind,
) -> tuple[FloatArray, FloatArray, int, bool]:
    """EM iterations of the box fit on (d, N) points until φ moves by less than ``tol`` (at most
    FIT_MAX_ITERATIONS). Returns (φ, rectangle, iterations, converged).

    The iterations only need the mean (a linear solve). When the iteration has entered an exact
    2-cycle (a point flipping between two faces, so that φ repeats bit for bit), it can never
    converge: the state the iteration cap would end on is known, and is returned without running
    the remaining iterations. The whole loop — point pass, Gram product, the p × p solve and the
    rectangle of φ — is one compiled call (:func:`_fit_iterate_kernel`): per iteration, the NumPy
    calls around the point pass cost as much as the pass itself.
    """
    phi, y_cur, it, converged = _fit_iterate_kernel(
        np.asarray(y_cur, dtype=float), np.asarray(phi, dtype=float), pts, model == "3d",
        C.FIT_INSIDE_FREE_DEPTH, 1.0 / C.FIT_INSIDE_SIGMA_RATIO, float(tol), P0, prior_eta,
        np.asarray(label, dtype=float), float(inv_s2), C.FIT_MIN_SIZE_FRACTION, C.FIT_MAX_ITERATIONS,
    )
    return phi, y_cur, int(it), bool(converged)


def _fit_em(
    start: FloatArray,
    pts: FloatArray,
    phi_label: FloatArray,
    P0: FloatArray,
    label: FloatArray,
    sigma: float,
    params: ModelParams,
) -> tuple[FloatArray, FloatArray, int, bool, float, FloatArray]:
    """Box fit from ``start`` (a rectangle): register each point to its nearest surface point of the
    current box, take the Gaussian mean of the point-to-surface model with the prior centred on
    the label, repeat (Gauss–Newton / EM). Returns (φ, Σ, iterations, converged, log posterior,
    fitted rectangle, RMS distance of the points to its surface).

    ``pts`` is (d, N) (transposed). The covariance is formed once, at the fitted box.
    """
    model = params.model
    phi = _box_to_phi_valid(start, model)
    prior_eta = P0 @ phi_label
    inv_s2 = 1.0 / sigma**2
    phi, y_cur, it, converged = _fit_iterate(start, phi, pts, C.FIT_TOLERANCE, P0, prior_eta, label, inv_s2, model)
    phi_rect = _box_to_phi_valid(y_cur, model)
    ata, _, rr, ss = _fit_normal_eq(y_cur, pts, g.point_dim(model), phi_rect)
    precision = P0 + ata * inv_s2
    cov = _spd_inverse(0.5 * (precision + precision.T))
    dphi = phi_rect - phi_label
    log_post = -0.5 * rr * inv_s2 - 0.5 * float(dphi @ P0 @ dphi)
    n = pts.shape[1]
    rms = math.sqrt(ss / n) if n else 0.0  # unweighted distance to the surface
    return phi, cov, it, converged, log_post, y_cur, rms


_BEV_OF_3D = np.array([0, 1, 3, 4, 5, 6])  # entries of φ_3d that make φ_bev: cx, cy, l·cos, l·sin, w·cos, w·sin


def _scored_metric(S: FloatArray, fit_model: ModelKind, scored: ModelKind) -> FloatArray:
    """Metric (p, p) of the label-error distance: S⁻¹ for the scored φ entries, zero elsewhere.

    A BEV run (``scored == "bev"``) of a 3D fit scores the BEV marginal of the Gaussian, i.e. the
    inverse of the (cx, cy, l·cos, l·sin, w·cos, w·sin) block of S: the fit is 3D so roof points
    register to the top face, but its cz and height are not what a BEV audit judges, and they are
    the least reliable parameters of the fit (the ground cut removes every point of the bottom
    face; near the sensor the roof of tall vehicles is above the top beam). On the issue-6
    benchmark scoring them raised false alarms on correct labels (docs/label-error.md).
    """
    if fit_model == scored:
        return np.linalg.inv(S)
    W = np.zeros_like(S)
    block = np.ix_(_BEV_OF_3D, _BEV_OF_3D)
    W[block] = np.linalg.inv(S[block])
    return W


def fit_label(
    box: ArrayLike,
    points: ArrayLike | None,
    class_name: str,
    params: ModelParams,
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
    """
    y = g.validate_box(box)
    # The fit is 3D whenever the points have a z: in BEV, roof and hood points lie *inside* the
    # rectangle and would pull its edges inwards; in 3D they register to the top face.
    arr = None if points is None else np.asarray(points, dtype=float)
    model: ModelKind = "3d" if arr is not None and arr.ndim == 2 and arr.shape[1] >= 3 else "bev"
    # The run's model decides what is scored: a BEV run scores the BEV marginal of the 3D fit.
    scored: ModelKind = "bev" if model == "bev" or params.model == "bev" else "3d"
    if model != params.model:
        params = dataclasses.replace(params, model=model)
    d = g.point_dim(model)
    pts = _clean_points(arr, d)
    n = pts.shape[0]
    prior = params.prior_for(class_name)
    phi_label = _box_to_phi_valid(y, model)
    G = g.dphi_dext(y, model)
    P0 = _prior_precision_from(np.linalg.inv(G), prior, params.prior_weight, model)
    tol = ClassPrior(**C.LABEL_TOLERANCE)
    S_tol = G @ prior_cov_extended(tol, model) @ G.T
    sigma = float(params.sigma)
    if params.estimate_sigma and n >= max(params.min_points, 2):
        s_hat = estimate_sigma(y, pts, model, num_nearest=params.num_nearest, sigma_init=sigma, outlier_prob=params.outlier_prob)
        if np.isfinite(s_hat):
            sigma = max(s_hat, C.SIGMA_FLOOR)

    pts_t = np.ascontiguousarray(pts.T)  # (d, N): the fit's layout (_fit_normal_eq)
    best = (_fit_em(y, pts_t, phi_label, P0, y, sigma, params), False)
    # A second start with length and width swapped, when the first fit leaves the points far from
    # its surface (RMS > FIT_SWAP_RESIDUAL × σ): the nearest-face registration cannot turn a box by
    # 90° on its own. The start with the higher log posterior wins.
    if n >= max(params.min_points, 1) and abs(y[3] - y[4]) > 1e-9 and best[0][6] > C.FIT_SWAP_RESIDUAL * sigma:
        swapped = y.copy()
        swapped[3], swapped[4] = y[4], y[3]
        alt = _fit_em(_closest_form(swapped, phi_label, P0, model), pts_t, phi_label, P0, y, sigma, params)
        if alt[4] > best[0][4] + 1e-9:
            best = (alt, True)
    (phi_fit, cov, iterations, converged, _, y_rect, _), is_swapped = best

    W = _scored_metric(cov + S_tol, model, scored)
    y_fit = _closest_form(y_rect, phi_label, W, model)
    phi_rect = _box_to_phi_valid(y_fit, model)
    delta = phi_label - phi_rect
    d2_tol = float(delta @ W @ delta)
    d2 = float(delta @ _scored_metric(cov, model, scored) @ delta)
    k = 5 if scored == "bev" else 7

    offsets = {name: float(y_fit[i] - y[i]) for i, name in enumerate(g.BOX_FIELDS)}
    offsets["yaw"] = float(g.normalize_angle(y_fit[6] - y[6]))
    y_fit[6] = y[6] + offsets["yaw"]  # same branch as the label's yaw, so fit_yaw − yaw is the offset
    if d == 2:
        offsets["cz"] = offsets["height"] = float("nan")
    return LabelFit(
        model=model,
        box=y_fit,
        phi=phi_rect,
        cov=cov,
        offsets=offsets,
        offset_m=float(np.linalg.norm(y_fit[:d] - y[:d])),
        mahalanobis=float(np.sqrt(max(d2, 0.0))),
        tolerance_distance=float(np.sqrt(max(d2_tol, 0.0))),
        label_error=_chi2_cdf(max(d2_tol, 0.0), k),
        iterations=iterations,
        converged=converged,
        swapped_start=is_swapped,
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


def hull_iou(box: ArrayLike, points: ArrayLike | None) -> float:
    """BEV IoU between a box and the convex hull of its points (a baseline label-quality score).

    0.0 when the hull has no area (fewer than 3 points, or all on a line). The hull (monotone
    chain), its clipping by the box (Sutherland–Hodgman) and the areas (shoelace) are one compiled
    call, :func:`_hull_iou_kernel`; coordinates are taken relative to the box centre.
    """
    y = g.validate_box(box)
    pts = _hull_candidates(_clean_points(points, 2))
    if len(pts) < 3:
        return 0.0
    local = pts - y[:2]
    order = np.lexsort((local[:, 1], local[:, 0]))  # by x, then y
    corners = g.box_corners(y, "bev") - y[:2]  # counter-clockwise
    return float(_hull_iou_kernel(np.ascontiguousarray(local[order]), np.ascontiguousarray(corners)))


@numba.njit(cache=True)
def _cross(o0, o1, a0, a1, b0, b1):  # pragma: no cover - compiled
    """z of (a − o) × (b − o): > 0 when o → a → b turns left."""
    return (a0 - o0) * (b1 - o1) - (a1 - o1) * (b0 - o0)


@numba.njit(cache=True)
def _shoelace(poly, m):  # pragma: no cover - compiled
    s = 0.0
    for i in range(m):
        j = (i + 1) % m
        s += poly[i, 0] * poly[j, 1] - poly[j, 0] * poly[i, 1]
    return 0.5 * s


@numba.njit(cache=True)
def _hull_iou_kernel(pts, corners):  # pragma: no cover - compiled
    """IoU of the convex hull of ``pts`` (N, 2), sorted by x then y, and the convex polygon
    ``corners`` (4, 2), counter-clockwise; 0.0 when the hull has no area."""
    n = pts.shape[0]
    hull = np.empty((2 * n + 1, 2))
    k = 0
    for i in range(n):  # lower hull; collinear and repeated points are dropped (≤ 0)
        while k >= 2 and _cross(hull[k - 2, 0], hull[k - 2, 1], hull[k - 1, 0], hull[k - 1, 1], pts[i, 0], pts[i, 1]) <= 0.0:
            k -= 1
        hull[k, 0], hull[k, 1] = pts[i, 0], pts[i, 1]
        k += 1
    lower = k + 1
    for i in range(n - 2, -1, -1):  # upper hull
        while k >= lower and _cross(hull[k - 2, 0], hull[k - 2, 1], hull[k - 1, 0], hull[k - 1, 1], pts[i, 0], pts[i, 1]) <= 0.0:
            k -= 1
        hull[k, 0], hull[k, 1] = pts[i, 0], pts[i, 1]
        k += 1
    m = k - 1  # the last point repeats the first
    if m < 3:
        return 0.0
    hull_area = _shoelace(hull, m)
    if not hull_area > 0.0:
        return 0.0
    poly = hull[:m].copy()
    for e in range(4):  # clip by each edge of the box: keep the left side (inside, on the edge)
        a0, a1 = corners[e, 0], corners[e, 1]
        b0, b1 = corners[(e + 1) % 4, 0], corners[(e + 1) % 4, 1]
        out = np.empty((2 * m + 2, 2))
        q = 0
        for i in range(m):
            p0, p1 = poly[i - 1, 0], poly[i - 1, 1]  # i − 1 = −1: the last vertex
            c0, c1 = poly[i, 0], poly[i, 1]
            sp = _cross(a0, a1, b0, b1, p0, p1)
            sc = _cross(a0, a1, b0, b1, c0, c1)
            if (sc >= 0.0) != (sp >= 0.0):  # the edge p → c crosses the line: add the crossing
                t = sp / (sp - sc)
                out[q, 0], out[q, 1] = p0 + t * (c0 - p0), p1 + t * (c1 - p1)
                q += 1
            if sc >= 0.0:
                out[q, 0], out[q, 1] = c0, c1
                q += 1
        poly = out[:q].copy()
        m = q
        if m < 3:
            return 0.0
    inter = max(_shoelace(poly, m), 0.0)
    union = hull_area + _shoelace(corners, 4) - inter
    return inter / union if union > 0.0 else 0.0


def _hull_candidates(pts: FloatArray) -> FloatArray:
    """The points (N, 2) that can be convex-hull vertices (Akl–Toussaint): a point strictly inside
    the quadrilateral of the extreme points in x and y is inside the hull and is dropped. Exact;
    dense boxes keep a few percent of their points, so the hull gets little to do."""
    if len(pts) < 8:
        return pts
    x, y = pts[:, 0], pts[:, 1]
    quad = pts[[np.argmin(x), np.argmin(y), np.argmax(x), np.argmax(y)]]  # counter-clockwise
    keep = np.zeros(len(pts), dtype=bool)
    edges = 0
    for (qx, qy), (rx, ry) in zip(quad, np.roll(quad, -1, axis=0)):
        ex, ey = rx - qx, ry - qy
        if ex == 0.0 and ey == 0.0:
            continue  # two extremes are the same point: the polygon has fewer sides
        edges += 1
        keep |= ex * (y - qy) - ey * (x - qx) <= 0.0  # not strictly left of this edge (on it: kept)
    return pts[keep] if edges else pts

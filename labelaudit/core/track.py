"""Every label judged against its own track: robust consensus of size, heading and trajectory.
Pure NumPy on one track at a time (docs/method.md, "Tracks"); no I/O.

A track is one object's labels over time, in the world frame (ego poses applied). Three
consensus models, each judged leave-one-out so that a frame is never compared with itself:

* **size** — vehicles are rigid: one size for the whole track. Its posterior is the product of
  the frames' evidence: every label is a measurement of the true size with the ordinary
  per-frame label noise σ, and a frame whose points pin a size adds the data precision of its
  per-frame posterior (the fitted size with precision 1/std² − 1/prior²). Robust weights
  (Huber, then Tukey's biweight) keep wrong labels out of it.
* **position** — smooth motion: the centre at frame i predicted by a robust local quadratic in
  time through the nearest frames in time (within ``window`` s, frame i left out).
* **heading** — continuous: the same local quadratic on the yaw, unwrapped around the
  neighbours' circular mean, so a label flipped by π is a residual of π, not a wrap.

Each residual is divided by its predictive std (σ of the label plus the consensus's own
variance) and turned into the posterior probability that the label is wrong under a
two-component model: a right label's standardised residual is N(0, I_d), a wrong one's is
N(0, k²·I_d) (errors ~k times the ordinary noise) with prior probability π.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle

FloatArray = NDArray[np.float64]

ISSUES: tuple[str, ...] = ("size", "heading", "position")
"""The kinds of contradiction, in the order of :attr:`TrackScores.kind_scores`'s columns; ``none`` when no kind is flagged."""


@dataclass(frozen=True)
class TrackParams:
    """The numbers of the track model (from :mod:`labelaudit.constants`, hashed).

    Attributes
    ----------
    window : s; the frames nearest in time to a frame, within this time, predict its centre and heading
    max_neighbours : 2 × this many nearest frames (as many on each side inside a track)
    min_frames : tracks with fewer labelled frames get no score (null)
    rate_prior : (centre velocity m/s, centre acceleration m/s², yaw rate rad/s, yaw acceleration
        rad/s²) — std of the ridge prior on the local quadratic's slope and curvature, so a
        frame with one neighbour gets a wide (honest) prediction instead of a singular one
    huber_k, biweight_c : robust weights, in standardised residuals
    error_prior : π, prior probability that a label contradicts its track
    error_scale : k, a wrong label's residual std in units of the ordinary noise
    """

    window: float
    max_neighbours: int
    min_frames: int
    rate_prior: tuple[float, float, float, float]
    huber_k: float
    biweight_c: float
    error_prior: float
    error_scale: float


def default_params() -> TrackParams:
    """The track model of :mod:`labelaudit.constants` (``TRACK_*``)."""
    return TrackParams(
        window=C.TRACK_WINDOW,
        max_neighbours=C.TRACK_MAX_NEIGHBOURS,
        min_frames=C.TRACK_MIN_FRAMES,
        rate_prior=tuple(C.TRACK_RATE_PRIOR),  # type: ignore[arg-type]
        huber_k=C.TRACK_HUBER_K,
        biweight_c=C.TRACK_BIWEIGHT_C,
        error_prior=C.TRACK_ERROR_PRIOR,
        error_scale=C.TRACK_ERROR_SCALE,
    )


@dataclass(frozen=True)
class TrackNoise:
    """Ordinary per-frame label noise (std): centre (3,) m, size (3,) m (l, w, h), yaw rad."""

    centre: FloatArray
    size: FloatArray
    yaw: float

    @classmethod
    def floor(cls) -> "TrackNoise":
        """The smallest noise ever assumed (:data:`~labelaudit.constants.TRACK_NOISE_FLOOR`)."""
        f = C.TRACK_NOISE_FLOOR
        return cls(np.full(3, f["center"]), np.array([f["length"], f["width"], f["height"]]), f["yaw"])


@dataclass
class TrackResiduals:
    """Standardised leave-one-out residuals of one track's n frames and its consensus.

    Attributes
    ----------
    size : (n, 3) (label − consensus of the other frames) / predictive std, per l, w, h
    position : (n, 3) centre residual / predictive std, per world x, y, z
    heading : (n,) wrapped yaw residual / predictive std
    size_mean, size_std : (3,) posterior mean and std of the track's size (all frames, robust weights)
    size_weight : (n,) robust weight of each label in the size posterior (1 = fully trusted)
    velocity : (n, 2) world BEV velocity of the centre from the local fit (m/s)
    expected : (n, 7) the box the rest of the track expects at each frame (world frame): the
        predicted centre, the other frames' size consensus and the predicted heading
    """

    size: FloatArray
    position: FloatArray
    heading: FloatArray
    size_mean: FloatArray
    size_std: FloatArray
    size_weight: FloatArray
    velocity: FloatArray
    expected: FloatArray


def _robust_weights(z: FloatArray, k: float, c: float, stage: int) -> FloatArray:
    """Huber weights in the first stages (convex: a safe start), Tukey's biweight after (a gross outlier gets weight 0)."""
    a = np.abs(z)
    if stage < C.TRACK_HUBER_ITERATIONS:
        return np.where(a <= k, 1.0, k / np.maximum(a, 1e-300))
    return np.where(a < c, (1.0 - (a / c) ** 2) ** 2, 0.0)


def neighbour_index(t: FloatArray, window: float, max_neighbours: int) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """The ``2 · max_neighbours`` frames nearest in time to each frame of a time-sorted track
    (itself excluded), within ``window`` seconds: inside a track as many before as after, at its
    ends all on one side — a one-sided extrapolation needs the extra frames most.

    Returns
    -------
    index : (n, 2m) frame indices, nearest first (clipped into range where invalid)
    valid : (n, 2m) whether that neighbour exists and lies within ``window`` seconds
    """
    n = len(t)
    k = 2 * max_neighbours
    offsets = np.concatenate([np.arange(-k, 0), np.arange(1, k + 1)])
    raw = np.arange(n)[:, None] + offsets[None, :]
    inside = (raw >= 0) & (raw < n)
    index = np.clip(raw, 0, max(n - 1, 0))
    gap = np.where(inside, np.abs(t[index] - t[:, None]), np.inf)
    order = np.argsort(gap, axis=1, kind="stable")[
        :, :k
    ]  # ties (a regular rate): the earlier frame first, both sides kept
    index = np.take_along_axis(index, order, axis=1)
    valid = np.take_along_axis(gap, order, axis=1) <= window
    return index, valid


def local_fit(
    dt: FloatArray,
    y: FloatArray,
    valid: NDArray[np.bool_],
    ridge: FloatArray,
    params: TrackParams,
    iterations: int = C.TRACK_IRLS_ITERATIONS,
    prior: FloatArray | None = None,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Robust weighted quadratic through each frame's neighbours, evaluated at the frame (dt = 0).

    Parameters
    ----------
    dt : (n, m) neighbour time minus the frame's time (s)
    y : (n, m, d) neighbour values, already divided by their noise std (so one set of robust
        weights per neighbour serves all d coordinates)
    valid : (n, m) which neighbours exist
    ridge : (3,) prior precision of the intercept, slope and curvature (standardised units)
    iterations : IRLS iterations: ``TRACK_HUBER_ITERATIONS`` Huber, the rest biweight
    prior : (n, m) weights in [0, 1] the robust weights are multiplied by (default 1)

    Returns
    -------
    pred : (n, d) predicted values at dt = 0
    var : (n,) variance of the prediction in units of the noise variance ([(XᵀWX + Λ)⁻¹]₀₀)
    slope : (n, d) first-order coefficient (per second)
    """
    n, m = dt.shape
    powers = np.stack(
        [np.ones_like(dt), dt, dt * dt, dt**3, dt**4], axis=-1
    )  # (n, m, 5): XᵀWX is a Hankel matrix of weighted moments
    base = valid.astype(float) if prior is None else valid * prior
    w = base
    lam = np.diag(ridge)
    hankel = np.array([[0, 1, 2], [1, 2, 3], [2, 3, 4]])
    for it in range(iterations + 1):
        moments = np.sum(powers * w[..., None], axis=1)  # (n, 5)
        a = moments[:, hankel] + lam  # (n, 3, 3)
        wy = w[..., None] * y  # (n, m, d)
        b = np.stack(
            [wy.sum(axis=1), (wy * dt[..., None]).sum(axis=1), (wy * (dt * dt)[..., None]).sum(axis=1)], axis=1
        )  # (n, 3, d)
        inv = _inverse_sym3(a)
        coef = np.einsum("nij,njd->nid", inv, b) if b.shape[2] > 1 else inv @ b  # (n, 3, d)
        if it == iterations:
            break
        resid = y - (
            coef[:, None, 0, :] + dt[..., None] * coef[:, None, 1, :] + (dt * dt)[..., None] * coef[:, None, 2, :]
        )
        z = np.sqrt(np.mean(resid * resid, axis=-1))  # one robust weight per neighbour (all d coordinates together)
        w = base * _robust_weights(z, params.huber_k, params.biweight_c, it)
    return coef[:, 0, :], inv[:, 0, 0], coef[:, 1, :]


def _inverse_sym3(a: FloatArray) -> FloatArray:
    """Inverses of a stack of symmetric positive-definite 3 × 3 matrices (n, 3, 3), by the adjugate:
    a batched LAPACK solve costs ~20× more on such small matrices."""
    p, q, r = a[:, 0, 0], a[:, 0, 1], a[:, 0, 2]
    s, t, u = a[:, 1, 1], a[:, 1, 2], a[:, 2, 2]
    c00, c01, c02 = s * u - t * t, r * t - q * u, q * t - r * s
    c11, c12, c22 = p * u - r * r, q * r - p * t, p * s - q * q
    det = p * c00 + q * c01 + r * c02
    inv = np.stack(
        [np.stack([c00, c01, c02], -1), np.stack([c01, c11, c12], -1), np.stack([c02, c12, c22], -1)], axis=1
    )
    return inv / det[:, None, None]


def pairwise_prediction(dt: FloatArray, y: FloatArray, valid: NDArray[np.bool_]) -> FloatArray:
    """Median over every pair of a frame's neighbours of the line through the pair, at dt = 0.

    A robust, leverage-free prediction (Theil–Sen-like) that one wrong neighbour cannot move:
    it only enters the pairs that contain it.

    Parameters
    ----------
    dt : (n, m) neighbour times relative to the frame; y : (n, m, d) their values; valid : (n, m)

    Returns
    -------
    (n, d) predictions; NaN where a frame has fewer than two neighbours at different times
    """
    m = dt.shape[1]
    j, k = np.triu_indices(m, 1)
    tj, tk = dt[:, j], dt[:, k]
    ok = valid[:, j] & valid[:, k] & (tj != tk)
    frac = np.where(ok, -tj / np.where(ok, tk - tj, 1.0), np.nan)  # (n, P): where dt = 0 lies on the segment j → k
    pred = y[:, j, :] + (y[:, k, :] - y[:, j, :]) * frac[..., None]
    ranked = np.sort(
        np.where(ok[..., None], pred, np.inf), axis=1
    )  # the valid pairs first (a masked median, without np.ma's cost)
    count = ok.sum(axis=1)
    rows = np.arange(len(count))
    lo, hi = np.maximum(count - 1, 0) // 2, np.maximum(count, 1) // 2
    med = 0.5 * (ranked[rows, lo, :] + ranked[rows, hi, :])
    return np.where((count > 0)[:, None], med, np.nan)


def robust_location(
    values: FloatArray, precision: FloatArray, params: TrackParams, iterations: int = C.TRACK_IRLS_ITERATIONS
) -> tuple[FloatArray, FloatArray]:
    """Robust precision-weighted mean of one track's measurements of a constant.

    Parameters
    ----------
    values : (n, d) standardised measurements (value / its noise std)
    precision : (n, d) prior weight of each measurement (1 = one ordinary label)

    Returns
    -------
    weight : (n, d) final weight = precision × robust weight
    mean : (d,) the weighted mean
    """
    mean = np.median(values, axis=0)
    w = precision.copy()
    for it in range(iterations):
        w = precision * _robust_weights((values - mean) * np.sqrt(precision), params.huber_k, params.biweight_c, it)
        total = w.sum(axis=0)
        mean = np.where(total > 0, (w * values).sum(axis=0) / np.maximum(total, 1e-300), mean)
    return w, mean


def track_residuals(
    t: FloatArray,
    centre: FloatArray,
    yaw: FloatArray,
    size: FloatArray,
    noise: TrackNoise,
    params: TrackParams,
    size_evidence: tuple[FloatArray, FloatArray] | None = None,
) -> TrackResiduals:
    """Leave-one-out residuals of every frame of one track against the rest of it.

    Parameters
    ----------
    t : (n,) time in seconds, strictly increasing
    centre : (n, 3) box centres in the world frame (m)
    yaw : (n,) headings in the world frame (rad)
    size : (n, 3) length, width, height (m)
    noise : ordinary per-frame label noise
    size_evidence : optional ((n, 3) sizes fitted to each frame's points, (n, 3) their data
        precision in 1/m², 0 where a frame has no evidence): the points' say in the size posterior
    """
    t = np.asarray(t, dtype=float)
    n = len(t)
    idx, valid = neighbour_index(t, params.window, params.max_neighbours)
    dt = np.where(valid, t[idx] - t[:, None], 0.0)
    v1, a1, w1, wa1 = params.rate_prior

    # A wrong neighbour must not pass its error on (near a track's end it has the most leverage on
    # the extrapolation): the frame that stands out most among its neighbours is left out of their
    # fits, and the fits are redone, until no frame stands out (a few rounds).
    def fit(y: FloatArray, ridge: FloatArray, residual: Any) -> tuple[FloatArray, FloatArray, FloatArray]:
        out = np.zeros(n, dtype=bool)
        # Which of two frames that both stand out is the wrong one: the one a median of pairwise
        # lines through its neighbours (insensitive to one wrong neighbour) disagrees with most.
        pp = pairwise_prediction(dt, y, valid)
        b = np.sqrt(np.sum(np.reshape(np.nan_to_num(residual(pp, np.zeros(n))), (n, -1)) ** 2, axis=1))
        for _ in range(C.TRACK_OUTLIER_ROUNDS):
            use = valid & ~out[idx]
            pred, var, slope = local_fit(dt, y, use, ridge, params)
            z = residual(pred, var)
            a = np.sqrt(np.sum(np.reshape(z, (n, -1)) ** 2, axis=1))
            worst_near = np.where(use, b[idx], 0.0).max(axis=1, initial=0.0)
            new = ((a > params.biweight_c) | (b > params.biweight_c)) & (b >= worst_near) & ~out
            if not new.any():
                break
            out |= new
        return pred, slope, z

    # position: all three coordinates share the robust weights of a neighbour
    sc = np.asarray(noise.centre, dtype=float)
    rel = (centre[idx] - centre[:, None, :]) / sc  # relative to the frame itself: small numbers, same fit
    ridge_c = np.array([C.TRACK_NO_NEIGHBOUR_PRECISION, (sc.min() / v1) ** 2, (sc.min() / a1) ** 2])
    pred_c, slope_c, pos = fit(rel, ridge_c, lambda pred, var: -pred / np.sqrt(1.0 + var)[:, None])  # the label is at 0
    velocity = slope_c[:, :2] * sc[:2]

    # heading: neighbours unwrapped around their circular mean, so flips are residuals of ±π
    ny = yaw[idx]
    s, c = np.where(valid, np.sin(ny), 0.0).sum(axis=1), np.where(valid, np.cos(ny), 0.0).sum(axis=1)
    ref = np.where((s != 0) | (c != 0), np.arctan2(s, c), yaw)
    d = normalize_angle(ny - ref[:, None])[..., None] / noise.yaw
    ridge_y = np.array([C.TRACK_NO_NEIGHBOUR_PRECISION, (noise.yaw / w1) ** 2, (noise.yaw / wa1) ** 2])
    pred_y, _, head = fit(
        d,
        ridge_y,
        lambda pred, var: normalize_angle(yaw - (ref + pred[:, 0] * noise.yaw)) / noise.yaw / np.sqrt(1.0 + var),
    )

    # size: one rigid size; labels and (optionally) the points' fitted sizes
    ss = np.asarray(noise.size, dtype=float)
    lab = size / ss
    prec = np.ones_like(lab)
    if size_evidence is not None:
        fit, data_prec = size_evidence
        fit = np.where(np.isfinite(fit), fit, size) / ss
        data_prec = np.where(np.isfinite(data_prec), np.maximum(data_prec, 0.0), 0.0) * ss * ss  # in units of one label
        values = np.concatenate([lab, fit])
        precision = np.concatenate([prec, data_prec])
    else:
        values, precision = lab, prec
    w, mean = robust_location(values, precision, params)
    total = w.sum(axis=0)
    wl = w[:n]
    loo_total = np.maximum(total - wl, 1e-12)
    loo_mean = ((w * values).sum(axis=0) - wl * lab) / loo_total
    size_z = (lab - loo_mean) / np.sqrt(1.0 + 1.0 / loo_total)
    size_std = ss / np.sqrt(np.maximum(total, 1e-12))
    weight = np.where(prec > 0, wl / prec, 0.0).min(axis=1)
    expected = np.concatenate(
        [centre + pred_c * sc, loo_mean * ss, normalize_angle(ref + pred_y[:, 0] * noise.yaw)[:, None]], axis=1
    )
    return TrackResiduals(size_z, pos, head, mean * ss, size_std, weight, velocity, expected)


def error_probability(q: FloatArray, dims: int, params: TrackParams) -> FloatArray:
    """Posterior probability that a label is wrong given its squared standardised residual ``q``.

    A right label: z ~ N(0, I_d); a wrong one: z ~ N(0, k² I_d), prior π. The log odds are
    logit π − d·ln k + q/2 · (1 − 1/k²): monotone in q, 0.5 where q = 2·(d ln k − logit π)/(1 − 1/k²).
    """
    k, p = params.error_scale, params.error_prior
    log_odds = math.log(p / (1.0 - p)) - dims * math.log(k) + 0.5 * np.asarray(q, dtype=float) * (1.0 - 1.0 / (k * k))
    return 1.0 / (1.0 + np.exp(-np.clip(log_odds, -700.0, 700.0)))


def kind_scores(res: TrackResiduals, params: TrackParams, size_dims: int = 3) -> FloatArray:
    """(n, 3) probability of each kind of contradiction (:data:`ISSUES` order: size, heading, position).

    ``size_dims``: 2 judges length and width only (a BEV run whose heights are not labelled).
    """
    q_size = np.sum(res.size[:, :size_dims] ** 2, axis=1)
    q_head = res.heading**2
    q_pos = np.sum(res.position**2, axis=1)
    return np.stack(
        [
            error_probability(q_size, size_dims, params),
            error_probability(q_head, 1, params),
            error_probability(q_pos, 3, params),
        ],
        axis=1,
    )


def issue_of(scores: FloatArray, threshold: float) -> list[str]:
    """Per frame the kind with the highest probability when it reaches ``threshold``, else ``none``."""
    best = np.argmax(scores, axis=1)
    top = scores[np.arange(len(scores)), best]
    return [ISSUES[b] if s >= threshold else "none" for b, s in zip(best, top)]


def to_frame(world_boxes: FloatArray, box: FloatArray, world_box: FloatArray) -> FloatArray:
    """Boxes of the world frame moved into the LiDAR/vehicle frame of the frame a label belongs to.

    The frame's pose comes from the label itself (the same box in both frames): heading
    ψ = world_yaw − yaw, BEV shift t = world_c − R(ψ)·c, height shift world_cz − cz.

    Parameters
    ----------
    world_boxes : (N, 7) boxes in the world frame (cx, cy, cz, length, width, height, yaw)
    box : (N, 7) or (7,) the label in its frame (the objects table's ``cx … yaw``)
    world_box : (N, 4) or (4,) the same label in the world frame (``world_cx, world_cy, world_cz, world_yaw``)

    Returns
    -------
    (N, 7) the boxes in the label's frame, sizes unchanged, yaw in [-π, π)
    """
    w = np.atleast_2d(np.asarray(world_boxes, dtype=float))
    b = np.broadcast_to(np.asarray(box, dtype=float), (len(w), 7))
    wb = np.broadcast_to(np.asarray(world_box, dtype=float), (len(w), 4))
    psi = wb[:, 3] - b[:, 6]
    c, s = np.cos(psi), np.sin(psi)
    # The label's world centre minus its frame centre rotated by ψ is the frame's origin in the world.
    ox = wb[:, 0] - (c * b[:, 0] - s * b[:, 1])
    oy = wb[:, 1] - (s * b[:, 0] + c * b[:, 1])
    dx, dy = w[:, 0] - ox, w[:, 1] - oy
    out = w.copy()
    out[:, 0] = c * dx + s * dy
    out[:, 1] = -s * dx + c * dy
    out[:, 2] = w[:, 2] - (wb[:, 2] - b[:, 2])
    out[:, 6] = normalize_angle(w[:, 6] - psi)
    return out

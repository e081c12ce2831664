"""Label uncertainty as training targets: detector encodings, their covariances, σ_p sources, KLD loss.

This module owns the mathematics of ``labelaudit export`` (docs/training.md): the regression
targets detectors use (``box``, ``log-size``/``centerpoint``, ``pixor``, ``residual``), the first-order
propagation of a box covariance to those targets with the exact Jacobian at the label, the
Jacobian of the reported box parameters with respect to φ (to start from the posterior covariance
of the paper's model), the heuristic sources of σ_p the paper compares against ("num points",
"convex hull") and fixed values, and a NumPy reference of the KL-divergence loss with its gradient.
It does no I/O: reading results and writing Parquet or infos files is :mod:`labelaudit.export`'s.

Box parameters are always ``y = (cx, cy, cz, l, w, h, yaw)`` (LiDAR frame, geometric centre,
:data:`labelaudit.core.params.BOX_FIELDS`); arrays of boxes have shape (N, 7).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C

FloatArray = NDArray[np.float64]

__all__ = [
    "BOX_PARAMS",
    "ENCODINGS",
    "GLENET_TARGETS",
    "Encoding",
    "VarianceSource",
    "available_params",
    "box_covariance_from_phi",
    "box_jacobian",
    "encode",
    "encoding_jacobian",
    "fixed_target_covariance",
    "gaussian_nll",
    "get_encoding",
    "glenet_variances",
    "heuristic_box_covariance",
    "hull_iou_scale",
    "kld_loss",
    "kld_loss_grad",
    "num_points_scale",
    "parse_source",
    "prior_box_variance",
    "propagate",
    "target_std",
]

BOX_PARAMS: tuple[str, ...] = ("cx", "cy", "cz", "l", "w", "h", "yaw")
"""Short names of the 7 box parameters, in the order of ``y``."""

_CX, _CY, _CZ, _L, _W, _H, _YAW = range(7)


@dataclass(frozen=True)
class Encoding:
    """One detector's regression targets.

    Attributes
    ----------
    name : the ``--encoding`` value
    targets : target names in the detector's order; export columns are ``std_<target>``
    uses : per target, the box parameters (indices into :data:`BOX_PARAMS`) it depends on
    angular : targets that are angles (differences are taken modulo 2π)
    needs_anchor : the targets are relative to an anchor box whose size enters the variance
    """

    name: str
    targets: tuple[str, ...]
    uses: tuple[tuple[int, ...], ...]
    angular: frozenset[str]
    needs_anchor: bool = False

    @property
    def size(self) -> int:
        """Number of targets T."""
        return len(self.targets)

    def depends(self) -> NDArray[np.bool_]:
        """(T, 7) mask: target t depends on box parameter k."""
        m = np.zeros((self.size, 7), dtype=bool)
        for t, ks in enumerate(self.uses):
            m[t, list(ks)] = True
        return m


ENCODINGS: dict[str, Encoding] = {
    "box": Encoding(
        "box",
        ("x", "y", "z", "l", "w", "h", "yaw"),
        ((_CX,), (_CY,), (_CZ,), (_L,), (_W,), (_H,), (_YAW,)),
        frozenset({"yaw"}),
    ),
    "log-size": Encoding(
        "log-size",
        ("x", "y", "z", "log_l", "log_w", "log_h", "sin_yaw", "cos_yaw"),
        ((_CX,), (_CY,), (_CZ,), (_L,), (_W,), (_H,), (_YAW,), (_YAW,)),
        frozenset(),
    ),
    "pixor": Encoding(
        "pixor",
        ("dx", "dy", "log_l", "log_w", "sin_yaw", "cos_yaw"),
        ((_CX,), (_CY,), (_L,), (_W,), (_YAW,), (_YAW,)),
        frozenset(),
    ),
    # OpenPCDet ResidualCoder / mmdet3d DeltaXYZWLHRBBoxCoder (code size 7), named as OpenPCDet's
    # encode_torch names them.
    "residual": Encoding(
        "residual",
        ("xt", "yt", "zt", "dxt", "dyt", "dzt", "rt"),
        ((_CX,), (_CY,), (_CZ,), (_L,), (_W,), (_H,), (_YAW,)),
        frozenset({"rt"}),
        needs_anchor=True,
    ),
}
"""The supported encodings; ``centerpoint`` is an alias of ``log-size``."""

ENCODING_ALIASES = {"centerpoint": "log-size"}


def get_encoding(name: str | Encoding) -> Encoding:
    """The :class:`Encoding` called ``name`` (``centerpoint`` = ``log-size``).

    Raises
    ------
    ValueError
        Unknown name; the message lists the valid ones.
    """
    if isinstance(name, Encoding):
        return name
    key = ENCODING_ALIASES.get(name, name)
    if key not in ENCODINGS:
        valid = ", ".join([*ENCODINGS, *ENCODING_ALIASES])
        raise ValueError(f"unknown encoding {name!r}; expected one of {valid}")
    return ENCODINGS[key]


def _boxes(boxes: ArrayLike) -> FloatArray:
    b = np.asarray(boxes, dtype=float)
    if b.ndim != 2 or b.shape[1] != 7:
        raise ValueError(f"boxes must be an (N, 7) array (cx, cy, cz, l, w, h, yaw), got shape {b.shape}")
    return b


def _anchor_sizes(anchor_sizes: ArrayLike | None, n: int) -> FloatArray:
    if anchor_sizes is None:
        raise ValueError("the residual encoding needs anchor sizes (N, 3): l, w, h of each object's anchor")
    a = np.asarray(anchor_sizes, dtype=float)
    a = np.broadcast_to(a, (n, 3)) if a.shape == (3,) else a
    if a.shape != (n, 3):
        raise ValueError(f"anchor sizes must have shape ({n}, 3) or (3,), got {a.shape}")
    return a


# ----------------------------------------------------------------------------------------------
# Encodings and their Jacobians
# ----------------------------------------------------------------------------------------------


def encode(
    boxes: ArrayLike,
    encoding: str | Encoding,
    *,
    anchors: ArrayLike | None = None,
    reference: ArrayLike | None = None,
) -> FloatArray:
    """Regression targets of boxes in an encoding (the map whose covariance :func:`propagate` gives).

    Parameters
    ----------
    boxes : (N, 7) boxes (cx, cy, cz, l, w, h, yaw)
    encoding : encoding name or object
    anchors : (N, 7) or (7,) anchor boxes (centre-based, like the boxes), ``residual`` only
    reference : (N, 2) or (2,) BEV point the ``pixor`` offsets are taken from (its pixel centre);
        default the origin. It does not change the variance.

    Returns
    -------
    targets : (N, T)

    Examples
    --------
    >>> encode([[10.0, 2.0, -1.0, 4.0, 1.6, 1.5, 0.0]], "log-size").round(3)
    array([[10.   ,  2.   , -1.   ,  1.386,  0.47 ,  0.405,  0.   ,  1.   ]])
    """
    enc = get_encoding(encoding)
    b = _boxes(boxes)
    x, y, z, l, w, h, yaw = b.T
    if enc.name == "box":
        return b.copy()
    if enc.name == "log-size":
        return np.stack([x, y, z, np.log(l), np.log(w), np.log(h), np.sin(yaw), np.cos(yaw)], axis=1)
    if enc.name == "pixor":
        ref = np.zeros(2) if reference is None else np.asarray(reference, dtype=float)
        ref = np.broadcast_to(ref, (len(b), 2))
        return np.stack([x - ref[:, 0], y - ref[:, 1], np.log(l), np.log(w), np.sin(yaw), np.cos(yaw)], axis=1)
    if anchors is None:
        raise ValueError("the residual encoding needs anchor boxes (N, 7)")
    a = np.broadcast_to(np.asarray(anchors, dtype=float), b.shape)
    xa, ya, za, la, wa, ha, ra = a.T
    diag = np.hypot(la, wa)
    return np.stack(
        [(x - xa) / diag, (y - ya) / diag, (z - za) / ha, np.log(l / la), np.log(w / wa), np.log(h / ha), yaw - ra],
        axis=1,
    )


def encoding_jacobian(boxes: ArrayLike, encoding: str | Encoding, anchor_sizes: ArrayLike | None = None) -> FloatArray:
    """Exact Jacobian ∂t/∂y of an encoding at each box.

    Parameters
    ----------
    boxes : (N, 7)
    encoding : encoding name or object
    anchor_sizes : (N, 3) or (3,) anchor l, w, h (``residual`` only; the anchor's position and
        yaw are constants of the encoding and do not enter the Jacobian)

    Returns
    -------
    J : (N, T, 7)
    """
    enc = get_encoding(encoding)
    b = _boxes(boxes)
    n = len(b)
    J = np.zeros((n, enc.size, 7))
    l, w, h, yaw = b[:, _L], b[:, _W], b[:, _H], b[:, _YAW]
    if enc.name == "box":
        J[:] = np.eye(7)
    elif enc.name == "log-size":
        J[:, 0, _CX] = J[:, 1, _CY] = J[:, 2, _CZ] = 1.0
        J[:, 3, _L], J[:, 4, _W], J[:, 5, _H] = 1.0 / l, 1.0 / w, 1.0 / h
        J[:, 6, _YAW], J[:, 7, _YAW] = np.cos(yaw), -np.sin(yaw)
    elif enc.name == "pixor":
        J[:, 0, _CX] = J[:, 1, _CY] = 1.0
        J[:, 2, _L], J[:, 3, _W] = 1.0 / l, 1.0 / w
        J[:, 4, _YAW], J[:, 5, _YAW] = np.cos(yaw), -np.sin(yaw)
    else:  # residual
        a = _anchor_sizes(anchor_sizes, n)
        diag = np.hypot(a[:, 0], a[:, 1])
        J[:, 0, _CX], J[:, 1, _CY], J[:, 2, _CZ] = 1.0 / diag, 1.0 / diag, 1.0 / a[:, 2]
        J[:, 3, _L], J[:, 4, _W], J[:, 5, _H] = 1.0 / l, 1.0 / w, 1.0 / h
        J[:, 6, _YAW] = 1.0
    return J


# ----------------------------------------------------------------------------------------------
# From the posterior covariance on φ to the box parameters
# ----------------------------------------------------------------------------------------------


def available_params(model: Literal["bev", "3d"]) -> NDArray[np.bool_]:
    """(7,) mask of the box parameters a model infers: BEV has no cz and h."""
    if model not in ("bev", "3d"):
        raise ValueError(f"model must be 'bev' or '3d', got {model!r}")
    m = np.ones(7, dtype=bool)
    if model == "bev":
        m[[_CZ, _H]] = False
    return m


def box_jacobian(boxes: ArrayLike, model: Literal["bev", "3d"]) -> FloatArray:
    """Jacobian ∂y/∂φ of the reported box parameters at rectangular boxes, vectorised.

    φ is BEV ``(c1, c2, l·cos, l·sin, w·cos, w·sin)`` or 3D ``(c1, c2, c3, l·cos, l·sin, w·cos,
    w·sin, h)`` (docs/method.md). The reported yaw of a parallelogram is the mean direction of its
    two axes, so its row is half the sum of the two axis-angle rows — the same map as
    :func:`labelaudit.core.geometry.box_param_jacobian`, whose rows it equals (cz and h rows are zero
    for BEV, where φ does not hold them).

    Returns
    -------
    K : (N, 7, 6) for BEV or (N, 7, 8) for 3D
    """
    b = _boxes(boxes)
    if model not in ("bev", "3d"):
        raise ValueError(f"model must be 'bev' or '3d', got {model!r}")
    three_d = model == "3d"
    p = 8 if three_d else 6
    o = 1 if three_d else 0  # φ index offset of the in-plane terms
    c, s = np.cos(b[:, _YAW]), np.sin(b[:, _YAW])
    l, w = b[:, _L], b[:, _W]
    K = np.zeros((len(b), 7, p))
    K[:, _CX, 0] = K[:, _CY, 1] = 1.0
    if three_d:
        K[:, _CZ, 2] = 1.0
        K[:, _H, 7] = 1.0
    K[:, _L, 2 + o], K[:, _L, 3 + o] = c, s
    K[:, _W, 4 + o], K[:, _W, 5 + o] = c, s
    K[:, _YAW, 2 + o], K[:, _YAW, 3 + o] = -0.5 * s / l, 0.5 * c / l
    K[:, _YAW, 4 + o], K[:, _YAW, 5 + o] = -0.5 * s / w, 0.5 * c / w
    return K


def box_covariance_from_phi(boxes: ArrayLike, cov_phi: ArrayLike, model: Literal["bev", "3d"]) -> FloatArray:
    """Covariance of y from the posterior covariance of φ: ``K Σ Kᵀ`` at each label.

    Parameters
    ----------
    boxes : (N, 7)
    cov_phi : (N, p, p) with p = 6 (BEV) or 8 (3D)

    Returns
    -------
    cov_y : (N, 7, 7); rows and columns of cz and h are zero for BEV (not inferred: see
        :func:`available_params`)
    """
    K = box_jacobian(boxes, model)
    S = np.asarray(cov_phi, dtype=float)
    if S.shape != (len(K), K.shape[2], K.shape[2]):
        raise ValueError(
            f"cov_phi must have shape ({len(K)}, {K.shape[2]}, {K.shape[2]}) for model {model!r}, got {S.shape}"
        )
    out = K @ S @ np.swapaxes(K, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def propagate(
    boxes: ArrayLike,
    cov_box: ArrayLike,
    encoding: str | Encoding,
    *,
    anchor_sizes: ArrayLike | None = None,
    available: ArrayLike | None = None,
) -> FloatArray:
    """First-order (delta-method) covariance of the encoded targets: ``J Σ_y Jᵀ`` with J exact at the label.

    Parameters
    ----------
    boxes : (N, 7) the labels (the mean of the label distribution)
    cov_box : (N, 7, 7) covariance of y
    encoding : encoding name or object
    anchor_sizes : (N, 3) or (3,), ``residual`` only
    available : (7,) or (N, 7) mask of the box parameters ``cov_box`` really holds; targets that
        depend on a missing one get NaN rows and columns (e.g. z and h of a BEV model)

    Returns
    -------
    cov : (N, T, T)

    Notes
    -----
    The approximation is first order: a target whose derivative vanishes at the label (sin yaw at
    yaw = ±π/2, cos yaw at 0 or ±π) gets variance 0, while its exact variance under a Gaussian yaw
    of std s is of order s⁴/2. The sin/cos pair as a whole keeps its variance s² (docs/training.md).
    """
    enc = get_encoding(encoding)
    b = _boxes(boxes)
    S = np.asarray(cov_box, dtype=float)
    if S.shape != (len(b), 7, 7):
        raise ValueError(f"cov_box must have shape ({len(b)}, 7, 7), got {S.shape}")
    J = encoding_jacobian(b, enc, anchor_sizes)
    out = J @ S @ np.swapaxes(J, 1, 2)
    out = 0.5 * (out + np.swapaxes(out, 1, 2))
    if available is not None:
        avail = np.broadcast_to(np.asarray(available, dtype=bool), (len(b), 7))
        missing = (enc.depends()[None, :, :] & ~avail[:, None, :]).any(axis=2)  # (N, T)
        if missing.any():
            out[missing[:, :, None] | missing[:, None, :]] = np.nan
    return out


def target_std(cov: ArrayLike) -> FloatArray:
    """Per-target std, the square root of the diagonal: (N, T, T) → (N, T) (NaN stays NaN)."""
    d = np.diagonal(np.asarray(cov, dtype=float), axis1=1, axis2=2)
    return np.sqrt(np.clip(d, 0.0, None))


GLENET_TARGETS: tuple[str, ...] = ("xt", "yt", "zt", "dxt", "dyt", "dzt", "sin_rt")
"""The seven label variances GLENet's training reads, in its order: OpenPCDet's ResidualCoder
deltas with the heading residual as the sine of the difference (GLENet's loss compares headings
by ``sin(a − b)``)."""


def glenet_variances(boxes: ArrayLike, cov_box: ArrayLike, anchor_sizes: ArrayLike) -> FloatArray:
    """Variances of GLENet's seven targets (:data:`GLENET_TARGETS`) from the covariance of y.

    With the anchor of the object's class (l_a, w_a, h_a), d = √(l_a² + w_a²) and the label as
    the mean (docs/training.md)::

        Var(xt) = Σ_xx / d²      Var(yt) = Σ_yy / d²      Var(zt) = Σ_zz / h_a²
        Var(dxt) = Σ_ll / l²     Var(dyt) = Σ_ww / w²     Var(dzt) = Σ_hh / h²
        Var(sin Δθ) = ½ (1 − exp(−2 Σ_θθ))

    x, y, z on the LiDAR axes. The first six are the delta method's (first order, the
    :func:`propagate` of the ``residual`` encoding); the last is exact for a Gaussian Δθ with mean
    0 (E sin Δθ = 0, E sin² Δθ = (1 − E cos 2Δθ)/2), equal to Σ_θθ to first order and never above
    ½, as a sample variance of sines.

    Parameters
    ----------
    boxes : (N, 7) the labels
    cov_box : (N, 7, 7) covariance of y, every parameter present
    anchor_sizes : (N, 3) or (3,) anchor l, w, h

    Returns
    -------
    var : (N, 7)
    """
    cov = propagate(boxes, cov_box, "residual", anchor_sizes=anchor_sizes)
    var = np.diagonal(cov, axis1=1, axis2=2).copy()
    var[:, 6] = -0.5 * np.expm1(-2.0 * var[:, 6])
    return var


# ----------------------------------------------------------------------------------------------
# Sources of σ_p
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VarianceSource:
    """Where σ_p comes from: ``model`` (posterior), ``num_points``, ``hull_iou`` or ``fixed`` (value = the variance)."""

    kind: Literal["model", "num_points", "hull_iou", "fixed"]
    value: float | None = None

    def __str__(self) -> str:
        return f"fixed:{self.value:g}" if self.kind == "fixed" else self.kind


def parse_source(text: str) -> VarianceSource:
    """Parse ``model``, ``num_points``, ``hull_iou`` or ``fixed:VAR`` (VAR > 0, in target units squared).

    Raises
    ------
    ValueError
        Anything else; the message lists the accepted forms.
    """
    t = text.strip()
    alias = {"num-points": "num_points", "hull-iou": "hull_iou"}
    t = alias.get(t, t)
    if t in ("model", "num_points", "hull_iou"):
        return VarianceSource(t)  # type: ignore[arg-type]
    if t.startswith("fixed:"):
        try:
            v = float(t[6:])
        except ValueError:
            v = float("nan")
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"fixed:VAR needs a finite variance > 0, got {t[6:]!r}")
        return VarianceSource("fixed", v)
    raise ValueError(f"unknown source {text!r}; expected model, num_points, hull_iou or fixed:VAR (e.g. fixed:0.01)")


def prior_box_variance(prior_std: ArrayLike, weight: float = 1.0) -> FloatArray:
    """Variance of y under the class prior: ``std² / w`` per parameter, (N, 7) → (N, 7).

    ``prior_std`` columns are (centre, centre, centre, length, width, height, yaw) std — the
    :class:`labelaudit.config.ClassPrior` entries. Propagated from the extended parameters to y
    the model's prior Σ0 is exactly this diagonal (the yaw row averages the two axis angles, whose
    covariance is built so that their mean has the class yaw std; docs/method.md).
    """
    if not weight > 0:
        raise ValueError(f"prior weight must be > 0, got {weight}")
    s = np.asarray(prior_std, dtype=float)
    if s.ndim != 2 or s.shape[1] != 7:
        raise ValueError(f"prior std must be an (N, 7) array, got shape {s.shape}")
    return np.square(s) / weight


def num_points_scale(num_points: ArrayLike, half: float = C.HEURISTIC_NUM_POINTS_HALF) -> FloatArray:
    """ "num points" heuristic: variance factor ``n0 / (n0 + n)`` — 1 without points, ∝ 1/n for many."""
    n = np.asarray(num_points, dtype=float)
    if np.any(n < 0):
        raise ValueError("num_points must be ≥ 0")
    return half / (half + n)


def hull_iou_scale(hull_iou: ArrayLike, floor: float = C.HEURISTIC_HULL_IOU_FLOOR) -> FloatArray:
    """ "convex hull" heuristic: variance factor ``max(1 − IoU, floor)`` — 1 without a hull, small when the hull fills the box."""
    iou = np.asarray(hull_iou, dtype=float)
    if np.any((iou < 0) | (iou > 1)):
        raise ValueError("hull_iou must be in [0, 1]")
    return np.maximum(1.0 - iou, floor)


def heuristic_box_covariance(prior_var: ArrayLike, scale: ArrayLike) -> FloatArray:
    """Diagonal covariance of y for a heuristic source: ``diag(prior_var) · scale``.

    Parameters
    ----------
    prior_var : (N, 7) from :func:`prior_box_variance`
    scale : (N,) from :func:`num_points_scale` or :func:`hull_iou_scale`

    Returns
    -------
    cov_y : (N, 7, 7)
    """
    v = np.asarray(prior_var, dtype=float) * np.asarray(scale, dtype=float)[:, None]
    out = np.zeros(v.shape + (7,))
    idx = np.arange(7)
    out[:, idx, idx] = v
    return out


def fixed_target_covariance(n: int, encoding: str | Encoding, variance: float) -> FloatArray:
    """``variance · I`` for every object and target: (n, T, T) (the paper's constant-σ_p baseline)."""
    enc = get_encoding(encoding)
    return np.broadcast_to(np.eye(enc.size) * float(variance), (n, enc.size, enc.size)).copy()


# ----------------------------------------------------------------------------------------------
# KL-divergence loss (reference implementation)
# ----------------------------------------------------------------------------------------------


def _kld_parts(pred_mean: ArrayLike, pred_log_var: ArrayLike, target: ArrayLike, target_var: ArrayLike):
    mu_q = np.asarray(pred_mean, dtype=float)
    s = np.asarray(pred_log_var, dtype=float)
    mu_p = np.asarray(target, dtype=float)
    var_p = np.asarray(target_var, dtype=float)
    if np.any(var_p < 0):
        raise ValueError("target_var must be ≥ 0")
    return mu_q, s, mu_p, var_p


def kld_loss(
    pred_mean: ArrayLike,
    pred_log_var: ArrayLike,
    target: ArrayLike,
    target_var: ArrayLike,
    *,
    include_constant: bool = True,
) -> FloatArray:
    """KL(p‖q) between the label distribution p = N(target, target_var) and the prediction q = N(pred_mean, exp(pred_log_var)).

    Element-wise (one univariate Gaussian per target; sum over targets for the paper's diagonal
    loss)::

        KL = ½ [ s − log σ_p² + (σ_p² + (μ_p − μ_q)²) e^{−s} − 1 ],   s = log σ_q²

    Parameters
    ----------
    pred_mean, pred_log_var : the prediction's mean and log variance (broadcastable arrays)
    target, target_var : the label (mean) and its variance σ_p² ≥ 0
    include_constant : keep ``−½ (log σ_p² + 1)``, the part that does not depend on the
        prediction. With False the loss is ``½ [s + (σ_p² + (μ_p − μ_q)²) e^{−s}]``, finite at
        σ_p² = 0 where it equals :func:`gaussian_nll` minus ½ log 2π; the gradient is the same.

    Returns
    -------
    loss : array of the broadcast shape (nats)

    Raises
    ------
    ValueError
        A negative target variance, or a zero one with ``include_constant=True`` (KL is infinite).

    See Also
    --------
    kld_loss_grad, gaussian_nll
    """
    mu_q, s, mu_p, var_p = _kld_parts(pred_mean, pred_log_var, target, target_var)
    core = 0.5 * (s + (var_p + np.square(mu_p - mu_q)) * np.exp(-s))
    if not include_constant:
        return core
    if np.any(var_p == 0):
        raise ValueError("target_var = 0 makes the KL divergence infinite; use include_constant=False (the NLL limit)")
    return core - 0.5 * (np.log(var_p) + 1.0)


def kld_loss_grad(
    pred_mean: ArrayLike, pred_log_var: ArrayLike, target: ArrayLike, target_var: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Gradient of :func:`kld_loss` with respect to the prediction.

    Returns
    -------
    d_mean : ``(μ_q − μ_p) e^{−s}``
    d_log_var : ``½ [1 − (σ_p² + (μ_p − μ_q)²) e^{−s}]``
    """
    mu_q, s, mu_p, var_p = _kld_parts(pred_mean, pred_log_var, target, target_var)
    inv = np.exp(-s)
    return (mu_q - mu_p) * inv, 0.5 * (1.0 - (var_p + np.square(mu_p - mu_q)) * inv)


def gaussian_nll(pred_mean: ArrayLike, pred_log_var: ArrayLike, target: ArrayLike) -> FloatArray:
    """Negative log-likelihood of ``target`` under N(pred_mean, exp(pred_log_var)): the loss KLD replaces."""
    mu_q = np.asarray(pred_mean, dtype=float)
    s = np.asarray(pred_log_var, dtype=float)
    d = np.asarray(target, dtype=float) - mu_q
    return 0.5 * (math.log(2.0 * math.pi) + s + np.square(d) * np.exp(-s))

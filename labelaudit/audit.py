"""Per-object audit: run the label model on one box and return the model columns of a result row.

This is the one function the pipeline calls per object (DESIGN.md §7); it never touches files.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from labelaudit import geometry as g
from labelaudit.config import RunConfig
from labelaudit.model import fit_label, hull_iou, infer_label
from labelaudit.spatial import jiou_gt

MODEL_COLUMNS: tuple[str, ...] = (
    "status",
    "num_points",
    "sigma",
    "jiou_gt",
    "label_error",
    "sigma_hat",
    "fit_offset_m",
    "corner_tv",
    "std_cx",
    "std_cy",
    "std_cz",
    "std_length",
    "std_width",
    "std_height",
    "std_yaw",
    "cov",
    "cov_dim",
    "model",
    "fit_cx",
    "fit_cy",
    "fit_cz",
    "fit_length",
    "fit_width",
    "fit_height",
    "fit_yaw",
    "hull_iou",
    "mahalanobis",
)
"""Keys of the dictionary returned by :func:`audit_object`."""


def audit_object(
    box: ArrayLike,
    points: ArrayLike | None,
    class_name: str,
    cfg: RunConfig,
    sensor_origin: ArrayLike = (0.0, 0.0, 0.0),
    *,
    fit_points: ArrayLike | None = None,
) -> dict[str, Any]:
    """Audit one labeled box against its LiDAR points.

    Parameters
    ----------
    box : (7,) labeled box (cx, cy, cz, l, w, h, yaw), LiDAR/vehicle frame.
    points : (N, ≥3) the box's cropped points (x, y, z, ...), or None / empty.
    class_name : selects the prior.
    cfg : run configuration (``cfg.model``, ``cfg.spatial``).
    sensor_origin : (3,) sensor position in the same frame (orders the corners, C1 nearest).
    fit_points : optional (M, ≥3) points of a *wider* crop for the label-error fit (a box shifted
        off its object loses, in its own crop, the points that would show it; ≈ 0.5 m margin
        recommended, docs/label-error.md). Default: ``points``.

    Returns
    -------
    dict with the keys of :data:`MODEL_COLUMNS`:
        ``status`` "no_points" (0 points: prior-only posterior), "few_points" (fewer than
        ``cfg.model.min_points``) or "ok"; ``num_points``; ``sigma`` (noise std used, m);
        ``jiou_gt``; ``sigma_hat`` (per-object EM residual at the label, NaN below 2 points);
        ``corner_tv`` (4 floats, m², C1 first); ``std_cx`` … ``std_yaw`` (NaN for cz/height in BEV);
        ``cov`` (row-major flattened φ covariance), ``cov_dim`` (6 BEV, 8 3D); ``model``.
        Label error (:func:`labelaudit.model.fit_label`, docs/label-error.md): ``label_error`` in
        [0, 1] (higher = more likely wrong), ``fit_cx`` … ``fit_yaw`` the suggested box (3D fit;
        written in the form nearest the label), ``fit_offset_m`` (BEV centre offset, m),
        ``mahalanobis`` (label vs suggested box, in posterior std); baseline ``hull_iou`` (BEV IoU
        of the box and the convex hull of its points; 0 below 3 points).

    Raises
    ------
    ValueError
        Invalid box (non-positive size, non-finite values) or malformed points.
    """
    y = g.validate_box(box)
    post = infer_label(y, points, class_name, cfg.model, sensor_origin)
    n = post.num_points
    if n == 0:
        status = "no_points"
    elif n < cfg.model.min_points:
        status = "few_points"
    else:
        status = "ok"
    fit = fit_label(y, points if fit_points is None else fit_points, class_name, cfg.model)
    row: dict[str, Any] = {
        "status": status,
        "num_points": int(n),
        "sigma": float(post.sigma),
        "jiou_gt": float(jiou_gt(post, cfg.spatial)),
        "label_error": float(fit.label_error),
        "sigma_hat": float(post.sigma_hat),
        "fit_offset_m": float(np.hypot(*(fit.box[:2] - y[:2]))),
        "corner_tv": [float(v) for v in post.corner_tv],
    }
    for name in g.BOX_FIELDS:
        row[f"std_{name}"] = float(post.std_box[name])
    row["cov"] = [float(v) for v in np.asarray(post.cov).ravel()]
    row["cov_dim"] = int(post.cov.shape[0])
    row["model"] = post.model
    for name, value in zip(g.BOX_FIELDS, fit.box):
        row[f"fit_{name}"] = float(value)
    if fit.model == "bev":  # points without z: the fit does not touch cz and height
        row["fit_cz"] = row["fit_height"] = float("nan")
    row["hull_iou"] = hull_iou(y, points)
    row["mahalanobis"] = float(fit.mahalanobis)
    return row

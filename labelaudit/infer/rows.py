"""Frame → result rows: the one place a row of the objects table is built.

:func:`audit_object` runs the label model on one box and returns the model columns of its row
(:data:`labelaudit.results.MODEL_COLUMNS`); :func:`process_frame` crops every selected box of a
:class:`~labelaudit.datasets.Frame`, adds the identity, box and dataset-extra columns and returns
normalised rows. Pure functions: no files, no printing; the columns themselves are defined in
:mod:`labelaudit.results`.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.config import ALL_CLASSES, RunConfig
from labelaudit.core import geometry as g
from labelaudit.core.fit import fit_label_valid
from labelaudit.core.freespace import ray_counts
from labelaudit.core.iou import hull_iou_valid
from labelaudit.core.posterior import bev_label_scores, box_prior_terms, box_prior_terms_bev_3d, infer_label_valid
from labelaudit.core.spatial import jiou_gt
from labelaudit.datasets import Frame
from labelaudit.errors import one_line
from labelaudit.infer.evidence import ObjectEvidence, fit_free_space, frame_evidence

DIFFICULTY_NAMES = {0: "Easy", 1: "Moderate", 2: "Hard"}
_FLOAT_TYPE = frozenset((float,))


# --------------------------------------------------------------------------- layer 1: one frame


def check_finite(result: dict[str, Any]) -> None:
    """Raise ``FloatingPointError`` when the model's JIoU-GT or covariance came out NaN/inf (an
    overflow on extreme but valid input): the object gets status ``error`` instead of NaN scores."""
    jiou = result.get("jiou_gt")
    cov = result.get("cov")
    if cov is None:
        cov_ok = True
    elif type(cov) is list and set(map(type, cov)) <= _FLOAT_TYPE:  # audit_object's flat list: no NumPy round trip
        # a finite sum has only finite terms (a NaN or ±inf term makes it NaN or ±inf); only a sum
        # that overflowed needs the terms one by one
        cov_ok = math.isfinite(sum(cov)) or all(map(math.isfinite, cov))
    else:
        cov_ok = bool(np.all(np.isfinite(cov)))
    if (jiou is not None and not math.isfinite(jiou)) or not cov_ok:
        raise FloatingPointError(f"non-finite model output (jiou_gt={jiou}, covariance finite: {cov_ok})")


def _usable(v: list[float]) -> bool:
    """Whether a label's 7 values (Python floats) make a box: :func:`~labelaudit.core.geometry.validate_box`'s
    test (finite, length, width and height > 0), also :func:`~labelaudit.infer.evidence.label_boxes`' rule."""
    return all(map(math.isfinite, v)) and v[3] > 0 and v[4] > 0 and v[5] > 0


def label_where(frame: Frame, i: int) -> str:
    """Where label ``i`` of ``frame`` was read: ``<label file>:<line>`` (KITTI) or the frame's source file."""
    lines = frame.extras.get("label_line")
    source = frame.source or f"frame {frame.frame_id}"
    return f"{source}:{int(lines[i])}" if lines is not None and frame.source else source


def frame_note(
    frame_id: str | None,
    unit: str,
    message: str,
    level: str = "error",
    file: str | None = None,
    line: int | None = None,
) -> dict[str, Any]:
    return {"unit": unit, "frame_id": frame_id, "file": file, "line": line, "level": level, "message": message}


def _present_extras(frame: Frame) -> list[tuple[str, Any]]:
    """The frame's (name, values) of :data:`~labelaudit.results.EXTRA_COLUMNS`, an array's values as
    a list of Python scalars (one conversion per frame instead of a NumPy scalar per object; the
    row's normalisation gives both the same value)."""
    present = []
    for name in R.EXTRA_COLUMNS:
        if name in frame.extras:
            values = frame.extras[name]
            present.append((name, values.tolist() if isinstance(values, np.ndarray) else values))
    return present


def _extras_for(frame: Frame, i: int, present: list[tuple[str, Any]] | None = None) -> dict[str, Any]:
    """The extra columns of label ``i``; ``present``: :func:`_present_extras` of the frame, looked up once per frame."""
    out: dict[str, Any] = {}
    if present is None:
        present = _present_extras(frame)
    for name, values in present:
        value = values[i]
        if name == "difficulty" and not isinstance(value, str):
            value = DIFFICULTY_NAMES.get(int(value), "unknown")
        out[name] = value
    return out


def world_boxes(frame: Frame, indices: list[int]) -> dict[int, dict[str, float | None]]:
    """The :data:`~labelaudit.results.WORLD_COLUMNS` of labels ``indices``: the frame's time and each
    box moved into the world frame with the ego pose (yaw turned by the pose's heading about z).
    Empty when the frame has neither pose nor time (KITTI object)."""
    if frame.pose is None and frame.timestamp is None:
        return {}
    out: dict[int, dict[str, float | None]] = {}
    ts = None if frame.timestamp is None else float(frame.timestamp)
    if frame.pose is None:
        return {i: {"timestamp": ts} for i in indices}
    pose = np.asarray(frame.pose, dtype=float)
    boxes = np.asarray(frame.boxes[indices], dtype=float).reshape(-1, 7)
    with np.errstate(
        invalid="ignore", over="ignore"
    ):  # a label the reader could not use (inf, NaN) stays unusable, silently: its row says why
        centres = boxes[:, :3] @ pose[:3, :3].T + pose[:3, 3]
        yaws = g.normalize_angle(boxes[:, 6] + math.atan2(pose[1, 0], pose[0, 0]))
    for j, i in enumerate(indices):
        cx, cy, cz = centres[j].tolist()
        out[i] = {"timestamp": ts, "world_cx": cx, "world_cy": cy, "world_cz": cz, "world_yaw": float(yaws[j])}
    return out


def wants_class(cfg: RunConfig, class_name: str) -> bool:
    """Whether objects of ``class_name`` are audited under ``cfg`` (``classes = ["all"]`` = every class)."""
    return ALL_CLASSES in cfg.classes or class_name in cfg.classes


def process_frame(frame: Frame, cfg: RunConfig) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Audit every selected box of one frame.

    Parameters
    ----------
    frame : points (N, 4) and boxes (K, 7) in the LiDAR frame
    cfg : run configuration (classes, length range, crop and model parameters)

    Returns
    -------
    rows : one dict per audited box, normalised (:func:`labelaudit.results.normalize_row`: every
        column of :data:`labelaudit.results.SCHEMA`, plain Python values, NaN as None); boxes of
        other classes are left out, boxes outside the length range get status ``skipped``, a
        box the reader could not use (``frame.object_errors``: NaN, size ≤ 0, out of range) or
        whose inference raised gets status ``error`` and the reason in ``message`` (one line).
    notes : frame warnings (level ``warning``) as rows of the errors table
    """
    notes = [frame_note(frame.frame_id, frame.frame_id, w, level="warning") for w in frame.warnings]
    origin = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    ox, oy = origin[:2].tolist()
    selected = [i for i, name in enumerate(frame.class_names) if wants_class(cfg, name)]
    rows: dict[int, dict[str, Any]] = {}
    final: set[int] = set()  # indices whose row is already normalised
    to_audit: list[int] = []
    extras = _present_extras(frame)
    world = world_boxes(frame, selected)
    # the labels as Python floats, converted once per frame: the row's box columns, the distance and
    # the validity test take the same values (and the same float64 operations) as NumPy scalars would
    labels = np.asarray(frame.boxes, dtype=float).reshape(-1, 7)
    values = labels.tolist()
    usable = [_usable(v) for v in values]
    for i in selected:
        v = values[i]
        row: dict[str, Any] = {
            "dataset": cfg.dataset_format,
            "frame_id": frame.frame_id,
            "object_index": i,
            "object_id": frame.object_ids[i],
            "class_name": frame.class_names[i],
            **dict(zip(R.BOX_COLUMNS, v)),
            "distance": math.hypot(v[0] - ox, v[1] - oy),
            "model": cfg.model.kind,
            "sigma": cfg.model.sigma,
            **_extras_for(frame, i, extras),
            **world.get(i, {}),
        }
        rows[i] = row
        problem = frame.object_errors.get(i)  # the reader's reason, naming file, line and field
        if problem is not None:
            row.update(status="error", message=problem)
            continue
        if not usable[i]:
            try:
                g.validate_box(frame.boxes[i])
            except ValueError as exc:
                row.update(status="error", message=f"{label_where(frame, i)}: invalid box: {exc}")
                continue
        length = v[3]
        if not (cfg.min_length <= length <= cfg.max_length):
            row.update(
                status="skipped", message=f"length {length:.2f} m outside [{cfg.min_length:g}, {cfg.max_length:g}] m"
            )
            continue
        to_audit.append(i)

    if to_audit:
        boxes = np.ascontiguousarray(frame.boxes[to_audit], dtype=float)
        # One Open3D pass gives each box's neighbourhood; the model's crop is refined from it
        # exactly, the label-error fit's wider crop is cut above the local ground, other labels'
        # points are dropped, and the rays that may cross the box are collected (infer/evidence.py).
        # errstate: extreme but valid boxes (1e38 m) overflow the geometry harmlessly, and it changes
        # no value: a non-finite result is refused per object (check_finite), not warned about on stderr
        with np.errstate(all="ignore"):
            # every usable label can own points (label_boxes, from the flags already computed)
            others = labels if all(usable) else labels[np.array(usable, dtype=bool)]
            evidence = frame_evidence(
                frame.points,
                boxes,
                origin,
                cfg.crop,
                others=others,
                ray_mask=frame.ray_mask,
                model_dim=g.point_dim(cfg.model.kind),
            )
            points = np.asarray(frame.points)
            for i, ev in zip(to_audit, evidence):
                row = rows[i]
                idx = ev.model_idx
                try:
                    # the crops as the model's passes take them, made by the evidence's pass (no
                    # gathering of the frame's rows and no cleaning per box)
                    result = audit_object(
                        frame.boxes[i],
                        ev.model_pts,
                        frame.class_names[i],
                        cfg,
                        origin,
                        fit_points=ev.fit_cols,
                        evidence=ev.for_object(points),
                        clean=True,
                    )
                    check_finite(result)
                    # values the schema cannot hold fail here, per object; the row is final after this
                    rows[i] = R.normalize_row({**row, **result})
                    final.add(i)
                except Exception as exc:  # one bad object never sinks the frame (docs/datasets.md, bad input)
                    row.update(
                        status="error",
                        message=one_line(f"{label_where(frame, i)}: {type(exc).__name__}: {exc}"),
                        num_points=len(idx),
                    )
    return [rows[i] if i in final else R.normalize_row(rows[i]) for i in selected], notes


def audit_object(
    box: ArrayLike,
    points: ArrayLike | None,
    class_name: str,
    cfg: RunConfig,
    sensor_origin: ArrayLike = (0.0, 0.0, 0.0),
    *,
    fit_points: ArrayLike | None = None,
    evidence: ObjectEvidence | None = None,
    clean: bool = False,
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
    evidence : optional free-space rays, neighbourhood points and diagnostics of the box
        (:func:`labelaudit.infer.evidence.frame_evidence`); the rays enter the label-error fit and
        are counted for the label and the suggested box. None: no free-space evidence, the ray
        columns are null.
    clean : the crops come as the model's passes take them (:func:`~labelaudit.infer.evidence.frame_evidence`'s
        ``model_pts`` and ``fit_cols``): ``points`` (N, d) float64 finite rows of the model's point
        dimension, C-contiguous, and ``fit_points`` (3, M) float64 finite columns; not cleaned again.

    Returns
    -------
    dict with the keys of :data:`labelaudit.results.MODEL_COLUMNS`:
        ``status`` "no_points" (0 points: prior-only posterior), "few_points" (fewer than
        ``cfg.model.min_points``) or "ok"; ``num_points``; ``sigma`` (noise std used, m);
        ``jiou_gt``; ``sigma_hat`` (per-object EM residual at the label, NaN below 2 points);
        ``corner_tv`` (4 floats, m², C1 first); ``std_cx`` … ``std_yaw`` (NaN for cz/height in BEV);
        ``cov`` (row-major flattened φ covariance), ``cov_dim`` (6 BEV, 8 3D); ``model``.
        Label error (:func:`labelaudit.core.fit.fit_label`, docs/label-error.md): ``label_error`` in
        [0, 1] (higher = more likely wrong), ``fit_cx`` … ``fit_yaw`` the suggested box (3D fit;
        written in the form nearest the label), ``fit_offset_m`` (BEV centre offset, m),
        ``mahalanobis`` (label vs suggested box, in posterior std); baseline ``hull_iou`` (BEV IoU
        of the box and the convex hull of its points; 0 below 3 points). Free space (with
        ``evidence``): ``free_rays`` / ``end_rays`` (rays through the label's solid lower body that
        end behind it / rays that end on or in it), ``fit_free_rays`` / ``fit_end_rays`` (the same
        for the suggested box), ``through_rays`` (rays through the slab that passed beyond the
        label's own returns: see-through, left out of the free space), ``neighbour_points`` and ``ground_z``.

    Raises
    ------
    ValueError
        Invalid box (non-positive size, non-finite values) or malformed points.
    """
    y = g.validate_box(box)
    params = cfg.model
    # Validated once here: the posterior takes the clean points, and a 3D run's posterior and the
    # label-error fit (3D) share the label's φ, Jacobians and prior precision; a BEV run's posterior
    # and the 3D fit each take their own, made in one compiled call.
    prior = params.prior_for(class_name)
    fs = None if evidence is None else fit_free_space(class_name, evidence.free_space)
    scores = None
    if (
        clean
        and params.kind == "bev"
        and not params.outlier_prob > 0
        and cfg.spatial.num_samples > 1
        and isinstance(fit_points, np.ndarray)
        and fit_points.shape[0] == 3
    ):
        # the pipeline's BEV path: both sets of prior terms, the posterior, JIoU-GT and the hull
        # IoU in two compiled calls (the values of the general steps below, bit for bit)
        ox, oy = g.sensor_xy(sensor_origin)
        scores = bev_label_scores(y, points, prior, params, cfg.spatial, ox, oy)
    if scores is not None:
        n = scores.num_points
        fit_terms = scores.fit_terms
        sigma, sigma_hat, cov, corner_tv, std = (
            scores.sigma,
            scores.sigma_hat,
            scores.cov,
            scores.corner_tv,
            scores.std_box,
        )
        jiou, hull, model = scores.jiou_gt, scores.hull_iou, "bev"
    else:
        fit_terms = None
        if clean and params.kind == "bev" and isinstance(fit_points, np.ndarray) and fit_points.shape[0] == 3:
            # the fit is 3D (the points have z): both sets of terms in one compiled call
            terms, fit_terms = box_prior_terms_bev_3d(y, prior, params.prior_weight)
        else:
            terms = box_prior_terms(y, prior, params.prior_weight, params.kind)
        pts = points if clean else g.clean_points(points, g.point_dim(params.kind))
        post = infer_label_valid(y, pts, class_name, params, sensor_origin, prior_terms=terms)
        n = post.num_points
        fit_terms = terms if fit_terms is None else fit_terms
        sigma, sigma_hat, cov, corner_tv, std = post.sigma, post.sigma_hat, post.cov, post.corner_tv, post.std_box
        jiou, model = jiou_gt(post, cfg.spatial), post.model
        hull = hull_iou_valid(y, pts if clean else points)  # the same x, y (converted exactly)
    if n == 0:
        status = "no_points"
    elif n < cfg.model.min_points:
        status = "few_points"
    else:
        status = "ok"
    fit = fit_label_valid(
        y,
        None if clean else (points if fit_points is None else fit_points),
        class_name,
        params,
        free_space=fs,
        prior_terms=fit_terms,
        sensor_origin=sensor_origin,
        columns=fit_points if clean else None,
    )
    fit_box, label = fit.box.tolist(), y.tolist()
    row: dict[str, Any] = {
        "status": status,
        "num_points": int(n),
        "sigma": float(sigma),
        "jiou_gt": float(jiou),
        "label_error": float(fit.label_error)
        if class_name in C.LABEL_ERROR_CLASSES
        else None,  # null: not validated for the class
        "sigma_hat": float(sigma_hat),
        "fit_offset_m": float(np.hypot(fit_box[0] - label[0], fit_box[1] - label[1])),
        "corner_tv": corner_tv.tolist(),
    }
    for name, column in zip(g.BOX_FIELDS, _STD_COLUMNS):
        row[column] = float(std[name])
    row["cov"] = np.asarray(cov).ravel().tolist()
    row["cov_dim"] = int(cov.shape[0])
    row["model"] = model
    for name, value in zip(_FIT_COLUMNS, fit_box):
        row[name] = value
    if fit.model == "bev":  # points without z: the fit does not touch cz and height
        row["fit_cz"] = row["fit_height"] = float("nan")
    row["hull_iou"] = hull
    row["mahalanobis"] = float(fit.mahalanobis)
    row["face_gap"] = float(fit.face_gap)  # NaN (null) when no side face is seen
    if evidence is not None:
        (row["free_rays"], row["end_rays"]), (row["fit_free_rays"], row["fit_end_rays"]) = ray_counts(
            np.array((y, fit.box)), evidence.free_space, evidence.near_points
        )
        row["through_rays"] = int(evidence.through_rays)
        row["neighbour_points"] = int(evidence.neighbour_points)
        row["scenery_points"] = int(evidence.scenery_points)
        row["ground_z"] = float(evidence.ground_z)
    else:
        row.update(dict.fromkeys(_EVIDENCE_COLUMNS))
    return row


_FIT_COLUMNS = tuple(f"fit_{name}" for name in g.BOX_FIELDS)
_STD_COLUMNS = tuple(f"std_{name}" for name in g.BOX_FIELDS)
_EVIDENCE_COLUMNS = (
    "free_rays",
    "end_rays",
    "fit_free_rays",
    "fit_end_rays",
    "through_rays",
    "neighbour_points",
    "scenery_points",
    "ground_z",
)

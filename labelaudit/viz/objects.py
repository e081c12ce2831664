"""Recompute one audited object exactly as ``infer`` did, for its picture: dataset, frame, crop, model.

A results folder's manifest names the dataset, its format and the full run parameters. This
module reopens that dataset (or the one given by ``--dataset``), reloads a frame, crops the box with
:func:`labelaudit.infer.evidence.frame_evidence` and runs :func:`labelaudit.core.posterior.infer_label`,
:func:`labelaudit.core.fit.fit_label` and :func:`labelaudit.core.spatial.jiou_gt` with the manifest's
config — the same calls in the same order as :func:`labelaudit.infer.rows.audit_object` — so a
picture shows the very numbers of its row (:attr:`ObjectAudit.matches_row` checks it). It owns the
look-ups and their error messages (unknown frame or object: the nearest valid ids); it draws
nothing (:mod:`labelaudit.viz.show` does).
"""

from __future__ import annotations

import bisect
import difflib
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.config import RunConfig, config_from_params, hash_inputs
from labelaudit.core import geometry as g
from labelaudit.core import track as T
from labelaudit.core.fit import LabelFit, fit_label
from labelaudit.core.posterior import LabelPosterior, infer_label
from labelaudit.core.spatial import BoxDistribution, Grid, jiou_gt, spatial_distribution
from labelaudit.datasets import DatasetReader, Frame, FrameFailure, FrameRef, open_dataset
from labelaudit.errors import ConfigError, LabelAuditError
from labelaudit.infer.evidence import fit_free_space, frame_evidence, label_boxes
from labelaudit.results import BOX_COLUMNS, MANIFEST_NAME, Results

FloatArray = NDArray[np.float64]

__all__ = [
    "ViewError",
    "AuditSource",
    "ObjectAudit",
    "TrackView",
    "open_source",
    "audit_view",
    "frame_rows",
    "object_row",
    "load_frame",
    "recompute",
    "track_view",
    "frame_candidates",
    "candidate_row",
    "frame_label_rows",
]

AUDITED_STATUSES = ("ok", "few_points", "no_points")
"""Statuses whose rows carry model results (``skipped`` and ``error`` rows do not)."""


class ViewError(LabelAuditError, ValueError):
    """A picture cannot be made: unknown frame or object, moved dataset, a row without model results."""


# --------------------------------------------------------------------------- the source of pictures


@dataclass
class AuditSource:
    """A results folder together with the dataset and the run configuration that produced it.

    Attributes
    ----------
    results : the opened results
    cfg : the run's configuration, rebuilt from the manifest (its hash is the manifest's)
    dataset : dataset path actually read (the manifest's input, or the ``--dataset`` override)
    dataset_format : "kitti", "waymo-v2", "waymo-v1" or "av2"
    reader : the dataset reader
    notes : warnings for the user (results of another labelaudit version or other model constants)
    """

    results: Results
    cfg: RunConfig
    dataset: Path
    dataset_format: str
    reader: DatasetReader
    notes: list[str] = field(default_factory=list)
    _frames: dict[str, Frame] = field(default_factory=dict, repr=False)


def open_source(results: Results, dataset: str | Path | None = None) -> AuditSource:
    """Reopen the dataset and the configuration of a results folder.

    Parameters
    ----------
    results : opened results folder (with its manifest)
    dataset : the dataset's current location when it moved since ``infer`` (``--dataset``)

    Raises
    ------
    ViewError
        No manifest with run parameters, a manifest whose parameters do not match their hash, or a
        dataset that is no longer where the manifest says (the message names ``--dataset``).
    """
    manifest = results.manifest
    where = results.root / MANIFEST_NAME if results.root.is_dir() else results.root
    missing = [k for k in ("params", "param_hash", "format", "input") if k not in manifest]
    if missing:
        raise ViewError(
            f"{where}: no run manifest with {', '.join(missing)}; pictures need a results folder written by `labelaudit infer`"
        )
    fmt = str(manifest["format"])
    path = Path(dataset) if dataset is not None else Path(str(manifest["input"]))
    if not path.exists():
        if dataset is not None:
            raise ViewError(f"--dataset {path}: no such file or folder")
        raise ViewError(
            f"{where}: the dataset of this run, {path}, is not there any more (moved or deleted); "
            "pass --dataset PATH with its current location"
        )
    try:
        cfg = config_from_params(manifest["params"], source=f"{where} params")
    except ConfigError as exc:
        raise ViewError(
            f"{exc}; these results were written by labelaudit {manifest.get('tool_version', '?')} with other parameter names: "
            "rerun `labelaudit infer --overwrite` with this version to draw them"
        ) from None
    if cfg.to_dict() != manifest["params"]:
        raise ViewError(
            f"{where}: the run parameters do not rebuild into a configuration of this labelaudit (edited manifest?); rerun `labelaudit infer`"
        )
    notes = []
    inputs = hash_inputs(cfg)
    for key, what in (
        ("tool_version", "labelaudit version"),
        ("constants_digest", "model constants (labelaudit/constants.py)"),
    ):
        if manifest.get(key) is not None and manifest.get(key) != inputs[key]:
            notes.append(
                f"these results were computed with another {what} ({manifest.get(key)} → {inputs[key]}): pictures may differ from their rows"
            )
    options: dict[str, Any] = {"split": manifest["split"]} if manifest.get("split") else {}
    reader = open_dataset(path, fmt, **options)
    return AuditSource(results, cfg, path, fmt, reader, notes)


# --------------------------------------------------------------------------- rows and frames


def _nearest(wanted: str, valid: Sequence[str], k: int = C.VIZ_NEAREST_IDS) -> list[str]:
    """Up to ``k`` valid ids near ``wanted``: its sorted-order neighbours (same-width numeric ids
    sort as numbers) and close spellings (``123`` → ``000123``)."""
    ordered = sorted(set(valid))
    out: list[str] = []
    if wanted.isdigit() and ordered and all(v.isdigit() for v in ordered):
        ordered.sort(key=lambda v: (abs(int(v) - int(wanted)), v))
        out = ordered[:k]
    else:
        out = difflib.get_close_matches(wanted, ordered, n=k, cutoff=0.5)
        pos = bisect.bisect_left(ordered, wanted)
        for v in ordered[max(0, pos - k // 2) : pos + k]:
            if len(out) >= k:
                break
            if v not in out:
                out.append(v)
    return out[:k]


def frame_rows(results: Results, frame_id: str) -> pa.Table:
    """All result rows of one frame, sorted by object_index.

    Raises
    ------
    ViewError
        The results have no row of ``frame_id`` (the message lists the nearest valid frame ids).
    """
    table = results.dataset.to_table(filter=pads.field("frame_id") == frame_id)
    if table.num_rows == 0:
        ids = pc.unique(results.dataset.to_table(columns=["frame_id"]).column("frame_id")).to_pylist()
        if not ids:
            raise ViewError(f"{results.root}: the results hold no objects; nothing to show")
        near = ", ".join(_nearest(frame_id, ids))
        raise ViewError(f"{results.root}: no frame {frame_id!r} in the results ({len(ids)} frames); nearest: {near}")
    return table.take(pc.sort_indices(table, sort_keys=[("object_index", "ascending")]))


def object_row(rows: pa.Table, object_index: int) -> dict[str, Any]:
    """The row of ``object_index`` among one frame's rows.

    Raises
    ------
    ViewError
        No such object in the frame (the message lists the frame's objects with their classes).
    """
    indices = rows.column("object_index").to_pylist()
    if object_index in indices:
        return rows.slice(indices.index(object_index), 1).to_pylist()[0]
    classes = rows.column("class_name").to_pylist()
    order = sorted(range(len(indices)), key=lambda j: (abs(indices[j] - object_index), indices[j]))
    listed = ", ".join(
        f"{indices[j]} ({classes[j]})" for j in sorted(order[: C.VIZ_NEAREST_IDS], key=lambda j: indices[j])
    )
    frame = rows.column("frame_id")[0].as_py()
    more = f" of {len(indices)}" if len(indices) > C.VIZ_NEAREST_IDS else ""
    raise ViewError(f"frame {frame}: no audited object {object_index}; nearest objects{more}: {listed}")


def frame_candidates(results: Results, frame_id: str) -> list[dict[str, Any]]:
    """The missing-label candidates of one frame (every column), by candidate_index; empty when
    the frame has none or the run did not search (``infer --no-missing``)."""
    from labelaudit.rank import read_candidates

    table = read_candidates(results)
    if table is None:
        return []
    rows = [r for r in table.filter(pc.equal(table.column("frame_id"), frame_id)).to_pylist()]
    return sorted(rows, key=lambda r: r["candidate_index"])


def frame_label_rows(frame: Frame) -> list[dict[str, Any]]:
    """Every usable label of a loaded frame, audited class or not, as the rows a close-up draws
    (box columns, ``class_name``, ``object_index``): a label of any class explains the returns
    around a missing-label candidate, so a reviewer sees them all (labels the reader refused are
    left out: they have no box)."""
    return [
        {**dict(zip(g.BOX_FIELDS, box.tolist())), "class_name": name, "object_index": i}
        for i, (box, name) in enumerate(zip(np.asarray(frame.boxes, dtype=float), frame.class_names))
        if i not in frame.object_errors and np.all(np.isfinite(box))
    ]


def candidate_row(results: Results, frame_id: str, candidate_index: int) -> dict[str, Any]:
    """One missing-label candidate.

    Raises
    ------
    ViewError
        The run did not search for missing labels, or the frame has no such candidate (the message
        lists the frame's candidates, or the frames that have some).
    """
    from labelaudit.rank import read_candidates

    table = read_candidates(results)
    if table is None:
        raise ViewError(
            f"{results.root}: no missing-label table (missing/): the run skipped the search (infer --no-missing)"
        )
    rows = frame_candidates(results, frame_id)
    for r in rows:
        if r["candidate_index"] == candidate_index:
            return r
    if rows:
        listed = ", ".join(
            f"{r['candidate_index']} ({r['class_name']}, score {r['score']:.2f})" for r in rows[: C.VIZ_NEAREST_IDS]
        )
        raise ViewError(f"frame {frame_id}: no candidate {candidate_index}; its candidates: {listed}")
    frames = sorted(set(table.column("frame_id").to_pylist()))
    near = ", ".join(_nearest(frame_id, frames)) if frames else "none"
    raise ViewError(f"frame {frame_id}: no missing-label candidate; frames with candidates nearest to it: {near}")


def _units_for(source: AuditSource, frame_id: str) -> list[FrameRef]:
    """Units that may hold ``frame_id``: KITTI's unit is the frame; Waymo's frame ids start with the segment name."""
    if source.dataset_format == "kitti":
        return [FrameRef("kitti", str(source.dataset), frame_id)]
    segment = frame_id.rsplit(":", 1)[0]
    units = source.reader.list_units()
    likely = [u for u in units if segment and segment in Path(u.key).name]
    return likely + [u for u in units if u not in likely]


def load_frame(source: AuditSource, frame_id: str) -> Frame:
    """Load one frame of the source's dataset (cached: several pictures of one frame read it once).

    Raises
    ------
    ViewError
        The dataset has no such frame (results and dataset disagree: wrong ``--dataset``?).
    DatasetError
        The frame's files are unreadable.
    """
    if frame_id in source._frames:
        return source._frames[frame_id]
    for ref in _units_for(source, frame_id):
        for frame in source.reader.load_unit(ref):
            if isinstance(frame, FrameFailure):  # a frame the reader could not read (the next ones still come)
                if frame.frame_id == frame_id:
                    raise frame.error
                continue
            if frame.frame_id == frame_id:
                if len(source._frames) >= C.VIZ_FRAME_CACHE:
                    source._frames.pop(next(iter(source._frames)))
                source._frames[frame_id] = frame
                return frame
    raise ViewError(
        f"{source.dataset}: frame {frame_id!r} of the results is not in this dataset; is --dataset the dataset these results were computed on?"
    )


# --------------------------------------------------------------------------- one object


@dataclass(frozen=True)
class ObjectAudit:
    """Everything a picture of one label shows, computed by the library functions of ``infer``.

    Attributes
    ----------
    box : (7,) the labeled box (LiDAR frame)
    class_name : the class (selects the prior)
    sensor_origin : (3,) sensor position
    points : (N, ≥3) the model's crop (``[crop] margin``)
    fit_points : (M, ≥3) the label-error fit's wider crop (``[crop] fit_margin``, cut above the
        local ground, other labels' points and unlabelled surfaces dropped; docs/label-error.md)
    fit_only : (M', ≥3) the fit's points that are not the model's (``fit_points`` minus ``points``)
    context : (K, ≥3) other points around the box for orientation (same ground cut, a wide
        margin), none of them in ``fit_points``
    posterior : the label posterior (covariance of φ, corner order)
    fit : the label-error fit (suggested box, ``label_error``)
    jiou_gt : JIoU-GT of the posterior
    grid : the grid of p_G (box frame: origin at the box centre, x along its length)
    mass : (ny, nx) probability mass of p_G per BEV cell (the BEV marginal for a 3D model)
    row : the results row this was recomputed for (None for a bare call of :func:`audit_view`)
    """

    box: FloatArray
    class_name: str
    sensor_origin: FloatArray
    points: FloatArray
    fit_points: FloatArray
    fit_only: FloatArray
    context: FloatArray
    posterior: LabelPosterior
    fit: LabelFit
    jiou_gt: float
    grid: Grid
    mass: FloatArray
    row: Mapping[str, Any] | None = None

    @property
    def label_error(self) -> float:
        return float(self.fit.label_error)

    @property
    def sigma_hat(self) -> float:
        return float(self.posterior.sigma_hat)

    @property
    def distance(self) -> float:
        return float(math.hypot(self.box[0] - self.sensor_origin[0], self.box[1] - self.sensor_origin[1]))

    def mismatches(self, rtol: float = 1e-9) -> dict[str, tuple[Any, Any]]:
        """Row values that the recomputation does not reproduce: {column: (row, recomputed)}."""
        if self.row is None:
            return {}
        mine = {
            "num_points": len(self.points),
            "jiou_gt": self.jiou_gt,
            "label_error": self.label_error,
            "sigma_hat": self.sigma_hat,
        }
        out: dict[str, tuple[Any, Any]] = {}
        for k, v in mine.items():
            r = self.row.get(k)
            if r is None and isinstance(v, float) and math.isnan(v):
                continue
            if r is None or not math.isclose(float(r), float(v), rel_tol=rtol, abs_tol=rtol):
                out[k] = (r, v)
        return out

    @property
    def matches_row(self) -> bool:
        """Whether points, JIoU-GT, label_error and σ̂ equal the row's (always True without a row)."""
        return not self.mismatches()


def audit_view(
    box: FloatArray,
    points: FloatArray,
    fit_points: FloatArray,
    class_name: str,
    cfg: RunConfig,
    sensor_origin: FloatArray | None = None,
    context: FloatArray | None = None,
    row: Mapping[str, Any] | None = None,
    free_space: Any = None,
) -> ObjectAudit:
    """Run the model of ``infer`` on one box and compute its spatial distribution for the picture.

    Parameters
    ----------
    box : (7,) labeled box
    points : (N, ≥3) the model's crop; fit_points : (M, ≥3) the fit's crop
    class_name : class (prior); cfg : run configuration
    sensor_origin : (3,) sensor position
    context : (K, ≥3) other points to draw for orientation (those also in ``fit_points`` are dropped)
    row : the results row, kept for :meth:`ObjectAudit.mismatches`
    free_space : the box's rays (:class:`labelaudit.core.freespace.FreeSpace`), as ``infer`` gave them to the fit
    """
    y = g.validate_box(box)
    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=float).reshape(3)
    post = infer_label(y, points, class_name, cfg.model, origin)
    fit = fit_label(y, fit_points, class_name, cfg.model, free_space=fit_free_space(class_name, free_space))
    score = float(jiou_gt(post, cfg.spatial))
    grid, mass = spatial_distribution(BoxDistribution.from_posterior(post), cfg.spatial)
    if mass.ndim == 3:  # 3D model: the picture is the BEV marginal
        mass = mass.sum(axis=2)
    pts, fpts = np.asarray(points), np.asarray(fit_points)
    ctx = (
        np.zeros((0, fpts.shape[1] if fpts.ndim == 2 else 3))
        if context is None
        else _rows_not_in(np.asarray(context), fpts)
    )
    return ObjectAudit(
        y, class_name, origin, pts, fpts, _rows_not_in(fpts, pts), ctx, post, fit, score, grid, mass, row
    )


def _rows_not_in(a: FloatArray, b: FloatArray) -> FloatArray:
    """Rows of ``a`` whose x, y, z are not a row of ``b`` (exact float equality; vectorised)."""
    if len(a) == 0 or len(b) == 0:
        return a

    def key(m: FloatArray) -> NDArray[np.void]:
        xyz = np.ascontiguousarray(np.asarray(m, dtype=np.float64)[:, :3])
        return xyz.view(np.dtype((np.void, 24))).ravel()

    return a[~np.isin(key(a), key(b))]


def _check_box(frame: Frame, row: Mapping[str, Any], where: Path) -> int:
    i = int(row["object_index"])
    if i >= frame.num_objects or frame.class_names[i] != row["class_name"]:
        raise ViewError(
            f"{where}: frame {frame.frame_id} object {i} is not the {row['class_name']} of the results; is --dataset the dataset these results were computed on?"
        )
    box_row = np.array([row[c] for c in BOX_COLUMNS], dtype=float)
    if not np.allclose(frame.boxes[i], box_row, rtol=0.0, atol=1e-9):
        raise ViewError(
            f"{where}: the box of frame {frame.frame_id} object {i} differs from the results row (labels edited since infer?); rerun `labelaudit infer`"
        )
    return i


def recompute(source: AuditSource, row: Mapping[str, Any], frame: Frame | None = None) -> ObjectAudit:
    """Recompute the audit of one results row from its dataset frame, as ``infer`` did.

    Raises
    ------
    ViewError
        The row has no model results (status ``skipped`` / ``error``), or the dataset's frame
        does not hold the row's box.
    """
    from labelaudit.infer.crop import crop_frame

    if row["status"] not in AUDITED_STATUSES:
        why = f" ({row['message']})" if row.get("message") else ""
        raise ViewError(
            f"frame {row['frame_id']} object {row['object_index']} has status {row['status']}{why}: no model result to show"
        )
    frame = frame or load_frame(source, str(row["frame_id"]))
    i = _check_box(frame, row, source.dataset)
    box = frame.boxes[i : i + 1]
    # a box's evidence depends on the box, the points and the frame's other labels only: one box suffices
    (ev,) = frame_evidence(
        frame.points,
        box,
        np.asarray(frame.sensor_origin, dtype=float),
        source.cfg.crop,
        others=label_boxes(frame.boxes),
        ray_mask=frame.ray_mask,
    )
    (ctx_idx,) = crop_frame(frame.points, box, replace(source.cfg.crop, margin=C.SHOW_CONTEXT_MARGIN))
    return audit_view(
        frame.boxes[i],
        frame.points[ev.model_idx],
        frame.points[ev.fit_idx],
        frame.class_names[i],
        source.cfg,
        np.asarray(frame.sensor_origin, dtype=float),
        context=frame.points[np.setdiff1d(ctx_idx, ev.fit_idx, assume_unique=True)],
        row=row,
        free_space=ev.free_space,
    )


# --------------------------------------------------------------------------- the object's track


@dataclass(frozen=True)
class TrackView:
    """The object's labels in the neighbouring frames of its track, moved into this frame.

    Attributes
    ----------
    dt : (T,) time of each neighbouring label relative to this frame (s)
    boxes : (T, 7) those labels in this frame's LiDAR/vehicle frame (through the world frame:
        the ego poses of both frames)
    frame_ids : T frame ids
    track_error, track_issue : this label's (None when the track was not scored)
    size : (3,) the track's fused length, width, height (tracks.parquet), or None
    expected : (7,) the box the rest of the track expects in this frame (its predicted centre and
        heading, the other frames' size), in this frame; None for a track of < 3 frames
    """

    dt: FloatArray
    boxes: FloatArray
    frame_ids: list[str]
    track_error: float | None
    track_issue: str | None
    size: FloatArray | None
    expected: FloatArray | None = None


def track_view(results: Results, row: Mapping[str, Any], frames: int = C.SHOW_TRACK_FRAMES) -> TrackView | None:
    """The labels of ``row``'s track in up to ``frames`` frames before and after it, or None when
    the row has no track (KITTI, no pose, a made-up id)."""
    needed = ("timestamp", "world_cx", "world_cy", "world_cz", "world_yaw")
    if any(row.get(c) is None for c in needed) or row.get("object_id") in (
        None,
        f"{row['frame_id']}:{row['object_index']}",
    ):
        return None
    log = str(row["frame_id"]).rsplit(":", 1)[0]
    cols = ["frame_id", "object_id", *needed, "length", "width", "height"]
    present = [c for c in cols if c in results.dataset.schema.names]
    if len(present) < len(cols):
        return None
    t = results.dataset.to_table(columns=cols, filter=pc.field("object_id") == row["object_id"])
    mates = [
        r
        for r in t.to_pylist()
        if str(r["frame_id"]).rsplit(":", 1)[0] == log and r["timestamp"] is not None and r["world_cx"] is not None
    ]
    mates.sort(key=lambda r: (r["timestamp"], r["frame_id"]))
    here = [i for i, r in enumerate(mates) if r["frame_id"] == row["frame_id"]]
    if not here:
        return None
    i = here[0]
    chosen = mates[max(0, i - frames) : i] + mates[i + 1 : i + 1 + frames]
    label = np.array([row[c] for c in BOX_COLUMNS], dtype=float)
    label_world = np.array([row["world_cx"], row["world_cy"], row["world_cz"], row["world_yaw"]], dtype=float)

    def here(world_boxes: Sequence[Sequence[float]]) -> FloatArray:  # into this frame (its pose from this row)
        return T.to_frame(np.asarray(world_boxes, dtype=float).reshape(-1, 7), label, label_world)

    boxes = here(
        [
            [r["world_cx"], r["world_cy"], r["world_cz"], r["length"], r["width"], r["height"], r["world_yaw"]]
            for r in chosen
        ]
    )
    size = None
    noise = T.TrackNoise.floor()
    tracks = results.tracks()
    if tracks is not None:
        for tr in tracks.filter(pc.field("object_id") == row["object_id"]).to_pylist():
            if tr["log_id"] == log and tr["length"] is not None:
                size = np.array([tr["length"], tr["width"], tr["height"]])
        used = (tracks.schema.metadata or {}).get(b"labelaudit")
        per_class = json.loads(used).get("track_noise", {}).get(row["class_name"]) if used else None
        if per_class:
            noise = T.TrackNoise(
                np.full(3, per_class["center"]),
                np.array([per_class["length"], per_class["width"], per_class["height"]]),
                per_class["yaw"],
            )
    expected = None
    if len(mates) >= C.TRACK_MIN_FRAMES:  # what the rest of the track expects here (the labels' size consensus)
        t = np.array([r["timestamp"] for r in mates], dtype=float)
        res = T.track_residuals(
            t - t[0],
            np.array([[r["world_cx"], r["world_cy"], r["world_cz"]] for r in mates]),
            np.array([r["world_yaw"] for r in mates]),
            np.array([[r["length"], r["width"], r["height"]] for r in mates]),
            noise,
            T.default_params(),
        )
        expected = here(res.expected[i])[0]
    return TrackView(
        np.array([r["timestamp"] - row["timestamp"] for r in chosen], dtype=float),
        boxes,
        [str(r["frame_id"]) for r in chosen],
        row.get("track_error"),
        row.get("track_issue"),
        size,
        expected,
    )

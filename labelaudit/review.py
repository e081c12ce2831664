"""The review loop: ``labelaudit export RESULTS --format kitti-labels -o review/`` (docs/review.md).

Writes what a labelling tool imports to fix the labels: per frame, the original labels, the
suggested box of the label-error fit for each label whose ``label_error`` is above a threshold, the
box its track expects for each tracked label (Waymo, Argoverse 2) whose ``track_error`` is above a
threshold, and the missing-label candidates (objects nobody labelled) whose ``score`` is at least a
threshold, plus a sidecar listing every added box.

- KITTI: ``review/label_2/<frame>.txt`` for every frame of the dataset (split) — the original file's
  lines unchanged, then one line per added box in the rectified camera frame, the review score in
  the 16th column (label_error of a suggestion, score of a candidate), every float written in its
  shortest exact form so the file reads back to the same LiDAR box —, beside symbolic links to the
  dataset's ``velodyne``, ``calib`` and ``image_2``, so ``review/`` is itself a KITTI folder.
- Every other format (Waymo, Argoverse 2, …): ``review/boxes.parquet``, the same boxes in the
  LiDAR/vehicle frame (``kind`` = label / suggested / missing; a suggestion's ``source`` = fit or
  track — a label may get both).
- Both: ``review/changes.csv`` (one row per added box: where it was written and why) and
  ``review/review.json`` (thresholds, counts, frames written without additions and why).

Every file is written under a temporary name and renamed; a label folder of an earlier export is
replaced only once the new one is complete. Computes no score; prints nothing.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
import shutil
import struct
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.config import config_from_params
from labelaudit.core.geometry import normalize_angle
from labelaudit.datasets import open_dataset
from labelaudit.datasets.kitti import (
    Calibration,
    alpha_from_location,
    boxes_camera_to_lidar,
    boxes_lidar_to_camera,
    format_label_line,
    project_box_to_image,
    read_calib,
    read_label,
    read_text_lines,
)
from labelaudit.errors import ConfigError, DatasetError, ExportError
from labelaudit.infer.tracks import NEEDED_COLUMNS as TRACK_INPUT_COLUMNS
from labelaudit.infer.tracks import expected_boxes
from labelaudit.rank import read_candidates

FloatArray = NDArray[np.float64]

__all__ = ["ReviewSummary", "export_review", "suggested_boxes", "CHANGE_COLUMNS", "BOXES_SCHEMA"]

LABEL_DIR = "label_2"
CHANGES_FILE = "changes.csv"
SUMMARY_FILE = "review.json"
BOXES_FILE = "boxes.parquet"
LINKED_DIRS = ("velodyne", "velodyne_reduced", "calib", "image_2")
"""Folders of the KITTI dataset linked into ``review/`` so it reads as a KITTI folder of its own."""
AUDITED_STATUSES = ("ok", "few_points", "no_points")
"""Statuses whose rows carry a fit (the others were not inferred)."""
MATCH_TOLERANCE = 1e-6
"""m / rad; a label whose box differs from its result row by more was edited since ``infer``."""

CHANGE_COLUMNS = (
    "frame_id", "file", "line", "change", "class_name", "score", "object_index", "original_line", "label_error",
    "fit_offset_m", "candidate_index", "source", "track_error", "track_issue", "cx", "cy", "cz", "length", "width", "height", "yaw",
)  # fmt: skip
"""Columns of ``changes.csv``: one row per added box. ``change`` is ``suggested_box`` (for label
``object_index``, written at ``line`` of ``file``; ``original_line`` is the label's own line;
``source`` fit: the label-error fit, track: the box its track expects, with its ``track_issue``)
or ``missing_label`` (candidate ``candidate_index``); the box in the LiDAR/vehicle frame."""

BOXES_SCHEMA = pa.schema([
    pa.field("frame_id", pa.string(), nullable=False),
    pa.field("kind", pa.string(), nullable=False),  # label | suggested | missing
    pa.field("class_name", pa.string(), nullable=False),
    *(pa.field(c, pa.float64(), nullable=False) for c in R.BOX_COLUMNS),
    pa.field("score", pa.float64()),  # label_error of a fit suggestion, track_error of a track suggestion, score of a candidate, null for a label
    pa.field("object_index", pa.int32()),  # the label (label, suggested)
    pa.field("object_id", pa.string()),
    pa.field("label_error", pa.float64()),
    pa.field("candidate_index", pa.int32()),  # the candidate (missing)
    pa.field("source", pa.string()),  # fit | track (suggested); points | detections | both (missing)
    pa.field("track_error", pa.float64()),  # the label's (label, suggested); null without a track
    pa.field("track_issue", pa.string()),  # size | heading | position | none
])  # fmt: skip
"""Schema of ``boxes.parquet`` (formats other than KITTI): every label, suggestion and candidate."""


@dataclass
class ReviewSummary:
    """What :func:`export_review` wrote.

    Attributes
    ----------
    output : the review folder; format : "kitti-labels" (label_2 files) or "parquet" (boxes.parquet)
    frames_written : label files written (KITTI) or frames with a box in boxes.parquet
    labels : original labels written; suggested : suggested boxes of the label-error fit added;
    track_suggested : boxes a track expects added; missing : candidates added
    frames_changed : frames with at least one added box
    min_label_error, min_track_error, min_score : the thresholds used
    missing_searched : False when the results have no missing-label table (``infer --no-missing``)
    unreviewed_frames : frame id → why nothing was added to it (its label file unreadable, or edited since
        infer: written as it is, so an import loses nothing; a frame of the results not in the dataset: not written)
    """

    output: str
    format: str
    frames_written: int
    labels: int
    suggested: int
    missing: int
    frames_changed: int
    min_label_error: float
    min_score: float
    missing_searched: bool
    track_suggested: int = 0
    min_track_error: float = C.EXPORT_REVIEW_TRACK_ERROR
    unreviewed_frames: dict[str, str] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


# --------------------------------------------------------------------------- what to add


def suggested_boxes(rows: pa.Table) -> FloatArray:
    """(N, 7) suggested boxes of result rows: the fit's centre, size and yaw (in [-π, π), as every box
    of the results); a BEV fit leaves the label's cz and height (its fit_cz / fit_height are null)."""

    def col(name: str, fallback: str | None = None) -> FloatArray:
        v = np.asarray(rows.column(name).to_numpy(zero_copy_only=False), dtype=float)
        if fallback is not None:
            label = np.asarray(rows.column(fallback).to_numpy(zero_copy_only=False), dtype=float)
            v = np.where(np.isfinite(v), v, label)
        return v

    yaw = col("fit_yaw")
    with np.errstate(
        invalid="ignore"
    ):  # the fit may leave its yaw just outside [-π, π); an angle inside is kept bit for bit
        yaw = np.where((yaw >= -np.pi) & (yaw < np.pi), yaw, normalize_angle(yaw))
    return np.stack(
        [
            col("fit_cx"),
            col("fit_cy"),
            col("fit_cz", "cz"),
            col("fit_length"),
            col("fit_width"),
            col("fit_height", "height"),
            yaw,
        ],
        axis=1,
    ).reshape(-1, 7)


def _selected(results: R.Results, min_score: float) -> tuple[pa.Table, pa.Table | None]:
    """The label rows (with the columns the export needs) and the candidates above their thresholds."""
    import pyarrow.compute as pc

    columns = ["frame_id", "object_index", "object_id", "class_name", "status", *R.BOX_COLUMNS, "label_error", "fit_offset_m", "label_line",
               "fit_cx", "fit_cy", "fit_cz", "fit_length", "fit_width", "fit_height", "fit_yaw", *R.TRACK_COLUMNS, *TRACK_INPUT_COLUMNS]  # fmt: skip
    labels = results.read(list(dict.fromkeys(columns)))
    candidates = read_candidates(results)
    if candidates is not None:
        candidates = candidates.filter(pc.fill_null(pc.greater_equal(candidates.column("score"), min_score), False))
    return labels, candidates


def _suggest_mask(labels: pa.Table, min_label_error: float) -> NDArray[np.bool_]:
    status = np.asarray(labels.column("status").to_pylist(), dtype=object)
    lerr = np.asarray(labels.column("label_error").to_numpy(zero_copy_only=False), dtype=float)
    fit = suggested_boxes(labels)
    with np.errstate(invalid="ignore"):
        return (
            np.isin(status, AUDITED_STATUSES)
            & (lerr > min_label_error)
            & np.isfinite(fit).all(axis=1)
            & (fit[:, 3:6] > 0).all(axis=1)
        )


def _track_suggestions(
    results: R.Results, labels: pa.Table, min_track_error: float
) -> tuple[NDArray[np.bool_], FloatArray]:
    """Which labels get the box their track expects (``track_error`` above the threshold), and those boxes (N, 7).

    The boxes are recomputed with the run's own configuration and per-class label noise (the
    metadata of ``tracks.parquet``), so they are the predictions the label's ``track_error`` judged it by.
    """
    err = np.asarray(labels.column("track_error").to_numpy(zero_copy_only=False), dtype=float)
    with np.errstate(invalid="ignore"):
        mask = err > min_track_error
    if not mask.any():
        return mask, np.full((labels.num_rows, 7), np.nan)
    try:
        cfg = config_from_params(results.manifest["params"], source=f"{results.root / R.MANIFEST_NAME} params")
    except (ConfigError, KeyError) as exc:
        raise ExportError(
            f"{results.root}: the run's parameters cannot be read ({exc}); rerun `labelaudit infer` with this labelaudit for track suggestions, or pass --min-track-error 1"
        ) from None
    tracks = results.tracks()
    used = (tracks.schema.metadata or {}).get(b"labelaudit") if tracks is not None else None
    noise = json.loads(used).get("track_noise") if used else None
    boxes = expected_boxes(labels, cfg, noise, only=mask)
    with np.errstate(invalid="ignore"):
        mask &= np.isfinite(boxes).all(axis=1) & (boxes[:, 3:6] > 0).all(axis=1)
    return mask, boxes


# --------------------------------------------------------------------------- KITTI


def png_size(path: Path) -> tuple[int, int] | None:
    """(width, height) of a PNG from its header, or None when the file is missing or not a PNG."""
    try:
        with open(path, "rb") as f:
            head = f.read(24)
    except OSError:
        return None
    if len(head) < 24 or head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR":
        return None
    w, h = struct.unpack(">II", head[16:24])
    return (int(w), int(h)) if w > 0 and h > 0 else None


def kitti_lines(boxes: FloatArray, class_names: Sequence[str], scores: FloatArray, truncated: FloatArray, occluded: NDArray[np.int64],
                calib: Calibration, image_size: tuple[int, int]) -> list[str]:  # fmt: skip
    """KITTI label lines (16 columns, the score last) of LiDAR-frame boxes (K, 7).

    Location, dimensions and rotation_y are written exactly (shortest round-trip floats), so
    :func:`labelaudit.datasets.kitti.read_label` and ``boxes_camera_to_lidar`` give back ``boxes`` to
    rounding; alpha and the 2D box (the projection into image_2, clipped to ``image_size``) are
    derived from them.
    """
    loc, dims, ry = boxes_lidar_to_camera(boxes, calib)
    out = []
    for k in range(len(boxes)):
        alpha = float(alpha_from_location(loc[k], ry[k]))
        bbox = project_box_to_image(boxes[k], calib, image_size)
        out.append(
            format_label_line(
                class_names[k],
                truncated[k],
                int(occluded[k]),
                alpha,
                bbox,
                dims[k],
                loc[k],
                float(ry[k]),
                float(scores[k]),
                precision=None,
            )
        )
    return out


def _stale(
    frame_rows: list[dict[str, Any]], file_boxes: FloatArray, file_lines: NDArray[np.int64], label_path: Path
) -> str | None:
    """Why a frame's label file no longer matches its result rows (None when it does)."""
    at = {int(n): k for k, n in enumerate(file_lines)}
    for row in frame_rows:
        line = row.get("label_line")
        if line is None:
            return f"{label_path}: the results carry no label_line (written by an older labelaudit); rerun `labelaudit infer --overwrite`"
        k = at.get(int(line))
        want = np.array([row[c] for c in R.BOX_COLUMNS], dtype=float)
        if k is None or not np.allclose(file_boxes[k], want, rtol=0.0, atol=MATCH_TOLERANCE, equal_nan=True):
            return f"{label_path}: line {line} is not the box of object {row['object_index']} in the results (labels edited since infer); rerun `labelaudit infer`"
    return None


def _link_dataset(data_dir: Path, output: Path) -> None:
    """Symbolic links review/velodyne → the dataset's velodyne (calib, image_2 …): a KITTI folder a tool opens as it is."""
    for name in LINKED_DIRS:
        target, link = data_dir / name, output / name
        if not target.is_dir():
            continue
        if link.is_symlink() or not os.path.lexists(link):
            tmp = output / f".{name}{R.TMP_MARKER}{os.getpid()}"
            if os.path.lexists(tmp):
                tmp.unlink()
            tmp.symlink_to(target.resolve(), target_is_directory=True)
            os.replace(tmp, link)


def _export_kitti(dataset: Path, split: str | None, output: Path, labels: pa.Table, suggest: NDArray[np.bool_],
                  candidates: pa.Table | None, changes: list[dict[str, Any]], summary: ReviewSummary) -> None:  # fmt: skip
    from labelaudit.datasets.kitti import KittiReader

    reader = open_dataset(dataset, "kitti", **({"split": split} if split else {}))
    assert isinstance(reader, KittiReader)
    by_frame: dict[str, list[dict[str, Any]]] = {}
    for k, row in enumerate(labels.to_pylist()):
        row["_suggest"] = bool(suggest[k])
        by_frame.setdefault(row["frame_id"], []).append(row)
    cand_by_frame: dict[str, list[dict[str, Any]]] = {}
    for row in candidates.to_pylist() if candidates is not None else []:
        cand_by_frame.setdefault(row["frame_id"], []).append(row)

    staging = output / f".{LABEL_DIR}{R.TMP_MARKER}{os.getpid()}"
    if os.path.lexists(staging):
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    frame_ids = [ref.key for ref in reader.list_units()]
    unknown = sorted((set(by_frame) | set(cand_by_frame)) - set(frame_ids))
    for fid in unknown:
        summary.unreviewed_frames[fid] = (
            f"{dataset}: frame {fid} of the results is not in this dataset, nothing written (pass --dataset with the dataset of the run)"
        )
    try:
        for fid in frame_ids:
            label_path = reader.label_path(fid)
            rows = sorted(by_frame.get(fid, []), key=lambda r: r["object_index"])
            cands = sorted(cand_by_frame.get(fid, []), key=lambda r: r["candidate_index"])
            try:
                lines = read_text_lines(label_path, "label file")
                added = (
                    _review_frame(reader, fid, lines, rows, cands, labels.schema, changes, summary)
                    if rows or cands
                    else []
                )
            except DatasetError as exc:  # an unreadable label or calibration file: the frame as it is, nothing added
                summary.unreviewed_frames[fid] = str(exc)
                if label_path.is_file():
                    shutil.copyfile(label_path, staging / f"{fid}.txt")
                    summary.frames_written += 1
                continue
            summary.labels += sum(1 for t in lines if t.split() and t.split()[0] != "DontCare")
            (staging / f"{fid}.txt").write_text("".join(t + "\n" for t in [*lines, *added]), encoding="utf-8")
            summary.frames_written += 1
        if summary.frames_written == 0:
            raise ExportError(
                f"{dataset}: no label file could be written ({len(frame_ids)} frames in the dataset; {_first(summary.unreviewed_frames)})"
            )
        final = output / LABEL_DIR
        old = output / f".{LABEL_DIR}.old{R.TMP_MARKER}{os.getpid()}"
        if os.path.lexists(final):
            os.replace(final, old)
        os.replace(staging, final)
        if os.path.lexists(old):
            shutil.rmtree(old)
    finally:
        if os.path.lexists(staging):
            shutil.rmtree(staging)
    _link_dataset(reader.data_dir, output)


def _review_frame(reader: Any, fid: str, lines: list[str], rows: list[dict[str, Any]], cands: list[dict[str, Any]], schema: pa.Schema,
                  changes: list[dict[str, Any]], summary: ReviewSummary) -> list[str]:  # fmt: skip
    """The lines to append to one frame's label file (its ``lines`` as read): suggested boxes, then candidates.

    A frame whose labels no longer match its result rows gets none (it is listed in
    ``summary.unreviewed_frames``). Raises :class:`DatasetError` for an unreadable label or calibration file.
    """
    label_path = reader.label_path(fid)
    parsed = read_label(label_path)
    calib = read_calib(reader.calib_path(fid))
    file_boxes = boxes_camera_to_lidar(parsed.location, parsed.dims_hwl, parsed.rotation_y, calib)
    why = _stale(rows, file_boxes, parsed.line, label_path)
    if why is not None:
        summary.unreviewed_frames[fid] = why
        return []
    image_size = png_size(reader.data_dir / "image_2" / f"{fid}.png") or C.EXPORT_REVIEW_IMAGE_SIZE
    file = f"{LABEL_DIR}/{fid}.txt"
    added: list[str] = []
    picked = [r for r in rows if r["_suggest"]]
    if picked:
        boxes = suggested_boxes(pa.Table.from_pylist(picked, schema=schema.append(pa.field("_suggest", pa.bool_()))))
        where = {int(n): k for k, n in enumerate(parsed.line)}
        src = [where[int(r["label_line"])] for r in picked]
        lerr = np.array([r["label_error"] for r in picked], dtype=float)
        new = kitti_lines(
            boxes,
            [r["class_name"] for r in picked],
            lerr,
            parsed.truncated[src],
            parsed.occluded[src],
            calib,
            image_size,
        )
        for r, box, text in zip(picked, boxes, new):
            added.append(text)
            changes.append(_change(fid, file, len(lines) + len(added), "suggested_box", r["class_name"], r["label_error"], box, object_index=r["object_index"],
                                   original_line=r["label_line"], label_error=r["label_error"], fit_offset_m=r["fit_offset_m"], source="fit"))  # fmt: skip
    if cands:
        boxes = np.array([[c[n] for n in R.BOX_COLUMNS] for c in cands], dtype=float)
        scores = np.array([c["score"] for c in cands], dtype=float)
        # A candidate has no annotator's truncation or occlusion: 0 and 3 (KITTI's "unknown").
        new = kitti_lines(
            boxes,
            [c["class_name"] for c in cands],
            scores,
            np.zeros(len(cands)),
            np.full(len(cands), 3, dtype=np.int64),
            calib,
            image_size,
        )
        for c, box, text in zip(cands, boxes, new):
            added.append(text)
            changes.append(_change(fid, file, len(lines) + len(added), "missing_label", c["class_name"], c["score"], box,
                                   candidate_index=c["candidate_index"], source=c["source"]))  # fmt: skip
    summary.suggested += len(picked)
    summary.missing += len(cands)
    summary.frames_changed += bool(added)
    return added


def _first(reasons: Mapping[str, str]) -> str:
    return next(iter(reasons.values()), "none")


def _change(
    frame_id: str,
    file: str | None,
    line: int | None,
    change: str,
    class_name: str,
    score: float,
    box: FloatArray,
    **kw: Any,
) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(CHANGE_COLUMNS)
    row.update(frame_id=frame_id, file=file, line=line, change=change, class_name=class_name, score=score, **kw)
    row.update(zip(R.BOX_COLUMNS, (float(v) for v in box)))
    return row


# --------------------------------------------------------------------------- other formats


def _export_parquet(output: Path, labels: pa.Table, suggest: NDArray[np.bool_], track: NDArray[np.bool_], track_boxes: FloatArray,
                    candidates: pa.Table | None, changes: list[dict[str, Any]], summary: ReviewSummary) -> None:  # fmt: skip
    rows: list[dict[str, Any]] = []
    fits = suggested_boxes(labels)
    changed: set[str] = set()
    for k, r in enumerate(labels.to_pylist()):
        box = {c: r[c] for c in R.BOX_COLUMNS}
        common = {"frame_id": r["frame_id"], "class_name": r["class_name"], "object_index": r["object_index"], "object_id": r["object_id"],
                  "label_error": r["label_error"], "track_error": r["track_error"], "track_issue": r["track_issue"]}  # fmt: skip
        rows.append({**common, **box, "kind": "label"})
        # A label may get both: the fit says where its points put it, the track where its other frames do.
        for source, on, new, score in (
            ("fit", suggest, fits, r["label_error"]),
            ("track", track, track_boxes, r["track_error"]),
        ):
            if not on[k]:
                continue
            rows.append(
                {
                    **common,
                    **dict(zip(R.BOX_COLUMNS, new[k].tolist())),
                    "kind": "suggested",
                    "score": score,
                    "source": source,
                }
            )
            changes.append(_change(r["frame_id"], None, None, "suggested_box", r["class_name"], score, new[k], object_index=r["object_index"],
                                   label_error=r["label_error"], fit_offset_m=r["fit_offset_m"] if source == "fit" else None, source=source,
                                   track_error=r["track_error"], track_issue=r["track_issue"]))  # fmt: skip
            changed.add(r["frame_id"])
    for c in candidates.to_pylist() if candidates is not None else []:
        rows.append({"frame_id": c["frame_id"], "class_name": c["class_name"], **{n: c[n] for n in R.BOX_COLUMNS}, "kind": "missing",
                     "score": c["score"], "candidate_index": c["candidate_index"], "source": c["source"]})  # fmt: skip
        changes.append(_change(c["frame_id"], None, None, "missing_label", c["class_name"], c["score"], np.array([c[n] for n in R.BOX_COLUMNS]),
                               candidate_index=c["candidate_index"], source=c["source"]))  # fmt: skip
        changed.add(c["frame_id"])
    kind_order = {"label": 0, "suggested": 1, "missing": 2}
    rows.sort(
        key=lambda r: (
            r["frame_id"],
            kind_order[r["kind"]],
            r.get("object_index") or 0,
            r.get("candidate_index") or 0,
            r.get("source") or "",
        )
    )
    table = pa.Table.from_pylist(rows, schema=BOXES_SCHEMA)
    R.write_parquet_atomic(table, output / BOXES_FILE)
    summary.frames_written = len({r["frame_id"] for r in rows})
    summary.labels = labels.num_rows
    summary.suggested = int(suggest.sum())
    summary.track_suggested = int(track.sum())
    summary.missing = 0 if candidates is None else candidates.num_rows
    summary.frames_changed = len(changed)


# --------------------------------------------------------------------------- entry point


def _changes_csv(changes: Sequence[Mapping[str, Any]]) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(CHANGE_COLUMNS)
    for c in changes:
        w.writerow(
            [
                "" if c[k] is None or (isinstance(c[k], float) and not math.isfinite(c[k])) else c[k]
                for k in CHANGE_COLUMNS
            ]
        )
    return buf.getvalue()


def export_review(
    results_path: str | Path,
    output: str | Path,
    *,
    min_label_error: float = C.EXPORT_REVIEW_LABEL_ERROR,
    min_score: float = C.EXPORT_REVIEW_MIN_SCORE,
    dataset: str | Path | None = None,
    min_track_error: float = C.EXPORT_REVIEW_TRACK_ERROR,
) -> ReviewSummary:
    """Write the review folder of a results folder (see the module docstring).

    Parameters
    ----------
    results_path : results folder written by ``labelaudit infer``
    output : the review folder (created; an earlier export in it is replaced)
    min_label_error : labels with ``label_error`` above this get their suggested box
    min_score : missing-label candidates with ``score`` at least this are added
    dataset : the dataset's current location when it moved since ``infer`` (KITTI)
    min_track_error : tracked labels (Waymo, Argoverse 2) with ``track_error`` above this get the box
        their track expects (:func:`labelaudit.infer.tracks.expected_boxes`), beside any fit suggestion

    Raises
    ------
    ExportError
        A threshold outside [0, 1], an output that is a file or a non-empty folder that is not a
        review folder, results without a manifest, a dataset that is not there, or no frame written.
    ResultsError
        Not a results folder.
    """
    for name, value in (
        ("--min-label-error", min_label_error),
        ("--min-score", min_score),
        ("--min-track-error", min_track_error),
    ):
        if not (isinstance(value, (int, float)) and 0.0 <= value <= 1.0):
            raise ExportError(f"{name} must be in [0, 1], got {value!r}")
    results = R.open_results(results_path)
    out = Path(output)
    _check_output(out)
    manifest = results.manifest
    fmt = manifest.get("format")
    if not fmt or "input" not in manifest:
        raise ExportError(
            f"{results.root}: no run manifest with the dataset's format and path; the review export needs a results folder written by `labelaudit infer`"
        )
    labels, candidates = _selected(results, min_score)
    suggest = _suggest_mask(labels, min_label_error)
    summary = ReviewSummary(str(out), "kitti-labels" if fmt == "kitti" else "parquet", 0, 0, 0, 0, 0, float(min_label_error), float(min_score), candidates is not None,
                            min_track_error=float(min_track_error))  # fmt: skip
    changes: list[dict[str, Any]] = []
    out.mkdir(parents=True, exist_ok=True)
    if fmt == "kitti":
        path = Path(dataset) if dataset is not None else Path(str(manifest["input"]))
        if not path.exists():
            raise ExportError(
                f"{path}: the dataset of these results is not there (moved?); pass --dataset with its current location"
            )
        _export_kitti(path, manifest.get("split"), out, labels, suggest, candidates, changes, summary)
    else:
        # Tracks exist only where object ids are track ids (Waymo, Argoverse 2): never in KITTI's label files.
        track, track_boxes = _track_suggestions(results, labels, min_track_error)
        _export_parquet(out, labels, suggest, track, track_boxes, candidates, changes, summary)
    changes.sort(
        key=lambda c: (
            c["frame_id"],
            c["line"] or 0,
            c["change"],
            c["object_index"] or 0,
            c["candidate_index"] or 0,
            c["source"] or "",
        )
    )
    R.write_text_atomic(_changes_csv(changes), out / CHANGES_FILE)
    record = {"tool": "labelaudit", "tool_version": __version__, "results": str(results.root.resolve()), "dataset": str(Path(str(dataset or manifest.get("input"))).absolute()),
              "dataset_format": fmt, "param_hash": manifest.get("param_hash"), **summary.to_dict()}  # fmt: skip
    R.write_json_atomic(record, out / SUMMARY_FILE)
    return summary


def _check_output(out: Path) -> None:
    """Refuse an output that is a file, or a non-empty folder that no review export wrote."""
    if os.path.lexists(out) and not out.is_dir():
        raise ExportError(f"{out}: exists and is not a folder; -o names the review folder to write")
    if out.is_dir() and not (out / SUMMARY_FILE).is_file() and any(not p.name.startswith(".") for p in out.iterdir()):
        raise ExportError(
            f"{out}: folder is not empty and holds no {SUMMARY_FILE} (not a review folder); choose a new or empty -o"
        )

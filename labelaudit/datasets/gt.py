"""Ground truth for detector evaluation (and the frames detections are aligned to): the labels of a dataset without its point clouds.

``eval`` needs every label (DontCare rows and the devkit's difficulty fields included) but no
LiDAR points, so this module reads label files only — the same files, conversions and object
numbering as the readers of :mod:`labelaudit.datasets` (``object_index`` here equals the results'
``object_index``, so rows of an ``infer`` results folder join by ``(frame_id, object_index)``):

* KITTI: ``label_2`` (through :func:`~labelaudit.datasets.kitti.read_label`) and ``calib`` (kept
  per frame: KITTI detections are converted to the LiDAR frame with it); the 2D box height,
  occlusion and truncation drive the difficulty; DontCare rows become DontCare regions when they
  carry a real 3D box (KITTI's carry placeholders, −1 sizes at −1000 m, see docs/eval.md).
* Waymo v1 and v2: the readers' labels without points (``reader.labels``: the ``laser_labels`` of
  each ``Frame`` record, range images not decoded; the ``lidar_box`` component).
* Argoverse 2: ``annotations.feather`` (and the sweep file names, so that frames without labels
  are frames here too); every box is one difficulty level, boxes with ``num_interior_pts = 0``
  are ignored like Waymo's empty boxes (AV2's own evaluation drops them).

It never reads detections or results.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

import numpy as np
from numpy.typing import NDArray

from labelaudit.datasets import DatasetError, FrameRef, open_dataset
from labelaudit.datasets.kitti import Calibration, boxes_camera_to_lidar, kitti_difficulty, read_calib, read_label
from labelaudit.datasets.waymo_common import FrameLabels, waymo_level
from labelaudit.datasets.waymo_common import class_name as waymo_class_name

FloatArray = NDArray[np.float64]

__all__ = ["GroundTruth", "GroundTruthFrame", "load_ground_truth"]


@dataclass
class GroundTruthFrame:
    """The labels of one frame (LiDAR/vehicle frame), in the order of the label file.

    Attributes
    ----------
    frame_id : as the dataset readers name it
    boxes : (K, 7) non-DontCare boxes
    class_names : K names
    object_index : (K,) position among the frame's objects as the reader numbers them
    height : (K,) 2D box height in pixels (NaN when the format has none)
    occluded : (K,) KITTI occlusion level (−1 unknown)
    truncated : (K,) KITTI truncation (NaN unknown)
    difficulty : (K,) KITTI devkit difficulty 0/1/2 (−1 none), Waymo level 1/2, Argoverse 2: 1
    num_points : (K,) the dataset's own LiDAR point count per box (Waymo, Argoverse 2; −1 unknown)
    dontcare : (M, 7) DontCare regions with a real 3D box
    dontcare_rows : DontCare rows in the file (with or without a 3D box)
    calib : KITTI calibration (None for Waymo)
    sensor_origin : (3,) sensor position (distances are measured from it)
    source : the label file (or segment file)
    """

    frame_id: str
    boxes: FloatArray
    class_names: list[str]
    object_index: NDArray[np.int64]
    height: FloatArray
    occluded: NDArray[np.int64]
    truncated: FloatArray
    difficulty: NDArray[np.int8]
    num_points: NDArray[np.int64]
    dontcare: FloatArray
    dontcare_rows: int
    calib: Calibration | None
    sensor_origin: FloatArray
    source: str


@dataclass
class GroundTruth:
    """Every evaluated frame's labels, concatenated (frames in the dataset's order).

    ``gt_off[f]:gt_off[f+1]`` are frame f's rows, ``dc_off`` the same for DontCare regions.
    """

    dataset_format: str
    frame_ids: list[str]
    gt_off: NDArray[np.int64]
    boxes: FloatArray
    class_names: list[str]
    object_index: NDArray[np.int64]
    height: FloatArray
    occluded: NDArray[np.int64]
    truncated: FloatArray
    difficulty: NDArray[np.int8]
    num_points: NDArray[np.int64]
    distance: FloatArray
    dc_off: NDArray[np.int64]
    dontcare: FloatArray
    dontcare_rows: int
    calibs: list[Calibration | None]
    sources: list[str]
    errors: list[dict[str, Any]] = field(default_factory=list)

    @property
    def num_frames(self) -> int:
        return len(self.frame_ids)

    @property
    def frame_of_row(self) -> NDArray[np.int64]:
        """(N,) frame index of every GT row."""
        return np.repeat(np.arange(self.num_frames), np.diff(self.gt_off))

    def index(self) -> dict[str, int]:
        """frame_id → frame position."""
        return {fid: i for i, fid in enumerate(self.frame_ids)}

    @classmethod
    def from_frames(
        cls, dataset_format: str, frames: list[GroundTruthFrame], errors: list[dict[str, Any]] | None = None
    ) -> "GroundTruth":
        counts = [len(f.boxes) for f in frames]
        dcs = [len(f.dontcare) for f in frames]
        cat = lambda xs, shape, dtype: np.concatenate(xs).astype(dtype) if xs else np.zeros(shape, dtype)  # noqa: E731
        boxes = cat([f.boxes for f in frames], (0, 7), float).reshape(-1, 7)
        origins = (
            np.repeat(np.array([f.sensor_origin for f in frames]).reshape(-1, 3), counts, axis=0)
            if frames
            else np.zeros((0, 3))
        )
        return cls(
            dataset_format=dataset_format,
            frame_ids=[f.frame_id for f in frames],
            gt_off=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
            boxes=boxes,
            class_names=[n for f in frames for n in f.class_names],
            object_index=cat([f.object_index for f in frames], 0, np.int64),
            height=cat([f.height for f in frames], 0, float),
            occluded=cat([f.occluded for f in frames], 0, np.int64),
            truncated=cat([f.truncated for f in frames], 0, float),
            difficulty=cat([f.difficulty for f in frames], 0, np.int8),
            num_points=cat([f.num_points for f in frames], 0, np.int64),
            distance=np.hypot(boxes[:, 0] - origins[:, 0], boxes[:, 1] - origins[:, 1]) if len(boxes) else np.zeros(0),
            dc_off=np.concatenate([[0], np.cumsum(dcs)]).astype(np.int64),
            dontcare=cat([f.dontcare for f in frames], (0, 7), float).reshape(-1, 7),
            dontcare_rows=int(sum(f.dontcare_rows for f in frames)),
            calibs=[f.calib for f in frames],
            sources=[f.source for f in frames],
            errors=list(errors or []),
        )


# --------------------------------------------------------------------------- KITTI


def kitti_frame(label_path: Path, calib_path: Path, frame_id: str) -> GroundTruthFrame:
    """Labels of one KITTI frame (raises :class:`DatasetError` naming file and line)."""
    labels = read_label(label_path)
    calib = read_calib(calib_path)
    is_dc = np.array([n == "DontCare" for n in labels.class_names], dtype=bool)
    rows = np.flatnonzero(~is_dc)
    dims = labels.dims_hwl[rows]
    bad = np.flatnonzero(~np.all(dims > 0, axis=1))
    if len(bad):
        r = rows[bad[0]]
        h, w, l = labels.dims_hwl[r]
        raise DatasetError(
            label_path, f"box dimensions must be > 0, got height={h:g} width={w:g} length={l:g}", int(labels.line[r])
        )
    boxes = (
        boxes_camera_to_lidar(labels.location[rows], dims, labels.rotation_y[rows], calib).reshape(-1, 7)
        if len(rows)
        else np.zeros((0, 7))
    )
    dc_rows = np.flatnonzero(is_dc)
    real = dc_rows[np.all(labels.dims_hwl[dc_rows] > 0, axis=1) & np.all(labels.location[dc_rows] > -999, axis=1)]
    dontcare = (
        boxes_camera_to_lidar(labels.location[real], labels.dims_hwl[real], labels.rotation_y[real], calib).reshape(
            -1, 7
        )
        if len(real)
        else np.zeros((0, 7))
    )
    bbox = labels.bbox2d[rows]
    return GroundTruthFrame(
        frame_id=frame_id,
        boxes=boxes,
        class_names=[labels.class_names[r] for r in rows],
        object_index=np.arange(len(rows), dtype=np.int64),
        height=bbox[:, 3] - bbox[:, 1],
        occluded=labels.occluded[rows].astype(np.int64),
        truncated=labels.truncated[rows].astype(float),
        difficulty=kitti_difficulty(bbox, labels.occluded[rows], labels.truncated[rows]),
        num_points=np.full(len(rows), -1, dtype=np.int64),
        dontcare=dontcare,
        dontcare_rows=int(len(dc_rows)),
        calib=calib,
        sensor_origin=np.zeros(3),
        source=str(label_path),
    )


# --------------------------------------------------------------------------- Waymo


def _waymo_frame(labels: FrameLabels) -> GroundTruthFrame:
    k = len(labels.boxes)
    return GroundTruthFrame(
        frame_id=labels.frame_id,
        boxes=np.asarray(labels.boxes, dtype=float).reshape(k, 7),
        class_names=[waymo_class_name(int(t)) for t in labels.types],
        object_index=np.arange(k, dtype=np.int64),
        height=np.full(k, np.nan),
        occluded=np.full(k, -1, dtype=np.int64),
        truncated=np.full(k, np.nan),
        difficulty=waymo_level(labels.difficulty, labels.num_points),
        num_points=np.asarray(labels.num_points, dtype=np.int64),
        dontcare=np.zeros((0, 7)),
        dontcare_rows=0,
        calib=None,
        sensor_origin=np.asarray(labels.sensor_origin, dtype=float),
        source=labels.source,
    )


# --------------------------------------------------------------------------- Argoverse 2


def _av2_frames(reader: Any, ref: FrameRef) -> Iterator[GroundTruthFrame]:
    """The frames of one AV2 log from the reader's labels (no sweep is read): the reader's frames,
    numbering and extras. A label the audit would mark as an error stops the log: eval needs every box."""
    frames = list(reader.labels(ref))  # the whole log is checked before any frame is kept
    for frame in frames:
        if frame.object_errors:
            message = next(iter(frame.object_errors.values()))  # "<file> row R: …"
            raise DatasetError(
                frame.source, message[len(frame.source) :].lstrip() if message.startswith(frame.source) else message
            )
    for frame in frames:
        k = frame.num_objects
        num = np.asarray(frame.extras.get("num_lidar_points_in_box", np.full(k, -1)), dtype=float)
        yield GroundTruthFrame(
            frame_id=frame.frame_id,
            boxes=frame.boxes,
            class_names=list(frame.class_names),
            object_index=np.arange(k, dtype=np.int64),
            height=np.full(k, np.nan),
            occluded=np.full(k, -1, dtype=np.int64),
            truncated=np.full(k, np.nan),
            difficulty=np.ones(k, dtype=np.int8),
            num_points=np.nan_to_num(num, nan=-1).astype(np.int64),
            dontcare=np.zeros((0, 7)),
            dontcare_rows=0,
            calib=None,
            sensor_origin=np.asarray(frame.sensor_origin, dtype=float),
            source=frame.source,
        )


# --------------------------------------------------------------------------- entry point


def _frames_of(fmt: str, reader: Any, ref: FrameRef) -> Iterator[GroundTruthFrame]:
    if fmt == "kitti":
        yield kitti_frame(reader.label_path(ref.key), reader.calib_path(ref.key), ref.key)
    elif fmt in ("waymo-v1", "waymo-v2"):
        for labels in reader.labels(ref):
            yield _waymo_frame(labels)
    elif fmt == "av2":
        yield from _av2_frames(reader, ref)
    else:
        raise ValueError(f"unknown dataset format {fmt!r}")


def _load_units(
    task: tuple[str, str, tuple[tuple[str, Any], ...], list[FrameRef], bool],
) -> tuple[list[GroundTruthFrame], list[dict[str, Any]]]:
    """The frames of some units (in order) and the errors of the units that failed."""
    root, fmt, options, refs, strict = task
    reader = open_dataset(root, fmt, **dict(options))
    frames: list[GroundTruthFrame] = []
    errors: list[dict[str, Any]] = []
    for ref in refs:
        try:
            frames.extend(_frames_of(fmt, reader, ref))
        except DatasetError as exc:
            if strict:
                raise
            errors.append(
                {
                    "unit": ref.key,
                    "frame_id": ref.key if fmt == "kitti" else None,
                    "file": exc.path,
                    "line": exc.line,
                    "level": "error",
                    "message": str(exc),
                }
            )
    return frames, errors


def load_ground_truth(
    dataset: str | Path,
    fmt: str,
    *,
    split: str | None = None,
    limit: int | None = None,
    strict: bool = True,
) -> GroundTruth:
    """Read the labels of every frame of a dataset (no point clouds), in one process.

    (Worker processes were measured slower: shipping the frames back costs more than parsing them,
    ~1.5 ms per KITTI frame.)

    Parameters
    ----------
    dataset : dataset folder (or a Waymo v1 .tfrecord file)
    fmt : "kitti", "waymo-v2", "waymo-v1" or "av2" (already resolved)
    split : KITTI ImageSets split, Waymo / Argoverse 2 split folder
    limit : only the first N units (KITTI frames, Waymo segments, AV2 logs), like ``infer --limit``
    strict : raise at the first unreadable unit; otherwise record it in ``errors`` and go on

    Raises
    ------
    DatasetError
        Unreadable dataset, or (``strict``) an unreadable label/calibration file.
    """
    options = tuple({"split": split}.items()) if split else ()
    reader = open_dataset(dataset, fmt, **dict(options))
    refs = reader.list_units()
    if limit is not None:
        refs = refs[:limit]
    frames, errors = _load_units((str(dataset), fmt, options, refs, strict))
    return GroundTruth.from_frames(fmt, frames, errors)

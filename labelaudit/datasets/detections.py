"""Detector outputs for ``labelaudit eval`` (and ``infer --detections``): four input formats, one in-memory form, the Parquet schema.

Formats (docs/eval.md has the full table):

* **KITTI result files** — a folder of ``<frame>.txt`` (or its ``data/`` sub-folder), 16 columns per
  line, the 15 of ``label_2`` plus an unbounded score, boxes in the rectified camera frame. They are
  converted to the LiDAR frame with the frame's own calibration, by the same code as the labels
  (:func:`labelaudit.datasets.kitti.boxes_camera_to_lidar`). A missing file means "no detections
  for that frame", like the devkit's reading loop (counted and reported, never silent).
* **Waymo ``Objects``** (``protos/metrics.proto``, what the Waymo evaluation tools read) — one or
  more ``.bin`` files of serialized ``Objects``; each ``Object`` names its frame by context name and
  timestamp; boxes in the vehicle frame. Decoded with labelaudit's own message classes
  (:mod:`labelaudit.datasets.waymo_proto`), no TensorFlow.
* **Argoverse 2** — a ``.feather`` file (or a folder of them) in the layout AV2's detection
  evaluation reads: the cuboid columns of ``annotations.feather`` (``tx_m … height_m``, ``qw …
  qz``, ``category``, ``timestamp_ns``) plus ``log_id`` and ``score``; boxes in the egovehicle frame,
  the yaw from the quaternion as for the labels.
* **labelaudit Parquet** (:data:`DETECTIONS_SCHEMA`) — one row per detection, boxes in the dataset's
  LiDAR/vehicle frame; optionally a covariance on φ (``cov``, as in the results) or per-parameter
  standard deviations (``std_cx`` …) for probabilistic detectors.

Every reader validates what it reads and names the file, line (or row / object) and field of a
bad value. This module never computes overlaps.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray

from labelaudit.datasets.gt import GroundTruth
from labelaudit.errors import DatasetError, DetectionsError

FloatArray = NDArray[np.float64]

__all__ = [
    "DETECTIONS_SCHEMA",
    "DETECTION_FORMATS",
    "DetectionsError",
    "Detections",
    "detect_detections_format",
    "read_detections",
    "write_av2_detections",
    "write_parquet_detections",
    "write_waymo_objects",
]

DETECTION_FORMATS = ("kitti", "waymo", "parquet", "av2")

BOX_COLUMNS = ("cx", "cy", "cz", "length", "width", "height", "yaw")
STD_COLUMNS = tuple(f"std_{c}" for c in BOX_COLUMNS)

# (name, type, required, description) — docs/eval.md shows the same table; a test checks they agree.
DETECTIONS_COLUMNS: tuple[tuple[str, pa.DataType, bool, str], ...] = (
    (
        "frame_id",
        pa.string(),
        True,
        "frame id as the dataset reader names it (KITTI '000123', Waymo '<segment>:<timestamp>')",
    ),
    ("class_name", pa.string(), True, "class (Car, Pedestrian, Cyclist; Waymo Vehicle, Pedestrian, Cyclist)"),
    ("cx", pa.float64(), True, "box centre x (m), dataset LiDAR/vehicle frame, geometric centre"),
    ("cy", pa.float64(), True, "box centre y (m)"),
    ("cz", pa.float64(), True, "box centre z (m)"),
    ("length", pa.float64(), True, "box length (m), > 0"),
    ("width", pa.float64(), True, "box width (m), > 0"),
    ("height", pa.float64(), True, "box height (m), > 0"),
    ("yaw", pa.float64(), True, "heading about +z (rad)"),
    ("score", pa.float64(), True, "confidence, any finite number (higher = more confident)"),
    (
        "cov",
        pa.list_(pa.float64()),
        False,
        "covariance of φ (row-major 6×6 BEV or 8×8 3D, docs/method.md) — a probabilistic detection",
    ),
    (
        "std_cx",
        pa.float64(),
        False,
        "per-parameter std (m) of cx; with std_cy … std_yaw a diagonal covariance on the box (used when cov is null)",
    ),
    ("std_cy", pa.float64(), False, "std of cy (m)"),
    ("std_cz", pa.float64(), False, "std of cz (m; 3D only)"),
    ("std_length", pa.float64(), False, "std of the length (m)"),
    ("std_width", pa.float64(), False, "std of the width (m)"),
    ("std_height", pa.float64(), False, "std of the height (m; 3D only)"),
    ("std_yaw", pa.float64(), False, "std of the yaw (rad)"),
    ("bbox_top", pa.float64(), False, "KITTI: top of the 2D box in the image (px); else projected from the box"),
    ("bbox_bottom", pa.float64(), False, "KITTI: bottom of the 2D box (px)"),
)
DETECTIONS_SCHEMA = pa.schema([pa.field(n, t, nullable=not req) for n, t, req, _ in DETECTIONS_COLUMNS])
"""Arrow schema of the labelaudit Parquet detections format (optional columns may be absent)."""


@dataclass
class Detections:
    """All detections aligned with the frames of a :class:`~labelaudit.datasets.gt.GroundTruth`.

    Attributes
    ----------
    det_off : (F+1,) detections of frame f are rows ``det_off[f]:det_off[f+1]``
    boxes : (N, 7) dataset LiDAR/vehicle frame
    class_names : N names
    scores : (N,)
    height : (N,) 2D box height in pixels (KITTI; NaN otherwise)
    cov : (N, k, k) covariance per detection (NaN-filled for deterministic ones) or None when no
        detection has one
    cov_on : "phi" (on φ) or "box" (on the box parameters; BEV (5, 5) over cx, cy, l, w, yaw, 3D 7×7)
    has_cov : (N,) bool
    source : N strings "file:line" (or "file:row n", "file:object n") for messages
    format : "kitti", "waymo", "parquet" or "av2"
    frames_without_file : frames of the dataset with no detections file (KITTI) / no rows (others)
    unknown_frames : frame id → number of detections for frames that are not in the dataset
    errors : per-frame problems recorded in lenient mode (rows of the errors table)
    """

    det_off: NDArray[np.int64]
    boxes: FloatArray
    class_names: list[str]
    scores: FloatArray
    height: FloatArray
    cov: FloatArray | None
    cov_on: str
    has_cov: NDArray[np.bool_]
    source: list[str]
    format: str
    frames_without_file: list[str] = field(default_factory=list)
    unknown_frames: dict[str, int] = field(default_factory=dict)
    errors: list[dict[str, Any]] = field(default_factory=list)

    @property
    def num(self) -> int:
        return len(self.scores)

    @property
    def frame_of_row(self) -> NDArray[np.int64]:
        return np.repeat(np.arange(len(self.det_off) - 1), np.diff(self.det_off))

    @property
    def probabilistic(self) -> bool:
        return bool(self.has_cov.any())


@dataclass
class _Rows:
    """Detections of one frame while reading."""

    boxes: list[FloatArray] = field(default_factory=list)
    names: list[str] = field(default_factory=list)
    scores: list[float] = field(default_factory=list)
    height: list[float] = field(default_factory=list)
    cov: list[FloatArray | None] = field(default_factory=list)
    source: list[str] = field(default_factory=list)


def detect_detections_format(path: str | Path) -> str:
    """ "kitti" (a folder of .txt files or one with ``data/``), "parquet" (a .parquet file or a folder
    of them) or "waymo" (any other file, or a folder of .bin files).

    Raises
    ------
    DetectionsError
        Missing path, or a folder holding none of these.
    """
    p = Path(path)
    if not p.exists():
        raise DetectionsError(p, "detections path does not exist")
    if p.is_file():
        return {".parquet": "parquet", ".feather": "av2"}.get(p.suffix, "waymo")
    if any(p.glob("*.txt")) or (p / "data").is_dir():
        return "kitti"
    if any(p.glob("*.parquet")):
        return "parquet"
    if any(p.glob("*.bin")):
        return "waymo"
    if any(p.glob("*.feather")):
        return "av2"
    raise DetectionsError(
        p,
        "cannot tell the detections format: expected KITTI result files (<frame>.txt, or data/<frame>.txt), Parquet (*.parquet), "
        "Waymo Objects (*.bin) or Argoverse 2 (*.feather); pass --detections-format",
    )


# --------------------------------------------------------------------------- KITTI


def _kitti_dir(path: Path) -> Path:
    if not any(path.glob("*.txt")) and (path / "data").is_dir():
        return path / "data"
    return path


def _as_detections_error(exc: DatasetError) -> DetectionsError:
    where = f"{exc.path}:{exc.line}: " if exc.line is not None else f"{exc.path}: "
    text = str(exc)
    return DetectionsError(exc.path, text[len(where) :] if text.startswith(where) else text, exc.line)


def _read_kitti_file(path: Path, calib: Any) -> _Rows:
    from labelaudit.datasets.kitti import boxes_camera_to_lidar, read_label

    try:
        labels = read_label(path)  # the one KITTI parser: BOM, CRLF, ranges, file:line:column errors
    except DatasetError as exc:
        raise _as_detections_error(exc) from None
    rows = _Rows()
    n = len(labels)
    if not n:
        return rows
    bad = np.flatnonzero(np.isnan(labels.score))
    if len(bad):
        raise DetectionsError(
            path,
            "field 'score': missing — a KITTI result line has 16 columns (the label's 15 and a score)",
            int(labels.line[bad[0]]),
        )
    sizes = labels.dims_hwl
    bad = np.argwhere(~(np.isfinite(sizes) & (sizes > 0)))
    if len(bad):
        k, c = bad[0]
        raise DetectionsError(
            path,
            f"field {('height', 'width', 'length')[c]!r}: expected a box size > 0, got {sizes[k, c]:g}",
            int(labels.line[k]),
        )
    vals = np.c_[labels.location, labels.rotation_y, labels.score]
    bad = np.argwhere(~np.isfinite(vals))
    if len(bad):
        k, c = bad[0]
        raise DetectionsError(
            path,
            f"field {('x', 'y', 'z', 'rotation_y', 'score')[c]!r}: expected a finite number, got {vals[k, c]!r}",
            int(labels.line[k]),
        )
    if calib is None:
        raise DetectionsError(
            path, "KITTI result files need a KITTI dataset (its calibration converts the boxes to the LiDAR frame)"
        )
    rows.boxes = list(boxes_camera_to_lidar(labels.location, labels.dims_hwl, labels.rotation_y, calib).reshape(-1, 7))
    rows.names = list(labels.class_names)
    rows.scores = labels.score.tolist()
    rows.height = (labels.bbox2d[:, 3] - labels.bbox2d[:, 1]).tolist()
    rows.cov = [None] * n
    rows.source = [f"{path}:{int(line)}" for line in labels.line]
    return rows


def _read_kitti(
    path: Path, gt: GroundTruth, strict: bool
) -> tuple[dict[str, _Rows], list[str], dict[str, int], list[dict[str, Any]]]:
    folder = _kitti_dir(path)
    files = {p.stem: p for p in folder.glob("*.txt")}
    index = gt.index()
    out: dict[str, _Rows] = {}
    errors: list[dict[str, Any]] = []
    missing = []
    for fid, f in index.items():
        p = files.get(fid)
        if p is None:
            missing.append(fid)
            continue
        try:
            out[fid] = _read_kitti_file(p, gt.calibs[f])
        except DetectionsError as exc:
            if strict:
                raise
            errors.append(_error(fid, exc))
    unknown = {}
    for stem, p in sorted(files.items()):
        if stem not in index:
            try:
                unknown[stem] = sum(1 for line in p.read_text().splitlines() if line.strip())
            except (OSError, UnicodeDecodeError):
                unknown[stem] = 0
    return out, missing, unknown, errors


def _error(frame_id: str | None, exc: DatasetError) -> dict[str, Any]:
    return {
        "unit": frame_id or exc.path,
        "frame_id": frame_id,
        "file": exc.path,
        "line": exc.line,
        "level": "error",
        "message": str(exc),
    }


# --------------------------------------------------------------------------- Waymo Objects


def _read_waymo(
    path: Path, gt: GroundTruth, strict: bool
) -> tuple[dict[str, _Rows], list[str], dict[str, int], list[dict[str, Any]]]:
    from labelaudit.datasets import waymo_proto as wp
    from labelaudit.datasets.waymo_common import class_name

    files = [path] if path.is_file() else sorted(p for p in path.glob("*.bin") if p.is_file())
    if not files:
        raise DetectionsError(path, "no Waymo Objects files (*.bin) found")
    index = gt.index()
    out: dict[str, _Rows] = {}
    unknown: dict[str, int] = {}
    errors: list[dict[str, Any]] = []
    bad_frames: set[str] = set()
    for f in files:
        try:
            msg = wp.Objects.FromString(f.read_bytes())
        except Exception as exc:  # protobuf's DecodeError, OSError
            raise DetectionsError(f, f"not a serialized Waymo Objects message (protos/metrics.proto): {exc}") from None
        for k, o in enumerate(msg.objects):
            fid = f"{o.context_name}:{o.frame_timestamp_micros}"
            if fid not in index:
                unknown[fid] = unknown.get(fid, 0) + 1
                continue
            if fid in bad_frames:
                continue
            b = o.object.box
            values = (b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading, o.score)
            names = (
                "object.box.center_x",
                "object.box.center_y",
                "object.box.center_z",
                "object.box.length",
                "object.box.width",
                "object.box.height",
                "object.box.heading",
                "score",
            )
            try:
                for n, v in zip(names, values):
                    if not math.isfinite(v):
                        raise DetectionsError(f, f"object {k}: field {n!r}: expected a finite number, got {v!r}")
                for n, v in zip(names[3:6], values[3:6]):
                    if v <= 0:
                        raise DetectionsError(f, f"object {k}: field {n!r}: expected a box size > 0, got {v:g}")
            except DetectionsError as exc:
                if strict:
                    raise
                errors.append(_error(fid, exc))
                bad_frames.add(fid)
                out.pop(fid, None)
                continue
            rows = out.setdefault(fid, _Rows())
            rows.boxes.append(np.array(values[:7], dtype=float))
            rows.names.append(class_name(o.object.type))
            rows.scores.append(float(o.score))
            rows.height.append(math.nan)
            rows.cov.append(None)
            rows.source.append(f"{f}:object {k}")
    missing = [fid for fid in index if fid not in out and fid not in bad_frames]
    return out, missing, unknown, errors


def write_waymo_objects(
    path: str | Path, frame_ids: Sequence[str], boxes: FloatArray, types: Sequence[int], scores: Sequence[float]
) -> Path:
    """Write detections as one serialized Waymo ``Objects`` file (atomically).

    Parameters
    ----------
    frame_ids : N "<context_name>:<timestamp>" ids
    boxes : (N, 7) vehicle-frame boxes
    types : N Waymo label types (1 vehicle, 2 pedestrian, 4 cyclist)
    scores : N scores
    """
    from labelaudit.datasets import waymo_proto as wp

    msg = wp.Objects()
    for fid, box, t, s in zip(frame_ids, np.asarray(boxes, dtype=float).reshape(-1, 7), types, scores):
        context, _, ts = str(fid).rpartition(":")
        o = msg.objects.add(score=float(s), context_name=context, frame_timestamp_micros=int(ts))
        o.object.type = int(t)
        b = o.object.box
        b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading = (float(v) for v in box)
    return _write_bytes_atomic(Path(path), msg.SerializeToString())


def _write_bytes_atomic(path: Path, data: bytes) -> Path:
    import os

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------- Argoverse 2

AV2_LOG = "log_id"
AV2_SCORE = "score"


def _av2_columns() -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(required columns, numeric columns) of AV2 detections."""
    from labelaudit.datasets import av2

    numeric = (*av2.CENTRE, *av2.SIZE, *av2.QUATERNION, AV2_SCORE)
    return (AV2_LOG, av2.TIMESTAMP, av2.CATEGORY, *numeric), numeric


def _read_av2(
    path: Path, gt: GroundTruth, strict: bool
) -> tuple[dict[str, _Rows], list[str], dict[str, int], list[dict[str, Any]]]:
    from labelaudit import constants as C
    from labelaudit.core.geometry import quaternion_yaw
    from labelaudit.datasets import av2

    files = (
        [path]
        if path.is_file()
        else sorted(p for p in path.glob("*.feather") if p.is_file() and not p.name.startswith("."))
    )
    if not files:
        raise DetectionsError(path, "no .feather files found")
    required, numeric = _av2_columns()
    index = gt.index()
    out: dict[str, _Rows] = {}
    unknown: dict[str, int] = {}
    errors: list[dict[str, Any]] = []
    bad_frames: set[str] = set()
    for f in files:
        try:
            t = av2.read_feather(f, required, numeric=numeric)
        except DatasetError as exc:
            raise _as_detections_error(exc) from None
        logs, cats, stamps = (t.column(c).to_pylist() for c in (AV2_LOG, av2.CATEGORY, av2.TIMESTAMP))
        v = np.stack([t.column(c).to_numpy(zero_copy_only=False).astype(float) for c in numeric], axis=1).reshape(
            -1, len(numeric)
        )
        q = v[:, 6:10]
        with np.errstate(invalid="ignore", over="ignore"):
            bad = (
                ~np.isfinite(v).all(axis=1)
                | (v[:, 3:6] <= 0).any(axis=1)
                | ~(np.abs(np.linalg.norm(q, axis=1) - 1.0) <= C.AV2_QUATERNION_TOLERANCE)
            )
        yaw = quaternion_yaw(q)
        for r in range(t.num_rows):
            where = f"row {r}"
            fid = f"{logs[r]}:{stamps[r]}" if logs[r] is not None and isinstance(stamps[r], int) else None
            try:
                if fid is None:
                    raise DetectionsError(
                        f,
                        f"{where}: field {AV2_LOG!r} or {av2.TIMESTAMP!r}: missing (expected a log id and integer nanoseconds)",
                    )
                if fid not in index:
                    unknown[fid] = unknown.get(fid, 0) + 1
                    continue
                if fid in bad_frames:
                    continue
                if bad[r]:
                    raise DetectionsError(f, f"{where}: {_av2_problem(v[r], numeric)}")
                if not cats[r]:
                    raise DetectionsError(f, f"{where}: field {av2.CATEGORY!r}: missing")
            except DetectionsError as exc:
                if strict:
                    raise
                errors.append(_error(fid if fid in index else None, exc))
                if fid in index:
                    bad_frames.add(fid)
                    out.pop(fid, None)
                continue
            rows = out.setdefault(fid, _Rows())
            rows.boxes.append(np.array([*v[r, :6], yaw[r]]))
            rows.names.append(str(cats[r]))
            rows.scores.append(float(v[r, 10]))
            rows.height.append(math.nan)
            rows.cov.append(None)
            rows.source.append(f"{f}:{where}")
    missing = [fid for fid in index if fid not in out and fid not in bad_frames]
    return out, missing, unknown, errors


def _av2_problem(values: FloatArray, names: Sequence[str]) -> str:
    """What is wrong with one AV2 detection row (values in the order of ``names``)."""
    for n, x in zip(names, values):
        if not math.isfinite(x):
            return f"field {n!r}: expected a finite number, got {x!r}"
    for n, x in zip(names[3:6], values[3:6]):
        if x <= 0:
            return f"field {n!r}: expected a box size > 0, got {x:g}"
    return f"fields qw, qx, qy, qz = ({', '.join(f'{x:g}' for x in values[6:10])}): expected a unit quaternion"


def write_av2_detections(
    path: str | Path, frame_ids: Sequence[str], boxes: FloatArray, categories: Sequence[str], scores: Sequence[float]
) -> Path:
    """Write detections as one Argoverse 2 ``.feather`` file (atomically).

    Parameters
    ----------
    frame_ids : N "<log_id>:<timestamp_ns>" ids
    boxes : (N, 7) egovehicle-frame boxes (the yaw becomes qw, qz)
    categories : N AV2 categories
    scores : N scores
    """
    import os

    import pyarrow.feather as feather

    from labelaudit.core.geometry import yaw_quaternion
    from labelaudit.datasets import av2

    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    q = yaw_quaternion(b[:, 6]).reshape(-1, 4)
    parts = [str(fid).rpartition(":") for fid in frame_ids]
    cols: dict[str, Any] = {
        AV2_LOG: pa.array([p[0] for p in parts], pa.string()),
        av2.TIMESTAMP: pa.array([int(p[2]) for p in parts], pa.int64()),
        av2.CATEGORY: pa.array(list(categories), pa.string()),
    }
    for j, c in enumerate((*av2.CENTRE, *av2.SIZE)):
        cols[c] = pa.array(b[:, j])
    for j, c in enumerate(av2.QUATERNION):
        cols[c] = pa.array(q[:, j])
    cols[AV2_SCORE] = pa.array(np.asarray(scores, dtype=float))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    feather.write_feather(pa.table(cols), tmp, compression="uncompressed")
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------- Parquet


def _read_parquet(
    path: Path, gt: GroundTruth, strict: bool, view: str
) -> tuple[dict[str, _Rows], list[str], dict[str, int], list[dict[str, Any]]]:
    files = [path] if path.is_file() else sorted(p for p in path.glob("*.parquet") if not p.name.startswith("."))
    if not files:
        raise DetectionsError(path, "no .parquet files found")
    index = gt.index()
    out: dict[str, _Rows] = {}
    unknown: dict[str, int] = {}
    errors: list[dict[str, Any]] = []
    bad_frames: set[str] = set()
    p_dim = 6 if view == "bev" else 8
    for f in files:
        try:
            table = pq.read_table(f)
        except (OSError, pa.ArrowException) as exc:
            raise DetectionsError(f, f"not a readable Parquet file: {exc}") from None
        names = table.schema.names
        missing_cols = [n for n, _, req, _ in DETECTIONS_COLUMNS if req and n not in names]
        if missing_cols:
            raise DetectionsError(
                f, f"missing required column(s) {', '.join(missing_cols)} (schema: docs/eval.md § Detections formats)"
            )
        cols = {n: table.column(n).to_pylist() for n in names if n in DETECTIONS_SCHEMA.names}
        for r in range(table.num_rows):
            fid = cols["frame_id"][r]
            where = f"row {r}"
            try:
                if fid is None:
                    raise DetectionsError(f, f"{where}: field 'frame_id': missing")
                fid = str(fid)
                if fid not in index:
                    unknown[fid] = unknown.get(fid, 0) + 1
                    continue
                if fid in bad_frames:
                    continue
                vals = []
                for n in (*BOX_COLUMNS, "score"):
                    v = cols[n][r]
                    if v is None or not math.isfinite(float(v)):
                        raise DetectionsError(f, f"{where}: field {n!r}: expected a finite number, got {v!r}")
                    vals.append(float(v))
                for n, v in zip(BOX_COLUMNS[3:6], vals[3:6]):
                    if v <= 0:
                        raise DetectionsError(f, f"{where}: field {n!r}: expected a box size > 0, got {v:g}")
                cls_name = cols["class_name"][r]
                if cls_name is None or not str(cls_name):
                    raise DetectionsError(f, f"{where}: field 'class_name': missing")
                cov = _row_cov(cols, r, f, where, p_dim, view)
                height = math.nan
                if (
                    "bbox_top" in cols
                    and "bbox_bottom" in cols
                    and cols["bbox_top"][r] is not None
                    and cols["bbox_bottom"][r] is not None
                ):
                    height = float(cols["bbox_bottom"][r]) - float(cols["bbox_top"][r])
            except DetectionsError as exc:
                if strict:
                    raise
                errors.append(_error(fid if isinstance(fid, str) and fid in index else None, exc))
                if isinstance(fid, str) and fid in index:
                    bad_frames.add(fid)
                    out.pop(fid, None)
                continue
            rows = out.setdefault(fid, _Rows())
            rows.boxes.append(np.array(vals[:7]))
            rows.names.append(str(cls_name))
            rows.scores.append(vals[7])
            rows.height.append(height)
            rows.cov.append(cov)
            rows.source.append(f"{f}:{where}")
    missing = [fid for fid in index if fid not in out and fid not in bad_frames]
    return out, missing, unknown, errors


def _row_cov(
    cols: dict[str, list[Any]], r: int, f: Path, where: str, p_dim: int, view: str
) -> tuple[str, FloatArray] | None:
    """("phi", (p, p)) from ``cov``, ("box", diagonal) from ``std_*``, or None."""
    raw = cols.get("cov", [None] * (r + 1))[r]
    if raw is not None:
        a = np.asarray(raw, dtype=float)
        if a.size != p_dim * p_dim:
            raise DetectionsError(
                f,
                f"{where}: field 'cov': expected {p_dim}×{p_dim} = {p_dim * p_dim} values (φ covariance of the {view} view), got {a.size}",
            )
        m = a.reshape(p_dim, p_dim)
        if (
            not np.all(np.isfinite(m))
            or not np.allclose(m, m.T, rtol=1e-6, atol=1e-12)
            or np.linalg.eigvalsh(0.5 * (m + m.T)).min() < -1e-9 * max(1.0, float(np.abs(m).max()))
        ):
            raise DetectionsError(f, f"{where}: field 'cov': expected a finite symmetric positive semi-definite matrix")
        return ("phi", m)
    want = ("std_cx", "std_cy", "std_length", "std_width", "std_yaw") if view == "bev" else STD_COLUMNS
    present = [n for n in STD_COLUMNS if n in cols and cols[n][r] is not None]
    if not present:
        return None
    missing = [n for n in want if n not in present]
    if missing:
        raise DetectionsError(
            f,
            f"{where}: std columns {', '.join(present)} given but {', '.join(missing)} missing (the {view} view needs {', '.join(want)})",
        )
    stds = np.array([float(cols[n][r]) for n in want])
    if not np.all(np.isfinite(stds)) or np.any(stds < 0):
        raise DetectionsError(f, f"{where}: std columns must be finite and ≥ 0, got {dict(zip(want, stds.tolist()))}")
    return ("box", np.diag(stds**2))


def write_parquet_detections(path: str | Path, table: pa.Table) -> Path:
    """Write a detections table (columns of :data:`DETECTIONS_SCHEMA`) atomically."""
    from labelaudit.results import write_parquet_atomic

    return write_parquet_atomic(table, path)


# --------------------------------------------------------------------------- entry point


def read_detections(
    path: str | Path, gt: GroundTruth, fmt: str = "auto", *, strict: bool = True, view: str = "bev"
) -> Detections:
    """Read detections and align them with the frames of ``gt``.

    Parameters
    ----------
    path : detections file or folder
    gt : the ground truth (frame ids; KITTI calibrations)
    fmt : "auto", "kitti", "waymo", "parquet" or "av2"
    strict : raise at the first bad value; otherwise the frame's detections are dropped, the frame
        recorded in ``errors`` (and excluded from the evaluation by the caller)
    view : "bev" or "3d" — the dimension a Parquet ``cov`` must have

    Raises
    ------
    DetectionsError
        Unreadable input or (``strict``) a bad line/row/object.
    """
    path = Path(path)
    if fmt == "auto":
        fmt = detect_detections_format(path)
    if fmt not in DETECTION_FORMATS:
        raise ValueError(f"unknown detections format {fmt!r}; expected auto or one of {', '.join(DETECTION_FORMATS)}")
    if not path.exists():
        raise DetectionsError(path, "detections path does not exist")
    if fmt == "kitti":
        if gt.dataset_format != "kitti":
            raise DetectionsError(
                path,
                f"KITTI result files need a KITTI dataset, not {gt.dataset_format} (use Parquet detections in the vehicle frame)",
            )
        rows, missing, unknown, errors = _read_kitti(path, gt, strict)
    elif fmt == "waymo":
        rows, missing, unknown, errors = _read_waymo(path, gt, strict)
    elif fmt == "av2":
        rows, missing, unknown, errors = _read_av2(path, gt, strict)
    else:
        rows, missing, unknown, errors = _read_parquet(path, gt, strict, view)
    return _assemble(rows, gt, fmt, missing, unknown, errors)


def _assemble(
    rows: dict[str, _Rows],
    gt: GroundTruth,
    fmt: str,
    missing: list[str],
    unknown: dict[str, int],
    errors: list[dict[str, Any]],
) -> Detections:
    boxes, names, scores, height, covs, source, counts = [], [], [], [], [], [], []
    for f, fid in enumerate(gt.frame_ids):
        r = rows.get(fid)
        n = 0 if r is None else len(r.scores)
        counts.append(n)
        if not n:
            continue
        boxes.extend(r.boxes)
        names.extend(r.names)
        scores.extend(r.scores)
        h = np.asarray(r.height, dtype=float)
        if gt.calibs[f] is not None and np.isnan(h).any():
            h = np.where(np.isnan(h), _projected_heights(np.asarray(r.boxes), gt.calibs[f]), h)
        height.extend(h.tolist())
        covs.extend(r.cov)
        source.extend(r.source)
    n = len(scores)
    kinds = {c[0] for c in covs if c is not None}
    if len(kinds) > 1:
        raise DetectionsError(
            "detections", "mixed covariance forms: some rows give cov (on φ), others std_* (on the box); use one form"
        )
    cov = None
    has_cov = np.array([c is not None for c in covs], dtype=bool)
    cov_on = kinds.pop() if kinds else "phi"
    if has_cov.any():
        k = next(c[1] for c in covs if c is not None).shape[0]
        cov = np.full((n, k, k), np.nan)
        for i, c in enumerate(covs):
            if c is not None:
                cov[i] = c[1]
    return Detections(
        det_off=np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        boxes=np.asarray(boxes, dtype=float).reshape(-1, 7),
        class_names=names,
        scores=np.asarray(scores, dtype=float),
        height=np.asarray(height, dtype=float),
        cov=cov,
        cov_on=cov_on,
        has_cov=has_cov,
        source=source,
        format=fmt,
        frames_without_file=missing,
        unknown_frames=unknown,
        errors=errors,
    )


def _projected_heights(boxes: FloatArray, calib: Any) -> FloatArray:
    """2D box heights (px) of LiDAR-frame boxes projected into the KITTI image (devkit needs them)."""
    from labelaudit.datasets.kitti import project_box_to_image

    bbox = np.array([project_box_to_image(b, calib) for b in boxes.reshape(-1, 7)]).reshape(-1, 4)
    return bbox[:, 3] - bbox[:, 1]

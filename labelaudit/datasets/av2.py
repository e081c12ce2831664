"""Argoverse 2 sensor dataset reader: one log folder is one unit of work, one lidar timestamp one frame.
It reads Feather files and builds Frames; it does not audit.

Layout (``docs/datasets.md`` § Argoverse 2)::

    <root>/<split>/<log_id>/annotations.feather                  cuboids of every annotated timestamp
                           /city_SE3_egovehicle.feather          ego poses (egovehicle → city)
                           /sensors/lidar/<timestamp_ns>.feather one sweep per lidar timestamp
                           /calibration/egovehicle_SE3_sensor.feather   sensor mounts (optional)

``root`` may also be a split folder (its children are logs) or a single log folder.

* **Frames.** Every timestamp that has cuboids in ``annotations.feather`` or a sweep file is a
  frame, ``frame_id = "<log_id>:<timestamp_ns>"``. A timestamp with cuboids but no sweep file (a
  log shipped without some sweeps) or with an empty sweep is a frame with 0 points: its labels
  still become rows (status ``no_points``) so a track keeps every frame, and a warning says why.
  A sweep without cuboids is a frame without labels. An unreadable sweep is a
  :class:`~labelaudit.datasets.FrameFailure` (the errors table), the log's next frame still reads.
* **Boxes.** Cuboids and sweeps are both in the egovehicle frame (x forward, y left, z up; origin
  at the rear axle on the ground). ``tx_m, ty_m, tz_m`` is the geometric centre, the yaw is the
  heading of the quaternion ``qw, qx, qy, qz`` (:func:`~labelaudit.core.geometry.quaternion_yaw`).
  ``object_id`` is the ``track_uuid``, ``class_name`` the AV2 ``category`` (``REGULAR_VEHICLE`` …),
  and ``num_interior_pts`` (AV2's own count, boundary included) goes to the extra
  ``num_lidar_points_in_box``.
* **Points.** ``x, y, z`` (float16 in the files, exact in float32) and ``intensity``, as written:
  AV2's cuboids are annotated against these coordinates (no motion compensation here).
* **Rays.** Two VLP-32C lidars are stacked on the roof (``up_lidar`` lasers 0–31, ``down_lidar``
  lasers 32–63, one return per firing), 11.5 cm apart. Every point is a ray for the free-space
  evidence, cast from the midpoint of the two lidars (``sensor_origin``): the offset moves a ray by
  at most 5.8 cm in height and 3 mm sideways where it crosses a box, well inside the free-space
  tolerance. The mounts come from ``calibration/`` when the log has it, else
  :data:`~labelaudit.constants.AV2_LIDAR_MOUNTS`.
* **Poses.** ``Frame.pose`` is ``city_SE3_egovehicle`` at the frame's timestamp (exact match; AV2
  writes a pose at every lidar timestamp), None with a warning when missing.
* **Region of interest.** AV2 labels objects near the road only: within ``AV2_ROI_MARGIN`` (5 m) of
  the drivable area. When the log has its map (``map/log_map_archive_*.json``), the drivable-area
  polygons, moved into each frame with its pose, are ``Frame.roi``; without a map (or a pose) it is
  None and only the range limit says where labels exist. A map that cannot be used is a warning.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.feather as feather
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import invert_transform, quaternion_to_matrix, quaternion_yaw, transform_points
from labelaudit.datasets.base import Frame, FrameFailure, FrameRef, RegionOfInterest, box_problems
from labelaudit.datasets.waymo_common import check_extras
from labelaudit.errors import DatasetError, one_line

FORMAT = "av2"
ANNOTATIONS = "annotations.feather"
POSES = "city_SE3_egovehicle.feather"
SWEEP_DIR = Path("sensors") / "lidar"
CALIBRATION = Path("calibration") / "egovehicle_SE3_sensor.feather"
MAP_DIR = "map"
MAP_GLOB = "log_map_archive_*.json"

TIMESTAMP = "timestamp_ns"
TRACK = "track_uuid"
CATEGORY = "category"
CENTRE = ("tx_m", "ty_m", "tz_m")
SIZE = ("length_m", "width_m", "height_m")
QUATERNION = ("qw", "qx", "qy", "qz")
NUM_POINTS = "num_interior_pts"
SWEEP_COLUMNS = ("x", "y", "z", "intensity")
SWEEP_OPTIONAL = ("laser_number", "offset_ns")
LIDARS = ("up_lidar", "down_lidar")

_BOX_FIELDS = (*CENTRE, *SIZE, "yaw (from qw, qx, qy, qz)")
_EXTRA_FIELDS = {"num_lidar_points_in_box": NUM_POINTS}


# --------------------------------------------------------------------------- files


def read_feather(
    path: Path, required: tuple[str, ...], optional: tuple[str, ...] = (), numeric: tuple[str, ...] = ()
) -> pa.Table:
    """A Feather table with the ``required`` columns (and the ``optional`` ones it has).

    Raises
    ------
    DatasetError
        Not a readable Feather file, a required column missing, or a ``numeric`` column holding
        something else than numbers (the message names the file and the column).
    """
    try:
        table = feather.read_table(path)
    except FileNotFoundError:
        raise DatasetError(path, "file not found") from None
    except (OSError, pa.ArrowException, ValueError) as exc:
        raise DatasetError(path, f"not a readable Feather (Arrow IPC) file ({one_line(str(exc))[:300]})") from None
    missing = [c for c in required if c not in table.schema.names]
    if missing:
        raise DatasetError(
            path, f"missing column(s) {', '.join(missing)}; the file has {', '.join(table.schema.names) or 'none'}"
        )
    table = table.select([*required, *(c for c in optional if c in table.schema.names)])
    for c in numeric:
        if c in table.schema.names:
            t = table.schema.field(c).type
            if not (pa.types.is_integer(t) or pa.types.is_floating(t)):
                raise DatasetError(path, f"column {c}: expected numbers, found {t}")
    return table


def _floats(table: pa.Table, column: str) -> NDArray[np.float64]:
    """A numeric column as float64, nulls as NaN."""
    return table.column(column).to_numpy(zero_copy_only=False).astype(np.float64)


def _nulls(table: pa.Table, column: str) -> NDArray[np.bool_]:
    return pc.is_null(table.column(column)).to_numpy(zero_copy_only=False)


def _strings(table: pa.Table, column: str, path: Path) -> list[str | None]:
    t = table.schema.field(column).type
    if pa.types.is_dictionary(t):
        t = t.value_type
    if not (pa.types.is_string(t) or pa.types.is_large_string(t)):
        raise DatasetError(path, f"column {column}: expected text, found {table.schema.field(column).type}")
    return table.column(column).to_pylist()


def _timestamps(table: pa.Table, path: Path) -> NDArray[np.int64]:
    """The ``timestamp_ns`` column as int64; a null or non-integer timestamp names its row."""
    col = table.column(TIMESTAMP)
    if not pa.types.is_integer(col.type):
        raise DatasetError(path, f"column {TIMESTAMP}: expected integer nanoseconds, found {col.type}")
    if col.null_count:
        row = int(np.flatnonzero(_nulls(table, TIMESTAMP))[0])
        raise DatasetError(path, f"row {row}: {TIMESTAMP} is null (expected integer nanoseconds in every row)")
    return col.to_numpy().astype(np.int64)


def _quaternion_problems(q: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(K,) rows whose quaternion (K, 4) is not finite or not of unit norm (within the tolerance)."""
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.linalg.norm(q, axis=1)
        return ~(np.abs(norm - 1.0) <= C.AV2_QUATERNION_TOLERANCE)


def _quaternion_message(q: NDArray[np.float64]) -> str:
    with np.errstate(invalid="ignore", over="ignore"):
        norm = float(np.linalg.norm(q))
    return f"qw, qx, qy, qz = ({', '.join(f'{v:g}' for v in q)}) has norm {norm:g} (expected a unit quaternion)"


@dataclass
class Cuboids:
    """The rows of one ``annotations.feather``, as arrays (row order of the file).

    Attributes
    ----------
    timestamps : (R,) int64 ns
    boxes : (R, 7) cx, cy, cz, l, w, h, yaw (NaN where the file has a null or a bad quaternion)
    categories, tracks : R strings (None where null)
    num_points : (R,) AV2's ``num_interior_pts`` (int64, or float64 with NaN for nulls); None
        when the file has no such column
    problems : row → why the box cannot be used (names the file, row and columns)
    tilted : rows whose quaternion also turns about x or y (audited upright with their heading)
    """

    path: Path
    timestamps: NDArray[np.int64]
    boxes: NDArray[np.float64]
    categories: list[str | None]
    tracks: list[str | None]
    num_points: np.ndarray | None
    problems: dict[int, str] = field(default_factory=dict)
    tilted: list[int] = field(default_factory=list)


def read_cuboids(path: str | Path) -> Cuboids:
    """Read an Argoverse 2 ``annotations.feather``.

    Raises
    ------
    DatasetError
        Unreadable file, a missing or non-numeric column, a null timestamp. Bad values in a row
        (null, NaN, size ≤ 0, a quaternion that is not a unit quaternion) are not raised: they are
        in :attr:`Cuboids.problems`, so only that label becomes an error row.
    """
    path = Path(path)
    numeric = (*CENTRE, *SIZE, *QUATERNION, NUM_POINTS)
    t = read_feather(path, (TIMESTAMP, TRACK, CATEGORY, *CENTRE, *SIZE, *QUATERNION), (NUM_POINTS,), numeric)
    ts = _timestamps(t, path)
    tracks, categories = _strings(t, TRACK, path), _strings(t, CATEGORY, path)
    q = np.stack([_floats(t, c) for c in QUATERNION], axis=1).reshape(-1, 4)
    boxes = np.empty((len(ts), 7))
    for j, c in enumerate((*CENTRE, *SIZE)):
        boxes[:, j] = _floats(t, c)
    boxes[:, 6] = quaternion_yaw(q)
    bad_q = _quaternion_problems(q)
    boxes[bad_q, 6] = np.nan
    problems: dict[int, list[str]] = {}
    for c in (*CENTRE, *SIZE, *QUATERNION):
        for r in np.flatnonzero(_nulls(t, c)):
            problems.setdefault(int(r), []).append(f"{c} is null (expected a number)")
    for r in np.flatnonzero(bad_q):
        if int(r) not in problems:  # a null already says it
            problems.setdefault(int(r), []).append(_quaternion_message(q[r]))
    for r, message in box_problems(boxes, _BOX_FIELDS).items():
        if r not in problems:
            problems[r] = [message]
    with np.errstate(invalid="ignore"):
        up_z = quaternion_to_matrix(q)[:, 2, 2]  # z of the box's up axis: 1 when upright
        tilted = np.flatnonzero(~bad_q & (np.arccos(np.clip(up_z, -1.0, 1.0)) > C.AV2_MAX_TILT))
    num = None
    if NUM_POINTS in t.schema.names:
        col = t.column(NUM_POINTS)
        num = col.to_numpy(zero_copy_only=False)
        if not pa.types.is_integer(col.type) or col.null_count:
            num = num.astype(np.float64)  # check_extras names fractional or negative counts
    return Cuboids(
        path,
        ts,
        boxes,
        categories,
        tracks,
        num,
        {r: f"{path} row {r}: {'; '.join(m)}" for r, m in sorted(problems.items())},
        [int(r) for r in tilted],
    )


def read_city_poses(path: str | Path) -> tuple[dict[int, NDArray[np.float64]], list[str]]:
    """``{timestamp_ns: (4, 4) egovehicle → city}`` of a ``city_SE3_egovehicle.feather``, and warnings.

    Rows with a null, non-finite or non-unit quaternion or translation are left out, each named in
    a warning. Raises :class:`DatasetError` when the file cannot be read or lacks a column.
    """
    path = Path(path)
    t = read_feather(path, (TIMESTAMP, *QUATERNION, *CENTRE), numeric=(*QUATERNION, *CENTRE))
    ts = _timestamps(t, path)
    q = np.stack([_floats(t, c) for c in QUATERNION], axis=1).reshape(-1, 4)
    trans = np.stack([_floats(t, c) for c in CENTRE], axis=1).reshape(-1, 3)
    bad = _quaternion_problems(q) | ~np.isfinite(trans).all(axis=1)
    warnings = [
        f"{path} row {r}: pose {_quaternion_message(q[r])}, translation ({', '.join(f'{v:g}' for v in trans[r])}); "
        "left out (expected a unit quaternion and a finite translation)"
        for r in np.flatnonzero(bad)
    ]
    rot = quaternion_to_matrix(q)
    poses: dict[int, NDArray[np.float64]] = {}
    for r in np.flatnonzero(~bad):
        m = np.eye(4)
        m[:3, :3], m[:3, 3] = rot[r], trans[r]
        poses[int(ts[r])] = m
    return poses, warnings


def lidar_origin(log_dir: str | Path) -> tuple[NDArray[np.float64], list[str]]:
    """(3,) ray origin of a log — the midpoint of ``up_lidar`` and ``down_lidar`` in the egovehicle
    frame — and warnings.

    From ``calibration/egovehicle_SE3_sensor.feather`` when the log has it, else (and when it cannot
    be used, with a warning) from :data:`~labelaudit.constants.AV2_LIDAR_MOUNTS`.
    """
    path = Path(log_dir) / CALIBRATION
    default = np.mean([C.AV2_LIDAR_MOUNTS[n] for n in LIDARS], axis=0)
    if not path.is_file():
        return default, []
    try:
        t = read_feather(path, ("sensor_name", *CENTRE), numeric=CENTRE)
        names = _strings(t, "sensor_name", path)
    except DatasetError as exc:
        return default, [f"{exc}; the standard AV2 lidar mounts are used"]
    trans = np.stack([_floats(t, c) for c in CENTRE], axis=1).reshape(-1, 3)
    found = {n: trans[i] for i, n in enumerate(names) if n in LIDARS}
    missing = [n for n in LIDARS if n not in found or not np.isfinite(found[n]).all()]
    if missing:
        return default, [f"{path}: no usable row for {', '.join(missing)}; the standard AV2 lidar mounts are used"]
    return np.mean([found[n] for n in LIDARS], axis=0), []


def read_drivable_areas(log_dir: str | Path) -> tuple[list[NDArray[np.float64]], str, list[str]]:
    """The drivable-area polygons of a log's map — each (P, 3) x, y, z in the city frame — the map
    file and warnings.

    No ``map/`` folder: no polygons and no warning (the map is optional). A ``map/`` without exactly
    one ``log_map_archive_*.json``, a file that is not such JSON, or a polygon with a bad vertex or
    fewer than 3 vertices: those polygons are left out, each named in a warning.
    """
    folder = Path(log_dir) / MAP_DIR
    if not folder.is_dir():
        return [], "", []
    files = sorted(folder.glob(MAP_GLOB))
    if len(files) != 1:
        found = ", ".join(p.name for p in files) or "none"
        return [], "", [f"{folder}: expected one {MAP_GLOB} (found {found}); no region of interest, {_RANGE_ONLY}"]
    path = files[0]
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        areas = data["drivable_areas"]
        if not isinstance(areas, dict):
            raise TypeError(f"drivable_areas is a {type(areas).__name__}, expected an object of areas by id")
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
        return [], "", [f"{path}: not an AV2 map ({one_line(str(exc))[:200]}); no region of interest, {_RANGE_ONLY}"]
    polygons, bad = [], []
    for key, area in areas.items():
        try:
            v = np.array([[float(p["x"]), float(p["y"]), float(p["z"])] for p in area["area_boundary"]])
        except (KeyError, TypeError, ValueError):
            bad.append(f"{key} (a vertex without numeric x, y, z)")
            continue
        if len(v) < 3 or not np.isfinite(v).all():
            bad.append(f"{key} ({len(v)} vertices{'' if np.isfinite(v).all() else ', not all finite'})")
            continue
        polygons.append(v)
    warnings = []
    if bad:
        warnings.append(
            f"{path}: drivable area(s) {', '.join(bad[:5])}{' …' if len(bad) > 5 else ''} left out of the region of "
            "interest (expected 3 or more finite vertices)"
        )
    if not polygons:
        warnings.append(f"{path}: no usable drivable area; no region of interest, {_RANGE_ONLY}")
        return [], "", warnings
    return polygons, str(path), warnings


_RANGE_ONLY = "so missing-label candidates are limited by range only"


def frame_roi(polygons: list[NDArray[np.float64]], pose: NDArray[np.float64], source: str) -> RegionOfInterest:
    """The region of interest of one frame: the city-frame drivable areas (each (P, 3)) moved into
    the ego frame through ``pose`` (egovehicle → city, 4 × 4), grown by ``AV2_ROI_MARGIN``."""
    ego_city = invert_transform(pose)
    return RegionOfInterest(tuple(transform_points(ego_city, p)[:, :2] for p in polygons), C.AV2_ROI_MARGIN, source)


def read_sweep(path: str | Path, warnings: list[str]) -> NDArray[np.float32]:
    """(N, 4) float32 x, y, z, intensity of a lidar sweep file, in the egovehicle frame.

    Points with a non-finite coordinate are dropped, with a warning in ``warnings``.

    Raises
    ------
    DatasetError
        Unreadable file, a missing column, a column that is not numeric.
    """
    path = Path(path)
    t = read_feather(path, SWEEP_COLUMNS, numeric=SWEEP_COLUMNS)
    points = np.empty((t.num_rows, 4), dtype=np.float32)
    for j, c in enumerate(SWEEP_COLUMNS):
        points[:, j] = t.column(c).to_numpy(zero_copy_only=False).astype(np.float32)  # nulls become NaN
    finite = np.isfinite(points[:, :3]).all(axis=1)
    if not finite.all():
        warnings.append(
            f"{path}: dropped {int((~finite).sum())} of {len(points)} points with a null or non-finite x, y or z"
        )
        points = points[finite]
    return points


# --------------------------------------------------------------------------- layout


def _is_log(d: Path) -> bool:
    return (d / ANNOTATIONS).is_file() or (d / SWEEP_DIR).is_dir()


def find_logs(base: str | Path) -> list[Path]:
    """Log folders (with ``annotations.feather`` or ``sensors/lidar/``): ``base`` itself, else its
    children, else its grandchildren (``<root>/<split>/<log_id>``); sorted by path."""
    base = Path(base)
    if not base.is_dir():
        return []
    if _is_log(base):
        return [base]
    children = sorted(d for d in base.iterdir() if d.is_dir())
    logs = [d for d in children if _is_log(d)]
    if logs:
        return logs
    return [g for d in children for g in sorted(x for x in d.iterdir() if x.is_dir()) if _is_log(g)]


def _sweep_files(log_dir: Path, warnings: list[str]) -> dict[int, Path]:
    folder = log_dir / SWEEP_DIR
    out: dict[int, Path] = {}
    if not folder.is_dir():
        return out
    odd = []
    for p in sorted(folder.glob("*.feather")):
        if p.stem.isdigit():
            out[int(p.stem)] = p
        else:
            odd.append(p.name)
    if odd:
        warnings.append(
            f"{folder}: {len(odd)} file(s) not named <timestamp_ns>.feather are ignored ({', '.join(odd[:5])}{' …' if len(odd) > 5 else ''})"
        )
    return out


class Av2Reader:
    """Reader of Argoverse 2 sensor-dataset logs.

    Parameters
    ----------
    root : a log folder, a split folder of logs, or the dataset folder above the splits
    classes : AV2 categories to keep ("REGULAR_VEHICLE", "BUS" …); None keeps every label
    split : read only ``root/<split>/`` (e.g. "train", "val")
    """

    format_name = FORMAT

    def __init__(self, root: str | Path, classes: tuple[str, ...] | list[str] | None = None, split: str | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "expected an Argoverse 2 folder (<split>/<log_id>/annotations.feather …)")
        if split is not None and not (self.root / split).is_dir():
            raise DatasetError(self.root / split, f"split folder {split!r} not found")
        self.classes = None if classes is None else tuple(classes)
        self.split = split

    def list_units(self) -> list[FrameRef]:
        """One unit per labelled log folder (with ``annotations.feather``), sorted by path.

        Logs with sweeps but no annotations (AV2's test split) have no label to audit and are not
        units; when every log found is such a one, that is the error.
        """
        base = self.root / self.split if self.split else self.root
        logs = find_logs(base)
        if not logs:
            raise DatasetError(
                base,
                f"no Argoverse 2 log here or one or two levels down (expected <log_id>/{ANNOTATIONS} or <log_id>/{SWEEP_DIR}/)",
            )
        labelled = [d for d in logs if (d / ANNOTATIONS).is_file()]
        if not labelled:
            raise DatasetError(
                base,
                f"{len(logs)} Argoverse 2 log(s) but none with {ANNOTATIONS} (an unlabelled split such as test?): no label to audit",
            )
        return [FrameRef(FORMAT, str(self.root), str(d)) for d in labelled]

    def load_unit(self, ref: FrameRef) -> Iterator[Frame | FrameFailure]:
        """Frames of one log, by timestamp (see the module notes for what makes a frame).

        Log-level notes (no poses, odd file names, a calibration that cannot be used) are warnings
        of the log's first frame.

        Raises
        ------
        DatasetError
            When ``annotations.feather`` cannot be read or lacks a column, or has a null timestamp.
        """
        return self._frames(ref, with_points=True)

    def labels(self, ref: FrameRef) -> Iterator[Frame]:
        """The frames of one log as :meth:`load_unit` yields them, without reading a sweep (0 points):
        the same frames, boxes, ids, numbering, extras and ``object_errors`` — what ``eval`` reads."""
        for frame in self._frames(ref, with_points=False):
            assert isinstance(frame, Frame)  # no sweep is read, so none can fail
            yield frame

    def _frames(self, ref: FrameRef, with_points: bool) -> Iterator[Frame | FrameFailure]:
        log_dir = Path(ref.key)
        log_id = log_dir.name
        log_notes: list[str] = []
        ann_path = log_dir / ANNOTATIONS
        cuboids = read_cuboids(ann_path) if ann_path.is_file() else None
        if cuboids is None:
            log_notes.append(f"{log_dir}: no {ANNOTATIONS}; its sweeps are read as frames without labels")
        sweeps = _sweep_files(log_dir, log_notes)
        origin, notes = lidar_origin(log_dir)
        log_notes += notes
        drivable, map_source, notes = read_drivable_areas(log_dir)
        log_notes += notes
        poses: dict[int, NDArray[np.float64]] = {}
        pose_path = log_dir / POSES
        if pose_path.is_file():
            try:
                poses, notes = read_city_poses(pose_path)
                log_notes += notes
            except DatasetError as exc:
                log_notes.append(f"{exc}; frames have no ego pose")
        else:
            log_notes.append(f"{pose_path}: not found; frames have no ego pose")

        rows_of: dict[int, list[int]] = {}
        if cuboids is not None:
            for r in np.argsort(cuboids.timestamps, kind="stable"):
                rows_of.setdefault(int(cuboids.timestamps[r]), []).append(int(r))
            null_class = [r for r, c in enumerate(cuboids.categories) if c is None]
            if null_class:
                log_notes.append(
                    f"{ann_path}: row(s) {', '.join(map(str, null_class[:10]))}{' …' if len(null_class) > 10 else ''} have a null "
                    f"{CATEGORY}; left out ({len(null_class)} label(s) of unknown class)"
                )
            if cuboids.tilted:
                log_notes.append(
                    f"{ann_path}: row(s) {', '.join(map(str, cuboids.tilted[:10]))}{' …' if len(cuboids.tilted) > 10 else ''} are tilted "
                    f"by more than {C.AV2_MAX_TILT:g} rad (roll or pitch); audited upright with their heading"
                )
        for ts in sorted(set(rows_of) | set(sweeps)):
            frame_id = f"{log_id}:{ts}"
            warnings: list[str] = []
            sweep = sweeps.get(ts)
            try:
                points = (
                    read_sweep(sweep, warnings)
                    if sweep is not None and with_points
                    else np.zeros((0, 4), dtype=np.float32)
                )
            except DatasetError as exc:
                yield FrameFailure(frame_id, exc)
                continue
            frame = self._frame(
                frame_id, ts, rows_of.get(ts, []), cuboids, points, origin, poses.get(ts), warnings, str(sweep or "")
            )
            if drivable and frame.pose is not None:
                frame.roi = frame_roi(drivable, frame.pose, map_source)
            elif drivable:
                warnings.append(f"{map_source}: the frame has no ego pose to place the map; {_RANGE_ONLY}")
            if sweep is None:
                warnings.append(
                    f"{log_dir / SWEEP_DIR / f'{ts}.feather'}: no sweep for this annotated timestamp; read with 0 points "
                    "(every box gets status no_points)"
                )
            elif with_points and not len(points) and frame.num_objects:
                warnings.append(f"{sweep}: the sweep holds no points (every box gets status no_points)")
            if ts not in poses and pose_path.is_file() and poses:
                warnings.append(f"{pose_path}: no pose at timestamp {ts}; the frame has no ego pose")
            if log_notes:
                frame.warnings[:0] = log_notes
                log_notes = []
            yield frame

    def _frame(
        self,
        frame_id: str,
        ts: int,
        rows: list[int],
        cuboids: Cuboids | None,
        points: NDArray[np.float32],
        origin: NDArray[np.float64],
        pose: NDArray[np.float64] | None,
        warnings: list[str],
        source: str,
    ) -> Frame:
        if cuboids is not None:
            rows = [r for r in rows if cuboids.categories[r] is not None]
            if self.classes is not None:
                rows = [r for r in rows if cuboids.categories[r] in self.classes]
        idx = np.asarray(rows, dtype=np.int64)
        if cuboids is None or not rows:
            boxes, names, ids, extras = np.zeros((0, 7)), [], [], {}
            errors: dict[int, str] = {}
        else:
            boxes = cuboids.boxes[idx]
            names = [str(cuboids.categories[r]) for r in rows]
            ids = [
                f"{frame_id}:{j}" if cuboids.tracks[r] is None else str(cuboids.tracks[r]) for j, r in enumerate(rows)
            ]
            extras = {}
            if cuboids.num_points is not None:
                extras = check_extras(
                    {"num_lidar_points_in_box": cuboids.num_points[idx]},
                    _EXTRA_FIELDS,
                    [f"{cuboids.path} row {r}" for r in rows],
                    warnings,
                )
            errors = {j: cuboids.problems[r] for j, r in enumerate(rows) if r in cuboids.problems}
            seen: dict[str, int] = {}
            for j, r in enumerate(rows):
                if cuboids.tracks[r] is not None and seen.setdefault(ids[j], r) != r:
                    warnings.append(
                        f"{cuboids.path} rows {seen[ids[j]]} and {r}: track {ids[j]} has two cuboids at timestamp {ts}"
                    )
        return Frame(
            frame_id=frame_id,
            points=points,
            boxes=boxes,
            class_names=names,
            object_ids=ids,
            sensor_origin=origin.copy(),
            extras=extras,
            warnings=warnings,
            source=str(cuboids.path) if cuboids is not None else source,
            object_errors=errors,
            ray_mask=None,
            pose=None if pose is None else pose.copy(),
            timestamp=ts / 1e9,
        )


__all__ = [
    "Av2Reader",
    "Cuboids",
    "FORMAT",
    "find_logs",
    "frame_roi",
    "lidar_origin",
    "read_city_poses",
    "read_drivable_areas",
    "read_cuboids",
    "read_sweep",
]

"""Waymo Open Dataset v2 reader: one Parquet file per component and segment.
It reads files and builds Frames; it does not audit.

Layout: ``<root>/<component>/<segment_context_name>.parquet`` (``root`` may also be the folder
above one or more split folders: ``<root>/<split>/<component>/…``). Components read:

========================  ===========================================================
``lidar_box``             boxes (vehicle frame), type, laser_object_id, point counts
``lidar``                 range images per lidar and return (already decompressed)
``lidar_calibration``     extrinsic and beam inclinations per lidar
``lidar_pose``            TOP per-pixel vehicle pose (rolling-shutter correction)
``vehicle_pose``          vehicle → world per frame (float32 or float64 accepted)
========================  ===========================================================

A segment is one unit of work. Only the needed columns are read, and the two big components
(``lidar``, ``lidar_pose``) are read one row group at a time and released once every frame in a
row group has been built, so memory stays at a few frames even for a 200-frame segment.
"""

from __future__ import annotations

import math
from collections import defaultdict
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from numpy.typing import NDArray

from labelaudit.datasets.base import Frame, FrameFailure, FrameRef
from labelaudit.datasets.waymo_common import (
    TOP,
    FrameLabels,
    LidarCalibration,
    LidarData,
    check_extras,
    frame_points,
    make_frame,
    no_lidar_warning,
    sensor_origin,
)
from labelaudit.errors import DatasetError, one_line

FORMAT = "waymo-v2"
COMPONENTS = ("lidar_box", "lidar", "lidar_calibration", "lidar_pose", "vehicle_pose")

K_SEG = "key.segment_context_name"
K_TS = "key.frame_timestamp_micros"
K_LASER = "key.laser_name"
K_OBJ = "key.laser_object_id"

_BOX = "[LiDARBoxComponent]"
BOX_COLUMNS = {
    "cx": f"{_BOX}.box.center.x",
    "cy": f"{_BOX}.box.center.y",
    "cz": f"{_BOX}.box.center.z",
    "length": f"{_BOX}.box.size.x",
    "width": f"{_BOX}.box.size.y",
    "height": f"{_BOX}.box.size.z",
    "heading": f"{_BOX}.box.heading",
    "type": f"{_BOX}.type",
}
# optional per-object extras: output name -> column
BOX_EXTRAS = {
    "num_lidar_points_in_box": f"{_BOX}.num_lidar_points_in_box",
    "num_top_lidar_points_in_box": f"{_BOX}.num_top_lidar_points_in_box",
    "detection_difficulty": f"{_BOX}.difficulty_level.detection",
    "tracking_difficulty": f"{_BOX}.difficulty_level.tracking",
    "speed_x": f"{_BOX}.speed.x",
    "speed_y": f"{_BOX}.speed.y",
}
_BOX_KEYS = ("cx", "cy", "cz", "length", "width", "height", "heading")
_LIDAR = "[LiDARComponent]"
LIDAR_RETURNS = [(f"{_LIDAR}.range_image_return{k}.values", f"{_LIDAR}.range_image_return{k}.shape") for k in (1, 2)]
_POSE = "[LiDARPoseComponent]"
POSE_COLUMNS = (f"{_POSE}.range_image_return1.values", f"{_POSE}.range_image_return1.shape")
_CAL = "[LiDARCalibrationComponent]"
CAL_EXTRINSIC = f"{_CAL}.extrinsic.transform"
CAL_MIN = f"{_CAL}.beam_inclination.min"
CAL_MAX = f"{_CAL}.beam_inclination.max"
CAL_VALUES = f"{_CAL}.beam_inclination.values"
VEHICLE_POSE = "[VehiclePoseComponent].world_from_vehicle.transform"


@contextmanager
def _reading(path: Path) -> Iterator[None]:
    """Anything but a :class:`DatasetError` raised while reading ``path`` becomes one naming it
    (a truncated row group, a null key, a column of the wrong type …)."""
    try:
        yield
    except DatasetError:
        raise
    except (pa.ArrowException, OSError, ValueError, TypeError, OverflowError, IndexError, KeyError) as exc:
        detail = one_line(f"{type(exc).__name__}: {exc}")
        raise DatasetError(path, f"cannot read this component file ({detail[:300]})") from None


def _check_numeric(path: Path, schema: pa.Schema, columns: list[str]) -> None:
    for c in columns:
        if c in schema.names and not (
            pa.types.is_integer(schema.field(c).type) or pa.types.is_floating(schema.field(c).type)
        ):
            raise DatasetError(path, f"column {c}: expected numbers, found {schema.field(c).type}")


def _keys(table: pa.Table, column: str, path: Path) -> NDArray[np.int64]:
    """An integer key column as int64; a null or non-integer key is a :class:`DatasetError` naming the row."""
    col = table.column(column)
    if not pa.types.is_integer(col.type):
        raise DatasetError(path, f"column {column}: expected integers, found {col.type}")
    if col.null_count:
        row = int(np.flatnonzero(pc.is_null(col).to_numpy(zero_copy_only=False))[0])
        raise DatasetError(path, f"column {column} is null in row {row} (a key column must be set in every row)")
    return col.to_numpy().astype(np.int64)


def _check_columns(path: Path, schema: pa.Schema, required: list[str]) -> None:
    missing = [c for c in required if c not in schema.names]
    if missing:
        raise DatasetError(path, f"missing column(s) {', '.join(missing)}; the file has {', '.join(schema.names)}")


def _read(path: Path, required: list[str], optional: list[str] = ()) -> pa.Table:  # type: ignore[assignment]
    try:
        schema = pq.read_schema(path)
    except (OSError, pa.ArrowException) as exc:
        raise DatasetError(path, f"not a readable Parquet file: {exc}") from exc
    _check_columns(path, schema, required)
    cols = list(required) + [c for c in optional if c in schema.names]
    try:
        return pq.read_table(path, columns=cols)
    except (OSError, pa.ArrowException) as exc:
        raise DatasetError(path, f"cannot read columns {cols}: {exc}") from exc


def _matrices(column: pa.ChunkedArray, n: int, path: Path, what: str) -> NDArray[np.float64]:
    """(rows, n) float64 from a list / fixed_size_list column of float32 or float64."""
    flat = pc.list_flatten(column).to_numpy(zero_copy_only=False).astype(np.float64)
    if flat.size != len(column) * n:
        raise DatasetError(path, f"{what}: expected {n} values per row, got {flat.size} for {len(column)} rows")
    return flat.reshape(len(column), n)


class _RowGroupCache:
    """Rows of one big component file by frame timestamp, loading row groups on demand.

    A row group is dropped once every timestamp it holds has been taken, so a segment is read
    once, in order, with only the row groups of the current frame(s) in memory.
    """

    def __init__(self, path: Path, columns: list[str]):
        self.path = path
        try:
            self.file = pq.ParquetFile(path)
        except (OSError, pa.ArrowException) as exc:
            raise DatasetError(path, f"not a readable Parquet file: {exc}") from exc
        _check_columns(path, self.file.schema_arrow, [K_TS, *columns])
        self.columns = columns
        self.groups_of: dict[int, list[int]] = defaultdict(list)
        self.pending: dict[int, set[int]] = {}
        for g in range(self.file.num_row_groups):
            with _reading(path):
                ts = _keys(self.file.read_row_group(g, columns=[K_TS]), K_TS, path)
            uniq = set(int(t) for t in np.unique(ts))
            self.pending[g] = uniq
            for t in uniq:
                self.groups_of[t].append(g)
        self.loaded: dict[int, pa.Table] = {}

    def timestamps(self) -> set[int]:
        return set(self.groups_of)

    def take(self, ts: int) -> list[tuple[pa.Table, NDArray[np.int64]]]:
        """Rows of frame ``ts`` as (row-group table, row indices) pairs — no copy of the images.

        Empty when the file has no row for ``ts``. Releases row groups whose frames are all taken.
        """
        parts = []
        for g in self.groups_of.get(ts, []):
            if g not in self.loaded:
                self.pending[g].discard(ts)  # a row group that fails to read is not retried by every frame
                with _reading(self.path):
                    self.loaded[g] = self.file.read_row_group(g, columns=[K_TS, *self.columns])
            t = self.loaded[g]
            parts.append((t, np.flatnonzero(t.column(K_TS).to_numpy() == ts)))
            self.pending[g].discard(ts)
            if not self.pending[g]:
                del self.loaded[g]
        return parts


def _image(table: pa.Table, row: int, values: str, shape: str, path: Path) -> NDArray[np.float32] | None:
    v = table.column(values)[row]
    s = table.column(shape)[row]
    if not v.is_valid or not s.is_valid or len(v) == 0:
        return None
    dims = [int(d) for d in s.as_py() if d is not None]
    arr = v.values.to_numpy(zero_copy_only=False).astype(np.float32, copy=False)
    if len(dims) != 3 or min(dims) < 1 or math.prod(dims) != arr.size:
        raise DatasetError(path, f"{values}: {arr.size} values do not fill shape {s.as_py()} (expected [H, W, C])")
    return arr.reshape(dims)


class WaymoV2Reader:
    """Reader of Waymo v2 Parquet segments.

    Parameters
    ----------
    root : the folder holding the component folders (``lidar_box/``, ``lidar/`` …), or a folder
        above split folders that do
    classes : class names to keep ("Vehicle", "Pedestrian", "Sign", "Cyclist", "Unknown");
        None keeps every label
    split : read only ``root/<split>/`` (e.g. "training", "validation")
    """

    format_name = FORMAT

    def __init__(self, root: str | Path, classes: tuple[str, ...] | list[str] | None = None, split: str | None = None):
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "expected a Waymo v2 folder (with lidar_box/, lidar/ …)")
        if split is not None and not (self.root / split).is_dir():
            raise DatasetError(self.root / split, f"split folder {split!r} not found")
        self.classes = None if classes is None else tuple(classes)
        self.split = split

    def _split_dirs(self) -> list[Path]:
        base = self.root / self.split if self.split else self.root
        if (base / "lidar_box").is_dir():
            return [base]
        return sorted(p.parent for p in base.glob("*/lidar_box") if p.is_dir())

    def list_units(self) -> list[FrameRef]:
        """One unit per ``lidar_box/<segment>.parquet`` file, sorted by path."""
        dirs = self._split_dirs()
        if not dirs:
            raise DatasetError(
                self.root,
                "no lidar_box/ folder here or one level down (Waymo v2 layout <root>/<component>/<segment>.parquet)",
            )
        files = [p for d in dirs for p in sorted((d / "lidar_box").glob("*.parquet"))]
        if not files:
            raise DatasetError(self.root, "lidar_box/ holds no .parquet files")
        return [FrameRef(FORMAT, str(self.root), str(p)) for p in files]

    def labels(self, ref: FrameRef) -> Iterator[FrameLabels]:
        """The labels of one segment's frames, without their points (:func:`read_labels`)."""
        return read_labels(Path(ref.key))

    def load_unit(self, ref: FrameRef) -> Iterator[Frame | FrameFailure]:
        """Frames of one segment, by timestamp.

        A frame whose range images or poses cannot be read is a :class:`FrameFailure` naming the
        component file (``lidar``, ``lidar_pose`` …), and the next frame is read. Box rows with
        NaN/null/out-of-range values become ``frame.object_errors`` naming the row and column;
        rows with a null type are left out with a warning (their class is unknown).

        Raises
        ------
        DatasetError
            When a component file is missing, unreadable, or lacks a needed column, or a key
            column has nulls (the message names the file).
        """
        box_path = Path(ref.key)
        base, segment = box_path.parent.parent, box_path.stem
        paths = {c: base / c / f"{segment}.parquet" for c in COMPONENTS}
        for c, p in paths.items():
            if not p.is_file():
                raise DatasetError(
                    p, f"missing Waymo v2 component file for segment {segment} (expected <root>/{c}/<segment>.parquet)"
                )

        box_file = paths["lidar_box"]
        boxes_t = _read(box_file, [K_TS, K_OBJ, *BOX_COLUMNS.values()], list(BOX_EXTRAS.values()))
        _check_numeric(box_file, boxes_t.schema, [*BOX_COLUMNS.values(), *BOX_EXTRAS.values()])
        with _reading(paths["lidar_calibration"]):
            calibrations = self._calibrations(paths["lidar_calibration"])
        with _reading(paths["vehicle_pose"]):
            poses = self._vehicle_poses(paths["vehicle_pose"])
        lidar = _RowGroupCache(paths["lidar"], [K_LASER, *(c for pair in LIDAR_RETURNS for c in pair)])
        lidar_pose = _RowGroupCache(paths["lidar_pose"], [K_LASER, *POSE_COLUMNS])
        origin = sensor_origin(calibrations)

        with _reading(box_file):
            ts_all = _keys(boxes_t, K_TS, box_file)
            order = np.argsort(ts_all, kind="stable")
            rows_of: dict[int, list[int]] = defaultdict(list)
            for i in order:
                rows_of[int(ts_all[i])].append(int(i))
            # nulls read as NaN: float64 for every box column, the null rows named below
            box_arrays = {
                k: boxes_t.column(c).to_numpy(zero_copy_only=False).astype(np.float64) for k, c in BOX_COLUMNS.items()
            }
            type_col = boxes_t.column(BOX_COLUMNS["type"])  # exact integers (a float64 copy rounds beyond 2^53)
            box_arrays["type"] = (
                pc.fill_null(type_col, 0).to_numpy(zero_copy_only=False).astype(np.int64)
                if pa.types.is_integer(type_col.type)
                else box_arrays["type"]
            )
            box_nulls = {
                k: pc.is_null(boxes_t.column(c)).to_numpy(zero_copy_only=False) for k, c in BOX_COLUMNS.items()
            }
            ids = boxes_t.column(K_OBJ).to_pylist()
            # same dtypes as the v1 reader (int64 counts and levels, float64 speeds); a null stays NaN (null in the results)
            extras_all = {}
            for k, c in BOX_EXTRAS.items():
                if c in boxes_t.schema.names:
                    v = boxes_t.column(c).to_numpy(zero_copy_only=False).astype(np.float64)
                    exact = len(v) == 0 or (not np.isnan(v).any() and np.abs(v).max() < 2**62)
                    extras_all[k] = (
                        v.astype(np.int64) if exact and not k.startswith("speed") else v
                    )  # else check_extras names them

        for ts in sorted(rows_of):
            frame_id = f"{segment}:{ts}"
            try:
                frame = self._frame(
                    ts,
                    frame_id,
                    rows_of[ts],
                    box_arrays,
                    box_nulls,
                    ids,
                    extras_all,
                    calibrations,
                    poses,
                    lidar,
                    lidar_pose,
                    origin,
                    paths,
                )
            except DatasetError as exc:  # this frame only: the next one still reads
                yield FrameFailure(frame_id, exc)
                continue
            yield frame

    def _frame(
        self,
        ts: int,
        frame_id: str,
        rows: list[int],
        box_arrays: dict[str, NDArray[np.float64]],
        box_nulls: dict[str, NDArray[np.bool_]],
        ids: list[object],
        extras_all: dict[str, np.ndarray],
        calibrations: dict[int, LidarCalibration],
        poses: dict[int, NDArray[np.float64]],
        lidar: "_RowGroupCache",
        lidar_pose: "_RowGroupCache",
        origin: NDArray[np.float64],
        paths: dict[str, Path],
    ) -> Frame:
        box_file = paths["lidar_box"]
        warnings: list[str] = []
        null_type = [r for r in rows if box_nulls["type"][r]]
        if null_type:
            warnings.append(
                f"{box_file}: row(s) {', '.join(map(str, null_type[:10]))}{' …' if len(null_type) > 10 else ''} of frame {frame_id} "
                f"have a null {BOX_COLUMNS['type']}; left out ({len(null_type)} label(s) of unknown class)"
            )
            rows = [r for r in rows if not box_nulls["type"][r]]
        idx = np.asarray(rows, dtype=np.int64)
        boxes = np.stack([box_arrays[k][idx] for k in _BOX_KEYS], axis=1).reshape(-1, 7)
        with np.errstate(invalid="ignore"):  # a float type column: values beyond int64 become a (named) odd class
            types = box_arrays["type"][idx].astype(np.int64)
        locations = [f"{box_file} row {r}" for r in rows]
        object_errors = {}
        for j, r in enumerate(rows):
            null_cols = [BOX_COLUMNS[k] for k in _BOX_KEYS if box_nulls[k][r]]
            if null_cols:
                object_errors[j] = f"{locations[j]}: {', '.join(null_cols)} is null (expected a number)"
        frame_pose = poses.get(ts)
        with _reading(paths["lidar_pose"]):
            pixel_pose = self._pixel_poses(lidar_pose.take(ts), paths["lidar_pose"])
        with _reading(paths["lidar"]):
            lidars = self._lidar_images(lidar.take(ts), pixel_pose, paths["lidar"])
        if lidars:
            if frame_pose is None:
                warnings.append(f"{paths['vehicle_pose']}: no vehicle pose for frame {frame_id}")
            points, ray_mask, no_label_zone = frame_points(lidars, calibrations, frame_pose, paths["lidar"], warnings)
        else:
            points, ray_mask = np.zeros((0, 4), dtype=np.float32), np.zeros(0, dtype=bool)
            no_label_zone = ray_mask
            warnings.append(no_lidar_warning(paths["lidar"], frame_id, len(idx)))
        extras = check_extras({k: v[idx] for k, v in extras_all.items()}, BOX_EXTRAS, locations, warnings)
        object_ids = [f"{frame_id}:{j}" if ids[r] is None else str(ids[r]) for j, r in enumerate(rows)]
        return make_frame(
            frame_id,
            points,
            boxes,
            types,
            object_ids,
            extras,
            origin,
            warnings,
            self.classes,
            source=str(box_file),
            locations=locations,
            box_fields=tuple(BOX_COLUMNS[k] for k in _BOX_KEYS),
            object_errors=object_errors,
            ray_mask=ray_mask,
            no_label_zone=no_label_zone,
            pose=frame_pose,
            timestamp=ts / 1e6,
        )

    @staticmethod
    def _calibrations(path: Path) -> dict[int, LidarCalibration]:
        t = _read(path, [K_LASER, CAL_EXTRINSIC, CAL_MIN, CAL_MAX], [CAL_VALUES])
        extr = _matrices(t.column(CAL_EXTRINSIC), 16, path, CAL_EXTRINSIC).reshape(-1, 4, 4)
        names = t.column(K_LASER).to_pylist()
        lo, hi = t.column(CAL_MIN).to_pylist(), t.column(CAL_MAX).to_pylist()
        values = t.column(CAL_VALUES).to_pylist() if CAL_VALUES in t.schema.names else [None] * len(names)
        out = {}
        for i, name in enumerate(names):
            out[int(name)] = LidarCalibration(
                name=int(name),
                extrinsic=extr[i],
                inclination_min=float(lo[i] if lo[i] is not None else 0.0),
                inclination_max=float(hi[i] if hi[i] is not None else 0.0),
                inclinations=np.asarray(values[i] or [], dtype=np.float64),
            )
        return out

    @staticmethod
    def _vehicle_poses(path: Path) -> dict[int, NDArray[np.float64]]:
        t = _read(path, [K_TS, VEHICLE_POSE])
        mats = _matrices(t.column(VEHICLE_POSE), 16, path, VEHICLE_POSE).reshape(-1, 4, 4)
        return {int(ts): mats[i] for i, ts in enumerate(t.column(K_TS).to_numpy())}

    @staticmethod
    def _pixel_poses(pose_rows: list[tuple[pa.Table, NDArray[np.int64]]], path: Path) -> dict[int, NDArray[np.float32]]:
        pixel_pose: dict[int, NDArray[np.float32]] = {}
        for table, idx in pose_rows:
            names = table.column(K_LASER)
            for i in idx:
                img = _image(table, int(i), *POSE_COLUMNS, path)
                if img is not None:
                    pixel_pose[int(names[int(i)].as_py())] = img
        return pixel_pose

    @staticmethod
    def _lidar_images(
        rows: list[tuple[pa.Table, NDArray[np.int64]]], pixel_pose: dict[int, NDArray[np.float32]], path: Path
    ) -> list[LidarData]:
        out = []
        for table, idx in rows:
            names = table.column(K_LASER)
            for i in idx:
                name = int(names[int(i)].as_py())
                returns = [
                    img
                    for vals, shape in LIDAR_RETURNS
                    if (img := _image(table, int(i), vals, shape, path)) is not None
                ]
                if returns:
                    # only TOP has per-pixel poses in Waymo; use whatever the file provides
                    out.append(LidarData(name=name, returns=returns, pixel_pose=pixel_pose.get(name)))
        return out


def read_vehicle_poses(path: str | Path) -> dict[int, NDArray[np.float64]]:
    """``{timestamp: (4, 4) world_from_vehicle}`` of a ``vehicle_pose`` component file."""
    return WaymoV2Reader._vehicle_poses(Path(path))


__all__ = ["WaymoV2Reader", "read_vehicle_poses", "COMPONENTS", "TOP"]


def read_labels(box_path: str | Path) -> Iterator[FrameLabels]:
    """The labels of every frame of one segment (its ``lidar_box`` file), by timestamp, file order
    within a frame (the reader's order); the sensor origin from ``lidar_calibration`` when present.

    Raises
    ------
    DatasetError
        An unreadable file or a missing column (the message names the file).
    """
    box_path = Path(box_path)
    segment = box_path.stem
    t = _read(box_path, [K_TS, *BOX_COLUMNS.values()], list(BOX_EXTRAS.values()))
    cal_path = box_path.parent.parent / "lidar_calibration" / f"{segment}.parquet"
    origin = sensor_origin(WaymoV2Reader._calibrations(cal_path)) if cal_path.is_file() else np.zeros(3)
    ts_all = t.column(K_TS).to_numpy()
    order = np.argsort(ts_all, kind="stable")
    rows_of: dict[int, list[int]] = defaultdict(list)
    for i in order:
        rows_of[int(ts_all[i])].append(int(i))
    cols = {k: t.column(c).to_numpy(zero_copy_only=False) for k, c in BOX_COLUMNS.items()}

    def extra(name: str, default: int) -> NDArray[np.int64]:
        c = BOX_EXTRAS[name]
        if c not in t.schema.names:
            return np.full(t.num_rows, default, dtype=np.int64)
        return np.nan_to_num(t.column(c).to_numpy(zero_copy_only=False).astype(float), nan=default).astype(np.int64)

    level, points = extra("detection_difficulty", 0), extra("num_lidar_points_in_box", -1)
    for ts in sorted(rows_of):
        idx = np.asarray(rows_of[ts])
        yield FrameLabels(
            frame_id=f"{segment}:{ts}",
            boxes=np.stack([cols[k][idx].astype(float) for k in _BOX_KEYS], axis=1).reshape(len(idx), 7),
            types=cols["type"][idx].astype(np.int64),
            difficulty=level[idx],
            num_points=points[idx],
            sensor_origin=np.asarray(origin, dtype=float),
            source=str(box_path),
        )

"""What the Waymo v1 (TFRecord) and v2 (Parquet) readers share: classes, calibration, range image → points.
Pure conversions, no file access.

Both forms store the same data: per lidar a range image (H × W × 4: range, intensity, elongation,
no-label-zone flag) per return, a calibration (extrinsic, beam inclinations), and for the TOP
lidar a per-pixel vehicle pose (H × W × 6: roll, pitch, yaw, x, y, z) for rolling-shutter
correction. :func:`range_image_to_points` is the one conversion both readers call.

Conventions (see ``docs/datasets.md`` § Waymo):

* Row 0 of a range image is the *highest* beam; calibrations list inclinations ascending.
* Column j looks along the vehicle-frame azimuth ``π − (j + ½)·2π/W`` (from +π at the left edge
  down to −π at the right edge); in the sensor frame that is minus the lidar's mounting yaw.
* Pixel poses are vehicle→world at the pixel's capture time, R = Rz(yaw)·Ry(pitch)·Rx(roll).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.datasets.base import Frame, box_problems

# Waymo label.proto Label.Type; names as the Waymo tools print them without the TYPE_ prefix.
CLASS_NAMES: dict[int, str] = {0: "Unknown", 1: "Vehicle", 2: "Pedestrian", 3: "Sign", 4: "Cyclist"}
# dataset.proto LaserName.Name
LASER_NAMES: dict[int, str] = {1: "TOP", 2: "FRONT", 3: "SIDE_LEFT", 4: "SIDE_RIGHT", 5: "REAR"}
TOP = 1


def class_name(label_type: int) -> str:
    """Class name of a Waymo label type (unknown numbers become ``"Type<n>"``)."""
    return CLASS_NAMES.get(int(label_type), f"Type{int(label_type)}")


def waymo_level(detection_difficulty: NDArray[np.integer], num_points: NDArray[np.integer]) -> NDArray[np.int8]:
    """Waymo difficulty level of each GT box: 2 when labelled LEVEL_2 or with at most
    ``EVAL_WAYMO_LEVEL2_MAX_POINTS`` points, else 1 (unknown levels count as LEVEL_1, like Waymo)."""
    lvl = np.asarray(detection_difficulty)
    pts = np.asarray(num_points)
    return np.where((lvl == 2) | (pts <= C.EVAL_WAYMO_LEVEL2_MAX_POINTS), 2, 1).astype(np.int8)


@dataclass(frozen=True)
class FrameLabels:
    """The labels of one Waymo frame without its points (what ``eval`` reads: no range image is decoded).

    Attributes
    ----------
    frame_id : ``<segment>:<timestamp_micros>``, as the readers name frames
    boxes : (K, 7) vehicle-frame boxes (cx, cy, cz, length, width, height, heading), in label order
    types : (K,) Waymo label types (:data:`CLASS_NAMES`)
    difficulty : (K,) detection difficulty level (0 unset, 1, 2)
    num_points : (K,) the dataset's LiDAR point count per box (−1 unknown)
    sensor_origin : (3,) the TOP lidar's position in the vehicle frame
    source : the segment file
    """

    frame_id: str
    boxes: NDArray[np.float64]
    types: NDArray[np.int64]
    difficulty: NDArray[np.int64]
    num_points: NDArray[np.int64]
    sensor_origin: NDArray[np.float64]
    source: str


@dataclass
class LidarCalibration:
    """Calibration of one lidar.

    Attributes
    ----------
    name : laser name number (1 TOP, 2 FRONT, 3 SIDE_LEFT, 4 SIDE_RIGHT, 5 REAR)
    extrinsic : (4, 4) lidar → vehicle transform
    inclination_min, inclination_max : radians, used when ``inclinations`` is empty
    inclinations : (H,) explicit beam inclinations in ascending order, or an empty array
    """

    name: int
    extrinsic: NDArray[np.float64]
    inclination_min: float = 0.0
    inclination_max: float = 0.0
    inclinations: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))

    def row_inclinations(self, height: int) -> NDArray[np.float64]:
        """(H,) elevation of each range-image row, row 0 the highest beam.

        Explicit inclinations when the calibration lists them (TOP), else ``height`` values evenly
        spaced at row centres between min and max.
        """
        if self.inclinations.size:
            if self.inclinations.size != height:
                raise ValueError(
                    f"lidar {LASER_NAMES.get(self.name, self.name)}: calibration has "
                    f"{self.inclinations.size} beam inclinations but the range image has {height} rows"
                )
            return self.inclinations[::-1].astype(np.float64)
        i = np.arange(height, dtype=np.float64)
        ascending = self.inclination_min + (i + 0.5) / height * (self.inclination_max - self.inclination_min)
        return ascending[::-1]


def column_azimuths(width: int, extrinsic: NDArray[np.float64]) -> NDArray[np.float64]:
    """(W,) sensor-frame azimuth of each range-image column (vehicle azimuth minus mounting yaw)."""
    j = np.arange(width, dtype=np.float64)
    yaw_mount = np.arctan2(extrinsic[1, 0], extrinsic[0, 0])
    return ((width - j - 0.5) / width * 2.0 - 1.0) * np.pi - yaw_mount


def euler_to_matrix(roll: NDArray, pitch: NDArray, yaw: NDArray) -> NDArray[np.float64]:
    """(..., 3, 3) rotation R = Rz(yaw)·Ry(pitch)·Rx(roll) for arrays of angles."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    cy, sy = np.cos(yaw), np.sin(yaw)
    r = np.empty(np.shape(roll) + (3, 3))
    r[..., 0, 0] = cy * cp
    r[..., 0, 1] = cy * sp * sr - sy * cr
    r[..., 0, 2] = cy * sp * cr + sy * sr
    r[..., 1, 0] = sy * cp
    r[..., 1, 1] = sy * sp * sr + cy * cr
    r[..., 1, 2] = sy * sp * cr - cy * sr
    r[..., 2, 0] = -sp
    r[..., 2, 1] = cp * sr
    r[..., 2, 2] = cp * cr
    return r


_DIRECTION_CACHE: dict[tuple, NDArray[np.float64]] = {}
_DIRECTION_CACHE_SIZE = 16  # (lidar, image size) direction grids kept; a dataset has 5 lidars


def ray_directions(calibration: LidarCalibration, height: int, width: int) -> NDArray[np.float64]:
    """(H, W, 3) unit ray direction of every pixel in the vehicle frame (extrinsic rotation applied).

    Depends only on the calibration and the image size, so it is cached: per frame only the
    ranges change.
    """
    e = np.asarray(calibration.extrinsic, dtype=np.float64)
    key = (
        calibration.name,
        height,
        width,
        e.tobytes(),
        calibration.inclination_min,
        calibration.inclination_max,
        np.asarray(calibration.inclinations, dtype=np.float64).tobytes(),
    )
    dirs = _DIRECTION_CACHE.get(key)
    if dirs is None:
        el = calibration.row_inclinations(height)
        az = column_azimuths(width, e)
        ce, se = np.cos(el)[:, None], np.sin(el)[:, None]
        sensor = np.stack(np.broadcast_arrays(ce * np.cos(az)[None, :], ce * np.sin(az)[None, :], se), axis=-1)
        dirs = np.ascontiguousarray(sensor @ e[:3, :3].T)
        if len(_DIRECTION_CACHE) >= _DIRECTION_CACHE_SIZE:
            _DIRECTION_CACHE.pop(next(iter(_DIRECTION_CACHE)))
        _DIRECTION_CACHE[key] = dirs
    return dirs


def _apply(rot: NDArray[np.float64], trans: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Per-point rigid transform: rot (N, 3, 3), trans (N, 3), p (N, 3)."""
    return rot[:, :, 0] * p[:, 0:1] + rot[:, :, 1] * p[:, 1:2] + rot[:, :, 2] * p[:, 2:3] + trans


def range_image_to_points(
    range_image: NDArray[np.floating],
    calibration: LidarCalibration,
    pixel_pose: NDArray[np.floating] | None = None,
    frame_pose: NDArray[np.floating] | None = None,
) -> NDArray[np.float32]:
    """Points of one range image (one lidar, one return) in the frame's vehicle frame.

    Parameters
    ----------
    range_image : (H, W, C≥2) — channel 0 range in metres (≤ 0 = no return), channel 1 intensity
    calibration : the lidar's calibration
    pixel_pose : optional (H, W, 6) roll, pitch, yaw, x, y, z — vehicle→world at each pixel's
        capture time (TOP lidar only). Needs ``frame_pose``.
    frame_pose : (4, 4) vehicle→world at the frame timestamp

    Returns
    -------
    (M, 4) float32 x, y, z, intensity of the pixels with range > 0, in row-major pixel order.
    """
    ri = np.asarray(range_image)
    if ri.ndim != 3 or ri.shape[2] < 2:
        raise ValueError(f"range image must be (H, W, C>=2), got shape {ri.shape}")
    h, w = ri.shape[:2]
    if pixel_pose is not None:
        if frame_pose is None:
            raise ValueError("a per-pixel pose needs the frame pose (vehicle → world)")
        pp = np.asarray(pixel_pose)
        if pp.shape[:2] != (h, w) or pp.shape[2] < 6:
            raise ValueError(f"pixel pose shape {pp.shape} does not match range image {(h, w)} x 6")
    if ri.dtype == np.float32 and h and w:  # as the readers give them: the compiled pass
        return _range_image_points(ri, calibration, pixel_pose, frame_pose)
    return _range_image_points_numpy(ri, calibration, pixel_pose, frame_pose)


def _range_image_points_numpy(
    ri: NDArray[np.floating],
    calibration: LidarCalibration,
    pixel_pose: NDArray[np.floating] | None,
    frame_pose: NDArray[np.floating] | None,
) -> NDArray[np.float32]:
    """:func:`range_image_to_points` of a checked range image (H, W, C ≥ 2) in NumPy passes: any
    float type, and pixel poses that vary within a column."""
    h, w = ri.shape[:2]
    valid = ri[..., 0] > 0  # NaN compares False: dropped too
    r = ri[..., 0][valid].astype(np.float64)
    extrinsic = np.asarray(calibration.extrinsic, dtype=np.float64)
    p = ray_directions(calibration, h, w)[valid] * r[:, None] + extrinsic[:3, 3]
    if pixel_pose is not None:
        pp = np.asarray(pixel_pose)
        fp = np.asarray(frame_pose, dtype=np.float64)
        f_rot_t = fp[:3, :3].T
        if (pp == pp[:1]).all():
            # Poses vary by column only (one capture time per azimuth): compose per column, then
            # gather — W rotations instead of one per point.
            rot, trans = _column_transforms(pp[0], fp)
            cols = np.nonzero(valid)[1]
            p = _apply(rot[cols], trans[cols], p)
        else:
            px = pp[valid].astype(np.float64)
            rot = f_rot_t @ euler_to_matrix(px[:, 0], px[:, 1], px[:, 2])
            p = _apply(rot, (px[:, 3:6] - fp[:3, 3]) @ f_rot_t.T, p)
    out = np.empty((len(r), 4), dtype=np.float32)
    out[:, :3] = p
    out[:, 3] = ri[..., 1][valid]
    return out


def _range_image_points(
    ri: NDArray[np.float32],
    calibration: LidarCalibration,
    pixel_pose: NDArray[np.floating] | None,
    frame_pose: NDArray[np.floating] | None,
) -> NDArray[np.float32]:
    """:func:`range_image_to_points` of a float32 range image (H, W, C ≥ 2), H, W ≥ 1: the same
    float64 operations in the same order, the points in one compiled pass
    (:func:`~labelaudit.core.pointops.range_image_points`); pixel poses that vary within a column
    take the NumPy path."""
    from labelaudit.core.pointops import range_image_points, rows_equal_first

    h, w = ri.shape[:2]
    extrinsic = np.asarray(calibration.extrinsic, dtype=np.float64)
    dirs = ray_directions(calibration, h, w)
    t = np.ascontiguousarray(extrinsic[:3, 3])
    rot, trans = _NO_ROT, _NO_TRANS
    if pixel_pose is not None:
        pp = np.asarray(pixel_pose)
        if not (pp.dtype == np.float32 and rows_equal_first(_read_only(pp))):
            return _range_image_points_numpy(ri, calibration, pixel_pose, frame_pose)
        # one capture time per azimuth: one transform per column
        rot, trans = _column_transforms(pp[0], np.asarray(frame_pose, dtype=np.float64))
        rot, trans = np.ascontiguousarray(rot), np.ascontiguousarray(trans)
    return range_image_points(_read_only(ri), dirs, t, rot, trans, pixel_pose is not None)


def _column_transforms(
    col_pose: NDArray[np.floating], frame_pose: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per column, the rotation (W, 3, 3) and translation (W, 3) from the vehicle frame at the
    column's capture time (``col_pose`` (W, ≥6): roll, pitch, yaw, x, y, z → world) to the
    vehicle frame at the frame's timestamp (``frame_pose`` (4, 4))."""
    col = col_pose.astype(np.float64)
    f_rot_t = frame_pose[:3, :3].T
    rot = f_rot_t @ euler_to_matrix(col[:, 0], col[:, 1], col[:, 2])
    trans = (col[:, 3:6] - frame_pose[:3, 3]) @ f_rot_t.T  # subtract first: keeps precision at large t
    return rot, trans


def _read_only(a: NDArray) -> NDArray:
    """A C-contiguous read-only view (or copy) of ``a``: the kernels' one argument type, whether
    the image came from Arrow (read-only) or was decoded into a writable array."""
    v = np.ascontiguousarray(a).view()
    v.flags.writeable = False
    return v


_NO_ROT = np.zeros((1, 3, 3))  # the kernel's column transforms when the image has no pixel poses
_NO_TRANS = np.zeros((1, 3))


@dataclass
class LidarData:
    """Range images of one lidar in one frame (either return may be missing)."""

    name: int
    returns: list[NDArray[np.float32]]
    pixel_pose: NDArray[np.float32] | None = None


def frame_points(
    lidars: list[LidarData],
    calibrations: dict[int, LidarCalibration],
    frame_pose: NDArray[np.floating] | None,
    source: str | Path,
    warnings: list[str],
) -> tuple[NDArray[np.float32], NDArray[np.bool_], NDArray[np.bool_]]:
    """Concatenate the points of all lidars and returns of a frame: (N, 4) float32 points, an (N,)
    bool mask of the TOP lidar's first returns and an (N,) bool mask of the points Waymo marks as in a
    No Label Zone (channel 3 of the range image > 0; an image without that channel has none).

    Only those are rays from :func:`sensor_origin` whose path up to the point is empty: the four
    short-range lidars sit elsewhere on the vehicle, and a second return lies behind a surface that
    already returned the first (free-space evidence, docs/label-error.md). Problems that lose part
    of the cloud (no calibration for a lidar, TOP pose without frame pose) are appended to
    ``warnings`` and the affected lidar is skipped or left uncorrected.
    """
    parts: list[NDArray[np.float32]] = []
    rays: list[NDArray[np.bool_]] = []
    zones: list[NDArray[np.bool_]] = []
    for lidar in sorted(lidars, key=lambda d: d.name):
        calib = calibrations.get(lidar.name)
        label = LASER_NAMES.get(lidar.name, str(lidar.name))
        if calib is None:
            warnings.append(f"{source}: no calibration for lidar {label}; its points are skipped")
            continue
        pose = lidar.pixel_pose
        if pose is not None and frame_pose is None:
            warnings.append(
                f"{source}: lidar {label} has per-pixel poses but the frame has no pose; not motion-corrected"
            )
            pose = None
        for r, image in enumerate(lidar.returns):
            if image is None or image.size == 0:
                continue
            try:
                with np.errstate(
                    over="ignore", invalid="ignore"
                ):  # absurd calibrations: non-finite points, dropped below
                    parts.append(range_image_to_points(image, calib, pose, frame_pose))
            except ValueError as exc:
                warnings.append(f"{source}: lidar {label}: {exc}; its points are skipped")
                continue
            rays.append(np.full(len(parts[-1]), lidar.name == TOP and r == 0))
            # the pixels range_image_to_points keeps (range > 0), in the same row-major order; most
            # images flag no pixel, and then one strided pass (~1 ms per Waymo frame) is all it costs
            flags = image[..., 3] > 0 if image.shape[2] > 3 else None
            zones.append(
                flags[image[..., 0] > 0] if flags is not None and flags.any() else np.zeros(len(parts[-1]), bool)
            )
    if not parts:
        return np.zeros((0, 4), dtype=np.float32), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)
    points = np.concatenate(parts, axis=0)
    ray_mask = np.concatenate(rays)
    no_label_zone = np.concatenate(zones)
    finite = np.isfinite(points[:, :3]).all(axis=1)
    if not finite.all():  # a NaN/inf calibration or pose value: those points cannot be placed
        n_bad = int(len(points) - finite.sum())
        warnings.append(
            f"{source}: dropped {n_bad} of {len(points)} points with NaN/inf coordinates (calibration or pose values?)"
        )
        points, ray_mask, no_label_zone = points[finite], ray_mask[finite], no_label_zone[finite]
    return points, ray_mask, no_label_zone


def sensor_origin(calibrations: dict[int, LidarCalibration]) -> NDArray[np.float64]:
    """(3,) position of the TOP lidar in the vehicle frame (zeros when unknown)."""
    top = calibrations.get(TOP)
    if top is None:
        return np.zeros(3)
    return np.asarray(top.extrinsic, dtype=np.float64)[:3, 3].copy()


# Ranges of the integer extras (they are int32 columns in the results): (low, high) inclusive.
EXTRA_RANGES: dict[str, tuple[int, int]] = {
    "num_lidar_points_in_box": (0, 2**31 - 1),
    "num_top_lidar_points_in_box": (0, 2**31 - 1),
    "detection_difficulty": (0, 2),  # label.proto DifficultyLevel: 0 UNKNOWN, 1 LEVEL_1, 2 LEVEL_2
    "tracking_difficulty": (0, 2),
}


def check_extras(
    extras: dict[str, np.ndarray], field_names: dict[str, str], locations: list[str], warnings: list[str]
) -> dict[str, np.ndarray]:
    """Integer extras with every value outside :data:`EXTRA_RANGES` replaced by NaN (null in the
    results; such an array becomes float64), one warning per bad value naming where and which field.

    ``locations`` names each label (``"<file> row 12"``), ``field_names`` each extra as the file
    spells it. NaN already in an array (a null in the file) is left alone without a warning.
    """
    out = dict(extras)
    for key, (lo, hi) in EXTRA_RANGES.items():
        if key not in extras:
            continue
        v = np.asarray(extras[key])
        with np.errstate(invalid="ignore"):
            bad = (
                (v < lo) | (v > hi)
                if v.dtype.kind in "iu"
                else ~np.isnan(v) & ((v < lo) | (v > hi) | (v != np.round(v)))
            )
        if bad.any():
            for i in np.flatnonzero(bad):
                warnings.append(
                    f"{locations[i]}: {field_names.get(key, key)} = {v[i]} is outside [{lo}, {hi}]; stored as null"
                )
            fixed = v.astype(np.float64)
            fixed[bad] = np.nan
            out[key] = fixed
    return out


def make_frame(
    frame_id: str,
    points: NDArray[np.float32],
    boxes: NDArray[np.float64],
    types: NDArray[np.integer],
    object_ids: list[str],
    extras: dict[str, np.ndarray],
    origin: NDArray[np.float64],
    warnings: list[str],
    classes: tuple[str, ...] | None,
    *,
    source: str = "",
    locations: list[str] | None = None,
    box_fields: tuple[str, ...] = ("center_x", "center_y", "center_z", "length", "width", "height", "heading"),
    object_errors: dict[int, str] | None = None,
    ray_mask: NDArray[np.bool_] | None = None,
    pose: NDArray[np.floating] | None = None,
    timestamp: float | None = None,
    no_label_zone: NDArray[np.bool_] | None = None,
) -> Frame:
    """Build a :class:`Frame`, keeping only the labels of ``classes`` (all when None).

    Labels whose box values are not finite, have a size ≤ 0 or are out of range get their reason
    in ``frame.object_errors`` (:func:`~labelaudit.datasets.base.box_problems`, named by
    ``locations`` and ``box_fields`` as the file spells them); ``object_errors`` adds reasons the
    reader found itself (e.g. a null column), keyed by the same label index.
    """
    names = [class_name(t) for t in types]
    keep = np.ones(len(names), dtype=bool) if classes is None else np.array([n in classes for n in names], dtype=bool)
    idx = np.nonzero(keep)[0]
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    where = locations or [f"{source or frame_id} label {i}" for i in range(len(names))]
    problems = {i: f"{where[i]}: {m}" for i, m in box_problems(boxes[idx], box_fields).items()}
    for j, i in enumerate(idx):
        if object_errors and int(i) in object_errors:
            problems[j] = object_errors[int(i)]
    return Frame(
        frame_id=frame_id,
        points=points,
        boxes=boxes[idx],
        class_names=[names[i] for i in idx],
        object_ids=[object_ids[i] for i in idx],
        sensor_origin=origin,
        extras={k: np.asarray(v)[idx] for k, v in extras.items()},
        warnings=warnings,
        source=str(source),
        object_errors=problems,
        ray_mask=ray_mask,
        pose=None if pose is None else np.asarray(pose, dtype=np.float64),
        timestamp=timestamp,
        no_label_zone=no_label_zone,
    )


def no_lidar_warning(source: str | Path, frame_id: str, num_boxes: int) -> str:
    """The message for a frame that has labels but no range images (e.g. a stripped sample)."""
    return (
        f"{source}: frame {frame_id} has {num_boxes} laser labels but no lidar range images; "
        "it is read with 0 points (every box gets status no_points)"
    )

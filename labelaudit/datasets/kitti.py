"""KITTI object-detection layout: calibration, label and point-cloud files, and the reader.
It reads and writes KITTI files and converts boxes between the camera and LiDAR frames; it does not audit.

Frames (docs/datasets.md)
---------------------
``label_2`` boxes live in the *rectified camera* frame: x right, y down, z forward; ``location`` is
the centre of the box **bottom**, ``rotation_y`` turns about camera y, dimensions are written
h, w, l. labelaudit computes in the *LiDAR* (velodyne) frame: x forward, y left, z up, box centre at
the geometric centre, yaw about +z. The conversion is

- ``T_cam_velo = R0_rect · Tr_velo_to_cam`` (4×4, velodyne → rectified camera), ``T_velo_cam`` its
  inverse;
- centre = ``T_velo_cam · location`` lifted by h/2 along LiDAR z;
- yaw = −rotation_y − π/2, wrapped to [−π, π).

This is the convention of the KITTI tool chains (OpenPCDet, mmdetection3d); it treats the camera y
axis as exactly vertical in the LiDAR frame, which is true to ~0.3° on KITTI. The inverse
(:func:`box_lidar_to_camera`) undoes it exactly, so written labels read back to the same boxes.
"""

from __future__ import annotations

import codecs
import math
import os
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import box_corners, normalize_angle
from labelaudit.core.params import BOX_FIELDS
from labelaudit.datasets.base import Frame, FrameRef, ImageView, box_problems
from labelaudit.errors import DatasetError

FloatArray = NDArray[np.float64]

__all__ = [
    "Calibration",
    "KittiLabels",
    "KittiReader",
    "LABEL_COLUMNS",
    "alpha_from_location",
    "box_camera_to_lidar",
    "box_lidar_to_camera",
    "boxes_camera_to_lidar",
    "boxes_lidar_to_camera",
    "format_calib",
    "format_label_line",
    "kitti_difficulty",
    "project_box_to_image",
    "read_calib",
    "read_label",
    "read_scan",
    "read_velodyne",
    "write_velodyne",
]

# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------

_CALIB_SHAPES: dict[str, tuple[int, int]] = {
    "P0": (3, 4),
    "P1": (3, 4),
    "P2": (3, 4),
    "P3": (3, 4),
    "R0_rect": (3, 3),
    "Tr_velo_to_cam": (3, 4),
    "Tr_imu_to_velo": (3, 4),
}
_CALIB_REQUIRED = ("P2", "R0_rect", "Tr_velo_to_cam")
# Spellings seen in KITTI-derived datasets and tools, mapped to the object-devkit names.
_CALIB_ALIASES = {"R_rect": "R0_rect", "Tr_velo_cam": "Tr_velo_to_cam", "Tr_imu_velo": "Tr_imu_to_velo"}


@dataclass
class Calibration:
    """KITTI object calibration of one frame.

    Attributes
    ----------
    P2 : (3, 4) projection of rectified camera coordinates into the left colour image
    R0_rect : (3, 3) rectifying rotation of camera 0
    Tr_velo_to_cam : (3, 4) rigid transform velodyne → (unrectified) camera 0
    P0, P1, P3 : (3, 4) projections of the other cameras, optional
    Tr_imu_to_velo : (3, 4) rigid transform IMU → velodyne, optional
    """

    P2: FloatArray
    R0_rect: FloatArray
    Tr_velo_to_cam: FloatArray
    P0: FloatArray | None = None
    P1: FloatArray | None = None
    P3: FloatArray | None = None
    Tr_imu_to_velo: FloatArray | None = None

    def __post_init__(self) -> None:
        for name in _CALIB_FIELDS:
            value = getattr(self, name)
            if value is None:
                if name in _CALIB_REQUIRED:
                    raise ValueError(f"calibration {name} is required")
                continue
            arr = np.array(value, dtype=float)
            shape = _CALIB_SHAPES[name]
            if arr.size != shape[0] * shape[1]:
                raise ValueError(f"calibration {name} must have {shape[0]}×{shape[1]} values, got shape {arr.shape}")
            arr = arr.reshape(shape)
            if not np.isfinite(arr).all():
                raise ValueError(f"calibration {name} has non-finite values: {arr.ravel().tolist()}")
            setattr(self, name, arr)
        self._check_rotations()

    @classmethod
    def _from_checked(cls, values: dict[str, FloatArray]) -> Calibration:
        """A calibration of matrices :func:`read_calib` has already checked (float64, their shapes,
        finite): only the rotation test of ``__post_init__`` is left to run."""
        calib = object.__new__(cls)
        calib.__dict__.update(dict.fromkeys(_CALIB_FIELDS), **values)
        calib._check_rotations()
        return calib

    def _check_rotations(self) -> None:
        for name, rot in (("R0_rect", self.R0_rect), ("Tr_velo_to_cam", self.Tr_velo_to_cam[:, :3])):
            (a, b, c), (d, e, f), (g, h, i) = rot.tolist()  # 3×3 by cofactors: no LAPACK call per frame
            det = a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
            # Loose on purpose: KITTI matrices are printed with 7 digits and are not exactly orthonormal.
            # (not ≤: a huge matrix overflows to inf or NaN and is refused too)
            if not abs(abs(det) - 1.0) <= 0.05:
                raise ValueError(f"calibration {name} rotation part is not a rotation (determinant {det:.4g})")

    @property
    def T_cam_velo(self) -> FloatArray:
        """(4, 4) velodyne → rectified camera: ``R0_rect · Tr_velo_to_cam``."""
        r0 = np.eye(4)
        r0[:3, :3] = self.R0_rect
        tr = np.eye(4)
        tr[:3, :] = self.Tr_velo_to_cam
        return r0 @ tr

    @property
    def T_velo_cam(self) -> FloatArray:
        """(4, 4) rectified camera → velodyne, the inverse of :attr:`T_cam_velo`.

        A general inverse, not the rigid one: the printed KITTI matrices are only nearly orthonormal.
        """
        return np.linalg.inv(self.T_cam_velo)


_CALIB_FIELDS = tuple(f.name for f in fields(Calibration))  # looked up once: dataclasses.fields() is slow per call


def read_text_lines(path: Path, what: str) -> list[str]:
    """The lines of a KITTI text file: UTF-8 (a leading byte-order mark is dropped), ``\\n`` or
    ``\\r\\n`` line ends. Lines are split on ``\\n`` only, so line numbers are those of ``wc -l``
    and every editor (``str.splitlines`` would also split on form feeds and other separators).

    Raises
    ------
    DatasetError
        The file cannot be read or is not UTF-8 text (the message names the byte offset).
    """
    return text_lines(read_file_bytes(path, what), path, what)


def read_file_bytes(path: Path, what: str, missing: str | None = None) -> bytes:
    """The bytes of a file; :class:`DatasetError` naming ``what`` when it cannot be read, with the
    message ``missing`` (when given) when there is no such file (a folder is not one)."""
    try:
        with open(path, "rb") as f:
            return f.read()
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError) as exc:
        if missing is not None:
            raise DatasetError(path, missing) from None
        raise DatasetError(path, f"cannot read {what}: {exc.strerror or exc}") from None
    except OSError as exc:
        raise DatasetError(path, f"cannot read {what}: {exc.strerror or exc}") from None


def text_lines(data: bytes, path: Path, what: str) -> list[str]:
    """:func:`read_text_lines` of bytes already read from ``path`` (named in errors)."""
    bom = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        text = data[bom:].decode("utf-8")
    except UnicodeDecodeError as exc:
        at = bom + exc.start
        line = data.count(b"\n", 0, at) + 1
        raise DatasetError(path, f"{what} is not UTF-8 text (byte {data[at]:#04x} at offset {at})", line) from None
    lines = text.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    return [l[:-1] if l.endswith("\r") else l for l in lines]


def read_calib(path: str | Path) -> Calibration:
    """Read a KITTI object calibration file (``key: v1 v2 …`` per line).

    Raises
    ------
    DatasetError
        Missing file, a line without ``key:``, a non-numeric value, a wrong number of values or a
        missing required key (P2, R0_rect, Tr_velo_to_cam); the message names the key and line.
    """
    path = path if isinstance(path, Path) else Path(path)
    return parse_calib(read_calib_bytes(path), path)


def read_calib_bytes(path: Path) -> bytes:
    """The bytes of a calibration file (:func:`read_calib`'s errors for a missing or unreadable one)."""
    return read_file_bytes(
        path,
        "calibration file",
        missing="calibration file not found (expected calib/<frame>.txt with P2, R0_rect, Tr_velo_to_cam)",
    )


def parse_calib(data: bytes, path: Path) -> Calibration:
    """:func:`read_calib` of the bytes of the calibration file ``path`` (named in errors)."""
    values: dict[str, FloatArray] = {}
    for lineno, raw in enumerate(text_lines(data, path, "calibration file"), start=1):
        line = raw.strip()
        if not line:
            continue
        if ":" not in line:
            raise DatasetError(path, f"expected 'key: numbers', got {line[:60]!r}", lineno)
        key, _, rest = line.partition(":")
        key = key.strip()
        key = _CALIB_ALIASES.get(key, key)
        if key not in _CALIB_SHAPES:
            continue  # other keys (e.g. from raw-data calib files) are not needed
        try:
            nums = [float(t) for t in rest.split()]
        except ValueError:
            raise DatasetError(
                path, f"calibration {key}: expected numbers, got {rest.strip()[:80]!r}", lineno
            ) from None
        shape = _CALIB_SHAPES[key]
        if len(nums) != shape[0] * shape[1]:
            raise DatasetError(
                path,
                f"calibration {key}: expected {shape[0] * shape[1]} numbers ({shape[0]}×{shape[1]}), got {len(nums)}",
                lineno,
            )
        if not all(map(math.isfinite, nums)):  # on the Python floats: no NumPy call per line
            raise DatasetError(path, f"calibration {key}: non-finite values", lineno)
        values[key] = np.array(nums, dtype=float).reshape(shape)
    missing = [k for k in _CALIB_REQUIRED if k not in values]
    if missing:
        raise DatasetError(
            path, f"calibration is missing key(s) {', '.join(missing)} (required: {', '.join(_CALIB_REQUIRED)})"
        )
    try:
        return Calibration._from_checked(values)
    except ValueError as exc:
        raise DatasetError(path, str(exc)) from None


def _fmt_exact(v: float) -> str:
    """KITTI-style scientific notation that still reads back to the identical float."""
    s = f"{v:.12e}"
    return s if float(s) == v else f"{v:.16e}"


def format_calib(calib: Calibration) -> str:
    """The calibration as KITTI object calib text (present keys in the standard order).

    Values are written like the official files (``7.070493000000e+02``) and read back exactly.
    """
    lines = []
    for key in ("P0", "P1", "P2", "P3", "R0_rect", "Tr_velo_to_cam", "Tr_imu_to_velo"):
        m = getattr(calib, key)
        if m is not None:
            lines.append(f"{key}: " + " ".join(_fmt_exact(float(v)) for v in np.asarray(m).ravel()))
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# Box conversion
# ---------------------------------------------------------------------------------------------


def boxes_camera_to_lidar(
    locations: ArrayLike, dims_hwl: ArrayLike, rotation_y: ArrayLike, calib: Calibration
) -> FloatArray:
    """Vectorised :func:`box_camera_to_lidar`.

    Parameters
    ----------
    locations : (K, 3) bottom centres in the rectified camera frame
    dims_hwl : (K, 3) height, width, length
    rotation_y : (K,)

    Returns
    -------
    boxes : (K, 7) cx, cy, cz, l, w, h, yaw in the LiDAR frame
    """
    return camera_to_lidar(locations, dims_hwl, rotation_y, calib.T_velo_cam)


def camera_to_lidar(locations: ArrayLike, dims_hwl: ArrayLike, rotation_y: ArrayLike, T: FloatArray) -> FloatArray:
    """:func:`boxes_camera_to_lidar` with the calibration's :attr:`~Calibration.T_velo_cam` ``T`` (4, 4)
    already computed (a reader derives it once per calibration file)."""
    loc = np.asarray(locations, dtype=float).reshape(-1, 3)
    dims = np.asarray(dims_hwl, dtype=float).reshape(-1, 3)
    ry = np.asarray(rotation_y, dtype=float).reshape(-1)
    out = np.empty((len(loc), 7))  # filled column by column: np.c_ costs more than the arithmetic
    with np.errstate(invalid="ignore", over="ignore"):  # a NaN/inf label stays NaN/inf; the reader reports it
        bottom = loc @ T[:3, :3].T + T[:3, 3]
        h = dims[:, 0]
        out[:, :2] = bottom[:, :2] + 0.0  # + 0.0 as the lift adds to x, y (−0.0 becomes 0.0)
        out[:, 2] = bottom[:, 2] + h / 2.0
        out[:, 3], out[:, 4], out[:, 5] = dims[:, 2], dims[:, 1], h
        out[:, 6] = normalize_angle(-ry - np.pi / 2.0)
    return out


def box_camera_to_lidar(location: ArrayLike, dims_hwl: ArrayLike, rotation_y: float, calib: Calibration) -> FloatArray:
    """One KITTI label box (rectified camera frame) as a LiDAR-frame box.

    Parameters
    ----------
    location : (3,) bottom centre x, y, z in the rectified camera frame (y down)
    dims_hwl : (3,) height, width, length as written in ``label_2``
    rotation_y : rotation about camera y, radians
    calib : the frame's calibration

    Returns
    -------
    box : (7,) cx, cy, cz, l, w, h, yaw — geometric centre, yaw = −rotation_y − π/2 wrapped
    """
    return boxes_camera_to_lidar(location, dims_hwl, [rotation_y], calib)[0]


def boxes_lidar_to_camera(boxes: ArrayLike, calib: Calibration) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Vectorised :func:`box_lidar_to_camera`: (K, 7) → locations (K, 3), dims_hwl (K, 3), rotation_y (K,)."""
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    bottom = b[:, :3] - np.c_[np.zeros(len(b)), np.zeros(len(b)), b[:, 5] / 2.0]
    T = calib.T_cam_velo
    loc = bottom @ T[:3, :3].T + T[:3, 3]
    dims = b[:, [5, 4, 3]].copy()
    ry = np.atleast_1d(normalize_angle(-b[:, 6] - np.pi / 2.0))
    return loc, dims, ry


def box_lidar_to_camera(box: ArrayLike, calib: Calibration) -> tuple[FloatArray, FloatArray, float]:
    """Inverse of :func:`box_camera_to_lidar`.

    Parameters
    ----------
    box : (7,) cx, cy, cz, l, w, h, yaw in the LiDAR frame

    Returns
    -------
    location : (3,) bottom centre in the rectified camera frame
    dims_hwl : (3,) height, width, length
    rotation_y : radians in [−π, π)
    """
    loc, dims, ry = boxes_lidar_to_camera(box, calib)
    return loc[0], dims[0], float(ry[0])


def alpha_from_location(location: ArrayLike, rotation_y: ArrayLike) -> FloatArray | float:
    """KITTI observation angle ``alpha = rotation_y − atan2(x, z)`` (wrapped), location in camera frame."""
    loc = np.asarray(location, dtype=float)
    return normalize_angle(np.asarray(rotation_y, dtype=float) - np.arctan2(loc[..., 0], loc[..., 2]))


def project_box_to_image(
    box: ArrayLike, calib: Calibration, image_size: tuple[int, int] = (1242, 375), min_depth: float = 0.1
) -> FloatArray:
    """2D box (left, top, right, bottom) of a LiDAR-frame box in the P2 image, clipped to the image.

    Corners closer than ``min_depth`` in front of the camera are clamped to that depth, so boxes
    reaching behind the camera still get a finite (truncated) 2D box.

    Parameters
    ----------
    box : (7,) LiDAR-frame box
    image_size : (width, height) in pixels (KITTI: 1242 × 375)
    """
    corners = box_corners(box, "3d")  # (8, 3)
    cam = corners @ calib.T_cam_velo[:3, :3].T + calib.T_cam_velo[:3, 3]
    cam[:, 2] = np.maximum(cam[:, 2], min_depth)
    uvw = np.c_[cam, np.ones(8)] @ calib.P2.T
    uv = uvw[:, :2] / uvw[:, 2:3]
    w, h = image_size
    left, top = np.clip(uv.min(0), 0, [w - 1, h - 1])
    right, bottom = np.clip(uv.max(0), 0, [w - 1, h - 1])
    return np.array([left, top, right, bottom])


# ---------------------------------------------------------------------------------------------
# Labels
# ---------------------------------------------------------------------------------------------

LABEL_COLUMNS: tuple[str, ...] = (
    "type", "truncated", "occluded", "alpha", "bbox_left", "bbox_top", "bbox_right", "bbox_bottom",
    "height", "width", "length", "x", "y", "z", "rotation_y", "score",
)  # fmt: skip
"""Column names of a KITTI label line (15 columns; results files add ``score``)."""

_OCCLUSION_LEVELS = frozenset((-1.0, 0.0, 1.0, 2.0, 3.0))  # 0 visible … 2 largely occluded, 3 unknown, -1 DontCare


def _fmt(v: float, precision: int | None) -> str:
    return repr(float(v)) if precision is None else f"{v:.{precision}f}"


def format_label_line(
    class_name: str,
    truncated: float,
    occluded: int,
    alpha: float,
    bbox2d: ArrayLike,
    dims_hwl: ArrayLike,
    location: ArrayLike,
    rotation_y: float,
    score: float | None = None,
    precision: int | None = 2,
) -> str:
    """One KITTI label line (no newline): 15 columns, or 16 with ``score``.

    Parameters
    ----------
    bbox2d : (4,) left, top, right, bottom in pixels
    dims_hwl : (3,) height, width, length
    location : (3,) bottom centre in the rectified camera frame
    precision : decimals, 2 like the official labels; ``None`` writes every float exactly
        (shortest round-trip form), so boxes read back bit-identical.
    """
    if not class_name or any(ch.isspace() for ch in class_name):
        raise ValueError(f"class name must be a non-empty word without spaces, got {class_name!r}")
    nums = [float(truncated)]
    tail = [float(alpha), *np.asarray(bbox2d, float).reshape(4), *np.asarray(dims_hwl, float).reshape(3)]
    tail += [*np.asarray(location, float).reshape(3), float(rotation_y)]
    parts = [class_name, _fmt(nums[0], precision), str(int(occluded))] + [_fmt(v, precision) for v in tail]
    if score is not None:
        parts.append(_fmt(score, None if precision is None else max(precision, 4)))
    return " ".join(parts)


@dataclass
class KittiLabels:
    """All rows of one KITTI label (or result) file, DontCare included, in file order.

    Attributes
    ----------
    class_names : K type strings
    truncated : (K,) float
    occluded : (K,) int (0 visible … 2 largely occluded, 3 unknown, -1 DontCare)
    alpha : (K,) observation angle
    bbox2d : (K, 4) left, top, right, bottom pixels
    dims_hwl : (K, 3) height, width, length
    location : (K, 3) bottom centre, rectified camera frame
    rotation_y : (K,)
    score : (K,) detection score, NaN for 15-column lines
    line : (K,) 1-based line number in the file
    """

    class_names: list[str]
    truncated: FloatArray
    occluded: NDArray[np.int64]
    alpha: FloatArray
    bbox2d: FloatArray
    dims_hwl: FloatArray
    location: FloatArray
    rotation_y: FloatArray
    score: FloatArray
    line: NDArray[np.int64]

    def __len__(self) -> int:
        return len(self.class_names)


def read_label(path: str | Path) -> KittiLabels:
    """Parse a KITTI ``label_2`` (15 columns) or result (16 columns, with score) file.

    Blank lines are skipped; an empty file gives zero rows. The file is UTF-8 with ``\\n`` or
    ``\\r\\n`` line ends; a leading byte-order mark is dropped (:func:`read_text_lines`). Values are
    parsed, not judged: a NaN or negative size reads as written (the reader makes such a label an
    error row, :meth:`KittiReader.load_frame`).

    Raises
    ------
    DatasetError
        Missing or non-UTF-8 file, a line with another column count, a non-numeric field (the
        message names the column) or an occlusion level other than -1, 0, 1, 2, 3.
    """
    path = path if isinstance(path, Path) else Path(path)
    names: list[str] = []
    rows: list[list[float]] = []
    lines: list[int] = []
    text = text_lines(read_file_bytes(path, "label file", missing="label file not found"), path, "label file")
    for lineno, raw in enumerate(text, start=1):
        tokens = raw.split()
        if not tokens:
            continue
        if len(tokens) not in (15, 16):
            raise DatasetError(path, f"expected 15 columns (16 with score), got {len(tokens)}", lineno)
        try:
            nums = [float(tok) for tok in tokens[1:]]
        except ValueError:  # find the column to name it
            for col, tok in zip(LABEL_COLUMNS[1:], tokens[1:]):
                try:
                    float(tok)
                except ValueError:
                    raise DatasetError(path, f"column {col!r}: expected a number, got {tok[:40]!r}", lineno) from None
            raise
        if nums[1] not in _OCCLUSION_LEVELS:  # also refuses 3e9, 1e300 and NaN: an int column must hold it
            raise DatasetError(
                path,
                f"column 'occluded': expected an integer (0, 1, 2, 3; -1 for DontCare), got {tokens[2][:40]!r}",
                lineno,
            )
        if len(nums) == 14:
            nums.append(math.nan)
        names.append(tokens[0])
        rows.append(nums)
        lines.append(lineno)
    a = np.array(rows, dtype=float).reshape(-1, 15)
    return KittiLabels(
        class_names=names,
        truncated=a[:, 0].copy(),
        occluded=a[:, 1].astype(np.int64),
        alpha=a[:, 2].copy(),
        bbox2d=a[:, 3:7].copy(),
        dims_hwl=a[:, 7:10].copy(),
        location=a[:, 10:13].copy(),
        rotation_y=a[:, 13].copy(),
        score=a[:, 14].copy(),
        line=np.array(lines, dtype=np.int64),
    )


def kitti_difficulty(bbox2d: ArrayLike, occluded: ArrayLike, truncated: ArrayLike) -> NDArray[np.int8]:
    """KITTI difficulty per the official object devkit: 0 Easy, 1 Moderate, 2 Hard, -1 none.

    A level admits a box when its 2D height is *greater than* the minimum height and its
    occlusion and truncation do not exceed the maxima (``constants.KITTI_*``); the easiest
    admitting level wins.

    Parameters
    ----------
    bbox2d : (K, 4) left, top, right, bottom
    occluded : (K,)
    truncated : (K,)
    """
    box = np.asarray(bbox2d, dtype=float).reshape(-1, 4)
    height = np.abs(box[:, 3] - box[:, 1])
    occ = np.asarray(occluded, dtype=float).reshape(-1)
    trunc = np.asarray(truncated, dtype=float).reshape(-1)
    out = np.full(len(box), -1, dtype=np.int8)
    for level in (2, 1, 0):  # hardest first, so easier levels overwrite
        ok = (
            (height > C.KITTI_MIN_HEIGHT[level])
            & (occ <= C.KITTI_MAX_OCCLUSION[level])
            & (trunc <= C.KITTI_MAX_TRUNCATION[level])
        )
        out[ok] = level
    return out


# ---------------------------------------------------------------------------------------------
# Point clouds
# ---------------------------------------------------------------------------------------------


def read_velodyne(path: str | Path) -> NDArray[np.float32]:
    """Read a KITTI velodyne ``.bin`` (little-endian float32 x, y, z, reflectance).

    Returns
    -------
    points : (N, 4) float32, as stored (non-finite values are *not* removed here)

    Raises
    ------
    DatasetError
        Missing file, or a size that is not a multiple of 16 bytes.
    """
    return read_scan(path)[0]


def read_scan(path: str | Path, missing: str = "point cloud file not found") -> tuple[NDArray[np.float32], bool]:
    """:func:`read_velodyne`, and whether every value of the scan is finite.

    The file is read in parts of :data:`_SCAN_PART` bytes into the array, and each part is tested
    while it is still in the cache: the test costs no second pass over the scan from memory.
    ``missing``: the message when there is no such file.
    """
    path = path if isinstance(path, Path) else Path(path)
    try:
        f = open(path, "rb", buffering=0)
    except (FileNotFoundError, IsADirectoryError, NotADirectoryError):
        raise DatasetError(path, missing) from None
    with f:
        size = os.fstat(f.fileno()).st_size
        if size % 16:
            raise DatasetError(
                path, f"file size {size} bytes is not a multiple of 16 (4 float32 per point: x, y, z, reflectance)"
            )
        flat = np.empty(size // 4, dtype="<f4")
        view = memoryview(flat).cast("B")
        finite, pos, tested = True, 0, 0
        while pos < size:
            got = f.readinto(view[pos : pos + _SCAN_PART])
            if not got:
                raise DatasetError(path, f"file ended after {pos} of its {size} bytes (changed while read?)")
            pos += got
            if finite:  # the whole values read so far that are not tested yet
                finite = bool(np.isfinite(flat[tested : pos // 4]).all())
                tested = pos // 4
    return flat.reshape(-1, 4).astype(np.float32, copy=False), finite


_SCAN_PART = 1 << 18  # bytes read (and tested for finiteness) at a time: a part stays in the cache


def write_velodyne(path: str | Path, points: ArrayLike) -> None:
    """Write points as a KITTI velodyne ``.bin``; (N, 3) input gets reflectance 0. Creates parent folders."""
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] not in (3, 4):
        raise ValueError(f"points must be (N, 3) or (N, 4), got shape {pts.shape}")
    if pts.shape[1] == 3:
        pts = np.c_[pts, np.zeros(len(pts))]
    path = path if isinstance(path, Path) else Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.ascontiguousarray(pts, dtype="<f4").tofile(path)


# ---------------------------------------------------------------------------------------------
# Reader
# ---------------------------------------------------------------------------------------------


class KittiReader:
    """KITTI object-detection dataset reader (one unit of work = one frame).

    Parameters
    ----------
    root : a folder holding ``training/`` (and optionally ``testing/`` and ``ImageSets/``), or the
        split folder itself (holding ``velodyne/``, ``label_2/``, ``calib/``)
    split : ``"train"``, ``"val"``, ``"test"`` … — frames listed in ``ImageSets/<split>.txt``
        (looked for next to ``training/``); ``None`` = every label file. ``"test"`` reads
        ``testing/`` when it exists, like the KITTI tool chains.
    classes : class names to keep; ``None`` keeps all but DontCare
    velodyne_dir : ``"velodyne"``, ``"velodyne_reduced"`` or ``"auto"`` (the first that exists)

    Notes
    -----
    ``object_ids`` are ``"<frame_id>:<index>"`` where ``index`` counts the non-DontCare rows of
    the label file in order — independent of the class filter, so ids stay the same whatever
    classes are kept (and equal OpenPCDet's ``gt_database`` numbering).
    """

    format_name = "kitti"

    def __init__(
        self,
        root: str | Path,
        split: str | None = None,
        classes: Sequence[str] | None = None,
        velodyne_dir: str = "auto",
    ) -> None:
        self.root = Path(root)
        if not self.root.is_dir():
            raise DatasetError(self.root, "KITTI root folder does not exist")
        self.split = split
        self.classes = None if classes is None else tuple(classes)
        sub = "testing" if split == "test" and (self.root / "testing").is_dir() else "training"
        if (self.root / sub).is_dir():
            self.data_dir = self.root / sub
            self.imagesets_dir = self.root / "ImageSets"
        else:
            self.data_dir = self.root
            self.imagesets_dir = self.root / "ImageSets"
            if not self.imagesets_dir.is_dir():
                self.imagesets_dir = self.root.parent / "ImageSets"
        if velodyne_dir == "auto":
            for name in ("velodyne", "velodyne_reduced"):
                if (self.data_dir / name).is_dir():
                    velodyne_dir = name
                    break
            else:
                raise DatasetError(
                    self.data_dir,
                    "no velodyne/ or velodyne_reduced/ folder (expected a KITTI object root or its training/ folder)",
                )
        elif not (self.data_dir / velodyne_dir).is_dir():
            raise DatasetError(self.data_dir / velodyne_dir, "point cloud folder not found")
        self.velodyne_dir = velodyne_dir
        if not (self.data_dir / "label_2").is_dir():
            raise DatasetError(self.data_dir / "label_2", "label folder not found (labelaudit audits labelled frames)")
        self._calibrations: dict[bytes, tuple[FloatArray, FloatArray]] = {}
        self._has_images = (self.data_dir / "image_2").is_dir()  # else every frame has KITTI's usual size

    # -- paths ------------------------------------------------------------------------------

    def label_path(self, frame_id: str) -> Path:
        return self.data_dir.joinpath("label_2", f"{frame_id}.txt")

    def velodyne_path(self, frame_id: str) -> Path:
        return self.data_dir.joinpath(self.velodyne_dir, f"{frame_id}.bin")

    def calib_path(self, frame_id: str) -> Path:
        return self.data_dir.joinpath("calib", f"{frame_id}.txt")

    # -- protocol ---------------------------------------------------------------------------

    def list_units(self) -> list[FrameRef]:
        """One :class:`FrameRef` per frame (key = frame id), sorted by id.

        With a split, the frames of ``ImageSets/<split>.txt`` in file order (missing files then
        fail at load time, as a frame error); without one, every ``label_2/*.txt``.
        """
        if self.split is not None:
            list_file = self.imagesets_dir / f"{self.split}.txt"
            if not list_file.is_file():
                raise DatasetError(
                    list_file, f"split list not found (expected ImageSets/{self.split}.txt next to training/)"
                )
            ids, first = [], {}
            for lineno, line in enumerate(read_text_lines(list_file, "split list"), start=1):
                for fid in line.split():
                    if fid in first:
                        raise DatasetError(
                            list_file,
                            f"frame {fid!r} is listed twice (lines {first[fid]} and {lineno}); list each frame once",
                            lineno,
                        )
                    first[fid] = lineno
                    ids.append(fid)
        else:
            ids = sorted(p.stem for p in (self.data_dir / "label_2").glob("*.txt"))
        return [FrameRef(self.format_name, str(self.root), fid) for fid in ids]

    def load_unit(self, ref: FrameRef) -> Iterator[Frame]:
        """Yield the one :class:`Frame` of ``ref``; raises :class:`DatasetError` for bad input."""
        yield self.load_frame(ref.key)

    def load_frame(self, frame_id: str) -> Frame:
        """Read one frame: points and boxes in the LiDAR frame, KITTI extras per object.

        A kept label whose box values are not finite, have a size ≤ 0 or are beyond the sane
        limits (``constants.MAX_BOX_*``) is still in the frame, with its reason in
        ``frame.object_errors`` (file, line, column, value): it becomes an error row and the rest
        of the frame is audited.

        Raises
        ------
        DatasetError
            A file that is missing or cannot be parsed (:func:`read_label`, :func:`read_calib`,
            :func:`read_velodyne`).
        """
        label_path = self.label_path(frame_id)
        velo_path = self.velodyne_path(frame_id)
        labels = read_label(label_path)
        points, all_finite = read_scan(velo_path, missing=f"point cloud not found for label file {label_path}")
        calib_path = self.calib_path(frame_id)
        velo_from_cam, projection = self.calibration(calib_path)

        not_dontcare = np.array([n != "DontCare" for n in labels.class_names], dtype=bool)
        index = np.cumsum(not_dontcare) - 1  # position among the non-DontCare rows
        keep = not_dontcare.copy()
        if self.classes is not None:
            keep &= np.array([n in self.classes for n in labels.class_names], dtype=bool)
        rows = np.flatnonzero(keep)

        dims = labels.dims_hwl[rows]
        warnings: list[str] = []
        # The whole scan was tested while read; the per-row test (~2 ms) only when something is not
        # finite (possibly just a reflectance, which is kept).
        finite = None if all_finite else np.all(np.isfinite(points[:, :3]), axis=1)
        n_bad = 0 if finite is None else int(len(points) - finite.sum())
        if n_bad:
            points = points[finite]
            warnings.append(f"{velo_path}: dropped {n_bad} of {n_bad + len(points)} points with NaN/inf coordinates")

        boxes = camera_to_lidar(labels.location[rows], dims, labels.rotation_y[rows], velo_from_cam)
        object_errors = _label_problems(labels, rows, boxes, label_path, calib_path)
        for name in {labels.class_names[r] for r in rows if not labels.class_names[r].isprintable()}:
            at = ", ".join(str(labels.line[r]) for r in rows if labels.class_names[r] == name)
            warnings.append(
                f"{label_path}: line {at}: class name {name!r} has unprintable characters (a byte-order mark or a control character?)"
            )
        if not _is_utf8(frame_id):
            warnings.append(
                f"{label_path}: the file name is not valid UTF-8; frame_id shows its undecodable bytes as \\xNN"
            )
        extras: dict[str, np.ndarray] = {
            "truncated": labels.truncated[rows],
            "occluded": labels.occluded[rows],
            "alpha": labels.alpha[rows],
            "bbox2d": labels.bbox2d[rows],
            "difficulty": kitti_difficulty(labels.bbox2d[rows], labels.occluded[rows], labels.truncated[rows]),
            "score": labels.score[rows],
            "label_line": labels.line[rows],
        }
        dontcare = labels.bbox2d[~not_dontcare].reshape(-1, 4)
        view = ImageView(projection, self.image_size(frame_id), np.asarray(dontcare, dtype=float))
        return Frame(
            frame_id=frame_id,
            points=np.ascontiguousarray(points, dtype=np.float32),
            boxes=boxes.reshape(-1, 7),
            class_names=[labels.class_names[r] for r in rows],
            object_ids=[f"{frame_id}:{int(index[r])}" for r in rows],
            sensor_origin=np.zeros(3),
            extras=extras,
            warnings=warnings,
            source=str(label_path),
            object_errors=object_errors,
            image_view=view,
        )

    def calibration(self, path: Path) -> tuple[FloatArray, FloatArray]:
        """(T_velo_cam (4, 4), the LiDAR → image_2 projection P2 · T_cam_velo (3, 4)) of a
        calibration file, read-only: parsed and derived once per distinct file content (a KITTI
        drive's frames share one calibration; the file is still read, and checked, every time).

        Raises
        ------
        DatasetError
            As :func:`read_calib`.
        """
        data = read_calib_bytes(path)
        derived = self._calibrations.get(data)
        if derived is None:
            calib = parse_calib(data, path)
            derived = (calib.T_velo_cam, calib.P2 @ calib.T_cam_velo)
            for a in derived:
                a.flags.writeable = False  # shared by the frames of the calibration
            if len(self._calibrations) >= _CALIBRATIONS_KEPT:
                self._calibrations.clear()
            self._calibrations[data] = derived
        return derived

    def image_size(self, frame_id: str) -> tuple[int, int]:
        """(width, height) of ``image_2/<frame_id>.png`` from its header; KITTI's usual size
        (:data:`~labelaudit.constants.KITTI_IMAGE_SIZE`) when there is no readable image."""
        if not self._has_images:
            return C.KITTI_IMAGE_SIZE
        try:
            with open(self.data_dir.joinpath("image_2", f"{frame_id}.png"), "rb") as f:
                head = f.read(24)
        except OSError:
            return C.KITTI_IMAGE_SIZE
        if len(head) == 24 and head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
            width, height = int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
            if 0 < width < 100_000 and 0 < height < 100_000:
                return width, height
        return C.KITTI_IMAGE_SIZE


_CALIBRATIONS_KEPT = 64  # distinct calibration files a reader keeps derived (KITTI object: one per drive day)

_LABEL_BOX_FIELDS = ("height", "width", "length", "x", "y", "z", "rotation_y")
_LABEL_BOX_KINDS = ("size", "size", "size", "centre", "centre", "centre", "angle")


def _label_problems(
    labels: KittiLabels, rows: NDArray[np.int64], boxes: FloatArray, label_path: Path, calib_path: Path
) -> dict[int, str]:
    """Object index → why its label cannot be audited: a label column that is not finite, a size
    ≤ 0 or beyond the sane limits (named as the file spells it), else a LiDAR-frame box out of
    range after the calibration."""
    raw = np.concatenate([labels.dims_hwl[rows], labels.location[rows], labels.rotation_y[rows, None]], axis=1)
    out = {
        i: f"{label_path}:{labels.line[rows[i]]}: {msg}"
        for i, msg in box_problems(raw, _LABEL_BOX_FIELDS, _LABEL_BOX_KINDS).items()
    }
    for i, msg in box_problems(boxes, BOX_FIELDS).items():
        if i not in out:
            out[i] = (
                f"{label_path}:{labels.line[rows[i]]}: box in the LiDAR frame out of range after {calib_path}: {msg}"
            )
    return out


def _is_utf8(name: str) -> bool:
    try:
        name.encode("utf-8")
        return True
    except UnicodeEncodeError:  # a surrogate-escaped byte of a non-UTF-8 file name
        return False

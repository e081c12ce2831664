"""Argoverse 2 sensor-dataset files: write cuboids, sweeps, ego poses and calibration of a log.
Test and benchmark fixtures in the layout :mod:`labelaudit.datasets.av2` reads; it never audits.

The file writers take whatever boxes and points they are given (a simulated sequence, a perturbed
copy of real annotations, a hand-made bad file), in the column names and types of the real
dataset: cuboids as float64 with a quaternion per row, sweeps as float16 ``x, y, z`` with uint8
``intensity`` and ``laser_number`` and int32 ``offset_ns``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from numpy.typing import ArrayLike, NDArray

from labelaudit.core.geometry import yaw_quaternion
from labelaudit.datasets import av2

FloatArray = NDArray[np.float64]


def _matrix_quaternion(rot: FloatArray) -> FloatArray:
    """(4,) unit quaternion (w, x, y, z) of a 3×3 rotation (Shepperd's method: the largest diagonal term first)."""
    m = np.asarray(rot, dtype=float)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    elif m[0, 0] >= m[1, 1] and m[0, 0] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = ((m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s)
    elif m[1, 1] >= m[2, 2]:
        s = 2.0 * np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = ((m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s)
    else:
        s = 2.0 * np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = ((m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s)
    out = np.asarray(q, dtype=float)
    return out / np.linalg.norm(out)


def write_annotations(
    path: str | Path,
    timestamps: ArrayLike,
    boxes: ArrayLike,
    categories: Sequence[str | None],
    tracks: Sequence[str | None],
    num_interior_pts: ArrayLike | None = None,
) -> Path:
    """Write an ``annotations.feather``: one row per cuboid.

    Parameters
    ----------
    timestamps : (R,) int ns of each row
    boxes : (R, 7) cx, cy, cz, l, w, h, yaw in the egovehicle frame (yaw becomes qw, qz)
    categories, tracks : R AV2 categories and track uuids (None writes a null)
    num_interior_pts : (R,) the dataset's own point count (omitted column when None)
    """
    b = np.asarray(boxes, dtype=np.float64).reshape(-1, 7)
    q = yaw_quaternion(b[:, 6]).reshape(-1, 4)
    cols: dict[str, pa.Array] = {
        av2.TIMESTAMP: pa.array(np.asarray(timestamps, dtype=np.int64)),
        av2.TRACK: pa.array(list(tracks), pa.string()),
        av2.CATEGORY: pa.array(list(categories), pa.string()),
    }
    for j, c in enumerate(av2.SIZE):
        cols[c] = pa.array(b[:, 3 + j])
    for j, c in enumerate(av2.QUATERNION):
        cols[c] = pa.array(q[:, j])
    for j, c in enumerate(av2.CENTRE):
        cols[c] = pa.array(b[:, j])
    if num_interior_pts is not None:
        cols[av2.NUM_POINTS] = pa.array(np.asarray(num_interior_pts, dtype=np.int64))
    return _write(path, pa.table(cols))


def write_sweep(path: str | Path, points: ArrayLike, laser_number: ArrayLike | None = None, offset_ns: ArrayLike | None = None) -> Path:
    """Write one lidar sweep ``<timestamp_ns>.feather``.

    Parameters
    ----------
    points : (N, ≥4) x, y, z (stored as float16, as AV2 does: ~mm steps near the car, 3 cm at 60 m),
        intensity (rounded to uint8)
    laser_number : (N,) 0–31 up lidar, 32–63 down lidar (zeros when None)
    offset_ns : (N,) capture time after the sweep timestamp (zeros when None)
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] < 4:
        raise ValueError(f"points must be (N, >=4) x, y, z, intensity, got shape {p.shape}")
    n = len(p)
    cols = {c: pa.array(p[:, j].astype(np.float16)) for j, c in enumerate(("x", "y", "z"))}
    cols["intensity"] = pa.array(np.clip(np.rint(p[:, 3]), 0, 255).astype(np.uint8))
    cols["laser_number"] = pa.array(np.zeros(n, np.uint8) if laser_number is None else np.asarray(laser_number, dtype=np.uint8))
    cols["offset_ns"] = pa.array(np.zeros(n, np.int32) if offset_ns is None else np.asarray(offset_ns, dtype=np.int32))
    return _write(path, pa.table(cols))


def write_poses(path: str | Path, timestamps: ArrayLike, poses: ArrayLike) -> Path:
    """Write ``city_SE3_egovehicle.feather``: (T,) int ns and (T, 4, 4) egovehicle → city transforms."""
    mats = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    q = np.array([_matrix_quaternion(m[:3, :3]) for m in mats]).reshape(-1, 4)
    cols: dict[str, pa.Array] = {av2.TIMESTAMP: pa.array(np.asarray(timestamps, dtype=np.int64))}
    for j, c in enumerate(av2.QUATERNION):
        cols[c] = pa.array(q[:, j])
    for j, c in enumerate(av2.CENTRE):
        cols[c] = pa.array(mats[:, j, 3])
    return _write(path, pa.table(cols))


def write_calibration(path: str | Path, mounts: dict[str, ArrayLike]) -> Path:
    """Write ``calibration/egovehicle_SE3_sensor.feather`` with upright sensors at the given (3,) positions."""
    names = sorted(mounts)
    t = np.array([np.asarray(mounts[n], dtype=np.float64).reshape(3) for n in names]).reshape(-1, 3)
    cols: dict[str, pa.Array] = {"sensor_name": pa.array(names, pa.string())}
    for j, c in enumerate(av2.QUATERNION):
        cols[c] = pa.array([1.0 if j == 0 else 0.0] * len(names))
    for j, c in enumerate(av2.CENTRE):
        cols[c] = pa.array(t[:, j])
    return _write(path, pa.table(cols))


def _write(path: str | Path, table: pa.Table) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    feather.write_feather(table, path, compression="uncompressed")
    return path


__all__ = ["write_annotations", "write_calibration", "write_poses", "write_sweep"]

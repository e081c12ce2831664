"""Write a simulated frame in the KITTI object-detection layout.
File writing only; the scene and noise come from the other ``sim`` modules.

Uses the KITTI helpers of :mod:`labelaudit.datasets.kitti` (calibration text, camera ↔ LiDAR box
conversion, label lines, velodyne files), so what the simulator writes is exactly what the reader
parses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.datasets.kitti import (
    Calibration,
    alpha_from_location,
    boxes_camera_to_lidar,
    boxes_lidar_to_camera,
    format_calib,
    format_label_line,
    write_velodyne,
)
from labelaudit.sim.scene import corners_of

FloatArray = NDArray[np.float64]

LABEL_FOV_CHOICES = ("camera", "all")
_MIN_DEPTH = 0.1  # corners nearer than this to the camera plane are clamped (same as project_box_to_image)
_MIN_CENTRE_DEPTH = 1.0  # an object is labelled only when its centre is this far in front of the camera (m)


def _rotation(rx: float, ry: float, rz: float) -> FloatArray:
    """Rotation matrix R = Rz · Ry · Rx from small angles (radians)."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def make_calibration(rng: np.random.Generator) -> Calibration:
    """A KITTI-like calibration with small per-frame variation (like KITTI's different drives).

    Intrinsics near KITTI's (focal ≈ 707–722 px, principal point ≈ (604–610, 172–181) px, colour
    camera 2 about 6 cm left of camera 0), ``R0_rect`` a rotation of well under a degree, and
    ``Tr_velo_to_cam`` the axis swap LiDAR (x fwd, y left, z up) → camera (x right, y down, z fwd)
    with sub-degree misalignment and the camera ≈ 0.27 m ahead of and 0.08 m below the LiDAR.
    """
    deg = np.pi / 180.0
    f = rng.uniform(707.0, 722.0)
    cu, cv = rng.uniform(604.0, 610.0), rng.uniform(172.0, 181.0)
    K = np.array([[f, 0.0, cu], [0.0, f, cv], [0.0, 0.0, 1.0]])

    def projection(offset_m: tuple[float, float, float]) -> FloatArray:
        return np.c_[K, K @ np.asarray(offset_m)]

    r0 = _rotation(*(rng.normal(0.0, 0.4, 3) * deg))
    swap = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    tr_rot = _rotation(*(rng.normal(0.0, 0.5, 3) * deg)) @ swap
    tr_t = np.array([rng.uniform(-0.025, 0.0), rng.uniform(-0.08, -0.06), rng.uniform(-0.33, -0.27)])
    mats = {
        "P0": projection((0.0, 0.0, 0.0)),
        "P1": projection((-0.537, 0.0, 0.0)),
        "P2": projection((0.06, 3e-4, 2.7e-3)),
        "P3": projection((-0.47, 3e-3, 2.7e-3)),
        "R0_rect": r0,
        "Tr_velo_to_cam": np.c_[tr_rot, tr_t],
    }
    # 7 significant digits, like the official files (the reader inverts generally, not rigidly).
    return Calibration(
        **{k: np.array([float(f"{v:.6e}") for v in m.ravel()]).reshape(m.shape) for k, m in mats.items()}
    )


@dataclass
class KittiLabelInfo:
    """What was written for the objects of one frame (one entry per scene object).

    Attributes
    ----------
    object_index : (K,) index among the written (non-DontCare) label rows, −1 when not written
    written_box : (K, 7) the box as the KITTI reader will read it back (rounding included); NaN
        rows for objects not written
    truncated, occluded, alpha, bbox2d : (K,), (K,), (K,), (K, 4) the KITTI label fields
    in_camera_fov : (K,) whether the object is in the camera's field of view
    lines : the label file's lines, in object_index order
    dropped : (K,) objects that would have been labelled but whose label was left out on purpose
        (``drop``: a missing label, for the missing-label benchmark)
    """

    object_index: NDArray[np.int64]
    written_box: FloatArray
    truncated: FloatArray
    occluded: NDArray[np.int64]
    alpha: FloatArray
    bbox2d: FloatArray
    in_camera_fov: NDArray[np.bool_]
    lines: list[str]
    dropped: NDArray[np.bool_] | None = None


def image_boxes(boxes: FloatArray, calib: Calibration) -> FloatArray:
    """Unclipped 2D boxes (left, top, right, bottom) of LiDAR-frame boxes in the P2 image.

    Corners nearer than 0.1 m to the camera plane are clamped to it, like
    :func:`labelaudit.datasets.kitti.project_box_to_image` (which also clips to the image).

    Parameters
    ----------
    boxes : (K, 7)

    Returns
    -------
    (K, 4)
    """
    T = calib.T_cam_velo
    cam = corners_of(boxes) @ T[:3, :3].T + T[:3, 3]  # (K, 8, 3)
    cam[..., 2] = np.maximum(cam[..., 2], _MIN_DEPTH)
    uvw = cam @ calib.P2[:, :3].T + calib.P2[:, 3]
    uv = uvw[..., :2] / uvw[..., 2:3]
    return np.concatenate([uv.min(axis=1), uv.max(axis=1)], axis=1)


def occlusion_level(occlusion_fraction: FloatArray) -> NDArray[np.int64]:
    """KITTI occlusion level from the share of an object's rays blocked by something else.

    0 fully visible, 1 partly occluded, 2 largely occluded (limits ``constants.SIM_OCCLUSION_LEVELS``),
    3 unknown (no ray reaches the object at all).
    """
    frac = np.asarray(occlusion_fraction, dtype=float)
    lo, hi = C.SIM_OCCLUSION_LEVELS
    level = np.where(frac <= lo, 0, np.where(frac <= hi, 1, 2))
    return np.where(np.isfinite(frac), level, 3).astype(np.int64)


def kitti_labels(
    true_boxes: FloatArray,
    written_boxes: FloatArray,
    class_names: list[str],
    occlusion_fraction: FloatArray,
    calib: Calibration,
    *,
    label_fov: str = "camera",
    precision: int | None = 2,
    image_size: tuple[int, int] = C.SIM_IMAGE_SIZE,
    drop: NDArray[np.bool_] | None = None,
) -> KittiLabelInfo:
    """Label lines for one frame and what the reader will read back from them.

    The 2D box and truncation come from the *true* box (2D boxes are drawn on the image of the
    real object); location, dimensions, rotation and alpha from the *written* (possibly
    perturbed) box.

    Parameters
    ----------
    true_boxes, written_boxes : (K, 7) LiDAR-frame boxes
    class_names : K names
    occlusion_fraction : (K,) share of each object's rays blocked by other objects (NaN: no rays)
    calib : the frame's calibration
    label_fov : "camera" — only objects in the camera's field of view are labelled (KITTI);
        "all" — objects all around (360°, like Waymo); objects outside the image get bbox 0 0 0 0
        and truncation 1. Either way, objects with more than ``SIM_MAX_LABEL_OCCLUSION`` of their
        rays blocked (or no rays at all) are not labelled.
    precision : decimals in the label file (2 like KITTI; ``None`` exact)
    image_size : (width, height) of the P2 image in pixels
    drop : (K,) objects whose label is left out even where it would be written (the object and its
        points stay: a missing label)
    """
    if label_fov not in LABEL_FOV_CHOICES:
        raise ValueError(f"label_fov must be one of {LABEL_FOV_CHOICES}, got {label_fov!r}")
    true_boxes = np.asarray(true_boxes, dtype=float).reshape(-1, 7)
    written_boxes = np.asarray(written_boxes, dtype=float).reshape(-1, 7)
    k = len(true_boxes)
    width, height = image_size
    T = calib.T_cam_velo
    centre_depth = true_boxes[:, :3] @ T[2, :3] + T[2, 3]
    full = image_boxes(true_boxes, calib)
    clipped = np.clip(full, 0.0, [width - 1, height - 1, width - 1, height - 1])
    area_full = np.clip(full[:, 2] - full[:, 0], 0, None) * np.clip(full[:, 3] - full[:, 1], 0, None)
    area_clip = (clipped[:, 2] - clipped[:, 0]) * (clipped[:, 3] - clipped[:, 1])
    overlaps = (full[:, 2] > 0) & (full[:, 0] < width - 1) & (full[:, 3] > 0) & (full[:, 1] < height - 1)
    visible = (centre_depth >= _MIN_CENTRE_DEPTH) & overlaps & (area_full > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        truncated = np.where(visible, np.clip(1.0 - area_clip / area_full, 0.0, 1.0), 1.0)
    bbox2d = np.where(visible[:, None], clipped, 0.0)
    in_fov = visible & (truncated <= C.SIM_MAX_TRUNCATION)
    occluded = occlusion_level(occlusion_fraction)
    # Annotators label what they can see: objects hidden behind others (or between beams) get no label.
    frac = np.asarray(occlusion_fraction, dtype=float)
    seen = np.isfinite(frac) & (frac <= C.SIM_MAX_LABEL_OCCLUSION)
    write = seen & in_fov if label_fov == "camera" else seen
    dropped = write & (np.zeros(k, dtype=bool) if drop is None else np.asarray(drop, dtype=bool).reshape(k))
    write &= ~dropped
    loc, dims, ry = boxes_lidar_to_camera(written_boxes, calib)
    alpha = np.atleast_1d(alpha_from_location(loc, ry))
    lines: list[str] = []
    object_index = np.full(k, -1, dtype=np.int64)
    written = np.full((k, 7), np.nan)
    for i in np.flatnonzero(write):
        if not in_fov[i]:
            bbox2d[i] = 0.0
            truncated[i] = 1.0
        line = format_label_line(
            class_names[i],
            truncated[i],
            int(occluded[i]),
            alpha[i],
            bbox2d[i],
            dims[i],
            loc[i],
            ry[i],
            precision=precision,
        )
        object_index[i] = len(lines)
        lines.append(line)
    if lines:
        # Read the numbers back the way the reader does, so the manifest holds the boxes it will see.
        tok = np.array([[float(t) for t in line.split()[1:]] for line in lines])
        written[object_index >= 0] = boxes_camera_to_lidar(tok[:, 10:13], tok[:, 7:10], tok[:, 13], calib)
    return KittiLabelInfo(object_index, written, truncated, occluded, alpha, bbox2d, in_fov, lines, dropped)


def write_kitti_frame(
    root: str | Path, frame_id: str, points: NDArray[np.float32], label_lines: list[str], calib: Calibration
) -> None:
    """Write ``training/{velodyne,label_2,calib}/<frame_id>.*`` under ``root``."""
    base = Path(root) / "training"
    write_velodyne(base / "velodyne" / f"{frame_id}.bin", points)
    for sub, text in (("label_2", "".join(line + "\n" for line in label_lines)), ("calib", format_calib(calib))):
        path = base / sub / f"{frame_id}.txt"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)

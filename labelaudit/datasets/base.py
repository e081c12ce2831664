"""The common frame type every dataset reader produces, the reader protocol and the checks readers share.

Readers turn files into :class:`Frame` s; a frame they cannot read at all is a
:class:`FrameFailure` (the unit's other frames still come), and a label they can read but not
use (a NaN or absurd box) goes into :attr:`Frame.object_errors`, so that one object becomes an
error row and the rest of its frame is audited. Nothing here reads files.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Iterator, Protocol, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import BEV_CORNERS_UNIT, near_polygons
from labelaudit.errors import DatasetError


@dataclass(frozen=True)
class ImageView:
    """The camera image a dataset's labels were drawn in (KITTI: image_2): where labels exist.

    Attributes
    ----------
    projection : (3, 4) LiDAR frame → pixels (homogeneous): KITTI's P2 · R0_rect · Tr_velo_to_cam
    size : (width, height) of the image in pixels
    dontcare : (M, 4) regions (left, top, right, bottom, pixels) the annotators marked DontCare
    """

    projection: NDArray[np.float64]
    size: tuple[int, int]
    dontcare: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 4)))

    def project(self, xyz: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pixels (M, 2) of LiDAR-frame points (M, 3) and their depth in front of the camera (M,)."""
        p = np.asarray(xyz, dtype=float).reshape(-1, 3)
        uvw = p @ self.projection[:, :3].T + self.projection[:, 3]
        depth = uvw[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            return uvw[:, :2] / depth[:, None], depth

    def in_image_share(self, boxes: ArrayLike, min_depth: float = 0.1) -> NDArray[np.float64]:
        """(K,) share of each LiDAR-frame box's (K, 7) 2D projection (its corners' bounding rectangle,
        corners nearer than ``min_depth`` to the camera plane clamped to it) that lies in the image:
        1 − KITTI's ``truncated``."""
        b = np.asarray(boxes, dtype=float).reshape(-1, 7)
        c, s = np.cos(b[:, 6:7]), np.sin(b[:, 6:7])
        sx = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * 0.5 * b[:, 3:4]
        sy = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * 0.5 * b[:, 4:5]
        sz = np.array([1, 1, 1, 1, -1, -1, -1, -1]) * 0.5 * b[:, 5:6]
        corners = np.stack([b[:, 0:1] + c * sx - s * sy, b[:, 1:2] + s * sx + c * sy, b[:, 2:3] + sz], axis=-1)
        uvw = corners @ self.projection[:, :3].T + self.projection[:, 3]  # (K, 8, 3)
        w = np.maximum(uvw[..., 2], min_depth)
        u, v = uvw[..., 0] / w, uvw[..., 1] / w
        width, height = self.size
        full = (u.max(axis=1) - u.min(axis=1)) * (v.max(axis=1) - v.min(axis=1))
        iw = np.clip(np.minimum(u.max(axis=1), width) - np.maximum(u.min(axis=1), 0.0), 0.0, None)
        ih = np.clip(np.minimum(v.max(axis=1), height) - np.maximum(v.min(axis=1), 0.0), 0.0, None)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(full > 0, iw * ih / full, 0.0)

    def box_to_image(self, box: ArrayLike, min_depth: float = 0.1) -> NDArray[np.float64]:
        """2D box (left, top, right, bottom) of a LiDAR-frame box (7,), clipped to the image; its
        corners nearer than ``min_depth`` to the camera plane are clamped to it."""
        b = np.asarray(box, dtype=float)
        c, s = np.cos(b[6]), np.sin(b[6])
        sx = np.array([1, 1, -1, -1, 1, 1, -1, -1]) * 0.5 * b[3]
        sy = np.array([1, -1, -1, 1, 1, -1, -1, 1]) * 0.5 * b[4]
        sz = np.array([1, 1, 1, 1, -1, -1, -1, -1]) * 0.5 * b[5]
        corners = np.c_[b[0] + c * sx - s * sy, b[1] + s * sx + c * sy, b[2] + sz]
        uvw = corners @ self.projection[:, :3].T + self.projection[:, 3]
        w = np.maximum(uvw[:, 2], min_depth)
        u, v = uvw[:, 0] / w, uvw[:, 1] / w
        width, height = self.size
        return np.array(
            [
                np.clip(u.min(), 0, width),
                np.clip(v.min(), 0, height),
                np.clip(u.max(), 0, width),
                np.clip(v.max(), 0, height),
            ]
        )


@dataclass(frozen=True)
class RegionOfInterest:
    """Where a dataset labels objects in bird's-eye view, from its map (Argoverse 2: the drivable
    area grown by ``AV2_ROI_MARGIN``, the region of interest its annotators label in).

    Attributes
    ----------
    polygons : each (P, 2) BEV vertices in the frame's LiDAR/vehicle coordinates (P ≥ 3)
    margin : m; the region is every point inside a polygon or within ``margin`` of one
    source : the map file the polygons come from (named by messages)
    """

    polygons: tuple[NDArray[np.float64], ...]
    margin: float
    source: str = ""

    def contains(self, xy: ArrayLike, slack: float = 0.0) -> NDArray[np.bool_]:
        """(M,) whether BEV points (M, 2) lie in the region grown by ``slack`` metres more."""
        return near_polygons(xy, self.polygons, self.margin + slack)


@dataclass
class Frame:
    """One LiDAR sweep with its labeled boxes, everything in the LiDAR/vehicle frame.

    Attributes
    ----------
    frame_id : unique within the dataset (KITTI "000123", Waymo "<segment>:<timestamp>", Argoverse 2
        "<log_id>:<timestamp_ns>")
    points : (N, 4) float32 — x, y, z, intensity
    boxes : (K, 7) float64 — cx, cy, cz, length, width, height, yaw (geometric centre, yaw about +z)
    class_names : K class names as written by the dataset ("Car", "Vehicle" …)
    object_ids : K ids (Waymo laser_object_id, Argoverse 2 track_uuid; else "<frame_id>:<index>")
    sensor_origin : (3,) position of the LiDAR in this frame (for distances and corner order)
    extras : per-object optional columns, each an array of length K (KITTI truncated, occluded,
        difficulty …)
    warnings : non-fatal notes about the input (e.g. "dropped 3 points with NaN coordinates")
    source : the file the labels were read from (KITTI label file, Waymo segment file); every
        error about this frame or one of its objects names it
    object_errors : object index → why the reader cannot use that label (the message names the
        file, the line or row and the field); those objects become rows with status ``error``
    ray_mask : (N,) bool — the points that end a ray from ``sensor_origin`` whose path up to the
        point is empty (free-space evidence); None = every point (KITTI: one lidar, one return).
        Waymo: the TOP lidar's first returns only; Argoverse 2: every point (both lidars)
    pose : (4, 4) float64 vehicle → world transform at the frame's timestamp (Waymo frame pose,
        Argoverse 2 ``city_SE3_egovehicle``), for putting the boxes of a sequence in one frame;
        None when the dataset has none (KITTI object) or the frame's pose is missing
    image_view : the camera image the labels were drawn in, when the dataset labels only what one
        camera sees (KITTI: image_2, with its DontCare regions); None = labels all around (Waymo)
    roi : where the dataset labels around the car, from its map (Argoverse 2 with the log's
        ``map/``: the drivable area grown by 5 m); None = everywhere within range
    no_label_zone : (N,) bool — the points the dataset marks as lying in an area it does not label
        (Waymo's No Label Zones: the far side of a highway, a crowded parking lot …); None = none
    timestamp : capture time in seconds (Waymo timestamp_micros / 1e6, Argoverse 2
        timestamp_ns / 1e9), for ordering a sequence in time; None when unknown (KITTI object)
    """

    frame_id: str
    points: NDArray[np.float32]
    boxes: NDArray[np.float64]
    class_names: list[str]
    object_ids: list[str]
    sensor_origin: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    source: str = ""
    object_errors: dict[int, str] = field(default_factory=dict)
    ray_mask: NDArray[np.bool_] | None = None
    pose: NDArray[np.float64] | None = None
    image_view: ImageView | None = None
    timestamp: float | None = None
    roi: RegionOfInterest | None = None
    no_label_zone: NDArray[np.bool_] | None = None

    def __post_init__(self) -> None:
        k = len(self.boxes)
        if self.boxes.shape != (k, 7):
            raise ValueError(f"frame {self.frame_id}: boxes must be (K, 7), got {self.boxes.shape}")
        if len(self.class_names) != k or len(self.object_ids) != k:
            raise ValueError(
                f"frame {self.frame_id}: {k} boxes but {len(self.class_names)} classes, {len(self.object_ids)} ids"
            )
        for name, values in self.extras.items():
            if len(values) != k:
                raise ValueError(f"frame {self.frame_id}: extra column {name!r} has {len(values)} values for {k} boxes")
        if self.no_label_zone is not None and np.shape(self.no_label_zone) != (len(self.points),):
            raise ValueError(
                f"frame {self.frame_id}: no_label_zone must be one flag per point ({len(self.points)}), "
                f"got shape {np.shape(self.no_label_zone)}"
            )
        if self.pose is not None and np.shape(self.pose) != (4, 4):
            raise ValueError(f"frame {self.frame_id}: pose must be a 4×4 transform, got shape {np.shape(self.pose)}")

    @property
    def num_objects(self) -> int:
        return len(self.boxes)


def in_labelled_region(
    boxes: ArrayLike,
    frame: Frame,
    max_range: float,
    *,
    dontcare: bool = True,
    slack_px: float = 0.0,
    slack_m: float = 0.0,
) -> NDArray[np.bool_]:
    """(K,) whether each box (K, 7) lies where the dataset labels objects: the one rule per format.

    Every format: BEV distance of the centre from the sensor ≤ ``max_range`` and beyond the ego zone
    (``MISSING_EGO_RADIUS``). With an image view (KITTI): the centre projects into image_2 (at least
    ``MISSING_MIN_DEPTH`` in front of the camera, ``slack_px`` pixels of slack) and, with
    ``dontcare``, the box's 2D projection is not ``MISSING_DONTCARE_OVERLAP`` or more inside a
    DontCare region. With a region of interest (Argoverse 2 with its map): a BEV corner of the box
    lies in it (grown by ``slack_m``), the rule AV2's own evaluation uses for cuboids. With
    ``dontcare`` and points flagged in a No Label Zone (Waymo): no such point lies in the box, the
    rule Waymo's metrics apply to predictions.
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    d = np.hypot(b[:, 0] - o[0], b[:, 1] - o[1])
    ok = (d <= max_range) & (d > C.MISSING_EGO_RADIUS)
    if frame.roi is not None and ok.any():
        k = np.flatnonzero(ok)
        c, s = np.cos(b[k, 6])[:, None], np.sin(b[k, 6])[:, None]
        u, v = BEV_CORNERS_UNIT[:, 0] * b[k, 3:4], BEV_CORNERS_UNIT[:, 1] * b[k, 4:5]  # (k, 4) each
        corners = np.stack([b[k, 0:1] + c * u - s * v, b[k, 1:2] + s * u + c * v], axis=-1)
        ok[k] = frame.roi.contains(corners.reshape(-1, 2), slack_m).reshape(-1, 4).any(axis=1)
    zone = frame.no_label_zone
    if dontcare and zone is not None and zone.any() and ok.any():
        p = np.asarray(frame.points[zone, :3], dtype=float)
        for k in np.flatnonzero(ok):
            c, s = np.cos(b[k, 6]), np.sin(b[k, 6])
            dx, dy = p[:, 0] - b[k, 0], p[:, 1] - b[k, 1]
            inside = (
                (np.abs(c * dx + s * dy) <= 0.5 * b[k, 3])
                & (np.abs(-s * dx + c * dy) <= 0.5 * b[k, 4])
                & (np.abs(p[:, 2] - b[k, 2]) <= 0.5 * b[k, 5])
            )
            ok[k] = not inside.any()
    view = frame.image_view
    if view is None or not len(b):
        return ok
    w, h = view.size
    centre = np.c_[b[:, :3], np.ones(len(b))] @ view.projection.T
    depth = centre[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u, v = centre[:, 0] / depth, centre[:, 1] / depth
    if slack_px > 0:  # a cluster's centroid (a pre-filter before boxing)
        ok &= (
            (depth > C.MISSING_MIN_DEPTH)
            & (u >= -slack_px)
            & (u < w + slack_px)
            & (v >= -slack_px)
            & (v < h + slack_px)
        )
    else:  # a box: KITTI labels objects truncated by the image's edge, up to MISSING_MAX_TRUNCATION of their 2D box
        centre_in = (u >= 0) & (u < w) & (v >= 0) & (v < h)
        ok &= (depth > C.MISSING_MIN_DEPTH) & (centre_in | (view.in_image_share(b) >= 1.0 - C.MISSING_MAX_TRUNCATION))
    if dontcare and len(view.dontcare):
        for k in np.flatnonzero(ok):
            rect = view.box_to_image(b[k])
            area = max(rect[2] - rect[0], 0.0) * max(rect[3] - rect[1], 0.0)
            if area <= 0:
                continue
            dc = view.dontcare
            iw = np.clip(np.minimum(dc[:, 2], rect[2]) - np.maximum(dc[:, 0], rect[0]), 0, None)
            ih = np.clip(np.minimum(dc[:, 3], rect[3]) - np.maximum(dc[:, 1], rect[1]), 0, None)
            if float((iw * ih).max()) >= C.MISSING_DONTCARE_OVERLAP * area:
                ok[k] = False
    return ok


@dataclass(frozen=True)
class FrameFailure:
    """A frame of a unit that could not be read; the reader goes on with the unit's next frame.

    ``frame_id`` is None when not even the id could be read (e.g. an undecodable record).
    """

    frame_id: str | None
    error: DatasetError


@dataclass(frozen=True)
class FrameRef:
    """A pointer to one unit of work (a KITTI frame, a Waymo segment) that a worker can load alone."""

    dataset_format: str
    root: str
    key: str  # KITTI frame id, or Waymo segment file path


class DatasetReader(Protocol):
    """What :mod:`labelaudit.infer` needs from a format.

    A reader lists its units of work cheaply in the main process; workers then load them by
    reference, so the main process never holds the whole dataset.
    """

    format_name: str

    def list_units(self) -> list[FrameRef]:
        """All units of work, in a stable order."""
        ...

    def load_unit(self, ref: FrameRef) -> Iterator[Frame | FrameFailure]:
        """Frames of one unit (a :class:`FrameFailure` for a frame that cannot be read); raises
        :class:`DatasetError` when the rest of the unit cannot be read."""
        ...


# --------------------------------------------------------------------------- checks readers share

BOX_FIELD_KINDS = ("centre", "centre", "centre", "size", "size", "size", "angle")
"""What each of the 7 box values is, for :func:`box_problems` (cx, cy, cz, l, w, h, yaw)."""


@functools.lru_cache(maxsize=16)
def _field_limits(kinds: tuple[str, ...]) -> tuple[NDArray[np.float64], NDArray[np.bool_], NDArray[np.float64]]:
    """The limit (F,) of every field kind, which are sizes (F,) and the lower bound (F,: MIN_BOX_SIZE
    for a size, −inf else): built once per kinds tuple (read only)."""
    limit = np.array([{"centre": C.MAX_BOX_CENTRE, "size": C.MAX_BOX_SIZE, "angle": C.MAX_BOX_ANGLE}[k] for k in kinds])
    is_size = np.array([k == "size" for k in kinds])
    lower = np.where(is_size, C.MIN_BOX_SIZE, -np.inf)
    limit.flags.writeable = is_size.flags.writeable = lower.flags.writeable = False
    return limit, is_size, lower


def box_problems(values: ArrayLike, names: Sequence[str], kinds: Sequence[str] = BOX_FIELD_KINDS) -> dict[int, str]:
    """Per-row problems of box values: not finite, or outside the sane limits (a size ≤ 0 included).

    Parameters
    ----------
    values : (K, F) the box values of K labels, F fields
    names : F field names as the file spells them (KITTI ``'x'``, Waymo v2 column names …)
    kinds : F kinds: ``"centre"`` (|v| ≤ :data:`~labelaudit.constants.MAX_BOX_CENTRE`),
        ``"size"`` (``MIN_BOX_SIZE`` ≤ v ≤ :data:`~labelaudit.constants.MAX_BOX_SIZE`) or ``"angle"``
        (|v| ≤ :data:`~labelaudit.constants.MAX_BOX_ANGLE`)

    Returns
    -------
    row → message naming every bad field, its value and what was expected (rows without
    problems are absent); vectorised, the loop runs over bad rows only.
    """
    v = np.asarray(values, dtype=np.float64).reshape(-1, len(names))
    limit, is_size, lower = _field_limits(tuple(kinds))
    ok = (np.abs(v) <= limit) & (v >= lower)  # NaN and ±inf fail the first test
    if ok.all():  # the usual frame: no label to name
        return {}
    bad = ~ok
    out: dict[int, str] = {}
    for r in np.flatnonzero(bad.any(axis=1)):
        parts = []
        for j in np.flatnonzero(bad[r]):
            x = v[r, j]
            if not np.isfinite(x):
                expected = "a finite number"
            elif is_size[j]:
                expected = f"a size in [{C.MIN_BOX_SIZE:g}, {C.MAX_BOX_SIZE:g}] m"
            else:
                expected = f"|value| ≤ {limit[j]:g}" + (" rad" if kinds[j] == "angle" else " m")
            parts.append(f"{names[j]} = {x:g} (expected {expected})")
        out[int(r)] = "; ".join(parts)
    return out

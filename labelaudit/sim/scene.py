"""Random driving scenes: a ground plane and vehicles (plus a few pedestrians and cyclists).
Pure functions of a seeded generator; no I/O.

Every object is a small set of boxes ("parts") — a car is a body plus a narrower cabin on top, a
truck a cab plus a cargo box — and its label is the union bounding box of its parts, so the label
fits its LiDAR points the way real labels fit real cars: well, but not perfectly.

Frame: the scene frame is the KITTI LiDAR frame (x forward, y left, z up, sensor at the origin),
the ground is the plane ``z = ground_z`` (−1.73 m for KITTI).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle

FloatArray = NDArray[np.float64]

VEHICLE_CLASSES: tuple[str, ...] = ("Car", "Van", "Truck")
"""Classes the label-noise injection perturbs (the paper's evaluation classes)."""

# KITTI training-set size statistics per class: mean and std of (length, width, height), in metres,
# plus the share of the class among vehicles / among vulnerable road users.
SIZE_STATS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float], float]] = {
    "Car": ((3.88, 1.63, 1.53), (0.43, 0.10, 0.14), 0.78),
    "Van": ((5.08, 1.90, 2.21), (0.50, 0.12, 0.30), 0.14),
    "Truck": ((10.1, 2.58, 3.25), (2.0, 0.15, 0.40), 0.08),
    "Pedestrian": ((0.84, 0.66, 1.76), (0.20, 0.12, 0.11), 0.6),
    "Cyclist": ((1.76, 0.60, 1.74), (0.18, 0.12, 0.09), 0.4),
}
_SIZE_LIMITS: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "Car": ((3.0, 1.4, 1.25), (5.2, 2.0, 2.0)),
    "Van": ((4.0, 1.6, 1.7), (6.5, 2.3, 3.0)),
    "Truck": ((6.5, 2.2, 2.5), (16.0, 3.0, 4.2)),
    "Pedestrian": ((0.35, 0.35, 1.3), (1.3, 1.0, 2.0)),
    "Cyclist": ((1.3, 0.4, 1.5), (2.1, 0.9, 2.0)),
}
_VEHICLE_MIX = ("Car", "Van", "Truck")
_VRU_MIX = ("Pedestrian", "Cyclist")

# Surface reflectivity ranges (dimensionless, 0..1): car paint varies a lot, glass is dark.
_PAINT_REFLECTIVITY = (0.15, 0.8)
_GLASS_REFLECTIVITY = (0.05, 0.15)
_CLOTH_REFLECTIVITY = (0.1, 0.5)
_GROUND_REFLECTIVITY = (0.12, 0.3)
_MIN_GAP = 0.3  # metres of free space kept between object footprints
_MIN_SENSOR_CLEARANCE = 2.5  # no object footprint comes closer than this to the sensor (m)
_PLACEMENT_TRIES = 40  # random placements tried per object before giving up on it


_UNIT_CORNERS = np.array(
    [[0.5, 0.5, -0.5], [-0.5, 0.5, -0.5], [-0.5, -0.5, -0.5], [0.5, -0.5, -0.5],
     [0.5, 0.5, 0.5], [-0.5, 0.5, 0.5], [-0.5, -0.5, 0.5], [0.5, -0.5, 0.5]]
)  # fmt: skip


def corners_of(boxes: FloatArray) -> FloatArray:
    """Corners of many boxes at once, in the order of :func:`labelaudit.core.geometry.box_corners`.

    A vectorised, unvalidated version for the simulator's inner loops.

    Parameters
    ----------
    boxes : (K, 7) cx, cy, cz, l, w, h, yaw

    Returns
    -------
    corners : (K, 8, 3) — 4 bottom corners counter-clockwise from front-left, then the top ones
    """
    b = np.asarray(boxes, dtype=float).reshape(-1, 7)
    local = _UNIT_CORNERS[None] * b[:, None, 3:6]  # (K, 8, 3)
    c, s = np.cos(b[:, 6])[:, None], np.sin(b[:, 6])[:, None]
    out = np.empty_like(local)
    out[..., 0] = b[:, None, 0] + c * local[..., 0] - s * local[..., 1]
    out[..., 1] = b[:, None, 1] + s * local[..., 0] + c * local[..., 1]
    out[..., 2] = b[:, None, 2] + local[..., 2]
    return out


@dataclass
class SimObject:
    """One object of a scene.

    Attributes
    ----------
    class_name : KITTI class name
    box : (7,) true label box (cx, cy, cz, l, w, h, yaw) — the union bounding box of ``parts``
    parts : (P, 7) boxes making up the object's surface, same yaw as ``box``
    reflectivity : (P,) surface reflectivity of each part, 0..1
    """

    class_name: str
    box: FloatArray
    parts: FloatArray
    reflectivity: FloatArray


@dataclass
class Scene:
    """A ground plane and objects, in the scene (= KITTI LiDAR) frame.

    Attributes
    ----------
    objects : the labelled objects, in placement order (nearest first is *not* guaranteed)
    ground_z : height of the ground plane (m)
    ground_reflectivity : reflectivity of the road surface
    clutter : unlabelled static surroundings (class "Building", "Pole" or :data:`VEGETATION`): they
        return points and occlude objects but never get a label; vegetation is porous (the
        ray-caster lets rays into it and some through it)
    """

    objects: list[SimObject] = field(default_factory=list)
    ground_z: float = -C.SIM_SENSOR_HEIGHT
    ground_reflectivity: float = 0.2
    clutter: list[SimObject] = field(default_factory=list)

    @property
    def boxes(self) -> FloatArray:
        """(K, 7) true boxes of all objects."""
        if not self.objects:
            return np.zeros((0, 7))
        return np.stack([o.box for o in self.objects])

    @property
    def class_names(self) -> list[str]:
        return [o.class_name for o in self.objects]


@dataclass(frozen=True)
class SceneSpec:
    """How scenes are drawn (defaults in :mod:`labelaudit.constants`).

    Attributes
    ----------
    num_vehicles : (min, max) vehicles per frame, inclusive
    num_vru : (min, max) pedestrians and cyclists per frame, inclusive
    distance : (min, max) distance of an object centre from the sensor (m)
    front_fraction : share of objects placed in the camera's horizontal field of view
    front_half_angle_deg : half-width of that field of view (KITTI's camera: about 40°)
    road_aligned_fraction : share of objects heading along the road (yaw near 0 or π)
    num_clutter : (min, max) unlabelled static surroundings per frame — building walls along the
        road, poles, bushes (default none: a flat, empty world)
    """

    num_vehicles: tuple[int, int] = C.SIM_NUM_VEHICLES
    num_vru: tuple[int, int] = C.SIM_NUM_VRU
    distance: tuple[float, float] = C.SIM_DISTANCE
    front_fraction: float = C.SIM_FRONT_FRACTION
    front_half_angle_deg: float = 38.0
    road_aligned_fraction: float = C.SIM_ROAD_ALIGNED_FRACTION
    num_clutter: tuple[int, int] = (0, 0)

    def __post_init__(self) -> None:
        for name in ("num_vehicles", "num_vru", "distance", "num_clutter"):
            lo, hi = getattr(self, name)
            if not (0 <= lo <= hi):
                raise ValueError(f"SceneSpec.{name} must be (min, max) with 0 <= min <= max, got ({lo}, {hi})")
        if self.distance[0] < 3.0:
            raise ValueError(
                f"SceneSpec.distance min must be >= 3 m (objects would hit the sensor), got {self.distance[0]}"
            )
        for name in ("front_fraction", "road_aligned_fraction"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise ValueError(f"SceneSpec.{name} must be in [0, 1], got {v}")


def _sample_size(rng: np.random.Generator, class_name: str) -> FloatArray:
    mean, std, _ = SIZE_STATS[class_name]
    lo, hi = _SIZE_LIMITS[class_name]
    return np.clip(np.asarray(mean) + np.asarray(std) * rng.standard_normal(3), lo, hi)


def _parts_local(rng: np.random.Generator, class_name: str, lwh: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Parts of an object in its own frame (centre at the label centre, x along its length).

    Returns
    -------
    parts : (P, 6) local (cx, cy, cz, l, w, h) whose union bounding box is exactly ``lwh``
    reflectivity : (P,)
    """
    length, width, height = lwh
    paint = rng.uniform(*_PAINT_REFLECTIVITY)
    glass = rng.uniform(*_GLASS_REFLECTIVITY)
    bottom, top = -height / 2, height / 2

    def part(x0: float, x1: float, w: float, z0: float, z1: float) -> list[float]:
        return [(x0 + x1) / 2, 0.0, (z0 + z1) / 2, x1 - x0, w, z1 - z0]

    if class_name in ("Car", "Van"):
        # Body over the full footprint, cabin (windows and roof) narrower and shorter on top.
        body_frac = rng.uniform(0.5, 0.6) if class_name == "Car" else rng.uniform(0.4, 0.5)
        cab_len = rng.uniform(0.45, 0.6) if class_name == "Car" else rng.uniform(0.7, 0.85)
        rear = rng.uniform(0.08, 0.2) if class_name == "Car" else rng.uniform(0.0, 0.05)
        z_mid = bottom + body_frac * height
        x_cab0 = -length / 2 + rear * length
        parts = [
            part(-length / 2, length / 2, width, bottom, z_mid),
            part(x_cab0, x_cab0 + cab_len * length, rng.uniform(0.82, 0.94) * width, z_mid, top),
        ]
        refl = [paint, glass]
    elif class_name == "Truck":
        # Cab in front (lower), cargo box behind it (full height), a small gap between them.
        cab = rng.uniform(0.18, 0.25) * length
        gap = rng.uniform(0.02, 0.05) * length
        parts = [
            part(
                length / 2 - cab,
                length / 2,
                rng.uniform(0.9, 0.97) * width,
                bottom,
                bottom + rng.uniform(0.7, 0.85) * height,
            ),
            part(-length / 2, length / 2 - cab - gap, width, bottom, top),
        ]
        refl = [paint, rng.uniform(*_PAINT_REFLECTIVITY)]
    elif class_name == "Pedestrian":
        # Legs (narrow) and torso with arms (full footprint).
        z_hip = bottom + rng.uniform(0.45, 0.52) * height
        parts = [
            part(-0.3 * length, 0.3 * length, 0.7 * width, bottom, z_hip),
            part(-length / 2, length / 2, width, z_hip, top),
        ]
        cloth = rng.uniform(*_CLOTH_REFLECTIVITY)
        refl = [cloth, cloth]
    elif class_name == "Cyclist":
        # Bicycle (long, thin) and rider (short, full width) on it.
        z_seat = bottom + rng.uniform(0.5, 0.6) * height
        parts = [
            part(-length / 2, length / 2, 0.3 * width, bottom, z_seat),
            part(-0.25 * length, 0.2 * length, width, z_seat - 0.1 * height, top),
        ]
        refl = [paint, rng.uniform(*_CLOTH_REFLECTIVITY)]
    else:
        raise ValueError(f"unknown class {class_name!r}; expected one of {sorted(SIZE_STATS)}")
    return np.asarray(parts, dtype=float), np.asarray(refl, dtype=float)


def make_object(
    class_name: str,
    center_xy: tuple[float, float],
    yaw: float,
    lwh: FloatArray,
    ground_z: float,
    rng: np.random.Generator,
) -> SimObject:
    """Build an object standing on the ground with its parts in the scene frame."""
    lwh = np.asarray(lwh, dtype=float)
    local, refl = _parts_local(rng, class_name, lwh)
    box = np.array([center_xy[0], center_xy[1], ground_z + lwh[2] / 2, *lwh, normalize_angle(yaw)])
    c, s = np.cos(box[6]), np.sin(box[6])
    parts = np.empty((len(local), 7))
    parts[:, 0] = box[0] + c * local[:, 0] - s * local[:, 1]
    parts[:, 1] = box[1] + s * local[:, 0] + c * local[:, 1]
    parts[:, 2] = box[2] + local[:, 2]
    parts[:, 3:6] = local[:, 3:6]
    parts[:, 6] = box[6]
    return SimObject(class_name, box, parts, refl)


def _footprints_overlap(corners: FloatArray, others: FloatArray, gap: float) -> bool:
    """Separating-axis test of one rectangle (4, 2) against many (K, 4, 2), with a safety gap."""
    if len(others) == 0:
        return False
    # Candidate separating axes: the two edge normals of every rectangle of each pair.
    axes_a = np.stack([corners[1] - corners[0], corners[3] - corners[0]])  # (2, 2)
    axes_b = np.stack([others[:, 1] - others[:, 0], others[:, 3] - others[:, 0]], axis=1)  # (K, 2, 2)
    axes = np.concatenate([np.broadcast_to(axes_a, axes_b.shape), axes_b], axis=1)  # (K, 4, 2)
    axes = axes / np.linalg.norm(axes, axis=-1, keepdims=True)
    pa = np.einsum("cd,kad->kac", corners, axes)  # (K, 4 axes, 4 corners)
    pb = np.einsum("kcd,kad->kac", others, axes)
    separated = (pa.max(-1) + gap < pb.min(-1)) | (pb.max(-1) + gap < pa.min(-1))  # (K, 4)
    return bool(np.any(~separated.any(axis=1)))


def sample_scene(
    rng: np.random.Generator, spec: SceneSpec = SceneSpec(), *, ground_z: float = -C.SIM_SENSOR_HEIGHT
) -> Scene:
    """Draw a random scene: vehicles first, then pedestrians and cyclists, none overlapping.

    Parameters
    ----------
    rng : the frame's scene generator (the same generator state always gives the same scene)
    spec : counts, distances and layout
    ground_z : height of the ground plane in the scene frame (m)
    """
    scene = Scene(ground_z=ground_z, ground_reflectivity=float(rng.uniform(*_GROUND_REFLECTIVITY)))
    n_veh = int(rng.integers(spec.num_vehicles[0], spec.num_vehicles[1] + 1))
    n_vru = int(rng.integers(spec.num_vru[0], spec.num_vru[1] + 1))
    veh_p = np.array([SIZE_STATS[c][2] for c in _VEHICLE_MIX])
    vru_p = np.array([SIZE_STATS[c][2] for c in _VRU_MIX])
    wanted = [str(c) for c in rng.choice(_VEHICLE_MIX, size=n_veh, p=veh_p / veh_p.sum())]
    wanted += [str(c) for c in rng.choice(_VRU_MIX, size=n_vru, p=vru_p / vru_p.sum())]
    footprints: list[FloatArray] = []
    half_fov = np.deg2rad(spec.front_half_angle_deg)
    for class_name in wanted:
        lwh = _sample_size(rng, class_name)
        for _ in range(_PLACEMENT_TRIES):
            front = rng.random() < spec.front_fraction
            azimuth = rng.uniform(-half_fov, half_fov) if front else rng.uniform(-np.pi, np.pi)
            dist = rng.uniform(*spec.distance)
            if rng.random() < spec.road_aligned_fraction:
                yaw = rng.normal(0.0, 0.08) + np.pi * rng.integers(0, 2)
            else:
                yaw = rng.uniform(-np.pi, np.pi)
            cxy = (dist * np.cos(azimuth), dist * np.sin(azimuth))
            trial = np.array([cxy[0], cxy[1], 0.0, lwh[0], lwh[1], 1.0, yaw])
            corners = corners_of(trial)[0, :4, :2]
            if dist - 0.5 * np.hypot(lwh[0], lwh[1]) < _MIN_SENSOR_CLEARANCE:
                continue
            if _footprints_overlap(corners, np.asarray(footprints).reshape(-1, 4, 2), _MIN_GAP):
                continue
            footprints.append(corners)
            scene.objects.append(make_object(class_name, cxy, yaw, lwh, ground_z, rng))
            break
    if spec.num_clutter[1] > 0:  # no draws otherwise: callers that keep using rng see the same stream
        _add_clutter(rng, scene, spec, footprints)
    return scene


_CLUTTER_REFLECTIVITY = (0.1, 0.6)
VEGETATION = "Vegetation"
"""Class name of the bushes among ``Scene.clutter``: porous to the ray-caster (``SIM_FOLIAGE_*``)."""


def _add_clutter(rng: np.random.Generator, scene: Scene, spec: SceneSpec, footprints: list[FloatArray]) -> None:
    """Unlabelled surroundings: building walls beside the road, poles, bushes; no overlaps."""
    n = int(rng.integers(spec.num_clutter[0], spec.num_clutter[1] + 1))
    for _ in range(n):
        kind = rng.choice(["building", "pole", "bush"], p=[0.4, 0.3, 0.3])
        for _ in range(_PLACEMENT_TRIES):
            if kind == "building":  # beside the road, along it
                lwh = np.array([rng.uniform(8, 25), rng.uniform(4, 12), rng.uniform(4, 12)])
                side = rng.choice([-1.0, 1.0])
                cxy = (rng.uniform(-60, 60), side * (rng.uniform(12, 30) + lwh[1] / 2))
                yaw = rng.normal(0.0, 0.05)
            else:
                lwh = (
                    np.array([0.3, 0.3, rng.uniform(4, 8)])
                    if kind == "pole"
                    else np.array([rng.uniform(1, 4), rng.uniform(1, 3), rng.uniform(0.5, 2.5)])
                )
                azimuth, dist = rng.uniform(-np.pi, np.pi), rng.uniform(*spec.distance)
                cxy = (dist * np.cos(azimuth), dist * np.sin(azimuth))
                yaw = rng.uniform(-np.pi, np.pi)
            corners = corners_of(np.array([cxy[0], cxy[1], 0.0, lwh[0], lwh[1], 1.0, yaw]))[0, :4, :2]
            if np.hypot(*cxy) - 0.5 * np.hypot(lwh[0], lwh[1]) < _MIN_SENSOR_CLEARANCE:
                continue
            if _footprints_overlap(corners, np.asarray(footprints).reshape(-1, 4, 2), _MIN_GAP):
                continue
            footprints.append(corners)
            box = np.array([cxy[0], cxy[1], scene.ground_z + lwh[2] / 2, *lwh, normalize_angle(yaw)])
            name = {"building": "Building", "pole": "Pole"}.get(str(kind), VEGETATION)
            scene.clutter.append(
                SimObject(name, box, box[None].copy(), np.array([rng.uniform(*_CLUTTER_REFLECTIVITY)]))
            )
            break

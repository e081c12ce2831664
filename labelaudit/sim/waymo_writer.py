"""Simulated Waymo segments, written as v2 Parquet components and as a v1 TFRecord.
Test and benchmark fixtures with known truth, built from the published v2 schema; it never audits.

The scene and the ray-caster are the KITTI simulator's (:mod:`labelaudit.sim.scene`,
:mod:`labelaudit.sim.raycast`); this module adds what Waymo needs:

* five lidars with a Waymo-like calibration — TOP (non-uniform beams, mounted rotated about z,
  64 × 2650 at full size) and FRONT / SIDE_LEFT / SIDE_RIGHT / REAR (uniform beams from −90° to
  +30°, 200 × 600 at full size);
* a moving ego vehicle: the TOP lidar sweeps while the vehicle moves, so its columns are rendered
  in ``chunks`` groups, each from the vehicle pose at that group's capture time, and the per-pixel
  pose (roll, pitch, yaw, x, y, z) is stored exactly as Waymo's TOP range-image pose;
* a second return on a share of the pixels that first hit an object (the beam's rest reaching the
  ground behind it);
* the expected points: every return's ray from the simulator's own geometry, mapped to the world
  with the pose it was rendered at and back into the frame's vehicle frame. The readers must
  reproduce them from the written files.

The scene is static in the world frame (ground z = 0) unless ``moving_fraction`` lets some vehicles
drive (constant speed and yaw rate, rendered where they are at each column group's capture time);
the ego vehicle drives with constant speed and yaw rate (planar motion: roll = pitch = 0, since
the ray-caster's ground is a plane).
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.datasets import waymo_proto as wp
from labelaudit.datasets import waymo_v2 as v2
from labelaudit.datasets.waymo_common import LidarCalibration
from labelaudit.datasets.waymo_v1 import encode_record
from labelaudit.infer.crop import points_in_boxes_numpy
from labelaudit.sim.manifest import SEQUENCE_MANIFEST_COLUMNS, write_manifest_table
from labelaudit.sim.noise import NoiseSpec, perturb_boxes
from labelaudit.sim.raycast import LidarSpec, ray_directions, render_range_image
from labelaudit.sim.scene import VEHICLE_CLASSES, Scene, SceneSpec, SimObject, sample_scene
from labelaudit.sim.tracknoise import TrackNoiseSpec, perturb_track_labels

FloatArray = NDArray[np.float64]

# KITTI simulator classes → Waymo label types (1 vehicle, 2 pedestrian, 4 cyclist)
WAYMO_TYPE = {"Car": 1, "Van": 1, "Truck": 1, "Pedestrian": 2, "Cyclist": 4}

# Full Waymo sizes (rows, columns); "small" keeps the geometry with fewer pixels, for tests.
SIZES: dict[str, dict[int, tuple[int, int]]] = {
    "real": {1: (64, 2650), 2: (200, 600), 3: (200, 600), 4: (200, 600), 5: (200, 600)},
    "small": {1: (32, 360), 2: (24, 60), 3: (24, 60), 4: (24, 60), 5: (24, 60)},
}
# name: (x, y, z, yaw) of each lidar on the vehicle; TOP is turned about z like the real one.
MOUNTS: dict[int, tuple[float, float, float, float]] = {
    1: (1.43, 0.0, 2.18, 2.59),
    2: (4.07, 0.0, 0.69, 0.0),
    3: (3.24, 1.03, 0.98, np.pi / 2),
    4: (3.24, -1.03, 0.98, -np.pi / 2),
    5: (-1.15, 0.0, 0.46, np.pi),
}
TOP_INCLINATION_DEG = (-17.6, 2.4)  # TOP beam elevation range; beams are denser near the horizon
SHORT_INCLINATION_RAD = (-np.pi / 2, np.pi / 6)  # FRONT/SIDE/REAR: uniform rows between these
MAX_RANGE = {1: 75.0, 2: 20.0, 3: 20.0, 4: 20.0, 5: 20.0}  # metres
SWEEP_SECONDS = 0.1  # one TOP revolution (10 Hz)


def _extrinsic(x: float, y: float, z: float, yaw: float, tilt: float = 0.0) -> FloatArray:
    c, s = np.cos(yaw), np.sin(yaw)
    ct, st = np.cos(tilt), np.sin(tilt)
    rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    ry = np.array([[ct, 0, st], [0, 1, 0], [-st, 0, ct]])
    e = np.eye(4)
    e[:3, :3] = rz @ ry
    e[:3, 3] = (x, y, z)
    return e


def waymo_calibrations(size: str = "small") -> dict[int, LidarCalibration]:
    """Waymo-like calibrations of the five lidars (TOP with explicit, non-uniform inclinations)."""
    out = {}
    for name, (x, y, z, yaw) in MOUNTS.items():
        h, _ = SIZES[size][name]
        tilt = 0.002 if name == 1 else 0.0  # the real TOP sits a few mrad off level
        if name == 1:
            lo, hi = np.deg2rad(TOP_INCLINATION_DEG)
            u = np.linspace(0.0, 1.0, h)
            inc = lo + (hi - lo) * (1.0 - (1.0 - u) ** 1.6)  # ascending, denser near the top (horizon)
            out[name] = LidarCalibration(name, _extrinsic(x, y, z, yaw, tilt), float(lo), float(hi), inc)
        else:
            lo, hi = SHORT_INCLINATION_RAD
            out[name] = LidarCalibration(name, _extrinsic(x, y, z, yaw), lo, hi, np.zeros(0))
    return out


def planar_pose(x: float, y: float, yaw: float) -> FloatArray:
    """(4, 4) vehicle → world for a vehicle on the ground plane."""
    return _extrinsic(x, y, 0.0, yaw)


def planar_motion(speed: float, yaw_rate: float, t: float) -> FloatArray:
    """(4, 4) pose after ``t`` seconds of driving at constant ``speed`` (m/s) and ``yaw_rate``
    (rad/s) from the identity pose: a circular arc (a straight line when the yaw rate is 0)."""
    yaw = yaw_rate * t
    if abs(yaw_rate) < 1e-12:
        x, y = speed * t, 0.0
    else:
        x, y = speed / yaw_rate * np.sin(yaw), speed / yaw_rate * (1.0 - np.cos(yaw))
    return planar_pose(x, y, yaw)


@dataclass
class SimLidarFrame:
    """What one lidar wrote in one frame: (H, W, 4) images per return, TOP pixel pose (H, W, 6)."""

    returns: list[NDArray[np.float32]]
    pixel_pose: NDArray[np.float32] | None = None


@dataclass
class SimWaymoFrame:
    """One simulated frame with its labels and the points the readers must reproduce."""

    timestamp: int
    pose: FloatArray  # (4, 4) vehicle → world at the frame timestamp
    lidars: dict[int, SimLidarFrame]
    boxes: FloatArray  # (K, 7) vehicle frame
    types: NDArray[np.int64]
    object_ids: list[str]
    num_points: NDArray[np.int64]
    points: NDArray[np.float32]  # (N, 4) expected x, y, z, intensity, vehicle frame
    sim_classes: list[str] = field(default_factory=list)  # the simulator's KITTI class names
    true_boxes: FloatArray | None = None  # (K, 7) before label noise (None: boxes are exact)
    perturbation: list[str] = field(default_factory=list)  # per object, labelaudit.sim.noise kinds
    track_error_kind: list[str] = field(
        default_factory=list
    )  # per object, labelaudit.sim.tracknoise kinds (empty: no track noise)
    track_error_size: list[float] = field(default_factory=list)  # per object, the injected error's magnitude (m / rad)


@dataclass
class SimWaymoSegment:
    name: str
    calibrations: dict[int, LidarCalibration]
    frames: list[SimWaymoFrame] = field(default_factory=list)


def scene_in_vehicle(scene: Scene, pose: FloatArray) -> Scene:
    """The world scene seen from a vehicle at planar ``pose`` (boxes moved and turned)."""
    inv = np.linalg.inv(pose)
    yaw = np.arctan2(pose[1, 0], pose[0, 0])

    def move(b: FloatArray) -> FloatArray:
        out = b.copy()
        out[..., :3] = b[..., :3] @ inv[:3, :3].T + inv[:3, 3]
        out[..., 6] = np.arctan2(np.sin(b[..., 6] - yaw), np.cos(b[..., 6] - yaw))
        return out

    objs = [SimObject(o.class_name, move(o.box), move(o.parts), o.reflectivity) for o in scene.objects]
    return Scene(objects=objs, ground_z=scene.ground_z, ground_reflectivity=scene.ground_reflectivity)


def vehicle_motions(rng: np.random.Generator, scene: Scene, fraction: float) -> list[tuple[float, float] | None]:
    """(speed, yaw rate) of each object that drives (vehicles only, a ``fraction`` of them), None for parked ones."""
    out: list[tuple[float, float] | None] = []
    for o in scene.objects:
        u, v, w = rng.random(3)
        if o.class_name in VEHICLE_CLASSES and u < fraction:
            lo, hi = C.SIM_MOVING_SPEED
            out.append((lo + (hi - lo) * v, C.SIM_MOVING_YAW_RATE * (2.0 * w - 1.0)))
        else:
            out.append(None)
    return out


def scene_at(world: Scene, motions: list[tuple[float, float] | None], t: float) -> Scene:
    """The world scene at time ``t``: each driving object moved along its arc (constant speed and yaw rate)."""
    if not any(motions):
        return world
    objs = []
    for o, m in zip(world.objects, motions):
        if m is None:
            objs.append(o)
            continue
        speed, rate = m
        c0, th0 = o.box[:2], float(o.box[6])
        if abs(rate) < 1e-9:
            shift = speed * t * np.array([np.cos(th0), np.sin(th0)])
        else:
            shift = (
                speed / rate * np.array([np.sin(th0 + rate * t) - np.sin(th0), np.cos(th0) - np.cos(th0 + rate * t)])
            )
        turn = rate * t
        rot = np.array([[np.cos(turn), -np.sin(turn)], [np.sin(turn), np.cos(turn)]])

        def move(
            b: FloatArray, c0: FloatArray = c0, rot: FloatArray = rot, shift: FloatArray = shift, turn: float = turn
        ) -> FloatArray:
            out = b.copy()
            out[..., :2] = (b[..., :2] - c0) @ rot.T + c0 + shift
            out[..., 6] = np.arctan2(np.sin(b[..., 6] + turn), np.cos(b[..., 6] + turn))
            return out

        objs.append(SimObject(o.class_name, move(o.box), move(o.parts), o.reflectivity))
    return Scene(objects=objs, ground_z=world.ground_z, ground_reflectivity=world.ground_reflectivity)


def _spec(calib: LidarCalibration, width: int, height: int, name: int, noise: bool) -> LidarSpec:
    el = np.rad2deg(calib.row_inclinations(height))  # top row first, the simulator's order
    kw = {} if noise else {"range_noise_std": 0.0, "dropout": 0.0, "far_dropout": 0.0}
    return LidarSpec(
        beams=height,
        columns=width,
        inclinations_deg=tuple(float(v) for v in el),
        min_range=0.3,
        max_range=MAX_RANGE[name],
        **kw,
    )


def _points_of(image: Any, rows_cols_mask: NDArray[np.bool_], ranges: NDArray[np.float32]) -> NDArray[np.float64]:
    """Vehicle-frame (render-time) xyz of the pixels in ``mask`` with the given ranges.

    Uses the simulator's own ray geometry (not the readers'), so the readers are checked against
    an independent implementation of the same convention.
    """
    dirs = ray_directions(image.inclinations, image.azimuths)[rows_cols_mask]
    xyz = dirs * ranges[rows_cols_mask][:, None].astype(np.float64)
    return xyz @ image.extrinsic[:3, :3].T + image.extrinsic[:3, 3]


def simulate_waymo_segment(
    seed: int = 0,
    frames: int = 2,
    size: str = "small",
    speed: float = 12.0,
    yaw_rate: float = 0.3,
    chunks: int = 16,
    second_return_fraction: float = 0.2,
    noise: bool = True,
    label_noise: NoiseSpec | None = None,
    scene_spec: SceneSpec | None = None,
    world_offset: tuple[float, float] = (1200.0, -340.0),
    name: str | None = None,
    track_noise: TrackNoiseSpec | None = None,
    moving_fraction: float = 0.0,
) -> SimWaymoSegment:
    """Render a Waymo segment of a static scene seen from a moving vehicle.

    Parameters
    ----------
    seed : scene and noise seed
    frames : frames at 10 Hz
    size : "small" (tests) or "real" (TOP 64 × 2650, others 200 × 600)
    speed, yaw_rate : ego motion (m/s, rad/s)
    chunks : TOP column groups rendered from their own pose (rolling shutter); 1 = no motion blur
    second_return_fraction : share of object pixels that also get a second (ground) return
    noise : range noise and dropout of the simulator's sensor
    label_noise : label noise injected into the written boxes (vehicles only, per frame, from the
        KITTI simulator); ``true_boxes`` and ``perturbation`` record it
    scene_spec : object counts and distances (default: the simulator's)
    world_offset : where the scene sits in the world frame, so poses have large translations
    name : segment context name (default derived from the seed)
    track_noise : per-frame label noise inside tracks (ordinary scatter and injected annotator
        errors, :mod:`labelaudit.sim.tracknoise`), after ``label_noise``; ``track_error_kind`` and
        ``track_error_size`` record it
    moving_fraction : share of vehicles that drive (constant speed and yaw rate, constants
        ``SIM_MOVING_*``); the rest of the scene is static. 0 keeps the scene of earlier versions
    """
    if size not in SIZES:
        raise ValueError(f"size must be one of {sorted(SIZES)}, got {size!r}")
    if frames < 1 or chunks < 1:
        raise ValueError(f"frames and chunks must be >= 1, got {frames}, {chunks}")
    rng = np.random.default_rng(seed)
    scene_v = sample_scene(rng, scene_spec or SceneSpec(), ground_z=0.0)
    ox, oy = world_offset
    start = planar_pose(ox, oy, 0.0)
    # the scene was drawn around the vehicle at t = 0: move it to the world
    world = scene_in_vehicle(scene_v, np.linalg.inv(start))
    motions = (
        vehicle_motions(np.random.default_rng([seed, 13]), world, moving_fraction)
        if moving_fraction > 0
        else [None] * len(world.objects)
    )
    calibs = waymo_calibrations(size)
    seg = SimWaymoSegment(name or f"{seed:019d}_0000_000_0020_000", calibs)
    ids = [f"sim{seed}-{i:04d}" for i in range(len(world.objects))]
    types = np.array([WAYMO_TYPE.get(o.class_name, 0) for o in world.objects], dtype=np.int64)
    t0 = 1_600_000_000_000_000 + seed * 1_000_000_000

    def pose_at(t: float) -> FloatArray:
        return start @ planar_motion(speed, yaw_rate, t)

    for f in range(frames):
        t_f = f * SWEEP_SECONDS
        pose_f = pose_at(t_f)
        pose_f_inv = np.linalg.inv(pose_f)
        lidars: dict[int, SimLidarFrame] = {}
        expected: list[NDArray[np.float32]] = []
        for name_, calib in calibs.items():
            h, w = SIZES[size][name_]
            spec = _spec(calib, w, h, name_, noise)
            n_chunks = chunks if name_ == 1 else 1
            bounds = np.linspace(0, w, n_chunks + 1).round().astype(int)
            r1 = np.zeros((h, w, 4), dtype=np.float32)
            r2 = np.zeros((h, w, 4), dtype=np.float32)
            r1[..., 3] = r2[..., 3] = -1.0  # not in a no-label zone
            r2[..., 0] = -1.0
            ppose = np.zeros((h, w, 6), dtype=np.float32)
            for c in range(n_chunks):
                j0, j1 = bounds[c], bounds[c + 1]
                if j1 <= j0:
                    continue
                # column j is captured at (j + ½)/W of the sweep, centred on the frame time
                t_c = t_f + ((j0 + j1) / 2.0 / w - 0.5) * SWEEP_SECONDS if n_chunks > 1 else t_f
                pose_c = pose_at(t_c)
                local = scene_in_vehicle(scene_at(world, motions, t_c), pose_c)
                img = render_range_image(local, spec, calib.extrinsic, rng if noise else None)
                ground = render_range_image(
                    Scene([], local.ground_z, local.ground_reflectivity), spec, calib.extrinsic, None
                )
                cols = np.zeros((h, w), dtype=bool)
                cols[:, j0:j1] = True
                rng_c = np.where(cols, img.range, -1.0).astype(np.float32)
                r1[..., 0] = np.where(cols, img.range, r1[..., 0])
                r1[..., 1] = np.where(cols, img.intensity, r1[..., 1])
                second = cols & (img.range > 0) & (img.hit >= 0) & (ground.range > 0)
                second &= rng.random((h, w)) < second_return_fraction
                r2[..., 0] = np.where(second, ground.range, r2[..., 0])
                r2[..., 1] = np.where(second, ground.intensity, r2[..., 1])
                m_to_frame = pose_f_inv @ pose_c
                for mask, ranges, inten in (
                    (rng_c > 0, img.range, img.intensity),
                    (second, ground.range, ground.intensity),
                ):
                    xyz = _points_of(img, mask, ranges) @ m_to_frame[:3, :3].T + m_to_frame[:3, 3]
                    pts = np.empty((len(xyz), 4), dtype=np.float32)
                    pts[:, :3], pts[:, 3] = xyz, inten[mask]
                    expected.append(pts)
                yaw_c = np.arctan2(pose_c[1, 0], pose_c[0, 0])
                ppose[:, j0:j1] = (0.0, 0.0, yaw_c, pose_c[0, 3], pose_c[1, 3], pose_c[2, 3])
            lidars[name_] = SimLidarFrame([r1, r2], ppose if name_ == 1 else None)
        true_boxes = scene_in_vehicle(scene_at(world, motions, t_f), pose_f).boxes
        classes = [o.class_name for o in world.objects]
        if label_noise is not None:
            boxes, kinds = perturb_boxes(true_boxes, classes, label_noise, np.random.default_rng([seed, f, 7]))
        else:
            boxes, kinds = true_boxes, ["none"] * len(classes)
        track_kinds: list[str] = []
        track_sizes: list[float] = []
        if track_noise is not None:
            boxes, track_kinds, mags = perturb_track_labels(
                boxes, classes, track_noise, np.random.default_rng([seed, f, 11])
            )
            track_sizes = mags.tolist()
        pts = np.concatenate(expected) if expected else np.zeros((0, 4), np.float32)
        counts = np.array(
            [len(idx) for idx in points_in_boxes_numpy(pts, boxes)], dtype=np.int64
        )  # Waymo counts every point in the box
        seg.frames.append(
            SimWaymoFrame(
                t0 + int(round(t_f * 1e6)),
                pose_f,
                lidars,
                boxes,
                types.copy(),
                list(ids),
                counts,
                pts,
                classes,
                true_boxes,
                kinds,
                track_kinds,
                track_sizes,
            )
        )
    return seg


# --- writers ---------------------------------------------------------------------------------------


def _difficulty(num_points: NDArray[np.int64]) -> NDArray[np.int8]:
    # Waymo: LEVEL_2 for boxes with at most 5 lidar points, else LEVEL_1
    return np.where(num_points <= 5, 2, 1).astype(np.int8)


def write_waymo_v1(segment: SimWaymoSegment, path: str | Path) -> Path:
    """Write the segment as one v1 TFRecord file of ``Frame`` protos; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "wb") as fh:
        for fr in segment.frames:
            msg = wp.Frame(timestamp_micros=fr.timestamp)
            msg.context.name = segment.name
            for name, c in segment.calibrations.items():
                lc = msg.context.laser_calibrations.add(name=name)
                lc.extrinsic.transform.extend(c.extrinsic.ravel().tolist())
                lc.beam_inclination_min, lc.beam_inclination_max = c.inclination_min, c.inclination_max
                lc.beam_inclinations.extend(c.inclinations.tolist())
            msg.pose.transform.extend(fr.pose.ravel().tolist())
            for name, lid in fr.lidars.items():
                laser = msg.lasers.add(name=name)
                for ri, image in zip((laser.ri_return1, laser.ri_return2), lid.returns):
                    ri.range_image_compressed = zlib.compress(wp.encode_matrix_float(image))
                if lid.pixel_pose is not None:
                    laser.ri_return1.range_image_pose_compressed = zlib.compress(wp.encode_matrix_float(lid.pixel_pose))
            diff = _difficulty(fr.num_points)
            for k, box in enumerate(fr.boxes):
                lab = msg.laser_labels.add(type=int(fr.types[k]), id=fr.object_ids[k])
                b = lab.box
                b.center_x, b.center_y, b.center_z, b.length, b.width, b.height, b.heading = (float(v) for v in box)
                lab.num_lidar_points_in_box = int(fr.num_points[k])
                lab.detection_difficulty_level = lab.tracking_difficulty_level = int(diff[k])
            fh.write(encode_record(msg.SerializeToString()))
    return path


def _image_columns(images: list[NDArray[np.float32] | None]) -> tuple[pa.Array, pa.Array]:
    values = pa.array([None if im is None else im.ravel() for im in images], type=pa.list_(pa.float32()))
    shapes = pa.array([None if im is None else list(im.shape) for im in images], type=pa.list_(pa.int32(), 3))
    return values, shapes


def write_waymo_v2(
    segment: SimWaymoSegment, root: str | Path, pose_dtype: type = np.float64, rows_per_group: int = 7
) -> Path:
    """Write the segment's five components under ``root/<component>/<segment>.parquet``.

    Parameters
    ----------
    pose_dtype : float type of ``vehicle_pose`` transforms (real files use float32)
    rows_per_group : Parquet row-group size of the big components, small so that a frame's rows
        span row groups (the reader must cope, as with real files)
    """
    root = Path(root)
    seg = segment.name
    for c in v2.COMPONENTS:
        (root / c).mkdir(parents=True, exist_ok=True)
    string, i64, i8 = pa.string(), pa.int64(), pa.int8()

    # lidar_box
    cols: dict[str, list] = {
        k: [] for k in [v2.K_SEG, v2.K_TS, v2.K_OBJ, *v2.BOX_COLUMNS.values(), *v2.BOX_EXTRAS.values()]
    }
    for fr in segment.frames:
        diff = _difficulty(fr.num_points)
        for k, box in enumerate(fr.boxes):
            cols[v2.K_SEG].append(seg)
            cols[v2.K_TS].append(fr.timestamp)
            cols[v2.K_OBJ].append(fr.object_ids[k])
            for key, value in zip(("cx", "cy", "cz", "length", "width", "height", "heading"), box):
                cols[v2.BOX_COLUMNS[key]].append(float(value))
            cols[v2.BOX_COLUMNS["type"]].append(int(fr.types[k]))
            cols[v2.BOX_EXTRAS["num_lidar_points_in_box"]].append(int(fr.num_points[k]))
            cols[v2.BOX_EXTRAS["num_top_lidar_points_in_box"]].append(0)
            cols[v2.BOX_EXTRAS["detection_difficulty"]].append(int(diff[k]))
            cols[v2.BOX_EXTRAS["tracking_difficulty"]].append(int(diff[k]))
            cols[v2.BOX_EXTRAS["speed_x"]].append(0.0)
            cols[v2.BOX_EXTRAS["speed_y"]].append(0.0)
    types = {
        v2.K_SEG: string,
        v2.K_TS: i64,
        v2.K_OBJ: string,
        v2.BOX_COLUMNS["type"]: i8,
        v2.BOX_EXTRAS["num_lidar_points_in_box"]: i64,
        v2.BOX_EXTRAS["num_top_lidar_points_in_box"]: i64,
        v2.BOX_EXTRAS["detection_difficulty"]: i8,
        v2.BOX_EXTRAS["tracking_difficulty"]: i8,
    }
    pq.write_table(
        pa.table({k: pa.array(v, type=types.get(k, pa.float64())) for k, v in cols.items()}),
        root / "lidar_box" / f"{seg}.parquet",
    )

    # lidar and lidar_pose
    keys: dict[str, list] = {v2.K_SEG: [], v2.K_TS: [], v2.K_LASER: []}
    ret: list[list] = [[], []]
    pkeys: dict[str, list] = {v2.K_SEG: [], v2.K_TS: [], v2.K_LASER: []}
    poses: list = []
    for fr in segment.frames:
        for name, lid in fr.lidars.items():
            for d in [keys] + ([pkeys] if lid.pixel_pose is not None else []):
                d[v2.K_SEG].append(seg)
                d[v2.K_TS].append(fr.timestamp)
                d[v2.K_LASER].append(name)
            for k in range(2):
                ret[k].append(lid.returns[k] if k < len(lid.returns) else None)
            if lid.pixel_pose is not None:
                poses.append(lid.pixel_pose)
    table = {
        v2.K_SEG: pa.array(keys[v2.K_SEG], string),
        v2.K_TS: pa.array(keys[v2.K_TS], i64),
        v2.K_LASER: pa.array(keys[v2.K_LASER], i8),
    }
    for k, (vcol, scol) in enumerate(v2.LIDAR_RETURNS):
        table[vcol], table[scol] = _image_columns(ret[k])
    pq.write_table(pa.table(table), root / "lidar" / f"{seg}.parquet", row_group_size=rows_per_group)
    ptable = {
        v2.K_SEG: pa.array(pkeys[v2.K_SEG], string),
        v2.K_TS: pa.array(pkeys[v2.K_TS], i64),
        v2.K_LASER: pa.array(pkeys[v2.K_LASER], i8),
    }
    ptable[v2.POSE_COLUMNS[0]], ptable[v2.POSE_COLUMNS[1]] = _image_columns(poses)
    pq.write_table(pa.table(ptable), root / "lidar_pose" / f"{seg}.parquet", row_group_size=max(1, rows_per_group // 3))

    # lidar_calibration
    names = sorted(segment.calibrations)
    cal = [segment.calibrations[n] for n in names]
    pq.write_table(
        pa.table(
            {
                v2.K_SEG: pa.array([seg] * len(names), string),
                v2.K_LASER: pa.array(names, i8),
                v2.CAL_EXTRINSIC: pa.array([c.extrinsic.ravel().tolist() for c in cal], pa.list_(pa.float64(), 16)),
                v2.CAL_MIN: pa.array([c.inclination_min for c in cal], pa.float64()),
                v2.CAL_MAX: pa.array([c.inclination_max for c in cal], pa.float64()),
                v2.CAL_VALUES: pa.array([c.inclinations.tolist() or None for c in cal], pa.list_(pa.float64())),
            }
        ),
        root / "lidar_calibration" / f"{seg}.parquet",
    )

    # vehicle_pose
    ftype = pa.float32() if np.dtype(pose_dtype) == np.float32 else pa.float64()
    pq.write_table(
        pa.table(
            {
                v2.K_SEG: pa.array([seg] * len(segment.frames), string),
                v2.K_TS: pa.array([fr.timestamp for fr in segment.frames], i64),
                v2.VEHICLE_POSE: pa.array([fr.pose.ravel().tolist() for fr in segment.frames], pa.list_(ftype, 16)),
            }
        ),
        root / "vehicle_pose" / f"{seg}.parquet",
    )
    return root


def write_as_kitti(segment: SimWaymoSegment, root: str | Path, seed: int = 0) -> list[str]:
    """Write the same frames in KITTI layout (``root/training/…``), for cross-format checks.

    The KITTI LiDAR frame is the Waymo vehicle frame, the velodyne file holds the simulator's
    expected points (all lidars), and labels are the same boxes (every object, exact floats, KITTI
    class names) through a KITTI-like camera calibration. Returns the KITTI frame ids in order.
    """
    from labelaudit.sim.kitti_writer import kitti_labels, make_calibration, write_kitti_frame

    rng = np.random.default_rng(seed)
    ids = []
    for i, fr in enumerate(segment.frames):
        frame_id = f"{i:06d}"
        calib = make_calibration(rng)
        info = kitti_labels(
            fr.boxes, fr.boxes, fr.sim_classes, np.zeros(len(fr.boxes)), calib, label_fov="all", precision=None
        )
        write_kitti_frame(root, frame_id, fr.points, info.lines, calib)
        ids.append(frame_id)
    return ids


def write_manifest(segments: list[SimWaymoSegment], path: str | Path) -> Path:
    """One row per object: frame_id, object_id, class names, true and written box, perturbation,
    the injected track error (``track_error_kind``: none / length / width / yaw / flip / centre) and its size."""
    rows: dict[str, list] = {k: [] for k in SEQUENCE_MANIFEST_COLUMNS}
    for seg in segments:
        for fr in seg.frames:
            true = fr.boxes if fr.true_boxes is None else fr.true_boxes
            for k in range(len(fr.boxes)):
                rows["frame_id"].append(f"{seg.name}:{fr.timestamp}")
                rows["object_id"].append(fr.object_ids[k])
                rows["class_name"].append(
                    {1: "Vehicle", 2: "Pedestrian", 4: "Cyclist"}.get(int(fr.types[k]), "Unknown")
                )
                rows["sim_class"].append(fr.sim_classes[k] if fr.sim_classes else "")
                rows["true_box"].append([float(v) for v in true[k]])
                rows["written_box"].append([float(v) for v in fr.boxes[k]])
                rows["perturbation"].append(fr.perturbation[k] if fr.perturbation else "none")
                rows["track_error_kind"].append(fr.track_error_kind[k] if fr.track_error_kind else "none")
                rows["track_error_size"].append(float(fr.track_error_size[k]) if fr.track_error_size else 0.0)
    return write_manifest_table(pa.table(rows), path)


def simulate_waymo_dataset(
    out_dir: str | Path,
    segments: int = 2,
    frames: int = 3,
    seed: int = 0,
    size: str = "small",
    formats: tuple[str, ...] = ("waymo-v2", "waymo-v1"),
    label_noise: NoiseSpec | None = None,
    track_noise: TrackNoiseSpec | None = None,
    moving_fraction: float = 0.0,
) -> dict[str, Path]:
    """Simulate ``segments`` Waymo segments and write them in each of ``formats``.

    Layout: ``out_dir/waymo_v2/<component>/<segment>.parquet``,
    ``out_dir/waymo_v1/<segment>.tfrecord`` and ``out_dir/manifest.parquet`` (true vs written
    boxes). Returns ``{format: dataset root}``.
    """
    unknown = set(formats) - {"waymo-v2", "waymo-v1"}
    if unknown:
        raise ValueError(f"unknown formats {sorted(unknown)}; expected waymo-v2 and/or waymo-v1")
    out = Path(out_dir)
    segs = [
        simulate_waymo_segment(
            seed=seed + i,
            frames=frames,
            size=size,
            label_noise=label_noise,
            track_noise=track_noise,
            moving_fraction=moving_fraction,
        )
        for i in range(segments)
    ]
    roots: dict[str, Path] = {}
    if "waymo-v2" in formats:
        roots["waymo-v2"] = out / "waymo_v2"
        for seg in segs:
            write_waymo_v2(seg, roots["waymo-v2"])
    if "waymo-v1" in formats:
        roots["waymo-v1"] = out / "waymo_v1"
        for seg in segs:
            write_waymo_v1(seg, roots["waymo-v1"] / f"{seg.name}.tfrecord")
    write_manifest(segs, out / "manifest.parquet")
    return roots

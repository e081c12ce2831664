"""Simulated Argoverse 2 logs, and the writers of AV2's files: cuboids, sweeps, ego poses, calibration.
Test and benchmark fixtures in the layout :mod:`labelaudit.datasets.av2` reads; it never audits.

The file writers take whatever boxes and points they are given (a simulated sequence, a perturbed
copy of real annotations, a hand-made bad file), in the column names and types of the real
dataset: cuboids as float64 with a quaternion per row, sweeps as float16 ``x, y, z`` with uint8
``intensity`` and ``laser_number`` and int32 ``offset_ns``. :func:`simulate_av2_log` renders a log
with the Waymo simulator's scene, ego motion and label noise and AV2's two lidars;
:func:`write_av2_log` writes any :class:`SimAv2Log` (its frames' boxes as they are, so noise
added to them afterwards is written too).
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import yaw_quaternion
from labelaudit.datasets import av2
from labelaudit.infer.crop import points_in_boxes_numpy
from labelaudit.sim.detector import DetectorSpec, DetectorSummary
from labelaudit.sim.manifest import MANIFEST_NAME, SEQUENCE_MANIFEST_COLUMNS, write_manifest_table
from labelaudit.sim.noise import NoiseSpec, perturb_boxes
from labelaudit.sim.raycast import LidarSpec, render_range_image
from labelaudit.sim.scene import SceneSpec, sample_scene
from labelaudit.sim.tracknoise import TrackNoiseSpec, perturb_track_labels
from labelaudit.sim.waymo_writer import planar_motion, planar_pose, scene_at, scene_in_vehicle, vehicle_motions

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


def write_sweep(
    path: str | Path, points: ArrayLike, laser_number: ArrayLike | None = None, offset_ns: ArrayLike | None = None
) -> Path:
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
    cols["laser_number"] = pa.array(
        np.zeros(n, np.uint8) if laser_number is None else np.asarray(laser_number, dtype=np.uint8)
    )
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
    """Write a Feather file atomically (a temporary name, then a rename): a stopped run leaves whole files."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    feather.write_feather(table, tmp, compression="uncompressed")
    os.replace(tmp, path)
    return path


# --------------------------------------------------------------------------- simulated logs

# The simulator's classes → AV2 categories (AV2's REGULAR_VEHICLE includes vans; a rider is BICYCLIST).
AV2_CATEGORY = {
    "Car": "REGULAR_VEHICLE",
    "Van": "REGULAR_VEHICLE",
    "Truck": "BOX_TRUCK",
    "Pedestrian": "PEDESTRIAN",
    "Cyclist": "BICYCLIST",
}
# Elevations (deg) of the 32 lasers of a VLP-32C, top first: dense around the horizon.
VLP32C_INCLINATION_DEG = (
    15.0,
    10.33,
    7.0,
    4.67,
    3.33,
    2.33,
    1.67,
    1.33,
    1.0,
    0.67,
    0.33,
    0.0,
    -0.33,
    -0.67,
    -1.0,
    -1.33,
    -1.67,
    -2.0,
    -2.33,
    -2.67,
    -3.0,
    -3.33,
    -3.67,
    -4.0,
    -4.67,
    -5.33,
    -6.15,
    -7.25,
    -8.84,
    -11.31,
    -15.64,
    -25.0,
)
AV2_COLUMNS = {"real": 1800, "small": 360}  # azimuth columns per sweep: 0.2° (VLP-32C at 10 Hz), or a cheap 1°
AV2_MAX_RANGE = 200.0  # m; VLP-32C
SWEEP_NS = 100_000_000  # 10 Hz
AV2_T0 = 315_966_265_259_836_000  # ns; timestamps start where the real val logs do (+ 1 s per seed)


@dataclass
class SimAv2Frame:
    """One simulated sweep with its labels (egovehicle frame).

    Attributes
    ----------
    timestamp : ns
    pose : (4, 4) egovehicle → city
    points : (N, 4) float32 x, y, z, intensity (0–255) as the reader returns them (float16-rounded)
    laser_number : (N,) 0–31 up lidar, 32–63 down lidar
    offset_ns : (N,) capture time after the sweep timestamp
    boxes : (K, 7) written labels; true_boxes (K, 7) before label noise
    categories, track_ids, sim_classes, perturbation : K strings each
    num_interior_pts : (K,) points of ``points`` inside each written box (boundary included)
    track_error_kind, track_error_size : K injected track errors (:mod:`labelaudit.sim.tracknoise`; empty without)
    """

    timestamp: int
    pose: FloatArray
    points: NDArray[np.float32]
    laser_number: NDArray[np.uint8]
    offset_ns: NDArray[np.int32]
    boxes: FloatArray
    true_boxes: FloatArray
    categories: list[str]
    track_ids: list[str]
    sim_classes: list[str]
    perturbation: list[str]
    num_interior_pts: NDArray[np.int64]
    track_error_kind: list[str] = field(
        default_factory=list
    )  # per object, labelaudit.sim.tracknoise kinds (empty: no track noise)
    track_error_size: list[float] = field(default_factory=list)  # per object, the injected error's magnitude (m / rad)


@dataclass
class SimAv2Log:
    log_id: str
    mounts: dict[str, tuple[float, float, float]]
    frames: list[SimAv2Frame] = field(default_factory=list)


def _uuid(rng: np.random.Generator) -> str:
    """A version-4 UUID string drawn from ``rng`` (reproducible, unlike uuid.uuid4)."""
    return str(uuid.UUID(bytes=rng.bytes(16), version=4))


def av2_lidar_spec(size: str = "small", noise: bool = True) -> LidarSpec:
    """One of AV2's two VLP-32C: 32 lasers, 0.2° azimuth step (``"small"``: 1°)."""
    if size not in AV2_COLUMNS:
        raise ValueError(f"size must be one of {sorted(AV2_COLUMNS)}, got {size!r}")
    kw = {} if noise else {"range_noise_std": 0.0, "dropout": 0.0, "far_dropout": 0.0}
    return LidarSpec(
        beams=len(VLP32C_INCLINATION_DEG),
        columns=AV2_COLUMNS[size],
        inclinations_deg=VLP32C_INCLINATION_DEG,
        min_range=1.0,
        max_range=AV2_MAX_RANGE,
        **kw,
    )


def simulate_av2_log(
    seed: int = 0,
    frames: int = 3,
    size: str = "small",
    speed: float = 8.0,
    yaw_rate: float = 0.2,
    noise: bool = True,
    label_noise: NoiseSpec | None = None,
    scene_spec: SceneSpec | None = None,
    world_offset: tuple[float, float] = (5200.0, 2380.0),
    track_noise: TrackNoiseSpec | None = None,
    moving_fraction: float = 0.0,
) -> SimAv2Log:
    """Render an Argoverse 2 log: a static scene seen from an ego vehicle driving through it.

    The scene, the ego motion and the label noise are the Waymo simulator's
    (:func:`~labelaudit.sim.waymo_writer.simulate_waymo_segment`); the sensors are AV2's two
    VLP-32C at the rig's mounts (both upright here; the real down lidar hangs upside down, which
    changes which elevations it covers, not where its rays start). Every sweep is rendered from
    the frame's pose, so its points are where the labels are (no motion distortion), as the reader
    assumes; ``offset_ns`` is each column's capture time within the sweep, for the record.
    Every object keeps one track uuid for the whole log.

    Parameters
    ----------
    seed : scene, sensor-noise and id seed
    frames : sweeps at 10 Hz
    size : "small" (1° azimuth step, tests) or "real" (0.2°, ~2 × 57k rays)
    speed, yaw_rate : ego motion (m/s, rad/s)
    noise : range noise and dropout of the sensors
    label_noise : label noise injected into the written boxes (vehicles, per frame)
    scene_spec : object counts and distances (default: the simulator's, labelled all around)
    world_offset : where the scene sits in the city frame
    track_noise : per-frame label noise inside tracks (ordinary scatter and injected annotator
        errors), after ``label_noise``, as the Waymo simulator's
    moving_fraction : share of vehicles that drive (the Waymo simulator's motion); 0 = a static scene
    """
    if frames < 1:
        raise ValueError(f"frames must be >= 1, got {frames}")
    rng = np.random.default_rng([seed, 21])
    spec = scene_spec or SceneSpec(front_fraction=0.0)  # AV2 labels 360°: objects all around
    scene_v = sample_scene(rng, spec, ground_z=0.0)
    start = planar_pose(*world_offset, 0.0)
    world = scene_in_vehicle(scene_v, np.linalg.inv(start))  # drawn around the ego at t = 0
    motions = (
        vehicle_motions(np.random.default_rng([seed, 13]), world, moving_fraction)
        if moving_fraction > 0
        else [None] * len(world.objects)
    )
    log = SimAv2Log(_uuid(rng), {n: tuple(C.AV2_LIDAR_MOUNTS[n]) for n in av2.LIDARS})
    tracks = [_uuid(rng) for _ in world.objects]
    classes = [o.class_name for o in world.objects]
    lidar = av2_lidar_spec(size, noise)
    t0 = AV2_T0 + seed * 1_000_000_000
    for f in range(frames):
        t = f * SWEEP_NS / 1e9
        pose = start @ planar_motion(speed, yaw_rate, t)
        local = scene_in_vehicle(scene_at(world, motions, t), pose)
        parts, lasers, offsets = [], [], []
        for k, name in enumerate(av2.LIDARS):
            x, y, z = log.mounts[name]
            mount = planar_pose(x, y, 0.0)
            mount[2, 3] = z
            image = render_range_image(local, lidar, mount, rng if noise else None)
            pts, _ = image.points("scene")
            rows, cols = np.nonzero(image.valid)
            parts.append(pts)
            lasers.append((32 * k + rows).astype(np.uint8))
            # column j is captured (j + ½)/W into the sweep; the down lidar fires half a turn later
            offsets.append((((cols + 0.5) / lidar.columns + 0.5 * k) % 1.0 * SWEEP_NS).astype(np.int32))
        points = np.concatenate(parts)
        points[:, 3] = np.clip(np.rint(points[:, 3] * 255.0), 0, 255)
        points[:, :3] = points[:, :3].astype(np.float16)  # what the file keeps
        true_boxes = local.boxes
        if label_noise is not None:
            boxes, kinds = perturb_boxes(true_boxes, classes, label_noise, np.random.default_rng([seed, f, 7]))
        else:
            boxes, kinds = true_boxes.copy(), ["none"] * len(classes)
        track_kinds: list[str] = []
        track_sizes: list[float] = []
        if track_noise is not None:
            boxes, track_kinds, mags = perturb_track_labels(
                boxes, classes, track_noise, np.random.default_rng([seed, f, 11])
            )
            track_sizes = mags.tolist()
        counts = np.array([len(i) for i in points_in_boxes_numpy(points, boxes)], dtype=np.int64)
        log.frames.append(
            SimAv2Frame(
                t0 + f * SWEEP_NS,
                pose,
                points,
                np.concatenate(lasers),
                np.concatenate(offsets),
                boxes,
                true_boxes,
                [AV2_CATEGORY.get(c, c.upper()) for c in classes],
                list(tracks),
                list(classes),
                list(kinds),
                counts,
                track_kinds,
                track_sizes,
            )
        )
    return log


def write_av2_log(log: SimAv2Log, root: str | Path, *, sweeps: bool = True) -> Path:
    """Write a log under ``root/<log_id>/`` (annotations, sweeps, poses, calibration); returns the log folder.

    ``sweeps=False`` writes the labels and poses only (a log as the av2-api test data ships it:
    annotation-only timestamps). Ego poses are written at every sweep timestamp and three times
    between sweeps, as AV2's pose stream is denser than its sweeps.
    """
    folder = Path(root) / log.log_id
    frames = log.frames
    ts = [fr.timestamp for fr in frames for _ in range(len(fr.boxes))]
    write_annotations(
        folder / av2.ANNOTATIONS,
        ts,
        np.concatenate([fr.boxes for fr in frames]).reshape(-1, 7),
        [c for fr in frames for c in fr.categories],
        [t for fr in frames for t in fr.track_ids],
        np.concatenate([fr.num_interior_pts for fr in frames]),
    )
    if sweeps:
        for fr in frames:
            write_sweep(folder / av2.SWEEP_DIR / f"{fr.timestamp}.feather", fr.points, fr.laser_number, fr.offset_ns)
    pose_ts, poses = [], []
    for a, b in zip(frames, frames[1:] + frames[-1:]):
        for q in range(4 if b is not a else 1):
            pose_ts.append(a.timestamp + q * (b.timestamp - a.timestamp) // 4)
            poses.append(_interpolate_planar(a.pose, b.pose, q / 4.0))
    write_poses(folder / av2.POSES, pose_ts, poses)
    write_calibration(folder / av2.CALIBRATION, {n: np.asarray(p) for n, p in log.mounts.items()})
    return folder


def _interpolate_planar(a: FloatArray, b: FloatArray, s: float) -> FloatArray:
    """The planar pose a fraction ``s`` of the way from ``a`` to ``b`` (yaw and translation linear)."""
    ya, yb = np.arctan2(a[1, 0], a[0, 0]), np.arctan2(b[1, 0], b[0, 0])
    yaw = ya + s * np.arctan2(np.sin(yb - ya), np.cos(yb - ya))
    out = planar_pose(*(a[:2, 3] + s * (b[:2, 3] - a[:2, 3])), yaw)
    out[2, 3] = a[2, 3] + s * (b[2, 3] - a[2, 3])
    return out


def av2_manifest_rows(log: SimAv2Log) -> dict[str, list]:
    """Manifest rows of a log (the columns of :func:`~labelaudit.sim.waymo_writer.write_manifest`)."""
    rows: dict[str, list] = {k: [] for k in SEQUENCE_MANIFEST_COLUMNS}
    for fr in log.frames:
        for k in range(len(fr.boxes)):
            rows["frame_id"].append(f"{log.log_id}:{fr.timestamp}")
            rows["object_id"].append(fr.track_ids[k])
            rows["class_name"].append(fr.categories[k])
            rows["sim_class"].append(fr.sim_classes[k])
            rows["true_box"].append([float(v) for v in fr.true_boxes[k]])
            rows["written_box"].append([float(v) for v in fr.boxes[k]])
            rows["perturbation"].append(fr.perturbation[k])
            rows["track_error_kind"].append(fr.track_error_kind[k] if fr.track_error_kind else "none")
            rows["track_error_size"].append(float(fr.track_error_size[k]) if fr.track_error_size else 0.0)
    return rows


def simulate_av2_detections(
    logs: Sequence[SimAv2Log], path: str | Path, spec: DetectorSpec | None = None, seed: int = 0
) -> DetectorSummary:
    """The synthetic detector (:func:`~labelaudit.sim.detector.detect_frame`) run on simulated logs,
    written as one AV2 detections ``.feather`` file (what ``labelaudit eval`` reads).

    The detector sees each frame's true boxes (before label noise) and the points on them; its
    classes become AV2 categories (Car → ``REGULAR_VEHICLE``, Pedestrian → ``PEDESTRIAN``, Cyclist
    → ``BICYCLIST``; like the KITTI detector it has no truck class and reports a van as a car or
    misses it). Its background false positives stand on the ground (z = 0 in the egovehicle frame)
    in the sector ahead. Frame ``f`` of log ``i`` draws from ``SeedSequence(seed, (i, f, 1000))``.
    """
    from labelaudit.datasets.detections import write_av2_detections
    from labelaudit.sim.detector import detect_frame

    spec = spec or DetectorSpec()
    fids: list[str] = []
    boxes: list[FloatArray] = []
    cats: list[str] = []
    scores: list[float] = []
    n_obj = n_fp = 0
    frames = 0
    for i, log in enumerate(logs):
        for f, fr in enumerate(log.frames):
            rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(i, f, 1000)))
            b, classes, s, _, kinds = detect_frame(
                rng, fr.true_boxes, fr.sim_classes, fr.num_interior_pts, spec, sensor_height=0.0
            )
            fids += [f"{log.log_id}:{fr.timestamp}"] * len(b)
            boxes.append(b)
            cats += [AV2_CATEGORY.get(c, c.upper()) for c in classes]
            scores += s.tolist()
            n_obj += kinds.count("object")
            n_fp += len(kinds) - kinds.count("object")
            frames += 1
    out = write_av2_detections(path, fids, np.concatenate(boxes) if boxes else np.zeros((0, 7)), cats, scores)
    return DetectorSummary(out.parent, None, frames, len(scores), n_obj, n_fp)


def simulate_av2_dataset(
    out_dir: str | Path,
    logs: int = 2,
    frames: int = 3,
    seed: int = 0,
    size: str = "small",
    label_noise: NoiseSpec | None = None,
    split: str = "val",
) -> Path:
    """Simulate ``logs`` AV2 logs into ``out_dir/<split>/<log_id>/`` and ``out_dir/manifest.parquet``
    (true vs written box per object and frame); returns the split folder."""
    out = Path(out_dir)
    logs_ = [simulate_av2_log(seed=seed + i, frames=frames, size=size, label_noise=label_noise) for i in range(logs)]
    for log in logs_:
        write_av2_log(log, out / split)
    rows: dict[str, list] = {k: [] for k in SEQUENCE_MANIFEST_COLUMNS}
    for log in logs_:
        for k, v in av2_manifest_rows(log).items():
            rows[k].extend(v)
    write_manifest_table(pa.table(rows), out / MANIFEST_NAME)
    return out / split


__all__ = [
    "SimAv2Frame",
    "SimAv2Log",
    "av2_lidar_spec",
    "av2_manifest_rows",
    "simulate_av2_dataset",
    "simulate_av2_detections",
    "simulate_av2_log",
    "write_annotations",
    "write_av2_log",
    "write_calibration",
    "write_poses",
    "write_sweep",
]

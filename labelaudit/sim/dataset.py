"""Synthetic LiDAR datasets with known label noise (``labelaudit simulate OUT``).
It writes files through :mod:`labelaudit.sim.kitti_writer` and runs frames on :mod:`labelaudit.executors`; it never audits.

One frame = a random scene (:mod:`labelaudit.sim.scene`), one sweep of a spinning LiDAR ray-cast
into it (:mod:`labelaudit.sim.raycast`, a range image first, points from it), label noise
(:mod:`labelaudit.sim.noise`), written in the KITTI layout (:mod:`labelaudit.sim.kitti_writer`).
A ``manifest.parquet`` records, for every object, its true box, the box written to the label file
and the perturbation applied — the ground truth for label-error benchmarks.

Determinism: frame *i* draws everything from ``SeedSequence(seed, spawn_key=(i, stream))`` with one
stream each for the scene, the sensor noise, the calibration and the label noise. So a frame is
the same whatever the number of frames or workers, and changing only the noise leaves the scenes
and the point clouds byte-identical (a clean and a noisy dataset from one seed share their points).
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from numpy.typing import NDArray
from tqdm import tqdm

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle
from labelaudit.core.params import BOX_FIELDS
from labelaudit.datasets.kitti import Calibration
from labelaudit.errors import OutputExistsError, UsageError
from labelaudit.executors import make_executor
from labelaudit.sim.kitti_writer import KittiLabelInfo, kitti_labels, make_calibration, write_kitti_frame
from labelaudit.sim.manifest import MANIFEST_NAME, write_manifest_table
from labelaudit.sim.noise import PERTURBATION_KINDS, NoiseSpec, perturb_boxes
from labelaudit.sim.raycast import LidarSpec, RangeImage, SeeThrough, render_range_image
from labelaudit.sim.scene import VEHICLE_CLASSES, Scene, SceneSpec, sample_scene

__all__ = [
    "LidarSpec",
    "NoiseSpec",
    "SceneSpec",
    "SeeThrough",
    "SimFrame",
    "SimulationSummary",
    "frame_generators",
    "render_range_image",
    "SEQUENCE_FORMATS",
    "prepare_output",
    "simulate_dataset",
    "simulate_frame",
    "simulate_sequences",
    "write_manifest",
]

MANIFEST_VERSION = "1"
_STREAMS = ("scene", "lidar", "calib", "noise", "drop", "see")
_SPLIT_KEY = 0xFFFFFFFF  # spawn key of the train/val split generator (no frame index reaches it)


def frame_generators(seed: int, index: int) -> dict[str, np.random.Generator]:
    """Independent generators of frame ``index``: "scene", "lidar", "calib", "noise", "drop" and
    "see" (the see-through draws).

    A Waymo writer that re-renders the same scene draws it from ``frame_generators(...)["scene"]``.
    """
    if seed < 0 or index < 0:
        raise ValueError(f"seed and frame index must be >= 0, got seed={seed}, index={index}")
    return {
        name: np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index, k)))
        for k, name in enumerate(_STREAMS)
    }


@dataclass
class SimFrame:
    """Everything about one simulated frame (KITTI rendering).

    Attributes
    ----------
    frame_id : "000123"
    scene : the true scene
    range_image : the sweep, with per-object ray counts
    points : (N, 4) float32 LiDAR-frame x, y, z, intensity (what velodyne/<id>.bin holds)
    point_hits : (N,) what each point hit: object index, −1 ground
    calib : the frame's calibration
    written_boxes : (K, 7) perturbed boxes before they are rounded into the label file
    perturbation : K perturbation kinds
    labels : label lines and what the reader reads back
    """

    frame_id: str
    scene: Scene
    range_image: RangeImage
    points: NDArray[np.float32]
    point_hits: NDArray[np.int32]
    calib: Calibration
    written_boxes: NDArray[np.float64]
    perturbation: list[str]
    labels: KittiLabelInfo

    def manifest_rows(self) -> dict[str, list[Any]]:
        """Manifest columns of this frame's objects (see :func:`manifest_schema`)."""
        true = self.scene.boxes
        k = len(true)
        ri, lab = self.range_image, self.labels
        delta = self.written_boxes - true
        delta[:, 6] = normalize_angle(delta[:, 6]) if k else delta[:, 6]
        labelled = lab.object_index >= 0
        rows: dict[str, list[Any]] = {
            "frame_id": [self.frame_id] * k,
            "object_index": [int(i) if i >= 0 else None for i in lab.object_index],
            "object_id": [f"{self.frame_id}:{i}" if i >= 0 else None for i in lab.object_index],
            "scene_index": list(range(k)),
            "class_name": self.scene.class_names,
            "labelled": labelled.tolist(),
            "dropped": (np.zeros(k, dtype=bool) if lab.dropped is None else lab.dropped).tolist(),
        }
        for j, name in enumerate(BOX_FIELDS):
            rows[f"true_{name}"] = true[:, j].tolist()
        for j, name in enumerate(BOX_FIELDS):
            rows[f"written_{name}"] = [float(v) if ok else None for v, ok in zip(lab.written_box[:, j], labelled)]
        rows["perturbation"] = list(self.perturbation)
        for j, name in enumerate(BOX_FIELDS):
            rows[f"delta_{name}"] = delta[:, j].tolist()
        rows["center_offset_m"] = np.hypot(delta[:, 0], delta[:, 1]).tolist()
        rows["num_points"] = ri.return_counts.tolist()
        rows["num_rays"] = ri.ray_counts.tolist()
        rows["visible_rays"] = ri.visible_counts.tolist()
        rows["occlusion_fraction"] = [None if not np.isfinite(v) else float(v) for v in ri.occlusion_fraction]
        rows["occluded"] = lab.occluded.tolist()
        rows["truncated"] = lab.truncated.tolist()
        rows["in_camera_fov"] = lab.in_camera_fov.tolist()
        rows["distance"] = np.hypot(true[:, 0], true[:, 1]).tolist()
        zeros = np.zeros(k)
        rows["glass_rays"] = (zeros if ri.glass_counts is None else ri.glass_counts).astype(np.int64).tolist()
        rows["under_rays"] = (zeros if ri.under_counts is None else ri.under_counts).astype(np.int64).tolist()
        rows["clearance"] = (zeros if ri.clearance is None else ri.clearance).tolist()
        return rows


def manifest_schema() -> pa.Schema:
    """Columns of ``manifest.parquet``, one row per scene object (labelled or not).

    ``object_index`` is the row among the label file's non-DontCare rows (null when the object was
    not labelled, e.g. outside the camera view), so the reader's object id is
    ``"<frame_id>:<object_index>"`` (column ``object_id``). ``true_*`` is the exact box of the
    object, ``written_*`` the label box as the KITTI reader reads it back (perturbation and the
    label file's rounding included), ``delta_*`` the perturbation applied (before rounding; yaw
    wrapped), ``perturbation`` one of "none", "jitter", "shift", "swap_lw", "yaw90". ``dropped``:
    a vehicle that would have been labelled but whose label was left out (``--drop-fraction``: a
    missing label; ``labelled`` is false for it).
    ``num_points`` counts the LiDAR returns on the true object; ``num_rays`` the rays that would hit
    it without occluders, ``visible_rays`` those it actually stops (before noise and dropout).
    ``glass_rays`` and ``under_rays`` count the rays that reached the object's windows or the gap
    under its body and passed through (``--see-through`` / ``--under-chassis``; else 0), and
    ``clearance`` is its ground clearance (m; 0 unless ``--under-chassis``).
    """
    fields = [
        pa.field("frame_id", pa.string()),
        pa.field("object_index", pa.int64()),
        pa.field("object_id", pa.string()),
        pa.field("scene_index", pa.int64()),
        pa.field("class_name", pa.string()),
        pa.field("labelled", pa.bool_()),
        pa.field("dropped", pa.bool_()),
    ]
    fields += [pa.field(f"{p}_{n}", pa.float64()) for p in ("true", "written") for n in BOX_FIELDS]
    fields += [pa.field("perturbation", pa.string())]
    fields += [pa.field(f"delta_{n}", pa.float64()) for n in BOX_FIELDS]
    fields += [
        pa.field("center_offset_m", pa.float64()),
        pa.field("num_points", pa.int64()),
        pa.field("num_rays", pa.int64()),
        pa.field("visible_rays", pa.int64()),
        pa.field("occlusion_fraction", pa.float64()),
        pa.field("occluded", pa.int64()),
        pa.field("truncated", pa.float64()),
        pa.field("in_camera_fov", pa.bool_()),
        pa.field("distance", pa.float64()),
        pa.field("glass_rays", pa.int64()),
        pa.field("under_rays", pa.int64()),
        pa.field("clearance", pa.float64()),
    ]
    return pa.schema(fields)


def simulate_frame(
    index: int,
    *,
    seed: int = 0,
    noise: NoiseSpec = NoiseSpec(),
    lidar: LidarSpec = LidarSpec(),
    scene_spec: SceneSpec = SceneSpec(),
    label_fov: str = "camera",
    label_precision: int | None = 2,
    scene: Scene | None = None,
    drop_fraction: float = 0.0,
    see_through: SeeThrough | None = None,
) -> SimFrame:
    """Simulate frame ``index`` of the dataset with ``seed`` (pure: writes nothing).

    Parameters
    ----------
    index : frame number (the frame id is ``f"{index:06d}"``)
    seed : dataset seed
    noise, lidar, scene_spec : label noise, sensor and scene distributions
    label_fov : "camera" (KITTI: label only objects in the camera view) or "all" (360°)
    label_precision : decimals of the label file (2 like KITTI, ``None`` exact)
    scene : render this scene instead of drawing one (its frame must be the KITTI LiDAR frame:
        sensor at the origin, ground at ``-lidar.sensor_height``) — e.g. to write the KITTI
        rendering of a scene also rendered for Waymo
    drop_fraction : share of the vehicle labels left out of the label file (their objects and points
        stay; the manifest's ``dropped``): missing labels, drawn per object from the frame's "drop"
        stream, so the scene, points and other labels are the same as without dropping
    see_through : vehicles' windows and the gap under them let rays through (:class:`SeeThrough`,
        drawn from the frame's "see" stream); None: opaque vehicles
    """
    gens = frame_generators(seed, index)
    if scene is None:
        scene = sample_scene(gens["scene"], scene_spec, ground_z=-lidar.sensor_height)
    ri = render_range_image(scene, lidar, None, gens["lidar"], see_through, gens["see"])
    points, hits = ri.points("scene")
    calib = make_calibration(gens["calib"])
    written, kinds = perturb_boxes(scene.boxes, scene.class_names, noise, gens["noise"])
    u = gens["drop"].random(
        len(scene.objects)
    )  # one draw per object whatever the fraction: a larger fraction drops a superset
    drop = (u < drop_fraction) & np.array([c in VEHICLE_CLASSES for c in scene.class_names], dtype=bool)
    labels = kitti_labels(
        scene.boxes,
        written,
        scene.class_names,
        ri.occlusion_fraction,
        calib,
        label_fov=label_fov,
        precision=label_precision,
        drop=drop,
    )
    return SimFrame(f"{index:06d}", scene, ri, points, hits, calib, written, kinds, labels)


def write_manifest(
    out_dir: str | Path, rows: list[dict[str, list[Any]]], metadata: dict[str, str] | None = None
) -> Path:
    """Write ``manifest.parquet`` (atomically) from per-frame :meth:`SimFrame.manifest_rows`."""
    schema = manifest_schema()
    columns: dict[str, list[Any]] = {name: [] for name in schema.names}
    for frame_rows in rows:
        for name in columns:
            columns[name].extend(frame_rows[name])
    table = pa.table(columns, schema=schema).replace_schema_metadata(metadata or {})
    return write_manifest_table(table, Path(out_dir) / MANIFEST_NAME)


@dataclass
class SimulationSummary:
    """What :func:`simulate_dataset` (KITTI) or :func:`simulate_sequences` (Waymo, AV2) wrote.

    Attributes
    ----------
    out_dir : dataset root (holds ``training/``, ``ImageSets/``, ``manifest.parquet``; sequences:
        the format's folder and ``manifest.parquet``)
    manifest : path of the manifest
    frames : frames written (all sequences)
    seed : the dataset seed
    num_points : LiDAR points written, all frames
    num_objects : objects in all scenes
    num_labels : label rows written
    perturbations : label rows per perturbation kind
    seconds : wall time
    """

    out_dir: Path
    manifest: Path
    frames: int
    seed: int
    num_points: int
    num_objects: int
    num_labels: int
    perturbations: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    detections: Any = None  # simulate_sequences(detections=…): the DetectorSummary of OUT/detections.feather

    @property
    def points_per_frame(self) -> float:
        return self.num_points / self.frames if self.frames else 0.0

    @property
    def frames_per_second(self) -> float:
        return self.frames / self.seconds if self.seconds > 0 else float("nan")

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["out_dir"], d["manifest"] = str(self.out_dir), str(self.manifest)
        d["points_per_frame"] = self.points_per_frame
        d["frames_per_second"] = self.frames_per_second
        return d


def _write_one(job: tuple[int, dict[str, Any]]) -> tuple[int, dict[str, list[Any]], int]:
    """Worker: simulate and write one frame; returns its manifest rows and point count."""
    index, opts = job
    out_dir = opts.pop("out_dir")
    frame = simulate_frame(index, **opts)
    write_kitti_frame(out_dir, frame.frame_id, frame.points, frame.labels.lines, frame.calib)
    return index, frame.manifest_rows(), len(frame.points)


_OWNED = ("training", "ImageSets", MANIFEST_NAME)


def prepare_output(out_dir: str | Path, owned: Sequence[str], overwrite: bool) -> Path:
    """Create the output folder of a simulation; with ``overwrite``, first remove what a previous
    simulation wrote there (the ``owned`` names only, nothing else in the folder).

    Raises
    ------
    UsageError
        The path is a file or cannot be created.
    OutputExistsError
        One of ``owned`` exists and ``overwrite`` is false.
    """
    out = Path(out_dir)
    try:
        if out.exists() and not out.is_dir():
            raise UsageError(f"{out}: exists and is not a folder; choose another output folder")
        existing = [out / name for name in owned if os.path.lexists(out / name)]
    except OSError as exc:  # e.g. a name too long for the file system
        raise UsageError(f"{out}: cannot use this output folder ({exc.strerror or exc})") from None
    if existing:
        if not overwrite:
            raise OutputExistsError(
                f"{out}: already holds {', '.join(p.name for p in existing)}; choose a new folder or overwrite it (--overwrite)"
            )
        for p in existing:
            shutil.rmtree(p) if p.is_dir() else p.unlink()
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # a dangling link, a path under a file …
        raise UsageError(
            f"{out}: cannot create the output folder ({exc.strerror or exc}); choose another one"
        ) from None
    return out


AV2_DETECTIONS = "detections.feather"  # the synthetic detector's output for simulated AV2 logs

SEQUENCE_FORMATS: dict[str, str] = {"waymo-v2": "waymo_v2", "waymo-v1": "waymo_v1", "av2": "val"}
"""Simulated sequence formats and the folder each writes under OUT (AV2: the ``val`` split)."""


def simulate_sequences(
    out_dir: str | Path,
    dataset_format: str,
    *,
    sequences: int = 2,
    frames: int = 10,
    seed: int = 0,
    noise: NoiseSpec = NoiseSpec(),
    size: str = "real",
    progress: bool = True,
    overwrite: bool = False,
    detections: Any = None,
    track_noise: Any = None,
    moving_fraction: float = 0.0,
) -> SimulationSummary:
    """Simulate Waymo segments or Argoverse 2 logs: sequences with track ids and a moving ego vehicle.

    Sequence ``i`` is drawn from seed ``seed + i`` (:func:`~labelaudit.sim.waymo_writer.simulate_waymo_segment`,
    :func:`~labelaudit.sim.av2_writer.simulate_av2_log`): a static scene seen from an ego vehicle
    driving through it, every object one track id for the whole sequence, ``noise`` injected per
    frame into the written vehicle boxes. Writes ``OUT/waymo_v2/<component>/<segment>.parquet``,
    ``OUT/waymo_v1/<segment>.tfrecord`` or ``OUT/val/<log_id>/…`` and ``OUT/manifest.parquet``
    (frame_id, object_id, class_name, sim_class, true_box, written_box, perturbation per object
    and frame).

    Parameters
    ----------
    dataset_format : "waymo-v2", "waymo-v1" or "av2"
    sequences : segments / logs
    frames : frames per sequence (10 Hz)
    size : "real" (the sensors' resolution) or "small" (fewer rays, for tests)
    detections : a :class:`~labelaudit.sim.detector.DetectorSpec` — AV2 only: also write the
        synthetic detector's output, ``OUT/detections.feather`` (AV2's detections layout; its
        :class:`~labelaudit.sim.detector.DetectorSummary` is ``summary.detections``)
    track_noise : a :class:`~labelaudit.sim.tracknoise.TrackNoiseSpec`: per-frame label noise inside
        tracks (ordinary scatter and injected annotator errors; the manifest's ``track_error_kind``
        and ``track_error_size``), or None
    moving_fraction : share of the vehicles that drive (0: a static scene)

    Raises
    ------
    UsageError
        Bad format, counts or size, or an output folder that cannot be used.
    OutputExistsError
        OUT already holds this format's folder or a manifest and ``overwrite`` is false.
    """
    from labelaudit.sim import av2_writer, waymo_writer

    if dataset_format not in SEQUENCE_FORMATS:
        raise UsageError(f"dataset format must be one of {', '.join(SEQUENCE_FORMATS)}, got {dataset_format!r}")
    if sequences < 1 or frames < 1:
        raise UsageError(f"sequences and frames must be >= 1, got {sequences} and {frames}")
    if seed < 0:
        raise UsageError(f"seed must be >= 0, got {seed}")
    if size not in ("real", "small"):
        raise UsageError(f"size must be 'real' or 'small', got {size!r}")
    if detections is not None and dataset_format != "av2":
        raise UsageError(
            f"the synthetic detector of sequences writes Argoverse 2 detections; not available for {dataset_format}"
        )
    folder = SEQUENCE_FORMATS[dataset_format]
    out = prepare_output(out_dir, (folder, MANIFEST_NAME, AV2_DETECTIONS), overwrite)
    start = time.perf_counter()
    num_points = 0
    segments: list[Any] = []
    logs: list[Any] = []
    manifest_rows: dict[str, list[Any]] = {}
    for i in tqdm(range(sequences), desc="simulate", unit="sequence", file=sys.stderr, disable=not progress):
        if dataset_format == "av2":
            log = av2_writer.simulate_av2_log(
                seed=seed + i,
                frames=frames,
                size=size,
                label_noise=noise,
                track_noise=track_noise,
                moving_fraction=moving_fraction,
            )
            av2_writer.write_av2_log(log, out / folder)
            num_points += sum(len(fr.points) for fr in log.frames)
            for k, v in av2_writer.av2_manifest_rows(log).items():
                manifest_rows.setdefault(k, []).extend(v)
            if detections is not None:
                log.frames = [
                    replace(fr, points=fr.points[:0]) for fr in log.frames
                ]  # the detector needs boxes and counts only
                logs.append(log)
            continue
        seg = waymo_writer.simulate_waymo_segment(
            seed=seed + i,
            frames=frames,
            size=size,
            label_noise=noise,
            track_noise=track_noise,
            moving_fraction=moving_fraction,
        )
        if dataset_format == "waymo-v2":
            waymo_writer.write_waymo_v2(seg, out / folder)
        else:
            waymo_writer.write_waymo_v1(seg, out / folder / f"{seg.name}.tfrecord")
        num_points += sum(len(fr.points) for fr in seg.frames)
        segments.append(seg)
    manifest = out / MANIFEST_NAME
    if dataset_format == "av2":
        write_manifest_table(pa.table(manifest_rows), manifest)
    else:
        waymo_writer.write_manifest(segments, manifest)
    kinds = np.asarray(
        pq.read_table(manifest, columns=["perturbation"]).column("perturbation").to_pylist(), dtype=object
    )
    det = (
        av2_writer.simulate_av2_detections(logs, out / AV2_DETECTIONS, detections, seed)
        if detections is not None
        else None
    )
    return SimulationSummary(
        out_dir=out,
        manifest=manifest,
        frames=sequences * frames,
        seed=seed,
        num_points=num_points,
        num_objects=len(kinds),
        num_labels=len(kinds),
        perturbations={k: int(np.count_nonzero(kinds == k)) for k in PERTURBATION_KINDS},
        seconds=time.perf_counter() - start,
        detections=det,
    )


def simulate_dataset(
    out_dir: str | Path,
    *,
    frames: int = 10,
    seed: int = 0,
    noise: NoiseSpec = NoiseSpec(),
    lidar: LidarSpec = LidarSpec(),
    workers: int = 1,
    progress: bool = True,
    scene: SceneSpec = SceneSpec(),
    label_fov: str = "camera",
    label_precision: int | None = 2,
    overwrite: bool = False,
    drop_fraction: float = 0.0,
    see_through: SeeThrough | None = None,
) -> SimulationSummary:
    """Simulate a KITTI-format dataset with known label noise.

    Writes ``training/velodyne/*.bin``, ``training/label_2/*.txt``, ``training/calib/*.txt``,
    ``ImageSets/{train,val}.txt`` and ``manifest.parquet`` (see :func:`manifest_schema`) under
    ``out_dir``. The same arguments give byte-identical files, on any number of workers.

    Parameters
    ----------
    out_dir : dataset root to create
    frames : number of frames (ids 000000 …)
    seed : dataset seed (>= 0)
    noise : label noise to inject (default none; :meth:`NoiseSpec.benchmark` for the label-error benchmark)
    lidar : the sensor (default: KITTI's HDL-64E, ~120k points per frame)
    workers : processes; frames are independent, so any count gives the same files
    progress : tqdm progress bar on stderr
    scene : scene distribution (object counts, distances, layout)
    label_fov : "camera" (KITTI: only objects in the camera view) or "all" (360°)
    label_precision : decimals in label files (2 like KITTI; ``None`` writes exact floats)
    overwrite : replace an existing simulated dataset in ``out_dir`` (only the simulator's own
        ``training/``, ``ImageSets/`` and manifest are removed)
    drop_fraction : share of vehicle labels left out (missing labels; manifest column ``dropped``)
    see_through : share of the rays that pass vehicles' windows and under their chassis
        (:class:`SeeThrough`; manifest columns ``glass_rays``, ``under_rays``, ``clearance``); None:
        opaque vehicles

    Raises
    ------
    ValueError
        (a :class:`~labelaudit.errors.UsageError`) Bad ``frames``, ``seed``, ``workers`` or
        ``label_fov``, or an output folder that cannot be created.
    OutputExistsError
        (a FileExistsError) ``out_dir`` already holds a dataset and ``overwrite`` is false.
    """
    if frames < 1:
        raise UsageError(f"frames must be >= 1, got {frames}")
    if seed < 0:
        raise UsageError(f"seed must be >= 0, got {seed}")
    if workers < 1:
        raise UsageError(f"workers must be >= 1, got {workers}")
    if not (0.0 <= drop_fraction <= 1.0):
        raise UsageError(f"drop_fraction must be in [0, 1], got {drop_fraction}")
    if label_fov not in ("camera", "all"):
        raise UsageError(f"label_fov must be 'camera' or 'all', got {label_fov!r}")
    if label_precision is not None and not (isinstance(label_precision, int) and 0 <= label_precision <= 17):
        raise UsageError(f"label_precision must be None or an integer 0..17, got {label_precision!r}")
    out = prepare_output(out_dir, _OWNED, overwrite)
    start = time.perf_counter()
    opts = {
        "out_dir": out,
        "seed": seed,
        "noise": noise,
        "lidar": lidar,
        "scene_spec": scene,
        "label_fov": label_fov,
        "label_precision": label_precision,
        "drop_fraction": drop_fraction,
        "see_through": see_through,
    }
    jobs = [(i, dict(opts)) for i in range(frames)]
    results: list[tuple[int, dict[str, list[Any]], int]] = []
    bar = tqdm(total=frames, desc="simulate", unit="frame", file=sys.stderr, disable=not progress)
    executor = make_executor(min(workers, frames))  # frames are independent: same files for any count
    try:
        for res in executor.run(jobs, _write_one):
            results.append(res)
            bar.update(1)
    finally:
        executor.close()
        bar.close()
    results.sort(key=lambda r: r[0])

    meta = {
        "labelaudit.simulator_version": MANIFEST_VERSION,
        "labelaudit.seed": str(seed),
        "labelaudit.frames": str(frames),
        "labelaudit.noise": json.dumps(asdict(noise)),
        "labelaudit.lidar": json.dumps(asdict(lidar)),
        "labelaudit.scene": json.dumps(asdict(scene)),
        "labelaudit.label_fov": label_fov,
        "labelaudit.drop_fraction": repr(float(drop_fraction)),
        "labelaudit.see_through": json.dumps(asdict(see_through or SeeThrough())),
    }
    manifest = write_manifest(out, [rows for _, rows, _ in results], meta)
    _write_imagesets(out, frames, seed)

    labelled = np.concatenate([np.asarray(rows["labelled"], dtype=bool) for _, rows, _ in results])
    kinds = np.concatenate([np.asarray(rows["perturbation"], dtype=object) for _, rows, _ in results])[labelled]
    return SimulationSummary(
        out_dir=out,
        manifest=manifest,
        frames=frames,
        seed=seed,
        num_points=int(sum(r[2] for r in results)),
        num_objects=len(labelled),
        num_labels=int(labelled.sum()),
        perturbations={k: int(np.count_nonzero(kinds == k)) for k in PERTURBATION_KINDS},
        seconds=time.perf_counter() - start,
    )


def _write_imagesets(out: Path, frames: int, seed: int) -> None:
    rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(_SPLIT_KEY,)))
    order = rng.permutation(frames)
    n_val = int(round(frames * C.SIM_VAL_FRACTION)) if frames > 1 else 0
    val, train = np.sort(order[:n_val]), np.sort(order[n_val:])
    sets = out / "ImageSets"
    sets.mkdir(parents=True, exist_ok=True)
    for name, ids in (("train", train), ("val", val)):
        (sets / f"{name}.txt").write_text("".join(f"{i:06d}\n" for i in ids))

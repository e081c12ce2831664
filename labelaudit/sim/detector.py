"""A synthetic 3D detector for simulated datasets: what ``labelaudit simulate --detections`` writes.

It "sees" the simulator's *true* boxes (``manifest.parquet``), so its errors against the labels
mix its own localisation noise with the injected label noise — as a real detector's do:

* each labelled object is detected unless missed (base rate, much higher with few points);
  a Van is reported as a Car with some probability (the devkit's neighbour-class rule then
  applies), Trucks are not detected (KITTI detectors have no such class);
* a detection is the true box plus Gaussian noise on centre, size and yaw whose std grows
  linearly with distance (doubling at ``range_scale``);
* the score is higher for better boxes (a logistic function of the normalised error, plus noise);
  some detections get a shifted, lower-scoring duplicate;
* background false positives (Poisson per frame, mostly low scores) appear in the camera's view;
* optionally (``probabilistic``) every detection reports the std it was drawn with — a calibrated
  probabilistic detector — written to ``detections.parquet`` (std_* columns).

Output: ``<dataset>/detections/<frame>.txt`` in KITTI result format (16 columns, camera frame,
converted with the frame's calibration; an empty file when there is nothing), one per frame, and
with ``probabilistic`` also ``<dataset>/detections.parquet`` (labelaudit's detections schema,
LiDAR frame). Frame i draws from its own seed stream, so outputs do not depend on the frame
count. This module only writes detections; it never reads point clouds.
"""

from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core.geometry import normalize_angle
from labelaudit.datasets.kitti import (
    Calibration,
    alpha_from_location,
    boxes_lidar_to_camera,
    format_label_line,
    read_calib,
)

FloatArray = NDArray[np.float64]

__all__ = ["DetectorSpec", "DetectorSummary", "detect_frame", "simulate_detections"]

DETECTIONS_DIR = "detections"
DETECTIONS_PARQUET = "detections.parquet"
_STREAM = 1000  # spawn key of the detector's per-frame generator (the dataset's streams use 0..3)
_FP_CLASSES = ("Car", "Pedestrian", "Cyclist")
_FP_CLASS_P = (0.8, 0.1, 0.1)


@dataclass(frozen=True)
class DetectorSpec:
    """The synthetic detector's error model (defaults in :mod:`labelaudit.constants`, ``SIM_DET_*``).

    Attributes
    ----------
    center_std, size_std, yaw_std : error std near the sensor (m, m, rad); they grow linearly with
        distance, doubling at ``range_scale`` (m)
    miss_rate : probability to miss an object with at least ``few_points`` LiDAR returns
    miss_rate_few : probability to miss one with fewer
    false_positives : mean number of background false positives per frame
    duplicate_rate : share of detections with an extra shifted, lower-scoring duplicate
    van_as_car : probability that a Van is reported as a Car (else it is not detected)
    probabilistic : report each detection's std (writes ``detections.parquet``)
    """

    center_std: float = C.SIM_DET_CENTER_STD
    size_std: float = C.SIM_DET_SIZE_STD
    yaw_std: float = C.SIM_DET_YAW_STD
    range_scale: float = C.SIM_DET_RANGE_SCALE
    miss_rate: float = C.SIM_DET_MISS[0]
    miss_rate_few: float = C.SIM_DET_MISS[1]
    few_points: int = C.SIM_DET_FEW_POINTS
    false_positives: float = C.SIM_DET_FALSE_POSITIVES
    duplicate_rate: float = C.SIM_DET_DUPLICATES
    van_as_car: float = C.SIM_DET_VAN_AS_CAR
    probabilistic: bool = False

    def __post_init__(self) -> None:
        for name in ("center_std", "size_std", "yaw_std", "false_positives"):
            if getattr(self, name) < 0:
                raise ValueError(f"DetectorSpec.{name} must be >= 0, got {getattr(self, name)}")
        if self.range_scale <= 0:
            raise ValueError(f"DetectorSpec.range_scale must be > 0, got {self.range_scale}")
        for name in ("miss_rate", "miss_rate_few", "duplicate_rate", "van_as_car"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"DetectorSpec.{name} must be in [0, 1], got {getattr(self, name)}")


@dataclass
class DetectorSummary:
    """What :func:`simulate_detections` wrote."""

    folder: Path
    parquet: Path | None
    frames: int
    detections: int
    objects_detected: int  # detections drawn from a labelled object
    false_positives_drawn: int  # duplicates and background detections


def _stds(spec: DetectorSpec, distance: FloatArray) -> FloatArray:
    """(K, 7) error std of (cx, cy, cz, l, w, h, yaw) at each distance."""
    grow = 1.0 + np.asarray(distance, dtype=float) / spec.range_scale
    base = np.array(
        [
            spec.center_std,
            spec.center_std,
            0.5 * spec.center_std,
            spec.size_std,
            spec.size_std,
            spec.size_std,
            spec.yaw_std,
        ]
    )
    return grow[:, None] * base[None, :]


def _score(rng: np.random.Generator, z: FloatArray) -> FloatArray:
    """Scores in (0, 1) falling with the normalised error z (≈ 1 for a typical detection)."""
    logit = 3.0 - 2.0 * z + rng.normal(0.0, 0.7, len(z))
    return 1.0 / (1.0 + np.exp(-logit))


def detect_frame(
    rng: np.random.Generator,
    true_boxes: FloatArray,
    classes: list[str],
    num_points: NDArray[np.integer],
    spec: DetectorSpec,
    sensor_height: float = C.SIM_SENSOR_HEIGHT,
) -> tuple[FloatArray, list[str], FloatArray, FloatArray, list[str]]:
    """Detections of one frame.

    Parameters
    ----------
    rng : the frame's generator
    true_boxes : (K, 7) true boxes of the labelled objects (LiDAR frame)
    classes : K class names
    num_points : (K,) LiDAR returns on each object

    Returns
    -------
    boxes : (D, 7), class names (D), scores (D,), stds (D, 7) of the error each was drawn with,
    kinds (D): "object" (a detected object), "duplicate" or "background" (a false positive)
    """
    from labelaudit.sim.scene import SIZE_STATS

    out_boxes, out_cls, out_score, out_std, kinds = [], [], [], [], []
    k = len(true_boxes)
    if k:
        dist = np.hypot(true_boxes[:, 0], true_boxes[:, 1])
        std = _stds(spec, dist)
        names = list(classes)
        for i, n in enumerate(names):
            if n == "Van":
                names[i] = "Car" if rng.random() < spec.van_as_car else ""
            elif n not in _FP_CLASSES:
                names[i] = ""
        miss = np.where(np.asarray(num_points) < spec.few_points, spec.miss_rate_few, spec.miss_rate)
        keep = (rng.random(k) >= miss) & np.array([bool(n) for n in names])
        noise = rng.normal(size=(k, 7)) * std
        boxes = true_boxes + noise
        boxes[:, 3:6] = np.maximum(boxes[:, 3:6], 0.2 * true_boxes[:, 3:6])
        boxes[:, 6] = normalize_angle(boxes[:, 6])
        z = np.sqrt(np.mean((noise / np.maximum(std, 1e-9)) ** 2, axis=1))
        scores = _score(rng, z)
        for i in np.flatnonzero(keep):
            out_boxes.append(boxes[i])
            out_cls.append(names[i])
            out_score.append(scores[i])
            out_std.append(std[i])
            kinds.append("object")
            if rng.random() < spec.duplicate_rate:
                dup = boxes[i].copy()
                shift = rng.normal(0.0, 0.5, 2) * np.array([true_boxes[i, 3], true_boxes[i, 4]]) * 0.5
                c, s = np.cos(dup[6]), np.sin(dup[6])
                dup[0] += c * shift[0] - s * shift[1]
                dup[1] += s * shift[0] + c * shift[1]
                out_boxes.append(dup)
                out_cls.append(names[i])
                out_score.append(scores[i] * rng.uniform(0.2, 0.6))
                out_std.append(std[i] * 3.0)
                kinds.append("duplicate")
    n_fp = rng.poisson(spec.false_positives)
    for _ in range(n_fp):
        cls = str(rng.choice(_FP_CLASSES, p=_FP_CLASS_P))
        mean, sd, _ = SIZE_STATS[cls]
        lwh = np.maximum(np.asarray(mean) + rng.normal(size=3) * np.asarray(sd), 0.3)
        r = rng.uniform(*C.SIM_DISTANCE)
        az = np.deg2rad(rng.uniform(-38.0, 38.0))
        box = np.array([r * np.cos(az), r * np.sin(az), -sensor_height + lwh[2] / 2, *lwh, rng.uniform(-np.pi, np.pi)])
        out_boxes.append(box)
        out_cls.append(cls)
        out_score.append(float(rng.beta(1.2, 6.0)))
        out_std.append(_stds(spec, np.array([r]))[0] * 3.0)
        kinds.append("background")
    return (
        np.asarray(out_boxes, dtype=float).reshape(-1, 7),
        out_cls,
        np.asarray(out_score, dtype=float),
        np.asarray(out_std, dtype=float).reshape(-1, 7),
        kinds,
    )


def _kitti_lines(boxes: FloatArray, classes: list[str], scores: FloatArray, calib: Calibration) -> list[str]:
    from labelaudit.sim.kitti_writer import image_boxes

    if not len(boxes):
        return []
    loc, dims, ry = boxes_lidar_to_camera(boxes, calib)
    alpha = np.atleast_1d(alpha_from_location(loc, ry))
    w, h = C.SIM_IMAGE_SIZE
    bbox = np.clip(image_boxes(boxes, calib), 0.0, [w - 1, h - 1, w - 1, h - 1])
    return [
        format_label_line(c, -1, -1, a, b, d, l, r, score=float(s), precision=None)
        for c, a, b, d, l, r, s in zip(classes, alpha, bbox, dims, loc, ry, scores)
    ]


def _write_text_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(text)
    os.replace(tmp, path)


def simulate_detections(
    dataset: str | Path, spec: DetectorSpec = DetectorSpec(), seed: int = 0, out: str | Path | None = None
) -> DetectorSummary:
    """Write the synthetic detector's output for a dataset made by ``labelaudit simulate``.

    Parameters
    ----------
    dataset : the simulated dataset root (holds ``manifest.parquet`` and ``training/calib``)
    spec : the detector's error model
    seed : detector seed (>= 0); the same seed gives the same files
    out : folder of the KITTI result files (default ``<dataset>/detections``)

    Raises
    ------
    FileNotFoundError
        No simulator manifest in ``dataset``.
    """
    from labelaudit.sim.manifest import read_manifest

    if seed < 0:
        raise ValueError(f"seed must be >= 0, got {seed}")
    root = Path(dataset)
    manifest = read_manifest(root)
    folder = Path(out) if out is not None else root / DETECTIONS_DIR
    folder.mkdir(parents=True, exist_ok=True)
    cols = manifest.to_pydict()
    frames: dict[str, list[int]] = {}
    for i, fid in enumerate(cols["frame_id"]):
        frames.setdefault(fid, []).append(i)
    true = (
        np.stack(
            [
                np.asarray(cols[f"true_{n}"], dtype=float)
                for n in ("cx", "cy", "cz", "length", "width", "height", "yaw")
            ],
            axis=1,
        )
        if cols["frame_id"]
        else np.zeros((0, 7))
    )
    labelled = np.asarray(cols["labelled"], dtype=bool) if cols["frame_id"] else np.zeros(0, bool)
    rows: dict[str, list[Any]] = {
        n: []
        for n in (
            "frame_id",
            "class_name",
            "cx",
            "cy",
            "cz",
            "length",
            "width",
            "height",
            "yaw",
            "score",
            "std_cx",
            "std_cy",
            "std_cz",
            "std_length",
            "std_width",
            "std_height",
            "std_yaw",
        )
    }
    total = tp = fp = 0
    for fid in sorted(frames):
        idx = np.asarray([i for i in frames[fid] if labelled[i]], dtype=np.int64)
        rng = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(int(fid), _STREAM)))
        boxes, classes, scores, stds, kinds = detect_frame(
            rng,
            true[idx],
            [cols["class_name"][i] for i in idx],
            np.asarray(cols["num_points"], dtype=np.int64)[idx],
            spec,
        )
        calib = read_calib(root / "training" / "calib" / f"{fid}.txt")
        lines = _kitti_lines(boxes, classes, scores, calib)
        _write_text_atomic(folder / f"{fid}.txt", "".join(line + "\n" for line in lines))
        total += len(boxes)
        tp += kinds.count("object")
        fp += len(kinds) - kinds.count("object")
        if spec.probabilistic:
            rows["frame_id"] += [fid] * len(boxes)
            rows["class_name"] += classes
            for k, n in enumerate(("cx", "cy", "cz", "length", "width", "height", "yaw")):
                rows[n] += boxes[:, k].tolist()
                rows[f"std_{n}"] += stds[:, k].tolist()
            rows["score"] += scores.tolist()
    parquet = None
    if spec.probabilistic:
        from labelaudit.datasets.detections import DETECTIONS_SCHEMA, write_parquet_detections

        schema = pa.schema([DETECTIONS_SCHEMA.field(n) for n in rows])
        table = pa.table(rows, schema=schema).replace_schema_metadata(
            {"labelaudit.detector": str(asdict(spec)), "labelaudit.seed": str(seed)}
        )
        parquet = write_parquet_detections(root / DETECTIONS_PARQUET, table)
    return DetectorSummary(folder, parquet, len(frames), total, tp, fp)

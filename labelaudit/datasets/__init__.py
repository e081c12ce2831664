"""Dataset readers (KITTI, Waymo v2 Parquet, Waymo v1 TFRecord, Argoverse 2 Feather) behind one entry point.
Readers turn files into :class:`Frame` s (LiDAR frame, one box type) and raise :class:`~labelaudit.errors.DatasetError` naming file and line; they never audit or write.
The labels without points (:mod:`.gt`) and detectors' outputs (:mod:`.detections`) are read here too, for ``eval`` and
the missing-label search alike."""

from __future__ import annotations

from pathlib import Path

from labelaudit.datasets.base import (
    DatasetReader,
    Frame,
    FrameFailure,
    FrameRef,
    ImageView,
    RegionOfInterest,
    in_labelled_region,
)
from labelaudit.errors import DatasetError

FORMATS = ("kitti", "waymo-v2", "waymo-v1", "av2")

__all__ = [
    "FORMATS",
    "DatasetError",
    "DatasetReader",
    "Frame",
    "FrameFailure",
    "FrameRef",
    "ImageView",
    "RegionOfInterest",
    "detect_format",
    "in_labelled_region",
    "open_dataset",
    "resolve_format",
]


def detect_format(root: str | Path) -> str:
    """Guess the format of a dataset folder (or a single .tfrecord file).

    Raises
    ------
    DatasetError
        When nothing in the folder looks like a supported dataset.
    """
    root = Path(root)
    if not root.exists():
        raise DatasetError(root, "dataset path does not exist")
    if root.is_file():
        if root.suffix == ".tfrecord" or ".tfrecord" in root.name:
            return "waymo-v1"
        raise DatasetError(root, "expected a dataset folder or a .tfrecord file")
    for base in (root, root / "training"):
        if (base / "velodyne").is_dir() or (base / "velodyne_reduced").is_dir():
            return "kitti"
    if (root / "lidar_box").is_dir() or any(root.glob("*/lidar_box")):
        return "waymo-v2"
    from labelaudit.datasets.av2 import find_logs

    if find_logs(root):
        return "av2"
    if next(root.rglob("*.tfrecord*"), None) is not None:
        return "waymo-v1"
    raise DatasetError(
        root,
        "cannot tell the format: expected KITTI (velodyne/ or training/velodyne/), "
        "Waymo v2 (lidar_box/ …), Argoverse 2 (<log_id>/annotations.feather or <log_id>/sensors/lidar/) "
        "or Waymo v1 (*.tfrecord); pass --dataset-format",
    )


def resolve_format(dataset: str | Path, fmt: str) -> str:
    """The format of ``dataset``: ``fmt`` itself after checking it and that the path exists, or the
    detected one for ``"auto"`` (:func:`detect_format`).

    Raises
    ------
    DatasetError
        Unknown format name, missing or unopenable path, undetectable format; the message names the path.
    """
    dataset = Path(dataset)
    if fmt != "auto" and fmt not in FORMATS:
        raise DatasetError(dataset, f"unknown dataset format {fmt!r}: expected auto or one of {', '.join(FORMATS)}")
    try:
        exists = dataset.exists()
    except OSError as exc:  # e.g. a name too long for the file system
        raise DatasetError(dataset, f"cannot open the dataset ({exc.strerror or exc})") from None
    if not exists:
        raise DatasetError(dataset, "dataset path does not exist")
    return detect_format(dataset) if fmt == "auto" else fmt


def open_dataset(root: str | Path, fmt: str = "auto", **options: object) -> DatasetReader:
    """Open a dataset folder with the reader of its format.

    Parameters
    ----------
    root : dataset folder (or a .tfrecord file for Waymo v1)
    fmt : "auto", "kitti", "waymo-v2", "waymo-v1" or "av2"
    options : reader options (KITTI: ``split``, ``classes``; Waymo v2 and Argoverse 2: ``split``, ``classes``)
    """
    if fmt == "auto":
        fmt = detect_format(root)
    if fmt == "kitti":
        from labelaudit.datasets.kitti import KittiReader

        return KittiReader(root, **options)  # type: ignore[arg-type]
    if fmt == "waymo-v2":
        from labelaudit.datasets.waymo_v2 import WaymoV2Reader

        return WaymoV2Reader(root, **options)  # type: ignore[arg-type]
    if fmt == "waymo-v1":
        from labelaudit.datasets.waymo_v1 import WaymoV1Reader

        return WaymoV1Reader(root, **options)  # type: ignore[arg-type]
    if fmt == "av2":
        from labelaudit.datasets.av2 import Av2Reader

        return Av2Reader(root, **options)  # type: ignore[arg-type]
    raise ValueError(f"unknown format {fmt!r}; expected auto or one of {', '.join(FORMATS)}")

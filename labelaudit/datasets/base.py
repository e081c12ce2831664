"""The common frame type every dataset reader produces, and the reader protocol.
Types only: no file access here."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator, Protocol

import numpy as np
from numpy.typing import NDArray


@dataclass
class Frame:
    """One LiDAR sweep with its labeled boxes, everything in the LiDAR/vehicle frame.

    Attributes
    ----------
    frame_id : unique within the dataset (KITTI "000123", Waymo "<segment>:<timestamp>")
    points : (N, 4) float32 — x, y, z, intensity
    boxes : (K, 7) float64 — cx, cy, cz, length, width, height, yaw (geometric centre, yaw about +z)
    class_names : K class names as written by the dataset ("Car", "Vehicle" …)
    object_ids : K ids (Waymo laser_object_id; else "<frame_id>:<index>")
    sensor_origin : (3,) position of the LiDAR in this frame (for distances and corner order)
    extras : per-object optional columns, each an array of length K (KITTI truncated, occluded,
        difficulty …)
    warnings : non-fatal notes about the input (e.g. "dropped 3 points with NaN coordinates")
    """

    frame_id: str
    points: NDArray[np.float32]
    boxes: NDArray[np.float64]
    class_names: list[str]
    object_ids: list[str]
    sensor_origin: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        k = len(self.boxes)
        if self.boxes.shape != (k, 7):
            raise ValueError(f"frame {self.frame_id}: boxes must be (K, 7), got {self.boxes.shape}")
        if len(self.class_names) != k or len(self.object_ids) != k:
            raise ValueError(f"frame {self.frame_id}: {k} boxes but {len(self.class_names)} classes, {len(self.object_ids)} ids")
        for name, values in self.extras.items():
            if len(values) != k:
                raise ValueError(f"frame {self.frame_id}: extra column {name!r} has {len(values)} values for {k} boxes")

    @property
    def num_objects(self) -> int:
        return len(self.boxes)


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

    def load_unit(self, ref: FrameRef) -> Iterator[Frame]:
        """Frames of one unit; raises :class:`DatasetError` for a bad unit."""
        ...

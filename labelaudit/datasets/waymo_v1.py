"""Waymo Open Dataset v1 reader: ``*.tfrecord`` segment files of ``Frame`` protos, without TensorFlow.
It reads files and builds Frames; it does not audit.

A DATASET is a folder searched recursively for ``*.tfrecord`` files, or one such file. Each file
is one segment, the unit of work and of resume.

TFRecord framing (per record)::

    uint64 length (little endian) | uint32 masked_crc32c(length bytes) | payload | uint32 masked_crc32c(payload)

with ``masked(c) = ((c >> 15) | (c << 17)) + 0xa282ead8 (mod 2³²)`` and CRC-32C (Castagnoli) from
the ``crc32c`` package. Payloads are decoded with our own minimal message classes
(:mod:`labelaudit.datasets.waymo_proto`); range images and the TOP range-image pose are
zlib-compressed ``MatrixFloat`` messages.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path
from typing import BinaryIO, Iterator

import crc32c
import numpy as np
from numpy.typing import NDArray

from labelaudit.datasets import waymo_proto as wp
from labelaudit.datasets.base import Frame, FrameFailure, FrameRef
from labelaudit.datasets.waymo_common import (
    TOP,
    FrameLabels,
    LidarCalibration,
    LidarData,
    check_extras,
    frame_points,
    make_frame,
    no_lidar_warning,
    sensor_origin,
)
from labelaudit.errors import DatasetError, one_line

FORMAT = "waymo-v1"
_MASK_DELTA = 0xA282EAD8
_HEADER = struct.Struct("<QI")
_FOOTER = struct.Struct("<I")


def masked_crc32c(data: bytes) -> int:
    """TFRecord's masked CRC-32C of ``data``."""
    crc = crc32c.crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & 0xFFFFFFFF


def encode_record(payload: bytes) -> bytes:
    """One TFRecord record (header, payload, footer) around ``payload``."""
    length = struct.pack("<Q", len(payload))
    return length + struct.pack("<I", masked_crc32c(length)) + payload + _FOOTER.pack(masked_crc32c(payload))


def iter_records(path: str | Path, verify: bool = True) -> Iterator[bytes]:
    """Payloads of a TFRecord file, in order.

    Raises
    ------
    DatasetError
        On a truncated record or a CRC mismatch; the message names the file, the record index
        and its byte offset. Records before the bad one have already been yielded.
    """
    for item in _records(path, verify):
        if isinstance(item, DatasetError):
            raise item
        yield item


def _records(path: str | Path, verify: bool) -> Iterator[bytes | DatasetError]:
    """Payloads of a TFRecord file; a record whose payload CRC does not match is yielded as its
    :class:`DatasetError` (the framing is intact, so the next record still reads). Framing errors
    (truncation, a length CRC mismatch, a length beyond the end of the file) raise."""
    path = Path(path)
    try:
        fh = open(path, "rb")
    except OSError as exc:
        raise DatasetError(path, f"cannot open the segment file ({exc.strerror or exc})") from None
    with fh:
        yield from _iter_stream(fh, path, verify)


def _iter_stream(fh: BinaryIO, path: Path, verify: bool) -> Iterator[bytes | DatasetError]:
    index = 0
    size = os.fstat(fh.fileno()).st_size
    while True:
        offset = fh.tell()
        header = fh.read(_HEADER.size)
        if not header:
            return
        if len(header) < _HEADER.size:
            raise DatasetError(
                path,
                f"truncated TFRecord: record {index} at byte {offset} has a {len(header)}-byte header (expected 12)",
            )
        length, length_crc = _HEADER.unpack(header)
        if verify and masked_crc32c(header[:8]) != length_crc:
            raise DatasetError(path, f"TFRecord length CRC mismatch in record {index} at byte {offset} (corrupt file?)")
        remaining = size - offset - _HEADER.size
        if length + _FOOTER.size > remaining:  # before reading: a forged length would ask for exabytes
            raise DatasetError(
                path,
                f"truncated TFRecord: record {index} at byte {offset} declares {length} payload bytes + 4 CRC bytes, "
                f"but the file has {remaining} bytes left (truncated file or corrupt length)",
            )
        payload = fh.read(length)
        footer = fh.read(_FOOTER.size)
        if len(payload) < length or len(footer) < _FOOTER.size:
            raise DatasetError(
                path,
                f"truncated TFRecord: record {index} at byte {offset} needs {length} payload bytes + 4 CRC bytes, "
                f"file ends after {len(payload) + len(footer)}",
            )
        if verify and masked_crc32c(payload) != _FOOTER.unpack(footer)[0]:
            yield DatasetError(
                path, f"TFRecord payload CRC mismatch in record {index} at byte {offset} (corrupt file?)"
            )
        else:
            yield payload
        index += 1


def _transform(msg: object, what: str, source: str) -> NDArray[np.float64] | None:
    values = list(msg.transform)  # type: ignore[attr-defined]
    if not values:
        return None
    if len(values) != 16:
        raise DatasetError(source, f"{what} has {len(values)} values, expected 16 (row-major 4x4)")
    return np.asarray(values, dtype=np.float64).reshape(4, 4)


def _calibrations(context: object, source: str) -> dict[int, LidarCalibration]:
    out: dict[int, LidarCalibration] = {}
    for c in context.laser_calibrations:  # type: ignore[attr-defined]
        extrinsic = _transform(c.extrinsic, f"laser calibration {c.name} extrinsic", source)
        out[int(c.name)] = LidarCalibration(
            name=int(c.name),
            extrinsic=np.eye(4) if extrinsic is None else extrinsic,
            inclination_min=float(c.beam_inclination_min),
            inclination_max=float(c.beam_inclination_max),
            inclinations=np.asarray(c.beam_inclinations, dtype=np.float64),
        )
    return out


def _matrix(blob: bytes, what: str, source: str) -> NDArray[np.float32]:
    try:
        return wp.decode_matrix_float(zlib.decompress(blob))
    except (zlib.error, ValueError) as exc:
        raise DatasetError(source, f"cannot decode {what}: {exc}") from exc


def _range_image(ri: object, what: str, source: str) -> NDArray[np.float32] | None:
    if ri.range_image_compressed:  # type: ignore[attr-defined]
        return _matrix(ri.range_image_compressed, what, source)  # type: ignore[attr-defined]
    if ri.HasField("range_image") and len(ri.range_image.data):  # type: ignore[attr-defined]
        m = ri.range_image  # type: ignore[attr-defined]
        return np.asarray(m.data, dtype=np.float32).reshape(tuple(m.shape.dims))
    return None


def iter_labels(path: str | Path, verify: bool = True) -> Iterator[FrameLabels]:
    """The labels of every frame of a segment file, in record order, without decoding a range image.

    Raises
    ------
    DatasetError
        A record that is not a Waymo ``Frame``, an empty or corrupt file (the message names the file and record).
    """
    path = Path(path)
    count = 0
    for index, payload in enumerate(iter_records(path, verify)):
        try:
            msg = wp.Frame.FromString(payload)
        except Exception as exc:  # protobuf's DecodeError
            raise DatasetError(path, f"record {index} is not a Waymo Frame: {exc}") from exc
        segment = msg.context.name or path.stem
        labels = msg.laser_labels
        boxes = np.array(
            [
                [l.box.center_x, l.box.center_y, l.box.center_z, l.box.length, l.box.width, l.box.height, l.box.heading]
                for l in labels
            ],
            dtype=float,
        ).reshape(-1, 7)
        yield FrameLabels(
            frame_id=f"{segment}:{msg.timestamp_micros}",
            boxes=boxes,
            types=np.array([l.type for l in labels], dtype=np.int64),
            difficulty=np.array([l.detection_difficulty_level for l in labels], dtype=np.int64),
            num_points=np.array([l.num_lidar_points_in_box for l in labels], dtype=np.int64),
            sensor_origin=sensor_origin(_calibrations(msg.context, f"{path} record {index}")),
            source=str(path),
        )
        count += 1
    if count == 0:
        raise DatasetError(path, "empty TFRecord file: no records")


def decode_frame(payload: bytes, source: str | Path, classes: tuple[str, ...] | None = None, index: int = 0) -> Frame:
    """Decode one serialized ``Frame`` into a labelaudit :class:`Frame`.

    Parameters
    ----------
    payload : one TFRecord record
    source : file name for messages
    classes : keep only these class names (all when None)
    index : record index, for messages

    Raises
    ------
    DatasetError
        Naming the file and record, for anything in the record that cannot be decoded.
    """
    try:
        return _decode_frame(payload, source, classes, index)
    except DatasetError:
        raise
    except (ValueError, TypeError, OverflowError, IndexError, KeyError, zlib.error, MemoryError) as exc:
        detail = one_line(f"{type(exc).__name__}: {exc}")
        raise DatasetError(source, f"record {index} cannot be decoded ({detail})") from None


def _decode_frame(payload: bytes, source: str | Path, classes: tuple[str, ...] | None, index: int) -> Frame:
    where = f"{source} record {index}"
    try:
        msg = wp.Frame.FromString(payload)
    except Exception as exc:  # protobuf raises DecodeError (a generic Exception subclass)
        raise DatasetError(source, f"record {index} is not a Waymo Frame: {exc}") from exc
    segment = msg.context.name or Path(source).stem
    frame_id = f"{segment}:{msg.timestamp_micros}"
    calibrations = _calibrations(msg.context, where)
    frame_pose = _transform(msg.pose, "frame pose", where)
    warnings: list[str] = []

    lidars: list[LidarData] = []
    for laser in msg.lasers:
        returns = []
        for k, ri in ((1, laser.ri_return1), (2, laser.ri_return2)):
            image = _range_image(ri, f"lidar {laser.name} return {k} range image", where)
            if image is not None:
                returns.append(image)
        pixel_pose = None
        if laser.name == TOP and laser.ri_return1.range_image_pose_compressed:
            pixel_pose = _matrix(laser.ri_return1.range_image_pose_compressed, "TOP range image pose", where)
        if returns:
            lidars.append(LidarData(name=int(laser.name), returns=returns, pixel_pose=pixel_pose))

    labels = msg.laser_labels
    k = len(labels)
    boxes = np.array(
        [
            [l.box.center_x, l.box.center_y, l.box.center_z, l.box.length, l.box.width, l.box.height, l.box.heading]
            for l in labels
        ],
        dtype=np.float64,
    ).reshape(k, 7)
    types = np.array([l.type for l in labels], dtype=np.int64)
    ids = [l.id or f"{frame_id}:{i}" for i, l in enumerate(labels)]
    locations = [f"{where} laser_labels[{i}]" for i in range(k)]
    extras = {
        "num_lidar_points_in_box": np.array([l.num_lidar_points_in_box for l in labels], dtype=np.int64),
        "num_top_lidar_points_in_box": np.array([l.num_top_lidar_points_in_box for l in labels], dtype=np.int64),
        "detection_difficulty": np.array([l.detection_difficulty_level for l in labels], dtype=np.int64),
        "tracking_difficulty": np.array([l.tracking_difficulty_level for l in labels], dtype=np.int64),
        "speed_x": np.array([l.metadata.speed_x for l in labels], dtype=np.float64),
        "speed_y": np.array([l.metadata.speed_y for l in labels], dtype=np.float64),
    }

    if lidars:
        points, ray_mask, no_label_zone = frame_points(lidars, calibrations, frame_pose, where, warnings)
    else:
        points, ray_mask = np.zeros((0, 4), dtype=np.float32), np.zeros(0, dtype=bool)
        no_label_zone = ray_mask
        if k:
            warnings.append(no_lidar_warning(where, frame_id, k))
    extras = check_extras(extras, _EXTRA_FIELDS, locations, warnings)
    return make_frame(
        frame_id,
        points,
        boxes,
        types,
        ids,
        extras,
        sensor_origin(calibrations),
        warnings,
        classes,
        source=str(source),
        locations=locations,
        box_fields=_BOX_FIELDS,
        ray_mask=ray_mask,
        no_label_zone=no_label_zone,
        pose=frame_pose,
        timestamp=msg.timestamp_micros / 1e6,
    )


_BOX_FIELDS = tuple(f"box.{f}" for f in ("center_x", "center_y", "center_z", "length", "width", "height", "heading"))
_EXTRA_FIELDS = {
    "num_lidar_points_in_box": "num_lidar_points_in_box",
    "num_top_lidar_points_in_box": "num_top_lidar_points_in_box",
    "detection_difficulty": "detection_difficulty_level",
    "tracking_difficulty": "tracking_difficulty_level",
}


class WaymoV1Reader:
    """Reader of Waymo v1 TFRecord segments.

    Parameters
    ----------
    root : folder searched recursively for ``*.tfrecord`` files, or one ``.tfrecord`` file
    classes : class names to keep ("Vehicle", "Pedestrian", "Sign", "Cyclist", "Unknown");
        None keeps every label
    verify_crc : check both CRCs of every record (cheap; on by default)
    split : search only ``root/<split>/`` (e.g. "training", "validation")
    """

    format_name = FORMAT

    def __init__(
        self,
        root: str | Path,
        classes: tuple[str, ...] | list[str] | None = None,
        verify_crc: bool = True,
        split: str | None = None,
    ):
        self.root = Path(root) / split if split else Path(root)
        if not self.root.exists():
            raise DatasetError(
                self.root, "dataset path does not exist" if not split else f"split folder {split!r} not found"
            )
        self.classes = None if classes is None else tuple(classes)
        self.verify_crc = verify_crc

    def list_units(self) -> list[FrameRef]:
        """One unit per ``.tfrecord`` file (a segment), sorted by path."""
        if self.root.is_file():
            files = [self.root]
        else:
            files = sorted(p for p in self.root.rglob("*.tfrecord") if p.is_file())
            if not files:
                raise DatasetError(self.root, "no *.tfrecord files found (searched recursively)")
        return [FrameRef(FORMAT, str(self.root), str(p)) for p in files]

    def labels(self, ref: FrameRef) -> Iterator[FrameLabels]:
        """The labels of one segment file's frames, without their points (:func:`iter_labels`)."""
        return iter_labels(Path(ref.key), self.verify_crc)

    def load_unit(self, ref: FrameRef) -> Iterator[Frame | FrameFailure]:
        """Frames of one segment file, in record order; a record that cannot be decoded (or whose
        payload CRC fails) is a :class:`FrameFailure` and the next record is read.

        Raises
        ------
        DatasetError
            For a missing, truncated or corrupt file (frames before the bad record are yielded first).
        """
        path = Path(ref.key)
        if not path.is_file():
            raise DatasetError(path, "segment file not found")
        count = 0
        seen: dict[str, int] = {}  # frame id → record: a frame id must not repeat (rows are keyed by it)
        for index, payload in enumerate(_records(path, self.verify_crc)):
            count += 1
            if isinstance(payload, DatasetError):
                yield FrameFailure(None, payload)
                continue
            try:
                frame = decode_frame(payload, path, self.classes, index)
            except DatasetError as exc:  # one bad record: the next one still reads
                yield FrameFailure(None, exc)
                continue
            if frame.frame_id in seen:
                yield FrameFailure(
                    frame.frame_id,
                    DatasetError(
                        path,
                        f"record {index} repeats frame {frame.frame_id} of record {seen[frame.frame_id]} (same segment name and timestamp); not read twice",
                    ),
                )
                continue
            seen[frame.frame_id] = index
            yield frame
        if count == 0:
            raise DatasetError(path, "empty TFRecord file: no records")

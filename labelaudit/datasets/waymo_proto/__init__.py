"""Minimal Waymo Open Dataset v1 message definitions, built at import time — no protoc, no TensorFlow.

Why this way
------------
``protoc`` is not guaranteed on users' machines and the official ``waymo-open-dataset`` wheels pin
TensorFlow. The wire format only cares about field *numbers* and wire types, which are facts of the
published format, so we declare just the messages and fields labelaudit reads, as a
``FileDescriptorProto`` written in Python, and let ``google.protobuf`` (upb, C speed) build the
classes. Every other field (camera images, camera labels, maps …) is skipped as unknown.

* Enums (laser name, label type, difficulty) are declared ``int32``: same varint wire encoding,
  and an out-of-range value stays readable instead of being dropped.
* The messages live in a private :class:`~google.protobuf.descriptor_pool.DescriptorPool` under
  the package ``labelaudit.waymo``, so they never clash with the official generated modules if a
  user imports both in one process.
* ``MatrixFloat`` (a range image, 0.7 M floats for TOP) has a NumPy fast path,
  :func:`decode_matrix_float` / :func:`encode_matrix_float`, that reads the packed float run with
  ``np.frombuffer`` instead of materialising a Python repeated field; anything unusual falls back
  to the generated class.

Field numbers (``waymo.open_dataset``, ``dataset.proto`` / ``label.proto``)::

    Frame            context 1, timestamp_micros 2, pose 3, lasers 5, laser_labels 6
    Context          name 1, laser_calibrations 3
    LaserCalibration name 1, beam_inclinations 2, beam_inclination_min 3, beam_inclination_max 4,
                     extrinsic 5
    Transform        transform 1 (16 doubles, row-major 4x4)
    Laser            name 1, ri_return1 2, ri_return2 3
    RangeImage       range_image 1 (deprecated, uncompressed), range_image_compressed 2,
                     range_image_pose_compressed 4
    MatrixFloat      data 1 (packed float), shape 2;  MatrixShape dims 1
    Label            box 1, metadata 2, type 3, id 4, detection_difficulty_level 5,
                     tracking_difficulty_level 6, num_lidar_points_in_box 7,
                     num_top_lidar_points_in_box 13
    Label.Box        center_x 1, center_y 2, center_z 3, width 4, length 5, height 6, heading 7
    Label.Metadata   speed_x 1, speed_y 2, accel_x 3, accel_y 4, speed_z 5, accel_z 6

and, for detections (``protos/metrics.proto``, what the Waymo evaluation tools read)::

    Objects          objects 1 (no_label_zone_objects 2 is skipped)
    Object           object 1 (a Label), score 2 (float, default 1.0), overlap_with_nlz 3,
                     context_name 4, frame_timestamp_micros 5, camera_name 6
"""

from __future__ import annotations

from typing import Any

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from numpy.typing import NDArray

__all__ = [
    "Frame",
    "Context",
    "LaserCalibration",
    "Laser",
    "RangeImage",
    "MatrixFloat",
    "MatrixShape",
    "Transform",
    "Label",
    "LabelBox",
    "Object",
    "Objects",
    "LabelMetadata",
    "decode_matrix_float",
    "encode_matrix_float",
]

_PACKAGE = "labelaudit.waymo"
_F = descriptor_pb2.FieldDescriptorProto

# (message name, [(field name, number, type, label, message type or None, packed)])
_OPT, _REP = _F.LABEL_OPTIONAL, _F.LABEL_REPEATED
_MESSAGES: list[tuple[str, list[tuple[str, int, int, int, str | None, bool]]]] = [
    ("Transform", [("transform", 1, _F.TYPE_DOUBLE, _REP, None, False)]),
    ("MatrixShape", [("dims", 1, _F.TYPE_INT32, _REP, None, False)]),
    (
        "MatrixFloat",
        [
            ("data", 1, _F.TYPE_FLOAT, _REP, None, True),
            ("shape", 2, _F.TYPE_MESSAGE, _OPT, "MatrixShape", False),
        ],
    ),
    (
        "LaserCalibration",
        [
            ("name", 1, _F.TYPE_INT32, _OPT, None, False),
            ("beam_inclinations", 2, _F.TYPE_DOUBLE, _REP, None, False),
            ("beam_inclination_min", 3, _F.TYPE_DOUBLE, _OPT, None, False),
            ("beam_inclination_max", 4, _F.TYPE_DOUBLE, _OPT, None, False),
            ("extrinsic", 5, _F.TYPE_MESSAGE, _OPT, "Transform", False),
        ],
    ),
    (
        "Context",
        [
            ("name", 1, _F.TYPE_STRING, _OPT, None, False),
            ("laser_calibrations", 3, _F.TYPE_MESSAGE, _REP, "LaserCalibration", False),
        ],
    ),
    (
        "RangeImage",
        [
            ("range_image", 1, _F.TYPE_MESSAGE, _OPT, "MatrixFloat", False),
            ("range_image_compressed", 2, _F.TYPE_BYTES, _OPT, None, False),
            ("range_image_pose_compressed", 4, _F.TYPE_BYTES, _OPT, None, False),
        ],
    ),
    (
        "Laser",
        [
            ("name", 1, _F.TYPE_INT32, _OPT, None, False),
            ("ri_return1", 2, _F.TYPE_MESSAGE, _OPT, "RangeImage", False),
            ("ri_return2", 3, _F.TYPE_MESSAGE, _OPT, "RangeImage", False),
        ],
    ),
    (
        "LabelBox",
        [
            ("center_x", 1, _F.TYPE_DOUBLE, _OPT, None, False),
            ("center_y", 2, _F.TYPE_DOUBLE, _OPT, None, False),
            ("center_z", 3, _F.TYPE_DOUBLE, _OPT, None, False),
            ("width", 4, _F.TYPE_DOUBLE, _OPT, None, False),
            ("length", 5, _F.TYPE_DOUBLE, _OPT, None, False),
            ("height", 6, _F.TYPE_DOUBLE, _OPT, None, False),
            ("heading", 7, _F.TYPE_DOUBLE, _OPT, None, False),
        ],
    ),
    (
        "LabelMetadata",
        [
            ("speed_x", 1, _F.TYPE_DOUBLE, _OPT, None, False),
            ("speed_y", 2, _F.TYPE_DOUBLE, _OPT, None, False),
            ("accel_x", 3, _F.TYPE_DOUBLE, _OPT, None, False),
            ("accel_y", 4, _F.TYPE_DOUBLE, _OPT, None, False),
            ("speed_z", 5, _F.TYPE_DOUBLE, _OPT, None, False),
            ("accel_z", 6, _F.TYPE_DOUBLE, _OPT, None, False),
        ],
    ),
    (
        "Label",
        [
            ("box", 1, _F.TYPE_MESSAGE, _OPT, "LabelBox", False),
            ("metadata", 2, _F.TYPE_MESSAGE, _OPT, "LabelMetadata", False),
            ("type", 3, _F.TYPE_INT32, _OPT, None, False),
            ("id", 4, _F.TYPE_STRING, _OPT, None, False),
            ("detection_difficulty_level", 5, _F.TYPE_INT32, _OPT, None, False),
            ("tracking_difficulty_level", 6, _F.TYPE_INT32, _OPT, None, False),
            ("num_lidar_points_in_box", 7, _F.TYPE_INT32, _OPT, None, False),
            ("num_top_lidar_points_in_box", 13, _F.TYPE_INT32, _OPT, None, False),
        ],
    ),
    (
        "Frame",
        [
            ("context", 1, _F.TYPE_MESSAGE, _OPT, "Context", False),
            ("timestamp_micros", 2, _F.TYPE_INT64, _OPT, None, False),
            ("pose", 3, _F.TYPE_MESSAGE, _OPT, "Transform", False),
            ("lasers", 5, _F.TYPE_MESSAGE, _REP, "Laser", False),
            ("laser_labels", 6, _F.TYPE_MESSAGE, _REP, "Label", False),
        ],
    ),
    # protos/metrics.proto: predictions (and GT) for the Waymo evaluation tools
    (
        "Object",
        [
            ("object", 1, _F.TYPE_MESSAGE, _OPT, "Label", False),
            ("score", 2, _F.TYPE_FLOAT, _OPT, None, False),
            ("overlap_with_nlz", 3, _F.TYPE_BOOL, _OPT, None, False),
            ("context_name", 4, _F.TYPE_STRING, _OPT, None, False),
            ("frame_timestamp_micros", 5, _F.TYPE_INT64, _OPT, None, False),
            ("camera_name", 6, _F.TYPE_INT32, _OPT, None, False),
        ],
    ),
    ("Objects", [("objects", 1, _F.TYPE_MESSAGE, _REP, "Object", False)]),
]
_DEFAULTS = {("Object", "score"): "1"}  # metrics.proto: an Object without a score is a GT box (score 1.0)


def _build_classes() -> dict[str, Any]:
    fdp = descriptor_pb2.FileDescriptorProto(name="labelaudit/waymo_minimal.proto", package=_PACKAGE, syntax="proto2")
    for msg_name, fields in _MESSAGES:
        msg = fdp.message_type.add(name=msg_name)
        for name, number, ftype, label, type_name, packed in fields:
            f = msg.field.add(name=name, number=number, type=ftype, label=label)
            if type_name is not None:
                f.type_name = f".{_PACKAGE}.{type_name}"
            if packed:
                f.options.packed = True
            if (msg_name, name) in _DEFAULTS:
                f.default_value = _DEFAULTS[(msg_name, name)]
    pool = descriptor_pool.DescriptorPool()
    pool.Add(fdp)
    return {
        name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"{_PACKAGE}.{name}")) for name, _ in _MESSAGES
    }


_CLASSES = _build_classes()
Transform = _CLASSES["Transform"]
MatrixShape = _CLASSES["MatrixShape"]
MatrixFloat = _CLASSES["MatrixFloat"]
LaserCalibration = _CLASSES["LaserCalibration"]
Context = _CLASSES["Context"]
RangeImage = _CLASSES["RangeImage"]
Laser = _CLASSES["Laser"]
LabelBox = _CLASSES["LabelBox"]
LabelMetadata = _CLASSES["LabelMetadata"]
Label = _CLASSES["Label"]
Frame = _CLASSES["Frame"]
Object = _CLASSES["Object"]
Objects = _CLASSES["Objects"]


# --- MatrixFloat fast path ------------------------------------------------------------------------


def _varint(buf: bytes, pos: int) -> tuple[int, int]:
    """Read a base-128 varint at ``pos``; returns (value, next position)."""
    value = shift = 0
    while True:
        if pos >= len(buf):
            raise ValueError("truncated varint")
        b = buf[pos]
        pos += 1
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos
        shift += 7
        if shift > 63:
            raise ValueError("varint longer than 10 bytes")


def _encode_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        b = value & 0x7F
        value >>= 7
        if value:
            out.append(b | 0x80)
        else:
            out.append(b)
            return bytes(out)


def _decode_slow(buf: bytes) -> NDArray[np.float32]:
    try:
        msg = MatrixFloat.FromString(buf)
    except Exception as exc:  # protobuf's DecodeError: report it like the fast path does
        raise ValueError(f"not a MatrixFloat message: {exc}") from exc
    data = np.asarray(msg.data, dtype=np.float32)
    dims = tuple(msg.shape.dims)
    if dims and int(np.prod(dims)) != data.size:
        raise ValueError(f"MatrixFloat has {data.size} values but shape {list(dims)}")
    return data.reshape(dims) if dims else data


def decode_matrix_float(buf: bytes) -> NDArray[np.float32]:
    """Decode a serialized ``MatrixFloat`` into a float32 array of shape ``shape.dims``.

    Parameters
    ----------
    buf : serialized MatrixFloat (already zlib-decompressed)

    Returns
    -------
    (dims...) float32 array — (H, W, 4) for a range image, (H, W, 6) for a range-image pose.

    Raises
    ------
    ValueError
        When the bytes are not a MatrixFloat or the data size does not match the shape.
    """
    data: NDArray[np.float32] | None = None
    dims: list[int] = []
    pos, n = 0, len(buf)
    while pos < n:
        tag, pos = _varint(buf, pos)
        field, wire = tag >> 3, tag & 7
        if field == 1 and wire == 2 and data is None:  # packed floats: one contiguous run
            size, pos = _varint(buf, pos)
            if pos + size > n or size % 4:
                raise ValueError(f"MatrixFloat data run of {size} bytes does not fit the message")
            data = np.frombuffer(buf, dtype="<f4", count=size // 4, offset=pos).astype(np.float32)
            pos += size
        elif field == 2 and wire == 2:
            size, pos = _varint(buf, pos)
            end = pos + size
            while pos < end:  # MatrixShape: dims, packed or not
                t, pos = _varint(buf, pos)
                if t == 0x08:
                    d, pos = _varint(buf, pos)
                    dims.append(d)
                elif t == 0x0A:
                    ln, pos = _varint(buf, pos)
                    stop = pos + ln
                    while pos < stop:
                        d, pos = _varint(buf, pos)
                        dims.append(d)
                else:
                    return _decode_slow(buf)
        else:  # unpacked floats, repeated runs or unknown fields: let protobuf handle it
            return _decode_slow(buf)
    if data is None:
        data = np.zeros(0, dtype=np.float32)
    if not dims:
        return data
    if int(np.prod(dims)) != data.size:
        raise ValueError(f"MatrixFloat has {data.size} values but shape {dims}")
    return data.reshape(dims)


def encode_matrix_float(array: NDArray[np.floating]) -> bytes:
    """Serialize an array as a ``MatrixFloat`` (packed float32 data, then its shape)."""
    a = np.ascontiguousarray(array, dtype="<f4")
    raw = a.tobytes()
    shape = b"".join(b"\x08" + _encode_varint(int(d)) for d in a.shape)
    return b"\x0a" + _encode_varint(len(raw)) + raw + b"\x12" + _encode_varint(len(shape)) + shape

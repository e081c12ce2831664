"""Waymo v1 (TFRecord) reader: real stripped frames, simulated segments, framing and corrupt files."""

from __future__ import annotations

import struct
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from labelaudit.datasets import DatasetError, FrameFailure, detect_format, open_dataset
from labelaudit.datasets.waymo_v1 import WaymoV1Reader, encode_record, iter_records, masked_crc32c
from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_waymo_v1

MMDET_FRAME = "mmdet3d-waymo/tests/data/waymo/waymo_format/validation/val.tfrecord"
PVPS_FRAME = "waymo-od-testdata/src/waymo_open_dataset/utils/testdata/pvps_data_one_frame.tfrecord"


def _one_frame(path: Path, **kw):
    reader = WaymoV1Reader(path, **kw)
    units = reader.list_units()
    assert len(units) == 1
    frames = list(reader.load_unit(units[0]))
    assert len(frames) == 1
    return frames[0]


# --- real frames (labels and calibrations, lidar stripped) ----------------------------------------


@pytest.mark.realdata
def test_mmdet3d_frame_labels(realdata: Path) -> None:
    f = _one_frame(realdata / MMDET_FRAME)
    assert f.frame_id == "1071392229495085036_1844_790_1864_790:1507315488219118"
    assert len(f.boxes) == 18
    assert Counter(f.class_names) == {"Sign": 17, "Vehicle": 1}
    # values of the one vehicle as documented in the realdata README (decoded independently there)
    k = f.class_names.index("Vehicle")
    np.testing.assert_allclose(f.boxes[k], [69.683, 33.335, 0.776, 4.36, 2.009, 1.46, -1.4788], atol=2e-3)
    assert f.object_ids[k] == "ujRqHN24m6Y6mmrLi9Tsnw"
    assert (f.extras["detection_difficulty"] == 0).all()
    assert f.extras["num_lidar_points_in_box"][k] == 15
    # TOP lidar position from the calibration; no lidar → 0 points and a clear, non-fatal note
    np.testing.assert_allclose(f.sensor_origin, [1.43, 0.0, 2.184])
    assert f.points.shape == (0, 4)
    assert (
        len(f.warnings) == 1
        and "no lidar range images" in f.warnings[0]
        and MMDET_FRAME.split("/")[-1] in f.warnings[0]
    )


@pytest.mark.realdata
def test_pvps_frame_labels(realdata: Path) -> None:
    f = _one_frame(realdata / PVPS_FRAME)
    assert f.frame_id == "1024360143612057520_3580_000_3600_000:1553735853462203"
    assert len(f.boxes) == 75
    assert Counter(f.class_names) == {"Vehicle": 37, "Sign": 25, "Pedestrian": 12, "Cyclist": 1}
    assert Counter(f.extras["detection_difficulty"].tolist()) == {0: 60, 2: 15}
    n = f.extras["num_lidar_points_in_box"]
    assert n.max() == 11442 and (n == 0).sum() == 2
    # Two vehicles checked by hand against the official generated protos (width is field 4,
    # length field 5: a swap would give length < width here).
    k = f.object_ids.index("5_YGq0d2QUJaCZqDOqNZHw")
    np.testing.assert_allclose(f.boxes[k], [4.9014, 6.1926, 1.0008, 5.0777, 2.3796, 2.25, -0.0056], atol=1e-4)
    assert n[k] == 11442 and f.class_names[k] == "Vehicle"
    k = f.object_ids.index("-zRacoa4APhIbgKYpgbiDQ")
    np.testing.assert_allclose(f.boxes[k], [10.2276, 1.978, 0.8304, 1.029, 0.8732, 1.59, 1.5491], atol=1e-4)
    assert f.class_names[k] == "Pedestrian"
    assert f.points.shape == (0, 4) and f.warnings


@pytest.mark.realdata
def test_pvps_class_filter_and_open_dataset(realdata: Path) -> None:
    path = realdata / PVPS_FRAME
    assert detect_format(path) == "waymo-v1"
    reader = open_dataset(path.parent, "auto", classes=("Vehicle",))
    frames = [f for u in reader.list_units() for f in reader.load_unit(u)]
    assert len(frames) == 1 and frames[0].class_names == ["Vehicle"] * 37
    assert len(frames[0].extras["num_lidar_points_in_box"]) == 37


@pytest.mark.realdata
def test_real_frames_match_official_protos(realdata: Path) -> None:
    """Every label equals what the official generated protos decode (only if they are importable)."""
    dataset_pb2 = pytest.importorskip("waymo_open_dataset.dataset_pb2")
    for rel in (MMDET_FRAME, PVPS_FRAME):
        payload = next(iter_records(realdata / rel))
        ref = dataset_pb2.Frame.FromString(payload)
        f = _one_frame(realdata / rel)
        want = np.array(
            [
                [l.box.center_x, l.box.center_y, l.box.center_z, l.box.length, l.box.width, l.box.height, l.box.heading]
                for l in ref.laser_labels
            ]
        )
        np.testing.assert_array_equal(f.boxes, want)
        assert f.object_ids == [l.id for l in ref.laser_labels]


# --- TFRecord framing ------------------------------------------------------------------------------


def test_record_roundtrip_and_crc(tmp_path: Path) -> None:
    payloads = [b"", b"abc", bytes(range(256)) * 40]
    path = tmp_path / "x.tfrecord"
    path.write_bytes(b"".join(encode_record(p) for p in payloads))
    assert list(iter_records(path)) == payloads
    raw = encode_record(b"abc")
    assert struct.unpack("<Q", raw[:8])[0] == 3
    assert struct.unpack("<I", raw[8:12])[0] == masked_crc32c(raw[:8])
    # the mask changes the CRC (a plain CRC-32C would not match real files)
    import crc32c

    assert masked_crc32c(b"abc") != crc32c.crc32c(b"abc")


@pytest.mark.realdata
def test_real_file_crcs_verify(realdata: Path) -> None:
    """The real files' CRCs (written by TensorFlow) verify with our masked CRC-32C."""
    raw = (realdata / MMDET_FRAME).read_bytes()
    length = struct.unpack("<Q", raw[:8])[0]
    assert struct.unpack("<I", raw[8:12])[0] == masked_crc32c(raw[:8])
    assert struct.unpack("<I", raw[12 + length : 16 + length])[0] == masked_crc32c(raw[12 : 12 + length])


# --- simulated segments ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def segment():
    return simulate_waymo_segment(seed=3, frames=2, size="small")


def _assert_same_points(got: np.ndarray, want: np.ndarray, tol: float = 0.01) -> None:
    assert got.shape == want.shape
    d1, i1 = cKDTree(want[:, :3]).query(got[:, :3])
    d2, _ = cKDTree(got[:, :3]).query(want[:, :3])
    assert d1.max() <= tol and d2.max() <= tol, (d1.max(), d2.max())
    np.testing.assert_allclose(got[:, 3], want[i1, 3], atol=1e-6)


def test_simulated_v1_reproduces_points_and_labels(tmp_path: Path, segment) -> None:
    path = write_waymo_v1(segment, tmp_path / "v1" / "a" / "seg.tfrecord")
    assert detect_format(tmp_path / "v1") == "waymo-v1"
    reader = open_dataset(tmp_path / "v1", "waymo-v1")
    frames = list(reader.load_unit(reader.list_units()[0]))
    assert [f.frame_id for f in frames] == [f"{segment.name}:{sf.timestamp}" for sf in segment.frames]
    for f, sf in zip(frames, segment.frames):
        assert not f.warnings
        assert len(f.points) > 1000
        _assert_same_points(f.points, sf.points)
        np.testing.assert_allclose(f.boxes, sf.boxes, atol=1e-12)
        assert f.object_ids == sf.object_ids
        np.testing.assert_array_equal(f.extras["num_lidar_points_in_box"], sf.num_points)
        np.testing.assert_allclose(f.sensor_origin, segment.calibrations[1].extrinsic[:3, 3])
    assert path.stat().st_size > 0


def _write_two(tmp_path: Path, segment) -> tuple[Path, Path]:
    a = write_waymo_v1(segment, tmp_path / "a.tfrecord")
    b = write_waymo_v1(segment, tmp_path / "b.tfrecord")
    return a, b


def _read_all(reader: WaymoV1Reader) -> tuple[dict[str, int], dict[str, str]]:
    """Frames read per file, and the error (unit-level, or of a failed record) per file."""
    done, errors = {}, {}
    for unit in reader.list_units():
        n = 0
        try:
            for frame in reader.load_unit(unit):
                if isinstance(frame, FrameFailure):
                    errors[Path(unit.key).name] = str(frame.error)
                else:
                    n += 1
        except DatasetError as exc:
            errors[Path(unit.key).name] = str(exc)
        done[Path(unit.key).name] = n
    return done, errors


def test_truncated_file_names_it_and_others_continue(tmp_path: Path, segment) -> None:
    a, _ = _write_two(tmp_path, segment)
    raw = a.read_bytes()
    a.write_bytes(raw[: len(raw) - 100])  # cut inside the second record
    done, errors = _read_all(WaymoV1Reader(tmp_path))
    assert done == {"a.tfrecord": 1, "b.tfrecord": 2}  # the first frame of a was still read
    assert set(errors) == {"a.tfrecord"}
    assert str(a) in errors["a.tfrecord"] and "truncated" in errors["a.tfrecord"] and "record 1" in errors["a.tfrecord"]


def test_crc_mismatch_names_file(tmp_path: Path, segment) -> None:
    a, _ = _write_two(tmp_path, segment)
    raw = bytearray(a.read_bytes())
    raw[40] ^= 0xFF  # inside the first payload
    a.write_bytes(bytes(raw))
    done, errors = _read_all(WaymoV1Reader(tmp_path))
    assert done == {"a.tfrecord": 1, "b.tfrecord": 2}  # the framing is intact: record 1 still reads
    assert (
        str(a) in errors["a.tfrecord"] and "CRC mismatch" in errors["a.tfrecord"] and "record 0" in errors["a.tfrecord"]
    )


def test_a_forged_length_is_named_before_reading(tmp_path: Path) -> None:
    # a length of 2^60 must be refused before the reader asks for exabytes (a bare "MemoryError while reading <file>: ")
    path = tmp_path / "x.tfrecord"
    good = encode_record(b"hello")
    length = struct.pack("<Q", 2**60)
    path.write_bytes(good + length + struct.pack("<I", masked_crc32c(length)) + b"rest")
    WaymoV1Reader(path)  # opening the file is fine: the forged length is met while reading
    with pytest.raises(
        DatasetError, match=r"record 1 at byte 21 declares 1152921504606846976 payload bytes .* has 4 bytes left"
    ):
        list(iter_records(path))


def test_length_crc_mismatch(tmp_path: Path) -> None:
    path = tmp_path / "x.tfrecord"
    raw = bytearray(encode_record(b"hello"))
    raw[0] ^= 0x01  # length says 4 instead of 5
    path.write_bytes(bytes(raw))
    with pytest.raises(DatasetError, match="length CRC mismatch in record 0"):
        list(iter_records(path))


def test_garbage_payload_with_valid_crc(tmp_path: Path) -> None:
    path = tmp_path / "x.tfrecord"
    path.write_bytes(encode_record(b"\xff\xff\xff"))
    reader = WaymoV1Reader(path)
    (failure,) = list(reader.load_unit(reader.list_units()[0]))
    assert isinstance(failure, FrameFailure) and "record 0 is not a Waymo Frame" in str(failure.error)
    assert failure.error.path == str(path)


def test_no_tfrecords_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no \\*.tfrecord"):
        WaymoV1Reader(tmp_path).list_units()


def test_split_option(tmp_path: Path, segment) -> None:
    write_waymo_v1(segment, tmp_path / "training" / "a.tfrecord")
    write_waymo_v1(segment, tmp_path / "validation" / "sub" / "b.tfrecord")
    assert [Path(u.key).name for u in WaymoV1Reader(tmp_path).list_units()] == ["a.tfrecord", "b.tfrecord"]
    assert [Path(u.key).name for u in WaymoV1Reader(tmp_path, split="validation").list_units()] == ["b.tfrecord"]
    with pytest.raises(DatasetError, match="split folder 'test' not found"):
        WaymoV1Reader(tmp_path, split="test")


def test_empty_file_is_an_error(tmp_path: Path) -> None:
    path = tmp_path / "empty.tfrecord"
    path.write_bytes(b"")
    reader = WaymoV1Reader(tmp_path)
    with pytest.raises(DatasetError, match="empty TFRecord") as info:
        list(reader.load_unit(reader.list_units()[0]))
    assert str(path) in str(info.value)

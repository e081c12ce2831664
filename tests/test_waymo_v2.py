"""Waymo v2 (Parquet) reader, the shared range image → points conversion and the proto codec."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from labelaudit.datasets import DatasetError, detect_format, open_dataset
from labelaudit.datasets import waymo_proto as wp
from labelaudit.datasets.waymo_common import (
    LidarCalibration,
    LidarData,
    euler_to_matrix,
    frame_points,
    range_image_to_points,
)
from labelaudit.datasets.waymo_v2 import K_TS, WaymoV2Reader, read_vehicle_poses
from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_waymo_v2

REAL_POSE = "waymo-od-testdata/src/waymo_open_dataset/v2/testdata/dataset/vehicle_pose/10023947602400723454_1120_000_1140_000.parquet"


# --- range image → points: known answers ------------------------------------------------------------


def _image(ranges: np.ndarray, intensity: float = 0.5) -> np.ndarray:
    img = np.zeros(ranges.shape + (4,), dtype=np.float32)
    img[..., 0] = ranges
    img[..., 1] = intensity
    return img


def test_columns_sweep_from_plus_pi_and_rows_top_first() -> None:
    # W = 4 columns look at vehicle azimuths 135°, 45°, −45°, −135°; one beam at elevation 0.
    calib = LidarCalibration(1, np.eye(4), inclinations=np.array([0.0]))
    pts = range_image_to_points(_image(np.full((1, 4), 10.0)), calib)
    s = 10 / np.sqrt(2)
    np.testing.assert_allclose(pts[:, :3], [[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]], atol=1e-5)
    np.testing.assert_allclose(pts[:, 3], 0.5)
    # uniform rows at row centres, row 0 the highest: H = 2 between −0.2 and 0.2 → +0.1, −0.1
    calib = LidarCalibration(2, np.eye(4), -0.2, 0.2)
    pts = range_image_to_points(_image(np.array([[10.0, 0, 0, 0], [10.0, 0, 0, 0]])), calib)
    np.testing.assert_allclose(pts[:, 2], [10 * np.sin(0.1), -10 * np.sin(0.1)], atol=1e-5)
    # explicit inclinations are listed ascending in the calibration: the last one is row 0
    calib = LidarCalibration(1, np.eye(4), inclinations=np.array([-0.3, 0.05]))
    pts = range_image_to_points(_image(np.array([[0, 10.0, 0, 0], [0, 10.0, 0, 0]])), calib)
    np.testing.assert_allclose(pts[:, 2], [10 * np.sin(0.05), 10 * np.sin(-0.3)], atol=1e-5)


def test_mounting_yaw_does_not_move_columns() -> None:
    # A lidar turned by 90° and mounted at (1, 2, 3): column 1 still looks at vehicle azimuth 45°.
    e = np.eye(4)
    e[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    e[:3, 3] = (1.0, 2.0, 3.0)
    calib = LidarCalibration(2, e, inclinations=np.array([0.0]))
    pts = range_image_to_points(_image(np.array([[0, 10.0, 0, 0]])), calib)
    s = 10 / np.sqrt(2)
    np.testing.assert_allclose(pts[0, :3], [1 + s, 2 + s, 3], atol=1e-5)


def test_no_return_pixels_are_dropped() -> None:
    calib = LidarCalibration(2, np.eye(4), -0.1, 0.1)
    ranges = np.array([[5.0, 0.0, -1.0, np.nan]])
    assert len(range_image_to_points(_image(ranges), calib)) == 1


def test_euler_convention_matches_scipy() -> None:
    rng = np.random.default_rng(0)
    angles = rng.uniform(-np.pi, np.pi, size=(20, 3))  # roll, pitch, yaw
    got = euler_to_matrix(angles[:, 0], angles[:, 1], angles[:, 2])
    want = Rotation.from_euler("ZYX", angles[:, ::-1]).as_matrix()  # Rz(yaw)·Ry(pitch)·Rx(roll)
    np.testing.assert_allclose(got, want, atol=1e-12)


def test_pixel_pose_moves_points_into_the_frame_pose() -> None:
    # Frame pose: at (100, 50, 0) turned 30°. Pixel captured 1 m further along world x, same heading:
    # the point moves +1 m along world x, i.e. by R_frameᵀ·(1, 0, 0) in the vehicle frame.
    yaw = np.deg2rad(30)
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_euler("z", yaw).as_matrix()
    frame[:3, 3] = (100.0, 50.0, 0.0)
    calib = LidarCalibration(1, np.eye(4), inclinations=np.array([0.0]))
    img = _image(np.array([[0, 10.0, 0, 0]]))
    pose = np.zeros((1, 4, 6), dtype=np.float32)
    pose[...] = (0, 0, yaw, 101.0, 50.0, 0.0)
    base = range_image_to_points(img, calib)
    moved = range_image_to_points(img, calib, pose, frame)
    np.testing.assert_allclose(moved[0, :3] - base[0, :3], [np.cos(yaw), -np.sin(yaw), 0], atol=1e-4)
    with pytest.raises(ValueError, match="frame pose"):
        range_image_to_points(img, calib, pose, None)


@pytest.mark.parametrize("per_column", [True, False])
def test_pixel_pose_matches_reference(per_column: bool) -> None:
    """Per-pixel poses (and the per-column fast path) against a transform built with scipy."""
    rng = np.random.default_rng(2)
    h, w = 3, 8
    calib = LidarCalibration(1, np.eye(4), inclinations=np.linspace(-0.2, 0.05, h))
    img = _image(rng.uniform(2, 50, size=(h, w)))
    pose = np.empty((h, w, 6), dtype=np.float32)
    pose[..., :3] = rng.normal(0, 0.05, size=(h, w, 3)) + [0, 0, 1.0]
    pose[..., 3:] = rng.normal(0, 1.0, size=(h, w, 3)) + [500.0, -300.0, 10.0]
    if per_column:
        pose[:] = pose[0]
    frame = np.eye(4)
    frame[:3, :3] = Rotation.from_euler("ZYX", [1.02, 0.01, -0.02]).as_matrix()
    frame[:3, 3] = (500.5, -299.0, 10.2)
    got = range_image_to_points(img, calib, pose, frame)
    p_v = range_image_to_points(img, calib)[:, :3].astype(np.float64)
    px = pose.reshape(-1, 6).astype(np.float64)
    world = Rotation.from_euler("ZYX", px[:, 2::-1]).apply(p_v) + px[:, 3:]
    want = (world - frame[:3, 3]) @ frame[:3, :3]
    np.testing.assert_allclose(got[:, :3], want, atol=1e-4)


@pytest.mark.parametrize("pose_kind", ["none", "per_column", "per_pixel", "nan_pose"])
def test_compiled_points_are_the_numpy_passes_bit_for_bit(pose_kind: str) -> None:
    """The compiled conversion of a float32 image gives the NumPy passes' points bit for bit: the
    same pixels (range ≤ 0 and NaN dropped), the same float64 operations in the same order; pixel
    poses that vary within a column (or hold a NaN) take the NumPy passes themselves."""
    from labelaudit.datasets.waymo_common import _range_image_points_numpy

    rng = np.random.default_rng(3)
    h, w = 5, 16
    e = np.eye(4)
    e[:3, :3] = Rotation.from_euler("ZYX", [0.3, 0.02, -0.01]).as_matrix()
    e[:3, 3] = (1.4, -0.1, 2.1)
    calib = LidarCalibration(1, e, inclinations=np.linspace(-0.3, 0.04, h))
    ranges = rng.uniform(1, 80, size=(h, w))
    ranges[rng.random((h, w)) < 0.2] = 0.0
    ranges[0, 3], ranges[2, 5] = np.nan, -1.0
    img = _image(ranges)
    img[..., 1] = rng.random((h, w))
    pose = frame = None
    if pose_kind != "none":
        pose = np.empty((h, w, 6), dtype=np.float32)
        pose[..., :3] = rng.normal(0, 0.05, size=(h, w, 3))
        pose[..., 3:] = rng.normal(0, 1.0, size=(h, w, 3)) + [5000.0, -3000.0, 10.0]
        if pose_kind != "per_pixel":
            pose[:] = pose[0]
        if pose_kind == "nan_pose":
            pose[:, 2, 0] = np.nan
        frame = np.eye(4)
        frame[:3, :3] = Rotation.from_euler("ZYX", [1.02, 0.01, -0.02]).as_matrix()
        frame[:3, 3] = (5000.5, -2999.0, 10.2)
    got = range_image_to_points(img, calib, pose, frame)
    want = _range_image_points_numpy(img, calib, pose, frame)
    assert got.dtype == np.float32 and got.shape == want.shape == (int(np.sum(ranges > 0)), 4)
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
    # a float64 image takes the NumPy passes, with the same points for the same values
    np.testing.assert_array_equal(range_image_to_points(img.astype(np.float64), calib, pose, frame), want)


# --- MatrixFloat codec --------------------------------------------------------------------------


def test_matrix_float_codec_roundtrip_and_fallbacks() -> None:
    a = np.random.default_rng(1).normal(size=(3, 5, 4)).astype(np.float32)
    enc = wp.encode_matrix_float(a)
    msg = wp.MatrixFloat.FromString(enc)  # the generated class agrees with our encoder
    assert list(msg.shape.dims) == [3, 5, 4]
    np.testing.assert_array_equal(np.asarray(msg.data, np.float32).reshape(3, 5, 4), a)
    np.testing.assert_array_equal(wp.decode_matrix_float(enc), a)
    np.testing.assert_array_equal(wp.decode_matrix_float(msg.SerializeToString()), a)
    # unpacked floats (wire type 5, one tag per value) take the slow path and still decode
    unpacked = b"".join(b"\x0d" + np.float32(v).tobytes() for v in a.ravel()) + b"\x12\x04\x08\x3c\x08\x01"
    np.testing.assert_array_equal(wp.decode_matrix_float(unpacked), a.reshape(60, 1))
    with pytest.raises(ValueError):
        wp.decode_matrix_float(enc[:-3] + b"\x08\x09\x08")  # dims no longer match the data
    with pytest.raises(ValueError):
        wp.decode_matrix_float(unpacked[:-9])  # corrupt: the slow path's DecodeError becomes ValueError


# --- real v2 file ------------------------------------------------------------------------------------


@pytest.mark.realdata
def test_real_vehicle_pose_float32(realdata: Path) -> None:
    path = realdata / REAL_POSE
    assert pq.read_schema(path).field("[VehiclePoseComponent].world_from_vehicle.transform").type.value_type == "float"
    poses = read_vehicle_poses(path)
    assert len(poses) == 199
    stack = np.stack(list(poses.values()))
    assert stack.dtype == np.float64
    rot = stack[:, :3, :3]
    np.testing.assert_allclose(rot @ rot.transpose(0, 2, 1), np.broadcast_to(np.eye(3), rot.shape), atol=1e-5)
    np.testing.assert_array_equal(stack[:, 3], np.broadcast_to([0, 0, 0, 1], (199, 4)))


# --- simulated segments --------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def segment():
    return simulate_waymo_segment(seed=5, frames=2, size="small")


def _assert_same_points(got: np.ndarray, want: np.ndarray, tol: float = 0.01) -> float:
    assert got.shape == want.shape
    d1, i1 = cKDTree(want[:, :3]).query(got[:, :3])
    d2, _ = cKDTree(got[:, :3]).query(want[:, :3])
    assert d1.max() <= tol and d2.max() <= tol, (d1.max(), d2.max())
    np.testing.assert_allclose(got[:, 3], want[i1, 3], atol=1e-6)
    return float(max(d1.max(), d2.max()))


@pytest.mark.parametrize("pose_dtype", [np.float64, np.float32])
def test_simulated_v2_reproduces_points_and_labels(tmp_path: Path, segment, pose_dtype) -> None:
    root = write_waymo_v2(segment, tmp_path / "v2", pose_dtype=pose_dtype)
    assert detect_format(root) == "waymo-v2"
    reader = open_dataset(root, "auto")
    units = reader.list_units()
    assert len(units) == 1
    frames = list(reader.load_unit(units[0]))
    assert [f.frame_id for f in frames] == [f"{segment.name}:{sf.timestamp}" for sf in segment.frames]
    for f, sf in zip(frames, segment.frames):
        assert not f.warnings
        _assert_same_points(f.points, sf.points)
        np.testing.assert_allclose(f.boxes, sf.boxes, atol=1e-12)
        assert f.object_ids == sf.object_ids
        names = {1: "Vehicle", 2: "Pedestrian", 4: "Cyclist"}
        assert f.class_names == [names[int(t)] for t in sf.types]
        np.testing.assert_array_equal(f.extras["num_lidar_points_in_box"], sf.num_points)
        assert set(f.extras["detection_difficulty"]) <= {1, 2}
        assert f.extras["num_lidar_points_in_box"].dtype == np.int64 and f.extras["speed_x"].dtype == np.float64


def test_rolling_shutter_correction_matters(segment) -> None:
    """Without the TOP per-pixel pose the moving vehicle's points are off by decimetres."""
    sf = segment.frames[1]
    lidars = [LidarData(n, lid.returns, None) for n, lid in sf.lidars.items()]
    warnings: list[str] = []
    pts, _, _ = frame_points(lidars, segment.calibrations, sf.pose, "sim", warnings)
    d, _ = cKDTree(sf.points[:, :3]).query(pts[:, :3])
    assert d.max() > 0.1


def test_only_the_top_lidars_first_returns_are_rays(tmp_path: Path, segment) -> None:
    """Free-space rays start at the TOP lidar (the frame's sensor_origin): its first returns are rays,
    the other lidars' points and every second return are not (docs/label-error.md)."""
    sf = segment.frames[0]
    lidars = [LidarData(n, lid.returns, lid.pixel_pose) for n, lid in sf.lidars.items()]
    pts, rays, _ = frame_points(lidars, segment.calibrations, sf.pose, "sim", [])
    top_first = np.asarray(sf.lidars[1].returns[0])
    assert rays.shape == (len(pts),) and rays.dtype == bool
    assert rays.sum() == int((top_first[..., 0] > 0).sum()) > 0
    assert 0 < rays.sum() < len(pts)  # second returns and the short-range lidars are there, and no rays
    write_waymo_v2(segment, tmp_path)
    reader = WaymoV2Reader(tmp_path)
    f = next(iter(reader.load_unit(reader.list_units()[0])))
    assert f.ray_mask is not None and f.ray_mask.shape == (len(f.points),) and f.ray_mask.sum() == rays.sum()


def test_split_folder_layout_and_class_filter(tmp_path: Path, segment) -> None:
    write_waymo_v2(segment, tmp_path / "training")
    reader = WaymoV2Reader(tmp_path, classes=("Vehicle",))
    units = reader.list_units()
    assert len(units) == 1
    f = next(iter(reader.load_unit(units[0])))
    assert set(f.class_names) == {"Vehicle"}
    assert len(f.boxes) == int((segment.frames[0].types == 1).sum()) > 0
    write_waymo_v2(segment, tmp_path / "validation")
    assert len(WaymoV2Reader(tmp_path).list_units()) == 2
    units = WaymoV2Reader(tmp_path, split="validation").list_units()
    assert len(units) == 1 and "validation" in units[0].key
    with pytest.raises(DatasetError, match="split folder 'test' not found"):
        WaymoV2Reader(tmp_path, split="test")


def _two_segments(tmp_path: Path, segment) -> Path:
    root = tmp_path / "v2"
    write_waymo_v2(segment, root)
    other = simulate_waymo_segment(seed=6, frames=1, size="small", name="other_segment")
    write_waymo_v2(other, root)
    return root


def _read_all(reader: WaymoV2Reader) -> tuple[dict[str, int], dict[str, str]]:
    done, errors = {}, {}
    for unit in reader.list_units():
        seg = Path(unit.key).stem
        done[seg] = 0
        try:
            for _ in reader.load_unit(unit):
                done[seg] += 1
        except DatasetError as exc:
            errors[seg] = str(exc)
    return done, errors


@pytest.mark.parametrize("component", ["lidar", "lidar_calibration", "lidar_pose", "vehicle_pose"])
def test_missing_component_file_names_it(tmp_path: Path, segment, component: str) -> None:
    root = _two_segments(tmp_path, segment)
    missing = root / component / f"{segment.name}.parquet"
    missing.unlink()
    done, errors = _read_all(WaymoV2Reader(root))
    assert done["other_segment"] == 1 and "other_segment" not in errors
    assert str(missing) in errors[segment.name] and "missing Waymo v2 component" in errors[segment.name]


def test_frame_with_boxes_but_no_lidar_rows_warns(tmp_path: Path, segment) -> None:
    root = write_waymo_v2(segment, tmp_path / "v2")
    path = root / "lidar" / f"{segment.name}.parquet"
    t = pq.read_table(path)
    pq.write_table(t.filter(pc.not_equal(t.column(K_TS), segment.frames[1].timestamp)), path)
    reader = WaymoV2Reader(root)
    frames = list(reader.load_unit(reader.list_units()[0]))
    assert len(frames) == 2
    assert not frames[0].warnings and len(frames[0].points) > 0
    assert frames[1].points.shape == (0, 4) and len(frames[1].boxes) == len(segment.frames[1].boxes)
    assert "no lidar range images" in frames[1].warnings[0] and str(path) in frames[1].warnings[0]


def test_missing_column_names_it(tmp_path: Path, segment) -> None:
    root = write_waymo_v2(segment, tmp_path / "v2")
    path = root / "lidar_box" / f"{segment.name}.parquet"
    t = pq.read_table(path)
    pq.write_table(t.drop(["[LiDARBoxComponent].box.heading"]), path)
    reader = WaymoV2Reader(root)
    with pytest.raises(DatasetError, match=r"missing column\(s\) \[LiDARBoxComponent\].box.heading") as info:
        list(reader.load_unit(reader.list_units()[0]))
    assert str(path) in str(info.value)


def test_no_lidar_box_folder(tmp_path: Path) -> None:
    (tmp_path / "lidar").mkdir()
    with pytest.raises(DatasetError, match="no lidar_box/"):
        WaymoV2Reader(tmp_path).list_units()
    shutil.rmtree(tmp_path / "lidar")


@pytest.mark.slow
def test_kitti_and_waymo_renderings_of_one_scene_agree(tmp_path: Path) -> None:
    """The same simulated frame written as KITTI and as Waymo v2 reads to the same boxes and points,
    and (once the core model is installed) audits to the same rows up to frame conventions."""
    from labelaudit.sim.waymo_writer import write_as_kitti

    seg = simulate_waymo_segment(seed=8, frames=1, size="small", chunks=1)
    write_as_kitti(seg, tmp_path / "kitti")
    write_waymo_v2(seg, tmp_path / "v2")
    kr = open_dataset(tmp_path / "kitti", "kitti")
    wr = open_dataset(tmp_path / "v2", "waymo-v2")
    kf = next(iter(kr.load_unit(kr.list_units()[0])))
    wf = next(iter(wr.load_unit(wr.list_units()[0])))
    np.testing.assert_allclose(kf.boxes, wf.boxes, atol=1e-9)
    _assert_same_points(wf.points, kf.points, tol=1e-3)
    vehicle = {"Car", "Van", "Truck"}
    assert [n in vehicle for n in kf.class_names] == [n == "Vehicle" for n in wf.class_names]

    pytest.importorskip("labelaudit.infer.rows")
    from labelaudit.config import RunConfig
    from labelaudit.infer.rows import process_frame

    kf.sensor_origin = wf.sensor_origin  # frame convention: KITTI puts its LiDAR at the origin
    krows, _ = process_frame(kf, RunConfig(dataset_format="kitti", classes=("Car", "Van", "Truck")))
    wrows, _ = process_frame(wf, RunConfig(dataset_format="waymo-v2", classes=("Vehicle",)))
    assert len(krows) == len(wrows) > 0
    for a, b in zip(krows, wrows):
        assert a["object_index"] == b["object_index"] and a["status"] == b["status"]
        assert a["num_points"] == b["num_points"]
        for key in ("cx", "cy", "length", "yaw", "jiou_gt", "std_cx", "std_length"):
            if a.get(key) is not None:
                assert a[key] == pytest.approx(b[key], abs=1e-3, nan_ok=True), key


def test_simulated_dataset_with_label_noise(tmp_path: Path) -> None:
    from labelaudit.sim.noise import NoiseSpec
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    roots = simulate_waymo_dataset(tmp_path, segments=2, frames=1, seed=11, label_noise=NoiseSpec(gross_fraction=0.5))
    manifest = pq.read_table(tmp_path / "manifest.parquet").to_pylist()
    by_id = {(m["frame_id"], m["object_id"]): m for m in manifest}
    kinds = {m["perturbation"] for m in manifest}
    assert kinds & {"shift", "swap_lw", "yaw90"}  # some gross errors were injected
    for fmt, root in roots.items():
        reader = open_dataset(root, fmt)
        units = reader.list_units()
        assert len(units) == 2
        for unit in units:
            for f in reader.load_unit(unit):
                for box, oid in zip(f.boxes, f.object_ids):
                    m = by_id[(f.frame_id, oid)]
                    np.testing.assert_allclose(box, m["written_box"], atol=1e-12)
                    moved = not np.allclose(m["true_box"], m["written_box"])
                    assert moved == (m["perturbation"] != "none")

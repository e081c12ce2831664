"""Argoverse 2 reader: quaternions, frames and ids, annotation-only timestamps, bad files, the real logs."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest

from labelaudit import constants as C
from labelaudit.config import resolve_config
from labelaudit.core.geometry import quaternion_to_matrix, quaternion_yaw, rotation_z, yaw_quaternion
from labelaudit.datasets import DatasetError, Frame, FrameFailure, detect_format, open_dataset
from labelaudit.datasets.av2 import ANNOTATIONS, POSES, SWEEP_DIR, Av2Reader, find_logs, read_city_poses
from labelaudit.executors import SerialExecutor
from labelaudit.infer.crop import points_in_boxes_numpy
from labelaudit.infer.run import InferRequest, run_infer
from labelaudit.results import open_results
from labelaudit.sim.av2_writer import write_annotations, write_calibration, write_poses, write_sweep

AV2_REAL = "av2-sensor"
LOG = "0a1b2c3d-0000-4000-8000-000000000001"
T0 = 315966265259836000
DT = 100_000_000


# --- quaternion → yaw -----------------------------------------------------------------------------


@pytest.mark.parametrize("yaw", [0.0, 0.3, math.pi / 2, -2.0, 3.1])
def test_quaternion_yaw_round_trip(yaw: float) -> None:
    q = yaw_quaternion(yaw)
    assert quaternion_yaw(q) == pytest.approx(yaw, abs=1e-12)
    assert quaternion_yaw(3.7 * q) == pytest.approx(yaw, abs=1e-12)  # the norm does not matter
    assert quaternion_yaw(-q) == pytest.approx(yaw, abs=1e-12)  # q and −q are one rotation
    np.testing.assert_allclose(quaternion_to_matrix(q), rotation_z(yaw), atol=1e-12)


def test_quaternion_known_answers() -> None:
    h = math.sqrt(0.5)
    assert quaternion_yaw([h, 0, 0, h]) == pytest.approx(math.pi / 2)  # 90° about +z: x → y
    assert abs(quaternion_yaw([0, 0, 0, 1])) == pytest.approx(math.pi)
    # 90° about +x (a roll) leaves the x axis where it is: heading 0
    assert quaternion_yaw([h, h, 0, 0]) == pytest.approx(0.0, abs=1e-12)
    np.testing.assert_allclose(quaternion_to_matrix([h, h, 0, 0]), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-12)
    assert np.isnan(quaternion_to_matrix([0, 0, 0, 0])).all()


# --- a small log -----------------------------------------------------------------------------------


def _car_points(box: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """n points strictly inside ``box`` (float16-representable after writing is not needed: counts use the file)."""
    u = rng.uniform(-0.45, 0.45, size=(n, 3)) * box[3:6]
    c, s = math.cos(box[6]), math.sin(box[6])
    xyz = np.stack([box[0] + c * u[:, 0] - s * u[:, 1], box[1] + s * u[:, 0] + c * u[:, 1], box[2] + u[:, 2]], axis=1)
    return np.concatenate([xyz, np.full((n, 1), 40.0)], axis=1)


def make_log(
    root: Path,
    *,
    sweeps: tuple[int, ...] = (0, 1),
    empty: tuple[int, ...] = (),
    calibration: bool = True,
    log_id: str = LOG,
) -> Path:
    """A log with 3 annotated timestamps (2 tracks), sweeps at the given frame indices, poses."""
    rng = np.random.default_rng(0)
    log = root / "val" / log_id
    car = np.array([10.0, 2.0, 0.8, 4.5, 1.9, 1.6, 0.3])
    bus = np.array([-15.0, -4.0, 1.6, 12.0, 2.6, 3.2, -1.2])
    ts, boxes, cats, tracks = [], [], [], []
    for f in range(3):
        for box, cat, tr in ((car, "REGULAR_VEHICLE", "car-1"), (bus, "BUS", "bus-7")):
            b = box.copy()
            b[0] += 1.5 * f
            ts.append(T0 + f * DT)
            boxes.append(b)
            cats.append(cat)
            tracks.append(tr)
    boxes_a = np.array(boxes)
    counts = np.zeros(len(ts), dtype=np.int64)
    for f in sweeps:
        rows = [i for i, t in enumerate(ts) if t == T0 + f * DT]
        pts = (
            np.zeros((0, 4))
            if f in empty
            else np.concatenate([_car_points(boxes_a[i], 50 + 10 * i, rng) for i in rows])
        )
        path = write_sweep(
            log / SWEEP_DIR / f"{T0 + f * DT}.feather",
            pts,
            rng.integers(0, 64, len(pts)),
            rng.integers(0, 10**8, len(pts)),
        )
        written = feather.read_table(path)
        xyz = np.stack([written.column(c).to_numpy().astype(np.float32) for c in "xyz"], axis=1)
        for i, idx in zip(rows, points_in_boxes_numpy(xyz, boxes_a[rows])):
            counts[i] = len(idx)
    write_annotations(log / ANNOTATIONS, ts, boxes_a, cats, tracks, counts)
    pose_ts = np.arange(T0 - DT, T0 + 4 * DT, DT // 4)
    poses = []
    for t in pose_ts:
        m = np.eye(4)
        m[:3, :3] = rotation_z(0.01 * (t - T0) / DT)
        m[:3, 3] = (5000.0 + 1.2 * (t - T0) / DT, 2400.0, 60.0)
        poses.append(m)
    write_poses(log / POSES, pose_ts, poses)
    if calibration:
        write_calibration(
            log / "calibration" / "egovehicle_SE3_sensor.feather",
            {"up_lidar": (1.3, 0.0, 1.7), "down_lidar": (1.3, 0.0, 1.5), "ring_front_center": (1.6, 0, 1.4)},
        )
    return log


def _frames(root: Path, **kw: object) -> list[Frame | FrameFailure]:
    reader = open_dataset(root, "av2", **kw)
    return [f for ref in reader.list_units() for f in reader.load_unit(ref)]


def test_frames_ids_tracks_and_poses(tmp_path: Path) -> None:
    make_log(tmp_path)
    assert detect_format(tmp_path) == "av2"
    assert detect_format(tmp_path / "val") == "av2"
    assert detect_format(tmp_path / "val" / LOG) == "av2"
    frames = _frames(tmp_path)
    assert [f.frame_id for f in frames] == [f"{LOG}:{T0 + i * DT}" for i in range(3)]
    for i, f in enumerate(frames):
        assert isinstance(f, Frame)
        assert f.object_ids == ["car-1", "bus-7"]  # the track uuid, in file order
        assert f.class_names == ["REGULAR_VEHICLE", "BUS"]
        assert f.boxes[0, 0] == pytest.approx(10.0 + 1.5 * i)
        assert f.boxes[1, 6] == pytest.approx(-1.2)
        np.testing.assert_allclose(f.sensor_origin, (1.3, 0.0, 1.6))  # midpoint of the two lidars
        assert f.ray_mask is None  # every point of both lidars is a ray
        # the pose at the frame's own timestamp, not a neighbour's
        assert f.pose is not None
        np.testing.assert_allclose(f.pose[:3, 3], (5000.0 + 1.2 * i, 2400.0, 60.0), atol=1e-9)
        np.testing.assert_allclose(f.pose[:3, :3], rotation_z(0.01 * i), atol=1e-12)
    # the reader's boxes and points reproduce the written point counts (boundary inclusive)
    for f in frames[:2]:
        counts = [len(i) for i in points_in_boxes_numpy(f.points, f.boxes)]
        assert counts == list(f.extras["num_lidar_points_in_box"]) and min(counts) > 0


def test_annotation_only_and_empty_sweeps_keep_their_labels(tmp_path: Path) -> None:
    make_log(tmp_path, sweeps=(0, 1), empty=(1,))
    f0, f1, f2 = _frames(tmp_path)
    assert len(f0.points) > 0 and not any("no sweep" in w for w in f0.warnings)
    assert len(f1.points) == 0 and f1.num_objects == 2
    assert any("holds no points" in w for w in f1.warnings)
    assert len(f2.points) == 0 and f2.num_objects == 2  # no sweep file at all: still a frame
    assert any(f"{T0 + 2 * DT}.feather" in w and "no sweep" in w and "no_points" in w for w in f2.warnings)


def test_sweep_without_annotations_is_a_frame_without_labels(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    write_sweep(log / SWEEP_DIR / f"{T0 + 5 * DT}.feather", np.array([[1.0, 2.0, 3.0, 4.0]]))
    frames = _frames(tmp_path)
    assert frames[-1].frame_id == f"{LOG}:{T0 + 5 * DT}" and frames[-1].num_objects == 0 and len(frames[-1].points) == 1
    assert any("no pose at timestamp" in w for w in frames[-1].warnings)


def test_class_filter_and_split(tmp_path: Path) -> None:
    make_log(tmp_path)
    frames = _frames(tmp_path, classes=("BUS",), split="val")
    assert all(f.class_names == ["BUS"] and f.object_ids == ["bus-7"] for f in frames)
    with pytest.raises(DatasetError, match="split folder 'train' not found"):
        Av2Reader(tmp_path, split="train")


def test_standard_mounts_without_calibration(tmp_path: Path) -> None:
    make_log(tmp_path, calibration=False)
    f = _frames(tmp_path)[0]
    np.testing.assert_allclose(f.sensor_origin, np.mean(list(C.AV2_LIDAR_MOUNTS.values()), axis=0))


# --- bad input ---------------------------------------------------------------------------------------


def _rewrite(path: Path, **columns: object) -> None:
    t = feather.read_table(path)
    for name, values in columns.items():
        i = t.schema.get_field_index(name)
        t = t.remove_column(i) if values is None else t.set_column(i, name, pa.array(values))
    feather.write_feather(t, path)


def test_missing_column_names_file_and_column(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    _rewrite(log / ANNOTATIONS, qz=None)
    reader = Av2Reader(tmp_path)
    with pytest.raises(DatasetError, match=rf"{ANNOTATIONS}: missing column\(s\) qz"):
        list(reader.load_unit(reader.list_units()[0]))


def test_null_timestamp_names_the_row(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    ts = feather.read_table(log / ANNOTATIONS).column("timestamp_ns").to_pylist()
    ts[3] = None
    _rewrite(log / ANNOTATIONS, timestamp_ns=pa.array(ts, pa.int64()))
    reader = Av2Reader(tmp_path)
    with pytest.raises(DatasetError, match="row 3: timestamp_ns is null"):
        list(reader.load_unit(reader.list_units()[0]))


def test_not_a_feather_file(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    (log / ANNOTATIONS).write_bytes(b"not arrow at all")
    reader = Av2Reader(tmp_path)
    with pytest.raises(DatasetError, match="not a readable Feather"):
        list(reader.load_unit(reader.list_units()[0]))


def test_bad_rows_become_object_errors_naming_row_and_column(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    t = feather.read_table(log / ANNOTATIONS)
    length = t.column("length_m").to_pylist()
    length[0] = float("nan")
    width = t.column("width_m").to_pylist()
    width[1] = None
    qw = t.column("qw").to_pylist()
    qw[2] = 2.0  # norm ≈ 2: corrupt, not a rounding
    length[3] = -1.0
    _rewrite(log / ANNOTATIONS, length_m=length, width_m=pa.array(width, pa.float64()), qw=qw)
    f0, f1, f2 = _frames(tmp_path)
    assert "row 0" in f0.object_errors[0] and "length_m = nan" in f0.object_errors[0]
    assert "row 1" in f0.object_errors[1] and "width_m is null" in f0.object_errors[1]
    assert "row 2" in f1.object_errors[0] and "expected a unit quaternion" in f1.object_errors[0]
    assert "row 3" in f1.object_errors[1] and "length_m = -1" in f1.object_errors[1]
    assert not f2.object_errors
    assert all(str(log / ANNOTATIONS) in m for m in (*f0.object_errors.values(), *f1.object_errors.values()))


def test_null_category_and_track(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    t = feather.read_table(log / ANNOTATIONS)
    cats, tracks = t.column("category").to_pylist(), t.column("track_uuid").to_pylist()
    cats[1], tracks[0] = None, None
    _rewrite(log / ANNOTATIONS, category=pa.array(cats, pa.string()), track_uuid=pa.array(tracks, pa.string()))
    f0 = _frames(tmp_path)[0]
    assert f0.class_names == ["REGULAR_VEHICLE"] and f0.object_ids == [f"{f0.frame_id}:0"]
    assert any("row(s) 1 have a null category" in w for w in f0.warnings)


def test_bad_sweep_is_a_frame_failure_and_the_log_goes_on(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    (log / SWEEP_DIR / f"{T0}.feather").write_bytes(b"garbage")
    _rewrite(log / SWEEP_DIR / f"{T0 + DT}.feather", intensity=None)
    bad, missing_col, ok = _frames(tmp_path)
    assert isinstance(bad, FrameFailure) and bad.frame_id == f"{LOG}:{T0}" and f"{T0}.feather" in str(bad.error)
    assert isinstance(missing_col, FrameFailure) and "missing column(s) intensity" in str(missing_col.error)
    assert isinstance(ok, Frame) and ok.num_objects == 2
    # the labels alone (what eval reads) do not touch a sweep: every frame, its boxes, no points
    reader = Av2Reader(tmp_path)
    labels = list(reader.labels(reader.list_units()[0]))
    assert [f.frame_id for f in labels] == [bad.frame_id, missing_col.frame_id, ok.frame_id]
    assert all(len(f.points) == 0 and f.num_objects == 2 for f in labels)
    np.testing.assert_array_equal(labels[2].boxes, ok.boxes)


def test_non_finite_points_are_dropped_with_a_warning(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    path = log / SWEEP_DIR / f"{T0}.feather"
    x = feather.read_table(path).column("x").to_numpy().copy()
    x[:3] = np.nan
    _rewrite(path, x=x)
    f0 = _frames(tmp_path)[0]
    assert any("dropped 3 of" in w for w in f0.warnings) and np.isfinite(f0.points).all()


def test_bad_poses_are_left_out_with_a_warning(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    t = feather.read_table(log / POSES)
    qw = t.column("qw").to_pylist()
    row = int(np.flatnonzero(t.column("timestamp_ns").to_numpy() == T0 + DT)[0])
    qw[row] = 0.2
    _rewrite(log / POSES, qw=qw)
    poses, warnings = read_city_poses(log / POSES)
    assert T0 + DT not in poses and T0 in poses
    assert len(warnings) == 1 and f"row {row}" in warnings[0]
    f0, f1, _ = _frames(tmp_path)
    assert f1.pose is None and any("no pose at timestamp" in w for w in f1.warnings)
    assert any(f"row {row}" in w for w in f0.warnings)  # log-level notes go with the first frame


def test_unlabelled_logs_are_not_units(tmp_path: Path) -> None:
    make_log(tmp_path)
    test_log = tmp_path / "test" / "f00dcafe-0000-4000-8000-000000000000"
    write_sweep(test_log / SWEEP_DIR / f"{T0}.feather", np.array([[1.0, 2.0, 3.0, 4.0]]))
    assert [Path(u.key).name for u in Av2Reader(tmp_path).list_units()] == [
        LOG
    ]  # the test split's sweeps have no label
    with pytest.raises(DatasetError, match=r"1 Argoverse 2 log\(s\) but none with annotations.feather"):
        Av2Reader(tmp_path, split="test").list_units()


def test_find_logs_and_no_logs(tmp_path: Path) -> None:
    assert find_logs(tmp_path) == []
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="no Argoverse 2 log"):
        Av2Reader(tmp_path).list_units()


# --- the real logs ---------------------------------------------------------------------------------


@pytest.mark.realdata
def test_real_counts_match_num_interior_pts(realdata: Path) -> None:
    root = realdata / AV2_REAL
    if not root.is_dir():
        pytest.skip(f"{root} not present")
    assert detect_format(root) == "av2"
    checked = matched = frames_with_points = 0
    frames = _frames(root)
    assert len(frames) == 312 and all(isinstance(f, Frame) for f in frames)  # 156 annotated timestamps per log
    for f in frames:
        assert f.pose is not None and f.pose.shape == (4, 4)
        if not len(f.points):
            assert any("no sweep" in w for w in f.warnings)
            continue
        frames_with_points += 1
        counts = np.array([len(i) for i in points_in_boxes_numpy(f.points, f.boxes)])
        expected = np.asarray(f.extras["num_lidar_points_in_box"])
        checked += len(counts)
        matched += int((counts == expected).sum())
    assert frames_with_points == 3
    assert (matched, checked) == (209, 209)


def _rows(out: Path) -> list[dict]:
    return sorted(open_results(out).read().to_pylist(), key=lambda r: (r["frame_id"], r["object_index"]))


def _trimmed_real(realdata: Path, tmp_path: Path) -> Path:
    """The real logs with their annotations cut to the sweeps' timestamps and the next one (no sweep):
    5 frames instead of 312, the same files otherwise (sweeps, poses and calibration linked, not copied)."""
    src = realdata / AV2_REAL / "val"
    if not src.is_dir():
        pytest.skip(f"{src} not present")
    for log in sorted(p for p in src.iterdir() if p.is_dir()):
        dst = tmp_path / "av2" / "val" / log.name
        dst.mkdir(parents=True)
        t = feather.read_table(log / ANNOTATIONS)
        ts = t.column("timestamp_ns").to_numpy()
        swept = sorted(int(p.stem) for p in (log / SWEEP_DIR).glob("*.feather"))
        after = np.unique(ts[ts > swept[-1]])[0]
        keep = np.isin(ts, [*swept, after])
        feather.write_feather(t.filter(pa.array(keep)), dst / ANNOTATIONS)
        for name in (POSES, "sensors", "calibration"):
            if (log / name).exists():
                (dst / name).symlink_to(log / name)
    return tmp_path / "av2"


@pytest.mark.realdata
def test_infer_on_the_real_logs(realdata: Path, tmp_path: Path) -> None:
    root = _trimmed_real(realdata, tmp_path)
    cfg = resolve_config(None, "av2")
    summary = run_infer(InferRequest(root, tmp_path / "res"), cfg, executor=SerialExecutor())
    assert summary.frames == 5
    rows = _rows(tmp_path / "res")
    assert {r["dataset"] for r in rows} == {"av2"}
    assert {r["class_name"] for r in rows} <= set(cfg.classes)
    by_frame: dict[str, list[dict]] = {}
    for r in rows:
        by_frame.setdefault(r["frame_id"], []).append(r)
    assert len(by_frame) == 5
    swept = [f for f, rs in by_frame.items() if any(r["status"] != "no_points" for r in rs)]
    assert len(swept) == 3
    for f, rs in by_frame.items():
        if f in swept:
            ok = [r for r in rs if r["status"] == "ok"]
            assert len(ok) >= 10 and all(0 < r["jiou_gt"] <= 1 and r["label_error"] is not None for r in ok)
            # the dataset's own count of the label (no margin, no ground cut) bounds what the audit crops loosely
            assert all(r["num_lidar_points_in_box"] is not None for r in rs)
        else:  # the annotation-only timestamp: every label a row, status no_points, the track id kept
            assert all(r["status"] == "no_points" and r["num_points"] == 0 for r in rs)
        assert all(len(r["object_id"]) == 36 and r["object_id"].count("-") == 4 for r in rs)  # track uuids
    errors = open_results(tmp_path / "res").errors().to_pylist()
    assert sum("no sweep" in e["message"] for e in errors) == 2 and all(e["level"] == "warning" for e in errors)


def test_waymo_frames_carry_their_pose(tmp_path: Path) -> None:
    # the same field as AV2's: vehicle → world at the frame's timestamp, from either Waymo form
    from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_waymo_v1, write_waymo_v2

    seg = simulate_waymo_segment(seed=1, frames=2, chunks=1, noise=False, scene_spec=None)
    write_waymo_v2(seg, tmp_path / "v2")
    write_waymo_v1(seg, tmp_path / "v1" / f"{seg.name}.tfrecord")
    for fmt in ("waymo-v2", "waymo-v1"):
        frames = _frames_fmt(tmp_path / fmt.replace("waymo-", ""), fmt)
        assert len(frames) == 2
        for f, truth in zip(frames, seg.frames):
            np.testing.assert_allclose(f.pose, truth.pose, atol=1e-9)
        assert not np.allclose(frames[0].pose, frames[1].pose)  # the ego moves


def _frames_fmt(root: Path, fmt: str) -> list[Frame]:
    reader = open_dataset(root, fmt)
    return [f for ref in reader.list_units() for f in reader.load_unit(ref)]

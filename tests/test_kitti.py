"""KITTI reader: calibration, camera ↔ LiDAR boxes, label/velodyne parsing, bad input, real frames."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from labelaudit.core.geometry import rotation_z
from labelaudit.datasets import DatasetError, detect_format, open_dataset
from labelaudit.datasets.kitti import (
    LABEL_COLUMNS,
    Calibration,
    KittiReader,
    alpha_from_location,
    box_camera_to_lidar,
    box_lidar_to_camera,
    format_calib,
    format_label_line,
    kitti_difficulty,
    project_box_to_image,
    read_calib,
    read_label,
    read_scan,
    read_velodyne,
    write_velodyne,
)

# Ideal KITTI-like mounting: camera x = −LiDAR y, camera y = −LiDAR z, camera z = LiDAR x, plus an
# offset (the camera sits 0.27 m behind and 0.08 m below the LiDAR origin in camera coordinates).
AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
SIMPLE_CALIB = Calibration(
    P2=np.array([[700.0, 0, 600, 45], [0, 700, 180, 0], [0, 0, 1, 0.005]]),
    R0_rect=np.eye(3),
    Tr_velo_to_cam=np.c_[AXES, [0.0, -0.08, -0.27]],
)

GOOD_LINE = "Car 0.00 0 -1.57 600.00 150.00 700.00 220.00 1.50 1.60 4.00 1.00 1.50 10.00 0.00"


def realistic_calib(seed: int = 0) -> Calibration:
    """A calibration with small random rotations around the ideal mounting (not a real one)."""
    rng = np.random.default_rng(seed)

    def small_rot() -> np.ndarray:
        a = rng.normal(0, 0.01, 3)
        cx, sx, cy, sy = np.cos(a[0]), np.sin(a[0]), np.cos(a[1]), np.sin(a[1])
        rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
        ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        return rotation_z(a[2]) @ ry @ rx

    return Calibration(
        P2=np.array([[721.5377, 0, 609.5593, 44.85728], [0, 721.5377, 172.854, 0.2163791], [0, 0, 1, 0.002745884]]),
        R0_rect=small_rot(),
        Tr_velo_to_cam=np.c_[AXES @ small_rot(), rng.normal(0, 0.1, 3)],
    )


def write_frame(
    root: Path,
    frame_id: str,
    points: np.ndarray,
    label_lines: list[str],
    calib: Calibration = SIMPLE_CALIB,
) -> None:
    """Write one KITTI frame under ``root/training``."""
    base = root / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True, exist_ok=True)
    write_velodyne(base / "velodyne" / f"{frame_id}.bin", points)
    (base / "label_2" / f"{frame_id}.txt").write_text("".join(line + "\n" for line in label_lines))
    (base / "calib" / f"{frame_id}.txt").write_text(format_calib(calib))


def random_points(n: int = 500, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-20, 20, (n, 3)), rng.uniform(0, 1, n)].astype(np.float32)


# --------------------------------------------------------------------------------------------
# Calibration and box conversion
# --------------------------------------------------------------------------------------------


def test_transforms_are_inverse_and_compose_r0_with_tr() -> None:
    calib = realistic_calib(1)
    T = calib.T_cam_velo
    assert T.shape == (4, 4)
    np.testing.assert_allclose(T[:3, :3], calib.R0_rect @ calib.Tr_velo_to_cam[:, :3])
    np.testing.assert_allclose(T[:3, 3], calib.R0_rect @ calib.Tr_velo_to_cam[:, 3])
    np.testing.assert_allclose(T @ calib.T_velo_cam, np.eye(4), atol=1e-12)


def test_box_camera_to_lidar_hand_computed() -> None:
    # Camera point (1, 1.5, 10) minus the offset (0, -0.08, -0.27) is (1, 1.58, 10.27); back through
    # the axes: LiDAR x = 10.27, y = -1, z = -1.58 (the bottom); the centre is h/2 = 0.75 higher.
    box = box_camera_to_lidar([1.0, 1.5, 10.0], [1.5, 1.6, 4.0], 0.0, SIMPLE_CALIB)
    np.testing.assert_allclose(box, [10.27, -1.0, -0.83, 4.0, 1.6, 1.5, -np.pi / 2], atol=1e-12)
    # rotation_y = -π/2 heads along camera +z = LiDAR +x: yaw 0.
    assert box_camera_to_lidar([1.0, 1.5, 10.0], [1.5, 1.6, 4.0], -np.pi / 2, SIMPLE_CALIB)[6] == pytest.approx(0.0)
    # rotation_y = π/2 heads towards the camera: yaw ±π (wrapped into [-π, π)).
    assert abs(box_camera_to_lidar([0, 0, 5], [1, 1, 1], np.pi / 2, SIMPLE_CALIB)[6]) == pytest.approx(np.pi)
    # rotation_y = π heads along camera -x = LiDAR +y: yaw π/2.
    assert box_camera_to_lidar([0, 0, 5], [1, 1, 1], np.pi, SIMPLE_CALIB)[6] == pytest.approx(np.pi / 2)


def test_box_round_trip_lidar_camera_lidar() -> None:
    calib = realistic_calib(2)
    rng = np.random.default_rng(3)
    for _ in range(50):
        box = np.r_[rng.uniform(-40, 40, 2), rng.uniform(-2, 1), rng.uniform(0.5, 6, 3), rng.uniform(-np.pi, np.pi)]
        loc, dims, ry = box_lidar_to_camera(box, calib)
        assert dims.tolist() == [box[5], box[4], box[3]]
        assert -np.pi <= ry < np.pi
        back = box_camera_to_lidar(loc, dims, ry, calib)
        np.testing.assert_allclose(back[:6], box[:6], atol=1e-9)
        assert np.cos(back[6] - box[6]) == pytest.approx(1.0)


def test_calib_round_trip_is_exact(tmp_path: Path) -> None:
    calib = realistic_calib(4)  # full-precision random values, not 7-digit KITTI numbers
    path = tmp_path / "c.txt"
    path.write_text(format_calib(calib))
    back = read_calib(path)
    for key in ("P2", "R0_rect", "Tr_velo_to_cam"):
        assert np.array_equal(getattr(back, key), getattr(calib, key))
    assert back.P0 is None and back.Tr_imu_to_velo is None
    assert format_calib(calib).splitlines()[0].startswith("P2: 7.215377000000e+02 ")


def test_alpha_and_projection() -> None:
    # KITTI 000000 pedestrian: location (1.84, 1.47, 8.41), rotation_y 0.01, alpha -0.20.
    assert alpha_from_location([1.84, 1.47, 8.41], 0.01) == pytest.approx(-0.205, abs=0.005)
    box = box_camera_to_lidar([1.0, 1.5, 10.0], [1.5, 1.6, 4.0], 0.0, SIMPLE_CALIB)
    left, top, right, bottom = project_box_to_image(box, SIMPLE_CALIB)
    # The bottom centre projects to u = 600 + 700·1/10 (+45/10 offset), v = 180 + 700·1.5/10.
    assert left < 600 + 70 + 4.5 < right
    assert bottom == pytest.approx(180 + 700 * 1.5 / (10 - 0.8 + 0.005), rel=0.02)
    assert top < bottom


# --------------------------------------------------------------------------------------------
# Labels and difficulty
# --------------------------------------------------------------------------------------------


def test_difficulty_follows_devkit_thresholds() -> None:
    def box(height: float) -> list[float]:
        return [0.0, 100.0, 50.0, 100.0 + height]

    cases = [  # (2D height, occlusion, truncation) -> level
        ((41, 0, 0.0), 0),
        ((40, 0, 0.0), 1),  # the devkit needs height > 40 for Easy
        ((41, 1, 0.0), 1),
        ((41, 0, 0.2), 1),
        ((30, 2, 0.0), 2),
        ((41, 0, 0.4), 2),
        ((25, 0, 0.0), -1),
        ((60, 3, 0.0), -1),  # occlusion 3 = unknown
        ((60, 0, 0.6), -1),
    ]
    got = kitti_difficulty([box(c[0][0]) for c in cases], [c[0][1] for c in cases], [c[0][2] for c in cases])
    assert got.tolist() == [c[1] for c in cases]


def test_format_label_line_matches_official_text(realdata: Path) -> None:
    path = realdata / "openpcdet-pr653-kitti/training/label_2/000001.txt"
    lines = path.read_text().splitlines()
    labels = read_label(path)
    for i, name in enumerate(labels.class_names):
        if name == "DontCare":
            continue
        text = format_label_line(
            name, labels.truncated[i], labels.occluded[i], labels.alpha[i], labels.bbox2d[i],
            labels.dims_hwl[i], labels.location[i], labels.rotation_y[i],
        )  # fmt: skip
        assert text == lines[labels.line[i] - 1]


def test_format_label_line_exact_round_trip(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    vals = rng.normal(size=13)
    line = format_label_line(
        "Van", 0.25, 1, vals[0], vals[1:5], np.abs(vals[5:8]) + 1, vals[8:11], vals[11], score=3.5, precision=None
    )
    path = tmp_path / "l.txt"
    path.write_text(line + "\n")
    lab = read_label(path)
    assert len(line.split()) == 16 and lab.class_names == ["Van"] and lab.occluded.tolist() == [1]
    np.testing.assert_array_equal(lab.location[0], vals[8:11])
    np.testing.assert_array_equal(lab.dims_hwl[0], np.abs(vals[5:8]) + 1)
    assert lab.rotation_y[0] == vals[11] and lab.score[0] == 3.5 and lab.truncated[0] == 0.25
    with pytest.raises(ValueError, match="class name"):
        format_label_line("Big Car", 0, 0, 0, [0, 0, 1, 1], [1, 1, 1], [0, 0, 5], 0)


# --------------------------------------------------------------------------------------------
# Reader on written datasets
# --------------------------------------------------------------------------------------------


def test_written_dataset_reads_back_same_boxes(tmp_path: Path) -> None:
    calib = realistic_calib(6)
    boxes = np.array([[12.0, -3.0, -0.9, 4.2, 1.8, 1.5, 0.3], [25.0, 6.0, -1.0, 0.8, 0.6, 1.8, -2.0]])
    lines = []
    for box, name in zip(boxes, ["Car", "Pedestrian"]):
        loc, dims, ry = box_lidar_to_camera(box, calib)
        bbox = project_box_to_image(box, calib)
        lines.append(
            format_label_line(name, 0.0, 0, float(alpha_from_location(loc, ry)), bbox, dims, loc, ry, precision=None)
        )
    lines.insert(1, "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10")
    write_frame(tmp_path, "000007", random_points(), lines, calib)
    assert detect_format(tmp_path) == "kitti"
    reader = open_dataset(tmp_path, "auto")
    (frame,) = list(reader.load_unit(reader.list_units()[0]))
    assert frame.frame_id == "000007"
    np.testing.assert_allclose(frame.boxes[:, :6], boxes[:, :6], atol=1e-9)
    np.testing.assert_allclose(np.cos(frame.boxes[:, 6] - boxes[:, 6]), 1.0)
    assert frame.class_names == ["Car", "Pedestrian"]
    assert frame.object_ids == ["000007:0", "000007:1"]
    assert frame.extras["label_line"].tolist() == [1, 3]
    assert frame.points.dtype == np.float32 and frame.points.shape == (500, 4)
    assert np.all(np.isnan(frame.extras["score"]))
    # Class filter: ids keep their index among the non-DontCare rows.
    (ped,) = list(KittiReader(tmp_path, classes=["Pedestrian"]).load_unit(reader.list_units()[0]))
    assert ped.object_ids == ["000007:1"] and ped.class_names == ["Pedestrian"]


def test_split_and_split_folder_as_root(tmp_path: Path) -> None:
    for fid in ("000001", "000002", "000003"):
        write_frame(tmp_path, fid, random_points(), [GOOD_LINE])
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets" / "val.txt").write_text("000003\n000001\n")
    assert [r.key for r in KittiReader(tmp_path).list_units()] == ["000001", "000002", "000003"]
    assert [r.key for r in KittiReader(tmp_path, split="val").list_units()] == ["000003", "000001"]
    direct = KittiReader(tmp_path / "training", split="val")  # ImageSets found next to training/
    assert [r.key for r in direct.list_units()] == ["000003", "000001"]
    with pytest.raises(DatasetError, match="train.txt"):
        KittiReader(tmp_path, split="train").list_units()


def test_velodyne_reduced_is_used_when_velodyne_is_absent(tmp_path: Path) -> None:
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    (tmp_path / "training" / "velodyne").rename(tmp_path / "training" / "velodyne_reduced")
    reader = KittiReader(tmp_path)
    assert reader.velodyne_dir == "velodyne_reduced"
    assert reader.load_frame("000001").points.shape == (500, 4)


# --------------------------------------------------------------------------------------------
# Bad input: a clear DatasetError naming file (and line), the rest of the dataset still reads
# --------------------------------------------------------------------------------------------


def _load_all(reader: KittiReader) -> tuple[dict[str, object], dict[str, DatasetError]]:
    ok, failed = {}, {}
    for ref in reader.list_units():
        try:
            ok[ref.key] = list(reader.load_unit(ref))[0]
        except DatasetError as exc:
            failed[ref.key] = exc
    return ok, failed


@pytest.mark.parametrize(
    ("bad_line", "pattern", "line"),
    [
        ("Car 0.00 0 -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0", "expected 15 columns .* got 14", 2),
        (GOOD_LINE + " 0.9 7", "expected 15 columns .* got 17", 2),
        (
            "Car 0.00 0 -1.57 600 150 700 220 1.5 abc 4.0 1.0 1.5 10.0 0.0",
            "column 'width': expected a number, got 'abc'",
            2,
        ),
        ("Car 0.00 0.5 -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0 0.0", "column 'occluded'", 2),
        # an occlusion an int column cannot hold is an object error, not an ArrowInvalid that ends the run
        (
            "Car 0.00 3000000000 -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0 0.0",
            "column 'occluded'.*'3000000000'",
            2,
        ),
        ("Car 0.00 1e300 -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0 0.0", "column 'occluded'.*'1e300'", 2),
        ("Car 0.00 7 -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0 0.0", "column 'occluded'", 2),
        ("Car 0.00 nan -1.57 600 150 700 220 1.5 1.6 4.0 1.0 1.5 10.0 0.0", "column 'occluded'", 2),
    ],
)
def test_bad_label_lines(tmp_path: Path, bad_line: str, pattern: str, line: int) -> None:
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    write_frame(tmp_path, "000002", random_points(), [GOOD_LINE, bad_line])
    ok, failed = _load_all(KittiReader(tmp_path))
    assert list(ok) == ["000001"] and list(failed) == ["000002"]
    err = failed["000002"]
    assert err.path.endswith("label_2/000002.txt") and err.line == line
    assert f"000002.txt:{line}:" in str(err)
    assert err.__class__ is DatasetError
    assert re.search(pattern, str(err)), str(err)


@pytest.mark.parametrize(
    ("field", "value", "pattern"),
    [
        ("x", "nan", "x = nan .expected a finite number"),  # a NaN box is an object error, the run goes on
        ("z", "nan", "z = nan"),
        ("rotation_y", "nan", "rotation_y = nan"),
        ("width", "0.0", r"width = 0 .expected a size in \[0.01, 200\] m"),
        ("width", "1e-300", "width = 1e-300"),  # the core overflowed (warnings on stderr)
        ("height", "-1.5", "height = -1.5"),
        ("length", "nan", "length = nan"),
        ("length", "1e300", "length = 1e\\+300"),  # the core failed with a two-line eigenvalue message
        ("x", "inf", "x = inf"),
        ("y", "-3e7", r"y = -3e\+07 .expected \|value\| ≤ 10000 m"),
        ("rotation_y", "1e30", "rotation_y = 1e\\+30"),
    ],
)
def test_bad_box_values_make_only_that_object_an_error(tmp_path: Path, field: str, value: str, pattern: str) -> None:
    tokens = GOOD_LINE.split()
    tokens[LABEL_COLUMNS.index(field)] = value
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE, " ".join(tokens), GOOD_LINE])
    frame = KittiReader(tmp_path).load_frame("000001")
    assert frame.num_objects == 3 and list(frame.object_errors) == [1]
    msg = frame.object_errors[1]
    assert msg.startswith(f"{tmp_path / 'training/label_2/000001.txt'}:2: "), msg
    assert re.search(pattern, msg), msg
    assert frame.source.endswith("label_2/000001.txt")


def test_a_calibration_that_throws_boxes_out_of_range_names_the_calib_file(tmp_path: Path) -> None:
    calib = Calibration(SIMPLE_CALIB.P2, SIMPLE_CALIB.R0_rect, np.c_[AXES, [0.0, 0.0, 1e9]])
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE], calib)
    frame = KittiReader(tmp_path).load_frame("000001")
    assert "out of range after" in frame.object_errors[0] and "calib/000001.txt" in frame.object_errors[0]


def test_bom_and_crlf_label_and_split_files_read_every_row(tmp_path: Path) -> None:
    # a byte-order mark must not make the first class '\ufeffCar' (neither audited nor reported)
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE, GOOD_LINE.replace("Car", "Van")])
    label = tmp_path / "training/label_2/000001.txt"
    label.write_bytes(b"\xef\xbb\xbf" + label.read_bytes().replace(b"\n", b"\r\n"))
    frame = KittiReader(tmp_path).load_frame("000001")
    assert frame.class_names == ["Car", "Van"] and frame.extras["label_line"].tolist() == [1, 2]
    assert frame.warnings == []
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets/val.txt").write_bytes(b"\xef\xbb\xbf000001\r\n")
    assert [r.key for r in KittiReader(tmp_path, split="val").list_units()] == ["000001"]


def test_lines_are_numbered_by_newlines_only(tmp_path: Path) -> None:
    # str.splitlines would also split at the form feed and shift the line numbers
    write_frame(tmp_path, "000001", random_points(), ["\x0c", GOOD_LINE, GOOD_LINE.replace("1.60", "abc")])
    with pytest.raises(DatasetError) as info:
        KittiReader(tmp_path).load_frame("000001")
    assert info.value.line == 3


def test_unprintable_class_names_are_warned_about(tmp_path: Path) -> None:
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE, "\u200bCar" + GOOD_LINE[3:]])
    frame = KittiReader(tmp_path).load_frame("000001")
    assert len(frame.warnings) == 1 and "line 2" in frame.warnings[0] and "unprintable" in frame.warnings[0]


def test_non_utf8_text_files_name_the_file(tmp_path: Path) -> None:
    # a non-UTF-8 ImageSets/val.txt is an input error naming the file, not a UnicodeDecodeError (exit 3)
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    (tmp_path / "ImageSets").mkdir()
    (tmp_path / "ImageSets/val.txt").write_bytes(b"000001\n\xff\xfe\n")
    with pytest.raises(DatasetError, match=r"val.txt:2: split list is not UTF-8 text \(byte 0xff at offset 7\)"):
        KittiReader(tmp_path, split="val").list_units()
    label = tmp_path / "training/label_2/000001.txt"
    label.write_bytes(b"\xef\xbb\xbf" + GOOD_LINE.encode() + b" \xe9\n")
    with pytest.raises(DatasetError, match="000001.txt:1: label file is not UTF-8 text .byte 0xe9"):
        read_label(label)


def test_non_utf8_file_names_are_read_with_a_warning(tmp_path: Path) -> None:
    import os

    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    base = os.fsencode(tmp_path / "training")
    for sub, ext in ((b"label_2", b".txt"), (b"velodyne", b".bin"), (b"calib", b".txt")):
        os.link(os.path.join(base, sub, b"000001" + ext), os.path.join(base, sub, b"\xff1" + ext))
    reader = KittiReader(tmp_path)
    frames = {f.frame_id: f for ref in reader.list_units() for f in reader.load_unit(ref)}
    odd = frames[os.fsdecode(b"\xff1")]
    assert odd.num_objects == 1 and "not valid UTF-8" in odd.warnings[0]


def test_dontcare_placeholders_are_not_bad_dimensions(tmp_path: Path) -> None:
    dc = "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10"
    write_frame(tmp_path, "000001", random_points(), [dc, GOOD_LINE, dc])
    frame = KittiReader(tmp_path).load_frame("000001")
    assert frame.class_names == ["Car"] and frame.extras["label_line"].tolist() == [2]
    assert frame.object_errors == {}


def test_bin_size_not_multiple_of_16(tmp_path: Path) -> None:
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    write_frame(tmp_path, "000002", random_points(), [GOOD_LINE])
    velo = tmp_path / "training/velodyne/000002.bin"
    velo.write_bytes(velo.read_bytes()[:-4])
    ok, failed = _load_all(KittiReader(tmp_path))
    assert list(ok) == ["000001"]
    assert failed["000002"].path == str(velo)
    assert "7996 bytes is not a multiple of 16" in str(failed["000002"])


def test_nan_and_inf_points_are_dropped_with_a_warning(tmp_path: Path) -> None:
    pts = random_points(100)
    pts[[3, 50], 0] = np.nan
    pts[70, 2] = np.inf
    pts[80, 3] = np.nan  # intensity only: the point is kept
    write_frame(tmp_path, "000001", pts, [GOOD_LINE])
    frame = KittiReader(tmp_path).load_frame("000001")
    assert frame.points.shape == (97, 4)
    assert np.all(np.isfinite(frame.points[:, :3]))
    assert len(frame.warnings) == 1 and "dropped 3 of 100 points" in frame.warnings[0]


def test_missing_and_bad_calib(tmp_path: Path) -> None:
    for fid in ("000001", "000002", "000003", "000004", "000005"):
        write_frame(tmp_path, fid, random_points(), [GOOD_LINE])
    calib_dir = tmp_path / "training/calib"
    (calib_dir / "000002.txt").unlink()
    text = format_calib(SIMPLE_CALIB)
    (calib_dir / "000003.txt").write_text("\n".join(l for l in text.splitlines() if not l.startswith("Tr_velo_to_cam")))
    (calib_dir / "000004.txt").write_text(text.replace("R0_rect: 1.000000000000e+00", "R0_rect: one"))
    (calib_dir / "000005.txt").write_text(text.replace("P2: ", "P2: 1 2 ").replace("\n", "\n", 1))
    ok, failed = _load_all(KittiReader(tmp_path))
    assert list(ok) == ["000001"]
    assert "calibration file not found" in str(failed["000002"])
    assert "missing key(s) Tr_velo_to_cam" in str(failed["000003"])
    assert failed["000004"].line == 2 and "calibration R0_rect: expected numbers" in str(failed["000004"])
    assert failed["000005"].line == 1 and "P2: expected 12 numbers (3×4), got 14" in str(failed["000005"])
    assert all(e.path.endswith(f"calib/{k}.txt") for k, e in failed.items())


def test_frames_sharing_a_calibration_get_its_matrices_and_a_bad_copy_still_fails(tmp_path: Path) -> None:
    """The reader derives a calibration's matrices once per file content: frames with the same
    content get exactly read_calib's T_velo_cam and P2 · T_cam_velo (read-only), another content
    its own, and a later file that cannot be parsed fails although an earlier one was good."""
    shared, other = realistic_calib(1), realistic_calib(2)
    for fid, calib in (("000001", shared), ("000002", other), ("000003", shared), ("000004", shared)):
        write_frame(tmp_path, fid, random_points(), [GOOD_LINE], calib)
    text = (tmp_path / "training/calib/000001.txt").read_text()
    (tmp_path / "training/calib/000004.txt").write_text(text.replace("P2: ", "P2: x "))
    reader = KittiReader(tmp_path)
    ok, failed = _load_all(reader)
    assert list(ok) == ["000001", "000002", "000003"] and list(failed) == ["000004"]
    assert "calibration P2: expected numbers" in str(failed["000004"])
    for fid in ("000001", "000002", "000003"):
        calib = read_calib(reader.calib_path(fid))
        velo_from_cam, projection = reader.calibration(reader.calib_path(fid))
        assert np.array_equal(velo_from_cam, calib.T_velo_cam)
        assert np.array_equal(projection, calib.P2 @ calib.T_cam_velo)
        assert np.array_equal(ok[fid].image_view.projection, projection)
        assert not velo_from_cam.flags.writeable and not projection.flags.writeable
    assert reader.calibration(reader.calib_path("000001"))[0] is reader.calibration(reader.calib_path("000003"))[0]
    assert not np.array_equal(ok["000001"].image_view.projection, ok["000002"].image_view.projection)
    np.testing.assert_array_equal(ok["000001"].boxes, ok["000003"].boxes)


def test_a_calibration_rotation_is_tested_by_its_determinant(tmp_path: Path) -> None:
    """R0_rect and Tr_velo_to_cam's rotation need |det| within 0.05 of 1 (KITTI prints 7 digits): a
    scaled, a singular and a huge matrix (whose determinant overflows to NaN) are refused, naming
    the key and the determinant; a slightly non-orthonormal one, as printed, is read."""
    text = format_calib(SIMPLE_CALIB)
    r0 = next(l for l in text.splitlines() if l.startswith("R0_rect:"))
    cases = {
        "000001": "R0_rect: 1.0000001 0 0 0 0.9999999 0 0 0 1.00000005",  # printed, nearly orthonormal
        "000002": "R0_rect: 2 0 0 0 1 0 0 0 1",  # determinant 2
        "000003": "R0_rect: 1 0 0 1 0 0 0 0 1",  # singular
        "000004": "R0_rect: " + " ".join(["1e300"] * 9),  # overflows: NaN
    }
    for fid, line in cases.items():
        write_frame(tmp_path, fid, random_points(), [GOOD_LINE])
        (tmp_path / f"training/calib/{fid}.txt").write_text(text.replace(r0, line))
    ok, failed = _load_all(KittiReader(tmp_path))
    assert list(ok) == ["000001"]
    assert "R0_rect rotation part is not a rotation (determinant 2)" in str(failed["000002"])
    assert "(determinant 0)" in str(failed["000003"])
    assert "(determinant nan)" in str(failed["000004"])


def test_label_without_point_cloud(tmp_path: Path) -> None:
    write_frame(tmp_path, "000001", random_points(), [GOOD_LINE])
    write_frame(tmp_path, "000002", random_points(), [GOOD_LINE])
    (tmp_path / "training/velodyne/000002.bin").unlink()
    ok, failed = _load_all(KittiReader(tmp_path))
    assert list(ok) == ["000001"]
    assert "point cloud not found for label file" in str(failed["000002"])
    assert failed["000002"].path.endswith("velodyne/000002.bin")


def test_not_a_kitti_folder(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match="no velodyne"):
        KittiReader(tmp_path)
    (tmp_path / "velodyne").mkdir()
    with pytest.raises(DatasetError, match="label folder not found"):
        KittiReader(tmp_path)


# --------------------------------------------------------------------------------------------
# Real KITTI files
# --------------------------------------------------------------------------------------------

REAL_COUNTS = {
    "000000": 115384,
    "000001": 120268,
    "000002": 126891,
    "000003": 113110,
    "000004": 115976,
    "000005": 125086,
}


def test_real_frames_read(realdata: Path) -> None:
    reader = open_dataset(realdata / "openpcdet-pr653-kitti", "kitti")
    frames = {f.frame_id: f for ref in reader.list_units() for f in reader.load_unit(ref)}
    assert {k: len(f.points) for k, f in frames.items()} == REAL_COUNTS
    assert frames["000001"].class_names == ["Truck", "Car", "Cyclist"]
    assert frames["000002"].class_names == ["Misc", "Car"]
    assert sum(f.num_objects for f in frames.values()) == 10
    cyc = frames["000001"]
    assert cyc.extras["occluded"].tolist() == [0, 0, 3]
    # Truck: 2D height 32.85 px, not occluded → Moderate; Car: 21.6 px → none; Cyclist: occlusion 3 → none.
    assert cyc.extras["difficulty"].tolist() == [1, -1, -1]
    assert frames["000000"].extras["difficulty"].tolist() == [0]
    np.testing.assert_allclose(frames["000000"].extras["bbox2d"][0], [712.40, 143.00, 810.73, 307.92])
    assert all(not f.warnings for f in frames.values())
    # 000000 comes from another recording day: different calibration.
    c0 = read_calib(realdata / "openpcdet-pr653-kitti/training/calib/000000.txt")
    c1 = read_calib(realdata / "openpcdet-pr653-kitti/training/calib/000001.txt")
    assert c0.P2[0, 0] == pytest.approx(707.0493) and c1.P2[0, 0] == pytest.approx(721.5377)
    assert c0.Tr_imu_to_velo is not None and c0.P0 is not None
    assert not np.allclose(c0.T_cam_velo, c1.T_cam_velo)


def _camera_frame_counts(points: np.ndarray, labels, calib: Calibration, rows: np.ndarray) -> list[int]:
    """Points inside each label box, counted in the rectified camera frame by the KITTI definition."""
    cam = points[:, :3].astype(float) @ calib.T_cam_velo[:3, :3].T + calib.T_cam_velo[:3, 3]
    counts = []
    for r in rows:
        h, w, l = labels.dims_hwl[r]
        d = cam - labels.location[r]
        c, s = np.cos(labels.rotation_y[r]), np.sin(labels.rotation_y[r])
        # Rotation about camera y by ry maps object x to (c, 0, -s); invert it.
        ox = c * d[:, 0] - s * d[:, 2]
        oz = s * d[:, 0] + c * d[:, 2]
        inside = (np.abs(ox) <= l / 2) & (np.abs(oz) <= w / 2) & (d[:, 1] <= 0) & (d[:, 1] >= -h)
        counts.append(int(inside.sum()))
    return counts


def test_real_boxes_hold_the_same_points_as_in_camera_frame(realdata: Path) -> None:
    """The converted LiDAR boxes select what the camera-frame boxes select (up to the ~0.3° tilt)."""
    from labelaudit.infer.crop import points_in_boxes_numpy

    root = realdata / "openpcdet-pr653-kitti"
    reader = KittiReader(root)
    for ref in reader.list_units():
        frame = reader.load_frame(ref.key)
        labels = read_label(reader.label_path(ref.key))
        rows = np.array([i for i, n in enumerate(labels.class_names) if n != "DontCare"])
        expected = _camera_frame_counts(frame.points, labels, read_calib(reader.calib_path(ref.key)), rows)
        got = [len(i) for i in points_in_boxes_numpy(frame.points, frame.boxes)]
        for e, g in zip(expected, got):
            assert e > 0 and abs(g - e) <= max(2, 0.01 * e), (ref.key, expected, got)
        # A wrong yaw convention (+π/2 instead of −π/2) loses many points of the vehicles.
        wrong = frame.boxes.copy()
        wrong[:, 6] += np.pi / 2
        long_boxes = frame.boxes[:, 3] > 3.0  # vehicles; a pedestrian's points stay in a turned box
        wrong_counts = np.array([len(i) for i in points_in_boxes_numpy(frame.points, wrong)])
        assert np.all(wrong_counts[long_boxes] < 0.8 * np.array(got)[long_boxes])


def test_mmdet3d_velodyne_reduced(realdata: Path, tmp_path: Path) -> None:
    src = realdata / "mmdet3d-kitti/tests/data/kitti/training/velodyne_reduced/000000.bin"
    pts = read_velodyne(src)
    assert pts.shape == (800, 4) and pts.dtype == np.float32
    assert 11.0 < pts[:, 0].min() and pts[:, 0].max() < 73.0
    assert read_velodyne(realdata / "mmdet3d-kitti/demo/data/kitti/000008.bin").shape == (17238, 4)
    # As a dataset: the real reduced scan with the real 000000 label and calib, linked into tmp.
    base = tmp_path / "training"
    for sub in ("velodyne_reduced", "label_2", "calib"):
        (base / sub).mkdir(parents=True)
    (base / "velodyne_reduced/000000.bin").symlink_to(src)
    for sub in ("label_2", "calib"):
        (base / sub / "000000.txt").symlink_to(realdata / f"openpcdet-pr653-kitti/training/{sub}/000000.txt")
    reader = KittiReader(tmp_path)
    assert reader.velodyne_dir == "velodyne_reduced"
    frame = reader.load_frame("000000")
    assert frame.points.shape == (800, 4) and frame.class_names == ["Pedestrian"]


def test_pointgnn_result_files(realdata: Path, tmp_path: Path) -> None:
    res = realdata / "pointgnn-kitti-results/results/data"
    lab = read_label(res / "000001.txt")
    assert len(lab) == 2 and lab.class_names == ["Car", "Car"]
    np.testing.assert_allclose(lab.score, [4.10767303327915, 18.881720485661116])
    assert np.all(lab.alpha == 0) and np.all(lab.occluded == -1)
    assert len(read_label(res / "000005.txt")) == 0
    # Read as a dataset (result files in place of label_2): scores come through, empty file → 0 boxes.
    base = tmp_path / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True)
    for fid in ("000001", "000005"):
        (base / "label_2" / f"{fid}.txt").symlink_to(res / f"{fid}.txt")
        for sub, ext in (("velodyne", "bin"), ("calib", "txt")):
            (base / sub / f"{fid}.{ext}").symlink_to(realdata / f"openpcdet-pr653-kitti/training/{sub}/{fid}.{ext}")
    reader = KittiReader(tmp_path)
    f1, f5 = (reader.load_frame(k) for k in ("000001", "000005"))
    np.testing.assert_allclose(f1.extras["score"], lab.score)
    assert f5.num_objects == 0 and f5.boxes.shape == (0, 7) and len(f5.points) == 125086


def test_read_scan_tests_every_part_for_finiteness(tmp_path: Path) -> None:
    """read_scan reads the scan in parts and tests each: a NaN or inf anywhere (the first value,
    a later part, the last value, a reflectance) is seen; the values are the file's, as np.fromfile
    reads them; an empty scan is finite; a missing file gets the given message."""
    rng = np.random.default_rng(4)
    pts = rng.uniform(-50, 50, (50_000, 4)).astype(np.float32)  # 800,000 bytes: four parts
    path = tmp_path / "scan.bin"
    write_velodyne(path, pts)
    got, finite = read_scan(path)
    assert finite and got.dtype == np.float32 and np.array_equal(got, np.fromfile(path, "<f4").reshape(-1, 4))
    for row, col, bad in ((0, 0, np.nan), (33_000, 1, np.inf), (49_999, 3, -np.inf), (16_384, 3, np.nan)):
        broken = pts.copy()
        broken[row, col] = bad
        write_velodyne(path, broken)
        got, finite = read_scan(path)
        assert not finite and np.array_equal(got, broken, equal_nan=True), (row, col)
    write_velodyne(path, np.zeros((0, 4)))
    got, finite = read_scan(path)
    assert finite and got.shape == (0, 4)
    with pytest.raises(DatasetError, match="no scan here"):
        read_scan(tmp_path / "absent.bin", missing="no scan here")
    with pytest.raises(DatasetError, match="point cloud file not found"):
        read_velodyne(tmp_path)  # a folder is no scan

"""KITTI overlaps as the devkit takes them: the rectified camera frame, heights along camera y.

Hand-computed cases where the camera frame and the LiDAR frame disagree (a calibration whose camera
y is tilted against the LiDAR's z), through the geometry functions and through a whole evaluation.
The comparison with the devkit itself is ``scripts/bench_devkit.py`` (docs/eval.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labelaudit.config import RunConfig
from labelaudit.datasets.detections import read_detections
from labelaudit.datasets.gt import load_ground_truth
from labelaudit.datasets.kitti import Calibration, boxes_camera_to_lidar, format_calib, format_label_line
from labelaudit.evaluate.labels import LabelSet
from labelaudit.evaluate.overlap import camera_frame_boxes, kitti_devkit_boxes, pair_overlaps
from labelaudit.evaluate.run import evaluate, overlap_geometry

PITCH = 0.01  # rad: camera y tilted against the LiDAR's −z (KITTI's own are a few mrad)


def pitched_calib(pitch: float = PITCH) -> Calibration:
    """LiDAR (x fwd, y left, z up) → camera (x right, y down, z fwd), the rectified camera pitched by ``pitch`` about its x axis."""
    K = np.array([[720.0, 0, 610.0], [0, 720.0, 175.0], [0, 0, 1]])
    swap = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    c, s = np.cos(pitch), np.sin(pitch)
    r0 = np.array([[1.0, 0, 0], [0, c, -s], [0, s, c]])
    return Calibration(P2=np.c_[K, np.zeros(3)], R0_rect=r0, Tr_velo_to_cam=np.c_[swap, [0.0, 0.08, -0.27]])


def line(loc, hwl, ry, score=None) -> str:
    return format_label_line(
        "Car", 0.0, 0, 0.0, [100.0, 100.0, 200.0, 200.0], hwl, loc, ry, score=score, precision=None
    )


def write_frame(root: Path, gt_lines: list[str], det_lines: list[str], calib: Calibration) -> tuple[Path, Path]:
    for sub in ("label_2", "calib", "velodyne"):
        (root / "training" / sub).mkdir(parents=True, exist_ok=True)
    (root / "training" / "label_2" / "000000.txt").write_text("".join(x + "\n" for x in gt_lines))
    (root / "training" / "calib" / "000000.txt").write_text(format_calib(calib))
    (root / "training" / "velodyne" / "000000.bin").write_bytes(b"")
    dets = root / "dets"
    dets.mkdir(exist_ok=True)
    (dets / "000000.txt").write_text("".join(x + "\n" for x in det_lines))
    return root, dets


def iou_only(root: Path, dets_dir: Path, view: str):
    gt = load_ground_truth(root, "kitti")
    dets = read_detections(dets_dir, gt, view=view)
    n, p = len(gt.boxes), 6 if view == "bev" else 8
    labels = LabelSet(np.full((n, p, p), np.nan), np.ones(n), [""] * n, np.ones(n, bool), view, "none", Path("-"))
    return gt, dets, evaluate(gt, dets, labels, ("Car",), view, RunConfig(), metrics=("iou",), workers=1)


# --------------------------------------------------------------------------- geometry


def test_camera_frame_boxes_height_interval_is_bottom_up_along_camera_y():
    # Same footprint, the detection's bottom 5 cm lower (camera y down): heights [y − h, y] overlap 1.45 of 1.5.
    loc = np.array([[2.0, 1.65, 20.0], [2.0, 1.70, 20.0]])
    hwl = np.array([[1.5, 1.6, 4.0], [1.5, 1.6, 4.0]])
    b = camera_frame_boxes(loc, hwl, [0.3, 0.3])
    np.testing.assert_allclose(b[:, 2] - b[:, 5] / 2, [0.15, 0.20])  # tops at y − h
    np.testing.assert_allclose(b[:, 2] + b[:, 5] / 2, [1.65, 1.70])  # bottoms at y
    _, iou, _ = pair_overlaps(b, b, [1], [0], "3d")
    inter = 4.0 * 1.6 * 1.45
    assert iou[0] == pytest.approx(inter / (2 * 4.0 * 1.6 * 1.5 - inter), abs=1e-12)


def test_camera_frame_rectangle_turns_with_rotation_y():
    # rotation_y = −π/2: the length lies along camera z. A 1 m shift along z leaves (4 − 1)/(4 + 1) of BEV IoU,
    # the same shift along x (across the 1.6 m width) leaves nothing.
    hwl = np.array([[1.5, 1.6, 4.0]] * 3)
    loc = np.array([[0.0, 1.6, 20.0], [0.0, 1.6, 21.0], [1.7, 1.6, 20.0]])
    b = camera_frame_boxes(loc, hwl, [-np.pi / 2] * 3)
    _, iou, _ = pair_overlaps(b, b, [1, 2], [0, 0], "bev")
    assert iou[0] == pytest.approx(3.0 / 5.0, abs=1e-12)
    assert iou[1] == 0.0


def test_lidar_and_camera_frames_disagree_and_the_camera_frame_is_the_devkits():
    # Two equal boxes with the same camera y, 0.7 m apart along camera z (their length). In the camera
    # frame the heights coincide: 3D IoU = BEV IoU = 3.3/4.7 (above 0.7). Pitched by 10 mrad, the LiDAR
    # sees the farther bottom 0.7·sin(0.01) m higher: z overlap (1.5 − 0.007)/1.5, 3D IoU below 0.7.
    calib = pitched_calib()
    loc = np.array([[0.0, 1.6, 20.0], [0.0, 1.6, 20.7]])
    hwl = np.array([[1.5, 1.6, 4.0]] * 2)
    ry = np.array([-np.pi / 2] * 2)
    lidar = boxes_camera_to_lidar(loc, hwl, ry, calib)
    devkit = kitti_devkit_boxes(lidar, [0, 0], [calib])
    np.testing.assert_allclose(
        devkit, camera_frame_boxes(loc, hwl, ry), atol=1e-9
    )  # exact inverse of the label conversion
    _, cam3, _ = pair_overlaps(devkit, devkit, [1], [0], "3d")
    _, lid3, _ = pair_overlaps(lidar, lidar, [1], [0], "3d")
    assert cam3[0] == pytest.approx(3.3 / 4.7, abs=1e-9)
    dz = 0.7 * np.sin(PITCH)
    inter = 3.3 * 1.6 * (1.5 - dz)
    assert lid3[0] == pytest.approx(inter / (2 * 4.0 * 1.6 * 1.5 - inter), abs=2e-5)
    assert lid3[0] < 0.7 < cam3[0]


def test_kitti_devkit_boxes_use_each_frames_calibration_and_refuse_a_missing_one():
    a, b = pitched_calib(0.0), pitched_calib(0.02)
    loc, hwl, ry = np.array([[1.0, 1.6, 15.0]]), np.array([[1.5, 1.6, 4.0]]), np.array([0.4])
    boxes = np.r_[boxes_camera_to_lidar(loc, hwl, ry, a), boxes_camera_to_lidar(loc, hwl, ry, b)]
    out = kitti_devkit_boxes(boxes[::-1], [1, 0], [a, b])  # rows of frames out of order
    np.testing.assert_allclose(out, np.r_[camera_frame_boxes(loc, hwl, ry)].repeat(2, axis=0), atol=1e-9)
    with pytest.raises(ValueError, match="no KITTI calibration"):
        kitti_devkit_boxes(boxes, [0, 1], [a, None])


# --------------------------------------------------------------------------- through the evaluation


def test_eval_3d_takes_the_height_overlap_along_camera_y(tmp_path):
    # The case above as files: the devkit counts the detection at Car 0.7 (3D IoU 0.702); heights
    # compared on LiDAR z (0.6966) would make it a false positive and the AP 0.
    calib = pitched_calib()
    root, dets = write_frame(
        tmp_path,
        [line([0.0, 1.6, 20.0], [1.5, 1.6, 4.0], -np.pi / 2)],
        [line([0.0, 1.6, 20.7], [1.5, 1.6, 4.0], -np.pi / 2, score=0.9)],
        calib,
    )
    gt, d, res = iou_only(root, dets, "3d")
    table = res.detections_table.to_pylist()
    assert table[0]["iou"] == pytest.approx(3.3 / 4.7, abs=1e-9)
    rec = {(r["difficulty"], r["threshold"], r["interp"]): r for r in res.summary["ap"]}
    # one GT: the devkit's 41 recall samples hold one point (precision 1 at sample 0), so R11 is 100/11
    assert (
        rec[("easy", 0.7, "R11")]["ap"] == pytest.approx(100.0 / 11, abs=1e-3)
        and rec[("easy", 0.7, "R11")]["max_recall"] == 1.0
    )
    assert rec[("easy", 0.75, "R11")]["ap"] == 0.0
    # the LiDAR-frame boxes of the same run disagree (what the 3D AP used to be computed on)
    _, lid3, _ = pair_overlaps(d.boxes, gt.boxes, [0], [0], "3d")
    assert lid3[0] < 0.7


def test_eval_bev_is_the_camera_x_z_rectangle(tmp_path):
    # BEV in the camera's ground plane: a detection 1 m higher (camera y) has the same BEV IoU
    # 3/5 as one at the same height, in a pitched frame too; its 3D IoU drops to 0.5/1.5 of height overlap.
    calib = pitched_calib()
    g = line([0.0, 1.6, 20.0], [1.5, 1.6, 4.0], -np.pi / 2)
    d1 = line([0.0, 1.6, 21.0], [1.5, 1.6, 4.0], -np.pi / 2, score=0.9)
    d2 = line([0.0, 0.6, 21.0], [1.5, 1.6, 4.0], -np.pi / 2, score=0.8)
    root, dets = write_frame(tmp_path, [g], [d1, d2], calib)
    gt, d, _ = iou_only(root, dets, "bev")
    gb, db, _ = overlap_geometry(gt, d)
    _, bev, _ = pair_overlaps(db, gb, [0, 1], [0, 0], "bev")
    np.testing.assert_allclose(bev, [0.6, 0.6], atol=1e-9)
    _, iou3, _ = pair_overlaps(db, gb, [0, 1], [0, 0], "3d")
    inter = 3.0 * 1.6 * 0.5
    np.testing.assert_allclose(iou3, [0.6, inter / (2 * 4.0 * 1.6 * 1.5 - inter)], atol=1e-9)


def test_waymo_keeps_its_vehicle_frame_boxes():
    from labelaudit.datasets.gt import GroundTruth, GroundTruthFrame

    box = np.array([[10.0, 1.0, 0.5, 4.5, 2.0, 1.6, 0.2]])
    f = GroundTruthFrame(
        "seg:1",
        box,
        ["Vehicle"],
        np.arange(1),
        np.full(1, np.nan),
        np.full(1, -1),
        np.full(1, np.nan),
        np.ones(1, np.int8),
        np.full(1, 50),
        np.zeros((0, 7)),
        0,
        None,
        np.zeros(3),
        "x",
    )
    gt = GroundTruth.from_frames("waymo-v2", [f])

    class _D:
        boxes = box + 0.1

    g, d, dc = overlap_geometry(gt, _D())
    assert g is gt.boxes and d is _D.boxes and dc is gt.dontcare

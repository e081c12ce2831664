"""LET-3D-AP and LET-3D-APL (``eval --let``): every step by hand, then whole evaluations.

Steps: the camera position (KITTI calibration, Waymo's constant), the longitudinal affinity, the
range alignment and LET-IoU, the Hungarian matching, the score cut-offs, Waymo's AP integration;
then GT fed back (100 / 100), detections pushed 5 % of their range along the line of sight
(LET-AP ≈ 100, LET-APL ≈ 50, IoU AP at 0.7 collapses), on KITTI and Waymo ground truth, and the CLI.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from labelaudit import constants as C
from labelaudit.cli import app
from labelaudit.config import RunConfig
from labelaudit.datasets.detections import Detections, read_detections
from labelaudit.datasets.gt import GroundTruth, GroundTruthFrame, load_ground_truth
from labelaudit.datasets.kitti import Calibration, boxes_lidar_to_camera, format_calib, format_label_line
from labelaudit.evaluate.labels import LabelSet
from labelaudit.evaluate.let import (
    camera_centre,
    let_curves,
    let_min_iou,
    let_origins,
    longitudinal_affinity,
    range_aligned_centres,
    score_cutoffs,
    waymo_average_precision,
)
from labelaudit.evaluate.overlap import pair_overlaps
from labelaudit.evaluate.run import evaluate

runner = CliRunner()


def kitti_calib(p2_tx: float = 0.0) -> Calibration:
    """LiDAR → camera as KITTI (camera 0.27 m ahead of and 0.08 m below the LiDAR); image_2 offset ``p2_tx`` m along camera x."""
    K = np.array([[720.0, 0, 610.0], [0, 720.0, 175.0], [0, 0, 1]])
    swap = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    return Calibration(
        P2=np.c_[K, K @ [p2_tx, 0.0, 0.0]], R0_rect=np.eye(3), Tr_velo_to_cam=np.c_[swap, [0.0, 0.08, -0.27]]
    )


# --------------------------------------------------------------------------- the camera


def test_kitti_camera_centre_from_p2_in_the_lidar_frame():
    # Tr maps LiDAR x to camera z and LiDAR −z to camera y, with t = (0, 0.08, −0.27): the rectified
    # camera's origin is at LiDAR (0.27, 0, 0.08). P2 = K·[I | (0.06, 0, 0)] puts image_2's centre at
    # camera x = −0.06, i.e. LiDAR y = +0.06.
    np.testing.assert_allclose(camera_centre(kitti_calib()), [0.27, 0.0, 0.08], atol=1e-12)
    np.testing.assert_allclose(camera_centre(kitti_calib(0.06)), [0.27, 0.06, 0.08], atol=1e-12)


def test_waymo_and_av2_cameras_are_constants_and_kitti_needs_calibration():
    np.testing.assert_allclose(let_origins("waymo-v2", [None, None]), [[1.43, 0.0, 2.18]] * 2)
    np.testing.assert_allclose(let_origins("waymo-v1", [None]), [C.EVAL_LET_WAYMO_CAMERA])
    np.testing.assert_allclose(let_origins("av2", [None]), [C.EVAL_LET_AV2_CAMERA])
    np.testing.assert_allclose(let_origins("kitti", [kitti_calib(), kitti_calib(0.06)])[:, 1], [0.0, 0.06], atol=1e-12)
    with pytest.raises(ValueError, match="no calibration"):
        let_origins("kitti", [None])
    with pytest.raises(ValueError, match="no camera position"):
        let_origins("nuscenes", [None])


# --------------------------------------------------------------------------- affinity and alignment


def test_longitudinal_affinity_by_hand():
    G = np.array(
        [[10.0, 0, 0], [10.0, 0, 0], [10.0, 0, 0], [3.0, 0, 0], [3.0, 0, 0], [10.0, 0, 0], [10.0, 0, 0], [0.0, 0, 0]]
    )
    P = np.array(
        [
            [10.0, 0, 0],  # exact: a = 1
            [10.5, 0, 0],  # 0.5 m long of 1.0 m tolerance (10 % of 10 m): a = 0.5
            [10.0, 3.0, 0],  # lateral error only: G·P/r = 10, a = 1
            [3.25, 0, 0],  # near: tolerance is the 0.5 m floor, 0.25 m error: a = 0.5
            [2.0, 0, 0],  # 1 m short of a 0.5 m tolerance: a = 0
            [-10.0, 0, 0],  # behind the camera: e = 20 m, a = 0
            [9.2, 0, 0],  # 0.8 m short: a = 0.2
            [0.2, 0, 0],  # GT at the camera: r = ε, tolerance 0.5 m, e ≈ 0: a = 1
        ]
    )
    np.testing.assert_allclose(
        longitudinal_affinity(G, P), [1.0, 0.5, 1.0, 0.5, 0.0, 0.0, 0.2, 1.0 - 1e-6 / 0.5], atol=1e-9
    )


def test_affinity_falls_with_the_longitudinal_error_and_is_symmetric():
    G = np.array([[20.0, 5.0, 1.0]])
    u = G / np.linalg.norm(G)
    errs = [0.0, 0.5, 1.0, 1.5, 2.0, 3.0]
    near = [longitudinal_affinity(G, G + e * u)[0] for e in errs]
    far = [longitudinal_affinity(G, G - e * u)[0] for e in errs]
    assert near == sorted(near, reverse=True) and near[0] == 1.0 and near[-1] == 0.0
    np.testing.assert_allclose(near, far, atol=1e-12)
    tol = 0.1 * np.linalg.norm(G)
    np.testing.assert_allclose(near[2], 1 - 1.0 / tol, atol=1e-12)


def test_range_alignment_moves_the_prediction_along_its_line_of_sight_to_the_gt():
    G = np.array([[10.0, 0, 0], [20.0, 4.0, 1.0]])
    P = np.array([[10.0, 2.0, 0], [21.0, 4.2, 1.05]])  # second: 5 % farther on the same ray
    A = range_aligned_centres(G, P)
    np.testing.assert_allclose(A[0], (100.0 / 104.0) * P[0], atol=1e-12)  # (G·P / |P|²)·P
    np.testing.assert_allclose(A[1], G[1], atol=1e-12)  # on the GT's own ray: back onto the GT
    # the aligned point is the foot of the perpendicular from G on the ray of P
    assert abs(np.dot(G[0] - A[0], P[0])) < 1e-12


def test_let_iou_of_a_pushed_box_is_one_and_its_plain_iou_collapses():
    origin = np.array([1.43, 0.0, 2.18])
    gt = np.array([[30.0, 8.0, 0.9, 4.5, 2.0, 1.7, 0.3]])
    G = gt[:, :3] - origin
    det = gt.copy()
    det[:, :3] = origin + 1.05 * G  # pushed 5 % of its range along the line of sight
    aligned = det.copy()
    aligned[:, :3] = origin + range_aligned_centres(G, det[:, :3] - origin)
    _, let_iou, _ = pair_overlaps(aligned, gt, [0], [0], "3d")
    _, iou, _ = pair_overlaps(det, gt, [0], [0], "3d")
    assert let_iou[0] == pytest.approx(1.0, abs=1e-9)
    assert iou[0] < 0.5
    assert longitudinal_affinity(G, 1.05 * G)[0] == pytest.approx(0.5, abs=1e-9)


def test_let_iou_thresholds():
    assert let_min_iou("Car") == let_min_iou("vehicle") == 0.5
    assert let_min_iou("Pedestrian") == let_min_iou("Cyclist") == 0.3


# --------------------------------------------------------------------------- AP integration


def test_waymo_average_precision_by_hand():
    # one point (recall 1, precision 1): padded every 0.05 down to 0, area 1
    assert waymo_average_precision([1.0], [1.0]) == pytest.approx(1.0)
    # precision 0.5 at recall 1: recall 0's precision 1 is overridden by the next point's, area 0.5
    assert waymo_average_precision([0.5], [1.0]) == pytest.approx(0.5)
    # two cut-offs: (p 1, r 0.5) and (p 0.5, r 1). From recall 1 down: 0.5 at 1, 0.95 … 0.55 padded at 0.5,
    # then 1 at 0.5 and below: area = 0.5·0.5 (the stretch 1 → 0.55 at 0.5, and 0.55 → 0.5 a trapezoid 0.5 → 1)
    expected = 0.45 * 0.5 + 0.5 * 0.05 * (0.5 + 1.0) + 0.5 * 1.0
    assert waymo_average_precision([1.0, 0.5], [0.5, 1.0]) == pytest.approx(expected)
    # running maximum: a lower precision at a lower recall does not lower the curve
    assert waymo_average_precision([0.2, 0.8], [0.5, 1.0]) == pytest.approx(0.8)
    # nothing recalled: recall 0 everywhere, area 0
    assert waymo_average_precision([1.0, 1.0], [0.0, 0.0]) == 0.0
    assert waymo_average_precision([], []) == 0.0


def test_waymo_average_precision_gives_the_answers_waymo_tests_its_own_with():
    # the cases of waymo-open-dataset's metrics_utils_test (ComputeMeanAveragePrecision), as numbers
    assert waymo_average_precision([0.1], [0.2], 0.05) == pytest.approx(0.2 * 0.1, abs=1e-6)
    assert waymo_average_precision([0.1, 0.05], [0.2, 1.0], 0.05) == pytest.approx(
        0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05, abs=1e-6
    )
    assert waymo_average_precision([0.1, 0.05], [0.2, 1.0], 1.0) == pytest.approx(
        0.2 * 0.1 + 0.5 * (0.1 + 0.05) * 0.8, abs=1e-6
    )
    # a lower precision at recall 0.4 changes nothing (the running maximum from recall 1 down)
    assert waymo_average_precision([0.1, 0.0, 0.05], [0.2, 0.4, 1.0], 0.05) == pytest.approx(
        0.05 * 0.8 + 0.1 * 0.2 + (0.1 - 0.05) * 0.5 * 0.05, abs=1e-6
    )


def test_score_cutoffs_are_hundredths():
    c = score_cutoffs()
    assert len(c) == 101 and c[0] == 0.0 and c[-1] == 1.0 and c[37] == 0.37


# --------------------------------------------------------------------------- matching


def _curves(
    gt_boxes, gt_cls, det_boxes, det_cls, scores, origin=(0.0, 0.0, 0.0), frames=None, det_frames=None, counted=None
):
    n, m = len(gt_boxes), len(det_boxes)
    gf = np.zeros(n, np.int64) if frames is None else np.asarray(frames)
    df = np.zeros(m, np.int64) if det_frames is None else np.asarray(det_frames)
    nf = int(max(gf.max(initial=0), df.max(initial=0))) + 1
    cnt = np.ones((1, n), bool) if counted is None else np.asarray(counted)
    return let_curves(
        np.asarray(gt_boxes, float),
        gf,
        gt_cls,
        cnt,
        np.ones(n, bool),
        np.asarray(det_boxes, float),
        df,
        det_cls,
        np.asarray(scores, float),
        np.tile(np.asarray(origin, float), (nf, 1)),
        sorted(set(gt_cls) | set(det_cls)),
    )


def test_hungarian_maximises_the_sum_where_greedy_by_score_would_not():
    # Two cars on one line of sight, at 20 m and 22.5 m (camera at the origin). Detection A (score
    # 0.9) lies between them at 21.25 m, B (0.8) on the far car. Range alignment makes every LET-IoU 1,
    # so the weights are the affinities: A–near 1 − 1.25/2 = 0.375, A–far 1 − 1.25/2.25 = 0.444,
    # B–far 1, B–near 0 (2.5 m off a 2 m tolerance). Taking pairs by score (A to its best, the far
    # car) would leave B unmatched; the Hungarian matching takes A–near and B–far (1.375 > 0.444).
    g1 = [20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    g2 = [22.5, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    a = [21.25, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    cur = _curves([g1, g2], ["Car", "Car"], [a, g2], ["Car", "Car"], [0.9, 0.8])[("Car", 0)]
    cut = score_cutoffs()
    low, mid = cut <= 0.8, (cut > 0.8) & (cut <= 0.9)
    np.testing.assert_array_equal(cur.tp[low], 2)
    np.testing.assert_allclose(cur.sum_affinity[low], 0.375 + 1.0, atol=1e-9)
    np.testing.assert_array_equal(cur.tp[mid], 1)  # A alone: the far car, its better pair
    np.testing.assert_allclose(cur.sum_affinity[mid], 1 - 1.25 / 2.25, atol=1e-9)
    np.testing.assert_array_equal(cur.tp[cut > 0.9], 0)
    np.testing.assert_array_equal(cur.fp, 0)
    assert cur.ap == pytest.approx(100.0)


def test_no_match_below_the_let_iou_threshold_or_without_affinity_or_across_classes():
    g = [20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    side = [20.0, 1.5, 0.0, 4.0, 2.0, 1.5, 0.0]  # lateral 1.5 m: LET-IoU 0.25/1.75 of the width... below 0.5
    far = [23.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]  # 3 m long of a 2 m tolerance: a = 0 although LET-IoU is 1
    cur = _curves([g], ["Car"], [side, far, g], ["Car", "Car", "Pedestrian"], [0.9, 0.9, 0.9])
    assert cur[("Car", 0)].tp.max() == 0 and cur[("Car", 0)].fp[0] == 2 and cur[("Car", 0)].fn[0] == 1
    assert cur[("Pedestrian", 0)].tp.max() == 0 and cur[("Pedestrian", 0)].num_gt == 0
    # a pedestrian needs LET-IoU 0.3 only: a pedestrian shifted sideways by a third of its width matches
    p = [10.0, 0.0, 0.0, 0.8, 0.6, 1.7, 0.0]
    q = [10.0, 0.2, 0.0, 0.8, 0.6, 1.7, 0.0]  # IoU 0.4/0.8 = 0.5 ≥ 0.3
    assert _curves([p], ["Pedestrian"], [q], ["Pedestrian"], [0.5])[("Pedestrian", 0)].tp[0] == 1


def test_matching_is_per_frame_and_score_cutoffs_drop_low_scores():
    g = [20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0]
    cur = _curves([g, g], ["Car", "Car"], [g, g], ["Car", "Car"], [0.25, 0.75], frames=[0, 1], det_frames=[1, 0])[
        ("Car", 0)
    ]
    cut = score_cutoffs()
    np.testing.assert_array_equal(cur.tp, np.where(cut <= 0.25, 2, np.where(cut <= 0.75, 1, 0)))
    np.testing.assert_array_equal(cur.fn, 2 - cur.tp)
    np.testing.assert_array_equal(cur.fp, 0)
    # AP: recall 1 at cut-offs ≤ 0.25, 0.5 up to 0.75, precision 1 throughout
    assert cur.ap == pytest.approx(100.0)


def test_apl_weights_each_true_positive_by_its_affinity():
    g = [[20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [0.0, 30.0, 0.0, 4.0, 2.0, 1.5, 1.0]]
    d = [[21.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [0.0, 30.0, 0.0, 4.0, 2.0, 1.5, 1.0]]  # first 1 m long of 2 m: a = 0.5
    cur = _curves(g, ["Car", "Car"], d, ["Car", "Car"], [0.6, 0.6])[("Car", 0)]
    assert cur.tp[0] == 2 and cur.sum_affinity[0] == pytest.approx(1.5)
    assert cur.ap == pytest.approx(100.0) and cur.apl == pytest.approx(75.0)


def test_a_match_to_a_gt_that_does_not_count_is_a_true_positive_and_its_miss_no_false_negative():
    # Waymo's rule: LEVEL_2 boxes in LEVEL_1 (here the second GT does not count at level 0)
    g = [[20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0], [0.0, 30.0, 0.0, 4.0, 2.0, 1.5, 1.0]]
    counted = np.array([[True, False], [True, True]])
    cur = _curves(g, ["Car", "Car"], [g[1]], ["Car"], [0.6], counted=counted)
    assert cur[("Car", 0)].tp[0] == 1 and cur[("Car", 0)].fn[0] == 1 and cur[("Car", 0)].num_gt == 1
    assert cur[("Car", 1)].tp[0] == 1 and cur[("Car", 1)].fn[0] == 1 and cur[("Car", 1)].num_gt == 2


# --------------------------------------------------------------------------- whole evaluations


def _scene(rng: np.random.Generator, n_frames: int, origin: np.ndarray) -> list[np.ndarray]:
    frames = []
    for _ in range(n_frames):
        k = int(rng.integers(3, 7))
        xs = rng.uniform(8, 60, k)
        ys = np.linspace(-25, 25, k) + rng.uniform(-1, 1, k)  # apart: no two boxes touch
        frames.append(
            np.c_[
                xs,
                ys,
                np.full(k, -0.8),
                rng.uniform(3.8, 4.8, k),
                rng.uniform(1.6, 2.0, k),
                rng.uniform(1.4, 1.7, k),
                rng.uniform(-np.pi, np.pi, k),
            ]
        )
    return frames


def _push(boxes: np.ndarray, origin: np.ndarray, factor: float) -> np.ndarray:
    out = boxes.copy()
    out[:, :3] = origin + factor * (boxes[:, :3] - origin)
    return out


def _waymo_gt(frames: list[np.ndarray], fmt: str = "waymo-v2", cls: str = "Vehicle") -> GroundTruth:
    fs = []
    for i, b in enumerate(frames):
        k = len(b)
        fs.append(
            GroundTruthFrame(
                f"seg:{i}",
                b,
                [cls] * k,
                np.arange(k),
                np.full(k, np.nan),
                np.full(k, -1),
                np.full(k, np.nan),
                np.ones(k, np.int8),
                np.full(k, 100),
                np.zeros((0, 7)),
                0,
                None,
                np.zeros(3),
                "mem",
            )
        )
    return GroundTruth.from_frames(fmt, fs)


def _dets(gt: GroundTruth, frames: list[np.ndarray], cls: str) -> Detections:
    boxes = np.concatenate(frames)
    n = len(boxes)
    off = np.concatenate([[0], np.cumsum([len(b) for b in frames])]).astype(np.int64)
    return Detections(
        det_off=off,
        boxes=boxes,
        class_names=[cls] * n,
        scores=np.full(n, 0.9),
        height=np.full(n, np.nan),
        cov=None,
        cov_on="phi",
        has_cov=np.zeros(n, bool),
        source=["mem"] * n,
        format="parquet",
    )


def _labels(gt: GroundTruth) -> LabelSet:
    n = len(gt.boxes)
    return LabelSet(np.full((n, 8, 8), np.nan), np.ones(n), [""] * n, np.ones(n, bool), "3d", "none", Path("-"))


def _ap(summary, metric, cls, diff, threshold=None):
    rec = [
        r
        for r in summary["ap"]
        if r["metric"] == metric
        and r["class"] == cls
        and r["difficulty"] == diff
        and (threshold is None or r["threshold"] == threshold)
        and r["interp"] in ("waymo", "R40")
    ]
    assert len(rec) == 1, rec
    return rec[0]["ap"]


def test_waymo_gt_fed_back_then_pushed_five_percent_along_the_line_of_sight():
    origin = np.asarray(C.EVAL_LET_WAYMO_CAMERA)
    frames = _scene(np.random.default_rng(0), 60, origin)
    gt = _waymo_gt(frames)
    assert len(gt.boxes) > C.EVAL_RECALL_POINTS  # enough boxes for the devkit's R40 to reach 100
    same = evaluate(
        gt,
        _dets(gt, frames, "Vehicle"),
        _labels(gt),
        ("Vehicle",),
        "3d",
        RunConfig(),
        metrics=("iou",),
        workers=1,
        let=True,
    ).summary
    pushed = evaluate(
        gt,
        _dets(gt, [_push(b, origin, 1.05) for b in frames], "Vehicle"),
        _labels(gt),
        ("Vehicle",),
        "3d",
        RunConfig(),
        metrics=("iou",),
        workers=1,
        let=True,
    ).summary
    for lvl in ("level_1", "level_2"):
        assert _ap(same, "let", "Vehicle", lvl) == pytest.approx(100.0)
        assert _ap(same, "let_apl", "Vehicle", lvl) == pytest.approx(100.0)
        assert _ap(same, "iou", "Vehicle", lvl, 0.7) == pytest.approx(100.0)
        assert _ap(pushed, "let", "Vehicle", lvl) == pytest.approx(100.0)
        assert _ap(pushed, "let_apl", "Vehicle", lvl) == pytest.approx(
            50.0, abs=1.0
        )  # a = 0.5 beyond 5 m (≥ 0.5 nearer)
        assert _ap(pushed, "iou", "Vehicle", lvl, 0.7) < 5.0
    meta = pushed["metric"]["let"]
    assert meta["camera"] == list(C.EVAL_LET_WAYMO_CAMERA) and meta["min_let_iou"] == {"Vehicle": 0.5}
    assert not [m for m in pushed["map"] if m["metric"].startswith("let")]


def test_argoverse2_ground_truth_uses_its_front_camera():
    origin = np.asarray(C.EVAL_LET_AV2_CAMERA)
    frames = _scene(np.random.default_rng(5), 45, origin)
    gt = _waymo_gt(frames, "av2", "REGULAR_VEHICLE")
    s = evaluate(
        gt,
        _dets(gt, [_push(b, origin, 1.05) for b in frames], "REGULAR_VEHICLE"),
        _labels(gt),
        ("REGULAR_VEHICLE",),
        "3d",
        RunConfig(),
        metrics=("iou",),
        workers=1,
        let=True,
    ).summary
    assert _ap(s, "let", "REGULAR_VEHICLE", "all") == pytest.approx(100.0)
    assert _ap(s, "let_apl", "REGULAR_VEHICLE", "all") == pytest.approx(50.0, abs=1.0)
    assert s["metric"]["let"]["camera"] == list(C.EVAL_LET_AV2_CAMERA) and s["metric"]["let"]["min_let_iou"] == {
        "REGULAR_VEHICLE": 0.5
    }


def test_the_camera_position_matters():
    # pushed 5 % along rays from the LiDAR origin instead of Waymo's camera: no longer purely
    # longitudinal for the camera, so LET-APL differs from the on-ray case
    origin = np.asarray(C.EVAL_LET_WAYMO_CAMERA)
    frames = _scene(np.random.default_rng(1), 10, origin)
    gt = _waymo_gt(frames)
    on_ray = evaluate(
        gt,
        _dets(gt, [_push(b, origin, 1.05) for b in frames], "Vehicle"),
        _labels(gt),
        ("Vehicle",),
        "3d",
        RunConfig(),
        metrics=("iou",),
        workers=1,
        let=True,
    ).summary
    off_ray = evaluate(
        gt,
        _dets(gt, [_push(b, np.zeros(3), 1.05) for b in frames], "Vehicle"),
        _labels(gt),
        ("Vehicle",),
        "3d",
        RunConfig(),
        metrics=("iou",),
        workers=1,
        let=True,
    ).summary
    assert _ap(on_ray, "let_apl", "Vehicle", "level_2") != pytest.approx(
        _ap(off_ray, "let_apl", "Vehicle", "level_2"), abs=0.5
    )


def _write_kitti(root: Path, frames: list[np.ndarray], calib: Calibration) -> Path:
    for sub in ("label_2", "calib", "velodyne"):
        (root / "training" / sub).mkdir(parents=True, exist_ok=True)
    for i, b in enumerate(frames):
        loc, dims, ry = boxes_lidar_to_camera(b, calib)
        lines = [
            format_label_line("Car", 0.0, 0, 0.0, [100.0, 100.0, 200.0, 200.0], dims[k], loc[k], ry[k], precision=None)
            for k in range(len(b))
        ]
        (root / "training" / "label_2" / f"{i:06d}.txt").write_text("".join(x + "\n" for x in lines))
        (root / "training" / "calib" / f"{i:06d}.txt").write_text(format_calib(calib))
        (root / "training" / "velodyne" / f"{i:06d}.bin").write_bytes(b"")
    return root


def _write_dets(folder: Path, frames: list[np.ndarray], calib: Calibration) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for i, b in enumerate(frames):
        loc, dims, ry = boxes_lidar_to_camera(b, calib)
        lines = [
            format_label_line(
                "Car", 0.0, 0, 0.0, [100.0, 100.0, 200.0, 200.0], dims[k], loc[k], ry[k], score=0.9, precision=None
            )
            for k in range(len(b))
        ]
        (folder / f"{i:06d}.txt").write_text("".join(x + "\n" for x in lines))
    return folder


def test_kitti_files_fed_back_then_pushed_from_the_image_2_camera(tmp_path):
    calib = kitti_calib(0.06)
    cam = camera_centre(calib)
    frames = _scene(np.random.default_rng(2), 50, cam)
    root = _write_kitti(tmp_path / "kitti", frames, calib)
    gt = load_ground_truth(root, "kitti")
    for name, factor in (("same", 1.0), ("pushed", 1.05)):
        dets = read_detections(
            _write_dets(tmp_path / name, [_push(b, cam, factor) for b in frames], calib), gt, view="3d"
        )
        s = evaluate(gt, dets, _labels(gt), ("Car",), "3d", RunConfig(), metrics=("iou",), workers=1, let=True).summary
        for diff in ("easy", "moderate", "hard"):
            assert _ap(s, "let", "Car", diff) == pytest.approx(100.0)
            assert _ap(s, "let_apl", "Car", diff) == pytest.approx(100.0 if factor == 1.0 else 50.0, abs=1.0)
            assert (
                (_ap(s, "iou", "Car", diff, 0.7) > 99.0) if factor == 1.0 else (_ap(s, "iou", "Car", diff, 0.7) < 5.0)
            )


def _kitti_pushed(tmp_path: Path, seed: int, n_frames: int) -> tuple[Path, Path]:
    """A KITTI layout and its detections pushed 5 % of their range from image_2's camera."""
    calib = kitti_calib()
    cam = camera_centre(calib)
    frames = _scene(np.random.default_rng(seed), n_frames, cam)
    return _write_kitti(tmp_path / "kitti", frames, calib), _write_dets(
        tmp_path / "dets", [_push(b, cam, 1.05) for b in frames], calib
    )


def test_cli_eval_let_json_and_table(tmp_path):
    root, dets = _kitti_pushed(tmp_path, 3, 8)
    r = runner.invoke(
        app, ["eval", str(root), str(dets), "--let", "--format", "json", "--workers", "1", "--classes", "Car"]
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    let = [x for x in doc["ap"] if x["metric"] in ("let", "let_apl")]
    assert {(x["metric"], x["difficulty"]) for x in let} == {
        (m, d) for m in ("let", "let_apl") for d in ("easy", "moderate", "hard")
    }
    assert all(x["interp"] == "waymo" and x["threshold"] == 0.5 and x["view"] == "3d" for x in let)
    r2 = runner.invoke(app, ["eval", str(root), str(dets), "--let", "--workers", "1", "--classes", "Car", "-q"])
    assert r2.exit_code == 0, r2.output
    assert "LET-AP" in r2.stdout and "LET-APL" in r2.stdout
    r3 = runner.invoke(app, ["eval", str(root), str(dets), "--format", "json", "--workers", "1", "--classes", "Car"])
    assert not [x for x in json.loads(r3.stdout)["ap"] if x["metric"].startswith("let")]  # only with --let


def test_eval_dir_with_let_is_read_by_the_report(tmp_path):
    from labelaudit.viz.evalsection import read_eval_dir
    from labelaudit.viz.objects import ViewError

    root, dets = _kitti_pushed(tmp_path, 4, 6)
    out = tmp_path / "ev"
    r = runner.invoke(
        app, ["eval", str(root), str(dets), "--let", "-o", str(out), "--workers", "1", "--classes", "Car", "-q"]
    )
    assert r.exit_code == 0, r.output
    sec = read_eval_dir(out)
    rows = {r["metric"]: r for r in sec.ap_rows if r["class"] == "Car"}
    assert rows["let"]["threshold"] == 0.5 and rows["iou"]["threshold"] == 0.7
    assert [c["ap"] for c in rows["let"]["cells"]] == [100.0] * 3 and [c["ap"] for c in rows["let_apl"]["cells"]] == [
        pytest.approx(50.0, abs=1.0)
    ] * 3
    doc = json.loads((out / "summary.json").read_text())
    next(x for x in doc["ap"] if x["metric"] == "let")["interp"] = "R40"  # LET is not sampled like the devkit
    (out / "summary.json").write_text(json.dumps(doc))
    with pytest.raises(ViewError, match=r"interp must be waymo for metric let"):
        read_eval_dir(out)

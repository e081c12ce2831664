"""The KITTI devkit's rules (evaluate_object.cpp), one test per rule, and AP from hand-computed PR curves.

Overlaps are given directly (a detection × GT matrix per frame), so each rule is seen in isolation.
"""

from __future__ import annotations

import numpy as np
import pytest

from labelaudit import constants as C
from labelaudit.datasets.waymo_common import waymo_level
from labelaudit.evaluate.ap import ap_r11, ap_r40, precision_curve
from labelaudit.evaluate.matching import (
    FrameBlocks,
    assign,
    first_pass,
    kitti_ignored_det,
    kitti_ignored_gt,
    recall_thresholds,
    second_pass,
    waymo_ignored_gt,
)
from labelaudit.evaluate.overlap import pair_overlaps


def evaluate_cell(frames, min_overlap=0.7):
    """frames: list of dicts with ov (D, K), gt_ign (K,), det_ign (D,), score (D,), optional dc (D, M).

    Returns (curve, n_gt, outcome codes at score threshold -inf, matched GT rows)."""
    ov = np.concatenate([np.asarray(f["ov"], float).reshape(-1) for f in frames])
    gi = np.concatenate([np.asarray(f["gt_ign"], np.int8) for f in frames])
    di = np.concatenate([np.asarray(f["det_ign"], np.int8) for f in frames])
    sc = np.concatenate([np.asarray(f["score"], float) for f in frames])
    dcs = [np.asarray(f.get("dc", np.zeros((len(f["score"]), 0))), float) for f in frames]
    blocks = FrameBlocks.build(
        [len(f["gt_ign"]) for f in frames],
        [len(f["score"]) for f in frames],
        [d.shape[1] for d in dcs],
        np.concatenate([d.reshape(-1) for d in dcs]) if dcs else np.zeros(0),
    )
    v, n_gt = first_pass(blocks, ov, gi, di, sc, min_overlap)
    ths = recall_thresholds(v, n_gt)
    tp, fp, fn = second_pass(blocks, ov, gi, di, sc, min_overlap, ths)
    outcome, matched = assign(blocks, ov, gi, di, sc, min_overlap)
    return precision_curve(tp, fp, fn, ths), n_gt, outcome, matched


def frame(ov, gt_ign=None, det_ign=None, score=None, dc=None):
    ov = np.asarray(ov, float)
    d, k = ov.shape
    f = {
        "ov": ov,
        "gt_ign": np.zeros(k) if gt_ign is None else gt_ign,
        "det_ign": np.zeros(d) if det_ign is None else det_ign,
        "score": np.linspace(1.0, 0.5, d) if score is None else score,
    }
    if dc is not None:
        f["dc"] = np.asarray(dc, float)
    return f


# --------------------------------------------------------------------------- AP from hand-computed curves


def test_ap_small_case_by_hand():
    # 4 GT; detections by score: 0.9 TP, 0.8 FP, 0.7 TP, 0.6 TP, GT 4 missed.
    # Pass 1: TP scores [0.9, 0.7, 0.6], 4 GT. With fewer than 40 GT every TP is one recall sample:
    # thresholds [0.9, 0.7, 0.6] → precision 1, 2/3, 3/4 → interpolated 1, 3/4, 3/4, 0, …
    ov = np.array([[0.9, 0, 0, 0], [0, 0, 0, 0], [0, 0.8, 0, 0], [0, 0, 0.75, 0]])
    curve, n_gt, outcome, _ = evaluate_cell([frame(ov, score=[0.9, 0.8, 0.7, 0.6])])
    assert n_gt == 4
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.7, 0.6])
    np.testing.assert_allclose(curve.raw_precision, [1, 2 / 3, 3 / 4])
    np.testing.assert_allclose(curve.recall, [0.25, 0.5, 0.75])
    np.testing.assert_allclose(curve.precision[:4], [1, 0.75, 0.75, 0])
    assert curve.ap_r40 == pytest.approx((0.75 + 0.75) / 40 * 100)  # samples 1 … 40
    assert curve.ap_r11 == pytest.approx(1.0 / 11 * 100)  # samples 0, 4, …, 40
    assert outcome.tolist() == [1, 0, 1, 1]


def test_ap_forty_gt_with_twenty_false_positives_by_hand():
    # 40 GT, 40 TPs with scores 1.00, 0.99, …, 0.61 and 20 FPs scored between TP 20 and TP 21.
    # Each TP is a recall sample; precision is 1 for the first 20, then (i+1)/(i+21), which rises
    # to 40/60, so the interpolated curve is 1 (samples 0–19), 2/3 (20–39) and 0 at sample 40.
    k = 40
    tp_scores = 1.0 - np.arange(k) / 100
    fp_scores = np.linspace(tp_scores[19] - 0.001, tp_scores[20] + 0.001, 20)
    ov = np.zeros((k + 20, k))
    ov[np.arange(k), np.arange(k)] = 0.8
    curve, n_gt, _, _ = evaluate_cell([frame(ov, score=np.r_[tp_scores, fp_scores])])
    assert n_gt == 40 and len(curve.thresholds) == 40
    want = np.r_[np.ones(20), np.full(20, 2 / 3), 0.0]
    np.testing.assert_allclose(curve.precision, want)
    assert curve.ap_r40 == pytest.approx((19 + 20 * 2 / 3) / 40 * 100)
    assert curve.ap_r11 == pytest.approx((5 + 5 * 2 / 3) / 11 * 100)


@pytest.mark.parametrize("n_gt, ap", [(2, 2.5), (40, 97.5), (41, 100.0), (100, 100.0)])
def test_perfect_detections_reach_ap_100_only_with_more_than_40_gt(n_gt, ap):
    # The devkit's recall sampling: with n ≤ 40 GT only n samples are filled (the rest stay 0).
    ov = np.eye(n_gt) * 0.95
    curve, _, _, _ = evaluate_cell([frame(ov, score=np.ones(n_gt))])
    assert curve.ap_r40 == pytest.approx(ap)


def test_recall_thresholds_sample_every_fortieth_of_recall():
    # 200 GT all detected with distinct scores: thresholds are taken near recall 0, 1/40, …, 1.
    scores = np.linspace(1, 0.001, 200)
    ths = recall_thresholds(scores, 200)
    assert len(ths) == C.EVAL_RECALL_POINTS
    ranks = np.searchsorted(-scores, -ths) + 1  # how many TPs score at least the threshold
    np.testing.assert_allclose(ranks / 200, np.r_[1 / 200, np.arange(1, 41) / 40], atol=1 / 200 + 1e-12)


def test_ap_helpers():
    p = np.r_[np.ones(21), np.zeros(20)]
    assert ap_r40(p) == pytest.approx(50.0)
    assert ap_r11(p) == pytest.approx(6 / 11 * 100)
    assert ap_r40(np.ones(41)) == ap_r11(np.ones(41)) == 100.0


# --------------------------------------------------------------------------- devkit rules, one per test


def test_rule_min_overlap_is_strict():
    # overlap > MIN_OVERLAP: exactly 0.7 is not a match (FP + FN), just above is.
    curve, _, outcome, _ = evaluate_cell([frame([[0.7]], score=[1.0])])
    assert outcome.tolist() == [0] and curve.max_recall == 0
    curve, _, outcome, _ = evaluate_cell([frame([[0.7000001]], score=[1.0])])
    assert outcome.tolist() == [1] and curve.max_recall == 1


def test_rule_duplicates_one_true_positive_the_rest_false():
    # Three detections on one GT: with every detection counted, one TP (pass 2 picks the largest
    # overlap) and two FPs.
    curve, _, outcome, matched = evaluate_cell([frame([[0.8], [0.95], [0.9]], score=[0.9, 0.5, 0.7])])
    assert outcome.tolist() == [0, 1, 0] and matched.tolist() == [-1, 0, -1]
    # The PR curve is sampled only at the scores of pass-1 true positives (here 0.9, the highest-
    # scoring candidate), so duplicates scoring lower never lower the precision.
    np.testing.assert_allclose(curve.thresholds, [0.9])
    np.testing.assert_allclose(curve.raw_precision, [1.0])
    # A duplicate does count when it scores at least a later threshold: GT A has det 0 (overlap
    # 0.95, score 0.9) and det 1 (0.8, 0.95), GT B det 2 (0.9, 0.85). Pass 1 gives thresholds
    # 0.95 (det 1) and 0.85 (det 2); at 0.85 pass 2 matches A to det 0 (larger overlap), so det 1
    # becomes an FP: precision 1 then 2/3.
    curve, _, _, _ = evaluate_cell([frame([[0.95, 0.0], [0.8, 0.0], [0.0, 0.9]], score=[0.9, 0.95, 0.85])])
    np.testing.assert_allclose(curve.thresholds, [0.95, 0.85])
    np.testing.assert_allclose(curve.raw_precision, [1.0, 2 / 3])


def test_rule_pass1_takes_highest_score_pass2_largest_overlap():
    # GT 0 overlaps det a (0.95, score 0.6) and det b (0.75, score 0.9).
    # Pass 1 (recall thresholds) takes the highest score: threshold 0.9.
    # Pass 2 at that threshold only sees b (a scores lower) → TP. So precision 1 at recall 1.
    ov = [[0.95], [0.75]]
    curve, _, outcome, matched = evaluate_cell([frame(ov, score=[0.6, 0.9])])
    np.testing.assert_allclose(curve.thresholds, [0.9])
    np.testing.assert_allclose(curve.raw_precision, [1.0])
    # With every detection counted (threshold −∞) pass 2 matches the larger overlap a, b is FP.
    assert outcome.tolist() == [1, 0] and matched.tolist() == [0, -1]


def test_rule_score_threshold_ignores_lower_detections():
    # At a threshold, lower-scoring detections are neither TP nor FP.
    ov = [[0.9, 0.0], [0.0, 0.0], [0.0, 0.9]]
    curve, n_gt, _, _ = evaluate_cell([frame(ov, score=[0.9, 0.8, 0.1])])
    assert n_gt == 2
    np.testing.assert_allclose(curve.thresholds, [0.9, 0.1])
    assert curve.tp.tolist() == [1, 2] and curve.fp.tolist() == [0, 1] and curve.fn.tolist() == [1, 0]


def test_rule_ignored_gt_absorbs_a_detection():
    # An ignored GT (too hard, or neighbour class): the detection on it is neither TP nor FP,
    # and the GT is not a false negative.
    curve, n_gt, outcome, matched = evaluate_cell([frame([[0.9, 0.0], [0.0, 0.9]], gt_ign=[1, 0], score=[0.95, 0.9])])
    assert n_gt == 1 and outcome.tolist() == [2, 1] and matched.tolist() == [0, 1]
    assert curve.fp.tolist() == [0] and curve.fn.tolist() == [0]


def test_rule_other_classes_are_not_evaluated():
    # gt_ign −1 (other class) cannot take a detection; det_ign −1 (other class) is never FP.
    curve, n_gt, outcome, _ = evaluate_cell(
        [frame([[0.9, 0.0], [0.0, 0.9]], gt_ign=[-1, 0], det_ign=[0, -1], score=[0.95, 0.9])]
    )
    assert n_gt == 1 and outcome.tolist() == [0, 4]
    assert curve.max_recall == 0.0


def test_rule_ignored_detection_used_only_when_no_counted_one_overlaps():
    # Pass 2: an ignored detection (too small) matches only when no counted detection does; then
    # the GT is not a false negative and nothing is a TP.
    _, _, outcome, matched = evaluate_cell([frame([[0.9], [0.8]], det_ign=[1, 0], score=[0.9, 0.8])])
    assert outcome.tolist() == [4, 1] and matched.tolist() == [-1, 0]  # the counted one wins despite less overlap
    curve, n_gt, outcome, matched = evaluate_cell([frame([[0.9]], det_ign=[1], score=[0.9])])
    assert n_gt == 1 and outcome.tolist() == [2] and curve.fn.sum() == 0 and curve.tp.sum() == 0


def test_rule_dontcare_region_removes_a_false_positive():
    # An unmatched detection whose overlap with a DontCare region (over its own area) exceeds the
    # minimum overlap is not a false positive; one that overlaps less still is.
    # (the two unmatched detections score above the TP, so the curve's one threshold counts them)
    f = frame([[0.9], [0.0], [0.0]], score=[0.7, 0.9, 0.8], dc=[[0.0], [0.75], [0.5]])
    curve, _, outcome, _ = evaluate_cell([f])
    assert outcome.tolist() == [1, 3, 0]
    assert curve.tp.tolist() == [1] and curve.fp.tolist() == [1]
    curve, _, _, _ = evaluate_cell([frame([[0.9], [0.0], [0.0]], score=[0.7, 0.9, 0.8])])
    assert curve.fp.tolist() == [2]


def test_dontcare_overlap_is_over_the_detection_area():
    det = np.array([[10.0, 0, 0, 4.0, 2.0, 1.5, 0.0]])
    region = np.array([[10.0, 0, 0, 20.0, 10.0, 3.0, 0.0]])  # far larger than the detection
    _, iou, over = pair_overlaps(det, region, [0], [0], "bev")
    assert over[0] == pytest.approx(1.0) and iou[0] == pytest.approx(8 / 200)


def test_rule_difficulty_filter_kitti():
    # Easy: height > 40, occlusion ≤ 0, truncation ≤ 0.15; Moderate: > 25, ≤ 1, ≤ 0.3; Hard: > 25, ≤ 2, ≤ 0.5.
    names = ["Car"] * 7
    height = np.array([41, 40, 30, 30, 30, 30, 41], float)
    occ = np.array([0, 0, 1, 2, 0, 0, 3])
    trunc = np.array([0.0, 0.0, 0.0, 0.0, 0.3, 0.31, 0.0])
    assert kitti_ignored_gt(names, height, occ, trunc, "Car", 0).tolist() == [0, 1, 1, 1, 1, 1, 1]
    assert kitti_ignored_gt(names, height, occ, trunc, "Car", 1).tolist() == [0, 0, 0, 1, 0, 1, 1]
    assert kitti_ignored_gt(names, height, occ, trunc, "Car", 2).tolist() == [0, 0, 0, 0, 0, 0, 1]
    # the boundary height itself is too small (the devkit ignores height <= MIN_HEIGHT)
    assert kitti_ignored_gt(["Car"], [25.0], [0], [0.0], "Car", 2).tolist() == [1]


def test_rule_neighbour_classes_and_case():
    names = ["Car", "Van", "Truck", "Pedestrian", "Person_sitting", "car", "DontCare", "Cyclist"]
    h, o, t = np.full(8, 100.0), np.zeros(8, int), np.zeros(8)
    assert kitti_ignored_gt(names, h, o, t, "Car", 1).tolist() == [0, 1, -1, -1, -1, 0, -1, -1]
    assert kitti_ignored_gt(names, h, o, t, "Pedestrian", 1).tolist() == [-1, -1, -1, 0, 1, -1, -1, -1]
    assert kitti_ignored_gt(names, h, o, t, "Cyclist", 1).tolist() == [-1, -1, -1, -1, -1, -1, -1, 0]  # no neighbour


def test_rule_neighbour_class_detection_on_a_van_is_not_a_false_positive():
    # A Car detection on a Van (ignored GT for Car) is neither TP nor FP; the Van is no FN.
    names = ["Van", "Car"]
    gi = kitti_ignored_gt(names, np.full(2, 100.0), np.zeros(2, int), np.zeros(2), "Car", 1)
    curve, n_gt, outcome, _ = evaluate_cell([frame([[0.9, 0.0], [0.0, 0.9]], gt_ign=gi, score=[0.9, 0.8])])
    assert n_gt == 1 and outcome.tolist() == [2, 1] and curve.fp.sum() == 0 and curve.fn.sum() == 0


def test_rule_small_detections_are_ignored_whatever_their_class():
    # ignored_det = 1 below the minimum height for any class (the devkit checks height first).
    names = ["Car", "Pedestrian", "Car", "Car"]
    height = np.array([24.9, 20.0, 25.0, 39.99])
    assert kitti_ignored_det(names, height, "Car", 1).tolist() == [1, 1, 0, 0]
    assert kitti_ignored_det(names, height, "Car", 0).tolist() == [1, 1, 1, 1]
    assert kitti_ignored_det(["Pedestrian"], [100.0], "Car", 0).tolist() == [-1]


def test_rule_waymo_levels():
    assert waymo_level(np.array([0, 1, 2, 1, 0]), np.array([100, 6, 100, 5, 0])).tolist() == [1, 1, 2, 2, 2]
    lvl = np.array([1, 2, 1, 2])
    pts = np.array([10, 3, 0, 100])
    names = ["Vehicle", "Vehicle", "Vehicle", "Pedestrian"]
    assert waymo_ignored_gt(names, lvl, pts, "Vehicle", 0).tolist() == [0, 1, 1, -1]  # LEVEL_1
    assert waymo_ignored_gt(names, lvl, pts, "Vehicle", 1).tolist() == [
        0,
        0,
        1,
        -1,
    ]  # LEVEL_2: no-point boxes still ignored


def test_frames_are_independent():
    # A detection in frame 2 never matches a GT of frame 1.
    f1 = frame(np.zeros((0, 1)), score=np.zeros(0))
    f2 = frame([[0.0]], score=[0.9])
    curve, n_gt, outcome, _ = evaluate_cell([f1, f2])
    assert n_gt == 2 and outcome.tolist() == [0] and curve.max_recall == 0


# --------------------------------------------------------------------------- overlaps


def test_pair_overlaps_equal_shapely():
    from labelaudit.core.iou import bev_iou_exact, iou_3d_exact

    rng = np.random.default_rng(3)
    n = 400
    a = np.c_[rng.uniform(-2, 2, (n, 3)), rng.uniform(0.3, 5, (n, 3)), rng.uniform(-4, 4, n)]
    b = np.c_[rng.uniform(-2, 2, (n, 3)), rng.uniform(0.3, 5, (n, 3)), rng.uniform(-4, 4, n)]
    idx = np.arange(n)
    _, iou, _ = pair_overlaps(a, b, idx, idx, "bev")
    _, iou3, _ = pair_overlaps(a, b, idx, idx, "3d")
    np.testing.assert_allclose(iou, [bev_iou_exact(x, y) for x, y in zip(a, b)], atol=1e-12)
    np.testing.assert_allclose(iou3, [iou_3d_exact(x, y) for x, y in zip(a, b)], atol=1e-12)
    assert (iou > 0).mean() > 0.3  # the test sees real intersections
    _, same, _ = pair_overlaps(a, a, idx, idx, "3d")
    np.testing.assert_allclose(same, 1.0, atol=1e-12)


def test_cell_compaction_gives_the_same_counts_and_matches():
    # The passes on a cell's relevant rows only equal the passes on every row (random frames).
    from labelaudit.evaluate.matching import Cell

    rng = np.random.default_rng(0)
    for _ in range(40):
        f = int(rng.integers(1, 6))
        ng, nd, nm = rng.integers(0, 5, f), rng.integers(0, 6, f), rng.integers(0, 3, f)
        ov = rng.uniform(0, 1, int((ng * nd).sum()))
        blocks = FrameBlocks.build(ng, nd, nm, rng.uniform(0, 1, int((nd * nm).sum())))
        gi = rng.integers(-1, 2, int(ng.sum())).astype(np.int8)
        di = rng.integers(-1, 2, int(nd.sum())).astype(np.int8)
        sc = rng.uniform(0, 1, int(nd.sum()))
        cell = Cell.build(blocks, gi, di)
        sub = (cell.blocks, ov[cell.pairs], cell.gt_ign, cell.det_ign, sc[cell.det_rows])
        for t in (0.3, 0.5, 0.7):
            v, n = first_pass(blocks, ov, gi, di, sc, t)
            v2, n2 = first_pass(*sub, t)
            assert n == n2 and np.array_equal(np.sort(v), np.sort(v2))
            ths = recall_thresholds(v, n)
            for a, b in zip(second_pass(blocks, ov, gi, di, sc, t, ths), second_pass(*sub, t, ths)):
                np.testing.assert_array_equal(a, b)
            o1, m1 = assign(blocks, ov, gi, di, sc, t)
            o2, m2 = assign(*sub, t)
            np.testing.assert_array_equal(o1[cell.det_rows], o2)
            assert np.all(o1[di == -1] == 4)
            back = np.where(m2 >= 0, cell.gt_rows[np.maximum(m2, 0)] if len(cell.gt_rows) else -1, -1)
            np.testing.assert_array_equal(m1[cell.det_rows], back)

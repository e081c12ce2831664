"""``labelaudit eval``: JIoU of detections, the whole evaluation, readers, bad input, EVAL_DIR, real data.

The devkit's rules one by one are in tests/test_eval_matching.py.
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from labelaudit import constants as C
from labelaudit.cli import app
from labelaudit.config import RunConfig
from labelaudit.core.iou import bev_iou_exact
from labelaudit.core.posterior import infer_label
from labelaudit.core.spatial import BoxDistribution, jiou, jiou_gt
from labelaudit.datasets.detections import (
    DETECTIONS_COLUMNS,
    DETECTIONS_SCHEMA,
    Detections,
    read_detections,
    write_waymo_objects,
)
from labelaudit.datasets.gt import GroundTruth, GroundTruthFrame, load_ground_truth
from labelaudit.datasets.kitti import Calibration, boxes_lidar_to_camera, format_calib, format_label_line
from labelaudit.evaluate.jiou import pair_jious
from labelaudit.evaluate.labels import LabelSet
from labelaudit.evaluate.overlap import pair_overlaps
from labelaudit.evaluate.run import evaluate, thresholds_for

runner = CliRunner()
CFG = RunConfig()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def kitti_calib() -> Calibration:
    """A KITTI-like calibration: LiDAR (x fwd, y left, z up) → camera (x right, y down, z fwd), camera 0.27 m ahead."""
    K = np.array([[720.0, 0, 610.0], [0, 720.0, 175.0], [0, 0, 1]])
    swap = np.array([[0.0, -1, 0], [0, 0, -1], [1, 0, 0]])
    return Calibration(P2=np.c_[K, np.zeros(3)], R0_rect=np.eye(3), Tr_velo_to_cam=np.c_[swap, [0.0, 0.08, -0.27]])


def label_line(
    cls: str, box, height_px: float = 60.0, occ: int = 0, trunc: float = 0.0, score: float | None = None, calib=None
) -> str:
    loc, dims, ry = boxes_lidar_to_camera(np.asarray(box, float)[None], calib or kitti_calib())
    return format_label_line(
        cls,
        trunc,
        occ,
        0.0,
        [100.0, 100.0, 150.0, 100.0 + height_px],
        dims[0],
        loc[0],
        ry[0],
        score=score,
        precision=None,
    )


def write_kitti(root: Path, frames: dict[str, list[str]], calib: Calibration | None = None) -> Path:
    """A KITTI layout with empty point clouds (eval reads labels; infer then gives prior-only covariances)."""
    for sub in ("label_2", "calib", "velodyne"):
        (root / "training" / sub).mkdir(parents=True, exist_ok=True)
    for fid, lines in frames.items():
        (root / "training" / "label_2" / f"{fid}.txt").write_text("".join(l + "\n" for l in lines))
        (root / "training" / "calib" / f"{fid}.txt").write_text(format_calib(calib or kitti_calib()))
        (root / "training" / "velodyne" / f"{fid}.bin").write_bytes(b"")
    return root


def write_dets(folder: Path, frames: dict[str, list[str]]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for fid, lines in frames.items():
        (folder / f"{fid}.txt").write_text("".join(l + "\n" for l in lines))
    return folder


CAR = [12.0, 1.0, -0.9, 4.0, 1.7, 1.5, 0.1]
CAR2 = [25.0, -4.0, -0.9, 4.2, 1.8, 1.5, -0.2]
VAN = [18.0, 6.0, -0.7, 5.0, 1.9, 2.1, 0.0]


# --------------------------------------------------------------------------- JIoU of detections


def posterior(box, n_points: int, seed: int = 0, model: str = "bev"):
    rng = np.random.default_rng(seed)
    box = np.asarray(box, float)
    cfg = CFG.with_overrides(model=replace(CFG.model, kind=model))
    local = np.c_[
        rng.uniform(-0.5, 0.5, n_points) * box[3],
        rng.choice([-0.5, 0.5], n_points) * box[4],
        rng.uniform(-0.5, 0.5, n_points) * box[5],
    ]
    c, s = np.cos(box[6]), np.sin(box[6])
    pts = np.c_[
        box[0] + c * local[:, 0] - s * local[:, 1], box[1] + s * local[:, 0] + c * local[:, 1], box[2] + local[:, 2]
    ]
    return infer_label(box, pts, "Car", cfg.model)


def random_pairs(n_labels: int, model: str, seed: int = 0):
    rng = np.random.default_rng(seed)
    gts, covs, dets, pg, pd = [], [], [], [], []
    for g in range(n_labels):
        box = np.array([rng.uniform(5, 50), rng.uniform(-10, 10), -1, 4.2, 1.8, 1.5, rng.uniform(-3, 3)])
        post = posterior(box, int(rng.integers(0, 80)), seed=g, model=model)
        gts.append(box)
        covs.append(post.cov)
        for _ in range(2):
            dets.append(
                box
                + np.r_[
                    rng.normal(0, 0.3, 2),
                    rng.normal(0, 0.1),
                    rng.normal(0, 0.2, 2),
                    rng.normal(0, 0.1),
                    rng.normal(0, 0.05),
                ]
            )
            pg.append(g)
            pd.append(len(dets) - 1)
    return np.array(gts), np.array(covs), np.array(dets), np.array(pg), np.array(pd)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_jiou_of_a_deterministic_detection_and_a_certain_label_is_the_iou(model):
    gts, covs, dets, pg, pd = random_pairs(12, model)
    _, iou, _ = pair_overlaps(dets, gts, pd, pg, model)
    tiny = np.repeat(np.eye(covs.shape[1])[None] * 1e-12, len(gts), axis=0)
    J = pair_jious(model, CFG.spatial, gts, tiny, dets, None, "phi", pg, pd, iou, workers=1)
    np.testing.assert_allclose(J, iou, atol=0.01)
    # no covariance at all: the exact IoU
    none = np.full_like(covs, np.nan)
    np.testing.assert_array_equal(
        pair_jious(model, CFG.spatial, gts, none, dets, None, "phi", pg, pd, iou, workers=1), iou
    )


def test_pair_jious_agree_with_spatial_jiou_on_a_finer_grid():
    gts, covs, dets, pg, pd = random_pairs(15, "bev", seed=2)
    _, iou, _ = pair_overlaps(dets, gts, pd, pg, "bev")
    J = pair_jious("bev", CFG.spatial, gts, covs, dets, None, "phi", pg, pd, iou, workers=1)
    fine = replace(CFG.spatial, cells_per_side=192)
    ref = np.array(
        [
            jiou(BoxDistribution.deterministic(dets[j], "bev"), BoxDistribution(gts[g], "bev", covs[g]), fine)
            for g, j in zip(pg, pd)
        ]
    )
    np.testing.assert_allclose(J, ref, atol=0.01)
    assert np.all(J <= iou + 0.01)  # a label's blur only lowers the overlap of a deterministic box
    # a probabilistic detection: the detection's own p_G
    dcov = np.repeat(np.diag([0.04, 0.04, 0.01, 0.01, 0.01, 0.01])[None], len(dets), axis=0)
    Jp = pair_jious("bev", CFG.spatial, gts, covs, dets, dcov, "phi", pg, pd, iou, workers=1)
    refp = np.array(
        [
            jiou(BoxDistribution(dets[j], "bev", dcov[j]), BoxDistribution(gts[g], "bev", covs[g]), fine)
            for g, j in zip(pg, pd)
        ]
    )
    np.testing.assert_allclose(Jp, refp, atol=0.015)


def test_pair_jious_in_worker_processes_equal_in_process():
    gts, covs, dets, pg, pd = random_pairs(6, "bev", seed=4)
    _, iou, _ = pair_overlaps(dets, gts, pd, pg, "bev")
    one = pair_jious("bev", CFG.spatial, gts, covs, dets, None, "phi", pg, pd, iou, workers=1)
    import labelaudit.evaluate.jiou as J

    old = J._MIN_PAIRS_FOR_POOL
    J._MIN_PAIRS_FOR_POOL = 1
    try:
        two = pair_jious("bev", CFG.spatial, gts, covs, dets, None, "phi", pg, pd, iou, workers=2)
    finally:
        J._MIN_PAIRS_FOR_POOL = old
    np.testing.assert_array_equal(one, two)


def test_jiou_falls_faster_towards_the_labels_uncertain_side():
    # A car seen from behind (points only on its rear face): its rear edge is certain, its front
    # edge (and so centre and length) uncertain. Shifting a detection by d towards the uncertain
    # front leaves the certain rear edge and costs more JIoU than shifting it backwards by d,
    # although both shifts have the same IoU; JIoU stays below IoU and falls with d.
    box = np.array([20.0, 0.0, -0.9, 4.0, 1.8, 1.5, 0.0])
    rng = np.random.default_rng(0)
    n = 60
    pts = np.c_[np.full(n, 18.0) + rng.normal(0, 0.02, n), rng.uniform(-0.9, 0.9, n), rng.uniform(-1.6, -0.2, n)]
    post = infer_label(box, pts, "Car", CFG.model)
    assert post.std_box["length"] > 3 * post.std_box["width"]
    shifts = np.array([0.1, 0.2, 0.3, 0.5])
    dets = np.concatenate([np.c_[box[0] + s * shifts, np.repeat(box[None, 1:], len(shifts), 0)] for s in (+1, -1)])
    k = len(dets)
    _, iou, _ = pair_overlaps(dets, box[None], np.arange(k), np.zeros(k, int), "bev")
    J = pair_jious(
        "bev", CFG.spatial, box[None], post.cov[None], dets, None, "phi", np.zeros(k, int), np.arange(k), iou, workers=1
    )
    front, back = J[: len(shifts)], J[len(shifts) :]
    np.testing.assert_allclose(iou[: len(shifts)], iou[len(shifts) :])
    assert np.all(front < back)
    assert np.all(J < iou)
    assert np.all(np.diff(front) < 0) and np.all(np.diff(back) < 0)


def test_jiou_of_the_label_box_itself_is_its_jiou_gt():
    gts, covs, _, _, _ = random_pairs(10, "bev", seed=5)
    k = len(gts)
    J = pair_jious(
        "bev", CFG.spatial, gts, covs, gts.copy(), None, "phi", np.arange(k), np.arange(k), np.ones(k), workers=1
    )
    ref = np.array(
        [jiou_gt(type("P", (), {"box": b, "model": "bev", "cov": c})(), CFG.spatial) for b, c in zip(gts, covs)]
    )
    np.testing.assert_allclose(J, ref, atol=0.01)


# --------------------------------------------------------------------------- the whole evaluation in memory


def _gt_frame(fid: str, boxes, classes, heights, occ=None, trunc=None) -> GroundTruthFrame:
    k = len(boxes)
    from labelaudit.datasets.kitti import kitti_difficulty

    heights = np.asarray(heights, float)
    occ = np.zeros(k, int) if occ is None else np.asarray(occ)
    trunc = np.zeros(k) if trunc is None else np.asarray(trunc, float)
    bbox = np.c_[np.zeros(k), np.zeros(k), np.zeros(k), heights]
    return GroundTruthFrame(
        fid,
        np.asarray(boxes, float).reshape(k, 7),
        list(classes),
        np.arange(k),
        heights,
        occ,
        trunc,
        kitti_difficulty(bbox, occ, trunc),
        np.full(k, -1),
        np.zeros((0, 7)),
        0,
        kitti_calib(),
        np.zeros(3),
        f"{fid}.txt",
    )


def _dets_like(gt: GroundTruth, boxes, classes, scores, heights, cov=None) -> Detections:
    n = len(scores)
    return Detections(
        gt.gt_off.copy() if n == len(gt.boxes) else np.array([0, n]),
        np.asarray(boxes, float).reshape(n, 7),
        list(classes),
        np.asarray(scores, float),
        np.asarray(heights, float),
        cov,
        "phi",
        np.zeros(n, bool) if cov is None else ~np.isnan(cov).any(axis=(1, 2)),
        [f"det {i}" for i in range(n)],
        "kitti",
    )


@pytest.fixture(scope="module")
def fed_back():
    """15 frames, 3 easy boxes per class each (45 per class), plus moderate-only and hard-only boxes."""
    rng = np.random.default_rng(7)
    sizes = {"Car": (4.0, 1.7, 1.5), "Pedestrian": (0.8, 0.6, 1.7), "Cyclist": (1.8, 0.6, 1.7)}
    frames = []
    for f in range(15):
        boxes, classes, heights, occ = [], [], [], []
        for k, (cls, (l, w, h)) in enumerate(sizes.items()):
            for j in range(4):
                x, y = 8 + 12 * j + rng.uniform(-1, 1), -12 + 9 * k + rng.uniform(-1, 1)
                boxes.append([x, y, -0.9, l, w, h, rng.uniform(-3, 3)])
                classes.append(cls)
                heights.append(60.0 if j < 3 else 30.0)  # the 4th: too small for easy
                occ.append(0 if j < 3 or f % 2 else 2)  # …and, in every other frame, hard only
        frames.append(_gt_frame(f"{f:06d}", boxes, classes, heights, occ))
    gt = GroundTruth.from_frames("kitti", frames)
    covs = np.stack([posterior(b, int(rng.integers(3, 60)), seed=i).cov for i, b in enumerate(gt.boxes)])
    jg = np.array(
        [jiou_gt(type("P", (), {"box": b, "model": "bev", "cov": c})(), CFG.spatial) for b, c in zip(gt.boxes, covs)]
    )
    labels = LabelSet(covs, jg, ["ok"] * len(jg), np.ones(len(jg), bool), "bev", "results", Path("mem"))
    dets = _dets_like(gt, gt.boxes, gt.class_names, np.ones(len(gt.boxes)), gt.height)
    return gt, dets, labels, evaluate(gt, dets, labels, ("Car", "Pedestrian", "Cyclist"), "bev", CFG, workers=1)


def test_ground_truth_fed_back_gives_ap_100(fed_back):
    gt, _, labels, result = fed_back
    recs = result.summary["ap"]
    counted = {(r["class"], r["difficulty"]): r["num_gt"] for r in recs}
    assert min(counted.values()) >= 45 and counted[("Car", "hard")] > counted[("Car", "easy")]
    for r in recs:
        if r["metric"] in ("iou", "jiou_ratio"):
            assert r["ap"] == pytest.approx(100.0), r
    # plain JIoU: a perfect detection scores the label's own JIoU-GT, so AP is 100 exactly up to
    # the smallest JIoU-GT of the counted labels and falls beyond it
    lowest = labels.jiou_gt.min()
    for r in recs:
        if r["metric"] == "jiou" and r["threshold"] < lowest - 0.01:
            assert r["ap"] == pytest.approx(100.0), r
    assert any(r["metric"] == "jiou" and r["ap"] < 100 for r in recs if r["threshold"] > lowest + 0.01)
    t = result.detections_table
    np.testing.assert_allclose(t.column("iou").to_numpy(), 1.0, atol=1e-9)
    np.testing.assert_allclose(t.column("jiou_ratio").to_numpy(), 1.0, atol=0.01)
    np.testing.assert_allclose(t.column("jiou").to_numpy(), t.column("jiou_gt").to_numpy(), atol=0.01)


def test_map_is_the_mean_over_the_thresholds(fed_back):
    result = fed_back[3]
    recs = [
        r
        for r in result.summary["ap"]
        if r["class"] == "Car" and r["difficulty"] == "moderate" and r["metric"] == "jiou" and r["interp"] == "R40"
    ]
    want = np.mean([r["ap"] for r in recs if r["threshold"] in C.EVAL_MAP_THRESHOLDS])
    got = next(
        m
        for m in result.summary["map"]
        if m["class"] == "Car" and m["difficulty"] == "moderate" and m["metric"] == "jiou" and m["interp"] == "R40"
    )
    assert got["map"] == pytest.approx(want, abs=1e-3)
    assert thresholds_for("Car") == list(C.EVAL_MAP_THRESHOLDS)


def test_every_ap_cell_is_one_flat_record(fed_back):
    recs = fed_back[3].summary["ap"]
    keys = {"class", "difficulty", "view", "metric", "threshold", "interp", "ap", "num_gt", "num_det"}
    assert all(keys <= set(r) for r in recs)
    cells = {(r["class"], r["difficulty"], r["metric"], r["threshold"], r["interp"]) for r in recs}
    assert len(cells) == len(recs) == 3 * 3 * 3 * len(C.EVAL_MAP_THRESHOLDS) * 2


def test_mean_overlap_records_by_distance(fed_back):
    s = fed_back[3].summary
    mo, by_class = s["mean_overlap"], s["mean_overlap_by_class"]
    assert {"difficulty", "distance_bin", "metric", "mean", "count"} <= set(mo[0])
    # the contract's records are one per difficulty × bin × metric (pooled over the classes)
    keys = [(r["difficulty"], r["distance_bin"], r["metric"]) for r in mo]
    assert len(keys) == len(set(keys)) and {r["class"] for r in mo} == {"all"}
    assert {r["distance_bin"] for r in mo} == {"all", "0-20", "20-40", "40+"}
    for r in mo + by_class:
        if r["metric"] == "iou" and r["count"]:
            assert r["mean"] == pytest.approx(1.0)
    pooled = {(r["difficulty"], r["distance_bin"], r["metric"]): r["count"] for r in mo}
    summed: dict = {}
    for r in by_class:
        k = (r["difficulty"], r["distance_bin"], r["metric"])
        summed[k] = summed.get(k, 0) + r["count"]
    assert summed == pooled
    allbin = {(r["class"], r["difficulty"], r["metric"]): r["count"] for r in by_class if r["distance_bin"] == "all"}
    per: dict = {}
    for r in by_class:
        if r["distance_bin"] != "all":
            k = (r["class"], r["difficulty"], r["metric"])
            per[k] = per.get(k, 0) + r["count"]
    assert per == allbin


def test_eval_dir_is_read_by_the_report(fed_back, tmp_path):
    # the EVAL_DIR contract, checked by the reader of `labelaudit report --eval`
    from labelaudit.evaluate.output import write_eval_dir
    from labelaudit.viz.evalsection import read_eval_dir

    write_eval_dir(fed_back[3], tmp_path / "ev")
    section = read_eval_dir(tmp_path / "ev")
    assert section.ap_columns == ["easy", "moderate", "hard"]
    assert {row["metric"] for row in section.ap_rows} == {"iou", "jiou", "jiou_ratio"}
    assert all(
        c["ap"] == pytest.approx(100.0) for row in section.ap_rows if row["metric"] == "iou" for c in row["cells"]
    )
    assert {name for name, _ in section.plots} >= {"ap_vs_threshold.png", "pr_curves.png", "mean_overlap_distance.png"}


def test_localisation_noise_lowers_iou_ap_and_jiou_ratio_recovers_part_of_it():
    # Boxes detected with centre noise: AP at 0.7 drops below 100 with IoU; JIoU-ratio (JIoU
    # relative to what the label's own uncertainty allows) is never lower than JIoU.
    rng = np.random.default_rng(1)
    frames = []
    for f in range(20):
        boxes = [[8 + 10 * j, rng.uniform(-5, 5), -0.9, 4.0, 1.7, 1.5, rng.uniform(-3, 3)] for j in range(4)]
        frames.append(_gt_frame(f"{f:06d}", boxes, ["Car"] * 4, [60.0] * 4))
    gt = GroundTruth.from_frames("kitti", frames)
    covs = np.stack([posterior(b, 5, seed=i).cov for i, b in enumerate(gt.boxes)])
    jg = np.array(
        [jiou_gt(type("P", (), {"box": b, "model": "bev", "cov": c})(), CFG.spatial) for b, c in zip(gt.boxes, covs)]
    )
    labels = LabelSet(covs, jg, ["ok"] * len(jg), np.ones(len(jg), bool), "bev", "results", Path("mem"))
    noisy = gt.boxes + np.c_[rng.normal(0, 0.25, (len(gt.boxes), 2)), np.zeros((len(gt.boxes), 5))]
    dets = _dets_like(gt, noisy, gt.class_names, rng.uniform(0.5, 1, len(noisy)), gt.height)
    s = evaluate(gt, dets, labels, ("Car",), "bev", CFG, workers=1).summary
    ap = {
        (r["metric"], r["threshold"]): r["ap"]
        for r in s["ap"]
        if r["difficulty"] == "moderate" and r["interp"] == "R40"
    }
    assert ap[("iou", 0.7)] < 100
    for t in C.EVAL_MAP_THRESHOLDS:
        assert ap[("jiou_ratio", t)] >= ap[("jiou", t)]
        assert ap[("jiou", t)] <= ap[("iou", t)] + 1e-9 or ap[("jiou", t)] - ap[("iou", t)] < 5


# --------------------------------------------------------------------------- on disk, through the CLI


@pytest.fixture()
def tiny_kitti(tmp_path) -> tuple[Path, Path]:
    calib = kitti_calib()
    dontcare_real = label_line("DontCare", [40.0, 10.0, -0.9, 6.0, 6.0, 2.0, 0.0]).replace(
        "DontCare 0.0 0", "DontCare -1 -1"
    )
    data = write_kitti(
        tmp_path / "kitti",
        {
            "000000": [
                label_line("Car", CAR),
                label_line("Van", VAN),
                "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10",
            ],
            "000001": [
                label_line("Car", CAR2),
                label_line("Pedestrian", [9.0, -3.0, -0.9, 0.8, 0.6, 1.7, 1.0]),
                dontcare_real,
            ],
            "000002": [label_line("Car", CAR, height_px=20.0)],
        },
        calib,
    )
    moved = np.array(CAR2) + [0.15, 0.05, 0, 0, 0, 0, 0.02]
    dets = write_dets(
        tmp_path / "dets",
        {
            "000000": [label_line("Car", CAR, score=9.5), label_line("Car", VAN, score=3.0)],
            "000001": [
                label_line("Car", moved, score=4.0),
                label_line("Car", [40.0, 10.0, -0.9, 4.0, 1.8, 1.5, 0.3], score=2.0),
                label_line("Pedestrian", [9.05, -3.0, -0.9, 0.8, 0.6, 1.7, 1.0], score=0.8),
            ],
            "000002": [],
        },
    )
    return data, dets


def test_cli_eval_writes_eval_dir_and_json_equals_summary(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    out = tmp_path / "ev"
    r = invoke("eval", data, dets, "-o", out, "--format", "json", "--workers", "1")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc == json.loads((out / "summary.json").read_text())
    assert {"ap", "mean_overlap", "counts", "dataset", "metric", "map"} <= set(doc)
    assert "no --results: inferring the label uncertainty" in r.stderr
    assert (out / "label-results" / "manifest.json").is_file()
    for name in ("ap_vs_threshold.png", "pr_curves.png", "mean_overlap_distance.png"):
        assert (out / name).stat().st_size > 10_000
    t = pq.read_table(out / "detections.parquet")
    assert t.num_rows == 5
    for col in (
        "frame_id",
        "class_name",
        "score",
        "matched_object_index",
        "iou",
        "jiou",
        "jiou_ratio",
        "jiou_gt",
        "outcome_iou_moderate",
        "outcome_jiou_ratio_hard",
    ):
        assert col in t.column_names
    rows = t.to_pylist()
    assert rows[0]["outcome_iou_moderate"] == "tp" and rows[0]["iou"] == pytest.approx(1.0)
    assert (
        rows[1]["outcome_iou_moderate"] == "ignored" and rows[1]["matched_class"] == "Van"
    )  # Car on a Van: neighbour class
    assert rows[3]["outcome_iou_moderate"] == "dontcare"  # inside the DontCare region with a 3D box
    assert doc["counts"]["dontcare_rows"] == 2 and doc["counts"]["dontcare_regions_3d"] == 1
    assert doc["counts"]["frames"] == 3 and doc["counts"]["detections"] == 5
    assert doc["classes"] == ["Car", "Pedestrian"]  # Cyclist is never detected: not evaluated (devkit)


def test_cli_eval_table_on_stdout_progress_on_stderr(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    r = invoke("eval", data, dets, "--workers", "1", "--classes", "Car")
    assert r.exit_code == 0, r.output
    assert "AP|R40" in r.stdout and "mean overlap" in r.stdout and "JIoU-ratio" in r.stdout
    assert "eval:" in r.stderr and "eval:" not in r.stdout


def test_cli_eval_with_results_equals_without(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    r1 = invoke("eval", data, dets, "-o", tmp_path / "a", "--format", "json", "--workers", "1")
    assert r1.exit_code == 0, r1.output
    r2 = invoke("eval", data, dets, "--results", tmp_path / "a" / "label-results", "--format", "json", "--workers", "1")
    assert r2.exit_code == 0, r2.output
    a, b = json.loads(r1.stdout), json.loads(r2.stdout)
    assert a["ap"] == b["ap"] and a["mean_overlap"] == b["mean_overlap"]
    assert b["labels"]["source"] == "results" and "inferring" not in r2.stderr


def test_results_of_another_dataset_or_config_are_refused(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    res = tmp_path / "res"
    assert invoke("infer", data, "-o", res, "--classes", "all", "-q", "--workers", "1").exit_code == 0
    other = tmp_path / "copy"
    import shutil

    shutil.copytree(data, other)
    r = invoke("eval", other, dets, "--results", res)
    assert r.exit_code == 2 and "do not fit" in r.stderr and "input dataset" in r.stderr
    from labelaudit.config import CONFIG_DIR

    cfg = tmp_path / "c.toml"
    text = (CONFIG_DIR / "kitti.toml").read_text()
    cfg.write_text(re.sub(r"(?m)^sigma = .*$", "sigma = 0.3", text))
    assert cfg.read_text() != text
    r = invoke("eval", data, dets, "--results", res, "--config", cfg)
    assert r.exit_code == 2 and "sigma" in r.stderr
    r = invoke("eval", data, dets, "--results", res, "--metric", "3d")
    assert r.exit_code == 2 and "model" in r.stderr
    ok = invoke("eval", data, dets, "--results", res, "--workers", "1")
    assert ok.exit_code == 0, ok.output


def test_results_without_the_needed_classes_are_refused(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    res = tmp_path / "res"
    assert invoke("infer", data, "-o", res, "--classes", "Car", "-q", "--workers", "1").exit_code == 0
    r = invoke("eval", data, dets, "--results", res)
    assert r.exit_code == 2 and "no results rows" in r.stderr and "Van" in r.stderr  # the neighbour class is needed too
    assert "--classes" in r.stderr


def test_malformed_detection_line_exit_2_names_file_line_field(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    f = dets / "000001.txt"
    lines = f.read_text().splitlines()
    parts = lines[1].split()
    parts[9] = "wide"  # the width column
    lines[1] = " ".join(parts)
    f.write_text("\n".join(lines) + "\n")
    r = invoke("eval", data, dets)
    assert r.exit_code == 2
    assert re.search(r"000001\.txt:2: column 'width': expected a number", r.stderr), r.stderr
    # lenient: the frame is left out and reported
    r = invoke("eval", data, dets, "--lenient", "--format", "json", "--workers", "1")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["counts"]["frames"] == 2 and doc["counts"]["failed_frames"] == 1
    assert "000001.txt:2" in doc["errors"][0]["message"]


def test_missing_score_and_bad_size(tiny_kitti):
    data, dets = tiny_kitti
    (dets / "000002.txt").write_text(label_line("Car", CAR) + "\n")  # 15 columns: no score
    r = invoke("eval", data, dets)
    assert r.exit_code == 2 and "000002.txt:1: field 'score': missing" in r.stderr
    (dets / "000002.txt").write_text(
        label_line("Car", CAR, score=1.0).replace(" 1.5 1.7 4.0 ", " 1.5 -1.7 4.0 ") + "\n"
    )
    r = invoke("eval", data, dets)
    assert r.exit_code == 2 and "000002.txt:1: field 'width': expected a box size > 0" in r.stderr


def test_missing_files_and_unknown_frames_are_counted(tiny_kitti):
    data, dets = tiny_kitti
    (dets / "000002.txt").unlink()
    (dets / "000777.txt").write_text(
        label_line("Car", CAR, score=1.0) + "\n" + label_line("Car", CAR2, score=1.0) + "\n"
    )
    r = invoke("eval", data, dets, "--format", "json", "--workers", "1")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    c = doc["counts"]
    assert c["missing_detection_files"] == 1 and c["unmatched_frames"] == 1 and c["detections_in_unmatched_frames"] == 2
    assert any("000002" in n and "no detection file" in n for n in doc["notes"])
    assert any("000777" in n and "not in the dataset" in n for n in doc["notes"])


def test_no_detections_at_all_is_an_error_and_an_undetected_class_says_so(tiny_kitti):
    data, dets = tiny_kitti
    for f in dets.glob("*.txt"):
        f.write_text("")
    r = invoke("eval", data, dets)
    assert r.exit_code == 2 and "nothing to evaluate" in r.stderr and "no detections at all" in r.stderr
    r = invoke("eval", data, dets, "--classes", "Car", "--format", "json", "--workers", "1")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    rec = next(x for x in doc["ap"] if x["metric"] == "iou" and x["difficulty"] == "moderate")
    assert rec["ap"] == 0.0 and "no detections" in rec["note"]
    assert any("no detections of class Car" in n for n in doc["notes"])


def test_nothing_evaluated_exits_2(tmp_path):
    # Only a GT box too small for every difficulty: nothing counts.
    data = write_kitti(tmp_path / "k", {"000000": [label_line("Car", CAR, height_px=10.0)]})
    dets = write_dets(tmp_path / "d", {"000000": [label_line("Car", CAR, score=1.0)]})
    r = invoke("eval", data, dets, "--workers", "1")
    assert r.exit_code == 2 and "nothing was evaluated" in r.stderr


def test_eval_3d_metric(tiny_kitti, tmp_path):
    data, dets = tiny_kitti
    r = invoke("eval", data, dets, "--metric", "3d", "--format", "json", "--workers", "1", "--classes", "Car")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["metric"]["view"] == "3d" and doc["labels"]["model"] == "3d"
    assert all(x["view"] == "3d" for x in doc["ap"])


# --------------------------------------------------------------------------- detection formats


def test_parquet_schema_is_documented():
    doc = (Path(__file__).resolve().parents[1] / "docs" / "eval.md").read_text()
    for name, _, required, _ in DETECTIONS_COLUMNS:
        assert re.search(rf"\| `{name}` \|[^\n]*\| {'yes' if required else 'no'} \|", doc), name


def _gt_for(tmp_path) -> GroundTruth:
    data = write_kitti(tmp_path / "k", {"000000": [label_line("Car", CAR)], "000001": [label_line("Car", CAR2)]})
    return load_ground_truth(data, "kitti")


def test_parquet_detections_with_cov_and_std(tmp_path):
    gt = _gt_for(tmp_path)
    rows = {"frame_id": ["000000", "000001", "000009"], "class_name": ["Car"] * 3, "score": [0.9, 0.8, 0.7]}
    for k, n in enumerate(("cx", "cy", "cz", "length", "width", "height", "yaw")):
        rows[n] = [CAR[k], CAR2[k], 0.0 if k < 3 else 1.0]
    rows["std_cx"] = [0.1, None, None]
    for n in ("std_cy", "std_length", "std_width", "std_yaw"):
        rows[n] = [0.1, None, None]
    t = pa.table(rows)
    pq.write_table(t, tmp_path / "d.parquet")
    d = read_detections(tmp_path / "d.parquet", gt)
    assert d.format == "parquet" and d.num == 2 and d.unknown_frames == {"000009": 1}
    assert d.has_cov.tolist() == [True, False] and d.cov_on == "box" and d.cov.shape == (2, 5, 5)
    np.testing.assert_allclose(d.boxes[0], CAR)
    assert np.isfinite(d.height).all()  # KITTI: 2D heights projected from the boxes
    bad = t.set_column(t.column_names.index("std_yaw"), "std_yaw", pa.array([None, None, None], pa.float64()))
    pq.write_table(bad, tmp_path / "bad.parquet")
    with pytest.raises(ValueError, match=r"row 0: std columns .* std_yaw missing"):
        read_detections(tmp_path / "bad.parquet", gt)
    cov = t.append_column("cov", pa.array([[0.0] * 36, [1.0] * 35, None], pa.list_(pa.float64())))
    pq.write_table(cov, tmp_path / "cov.parquet")
    with pytest.raises(ValueError, match=r"row 1: field 'cov': expected 6×6 = 36 values"):
        read_detections(tmp_path / "cov.parquet", gt)
    missing = pa.table({"frame_id": ["000000"], "class_name": ["Car"]})
    pq.write_table(missing, tmp_path / "m.parquet")
    with pytest.raises(ValueError, match="missing required column"):
        read_detections(tmp_path / "m.parquet", gt)
    assert set(DETECTIONS_SCHEMA.names) >= set(rows)


def test_waymo_ground_truth_equals_the_readers_and_objects_round_trip(tmp_path):
    from labelaudit.datasets import open_dataset
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    roots = simulate_waymo_dataset(tmp_path / "w", segments=1, frames=2, seed=3)
    gts = {fmt: load_ground_truth(root, fmt) for fmt, root in roots.items()}
    for fmt, gt in gts.items():
        reader = open_dataset(roots[fmt], fmt)
        frames = [f for ref in reader.list_units() for f in reader.load_unit(ref)]
        assert gt.frame_ids == [f.frame_id for f in frames]
        np.testing.assert_array_equal(gt.boxes, np.concatenate([f.boxes for f in frames]))
        assert gt.class_names == [n for f in frames for n in f.class_names]
        np.testing.assert_allclose(
            gt.distance,
            np.concatenate(
                [np.hypot(f.boxes[:, 0] - f.sensor_origin[0], f.boxes[:, 1] - f.sensor_origin[1]) for f in frames]
            ),
        )
    gt = gts["waymo-v2"]
    np.testing.assert_array_equal(gt.boxes, gts["waymo-v1"].boxes)
    types = {"Vehicle": 1, "Pedestrian": 2, "Cyclist": 4}
    keep = [i for i, n in enumerate(gt.class_names) if n in types]
    fids = [gt.frame_ids[f] for f in gt.frame_of_row[keep]]
    path = write_waymo_objects(
        tmp_path / "preds.bin", fids, gt.boxes[keep], [types[gt.class_names[i]] for i in keep], np.full(len(keep), 0.9)
    )
    d = read_detections(path, gt)
    assert d.format == "waymo" and d.num == len(keep) > 0
    np.testing.assert_allclose(d.boxes, gt.boxes[keep], atol=1e-12)
    assert d.class_names == [gt.class_names[i] for i in keep]


def test_kitti_ground_truth_equals_the_reader(tiny_kitti):
    from labelaudit.datasets import open_dataset

    data, _ = tiny_kitti
    gt = load_ground_truth(data, "kitti")
    reader = open_dataset(data, "kitti")
    frames = [reader.load_frame(fid) for fid in gt.frame_ids]
    np.testing.assert_array_equal(gt.boxes, np.concatenate([f.boxes for f in frames]))
    assert [f"{gt.frame_ids[f]}:{i}" for f, i in zip(gt.frame_of_row, gt.object_index)] == [
        o for f in frames for o in f.object_ids
    ]
    np.testing.assert_array_equal(gt.difficulty, np.concatenate([f.extras["difficulty"] for f in frames]))


# --------------------------------------------------------------------------- synthetic detector


def test_synthetic_detector_is_deterministic_and_scores_follow_quality(tmp_path):
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.detector import DetectorSpec, simulate_detections

    root = tmp_path / "sim"
    simulate_dataset(root, frames=6, seed=2, progress=False)
    a = simulate_detections(root, DetectorSpec(probabilistic=True), seed=1)
    texts = {p.name: p.read_text() for p in sorted(a.folder.glob("*.txt"))}
    b = simulate_detections(root, DetectorSpec(probabilistic=True), seed=1, out=tmp_path / "again")
    assert texts == {p.name: p.read_text() for p in sorted(b.folder.glob("*.txt"))}
    assert len(texts) == 6 and a.detections > 0 and a.false_positives_drawn > 0 and a.objects_detected > 0
    gt = load_ground_truth(root, "kitti")
    d = read_detections(a.folder, gt)
    p = read_detections(a.parquet, gt)
    assert d.num == p.num == a.detections and p.probabilistic and not d.probabilistic
    np.testing.assert_allclose(d.boxes, p.boxes, atol=1e-9)  # the KITTI files convert back to the same boxes
    # better boxes get higher scores: IoU with the nearest true box vs score
    from labelaudit.sim.manifest import read_manifest

    m = read_manifest(root).to_pydict()
    true = np.stack(
        [np.asarray(m[f"true_{n}"]) for n in ("cx", "cy", "cz", "length", "width", "height", "yaw")], axis=1
    )
    best = []
    for i in range(d.num):
        fid = gt.frame_ids[d.frame_of_row[i]]
        cand = [j for j, f in enumerate(m["frame_id"]) if f == fid]
        best.append(max((bev_iou_exact(d.boxes[i], true[j]) for j in cand), default=0.0))
    best = np.array(best)
    assert np.corrcoef(best, d.scores)[0, 1] > 0.5


def test_cli_simulate_with_detections_then_eval(tmp_path):
    root = tmp_path / "sim"
    r = invoke("simulate", root, "--frames", "4", "--detections", "--detections-cov", "-q")
    assert r.exit_code == 0, r.output
    assert (
        (root / "detections" / "000003.txt").is_file()
        and (root / "detections.parquet").is_file()
        and "labelaudit eval" in r.stderr
    )
    r = invoke("simulate", tmp_path / "x", "--frames", "2", "--detections-cov", "-q")
    assert r.exit_code == 2 and "--detections" in r.stderr
    # a probabilistic detector: its own distributions against the same boxes as deterministic ones
    assert invoke("infer", root, "-o", tmp_path / "res", "-q", "--workers", "1").exit_code == 0
    out = tmp_path / "ev"
    r = invoke(
        "eval",
        root,
        root / "detections.parquet",
        "--results",
        tmp_path / "res",
        "--classes",
        "Car",
        "-o",
        out,
        "--format",
        "json",
        "--workers",
        "1",
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["counts"]["probabilistic_detections"] == doc["counts"]["detections"] > 0
    assert {x["metric"] for x in doc["ap"]} == {"iou", "jiou", "jiou_ratio"}
    assert {x["metric"] for x in doc["probabilistic_ap"]} == {"jiou_deterministic"}
    rec = doc["probabilistic"][0]
    assert rec["recall_gain"] == pytest.approx(rec["recall_probabilistic"] - rec["recall_deterministic"], abs=1e-6)
    assert (out / "recall_gain.png").stat().st_size > 10_000
    t = pq.read_table(out / "detections.parquet")
    assert "jiou_deterministic" in t.column_names and all(t.column("probabilistic").to_pylist())
    from labelaudit.viz.evalsection import read_eval_dir

    assert any(name == "recall_gain.png" for name, _ in read_eval_dir(out).plots)


# --------------------------------------------------------------------------- real data


@pytest.mark.realdata
def test_real_pointgnn_detections_on_kitti(realdata, tmp_path):
    from shapely.geometry import Polygon

    from labelaudit.datasets.kitti import read_label

    data = realdata / "openpcdet-pr653-kitti"
    dets = realdata / "pointgnn-kitti-results" / "results"
    out = tmp_path / "ev"
    r = invoke("eval", data, dets, "-o", out, "--format", "json", "--workers", "1")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    c = doc["counts"]
    assert (
        c["frames"] == 6 and c["detections"] == 6 and c["missing_detection_files"] == 2
    )  # 000000, 000003 have no results
    assert doc["classes"] == ["Car"]
    t = pq.read_table(out / "detections.parquet").to_pylist()
    matched = [row for row in t if row["matched_object_index"] is not None]
    assert len(matched) == 4  # 000001, 000002 and both cars of 000004
    unmatched = {(row["frame_id"], round(row["score"], 2)) for row in t if row["matched_object_index"] is None}
    assert unmatched == {("000001", 18.88), ("000004", 0.62)}

    # IoU against the matched GT, as the devkit computes it: in the camera frame's x–z plane
    def polygon(l, w, x, z, ry):
        c, s = np.cos(ry), np.sin(ry)
        pts = [(l / 2, w / 2), (l / 2, -w / 2), (-l / 2, -w / 2), (-l / 2, w / 2)]
        return Polygon([(x + c * a + s * b, z - s * a + c * b) for a, b in pts])

    for row in matched:
        g = read_label(data / "training" / "label_2" / f"{row['frame_id']}.txt")
        gi = [i for i, n in enumerate(g.class_names) if n != "DontCare"][row["matched_object_index"]]
        dl = read_label(dets / "data" / f"{row['frame_id']}.txt")
        di = row["det_index"]
        pg = polygon(g.dims_hwl[gi, 2], g.dims_hwl[gi, 1], g.location[gi, 0], g.location[gi, 2], g.rotation_y[gi])
        pd_ = polygon(dl.dims_hwl[di, 2], dl.dims_hwl[di, 1], dl.location[di, 0], dl.location[di, 2], dl.rotation_y[di])
        inter = pg.intersection(pd_).area
        assert row["iou"] == pytest.approx(inter / (pg.area + pd_.area - inter), abs=2e-3)
        assert 0 < row["jiou"] <= row["iou"] + 0.01
    # devkit: 3 Cars count at Moderate (000002, 000003, and the near car of 000004), 2 are found
    mod = next(
        x
        for x in doc["ap"]
        if x["metric"] == "iou" and x["difficulty"] == "moderate" and x["threshold"] == 0.7 and x["interp"] == "R40"
    )
    assert mod["num_gt"] == 3 and mod["max_recall"] == pytest.approx(2 / 3) and mod["ap"] == pytest.approx(2.5)


@pytest.mark.realdata
def test_real_waymo_objects_file(realdata, tmp_path):
    base = realdata / "mmdet3d-waymo" / "tests" / "data" / "waymo" / "waymo_format"
    gt = load_ground_truth(base / "validation" / "val.tfrecord", "waymo-v1")
    d = read_detections(base / "gt.bin", gt)
    assert d.num == 1 and d.class_names == ["Vehicle"] and d.scores[0] == pytest.approx(0.8)
    v = gt.class_names.index("Vehicle")
    assert bev_iou_exact(d.boxes[0], gt.boxes[v]) > 0.95
    r = invoke(
        "eval",
        base / "validation" / "val.tfrecord",
        base / "gt.bin",
        "--format",
        "json",
        "--workers",
        "1",
        "-o",
        tmp_path / "ev",
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["metric"]["difficulties"] == ["level_1", "level_2"] and doc["classes"] == ["Vehicle"]
    rec = next(
        x
        for x in doc["ap"]
        if x["metric"] == "iou" and x["difficulty"] == "level_2" and x["interp"] == "R40" and x["threshold"] == 0.7
    )
    assert rec["num_gt"] == 1 and rec["max_recall"] == 1.0


def test_worker_warm_up_runs():
    from labelaudit.evaluate.warmup import warm_up

    warm_up(strict=True)

"""``eval`` on Argoverse 2: ground truth from annotations.feather, detections in AV2's Feather layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.feather as feather
import pytest
from typer.testing import CliRunner

from labelaudit.cli import app
from labelaudit.datasets import open_dataset
from labelaudit.datasets.detections import detect_detections_format, read_detections, write_av2_detections
from labelaudit.datasets.gt import load_ground_truth
from labelaudit.errors import DetectionsError
from tests.test_av2 import _trimmed_real, make_log


def invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args])


def test_ground_truth_numbers_objects_as_the_reader_does(tmp_path: Path) -> None:
    log = make_log(tmp_path, sweeps=(0,))
    t = feather.read_table(log / "annotations.feather")
    cats = t.column("category").to_pylist()
    cats[0] = None  # left out by the reader: the GT must number the rest the same way
    t = t.set_column(t.schema.get_field_index("category"), "category", pa.array(cats, pa.string()))
    feather.write_feather(t, log / "annotations.feather")
    gt = load_ground_truth(tmp_path, "av2")
    reader = open_dataset(tmp_path, "av2")
    frames = [f for ref in reader.list_units() for f in reader.load_unit(ref)]
    assert gt.frame_ids == [f.frame_id for f in frames]
    for i, f in enumerate(frames):
        rows = slice(gt.gt_off[i], gt.gt_off[i + 1])
        np.testing.assert_array_equal(gt.boxes[rows], f.boxes)
        assert gt.class_names[rows] == f.class_names
        np.testing.assert_array_equal(gt.num_points[rows], f.extras["num_lidar_points_in_box"])
    assert set(gt.difficulty.tolist()) == {1}


def test_bad_label_fails_the_log_naming_the_row(tmp_path: Path) -> None:
    log = make_log(tmp_path)
    t = feather.read_table(log / "annotations.feather")
    w = t.column("width_m").to_pylist()
    w[2] = 0.0
    feather.write_feather(
        t.set_column(t.schema.get_field_index("width_m"), "width_m", pa.array(w)), log / "annotations.feather"
    )
    with pytest.raises(Exception, match=r"annotations.feather: row 2: width_m = 0"):
        load_ground_truth(tmp_path, "av2")
    gt = load_ground_truth(tmp_path, "av2", strict=False)
    assert gt.num_frames == 0 and len(gt.errors) == 1


def _gt_detections(gt, path: Path, shift: float = 0.0, drop: int = 0) -> Path:
    boxes = gt.boxes.copy()
    boxes[:, 0] += shift
    fids = [gt.frame_ids[f] for f in gt.frame_of_row]
    keep = np.arange(len(boxes)) >= drop
    return write_av2_detections(
        path,
        [f for f, k in zip(fids, keep) if k],
        boxes[keep],
        [c for c, k in zip(gt.class_names, keep) if k],
        np.linspace(0.9, 0.5, keep.sum()),
    )


def test_detections_round_trip_and_bad_rows(tmp_path: Path) -> None:
    make_log(tmp_path)
    gt = load_ground_truth(tmp_path, "av2")
    path = _gt_detections(gt, tmp_path / "dets.feather")
    assert detect_detections_format(path) == "av2"
    d = read_detections(path, gt)
    assert d.format == "av2" and d.num == len(gt.boxes)
    np.testing.assert_allclose(d.boxes, gt.boxes, atol=1e-12)
    assert d.class_names == gt.class_names
    # a corrupt row is named (file, row, field, expectation)
    t = feather.read_table(path)
    qw = t.column("qw").to_pylist()
    qw[3] = 0.1
    feather.write_feather(t.set_column(t.schema.get_field_index("qw"), "qw", pa.array(qw)), path)
    with pytest.raises(
        DetectionsError, match=r"dets.feather: row 3: fields qw, qx, qy, qz = \(0.1, .*expected a unit quaternion"
    ):
        read_detections(path, gt)
    lenient = read_detections(path, gt, strict=False)
    assert len(lenient.errors) == 1 and lenient.errors[0]["frame_id"] == gt.frame_ids[gt.frame_of_row[3]]
    feather.write_feather(t.drop_columns(["score"]), path)
    with pytest.raises(DetectionsError, match=r"missing column\(s\) score"):
        read_detections(path, gt)


def test_eval_perfect_beats_shifted_beats_badly_off(tmp_path: Path) -> None:
    make_log(tmp_path / "data", sweeps=(0, 1, 2))
    gt = load_ground_truth(tmp_path / "data", "av2")
    ap: dict[tuple[str, float], float] = {}
    for name, shift in (("perfect", 0.0), ("slight", 0.3), ("bad", 2.5)):  # a 4.5 m car: BEV IoU 1, 0.88, 0.29
        det = _gt_detections(gt, tmp_path / f"{name}.feather", shift=shift)
        r = invoke(
            "eval", tmp_path / "data", det, "--format", "json", "--workers", "1", "--classes", "REGULAR_VEHICLE,BUS"
        )
        assert r.exit_code == 0, r.output
        doc = json.loads(r.stdout)
        assert doc["metric"]["difficulties"] == ["all"]
        for x in doc["ap"]:
            if x["class"] == "REGULAR_VEHICLE" and x["interp"] == "R40" and x["metric"] == "iou":
                assert x["num_gt"] == 3 and x["difficulty"] == "all"
                ap[name, x["threshold"]] = x["ap"]
    assert ap["perfect", 0.9] > 0 and ap["slight", 0.9] == 0.0  # 0.3 m off fails the strict threshold only
    assert ap["slight", 0.7] == ap["perfect", 0.7] > 0
    assert ap["bad", 0.5] == 0.0 < ap["slight", 0.5]


@pytest.mark.realdata
def test_eval_on_the_real_logs(realdata: Path, tmp_path: Path) -> None:
    root = _trimmed_real(realdata, tmp_path)
    gt = load_ground_truth(root, "av2")
    assert gt.num_frames == 5
    assert (gt.num_points >= 0).all()  # AV2's own counts, also on timestamps whose sweep is not shipped
    rng = np.random.default_rng(0)
    noisy = gt.boxes.copy()
    noisy[:, :2] += rng.normal(0, 0.1, (len(noisy), 2))
    fids = [gt.frame_ids[f] for f in gt.frame_of_row]
    det = write_av2_detections(
        tmp_path / "dets.feather", fids, noisy, gt.class_names, rng.uniform(0.3, 1.0, len(noisy))
    )
    r = invoke(
        "eval", root, det, "--format", "json", "--workers", "1", "--metric", "bev", "--classes", "REGULAR_VEHICLE"
    )
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    rec = {x["metric"]: x for x in doc["ap"] if x["interp"] == "R40" and x["threshold"] == 0.5}
    # every box with a point is found at IoU 0.5 (10 cm noise; AP in percent); JIoU-ratio ≥ JIoU (JIoU-GT ≤ 1)
    assert rec["iou"]["max_recall"] == 1.0 and rec["iou"]["ap"] > 95.0 and rec["iou"]["num_gt"] > 100
    assert rec["jiou_ratio"]["ap"] >= rec["jiou"]["ap"]

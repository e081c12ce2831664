"""Where a dataset labels: the polygon test, Argoverse 2's region of interest from its map, and
labels of every category (audited or not) explaining their returns in the missing-label search."""

from __future__ import annotations

import io
import json
import math
from dataclasses import replace
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest

from labelaudit import constants as C
from labelaudit.config import RunConfig, resolve_config
from labelaudit.core import geometry as g
from labelaudit.core.geometry import near_polygons, transform_points
from labelaudit.datasets import RegionOfInterest, in_labelled_region, open_dataset
from labelaudit.datasets.av2 import ANNOTATIONS, POSES, SWEEP_DIR, read_city_poses
from labelaudit.executors import SerialExecutor
from labelaudit.infer.missing import FrameDetections, find_missing
from labelaudit.infer.run import InferRequest, run_infer
from labelaudit.results import open_results
from labelaudit.sim.av2_writer import write_annotations, write_sweep
from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_waymo_v1, write_waymo_v2
from labelaudit.viz.objects import frame_label_rows
from labelaudit.viz.show import OTHER_LABEL_COLOUR, REGION_COLOUR, render_candidate, render_frame
from test_av2 import T0, make_log
from test_missing import GROUND, _best, _car_points, _frame

SQUARE = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]])


# --------------------------------------------------------------------------- the polygon test


def test_near_polygons_known_answers():
    pts = np.array(
        [
            [5.0, 5.0],  # inside
            [-4.9, 5.0],  # 4.9 m left of the left edge
            [-5.1, 5.0],  # 5.1 m
            [-3.5, -3.5],  # 4.95 m from the corner (0, 0)
            [-3.6, -3.6],  # 5.09 m from it: the grown square is rounded at its corners
            [15.0, 15.0],  # 7.07 m from the corner (10, 10)
        ]
    )
    assert near_polygons(pts, [SQUARE], 5.0).tolist() == [True, True, False, True, False, False]
    assert near_polygons(pts, [SQUARE], 0.0).tolist() == [True, False, False, False, False, False]
    closed = np.vstack([SQUARE[::-1], SQUARE[-1:]])  # the other orientation, first vertex repeated
    assert near_polygons(pts, [closed], 5.0).tolist() == [True, True, False, True, False, False]
    assert not near_polygons(pts, [SQUARE[:2]], 5.0).any()  # fewer than 3 vertices: no polygon


def test_near_polygons_concave_and_several():
    ell = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 10.0], [10.0, 10.0], [10.0, 30.0], [0.0, 30.0]])
    # in the notch: 9.9 m and 4.2 m from the inner corner (10, 10); then two points inside the L
    notch = np.array([[25.0, 25.0], [17.0, 17.0], [13.0, 13.0], [5.0, 5.0], [25.0, 5.0]])
    assert near_polygons(notch, [ell], 0.0).tolist() == [False, False, False, True, True]
    assert near_polygons(notch, [ell], 5.0).tolist() == [False, False, True, True, True]
    far = SQUARE + 100.0
    assert near_polygons([[104.0, 104.0], [5.0, 5.0], [50.0, 50.0]], [SQUARE, far], 1.0).tolist() == [True, True, False]


# --------------------------------------------------------------------------- the search keeps to the region


def _road(y0: float, y1: float) -> RegionOfInterest:
    """A straight road along x between y0 and y1 (drivable area), grown by AV2's 5 m."""
    return RegionOfInterest((np.array([[-100.0, y0], [100.0, y0], [100.0, y1], [-100.0, y1]]),), C.AV2_ROI_MARGIN)


def test_a_candidate_off_the_region_of_interest_is_dropped_one_on_it_kept():
    cfg = resolve_config(None, "av2")
    frame = _frame(_car_points(15.0, 3.0))
    assert _best(find_missing(frame, cfg), 15.0, 3.0) >= 0.5  # no map: found within range
    frame.roi = _road(-2.0, 6.0)  # the car stands on the road
    assert _best(find_missing(frame, cfg), 15.0, 3.0) >= 0.5
    frame.roi = _road(-10.0, -4.0)  # its near side (y ≈ 2.1) lies 6.1 m from the road's edge
    assert find_missing(frame, cfg) == []
    frame.roi = _road(-10.0, -2.5)  # 4.6 m: inside the grown region
    assert _best(find_missing(frame, cfg), 15.0, 3.0) >= 0.5


def test_the_region_rule_is_any_corner_of_the_box():
    frame = _frame()
    frame.roi = _road(-2.0, 2.0)  # region: |y| ≤ 7
    boxes = np.array(
        [
            [20.0, 8.5, 0.0, 4.0, 2.0, 1.5, 0.0],  # near side at y = 7.5: out
            [20.0, 8.5, 0.0, 4.0, 4.0, 1.5, math.pi / 4],  # turned 45°: a corner reaches y = 5.67
            [20.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # on the road
            [90.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0],  # on the road, beyond max_range
        ]
    )
    assert in_labelled_region(boxes, frame, 70.0).tolist() == [False, True, True, False]
    assert in_labelled_region(boxes, frame, 70.0, slack_m=1.0).tolist() == [True, True, True, False]


def test_a_label_of_any_category_explains_its_returns():
    cfg = resolve_config(None, "av2")
    assert "VEHICULAR_TRAILER" not in cfg.classes and "BOLLARD" not in cfg.classes
    car = _car_points(15.0, 3.0)
    assert _best(find_missing(_frame(car), cfg), 15.0, 3.0) >= 0.5
    for name in ("VEHICULAR_TRAILER", "BOLLARD"):  # not audited: still a label, its returns are explained
        label = [15.0, 3.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0]
        assert find_missing(_frame(car, boxes=[label], names=[name]), cfg) == [], name


# --------------------------------------------------------------------------- Argoverse 2: the map


def _write_map(log: Path, areas: object) -> Path:
    path = log / "map" / f"log_map_archive_{log.name}____PIT_city_1.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"drivable_areas": areas, "lane_segments": {}, "pedestrian_crossings": {}}))
    return path


def _city(log: Path, ts: int, ego_xy: list[tuple[float, float]]) -> list[dict[str, float]]:
    """Vertices (city frame, AV2's JSON form) of ego-frame BEV points at the ground of timestamp ``ts``."""
    poses, _ = read_city_poses(log / POSES)
    pts = transform_points(poses[ts], np.array([[x, y, 0.0] for x, y in ego_xy]))
    return [{"x": float(p[0]), "y": float(p[1]), "z": float(p[2])} for p in pts]


def _map_note(warning: str) -> bool:
    return "region of interest" in warning or "place the map" in warning


def _av2_frames(root: Path) -> list:
    reader = open_dataset(root, "av2")
    return [f for ref in reader.list_units() for f in reader.load_unit(ref)]


def test_av2_frames_carry_the_maps_region_of_interest(tmp_path):
    log = make_log(tmp_path)
    source = _write_map(
        log, {"7": {"id": 7, "area_boundary": _city(log, T0, [(-50, -3), (50, -3), (50, 3), (-50, 3)])}}
    )
    frames = _av2_frames(tmp_path)
    assert all(f.roi is not None and f.roi.source == str(source) and f.roi.margin == C.AV2_ROI_MARGIN for f in frames)
    assert not any(_map_note(w) for f in frames for w in f.warnings)
    # frame 0: the road as drawn (|y| ≤ 3, grown by 5 m); the ego moves 1.2 m along x per frame
    assert frames[0].roi.contains([[0.0, 0.0], [20.0, 7.9], [20.0, 8.1], [-54.0, 0.0]]).tolist() == [
        True,
        True,
        False,
        True,
    ]
    # frame 2: the ego has moved 2.4 m along the city's x and turned by 0.02 rad (make_log's poses)
    c, s = math.cos(0.02), math.sin(0.02)
    x, y = 50.0 - 2.4, 3.0
    assert np.allclose(frames[2].roi.polygons[0][2], [c * x + s * y, -s * x + c * y], atol=1e-6)


def test_av2_without_a_map_has_no_region_and_no_warning(tmp_path):
    make_log(tmp_path)
    frames = _av2_frames(tmp_path)
    assert all(f.roi is None for f in frames) and not any(_map_note(w) for f in frames for w in f.warnings)


@pytest.mark.parametrize(
    "content, expected",
    [
        ("{not json", "not an AV2 map"),
        (json.dumps({"lane_segments": {}}), "not an AV2 map"),
        (json.dumps({"drivable_areas": [1, 2]}), "expected an object of areas by id"),
        (
            json.dumps({"drivable_areas": {"3": {"id": 3, "area_boundary": [{"x": 1, "y": 2}]}}}),
            "no usable drivable area",
        ),
    ],
)
def test_av2_bad_map_is_a_warning_naming_the_file(tmp_path, content, expected):
    log = make_log(tmp_path)
    path = log / "map" / "log_map_archive_x.json"
    path.parent.mkdir()
    path.write_text(content)
    frames = _av2_frames(tmp_path)
    assert all(f.roi is None for f in frames)
    notes = [w for w in frames[0].warnings if str(path) in w]
    assert len(notes) >= 1 and any(expected in w for w in notes) and "range only" in notes[-1], notes


def test_av2_bad_polygon_is_left_out_by_name(tmp_path):
    log = make_log(tmp_path)
    good = {"id": 1, "area_boundary": _city(log, T0, [(-50, -3), (50, -3), (50, 3), (-50, 3)])}
    path = _write_map(log, {"1": good, "2": {"id": 2, "area_boundary": good["area_boundary"][:2]}})
    frames = _av2_frames(tmp_path)
    assert all(f.roi is not None and len(f.roi.polygons) == 1 for f in frames)
    assert any(str(path) in w and "drivable area(s) 2 (2 vertices)" in w for w in frames[0].warnings)


def test_infer_av2_keeps_candidates_to_the_map_and_unaudited_labels_explain_their_returns(tmp_path):
    """End to end: four logs with the same unlabelled car; one labels it as a trailer (not audited),
    one has a map whose road passes 20 m away, one a map whose road passes under it."""
    scene = _frame(_car_points(15.0, 3.0)).points[:, :3] + [0.0, 0.0, -GROUND]  # AV2's ego frame: ground at z = 0
    trailer = np.array([[15.0, 3.0, 0.75, 4.2, 1.8, 1.5, 0.0]])
    for name, label, road in (
        ("plain", False, None),
        ("trailer", True, None),
        ("off-road", False, (-30.0, -20.0)),
        ("on-road", False, (-2.0, 6.0)),
    ):
        log = make_log(tmp_path, sweeps=(), log_id=f"log-{name}")
        write_sweep(log / SWEEP_DIR / f"{T0}.feather", np.c_[scene, np.zeros(len(scene))])
        write_annotations(
            log / ANNOTATIONS,
            [T0] * int(label),
            trailer[: int(label)],
            ["VEHICULAR_TRAILER"] * int(label),
            ["t-1"] * int(label),
        )
        if road is not None:
            y0, y1 = road
            _write_map(
                log, {"1": {"id": 1, "area_boundary": _city(log, T0, [(-99, y0), (99, y0), (99, y1), (-99, y1)])}}
            )
    cfg = resolve_config(None, "av2")
    out = run_infer(InferRequest(tmp_path, tmp_path / "res", "av2"), cfg, executor=SerialExecutor()).output
    rows = open_results(out).missing().to_pylist()
    found = {
        r["frame_id"].split(":")[0] for r in rows if r["score"] >= 0.5 and math.hypot(r["cx"] - 15, r["cy"] - 3) < 1.5
    }
    assert found == {"log-plain", "log-on-road"}
    assert not any(r["frame_id"].startswith(("log-trailer", "log-off-road")) for r in rows)


# --------------------------------------------------------------------------- the real logs


def test_real_av2_no_candidate_lies_on_a_label_of_any_category(realdata):
    """The real sweeps carry pedestrians, bollards, bicycles, a trailer … beside the audited
    vehicles: no candidate may sit on any of them. Their folder has no map/: range only."""
    root = realdata / "av2-sensor"
    if not root.is_dir():
        pytest.skip("no Argoverse 2 logs in the real data")
    cfg = resolve_config(None, "av2")
    frames = [f for f in _av2_frames(root) if len(f.points)]
    assert frames and all(f.roi is None for f in frames)
    unaudited = 0
    for f in frames:
        unaudited += sum(c not in cfg.classes for c in f.class_names)
        for r in find_missing(f, cfg):
            for box in f.boxes:
                c, s = math.cos(box[6]), math.sin(box[6])
                dx, dy = r["cx"] - box[0], r["cy"] - box[1]
                assert abs(c * dx + s * dy) > box[3] / 2 or abs(-s * dx + c * dy) > box[4] / 2, r
    assert unaudited > 50  # the check means something: most of the labels are of other categories


# --------------------------------------------------------------------------- Waymo: No Label Zones


def test_a_candidate_touching_a_no_label_zone_is_dropped():
    cfg = RunConfig()
    frame = _frame(_car_points(15.0, 3.0))
    on_car = (np.abs(frame.points[:, 0] - 15.0) < 2.2) & (np.abs(frame.points[:, 1] - 3.0) < 1.0)
    on_car &= frame.points[:, 2] > GROUND + 0.5
    frame.no_label_zone = np.zeros(len(frame.points), dtype=bool)
    frame.no_label_zone[np.flatnonzero(frame.points[:, 0] > 40.0)[:50]] = True  # a zone elsewhere
    assert _best(find_missing(frame, cfg), 15.0, 3.0) >= 0.5
    dets = FrameDetections(np.array([[15.0, 3.0, GROUND + 0.8, 4.4, 2.0, 1.6, 0.0]]), np.array([0.9]), ["Car"], ["d:1"])
    assert _best(find_missing(frame, cfg, dets), 15.0, 3.0) >= 0.9
    frame.no_label_zone[np.flatnonzero(on_car)[:1]] = True  # one return of the car in a zone: Waymo's rule
    assert _best(find_missing(frame, cfg), 15.0, 3.0) == 0.0
    assert find_missing(frame, cfg, dets) == []  # a detection there is not a candidate either
    with pytest.raises(ValueError, match="one flag per point"):
        replace(frame, no_label_zone=np.zeros(3, dtype=bool))


@pytest.mark.parametrize("fmt", ["waymo-v1", "waymo-v2"])
def test_waymo_readers_flag_the_points_in_no_label_zones(tmp_path, fmt):
    segment = simulate_waymo_segment(seed=5, frames=1, size="small")
    top = segment.frames[0].lidars[1]
    flagged = 0
    for image in top.returns:
        image[:, :40, 3] = 1.0  # the first 40 columns: an azimuth wedge from +π down (the vehicle's rear-left)
        flagged += int((image[:, :40, 0] > 0).sum())
    (write_waymo_v1 if fmt == "waymo-v1" else write_waymo_v2)(segment, tmp_path / "seg")
    reader = open_dataset(tmp_path / "seg", fmt)
    frame = next(f for ref in reader.list_units() for f in reader.load_unit(ref))
    zone = frame.no_label_zone
    assert zone is not None and zone.shape == (len(frame.points),) and int(zone.sum()) == flagged > 0
    # column j looks along the azimuth π − (j + ½)·2π/W: the first 40 columns, from 180° down
    wedge = 40 * 360.0 / top.returns[0].shape[1]
    rel = frame.points[zone, :2] - frame.sensor_origin[:2]  # seen from the TOP lidar
    az = np.degrees(np.arctan2(rel[:, 1], rel[:, 0])) % 360.0
    assert (az > 180.0 - wedge - 3.0).all() and (az < 183.0).all(), (wedge, az.min(), az.max())


# --------------------------------------------------------------------------- where a user looks


def _pixels(png: bytes, colour: str) -> int:
    image = mpimg.imread(io.BytesIO(png), format="png")[..., :3]
    want = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0
    return int(np.sum(np.abs(image - want).max(axis=-1) < 0.08))


def test_the_frame_picture_draws_the_region_and_the_labels_not_audited():
    frame = _frame(_car_points(15.0, 3.0))
    road = _road(-2.0, 2.0)
    trailer = np.array([[3.0, 3.0, GROUND + 0.75, 3.0, 1.5, 1.5, 0.3]])
    plain = render_frame("f", frame.points, [], "jiou_gt", (600, 500), 3, frame.sensor_origin)
    drawn = render_frame(
        "f", frame.points, [], "jiou_gt", (600, 500), 3, frame.sensor_origin, other_labels=trailer, roi=road
    )
    assert _pixels(plain.png, REGION_COLOUR) == 0 and _pixels(drawn.png, REGION_COLOUR) > 100
    assert _pixels(plain.png, OTHER_LABEL_COLOUR) == 0 and _pixels(drawn.png, OTHER_LABEL_COLOUR) > 30


def test_the_candidate_close_up_draws_the_labels_of_every_class():
    boxes = [
        [15.0, 5.5, GROUND + 0.9, 0.6, 0.6, 1.8, 0.0],  # a pedestrian beside the car: not audited
        [15.0, 0.0, GROUND + 0.75, 4.0, 1.8, 1.5, 0.0],  # a car label
        [15.0, 9.0, GROUND + 0.75, np.nan, 1.8, 1.5, 0.0],  # refused by the reader: no box to draw
    ]
    frame = _frame(_car_points(15.0, 3.0), boxes=boxes, names=["PEDESTRIAN", "REGULAR_VEHICLE", "BUS"])
    frame.object_errors = {2: "row 2: length_m = nan"}
    rows = frame_label_rows(frame)
    assert [(r["object_index"], r["class_name"]) for r in rows] == [(0, "PEDESTRIAN"), (1, "REGULAR_VEHICLE")]
    candidate = dict(zip(g.BOX_FIELDS, [15.0, 3.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0]))
    candidate.update(
        candidate_index=0, score=0.9, class_name="REGULAR_VEHICLE", source="points", num_points=100, distance=15.3
    )
    pic = render_candidate("f", frame.points, candidate, rows, (500, 450), frame.sensor_origin)
    assert sorted(pic.label_classes) == ["PEDESTRIAN", "REGULAR_VEHICLE"]

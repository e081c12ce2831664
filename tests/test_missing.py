"""Missing-label candidates: the ``missing/`` table contract, its writer in ``infer``, resume and error rows."""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import labelaudit.infer.missing as M
from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.config import MissingParams, RunConfig
from labelaudit.datasets import Frame, ImageView
from labelaudit.errors import ResultsError
from labelaudit.executors import SerialExecutor
from labelaudit.infer.missing import FrameDetections, SearchTrace, find_missing, in_labelled_region, search_clusters
from labelaudit.infer.run import InferRequest, run_infer

DOCS = Path(__file__).resolve().parents[1] / "docs" / "results-schema.md"
CONTRACT = (
    "frame_id",
    "candidate_index",
    "class_name",
    "cx",
    "cy",
    "cz",
    "length",
    "width",
    "height",
    "yaw",
    "num_points",
    "distance",
    "score",
    "source",
)


def _candidate(frame_id: str, index: int, **kw) -> dict:
    row = {
        "frame_id": frame_id,
        "candidate_index": index,
        "class_name": "Car",
        "cx": 12.0,
        "cy": 3.0,
        "cz": -0.9,
        "length": 4.1,
        "width": 1.7,
        "height": 1.5,
        "yaw": 0.2,
        "num_points": 240,
        "distance": 12.4,
        "score": 0.8,
        "source": "points",
        "dataset": "kitti",
        "max_label_iou": 0.0,
    }
    row.update(kw)
    return row


def test_the_contract_columns_come_first_with_their_types():
    assert R.MISSING_COLUMN_NAMES[: len(CONTRACT)] == CONTRACT
    types = {f.name: f.type for f in R.MISSING_SCHEMA}
    assert (
        types["frame_id"] == pa.string()
        and types["candidate_index"] == pa.int32()
        and types["num_points"] == pa.int32()
    )
    assert all(
        types[c] == pa.float64() for c in ("cx", "cy", "cz", "length", "width", "height", "yaw", "distance", "score")
    )
    assert types["source"] == pa.string() and types["class_name"] == pa.string()


def test_every_missing_column_is_documented():
    documented = set(re.findall(r"^\| `([a-z_0-9]+)` \|", DOCS.read_text(), flags=re.M))
    assert set(R.MISSING_COLUMN_NAMES) <= documented, set(R.MISSING_COLUMN_NAMES) - documented


def test_read_missing_of_a_folder_without_candidates_is_empty_with_the_schema(tmp_path):
    (tmp_path / "res").mkdir()
    t = R.read_missing(tmp_path / "res")
    assert t.num_rows == 0 and t.schema.equals(R.MISSING_SCHEMA)
    with pytest.raises(ResultsError, match="no such results folder"):
        R.read_missing(tmp_path / "nowhere")


def test_read_missing_gathers_shards_sorted_and_fills_absent_columns(tmp_path):
    root = tmp_path / "res"
    R.write_parquet_atomic(
        R.missing_rows_to_table(
            [_candidate("000002", 0), _candidate("000001", 1), _candidate("000001", 0, detection_score=float("nan"))]
        ),
        root / R.MISSING_DIR / "part-a.parquet",
    )
    # a shard of an older build without the evidence columns
    old = pa.table({"frame_id": ["000000"], "candidate_index": pa.array([0], pa.int32()), "score": [0.3]})
    pq.write_table(old, root / R.MISSING_DIR / "part-b.parquet")
    (root / R.MISSING_DIR / f".part-c.parquet{R.TMP_MARKER}1").write_bytes(b"half")
    t = R.read_missing(root)
    assert t.schema.equals(R.MISSING_SCHEMA)
    assert list(zip(t["frame_id"].to_pylist(), t["candidate_index"].to_pylist())) == [
        ("000000", 0),
        ("000001", 0),
        ("000001", 1),
        ("000002", 0),
    ]
    assert (
        t["class_name"].to_pylist()[0] is None and t["detection_score"].to_pylist()[1] is None
    )  # NaN in an evidence column is no value
    bad = root / R.MISSING_DIR / "part-d.parquet"
    bad.write_bytes(b"not parquet")
    with pytest.raises(ResultsError, match="part-d.parquet.*damaged"):
        R.read_missing(root)


@pytest.fixture(scope="module")
def sim_kitti(tmp_path_factory) -> Path:
    from labelaudit.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("sim") / "kitti"
    simulate_dataset(root, frames=3, seed=5, progress=False)
    return root


def _run(dataset: Path, out: Path, cfg: RunConfig | None = None, **kw):
    return run_infer(
        InferRequest(dataset, out, "auto", chunk_units=2, **kw), cfg or RunConfig(), executor=SerialExecutor()
    )


def test_infer_writes_one_missing_shard_per_chunk_and_none_with_no_missing(sim_kitti, tmp_path):
    out = _run(sim_kitti, tmp_path / "on").output
    objects = sorted(p.name for p in (out / R.OBJECTS_DIR).glob("*.parquet"))
    assert sorted(p.name for p in (out / R.MISSING_DIR).glob("*.parquet")) == objects
    assert R.read_missing(out).schema.equals(R.MISSING_SCHEMA)
    off = replace(RunConfig(), missing=MissingParams(enabled=False))
    out_off = _run(sim_kitti, tmp_path / "off", off).output
    assert not (out_off / R.MISSING_DIR).exists() and R.read_missing(out_off).num_rows == 0
    assert off.param_hash() != RunConfig().param_hash()
    assert R.open_results(out).read().equals(R.open_results(out_off).read())  # the search changes no object row


def test_resume_reruns_a_chunk_whose_missing_shard_is_gone(sim_kitti, tmp_path):
    out = _run(sim_kitti, tmp_path / "res").output
    victim = sorted((out / R.MISSING_DIR).glob("*.parquet"))[0]
    victim.write_bytes(b"truncated")
    summary = _run(sim_kitti, out)
    assert summary.chunks_skipped == summary.chunks - 1 and R.is_whole_parquet(victim)


def test_a_failing_search_is_an_error_row_naming_the_file_and_the_objects_stay(sim_kitti, tmp_path, monkeypatch):
    from labelaudit.infer import run as run_module

    def boom(frame, cfg, detections=None):
        if frame.frame_id == "000001":
            raise ValueError("synthetic search failure")
        return []

    monkeypatch.setattr(run_module, "missing_of_frame", boom)
    out = _run(sim_kitti, tmp_path / "res").output
    errors = R.open_results(out).errors().to_pylist()
    assert len(errors) == 1 and errors[0]["frame_id"] == "000001" and errors[0]["level"] == "error"
    assert errors[0]["file"].endswith("label_2/000001.txt") and "synthetic search failure" in errors[0]["message"]
    ids = set(R.open_results(out).read(["frame_id"])["frame_id"].to_pylist())
    assert "000001" in ids


# --------------------------------------------------------------------------- the search itself

GROUND = -1.73


def _ground(x0=2.0, x1=60.0, y0=-25.0, y1=25.0, step=0.25):
    xs, ys = np.meshgrid(np.arange(x0, x1, step), np.arange(y0, y1, step))
    return np.c_[xs.ravel(), ys.ravel(), np.full(xs.size, GROUND)]


def _face(p0, p1, z0, z1, step):
    """Points on the vertical rectangle above the segment p0 → p1 between heights z0 and z1."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = max(2, int(np.linalg.norm(p1 - p0) / step))
    t = np.linspace(0, 1, n)
    zs = np.arange(z0, z1, step)
    xy = p0 + t[:, None] * (p1 - p0)
    return np.array([[x, y, z] for x, y in xy for z in zs])


def _car_points(cx, cy, length=4.2, width=1.8, height=1.5, step=0.08):
    """The two faces a sensor at the origin sees of an axis-aligned car ahead and to the left."""
    x0, y0 = cx - length / 2, cy - width / 2
    return np.vstack(
        [
            _face((x0, y0), (x0, y0 + width), GROUND + 0.2, GROUND + height, step),  # rear
            _face((x0, y0), (x0 + length, y0), GROUND + 0.2, GROUND + height, step),
        ]
    )  # right side


def _unshadowed(ground, objects):
    """The ground returns no object hides from the sensor at the origin (its azimuth window, behind its nearest return)."""
    keep = np.ones(len(ground), dtype=bool)
    az = np.arctan2(ground[:, 1], ground[:, 0])
    r = np.hypot(ground[:, 0], ground[:, 1])
    for obj in objects:
        if len(obj) == 0:
            continue
        oaz = np.arctan2(obj[:, 1], obj[:, 0])
        keep &= ~((az >= oaz.min()) & (az <= oaz.max()) & (r >= np.hypot(obj[:, 0], obj[:, 1]).min()))
    return ground[keep]


def _frame(*objects, boxes=None, names=(), view=None):
    pts = np.vstack([_unshadowed(_ground(), objects), *objects])
    boxes = np.zeros((0, 7)) if boxes is None else np.asarray(boxes, dtype=float).reshape(-1, 7)
    return Frame(
        "000001",
        np.c_[pts, np.zeros(len(pts))].astype(np.float32),
        boxes,
        list(names),
        [f"000001:{i}" for i in range(len(boxes))],
        image_view=view,
    )


def _best(rows, x, y, radius=1.5):
    near = [r for r in rows if math.hypot(r["cx"] - x, r["cy"] - y) <= radius]
    return max((r["score"] for r in near), default=0.0)


def test_an_unlabelled_car_is_found_where_it_stands_and_a_labelled_one_is_not():
    cfg = RunConfig()
    rows = find_missing(_frame(_car_points(15.0, 3.0)), cfg)
    assert _best(rows, 15.0, 3.0) >= 0.5
    top = max(rows, key=lambda r: r["score"])
    assert (
        math.hypot(top["cx"] - 15.0, top["cy"] - 3.0) < 1.0 and top["class_name"] == "Car" and top["source"] == "points"
    )
    assert 3.0 <= top["length"] <= 5.3 and 1.4 <= top["width"] <= 2.2
    labelled = find_missing(
        _frame(_car_points(15.0, 3.0), boxes=[[15.0, 3.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0]], names=["Car"]), cfg
    )
    assert _best(labelled, 15.0, 3.0) == 0.0  # its label explains its returns


def test_a_car_scores_higher_than_a_wall_a_pole_a_bush_and_a_kerb():
    cfg = RunConfig()
    rng = np.random.default_rng(0)
    car = _car_points(20.0, 4.0)
    wall = _face((14.0, -8.0), (34.0, -8.0), GROUND + 0.1, GROUND + 4.0, 0.1)  # 20 m of building front
    pole = np.vstack(
        [
            _face((25.0, 10.0), (25.3, 10.0), GROUND, GROUND + 6.0, 0.05),
            _face((25.0, 10.0), (25.0, 10.3), GROUND, GROUND + 6.0, 0.05),
        ]
    )
    bush = np.array([28.0, -3.0, GROUND + 0.9]) + rng.normal(
        0.0, [1.0, 0.8, 0.45], (1500, 3)
    )  # foliage: returns scattered in depth
    kerb = _face((10.0, -5.0), (30.0, -5.0), GROUND, GROUND + 0.15, 0.05)
    rows = find_missing(_frame(car, wall, pole, bush, kerb), cfg)
    car_score = _best(rows, 20.0, 4.0)
    assert car_score >= 0.5
    for x, y, what in ((24.0, -8.5, "wall"), (25.0, 10.0, "pole"), (28.0, -3.0, "bush"), (20.0, -5.0, "kerb")):
        assert _best(rows, x, y, radius=2.5) < min(0.5, car_score), what


def test_a_car_in_a_shadow_is_measured_from_the_road_around_not_from_its_own_lowest_returns():
    """An occluder hides the road around a car and its lower body: the 3 × 3 ground cells under it
    hold only its own returns. Its height must come from the road a few metres off, so it is found
    with its height, and a shadow with nothing in it stays empty."""
    cfg = RunConfig()
    whole = _car_points(25.0, 3.0)
    car = whole[whole[:, 2] >= GROUND + 0.7]  # the lower body hidden behind something low ahead of it
    ground = _unshadowed(_ground(), [whole])
    hole = (np.abs(ground[:, 0] - 25.0) < 4.5) & (np.abs(ground[:, 1] - 3.0) < 3.0)  # no road seen around it
    pts = np.vstack([ground[~hole], car])
    frame = Frame("000001", np.c_[pts, np.zeros(len(pts))].astype(np.float32), np.zeros((0, 7)), [], [])
    rows = find_missing(frame, cfg)
    assert _best(rows, 25.0, 3.0) >= 0.5
    top = max(rows, key=lambda r: r["score"])
    assert abs(top["height"] - 1.5) < 0.2 and abs(top["cz"] - (GROUND + 0.75)) < 0.2
    empty = Frame("000001", np.c_[ground[~hole], np.zeros((~hole).sum())].astype(np.float32), np.zeros((0, 7)), [], [])
    assert find_missing(empty, cfg) == []


def test_a_car_in_a_shadow_wider_than_the_ground_opening_is_found_and_a_low_wall_there_is_not(monkeypatch):
    """A shadow wider than ``MISSING_GROUND_OPENING`` around a car whose lower body is hidden: every
    square of the opening around it sees only its own returns. The wider opening, applied where the
    square holds few cells with returns, takes the road past the shadow's edge: the car is found with
    its height; without it its lowest return is the road and it is too low to be a car. A low wall in
    such a shadow, measured from the road, is still too low."""
    cfg = RunConfig()
    whole = _car_points(25.0, 3.0)
    car = whole[whole[:, 2] >= GROUND + 0.7]
    ground = _unshadowed(_ground(), [whole])
    hole = (np.abs(ground[:, 0] - 25.0) < 7.0) & (np.abs(ground[:, 1] - 3.0) < 7.0)  # 14 m without road returns

    def frame(obj):
        pts = np.vstack([ground[~hole], obj])
        return Frame("000001", np.c_[pts, np.zeros(len(pts))].astype(np.float32), np.zeros((0, 7)), [], [])

    rows = find_missing(frame(car), cfg)
    assert _best(rows, 25.0, 3.0) >= 0.5
    top = max(rows, key=lambda r: r["score"])
    assert abs(top["height"] - 1.5) < 0.2 and abs(top["cz"] - (GROUND + 0.75)) < 0.2
    wall = _face((22.0, 1.0), (28.0, 1.0), GROUND + 0.35, GROUND + 0.7, 0.08)  # 0.7 m high, its foot hidden
    assert _best(find_missing(frame(wall), cfg), 25.0, 1.0, radius=3.0) == 0.0
    monkeypatch.setattr(C, "MISSING_GROUND_MIN_CELLS", 0.0)  # the 9 m opening alone
    assert _best(find_missing(frame(car), cfg), 25.0, 3.0) < 0.5


def _plate_ghosts(pts: np.ndarray, hit: np.ndarray, k: int, every: int = 5) -> np.ndarray:
    """The road's mirror image of the number plate of simulated object ``k`` (a wet or glossy road
    reflects the beam onto it): a fifth of its returns 0.63–0.78 m up within 0.25 m of its return
    nearest the sensor, mirrored in the ground plane (as far under the road as the plate is above)."""
    own = pts[hit == k, :3]
    n = own[np.argmin(np.hypot(own[:, 0], own[:, 1]))]
    plate = own[(np.hypot(own[:, 0] - n[0], own[:, 1] - n[1]) <= 0.25) & (np.abs(own[:, 2] - (GROUND + 0.7)) <= 0.075)]
    ghosts = plate[::every].copy()
    ghosts[:, 2] = 2 * GROUND - ghosts[:, 2]
    return np.c_[ghosts, np.zeros(len(ghosts))].astype(np.float32)


@pytest.mark.parametrize("share", [0.0, C.MISSING_GROUND_SHARE])
def test_a_car_beside_the_sensor_is_found_over_a_plates_mirror_image_under_the_road(monkeypatch, share):
    """Two cars parked 4–9 m from the sensor (simulated sweep), the farther one labelled; the road
    mirrors a dozen returns of its number plate 0.7 m under the road. Those returns are a few of
    the hundreds in their ground cell: as the cell's floor (its third-lowest return) they sink the
    ground 0.8 m over 3 × 3 m, the road there rises into the search band and joins the unlabelled
    car, which is then too big for a car and its face a wall's. Ignored by their share of the
    cell's returns, the car is found; a low wall beside the sensor is still none, with or without."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import Scene, SimObject, make_object

    monkeypatch.setattr(C, "MISSING_GROUND_SHARE", share)
    free = make_object("Car", (4.6, 3.0), -0.28, np.array([3.9, 1.6, 1.55]), GROUND, np.random.default_rng(0))
    labelled = make_object("Car", (8.6, 0.9), 2.85, np.array([3.9, 1.6, 1.55]), GROUND, np.random.default_rng(1))
    wall_box = np.array([7.0, -4.5, GROUND + 0.3, 6.0, 0.3, 0.6, 0.0])  # 0.6 m high
    wall = SimObject("Building", wall_box, wall_box[None].copy(), np.array([0.5]))
    pts, hit = render_range_image(Scene(objects=[free, labelled], clutter=[wall]), LidarSpec()).points()
    ghosts = _plate_ghosts(pts, hit, 1)
    assert 8 <= len(ghosts) <= 16
    frame = Frame("000001", np.vstack([pts, ghosts]), labelled.box[None], ["Car"], ["000001:0"])
    rows = find_missing(frame, RunConfig())
    assert (_best(rows, 4.6, 3.0, radius=1.0) >= 0.5) == (share > 0)
    assert _best(rows, 7.0, -4.5, radius=3.0) < 0.5
    clean = Frame("000001", pts, labelled.box[None], ["Car"], ["000001:0"])  # no mirror image: found either way
    assert _best(find_missing(clean, RunConfig()), 4.6, 3.0, radius=1.0) >= 0.5


@pytest.mark.parametrize("near_rays", [False, True])
def test_a_car_parked_beside_the_sensor_is_found_and_a_bush_there_is_not(monkeypatch, near_rays):
    """Cars parked in the next lane, 2.3–2.8 m beside the sensor (simulated sweeps): their near end
    lies in the ego zone (no return there is searched) and their lower body under the lowest beam,
    and their near end subtends several times the angle of their far end. Returns per ray counted
    over the sides facing the sensor at each direction's own range, outside the ego zone and within
    the beams, they are a solid surface and found; counted over the whole rectangle at its nearest
    range (the rule before) they looked like a porous fragment. A bush as long beside the sensor is
    still no candidate either way."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import VEGETATION, Scene, SimObject, make_object

    if not near_rays:  # the rule before: the whole rectangle at its nearest range, every elevation

        def nearest_range(n, corners, ox, oy, z_lo, z_hi, rate, elevations=None):
            az = np.arctan2(corners[:, 1] - oy, corners[:, 0] - ox)
            az = (az - az[0] + np.pi) % (2 * np.pi) - np.pi
            d = float(np.min(np.hypot(corners[:, 0] - ox, corners[:, 1] - oy)))
            solid = float(az.max() - az.min()) * max(math.atan2(z_hi, d) - math.atan2(z_lo, d), 0.0)
            return n / max(solid * rate, 1.0)

        monkeypatch.setattr(M, "_fill", nearest_range)

    def best(objects, clutter, x, y):
        scene = Scene(objects=objects, clutter=clutter)  # foliage is porous only with a generator
        pts, _ = render_range_image(scene, LidarSpec(), None, np.random.default_rng(1)).points()
        return _best(find_missing(Frame("000001", pts, np.zeros((0, 7)), [], []), RunConfig()), x, y, radius=1.0)

    for x, y, yaw in ((1.5, -2.8, 0.3), (3.0, 2.3, 0.0), (-1.5, 2.8, 0.0)):
        car = make_object("Car", (x, y), yaw, np.array([3.9, 1.6, 1.55]), GROUND, np.random.default_rng(0))
        assert (best([car], [], x, y) >= 0.5) == near_rays, (x, y)
        box = np.array([x, y, GROUND + 0.75, 3.9, 1.6, 1.5, yaw])
        bush = SimObject(VEGETATION, box, box[None].copy(), np.array([0.4]))
        assert best([], [bush], x, y) < 0.5, (x, y)


def test_the_trace_says_what_became_of_each_cluster():
    """A found car's group is boxed and its box kept; a low wall is left unboxed as low, a pole as
    too small; a labelled car's returns form no group; the rows are the same with or without a trace."""
    car = _car_points(15.0, 3.0)
    low_wall = _face((20.0, -6.0), (24.0, -6.0), GROUND + 0.2, GROUND + 0.6, 0.05)
    pole = _face((25.0, 8.0), (25.2, 8.0), GROUND + 0.2, GROUND + 1.6, 0.04)
    labelled = _car_points(30.0, -3.0)
    frame = _frame(
        car, low_wall, pole, labelled, boxes=[[30.0, -3.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0]], names=["Car"]
    )
    trace = SearchTrace()
    rows = find_missing(frame, RunConfig(), trace=trace)
    assert rows == find_missing(frame, RunConfig())

    def group_at(x, y):
        return [g for g in trace.groups if g["x0"] <= x <= g["x1"] and g["y0"] <= y <= g["y1"]]

    (g_car,) = group_at(14.0, 2.5)
    assert g_car["fate"] == "boxed" and g_car["clusters"]
    kept = [trace.clusters[k] for k in g_car["clusters"]]
    assert any(f == "kept" and math.hypot(c.box[0] - 15.0, c.box[1] - 3.0) < 1.0 for c, f in kept)
    assert [g["fate"] for g in group_at(22.0, -6.0)] == ["low"]
    assert [g["fate"] for g in group_at(25.1, 8.0)] == ["footprint"]
    assert group_at(30.0, -3.0) == []
    assert len(trace.clusters) == sum(len(g["clusters"]) for g in trace.groups)


@pytest.mark.parametrize("own_cells", [0, C.MISSING_OWN_FRAGMENT_CELLS])
def test_a_car_whose_far_end_shows_past_a_gap_is_found_and_a_wall_broken_the_same_way_is_not(monkeypatch, own_cells):
    """A car's side hidden in its middle (behind a post) shows its far end as two small fragments in
    line with its face: they lie inside the box the car would become, so they are its own, not a
    wall going on — as fragments of at most ``MISSING_OWN_FRAGMENT_CELLS`` cells, and (with that
    rule off) as groups every cell of which lies inside the box. A wall broken the same way whose
    pieces run on for metres beyond is still a wall."""
    monkeypatch.setattr(C, "MISSING_OWN_FRAGMENT_CELLS", own_cells)
    x0, y0, h0, h1 = 13.05, 2.1, GROUND + 0.2, GROUND + 1.5
    rear = _face((x0, y0), (x0, y0 + 1.8), h0, h1, 0.08)
    near_side = _face((x0, y0), (15.2, y0), h0, h1, 0.08)
    tips = [_face((a, y0), (a + 0.2, y0), h0, h1, 0.08) for a in (16.0, 16.6)]
    rows = find_missing(_frame(rear, near_side, *tips), RunConfig())
    assert _best(rows, 15.0, 3.0, radius=1.0) >= 0.5
    wall = [_face((a, -6.0), (a + 0.2, -6.0), GROUND + 0.2, GROUND + 2.0, 0.08) for a in np.arange(15.9, 26.0, 0.7)]
    wall_rows = find_missing(
        _frame(_face((13.0, -6.0), (14.8, -6.0), GROUND + 0.2, GROUND + 2.0, 0.08), *wall), RunConfig()
    )
    assert _best(wall_rows, 14.5, -6.5, radius=2.5) < 0.5


def _turned(points: np.ndarray, degrees: float, about=(15.0, 3.0)) -> np.ndarray:
    """``points`` (N, 3) turned by ``degrees`` about the vertical line through ``about``."""
    a = math.radians(degrees)
    c, s = math.cos(a), math.sin(a)
    out = points.copy()
    dx, dy = points[:, 0] - about[0], points[:, 1] - about[1]
    out[:, 0] = about[0] + c * dx - s * dy
    out[:, 1] = about[1] + s * dx + c * dy
    return out


@pytest.mark.parametrize("degrees", [-5.0, -8.0, -10.0])
def test_a_car_whose_far_side_shows_past_a_gap_as_a_group_of_its_own_is_found_and_one_running_on_is_a_wall(degrees):
    """A car turned a few degrees from the grid, seen from behind and along its near side, whose
    side is hidden over 0.6 m (behind a post): the side's far part is a group of more cells than an
    own fragment (``MISSING_OWN_FRAGMENT_CELLS``), in line with the face, but every cell of it lies
    inside the box the car would become (3.9 m from its rear): the car's own, and the car is found.
    The same far part running on 0.4 m or more past that box is a wall going on: nothing is found."""
    x0, y0, h0, h1 = 13.05, 2.1, GROUND + 0.2, GROUND + 1.5
    rear = _turned(_face((x0, y0), (x0, y0 + 1.8), h0, h1, 0.08), degrees)
    near_side = _turned(_face((x0, y0), (15.0, y0), h0, h1, 0.08), degrees)
    for end, found in ((16.9, True), (17.3, False), (18.0, False), (20.0, False)):
        far = _turned(_face((15.6, y0), (end, y0), h0, h1, 0.08), degrees)
        assert len({(int(x // C.MISSING_CELL), int(y // C.MISSING_CELL)) for x, y in far[:, :2]}) > (
            C.MISSING_OWN_FRAGMENT_CELLS
        )
        rows = find_missing(_frame(rear, near_side, far), RunConfig())
        assert (_best(rows, 15.0, 3.0, radius=1.0) >= 0.5) == found, end


@pytest.mark.parametrize("rule", [False, True])
def test_a_car_with_a_bush_in_line_with_its_side_is_found_and_with_a_wall_there_is_not(monkeypatch, rule):
    """A car 30 m off (simulated sweep) with a bush standing 1 m past its end, its near face in line
    with the car's side: the bush's returns run on along the car's face, as a wall's would. They are
    foliage (as rough along the beams as the surface factor's end, ``MISSING_SURFACE_ROUGH[1]``) and
    the car a solid surface, so the car is no piece of it: found. Without the rule (nothing rough
    enough to be foliage) it was taken for a piece of a longer structure; with a solid block in the
    bush's place it is, either way."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import VEGETATION, Scene, SimObject, make_object

    if not rule:
        monkeypatch.setattr(C, "MISSING_SURFACE_ROUGH", (C.MISSING_SURFACE_ROUGH[0], np.inf))
    x, y = 30.0, 6.0
    car = make_object("Car", (x, y), 0.0, np.array([3.9, 1.6, 1.55]), GROUND, np.random.default_rng(0))
    box = np.array([x + 1.95 + 1.0 + 1.0, y - 0.8 + 0.6, GROUND + 0.8, 2.0, 1.2, 1.6, 0.0])  # near face at the car's
    for name, found in ((VEGETATION, rule), ("Building", False)):
        scene = Scene(objects=[car], clutter=[SimObject(name, box, box[None].copy(), np.array([0.4]))])
        pts, _ = render_range_image(scene, LidarSpec(), None, np.random.default_rng(0)).points()
        rows = find_missing(Frame("000001", pts, np.zeros((0, 7)), [], []), RunConfig())
        assert (_best(rows, x, y, radius=1.0) >= 0.5) == found, name


def _row_of_returns(p0, p1, z, step):
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    n = int(np.linalg.norm(p1 - p0) / step) + 1
    t = np.linspace(0, 1, n)
    return np.c_[p0 + t[:, None] * (p1 - p0), np.full(n, z)]


@pytest.mark.parametrize("rules", ["before", "now"])
def test_a_far_car_with_twenty_returns_is_found_and_a_tree_is_not_judged_by_its_trunk(monkeypatch, rules):
    """A car 52 m off seen from behind by two beams (20 returns) is a vehicle: too few returns to
    tell only below ``MISSING_POINTS_RAMP``. A tree whose few lower-body returns are its trunk (one
    face) is judged on all its returns (``MISSING_FACE_MIN_LOWER``): its crown is on no face. With
    the rules before (12–30 returns, faces from 3 lower returns) the car scored under 0.5 and the
    tree's trunk made a perfect face."""
    if rules == "before":
        monkeypatch.setattr(C, "MISSING_POINTS_RAMP", (12, 30))
        monkeypatch.setattr(C, "MISSING_FACE_MIN_LOWER", 3)
        monkeypatch.setattr(C, "MISSING_SURFACE_ROUGH", (np.inf, np.inf))  # (the crown's scatter, judged later)
    car = np.vstack([_row_of_returns((49.9, 5.1), (49.9, 6.9), GROUND + z, 0.19) for z in (0.5, 1.2)])
    rng = np.random.default_rng(3)
    trunk = np.c_[np.full(5, 30.0), np.full(5, -8.0), GROUND + np.linspace(0.35, 0.65, 5)]
    crown = np.c_[rng.uniform(28.8, 31.2, 40), rng.uniform(-8.8, -7.2, 40), rng.uniform(GROUND + 1.2, GROUND + 2.4, 40)]
    trace = SearchTrace()
    rows = find_missing(_frame(car, trunk, crown), RunConfig(), trace=trace)
    (tree_shape,) = [c.shape_score for c, _ in trace.clusters if math.hypot(c.box[0] - 30.0, c.box[1] + 8.0) < 2.0]
    assert _best(rows, 49.9 + 1.95, 6.0, radius=1.0) >= 0.5 if rules == "now" else _best(rows, 51.85, 6.0) < 0.5
    if rules == "now":  # (before, only the free space held the tree back, and its box now goes where no ray passes)
        assert _best(rows, 30.0, -8.0, radius=2.5) < 0.5
    assert tree_shape < 0.5 if rules == "now" else tree_shape >= 0.85


@pytest.mark.parametrize("splits", [0, C.MISSING_SPLITS])
def test_two_cars_parked_side_by_side_are_two_candidates(monkeypatch, splits):
    """Two cars 0.4 m apart make one cluster no class fits (4 m wide): it is split at the gap and
    each car is found where it stands; without the split neither is. (The road behind the far car's
    whole body is in its shadow: the rays that pass the first car's rear reach its hidden side.)"""
    monkeypatch.setattr(C, "MISSING_SPLITS", splits)
    near = _car_points(15.0, 3.0)
    far = _face((13.6, 4.3), (13.6, 6.1), GROUND + 0.2, GROUND + 1.5, 0.08)  # only its rear shows beside the first
    body = np.array([[13.6, 4.3, GROUND + 0.5], [17.8, 4.3, GROUND + 0.5], [17.8, 6.1, GROUND + 0.5]])
    frame = _frame(near, far)
    ground = _unshadowed(_ground(), [near, far, body])
    pts = np.vstack([ground, near, far])
    frame = replace(frame, points=np.c_[pts, np.zeros(len(pts))].astype(np.float32))
    rows = find_missing(frame, RunConfig())
    found = [_best(rows, x, y, radius=1.0) >= 0.5 for x, y in ((15.0, 3.0), (15.7, 5.2))]
    assert found == ([True, True] if splits else [False, False])


def test_a_car_beside_a_hedge_is_found_and_the_hedge_is_not():
    rng = np.random.default_rng(1)
    car = _car_points(18.0, 3.0)
    hedge = np.c_[
        rng.uniform(15.5, 21.0, 2500), rng.uniform(4.4, 5.6, 2500), rng.uniform(GROUND + 0.3, GROUND + 1.6, 2500)
    ]
    rows = find_missing(_frame(car, hedge), RunConfig())
    assert _best(rows, 18.0, 3.0, radius=1.0) >= 0.5
    assert _best(rows, 18.25, 5.0, radius=0.9) < 0.5


def test_a_car_at_the_edge_of_the_camera_view_merged_with_a_hedge_outside_it_is_found():
    """The merged cluster's centroid lies outside the camera's view, the car inside it: the cluster
    is searched because one of its fragments is in view, and the split frees the car."""
    rng = np.random.default_rng(2)
    car = _car_points(8.0, 4.5)  # 29–34° off the camera's axis (its edge: 41.6°)
    hedge = np.c_[
        rng.uniform(2.0, 9.5, 4000), rng.uniform(5.8, 8.5, 4000), rng.uniform(GROUND + 0.3, GROUND + 1.8, 4000)
    ]
    rows = find_missing(_frame(car, hedge, view=_camera()), RunConfig())
    assert _best(rows, 8.0, 4.5, radius=1.0) >= 0.5


def test_a_truck_seen_from_a_corner_is_found_as_a_truck_and_a_wall_or_fence_as_long_is_not(monkeypatch):
    cfg = RunConfig()
    truck = _car_points(22.0, 6.0, length=10.0, width=2.5, height=3.2, step=0.1)
    rows = find_missing(_frame(truck), cfg)
    top = max(rows, key=lambda r: r["score"])
    assert top["score"] >= 0.5 and top["class_name"] == "Truck"
    assert math.hypot(top["cx"] - 22.0, top["cy"] - 6.0) < 1.0 and 8.0 <= top["length"] <= 12.0
    # the truck's side alone, as high (a wall) or lower (a fence), under beams that would show a truck's roof
    wall = _face((17.0, 4.75), (27.0, 4.75), GROUND + 0.1, GROUND + 3.5, 0.1)
    fence = _face((17.0, 4.75), (27.0, 4.75), GROUND + 0.1, GROUND + 1.5, 0.1)
    az = np.radians(np.arange(-90.0, 90.0, 0.2))
    sky = np.c_[60.0 * np.cos(az), 60.0 * np.sin(az), np.full(len(az), 6.0)]  # the top beams reach 6 m at 60 m
    for what in (wall, fence):  # the points alone (before the rays through the box are counted) say "no truck"
        assert max((c.score for c in search_clusters(_frame(what, sky), cfg)), default=0.0) < 0.5
    monkeypatch.setattr(C, "MISSING_CLASS_MIN_CORNER", {})  # without the L-shape a wall is a truck's side
    assert max(c.score for c in search_clusters(_frame(wall, sky), cfg)) >= 0.5


def test_a_truck_seen_from_behind_is_a_truck_and_a_porous_face_or_one_seen_at_a_grazing_angle_is_not(monkeypatch):
    """A truck's rear alone (2.5 m wide, 3.2 m high, solid, square to the rays) is a Truck grown
    away from the sensor, its centre within 1 m of a 10 m truck's; the same face sending back a
    third of the rays (a building front of glass and windows), the face turned to run along the
    rays (a stretch of wall at a grazing angle) and a van-wide face are no Truck. Without the rule
    the rear is no Truck either (no L-shape)."""
    cfg = RunConfig()
    az = np.radians(np.arange(-90.0, 90.0, 0.2))
    sky = np.c_[60.0 * np.cos(az), 60.0 * np.sin(az), np.full(len(az), 6.0)]
    rear = _face((30.0, 1.0), (30.0, 3.5), GROUND + 0.3, GROUND + 3.2, 0.2)
    # the road behind the truck's whole body is in its shadow (the rays past the rear's edge meet its side)
    body = np.array([[30.0, 1.0, GROUND + 0.5], [40.0, 1.0, GROUND + 0.5], [40.0, 3.5, GROUND + 0.5]])
    pts = np.vstack([_unshadowed(_ground(), [rear, body]), rear, sky])
    frame = replace(_frame(rear, sky), points=np.c_[pts, np.zeros(len(pts))].astype(np.float32))
    top = max(find_missing(frame, cfg), key=lambda r: r["score"])
    assert top["class_name"] == "Truck" and top["score"] >= 0.5
    assert math.hypot(top["cx"] - 35.0, top["cy"] - 2.25) < 1.0

    def truck(*objects) -> bool:
        return any(c.class_name == "Truck" and c.score >= 0.5 for c in search_clusters(_frame(*objects, sky), cfg))

    porous = rear[::3]
    grazing = _face((30.0, 8.0), (32.5, 8.0), GROUND + 0.3, GROUND + 3.2, 0.2)
    van = _face((30.0, 1.0), (30.0, 2.9), GROUND + 0.3, GROUND + 2.2, 0.2)
    assert not truck(porous) and not truck(grazing) and not truck(van)
    monkeypatch.setattr(C, "MISSING_REAR_FILL", 0.0)  # returns per ray not asked: the porous face passes
    assert truck(porous)
    monkeypatch.setattr(C, "MISSING_CLASS_REAR_WIDTH", {})
    assert not truck(rear)


def test_a_truck_whose_cab_shows_past_a_gap_is_found_and_an_l_whose_side_goes_on_past_a_truck_is_not(monkeypatch):
    """A truck seen from a corner (its rear and 8 m of its box's side) with its cab, lower, past the
    0.6 m gap between cab and box: the cab is a group in line with the side, within a truck's largest
    length, and the truck's own (found where its box stands). The same L whose side's line goes on
    past a truck's largest length (a building's front) is no truck; nor is the truck when groups in
    line are not looked at as its own."""
    cfg = RunConfig()
    az = np.radians(np.arange(-90.0, 90.0, 0.2))
    sky = np.c_[60.0 * np.cos(az), 60.0 * np.sin(az), np.full(len(az), 6.0)]
    rear = _face((17.0, 4.75), (17.0, 7.25), GROUND + 0.3, GROUND + 3.2, 0.1)
    side = _face((17.0, 4.75), (25.0, 4.75), GROUND + 0.3, GROUND + 3.2, 0.1)
    cab = _face((25.6, 4.8), (27.6, 4.8), GROUND + 0.3, GROUND + 2.6, 0.1)
    front = _face((25.6, 4.75), (36.0, 4.75), GROUND + 0.3, GROUND + 3.2, 0.1)

    def trucks(*objects):
        return [c for c in search_clusters(_frame(*objects, sky), cfg) if c.class_name == "Truck" and c.score >= 0.5]

    found = trucks(rear, side, cab)
    assert len(found) == 1 and math.hypot(found[0].box[0] - 22.3, found[0].box[1] - 6.0) < 1.0
    assert not trucks(rear, side, front)
    monkeypatch.setattr(C, "MISSING_CLASS_OWN_REACH", ())
    assert not trucks(rear, side, cab)


def _column(x, y):
    """One column of returns (a truck's side at a grazing angle: one azimuth step's returns)."""
    return _face((x, y), (x + 0.01, y), GROUND + 0.3, GROUND + 3.2, 0.08)


def test_a_truck_side_seen_at_a_grazing_angle_in_fragments_is_joined_and_found(monkeypatch):
    """The side runs almost along the rays: one column of returns every 0.55 m (beyond the fragment
    merge's reach), on one line. Joined to the rear it is a truck; left apart it is not (the rear
    alone, as wide as a truck, is a truck seen from behind: that rule is off here)."""
    cfg = RunConfig()
    az = np.radians(np.arange(-90.0, 90.0, 0.2))
    sky = np.c_[60.0 * np.cos(az), 60.0 * np.sin(az), np.full(len(az), 6.0)]
    rear = _face((22.0, 1.2), (22.0, 3.7), GROUND + 0.3, GROUND + 3.2, 0.08)
    truck = np.vstack([rear, *[_column(22.0 + 0.55 * k, 1.2) for k in range(1, 17)]])  # 8.8 m long
    found = [c for c in search_clusters(_frame(truck, sky), cfg) if c.score >= 0.5]
    assert len(found) == 1 and found[0].class_name == "Truck"
    assert math.hypot(found[0].box[0] - 26.4, found[0].box[1] - 2.45) < 1.0
    monkeypatch.setattr(C, "MISSING_CLASS_REAR_WIDTH", {})
    monkeypatch.setattr(C, "MISSING_ROW_MIN", 10**6)  # without the row join: no truck
    assert not any(c.class_name == "Truck" and c.score >= 0.5 for c in search_clusters(_frame(truck, sky), cfg))


def test_fragments_in_a_straight_row_along_the_rays_are_joined_and_an_l_of_them_is_not(monkeypatch):
    """The same columns as one straight row along the rays (one group) and as an L whose second
    leg turns away from the first (a wall's corner): not joined, unless the line test is off."""
    cfg = RunConfig()

    def groups(*objects):
        trace = SearchTrace()
        search_clusters(_frame(*objects), cfg, trace=trace)
        return len(trace.groups)

    row = [_column(22.0 + 0.55 * k, 1.2) for k in range(14)]
    corner = [_column(22.0 + 0.55 * k, 1.2) for k in range(7)] + [_column(25.3, 1.2 + 0.55 * k) for k in range(1, 8)]
    assert groups(*row) == 1
    assert groups(*corner) >= 2
    monkeypatch.setattr(C, "MISSING_ROW_RESIDUAL", 1e9)
    monkeypatch.setattr(C, "MISSING_ROW_ANGLE", 90.0)
    assert groups(*corner) == 1


def test_a_truck_sized_l_whose_short_leg_goes_on_in_line_is_a_building_corner():
    """The same L-shape as a truck seen from its corner, but its short leg (the rear) goes on in line
    past a gap: the end wall of a building broken by a window, not a truck."""
    cfg = RunConfig()
    az = np.radians(np.arange(-90.0, 90.0, 0.2))
    sky = np.c_[60.0 * np.cos(az), 60.0 * np.sin(az), np.full(len(az), 6.0)]
    truck = _car_points(22.0, 6.0, length=10.0, width=2.5, height=3.2, step=0.1)
    beyond = _face((17.0, 7.85), (17.0, 9.85), GROUND + 0.1, GROUND + 3.2, 0.1)  # the rear's line, 0.6 m on
    assert max(c.score for c in search_clusters(_frame(truck, sky), cfg)) >= 0.5
    near = [
        c for c in search_clusters(_frame(truck, beyond, sky), cfg) if math.hypot(c.box[0] - 22.0, c.box[1] - 6.0) < 3.0
    ]
    assert near and max(c.score for c in near) < 0.5


def test_nothing_inside_the_ego_zone_or_beyond_the_labelled_range():
    cfg = RunConfig()
    near = _car_points(2.5, 0.0)
    far = _car_points(80.0, 3.0)
    rows = find_missing(_frame(near, far), cfg)
    assert all(r["distance"] > 3.0 and r["distance"] <= cfg.missing.max_range for r in rows)


def _camera() -> ImageView:
    """A pinhole camera at the sensor looking along +x (KITTI-like: u right, v down), 1242 × 375."""
    f, cu, cv = 700.0, 621.0, 187.5
    # camera axes: x_cam = −y_lidar, y_cam = −z_lidar, z_cam = x_lidar
    P = np.array([[cu, -f, 0.0, 0.0], [cv, 0.0, -f, 0.0], [1.0, 0.0, 0.0, 0.0]])
    return ImageView(P, (1242, 375))


def test_kitti_only_in_the_camera_view_and_not_in_dontcare_waymo_all_around():
    cfg = RunConfig()
    ahead, behind = _car_points(15.0, 3.0), _car_points(15.0, 3.0) * [-1, 1, 1]
    behind[:, 2] = _car_points(15.0, 3.0)[:, 2]
    all_round = find_missing(_frame(ahead, behind), cfg)
    assert _best(all_round, 15.0, 3.0) >= 0.5 and _best(all_round, -15.0, 3.0) >= 0.5
    view = _camera()
    kitti = find_missing(_frame(ahead, behind, view=view), cfg)
    assert _best(kitti, 15.0, 3.0) >= 0.5 and _best(kitti, -15.0, 3.0) == 0.0
    box = max(kitti, key=lambda r: r["score"])
    rect = view.box_to_image([box[k] for k in ("cx", "cy", "cz", "length", "width", "height", "yaw")])
    covered = ImageView(view.projection, view.size, np.array([[rect[0] - 5, rect[1] - 5, rect[2] + 5, rect[3] + 5]]))
    assert _best(find_missing(_frame(ahead, behind, view=covered), cfg), 15.0, 3.0) == 0.0  # inside a DontCare region
    elsewhere = ImageView(view.projection, view.size, np.array([[0.0, 0.0, 50.0, 50.0]]))
    assert _best(find_missing(_frame(ahead, behind, view=elsewhere), cfg), 15.0, 3.0) >= 0.5
    inside = in_labelled_region(
        np.array([[15.0, 3.0, -1.0, 4.0, 1.8, 1.5, 0.0], [-15.0, 3.0, -1.0, 4.0, 1.8, 1.5, 0.0]]),
        _frame(view=view),
        70.0,
    )
    assert inside.tolist() == [True, False]


def test_kitti_a_car_truncated_by_the_image_edge_is_where_labels_exist_one_out_of_view_is_not(monkeypatch):
    """KITTI labels objects the image's edge cuts (truncated up to ~0.9): a car whose centre
    projects just outside image_2 but 40 % of whose 2D box is inside is a candidate; one wholly
    outside is not, nor one whose 2D box lies more than MISSING_MAX_TRUNCATION outside."""
    view = _camera()
    boxes = np.array(
        [
            [10.0, 9.0, -1.0, 4.0, 1.8, 1.5, 0.0],  # centre 9 px left of the image, 38 % of its 2D box inside
            [10.0, 14.0, -1.0, 4.0, 1.8, 1.5, 0.0],  # wholly left of it
            [20.0, 3.0, -1.0, 4.0, 1.8, 1.5, 0.0],  # wholly inside
        ]
    )
    share = view.in_image_share(boxes)
    assert 0.3 < share[0] < 0.45 and share[1] == 0.0 and share[2] == 1.0
    assert in_labelled_region(boxes, _frame(view=view), 70.0).tolist() == [True, False, True]
    rows = find_missing(_frame(_car_points(10.0, 9.0, width=1.8), view=view), RunConfig())
    assert _best(rows, 10.0, 9.0, radius=1.0) >= 0.5
    monkeypatch.setattr(C, "MISSING_MAX_TRUNCATION", 0.5)  # at most half outside: the same car is not one
    assert in_labelled_region(boxes[:1], _frame(view=view), 70.0).tolist() == [False]


def test_detections_without_a_label_are_candidates_and_one_found_both_ways_is_one():
    cfg = RunConfig()
    label = [30.0, -6.0, GROUND + 0.75, 4.0, 1.7, 1.5, 0.0]
    dets = FrameDetections(
        boxes=np.array(
            [
                [15.0, 3.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0],  # on the unlabelled car: both
                [40.0, 10.0, GROUND + 0.75, 4.0, 1.7, 1.5, 0.3],  # no label, no cluster: detections
                [30.2, -6.1, GROUND + 0.75, 4.0, 1.7, 1.5, 0.0],
            ]
        ),  # on the label: not a candidate
        scores=np.array([0.9, 0.8, 0.95]),
        class_names=["Car", "Car", "Car"],
        sources=["d.txt:1", "d.txt:2", "d.txt:3"],
    )
    rows = find_missing(_frame(_car_points(15.0, 3.0), boxes=[label], names=["Car"]), cfg, dets)
    by_source = {r["source"]: r for r in rows if r["score"] >= 0.5}
    assert set(by_source) == {"both", "detections"}
    assert math.hypot(by_source["both"]["cx"] - 15.0, by_source["both"]["cy"] - 3.0) < 0.01  # the detection's box
    assert by_source["both"]["detection_source"] == "d.txt:1" and by_source["both"]["points_score"] >= 0.5
    assert by_source["detections"]["detection_score"] == 0.8 and by_source["detections"]["score"] == 0.8
    assert not any(math.hypot(r["cx"] - 30.0, r["cy"] + 6.0) < 1.0 for r in rows)
    assert [r["candidate_index"] for r in rows] == list(range(len(rows)))
    assert sorted(r["distance"] for r in rows) == [r["distance"] for r in rows]


def test_rows_of_a_frame_are_reproducible():
    frame = _frame(_car_points(15.0, 3.0), _car_points(30.0, -4.0))
    assert find_missing(frame, RunConfig()) == find_missing(frame, RunConfig())


def test_no_missing_turns_the_search_off():
    off = replace(RunConfig(), missing=MissingParams(enabled=False))
    assert find_missing(_frame(_car_points(15.0, 3.0)), off) == []


# --------------------------------------------------------------------------- simulator


def test_simulated_dropped_labels_keep_their_points_and_are_in_the_manifest(tmp_path):
    from labelaudit.sim.dataset import simulate_dataset, simulate_frame
    from labelaudit.sim.manifest import read_manifest
    from labelaudit.sim.scene import SceneSpec

    kept = simulate_frame(2, seed=4)
    dropped = simulate_frame(2, seed=4, drop_fraction=1.0)
    assert np.array_equal(kept.points, dropped.points)  # same scene, same returns
    assert dropped.labels.dropped.any() and not kept.labels.dropped.any()
    vehicles = np.array([c in ("Car", "Van", "Truck") for c in kept.scene.class_names])
    assert np.array_equal(dropped.labels.dropped, (kept.labels.object_index >= 0) & vehicles)
    assert np.all(dropped.labels.object_index[dropped.labels.dropped] < 0)
    simulate_dataset(
        tmp_path / "sim", frames=2, seed=4, scene=SceneSpec(num_clutter=(3, 3)), drop_fraction=0.5, progress=False
    )
    man = read_manifest(tmp_path / "sim")
    assert "dropped" in man.column_names and man.schema.metadata[b"labelaudit.drop_fraction"] == b"0.5"
    rows = man.to_pylist()
    assert all(not r["labelled"] for r in rows if r["dropped"])


def test_clutter_stays_unlabelled(tmp_path):
    from labelaudit.sim.dataset import simulate_frame
    from labelaudit.sim.scene import SceneSpec

    f = simulate_frame(1, seed=2, scene_spec=SceneSpec(num_clutter=(6, 6)))
    assert len(f.scene.clutter) >= 1 and len(f.labels.lines) == int((f.labels.object_index >= 0).sum())


# --------------------------------------------------------------------------- real KITTI


@pytest.mark.parametrize(
    "folder, frame_id, line",
    [
        ("openpcdet-pr653-kitti", "000004", 1),  # a Car with ~70 points at 41 m
        ("kitti-object-more", "000015", 1),  # a Car 4 m beside the sensor at the camera's edge, against a hedge
        ("kitti-object-more", "000019", 1),  # a Truck 6 m away, seen from its corner
    ],
)
def test_a_real_vehicle_removed_from_its_label_file_is_found(realdata, tmp_path, folder, frame_id, line):
    from labelaudit.datasets import FrameRef, open_dataset

    src = realdata / folder / "training"
    if not (src / "label_2" / f"{frame_id}.txt").is_file():
        pytest.skip(f"{folder} frame {frame_id} not present")
    for sub in ("velodyne", "calib", "image_2"):
        (tmp_path / "training" / sub).mkdir(parents=True)
        for f in (src / sub).glob(f"{frame_id}.*"):
            (tmp_path / "training" / sub / f.name).symlink_to(f)
    lines = (src / "label_2" / f"{frame_id}.txt").read_text().splitlines(keepends=True)
    (tmp_path / "training" / "label_2").mkdir()
    (tmp_path / "training" / "label_2" / f"{frame_id}.txt").write_text("".join(lines[: line - 1] + lines[line:]))
    full = next(open_dataset(src.parent, "kitti").load_unit(FrameRef("kitti", str(src.parent), frame_id)))
    cut = next(open_dataset(tmp_path, "kitti").load_unit(FrameRef("kitti", str(tmp_path), frame_id)))
    k = list(full.extras["label_line"]).index(line)
    vehicle = full.boxes[k]
    assert full.class_names[k] in ("Car", "Van", "Truck")
    rows = find_missing(cut, RunConfig())
    assert _best(rows, vehicle[0], vehicle[1], radius=1.0) >= 0.5
    assert _best(find_missing(full, RunConfig()), vehicle[0], vehicle[1], radius=1.0) == 0.0


def test_simulated_foliage_is_porous_and_solid_clutter_is_not():
    from labelaudit.sim.raycast import HIT_CLUTTER, LidarSpec, render_range_image
    from labelaudit.sim.scene import VEGETATION, Scene, SimObject

    box = np.array([15.0, 0.0, GROUND + 1.0, 2.0, 3.0, 2.0, 0.0])

    def returns(name):
        scene = Scene([], GROUND, clutter=[SimObject(name, box, box[None].copy(), np.array([0.4]))])
        ri = render_range_image(scene, LidarSpec(), None, np.random.default_rng(1))
        pts, hits = ri.points("scene")
        return pts[hits == HIT_CLUTTER, :3].astype(float)

    solid, bush = returns("Building"), returns(VEGETATION)
    face = box[0] - box[3] / 2
    assert np.abs(solid[:, 0] - face).max() < 0.1  # on the face, range noise only
    assert np.median(bush[:, 0] - face) > 0.1 and (bush[:, 0] - face).std() > 0.15  # returns from inside the foliage
    assert 0.6 * len(solid) < len(bush) < 0.9 * len(solid)  # some rays pass through its gaps


def test_detections_need_the_search_and_an_existing_path(sim_kitti, tmp_path):
    from labelaudit.errors import InferError
    from labelaudit.infer.run import infer_dataset

    with pytest.raises(InferError, match="--detections and --no-missing"):
        infer_dataset(InferRequest(sim_kitti, tmp_path / "a", missing=False, detections=sim_kitti))
    with pytest.raises(InferError, match="nowhere: --detections path does not exist"):
        infer_dataset(InferRequest(sim_kitti, tmp_path / "b", detections=tmp_path / "nowhere"))


def test_a_label_shifted_off_its_car_is_a_wrong_label_not_a_missing_one():
    cfg = RunConfig()
    shifted = [
        16.2,
        3.4,
        GROUND + 0.75,
        4.2,
        1.8,
        1.5,
        0.0,
    ]  # 1.2 m off: the returns at its rear and side are outside it
    rows = find_missing(_frame(_car_points(15.0, 3.0), boxes=[shifted], names=["Car"]), cfg)
    assert _best(rows, 15.0, 3.0) == 0.0
    far = [30.0, -8.0, GROUND + 0.75, 4.2, 1.8, 1.5, 0.0]
    assert _best(find_missing(_frame(_car_points(15.0, 3.0), boxes=[far], names=["Car"]), cfg), 15.0, 3.0) >= 0.5


def _hidden_behind_a_van(monkeypatch, min_hidden):
    """A car parked across the line of sight (length 4.2 m along y, centre (30, 3.1)) whose near
    end (y < 2.6) is hidden behind a labelled van at 18–22 m: only 2.6 m of its rear face shows."""
    monkeypatch.setattr(C, "MISSING_PLACE_MIN_HIDDEN", min_hidden)
    van = _face((17.9, -0.2), (17.9, 1.6), GROUND + 0.2, GROUND + 2.2, 0.08)
    car = _face((29.1, 2.6), (29.1, 5.2), GROUND + 0.2, GROUND + 1.5, 0.08)
    frame = _frame(van, car, boxes=[[20.0, 0.7, GROUND + 1.1, 4.2, 1.8, 2.2, 0.0]], names=["Van"])
    rows = [r for r in find_missing(frame, RunConfig()) if math.hypot(r["cx"] - 30.0, r["cy"] - 3.9) < 3.0]
    top = max(rows, key=lambda r: r["score"])
    return math.hypot(top["cx"] - 30.0, top["cy"] - 3.1), top["score"]


def test_a_partly_hidden_car_is_boxed_towards_its_occluder_not_into_the_road_seen_empty(monkeypatch):
    """Its hidden extent goes where the van blocks the view, not past its visible end, where the
    sensor sees the road empty; grown away from the sensor (the placement off) it lands 1.6 m off."""
    off, score = _hidden_behind_a_van(monkeypatch, C.MISSING_PLACE_MIN_HIDDEN)
    assert off < 1.0 and score >= 0.5
    off_grown, _ = _hidden_behind_a_van(monkeypatch, 1e9)
    assert off_grown > 1.0 > off


def test_a_car_in_full_view_keeps_its_box(monkeypatch):
    frame = _frame(_car_points(15.0, 3.0), _car_points(32.0, -6.0))
    placed = find_missing(frame, RunConfig())
    monkeypatch.setattr(C, "MISSING_PLACE_MIN_HIDDEN", 1e9)
    assert find_missing(frame, RunConfig()) == placed


_PLACE_BY_RAYS = M._place_by_rays


def _sim_rows(objects, rays: bool):
    """The search's rows on a simulated sweep of ``objects`` (unlabelled), the placement by the
    frame's rays on or off."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import Scene

    pts, _ = render_range_image(Scene(objects=objects), LidarSpec(), None, np.random.default_rng(0)).points()
    frame = Frame("000001", pts, np.zeros((0, 7)), [], [])
    if rays:
        return find_missing(frame, RunConfig())
    original = M._place_by_rays
    M._place_by_rays = lambda frame, clusters, cfg: clusters
    try:
        return find_missing(frame, RunConfig())
    finally:
        M._place_by_rays = original


@pytest.mark.parametrize("where", [(30.0, -8.0, 0.3), (22.0, 9.0, -0.2)])
def test_a_truck_whose_far_end_is_seen_is_boxed_as_long_as_the_rays_past_it_allow(where):
    """A 7 m truck seen from a corner, nothing in front of it: its rear, its side and the road past
    its front are all in view. Grown to a Truck's mean 10.1 m, the box reaches over that road, where
    the rays went on to the ground behind it: placed where the rays let it be (its seen ends kept,
    the length the prior and the rays allow) it lands on the truck; grown away from the sensor (the
    placement off) more than 1 m off."""
    from labelaudit.sim.scene import make_object

    x, y, yaw = where
    truck = make_object("Truck", (x, y), yaw, np.array([7.0, 2.5, 3.2]), GROUND, np.random.default_rng(0))

    def placed(rays):
        rows = [r for r in _sim_rows([truck], rays) if r["score"] >= 0.5 and math.hypot(r["cx"] - x, r["cy"] - y) < 4.0]
        (row,) = rows
        return math.hypot(row["cx"] - x, row["cy"] - y), row["length"]

    off, length = placed(True)
    off_grown, length_grown = placed(False)
    assert off < 0.5 < 1.0 < off_grown
    assert abs(length - 7.0) < 0.5 < abs(length_grown - 7.0)


@pytest.mark.parametrize("yaw", [-1.31, -1.2])
def test_a_car_seen_from_its_corner_with_most_of_its_side_hidden_gets_its_length_where_the_rays_allow(monkeypatch, yaw):
    """A car 20 m ahead whose side faces the sensor at about 65°, hidden behind a labelled van but
    for its rear and 0.8 m of its side: the visible rectangle (1.6 × 0.8 m) fits a car's width both
    ways, and the length taken along the axis nearer the line of sight (a car seen from one end)
    puts the box across the car, more than 1 m off. Weighing the placements with the length on
    either axis, the rays past its rear's far corner and in front of its side rule that one out:
    found within 0.5 m, heading along its length."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import Scene, make_object

    car = make_object("Car", (20.0, -3.0), yaw, np.array([4.1, 1.64, 1.5]), GROUND, np.random.default_rng(0))
    van = make_object("Van", (10.5, -2.32), 0.0, np.array([5.0, 1.9, 2.2]), GROUND, np.random.default_rng(1))
    pts, _ = render_range_image(Scene(objects=[car, van]), LidarSpec(), None, np.random.default_rng(0)).points()
    frame = Frame("000001", pts, van.box[None, :], ["Van"], ["000001:0"])

    def placed():
        (row,) = [r for r in find_missing(frame, RunConfig()) if math.hypot(r["cx"] - 20.0, r["cy"] + 3.0) < 4.0]
        turn = abs((row["yaw"] - yaw + 0.5 * math.pi) % math.pi - 0.5 * math.pi)
        return math.hypot(row["cx"] - 20.0, row["cy"] + 3.0), turn

    off, turn = placed()
    assert off < 0.5 and turn < 0.1
    one_axis = M._Hidden
    monkeypatch.setattr(M, "_Hidden", lambda *fields: one_axis(*fields[:-1], False))  # the length's axis as chosen
    off_one_axis, _ = placed()
    assert off_one_axis > 1.0 > off


def _corner_car_frame(ray_mask=None):
    """A car 20 m ahead, its side at about 65° to the line of sight, hidden behind a labelled van but
    for its rear and 0.8 m of its side (simulated)."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import Scene, make_object

    car = make_object("Car", (20.0, -3.0), -1.31, np.array([4.1, 1.64, 1.5]), GROUND, np.random.default_rng(0))
    van = make_object("Van", (10.5, -2.32), 0.0, np.array([5.0, 1.9, 2.2]), GROUND, np.random.default_rng(1))
    pts, _ = render_range_image(Scene(objects=[car, van]), LidarSpec(), None, np.random.default_rng(0)).points()
    mask = None if ray_mask is None else ray_mask(len(pts))
    return Frame("000001", pts, van.box[None, :], ["Van"], ["000001:0"], ray_mask=mask)


@pytest.mark.parametrize("ray_mask", [None, lambda n: np.arange(n) % 3 != 0])
def test_the_placements_counted_in_one_pass_are_what_each_placement_counts_alone(ray_mask):
    """The counts of every placement of a partly hidden car, made in one pass over the frame with a
    difference array per row of placements, are each placement's own: its free rays (those of
    ray_counts: deeper than τ through its slab, not ending on or in it) plus its returns deeper than
    τ_in inside its slab, counted box by box against every ray of the frame. (Only the rays a mask
    keeps are rays; every return can be inside.)"""
    from labelaudit.core.freespace import FreeSpace, ray_counts

    frame = _corner_car_frame(ray_mask)
    cfg = RunConfig()
    (cl,) = [
        c for c in search_clusters(frame, cfg) if c.hidden is not None and math.hypot(c.box[0] - 20, c.box[1] + 3) < 4
    ]
    hid = cl.hidden
    variants = M._variants(hid)
    assert hid.either_axis and len(variants) > 8  # both axes, several lengths
    groups = [(P, Q, ext) for _, _, P, Q, ext in variants]
    a1, b1, a2, b2 = hid.vis
    L = max(hid.size)
    envelope = (min(a1, b1 - L), max(b1, a1 + L), min(a2, b2 - L), max(b2, a2 + L))
    (counts,) = M._placement_costs(frame, cfg, [M._Weighed(cl, envelope, groups)])
    xyz = np.asarray(frame.points[:, :3], dtype=float)
    rays = xyz if ray_mask is None else xyz[frame.ray_mask]
    height = float(cl.box[5])
    slab = (C.FREE_SPACE_SLAB[0], C.FREE_SPACE_SLAB[1] * height)
    fs = FreeSpace(
        origin=np.zeros(3),
        ends=rays,
        ground=np.array([cl.ground_z, 0.0, 0.0, 0.0]),
        ref=np.zeros(2),
        slab=slab,
        tolerance=C.FREE_SPACE_TOLERANCE,
        object_height=cfg.crop.ground_cut,
    )
    h = xyz[:, 2] - cl.ground_z
    in_slab = xyz[(h >= slab[0]) & (h <= slab[1]), :2]
    n = 0
    for (P, Q, ext), got in zip(groups, counts):
        boxes = np.array([M._rect_box(hid, (p, q), ext, float(cl.box[2]), height) for p in P for q in Q])
        free = np.array([f for f, _ in ray_counts(boxes, fs, xyz[:1])])
        c, s = np.cos(boxes[:, 6])[:, None], np.sin(boxes[:, 6])[:, None]
        dx, dy = in_slab[None, :, 0] - boxes[:, 0:1], in_slab[None, :, 1] - boxes[:, 1:2]
        depth = np.minimum(
            0.5 * boxes[:, 3:4] - np.abs(c * dx + s * dy), 0.5 * boxes[:, 4:5] - np.abs(-s * dx + c * dy)
        )
        inside = np.count_nonzero(depth > C.FREE_SPACE_INSIDE_TOLERANCE, axis=1)
        assert got.shape == (len(P), len(Q))
        np.testing.assert_array_equal(got.ravel(), free + inside)
        n += int(np.count_nonzero(free)) + int(np.count_nonzero(inside))
    assert n > 20  # (placements that do count something: not a test of zeros)


def _hidden_behind_a_van_past_a_parked_car(monkeypatch, sight_height, rays=False):
    """The car of :func:`_hidden_behind_a_van`, and a labelled car parked near the sensor (top
    1.45 m over the road, 6–10 m off) right on the lines of sight to the road past its visible far
    end. That parked car hides the lower 0.9 m of the far car's face (its returns start there), and
    nothing above: the sensor, 1.73 m up, sees over it."""
    monkeypatch.setattr(C, "MISSING_PLACE_SIGHT_HEIGHT", sight_height)
    monkeypatch.setattr(M, "_place_by_rays", _PLACE_BY_RAYS if rays else (lambda frame, clusters, cfg: clusters))
    van = _face((17.9, -0.2), (17.9, 1.6), GROUND + 0.2, GROUND + 2.2, 0.08)
    car = _face((29.1, 2.6), (29.1, 5.2), GROUND + 0.9, GROUND + 1.5, 0.08)
    parked = _face((6.0, 1.1), (6.0, 2.3), GROUND + 0.2, GROUND + 1.45, 0.08)
    labels = [[20.0, 0.7, GROUND + 1.1, 4.2, 1.8, 2.2, 0.0], [8.0, 1.7, GROUND + 0.725, 4.0, 1.2, 1.45, 0.0]]
    frame = _frame(van, car, parked, boxes=labels, names=["Van", "Car"])
    rows = [r for r in find_missing(frame, RunConfig()) if math.hypot(r["cx"] - 30.0, r["cy"] - 3.9) < 3.0]
    top = max(rows, key=lambda r: r["score"])
    return math.hypot(top["cx"] - 30.0, top["cy"] - 3.1), top["score"]


def test_a_parked_car_the_sensor_sees_over_does_not_hide_the_road_past_a_far_car(monkeypatch):
    """Aimed at the far car's height, the lines of sight to the road past its visible end pass over
    the labelled car parked near the sensor: that road is seen empty, and the hidden extent goes
    towards the van (found). Aimed at the road itself (height share 0), the parked car hides those
    spots as a label at every height did: nothing tells, and the box grows away from the sensor,
    over the road, more than 1 m off."""
    off, score = _hidden_behind_a_van_past_a_parked_car(monkeypatch, C.MISSING_PLACE_SIGHT_HEIGHT)
    assert off < 1.0 and score >= 0.5
    off_low, _ = _hidden_behind_a_van_past_a_parked_car(monkeypatch, 0.0)
    assert off_low > 1.0 > off
    # the frame's rays say it too: those through the road past its visible end reach the ground
    # behind, and the box placed where they let it be is found with the lines aimed at the road
    off_rays, _ = _hidden_behind_a_van_past_a_parked_car(monkeypatch, 0.0, rays=True)
    assert off_rays < 1.0 < off_low


def _car_above_its_lower_body(x0, width=1.7, step=0.1):
    """A car straight ahead of the sensor, seen from behind (rear face at ``x0``), whose lower body
    is hidden (behind something low ahead of it): only returns from 0.75 m up. Its body reaches
    1.0 m; its cabin above, to 1.5 m, 0.2 m narrower, is set back 0.6 m from the rear (a simulated
    car's cabin, :mod:`labelaudit.sim.scene`)."""
    body = _face((x0, -width / 2), (x0, width / 2), GROUND + 0.75, GROUND + 1.0, step)
    cabin = _face((x0 + 0.6, -width / 2 + 0.1), (x0 + 0.6, width / 2 - 0.1), GROUND + 1.05, GROUND + 1.5, step)
    return np.vstack([body, cabin])


@pytest.mark.parametrize("rules", ["before", "now"])
def test_a_car_judged_on_all_its_returns_is_found_with_its_cabin_off_the_faces_and_a_bush_is_not(monkeypatch, rules):
    """A car with no lower-body return is judged on all its returns: seen from behind, its body's
    rear and its cabin's rear, set back, are two parallel faces and only one is counted. A car's
    ramp on all returns (``MISSING_FACE_SHARE_ALL``) finds it; with the lower body's ramp (the rules
    before) it scored under 0.5. A bush of a car's size whose returns are scattered in depth, judged
    on all its returns too, is still no candidate."""
    if rules == "before":
        monkeypatch.setattr(C, "MISSING_FACE_SHARE_ALL", {})
    car = _car_above_its_lower_body(28.0)
    rng = np.random.default_rng(5)
    bush = np.c_[
        rng.uniform(26.0, 29.5, 400), rng.uniform(-7.5, -5.8, 400), rng.uniform(GROUND + 0.8, GROUND + 1.6, 400)
    ]
    trace = SearchTrace()
    rows = find_missing(_frame(car, bush), RunConfig(), trace=trace)
    (car_cluster,) = [c for c, _ in trace.clusters if math.hypot(c.box[0] - 30.0, c.box[1]) < 1.5]
    assert car_cluster.class_name == "Car" and 0.0 < car_cluster.shape_score < 1.0  # share between the ramps' ends
    assert _best(rows, 30.0, 0.0, radius=1.0) >= 0.5 if rules == "now" else _best(rows, 30.0, 0.0) < 0.5
    assert _best(rows, 27.75, -6.65, radius=2.5) < 0.5


@pytest.mark.parametrize("rule", [False, True])
def test_a_car_sized_bush_is_no_candidate_by_its_scatter_along_the_beams_and_a_car_still_is(monkeypatch, rule):
    """Car-sized bushes at 50 and 60 m (simulated sweeps: foliage returns from anywhere in its depth
    and lets some rays through): at that range a few dozen returns fall on its sides' slices as
    a car's would, and without the surface rule they are candidates. Along each beam their returns
    lie tens of centimetres off their neighbours' line — a car's lie within the range noise — and
    with ``MISSING_SURFACE_ROUGH`` they are none. Cars in their place across the road are found
    either way."""
    from labelaudit.sim.raycast import LidarSpec, render_range_image
    from labelaudit.sim.scene import VEGETATION, Scene, SimObject, make_object

    if not rule:
        monkeypatch.setattr(C, "MISSING_SURFACE_ROUGH", (np.inf, np.inf))
    for x, y, yaw in ((50.0, 5.0, 0.0), (60.0, 8.0, 0.2)):
        box = np.array([x, y, GROUND + 0.8, 3.8, 1.7, 1.6, yaw])
        bush = SimObject(VEGETATION, box, box[None].copy(), np.array([0.4]))
        car = make_object("Car", (x, -y), yaw, np.array([3.9, 1.6, 1.55]), GROUND, np.random.default_rng(0))
        scene = Scene(objects=[car], clutter=[bush])  # foliage is porous only with a generator
        pts, _ = render_range_image(scene, LidarSpec(), None, np.random.default_rng(0)).points()
        rows = find_missing(Frame("000001", pts, np.zeros((0, 7)), [], []), RunConfig())
        assert (_best(rows, x, y, radius=3.0) < 0.5) == rule, (
            x,
            y,
        )  # (foliage has no solid body to place: its box may land metres off)
        assert _best(rows, x, -y, radius=1.0) >= 0.5, (x, -y)


def test_the_search_grids_kept_from_one_frame_to_the_next_come_back_clean(monkeypatch):
    """The search keeps its 0.2 m grids per thread and puts back only the cells a frame wrote: a
    frame searched after another gives the rows it gives alone, and the grids are all clean after
    each frame; a search that fails drops them (the next one starts from new grids)."""
    from labelaudit.sim.dataset import simulate_frame

    frames = []
    for seed in (3, 5):
        sim = simulate_frame(0, seed=seed)
        half = len(sim.written_boxes) // 2  # half the labels left out: clusters are found and boxed
        names = list(sim.scene.class_names)[:half]
        frames.append(Frame("000000", sim.points, sim.written_boxes[:half], names, [str(i) for i in range(half)]))

    def clean():
        grids = M._Grids._local.grids
        return not grids.mask.any() and not grids.counts.any() and not grids.over.any() and (grids.comp == -1).all()

    first = find_missing(frames[0], RunConfig())
    assert first and clean()
    second = find_missing(frames[1], RunConfig())
    assert second and clean()
    assert find_missing(frames[0], RunConfig()) == first
    monkeypatch.setattr(M, "_comp_extras", lambda *a: 1 / 0)
    with pytest.raises(ZeroDivisionError):
        find_missing(frames[1], RunConfig())
    assert M._Grids._local.grids is None
    monkeypatch.undo()
    assert find_missing(frames[1], RunConfig()) == second and clean()

"""Simulator: ray-caster known answers, occlusion, label-noise statistics, KITTI round trip, determinism."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from labelaudit import constants as C
from labelaudit.core.params import BOX_FIELDS
from labelaudit.datasets.kitti import KittiReader, read_label, read_velodyne
from labelaudit.sim.dataset import frame_generators, simulate_dataset, simulate_frame
from labelaudit.sim.manifest import read_manifest
from labelaudit.sim.noise import NoiseSpec, perturb_boxes
from labelaudit.sim.raycast import HIT_GROUND, HIT_NOTHING, LidarSpec, SeeThrough, render_range_image
from labelaudit.sim.scene import Scene, SceneSpec, make_object, sample_scene

COARSE = LidarSpec.coarse()
GROUND_Z = -1.73


def _car(x: float, y: float, yaw: float = 0.0, lwh=(4.0, 1.8, 1.5), seed: int = 0):
    return make_object("Car", (x, y), yaw, np.array(lwh), GROUND_Z, np.random.default_rng(seed))


def _surface_distance(points: np.ndarray, parts: np.ndarray) -> np.ndarray:
    """Distance of each point (N, 3) to the nearest face of any of the boxes (P, 7)."""
    best = np.full(len(points), np.inf)
    for b in parts:
        d = points - b[:3]
        c, s = np.cos(b[6]), np.sin(b[6])
        q = np.abs(np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        excess = q - b[3:6] / 2
        outside = np.linalg.norm(np.maximum(excess, 0.0), axis=1)
        inside = np.minimum(-excess.max(axis=1), np.inf)
        dist = np.where(excess.max(axis=1) > 0, outside, inside)
        best = np.minimum(best, dist)
    return best


def _tree_digest(root: Path) -> dict[str, str]:
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# --- range image layout and known answers ---------------------------------------------------------


def test_range_image_layout_follows_waymo_convention():
    ri = render_range_image(Scene([], GROUND_Z), COARSE)
    w = COARSE.columns
    assert ri.range.shape == ri.intensity.shape == ri.hit.shape == (COARSE.beams, w)
    assert np.all(np.diff(ri.inclinations) < 0), "top row must have the highest elevation"
    assert np.isclose(ri.inclinations[0], np.deg2rad(2.0)) and np.isclose(ri.inclinations[-1], np.deg2rad(-24.8))
    assert np.isclose(ri.azimuths[0], np.pi - np.pi / w) and np.isclose(ri.azimuths[-1], -np.pi + np.pi / w)
    assert np.all(np.diff(ri.azimuths) < 0)
    # a yawed extrinsic shifts the sensor-frame azimuths by minus its yaw (Waymo's az_correction)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(0.3), -np.sin(0.3)], [np.sin(0.3), np.cos(0.3)]]
    assert np.allclose(COARSE.azimuths(T), ri.azimuths - 0.3)


def test_ground_ranges_are_closed_form():
    ri = render_range_image(Scene([], GROUND_Z), COARSE)
    expected = 1.73 / np.sin(-ri.inclinations)  # down-looking beams; others see nothing
    for row, inc in enumerate(ri.inclinations):
        if inc < 0 and expected[row] <= COARSE.max_range:
            assert np.allclose(ri.range[row], expected[row], rtol=1e-6)
            assert np.all(ri.hit[row] == HIT_GROUND)
        else:
            assert np.all(ri.range[row] == -1.0) and np.all(ri.hit[row] == HIT_NOTHING)
    pts, _ = ri.points()
    assert np.allclose(pts[:, 2], GROUND_Z, atol=1e-5)


def test_box_face_hit_at_exact_range():
    car = _car(10.0, 0.0)  # rear face of the body at x = 8 m, facing the sensor
    ri = render_range_image(Scene([car], GROUND_Z), COARSE)
    hit_rows, hit_cols = np.nonzero(ri.hit == 0)
    assert len(hit_rows) > 20
    inc, az = ri.inclinations[hit_rows], ri.azimuths[hit_cols]
    front_face = ri.range[hit_rows, hit_cols] * np.cos(inc) * np.cos(az)
    # every return of a body seen from straight behind lies on the x = 8 plane or on the cabin (x ≥ 8)
    assert np.all(front_face >= 8.0 - 1e-4)
    assert np.isclose(front_face.min(), 8.0, atol=1e-4)
    body_rows = np.abs(front_face - 8.0) < 1e-4
    expected = 8.0 / (np.cos(inc) * np.cos(az))
    assert np.allclose(ri.range[hit_rows, hit_cols][body_rows], expected[body_rows], rtol=1e-5)


def test_object_behind_the_sensor_across_the_azimuth_seam():
    # Column azimuths are symmetric under x → −x, so a mirrored car gets exactly as many rays,
    # although its azimuth sector wraps around ±π (the first and last columns).
    front = render_range_image(Scene([_car(10.0, 0.0, 0.0)], GROUND_Z), COARSE)
    back = render_range_image(Scene([_car(-10.0, 0.0, np.pi)], GROUND_Z), COARSE)
    assert back.ray_counts[0] == front.ray_counts[0] > 50
    cols = np.nonzero((back.hit == 0).any(axis=0))[0]
    assert 0 in cols and COARSE.columns - 1 in cols


def test_extrinsic_pose_equals_moving_the_scene():
    # A sensor turned by a whole number of azimuth steps and lifted above a z = 0 ground sees the
    # turned, lifted scene exactly as the unmoved sensor sees the original: columns shift by that number.
    shift = 37
    psi = shift * 2 * np.pi / COARSE.columns
    scene_a = sample_scene(np.random.default_rng(11), SceneSpec(num_vehicles=(12, 12)))
    c, s = np.cos(psi), np.sin(psi)
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[2, 3] = 1.73
    objs = []
    for o in scene_a.objects:

        def move(b):
            out = b.copy()
            out[..., 0], out[..., 1] = c * b[..., 0] - s * b[..., 1], s * b[..., 0] + c * b[..., 1]
            out[..., 2] += 1.73
            out[..., 6] += psi
            return out

        objs.append(type(o)(o.class_name, move(o.box), move(o.parts), o.reflectivity))
    scene_b = Scene(objs, 0.0, scene_a.ground_reflectivity)
    a = render_range_image(scene_a, COARSE)
    b = render_range_image(scene_b, COARSE, T)
    a_rolled = np.roll(a.range, -shift, axis=1)
    assert np.mean(np.roll(a.hit, -shift, axis=1) == b.hit) > 0.999  # grazing rays may flip
    same = np.roll(a.hit, -shift, axis=1) == b.hit
    assert np.allclose(a_rolled[same], b.range[same], atol=1e-3)
    pts_b, hits_b = b.points()
    assert np.allclose(pts_b[hits_b == HIT_GROUND, 2], 0.0, atol=1e-4)
    assert np.abs(a.ray_counts - b.ray_counts).max() <= 2 and a.ray_counts.sum() > 1000


@pytest.mark.parametrize("noisy", [False, True])
def test_points_lie_on_the_ground_or_an_object(noisy: bool):
    rng = np.random.default_rng(3)
    scene = sample_scene(rng, SceneSpec(num_vehicles=(15, 15), num_vru=(3, 3)))
    ri = render_range_image(scene, COARSE, rng=np.random.default_rng(4) if noisy else None)
    pts, hits = ri.points()
    tol = 6 * COARSE.range_noise_std if noisy else 1e-4
    ground = hits == HIT_GROUND
    assert np.all(np.abs(pts[ground, 2] - GROUND_Z) < tol)
    assert np.count_nonzero(~ground) > 500
    for k, obj in enumerate(scene.objects):
        on = hits == k
        if on.any():
            assert _surface_distance(pts[on, :3].astype(float), obj.parts).max() < tol, obj.class_name
    assert 0.0 <= pts[:, 3].min() and pts[:, 3].max() <= 1.0
    if noisy:  # range noise and dropout do what the spec says
        clean = render_range_image(scene, COARSE)
        both = (ri.range > 0) & (clean.range > 0)
        err = (ri.range - clean.range)[both]
        assert abs(err.std() - COARSE.range_noise_std) < 0.002
        lost = np.count_nonzero((clean.range > 0) & (ri.range <= 0)) / np.count_nonzero(clean.range > 0)
        assert COARSE.dropout < lost < COARSE.dropout + COARSE.far_dropout


def test_occluded_object_gets_fewer_points():
    back = _car(25.0, 0.0, seed=1)
    alone = render_range_image(Scene([back], GROUND_Z), COARSE)
    front = _car(12.0, 0.3, seed=2)
    both = render_range_image(Scene([back, front], GROUND_Z), COARSE)
    assert both.ray_counts[0] == alone.ray_counts[0]  # same geometry, only blocked
    assert both.return_counts[0] < 0.5 * alone.return_counts[0]
    assert both.occlusion_fraction[0] > 0.5
    assert both.occlusion_fraction[1] == 0.0 and alone.occlusion_fraction[0] == 0.0
    assert both.return_counts[1] > alone.return_counts[0]  # the nearer car also gets more points


def test_far_objects_get_fewer_points():
    counts = [render_range_image(Scene([_car(d, 0.0)], GROUND_Z), COARSE).return_counts[0] for d in (10, 20, 40)]
    assert counts[0] > counts[1] > counts[2] > 0


def test_scene_objects_do_not_overlap_and_stand_on_the_ground():
    from shapely.geometry import Polygon

    from labelaudit.core.geometry import box_corners

    for seed in range(5):
        scene = sample_scene(np.random.default_rng(seed), SceneSpec(num_vehicles=(25, 25)))
        assert len(scene.objects) >= 20
        polys = [Polygon(box_corners(o.box, "bev")) for o in scene.objects]
        for i in range(len(polys)):
            for j in range(i):
                assert polys[i].intersection(polys[j]).area == 0.0
        for o in scene.objects:
            assert np.isclose(o.box[2] - o.box[5] / 2, GROUND_Z)
            lo = (o.parts[:, 2] - o.parts[:, 5] / 2).min()
            hi = (o.parts[:, 2] + o.parts[:, 5] / 2).max()
            assert np.isclose(lo, GROUND_Z) and np.isclose(hi, GROUND_Z + o.box[5])  # label = union box
            assert 5.0 <= np.hypot(*o.box[:2]) <= 70.0


# --- label noise ------------------------------------------------------------------------------------


def _many_boxes(n: int) -> tuple[np.ndarray, list[str]]:
    rng = np.random.default_rng(0)
    boxes = np.c_[rng.uniform(5, 50, (n, 2)), np.full(n, -1.0), np.tile([4.0, 1.7, 1.5], (n, 1)), rng.uniform(-3, 3, n)]
    return boxes, ["Car"] * n


def test_no_noise_by_default():
    boxes, names = _many_boxes(100)
    written, kinds = perturb_boxes(boxes, names, NoiseSpec(), np.random.default_rng(1))
    assert np.array_equal(written, boxes) and set(kinds) == {"none"}


def test_perturbation_statistics_match_the_spec():
    spec = NoiseSpec.benchmark()
    assert (spec.fraction, spec.gross_fraction, spec.center_std, spec.size_std, spec.yaw_std) == (
        0.2,
        0.02,
        0.3,
        0.2,
        0.1,
    )
    n = 40_000
    boxes, names = _many_boxes(n)
    names[:1000] = ["Pedestrian"] * 1000
    written, kinds = perturb_boxes(boxes, names, spec, np.random.default_rng(2))
    kinds = np.array(kinds)
    assert set(kinds[:1000]) == {"none"} and np.array_equal(written[:1000], boxes[:1000])
    veh = slice(1000, None)
    k, d = kinds[veh], (written - boxes)[veh]
    d[:, 6] = (d[:, 6] + np.pi) % (2 * np.pi) - np.pi
    assert abs(np.mean(k == "jitter") - 0.2) < 0.01
    assert abs(np.mean(np.isin(k, ["shift", "swap_lw", "yaw90"])) - 0.02) < 0.003
    j = d[k == "jitter"]
    assert np.allclose(j[:, :2].std(axis=0), 0.3, rtol=0.05)
    assert np.allclose(j[:, 3:5].std(axis=0), 0.2, rtol=0.05)
    assert np.isclose(j[:, 6].std(), 0.1, rtol=0.05)
    assert np.all(j[:, [2, 5]] == 0.0)  # z and height untouched by default
    assert np.all(d[k == "none"] == 0.0)
    shift = d[k == "shift"]
    assert np.allclose(np.hypot(shift[:, 0], shift[:, 1]), 1.0) and np.all(shift[:, 3:] == 0)
    sw = kinds == "swap_lw"
    assert np.allclose(written[sw][:, [3, 4]], boxes[sw][:, [4, 3]])
    y90 = d[k == "yaw90"]
    assert np.allclose(np.abs(y90[:, 6]), np.pi / 2) and np.all(y90[:, :6] == 0)
    assert min(np.count_nonzero(k == g) for g in ("shift", "swap_lw", "yaw90")) > 150


def test_invalid_specs_are_rejected_with_the_bad_value():
    with pytest.raises(ValueError, match="fraction must be in"):
        NoiseSpec(fraction=1.5)
    with pytest.raises(ValueError, match="center_std"):
        NoiseSpec(center_std=-0.1)
    with pytest.raises(ValueError, match="beams must be >= 1, got 0"):
        LidarSpec(beams=0)
    with pytest.raises(ValueError, match="inclinations_deg"):
        LidarSpec(beams=3, inclinations_deg=(1.0, 2.0, 3.0))


# --- dataset writing ----------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory) -> tuple[Path, object]:
    out = tmp_path_factory.mktemp("sim") / "ds"
    summary = simulate_dataset(out, frames=4, seed=7, noise=NoiseSpec.benchmark(), lidar=COARSE, progress=False)
    return out, summary


def test_dataset_reads_back_with_the_kitti_reader(small_dataset):
    out, summary = small_dataset
    manifest = read_manifest(out).to_pylist()
    reader = KittiReader(out)
    refs = reader.list_units()
    assert [r.key for r in refs] == [f"{i:06d}" for i in range(4)]
    by_id = {m["object_id"]: m for m in manifest if m["labelled"]}
    seen = 0
    for ref in refs:
        frame = next(reader.load_unit(ref))
        assert frame.points.shape[1] == 4 and len(frame.points) > 10_000
        for box, oid, cls in zip(frame.boxes, frame.object_ids, frame.class_names):
            m = by_id[oid]
            assert m["class_name"] == cls
            written = np.array([m[f"written_{n}"] for n in BOX_FIELDS])
            assert np.allclose(box[:6], written[:6], atol=1e-4)
            assert abs((box[6] - written[6] + np.pi) % (2 * np.pi) - np.pi) < 1e-4
            true = np.array([m[f"true_{n}"] for n in BOX_FIELDS])
            if m["perturbation"] == "none":  # only the label file's 2-decimal rounding
                assert np.abs(box[:6] - true[:6]).max() < 0.02
        seen += len(frame.boxes)
    assert seen == summary.num_labels == len(by_id) > 10
    sets = {n: (out / "ImageSets" / f"{n}.txt").read_text().split() for n in ("train", "val")}
    assert sorted(sets["train"] + sets["val"]) == [f"{i:06d}" for i in range(4)] and len(sets["val"]) == 2


def test_manifest_records_points_and_camera_view(small_dataset):
    out, _ = small_dataset
    table = pq.read_table(out / "manifest.parquet")
    rows = table.to_pylist()
    assert {"true_cx", "written_yaw", "delta_cx", "perturbation", "num_points", "occluded"} <= set(table.column_names)
    frame = simulate_frame(0, seed=7, noise=NoiseSpec.benchmark(), lidar=COARSE)
    pts = read_velodyne(out / "training" / "velodyne" / "000000.bin")
    assert np.array_equal(pts, frame.points)
    for m in rows:
        if m["frame_id"] != "000000":
            continue
        on = frame.point_hits == m["scene_index"]
        assert m["num_points"] == np.count_nonzero(on)
        if m["labelled"]:
            assert m["in_camera_fov"] and m["visible_rays"] > 0
            cam = frame.calib.T_cam_velo @ np.r_[m["true_cx"], m["true_cy"], m["true_cz"], 1.0]
            assert cam[2] > 0  # in front of the camera
    labels = read_label(out / "training" / "label_2" / "000000.txt")
    assert len(labels) == sum(1 for m in rows if m["frame_id"] == "000000" and m["labelled"])
    assert np.all((labels.bbox2d[:, 2] <= 1241) & (labels.bbox2d[:, 3] <= 374) & (labels.bbox2d >= 0).all(axis=1))


def test_label_fov_all_labels_every_object(tmp_path):
    simulate_dataset(tmp_path, frames=1, seed=7, lidar=COARSE, progress=False, label_fov="all")
    rows = read_manifest(tmp_path).to_pylist()
    seen = [m["occlusion_fraction"] is not None and m["occlusion_fraction"] <= 0.9 for m in rows]
    assert [m["labelled"] for m in rows] == seen
    assert any(m["labelled"] and not m["in_camera_fov"] for m in rows)


def test_same_seed_same_bytes_and_noise_leaves_points_alone(tmp_path, small_dataset):
    out, _ = small_dataset
    again = tmp_path / "again"
    simulate_dataset(again, frames=4, seed=7, noise=NoiseSpec.benchmark(), lidar=COARSE, progress=False)
    assert _tree_digest(again) == _tree_digest(out)
    clean = tmp_path / "clean"
    simulate_dataset(clean, frames=4, seed=7, lidar=COARSE, progress=False)
    a, b = _tree_digest(out), _tree_digest(clean)
    velo = [k for k in a if "velodyne" in k]
    assert velo and all(a[k] == b[k] for k in velo)
    assert any(a[k] != b[k] for k in a if "label_2" in k)
    other = tmp_path / "other"
    simulate_dataset(other, frames=1, seed=8, lidar=COARSE, progress=False)
    assert _tree_digest(other)["training/velodyne/000000.bin"] != a["training/velodyne/000000.bin"]


@pytest.mark.slow
def test_worker_count_does_not_change_the_files(tmp_path, small_dataset):
    out, _ = small_dataset
    simulate_dataset(
        tmp_path / "w2", frames=4, seed=7, noise=NoiseSpec.benchmark(), lidar=COARSE, workers=2, progress=False
    )
    assert _tree_digest(tmp_path / "w2") == _tree_digest(out)


def test_existing_dataset_is_not_overwritten_silently(small_dataset, tmp_path):
    out, _ = small_dataset
    with pytest.raises(FileExistsError, match="overwrite"):
        simulate_dataset(out, frames=1, lidar=COARSE, progress=False)
    with pytest.raises(ValueError, match="frames must be >= 1, got 0"):
        simulate_dataset(tmp_path / "x", frames=0, progress=False)


def test_frame_streams_are_independent_of_frame_count():
    a = frame_generators(5, 3)["scene"].random(4)
    b = frame_generators(5, 3)["scene"].random(4)
    c = frame_generators(5, 4)["scene"].random(4)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


def test_hidden_objects_get_no_label():
    from labelaudit.sim.kitti_writer import kitti_labels, make_calibration

    calib = make_calibration(np.random.default_rng(0))
    boxes = np.array([_car(15.0, 0.0).box, _car(25.0, 0.5).box, _car(35.0, -1.0).box])
    info = kitti_labels(boxes, boxes, ["Car"] * 3, np.array([0.0, 0.95, np.nan]), calib)
    assert info.in_camera_fov.all()
    assert info.object_index.tolist() == [0, -1, -1] and len(info.lines) == 1
    assert info.occluded.tolist() == [0, 2, 3]


def test_a_given_scene_renders_and_empty_frames_write(tmp_path):
    frame = simulate_frame(0, lidar=COARSE, scene=Scene([_car(12.0, 1.0)], GROUND_Z))
    assert len(frame.labels.lines) == 1 and frame.labels.lines[0].startswith("Car ")
    assert frame.manifest_rows()["num_points"][0] == np.count_nonzero(frame.point_hits == 0) > 50
    empty = SceneSpec(num_vehicles=(0, 0), num_vru=(0, 0))
    summary = simulate_dataset(tmp_path, frames=1, lidar=COARSE, scene=empty, progress=False)
    assert summary.num_labels == 0 and (tmp_path / "training" / "label_2" / "000000.txt").read_text() == ""
    assert len(next(KittiReader(tmp_path).load_unit(KittiReader(tmp_path).list_units()[0])).points) > 1000


def test_clutter_returns_points_occludes_and_is_never_labelled(tmp_path):
    from labelaudit.sim.raycast import HIT_CLUTTER

    plain = sample_scene(np.random.default_rng(5), SceneSpec())
    spec = SceneSpec(num_clutter=(15, 15))
    busy = sample_scene(np.random.default_rng(5), spec)
    assert plain.clutter == [] and len(busy.clutter) >= 10
    assert np.array_equal(plain.boxes, busy.boxes)  # clutter is drawn after the objects
    ri = render_range_image(busy, COARSE)
    pts, hits = ri.points()
    on = hits == HIT_CLUTTER
    assert on.sum() > 200
    assert _surface_distance(pts[on, :3].astype(float), np.stack([c.box for c in busy.clutter])).max() < 1e-4
    wall = make_object("Car", (15.0, 0.0), 0.0, np.array([1.0, 6.0, 3.0]), GROUND_Z, np.random.default_rng(0))
    wall.class_name = "Clutter"
    car = _car(25.0, 0.0)
    hidden = render_range_image(Scene([car], GROUND_Z, clutter=[wall]), COARSE)
    assert hidden.ray_counts[0] > 20 and hidden.visible_counts[0] == 0 and hidden.occlusion_fraction[0] == 1.0
    summary = simulate_dataset(tmp_path, frames=2, lidar=COARSE, scene=spec, progress=False)
    rows = read_manifest(tmp_path).to_pylist()
    assert summary.num_labels > 0 and all(m["class_name"] != "Clutter" for m in rows)


# --- see-through vehicles (windows, the gap under the chassis) ------------------------------------


def _passed_returns(ri, obj: int):
    """Scene-frame returns (N, 3) of the rays that passed object ``obj``'s windows or chassis, and
    the range each ray travelled."""
    rows, cols = np.nonzero((ri.passed == obj) & (ri.range > 0))
    r = ri.range[rows, cols].astype(float)
    inc, az = ri.inclinations[rows], ri.azimuths[cols]
    xyz = np.c_[r * np.cos(inc) * np.cos(az), r * np.cos(inc) * np.sin(az), r * np.sin(inc)]
    return xyz, r


def _depth_in(xy: np.ndarray, box: np.ndarray) -> np.ndarray:
    """BEV depth of points (N, 2) inside the rectangle of ``box`` (negative outside)."""
    c, s = np.cos(box[6]), np.sin(box[6])
    d = xy - box[:2]
    lx, ly = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return np.minimum(box[3] / 2 - np.abs(lx), box[4] / 2 - np.abs(ly))


def test_see_through_rays_end_on_the_ground_behind_the_car_or_inside_it():
    car = _car(12.0, 1.0, yaw=0.4)
    scene = Scene([car], GROUND_Z)
    rng = np.random.default_rng(5)
    opaque = render_range_image(scene, COARSE)
    glass = render_range_image(scene, COARSE, see_through=SeeThrough(glass=1.0), see_rng=rng)
    assert glass.glass_counts[0] > 20 and glass.under_counts[0] == 0
    xyz, r = _passed_returns(glass, 0)
    assert len(xyz) == glass.glass_counts[0]
    near = np.linalg.norm(car.box[:2]) - 0.5 * np.hypot(car.box[3], car.box[4])
    assert np.all(r > near)  # every such ray went on past the car's near side …
    body_top = car.parts[0, 2] + car.parts[0, 5] / 2
    on_ground = np.abs(xyz[:, 2] - GROUND_Z) < 1e-3
    inside = (_depth_in(xyz[:, :2], car.box) > -1e-3) & (np.abs(xyz[:, 2] - body_top) < 1e-3)
    assert np.all(on_ground | inside)  # … to the road or onto the car's interior (the body's top)
    assert np.all(_depth_in(xyz[on_ground, :2], car.box) < 0)  # the road behind the car, not under it
    assert on_ground.sum() > 10
    # opaque cars stop every such ray on their windows: the same rays hit the car without see-through
    rows, cols = np.nonzero(glass.passed == 0)
    assert np.all(opaque.hit[rows, cols] == 0)
    # nothing passes below the windows: no see-through ray crosses the solid body's height inside the box
    assert glass.return_counts[0] < opaque.return_counts[0]


def test_rays_under_the_chassis_end_on_the_ground_under_or_behind_it():
    car = _car(8.0, -0.5, yaw=0.1)
    scene = Scene([car], GROUND_Z)
    ri = render_range_image(scene, COARSE, see_through=SeeThrough(under=1.0), see_rng=np.random.default_rng(1))
    lo, hi = C.SIM_CHASSIS_CLEARANCE["Car"]
    assert lo <= ri.clearance[0] <= hi and ri.under_counts[0] > 5 and ri.glass_counts[0] == 0
    xyz, _ = _passed_returns(ri, 0)
    assert np.allclose(xyz[:, 2], GROUND_Z, atol=1e-3)  # on the road …
    near = np.linalg.norm(car.box[:2]) - 0.5 * np.hypot(car.box[3], car.box[4])
    assert np.all(np.linalg.norm(xyz[:, :2], axis=1) > near)  # … beyond the car's nearest corner
    opaque = render_range_image(scene, COARSE)
    # what the gap lets through lay below the clearance: the car lost exactly those returns
    assert opaque.return_counts[0] - ri.return_counts[0] == ri.under_counts[0]


def test_see_through_off_renders_exactly_the_opaque_scene_and_fractions_nest(tmp_path):
    a = simulate_frame(2, seed=3)
    b = simulate_frame(2, seed=3, see_through=SeeThrough())
    assert np.array_equal(a.points, b.points)
    assert not a.manifest_rows()["glass_rays"] or max(a.manifest_rows()["glass_rays"]) == 0
    counts = [
        int(simulate_frame(2, seed=3, see_through=SeeThrough(glass=g, under=g)).range_image.glass_counts.sum())
        for g in (0.1, 0.3, 0.5)
    ]
    assert 0 < counts[0] < counts[1] < counts[2]  # one draw per (ray, part): a larger share passes a superset
    with pytest.raises(ValueError, match="glass must be a share"):
        SeeThrough(glass=1.5)
    summary = simulate_dataset(
        tmp_path / "st", frames=2, seed=3, progress=False, see_through=SeeThrough(glass=0.5, under=0.5)
    )
    table = pq.read_table(summary.manifest)
    assert sum(table.column("glass_rays").to_pylist()) > 0 and sum(table.column("under_rays").to_pylist()) > 0
    meta = table.schema.metadata[b"labelaudit.see_through"].decode()
    assert '"glass": 0.5' in meta and '"under": 0.5' in meta

"""Per-box point selection: Open3D against the NumPy reference, margin and ground cut, real crops."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from labelaudit.config import CropParams
from labelaudit.datasets.kitti import KittiReader, read_velodyne
from labelaudit.infer.crop import crop_frame, crop_frame_pair, points_in_boxes_numpy, refine_crop, selection_boxes


def _face_distance(points: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(K, N) distance of each point to the nearest face plane of each selection box (box frame)."""
    out = []
    for cx, cy, cz, l, w, h, yaw in boxes:
        d = points[:, :3].astype(float) - [cx, cy, cz]
        c, s = np.cos(yaw), np.sin(yaw)
        local = np.abs(np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]])
        out.append(np.min(np.abs(local - [l / 2, w / 2, h / 2]), axis=1))
    return np.array(out)


@pytest.mark.parametrize(("margin", "ground_cut"), [(0.0, 0.0), (0.1, 0.1), (0.3, 0.5)])
def test_open3d_matches_reference_on_random_rotated_boxes(margin: float, ground_cut: float) -> None:
    rng = np.random.default_rng(int(margin * 10 + ground_cut * 100))
    points = np.c_[rng.uniform(-12, 12, (60_000, 3)), rng.uniform(0, 1, 60_000)].astype(np.float32)
    boxes = np.c_[rng.uniform(-8, 8, (25, 3)), rng.uniform(0.4, 6.0, (25, 3)), rng.uniform(-np.pi, np.pi, 25)]
    got = crop_frame(points, boxes, CropParams(margin=margin, ground_cut=ground_cut))
    ref = points_in_boxes_numpy(points, boxes, margin, ground_cut)
    near = _face_distance(points, selection_boxes(boxes, margin, ground_cut)) < 1e-9
    assert len(got) == len(boxes)
    total = 0
    for k, (a, b) in enumerate(zip(got, ref)):
        assert a.dtype == np.int64 and np.all(np.diff(a) > 0)  # sorted, unique
        diff = np.setxor1d(a, b)
        assert np.all(near[k, diff]), f"box {k}: {len(diff)} points differ away from the faces"
        total += len(a)
    assert total > 1000  # the boxes really hold points


def test_margin_widens_only_bev_and_ground_cut_raises_bottom() -> None:
    box = np.array([[10.0, 5.0, 1.0, 4.0, 2.0, 2.0, 0.0]])  # x 8..12, y 4..6, z 0..2
    pts = np.array(
        [
            [10.0, 5.0, 1.0],  # 0 centre
            [12.05, 5.0, 1.0],  # 1 5 cm beyond the front
            [10.0, 3.95, 1.0],  # 2 5 cm beyond the right side
            [10.0, 5.0, 2.05],  # 3 5 cm above the top
            [10.0, 5.0, 0.05],  # 4 5 cm above the bottom
            [10.0, 5.0, 0.15],  # 5 15 cm above the bottom
            [12.15, 5.0, 1.0],  # 6 15 cm beyond the front
        ]
    )
    for fn in (
        lambda m, g: crop_frame(pts, box, CropParams(m, g))[0],
        lambda m, g: points_in_boxes_numpy(pts, box, m, g)[0],
    ):
        assert fn(0.0, 0.0).tolist() == [0, 4, 5]
        assert fn(0.1, 0.0).tolist() == [0, 1, 2, 4, 5]  # top gets no margin
        assert fn(0.1, 0.1).tolist() == [0, 1, 2, 5]
        assert fn(0.2, 0.1).tolist() == [0, 1, 2, 5, 6]
        assert fn(0.0, 2.5).tolist() == []  # cut above the top


def test_rotated_box_and_inclusive_faces() -> None:
    # A box turned by 90°: its length runs along y.
    box = np.array([[0.0, 0.0, 0.0, 4.0, 2.0, 2.0, np.pi / 2]])
    pts = np.array([[0.0, 1.9, 0.0], [1.9, 0.0, 0.0], [0.0, 2.1, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    assert crop_frame(pts, box, CropParams(0.0, 0.0))[0].tolist() == [0, 3, 4]
    # Faces of an axis-aligned box are exact in floating point: both selections include them.
    axis = np.array([[0.0, 0.0, 0.0, 2.0, 2.0, 2.0, 0.0]])
    faces = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0, 0, -1.0], [1.001, 0, 0]])
    assert crop_frame(faces, axis, CropParams(0.0, 0.0))[0].tolist() == [0, 1, 2, 3, 4]
    assert points_in_boxes_numpy(faces, axis)[0].tolist() == [0, 1, 2, 3, 4]


def test_empty_inputs_and_shapes() -> None:
    pts = np.zeros((0, 4), np.float32)
    box = np.array([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0]])
    assert [len(i) for i in crop_frame(pts, box, CropParams())] == [0]
    assert crop_frame(np.ones((5, 3)), np.zeros((0, 7)), CropParams()) == []
    with pytest.raises(ValueError, match=r"\(K, 7\)"):
        crop_frame(np.ones((5, 3)), np.ones((2, 6)), CropParams())
    with pytest.raises(ValueError, match=r"\(N, ≥3\)"):
        crop_frame(np.ones((5, 2)), box, CropParams())


def _boundary_points(boxes: np.ndarray, params: CropParams, rng: np.random.Generator, per_box: int) -> np.ndarray:
    """Points on and within a few ulps of every face of the selection boxes (float32, as read)."""
    out = []
    for cx, cy, cz, l, w, h, yaw in selection_boxes(boxes, params.margin, params.ground_cut):
        local = rng.uniform(-0.5, 0.5, (per_box, 3)) * [l, w, h]
        axis = rng.integers(0, 3, per_box)
        local[np.arange(per_box), axis] = np.where(rng.random(per_box) < 0.5, -0.5, 0.5) * np.array([l, w, h])[axis]
        c, s = np.cos(yaw), np.sin(yaw)
        world = np.c_[cx + c * local[:, 0] - s * local[:, 1], cy + s * local[:, 0] + c * local[:, 1], cz + local[:, 2]]
        world = world.astype(np.float32)
        out.append(np.nextafter(world, world + rng.choice([-1, 0, 1], world.shape).astype(np.float32)))
    return np.concatenate(out)


@pytest.mark.parametrize("ground_cut", [0.0, 0.25, 0.15])
def test_refined_crop_equals_open3d_crop(ground_cut: float) -> None:
    """The narrow crop taken from the wide one has exactly Open3D's indices, also for points on the faces."""
    rng = np.random.default_rng(7)
    boxes = np.c_[rng.uniform(-8, 8, (30, 3)), rng.uniform(0.4, 6.0, (30, 3)), rng.uniform(-np.pi, np.pi, 30)]
    boxes[3:6, 6] = [np.pi / 2, -np.pi, 1e-12]
    # Dyadic boxes at yaw 0: faces exact in floating point, so points land exactly on them (ties).
    boxes[:3] = [
        [1.5, -2.25, 0.5, 4.0, 2.0, 1.5, 0.0],
        [-3.0, 4.5, 0.25, 1.75, 0.75, 2.0, 0.0],
        [6.0, 6.0, -1.0, 3.5, 1.5, 1.0, 0.0],
    ]
    params = CropParams(margin=0.125, ground_cut=ground_cut, fit_margin=0.5)
    random = rng.uniform(-12, 12, (40_000, 3)).astype(np.float32)
    edges = _boundary_points(boxes, params, rng, 400)  # on the narrow faces: ties decide
    points = np.c_[np.concatenate([random, edges]), np.zeros(len(random) + len(edges), np.float32)]
    narrow, wide = crop_frame_pair(points, boxes, params)
    exact = selection_boxes(boxes[:3], params.margin, params.ground_cut)
    local = np.abs(points[:, None, :3].astype(float) - exact[:, :3])  # yaw 0: box frame = world frame
    ties = np.sum(np.any(local == exact[:, 3:6] / 2, axis=2) & np.all(local <= exact[:, 3:6] / 2, axis=2))
    assert ties > 100
    expected = crop_frame(points, boxes, params)
    expected_wide = crop_frame(points, boxes, CropParams(margin=0.5, ground_cut=ground_cut))
    on_face = 0
    for k in range(len(boxes)):
        np.testing.assert_array_equal(narrow[k], expected[k])
        np.testing.assert_array_equal(wide[k], expected_wide[k])
        assert narrow[k].dtype == np.int64 and np.all(np.isin(narrow[k], wide[k]))
        on_face += np.sum(expected[k] >= len(random))
    assert on_face > 2000 and sum(len(w) - len(n) for n, w in zip(narrow, wide)) > 1000  # ties and a real difference
    # Fit margin not wider: one crop, the same list for both.
    same, same_fit = crop_frame_pair(points, boxes, CropParams(margin=0.125, ground_cut=ground_cut, fit_margin=0.125))
    assert same is same_fit and all(np.array_equal(a, b) for a, b in zip(same, expected))


def test_refine_crop_rejects_mismatched_candidates() -> None:
    box = np.array([[0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="one candidate array per box"):
        refine_crop(np.zeros((3, 3)), box, [], CropParams())


def test_real_refined_crop_equals_open3d_crop(realdata: Path) -> None:
    """On the real KITTI frames, with the pipeline's default margins and a few others."""
    reader = KittiReader(realdata / "openpcdet-pr653-kitti")
    boxes_seen = 0
    for ref in reader.list_units():
        frame = reader.load_frame(ref.key)
        for params in (
            CropParams(),
            CropParams(margin=0.0, ground_cut=0.0, fit_margin=0.3),
            CropParams(margin=0.05, ground_cut=0.3, fit_margin=1.0),
        ):
            narrow, wide = crop_frame_pair(frame.points, frame.boxes, params)
            for a, b in zip(narrow, crop_frame(frame.points, frame.boxes, params)):
                np.testing.assert_array_equal(a, b)
            for a, b in zip(
                wide, crop_frame(frame.points, frame.boxes, CropParams(params.fit_margin, params.ground_cut))
            ):
                np.testing.assert_array_equal(a, b)
        boxes_seen += len(frame.boxes)
    assert boxes_seen >= 10


def _gt_database_rows(realdata: Path):
    root = realdata / "openpcdet-pr653-kitti"
    reader = KittiReader(root)
    for ref in reader.list_units():
        frame = reader.load_frame(ref.key)
        for k, (oid, name) in enumerate(zip(frame.object_ids, frame.class_names)):
            # OpenPCDet names crops <frame>_<class>_<i>, i = row of the label file; KITTI writes
            # DontCare rows last, so i is also our index among the non-DontCare rows.
            index = oid.split(":")[1]
            yield frame, k, read_velodyne(root / "gt_database" / f"{frame.frame_id}_{name}_{index}.bin")


def test_real_crops_match_openpcdet_gt_database(realdata: Path) -> None:
    """OpenPCDet's CPU points-in-box test adds 1 cm in BEV; with that margin the point sets are equal."""
    n = 0
    for frame, k, gt in _gt_database_rows(realdata):
        idx = crop_frame(frame.points, frame.boxes[k : k + 1], CropParams(margin=0.01, ground_cut=0.0))[0]
        ours = frame.points[idx].copy()
        ours[:, :3] -= frame.boxes[k, :3].astype(np.float32)  # gt_database stores points relative to the centre
        assert len(ours) == len(gt), (frame.frame_id, k)
        a, b = ours[np.lexsort(ours.T)], gt[np.lexsort(gt.T)]
        np.testing.assert_allclose(a, b, atol=1e-5)
        n += 1
    assert n == 10


def test_real_exact_box_counts_against_gt_database(realdata: Path) -> None:
    """With margin 0 the exact boxes hold a subset of the gt_database crop; the rest lies within 1 cm outside."""
    counts = []
    for frame, k, gt in _gt_database_rows(realdata):
        idx = crop_frame(frame.points, frame.boxes[k : k + 1], CropParams(margin=0.0, ground_cut=0.0))[0]
        wide = crop_frame(frame.points, frame.boxes[k : k + 1], CropParams(margin=0.01, ground_cut=0.0))[0]
        assert np.all(np.isin(idx, wide))
        counts.append((len(idx), len(gt)))
    ours, theirs = np.array(counts).T
    assert np.all(ours <= theirs) and np.all(theirs - ours <= 6)
    assert np.sum(np.abs(ours - theirs) <= 2) >= 8  # 8 of the 10 boxes agree within ±2 points


def test_frames_with_many_boxes_crop_through_the_grid_to_identical_indices():
    """A 10,000-line label file would take 27 s in Open3D's crop (it tests every point against
    every box, K·N); from CROP_GRID_MIN_BOXES boxes on the crop goes through a BEV grid. Its
    indices must equal Open3D's exactly, on faces, corners and non-finite points too."""
    from dataclasses import replace

    from labelaudit import constants as C
    from labelaudit.core.geometry import box_corners
    from labelaudit.infer.crop import bev_candidates, crop_frame, crop_frame_pair, selection_boxes

    params = CropParams()
    for seed in range(6):
        rng = np.random.default_rng(seed)
        k = C.CROP_GRID_MIN_BOXES + 16
        pts = np.c_[rng.uniform(-60, 60, (20000, 2)), rng.uniform(-2, 2, 20000), rng.uniform(0, 1, 20000)].astype(
            np.float32
        )
        boxes = np.c_[
            rng.uniform(-50, 50, (k, 2)),
            rng.uniform(-1, 0.5, k),
            rng.uniform(0.3, 8, (k, 1)),
            rng.uniform(0.3, 3, (k, 1)),
            rng.uniform(0.05, 3, k),
            rng.uniform(-4, 4, k),
        ]
        for margin in (params.margin, params.fit_margin):  # points exactly on the corners of both crops
            sel = selection_boxes(boxes, margin, params.ground_cut)
            corners = np.concatenate([box_corners(b, "3d") for b in sel[:30] if b[5] > 0])
            pts = np.r_[pts, np.c_[corners, np.zeros(len(corners))].astype(np.float32)]
        pts = np.r_[
            pts, np.array([[np.nan, 0, 0, 0], [np.inf, 1, 1, 0], [1e38, 1e38, 0, 0], [0, 0, np.nan, 0]], np.float32)
        ]
        narrow, wide = crop_frame_pair(pts, boxes, params)
        assert all(np.array_equal(a, b) for a, b in zip(narrow, crop_frame(pts, boxes, params), strict=True))
        assert all(
            np.array_equal(a, b)
            for a, b in zip(wide, crop_frame(pts, boxes, replace(params, margin=params.fit_margin)), strict=True)
        )
        sel = selection_boxes(boxes, params.fit_margin, params.ground_cut)
        assert all(np.isin(w, c).all() for w, c in zip(wide, bev_candidates(pts, sel), strict=True))  # a superset


def _open3d_whole_frame(points: np.ndarray, boxes: np.ndarray, params: CropParams) -> list[np.ndarray]:
    """Open3D asked about every point of the frame (what crop_frame did before its BEV index)."""
    import open3d as o3d

    from labelaudit.core.geometry import rotation_z

    cloud = o3d.utility.Vector3dVector(np.ascontiguousarray(points[:, :3], dtype=np.float64))
    sel = selection_boxes(boxes, params.margin, params.ground_cut)
    out = []
    for box, R in zip(sel, rotation_z(sel[:, 6])):
        if box[5] <= 0:
            out.append(np.empty(0, dtype=np.int64))
            continue
        obb = o3d.geometry.OrientedBoundingBox(box[:3], R, box[3:6])
        out.append(np.sort(np.asarray(obb.get_point_indices_within_bounding_box(cloud), dtype=np.int64)))
    return out


@pytest.mark.parametrize("spread", [10.0, 3000.0])  # 3 km apart: the index grid coarsens its cells
def test_indexed_crop_equals_open3d_on_the_whole_frame(spread: float) -> None:
    """The BEV index only chooses which points Open3D is asked about: same indices as asking about all,
    also for points on the faces, points far outside, non-finite points and empty selections."""
    rng = np.random.default_rng(int(spread))
    boxes = np.c_[rng.uniform(-8, 8, (30, 3)), rng.uniform(0.4, 6.0, (30, 3)), rng.uniform(-np.pi, np.pi, 30)]
    boxes[:3] = [
        [1.5, -2.25, 0.5, 4.0, 2.0, 1.5, 0.0],
        [-3.0, 4.5, 0.25, 1.75, 0.75, 2.0, np.pi / 2],
        [6.0, 6.0, -1.0, 3.5, 1.5, 0.05, 0.0],
    ]
    boxes[-1, :2] = spread  # one box far from the others
    params = CropParams(margin=0.125, ground_cut=0.1, fit_margin=0.5)
    random = rng.uniform(-12, 12, (40_000, 3)).astype(np.float32)
    far = (boxes[-1, :3] + rng.normal(0, 2.0, (2000, 3))).astype(np.float32)
    edges = _boundary_points(boxes, params, rng, 300)
    xyz = np.concatenate([random, far, edges, [[np.nan, 0, 0], [np.inf, 1, 1], [1e30, 0, 0]]]).astype(np.float32)
    points = np.c_[xyz, np.zeros(len(xyz), np.float32)]
    for p in (params, CropParams(margin=0.5, ground_cut=0.1)):
        got, want = crop_frame(points, boxes, p), _open3d_whole_frame(points, boxes, p)
        for a, b in zip(got, want):
            np.testing.assert_array_equal(a, b)
        assert sum(map(len, want)) > 1000 and len(want[2]) == 0 and len(want[-1]) > 10


def test_real_indexed_crop_equals_open3d_on_the_whole_frame(realdata: Path) -> None:
    reader = KittiReader(realdata / "openpcdet-pr653-kitti")
    for ref in reader.list_units():
        frame = reader.load_frame(ref.key)
        for p in (CropParams(), CropParams(margin=0.5, ground_cut=0.1)):
            for a, b in zip(
                crop_frame(frame.points, frame.boxes, p), _open3d_whole_frame(frame.points, frame.boxes, p)
            ):
                np.testing.assert_array_equal(a, b)


def test_grid_index_counting_sort_equals_the_numpy_sort(monkeypatch) -> None:
    """Both ways of building the BEV index give the same keys and point order (NaN points out)."""
    from labelaudit import constants as C
    from labelaudit.infer import crop as CR

    rng = np.random.default_rng(11)
    pts = np.c_[rng.uniform(-30, 30, (20_000, 3)), np.zeros(20_000)].astype(np.float32)
    pts[:5, 0] = np.nan
    pts[5:10] = np.round(pts[5:10])  # on cell edges
    boxes = np.c_[rng.uniform(-20, 20, (12, 3)), rng.uniform(0.4, 6.0, (12, 3)), rng.uniform(-np.pi, np.pi, 12)]
    sel = selection_boxes(boxes, 0.5, 0.1)
    dense = CR._BevIndex(pts, sel, C.CROP_GRID_CELL)
    monkeypatch.setattr(C, "CROP_GRID_DENSE_CELLS", 0)
    sparse = CR._BevIndex(pts, sel, C.CROP_GRID_CELL)
    assert (
        np.array_equal(dense.keys, sparse.keys)
        and np.array_equal(dense.index, sparse.index)
        and len(dense.index) > 1000
    )
    for a, b in zip(dense.candidates(slice(None)), sparse.candidates(slice(None))):
        assert np.array_equal(a, b)

"""`show` pictures: recomputed from the dataset they equal the rows; what is drawn is where p_G puts it."""

from __future__ import annotations

import io
import json
import shutil

import matplotlib.image as mpimg
import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.colors import Normalize

from _core_synth import face_points
from labelaudit.config import config_from_params, load_config
from labelaudit.results import open_results
from labelaudit.viz.objects import (
    ViewError,
    audit_view,
    frame_rows,
    load_frame,
    object_row,
    open_source,
    recompute,
)
from labelaudit.viz.show import (
    HEAT_CMAP,
    corner_covariances,
    parse_size,
    render_frame,
    render_object,
    worst_order,
)
from viz_data import simulate_and_infer


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate_and_infer(tmp_path_factory.mktemp("viz_show"))


def _png_shape(png: bytes) -> tuple[int, ...]:
    return mpimg.imread(io.BytesIO(png), format="png").shape


def test_config_from_params_is_the_inverse_of_to_dict():
    for fmt in ("kitti", "waymo-v2"):
        cfg = load_config(None, fmt)
        back = config_from_params(json.loads(json.dumps(cfg.to_dict())))  # through JSON, as in a manifest
        assert back == cfg and back.param_hash() == cfg.param_hash()


def test_recomputed_objects_equal_their_rows(sim):
    """The picture's numbers are the row's: same crop, same model calls, same config."""
    _, results = sim
    opened = open_results(results)
    source = open_source(opened)
    rows = opened.read().to_pylist()
    assert len(rows) >= 10
    for row in rows:
        audit = recompute(source, row)
        assert len(audit.points) == row["num_points"]
        assert audit.jiou_gt == row["jiou_gt"]
        assert audit.label_error == row["label_error"]
        assert (np.isnan(audit.sigma_hat) and row["sigma_hat"] is None) or audit.sigma_hat == row["sigma_hat"]
        np.testing.assert_array_equal(
            audit.fit.box[[0, 1, 3, 4, 6]], [row[c] for c in ("fit_cx", "fit_cy", "fit_length", "fit_width", "fit_yaw")]
        )
        np.testing.assert_allclose(np.trace(corner_covariances(audit), axis1=1, axis2=2), row["corner_tv"], rtol=1e-12)
        assert audit.matches_row and audit.mismatches(rtol=0.0) == {}


def test_object_picture_has_the_requested_size_and_shows_p_g(sim):
    _, results = sim
    opened = open_results(results)
    row = max(opened.read().to_pylist(), key=lambda r: r["label_error"])
    audit = recompute(open_source(opened), row)
    pic = render_object(audit, (500, 420))
    assert _png_shape(pic.png)[:2] == (420, 500)
    # The heatmap is p_G: back to mass it sums to what the grid holds (≈ 1), the drawn array is p_G / cell area.
    cell = np.outer(np.diff(audit.grid.y_edges), np.diff(audit.grid.x_edges))
    np.testing.assert_allclose(pic.density * cell / (audit.box[3] * audit.box[4]), audit.mass, rtol=1e-12)
    assert 0.97 < float(audit.mass.sum()) <= 1.0 + 1e-9
    # Geometry in the label's frame: the label is centred and axis-aligned, C1 is the corner nearest the sensor.
    l, w = audit.box[3], audit.box[4]
    assert np.allclose(np.abs(pic.label_corners), [l / 2, w / 2])
    sensor_local = pic.sensor_direction * np.hypot(*(audit.sensor_origin[:2] - audit.box[:2]))
    d = np.linalg.norm(pic.ellipse_centres - sensor_local, axis=1)
    assert np.argmin(d) == 0
    assert (
        pic.caption.startswith(row["class_name"])
        and f"{row['jiou_gt']:.3f}" in pic.caption
        and f"{row['label_error']:.3f}" in pic.caption
    )
    # The suggested box is the fit's.
    assert np.allclose(pic.fit_corners.mean(axis=0), _local(audit.fit.box[:2], audit.box))


def _local(xy, box):
    c, s = np.cos(box[6]), np.sin(box[6])
    d = np.asarray(xy, float) - box[:2]
    return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


def test_rendered_heatmap_pixels_are_p_g(sim):
    """Without overlays the axes fill the PNG: each pixel's colour is the colour map of p_G in its cell."""
    _, results = sim
    opened = open_results(results)
    row = min(opened.read().to_pylist(), key=lambda r: r["jiou_gt"])
    audit = recompute(open_source(opened), row)
    W, H = 600, 560
    pic = render_object(audit, (W, H), overlays=False)
    img = mpimg.imread(io.BytesIO(pic.png), format="png")[..., :3]
    x0, x1, y0, y1 = pic.view
    xe, ye = audit.grid.x_edges, audit.grid.y_edges
    cmap, norm = colormaps[HEAT_CMAP], Normalize(0.0, max(1.0, float(pic.density.max())))
    checked = bad = 0
    for j in range(0, len(ye) - 1, 3):
        for i in range(0, len(xe) - 1, 3):
            xc, yc = 0.5 * (xe[i] + xe[i + 1]), 0.5 * (ye[j] + ye[j + 1])
            px, py = (xc - x0) / (x1 - x0) * W, (y1 - yc) / (y1 - y0) * H
            half_px = 0.5 * (xe[1] - xe[0]) / (x1 - x0) * W
            if not (2 <= px < W - 2 and 2 <= py < H - 2) or half_px < 1.5:
                continue
            want = np.asarray(cmap(norm(pic.density[j, i]))[:3])
            got = img[int(py), int(px)]
            checked += 1
            bad += int(np.max(np.abs(got - want)) > 3 / 255)
    assert checked > 100 and bad <= 0.02 * checked


BOX = np.array([0.0, 12.0, -0.9, 4.2, 1.8, 1.5, 0.0])  # sensor at the origin: the −y face is the near one


def _view(points):
    cfg = load_config(None, "kitti")
    return audit_view(BOX, points, points, "Car", cfg, np.zeros(3))


def test_a_dense_object_is_nearly_uniform_inside_its_box():
    pts = face_points(BOX, ["-x", "+x", "-y", "+y"], 300, noise=0.02, seed=1)
    audit = _view(pts)
    pic = render_object(audit, (400, 380))
    xe, ye = audit.grid.x_edges, audit.grid.y_edges
    xc, yc = 0.5 * (xe[1:] + xe[:-1]), 0.5 * (ye[1:] + ye[:-1])
    inner = (np.abs(yc)[:, None] < 0.35 * BOX[4]) & (np.abs(xc)[None, :] < 0.4 * BOX[3])
    v = pic.density[inner]
    assert audit.jiou_gt > 0.95
    assert abs(v.mean() - 1.0) < 0.03 and v.std() / v.mean() < 0.03  # the label's uniform density


def test_a_one_face_object_is_sharp_on_the_observed_side():
    """Fig. 8: points on the near (−y) face pin that side; the far side blurs outwards."""
    pts = face_points(BOX, ["-y"], 120, noise=0.02, seed=2)
    audit = _view(pts)
    pic = render_object(audit, (400, 380))
    ye = audit.grid.y_edges
    yc = 0.5 * (ye[1:] + ye[:-1])
    mass = audit.mass.sum(axis=1)  # per row of the grid (across the box)
    w = BOX[4]
    near_out, far_out = mass[yc < -w / 2].sum(), mass[yc > w / 2].sum()
    assert far_out > 3 * near_out
    inside = np.abs(yc) < w / 2
    near_in, far_in = mass[inside & (yc < 0)].sum(), mass[inside & (yc > 0)].sum()
    assert near_in > far_in
    # The corners on the observed face are the best constrained; C1 is one of them.
    tv = np.trace(pic.ellipse_covs, axis1=1, axis2=2)
    assert pic.ellipse_centres[0][1] < 0 and pic.ellipse_centres[1][1] < 0 and tv[:2].max() < tv[2:].min()
    # The arrow to the sensor points down (−y) in the box frame.
    np.testing.assert_allclose(pic.sensor_direction, [0.0, -1.0], atol=1e-12)


def test_frame_picture_numbers_the_worst(sim):
    _, results = sim
    opened = open_results(results)
    source = open_source(opened)
    fid = opened.read(["frame_id"]).column("frame_id")[0].as_py()
    rows = frame_rows(opened, fid).to_pylist()
    frame = load_frame(source, fid)
    for by in ("jiou_gt", "label_error"):
        pic = render_frame(fid, frame.points, rows, by, (700, 500), worst=3)
        assert _png_shape(pic.png)[:2] == (500, 700)
        scores = np.array([r[by] for r in rows])
        ranked = sorted(rows, key=lambda r: (r[by] if by == "jiou_gt" else -r[by], r["object_index"]))
        assert pic.numbered == [r["object_index"] for r in ranked[:3]]
        np.testing.assert_array_equal(pic.scores, scores)
    np.testing.assert_array_equal(worst_order(np.array([0.5, np.nan, 0.1, 0.9]), "jiou_gt"), [2, 0, 3])
    np.testing.assert_array_equal(worst_order(np.array([0.5, np.nan, 0.1, 0.9]), "label_error"), [3, 0, 2])


def test_lookups_name_the_nearest_valid_ids(sim):
    _, results = sim
    opened = open_results(results)
    with pytest.raises(ViewError, match=r"no frame '1'.*nearest: 000001, 000000, 000002"):
        frame_rows(opened, "1")
    rows = frame_rows(opened, "000001")
    with pytest.raises(ViewError, match=r"no audited object 99; nearest objects"):
        object_row(rows, 99)
    assert object_row(rows, 0)["object_index"] == 0


def test_a_moved_dataset_is_named_and_dataset_overrides_it(sim, tmp_path):
    data, results = sim
    moved = tmp_path / "moved"
    shutil.copytree(results, tmp_path / "res")
    manifest = json.loads((tmp_path / "res" / "manifest.json").read_text())
    manifest["input"] = str(tmp_path / "gone")
    (tmp_path / "res" / "manifest.json").write_text(json.dumps(manifest))
    opened = open_results(tmp_path / "res")
    with pytest.raises(ViewError, match="not there any more.*--dataset"):
        open_source(opened)
    shutil.copytree(data, moved)
    source = open_source(opened, moved)
    row = opened.read().to_pylist()[0]
    assert recompute(source, row).matches_row


def test_edited_labels_are_refused(sim, tmp_path):
    data, results = sim
    copy = tmp_path / "data"
    shutil.copytree(data, copy)
    opened = open_results(results)
    row = opened.read().to_pylist()[0]
    label = copy / "training" / "label_2" / f"{row['frame_id']}.txt"
    lines = label.read_text().splitlines()
    parts = lines[0].split()
    parts[11] = f"{float(parts[11]) + 0.5:.2f}"  # move the first box 0.5 m along the camera x
    label.write_text("\n".join([" ".join(parts)] + lines[1:]) + "\n")
    with pytest.raises(ViewError, match="differs from the results row"):
        recompute(open_source(opened, copy), row)


def test_parse_size():
    assert (
        parse_size("640x480") == (640, 480) and parse_size("300") == (300, 300) and parse_size("200×100") == (200, 100)
    )
    for bad in ("x", "10x10", "abc", "640x480x2", "99999"):
        with pytest.raises(ValueError, match="WIDTHxHEIGHT"):
            parse_size(bad)


@pytest.mark.realdata
def test_real_kitti_pictures_match_their_rows(realdata, tmp_path):
    from labelaudit.config import resolve_config
    from labelaudit.executors import SerialExecutor
    from labelaudit.infer.run import InferRequest, run_infer

    root = realdata / "openpcdet-pr653-kitti"
    run_infer(
        InferRequest(root, tmp_path / "res", "kitti", limit=2), resolve_config(None, "kitti"), executor=SerialExecutor()
    )
    opened = open_results(tmp_path / "res")
    source = open_source(opened)
    rows = [r for r in opened.read().to_pylist() if r["status"] in ("ok", "few_points", "no_points")]
    assert rows
    for row in rows:
        assert recompute(source, row).mismatches(rtol=0.0) == {}
    pic = render_object(recompute(source, rows[0]))
    assert _png_shape(pic.png)[:2] == (600, 640)


@pytest.mark.parametrize("fmt", ["waymo-v2", "waymo-v1"])
def test_waymo_frames_are_found_in_their_segment(fmt, tmp_path):
    """Waymo frame ids are '<segment>:<timestamp>': the picture loads the frame from its segment file."""
    from labelaudit.config import resolve_config
    from labelaudit.executors import SerialExecutor
    from labelaudit.infer.run import InferRequest, run_infer
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    roots = simulate_waymo_dataset(tmp_path / "waymo", segments=2, frames=2, seed=5)
    run_infer(InferRequest(roots[fmt], tmp_path / "res", fmt), resolve_config(None, fmt), executor=SerialExecutor())
    opened = open_results(tmp_path / "res")
    source = open_source(opened)
    rows = [r for r in opened.read().to_pylist() if r["status"] in ("ok", "few_points", "no_points")]
    last = max(rows, key=lambda r: (r["frame_id"], r["object_index"]))  # a frame of the second segment
    for row in (rows[0], last):
        audit = recompute(source, row)
        assert audit.mismatches(rtol=0.0) == {}
    assert len({r["frame_id"].rsplit(":", 1)[0] for r in rows}) == 2

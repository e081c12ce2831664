"""Tracks through the real pipeline: simulated Waymo segments with errors inside tracks → infer (pool,
resume) → track columns, tracks.parquet, show and report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from labelaudit import results as R
from labelaudit.infer.run import InferRequest, infer_dataset
from labelaudit.sim.tracknoise import ISSUE_OF_KIND, TrackNoiseSpec
from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_manifest, write_waymo_v2


@pytest.fixture(scope="module")
def segments(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Any]]:
    root = tmp_path_factory.mktemp("tracks")
    segs = [
        simulate_waymo_segment(
            seed=21 + i,
            frames=9,
            size="small",
            chunks=2,
            moving_fraction=0.5,
            track_noise=TrackNoiseSpec(error_fraction=0.12, kinds=("length", "flip", "centre")),
        )
        for i in range(2)
    ]
    for s in segs:
        write_waymo_v2(s, root / "waymo_v2")
    write_manifest(segs, root / "manifest.parquet")
    return root, segs


@pytest.fixture(scope="module")
def run1(segments: tuple[Path, list[Any]], tmp_path_factory: pytest.TempPathFactory) -> Path:
    root, _ = segments
    out = tmp_path_factory.mktemp("res1") / "r"
    infer_dataset(InferRequest(root / "waymo_v2", out, workers=1))
    return out


def _objects(path: Path) -> Any:
    return R.read_results(path).sort_by([("frame_id", "ascending"), ("object_index", "ascending")])


def test_injected_errors_are_found_and_named(segments: tuple[Path, list[Any]], run1: Path) -> None:
    root, _ = segments
    truth = {
        (r["frame_id"], r["object_id"]): r["track_error_kind"]
        for r in pq.read_table(root / "manifest.parquet").to_pylist()
    }
    rows = _objects(run1).to_pylist()
    judged = [r for r in rows if r["track_error"] is not None]
    assert len(judged) == len(rows)  # every label of these 9-frame tracks is judged
    bad = [r for r in judged if truth[(r["frame_id"], r["object_id"])] != "none"]
    clean = [r for r in judged if truth[(r["frame_id"], r["object_id"])] == "none"]
    assert len(bad) >= 5
    assert min(r["track_error"] for r in bad) > max(
        r["track_error"] for r in clean
    )  # every injected error ranks above every clean label
    assert all(r["track_issue"] == ISSUE_OF_KIND[truth[(r["frame_id"], r["object_id"])]] for r in bad)
    assert all(r["world_cx"] is not None and r["timestamp"] is not None for r in rows)
    tracks = R.open_results(run1).tracks()
    assert tracks is not None and tracks.num_rows == len({r["object_id"] for r in rows})
    assert sum(tracks.column("flagged").to_pylist()) == sum(r["track_error"] >= 0.9 for r in rows)


def test_pool_and_resume_after_a_killed_tracks_pass_give_the_same_rows(
    segments: tuple[Path, list[Any]], run1: Path, tmp_path: Path
) -> None:
    root, _ = segments
    out = tmp_path / "r2"
    infer_dataset(InferRequest(root / "waymo_v2", out, workers=2))
    assert _objects(out).equals(_objects(run1))
    assert pq.read_table(out / R.TRACKS_FILE).equals(pq.read_table(run1 / R.TRACKS_FILE))
    dask = tmp_path / "dask"  # a real LocalCluster: the pass runs in the client over the rows the workers wrote
    infer_dataset(InferRequest(root / "waymo_v2", dask, scheduler="local:1"))
    assert _objects(dask).equals(_objects(run1))
    assert pq.read_table(dask / R.TRACKS_FILE).equals(pq.read_table(run1 / R.TRACKS_FILE))
    # a run killed during the tracks pass: one shard without its scores, no tracks.parquet, manifest incomplete
    shard = sorted((out / R.OBJECTS_DIR).glob("*.parquet"))[0]
    t = pq.read_table(shard)
    meta = t.schema.metadata
    for c in R.TRACK_COLUMNS:
        t = t.set_column(
            t.schema.get_field_index(c),
            R.SCHEMA.field(c),
            __import__("pyarrow").nulls(t.num_rows, R.SCHEMA.field(c).type),
        )
    R.write_parquet_atomic(t.replace_schema_metadata(meta), shard)
    (out / R.TRACKS_FILE).unlink()
    manifest = json.loads((out / R.MANIFEST_NAME).read_text())
    R.write_json_atomic({**manifest, "complete": False}, out / R.MANIFEST_NAME)
    summary = infer_dataset(InferRequest(root / "waymo_v2", out, workers=1))
    assert summary.chunks_skipped == summary.chunks  # no chunk was recomputed: only the pass ran again
    assert _objects(out).equals(_objects(run1))
    assert pq.read_table(out / R.TRACKS_FILE).equals(pq.read_table(run1 / R.TRACKS_FILE))


def test_show_moves_the_neighbouring_labels_into_this_frame(segments: tuple[Path, list[Any]], run1: Path) -> None:
    from labelaudit.viz.objects import open_source, recompute, track_view
    from labelaudit.viz.show import render_object

    _, segs = segments
    results = R.open_results(run1)
    rows = _objects(run1).to_pylist()
    row = max((r for r in rows if r["status"] == "ok"), key=lambda r: r["track_error"])
    view = track_view(results, row)
    assert view is not None and 1 <= len(view.boxes) <= 6 and view.track_error == row["track_error"]
    # the simulator's own poses and labels: neighbour j's label, vehicle j → world → vehicle i
    seg = next(s for s in segs if row["frame_id"].startswith(s.name + ":"))
    by_ts = {f"{seg.name}:{f.timestamp}": f for f in seg.frames}
    here = by_ts[row["frame_id"]]
    k = here.object_ids.index(row["object_id"])
    inv = np.linalg.inv(here.pose)
    for fid, box in zip(view.frame_ids, view.boxes):
        fr = by_ts[fid]
        b = fr.boxes[fr.object_ids.index(row["object_id"])]
        m = inv @ fr.pose
        want_c = m[:3, :3] @ b[:3] + m[:3, 3]
        want_yaw = b[6] + np.arctan2(m[1, 0], m[0, 0])
        np.testing.assert_allclose(box[:3], want_c, atol=1e-6)
        assert abs(np.angle(np.exp(1j * (box[6] - want_yaw)))) < 1e-6
        np.testing.assert_allclose(box[3:6], b[3:6], atol=1e-9)
    assert np.allclose(here.boxes[k], [row[c] for c in R.BOX_COLUMNS], atol=1e-6)
    pic = render_object(recompute(open_source(results), row), track=view)
    assert pic.track_corners.shape == (len(view.boxes), 4, 2) and "track_error" in pic.caption
    # the box the rest of the track expects here: the true box, up to the ordinary noise (the label is the wrong one)
    assert view.expected is not None and pic.expected_corners.shape == (4, 2)
    truth = here.true_boxes[k]
    assert np.hypot(*(view.expected[:2] - truth[:2])) < 0.15 and np.all(np.abs(view.expected[3:5] - truth[3:5]) < 0.08)
    assert abs(np.angle(np.exp(1j * (view.expected[6] - truth[6])))) < 0.08
    # KITTI-like rows (no pose, made-up ids) have no track to draw
    assert track_view(results, {**row, "world_cx": None}) is None


def test_report_has_a_tracks_section_and_gallery(run1: Path, tmp_path: Path) -> None:
    from labelaudit.viz.report import build_report

    s = build_report(run1, tmp_path / "r.html", top=2)
    html = (tmp_path / "r.html").read_text()
    assert 'id="tracks"' in html and 'id="worst-tracks"' in html and 'data-gallery="track_error"' in html
    assert s.gallery.get("track_error") == 2


def test_simulate_and_rank_from_the_command_line(tmp_path: Path) -> None:
    import _hostile as H

    sim, out = tmp_path / "sim", tmp_path / "res"
    run = H.run_cli(
        "simulate",
        sim,
        "--dataset-format",
        "av2",
        "--sequences",
        "1",
        "--frames",
        "12",
        "--size",
        "small",
        "--track-noise",
        "--moving",
        "0.5",
        "--noise-fraction",
        "0",
        "--gross-fraction",
        "0",
        "-q",
    )
    assert run.exit_code == 0, run.stderr
    truth = {
        (r["frame_id"], r["object_id"]): r["track_error_kind"]
        for r in pq.read_table(sim / "manifest.parquet").to_pylist()
    }
    assert set(truth.values()) - {"none"}  # errors were injected and recorded
    assert H.run_cli("infer", sim, "-o", out, "--workers", "1", "-q").exit_code == 0
    ranked = json.loads(H.run_cli("rank", out, "--by", "track_error", "--top", "3", "--format", "json").stdout)
    assert ranked and all(truth[(r["frame_id"], r["object_id"])] != "none" and r["track_error"] > 0.9 for r in ranked)
    bad = H.run_cli("simulate", tmp_path / "k", "--track-noise")  # KITTI frames are no sequences
    assert bad.exit_code == 2 and "--track-noise" in bad.stderr

"""Tracks: every label judged against its own track (labelaudit/core/track.py, labelaudit/infer/tracks.py)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow.parquet as pq
import pytest

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.core import track as T
from labelaudit.infer.tracks import TRACKS_SCHEMA, log_of, run_tracks_pass, score_table
from results_factory import make_row

P = T.default_params()


def drive(
    n: int = 40,
    rng: np.random.Generator | None = None,
    speed: float = 10.0,
    yaw_rate: float = 0.3,
    noise: tuple[float, float, float, float] = (0.03, 0.03, 0.02, 0.02),
) -> dict[str, np.ndarray]:
    """A car turning at constant speed, 10 Hz, with ordinary per-frame label noise (centre, length, width, yaw)."""
    rng = rng or np.random.default_rng(0)
    t = np.arange(n) * 0.1
    th = yaw_rate * t
    x = speed / yaw_rate * np.sin(th) if yaw_rate else speed * t
    y = speed / yaw_rate * (1 - np.cos(th)) if yaw_rate else 0 * t
    centre = np.stack([x + 500.0, y - 200.0, np.full(n, 1.0)], axis=1) + rng.normal(0, noise[0], (n, 3)) * [1, 1, 0.5]
    size = np.array([4.5, 1.9, 1.6]) + rng.normal(0, 1, (n, 3)) * [noise[1], noise[2], 0.02]
    yaw = th + 0.4 + rng.normal(0, noise[3], n)
    return {"t": t, "centre": centre, "yaw": yaw, "size": size}


def scores_of(tr: dict[str, np.ndarray], noise: T.TrackNoise | None = None) -> tuple[np.ndarray, list[str]]:
    res = T.track_residuals(
        tr["t"],
        tr["centre"],
        np.asarray(normalize(tr["yaw"])),
        tr["size"],
        noise or T.TrackNoise(np.full(3, 0.03), np.array([0.03, 0.02, 0.03]), 0.02),
        P,
    )
    s = T.kind_scores(res, P)
    return s.max(axis=1), T.issue_of(s, C.TRACK_ISSUE_MIN)


def normalize(a: np.ndarray) -> np.ndarray:
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


@pytest.mark.parametrize(
    ("kind", "change", "issue"),
    [
        ("length", 0.3, "size"),
        ("length", -0.25, "size"),
        ("width", 0.17, "size"),
        ("flip", math.pi, "heading"),
        (
            "yaw",
            0.2,
            "heading",
        ),  # 10 σ; 0.1 rad (5 σ) reaches 0.9 inside a track, not always at its ends (extrapolated)
        ("centre", 0.35, "position"),
    ],
)
@pytest.mark.parametrize("frame", [1, 17, 38])
def test_an_annotator_error_inside_a_track_is_flagged_with_its_kind(
    kind: str, change: float, issue: str, frame: int
) -> None:
    tr = drive()
    if kind == "length":
        tr["size"][frame, 0] += change
    elif kind == "width":
        tr["size"][frame, 1] += change
    elif kind in ("flip", "yaw"):
        tr["yaw"][frame] += change
    else:
        tr["centre"][frame, :2] += change * np.array([0.6, -0.8])
    err, kinds = scores_of(tr)
    assert err[frame] >= 0.9, (kind, frame, err[frame])
    assert kinds[frame] == issue
    others = np.delete(err, frame)
    assert others.max() < 0.9  # one wrong label does not drag its neighbours along


def test_ordinary_per_frame_noise_is_not_flagged() -> None:
    rng = np.random.default_rng(1)
    errs = np.concatenate(
        [
            scores_of(drive(60, rng, speed=s, yaw_rate=w))[0]
            for s, w in [(0.0, 0.0), (5.0, 0.0), (12.0, 0.4), (20.0, -0.1)] * 10
        ]
    )
    assert np.mean(errs >= 0.9) <= 0.01
    assert np.median(errs) < 0.05


def test_scores_grow_with_the_size_of_the_error() -> None:
    base = drive(rng=np.random.default_rng(3))
    out = []
    for dl in (0.0, 0.08, 0.15, 0.3):
        tr = {k: v.copy() for k, v in base.items()}
        tr["size"][20, 0] += dl
        out.append(scores_of(tr)[0][20])
    assert out[0] < out[1] < out[2] < out[3]
    tr = {k: v.copy() for k, v in base.items()}
    heading = []
    for dy in (0.0, 0.05, 0.1, 0.2, math.pi):
        tr["yaw"] = base["yaw"].copy()
        tr["yaw"][20] += dy
        heading.append(scores_of(tr)[0][20])
    assert heading == sorted(heading) and heading[0] < 0.1 < 0.9 < heading[-2]


def test_the_size_posterior_is_the_rigid_size_and_narrows_with_frames() -> None:
    rng = np.random.default_rng(4)
    noise = T.TrackNoise(np.full(3, 0.03), np.array([0.03, 0.02, 0.03]), 0.02)
    short, long_ = drive(10, rng), drive(80, rng)
    long_["size"][5, 0] += 0.5  # a wrong label does not move the consensus (robust weight 0)
    r_short = T.track_residuals(short["t"], short["centre"], normalize(short["yaw"]), short["size"], noise, P)
    r_long = T.track_residuals(long_["t"], long_["centre"], normalize(long_["yaw"]), long_["size"], noise, P)
    assert abs(r_long.size_mean[0] - 4.5) < 0.015 and abs(r_long.size_mean[1] - 1.9) < 0.01
    assert r_long.size_std[0] < r_short.size_std[0]
    assert r_long.size_weight[5] == 0.0 and np.median(r_long.size_weight) > 0.8
    # points that pin the size pull the posterior: labels all 0.2 m long, the points say 4.5
    labels = drive(30, rng)
    labels["size"][:, 0] += 0.2
    fit = np.tile([4.5, 1.9, np.nan], (30, 1))
    prec = np.tile([1 / 0.01**2, 1 / 0.01**2, 0.0], (30, 1))
    r_pts = T.track_residuals(
        labels["t"], labels["centre"], normalize(labels["yaw"]), labels["size"], noise, P, (fit, prec)
    )
    r_lab = T.track_residuals(labels["t"], labels["centre"], normalize(labels["yaw"]), labels["size"], noise, P)
    assert abs(r_lab.size_mean[0] - 4.7) < 0.02 and abs(r_pts.size_mean[0] - 4.5) < 0.05


def test_error_probability_is_the_two_component_posterior() -> None:
    k, p = P.error_scale, P.error_prior
    q = np.array([0.0, 9.0, 25.0])
    for d in (1, 3):
        want = [1 / (1 + (1 - p) / p * k**d * math.exp(-qq / 2 * (1 - 1 / k**2))) for qq in q]
        np.testing.assert_allclose(T.error_probability(q, d, P), want, rtol=1e-12)
    assert T.error_probability(np.array([1e6]), 1, P)[0] == 1.0


def test_a_lone_frame_and_a_gap_get_a_wide_prediction_not_an_alarm() -> None:
    tr = drive(12)
    t = tr["t"].copy()
    t[6:] += 5.0  # a 5 s gap: frames on either side are not neighbours
    res = T.track_residuals(t, tr["centre"], normalize(tr["yaw"]), tr["size"], T.TrackNoise.floor(), P)
    assert np.all(np.isfinite(res.position)) and np.all(np.isfinite(res.heading))


# --------------------------------------------------------------------------- the pass over results rows


def track_rows(
    log: str,
    obj: str,
    tr: dict[str, np.ndarray],
    dataset: str = "waymo-v2",
    index: int = 0,
    t0: int = 1_600_000_000_000_000,
) -> list[dict[str, Any]]:
    rows = []
    for i in range(len(tr["t"])):
        ts = t0 + int(round(tr["t"][i] * 1e6))
        fid = f"{log}:{ts}"
        l, w, h = tr["size"][i]
        rows.append(
            make_row(
                fid,
                index,
                "Vehicle",
                dataset=dataset,
                object_id=obj,
                length=float(l),
                width=float(w),
                height=float(h),
                timestamp=ts / 1e6,
                world_cx=float(tr["centre"][i, 0]),
                world_cy=float(tr["centre"][i, 1]),
                world_cz=float(tr["centre"][i, 2]),
                world_yaw=float(normalize(tr["yaw"][i])),
            )
        )
    return rows


def write_folder(root: Path, shards: list[list[dict[str, Any]]], fmt: str = "waymo-v2") -> dict[str, Any]:
    meta = R.run_metadata({"model": "bev"}, "0123456789abcdef", "/data/x", fmt)
    for i, rows in enumerate(shards):
        R.write_parquet_atomic(
            R.rows_to_table(rows, {**meta, "chunk": {"notes": 0, "failed_frames": 0, "failed_objects": 0}}),
            root / R.OBJECTS_DIR / f"part-{i:04d}.parquet",
        )
    R.write_json_atomic({**meta, "complete": True}, root / R.MANIFEST_NAME)
    return meta


def some_tracks() -> list[list[dict[str, Any]]]:
    rng = np.random.default_rng(7)
    a, b, c = drive(30, rng), drive(30, rng, speed=0.0, yaw_rate=0.0), drive(2, rng)
    a["size"][12, 0] += 0.4
    b["yaw"][7] += math.pi
    return [
        track_rows("segA", "car-a", a, index=0),
        track_rows("segA", "car-b", b, index=1),
        track_rows("segB", "car-c", c, index=0),
    ]


def test_a_track_split_across_shards_is_judged_whole(tmp_path: Path) -> None:
    a, b, c = some_tracks()
    rows = a + b + c
    whole, split = tmp_path / "whole", tmp_path / "split"
    meta = write_folder(whole, [rows])
    write_folder(split, [rows[::3], rows[1::3], rows[2::3]])
    from labelaudit.config import load_config

    cfg = load_config(None, "waymo-v2")
    assert run_tracks_pass(whole, cfg, meta) == 2  # car-c has 2 frames: too short, null
    run_tracks_pass(split, cfg, meta)
    cols = ["frame_id", "object_index", "track_error", "track_issue"]
    t1 = R.read_results(whole, cols).sort_by([("frame_id", "ascending"), ("object_index", "ascending")])
    t2 = R.read_results(split, cols).sort_by([("frame_id", "ascending"), ("object_index", "ascending")])
    assert t1.equals(t2)
    assert pq.read_table(whole / R.TRACKS_FILE).equals(pq.read_table(split / R.TRACKS_FILE))
    got = {(r["frame_id"], r["object_index"]): (r["track_error"], r["track_issue"]) for r in t1.to_pylist()}
    assert got[(a[12]["frame_id"], 0)][0] >= 0.9 and got[(a[12]["frame_id"], 0)][1] == "size"
    assert got[(b[7]["frame_id"], 1)][1] == "heading"
    assert got[(c[0]["frame_id"], 0)] == (None, None)
    tracks = R.open_results(whole).tracks()
    assert tracks is not None and tracks.schema.equals(TRACKS_SCHEMA, check_metadata=False)
    by_id = {r["object_id"]: r for r in tracks.to_pylist()}
    assert by_id["car-a"]["worst_frame_id"] == a[12]["frame_id"] and by_id["car-a"]["worst_issue"] == "size"
    assert by_id["car-a"]["flagged"] == 1 and abs(by_id["car-a"]["length"] - 4.5) < 0.03
    assert by_id["car-b"]["heading_vs_motion"] is None  # parked
    assert abs(abs(by_id["car-a"]["heading_vs_motion"]) - 0.4) < 0.1  # the labels point 0.4 rad off the motion
    # shards keep the chunk record --resume reads, and a second pass rewrites nothing
    before = {p.name: p.stat().st_mtime_ns for p in (split / R.OBJECTS_DIR).glob("*.parquet")}
    assert R.shard_metadata(next((split / R.OBJECTS_DIR).glob("*.parquet")))["chunk"]["failed_objects"] == 0
    run_tracks_pass(split, cfg, meta)
    assert before == {p.name: p.stat().st_mtime_ns for p in (split / R.OBJECTS_DIR).glob("*.parquet")}


def test_kitti_rows_have_no_tracks(tmp_path: Path) -> None:
    rows = [make_row(f"{i:06d}", 0) for i in range(5)]
    meta = write_folder(tmp_path, [rows], fmt="kitti")
    (tmp_path / R.TRACKS_FILE).write_bytes(b"stale")
    assert run_tracks_pass(tmp_path, None, meta) == 0  # type: ignore[arg-type]
    assert not (tmp_path / R.TRACKS_FILE).exists()
    t = R.read_results(tmp_path, ["track_error", "track_issue"])
    assert t.column("track_error").null_count == 5 and t.column("track_issue").null_count == 5
    assert R.open_results(tmp_path).tracks() is None
    # rows of a tracked format without a pose, or with the made-up '<frame>:<index>' id, are not tracks either
    a = some_tracks()[0]
    for r in a:
        r["object_id"] = f"{r['frame_id']}:{r['object_index']}"
    from labelaudit.results import rows_to_table

    s = score_table(rows_to_table(a))
    assert np.isnan(s.track_error).all() and s.tracks == []


def test_log_of() -> None:
    assert log_of("seg_1:1600000000000000") == "seg_1" and log_of("a:b:123") == "a:b" and log_of("000123") == "000123"


# --------------------------------------------------------------------------- simulator: noise inside tracks


def test_track_noise_injects_recorded_errors_of_the_given_sizes() -> None:
    from labelaudit.sim.tracknoise import TrackNoiseSpec, perturb_track_labels

    k = 4000
    boxes = np.tile([10.0, 5.0, -1.0, 4.5, 1.9, 1.6, 0.3], (k, 1))
    classes = ["Car"] * (k - 10) + ["Pedestrian"] * 10
    spec = TrackNoiseSpec(error_fraction=0.5)
    out, kinds, mag = perturb_track_labels(boxes, classes, spec, np.random.default_rng(0))
    again = perturb_track_labels(boxes, classes, spec, np.random.default_rng(0))
    assert np.array_equal(out, again[0]) and kinds == again[1]
    assert np.array_equal(out[-10:], boxes[-10:]) and set(kinds[-10:]) == {"none"}  # other classes untouched
    kinds_a = np.array(kinds)
    d = out - boxes
    clean = kinds_a == "none"
    assert 0.45 < np.mean(~clean[:-10]) < 0.55
    np.testing.assert_allclose(np.std(d[clean][:, [0, 1, 3, 4]], axis=0), [0.03, 0.03, 0.03, 0.02], rtol=0.1)
    assert abs(np.std(normalize(d[clean][:, 6])) - 0.02) < 0.003
    for kind, col, (lo, hi) in (("length", 3, (0.25, 0.5)), ("width", 4, (0.15, 0.3)), ("yaw", 6, (0.1, 0.25))):
        sel = kinds_a == kind
        assert sel.sum() > 300
        assert np.all((np.abs(mag[sel]) >= lo) & (np.abs(mag[sel]) <= hi))
        off = normalize(d[sel][:, col]) if col == 6 else d[sel][:, col]
        assert np.all(np.abs(off - mag[sel]) < 0.15)  # the error plus the ordinary noise
    flip = kinds_a == "flip"
    assert np.all(np.abs(np.abs(normalize(d[flip][:, 6])) - np.pi) < 0.1)
    centre = kinds_a == "centre"
    assert np.all(np.abs(np.hypot(d[centre][:, 0], d[centre][:, 1]) - mag[centre]) < 0.15) and mag[centre].min() >= 0.3
    with pytest.raises(ValueError, match="kinds"):
        TrackNoiseSpec(kinds=("bogus",))


def test_simulated_segment_vehicles_drive_and_record_track_errors(tmp_path: Path) -> None:
    from labelaudit.sim.tracknoise import TrackNoiseSpec
    from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_manifest

    seg = simulate_waymo_segment(
        seed=3, frames=3, size="small", chunks=1, moving_fraction=1.0, track_noise=TrackNoiseSpec(error_fraction=0.3)
    )
    f0, f2 = seg.frames[0], seg.frames[2]

    def world(fr: Any) -> np.ndarray:
        return fr.true_boxes[:, :3] @ fr.pose[:3, :3].T + fr.pose[:3, 3]

    step = np.hypot(*(world(f2) - world(f0))[:, :2].T) / 0.2
    vehicles = np.array([c in ("Car", "Van", "Truck") for c in f0.sim_classes])
    lo, hi = C.SIM_MOVING_SPEED
    assert np.all((step[vehicles] > lo * 0.95) & (step[vehicles] < hi * 1.01)) and np.all(step[~vehicles] < 1e-9)
    assert set(f0.track_error_kind) - {"none"} and len(f0.track_error_size) == len(f0.boxes)
    m = pq.read_table(write_manifest([seg], tmp_path / "manifest.parquet")).to_pylist()
    assert {r["track_error_kind"] for r in m} >= {"none"} and len(m) == sum(len(f.boxes) for f in seg.frames)
    # without the new options the scene is the one earlier versions rendered
    plain = simulate_waymo_segment(seed=3, frames=1, size="small", chunks=1)
    still = simulate_waymo_segment(seed=3, frames=1, size="small", chunks=1, moving_fraction=0.0)
    assert np.array_equal(plain.frames[0].points, still.frames[0].points) and plain.frames[0].track_error_kind == []


def test_to_frame_moves_world_boxes_into_a_labels_frame() -> None:
    """The frame's pose from one label (frame rotated by π/2 in the world, origin at (10, 5, 2)): a known answer, and the label itself comes back."""
    label = np.array([1.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0])
    label_world = np.array([10.0, 6.0, 2.0, math.pi / 2])
    world = np.array([[10.0, 8.0, 3.0, 4.5, 1.8, 1.6, math.pi], [10.0, 6.0, 2.0, 4.0, 2.0, 1.5, math.pi / 2]])
    out = T.to_frame(world, label, label_world)
    assert np.allclose(out[0], [3.0, 0.0, 1.0, 4.5, 1.8, 1.6, math.pi / 2], atol=1e-12)
    assert np.allclose(out[1], label, atol=1e-12)

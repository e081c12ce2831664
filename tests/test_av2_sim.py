"""Simulated Argoverse 2 logs and `labelaudit simulate --dataset-format …`: files that round-trip
through the readers, tracks and moving ego poses, and runs that resume and do not depend on workers."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from labelaudit.cli import app
from labelaudit.config import resolve_config
from labelaudit.datasets import Frame, detect_format, open_dataset
from labelaudit.executors import PoolExecutor, SerialExecutor
from labelaudit.infer.crop import points_in_boxes_numpy
from labelaudit.infer.run import InferRequest, run_infer
from labelaudit.results import open_results
from labelaudit.sim.av2_writer import simulate_av2_log, write_av2_log
from labelaudit.sim.noise import NoiseSpec


def invoke(*args: object):
    return CliRunner().invoke(app, [str(a) for a in args])


def _frames(root: Path, fmt: str = "auto") -> list[Frame]:
    reader = open_dataset(root, fmt)
    frames = [f for ref in reader.list_units() for f in reader.load_unit(ref)]
    assert all(isinstance(f, Frame) for f in frames)
    return frames  # type: ignore[return-value]


def test_simulated_log_round_trips_through_the_reader(tmp_path: Path) -> None:
    log = simulate_av2_log(seed=4, frames=3, label_noise=NoiseSpec(fraction=0.3, gross_fraction=0.1))
    write_av2_log(log, tmp_path / "val")
    frames = _frames(tmp_path)
    assert [f.frame_id for f in frames] == [f"{log.log_id}:{fr.timestamp}" for fr in log.frames]
    for f, truth in zip(frames, log.frames):
        np.testing.assert_array_equal(f.points, truth.points)  # bit for bit: float16 coordinates, uint8 intensity
        np.testing.assert_allclose(f.boxes, truth.boxes, atol=1e-9)  # the written (noisy) boxes, yaw via the quaternion
        np.testing.assert_allclose(f.pose, truth.pose, atol=1e-9)
        assert f.object_ids == truth.track_ids and f.class_names == truth.categories
        counts = [len(i) for i in points_in_boxes_numpy(f.points, f.boxes)]
        assert counts == list(f.extras["num_lidar_points_in_box"]) == list(truth.num_interior_pts)
        assert not f.warnings
    # one track id per object for the whole log, the ego drives (poses move), the world stays put
    assert frames[0].object_ids == frames[-1].object_ids and len(set(frames[0].object_ids)) == frames[0].num_objects
    step = np.linalg.norm(frames[1].pose[:3, 3] - frames[0].pose[:3, 3])
    assert step == pytest.approx(0.8, rel=0.01)  # 8 m/s at 10 Hz
    true_world = [fr.pose[:3, :3] @ fr.true_boxes[:, :3].T + fr.pose[:3, 3:4] for fr in log.frames]
    np.testing.assert_allclose(true_world[0], true_world[-1], atol=1e-9)  # static objects in the city frame
    kinds = [k for fr in log.frames for k in fr.perturbation]
    moved = [not np.allclose(b, t) for fr in log.frames for b, t in zip(fr.boxes, fr.true_boxes)]
    assert moved == [k != "none" for k in kinds] and any(moved)  # the noise is written, and only where recorded
    assert {"REGULAR_VEHICLE"} <= set(frames[0].class_names)
    # both lidars: laser numbers 0–31 and 32–63, capture times within the sweep
    fr = log.frames[0]
    assert (fr.laser_number < 32).any() and (fr.laser_number >= 32).any() and fr.laser_number.max() <= 63
    assert 0 <= fr.offset_ns.min() and fr.offset_ns.max() < 100_000_000


def test_same_seed_same_log_and_labels_only(tmp_path: Path) -> None:
    a, b = simulate_av2_log(seed=9, frames=2), simulate_av2_log(seed=9, frames=2)
    assert a.log_id == b.log_id and a.frames[1].track_ids == b.frames[1].track_ids
    np.testing.assert_array_equal(a.frames[1].points, b.frames[1].points)
    assert simulate_av2_log(seed=10, frames=1).log_id != a.log_id
    write_av2_log(a, tmp_path, sweeps=False)  # the av2-api test logs' shape: labels and poses, no sweeps
    frames = _frames(tmp_path)
    assert len(frames) == 2 and all(len(f.points) == 0 and f.num_objects == len(a.frames[0].boxes) for f in frames)
    assert all(any("no sweep" in w for w in f.warnings) for f in frames)


@pytest.mark.parametrize("fmt", ["av2", "waymo-v2", "waymo-v1"])
def test_cli_simulates_sequences_that_the_readers_detect(tmp_path: Path, fmt: str) -> None:
    out = tmp_path / "sim"
    r = invoke(
        "simulate",
        out,
        "--dataset-format",
        fmt,
        "--sequences",
        "2",
        "--frames",
        "2",
        "--size",
        "small",
        "--gross-fraction",
        "0.2",
        "-q",
    )
    assert r.exit_code == 0, r.output
    assert detect_format(out) == fmt
    frames = _frames(out, fmt)
    assert len(frames) == 4
    assert len({f.frame_id.split(":")[0] for f in frames}) == 2  # two sequences
    assert all(f.pose is not None for f in frames)
    manifest = pq.read_table(out / "manifest.parquet").to_pylist()
    assert len(manifest) == sum(f.num_objects for f in frames)
    by_key = {(m["frame_id"], m["object_id"]): m for m in manifest}
    for f in frames:
        for box, oid in zip(f.boxes, f.object_ids):
            np.testing.assert_allclose(by_key[f.frame_id, oid]["written_box"], box, atol=1e-4)
    assert any(m["perturbation"] != "none" for m in manifest)
    # a second run does not overwrite without being asked
    again = invoke("simulate", out, "--dataset-format", fmt, "--frames", "1", "--size", "small", "-q")
    assert again.exit_code == 2 and "--overwrite" in again.output
    assert (
        invoke(
            "simulate",
            out,
            "--dataset-format",
            fmt,
            "--frames",
            "1",
            "--sequences",
            "1",
            "--size",
            "small",
            "-q",
            "--overwrite",
        ).exit_code
        == 0
    )
    assert len(_frames(out, fmt)) == 1


def test_cli_rejects_what_sequences_do_not_have(tmp_path: Path) -> None:
    r = invoke("simulate", tmp_path / "s", "--dataset-format", "waymo-v2", "--detections")
    assert r.exit_code == 2 and "--detections" in r.output
    r = invoke("simulate", tmp_path / "s", "--dataset-format", "av2", "--detections", "--detections-cov")
    assert r.exit_code == 2 and "--detections-cov" in r.output
    r = invoke("simulate", tmp_path / "s", "--dataset-format", "av2", "--sequences", "0")
    assert r.exit_code == 2 and "--sequences" in r.output


def _rows(out: Path) -> list[dict]:
    return sorted(open_results(out).read().to_pylist(), key=lambda r: (r["frame_id"], r["object_index"]))


@pytest.mark.slow
def test_infer_on_simulated_logs_is_identical_across_workers_and_resumes(tmp_path: Path) -> None:
    noise = NoiseSpec(fraction=0.2, gross_fraction=0.1)
    for seed in (0, 1, 2):
        write_av2_log(simulate_av2_log(seed=seed, frames=2, label_noise=noise), tmp_path / "data" / "val")
    root = tmp_path / "data"
    cfg = resolve_config(None, "av2")
    s1 = run_infer(InferRequest(root, tmp_path / "w1"), cfg, executor=SerialExecutor())
    s2 = run_infer(InferRequest(root, tmp_path / "w2"), cfg, executor=PoolExecutor(2))
    assert s1.chunks == s2.chunks == 3 and s1.frames == 6
    rows = _rows(tmp_path / "w1")
    assert rows == _rows(tmp_path / "w2")
    assert {r["dataset"] for r in rows} == {"av2"} and "ok" in {r["status"] for r in rows}
    assert {r["class_name"] for r in rows} <= set(cfg.classes)
    s3 = run_infer(InferRequest(root, tmp_path / "w1"), cfg, executor=SerialExecutor())
    assert s3.chunks_skipped == 3 and _rows(tmp_path / "w1") == rows


def test_simulated_av2_detections_evaluate(tmp_path: Path) -> None:
    import json

    out = tmp_path / "sim"
    r = invoke(
        "simulate",
        out,
        "--dataset-format",
        "av2",
        "--sequences",
        "2",
        "--frames",
        "3",
        "--size",
        "small",
        "--detections",
        "-q",
    )
    assert r.exit_code == 0, r.output
    det = out / "detections.feather"
    first = det.read_bytes()
    assert (
        invoke(
            "simulate",
            out,
            "--dataset-format",
            "av2",
            "--sequences",
            "2",
            "--frames",
            "3",
            "--size",
            "small",
            "--detections",
            "-q",
            "--overwrite",
        ).exit_code
        == 0
    )
    assert det.read_bytes() == first  # same seed, same detections
    r = invoke("eval", out, det, "--format", "json", "--workers", "1", "--classes", "REGULAR_VEHICLE")
    assert r.exit_code == 0, r.output
    doc = json.loads(r.stdout)
    assert doc["detections_source"]["format"] == "av2"
    rec = next(x for x in doc["ap"] if x["metric"] == "iou" and x["interp"] == "R40" and x["threshold"] == 0.5)
    # a noisy but real detector: it finds most cars (AP in percent), not all, and not none
    assert rec["num_gt"] > 20 and 20.0 < rec["ap"] < 100.0

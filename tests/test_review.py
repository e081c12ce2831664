"""The review loop: `export --format kitti-labels` writes label_2 files a labelling tool imports,
the boxes read back exactly, changes.csv lists what was added; other formats get boxes.parquet."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from conftest import REALDATA
from labelaudit import results as R
from labelaudit.cli import app
from labelaudit.datasets.kitti import LABEL_COLUMNS, KittiReader, boxes_camera_to_lidar, read_calib, read_label
from labelaudit.review import kitti_lines, png_size, suggested_boxes
from results_factory import add_missing, make_candidate, make_results, make_row
from viz_data import simulate_and_infer

runner = CliRunner()
REAL_KITTI = REALDATA / "openpcdet-pr653-kitti" / "training"  # optional: tests skip or shrink without it


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def audited(tmp_path_factory):
    """A simulated KITTI dataset with injected label errors, audited for real, and three candidates."""
    root = tmp_path_factory.mktemp("review")
    data, results = simulate_and_infer(root)
    shutil.rmtree(results / "missing", ignore_errors=True)  # the test's own candidates, whatever the search found
    add_missing(
        results,
        [
            [
                make_candidate("000000", 0, 0.9, cx=18.0, cy=2.5, yaw=0.4),
                make_candidate("000000", 1, 0.3, cx=25.0, cy=-3.0),  # below the default score threshold
                make_candidate(
                    "000001",
                    0,
                    0.6,
                    class_name="Van",
                    cx=12.0,
                    cy=-1.0,
                    cz=-0.6,
                    length=5.1,
                    width=2.0,
                    height=2.1,
                    yaw=-2.9,
                ),
            ]
        ],
    )
    return data, results


def _file_boxes(path: Path, calib_path: Path) -> tuple[np.ndarray, object]:
    labels = read_label(path)
    return boxes_camera_to_lidar(labels.location, labels.dims_hwl, labels.rotation_y, read_calib(calib_path)), labels


def test_kitti_labels_keep_the_originals_and_add_suggestions_and_candidates(audited, tmp_path):
    data, results = audited
    out = tmp_path / "review"
    result = invoke("export", results, "--format", "kitti-labels", "-o", out, "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    rows = R.read_results(results)
    lerr = np.asarray(rows.column("label_error").to_numpy(zero_copy_only=False), dtype=float)
    expected_suggestions = int(np.sum(lerr > 0.5))
    assert expected_suggestions > 0  # the simulator injected label errors: some must be suggested
    assert summary["suggested"] == expected_suggestions and summary["missing"] == 2
    assert summary["frames_written"] == 3 and summary["unreviewed_frames"] == {}
    assert "suggested boxes" in result.stderr and "changes.csv" in result.stderr

    changes = list(csv.DictReader((out / "changes.csv").open()))
    assert len(changes) == expected_suggestions + 2
    sim_root = data / "training" if (data / "training").is_dir() else data
    for fid in ("000000", "000001", "000002"):
        original = (sim_root / "label_2" / f"{fid}.txt").read_text().splitlines()
        written = (out / "label_2" / f"{fid}.txt").read_text().splitlines()
        assert written[: len(original)] == original  # the original labels, byte for byte
        added = written[len(original) :]
        mine = [c for c in changes if c["frame_id"] == fid]
        assert len(added) == len(mine)
        boxes, labels = _file_boxes(out / "label_2" / f"{fid}.txt", sim_root / "calib" / f"{fid}.txt")
        for c in mine:
            line = int(c["line"])
            k = list(labels.line).index(line)
            assert len(written[line - 1].split()) == 16
            assert labels.score[k] == pytest.approx(float(c["score"]), abs=0)  # the score in the 16th column
            want = np.array([float(c[n]) for n in R.BOX_COLUMNS])
            np.testing.assert_allclose(boxes[k], want, rtol=0, atol=1e-9)  # the round trip through the KITTI reader
            if c["change"] == "suggested_box":
                row = rows.filter(np.asarray(rows.column("frame_id").to_pylist()) == fid).to_pylist()
                (r,) = [r for r in row if r["object_index"] == int(c["object_index"])]
                assert r["label_error"] > 0.5 and float(c["score"]) == r["label_error"]
                assert int(c["original_line"]) == r["label_line"] and labels.class_names[k] == r["class_name"]
                fit = suggested_boxes(
                    rows.filter(
                        np.asarray(
                            [x["frame_id"] == fid and x["object_index"] == r["object_index"] for x in rows.to_pylist()]
                        )
                    )
                )[0]
                np.testing.assert_allclose(boxes[k], fit, rtol=0, atol=1e-9)
            else:
                assert c["change"] == "missing_label" and float(c["score"]) >= 0.5 and c["source"] == "points"
    cand = [c for c in changes if c["change"] == "missing_label"]
    assert {(c["frame_id"], c["candidate_index"], c["class_name"]) for c in cand} == {
        ("000000", "0", "Car"),
        ("000001", "0", "Van"),
    }

    # review/ is a KITTI folder of its own: the reader loads it, the added boxes included.
    reader = KittiReader(out)
    frame = reader.load_frame("000001")
    van = [k for k, n in enumerate(frame.class_names) if n == "Van" and frame.extras["score"][k] == 0.6]
    assert len(van) == 1
    np.testing.assert_allclose(frame.boxes[van[0]], [12.0, -1.0, -0.6, 5.1, 2.0, 2.1, -2.9], rtol=0, atol=1e-9)
    meta = json.loads((out / "review.json").read_text())
    assert meta["suggested"] == expected_suggestions and meta["min_score"] == 0.5 and meta["dataset_format"] == "kitti"


def test_kitti_labels_thresholds_rewrite_and_refusals(audited, tmp_path):
    data, results = audited
    out = tmp_path / "review"
    assert invoke("export", results, "--format", "kitti-labels", "-o", out).exit_code == 0
    # Stricter thresholds, same folder: the earlier export is replaced, not added to.
    result = invoke(
        "export",
        results,
        "--format",
        "kitti-labels",
        "-o",
        out,
        "--min-score",
        "0.95",
        "--min-label-error",
        "1.0",
        "--json",
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["suggested"] == 0 and summary["missing"] == 0 and summary["frames_changed"] == 0
    assert list(csv.DictReader((out / "changes.csv").open())) == []
    sim_root = data / "training" if (data / "training").is_dir() else data
    for fid in ("000000", "000001", "000002"):
        assert (out / "label_2" / f"{fid}.txt").read_text() == (sim_root / "label_2" / f"{fid}.txt").read_text()
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left behind
    for args, needle in (
        (("--min-score", "1.5"), "--min-score must be in [0, 1]"),
        (("--min-label-error", "-0.1"), "--min-label-error must be in [0, 1]"),
    ):
        result = invoke("export", results, "--format", "kitti-labels", "-o", tmp_path / "x", *args)
        assert result.exit_code == 2 and needle in result.stderr, result.output
    for args, needle in (
        (("--format", "kitti-labels", "--infos", tmp_path / "x.pkl"), "--infos"),
        (("--format", "kitti-labels", "--encoding", "pixor"), "--encoding"),
        (("--min-score", "0.7"), "only with --format kitti-labels"),
    ):
        result = invoke("export", results, "-o", tmp_path / "y", *args)
        assert result.exit_code == 2 and needle in result.stderr, (args, result.output)
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    result = invoke("export", results, "--format", "kitti-labels", "-o", tmp_path / "busy")
    assert result.exit_code == 2 and "not a review folder" in result.stderr
    assert (tmp_path / "busy" / "notes.txt").read_text() == "mine"


def test_kitti_labels_leave_a_frame_whose_labels_changed_since_infer_as_it_is(audited, tmp_path):
    data, results = audited
    moved = tmp_path / "moved"
    shutil.copytree(data, moved)
    sim_root = moved / "training" if (moved / "training").is_dir() else moved
    label = sim_root / "label_2" / "000001.txt"
    lines = label.read_text().splitlines()
    first = next(i for i, l in enumerate(lines) if not l.startswith("DontCare"))
    parts = lines[first].split()
    parts[11] = f"{float(parts[11]) + 0.5:.2f}"  # x of the location moved by half a metre
    lines[first] = " ".join(parts)
    label.write_text("\n".join(lines) + "\n")
    result = invoke(
        "export", results, "--format", "kitti-labels", "-o", tmp_path / "review", "--dataset", moved, "--json"
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["frames_written"] == 3 and list(summary["unreviewed_frames"]) == ["000001"]
    why = summary["unreviewed_frames"]["000001"]
    assert "labels edited since infer" in why and "000001.txt" in why
    assert "warning: frame 000001 not reviewed" in result.stderr
    # Written as it is now: an import loses nothing, and nothing computed for the old labels is added.
    assert (tmp_path / "review" / "label_2" / "000001.txt").read_text() == label.read_text()
    assert {c["frame_id"] for c in csv.DictReader((tmp_path / "review" / "changes.csv").open())} <= {"000000", "000002"}
    # An unreadable label file is copied as it is and named.
    (sim_root / "label_2" / "000002.txt").write_bytes(b"Car 0 0 \xff\n")
    result = invoke(
        "export", results, "--format", "kitti-labels", "-o", tmp_path / "review", "--dataset", moved, "--json"
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert "not UTF-8" in summary["unreviewed_frames"]["000002"] and summary["frames_written"] == 3
    assert (tmp_path / "review" / "label_2" / "000002.txt").read_bytes() == b"Car 0 0 \xff\n"


def test_waymo_results_get_a_parquet_of_boxes(tmp_path):
    fit = {
        "fit_cx": 11.0,
        "fit_cy": 2.5,
        "fit_cz": None,
        "fit_length": 4.4,
        "fit_width": 1.8,
        "fit_height": None,
        "fit_yaw": 0.2,
    }
    rows = [
        make_row("seg:1", 0, dataset="waymo-v2", label_error=0.95, **fit),
        make_row("seg:1", 1, dataset="waymo-v2", label_error=0.1, **fit),
        make_row("seg:2", 0, dataset="waymo-v2", label_error=None),
    ]
    root = make_results(tmp_path / "r", [rows])
    manifest = json.loads((root / "manifest.json").read_text())
    R.write_json_atomic({**manifest, "format": "waymo-v2", "input": "/data/waymo"}, root / "manifest.json")
    add_missing(
        root,
        [[make_candidate("seg:2", 0, 0.7, dataset="waymo-v2"), make_candidate("seg:2", 1, 0.2, dataset="waymo-v2")]],
    )
    result = invoke("export", root, "--format", "kitti-labels", "-o", tmp_path / "review", "--json")
    assert result.exit_code == 0, result.output
    table = pq.read_table(tmp_path / "review" / "boxes.parquet").to_pylist()
    assert [(b["frame_id"], b["kind"], b["object_index"], b["candidate_index"]) for b in table] == [
        ("seg:1", "label", 0, None),
        ("seg:1", "label", 1, None),
        ("seg:1", "suggested", 0, None),
        ("seg:2", "label", 0, None),
        ("seg:2", "missing", None, 0),
    ]
    suggested = table[2]
    # A BEV fit keeps the label's cz and height.
    assert [suggested[c] for c in R.BOX_COLUMNS] == [11.0, 2.5, -0.8, 4.4, 1.8, 1.5, 0.2] and suggested["score"] == 0.95
    changes = list(csv.DictReader((tmp_path / "review" / "changes.csv").open()))
    assert [(c["frame_id"], c["change"], c["file"]) for c in changes] == [
        ("seg:1", "suggested_box", ""),
        ("seg:2", "missing_label", ""),
    ]
    assert json.loads(result.stdout)["format"] == "parquet"


def test_kitti_lines_round_trip_on_real_calibrations(realdata):
    """Exact write → read on the real KITTI calibrations (printed matrices, not exactly orthonormal)."""
    calibs = sorted((realdata / "openpcdet-pr653-kitti" / "training" / "calib").glob("*.txt"))
    assert calibs, "the real KITTI folder has no calib files"
    rng = np.random.default_rng(0)
    for path in calibs:
        calib = read_calib(path)
        boxes = np.c_[rng.uniform(2, 60, 20), rng.uniform(-20, 20, 20), rng.uniform(-2, 0.5, 20), rng.uniform(0.5, 12, 20),
                      rng.uniform(0.4, 3, 20), rng.uniform(1, 4, 20), rng.uniform(-np.pi, np.pi, 20)]  # fmt: skip
        lines = kitti_lines(
            boxes,
            ["Car"] * 20,
            rng.uniform(0, 1, 20),
            np.zeros(20),
            np.full(20, 3),
            calib,
            png_size(REAL_KITTI / "image_2" / f"{path.stem}.png") or (1242, 375),
        )
        parsed = np.array([[float(v) for v in line.split()[1:]] for line in lines])
        assert parsed.shape == (20, len(LABEL_COLUMNS) - 1)
        back = boxes_camera_to_lidar(parsed[:, 10:13], parsed[:, 7:10], parsed[:, 13], calib)
        d = back - boxes
        d[:, 6] = (d[:, 6] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(d).max() < 1e-9, (path, np.abs(d).max())


def test_png_size_reads_the_header(tmp_path):
    if REAL_KITTI.is_dir():
        assert png_size(REAL_KITTI / "image_2" / "000001.png") == (1242, 375)
    (tmp_path / "x.png").write_bytes(b"not a png")
    assert png_size(tmp_path / "x.png") is None and png_size(tmp_path / "none.png") is None


def test_kitti_labels_on_real_frames(realdata, tmp_path):
    """Real KITTI frames: every suggestion (threshold 0: all fitted labels) reads back as its fit, originals untouched."""
    from labelaudit.config import resolve_config
    from labelaudit.executors import SerialExecutor
    from labelaudit.infer.run import InferRequest, run_infer

    root = realdata / "openpcdet-pr653-kitti"
    run_infer(
        InferRequest(root, tmp_path / "res", "kitti", limit=3), resolve_config(None, "kitti"), executor=SerialExecutor()
    )
    out = tmp_path / "review"
    result = invoke(
        "export", tmp_path / "res", "--format", "kitti-labels", "-o", out, "--min-label-error", "0", "--json"
    )
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    changes = [c for c in csv.DictReader((out / "changes.csv").open()) if c["change"] == "suggested_box"]
    assert summary["suggested"] == len(changes) > 0
    reader = KittiReader(out)
    for c in changes:
        fid = c["frame_id"]
        original = (root / "training" / "label_2" / f"{fid}.txt").read_text().splitlines()
        written = (out / "label_2" / f"{fid}.txt").read_text().splitlines()
        assert written[: len(original)] == original
        frame = reader.load_frame(fid)  # the review folder reads as KITTI: real points through the links
        k = list(frame.extras["label_line"]).index(int(c["line"]))
        np.testing.assert_allclose(frame.boxes[k], [float(c[n]) for n in R.BOX_COLUMNS], rtol=0, atol=1e-9)
        assert frame.extras["score"][k] == float(c["score"]) and len(frame.points) > 10000


@pytest.fixture(scope="module")
def av2_tracks(tmp_path_factory):
    """Simulated Argoverse 2 logs with annotator errors injected inside tracks, audited through the CLI."""
    root = tmp_path_factory.mktemp("review-av2")
    sim, results = root / "sim", root / "results"
    r = invoke("simulate", sim, "--dataset-format", "av2", "--track-noise", "--moving", "0.5", "--noise-fraction", "0", "--gross-fraction", "0",
               "--frames", "12", "--sequences", "2", "--size", "small", "--seed", "3", "-q")  # fmt: skip
    assert r.exit_code == 0, r.output
    r = invoke("infer", sim, "-o", results, "--workers", "1")
    assert r.exit_code == 0, r.output
    return sim, results


def test_track_suggestions_fix_the_injected_frames_and_leave_clean_ones_alone(av2_tracks, tmp_path):
    from labelaudit.core.geometry import box_corners
    from labelaudit.infer.tracks import log_of
    from labelaudit.sim.tracknoise import ISSUE_OF_KIND

    sim, results = av2_tracks
    result = invoke("export", results, "--format", "kitti-labels", "-o", tmp_path / "review", "--json")
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert "boxes from tracks (track_error > 0.5)" in result.stderr
    truth = {(m["frame_id"], m["object_id"]): m for m in pq.read_table(sim / "manifest.parquet").to_pylist()}
    boxes = pq.read_table(tmp_path / "review" / "boxes.parquet").to_pylist()
    labels = {(b["frame_id"], b["object_index"]): b for b in boxes if b["kind"] == "label"}
    track = {
        (b["frame_id"], b["object_index"]): b for b in boxes if b["kind"] == "suggested" and b["source"] == "track"
    }
    assert all(b["source"] in ("fit", "track") for b in boxes if b["kind"] == "suggested")
    injected = {k for k, b in labels.items() if truth[(b["frame_id"], b["object_id"])]["track_error_kind"] != "none"}
    assert len(injected) >= 10 and set(track) == injected  # every injected frame gets one, no clean frame does
    assert summary["track_suggested"] == len(injected)
    fused = {
        (t["log_id"], t["object_id"]): (t["length"], t["width"], t["height"])
        for t in pq.read_table(results / R.TRACKS_FILE).to_pylist()
    }

    def corner_error(b, true_box):  # mean distance of the 8 corners (in order: a flip counts)
        return float(np.linalg.norm(box_corners([b[c] for c in R.BOX_COLUMNS]) - box_corners(true_box), axis=-1).mean())

    errors = []
    for key in injected:
        label, fix = labels[key], track[key]
        m = truth[(label["frame_id"], label["object_id"])]
        assert (
            fix["track_issue"] == ISSUE_OF_KIND[m["track_error_kind"]]
            and fix["score"] == fix["track_error"] == label["track_error"] > 0.5
        )
        errors.append((corner_error(fix, m["true_box"]), corner_error(label, m["true_box"])))
        assert errors[-1][0] < errors[-1][1], (
            m["track_error_kind"],
            fix,
            label,
        )  # closer to the true box than the label it fixes
        assert [fix["length"], fix["width"], fix["height"]] == pytest.approx(
            fused[(log_of(label["frame_id"]), label["object_id"])], abs=1e-9
        )
    assert np.median([f for f, _ in errors]) < 0.25 * np.median([lab for _, lab in errors])
    # A label with both suggestions gets both rows, and both are in the sidecar, tagged.
    fits = {(b["frame_id"], b["object_index"]) for b in boxes if b["kind"] == "suggested" and b["source"] == "fit"}
    assert fits & injected
    changes = list(csv.DictReader((tmp_path / "review" / "changes.csv").open()))
    assert sorted((c["frame_id"], int(c["object_index"]), c["source"]) for c in changes) == sorted(
        [(f, i, "fit") for f, i in fits] + [(f, i, "track") for f, i in track]
    )
    assert all(c["track_issue"] != "none" for c in changes if c["source"] == "track")
    # The threshold moves them; bad values and misuse are refused.
    result = invoke(
        "export", results, "--format", "kitti-labels", "-o", tmp_path / "review", "--json", "--min-track-error", "1"
    )
    assert result.exit_code == 0 and json.loads(result.stdout)["track_suggested"] == 0
    assert not any(b["source"] == "track" for b in pq.read_table(tmp_path / "review" / "boxes.parquet").to_pylist())
    assert (
        invoke(
            "export", results, "--format", "kitti-labels", "-o", tmp_path / "r2", "--min-track-error", "1.5"
        ).exit_code
        == 2
    )
    assert invoke("export", results, "-o", tmp_path / "x.parquet", "--min-track-error", "0.7").exit_code == 2

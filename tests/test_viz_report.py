"""`report` and the `show`/`report` commands: sections, gallery, anchors, eval folder, bad input, exit codes."""

from __future__ import annotations

import json
import re
import shutil
from html.parser import HTMLParser

import matplotlib.image as mpimg
import numpy as np
import pytest
from typer.testing import CliRunner

from labelaudit import results as R
from labelaudit.cli import app
from labelaudit.viz.evalsection import read_eval_dir, usual_threshold
from labelaudit.viz.objects import ViewError
from labelaudit.viz.plots import binned_means, corner_variance_plot, distribution_plot
from labelaudit.viz.report import anchor_of, build_report
from results_factory import make_results, make_row
from viz_data import eval_summary, make_eval_dir, simulate_and_infer

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate_and_infer(tmp_path_factory.mktemp("viz_report"))


class _Page(HTMLParser):
    """The bits of a report the tests look at: ids, images, gallery entries, external references."""

    def __init__(self):
        super().__init__()
        self.ids, self.imgs, self.entries, self.external = [], [], {}, []
        self._gallery = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if "id" in a:
            self.ids.append(a["id"])
        if tag == "section" and "data-gallery" in a:
            self._gallery = a["data-gallery"]
            self.entries[self._gallery] = []
        if tag == "article" and "entry" in a.get("class", ""):
            self.entries[self._gallery].append(a["data-object"])
        if tag == "img":
            self.imgs.append(a["src"])
        for key in ("src", "href"):
            v = a.get(key, "")
            if v and not v.startswith(("#", "data:")):
                self.external.append(v)
        if tag in ("script", "link"):
            self.external.append(tag)


def _page(path) -> _Page:
    p = _Page()
    p.feed(path.read_text())
    return p


def test_report_holds_summary_gate_plots_gallery_and_eval(sim, tmp_path):
    _, results = sim
    ev = make_eval_dir(tmp_path / "eval")
    out = tmp_path / "r" / "report.html"
    calls = []
    s = build_report(results, out, gate="default", top=4, eval_dir=ev, progress=lambda d, n: calls.append((d, n)))
    page = _page(out)
    html = out.read_text()
    assert (
        s.objects == s.evaluated > 0
        and s.gallery == {"label_error": 4, "jiou_gt": 4}
        and s.gate_verdict in ("PASS", "FAIL")
    )
    # One progress bar over the gallery pictures and then the missing-label candidates' pictures.
    assert calls and calls[-1][0] == calls[-1][1] == s.pictures + s.missing_pictures and 4 <= s.pictures <= 8
    for section in ("summary", "gate", "plots", "by-label_error", "by-jiou_gt", "eval", "ap", "overlap", "counts"):
        assert section in page.ids
    assert page.external == []  # self-contained: no script, no stylesheet link, no remote src/href
    assert all(src.startswith("data:image/png;base64,") for src in page.imgs)
    # 5 plots, one per gallery entry, one per pictured missing-label candidate, 2 eval PNGs
    assert len(page.imgs) == 5 + sum(len(g) for g in page.entries.values()) + s.missing_pictures + 2
    # Galleries: worst by label_error / JIoU-GT in rank order, anchors unique and stable.
    opened = R.open_results(results)
    rows = opened.read().to_pylist()
    by_le = [
        anchor_of(r["frame_id"], r["object_index"])
        for r in sorted(rows, key=lambda r: (-r["label_error"], r["frame_id"], r["object_index"]))[:4]
    ]
    by_j = [
        anchor_of(r["frame_id"], r["object_index"])
        for r in sorted(
            (r for r in rows if r["num_points"] >= 1), key=lambda r: (r["jiou_gt"], r["frame_id"], r["object_index"])
        )[:4]
    ]
    assert page.entries == {"label_error": by_le, "jiou_gt": by_j}
    assert len(page.ids) == len(set(page.ids))
    assert set(by_le + by_j) <= set(page.ids)
    assert re.search(r'id="\d{6}-\d+"', html)
    # Eval: Car at 0.7, Pedestrian at 0.5, R40 only.
    assert 'Car</td><td class="n">0.7' in html and 'Pedestrian</td><td class="n">0.5' in html
    assert "0.6000" in html  # Car iou Easy, R40 at 0.7 (0.80 − 0.2)
    assert "0.5900" not in html and "0.8000" not in html  # …not its R11 value, not Car at 0.5
    assert "pr_curve.png" in html and "jiou_vs_distance.png" in html


def test_report_escapes_user_strings(tmp_path):
    evil = "<script>alert(1)</script>"
    root = make_results(tmp_path / "res", [[make_row("000001", 0, class_name=evil, label_error=0.5)]])
    m = json.loads((root / "manifest.json").read_text())
    m["input"] = str(tmp_path / "gone")
    (root / "manifest.json").write_text(json.dumps(m))
    # The gallery needs the dataset: a moved one is an error naming --dataset …
    with pytest.raises(ViewError, match="--dataset"):
        build_report(root, tmp_path / "r.html")
    # … and the summary escapes the class name (no gallery needed: --top is still ≥ 1, so patch ranking away)
    out = tmp_path / "r2.html"
    from labelaudit.viz import report as rep

    text = rep.render_report(
        {
            "title": evil,
            "results_root": evil,
            "generated": "now",
            "version": "x",
            "gate": None,
            "plots": [],
            "top": 1,
            "gallery_size": (10, 10),
            "eval": None,
            "galleries": [],
            "tracks": {
                "tracks": 1,
                "judged": 3,
                "flagged": 1,
                "threshold": 0.9,
                "by_issue": [("size", 1)],
                "tracks_flagged": 1,
                "noise": [(evil, "center 0.030")],
                "worst": [
                    {
                        "log_id": evil,
                        "object_id": evil,
                        "class_name": evil,
                        "frames": 3,
                        "size": evil,
                        "speed": 1.0,
                        "flagged": 1,
                        "max_track_error": 0.99,
                        "worst_frame_id": evil,
                        "worst_object_index": 0,
                        "worst_issue": "size",
                        "anchor": evil,
                    }
                ],
            },
            "missing": {
                "searched": True,
                "total": 1,
                "counted": 1,
                "frames": 1,
                "min_score": 0.5,
                "by_class": [{"name": evil, "counted": 1, "total": 1, "sources": [1, 0, 0]}],
                "entries": [
                    {
                        "rank": 1,
                        "anchor": f"missing-{evil}-0",
                        "frame_id": evil,
                        "candidate_index": 0,
                        "class_name": evil,
                        "numbers": [("source", evil)],
                        "command": evil,
                        "src": "",
                        "error": evil,
                    }
                ],
            },
            "summary": {
                "objects": 1,
                "evaluated": 1,
                "complete": True,
                "run": [("dataset", evil)],
                "statuses": ["ok"],
                "status_totals": [1],
                "by_class": [
                    {"name": evil, "total": 1, "statuses": [1], "median_jiou_gt": 0.5, "median_label_error": None}
                ],
                "failed_frames": [],
                "failed_total": 0,
                "warnings_total": 0,
            },
        }
    )
    out.write_text(text)
    assert evil not in text and "&lt;script&gt;" in text
    assert _page(out).external == []


def test_empty_and_failed_results_give_a_report_that_says_so(sim, tmp_path):
    data, _ = sim
    # A run whose every frame fails: no objects, errors.parquet lists them.
    broken = tmp_path / "broken"
    shutil.copytree(data, broken)
    for f in (broken / "training" / "velodyne").glob("*.bin"):
        f.unlink()
    from labelaudit.config import resolve_config
    from labelaudit.executors import SerialExecutor
    from labelaudit.infer.run import InferRequest, run_infer

    run_infer(InferRequest(broken, tmp_path / "res", "kitti"), resolve_config(None, "kitti"), executor=SerialExecutor())
    result = invoke("report", tmp_path / "res", "-o", tmp_path / "r.html", "--gate", "default")
    assert result.exit_code == 2, result.output
    html = (tmp_path / "r.html").read_text()
    assert "holds no audited objects" in html and "frame(s) failed" in html and "point cloud not found" in html
    assert "NOT EVALUATED" in html
    assert result.stdout.strip() == str(tmp_path / "r.html")
    # A results folder with a manifest but no shard at all.
    bare = tmp_path / "bare"
    make_results(bare, [])
    result = invoke("report", bare, "-o", tmp_path / "b.html")
    assert result.exit_code == 2 and "holds no audited objects" in (tmp_path / "b.html").read_text()
    # show: exit 2
    result = invoke("show", bare, "000001", "0", "-o", tmp_path / "x.png")
    assert result.exit_code == 2 and not (tmp_path / "x.png").exists()
    # not a results folder at all
    result = invoke("report", tmp_path / "nothing", "-o", tmp_path / "n.html")
    assert result.exit_code == 2 and "no such results folder" in result.stderr


def test_show_command(sim, tmp_path):
    data, results = sim
    out = tmp_path / "o.png"
    result = invoke("show", results, "000001", "2", "-o", out, "--size", "480x400")
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(out) and mpimg.imread(out).shape[:2] == (400, 480)
    result = invoke("show", results, "000001", "-o", tmp_path / "f.png", "--by", "label_error")
    assert result.exit_code == 0 and mpimg.imread(tmp_path / "f.png").shape[:2] == (800, 1000)
    result = invoke("show", results, "1", "0", "-o", out)
    assert result.exit_code == 2 and "nearest: 000001" in result.stderr
    result = invoke("show", results, "000001", "42", "-o", out)
    assert result.exit_code == 2 and "no audited object 42" in result.stderr and "(Car)" in result.stderr
    result = invoke("show", results, "000001", "0", "--size", "big")
    assert result.exit_code == 2 and "WIDTHxHEIGHT" in result.output
    moved = tmp_path / "res"
    shutil.copytree(results, moved)
    m = json.loads((moved / "manifest.json").read_text())
    m["input"] = str(tmp_path / "gone")
    (moved / "manifest.json").write_text(json.dumps(m))
    result = invoke("show", moved, "000001", "0", "-o", out)
    assert result.exit_code == 2 and "--dataset" in result.stderr
    result = invoke("show", moved, "000001", "0", "-o", out, "--dataset", data)
    assert result.exit_code == 0, result.output
    result = invoke("report", moved, "-o", tmp_path / "m.html", "--top", "2")
    assert result.exit_code == 2 and "--dataset" in result.stderr
    result = invoke("report", moved, "-o", tmp_path / "m.html", "--top", "2", "--dataset", data, "--quiet")
    assert result.exit_code == 0 and (tmp_path / "m.html").is_file()


@pytest.mark.parametrize("command", ["show", "report"])
def test_help_has_examples(command):
    result = invoke(command, "--help")
    assert result.exit_code == 0 and "Examples" in result.stdout and f"labelaudit {command}" in result.stdout


def test_eval_dir_contract_is_checked(tmp_path):
    ok = read_eval_dir(make_eval_dir(tmp_path / "ok"))
    assert [p[0] for p in ok.plots] == ["jiou_vs_distance.png", "pr_curve.png"]
    assert ok.ap_columns == ["Easy", "Moderate", "Hard"]
    car = [r for r in ok.ap_rows if r["class"] == "Car"]
    assert {r["threshold"] for r in car} == {0.7} and [r["metric"] for r in car] == ["iou", "jiou", "jiou_ratio"]
    assert car[0]["cells"][0]["ap"] == pytest.approx(0.6)
    assert usual_threshold("Car") == 0.7 and usual_threshold("Pedestrian") == 0.5 and usual_threshold("Cyclist") == 0.5
    assert ok.overlap_columns == ["0-20 m", "20-40 m", "40+ m"] and ok.overlap_rows[0]["cells"][2]["count"] == 12

    s = eval_summary()
    del s["ap"][3]["threshold"]
    make_eval_dir(tmp_path / "b1", s)
    with pytest.raises(ViewError, match=r"summary.json: ap\[3\] has no field 'threshold'"):
        read_eval_dir(tmp_path / "b1")
    s = eval_summary()
    s["mean_overlap"][1]["metric"] = "giou"
    make_eval_dir(tmp_path / "b2", s)
    with pytest.raises(ViewError, match=r"mean_overlap\[1\]\.metric must be one of iou, jiou, jiou_ratio"):
        read_eval_dir(tmp_path / "b2")
    s = eval_summary()
    s["ap"][0]["num_gt"] = "many"
    make_eval_dir(tmp_path / "b3", s)
    with pytest.raises(ViewError, match=r"ap\[0\]\.num_gt must be int"):
        read_eval_dir(tmp_path / "b3")
    s = eval_summary()
    del s["counts"]
    make_eval_dir(tmp_path / "b4", s)
    with pytest.raises(ViewError, match="missing top-level key.*counts"):
        read_eval_dir(tmp_path / "b4")
    make_eval_dir(tmp_path / "b5")
    (tmp_path / "b5" / "summary.json").write_text('{"ap": [,]}')
    with pytest.raises(ViewError, match=r"summary.json:1:\d+: not valid JSON"):
        read_eval_dir(tmp_path / "b5")
    make_eval_dir(tmp_path / "b6")
    (tmp_path / "b6" / "broken.png").write_bytes(b"GIF89a")
    with pytest.raises(ViewError, match="broken.png: not a PNG"):
        read_eval_dir(tmp_path / "b6")
    with pytest.raises(ViewError, match="no such folder"):
        read_eval_dir(tmp_path / "absent")
    s = eval_summary()
    s["ap"] = [r for r in s["ap"] if not (r["class"] == "Car" and r["threshold"] == 0.7)]
    make_eval_dir(tmp_path / "b7", s)
    note = [r for r in read_eval_dir(tmp_path / "b7").ap_rows if r["class"] == "Car"][0]["note"]
    assert "no R40 AP at 0.7" in note and "thresholds 0.5" in note


def test_plot_numbers():
    centres, means, counts = binned_means(
        np.array([1.0, 2.0, 3.0, 11.0, 12.0, 13.0, 25.0]),
        np.array([0.9, 0.8, 0.7, 0.5, 0.6, 0.7, 0.1]),
        np.array([0.0, 10.0, 20.0, 30.0]),
    )
    np.testing.assert_allclose(centres, [5, 15, 25])
    np.testing.assert_allclose(means[:2], [0.8, 0.6]) and np.testing.assert_array_equal(counts, [3, 3, 1])
    assert np.isnan(means[2])  # one object: below REPORT_MIN_BIN_COUNT
    cls = np.array(["Car", "Car", "Van"], dtype=object)
    p = corner_variance_plot(cls, np.array([[1.0, 2, 3, 4], [3.0, 4, 5, 6], [0.5, 0.5, 0.5, 0.5]]))
    assert p.data["Car"] == {"mean": [2.0, 3.0, 4.0, 5.0], "count": 2} and p.png.startswith(b"\x89PNG")
    d = distribution_plot(cls, np.array([0.05, 0.95, np.nan]), "t", "x", bins=10)
    assert d.data["Car"]["counts"] == [1, 0, 0, 0, 0, 0, 0, 0, 0, 1] and "Van" not in d.data

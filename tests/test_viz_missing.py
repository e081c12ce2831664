"""Missing-label candidates where a user looks: `show` (frame and close-up) and the report's section."""

from __future__ import annotations

import io
import re

import matplotlib.image as mpimg
import numpy as np
import pytest
from typer.testing import CliRunner

from labelaudit.cli import app
from labelaudit.core import geometry as g
from labelaudit.results import open_results
from labelaudit.viz.objects import frame_candidates, frame_rows, load_frame, open_source
from labelaudit.viz.report import build_report, missing_anchor
from labelaudit.viz.show import CANDIDATE_COLOUR, render_candidate, render_frame
from results_factory import add_missing, make_candidate
from viz_data import simulate_and_infer, simulate_with_a_dropped_label

runner = CliRunner()
FRAME = "000001"


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture(scope="module")
def dropped(tmp_path_factory):
    return simulate_with_a_dropped_label(tmp_path_factory.mktemp("viz_missing"), FRAME)


def _image(png: bytes) -> np.ndarray:
    return mpimg.imread(io.BytesIO(png), format="png")[..., :3]


def _magenta_pixels(png: bytes) -> int:
    want = np.array([int(CANDIDATE_COLOUR[i : i + 2], 16) for i in (1, 3, 5)]) / 255.0
    return int(np.sum(np.abs(_image(png) - want).max(axis=-1) < 0.08))


def _frame(results):
    """The opened results, the frame, its label rows and its candidates."""
    opened = open_results(results)
    return (
        opened,
        load_frame(open_source(opened), FRAME),
        frame_rows(opened, FRAME).to_pylist(),
        frame_candidates(opened, FRAME),
    )


def test_frame_picture_draws_candidates_in_their_own_style(dropped):
    _, results, box = dropped
    _, frame, rows, cands = _frame(results)
    assert [c["candidate_index"] for c in cands] == [0, 1]
    with_c = render_frame(FRAME, frame.points, rows, "jiou_gt", (800, 640), 3, frame.sensor_origin, cands)
    without = render_frame(FRAME, frame.points, rows, "jiou_gt", (800, 640), 3, frame.sensor_origin)
    assert list(with_c.candidate_indices) == [0, 1]
    np.testing.assert_allclose(with_c.candidate_corners[0], g.box_corners(box, "bev"))
    assert "2 possibly missing label(s): M0 Car (0.93)  M1 Car (0.55)" in with_c.caption
    # Magenta is the candidates' alone: none without them, plenty with them.
    assert _magenta_pixels(without.png) == 0 and _magenta_pixels(with_c.png) > 200
    assert _image(with_c.png).shape[:2] == (640, 800)
    # The view reaches every candidate.
    x0, x1, y0, y1 = with_c.view
    corners = with_c.candidate_corners.reshape(-1, 2)
    assert (
        (corners[:, 0] > x0).all()
        and (corners[:, 0] < x1).all()
        and (corners[:, 1] > y0).all()
        and (corners[:, 1] < y1).all()
    )


def test_candidate_close_up_holds_the_dropped_cars_points(dropped):
    _, results, box = dropped
    _, frame, rows, (cand, weak) = _frame(results)
    pic = render_candidate(FRAME, frame.points, cand, rows, (640, 600), frame.sensor_origin)
    # Independently: the frame's points inside the dropped car's box (BEV, between its bottom and top).
    pts = frame.points.astype(float)
    c, s = np.cos(box[6]), np.sin(box[6])
    d = pts[:, :2] - box[:2]
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    inside = (
        (np.abs(u) <= box[3] / 2)
        & (np.abs(v) <= box[4] / 2)
        & (pts[:, 2] >= box[2] - box[5] / 2)
        & (pts[:, 2] <= box[2] + box[5] / 2)
    )
    assert inside.sum() >= 30  # the nearest car of the frame: a real object the label file no longer has
    assert len(pic.points_xy) == int(inside.sum())
    assert (np.abs(pic.points_xy[:, 0]) <= box[3] / 2 + 1e-9).all() and (pic.point_height >= 0).all()
    np.testing.assert_allclose(np.abs(pic.box_corners), np.tile([box[3] / 2, box[4] / 2], (4, 1)), atol=1e-9)
    assert np.linalg.norm(pic.sensor_direction) == pytest.approx(1.0)
    assert "score 0.930" in pic.caption and "looks like Car" in pic.caption and "source points" in pic.caption
    assert _magenta_pixels(pic.png) > 200
    # The weak candidate on open ground: few or no points inside.
    weak_pic = render_candidate(FRAME, frame.points, weak, rows, (640, 600), frame.sensor_origin, compact=True)
    assert len(weak_pic.points_xy) < len(pic.points_xy)


def test_show_command_with_candidates(dropped, tmp_path, monkeypatch):
    _, results, _ = dropped
    monkeypatch.chdir(tmp_path)  # the default name is written to the working folder, not the repository's
    out = tmp_path / "c.png"
    result = invoke("show", results, FRAME, "--candidate", "0", "-o", out)
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == str(out) and _image(out.read_bytes()).shape[:2] == (600, 640)
    result = invoke("show", results, FRAME, "-o", tmp_path / "f.png", "--min-score", "0.9")
    assert result.exit_code == 0, result.output
    default_name = invoke("show", results, FRAME, "--candidate", "1")
    assert default_name.exit_code == 0 and default_name.stdout.strip() == f"show-{FRAME}-missing-1.png"
    assert (tmp_path / f"show-{FRAME}-missing-1.png").is_file()
    for args, needle in (
        ((FRAME, "--candidate", "7"), "no candidate 7; its candidates: 0 (Car, score 0.93), 1 (Car, score 0.55)"),
        (("000000", "--candidate", "0"), "no missing-label candidate; frames with candidates nearest to it: 000001"),
        ((FRAME, "0", "--candidate", "0"), "either an OBJECT or a --candidate"),
        ((FRAME, "--min-score", "2"), "--min-score"),
    ):
        result = invoke("show", results, *args, "-o", tmp_path / "x.png")
        assert result.exit_code == 2, (args, result.output)
        assert needle in result.stderr.replace("\n", " "), (args, result.stderr)


def test_report_has_a_possibly_missing_labels_section(dropped, tmp_path):
    _, results, _ = dropped
    out = tmp_path / "report.html"
    summary = build_report(results, out, top=3)
    html = out.read_text()
    assert summary.missing_pictures == 2 and summary.missing_counted == 2
    section = html[html.index('<section id="missing"') :]
    section = section[: section.index("</section>")]
    assert "Possibly missing labels" in section and "<strong>2</strong> candidate(s)" in section
    anchors = re.findall(r'<article class="candidate" id="([^"]+)" data-candidate', section)
    assert anchors == [missing_anchor(FRAME, 0), missing_anchor(FRAME, 1)] == ["missing-000001-0", "missing-000001-1"]
    assert section.count('src="data:image/png;base64,') == 2
    assert f"--candidate 0 -o missing-{FRAME}-0.png" in section
    assert '<a href="#missing">' in html


def test_report_section_without_search_or_without_strong_candidates(tmp_path):
    import shutil

    data, results = simulate_and_infer(tmp_path, frames=1)
    plain = tmp_path / "plain"
    assert invoke("infer", data, "-o", plain, "--no-missing", "--quiet").exit_code == 0
    build_report(plain, tmp_path / "a.html", top=1)
    assert "did not search for objects without a label" in (tmp_path / "a.html").read_text()
    shutil.rmtree(results / "missing", ignore_errors=True)
    add_missing(results, [[make_candidate("000000", 0, 0.2)]])
    summary = build_report(results, tmp_path / "b.html", top=1)
    html = (tmp_path / "b.html").read_text()
    assert "No candidate with a score of at least 0.5 (1 below it)" in html and summary.missing_pictures == 0


def test_report_command_names_the_missing_labels(dropped, tmp_path):
    _, results, _ = dropped
    result = invoke("report", results, "-o", tmp_path / "r.html", "--top", "1")
    assert result.exit_code == 0, result.output
    assert "2 possibly missing labels (1 pictured)" in result.stderr.replace("\n", " ")
    assert result.stdout.strip() == str(tmp_path / "r.html")


def test_a_frame_without_labels_but_with_a_candidate_is_drawn(tmp_path):
    import shutil

    from labelaudit.sim.dataset import simulate_dataset

    data = tmp_path / "sim"
    simulate_dataset(data, frames=2, seed=4, progress=False)
    split = data / "training" if (data / "training").is_dir() else data
    (split / "label_2" / "000000.txt").write_text("")  # nobody labelled this frame
    assert invoke("infer", data, "-o", tmp_path / "res", "--quiet").exit_code == 0
    shutil.rmtree(tmp_path / "res" / "missing", ignore_errors=True)
    add_missing(tmp_path / "res", [[make_candidate("000000", 0, 0.8)]])
    result = invoke("show", tmp_path / "res", "000000", "-o", tmp_path / "f.png")
    assert result.exit_code == 0, result.output
    assert _magenta_pixels((tmp_path / "f.png").read_bytes()) > 100
    assert invoke("show", tmp_path / "res", "000000", "--candidate", "0", "-o", tmp_path / "c.png").exit_code == 0
    result = invoke("show", tmp_path / "res", "000000", "0", "-o", tmp_path / "o.png")  # an object: there is none
    assert result.exit_code == 2 and "000000" in result.stderr

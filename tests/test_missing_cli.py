"""The missing-label candidates through the CLI: `rank --missing` (table / JSON / CSV, filters, exit codes)."""

from __future__ import annotations

import csv
import io
import json

import pytest
from typer.testing import CliRunner

from labelaudit.cli import app
from results_factory import add_missing, make_candidate, make_results, make_row

runner = CliRunner()


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


@pytest.fixture()
def with_missing(tmp_path):
    root = make_results(
        tmp_path / "r", [[make_row("000001", i) for i in range(3)], [make_row("000002", i) for i in range(2)]]
    )
    return add_missing(
        root,
        [
            [
                make_candidate("000001", 0, 0.95),
                make_candidate("000001", 1, 0.30, class_name="Van"),
                make_candidate("000001", 2, 0.55, source="both"),
            ],
            [make_candidate("000002", 0, 0.72, source="detections", num_points=12), make_candidate("000002", 1, 0.55)],
            [],  # a chunk whose frames had no candidate
        ],
    )


def test_rank_missing_json_is_highest_score_first_with_every_column(with_missing):
    result = invoke("rank", with_missing, "--missing", "--format", "json")
    assert result.exit_code == 0, result.output
    rows = json.loads(result.stdout)
    assert [(r["frame_id"], r["candidate_index"]) for r in rows] == [
        ("000001", 0),
        ("000002", 0),
        ("000001", 2),
        ("000002", 1),
        ("000001", 1),
    ]
    assert [r["score"] for r in rows] == sorted((r["score"] for r in rows), reverse=True)
    first = list(rows[0])
    assert first[:14] == [
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
    ]
    assert "size_score" in first and rows[0]["detection_score"] is None  # evidence columns, nulls as null


def test_rank_missing_filters(with_missing):
    rows = json.loads(
        invoke("rank", with_missing, "--missing", "--min-score", "0.5", "--class", "Car", "--format", "json").stdout
    )
    assert {(r["frame_id"], r["candidate_index"]) for r in rows} == {
        ("000001", 0),
        ("000001", 2),
        ("000002", 0),
        ("000002", 1),
    }
    rows = json.loads(
        invoke("rank", with_missing, "--missing", "--source", "detections,both", "--format", "json").stdout
    )
    assert [(r["frame_id"], r["candidate_index"]) for r in rows] == [("000002", 0), ("000001", 2)]
    rows = json.loads(
        invoke("rank", with_missing, "--missing", "--min-points", "100", "--top", "2", "--format", "json").stdout
    )
    assert [(r["frame_id"], r["candidate_index"]) for r in rows] == [("000001", 0), ("000001", 2)]
    rows = json.loads(
        invoke(
            "rank",
            with_missing,
            "--missing",
            "--where",
            "frame_id==000002",
            "--by",
            "num_points",
            "--asc",
            "--format",
            "json",
        ).stdout
    )
    assert [r["num_points"] for r in rows] == [12, 150]
    result = invoke("rank", with_missing, "--missing", "--min-score", "0.99", "--format", "json")
    assert result.exit_code == 0 and json.loads(result.stdout) == [] and "no candidates match" in result.stderr


def test_rank_missing_csv_and_table(with_missing):
    result = invoke("rank", with_missing, "--missing", "--format", "csv", "--top", "3")
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader(io.StringIO(result.stdout)))
    assert len(rows) == 3 and float(rows[0]["score"]) == 0.95 and rows[0]["detection_score"] == ""
    result = invoke("rank", with_missing, "--missing")
    assert result.exit_code == 0, result.output
    assert (
        "missing-label candidates" in result.stdout and "candidate_index" in result.stdout and "0.950" in result.stdout
    )
    assert "5 in the results" in result.stdout


def test_rank_missing_usage_errors(with_missing, tmp_path):
    for args, needle in (
        (("--missing", "--status", "ok"), "--status"),
        (("--missing", "--min-score", "1.5"), "--min-score"),
        (("--missing", "--source", "radar"), "--source"),
        (("--missing", "--by", "jiou_gt"), "not a numeric column"),
        (("--missing", "--top", "0"), "--top"),
        (("--min-score", "0.5"), "only with --missing"),
    ):
        result = invoke("rank", with_missing, *args)
        assert result.exit_code == 2, (args, result.output)
        assert needle in result.stderr, (args, result.stderr)
        assert result.stdout == ""
    # A run without the search: exit 2, and the message says how to get the table.
    plain = make_results(tmp_path / "plain", [[make_row("000001", 0)]])
    result = invoke("rank", plain, "--missing")
    assert result.exit_code == 2 and "--no-missing" in result.stderr
    # The labels' ranking is unchanged by the candidates beside it.
    rows = json.loads(invoke("rank", with_missing, "--format", "json").stdout)
    assert len(rows) == 5 and all("object_index" in r for r in rows)


# --------------------------------------------------------------------------- check


def _gate_file(tmp_path, per_frame: float, floor: float = 0.5):
    path = tmp_path / f"gate-{per_frame}.toml"
    path.write_text(
        f"[default]\nmin_median_jiou_gt = 0.5\nmissing_score_threshold = {floor}\nmax_missing_per_frame = {per_frame}\n"
    )
    return path


def test_check_missing_rule_exit_codes_json_and_junit(with_missing, tmp_path):
    import xml.etree.ElementTree as ET

    # 4 candidates with score ≥ 0.5 in 2 frames: 2 per frame.
    result = invoke("check", with_missing, "--config", _gate_file(tmp_path, 2.0), "--json")
    assert result.exit_code == 0, result.output
    (rule,) = [r for r in json.loads(result.stdout)["rules"] if r["rule"] == "max_missing_per_frame"]
    assert (
        rule["value"] == 2.0 and rule["status"] == "pass" and rule["scope"] == "dataset" and rule["comparison"] == "<="
    )
    junit = tmp_path / "gate.xml"
    result = invoke("check", with_missing, "--config", _gate_file(tmp_path, 1.5), "--json", "--junit", junit)
    assert result.exit_code == 1, result.output
    data = json.loads(result.stdout)
    assert data["verdict"] == "FAIL"
    (rule,) = [r for r in data["rules"] if r["rule"] == "max_missing_per_frame"]
    assert rule["status"] == "fail" and "most in frame 000001 (2)" in rule["note"]
    cases = {c.get("name"): c for c in ET.parse(junit).getroot().iter("testcase")}
    assert cases["max_missing_per_frame"].find("failure") is not None
    # The score threshold comes from the gate file: at 0.9 only one candidate counts.
    assert invoke("check", with_missing, "--config", _gate_file(tmp_path, 0.5, floor=0.9)).exit_code == 0
    # The table output names the rule; a gate file with a bad value is exit 2.
    result = invoke("check", with_missing, "--config", _gate_file(tmp_path, 1.5))
    assert result.exit_code == 1 and "max_missing_per_frame" in result.stdout
    bad = tmp_path / "bad.toml"
    bad.write_text("[default]\nmax_missing_per_frame = 1\n")
    result = invoke("check", with_missing, "--config", bad)
    assert result.exit_code == 2 and "needs missing_score_threshold" in result.stderr


def test_check_default_gate_skips_the_missing_rule_without_the_search(tmp_path):
    plain = make_results(tmp_path / "plain", [[make_row("000001", i, jiou_gt=0.85) for i in range(20)]])
    result = invoke("check", plain, "--json")
    assert result.exit_code == 0, result.output
    (rule,) = [r for r in json.loads(result.stdout)["rules"] if r["rule"] == "max_missing_per_frame"]
    assert rule["status"] == "skip"

"""CI gate: config validation, per-class rules, exit codes, JSON and JUnit output."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest

from labelaudit.config import ConfigError
from labelaudit.gate import DEFAULT_GATE_PATH, KEYS, evaluate_gate, gate_from_dict, load_gate
from labelaudit.results import ResultsError, open_results
from results_factory import make_results, make_row

ISSUE_EXAMPLE = {
    "default": {
        "min_median_jiou_gt": 0.6,
        "jiou_gt_threshold": 0.3,
        "max_fraction_jiou_gt_below": 0.05,
        "max_fraction_no_points": 0.10,
        "label_error_threshold": 0.5,
        "max_fraction_label_error_above": 0.02,
        "max_failed_frames": 0,
    },
    "class": {"Pedestrian": {"min_median_jiou_gt": 0.4}},
}


def _cars(n: int, jiou: float, frame: str = "000001", **kw):
    return [make_row(frame, i, jiou_gt=jiou, **kw) for i in range(n)]


def _outcome(report, scope: str, rule: str):
    (r,) = [r for r in report.results if r.scope == scope and r.rule == rule]
    return r


def test_builtin_gate_file_loads_and_uses_the_issue_key_names():
    gate = load_gate(None)
    assert DEFAULT_GATE_PATH.is_file()
    for key in ISSUE_EXAMPLE["default"]:
        assert key in gate.default
    assert gate.rules_for("Pedestrian")["min_median_jiou_gt"] < gate.rules_for("Car")["min_median_jiou_gt"]


@pytest.mark.parametrize(
    "data, match",
    [
        ({"default": {"min_median_jiou": 0.5}}, "unknown key.*min_median_jiou"),
        ({"defaults": {}}, "unknown table"),
        ({"default": {"max_fraction_jiou_gt_below": 0.1}}, "needs jiou_gt_threshold"),
        ({"default": {"max_fraction_no_points": 1.5}}, r"fraction in \[0, 1\]"),
        ({"default": {"max_failed_frames": 0.5}}, "whole number"),
        ({"default": {"min_median_jiou_gt": "high"}}, "must be a number"),
        ({"default": {"min_median_jiou_gt": 0.5}, "class": {"Car": {"max_failed_frames": 1}}}, "dataset-wide"),
        ({"default": {"jiou_gt_threshold": 0.3}}, "no rules"),
    ],
)
def test_bad_gate_configs_are_rejected_with_the_key(data, match):
    with pytest.raises(ConfigError, match=match):
        gate_from_dict(data, source="gate.toml")


def test_gate_file_errors_name_the_file(tmp_path):
    bad = tmp_path / "g.toml"
    bad.write_text("[default]\nmin_median_jiou_gt = \n")
    with pytest.raises(ConfigError, match="g.toml.*not valid TOML"):
        load_gate(bad)
    with pytest.raises(ConfigError, match="not found"):
        load_gate(tmp_path / "missing.toml")


def test_all_rules_pass_gives_exit_0(tmp_path):
    res = open_results(make_results(tmp_path, [_cars(20, 0.8)]))
    report = evaluate_gate(res, gate_from_dict(ISSUE_EXAMPLE))
    assert report.exit_code == 0 and report.verdict == "PASS"
    assert _outcome(report, "Car", "min_median_jiou_gt").value == pytest.approx(0.8)
    # label_error is all null: its rule is inactive, not an error
    assert _outcome(report, "Car", "max_fraction_label_error_above").status == "skip"
    assert _outcome(report, "dataset", "max_failed_frames").status == "pass"


def test_low_median_fails_with_exit_1(tmp_path):
    res = open_results(make_results(tmp_path, [_cars(20, 0.5)]))
    report = evaluate_gate(res, gate_from_dict(ISSUE_EXAMPLE))
    assert _outcome(report, "Car", "min_median_jiou_gt").status == "fail"
    assert report.exit_code == 1


def test_fraction_below_threshold_grows_with_bad_labels(tmp_path):
    values = []
    for n_bad in (0, 1, 4):
        rows = _cars(20 - n_bad, 0.8) + [make_row("000009", i, jiou_gt=0.1) for i in range(n_bad)]
        res = open_results(make_results(tmp_path / str(n_bad), [rows]))
        values.append(_outcome(evaluate_gate(res, gate_from_dict(ISSUE_EXAMPLE)), "Car", "max_fraction_jiou_gt_below"))
    assert [v.value for v in values] == [0.0, 0.05, 0.2]
    assert [v.status for v in values] == ["pass", "pass", "fail"]


def test_per_class_override(tmp_path):
    rows = _cars(10, 0.8) + [make_row("000002", i, "Pedestrian", jiou_gt=0.45) for i in range(10)]
    report = evaluate_gate(open_results(make_results(tmp_path, [rows])), gate_from_dict(ISSUE_EXAMPLE))
    assert _outcome(report, "Pedestrian", "min_median_jiou_gt").threshold == 0.4
    assert _outcome(report, "Pedestrian", "min_median_jiou_gt").status == "pass"
    assert report.exit_code == 0
    stricter = {"default": ISSUE_EXAMPLE["default"]}  # without the override 0.45 < 0.6 fails
    assert evaluate_gate(open_results(make_results(tmp_path / "b", [rows])), gate_from_dict(stricter)).exit_code == 1


def test_label_error_rule_becomes_active_with_values(tmp_path):
    rows = _cars(49, 0.8, label_error=0.1) + [make_row("000002", 0, jiou_gt=0.8, label_error=0.9)]
    report = evaluate_gate(open_results(make_results(tmp_path, [rows])), gate_from_dict(ISSUE_EXAMPLE))
    r = _outcome(report, "Car", "max_fraction_label_error_above")
    assert r.status == "pass" and r.value == pytest.approx(0.02)
    rows += [make_row("000003", 0, jiou_gt=0.8, label_error=0.9)]
    report = evaluate_gate(open_results(make_results(tmp_path / "b", [rows])), gate_from_dict(ISSUE_EXAMPLE))
    assert _outcome(report, "Car", "max_fraction_label_error_above").status == "fail"


def test_no_points_and_failed_frames(tmp_path):
    rows = _cars(8, 0.8) + [make_row("000002", i, status="no_points", jiou_gt=0.7) for i in range(2)]
    errors = [
        {
            "unit": "000003",
            "frame_id": None,
            "file": "x.bin",
            "line": None,
            "level": "error",
            "message": "size not a multiple of 16",
        }
    ]
    report = evaluate_gate(open_results(make_results(tmp_path, [rows], errors)), gate_from_dict(ISSUE_EXAMPLE))
    assert _outcome(report, "Car", "max_fraction_no_points").value == pytest.approx(0.2)
    assert _outcome(report, "Car", "max_fraction_no_points").status == "fail"
    assert _outcome(report, "dataset", "max_failed_frames").value == 1
    assert _outcome(report, "dataset", "max_failed_frames").status == "fail"
    assert report.exit_code == 1


def test_nothing_evaluable_is_exit_2_never_0(tmp_path):
    skipped = [make_row("000001", i, status="skipped", message="too long") for i in range(5)]
    report = evaluate_gate(
        open_results(make_results(tmp_path, [skipped])), gate_from_dict({"default": {"min_median_jiou_gt": 0.5}})
    )
    assert report.exit_code == 2
    assert _outcome(report, "Car", "min_median_jiou_gt").status == "error"
    # only inactive rules → nothing evaluated → 2
    only_label_error = {"default": {"label_error_threshold": 0.5, "max_fraction_label_error_above": 0.1}}
    report = evaluate_gate(
        open_results(make_results(tmp_path / "b", [_cars(5, 0.9)])), gate_from_dict(only_label_error)
    )
    assert {r.status for r in report.results} == {"skip"} and report.exit_code == 2


def test_empty_or_incomplete_results_are_refused(tmp_path):
    with pytest.raises(ResultsError, match="no objects"):
        evaluate_gate(open_results(make_results(tmp_path / "a", [[]])), load_gate(None))
    with pytest.raises(ResultsError, match="did not finish"):
        evaluate_gate(open_results(make_results(tmp_path / "b", [_cars(3, 0.9)], complete=False)), load_gate(None))


def test_class_override_without_objects_is_listed_as_absent(tmp_path):
    report = evaluate_gate(open_results(make_results(tmp_path, [_cars(5, 0.9)])), gate_from_dict(ISSUE_EXAMPLE))
    assert report.absent_classes == ["Pedestrian"]
    assert {r.scope for r in report.results} == {"Car", "dataset"}
    assert report.exit_code == 0


def test_json_and_junit_reports(tmp_path):
    rows = _cars(10, 0.5)
    report = evaluate_gate(open_results(make_results(tmp_path, [rows])), gate_from_dict(ISSUE_EXAMPLE))
    data = json.loads(report.to_json())
    assert data["verdict"] == "FAIL" and data["exit_code"] == 1
    assert {r["rule"] for r in data["rules"]} <= set(KEYS)
    suite = ET.fromstring(report.to_junit()).find("testsuite")
    assert suite is not None
    assert int(suite.get("tests")) == len(report.results)
    assert int(suite.get("failures")) == sum(r.status == "fail" for r in report.results) >= 1
    failed = [c.get("name") for c in suite.iter("testcase") if c.find("failure") is not None]
    assert "min_median_jiou_gt" in failed


def test_track_error_rule_counts_labels_at_or_above_the_threshold_and_is_inactive_without_tracks(tmp_path):
    gate = gate_from_dict({"default": {"track_error_threshold": 0.9, "max_fraction_track_error_above": 0.02}})
    kitti = evaluate_gate(open_results(make_results(tmp_path / "k", [_cars(20, 0.8)])), gate)
    assert _outcome(kitti, "Car", "max_fraction_track_error_above").status == "skip" and kitti.exit_code == 2
    rows = _cars(49, 0.8, track_error=0.1) + [make_row("000002", 0, jiou_gt=0.8, track_error=0.9)]
    r = _outcome(
        evaluate_gate(open_results(make_results(tmp_path / "a", [rows])), gate), "Car", "max_fraction_track_error_above"
    )
    assert r.status == "pass" and r.value == pytest.approx(0.02) and r.objects == 50
    rows += [
        make_row("000003", 0, jiou_gt=0.8, track_error=0.95),
        make_row("000004", 0, jiou_gt=0.8),
    ]  # a row without a track does not count
    r = _outcome(
        evaluate_gate(open_results(make_results(tmp_path / "b", [rows])), gate), "Car", "max_fraction_track_error_above"
    )
    assert r.status == "fail" and r.objects == 51
    with pytest.raises(ConfigError, match="track_error_threshold"):
        gate_from_dict({"default": {"max_fraction_track_error_above": 0.02}})


# --------------------------------------------------------------------------- missing labels

MISSING_GATE = {"default": {"min_median_jiou_gt": 0.5, "missing_score_threshold": 0.5, "max_missing_per_frame": 0.5}}


def test_missing_rule_counts_candidates_above_the_score_per_frame(tmp_path):
    from results_factory import add_missing, make_candidate

    rows = [make_row(f"00000{f}", i) for f in range(4) for i in range(2)]  # 4 frames with labels
    values = []
    for n in (0, 1, 2, 3):  # candidates scoring ≥ 0.5, always in frame 000001, plus one below the threshold
        cands = [make_candidate("000001", k, 0.9) for k in range(n)] + [make_candidate("000002", 0, 0.49)]
        root = add_missing(make_results(tmp_path / str(n), [rows]), [cands])
        values.append(
            _outcome(
                evaluate_gate(open_results(root), gate_from_dict(MISSING_GATE)), "dataset", "max_missing_per_frame"
            )
        )
    assert [v.value for v in values] == [0.0, 0.25, 0.5, 0.75]
    assert [v.status for v in values] == ["pass", "pass", "pass", "fail"]
    assert (
        "3 candidates with score ≥ 0.5 in 4 frames" in values[3].note and "most in frame 000001 (3)" in values[3].note
    )
    # A frame with a candidate but no label counts as a frame.
    root = add_missing(make_results(tmp_path / "extra", [rows]), [[make_candidate("000009", 0, 0.9)]])
    r = _outcome(evaluate_gate(open_results(root), gate_from_dict(MISSING_GATE)), "dataset", "max_missing_per_frame")
    assert r.value == pytest.approx(1 / 5)


def test_missing_rule_is_inactive_without_the_search_and_validated(tmp_path):
    report = evaluate_gate(open_results(make_results(tmp_path, [_cars(5, 0.9)])), gate_from_dict(MISSING_GATE))
    r = _outcome(report, "dataset", "max_missing_per_frame")
    assert r.status == "skip" and "--no-missing" in r.note and report.exit_code == 0
    for data, match in (
        ({"default": {"max_missing_per_frame": 1}}, "needs missing_score_threshold"),
        ({"default": {"missing_score_threshold": 1.5, "max_missing_per_frame": 1}}, r"in \[0, 1\]"),
        ({"default": {"missing_score_threshold": 0.5, "max_missing_per_frame": -1}}, "≥ 0"),
        ({"default": {"min_median_jiou_gt": 0.5}, "class": {"Car": {"max_missing_per_frame": 1}}}, "dataset-wide"),
    ):
        with pytest.raises(ConfigError, match=match):
            gate_from_dict(data, source="gate.toml")
    builtin = load_gate(None)
    assert 0 < builtin.default["missing_score_threshold"] <= 1 and builtin.default["max_missing_per_frame"] >= 0

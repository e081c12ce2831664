"""Results contract: schema, atomic shards, reader, ranking queries (hand-built Parquet folders)."""

from __future__ import annotations

import csv
import io
import json
import math
import re
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from labelaudit import results as R
from labelaudit.rank import RankQuery, default_descending, rank_results, to_csv, to_json
from labelaudit.summary import summarize
from results_factory import make_results, make_row

DOCS = Path(__file__).resolve().parents[1] / "docs" / "results-schema.md"


def test_every_schema_column_is_documented_with_its_type():
    text = DOCS.read_text()
    documented = set(re.findall(r"^\| `([a-z_0-9]+)` \|", text, flags=re.M))
    assert set(R.COLUMN_NAMES) <= documented, set(R.COLUMN_NAMES) - documented
    assert set(R.ERRORS_SCHEMA.names) <= documented


def test_design_contract_columns_are_all_in_the_schema():
    design = [
        "dataset", "frame_id", "object_index", "object_id", "class_name", "cx", "cy", "cz", "length", "width",
        "height", "yaw", "distance", "num_points", "status", "sigma", "jiou_gt", "label_error", "sigma_hat",
        "fit_offset_m", "corner_tv", "std_cx", "std_cy", "std_cz", "std_length", "std_width", "std_height",
        "std_yaw", "cov", "cov_dim", "model", "truncated", "occluded", "difficulty",
    ]  # fmt: skip
    assert [c for c in design if c not in R.COLUMN_NAMES] == []


def test_normalize_row_turns_nan_into_null_and_drops_unknown_keys():
    row = make_row("000001", 0, std_cz=float("nan"), corner_tv=[0.1, float("nan"), 0.2, 0.3], not_a_column=5)
    out = R.normalize_row(row)
    assert out["std_cz"] is None and out["std_cx"] == 0.05
    assert out["corner_tv"][1] is None and out["corner_tv"][0] == 0.1
    assert "not_a_column" not in out
    assert out["label_error"] is None  # missing → null
    assert set(out) == set(R.COLUMN_NAMES)


def test_rows_to_table_sorts_by_frame_then_index_and_keeps_the_schema():
    rows = [make_row("000002", 1), make_row("000001", 3), make_row("000002", 0), make_row("000001", 0)]
    t = R.rows_to_table(rows)
    assert t.schema.equals(R.SCHEMA)
    keys = list(zip(t.column("frame_id").to_pylist(), t.column("object_index").to_pylist()))
    assert keys == [("000001", 0), ("000001", 3), ("000002", 0), ("000002", 1)]
    assert R.rows_to_table([]).num_rows == 0


def test_table_of_rows_is_from_pylist_table_and_errors():
    """The struct conversion gives from_pylist's table (values, nulls, lists, schema) and raises the
    same error types for values the schema cannot hold; keys outside the schema are ignored."""
    rows = [
        R.normalize_row(make_row("000002", i, std_cz=float("nan"), corner_tv=[0.1, None, 0.2, 0.3])) for i in range(3)
    ]
    rows[1]["label_error"] = None
    rows[2]["cov"] = []
    for schema, some in ((R.SCHEMA, rows), (R.SCHEMA, []), (R.SCHEMA, [{**rows[0], "not_a_column": 5}])):
        want, got = pa.Table.from_pylist(some, schema=schema), R.table_of_rows(some, schema)
        assert got.equals(want) and got.schema.equals(want.schema, check_metadata=True)
    assert R.table_of_rows(rows, R.SCHEMA).column("corner_tv").to_pylist()[0] == [0.1, None, 0.2, 0.3]
    for bad in ({"frame_id": "a\udcff"}, {"num_points": 2**40}, {"cx": "x"}):
        with pytest.raises(Exception) as want:
            pa.Table.from_pylist([{**rows[0], **bad}], schema=R.SCHEMA)
        with pytest.raises(type(want.value)):
            R.table_of_rows([{**rows[0], **bad}], R.SCHEMA)
    candidates = [{n: None for n in R.MISSING_SCHEMA.names}]
    assert R.table_of_rows(candidates, R.MISSING_SCHEMA).equals(
        pa.Table.from_pylist(candidates, schema=R.MISSING_SCHEMA)
    )


def test_atomic_write_leaves_no_temp_file_and_keeps_metadata(tmp_path):
    meta = R.run_metadata({"a": 1}, "feedbeef", "/in", "kitti")
    path = R.write_parquet_atomic(
        R.rows_to_table([make_row("000001", 0)], meta), tmp_path / "objects" / "part-x.parquet"
    )
    assert [p.name for p in path.parent.iterdir()] == ["part-x.parquet"]
    got = R.shard_metadata(path)
    assert got["param_hash"] == "feedbeef" and got["params"] == {"a": 1} and got["schema_version"] == R.SCHEMA_VERSION


def test_reader_ignores_and_cleanup_removes_leftover_temp_files(tmp_path):
    root = make_results(tmp_path / "res", [[make_row("000001", 0), make_row("000001", 1)]])
    leftover = root / R.OBJECTS_DIR / f".part-9999.parquet{R.TMP_MARKER}123"
    leftover.write_bytes(b"half a parquet file")
    res = R.open_results(root)
    assert res.dataset.count_rows() == 2
    assert R.remove_temp_files(root) == [leftover]
    assert not leftover.exists()


def test_open_results_errors_name_the_path(tmp_path):
    with pytest.raises(R.ResultsError, match="no such results folder"):
        R.open_results(tmp_path / "missing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(R.ResultsError, match="no result shards"):
        R.open_results(tmp_path / "empty")
    bad = tmp_path / "bad"
    (bad / R.OBJECTS_DIR).mkdir(parents=True)
    (bad / R.OBJECTS_DIR / "part-1.parquet").write_bytes(b"not parquet")
    with pytest.raises(R.ResultsError, match="unreadable"):
        R.open_results(bad)


def test_reader_does_not_depend_on_column_order_and_fills_missing_optional_columns(tmp_path):
    table = R.rows_to_table([make_row("000001", 0, jiou_gt=0.4), make_row("000001", 1, jiou_gt=0.9)])
    shuffled = table.select(list(reversed(table.schema.names))).drop_columns(["label_error"])
    path = tmp_path / "r" / R.OBJECTS_DIR / "part-0.parquet"
    path.parent.mkdir(parents=True)
    pq.write_table(shuffled, path)
    res = R.open_results(tmp_path / "r")
    t = res.read(["frame_id", "jiou_gt", "label_error"])
    assert t.schema.names == ["frame_id", "jiou_gt", "label_error"]
    assert t.column("jiou_gt").to_pylist() == [0.4, 0.9]
    assert t.column("label_error").null_count == 2
    assert rank_results(res, RankQuery(top=1)).table.column("jiou_gt").to_pylist() == [0.4]


def test_failed_frames_count_errors_not_warnings(tmp_path):
    errors = [
        {
            "unit": "000003",
            "frame_id": None,
            "file": "/d/label_2/000003.txt",
            "line": 2,
            "level": "error",
            "message": "bad",
        },
        {
            "unit": "000004",
            "frame_id": "000004",
            "file": None,
            "line": None,
            "level": "warning",
            "message": "dropped 3 NaN points",
        },
    ]
    res = R.open_results(make_results(tmp_path, [[make_row("000001", 0)]], errors))
    assert res.failed_frames() == 1
    assert res.errors().column("line").to_pylist() == [2, None]


# --------------------------------------------------------------------------- ranking


@pytest.fixture()
def ranked_results(tmp_path):
    rows_a = [
        make_row("000001", i, jiou_gt=j, label_error=e)
        for i, (j, e) in enumerate([(0.9, 0.1), (0.2, 0.7), (0.5, None)])
    ]
    rows_b = [
        make_row("000002", 0, "Pedestrian", jiou_gt=0.1, label_error=0.9, num_points=5, distance=50.0),
        make_row("000002", 1, status="skipped", message="length 9.00 m outside [3, 6.5] m"),
        make_row("000002", 2, status="no_points", jiou_gt=0.3, label_error=0.2),
    ]
    return R.open_results(make_results(tmp_path, [rows_a, rows_b]))


def _keys(t: pa.Table) -> list[tuple[str, int]]:
    return list(zip(t.column("frame_id").to_pylist(), t.column("object_index").to_pylist()))


def test_rank_by_jiou_gt_is_ascending_and_leaves_out_null_values(ranked_results):
    res = rank_results(ranked_results, RankQuery(top=10))
    assert res.table.column("jiou_gt").to_pylist() == [0.1, 0.2, 0.3, 0.5, 0.9]
    assert res.matched == 5  # the skipped box has no JIoU-GT
    assert res.table.schema.names[: len(R.COLUMN_NAMES)] == list(R.COLUMN_NAMES)


def test_rank_by_label_error_is_descending_by_default_and_asc_overrides(ranked_results):
    assert default_descending("label_error") and not default_descending("jiou_gt")
    desc = rank_results(ranked_results, RankQuery(by="label_error", top=2))
    assert desc.table.column("label_error").to_pylist() == [0.9, 0.7]
    asc = rank_results(ranked_results, RankQuery(by="label_error", top=2, descending=False))
    assert asc.table.column("label_error").to_pylist() == [0.1, 0.2]
    desc_jiou = rank_results(ranked_results, RankQuery(by="jiou_gt", top=1, descending=True))
    assert desc_jiou.table.column("jiou_gt").to_pylist() == [0.9]


def test_rank_filters(ranked_results):
    assert _keys(rank_results(ranked_results, RankQuery(classes=("Pedestrian",))).table) == [("000002", 0)]
    assert _keys(rank_results(ranked_results, RankQuery(statuses=("no_points",))).table) == [("000002", 2)]
    near = rank_results(ranked_results, RankQuery(max_distance=20.0)).table
    assert ("000002", 0) not in _keys(near) and len(near) == 4
    assert ("000002", 0) not in _keys(rank_results(ranked_results, RankQuery(min_points=10)).table)
    assert rank_results(ranked_results, RankQuery(classes=("Tram",))).table.num_rows == 0


def test_rank_rejects_non_numeric_or_unknown_columns(ranked_results):
    with pytest.raises(R.ResultsError, match="not a numeric column"):
        rank_results(ranked_results, RankQuery(by="class_name"))
    with pytest.raises(R.ResultsError, match="jiou_gt"):
        rank_results(ranked_results, RankQuery(by="nope"))


def test_json_and_csv_carry_every_column_by_name(ranked_results):
    table = rank_results(ranked_results, RankQuery(top=2)).table
    records = json.loads(to_json(table))
    assert [r["jiou_gt"] for r in records] == [0.1, 0.2]
    assert set(R.COLUMN_NAMES) <= set(records[0])
    assert records[0]["std_cz"] is None and len(records[0]["corner_tv"]) == 4
    rows = list(csv.DictReader(io.StringIO(to_csv(table))))
    assert len(rows) == 2 and set(R.COLUMN_NAMES) <= set(rows[0])
    assert float(rows[0]["jiou_gt"]) == 0.1 and rows[0]["std_cz"] == ""
    assert json.loads(rows[0]["corner_tv"]) == [0.01, 0.02, 0.03, 0.04]


def test_summarize_counts_statuses_and_medians(ranked_results):
    s = summarize(ranked_results)
    assert s["objects"] == 6
    assert s["by_status"] == {"ok": 4, "no_points": 1, "skipped": 1}
    assert math.isclose(s["classes"]["Car"]["median_jiou_gt"], 0.4)  # 0.9 0.2 0.5 0.3
    assert s["classes"]["Pedestrian"]["median_jiou_gt"] == 0.1


def test_rank_where_conditions(ranked_results):
    res = rank_results(ranked_results, RankQuery(where=("class_name==Car", "jiou_gt>=0.3")))
    assert res.table.column("jiou_gt").to_pylist() == [0.3, 0.5, 0.9]
    res = rank_results(ranked_results, RankQuery(where=("distance > 20",)))
    assert _keys(res.table) == [("000002", 0)]
    for bad, match in [
        ("num_points>>3", "numeric"),
        ("jiou_gt 0.3", "expected COLUMN"),
        ("nope==1", "unknown column"),
        ("num_points>=many", "numeric"),
        ("cov==1", "cannot compare"),
    ]:
        with pytest.raises(R.ResultsError, match=match):
            rank_results(ranked_results, RankQuery(where=(bad,)))


def test_shards_with_fewer_columns_read_as_nulls(tmp_path):
    root = make_results(tmp_path / "r", [[make_row("000002", 0, jiou_gt=0.7, hull_iou=0.5)]])
    old = R.rows_to_table([make_row("000001", 0, jiou_gt=0.4)]).drop_columns(["hull_iou", "label_line"])
    pq.write_table(old, root / R.OBJECTS_DIR / "part-0000-old.parquet")  # sorts first
    res = R.open_results(root)
    t = res.read(["frame_id", "hull_iou"])
    assert sorted(zip(t.column("frame_id").to_pylist(), t.column("hull_iou").to_pylist())) == [
        ("000001", None),
        ("000002", 0.5),
    ]
    assert "label_line" in res.read().schema.names

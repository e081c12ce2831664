"""Missing-label candidates: the ``missing/`` table contract, its writer in ``infer``, resume and error rows."""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from labelaudit import results as R
from labelaudit.config import MissingParams, RunConfig
from labelaudit.errors import ResultsError
from labelaudit.executors import SerialExecutor
from labelaudit.infer.run import InferRequest, run_infer

DOCS = Path(__file__).resolve().parents[1] / "docs" / "results-schema.md"
CONTRACT = ("frame_id", "candidate_index", "class_name", "cx", "cy", "cz", "length", "width", "height", "yaw", "num_points", "distance", "score", "source")


def _candidate(frame_id: str, index: int, **kw) -> dict:
    row = {"frame_id": frame_id, "candidate_index": index, "class_name": "Car", "cx": 12.0, "cy": 3.0, "cz": -0.9,
           "length": 4.1, "width": 1.7, "height": 1.5, "yaw": 0.2, "num_points": 240, "distance": 12.4, "score": 0.8,
           "source": "points", "dataset": "kitti", "max_label_iou": 0.0}
    row.update(kw)
    return row


def test_the_contract_columns_come_first_with_their_types():
    assert R.MISSING_COLUMN_NAMES[: len(CONTRACT)] == CONTRACT
    types = {f.name: f.type for f in R.MISSING_SCHEMA}
    assert types["frame_id"] == pa.string() and types["candidate_index"] == pa.int32() and types["num_points"] == pa.int32()
    assert all(types[c] == pa.float64() for c in ("cx", "cy", "cz", "length", "width", "height", "yaw", "distance", "score"))
    assert types["source"] == pa.string() and types["class_name"] == pa.string()


def test_every_missing_column_is_documented():
    documented = set(re.findall(r"^\| `([a-z_0-9]+)` \|", DOCS.read_text(), flags=re.M))
    assert set(R.MISSING_COLUMN_NAMES) <= documented, set(R.MISSING_COLUMN_NAMES) - documented


def test_read_missing_of_a_folder_without_candidates_is_empty_with_the_schema(tmp_path):
    (tmp_path / "res").mkdir()
    t = R.read_missing(tmp_path / "res")
    assert t.num_rows == 0 and t.schema.equals(R.MISSING_SCHEMA)
    with pytest.raises(ResultsError, match="no such results folder"):
        R.read_missing(tmp_path / "nowhere")


def test_read_missing_gathers_shards_sorted_and_fills_absent_columns(tmp_path):
    root = tmp_path / "res"
    R.write_parquet_atomic(R.missing_rows_to_table([_candidate("000002", 0), _candidate("000001", 1), _candidate("000001", 0, detection_score=float("nan"))]), root / R.MISSING_DIR / "part-a.parquet")
    # a shard of an older build without the evidence columns
    old = pa.table({"frame_id": ["000000"], "candidate_index": pa.array([0], pa.int32()), "score": [0.3]})
    pq.write_table(old, root / R.MISSING_DIR / "part-b.parquet")
    (root / R.MISSING_DIR / f".part-c.parquet{R.TMP_MARKER}1").write_bytes(b"half")
    t = R.read_missing(root)
    assert t.schema.equals(R.MISSING_SCHEMA)
    assert list(zip(t["frame_id"].to_pylist(), t["candidate_index"].to_pylist())) == [("000000", 0), ("000001", 0), ("000001", 1), ("000002", 0)]
    assert t["class_name"].to_pylist()[0] is None and t["detection_score"].to_pylist()[1] is None  # NaN in an evidence column is no value
    bad = root / R.MISSING_DIR / "part-d.parquet"
    bad.write_bytes(b"not parquet")
    with pytest.raises(ResultsError, match="part-d.parquet.*damaged"):
        R.read_missing(root)


@pytest.fixture(scope="module")
def sim_kitti(tmp_path_factory) -> Path:
    from labelaudit.sim.dataset import simulate_dataset

    root = tmp_path_factory.mktemp("sim") / "kitti"
    simulate_dataset(root, frames=3, seed=5, progress=False)
    return root


def _run(dataset: Path, out: Path, cfg: RunConfig | None = None, **kw):
    return run_infer(InferRequest(dataset, out, "auto", chunk_units=2, **kw), cfg or RunConfig(), executor=SerialExecutor())


def test_infer_writes_one_missing_shard_per_chunk_and_none_with_no_missing(sim_kitti, tmp_path):
    out = _run(sim_kitti, tmp_path / "on").output
    objects = sorted(p.name for p in (out / R.OBJECTS_DIR).glob("*.parquet"))
    assert sorted(p.name for p in (out / R.MISSING_DIR).glob("*.parquet")) == objects
    assert R.read_missing(out).schema.equals(R.MISSING_SCHEMA)
    off = replace(RunConfig(), missing=MissingParams(enabled=False))
    out_off = _run(sim_kitti, tmp_path / "off", off).output
    assert not (out_off / R.MISSING_DIR).exists() and R.read_missing(out_off).num_rows == 0
    assert off.param_hash() != RunConfig().param_hash()
    assert R.open_results(out).read().equals(R.open_results(out_off).read())  # the search changes no object row


def test_resume_reruns_a_chunk_whose_missing_shard_is_gone(sim_kitti, tmp_path):
    out = _run(sim_kitti, tmp_path / "res").output
    victim = sorted((out / R.MISSING_DIR).glob("*.parquet"))[0]
    victim.write_bytes(b"truncated")
    summary = _run(sim_kitti, out)
    assert summary.chunks_skipped == summary.chunks - 1 and R.is_whole_parquet(victim)


def test_a_failing_search_is_an_error_row_naming_the_file_and_the_objects_stay(sim_kitti, tmp_path, monkeypatch):
    from labelaudit.infer import run as run_module

    def boom(frame, cfg, detections=None):
        if frame.frame_id == "000001":
            raise ValueError("synthetic search failure")
        return []

    monkeypatch.setattr(run_module, "missing_of_frame", boom)
    out = _run(sim_kitti, tmp_path / "res").output
    errors = R.open_results(out).errors().to_pylist()
    assert len(errors) == 1 and errors[0]["frame_id"] == "000001" and errors[0]["level"] == "error"
    assert errors[0]["file"].endswith("label_2/000001.txt") and "synthetic search failure" in errors[0]["message"]
    ids = set(R.open_results(out).read(["frame_id"])["frame_id"].to_pylist())
    assert "000001" in ids

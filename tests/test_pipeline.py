"""The infer engine: per-frame rows, chunking, shards, resume/overwrite, errors, determinism.

Most tests replace the core's ``audit_object`` by a small stand-in (serial executor, so the
stand-in is seen), which isolates this module's own logic; the end-to-end tests at the bottom use
the real core, simulator and KITTI reader.
"""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from labelaudit import results as R
from labelaudit.config import ALL_CLASSES, RunConfig, resolve_config
from labelaudit.datasets import Frame, FrameRef
from labelaudit.errors import DatasetError, InferError, StrictError
from labelaudit.executors import SerialExecutor
from labelaudit.infer.rows import process_frame
from labelaudit.infer.run import InferRequest, chunk_name, plan_chunks, run_infer


def _fake_audit(box, points, class_name, cfg, sensor_origin, *, fit_points=None, evidence=None, clean=False):
    """Stand-in for the core: more points → higher JIoU-GT; raises for a marker class."""
    assert fit_points is not None  # the fit's own crop (wider, cut above the local ground, neighbours dropped)
    if class_name == "Boom":
        raise RuntimeError("synthetic failure")
    n = len(points)
    status = "no_points" if n == 0 else ("few_points" if n < cfg.model.min_points else "ok")
    return {
        "status": status,
        "num_points": n,
        "sigma": cfg.model.sigma,
        "jiou_gt": 1.0 - 1.0 / (n + 2.0),
        "label_error": None,
        "sigma_hat": float("nan") if n < 2 else 0.05,
        "fit_offset_m": None,
        "corner_tv": [0.1, 0.2, 0.3, 0.4],
        **{f"std_{c}": 0.1 for c in R.BOX_COLUMNS},
        "std_cz": float("nan"),
        "std_height": float("nan"),
        "cov": list(np.eye(6).ravel()),
        "cov_dim": 6,
        "model": cfg.model.kind,
    }


@pytest.fixture()
def fake_core(monkeypatch):
    from labelaudit.infer import rows

    monkeypatch.setattr(rows, "audit_object", _fake_audit)
    return rows


def _frame() -> Frame:
    rng = np.random.default_rng(0)
    # 200 points inside box 0, 1 inside box 1, none in the others
    pts0 = np.c_[rng.uniform(8.2, 11.8, 200), rng.uniform(-0.7, 0.7, 200), rng.uniform(-0.5, 0.6, 200), np.zeros(200)]
    pts1 = np.array([[20.0, 5.0, 0.0, 0.0]])
    boxes = np.array(
        [
            [10.0, 0.0, 0.0, 4.0, 1.8, 1.6, 0.0],  # Car with points
            [20.0, 5.0, 0.0, 4.0, 1.8, 1.6, 0.3],  # Car with one point
            [30.0, -5.0, 0.0, 0.8, 0.6, 1.7, 0.0],  # Pedestrian (not selected by default)
            [40.0, 0.0, 0.0, 12.0, 2.5, 3.0, 0.0],  # Truck, too long for max_length
            [50.0, 0.0, 0.0, 4.0, 1.8, 1.6, 0.0],  # Boom: the stand-in raises
        ]
    )
    return Frame(
        frame_id="000007",
        points=np.vstack([pts0, pts1]).astype(np.float32),
        boxes=boxes,
        class_names=["Car", "Car", "Pedestrian", "Truck", "Boom"],
        object_ids=[f"000007:{i}" for i in range(5)],
        extras={
            "difficulty": np.array([0, 1, 2, -1, 0], dtype=np.int8),
            "truncated": np.zeros(5),
            "label_line": np.arange(1, 6),
        },
        warnings=["dropped 2 points with NaN coordinates"],
    )


def test_process_frame_selects_classes_marks_skipped_and_errors(fake_core):
    cfg = RunConfig(classes=("Car", "Truck", "Boom"), max_length=7.0)
    rows, notes = process_frame(_frame(), cfg)
    by_index = {r["object_index"]: r for r in rows}
    assert sorted(by_index) == [0, 1, 3, 4]  # the pedestrian is not audited at all
    assert by_index[0]["status"] == "ok" and by_index[0]["num_points"] == 200
    assert by_index[1]["status"] == "few_points" and by_index[1]["num_points"] == 1
    assert by_index[0]["jiou_gt"] > by_index[1]["jiou_gt"]
    assert by_index[3]["status"] == "skipped" and "length 12.00 m" in by_index[3]["message"]
    assert by_index[4]["status"] == "error" and "synthetic failure" in by_index[4]["message"]
    assert by_index[0]["difficulty"] == "Easy" and by_index[3]["difficulty"] == "unknown"
    assert by_index[0]["distance"] == pytest.approx(10.0) and by_index[0]["object_id"] == "000007:0"
    assert by_index[0]["label_line"] == 1
    assert notes[0]["level"] == "warning" and "NaN" in notes[0]["message"]
    table = R.rows_to_table(rows)  # every row fits the schema
    assert table.num_rows == 4


def test_process_frame_all_classes_and_invalid_box(fake_core):
    frame = _frame()
    frame.boxes[0, 3] = -1.0  # invalid length
    rows, _ = process_frame(frame, RunConfig(classes=(ALL_CLASSES,)))
    assert len(rows) == 5
    assert rows[0]["status"] == "error" and "invalid box" in rows[0]["message"]


def test_check_finite_refuses_nan_and_inf_in_the_covariance_but_not_a_sum_that_overflows():
    from labelaudit.infer.rows import check_finite

    check_finite({"jiou_gt": 0.5, "cov": [1e308, 1e308, 1.0]})  # finite terms whose sum overflows: accepted
    check_finite({"jiou_gt": 0.5, "cov": [1.0, -1e308, -1e308]})
    for bad in (float("nan"), float("inf"), -float("inf")):
        with pytest.raises(FloatingPointError, match="covariance finite: False"):
            check_finite({"jiou_gt": 0.5, "cov": [1.0, bad, 2.0]})
    with pytest.raises(FloatingPointError, match="covariance finite: False"):
        check_finite({"jiou_gt": 0.5, "cov": [float("inf"), -float("inf")]})  # a NaN sum
    with pytest.raises(FloatingPointError, match="jiou_gt=nan"):
        check_finite({"jiou_gt": float("nan"), "cov": [1.0]})
    check_finite({"jiou_gt": 0.5, "cov": np.eye(2)})  # an array: NumPy's test


def test_resolve_config_overrides():
    cfg = resolve_config(None, "kitti", ["Car", " Van"], "3d")
    assert cfg.classes == ("Car", "Van") and cfg.model.kind == "3d" and cfg.dataset_format == "kitti"
    assert resolve_config(None, "kitti", ["all"]).classes == (ALL_CLASSES,)
    assert resolve_config(None, "kitti", ["Car"]).param_hash() != resolve_config(None, "kitti", ["Van"]).param_hash()


def test_chunks_do_not_depend_on_anything_but_the_unit_list():
    refs = [FrameRef("kitti", "/d", f"{i:06d}") for i in range(20)]
    plan = plan_chunks(refs, 8)
    assert [len(c) for _, c in plan] == [8, 6, 3, 2, 1]  # the last chunks halve: the workers end together
    assert [r for _, c in plan for r in c] == refs  # every unit once, in list order
    assert plan[0][0] == chunk_name(refs[:8]) != chunk_name(refs[1:9])
    assert plan == plan_chunks(list(refs), 8)
    assert [len(c) for _, c in plan_chunks(refs * 6, 8)] == [8] * 14 + [4, 2, 1, 1]
    assert [len(c) for _, c in plan_chunks(refs, 1)] == [1] * 20  # one unit per chunk: as before


# --------------------------------------------------------------------------- runs on simulated KITTI


@pytest.fixture(scope="module")
def sim_kitti(tmp_path_factory) -> Path:
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec

    root = tmp_path_factory.mktemp("sim") / "kitti"
    simulate_dataset(root, frames=5, seed=3, noise=NoiseSpec(fraction=0.3, gross_fraction=0.1), progress=False)
    return root


def _run(dataset: Path, out: Path, cfg: RunConfig | None = None, **kw) -> object:
    request = InferRequest(dataset, out, "auto", **{"chunk_units": 2, **kw})
    return run_infer(request, cfg or RunConfig(), executor=kw.pop("executor", None) or SerialExecutor())


def _rows(out: Path) -> list[dict]:
    t = R.open_results(out).read()
    return sorted(t.to_pylist(), key=lambda r: (r["frame_id"], r["object_index"]))


def test_run_writes_shards_manifest_and_errors(fake_core, sim_kitti, tmp_path):
    out = tmp_path / "res"
    summary = _run(sim_kitti, out)
    assert summary.units == 5 and summary.chunks == 3 and summary.chunks_skipped == 0 and summary.frames == 5
    manifest = R.read_manifest(out)
    cfg = RunConfig()
    assert manifest["complete"] and manifest["param_hash"] == cfg.param_hash() and manifest["params"] == cfg.to_dict()
    assert manifest["format"] == "kitti" and manifest["input"] == str(sim_kitti.resolve())
    shards = sorted((out / R.OBJECTS_DIR).glob("*.parquet"))
    assert len(shards) == 3
    assert R.shard_metadata(shards[0])["param_hash"] == cfg.param_hash()
    assert pq.read_table(out / R.ERRORS_FILE).num_rows == 0
    rows = _rows(out)
    assert rows and {r["class_name"] for r in rows} <= set(cfg.classes)
    assert all(r["dataset"] == "kitti" and r["difficulty"] in ("Easy", "Moderate", "Hard", "unknown") for r in rows)
    for shard in shards:  # sorted inside every shard
        t = pq.read_table(shard, columns=["frame_id", "object_index"]).to_pylist()
        assert t == sorted(t, key=lambda r: (r["frame_id"], r["object_index"]))


def test_resume_skips_done_shards_and_cleans_temp_files(fake_core, sim_kitti, tmp_path):
    out = tmp_path / "res"
    _run(sim_kitti, out)
    before = _rows(out)
    victim = sorted((out / R.OBJECTS_DIR).glob("*.parquet"))[1]
    victim.unlink()  # as if the run had been killed before this shard
    leftover = out / R.OBJECTS_DIR / f".{victim.name}{R.TMP_MARKER}4242"
    leftover.write_bytes(b"partial")
    summary = _run(sim_kitti, out)
    assert summary.chunks_skipped == 2 and summary.frames in (1, 2)  # the redone chunk only
    assert not leftover.exists() and victim.exists()
    assert _rows(out) == before


def test_a_run_that_wrote_every_row_summarises_them_as_the_folder_does(fake_core, sim_kitti, tmp_path):
    """The end-of-run summary from the rows' columns the workers sent back equals the one read from
    the folder (counts, per-class median JIoU-GT, failed frames); a resumed run has none to offer."""
    from labelaudit.summary import summarize, summarize_columns

    out = tmp_path / "res"
    first = _run(sim_kitti, out)
    c = first.columns
    assert c is not None and len(c["status"]) == first.objects > 0
    from_rows = summarize_columns(c["class_name"], c["status"], c["jiou_gt"], first.failed_frames)
    assert from_rows == summarize(R.open_results(out))
    assert from_rows["classes"] and all(v["median_jiou_gt"] is not None for v in from_rows["classes"].values())
    assert _run(sim_kitti, out).columns is None  # everything resumed: the rows are only in the folder
    known = summarize_columns(["Car", "Van", "Car", "Car"], ["ok", "ok", "few_points", "ok"], [0.5, 0.9, None, 0.7], 2)
    assert known == {
        "objects": 4,
        "by_status": {"ok": 3, "few_points": 1},
        "classes": {"Car": {"objects": 3, "median_jiou_gt": 0.6}, "Van": {"objects": 1, "median_jiou_gt": 0.9}},
        "failed_frames": 2,
    }


def test_resume_refuses_other_parameters_unless_overwrite(fake_core, sim_kitti, tmp_path):
    out = tmp_path / "res"
    _run(sim_kitti, out)
    other = replace(RunConfig(), classes=("Car",))
    with pytest.raises(InferError, match="other parameters.*classes.*--overwrite"):
        _run(sim_kitti, out, other)
    summary = _run(sim_kitti, out, other, overwrite=True)
    assert summary.chunks_skipped == 0
    assert {r["class_name"] for r in _rows(out)} == {"Car"}
    assert R.read_manifest(out)["param_hash"] == other.param_hash()


def test_resume_refuses_a_changed_model_constant(fake_core, sim_kitti, tmp_path, monkeypatch):
    from labelaudit import constants as C

    out = tmp_path / "res"
    _run(sim_kitti, out)
    before = RunConfig().param_hash()
    monkeypatch.setattr(C, "FIT_TOLERANCE", C.FIT_TOLERANCE / 2)  # an upgrade that changes label_error
    assert RunConfig().param_hash() != before
    with pytest.raises(InferError, match="cannot resume: computed with other model constants.*--overwrite"):
        _run(sim_kitti, out)
    monkeypatch.setattr(C, "LABEL_TOLERANCE", {**C.LABEL_TOLERANCE, "yaw": 0.5})
    with pytest.raises(InferError, match="other model constants"):
        _run(sim_kitti, out)


@pytest.mark.parametrize(
    "key, value, what",
    [("tool_version", "0.0.1", "labelaudit version"), ("schema_version", "0", "results schema version")],
)
def test_resume_refuses_another_version_whatever_the_hash(fake_core, sim_kitti, tmp_path, key, value, what):
    out = tmp_path / "res"
    _run(sim_kitti, out)
    manifest = R.read_manifest(out)
    R.write_json_atomic({**manifest, key: value}, out / R.MANIFEST_NAME)  # same param_hash, other version
    with pytest.raises(InferError, match=f"cannot resume: written by {what} '{value}'"):
        _run(sim_kitti, out)
    _run(sim_kitti, out, overwrite=True)
    assert R.read_manifest(out)[key] != value


def test_param_hash_covers_versions_and_constants(monkeypatch):
    import labelaudit
    from labelaudit import constants as C

    base = RunConfig().param_hash()
    monkeypatch.setattr(labelaudit, "__version__", "99.0")
    assert RunConfig().param_hash() != base
    monkeypatch.undo()
    monkeypatch.setattr(C, "EM_MAX_ITERATIONS", C.EM_MAX_ITERATIONS + 1)
    assert RunConfig().param_hash() != base
    monkeypatch.undo()
    monkeypatch.setattr(C, "SIM_BEAMS", 32)  # the simulator's numbers cannot change a row of infer
    monkeypatch.setattr(C, "DEFAULT_RANK_TOP", 5)
    assert RunConfig().param_hash() == base


def test_unhashed_constants_are_only_those_that_cannot_change_a_row():
    from labelaudit import constants as C
    from labelaudit.config import is_unhashed

    hashed = {n for n in dir(C) if n.isupper() and not is_unhashed(n)}
    for name in (
        "FIT_TOLERANCE",
        "LABEL_TOLERANCE",
        "EM_TOLERANCE",
        "DEFAULT_GROUND_CUT",
        "KITTI_MIN_HEIGHT",
        "DEFAULT_PRIORS",
        "MAX_CELLS_PER_AXIS",
    ):
        assert name in hashed, name


def test_output_folder_that_is_not_results_is_refused(fake_core, sim_kitti, tmp_path):
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "thesis.tex").write_text("keep me")
    with pytest.raises(InferError, match="not a labelaudit results folder"):
        _run(sim_kitti, tmp_path / "mine", overwrite=True)
    assert (tmp_path / "mine" / "thesis.tex").exists()


def test_limit_then_full_run_leaves_no_stale_shards(fake_core, sim_kitti, tmp_path):
    out = tmp_path / "res"
    _run(sim_kitti, out, limit=3)
    assert {r["frame_id"] for r in _rows(out)} <= {"000000", "000001", "000002"}
    _run(sim_kitti, out)  # same parameters: resumes, re-plans chunks, drops the old partial shard
    full = _rows(out)
    fresh = tmp_path / "fresh"
    _run(sim_kitti, fresh)
    assert full == _rows(fresh)


def test_bad_frame_is_recorded_and_strict_makes_it_fatal(fake_core, sim_kitti, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(sim_kitti, data)
    (data / "training" / "velodyne" / "000002.bin").write_bytes(b"\0" * 10)  # not a multiple of 16 bytes
    summary = _run(data, tmp_path / "res")
    assert summary.failed_frames == 1
    errors = pq.read_table(tmp_path / "res" / R.ERRORS_FILE).to_pylist()
    assert errors[0]["unit"] == "000002" and errors[0]["file"].endswith("000002.bin") and errors[0]["level"] == "error"
    assert "000002" not in {r["frame_id"] for r in _rows(tmp_path / "res")}
    with pytest.raises(StrictError, match="000002"):
        _run(data, tmp_path / "strict", strict=True)


def test_input_errors(fake_core, tmp_path):
    with pytest.raises(DatasetError, match="nope: dataset path does not exist"):
        _run(tmp_path / "nope", tmp_path / "res")
    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="cannot tell the format"):
        _run(tmp_path / "empty", tmp_path / "res")


def test_resolve_format_checks_the_name_and_the_path(tmp_path):
    from labelaudit.datasets import resolve_format

    (tmp_path / "training" / "velodyne").mkdir(parents=True)
    assert resolve_format(tmp_path, "auto") == "kitti"
    assert resolve_format(tmp_path, "waymo-v2") == "waymo-v2"  # a named format is taken as given
    with pytest.raises(DatasetError, match=r"unknown dataset format 'kiti': expected auto or one of kitti, waymo-v2"):
        resolve_format(tmp_path, "kiti")
    with pytest.raises(DatasetError, match="cannot open the dataset"):
        resolve_format(tmp_path / ("x" * 5000), "kitti")


# --------------------------------------------------------------------------- end to end with the real core


@pytest.mark.slow
def test_same_rows_for_one_and_two_workers(sim_kitti, tmp_path):
    from labelaudit.executors import PoolExecutor

    cfg = resolve_config(None, "kitti")
    run_infer(InferRequest(sim_kitti, tmp_path / "w1", chunk_units=2), cfg, executor=SerialExecutor())
    run_infer(InferRequest(sim_kitti, tmp_path / "w2", chunk_units=2), cfg, executor=PoolExecutor(2))
    rows1, rows2 = _rows(tmp_path / "w1"), _rows(tmp_path / "w2")
    assert rows1 == rows2
    statuses = {r["status"] for r in rows1}
    assert statuses <= {"ok", "few_points", "no_points"} and "ok" in statuses
    ok = [r for r in rows1 if r["status"] == "ok"]
    assert all(0.0 < r["jiou_gt"] <= 1.0 and r["cov_dim"] == 6 and len(r["cov"]) == 36 for r in ok)


@pytest.mark.realdata
def test_real_kitti_frames(realdata, tmp_path):
    root = realdata / "openpcdet-pr653-kitti"
    cfg = resolve_config(None, "kitti", ["all"])
    summary = run_infer(InferRequest(root, tmp_path / "res"), cfg, executor=SerialExecutor())
    assert summary.frames == 6 and summary.failed_frames == 0
    rows = _rows(tmp_path / "res")
    assert {r["status"] for r in rows} <= {"ok", "few_points", "no_points"}
    cars = [r for r in rows if r["class_name"] == "Car" and r["status"] == "ok"]
    assert cars and all(0.0 < r["jiou_gt"] <= 1.0 for r in cars)
    # near, well-observed cars are more certain than far ones (direction, not a value)
    near = [r["jiou_gt"] for r in cars if r["distance"] < 20]
    far = [r["jiou_gt"] for r in cars if r["distance"] > 40]
    if near and far:
        assert np.median(near) > np.median(far)


def _square(x: int) -> int:
    return x * x


def _die(x: int) -> int:
    import os

    os._exit(3)


def test_pool_executor_returns_every_result_and_reports_a_dead_worker():
    from labelaudit.errors import WorkerCrashed
    from labelaudit.executors import PoolExecutor

    assert sorted(PoolExecutor(2).run([1, 2, 3], _square)) == [1, 4, 9]
    with pytest.raises(WorkerCrashed, match="rerun the same command to resume"):
        list(PoolExecutor(2).run([1, 2], _die))


_LINGER = 2.0  # s a worker of the test below takes to exit


def _square_then_linger(x: int) -> int:
    from multiprocessing import util

    if not getattr(util, "_labelaudit_test_linger", False):  # once per worker: a slow exit
        util._labelaudit_test_linger = True
        util.Finalize(None, time.sleep, args=(_LINGER,), exitpriority=0)
    return x * x


def test_a_finished_pool_run_lets_the_caller_go_on_while_its_workers_stop_and_close_waits_for_them():
    """Once every result is back the pool's workers are stopped in the background: the caller
    (infer: the end of the run) goes on at once, and close() returns when every worker has exited."""
    import multiprocessing

    from labelaudit.executors import PoolExecutor

    pool = PoolExecutor(2)
    results = pool.run([1, 2, 3, 4], _square_then_linger)
    got = [next(results) for _ in range(4)]
    t = time.perf_counter()
    assert next(results, None) is None  # exhausted: the workers are not waited for here
    assert time.perf_counter() - t < _LINGER / 2
    pool.close()
    assert time.perf_counter() - t >= _LINGER * 0.9 and not multiprocessing.active_children()
    assert sorted(got) == [1, 4, 9, 16]


def test_waymo_v1_and_v2_give_the_same_rows(fake_core, tmp_path):
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    roots = simulate_waymo_dataset(tmp_path / "waymo", segments=2, frames=2, seed=5)
    cfg = RunConfig(classes=(ALL_CLASSES,))
    out = {}
    for fmt, root in roots.items():
        summary = run_infer(InferRequest(root, tmp_path / fmt, fmt), cfg, executor=SerialExecutor())
        assert summary.units == 2 and summary.chunks == 2 and summary.frames == 4  # one shard per segment
        out[fmt] = _rows(tmp_path / fmt)
    v1, v2 = out["waymo-v1"], out["waymo-v2"]
    assert v1 and all(r["dataset"] == "waymo-v1" for r in v1)
    assert all(r["num_lidar_points_in_box"] is not None and r["truncated"] is None for r in v2)
    drop = {"dataset"}
    strip = lambda rows: [{k: v for k, v in r.items() if k not in drop} for r in rows]  # noqa: E731
    a, b = strip(v1), strip(v2)
    assert [(r["frame_id"], r["object_id"], r["class_name"]) for r in a] == [
        (r["frame_id"], r["object_id"], r["class_name"]) for r in b
    ]
    assert [r["num_points"] for r in a] == [r["num_points"] for r in b]
    # --limit N on Waymo: first N segments, at most N frames each
    summary = run_infer(
        InferRequest(roots["waymo-v2"], tmp_path / "lim", "waymo-v2", limit=1), cfg, executor=SerialExecutor()
    )
    assert summary.units == 1 and summary.frames == 1


def test_chunk_size_depends_on_the_unit_count_only():
    from labelaudit.infer.run import chunk_size_for

    assert chunk_size_for("kitti", 12) == 1  # small runs: one frame per chunk, balanced workers
    assert chunk_size_for("kitti", 300) == 10
    assert chunk_size_for("kitti", 7481) == 16  # capped: shards stay a few hundred
    assert chunk_size_for("waymo-v2", 800) == 1  # a segment is already ~200 frames


def _three_frames_the_second_failing(monkeypatch) -> None:
    """One unit "seg" of three frames read by any reader; process_frame raises on the second."""
    import labelaudit.infer.run as P

    frames = [replace(_frame(), frame_id=f"seg:{t}") for t in range(3)]

    class Reader:
        def load_unit(self, ref):
            yield from frames

    monkeypatch.setattr(P, "open_dataset", lambda root, fmt, **options: Reader())
    real = P.process_frame

    def flaky(frame, cfg):
        if frame.frame_id == "seg:1":
            raise RuntimeError("crop exploded")
        return real(frame, cfg)

    monkeypatch.setattr(P, "process_frame", flaky)


def test_a_failing_frame_does_not_take_its_unit_along(fake_core, monkeypatch, tmp_path):
    from labelaudit.infer.run import ChunkTask, process_chunk

    _three_frames_the_second_failing(monkeypatch)
    result = process_chunk(ChunkTask("x", (FrameRef("fake", "/r", "seg"),), RunConfig()))
    assert result.frames == 2
    assert set(result.table.column("frame_id").to_pylist()) == {"seg:0", "seg:2"}
    (err,) = result.failed
    assert err["frame_id"] == "seg:1" and "crop exploded" in err["message"] and err["unit"] == "seg"


def test_a_chunk_encoded_by_its_worker_is_the_files_written_from_its_tables(fake_core, monkeypatch, tmp_path):
    """encode_chunk's bytes are the shards write_parquet_atomic writes from the tables, byte for byte
    (objects with the chunk record, missing-label candidates, errors), and its --strict message is
    the one of the tables."""
    import labelaudit.infer.run as P
    from labelaudit.infer.run import ChunkTask, chunk_failure, encode_chunk, process_chunk

    _three_frames_the_second_failing(monkeypatch)
    monkeypatch.setattr(P, "missing_of_frame", lambda frame, cfg, detections=None: [])
    metadata = {"tool": "labelaudit", "param_hash": "abc"}
    refs = (FrameRef("fake", "/r", "seg"),)
    plain = process_chunk(ChunkTask("x.parquet", refs, RunConfig()))
    encoded = process_chunk(ChunkTask("x.parquet", refs, RunConfig(), metadata=metadata))
    assert plain.shards is None and plain.table is not None and plain.table.num_rows > 0
    assert encoded.table is None and encoded.missing is None  # only bytes travel back
    assert (encoded.frames, encoded.objects, encoded.errors) == (plain.frames, plain.objects, plain.errors)
    chunk = R.chunk_record(plain.table, plain.errors)
    expected = {
        R.OBJECTS_DIR: R.write_parquet_atomic(
            R.with_metadata(plain.table, {**metadata, "chunk": chunk}), tmp_path / "objects.parquet"
        ),
        R.MISSING_DIR: R.write_parquet_atomic(R.with_metadata(plain.missing, metadata), tmp_path / "missing.parquet"),
        R.ERRORS_DIR: R.write_parquet_atomic(R.errors_to_table(plain.errors, metadata), tmp_path / "errors.parquet"),
    }
    assert set(encoded.shards) == set(expected)
    for folder, path in expected.items():
        assert encoded.shards[folder] == path.read_bytes(), folder
    assert encoded.failure == chunk_failure(plain) and "crop exploded" in encoded.failure
    assert encode_chunk(encoded, metadata) is encoded  # encoding twice is a no-op
    clean = encode_chunk(replace(plain, errors=[]), metadata)
    assert clean.failure is None and R.ERRORS_DIR not in clean.shards  # no notes: no errors part


def test_a_second_writer_is_refused_and_a_stale_lock_taken_over(fake_core, sim_kitti, tmp_path):
    import os
    import subprocess

    from labelaudit.results import LOCK_NAME

    out = tmp_path / "res"
    out.mkdir()
    lock = out / LOCK_NAME
    lock.write_text(str(os.getppid()))  # a live process that is not us
    with pytest.raises(InferError, match="another labelaudit infer"):
        _run(sim_kitti, out)
    dead = subprocess.Popen(["true"])
    dead.wait()
    lock.write_text(str(dead.pid))  # its writer is gone
    summary = _run(sim_kitti, out)
    assert summary.frames == 5 and not lock.exists()


def test_every_column_the_core_returns_has_a_place_in_the_schema():
    from labelaudit.infer.rows import audit_object

    assert set(R.MODEL_COLUMNS) <= set(R.COLUMN_NAMES), (
        "add new model columns to labelaudit/results.py COLUMNS and docs"
    )
    rng = np.random.default_rng(1)
    pts = np.c_[rng.uniform(-2, 2, 50), rng.uniform(-0.9, 0.9, 50), rng.uniform(-0.7, 0.7, 50)]
    for model in ("bev", "3d"):
        cfg = resolve_config(None, "kitti", model=model)
        row = audit_object(np.array([0, 0, 0, 4.0, 1.8, 1.5, 0.2]), pts, "Car", cfg)
        assert set(row) <= set(R.COLUMN_NAMES) and set(row) == set(R.MODEL_COLUMNS)
        clean = R.normalize_row(row)
        assert clean["cov_dim"] in (6, 8) and len(clean["cov"]) == clean["cov_dim"] ** 2


def test_the_label_error_fit_gets_the_wider_crop(fake_core, monkeypatch):
    seen = {}

    def recording(box, points, class_name, cfg, sensor_origin, *, fit_points=None, evidence=None, clean=False):
        # the pipeline hands the crops cleaned: the model's as rows, the fit's as (3, M) columns
        assert clean and points.shape[1] == 2 and fit_points.shape[0] == 3
        seen[class_name, round(float(box[0]))] = (len(points), fit_points.shape[1])
        return _fake_audit(box, points, class_name, cfg, sensor_origin, fit_points=fit_points, evidence=evidence)

    monkeypatch.setattr(fake_core, "audit_object", recording)
    frame = _frame()
    outside = np.array([[10.0, 1.2, 0.0, 0.0]], dtype=np.float32)  # 0.3 m beside box 0 (width 1.8)
    frame.points = np.vstack([frame.points, outside])
    process_frame(frame, RunConfig(classes=("Car",)))
    assert seen["Car", 10] == (200, 201)
    narrow = RunConfig(classes=("Car",), crop=replace(RunConfig().crop, fit_margin=RunConfig().crop.margin))
    process_frame(frame, narrow)
    assert seen["Car", 10] == (200, 200)


def test_worker_warmup_runs_the_audit() -> None:
    """The fork server's warm-up (constants.WORKER_PRELOAD) really audits an object (in the BEV model,
    and in the 3D one too on numba's JIT path)."""
    from labelaudit import constants
    from labelaudit.infer.warmup import warm_up

    assert "labelaudit.infer.warmup" in constants.WORKER_PRELOAD
    warm_up(strict=True)


_CHUNK_AFTER_PRELOAD = """
import sys, importlib
from pathlib import Path
import multiprocessing.forkserver
from labelaudit import constants
for name in constants.WORKER_PRELOAD:  # what the fork server imports (and warms up) before it forks a worker
    importlib.import_module(name)
from labelaudit.config import resolve_config
from labelaudit.datasets import open_dataset
from labelaudit.infer.run import ChunkTask, plan_chunks, process_chunk
root = Path(sys.argv[1])
cfg = resolve_config(None, "kitti")
refs = open_dataset(root, "kitti").list_units()
before = set(sys.modules)
for name, chunk in plan_chunks(refs, len(refs)):
    result = process_chunk(ChunkTask(name, chunk, cfg, metadata={"run": "test"}))
    assert result.objects > 0 and result.shards, result
print(" ".join(sorted(set(sys.modules) - before)))
"""


def test_a_worker_forked_from_the_warm_fork_server_imports_nothing(sim_kitti):
    """Every module a chunk needs (the audit, the missing-label search with the labels' exact overlap,
    the shards' Parquet writer) is imported by the fork server's preload and warm-up, once, rather
    than by every worker in its first chunk."""
    import subprocess
    import sys

    proc = subprocess.run(
        [sys.executable, "-c", _CHUNK_AFTER_PRELOAD, str(sim_kitti)], capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == []


def test_a_run_that_audits_nothing_is_an_error_and_a_resumed_one_is_not(fake_core, sim_kitti, tmp_path):
    from labelaudit.errors import ResultsError
    from labelaudit.infer.run import infer_dataset

    def run(out: Path, classes: tuple[str, ...] | None, **kw) -> object:
        request = InferRequest(sim_kitti, out, classes=classes, missing=False, chunk_units=2, **kw)
        return infer_dataset(request, executor=SerialExecutor())

    with pytest.raises(ResultsError, match="no objects audited.*--classes"):
        run(tmp_path / "none", ("NoSuchClass",))
    first = run(tmp_path / "res", None)
    assert first.objects > 0
    again = run(tmp_path / "res", None)  # every chunk resumed: no row written now, the folder still has them
    assert again.objects == 0 and again.chunks_skipped == again.chunks
    with pytest.raises(ResultsError, match="no objects audited"):  # resumed, and nothing there either
        run(tmp_path / "none", ("NoSuchClass",))


def test_a_pool_run_again_first_waits_for_the_workers_of_the_finished_one():
    """The first run's workers take 2 s to exit after its last result; the second run waits for
    them, so once it is closed no worker of either is left."""
    import multiprocessing

    from labelaudit.executors import PoolExecutor

    pool = PoolExecutor(2)
    assert sorted(pool.run([1, 2, 3], _square_then_linger)) == [1, 4, 9]
    assert sorted(pool.run([4, 5], _square)) == [16, 25]
    pool.close()
    assert not multiprocessing.active_children()

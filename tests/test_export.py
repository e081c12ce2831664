"""labelaudit.export and `labelaudit export`: Parquet targets, infos copies aligned by object, bad input."""

from __future__ import annotations

import copy
import json
import os
import pickle
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from _core_synth import face_points
from infos_factory import kitti_frames_and_rows, mmdet3d_kitti_infos, openpcdet_kitti_infos, openpcdet_waymo_infos
from labelaudit import export as E
from labelaudit import training as T
from labelaudit.cli import app
from labelaudit.config import ModelParams
from labelaudit.core.posterior import infer_label
from results_factory import make_results, make_row

runner = CliRunner()

# Label order of label_2 files: DontCare last (KITTI's files) and one frame with a DontCare in the
# middle, classes that are not audited (Pedestrian, Cyclist), an empty frame.
FRAMES = {
    "000001": [
        ("Truck", 8.0, 2.5, 3.2),
        ("Car", 4.1, 1.7, 1.5),
        ("Cyclist", 1.8, 0.6, 1.7),
        ("DontCare", -1, -1, -1),
        ("DontCare", -1, -1, -1),
    ],
    "000002": [("Car", 3.9, 1.6, 1.5), ("DontCare", -1, -1, -1), ("Pedestrian", 0.8, 0.6, 1.7), ("Van", 4.8, 1.9, 2.1)],
    "000003": [],
    "000004": [("Car", 4.4, 1.8, 1.4), ("Car", 3.7, 1.6, 1.5), ("DontCare", -1, -1, -1)],
}


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def drop_info_with_name(info: dict, name: str) -> dict:
    """What OpenPCDet does to annos before training (common_utils.drop_info_with_name): index every key.

    (``gt_boxes_lidar`` is left out: it has the non-DontCare rows only, which OpenPCDet's own
    indexing handles only when DontCare come last, as in KITTI's files.)
    """
    keep = [i for i, x in enumerate(info["name"]) if x != name]
    return {k: v[keep] for k, v in info.items() if k != "gt_boxes_lidar"}


@pytest.fixture()
def kitti(tmp_path):
    frames, rows = kitti_frames_and_rows(FRAMES)
    res = make_results(tmp_path / "res", [rows])
    infos = tmp_path / "kitti_infos_train.pkl"
    infos.write_bytes(pickle.dumps(openpcdet_kitti_infos(frames)))
    return res, infos, rows


def expected_by_key(res, encoding="box", source="model", anchors=None):
    arrays = E.read_result_arrays(res)
    t = E.compute_targets(arrays, encoding, source, anchors)
    return {
        (f, int(i)): (t.std[k], t.valid[k]) for k, (f, i) in enumerate(zip(arrays.frame_id, arrays.object_index))
    }, t


# ----------------------------------------------------------------------------- Parquet


@pytest.mark.parametrize("encoding", ["box", "log-size", "centerpoint", "pixor", "residual"])
def test_parquet_columns_keys_and_covariance(kitti, tmp_path, encoding):
    res, _, rows = kitti
    out = tmp_path / "t.parquet"
    summary = E.export_results(res, out, encoding=encoding)
    table = pq.read_table(out)
    enc = T.get_encoding(encoding)
    for c in ("frame_id", "object_index", "object_id", "valid", "cov", "cov_dim", *(f"std_{t}" for t in enc.targets)):
        assert c in table.column_names
    assert table.num_rows == len(rows) == summary.results_rows
    d = table.to_pylist()
    assert [(r["frame_id"], r["object_index"]) for r in d] == sorted((r["frame_id"], r["object_index"]) for r in rows)
    meta = json.loads(table.schema.metadata[b"labelaudit_export"])
    assert meta["encoding"] == enc.name and meta["targets"] == list(enc.targets) and meta["source"] == "model"
    for r in d:
        if not r["valid"]:
            assert r["cov"] is None and r["reason"]
            continue
        C = np.array(r["cov"]).reshape(enc.size, enc.size)
        std = np.array([np.nan if r[f"std_{t}"] is None else r[f"std_{t}"] for t in enc.targets])
        assert np.allclose(np.sqrt(np.diag(C)), std, equal_nan=True)
        # BEV results: exactly the targets that need z or h are null
        missing = {t for t in enc.targets if r[f"std_{t}"] is None}
        assert missing == {t for t, dep in zip(enc.targets, enc.depends()) if dep[2] or dep[5]}
    if encoding == "residual":  # Van and Truck have no default KITTI anchor
        assert summary.rows_without_targets == {
            "no anchor size for class Truck (--anchor-size Truck=l,w,h)": 1,
            "no anchor size for class Van (--anchor-size Van=l,w,h)": 1,
        }
    else:
        assert summary.rows_without_targets == {}


def test_box_encoding_std_equals_the_results_std_columns(tmp_path):
    """Export of a real posterior gives back the std_* the results carry (one definition of the Jacobian)."""
    rows = []
    for i, (model, yaw) in enumerate((("bev", 0.4), ("3d", -2.9), ("3d", 1.57))):
        box = np.array([12.0 + i, 4.0, -0.8, 4.2, 1.7, 1.5, yaw])
        post = infer_label(box, face_points(box, ["-x", "-y"], 50, noise=0.03, seed=i), "Car", ModelParams(kind=model))
        rows.append(make_row(f"00000{i}", 0, cx=box[0], cy=box[1], cz=box[2], length=4.2, width=1.7, height=1.5, yaw=yaw,
                             cov=post.cov.ravel().tolist(), cov_dim=post.cov.shape[0], model=model,
                             **{f"std_{k}": v for k, v in post.std_box.items()}))  # fmt: skip
    res = make_results(tmp_path / "res", [rows])
    E.export_results(res, tmp_path / "t.parquet", encoding="box")
    out = {r["frame_id"]: r for r in pq.read_table(tmp_path / "t.parquet").to_pylist()}
    for r in rows:
        e = out[r["frame_id"]]
        for ours, theirs in (
            ("x", "cx"),
            ("y", "cy"),
            ("z", "cz"),
            ("l", "length"),
            ("w", "width"),
            ("h", "height"),
            ("yaw", "yaw"),
        ):
            if np.isnan(r[f"std_{theirs}"]):
                assert e[f"std_{ours}"] is None
            else:
                assert e[f"std_{ours}"] == pytest.approx(r[f"std_{theirs}"], rel=1e-9)


def test_sources_and_missing_inputs(tmp_path):
    rows = [
        make_row("000001", 0, num_points=200, hull_iou=0.8),
        make_row("000001", 1, num_points=5, hull_iou=0.1),
        make_row("000001", 2, status="skipped", num_points=None),
        make_row("000001", 3, status="error", num_points=None, cov=None, cov_dim=None),
        make_row("000002", 0, status="no_points", num_points=0, hull_iou=0.0, cov=None, cov_dim=None),
    ]
    res = make_results(tmp_path / "res", [rows])
    arrays = E.read_result_arrays(res)
    npts = E.compute_targets(arrays, "log-size", "num_points")
    hull = E.compute_targets(arrays, "log-size", "hull_iou")
    model = E.compute_targets(arrays, "log-size", "model")
    assert list(npts.valid) == list(hull.valid) == [True, True, False, False, True]
    assert np.all(npts.std[0] < npts.std[1]) and np.all(npts.std[1] < npts.std[4])  # 200 < 5 < 0 points
    assert np.all(hull.std[0] < hull.std[1]) and np.all(hull.std[1] < hull.std[4])
    # no evidence: both heuristics give the class prior itself (the model's prior covariance)
    assert np.allclose(npts.std[4], hull.std[4])
    assert model.reasons() == {"status skipped": 1, "status error": 1, "no cov": 1}
    fixed = E.compute_targets(arrays, "pixor", "fixed:0.0025")
    assert np.allclose(fixed.std[fixed.valid], 0.05) and fixed.valid.sum() == 3
    with pytest.raises(E.ExportError, match="unknown source"):
        E.compute_targets(arrays, "box", "nll")


def test_nothing_to_export_is_an_error(tmp_path):
    res = make_results(tmp_path / "res", [[make_row("000001", 0, status="skipped")]])
    with pytest.raises(E.ExportError, match="no result row has targets"):
        E.export_results(res, tmp_path / "t.parquet")
    assert not (tmp_path / "t.parquet").exists()


# ----------------------------------------------------------------------------- OpenPCDet KITTI


@pytest.mark.parametrize("encoding", ["box", "residual", "log-size"])
def test_openpcdet_round_trip_keeps_the_file_order(kitti, tmp_path, encoding):
    res, infos, rows = kitti
    out = tmp_path / "kitti_infos_train_sigma.pkl"
    anchors = {"Van": (5.0, 2.0, 2.0)}
    summary = E.export_results(res, out, encoding=encoding, fmt="openpcdet", infos=infos, anchor_sizes=anchors)
    original = pickle.loads(infos.read_bytes())
    new = pickle.loads(out.read_bytes())
    expected, targets = expected_by_key(res, encoding, anchors=anchors)
    Tn = targets.encoding.size
    assert len(new) == len(original)
    n_obj = 0
    for info, orig in zip(new, original):
        annos = info["annos"]
        names = list(annos["name"])
        K = len(names)
        n_obj += K
        std, cov, valid = (annos[k] for k in E.INFOS_KEYS)
        assert std.shape == (K, Tn) and cov.shape == (K, Tn, Tn) and valid.shape == (K,)
        assert std.dtype == np.float32 and valid.dtype == bool
        ordinal = -1
        for j, name in enumerate(names):
            if name == "DontCare":
                assert not valid[j] and np.isnan(std[j]).all()
                continue
            ordinal += 1
            key = (info["point_cloud"]["lidar_idx"], ordinal)
            if key in expected and expected[key][1]:
                assert valid[j]
                assert np.allclose(std[j], expected[key][0].astype(np.float32), equal_nan=True)
            else:  # not audited (Pedestrian, Cyclist) or no anchor (Truck)
                assert not valid[j] and np.isnan(std[j]).all()
        # untouched originals, and OpenPCDet's DontCare filtering keeps the new arrays aligned
        for k in orig["annos"]:
            assert np.array_equal(annos[k], orig["annos"][k])
        kept = drop_info_with_name(annos, "DontCare")
        assert len(kept["label_std"]) == len(kept["name"]) == len(orig["annos"]["gt_boxes_lidar"])
        assert info[E.INFOS_META_KEY]["targets"] == list(targets.encoding.targets)
    assert summary.infos_objects == n_obj == sum(len(v) for v in FRAMES.values())
    audited = sum(1 for r in rows if (encoding != "residual" or r["class_name"] in ("Car", "Van")))
    assert summary.infos_objects_with_targets == audited
    reasons = summary.infos_objects_without_targets
    assert (
        reasons["DontCare"] == 4
        and reasons["class Pedestrian not audited"] == 1
        and reasons["class Cyclist not audited"] == 1
    )


def test_openpcdet_missing_results_are_nan_with_a_count(kitti, tmp_path):
    """Rows missing from the results (a frame not audited, an object without a row) → NaN, counted, no shift."""
    _, infos, rows = kitti
    keep = [r for r in rows if not (r["frame_id"] == "000004" and r["object_index"] == 0)]
    res2 = make_results(tmp_path / "res2", [keep])
    data = pickle.loads(infos.read_bytes())
    extra = copy.deepcopy(data[0])
    extra["point_cloud"]["lidar_idx"] = "000099"
    data.append(extra)
    infos2 = tmp_path / "infos2.pkl"
    infos2.write_bytes(pickle.dumps(data))
    out = tmp_path / "o.pkl"
    summary = E.export_results(res2, out, fmt="openpcdet", infos=infos2)
    new = pickle.loads(out.read_bytes())
    f4 = new[3]["annos"]
    assert list(f4["label_std_valid"]) == [False, True, False]  # the second Car keeps its own row
    expected, _ = expected_by_key(res2)
    assert np.allclose(f4["label_std"][1], expected[("000004", 1)][0].astype(np.float32), equal_nan=True)
    assert not new[4]["annos"]["label_std_valid"].any()
    r = summary.infos_objects_without_targets
    assert r["no result row"] == 1 and r["frame not in the results"] == 5 - 2  # Truck, Car, Cyclist of frame 000099
    assert summary.infos_frames_without_results == 2  # 000003 (empty) and 000099


def test_openpcdet_mismatch_exits_2_naming_the_first_frame(kitti, tmp_path):
    res, infos, _ = kitti
    out = tmp_path / "o.pkl"
    out.write_bytes(b"old output")
    data = pickle.loads(infos.read_bytes())
    data[1]["annos"]["dimensions"][3] = [5.5, 2.1, 1.9]  # Van of 000002: other sizes
    data[3]["annos"]["name"][1] = "Pedestrian"  # and a later frame, other class
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps(data))
    result = invoke("export", res, "-o", out, "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2
    assert "frame 000002" in result.stderr and "000004" not in result.stderr
    assert out.read_bytes() == b"old output"  # nothing written on error
    # fewer objects in the infos than the results index
    data = pickle.loads(infos.read_bytes())
    for k in data[3]["annos"]:
        data[3]["annos"][k] = data[3]["annos"][k][:1]
    bad.write_bytes(pickle.dumps(data))
    result = invoke("export", res, "-o", out, "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2 and "frame 000004" in result.stderr and "object_index 1" in result.stderr
    # no frame in common
    data = pickle.loads(infos.read_bytes())
    for info in data:
        info["point_cloud"]["lidar_idx"] = "9" + info["point_cloud"]["lidar_idx"]
    bad.write_bytes(pickle.dumps(data))
    result = invoke("export", res, "-o", out, "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2 and "none of its 4 frames" in result.stderr


def test_malformed_or_unlabelled_infos_exit_2_naming_the_entry(kitti, tmp_path):
    res, infos, _ = kitti
    data = pickle.loads(infos.read_bytes())
    data[2]["annos"]["dimensions"] = np.zeros((5, 2))
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(pickle.dumps(data))
    result = invoke("export", res, "-o", tmp_path / "o.pkl", "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2 and "frame entry 2: malformed entry" in result.stderr
    for info in data:
        del info["annos"]  # a test-split infos file
    bad.write_bytes(pickle.dumps(data))
    result = invoke("export", res, "-o", tmp_path / "o.pkl", "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2 and "frame entry 0: no 'annos'" in result.stderr


def test_openpcdet_waymo_infos_align_by_laser_object_id(tmp_path):
    seg, ts = "1071392229495085036_1844_790_1864_790", "1507315488219118"
    fid = f"{seg}:{ts}"
    objs = [("idA", "Vehicle", 4.4, 2.0, 1.5), ("idB", "Sign", 0.1, 0.6, 0.6), ("idC", "Vehicle", 4.9, 2.1, 1.8)]
    rows = [
        make_row(
            fid,
            2,
            object_id="idC",
            class_name="Vehicle",
            length=4.9,
            width=2.1,
            height=1.8,
            dataset="waymo-v1",
            cov=(np.eye(6) * 2e-3).ravel().tolist(),
        ),
        make_row(
            fid,
            0,
            object_id="idA",
            class_name="Vehicle",
            length=4.4,
            width=2.0,
            height=1.5,
            dataset="waymo-v1",
            cov=(np.eye(6) * 1e-3).ravel().tolist(),
        ),
    ]
    res = make_results(tmp_path / "res", [rows])
    infos = tmp_path / "waymo_infos.pkl"
    infos.write_bytes(pickle.dumps(openpcdet_waymo_infos({fid: objs})))
    out = tmp_path / "o.pkl"
    summary = E.export_results(res, out, fmt="openpcdet", infos=infos, encoding="residual")
    annos = pickle.loads(out.read_bytes())[0]["annos"]
    assert list(annos["label_std_valid"]) == [True, False, True]
    assert np.isfinite(annos["label_std"][[0, 2]][:, [0, 1, 3, 4, 6]]).all() and np.isnan(annos["label_std"][1]).all()
    # residual with the Waymo default anchors: xt std = std_x / diagonal of the Vehicle anchor (4.7, 2.1)
    assert annos["label_std"][0, 0] == pytest.approx(np.sqrt(1e-3) / np.hypot(4.7, 2.1), rel=1e-6)
    assert annos["label_std"][2, 0] == pytest.approx(np.sqrt(2e-3) / np.hypot(4.7, 2.1), rel=1e-6)
    assert summary.infos_objects_without_targets == {"class Sign not audited": 1}


# ----------------------------------------------------------------------------- mmdet3d v2


def test_mmdet3d_round_trip(kitti, tmp_path):
    res, _, rows = kitti
    infos = tmp_path / "kitti_infos_train.pkl"
    infos.write_bytes(pickle.dumps(mmdet3d_kitti_infos(FRAMES)))
    out = tmp_path / "mm.pkl"
    summary = E.export_results(res, out, fmt="mmdet3d", infos=infos, encoding="log-size", source="hull_iou")
    new = pickle.loads(out.read_bytes())
    expected, _ = expected_by_key(res, "log-size", "hull_iou")
    assert new["metainfo"][E.INFOS_META_KEY]["source"] == "hull_iou"
    for item in new["data_list"]:
        fid = Path(item["lidar_points"]["lidar_path"]).stem
        for inst in item["instances"]:
            std, cov, valid = (inst[k] for k in E.INFOS_KEYS)
            assert std.shape == (8,) and cov.shape == (8, 8) and std.dtype == np.float32 and isinstance(valid, bool)
            key = (fid, inst["index"])
            if inst["index"] >= 0 and key in expected:
                assert valid and np.allclose(std, expected[key][0].astype(np.float32), equal_nan=True)
            else:
                assert not valid and np.isnan(std).all()
    assert summary.infos_objects_with_targets == len(rows)
    # the wrong kind of file for the format
    result = invoke("export", res, "-o", out, "--format", "openpcdet", "--infos", infos)
    assert result.exit_code == 2 and "use --format mmdet3d" in result.stderr


# ----------------------------------------------------------------------------- pickles


class _Evil:
    def __reduce__(self):
        return (os.system, ("touch pwned",))


def test_a_pickle_with_a_disallowed_global_is_refused(kitti, tmp_path, monkeypatch):
    res, _, _ = kitti
    monkeypatch.chdir(tmp_path)
    bad = tmp_path / "evil.pkl"
    bad.write_bytes(pickle.dumps([{"point_cloud": {"lidar_idx": "000001"}, "annos": {"name": _Evil()}}]))
    with pytest.raises(E.UnsafePickleError, match="posix.system|os.system|nt.system"):
        E.load_infos(bad)
    result = invoke("export", res, "-o", tmp_path / "o.pkl", "--format", "openpcdet", "--infos", bad)
    assert result.exit_code == 2 and "refused to load the global" in result.stderr
    assert not (tmp_path / "pwned").exists() and not (tmp_path / "o.pkl").exists()
    bad.write_bytes(pickle.dumps({"x": eval}))
    with pytest.raises(E.UnsafePickleError, match="builtins.eval"):
        E.load_infos(bad)
    bad.write_bytes(b"not a pickle at all")
    with pytest.raises(E.ExportError, match="not a readable infos pickle"):
        E.load_infos(bad)


def test_written_infos_load_in_numpy_1_and_2_and_leave_no_temp_files(kitti, tmp_path):
    res, infos, _ = kitti
    out = tmp_path / "sub" / "o.pkl"
    E.export_results(res, out, fmt="openpcdet", infos=infos)
    raw = out.read_bytes()
    assert b"numpy._core" not in raw and b"numpy.core.multiarray" in raw  # names NumPy 1.x also has
    assert E.load_infos(out)[0]["annos"]["label_std"].shape[1] == 7  # and our own reader accepts it
    assert [p.name for p in out.parent.iterdir()] == ["o.pkl"]


# ----------------------------------------------------------------------------- CLI


def test_cli_help_and_json_summary(kitti, tmp_path):
    help_ = invoke("export", "--help")
    assert help_.exit_code == 0 and "Examples" in help_.stdout and "labelaudit export" in help_.stdout
    res, infos, _ = kitti
    result = invoke("export", res, "-o", tmp_path / "o.pkl", "--format", "openpcdet", "--infos", infos, "--encoding", "residual",
                    "--anchor-size", "Van=5,2,2", "--anchor-size", "Truck=8,2.5,3.2", "--json")  # fmt: skip
    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["infos_objects_with_targets"] == 6 and summary["rows_without_targets"] == {}
    assert "infos objects" in result.stderr


@pytest.mark.parametrize(
    "args,message",
    [
        (["--source", "bogus"], "unknown source"),
        (["--source", "fixed:-2"], "fixed:VAR"),
        (["--encoding", "residual", "--anchor-size", "Car=3.9,1.6"], "CLASS=l,w,h"),
        (["--format", "openpcdet"], "--infos FILE"),
        (["--infos", "x.pkl"], "--infos is for"),
    ],
)
def test_cli_bad_options_exit_2(kitti, tmp_path, args, message):
    res, _, _ = kitti
    result = invoke("export", res, "-o", tmp_path / "o.parquet", *args)
    assert result.exit_code == 2 and message in result.stderr


def test_cli_refuses_to_overwrite_the_input_infos_and_missing_results(kitti, tmp_path):
    res, infos, _ = kitti
    result = invoke("export", res, "-o", infos, "--format", "openpcdet", "--infos", infos)
    assert result.exit_code == 2 and "overwrite the input" in result.stderr
    result = invoke("export", tmp_path / "nope", "-o", tmp_path / "o.parquet")
    assert result.exit_code == 2 and "no such results folder" in result.stderr


# ----------------------------------------------------------------------------- real KITTI


@pytest.mark.realdata
@pytest.mark.slow
def test_real_kitti_frames_into_openpcdet_infos(realdata, tmp_path):
    """Six real KITTI frames (DontCare rows, Truck/Misc/Pedestrian/Cyclist): infer, then attach to infos built from label_2."""
    from labelaudit import InferRequest, run_infer
    from labelaudit.config import resolve_config
    from labelaudit.datasets.kitti import read_label
    from labelaudit.executors import SerialExecutor

    root = realdata / "openpcdet-pr653-kitti"
    cfg = resolve_config(None, "kitti", ["Car", "Pedestrian", "Cyclist"])
    run_infer(InferRequest(root, tmp_path / "res"), cfg, executor=SerialExecutor())
    frames = {}
    for p in sorted((root / "training" / "label_2").glob("*.txt")):
        lab = read_label(p)
        frames[p.stem] = [(n, l, w, h) for n, (h, w, l) in zip(lab.class_names, lab.dims_hwl)]
    infos = tmp_path / "kitti_infos_train.pkl"
    infos.write_bytes(pickle.dumps(openpcdet_kitti_infos(frames)))
    out = tmp_path / "o.pkl"
    summary = E.export_results(tmp_path / "res", out, fmt="openpcdet", infos=infos, encoding="residual")
    assert summary.infos_objects == 25 and summary.infos_objects_without_targets["DontCare"] == 15
    assert summary.infos_objects_without_targets == {
        "DontCare": 15,
        "class Truck not audited": 1,
        "class Misc not audited": 1,
    }
    assert summary.infos_objects_with_targets == 8
    new = pickle.loads(out.read_bytes())
    expected, _ = expected_by_key(tmp_path / "res", "residual")
    for info in new:
        annos = info["annos"]
        ordinal = -1
        for j, name in enumerate(annos["name"]):
            if name == "DontCare":
                continue
            ordinal += 1
            key = (info["point_cloud"]["lidar_idx"], ordinal)
            if name in ("Car", "Pedestrian", "Cyclist"):
                assert annos["label_std_valid"][j]
                assert np.allclose(annos["label_std"][j], expected[key][0].astype(np.float32), equal_nan=True)
                assert np.isnan(annos["label_std"][j][[2, 5]]).all()  # BEV model: zt, dzt not inferred

"""`labelaudit export --format glenet`: GLENet's infos and gt-database infos with label variances."""

from __future__ import annotations

import json
import os
import pickle
import pickletools
import subprocess
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from _core_synth import face_points
from infos_factory import (
    openpcdet_dbinfos,
    openpcdet_kitti_infos,
    openpcdet_kitti_infos_from_labels,
    openpcdet_waymo_infos,
)
from labelaudit import constants as C
from labelaudit import export as E
from labelaudit import training as T
from labelaudit.cli import app
from labelaudit.config import ModelParams
from labelaudit.core.posterior import infer_label
from labelaudit.export import glenet as G
from results_factory import make_results, make_row

runner = CliRunner()
KITTI_ANCHORS = C.DEFAULT_ANCHOR_SIZES["kitti"]

# KITTI label order: DontCare last; classes GLENet has no anchor for (Van, Truck) and one not audited (Misc).
FRAMES = {
    "000010": [
        ("Car", 4.1, 1.7, 1.5),
        ("Pedestrian", 0.8, 0.6, 1.75),
        ("Van", 4.8, 1.9, 2.1),
        ("DontCare", -1, -1, -1),
        ("DontCare", -1, -1, -1),
    ],
    "000011": [("Misc", 2.0, 1.0, 1.0), ("Cyclist", 1.8, 0.6, 1.7), ("Car", 3.9, 1.6, 1.5)],
    "000012": [],
    "000013": [("Car", 4.4, 1.8, 1.4), ("Car", 3.7, 1.6, 1.5), ("Truck", 8.0, 2.5, 3.2), ("DontCare", -1, -1, -1)],
}
AUDITED = ("Car", "Pedestrian", "Cyclist", "Van", "Truck")


def invoke(*args):
    return runner.invoke(app, [str(a) for a in args])


def posterior_rows(frames, model: str, skip=(), dataset="kitti", ids=None):
    """Result rows with real posteriors (points on the two faces a sensor at the origin sees), one per audited object."""
    rows = []
    for f, (fid, objs) in enumerate(frames.items()):
        ordinal = -1
        for j, (name, l, w, h) in enumerate(objs):
            if name == "DontCare":
                continue
            ordinal += 1
            if name not in AUDITED:
                continue
            box = np.array([8.0 + 3 * ordinal, 2.0 + f, -0.9, l, w, h, 0.3 + 0.7 * ordinal])
            n = 0 if (fid, ordinal) in skip else 15 + 10 * ordinal
            pts = face_points(box, ["-x", "-y"], n, noise=0.03, seed=f * 10 + ordinal) if n else np.zeros((0, 3))
            post = infer_label(box, pts, name, ModelParams(kind=model))
            status = "skipped" if (fid, ordinal) in skip else "ok"
            rows.append(make_row(
                fid, ordinal, class_name=name, status=status, dataset=dataset,
                object_id=(ids or {}).get((fid, j), f"{fid}:{ordinal}"),
                cx=box[0], cy=box[1], cz=box[2], length=l, width=w, height=h, yaw=box[6],
                cov=None if status == "skipped" else post.cov.ravel().tolist(), cov_dim=post.cov.shape[0], model=model,
                **{f"std_{k}": v for k, v in post.std_box.items()},
            ))  # fmt: skip
    return rows


def write_kitti(tmp_path, model="bev", skip=()):
    rows = posterior_rows(FRAMES, model, skip)
    res = make_results(tmp_path / f"res-{model}", [rows])
    infos = openpcdet_kitti_infos(FRAMES)
    (tmp_path / "in").mkdir(exist_ok=True)
    ip, dp = tmp_path / "in" / "kitti_infos_train.pkl", tmp_path / "in" / "kitti_dbinfos_train.pkl"
    ip.write_bytes(pickle.dumps(infos))
    dp.write_bytes(pickle.dumps(openpcdet_dbinfos(infos)))
    return res, ip, dp, rows


def drop_dontcare(annos: dict) -> dict:
    """GLENet's KittiDataset.__getitem__: common_utils.drop_info_with_name(annos, 'DontCare') indexes every key."""
    keep = [i for i, x in enumerate(annos["name"]) if x != "DontCare"]
    return {k: v[keep] for k, v in annos.items() if k != "gt_boxes_lidar"}


def expected_values(row, anchor, model):
    """The seven values by the formulas of docs/training.md, from the row's std_* columns."""
    d = np.hypot(anchor[0], anchor[1])
    if model == "bev":  # z and h from the class prior
        p = C.DEFAULT_PRIORS.get(row["class_name"], C.DEFAULT_PRIORS["default"])
        sz, sh = p["center"], p["height"]
    else:
        sz, sh = row["std_cz"], row["std_height"]
    s_yaw2 = row["std_yaw"] ** 2
    return np.array([
        row["std_cx"] ** 2 / d**2, row["std_cy"] ** 2 / d**2, sz**2 / anchor[2] ** 2,
        (row["std_length"] / row["length"]) ** 2, (row["std_width"] / row["width"]) ** 2, (sh / row["height"]) ** 2,
        0.5 * (1 - np.exp(-2 * s_yaw2)),
    ])  # fmt: skip


# ----------------------------------------------------------------------------- the formulas


def test_glenet_variances_known_answer_and_first_order():
    box = np.array([[20.0, -3.0, -0.7, 4.0, 1.8, 1.6, 0.4]])
    std = np.array([0.2, 0.1, 0.05, 0.3, 0.08, 0.04, 0.1])
    cov = np.diag(std**2)[None]
    anchor = np.array([3.9, 1.6, 1.56])
    v = T.glenet_variances(box, cov, anchor)[0]
    d2 = 3.9**2 + 1.6**2
    want = [
        0.04 / d2,
        0.01 / d2,
        0.0025 / 1.56**2,
        (0.3 / 4.0) ** 2,
        (0.08 / 1.8) ** 2,
        (0.04 / 1.6) ** 2,
        0.5 * (1 - np.exp(-0.02)),
    ]
    assert v == pytest.approx(want, rel=1e-12)
    # Var(sin Δθ) of a Gaussian Δθ: first order (= Σ_θθ) for small std, below it, and never above ½
    for s in (1e-3, 0.1, 0.5, 3.0):
        c = np.diag([0.01] * 6 + [s * s])[None]
        vs = T.glenet_variances(box, c, anchor)[0, 6]
        samples = np.sin(np.random.default_rng(0).normal(0.0, s, 400_000))
        assert vs == pytest.approx(samples.var(), rel=0.02, abs=1e-4)
        assert vs <= min(s * s, 0.5)
    assert T.glenet_variances(box, np.diag([0.01] * 6 + [1e-6])[None], anchor)[0, 6] == pytest.approx(1e-6, rel=1e-5)
    # larger box covariance → larger variances (direction), every entry
    assert np.all(T.glenet_variances(box, 4 * cov, anchor) > T.glenet_variances(box, cov, anchor))
    # log-size variances: larger objects of the same absolute std are relatively surer
    big = box.copy()
    big[0, 3:6] *= 2
    assert np.all(T.glenet_variances(big, cov, anchor)[0, 3:6] == pytest.approx(v[3:6] / 4))


def test_correlations_do_not_leak_into_the_variances():
    """Only the diagonal of the residual covariance is exported: a correlation between x and l changes nothing."""
    box = np.array([[10.0, 1.0, -0.8, 4.0, 1.7, 1.5, 0.0]])
    cov = np.diag([0.04, 0.01, 0.01, 0.09, 0.01, 0.01, 0.01])
    corr = cov.copy()
    corr[0, 3] = corr[3, 0] = 0.05
    a = T.glenet_variances(box, cov[None], (3.9, 1.6, 1.56))
    b = T.glenet_variances(box, corr[None], (3.9, 1.6, 1.56))
    assert np.array_equal(a, b)


# ----------------------------------------------------------------------------- KITTI round trip (simulated)


@pytest.mark.parametrize("model", ["bev", "3d"])
def test_kitti_round_trip_aligned_with_annos_and_dbinfos(tmp_path, model):
    res, ip, dp, rows = write_kitti(tmp_path, model, skip={("000013", 1)})
    out = tmp_path / "glenet"
    summary = E.export_results(res, out, fmt="glenet", infos=ip, dbinfos=dp)
    assert sorted(p.name for p in out.iterdir()) == [
        "kitti_dbinfos_train.pkl",
        "kitti_infos_train.pkl",
        G.GLENET_META_NAME,
    ]
    infos = pickle.loads((out / "kitti_infos_train.pkl").read_bytes())
    db = pickle.loads((out / "kitti_dbinfos_train.pkl").read_bytes())
    original = pickle.loads(ip.read_bytes())
    by_key = {(r["frame_id"], r["object_index"]): r for r in rows}
    n_values = 0
    for info, orig in zip(infos, original):
        annos = info["annos"]
        fid = info["point_cloud"]["lidar_idx"]
        u = annos[G.GLENET_KEY]
        assert u.shape == (len(annos["name"]), 7) and u.dtype == np.float32
        for k in orig["annos"]:  # nothing else changed
            assert np.array_equal(annos[k], orig["annos"][k])
        for j, (name, idx) in enumerate(zip(annos["name"], annos["index"])):
            row = by_key.get((fid, int(idx)))
            if name in KITTI_ANCHORS and row is not None and row["status"] == "ok":
                assert np.all(u[j] > 0)
                # the must-hold: Var(log l) = (std_length/length)², Var(x)/diag² = std_cx²/diag² (to first order, within 5 %)
                want = expected_values(row, KITTI_ANCHORS[name], model)
                assert u[j] == pytest.approx(want, rel=0.05)
                assert u[j][[0, 3]] == pytest.approx(
                    want[[0, 3]], rel=1e-5
                )  # the same linear algebra: float32 rounding only
                n_values += 1
            else:  # DontCare, Misc (not audited), Van/Truck (no GLENet anchor), the skipped Car
                assert np.all(u[j] == -1.0), (fid, j, name)
        # GLENet's dataset drops DontCare from every annos array together: uncertainty stays aligned with the boxes
        kept = drop_dontcare(annos)
        assert len(kept[G.GLENET_KEY]) == len(kept["name"]) == len(orig["annos"]["gt_boxes_lidar"])
    assert n_values == summary.infos_objects_with_targets == 5
    assert summary.infos_objects_without_targets == {
        "DontCare": 3, "class Misc not audited": 1, "status skipped": 1,
        "no anchor size for class Van (--anchor-size Van=l,w,h)": 1, "no anchor size for class Truck (--anchor-size Truck=l,w,h)": 1,
    }  # fmt: skip
    assert summary.objects_z_h_from_prior == (
        5 if model == "bev" else 0
    )  # the rows exported (Van, Truck have no anchor)
    # every gt-database entry carries its frame's row
    frame_of = {info["point_cloud"]["lidar_idx"]: info for info in infos}
    n_db = 0
    for cls, entries in db.items():
        for e in entries:
            annos = frame_of[e["image_idx"]]["annos"]
            j = int(np.flatnonzero(annos["index"] == e["gt_idx"])[0])
            assert annos["name"][j] == cls
            assert e[G.GLENET_KEY].shape == (7,) and np.array_equal(e[G.GLENET_KEY], annos[G.GLENET_KEY][j])
            n_db += 1
    assert n_db == summary.dbinfos_objects == 9
    assert summary.dbinfos_objects_with_targets == 5
    assert summary.dbinfos_objects_without_targets == {
        "class Misc not audited": 1, "status skipped": 1,
        "no anchor size for class Van (--anchor-size Van=l,w,h)": 1, "no anchor size for class Truck (--anchor-size Truck=l,w,h)": 1,
    }  # fmt: skip
    # what GLENet's database sampler stacks for pasted objects
    assert np.array([x[G.GLENET_KEY] for x in db["Car"]]).shape == (len(db["Car"]), 7)
    meta = json.loads((out / G.GLENET_META_NAME).read_text())
    assert meta["targets"] == list(T.GLENET_TARGETS) and meta["anchor_sizes"]["Car"] == [3.9, 1.6, 1.56]
    assert meta["objects_with_z_h_from_prior"] == summary.objects_z_h_from_prior


def test_bev_z_and_h_come_from_the_class_prior_and_the_note_says_so(tmp_path):
    res, ip, dp, _ = write_kitti(tmp_path, "bev")
    result = invoke("export", res, "--format", "glenet", "--infos", ip, "--dbinfos", dp, "-o", tmp_path / "g", "--json")
    assert result.exit_code == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["objects_z_h_from_prior"] == 6 and "class prior" in result.stderr and "--model 3d" in result.stderr
    infos = pickle.loads((tmp_path / "g" / "kitti_infos_train.pkl").read_bytes())
    u = infos[0]["annos"][G.GLENET_KEY][0]  # the Car of 000010
    p = C.DEFAULT_PRIORS["default"]
    assert u[2] == pytest.approx(p["center"] ** 2 / 1.56**2, rel=1e-6)
    assert u[5] == pytest.approx((p["height"] / 1.5) ** 2, rel=1e-6)
    ped = infos[0]["annos"][G.GLENET_KEY][1]
    assert ped[2] == pytest.approx(C.DEFAULT_PRIORS["Pedestrian"]["center"] ** 2 / 1.73**2, rel=1e-6)


def test_anchor_size_option_gives_van_values_and_fewer_points_give_larger_values(tmp_path):
    res, ip, dp, rows = write_kitti(tmp_path, "3d")
    db = pickle.loads(dp.read_bytes())
    db["Car"].append({**db["Car"][0], "image_idx": "000777"})  # a gt-database entry of a frame the infos do not hold
    dp.write_bytes(pickle.dumps(db))
    summary = E.export_results(
        res, tmp_path / "g", fmt="glenet", infos=ip, dbinfos=dp, anchor_sizes={"Van": (5.0, 2.0, 2.0)}
    )
    assert summary.dbinfos_objects_without_targets["frame not in the infos"] == 1
    assert np.all(pickle.loads((tmp_path / "g" / dp.name).read_bytes())["Car"][-1][G.GLENET_KEY] == -1)
    infos = pickle.loads((tmp_path / "g" / "kitti_infos_train.pkl").read_bytes())
    van = infos[0]["annos"][G.GLENET_KEY][2]
    assert np.all(van > 0)
    row = next(r for r in rows if r["class_name"] == "Van")
    assert van[0] == pytest.approx(row["std_cx"] ** 2 / (5.0**2 + 2.0**2), rel=1e-5)
    # 000013: the first Car has 15 points a face, the second 25: the second is surer in x, y and length
    cars = infos[3]["annos"][G.GLENET_KEY]
    assert np.all(cars[1][[0, 1, 3]] < cars[0][[0, 1, 3]])


# ----------------------------------------------------------------------------- pickles


def pickle_globals(raw: bytes) -> tuple[int, set[tuple[str, str]]]:
    """(protocol, every (module, name) the pickle imports), read from its opcodes."""
    protocol, found, memo, pushed = 0, set(), {}, []
    for op, arg, _ in pickletools.genops(raw):
        if op.name == "PROTO":
            protocol = arg
        elif op.name == "GLOBAL":
            module, name = arg.split(" ")
            found.add((module, name))
        elif op.name in ("SHORT_BINUNICODE", "BINUNICODE", "UNICODE", "BINUNICODE8"):
            pushed.append(arg)
        elif op.name == "MEMOIZE":
            memo[len(memo)] = pushed[-1] if pushed else None
        elif op.name in ("BINPUT", "LONG_BINPUT", "PUT"):
            memo[arg] = pushed[-1] if pushed else None
        elif op.name in ("BINGET", "LONG_BINGET", "GET"):
            pushed.append(memo.get(arg))
        elif op.name == "STACK_GLOBAL":
            found.add((pushed[-2], pushed[-1]))
            pushed.append(None)
        elif op.name not in ("FRAME", "MARK", "STOP"):
            pushed.append(None)
    return protocol, found


NUMPY1_GLOBALS = {
    ("numpy.core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"),
    ("numpy", "ndarray"),
    ("numpy", "dtype"),
}


def test_written_pickles_import_only_names_numpy_1_has(tmp_path):
    res, ip, dp, _ = write_kitti(tmp_path, "bev")
    # inputs written by NumPy 2 (this environment): their arrays name numpy._core
    raw_in = ip.read_bytes()
    if np.__version__.startswith("2."):
        assert any(m.startswith("numpy._core") for m, _ in pickle_globals(raw_in)[1])
    E.export_results(res, tmp_path / "g", fmt="glenet", infos=ip, dbinfos=dp)
    for name in ("kitti_infos_train.pkl", "kitti_dbinfos_train.pkl"):
        raw = (tmp_path / "g" / name).read_bytes()
        protocol, found = pickle_globals(raw)
        assert protocol <= C.INFOS_PICKLE_PROTOCOL <= 4  # Python 3.4+
        assert found and found <= NUMPY1_GLOBALS, found - NUMPY1_GLOBALS
        assert b"numpy._core" not in raw
        assert E.load_infos(tmp_path / "g" / name)  # and our restricted reader takes it back
    # the opcode reader itself sees a numpy._core global where there is one
    assert ("numpy._core.multiarray", "_reconstruct") in pickle_globals(pickle.dumps(np.zeros(2), protocol=4))[
        1
    ] or not np.__version__.startswith("2.")
    assert [p.name for p in (tmp_path / "g").iterdir() if ".tmp-" in p.name] == []


def test_a_failed_write_leaves_the_previous_files_whole_and_no_temporaries(tmp_path, monkeypatch):
    """Infos and gt-database infos are replaced together or not at all (a failure in the second write keeps both old files)."""
    res, ip, dp, _ = write_kitti(tmp_path, "bev")
    out = tmp_path / "g"
    E.export_results(res, out, fmt="glenet", infos=ip, dbinfos=dp)
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    import labelaudit.export.pickles as P

    real_dump, calls = pickle.dump, []

    def failing_dump(obj, f, protocol=None):
        calls.append(1)
        if len(calls) == 2:  # the gt-database file: half written, then the disk is full
            f.write(b"\x80\x04partial")
            raise OSError(28, "No space left on device")
        real_dump(obj, f, protocol=protocol)

    monkeypatch.setattr(P.pickle, "dump", failing_dump)
    with pytest.raises(OSError, match="No space left"):
        E.export_results(res, out, fmt="glenet", infos=ip, dbinfos=dp, source="fixed:0.01")
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before  # both old files, no temporaries


@pytest.mark.skipif(
    not os.environ.get("LABELAUDIT_NUMPY1_PYTHON"), reason="set LABELAUDIT_NUMPY1_PYTHON to a Python with NumPy 1.x"
)
def test_written_pickles_load_in_a_real_numpy_1(tmp_path):
    """The files load in a NumPy 1.x interpreter, the NumPy-2 inputs do not (numpy._core)."""
    res, ip, dp, _ = write_kitti(tmp_path, "3d")
    E.export_results(res, tmp_path / "g", fmt="glenet", infos=ip, dbinfos=dp)
    code = (
        "import pickle, sys, numpy as np; assert np.__version__.startswith('1.'), np.__version__; "
        "i = pickle.load(open(sys.argv[1], 'rb')); d = pickle.load(open(sys.argv[2], 'rb')); "
        "print(float(i[0]['annos']['uncertainty'][0][3]), float(d['Car'][0]['uncertainty'][3]))"
    )
    py = os.environ["LABELAUDIT_NUMPY1_PYTHON"]
    out = subprocess.run(
        [py, "-c", code, tmp_path / "g" / ip.name, tmp_path / "g" / dp.name], capture_output=True, text=True, check=True
    )
    a, b = map(float, out.stdout.split())
    assert a == b > 0
    bad = subprocess.run([py, "-c", code, ip, dp], capture_output=True, text=True)
    assert bad.returncode != 0 and "numpy._core" in bad.stderr


# ----------------------------------------------------------------------------- Waymo


def test_waymo_per_sequence_infos_folder_and_vehicle_dbinfos(tmp_path):
    segs = [
        "1071392229495085036_1844_790_1864_790",
        "10017090168044687777_6380_000_6400_000",
        "9999999999999999999_0_000_20_000",
    ]
    frames = {
        f"{segs[0]}:1507315488219118": [
            ("idA", "Vehicle", 4.4, 2.0, 1.5),
            ("idB", "Sign", 0.1, 0.6, 0.6),
            ("idC", "Vehicle", 4.9, 2.1, 1.8),
        ],
        f"{segs[0]}:1507315488319118": [("idA", "Vehicle", 4.4, 2.0, 1.5), ("idD", "Pedestrian", 0.9, 0.8, 1.8)],
        f"{segs[1]}:1510593600000000": [],
        f"{segs[2]}:1510593700000000": [("idZ", "Vehicle", 4.0, 1.9, 1.6)],  # a sequence not audited
    }
    rows = []
    for fid, objs in list(frames.items())[:3]:
        for j, (oid, name, l, w, h) in enumerate(objs):
            if name == "Sign":
                continue
            cov = np.diag([4e-3, 1e-3, 2e-3, 3e-3, 1e-3, 5e-4, 1e-3, 1e-3]) * (1 + j)
            rows.append(make_row(fid, j, object_id=oid, class_name=name, length=l, width=w, height=h, dataset="waymo-v1",
                                 cov=cov.ravel().tolist(), cov_dim=8, model="3d"))  # fmt: skip
    res = make_results(tmp_path / "res", [rows])
    root = tmp_path / "waymo_processed_data_v0_5_0"
    all_infos = []
    for seg in segs:
        seq = f"segment-{seg}_with_camera_labels"
        part = openpcdet_waymo_infos({k: v for k, v in frames.items() if k.startswith(seg)})
        (root / seq).mkdir(parents=True)
        (root / seq / f"{seq}.pkl").write_bytes(pickle.dumps(part))
        all_infos += part
    db = openpcdet_dbinfos(all_infos)
    dp = tmp_path / "waymo_processed_data_v0_5_0_waymo_dbinfos_train_sampled_1.pkl"
    dp.write_bytes(pickle.dumps(db))
    out = tmp_path / "g"
    summary = E.export_results(res, out, fmt="glenet", infos=root, dbinfos=dp)
    written = sorted(str(p.relative_to(out)) for p in out.rglob("*.pkl"))
    assert written == sorted(
        [f"segment-{s}_with_camera_labels/segment-{s}_with_camera_labels.pkl" for s in segs] + [dp.name]
    )
    seq0 = f"segment-{segs[0]}_with_camera_labels"
    infos0 = pickle.loads((out / seq0 / f"{seq0}.pkl").read_bytes())
    u = infos0[0]["annos"][G.GLENET_KEY]
    assert u.shape == (3, 7) and np.all(u[1] == -1) and np.all(u[[0, 2]] > 0)
    # the Vehicle anchor 4.7 × 2.1 × 1.7: xt = x / diag, zt = z / h_a
    assert u[0, 0] == pytest.approx(4e-3 / (4.7**2 + 2.1**2), rel=1e-5)
    assert u[2, 2] == pytest.approx(3 * 2e-3 / 1.7**2, rel=1e-5)  # the third object's covariance is 3×
    assert infos0[1]["annos"][G.GLENET_KEY][1][0] > 0  # the Pedestrian with its own anchor
    empty = pickle.loads(
        (out / f"segment-{segs[1]}_with_camera_labels" / f"segment-{segs[1]}_with_camera_labels.pkl").read_bytes()
    )
    assert empty[0]["annos"][G.GLENET_KEY].shape == (0, 7)
    new_db = pickle.loads((out / dp.name).read_bytes())
    annos_of = {}
    for p in out.glob("*/*.pkl"):
        for info in pickle.loads(p.read_bytes()):
            annos_of[(info["point_cloud"]["lidar_sequence"], info["point_cloud"]["sample_idx"])] = info["annos"]
    for entries in new_db.values():
        for e in entries:  # every entry carries its frame's row (gt_idx = the annos row for Waymo)
            assert np.array_equal(
                e[G.GLENET_KEY], annos_of[(e["sequence_name"], e["sample_idx"])][G.GLENET_KEY][e["gt_idx"]]
            )
    zed = [e for e in new_db["Vehicle"] if e["sequence_name"].startswith(f"segment-{segs[2]}")]
    assert len(zed) == 1 and np.all(zed[0][G.GLENET_KEY] == -1)  # its sequence was not audited
    assert summary.dbinfos_objects == 6 and summary.dbinfos_objects_with_targets == 4
    assert summary.dbinfos_objects_without_targets == {"class Sign not audited": 1, "frame not in the results": 1}
    assert summary.infos_frames_without_results == 2  # the empty frame and the sequence not audited


# ----------------------------------------------------------------------------- bad input


def test_bad_options_and_mismatching_dbinfos_exit_2_and_write_nothing(tmp_path):
    res, ip, dp, _ = write_kitti(tmp_path, "bev")
    out = tmp_path / "g"
    r = invoke("export", res, "--format", "glenet", "-o", out)
    assert r.exit_code == 2 and "--infos FILE" in r.stderr
    r = invoke("export", res, "--format", "glenet", "--infos", ip, "--encoding", "residual", "-o", out)
    assert r.exit_code == 2 and "drop --encoding" in r.stderr
    r = invoke("export", res, "--format", "openpcdet", "--infos", ip, "--dbinfos", dp, "-o", tmp_path / "o.pkl")
    assert r.exit_code == 2 and "--dbinfos is for --format glenet" in r.stderr
    r = invoke("export", res, "--format", "glenet", "--infos", ip, "--dbinfos", dp, "-o", ip.parent)
    assert r.exit_code == 2 and "would overwrite the input" in r.stderr
    r = invoke("export", res, "--format", "glenet", "--infos", tmp_path, "-o", out)
    assert r.exit_code == 2 and "<sequence>/<sequence>.pkl" in r.stderr
    db = pickle.loads(dp.read_bytes())
    db["Car"][2]["gt_idx"] = 7
    bad = tmp_path / "bad_db.pkl"
    bad.write_bytes(pickle.dumps(db))
    r = invoke("export", res, "--format", "glenet", "--infos", ip, "--dbinfos", bad, "-o", out)
    assert r.exit_code == 2 and "Car[2]: gt_idx 7" in r.stderr and "000013" in r.stderr
    db = pickle.loads(dp.read_bytes())
    db["Car"][0]["box3d_lidar"] = db["Car"][0]["box3d_lidar"] * 1.1
    bad.write_bytes(pickle.dumps(db))
    r = invoke("export", res, "--format", "glenet", "--infos", ip, "--dbinfos", bad, "-o", out)
    assert r.exit_code == 2 and "Car[0]" in r.stderr and "does not belong to these infos" in r.stderr
    bad.write_bytes(pickle.dumps([1, 2]))
    r = invoke("export", res, "--format", "glenet", "--infos", ip, "--dbinfos", bad, "-o", out)
    assert r.exit_code == 2 and "class name → list of entries" in r.stderr
    assert not out.exists()  # nothing written on any error


# ----------------------------------------------------------------------------- real KITTI


def real_round_trip(root: Path, tmp_path: Path, model: str):
    """Infos and gt-database infos built from a real KITTI root's label_2 + calib as OpenPCDet does, an infer, the export, every check.

    Returns the summary and the largest relative deviation of Var(dxt), Var(xt) from (std_length/length)², std_cx²/d².
    """
    import pyarrow.parquet as pq

    from labelaudit import InferRequest, run_infer
    from labelaudit.config import resolve_config
    from labelaudit.executors import SerialExecutor

    infos = openpcdet_kitti_infos_from_labels(root)
    db = openpcdet_dbinfos(infos)
    ip, dp = tmp_path / "kitti_infos_train.pkl", tmp_path / "kitti_dbinfos_train.pkl"
    ip.write_bytes(pickle.dumps(infos))
    dp.write_bytes(pickle.dumps(db))
    cfg = resolve_config(None, "kitti", ["Car", "Pedestrian", "Cyclist"], model=model)
    run_infer(InferRequest(root, tmp_path / "res"), cfg, executor=SerialExecutor())
    summary = E.export_results(tmp_path / "res", tmp_path / "g", fmt="glenet", infos=ip, dbinfos=dp)
    table = {(r["frame_id"], r["object_index"]): r for r in pq.read_table(tmp_path / "res" / "objects").to_pylist()}
    new = pickle.loads((tmp_path / "g" / "kitti_infos_train.pkl").read_bytes())
    checked, dev = 0, 0.0
    for info in new:
        annos = info["annos"]
        u = annos[G.GLENET_KEY]
        assert u.shape == (len(annos["name"]), 7)
        for j, (name, idx) in enumerate(zip(annos["name"], annos["index"])):
            row = table.get((info["point_cloud"]["lidar_idx"], int(idx)))
            if row is None or name not in KITTI_ANCHORS:
                assert np.all(u[j] == -1), (name, idx)
                continue
            assert np.all(u[j] > 0)
            anchor = KITTI_ANCHORS[name]
            assert u[j] == pytest.approx(expected_values(row, anchor, model), rel=0.05)
            # the must-hold: Var(log l) = (std_length/length)², Var(x)/diag² = std_cx²/diag², within 5 %
            for got, want in (
                (u[j][3], (row["std_length"] / row["length"]) ** 2),
                (u[j][0], row["std_cx"] ** 2 / (anchor[0] ** 2 + anchor[1] ** 2)),
            ):
                assert got == pytest.approx(want, rel=0.05)
                dev = max(dev, abs(float(got) / want - 1))
            checked += 1
        kept = drop_dontcare(annos)  # what GLENet's KittiDataset keeps: rows still one per box
        assert len(kept[G.GLENET_KEY]) == len(kept["name"]) == len(annos["gt_boxes_lidar"])
    assert checked == summary.infos_objects_with_targets > 0
    new_db = pickle.loads((tmp_path / "g" / "kitti_dbinfos_train.pkl").read_bytes())
    frame_of = {i["point_cloud"]["lidar_idx"]: i["annos"] for i in new}
    for entries in new_db.values():
        for e in entries:
            a = frame_of[e["image_idx"]]
            j = int(np.flatnonzero(a["index"] == e["gt_idx"])[0])
            assert np.array_equal(e[G.GLENET_KEY], a[G.GLENET_KEY][j])
    assert summary.dbinfos_objects == sum(len(v) for v in db.values())
    assert summary.dbinfos_objects_with_targets == checked  # every audited object has one gt-database entry
    return summary, dev


@pytest.mark.realdata
@pytest.mark.slow
def test_real_kitti_frames_round_trip_3d(realdata, tmp_path):
    """Six real KITTI frames (OpenPCDet's sample), a 3D infer: all seven values from the posterior."""
    root = realdata / "openpcdet-pr653-kitti"
    # our gt_idx convention is OpenPCDet's: its real gt_database files are named <image_idx>_<name>_<gt_idx>.bin
    real_db = sorted(p.name for p in (root / "gt_database").glob("*.bin"))
    ours = sorted(
        Path(e["path"]).name
        for entries in openpcdet_dbinfos(openpcdet_kitti_infos_from_labels(root)).values()
        for e in entries
    )
    assert real_db == ours
    summary, dev = real_round_trip(root, tmp_path, "3d")
    assert (
        summary.infos_objects == 25 and summary.infos_objects_with_targets == 8 and summary.objects_z_h_from_prior == 0
    )
    assert summary.infos_objects_without_targets == {
        "DontCare": 15,
        "class Truck not audited": 1,
        "class Misc not audited": 1,
    }
    assert summary.dbinfos_objects == 10 and dev < 1e-5


@pytest.mark.realdata
@pytest.mark.slow
def test_real_kitti_more_frames_round_trip_bev(realdata, tmp_path):
    """Seven more real KITTI frames, a BEV infer: z and h from the class prior, counted."""
    root = realdata / "kitti-object-more"
    summary, dev = real_round_trip(root, tmp_path, "bev")
    assert summary.objects_z_h_from_prior == summary.infos_objects_with_targets == summary.rows_with_targets
    assert summary.infos_objects_without_targets.get("class Van not audited") == 2 and dev < 1e-5

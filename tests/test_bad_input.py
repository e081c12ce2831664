"""One regression test per way hostile input through ``labelaudit infer`` once broke it, end to end.

Each test builds a tiny dataset (tests/_hostile.py), damages it the way a fuzz campaign
did, runs the real command line and checks what the user sees (docs/datasets.md § Bad input):
exit 0 with the damage recorded where it belongs, or exit 2 and one line naming the file.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import _hostile as H
from labelaudit import results as R

INFER = ("--workers", "1", "-q")


def _set_token(label: Path, line: int, column: int, value: str) -> None:
    rows = label.read_text().split("\n")
    tokens = rows[line].split()
    tokens[column] = value
    rows[line] = " ".join(tokens)
    label.write_text("\n".join(rows))


@pytest.fixture()
def kitti(tmp_path) -> Path:
    return H.write_kitti(tmp_path / "data", ["000000", "000001"])


def _infer(data: Path, out: Path, *extra: str, allowed=(0,)) -> H.CliRun:
    run = H.run_cli("infer", data, "-o", out, *INFER, *extra)
    H.check_output(run, allowed=allowed)
    return run


# --------------------------------------------------------------------------- 1. NaN box fields


@pytest.mark.parametrize("column", [11, 12, 13, 14])  # x, y, z, rotation_y
def test_a_nan_kitti_box_field_is_an_error_row_and_the_rest_is_audited(kitti, tmp_path, column):
    label = kitti / "training/label_2/000000.txt"
    _set_token(label, 1, column, "nan")
    _infer(kitti, tmp_path / "out")  # was: ArrowInvalid "Column 'cx' is declared non-nullable", exit 3
    rows = H.rows_by_frame(tmp_path / "out")
    assert [r["status"] for r in rows["000000"]] == ["ok", "error", "ok"]
    bad = rows["000000"][1]
    assert bad["message"].startswith(f"{label}:2: ") and "= nan (expected a finite number)" in bad["message"]
    assert bad["label_line"] == 2 and bad["jiou_gt"] is None
    assert [r["status"] for r in rows["000001"]] == ["ok"] * 3


def _waymo_segment():
    from labelaudit.sim.scene import SceneSpec
    from labelaudit.sim.waymo_writer import simulate_waymo_segment

    return simulate_waymo_segment(
        seed=2,
        frames=1,
        size="small",
        name="seg",
        scene_spec=SceneSpec(num_vehicles=(2, 2), num_vru=(0, 0), distance=(6.0, 20.0)),
    )


def test_a_nan_waymo_v1_box_field_is_an_error_row(tmp_path):
    from labelaudit.datasets import waymo_proto as wp
    from labelaudit.datasets.waymo_v1 import encode_record, iter_records
    from labelaudit.sim.waymo_writer import write_waymo_v1

    path = write_waymo_v1(_waymo_segment(), tmp_path / "v1" / "seg.tfrecord")
    msg = wp.Frame.FromString(next(iter_records(path)))
    msg.laser_labels[0].box.center_y = float("nan")
    path.write_bytes(encode_record(msg.SerializeToString()))
    _infer(tmp_path / "v1", tmp_path / "out", "--classes", "all")
    (rows,) = H.rows_by_frame(tmp_path / "out").values()
    assert rows[0]["status"] == "error" and rows[1]["status"] != "error"
    assert rows[0]["message"] == f"{path} record 0 laser_labels[0]: box.center_y = nan (expected a finite number)"


@pytest.mark.parametrize("value", [None, float("nan")])
def test_a_nan_or_null_waymo_v2_box_column_is_an_error_row(tmp_path, value):
    from labelaudit.datasets.waymo_v2 import BOX_COLUMNS
    from labelaudit.sim.waymo_writer import write_waymo_v2

    root = write_waymo_v2(_waymo_segment(), tmp_path / "v2")
    box = root / "lidar_box" / "seg.parquet"
    t = pq.read_table(box)
    col = BOX_COLUMNS["width"]
    values = t.column(col).to_pylist()
    values[1] = value
    pq.write_table(t.set_column(t.schema.get_field_index(col), col, pa.array(values, pa.float64())), box)
    _infer(root, tmp_path / "out", "--classes", "all")
    (rows,) = H.rows_by_frame(tmp_path / "out").values()
    assert [r["status"] == "error" for r in rows] == [False, True]
    what = "is null (expected a number)" if value is None else "= nan (expected a finite number)"
    assert rows[1]["message"] == f"{box} row 1: {col} {what}"


# --------------------------------------------------------------------------- 2. integers beyond int32


@pytest.mark.parametrize("value", ["3000000000", "1e10", "1e300"])
def test_an_occlusion_beyond_int32_is_a_frame_error_naming_file_line_and_column(kitti, tmp_path, value):
    label = kitti / "training/label_2/000000.txt"
    _set_token(label, 2, 2, value)
    _infer(kitti, tmp_path / "out")  # was: "Value 3000000000 too large to fit in C integer type", exit 3
    (err,) = H.errors_of(tmp_path / "out")
    assert err["file"] == str(label) and err["line"] == 3 and err["unit"] == "000000"
    assert f"column 'occluded': expected an integer (0, 1, 2, 3; -1 for DontCare), got '{value}'" in err["message"]
    assert list(H.rows_by_frame(tmp_path / "out")) == ["000001"]


def test_a_waymo_v2_count_beyond_int32_is_null_with_a_warning(tmp_path):
    from labelaudit.datasets.waymo_v2 import BOX_EXTRAS
    from labelaudit.sim.waymo_writer import write_waymo_v2

    root = write_waymo_v2(_waymo_segment(), tmp_path / "v2")
    box = root / "lidar_box" / "seg.parquet"
    t = pq.read_table(box)
    col = BOX_EXTRAS["num_lidar_points_in_box"]
    values = t.column(col).to_pylist()
    values[0] = 2**40
    pq.write_table(t.set_column(t.schema.get_field_index(col), col, pa.array(values, pa.int64())), box)
    _infer(root, tmp_path / "out", "--classes", "all")
    (rows,) = H.rows_by_frame(tmp_path / "out").values()
    assert rows[0]["num_lidar_points_in_box"] is None and rows[1]["num_lidar_points_in_box"] == values[1]
    assert rows[0]["status"] != "error"  # the box itself is fine: it is audited
    (warning,) = H.errors_of(tmp_path / "out")
    assert warning["level"] == "warning" and warning["file"] == str(box)
    assert warning["message"] == f"{box} row 0: {col} = {2**40} is outside [0, 2147483647]; stored as null"


# --------------------------------------------------------------------------- 3. file names that are not UTF-8


def test_non_utf8_frame_file_names_are_audited_with_a_warning(kitti, tmp_path):
    base = os.fsencode(kitti / "training")
    for sub, ext in ((b"label_2", b".txt"), (b"calib", b".txt"), (b"velodyne", b".bin")):
        shutil.copyfile(os.path.join(base, sub, b"000001" + ext), os.path.join(base, sub, b"\xff1" + ext))
    _infer(kitti, tmp_path / "out")  # was: UnicodeEncodeError "surrogates not allowed", exit 3
    rows = H.rows_by_frame(tmp_path / "out")
    assert [r["status"] for r in rows["\\xff1"]] == ["ok"] * 3  # the bytes shown escaped
    (warning,) = H.errors_of(tmp_path / "out")
    assert warning["unit"] == "\\xff1" and "not valid UTF-8" in warning["message"]


def test_a_non_utf8_calib_name_is_a_missing_calib_of_that_frame(kitti, tmp_path):
    calib = os.fsencode(kitti / "training" / "calib")
    os.rename(os.path.join(calib, b"000001.txt"), os.path.join(calib, b"\xff1.txt"))
    _infer(kitti, tmp_path / "out")
    (err,) = H.errors_of(tmp_path / "out")
    assert err["unit"] == "000001" and err["file"].endswith("calib/000001.txt") and "not found" in err["message"]


# --------------------------------------------------------------------------- 4. Rich markup in user strings


def test_markup_in_class_names_and_paths_prints_as_written(kitti, tmp_path):
    _set_token(kitti / "training/label_2/000000.txt", 0, 0, "[/]")
    out = tmp_path / "[bold]out"
    run = H.run_cli("infer", kitti, "-o", out, "--workers", "1", "--classes", "all")  # not quiet: the summary table
    H.check_output(run, allowed=(0,))  # was: MarkupError after the results were written
    assert "[/]" in run.stderr and "[bold]out" in run.stderr
    for cmd in (["rank", out], ["rank", out, "--class", "[/]"], ["check", out]):
        r = H.run_cli(*cmd)
        H.check_output(r)
        assert "[/]" in r.stdout
    sim = H.run_cli("simulate", tmp_path / "[red]sim", "--frames", "1", "-q")
    H.check_output(sim, allowed=(0,))
    assert "[red]sim" in sim.stderr


# --------------------------------------------------------------------------- 5. output paths that cannot be used


def test_unusable_output_paths_are_one_line_exit_2(kitti, tmp_path):
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    (tmp_path / "FILE").write_text("x")
    cases = {
        str(tmp_path / "dangling"): "is a symbolic link to",
        str(tmp_path / "FILE" / "sub"): "FILE is not a folder",
        str(tmp_path / ("x" * 300)): "File name too long",
        "": "-o/--output is empty",
    }
    for output, message in cases.items():
        run = (
            _infer(kitti, Path(output) if output else "", allowed=(2,))
            if output
            else H.run_cli("infer", kitti, "-o", "", *INFER)
        )
        H.check_output(run, allowed=(2,))
        assert message in run.stderr, run.stderr
        if output:
            assert output[:60] in run.stderr
    assert not (Path.cwd() / R.MANIFEST_NAME).exists()  # -o "" wrote nothing into the current folder


# --------------------------------------------------------------------------- 6. damaged results folders


def _manifest(out: Path, how: str) -> None:
    p = out / R.MANIFEST_NAME
    p.unlink()
    if how == "dir":
        p.mkdir()
    elif how == "bytes":
        p.write_bytes(b"\xff\xfe{")
    else:
        p.write_text(how)


DAMAGE = {
    "manifest a folder": (lambda o: _manifest(o, "dir"), R.MANIFEST_NAME),
    "manifest [1, 2]": (lambda o: _manifest(o, "[1, 2]"), R.MANIFEST_NAME),
    'manifest "hello"': (lambda o: _manifest(o, '"hello"'), R.MANIFEST_NAME),
    "manifest not UTF-8": (lambda o: _manifest(o, "bytes"), R.MANIFEST_NAME),
    "lock a folder": (lambda o: (o / R.LOCK_NAME).mkdir(), R.LOCK_NAME),
    "objects a file": (
        lambda o: (shutil.rmtree(o / R.OBJECTS_DIR), (o / R.OBJECTS_DIR).write_text("x")),
        R.OBJECTS_DIR,
    ),
    "errors.parquet a folder": (lambda o: ((o / R.ERRORS_FILE).unlink(), (o / R.ERRORS_FILE).mkdir()), R.ERRORS_FILE),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_a_damaged_results_folder_is_named_with_the_fix(kitti, tmp_path, damage):
    out = tmp_path / "out"
    _infer(kitti, out)
    rows = H.rows_by_frame(out)
    apply, name = DAMAGE[damage]
    apply(out)
    run = _infer(kitti, out, allowed=(2,))  # was: exit 3 (IsADirectoryError, AttributeError, UnicodeDecodeError …)
    assert str(out / name) in run.stderr and "--overwrite" in run.stderr
    _infer(kitti, out, "--overwrite")
    assert H.rows_by_frame(out) == rows


def test_a_truncated_errors_part_is_recomputed(kitti, tmp_path):
    (kitti / "training/velodyne/000001.bin").write_bytes(b"\0" * 10)
    out = tmp_path / "out"
    _infer(kitti, out)
    (part,) = (out / R.ERRORS_DIR).glob("part-*.parquet")
    part.write_bytes(part.read_bytes()[:20])  # was: ArrowInvalid at the end of the run, exit 3
    _infer(kitti, out)
    (err,) = H.errors_of(out)
    assert err["unit"] == "000001" and R.is_whole_parquet(part)


# --------------------------------------------------------------------------- 7. text inputs that are not UTF-8


def test_non_utf8_split_list_and_config_name_the_file(kitti, tmp_path):
    (kitti / "ImageSets" / "val.txt").write_bytes(b"000000\n\xff\xfe000001\n")
    run = _infer(kitti, tmp_path / "out", "--split", "val", allowed=(2,))
    assert f"{kitti / 'ImageSets' / 'val.txt'}:2: split list is not UTF-8 text" in run.stderr
    run = _infer(
        kitti, tmp_path / "out", "--split", "x" * 300, allowed=(2,)
    )  # fuzz seed 16: exit 3 (File name too long)
    assert "cannot list the dataset (File name too long)" in run.stderr
    cfg = tmp_path / "model.toml"
    cfg.write_bytes(b"[model]\nsigma = 0.2 # \xe9\n")
    run = _infer(kitti, tmp_path / "out", "--config", cfg, allowed=(2,))
    assert f"{cfg}: config file is not UTF-8 text" in run.stderr


# --------------------------------------------------------------------------- also found


def test_bom_and_crlf_labels_lose_no_row(kitti, tmp_path):
    label = kitti / "training/label_2/000000.txt"
    label.write_bytes(b"\xef\xbb\xbf" + label.read_bytes().replace(b"\n", b"\r\n"))
    _infer(kitti, tmp_path / "out")
    rows = H.rows_by_frame(tmp_path / "out")["000000"]
    assert [r["class_name"] for r in rows] == ["Car"] * 3  # was: '\ufeffCar', neither audited nor reported


def test_resume_retries_a_fixed_frame_and_leaves_other_shards_alone(tmp_path):
    data = H.write_kitti(tmp_path / "data", [f"{i:06d}" for i in range(40)])  # 40 frames: several shards
    label = data / "training/label_2/000007.txt"
    good = label.read_text()
    _set_token(label, 0, 5, "abc")
    out = tmp_path / "out"
    _infer(data, out)
    assert "000007" not in H.rows_by_frame(out)
    (err,) = H.errors_of(out)
    assert err["unit"] == "000007"
    shards = {p.name: p.stat().st_mtime_ns for p in (out / R.OBJECTS_DIR).glob("*.parquet")}
    label.write_text(good)  # the user fixes the label
    run = H.run_cli("infer", data, "-o", out, "--workers", "1")
    H.check_output(run, allowed=(0,))
    assert "1 shard of an earlier run re-tried" in " ".join(run.stderr.split())
    assert [r["status"] for r in H.rows_by_frame(out)["000007"]] == ["ok"] * 3
    assert H.errors_of(out) == []  # the stale error is gone
    after = {p.name: p.stat().st_mtime_ns for p in (out / R.OBJECTS_DIR).glob("*.parquet")}
    changed = [name for name in shards if after[name] != shards[name]]
    assert len(changed) == 1 and set(after) == set(shards)  # every other shard untouched


def test_waymo_v2_errors_name_the_damaged_component(tmp_path):
    from labelaudit.sim.waymo_writer import write_waymo_v2

    segment = _waymo_segment()
    for component in ("lidar", "lidar_pose", "lidar_calibration", "vehicle_pose"):
        root = write_waymo_v2(segment, tmp_path / component)
        damaged = root / component / "seg.parquet"
        damaged.write_bytes(damaged.read_bytes()[:200])
        _infer(root, tmp_path / f"{component}-out", "--classes", "all", allowed=(0, 2))  # 2: no frame was left to audit
        errors = H.errors_of(tmp_path / f"{component}-out")
        assert errors and all(e["file"] == str(damaged) for e in errors), errors  # was: lidar_box/<seg>.parquet or null


def test_a_forged_tfrecord_length_names_the_file_and_record(tmp_path):
    import struct

    from labelaudit.datasets.waymo_v1 import masked_crc32c
    from labelaudit.sim.waymo_writer import write_waymo_v1

    path = write_waymo_v1(_waymo_segment(), tmp_path / "v1" / "seg.tfrecord")
    raw = path.read_bytes()
    length = struct.pack("<Q", 2**60)
    path.write_bytes(length + struct.pack("<I", masked_crc32c(length)) + raw[12:])
    _infer(tmp_path / "v1", tmp_path / "out", allowed=(2,))  # nothing else to audit: exit 2 says so
    (err,) = H.errors_of(tmp_path / "out")
    assert err["file"] == str(path)  # was: "MemoryError while reading <file>: " and no file
    assert "record 0 at byte 0 declares 1152921504606846976 payload bytes" in err["message"]


def test_strict_names_the_file_on_one_line(kitti, tmp_path):
    label = kitti / "training/label_2/000000.txt"
    _set_token(label, 1, 10, "1e300")  # the width: the core raised a two-line eigenvalue message
    run = _infer(kitti, tmp_path / "out", "--strict", allowed=(2,))
    assert f"--strict: frame 000000 object 1 failed: {label}:2: " in run.stderr and "length = 1e+300" in run.stderr
    (kitti / "training/velodyne/000001.bin").write_bytes(b"\0" * 10)
    _set_token(label, 1, 10, "4.0")
    run = _infer(kitti, tmp_path / "out2", "--strict", allowed=(2,))
    assert "--strict: unit 000001 failed: " in run.stderr and "velodyne/000001.bin" in run.stderr


@pytest.mark.parametrize(
    "args",
    [["--workers", "abc"], ["--limit", "x"], ["--model", "4d"], ["--dataset-format", "foo"], ["--nope"], ["--workers"]],
)
def test_usage_errors_are_one_line(kitti, tmp_path, args):
    run = H.run_cli("infer", kitti, "-o", tmp_path / "out", *args)
    H.check_output(run, allowed=(2,))  # was: Typer's multi-line box
    assert "see `labelaudit infer --help`" in run.stderr or args == ["--workers"]
    for cmd in (["rank", tmp_path, "--format", "xml"], ["rank", tmp_path, "--top", "x"], ["check"], ["nope"]):
        H.check_output(H.run_cli(*cmd), allowed=(2,))


@pytest.mark.parametrize("sigma", ["inf", "1e308"])
def test_absurd_model_parameters_are_refused(kitti, tmp_path, sigma):
    cfg = tmp_path / "model.toml"
    cfg.write_text(f"[model]\nsigma = {sigma}\n")
    run = _infer(kitti, tmp_path / "out", "--config", cfg, allowed=(2,))  # was: accepted, exit 0
    assert "[model] sigma must be in [0.0001, 10]" in run.stderr


def test_a_label_file_with_thousands_of_boxes_goes_through_the_linear_crop(kitti, tmp_path, monkeypatch):
    from labelaudit import constants as C
    from labelaudit.infer import crop

    label = kitti / "training/label_2/000000.txt"
    lines = label.read_text().split("\n")[:3]
    label.write_text("\n".join(lines * 700) + "\n")  # 2100 boxes: Open3D per box would test N points each

    def no_per_box_open3d(*args, **kwargs):
        raise AssertionError("the per-box Open3D crop ran for a frame of many boxes")

    monkeypatch.setattr(crop, "crop_frame", no_per_box_open3d)
    from labelaudit.infer import rows

    monkeypatch.setattr(rows, "audit_object", H.quick_audit)
    _infer(kitti, tmp_path / "out")
    got = H.rows_by_frame(tmp_path / "out")["000000"]
    assert len(got) == 2100 >= C.CROP_GRID_MIN_BOXES
    assert [r["num_points"] for r in got[:3]] == [r["num_points"] for r in got[3:6]]  # same boxes, same crops


def test_show_draws_a_frame_whose_label_was_refused(kitti, tmp_path):
    _set_token(kitti / "training/label_2/000000.txt", 1, 11, "nan")
    _infer(kitti, tmp_path / "out")
    run = H.run_cli("show", tmp_path / "out", "000000", "-o", tmp_path / "frame.png")
    H.check_output(run, allowed=(0,))  # was: ValueError "box has non-finite values" (exit 3)
    assert (tmp_path / "frame.png").stat().st_size > 0
    run = H.run_cli("show", tmp_path / "out", "000000", "1", "-o", tmp_path / "object.png")
    H.check_output(run, allowed=(2,))
    assert "status error" in run.stderr and "x = nan" in run.stderr

"""Seeded fuzzing of every input kind through the real command line.

Each test takes one input kind — KITTI labels, velodyne bins, calib files, file names; Waymo v1
records (bytes) and Frame fields; Waymo v2 columns and component files; results-folder states;
command-line values — applies a few hundred seeded mutations to tiny datasets and runs
``labelaudit infer`` (in-process). Every run must keep the contract of docs/datasets.md § Bad input:

- never exit 3, never a traceback or a Python warning without ``--debug``, one line on exit 2;
- the good unit next to the damaged ones keeps exactly its rows;
- a damaged unit is never silently lost: it has rows, or an error row naming its file (every row
  of the errors table has a ``file``; a ``line`` appears in its message), and its objects are
  numbered without gaps; an object with status ``error`` names its file in its message;
- ``--strict`` (on a sample of the cases) exits 2 with one line naming a file when the case failed
  anything, else 0.

Mutations are drawn from ``random.Random(f"{SEED}:{kind}:{case}")``: a failure message prints the
kind, the case number and what was done, and reruns with ``LABELAUDIT_FUZZ_SEED``. Scale a
campaign with ``LABELAUDIT_FUZZ_SCALE=10``; ``LABELAUDIT_FUZZ_CORE=real`` runs the real model on
every case (by default the first batch of each kind does, the rest use a fast stand-in with the
same input checks, :func:`_hostile.quick_audit`). Many cases share one run (a batch of units next
to one good unit); the shard count of those runs is kept small (``TARGET_CHUNKS``) for speed.
"""

from __future__ import annotations

import json
import math
import os
import random
import shutil
import struct
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import _hostile as H
from labelaudit import results as R
from labelaudit.results import safe_text

SEED = int(os.environ.get("LABELAUDIT_FUZZ_SEED", "15"))
SCALE = float(os.environ.get("LABELAUDIT_FUZZ_SCALE", "1"))
REAL_CORE = os.environ.get("LABELAUDIT_FUZZ_CORE", "") == "real"
STRICT_SAMPLE = 0.1  # share of the cases also run with --strict on their own
REAL_CASES = 6  # the first cases of every kind run the real model (one batch of their own)
FOUND: dict[str, int] = {}  # kind → cases run (printed at the end of the module)


def cases(n: int) -> int:
    return max(1, round(n * SCALE))


def batches(n: int, size: int) -> list[tuple[int, int]]:
    """(first, last) case ranges: the REAL_CASES first (real model), then batches of ``size``."""
    edges = [0, min(n, REAL_CASES)] + list(range(REAL_CASES + size, n, size)) + [n]
    return [(a, b) for a, b in zip(edges, edges[1:]) if b > a]


def rng_for(kind: str, case: int) -> random.Random:
    return random.Random(f"{SEED}:{kind}:{case}")


@dataclass
class Case:
    kind: str
    number: int
    what: list[str] = field(default_factory=list)
    unit: str = ""  # the unit key the reader will list (a frame id, a segment file)
    prefix: str = ""  # frame ids of this unit start with it (Waymo)

    def __str__(self) -> str:
        return f"[{self.kind} case {self.number}, LABELAUDIT_FUZZ_SEED={SEED}] {'; '.join(self.what)}"


@pytest.fixture(autouse=True)
def _few_shards_and_quick_core(monkeypatch, request):
    from labelaudit import constants as C
    from labelaudit.infer import rows

    monkeypatch.setattr(C, "TARGET_CHUNKS", 4)
    request.node.quick = lambda on: monkeypatch.setattr(
        rows, "audit_object", H.quick_audit if on and not REAL_CORE else _REAL_AUDIT
    )


from labelaudit.infer.rows import audit_object as _REAL_AUDIT  # noqa: E402


def teardown_module() -> None:
    print("\nfuzz cases per kind:", json.dumps(FOUND), "total", sum(FOUND.values()))


# --------------------------------------------------------------------------- values that break parsers

NUMBERS = [
    "nan",
    "-nan",
    "NaN",
    "inf",
    "-inf",
    "Infinity",
    "1e300",
    "-1e300",
    "1e-300",
    "0",
    "-0",
    "-1",
    "0.0",
    "3000000000",
    "2147483648",
    "-2147483649",
    "1e10",
    "9" * 400,
    "1_000",
    "0x10",
    "1e",
    ".",
    "+",
    "",
    "abc",
    "[/]",
    "\ufeff1",
    "١",
    "1.5",
    "2",
    "3",
    "4.2",
    "1e3",
    "1e4",
    "1e5",
    "-1e5",
    "7",
]
WORDS = [
    "[/]",
    "[bold]x",
    "\\",
    "Car\x00",
    "Ca r",
    "ДЖ",
    "\ufeffCar",
    "\u200bCar",
    "Car\r",
    "",
    "DontCare",
    "Van",
    "x" * 300,
    "%s%n",
    "Car;rm",
]


def pick(rng: random.Random, pool: list[str]) -> str:
    return rng.choice(pool)


def mutate_text(rng: random.Random, text: str, what: list[str], line_words: bool = True) -> bytes:
    """1–3 random edits of a whitespace-separated text file; returns the bytes to write."""
    lines = text.split("\n")
    data: bytes | None = None
    for _ in range(rng.randint(1, 3)):
        op = rng.randrange(14)
        i = rng.randrange(max(1, len(lines)))
        toks = lines[i].split(" ") if i < len(lines) else []
        if op <= 3 and toks:  # a token replaced
            j = rng.randrange(len(toks))
            v = pick(rng, NUMBERS if (j or not line_words) and rng.random() < 0.85 else WORDS)
            what.append(f"line {i + 1} token {j} := {v[:20]!r}")
            toks[j] = v
            lines[i] = " ".join(toks)
        elif op == 4 and toks:
            j = rng.randrange(len(toks))
            what.append(f"line {i + 1} token {j} deleted")
            del toks[j]
            lines[i] = " ".join(toks)
        elif op == 5:
            what.append(f"line {i + 1} gets an extra token")
            lines[i] = lines[i] + " " + pick(rng, NUMBERS)
        elif op == 6:
            k = rng.choice([2, 10, 70, 300])
            what.append(f"line {i + 1} repeated ×{k}")
            lines[i : i + 1] = [lines[i]] * k
        elif op == 7:
            what.append(f"line {i + 1} deleted")
            lines[i : i + 1] = []
        elif op == 8:
            junk = rng.choice(["", "   ", "\t", "\x0c", "\x0b", "\x00", "\x1c", "#comment", "\u2028", "\x85"])
            what.append(f"junk line {junk!r} before line {i + 1}")
            lines.insert(i, junk)
        elif op == 9:
            what.append("CRLF line ends")
            lines = [l + "\r" for l in lines]
        elif op == 10:
            what.append("byte-order mark")
            lines[0] = "\ufeff" + lines[0] if lines else "\ufeff"
        elif op == 11:
            what.append("old-Mac CR line ends")
            lines = ["\r".join(lines)]
        elif op == 12:
            cut = rng.randrange(len(text) + 1)
            what.append(f"truncated at char {cut}")
            lines = text[:cut].split("\n")
        else:
            what.append("a non-UTF-8 byte")
            data = "\n".join(lines).encode() + b" \xff\xfe\n"
    return data if data is not None else "\n".join(lines).encode("utf-8", "surrogateescape")


# --------------------------------------------------------------------------- KITTI: one run per batch


GOOD = "000000"


def kitti_template(tmp: Path) -> Path:
    return H.write_kitti(tmp / "template", [GOOD, "tmpl"])


def baseline_rows(tmp: Path, template: Path, quick: Callable[[bool], None], real: bool) -> list[dict]:
    data = tmp / f"baseline-{real}"
    if not data.exists():
        shutil.copytree(template, data)
        for sub, ext in (("label_2", "txt"), ("calib", "txt"), ("velodyne", "bin")):
            (data / "training" / sub / f"tmpl.{ext}").unlink()
    quick(not real)
    out = tmp / f"baseline-out-{real}"
    shutil.rmtree(out, ignore_errors=True)
    H.check_output(H.run_cli("infer", data, "-o", out, "--workers", "1", "-q", "--classes", "all"), allowed=(0,))
    return H.rows_by_frame(out)[GOOD]


def kitti_paths(root: Path, fid: str) -> dict[str, Path]:
    base = root / "training"
    return {
        "label": base / "label_2" / f"{fid}.txt",
        "calib": base / "calib" / f"{fid}.txt",
        "velo": base / "velodyne" / f"{fid}.bin",
    }


def copy_case_frame(template: Path, root: Path, fid: str) -> dict[str, Path]:
    src, dst = kitti_paths(template, "tmpl"), kitti_paths(root, fid)
    for k in src:
        shutil.copyfile(src[k], dst[k])
    return dst


def mutate_label(rng: random.Random, case: Case, paths: dict[str, Path]) -> None:
    paths["label"].write_bytes(mutate_text(rng, paths["label"].read_text(), case.what))


def mutate_calib(rng: random.Random, case: Case, paths: dict[str, Path]) -> None:
    p = paths["calib"]
    op = rng.randrange(10)
    if op == 0:
        what = rng.choice(["empty", "folder", "missing"])
        case.what.append(f"calib {what}")
        p.unlink()
        if what == "empty":
            p.write_bytes(b"")
        elif what == "folder":
            p.mkdir()
        return
    if op == 1:  # a matrix that is not a rotation, or singular
        key = rng.choice(["R0_rect", "Tr_velo_to_cam"])
        scale = rng.choice(["0", "1e-300", "1e300", "2", "-1"])
        case.what.append(f"{key} scaled by {scale}")
        lines = []
        for line in p.read_text().split("\n"):
            if line.startswith(key + ":"):
                line = key + ": " + " ".join(repr(float(v) * float(scale)) for v in line.split()[1:])
            lines.append(line)
        p.write_text("\n".join(lines))
        return
    if op == 2:
        case.what.append("translation of Tr_velo_to_cam := 1e9")
        lines = [
            l if not l.startswith("Tr_velo_to_cam:") else " ".join(l.split()[:4] + ["1e9"] + l.split()[5:])
            for l in p.read_text().split("\n")
        ]
        p.write_text("\n".join(lines))
        return
    if op == 3:
        case.what.append("a key spelled differently / duplicated / unknown")
        p.write_text(
            p.read_text().replace("R0_rect", rng.choice(["R_rect", "R0_rect_x", "r0_rect"]))
            + rng.choice(["", "P2: 1 2 3\n", "Foo: bar\n"])
        )
        return
    p.write_bytes(mutate_text(rng, p.read_text(), case.what, line_words=False))


def mutate_velodyne(rng: random.Random, case: Case, paths: dict[str, Path]) -> None:
    p = paths["velo"]
    raw = bytearray(p.read_bytes())
    op = rng.randrange(9)
    if op == 0:
        cut = rng.randrange(len(raw))
        case.what.append(f"bin truncated to {cut} bytes")
        raw = raw[:cut]
    elif op == 1:
        case.what.append("bin empty")
        raw = bytearray()
    elif op == 2:
        k = rng.randint(1, 40)
        case.what.append(f"{k} random bytes flipped")
        for _ in range(k):
            raw[rng.randrange(len(raw))] = rng.randrange(256)
    elif op == 3:
        pts = np.frombuffer(bytes(raw), "<f4").reshape(-1, 4).copy()
        v = rng.choice([np.nan, np.inf, -np.inf, 3e38, -3e38, 1e-45, 0.0])
        rows = [rng.randrange(len(pts)) for _ in range(rng.randint(1, len(pts)))]
        col = rng.randrange(4)
        case.what.append(f"{len(rows)} points: column {col} := {v}")
        pts[rows, col] = v
        raw = bytearray(pts.tobytes())
    elif op == 4:
        case.what.append("bin is a folder")
        p.unlink()
        p.mkdir()
        return
    elif op == 5:
        case.what.append("bin missing")
        p.unlink()
        return
    elif op == 6:
        case.what.append("bin ×50 (many duplicate points)")
        raw = raw * 50
    elif op == 7:
        extra = rng.choice([4, 8, 12, 17])
        case.what.append(f"{extra} garbage bytes appended")
        raw += bytes(rng.randrange(256) for _ in range(extra))
    else:
        case.what.append("all points NaN")
        raw = bytearray(np.full(len(raw) // 4, np.nan, "<f4").tobytes())
    p.write_bytes(bytes(raw))


NAMES = [
    b"\xff1",
    b"a b",
    b"[bold]x",
    b"[red]x[",
    b"-rf",
    b"x" * 200,
    "é".encode(),
    "e\u0301".encode(),
    b".hidden",
    b"\xc3\x28",
    b"000000 ",
    b"tab\tname",
    b"%d",
]


def mutate_names(rng: random.Random, case: Case, paths: dict[str, Path]) -> str:
    """Renames: the frame id the reader will list (or "" when no label file is left)."""
    new = rng.choice(NAMES) + f"-{case.number}".encode()  # unique within a batch
    which = rng.choice(["all", "label", "calib", "velo", "extra"])
    case.what.append(f"{which} renamed to {new!r}")
    if which == "extra":  # stray entries in label_2: a backup, a folder that looks like a label
        label_dir = paths["label"].parent
        kind = rng.choice(["bak", "dir", "readme"])
        case.what[-1] = f"stray {kind} in label_2"
        if kind == "bak":
            shutil.copyfile(paths["label"], label_dir / (paths["label"].name + ".bak"))
        elif kind == "readme":
            (label_dir / "README.md").write_text("labels")
        else:
            (label_dir / f"{paths['label'].stem}x.txt").mkdir()
            return paths["label"].stem + "x|" + paths["label"].stem
        return paths["label"].stem
    targets = ["label", "calib", "velo"] if which == "all" else [which]
    for k in targets:
        old = paths[k]
        os.rename(os.fsencode(old), os.path.join(os.fsencode(old.parent), new + os.fsencode(old.suffix)))
    if "label" in targets:
        return os.fsdecode(new)
    return paths["label"].stem


def run_kitti_kind(tmp: Path, request, kind: str, n: int, mutate, batch: int = 40) -> None:
    template = kitti_template(tmp)
    quick = request.node.quick
    base_quick = baseline_rows(tmp, template, quick, real=False)
    base_real = baseline_rows(tmp, template, quick, real=True)
    all_cases = list(range(cases(n)))
    for first, last in batches(len(all_cases), batch):
        real = first == 0
        quick(not real)
        root = tmp / f"{kind}-{first}"
        H.write_kitti(root, [GOOD])
        shutil.copyfile(kitti_paths(template, GOOD)["label"], kitti_paths(root, GOOD)["label"])
        batch_cases: list[Case] = []
        for c in all_cases[first:last]:
            case = Case(kind, c)
            fid = f"c{c:04d}"
            paths = copy_case_frame(template, root, fid)
            rng = rng_for(kind, c)
            unit = mutate(rng, case, paths)
            case.unit = fid if unit is None else unit
            batch_cases.append(case)
        check_kitti_batch(root, tmp / f"{kind}-{first}-out", batch_cases, base_real if real else base_quick)
        for case in batch_cases:
            if rng_for(kind + "/strict", case.number).random() < STRICT_SAMPLE:
                check_strict_alone(root, tmp / f"{kind}-strict-{case.number}", case, template, kind, mutate)
    FOUND[kind] = len(all_cases)


def check_kitti_batch(root: Path, out: Path, batch_cases: list[Case], good_rows: list[dict]) -> None:
    run = H.run_cli("infer", root, "-o", out, "--workers", "1", "-q", "--classes", "all")
    try:
        H.check_output(run, allowed=(0,))
    except AssertionError:  # name the case that breaks the run
        for case in batch_cases:
            alone = root.parent / f"{root.name}-alone-{case.number}"
            _only(root, alone, case.unit)
            r = H.run_cli("infer", alone, "-o", alone / "out", "--workers", "1", "-q", "--classes", "all")
            try:
                H.check_output(r, allowed=(0,))
            except AssertionError as inner:
                raise AssertionError(f"{case}\n{inner}") from None
        raise
    rows = H.rows_by_frame(out)
    errors = H.errors_of(out)
    assert rows[GOOD] == good_rows, "the good frame next to the damaged ones changed its rows"
    check_error_table(errors, root)
    for case in batch_cases:
        for unit in case.unit.split("|"):
            if not unit:
                continue
            shown = safe_text(unit)
            unit_errors = [e for e in errors if e["unit"] == shown and e["level"] == "error"]
            frame_rows = rows.get(shown, [])
            if not unit_errors:  # read: one row per non-DontCare line, none lost
                expected = expected_labels(kitti_paths(root, unit)["label"])
                assert len(frame_rows) == expected, (
                    f"{case}: frame {shown!r}: {len(frame_rows)} rows for {expected} labels (silently lost?)"
                )
            check_object_rows(case, frame_rows, root)


def expected_labels(label: Path) -> int | None:
    """Non-DontCare label lines of a file, counted independently of the reader (None: not UTF-8)."""
    try:
        text = label.read_bytes().decode("utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    lines = [l.split() for l in text.removeprefix("\ufeff").split("\n")]
    return sum(1 for t in lines if t and t[0] != "DontCare")


def _only(root: Path, alone: Path, unit: str) -> None:
    """A copy of ``root`` with the good frame and the units of one case only."""
    shutil.rmtree(alone, ignore_errors=True)
    shutil.copytree(root, alone)
    keep = {os.fsencode(GOOD)} | {os.fsencode(u) for u in unit.split("|") if u}
    for sub in ("label_2", "calib", "velodyne"):
        d = os.fsencode(alone / "training" / sub)
        for name in os.listdir(d):
            stem = os.path.splitext(name)[0]
            if stem not in keep and name.startswith(b"c"):
                p = os.path.join(d, name)
                shutil.rmtree(p) if os.path.isdir(p) else os.unlink(p)


def check_error_table(errors: list[dict], root: Path) -> None:
    for e in errors:
        assert e["file"], f"error without a file: {e}"
        assert str(root) in e["file"] or e["file"].startswith(safe_text(str(root))), (
            f"error names a file outside the dataset: {e}"
        )
        if e["line"] is not None:
            assert f":{e['line']}:" in e["message"], f"line {e['line']} not in the message: {e}"
        assert "\n" not in e["message"], f"multi-line error message: {e}"


def check_object_rows(case: Case, rows: list[dict], root: Path) -> None:
    assert [r["object_index"] for r in rows] == list(range(len(rows))), (
        f"{case}: objects numbered with a gap (one dropped?)"
    )
    for r in rows:
        assert r["status"] in R.STATUSES
        if r["status"] == "error":
            assert r["message"] and safe_text(str(root)) in r["message"], (
                f"{case}: an object error that names no file: {r['message']!r}"
            )
            assert "\n" not in r["message"]


def check_strict_alone(root: Path, work: Path, case: Case, template: Path, kind: str, mutate) -> None:
    """The case on its own with --strict: exit 2 and one line naming a file if it failed anything, else 0."""
    alone = work / "data"
    _only(root, alone, case.unit)
    plain = H.run_cli("infer", alone, "-o", work / "plain", "--workers", "1", "-q", "--classes", "all")
    H.check_output(plain, allowed=(0,))
    failed = any(e["level"] == "error" for e in H.errors_of(work / "plain")) or any(
        r["status"] == "error" for rows in H.rows_by_frame(work / "plain").values() for r in rows
    )
    strict = H.run_cli("infer", alone, "-o", work / "strict", "--workers", "1", "-q", "--classes", "all", "--strict")
    H.check_output(strict, allowed=(2,) if failed else (0,))
    if failed:
        assert "--strict" in strict.stderr and safe_text(str(alone)) in strict.stderr, (
            f"{case}: --strict names no file: {strict.stderr}"
        )


def test_fuzz_kitti_labels(tmp_path, request):
    run_kitti_kind(tmp_path, request, "kitti-labels", 240, mutate_label)


def test_fuzz_kitti_bins(tmp_path, request):
    run_kitti_kind(tmp_path, request, "kitti-bins", 150, mutate_velodyne)


def test_fuzz_kitti_calib(tmp_path, request):
    run_kitti_kind(tmp_path, request, "kitti-calib", 150, mutate_calib)


def test_fuzz_kitti_file_names(tmp_path, request):
    run_kitti_kind(tmp_path, request, "kitti-names", 120, mutate_names)


# --------------------------------------------------------------------------- Waymo: segments next to a good one

FUZZ_CONFIG = "[dataset]\nclasses = ['all']\nmin_length = 0.0\n"
FLOATS = [math.nan, math.inf, -math.inf, 1e300, -1e300, 1e-300, 0.0, -1.0, 5e3, 2e4, 1e38, -0.0]
INTS = [-1, 0, 7, 255, 2**31 - 1, -(2**31), 2**40, 2**63 - 1]


@pytest.fixture(scope="module")
def waymo_segment():
    """Two frames of five lidars at a quarter of the simulator's "small" resolution (decoding
    costs per pixel), three vehicles and at most one pedestrian."""
    from labelaudit.sim import waymo_writer as ww
    from labelaudit.sim.scene import SceneSpec

    ww.SIZES["fuzz"] = {1: (16, 180), 2: (12, 30), 3: (12, 30), 4: (12, 30), 5: (12, 30)}
    try:
        return ww.simulate_waymo_segment(
            seed=1,
            frames=2,
            size="fuzz",
            name="tmpl",
            scene_spec=SceneSpec(num_vehicles=(3, 3), num_vru=(0, 1), distance=(6.0, 20.0)),
        )
    finally:
        del ww.SIZES["fuzz"]


def _fuzz_config(tmp: Path) -> Path:
    cfg = tmp / "fuzz.toml"
    cfg.write_text(FUZZ_CONFIG)
    return cfg


def run_waymo_batch(
    tmp: Path,
    request,
    kind: str,
    fmt: str,
    root: Path,
    good_rows: dict,
    batch_cases: list[Case],
    expected: dict[str, int | None],
    damaged: dict[str, str],
    real: bool,
) -> None:
    request.node.quick(not real)
    out = tmp / f"{root.name}-out"
    args = ("--workers", "1", "-q", "--dataset-format", fmt, "--config", _fuzz_config(tmp))
    run = H.run_cli("infer", root, "-o", out, *args)
    try:
        H.check_output(run, allowed=(0,))
    except AssertionError:  # name the case that breaks the run
        for case in batch_cases:
            alone = tmp / f"{root.name}-alone-{case.number}"
            for f in root.rglob("*"):
                if f.is_file() and (f.stem == "good" or f.stem == case.prefix):
                    (alone / f.relative_to(root)).parent.mkdir(parents=True, exist_ok=True)
                    shutil.copyfile(f, alone / f.relative_to(root))
            try:
                H.check_output(H.run_cli("infer", alone, "-o", alone / "out", *args), allowed=(0,))
            except AssertionError as inner:
                raise AssertionError(f"{case}\n{inner}") from None
        raise
    rows = H.rows_by_frame(out)
    errors = H.errors_of(out)
    assert {k: v for k, v in rows.items() if k.startswith("good")} == good_rows, "the good segment changed its rows"
    check_error_table(errors, root)
    for case in batch_cases:
        unit_errors = [e for e in errors if e["unit"] == case.unit and e["level"] == "error"]
        unit_rows = [r for fid, rs in rows.items() if fid.startswith(case.prefix + ":") for r in rs]
        if not unit_errors and expected.get(case.unit) is not None:
            assert len(unit_rows) == expected[case.unit], (
                f"{case}: {len(unit_rows)} rows for {expected[case.unit]} labels (silently lost?)"
            )
        for fid in {r["frame_id"] for r in unit_rows}:
            check_object_rows(case, rows[fid], root)
        if case.unit in damaged and unit_errors:
            named = {e["file"] for e in unit_errors}
            assert damaged[case.unit] in named, (
                f"{case}: the damaged file {damaged[case.unit]} is not named; errors name {named}"
            )
    FOUND[kind] = FOUND.get(kind, 0) + len(batch_cases)


def _v1_payloads(segment, tmp: Path) -> list[bytes]:
    from labelaudit.datasets.waymo_v1 import iter_records
    from labelaudit.sim.waymo_writer import write_waymo_v1

    return list(iter_records(write_waymo_v1(segment, tmp / "tmpl.tfrecord")))


def _v1_write(path: Path, payloads: list[bytes]) -> None:
    from labelaudit.datasets.waymo_v1 import encode_record

    path.write_bytes(b"".join(encode_record(p) for p in payloads))


def _renamed(payload: bytes, name: str):
    from labelaudit.datasets import waymo_proto as wp

    msg = wp.Frame.FromString(payload)
    msg.context.name = name
    return msg


def mutate_v1_fields(rng: random.Random, case: Case, msgs: list) -> None:
    for _ in range(rng.randint(1, 3)):
        msg = msgs[rng.randrange(len(msgs))]
        op = rng.randrange(11)
        labels = msg.laser_labels
        if op <= 2 and len(labels):
            lab = labels[rng.randrange(len(labels))]
            f = rng.choice(["center_x", "center_y", "center_z", "length", "width", "height", "heading"])
            v = rng.choice(FLOATS)
            case.what.append(f"label box.{f} := {v}")
            setattr(lab.box, f, v)
        elif op == 3 and len(labels):
            lab = labels[rng.randrange(len(labels))]
            f = rng.choice(
                [
                    "type",
                    "num_lidar_points_in_box",
                    "num_top_lidar_points_in_box",
                    "detection_difficulty_level",
                    "tracking_difficulty_level",
                ]
            )
            v = rng.choice([x for x in INTS if -(2**31) <= x < 2**31])
            case.what.append(f"label {f} := {v}")
            setattr(lab, f, v)
        elif op == 4 and len(labels):
            lab = labels[rng.randrange(len(labels))]
            v = rng.choice(["", "x" * 5000, "[/]", "\u200b", "a\nb"])
            case.what.append(f"label id := {v[:10]!r}")
            lab.id = v
        elif op == 5 and len(labels):
            k = rng.choice([0, 30])
            case.what.append(f"labels ×{k}")
            keep = list(labels)
            del labels[:]
            for _ in range(k):
                labels.extend(keep)
        elif op == 6 and len(msg.lasers):
            laser = msg.lasers[rng.randrange(len(msg.lasers))]
            how = rng.choice(["garbage", "truncated", "zlib of garbage", "empty"])
            case.what.append(f"laser {laser.name} range image: {how}")
            blob = laser.ri_return1.range_image_compressed
            laser.ri_return1.range_image_compressed = {
                "garbage": bytes(rng.randrange(256) for _ in range(50)),
                "truncated": blob[: len(blob) // 2],
                "zlib of garbage": zlib.compress(bytes(rng.randrange(256) for _ in range(64))),
                "empty": b"",
            }[how]
        elif op == 7 and len(msg.context.laser_calibrations):
            cal = msg.context.laser_calibrations[rng.randrange(len(msg.context.laser_calibrations))]
            how = rng.choice(["15 values", "nan", "inclinations count", "huge"])
            case.what.append(f"calibration {cal.name}: {how}")
            n_values = len(cal.extrinsic.transform)
            if how == "15 values" and n_values:
                del cal.extrinsic.transform[-1]
            elif how == "nan" and n_values:
                cal.extrinsic.transform[rng.randrange(n_values)] = math.nan
            elif how == "huge" and n_values > 3:
                cal.extrinsic.transform[3] = 1e300
            else:
                cal.beam_inclinations.append(0.1)
        elif op == 8:
            how = rng.choice(["nan", "short", "none"])
            case.what.append(f"frame pose: {how}")
            if how == "nan" and len(msg.pose.transform):
                msg.pose.transform[0] = math.nan
            elif how == "short":
                del msg.pose.transform[5:]
            else:
                msg.ClearField("pose")
        elif op == 9:
            case.what.append("no lasers")
            del msg.lasers[:]
        else:
            v = rng.choice([-1, 0, 2**63 - 1])
            case.what.append(f"timestamp := {v}")
            msg.timestamp_micros = v


def mutate_v1_records(rng: random.Random, case: Case, records: list[bytes]) -> bytes:
    """Byte-level damage of a TFRecord file (the first 16 payload bytes, the segment name, are kept)."""
    from labelaudit.datasets.waymo_v1 import encode_record, masked_crc32c

    blob = bytearray(b"".join(encode_record(p) for p in records))
    op = rng.randrange(8)
    first = len(encode_record(records[0]))
    if op == 0:
        cut = rng.randrange(len(blob))
        case.what.append(f"file truncated at byte {cut}")
        return bytes(blob[:cut])
    if op == 1:
        k = rng.randint(1, 20)
        case.what.append(f"{k} bytes flipped in the payloads (CRC left stale)")
        for _ in range(k):
            i = rng.randrange(28, len(blob))
            blob[i] ^= 1 << rng.randrange(8)
        return bytes(blob)
    if op == 2:
        payload = bytearray(records[0])
        for _ in range(rng.randint(1, 30)):
            i = rng.randrange(16, len(payload))
            payload[i] = rng.randrange(256)
        case.what.append("record 0 payload scrambled with a valid CRC")
        return encode_record(bytes(payload)) + bytes(blob[first:])
    if op == 3:
        n = rng.choice([0, 1, 2**31, 2**60, 2**64 - 1])
        length = struct.pack("<Q", n)
        case.what.append(f"record 1 length forged to {n} with a valid length CRC")
        return bytes(blob[:first]) + length + struct.pack("<I", masked_crc32c(length)) + bytes(blob[first + 12 :])
    if op == 4:
        case.what.append("an empty record between the others")
        return bytes(blob[:first]) + encode_record(b"") + bytes(blob[first:])
    if op == 5:
        case.what.append("garbage between records")
        return bytes(blob[:first]) + bytes(rng.randrange(256) for _ in range(rng.randint(1, 40))) + bytes(blob[first:])
    if op == 6:
        case.what.append("record 0 ×30")
        return encode_record(records[0]) * 30 + bytes(blob[first:])
    case.what.append("empty file")
    return b""


def _count_labels(payloads: list[bytes]) -> int | None:
    from labelaudit.datasets import waymo_proto as wp

    try:
        return sum(len(wp.Frame.FromString(p).laser_labels) for p in payloads)
    except Exception:
        return None


def run_v1_kind(tmp: Path, request, waymo_segment, kind: str, n: int, batch: int = 25) -> None:
    from labelaudit.datasets.waymo_v1 import iter_records

    template = _v1_payloads(waymo_segment, tmp)
    for b, last in batches(cases(n), batch):
        root = tmp / f"{kind}-{b}"
        root.mkdir()
        _v1_write(root / "good.tfrecord", [_renamed(p, "good").SerializeToString() for p in template])
        batch_cases, expected = [], {}
        for c in range(b, last):
            rng = rng_for(kind, c)
            name = f"c{c:04d}"
            case = Case(kind, c, prefix=name, unit=str(root / f"{name}.tfrecord"))
            msgs = [_renamed(p, name) for p in template]
            if kind == "waymo-v1-fields":
                mutate_v1_fields(rng, case, msgs)
                payloads = [m.SerializeToString() for m in msgs]
                _v1_write(Path(case.unit), payloads)
                expected[case.unit] = _count_labels(payloads)
            else:
                blob = mutate_v1_records(rng, case, [m.SerializeToString() for m in msgs])
                Path(case.unit).write_bytes(blob)
                try:
                    expected[case.unit] = _count_labels(list(iter_records(case.unit)))
                except Exception:
                    expected[case.unit] = None
            batch_cases.append(case)
        good_rows = _good_rows(tmp, request, "waymo-v1", root / "good.tfrecord")[b == 0]
        run_waymo_batch(tmp, request, kind, "waymo-v1", root, good_rows, batch_cases, expected, {}, real=b == 0)


def _good_rows(tmp: Path, request, fmt: str, good: Path) -> dict:
    """Rows of the good segment on its own (quick core; the real-core batch compares to its own run)."""
    cache = getattr(request.node, "good_cache", None)
    if cache is None:
        cache = request.node.good_cache = {}
    key = (fmt, good.name)
    if key not in cache:
        alone = tmp / f"good-{fmt}"
        alone.mkdir(exist_ok=True)
        if fmt == "waymo-v1":
            shutil.copyfile(good, alone / good.name)
        else:
            for comp in good.parent.parent.iterdir():
                (alone / comp.name).mkdir(exist_ok=True)
                shutil.copyfile(comp / good.name, alone / comp.name / good.name)
        out = {}
        for real in (True, False):
            request.node.quick(not real)
            o = tmp / f"good-{fmt}-out-{real}"
            H.check_output(
                H.run_cli(
                    "infer",
                    alone,
                    "-o",
                    o,
                    "--workers",
                    "1",
                    "-q",
                    "--dataset-format",
                    fmt,
                    "--config",
                    _fuzz_config(tmp),
                ),
                allowed=(0,),
            )
            out[real] = H.rows_by_frame(o)
        cache[key] = out
    return cache[key]


def test_fuzz_waymo_v1_records(tmp_path, request, waymo_segment):
    run_v1_kind(tmp_path, request, waymo_segment, "waymo-v1-records", 150)


def test_fuzz_waymo_v1_fields(tmp_path, request, waymo_segment):
    run_v1_kind(tmp_path, request, waymo_segment, "waymo-v1-fields", 180)


def _v2_tables(segment, tmp: Path) -> dict[str, pa.Table]:
    from labelaudit.datasets.waymo_v2 import COMPONENTS
    from labelaudit.sim.waymo_writer import write_waymo_v2

    root = write_waymo_v2(segment, tmp / "v2-template")
    tables = {}
    for c in COMPONENTS:
        path = root / c / "tmpl.parquet"
        t = pq.read_table(path)
        pq.write_table(t, path, row_group_size=max(1, (t.num_rows + 1) // 2))  # two row groups: frames span them
        tables[c] = t
        _TEMPLATE_FILES[id(t)] = path
    return tables


_TEMPLATE_FILES: dict[int, Path] = {}  # id(template table) → its file, hard-linked for unchanged components


def _v2_write(root: Path, name: str, tables: dict[str, pa.Table]) -> dict[str, Path]:
    """The five component files of segment ``name`` (the reader takes the segment from the file
    name); a table that is still the template's is hard-linked, not written again."""
    paths = {}
    for comp, t in tables.items():
        (root / comp).mkdir(parents=True, exist_ok=True)
        paths[comp] = root / comp / f"{name}.parquet"
        if id(t) in _TEMPLATE_FILES:
            os.link(_TEMPLATE_FILES[id(t)], paths[comp])
        else:
            pq.write_table(t, paths[comp], row_group_size=max(1, (t.num_rows + 1) // 2))
    return paths


def _with_values(t: pa.Table, col: str, rows: list[int], value) -> pa.Table:
    i = t.schema.get_field_index(col)
    values = t.column(col).to_pylist()
    for r in rows:
        values[r] = value
    typ = t.schema.field(col).type
    try:
        arr = pa.array(values, typ)
    except (pa.ArrowException, OverflowError, TypeError, ValueError):
        arr = pa.array(values)  # the value does not fit: the column changes type
    return t.set_column(i, pa.field(col, arr.type), arr)


def mutate_v2_columns(rng: random.Random, case: Case, tables: dict[str, pa.Table]) -> None:
    from labelaudit.datasets import waymo_v2 as v2

    for _ in range(rng.randint(1, 3)):
        comp = rng.choice(["lidar_box"] * 4 + ["lidar", "lidar_pose", "lidar_calibration", "vehicle_pose"])
        t = tables[comp]
        names = [c for c in t.schema.names if c != v2.K_SEG]
        if not names or not t.num_rows:
            continue
        col = rng.choice(names)
        rows = sorted({rng.randrange(t.num_rows) for _ in range(rng.randint(1, 3))})
        op = rng.randrange(7)
        typ = t.schema.field(col).type
        if op == 0:
            case.what.append(f"{comp} {col}: rows {rows} := null")
            tables[comp] = _with_values(t, col, rows, None)
        elif op == 1 and (pa.types.is_floating(typ) or pa.types.is_integer(typ)):
            v = rng.choice(FLOATS if pa.types.is_floating(typ) else INTS)
            case.what.append(f"{comp} {col}: rows {rows} := {v}")
            tables[comp] = _with_values(t, col, rows, v)
        elif op == 2:
            case.what.append(f"{comp}: column {col} dropped")
            tables[comp] = t.drop_columns([col])
        elif op == 3:
            case.what.append(f"{comp}: column {col} as strings")
            i = t.schema.get_field_index(col)
            tables[comp] = t.set_column(
                i, col, pa.array([None if v is None else str(v)[:50] for v in t.column(col).to_pylist()], pa.string())
            )
        elif op == 4 and (pa.types.is_list(typ) or pa.types.is_fixed_size_list(typ)):
            how = rng.choice(["shorter", "empty", "nan", "other shape"])
            case.what.append(f"{comp} {col}: rows {rows} list {how}")
            values = t.column(col).to_pylist()
            for r in rows:
                v = values[r]
                if v is None:
                    continue
                values[r] = {
                    "shorter": v[: len(v) // 2],
                    "empty": [],
                    "nan": [math.nan] * len(v),
                    "other shape": [1, 2][: len(v)] + [-1] * max(0, len(v) - 2),
                }[how]
            arr = None
            for target in (typ, pa.list_(typ.value_type), pa.list_(pa.float64()), None):
                try:
                    arr = pa.array(values, target)
                    break
                except (pa.ArrowException, ValueError, TypeError):
                    continue
            if arr is not None:
                tables[comp] = t.set_column(t.schema.get_field_index(col), pa.field(col, arr.type), arr)
        elif op == 5:
            case.what.append(f"{comp}: rows {rows} duplicated ×3")
            dup = t.take(pa.array(rows, pa.int64()))
            tables[comp] = pa.concat_tables([t, dup, dup, dup])
        else:
            case.what.append(f"{comp}: rows {rows} deleted")
            keep = [r for r in range(t.num_rows) if r not in rows]
            tables[comp] = t.take(pa.array(keep, pa.int64()))


def mutate_v2_files(rng: random.Random, case: Case, paths: dict[str, Path]) -> str:
    comp = rng.choice(list(paths))
    p = paths[comp]
    op = rng.randrange(7)
    raw = p.read_bytes()
    p.unlink()  # a hard link to the template: damage a copy
    p.write_bytes(raw)
    if op == 0:
        cut = rng.randrange(len(raw))
        case.what.append(f"{comp} truncated to {cut} bytes")
        p.write_bytes(raw[:cut])
    elif op == 1:
        case.what.append(f"{comp} is garbage")
        p.write_bytes(bytes(rng.randrange(256) for _ in range(rng.randint(0, 3000))))
    elif op == 2:
        case.what.append(f"{comp} deleted")
        p.unlink()
    elif op == 3:
        case.what.append(f"{comp} is a folder")
        p.unlink()
        p.mkdir()
    elif op == 4:
        case.what.append(f"{comp} has no rows")
        pq.write_table(pq.read_table(p).slice(0, 0), p)
    elif op == 5:
        k = rng.randint(1, 30)
        case.what.append(f"{comp}: {k} bytes flipped")
        b = bytearray(raw)
        for _ in range(k):
            b[rng.randrange(len(b))] ^= 1 << rng.randrange(8)
        p.write_bytes(bytes(b))
    else:
        other = rng.choice([c for c in paths if c != comp])
        case.what.append(f"{comp} holds the {other} table")
        shutil.copyfile(paths[other], p)
    return str(p)


def run_v2_kind(tmp: Path, request, waymo_segment, kind: str, n: int, batch: int = 20) -> None:
    from labelaudit.datasets.waymo_v2 import BOX_COLUMNS, K_TS

    template = _v2_tables(waymo_segment, tmp)
    for b, last in batches(cases(n), batch):
        root = tmp / f"{kind}-{b}"
        good = _v2_write(root, "good", template)
        batch_cases, expected, damaged = [], {}, {}
        for c in range(b, last):
            rng = rng_for(kind, c)
            name = f"c{c:04d}"
            case = Case(kind, c, prefix=name, unit=str(root / "lidar_box" / f"{name}.parquet"))
            tables = dict(template)
            if kind == "waymo-v2-columns":
                mutate_v2_columns(rng, case, tables)
                _v2_write(root, name, tables)
                box = tables["lidar_box"]
                col = BOX_COLUMNS["type"]
                ok = (
                    col in box.schema.names
                    and K_TS in box.schema.names
                    and pa.types.is_integer(box.schema.field(col).type)
                )
                expected[case.unit] = box.num_rows - box.column(col).null_count if ok else None
            else:
                damaged[case.unit] = mutate_v2_files(rng, case, _v2_write(root, name, tables))
                expected[case.unit] = template["lidar_box"].num_rows if "lidar_box" not in damaged[case.unit] else None
            batch_cases.append(case)
        good_rows = _good_rows(tmp, request, "waymo-v2", good["lidar_box"])[b == 0]
        run_waymo_batch(tmp, request, kind, "waymo-v2", root, good_rows, batch_cases, expected, damaged, real=b == 0)


def test_fuzz_waymo_v2_columns(tmp_path, request, waymo_segment):
    run_v2_kind(tmp_path, request, waymo_segment, "waymo-v2-columns", 180)


def test_fuzz_waymo_v2_files(tmp_path, request, waymo_segment):
    run_v2_kind(tmp_path, request, waymo_segment, "waymo-v2-files", 120)


# --------------------------------------------------------------------------- results-folder states


def _damage_folder(rng: random.Random, case: Case, out: Path) -> None:
    """1–3 kinds of damage to a finished results folder."""
    shards = sorted((out / "objects").glob("part-*.parquet"))
    parts = sorted((out / "errors").glob("part-*.parquet")) if (out / "errors").is_dir() else []
    for _ in range(rng.randint(1, 3)):
        target = rng.choice(["manifest", "lock", "objects", "shard", "errors", "errors.parquet", "tmp", "foreign"])
        man, lock = out / "manifest.json", out / ".labelaudit.lock"
        if target == "manifest":
            how = rng.choice(
                [
                    "folder",
                    "[1, 2]",
                    '"hello"',
                    "bytes",
                    "{",
                    "",
                    "null",
                    "{}",
                    "other hash",
                    "incomplete",
                    "deleted",
                    "dangling link",
                ]
            )
            case.what.append(f"manifest: {how}")
            if how in ("other hash", "incomplete") and man.is_file():
                try:
                    data = json.loads(man.read_text())
                except ValueError:
                    continue
                if not isinstance(data, dict):
                    continue
                data.update({"param_hash": "0" * 16} if how == "other hash" else {"complete": False})
                man.write_text(json.dumps(data))
                continue
            R._remove(man)
            if how == "folder":
                man.mkdir()
            elif how == "bytes":
                man.write_bytes(b"\xff\xfe{")
            elif how == "dangling link":
                man.symlink_to(out / "nowhere")
            elif how != "deleted":
                man.write_text(how)
        elif target == "lock":
            how = rng.choice(
                ["folder", "garbage", "-1", "99999999999999999999", str(os.getpid()), "0", "dangling link", b"\xff"]
            )
            case.what.append(f"lock: {how!r}")
            R._remove(lock)
            if how == "folder":
                lock.mkdir()
            elif how == "dangling link":
                lock.symlink_to(out / "nowhere")
            elif isinstance(how, bytes):
                lock.write_bytes(how)
            else:
                lock.write_text(how)
        elif target == "objects":
            how = rng.choice(["a file", "deleted", "empty", "junk shard"])
            case.what.append(f"objects/: {how}")
            if how == "junk shard" and (out / "objects").is_dir():
                (out / "objects" / "part-junk.parquet").write_bytes(b"PAR1junk")
                continue
            R._remove(out / "objects")
            if how == "a file":
                (out / "objects").write_text("x")
            elif how == "empty":
                (out / "objects").mkdir()
        elif target == "shard" and shards:
            shard = rng.choice(shards)
            how = rng.choice(["truncated", "a folder", "errors table", "empty file"])
            case.what.append(f"shard {shard.name}: {how}")
            if not shard.exists() or shard.is_dir():
                continue
            raw = shard.read_bytes()
            R._remove(shard)
            if how == "truncated":
                shard.write_bytes(raw[: rng.randrange(len(raw))])
            elif how == "a folder":
                shard.mkdir()
            elif how == "errors table":
                pq.write_table(R.ERRORS_SCHEMA.empty_table(), shard)
            else:
                shard.write_bytes(b"")
        elif target == "errors":
            how = rng.choice(["a file", "truncated part", "part a folder", "junk part"])
            case.what.append(f"errors/: {how}")
            if how == "a file":
                R._remove(out / "errors")
                (out / "errors").write_text("x")
            else:
                (out / "errors").mkdir(exist_ok=True) if not os.path.lexists(out / "errors") else None
                if not (out / "errors").is_dir():
                    continue
                name = parts[0].name if parts else (shards[0].name if shards else "part-x.parquet")
                p = out / "errors" / name
                R._remove(p)
                if how == "truncated part":
                    p.write_bytes(b"PAR1\x00\x00")
                elif how == "part a folder":
                    p.mkdir()
                else:
                    (out / "errors" / "part-junk.parquet").write_bytes(b"junk")
        elif target == "errors.parquet":
            how = rng.choice(["folder", "garbage", "deleted"])
            case.what.append(f"errors.parquet: {how}")
            R._remove(out / "errors.parquet")
            if how == "folder":
                (out / "errors.parquet").mkdir()
            elif how == "garbage":
                (out / "errors.parquet").write_bytes(b"PAR1xx")
        elif target == "tmp":
            case.what.append("temporary files of a killed run")
            (out / ".manifest.json.tmp-999").write_text("{")
            if (out / "objects").is_dir():
                (out / "objects" / ".part-x.parquet.tmp-999").mkdir(exist_ok=True)
        else:
            case.what.append("a foreign file")
            (out / "notes.txt").write_text("mine")


def test_fuzz_results_folder_states(tmp_path, request):
    request.node.quick(True)
    data = H.write_kitti(tmp_path / "data", [GOOD, "000001"])
    (data / "training" / "velodyne" / "000001.bin").write_bytes(b"\0" * 10)  # a failed frame: errors/ has a part
    good = tmp_path / "good"
    H.check_output(H.run_cli("infer", data, "-o", good, "--workers", "1", "-q"), allowed=(0,))
    baseline = H.rows_by_frame(good)
    n = cases(100)
    for c in range(n):
        rng = rng_for("folders", c)
        case = Case("results-folders", c)
        out = tmp_path / f"f{c}"
        shutil.copytree(good, out, symlinks=True)
        _damage_folder(rng, case, out)
        for cmd in (["rank", out, "--format", "json"], ["check", out, "--json"]) if rng.random() < 0.2 else ():
            H.check_output(H.run_cli(*cmd), allowed=(0, 1, 2))
        resumed = H.run_cli("infer", data, "-o", out, "--workers", "1", "-q")
        try:
            H.check_output(resumed, allowed=(0, 2))
        except AssertionError as exc:
            raise AssertionError(f"{case}\n{exc}") from None
        if resumed.exit_code == 0:
            assert H.rows_by_frame(out) == baseline, f"{case}: resumed into a damaged folder, the rows changed"
            assert R.read_manifest(out)["complete"] and len(H.errors_of(out)) == 1, (
                f"{case}: incomplete results after the resume"
            )
            continue
        assert str(out) in resumed.stderr, f"{case}: the refusal does not name the folder: {resumed.stderr}"
        assert "--overwrite" in resumed.stderr or "choose" in resumed.stderr, (
            f"{case}: no fix offered: {resumed.stderr}"
        )
        again = H.run_cli("infer", data, "-o", out, "--workers", "1", "-q", "--overwrite")
        H.check_output(again, allowed=(0, 2))
        if again.exit_code == 0:
            assert H.rows_by_frame(out) == baseline, f"{case}: --overwrite did not rebuild the results"
        else:  # only a folder that is not ours may be refused: --overwrite never deletes foreign files
            assert "not a labelaudit results folder" in again.stderr, f"{case}: --overwrite refused: {again.stderr}"
    FOUND["results-folders"] = n


# --------------------------------------------------------------------------- command-line values

ODD = [
    "",
    " ",
    "-",
    "--",
    "[/]",
    "[bold]",
    "\\",
    "x" * 300,
    "ДЖ",
    "a\nb",
    "-1",
    "0",
    "nan",
    "inf",
    "1e400",
    "2147483648",
    "9" * 40,
    "--nope",
]


def _cli_case(rng: random.Random, env: dict[str, Path]) -> list[str]:
    """One command line: a command, its positional argument and 0–4 options with hostile values."""
    cmd = rng.choice(["infer"] * 4 + ["rank"] * 3 + ["check"] * 2 + ["simulate"])
    pool = {
        "infer": {
            "--workers": ["1", "0", "-3", "x", "", "1.5"],
            "--limit": ["1", "0", "-1", "x", "10000000000", ""],
            "--model": ["bev", "3d", "4d", "", "BEV"],
            "--dataset-format": ["auto", "kitti", "waymo-v2", "waymo-v1", "foo", ""],
            "--classes": ["all", "Car", "", ",", "[/]", "Car,,Van", " ", "Nope"],
            "--split": ["val", "train", "", "../x", "a/b", "[/]", "\n"],
            "--config": [
                str(env["cfg"]),
                str(env["bad_cfg"]),
                str(env["bytes_cfg"]),
                str(env["data"]),
                str(env["data"] / "nope.toml"),
                "",
            ],
            "-o": [
                str(env["tmp"] / f"out-{rng.randrange(10**6)}"),
                str(env["results"]),
                "",
                str(env["dangling"]),
                str(env["file"] / "sub"),
                str(env["tmp"] / ("y" * 300)),
                str(env["data"]),
                str(env["tmp"] / "[bold]o"),
            ],
            "--strict": None,
            "--overwrite": None,
            "--resume": None,
        },
        "rank": {
            "--by": ["jiou_gt", "label_error", "class_name", "nope", "", "[/]"],
            "--top": ["0", "-1", "5", "1000000000000", "x"],
            "--class": ["Car", "", "[/]"],
            "--status": ["ok", "fine", "", "error"],
            "--min-points": ["-1", "x", "1000000000000", "3"],
            "--max-distance": ["nan", "inf", "-1", "x", "1e400"],
            "--format": ["table", "json", "csv", "xml", ""],
            "--where": [
                "jiou_gt>0.5",
                "oops",
                "jiou_gt>=nan",
                "class_name==[/]",
                "",
                "a==b==c",
                "num_points>1e400",
                "cx<inf",
                "status==ok",
            ],
            "--asc": None,
            "--desc": None,
        },
        "check": {
            "--config": [str(env["gate"]), str(env["bad_cfg"]), str(env["bytes_cfg"]), str(env["data"]), ""],
            "--json": None,
            "--junit": [
                str(env["tmp"] / "j.xml"),
                str(env["data"]),
                str(env["file"] / "sub"),
                "",
                str(env["tmp"] / ("z" * 300)),
            ],
        },
        "simulate": {
            "--frames": ["0", "-1", "x", ""],
            "--seed": ["-1", "x", "99999999999999999999"],
            "--noise-fraction": ["nan", "2", "-1", "x"],
            "--workers": ["0", "x"],
            "--noise-center-std": ["inf", "-1"],
            "--overwrite": None,
        },
    }[cmd]
    first = {
        "infer": [
            str(env["data"]),
            str(env["data"] / "nope"),
            str(env["file"]),
            "",
            str(env["tmp"] / ("w" * 300)),
            "[/]",
        ],
        "rank": [str(env["results"]), str(env["data"]), str(env["file"]), "", str(env["tmp"] / "none")],
        "check": [str(env["results"]), str(env["data"]), str(env["file"]), ""],
        "simulate": [str(env["tmp"] / f"sim-{rng.randrange(10**6)}"), str(env["file"]), "", str(env["dangling"])],
    }[cmd]
    # the good value first in every list: most options get it, so runs also get past the parsing
    argv = [cmd] + ([first[0] if rng.random() < 0.6 else rng.choice(first)] if rng.random() < 0.95 else [])
    for opt in rng.sample(sorted(pool), k=min(len(pool), rng.randint(0, 3))):
        values = pool[opt]
        if values is not None:
            r = rng.random()
            argv += [opt, values[0] if r < 0.5 else rng.choice(values) if r < 0.9 else rng.choice(ODD)]
        else:
            argv += [opt]
    if cmd == "infer":
        argv += ["-q", "--workers", "1"] if "--workers" not in argv else ["-q"]
    if cmd == "simulate" and "--frames" not in argv:
        argv += ["--frames", "0"]  # stays fast: every simulate case is refused before it renders
    return argv


def test_fuzz_command_line_values(tmp_path, request, monkeypatch):
    request.node.quick(True)
    monkeypatch.chdir(tmp_path)  # without -o, infer writes ./labelaudit-results
    data = H.write_kitti(tmp_path / "data", [GOOD])
    results = tmp_path / "results"
    H.check_output(H.run_cli("infer", data, "-o", results, "--workers", "1", "-q"), allowed=(0,))
    env = {
        "tmp": tmp_path,
        "data": data,
        "results": results,
        "file": tmp_path / "a-file",
        "dangling": tmp_path / "dangling",
        "cfg": _fuzz_config(tmp_path),
        "bad_cfg": tmp_path / "bad.toml",
        "bytes_cfg": tmp_path / "bytes.toml",
        "gate": tmp_path / "gate.toml",
    }
    env["file"].write_text("x")
    env["dangling"].symlink_to(tmp_path / "nowhere")
    env["bad_cfg"].write_text("[model]\nsigma = inf\n[spatial\n")
    env["bytes_cfg"].write_bytes(b"[model]\nsigma = 0.2 # \xff\n")
    env["gate"].write_text("[default]\nmin_median_jiou_gt = 0.1\n")
    n = cases(300)
    for c in range(n):
        argv = _cli_case(rng_for("cli", c), env)
        run = H.run_cli(*argv)
        allowed = {"infer": (0, 2), "rank": (0, 2), "check": (0, 1, 2), "simulate": (2,)}[argv[0]]
        try:
            H.check_output(run, allowed=allowed)
        except AssertionError as exc:
            raise AssertionError(f"[cli case {c}, LABELAUDIT_FUZZ_SEED={SEED}] {argv!r}\n{exc}") from None
    FOUND["cli-values"] = n

"""Benchmark of the missing-label search (`infer`'s missing/ table): recall and false candidates.

Simulated (always): ``simulate --clutter --drop-fraction F`` frames; a dropped vehicle with at least
``--min-points`` returns is found when a candidate with score ≥ ``--threshold`` lies within 1.0 m
(BEV) of its true centre; a false candidate scores ≥ the threshold and lies more than 2 m from
every vehicle of the scene (labelled or not). Printed overall and by distance and by points.

Real KITTI (``--real``, when the folder exists): every vehicle (Car, Van, Truck) with at least 50
LiDAR points is removed from its own copy of the frame (label line deleted, points kept) and
searched for (same rule); the unmodified frames give the candidates per frame. Frames are reported
separately for the two folders: openpcdet-pr653-kitti (looked at while the search was built) and
kitti-object-more (held out: never looked at before the figures were final).

    .venv/bin/python scripts/bench_missing.py [--frames 60] [--seed 11 [7 3 21]] [--drop-fraction 0.15] [--real [DIR]] [--why]

``--why`` says, for every simulated miss, why: a candidate placed more than 1 m off (by how much,
along and across the vehicle), a score under the threshold (its weakest factor), a cluster boxed but
not written (outside the labelled region, under the kept minimum, over a label), a group of returns
left unboxed (by which rule: points, footprint, tall, low, region), returns merged into a group boxed
elsewhere, or no group at all; and counts the causes with their classes, points, distance and
visible share. The pooled benchmark of docs/missing.md:

    .venv/bin/python scripts/bench_missing.py --frames 60 --seed 11 7 3 21 --why

``--cost`` prints instead what the search costs, stage by stage (CPU ms per frame in one warm
process, the allocator tuned as ``infer`` tunes it): on ``bench_infer``'s 120 frames (seed 4, its
issue's per-frame target counts the search) and on cluttered frames with dropped labels:

    .venv/bin/python scripts/bench_missing.py --cost [--keep DIR] [--repeat 3]
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import tempfile
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REALDATA = Path(os.environ.get("LABELAUDIT_REALDATA", REPO.parent / "shared" / "realdata"))
REAL_FOLDERS = (("openpcdet-pr653-kitti", "built with"), ("kitti-object-more", "held out"))
VEHICLES = ("Car", "Van", "Truck")
DIST_BINS = (0.0, 20.0, 40.0, 70.0)
POINT_BINS = (30, 100, 300, 10**9)
VISIBLE_BINS = (0.0, 0.3, 0.6, 1.000001)


def _bin(value: float, edges: tuple) -> str:
    for lo, hi in zip(edges[:-1], edges[1:]):
        if lo <= value < hi:
            return f"{lo:g}–{hi:g}" if hi < 10**8 else f"≥ {lo:g}"
    return "other"


def _candidates(frame, cfg, trace=None):
    from labelaudit.infer.missing import find_missing

    return find_missing(frame, cfg, trace=trace)


FACTORS = ("size_score", "shape_score", "density_score", "free_space_score")


def _weakest(c) -> str:
    """The factor that brought a cluster's score down most (a row dict or a Cluster)."""
    get = c.get if isinstance(c, dict) else lambda k: getattr(c, k, None)
    vals = {k[:-6].replace("_", " "): get(k) for k in FACTORS if get(k) is not None}
    return min(vals, key=vals.get) if vals else "?"


def _factors(c) -> str:
    get = c.get if isinstance(c, dict) else lambda k: getattr(c, k, None)
    return " ".join(f"{k[:-6]} {get(k):.2f}" for k in FACTORS if get(k) is not None)


def _in_footprint(x, y, o: dict, grow: float = 0.0):
    """Whether BEV points (arrays) lie in the rectangle of ``o`` (``true_*`` fields) grown by ``grow``."""
    dx, dy = x - o["true_cx"], y - o["true_cy"]
    c, s = math.cos(o["true_yaw"]), math.sin(o["true_yaw"])
    return (np.abs(c * dx + s * dy) <= 0.5 * o["true_length"] + grow) & (
        np.abs(-s * dx + c * dy) <= 0.5 * o["true_width"] + grow
    )


def _why(o: dict, rows: list, trace, frame, threshold: float) -> tuple[str, str]:
    """Why a dropped vehicle ``o`` (manifest row) was missed: (kind, detail). Kinds, first that applies:
    ``placed > 1 m off`` (a candidate ≥ threshold within 3 m), ``score < threshold: <factor>`` (a
    written row within 3 m, its weakest factor), ``dropped: <fate>`` (a boxed cluster within 3 m not
    written: outside the labelled region, score under the kept minimum, over a label), ``unboxed:
    <rule>`` (the group holding most of its returns left unboxed by that rule), ``merged: boxed
    elsewhere`` (that group's boxes all lie > 3 m off), ``no group`` (none of its returns clustered)."""

    def off(c):
        return math.hypot(c[0] - o["true_cx"], c[1] - o["true_cy"])

    def along_across(x, y):
        dx, dy = x - o["true_cx"], y - o["true_cy"]
        c, s = math.cos(o["true_yaw"]), math.sin(o["true_yaw"])
        return abs(c * dx + s * dy), abs(-s * dx + c * dy)

    good = [r for r in rows if r["score"] >= threshold and off((r["cx"], r["cy"])) <= 3.0]
    if good:
        r = min(good, key=lambda r: off((r["cx"], r["cy"])))
        a, b = along_across(r["cx"], r["cy"])
        return "placed > 1 m off", (
            f"{off((r['cx'], r['cy'])):.1f} m off ({a:.1f} along, {b:.1f} across), boxed as {r['class_name']}"
            f" {r['length']:.1f} × {r['width']:.1f} m (true {o['true_length']:.1f} × {o['true_width']:.1f}), score {r['score']:.2f}"
        )
    weak = [r for r in rows if off((r["cx"], r["cy"])) <= 3.0]
    if weak:
        r = min(weak, key=lambda r: off((r["cx"], r["cy"])))
        return f"score < {threshold:g}: {_weakest(r)}", (
            f"{off((r['cx'], r['cy'])):.1f} m off, {r['class_name']}, score {r['score']:.2f} ({_factors(r)})"
        )
    dropped = [(c, f) for c, f in trace.clusters if f != "kept" and off(c.box) <= 3.0]
    if dropped:
        c, f = min(dropped, key=lambda cf: off(cf[0].box))
        kind = f"dropped: {f}" + (f" ({_weakest(c)})" if f == "low score" else "")
        return kind, f"{off(c.box):.1f} m off, {c.class_name}, score {c.score:.2f} ({_factors(c)})"
    # the group holding most of its returns (a truck seen from its rear: its returns, not its centre)
    pts = frame.points[:, :2]
    mine = pts[_in_footprint(pts[:, 0], pts[:, 1], o)]
    held = [
        (
            int(
                (
                    (mine[:, 0] >= g["x0"])
                    & (mine[:, 0] <= g["x1"])
                    & (mine[:, 1] >= g["y0"])
                    & (mine[:, 1] <= g["y1"])
                ).sum()
            ),
            g,
        )
        for g in trace.groups
    ]
    n_held, g = max(held, key=lambda hg: hg[0], default=(0, None))
    if n_held > 0:
        size = f"{g['x1'] - g['x0']:.1f} × {g['y1'] - g['y0']:.1f} m, {g['points']} band returns"
        if g["fate"] != "boxed":
            return f"unboxed: {g['fate']}", f"its group {size}"
        boxes = [trace.clusters[k] for k in g["clusters"]]
        near = min(boxes, key=lambda cf: off(cf[0].box), default=None)
        if near is None:
            return "merged: boxed elsewhere", f"its group {size}"
        c, f = near
        return "merged: boxed elsewhere", (
            f"its group {size} boxed as {len(boxes)} box(es), the nearest {off(c.box):.1f} m off, {c.class_name},"
            f" score {c.score:.2f} ({_factors(c)}), {f}"
        )
    # no group: its returns are explained by a neighbouring label (grown by the margin), or lie outside the band
    from labelaudit import constants as C

    mine = _in_footprint(pts[:, 0], pts[:, 1], o)
    near = np.zeros(len(pts), dtype=bool)
    for b in frame.boxes:
        other = {"true_cx": b[0], "true_cy": b[1], "true_length": b[3], "true_width": b[4], "true_yaw": b[6]}
        near |= _in_footprint(pts[:, 0], pts[:, 1], other, C.MISSING_LABEL_MARGIN)
    n = int(mine.sum())
    return "no group", f"{int((mine & near).sum())} of its {n} returns (BEV) within a label's margin"


def _simulate_cluttered(out: Path, frames: int, seed: int, drop: float, workers: int) -> None:
    """``simulate --clutter --drop-fraction drop``: the benchmark's frames, into ``out``."""
    from labelaudit import constants as C
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.scene import SceneSpec

    simulate_dataset(
        out,
        frames=frames,
        seed=seed,
        scene=SceneSpec(num_clutter=C.SIM_CLUTTER),
        drop_fraction=drop,
        workers=workers,
        progress=False,
    )


def bench_sim(
    frames: int,
    seed: int,
    drop: float,
    threshold: float,
    min_points: int,
    workers: int,
    keep: Path | None,
    verbose: bool = False,
    why: bool = False,
) -> dict:
    """One seed's simulated benchmark; prints its figures and returns its tallies (for pooling)."""
    import pyarrow.parquet as pq

    from labelaudit.config import load_config
    from labelaudit.datasets import open_dataset
    from labelaudit.infer.missing import SearchTrace

    tmp = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="bench-missing-"))
    data = tmp / "sim"
    if not (data / "manifest.parquet").is_file():
        t = time.perf_counter()
        _simulate_cluttered(data, frames, seed, drop, workers)
        print(
            f"simulated {frames} frames with clutter, {drop:.0%} of vehicle labels dropped (seed {seed}) in {time.perf_counter() - t:.0f} s"
        )
    manifest = pq.read_table(data / "manifest.parquet").to_pylist()
    by_frame = defaultdict(list)
    for row in manifest:
        by_frame[row["frame_id"]].append(row)
    cfg = load_config(None, "kitti")
    reader = open_dataset(data, "kitti")
    found, total = defaultdict(int), defaultdict(int)
    false_by = defaultdict(int)
    n_false = n_frames = 0
    seconds = 0.0
    misses = []
    falses = []
    for n_ref, ref in enumerate(reader.list_units()):
        frame = next(reader.load_unit(ref))
        trace = SearchTrace() if why else None
        t = time.process_time()
        all_cands = _candidates(frame, cfg, trace)
        cands = [c for c in all_cands if c["score"] >= threshold]
        if n_ref >= 2:  # the first frames load (or compile) the kernels
            seconds += time.process_time() - t
        n_frames += 1
        objs = by_frame[frame.frame_id]
        vehicles = [o for o in objs if o["class_name"] in VEHICLES]
        for o in vehicles:
            if not o["dropped"] or o["num_points"] < min_points:
                continue
            hit = any(math.hypot(c["cx"] - o["true_cx"], c["cy"] - o["true_cy"]) <= 1.0 for c in cands)
            visible = 1.0 - (o["occlusion_fraction"] or 0.0)
            if not hit:
                kind, detail = (
                    _why(o, all_cands, trace, frame, threshold) if why else ("missed", _nearest(o, all_cands))
                )
                misses.append(
                    {
                        "seed": seed,
                        "kind": kind,
                        "class": o["class_name"],
                        "distance": o["distance"],
                        "points": o["num_points"],
                        "visible": visible,
                        "text": f"    seed {seed} {frame.frame_id} {o['class_name']} at ({o['true_cx']:.1f}, {o['true_cy']:.1f}) {o['distance']:.0f} m,"
                        f" {o['num_points']} points, {visible:.0%} visible: {kind}: {detail}",
                    }
                )
            for key in (
                "all",
                f"class {o['class_name']}",
                f"distance {_bin(o['distance'], DIST_BINS)} m",
                f"points {_bin(o['num_points'], POINT_BINS)}",
                f"visible {_bin(visible, VISIBLE_BINS)}",
            ):
                total[key] += 1
                found[key] += hit
        for c in cands:
            if all(math.hypot(c["cx"] - o["true_cx"], c["cy"] - o["true_cy"]) > 2.0 for o in vehicles):
                n_false += 1
                falses.append(
                    f"    seed {seed} {frame.frame_id} candidate {c['class_name']} at ({c['cx']:.1f}, {c['cy']:.1f})"
                    f" {c['distance']:.0f} m, {c['num_points']} points, score {c['score']:.2f} ({_factors(c)})"
                )
                false_by[f"distance {_bin(c['distance'], DIST_BINS)} m"] += 1
                false_by[f"points {_bin(c['num_points'], POINT_BINS)}"] += 1
    tally = {
        "found": found,
        "total": total,
        "false": n_false,
        "false_by": false_by,
        "frames": n_frames,
        "misses": misses,
        "falses": falses,
        "seconds": seconds,
        "timed": max(n_frames - 2, 1),
    }
    _print_sim(f"seed {seed}, {drop:.0%} dropped", tally, threshold, min_points, verbose, why)
    if not keep:
        shutil.rmtree(tmp, ignore_errors=True)
    return tally


def _nearest(o: dict, cands: list) -> str:
    near = min(cands, key=lambda c: math.hypot(c["cx"] - o["true_cx"], c["cy"] - o["true_cy"]), default=None)
    d = None if near is None else math.hypot(near["cx"] - o["true_cx"], near["cy"] - o["true_cy"])
    if d is None or d > 3.0:
        return "no cluster boxed"
    return f"nearest candidate {d:.1f} m off, {near['class_name']}, score {near['score']:.2f} {_factors(near)}"


def _print_sim(title: str, t: dict, threshold: float, min_points: int, verbose: bool, why: bool) -> None:
    found, total, frames = t["found"], t["total"], max(t["frames"], 1)
    print(
        f"simulated, clutter, {title}, score ≥ {threshold}: dropped vehicles with ≥ {min_points} points found within 1.0 m"
    )
    for key in sorted(total, key=lambda k: (k != "all", k)):
        print(f"  recall {key:22s} {found[key]:4d} / {total[key]:4d} = {found[key] / total[key]:.3f}")
    print(
        f"  false candidates (> 2 m from every vehicle): {t['false']} in {frames} frames = {t['false'] / frames:.3f} per frame"
    )
    for key in sorted(t["false_by"]):
        print(f"    {key:22s} {t['false_by'][key] / frames:.3f} per frame")
    print(
        f"  search CPU time: {t['seconds'] / t['timed'] * 1e3:.1f} ms per frame after the first two (this process, load {os.getloadavg()[0]:.1f}; "
        "frames with dropped labels and clutter: more clusters to box than a fully labelled frame)"
    )
    if why and t["misses"]:
        _print_why(t["misses"])
    if verbose or why:
        print("  missed:")
        print("\n".join(m["text"] for m in sorted(t["misses"], key=lambda m: (m["kind"], m["seed"], m["text"]))))
    if verbose and t.get("falses"):
        print("  false candidates:")
        print("\n".join(t["falses"]))


def _print_why(misses: list) -> None:
    """The misses by cause, each with its classes and its medians of points, distance and visible share."""
    by = defaultdict(list)
    for m in misses:
        by[m["kind"]].append(m)
    print(
        f"  why the {len(misses)} misses were missed (cause: count; classes; median points, distance, visible share):"
    )
    for kind, ms in sorted(by.items(), key=lambda kv: (-len(kv[1]), kv[0])):
        classes = ", ".join(
            f"{c} {sum(m['class'] == c for m in ms)}" for c in VEHICLES if any(m["class"] == c for m in ms)
        )
        med = {k: float(np.median([m[k] for m in ms])) for k in ("points", "distance", "visible")}
        print(
            f"    {kind:34s} {len(ms):3d}; {classes}; {med['points']:.0f} points, {med['distance']:.0f} m, {med['visible']:.0%} visible"
        )


def _copy_frame(src: Path, dst: Path, fid: str, drop_line: int | None) -> None:
    for sub in ("velodyne", "calib", "image_2"):
        f = (
            src
            / "training"
            / sub
            / (f"{fid}.bin" if sub == "velodyne" else f"{fid}.png" if sub == "image_2" else f"{fid}.txt")
        )
        if f.is_file():
            (dst / "training" / sub).mkdir(parents=True, exist_ok=True)
            os.symlink(f, dst / "training" / sub / f.name)
    lines = (src / "training" / "label_2" / f"{fid}.txt").read_text().splitlines(keepends=True)
    if drop_line is not None:
        del lines[drop_line - 1]
    (dst / "training" / "label_2").mkdir(parents=True, exist_ok=True)
    (dst / "training" / "label_2" / f"{fid}.txt").write_text("".join(lines))


def bench_real(root: Path, threshold: float, min_points: int, verbose: bool) -> None:
    from labelaudit.config import load_config
    from labelaudit.datasets import open_dataset
    from labelaudit.infer.crop import crop_frame

    cfg = load_config(None, "kitti")
    for name, role in REAL_FOLDERS:
        src = root / name
        if not (src / "training" / "label_2").is_dir():
            print(f"real KITTI {name}: not present, skipped")
            continue
        reader = open_dataset(src, "kitti")
        found = total = n_cands = n_frames = 0
        lines_out = []
        for ref in reader.list_units():
            frame = next(reader.load_unit(ref))
            cands = [c for c in _candidates(frame, cfg) if c["score"] >= threshold]
            n_cands += len(cands)
            n_frames += 1
            for c in cands:
                lines_out.append(
                    f"    {frame.frame_id} candidate {c['class_name']} at ({c['cx']:.1f}, {c['cy']:.1f}) {c['distance']:.0f} m, {c['num_points']} points, score {c['score']:.2f}"
                )
            counts = [len(i) for i in crop_frame(frame.points, frame.boxes, cfg.crop)]
            for i, cls in enumerate(frame.class_names):
                if cls not in VEHICLES or counts[i] < min_points:
                    continue
                with tempfile.TemporaryDirectory(prefix="bench-missing-real-") as tmp:
                    _copy_frame(src, Path(tmp), frame.frame_id, int(frame.extras["label_line"][i]))
                    cut = next(open_dataset(tmp, "kitti").load_unit(ref.__class__("kitti", tmp, frame.frame_id)))
                    got = [c for c in _candidates(cut, cfg) if c["score"] >= threshold]
                b = frame.boxes[i]
                hit = any(math.hypot(c["cx"] - b[0], c["cy"] - b[1]) <= 1.0 for c in got)
                total += 1
                found += hit
                lines_out.append(
                    f"    {frame.frame_id} removed {cls} line {int(frame.extras['label_line'][i])} at ({b[0]:.1f}, {b[1]:.1f}), {counts[i]} points: {'found' if hit else 'MISSED'}"
                )
        print(f"real KITTI {name} ({role}, {n_frames} frames), score ≥ {threshold}:")
        print(
            f"  recall of removed vehicles with ≥ {min_points} points: {found} / {total} = {found / max(total, 1):.3f}"
        )
        print(f"  candidates on the unmodified frames: {n_cands} = {n_cands / max(n_frames, 1):.2f} per frame")
        if verbose:
            print("\n".join(lines_out))


# --------------------------------------------------------------------------- cost, stage by stage

COST_STAGES = (  # (label, name in labelaudit.infer.missing, the stage it is part of: None = top level)
    ("search_clusters", "search_clusters", None),
    ("ground grid", "_ground_grid", "search_clusters"),
    ("label mask", "_label_mask", "search_clusters"),
    ("occupancy", "_occupancy", "search_clusters"),
    ("components", "_components", "search_clusters"),
    ("component extras", "_comp_extras", "search_clusters"),
    ("fragments joined", "_merge_fragments", "search_clusters"),
    ("gather", "_gather", "search_clusters"),
    ("owners", "_owners", "search_clusters"),
    ("rays per sr", "_rays_per_rad2", "search_clusters"),
    ("box clusters", "_box_cluster", "search_clusters"),
    ("faces", "_faces", "_box_cluster"),
    ("place", "_place", "_box_cluster"),
    ("continues", "_continues", "_box_cluster"),
    ("roughness", "_roughness", "_box_cluster"),
    ("labelled region", "in_labelled_region", None),
    ("labelled region", "in_labelled_region@search_clusters", "search_clusters"),  # (its fragments, before boxing)
    ("free space + fit", "with_free_space", None),
    ("frame evidence", "frame_evidence", "with_free_space"),
    ("label-error fit", "fit_label_valid", "with_free_space"),
    ("ray counts", "ray_counts", "with_free_space"),
)


def search_cost(data: Path, frames: int, warm: int = 10) -> tuple[int, float, dict[str, float], float]:
    """CPU seconds of ``find_missing`` over ``frames`` frames of the KITTI folder ``data`` in this
    (warm) process, after ``warm`` frames, with the seconds of each function of
    :data:`COST_STAGES` (outermost calls only: a recursive box counts once); returns (frames,
    total seconds, seconds per stage, clusters boxed per frame)."""
    from labelaudit.config import load_config
    from labelaudit.datasets import open_dataset
    from labelaudit.executors import tune_allocator
    from labelaudit.infer import missing as M

    tune_allocator()  # where memory comes from, as in every process that audits (process_chunk calls it)
    clock = time.process_time
    acc: dict[str, float] = defaultdict(float)
    depth: dict[str, int] = defaultdict(int)
    calls = [0]
    staged = {name for _, name, _ in COST_STAGES}
    originals = {name: getattr(M, name) for name in staged if hasattr(M, name)}  # (an older checkout lacks some)

    def timed(name, f):
        def run(*a, **k):
            if depth[name]:  # a recursive call: its time is in the outer one's
                return f(*a, **k)
            depth[name] += 1
            calls[0] += name == "_box_cluster"
            inner = f"{name}@search_clusters"  # the same function called within search_clusters: its own line
            key = inner if inner in staged and depth["search_clusters"] else name
            t = clock()
            try:
                return f(*a, **k)
            finally:
                acc[key] += clock() - t
                depth[name] -= 1

        return run

    cfg = load_config(None, "kitti")
    reader = open_dataset(data, "kitti")
    refs = reader.list_units()[: warm + frames]
    loaded = [f for ref in refs for f in reader.load_unit(ref)]
    for frame in loaded[:warm]:
        M.find_missing(frame, cfg)
    try:
        for name, f in originals.items():
            setattr(M, name, timed(name, f))
        t0 = clock()
        for frame in loaded[warm:]:
            M.find_missing(frame, cfg)
        total = clock() - t0
    finally:
        for name, f in originals.items():
            setattr(M, name, f)
    n = max(len(loaded) - warm, 1)
    return n, total, dict(acc), calls[0] / n


def bench_cost(datasets: list[tuple[str, Path]], frames: int, repeat: int) -> None:
    """Print the search's CPU ms per frame, stage by stage, for each dataset (median of ``repeat``
    runs, their range in brackets)."""
    for title, data in datasets:
        runs = [search_cost(data, frames) for _ in range(repeat)]
        n = runs[0][0]

        def ms(values: list[float]) -> str:
            v = sorted(x / n * 1e3 for x in values)
            return f"{v[len(v) // 2]:6.3f} [{v[0]:.3f}–{v[-1]:.3f}]" if len(v) > 1 else f"{v[0]:6.3f}"

        print(
            f"search cost, {title}: {n} frames, {runs[0][3]:.2f} clusters boxed per frame, CPU ms per frame "
            f"(load {' '.join(f'{x:.1f}' for x in os.getloadavg())}):"
        )
        print(f"  find_missing              {ms([r[1] for r in runs])} ms")
        children: dict[str | None, list[str]] = defaultdict(list)
        for _, name, parent in COST_STAGES:
            children[parent].append(name)
        labels = {name: label for label, name, _ in COST_STAGES}

        def show(name: str, indent: int) -> None:
            print(f"  {' ' * indent}{labels[name]:{24 - indent}s}{ms([r[2].get(name, 0.0) for r in runs])} ms")
            for child in children.get(name, []):
                show(child, indent + 2)
            if children.get(name):
                rest = [r[2].get(name, 0.0) - sum(r[2].get(c, 0.0) for c in children[name]) for r in runs]
                print(f"  {' ' * (indent + 2)}{'(the rest)':{22 - indent}s}{ms(rest)} ms")

        for name in children[None]:
            show(name, 2)
        rest = [r[1] - sum(r[2].get(c, 0.0) for c in children[None]) for r in runs]
        print(f"    {'(rows, label IoU)':22s}{ms(rest)} ms")


def cost_datasets(keep: Path | None, frames: int, seed: int, drop: float, workers: int) -> list[tuple[str, Path]]:
    """``bench_infer``'s frames (120, seed 4, no clutter) and ``frames`` cluttered frames of ``seed``
    with ``drop`` of the vehicle labels dropped, simulated once into ``keep`` (or a temporary folder)."""
    from labelaudit.sim.dataset import simulate_dataset

    tmp = Path(keep) if keep else Path(tempfile.mkdtemp(prefix="bench-missing-cost-"))
    plain, cluttered = tmp / "cost-seed-4", tmp / f"cost-clutter-seed-{seed}"
    if not (plain / "manifest.parquet").is_file():
        simulate_dataset(plain, frames=120, seed=4, workers=workers, progress=False)
    if not (cluttered / "manifest.parquet").is_file():
        _simulate_cluttered(cluttered, frames, seed, drop, workers)
    return [
        ("bench_infer's frames (seed 4)", plain),
        (f"clutter, {drop:.0%} of vehicle labels dropped (seed {seed})", cluttered),
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument(
        "--seed", type=int, nargs="+", default=[11], help="one or more simulator seeds (several: also pooled figures)"
    )
    ap.add_argument("--drop-fraction", type=float, default=0.15)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument(
        "--min-points", type=int, default=30, help="simulated: dropped vehicles with at least this many returns count"
    )
    ap.add_argument("--workers", type=int, default=2, help="simulator processes")
    ap.add_argument(
        "--keep",
        type=Path,
        default=None,
        help="keep (or reuse) the simulated data in this folder (several seeds: one sub-folder seed-S each)",
    )
    ap.add_argument(
        "--real",
        nargs="?",
        const=REALDATA,
        type=Path,
        default=None,
        help="also the real KITTI frames (default folder: ../shared/realdata)",
    )
    ap.add_argument("--no-sim", action="store_true", help="only the real frames")
    ap.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        help="list every real candidate and removed vehicle, and every simulated miss",
    )
    ap.add_argument(
        "--why",
        action="store_true",
        help="say why each simulated miss was missed (placed off, which score factor, which rule dropped its cluster) and count the causes",
    )
    ap.add_argument(
        "--cost",
        action="store_true",
        help="instead of recall: the search's CPU time per frame, stage by stage, in one warm process, on "
        "bench_infer's 120 frames (seed 4) and on --frames cluttered frames of the first --seed",
    )
    ap.add_argument("--repeat", type=int, default=3, help="--cost: runs per dataset (median and range printed)")
    args = ap.parse_args()
    if args.cost:
        datasets = cost_datasets(args.keep, args.frames, args.seed[0], args.drop_fraction, args.workers)
        bench_cost(datasets, 100, args.repeat)
        return
    if not args.no_sim:
        tallies = []
        for seed in args.seed:
            keep = args.keep if args.keep is None or len(args.seed) == 1 else args.keep / f"seed-{seed}"
            tallies.append(
                bench_sim(
                    args.frames,
                    seed,
                    args.drop_fraction,
                    args.threshold,
                    args.min_points,
                    args.workers,
                    keep,
                    args.verbose,
                    args.why,
                )
            )
        if len(tallies) > 1:
            pooled = {
                "found": defaultdict(int),
                "total": defaultdict(int),
                "false_by": defaultdict(int),
                "false": 0,
                "frames": 0,
                "misses": [],
                "seconds": 0.0,
                "timed": 0,
            }
            for t in tallies:
                for k in ("found", "total", "false_by"):
                    for key, v in t[k].items():
                        pooled[k][key] += v
                for k in ("false", "frames", "misses", "seconds", "timed"):
                    pooled[k] += t[k]
            per_seed = " / ".join(f"{t['found']['all'] / max(t['total']['all'], 1):.3f}" for t in tallies)
            print(f"\nPOOLED over seeds {' '.join(map(str, args.seed))} (recall per seed: {per_seed})")
            _print_sim(
                f"{args.drop_fraction:.0%} dropped, pooled",
                pooled,
                args.threshold,
                args.min_points,
                False,
                args.why,
            )
    if args.real is not None:
        if args.real.is_dir():
            bench_real(args.real, args.threshold, 50, args.verbose)
        else:
            print(f"real KITTI: {args.real} not present, skipped")


if __name__ == "__main__":
    main()

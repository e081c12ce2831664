#!/usr/bin/env python
"""Benchmark the simulator: frames/s and points/frame, ray-casting alone, writing a KITTI dataset, and
simulated sequences (Waymo v2 segments, Argoverse 2 logs) at the sensors' real resolution.

Usage::

    .venv/bin/python scripts/bench_simulate.py [--frames 500] [--workers 1 2] [--keep DIR] [--sequence-frames 50]

Prints one line per measurement. The dataset is written to a temporary folder and removed
(unless ``--keep``); 500 KITTI-size frames take about 0.8 GB.
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from labelaudit.sim.dataset import NoiseSpec, frame_generators, simulate_dataset
from labelaudit.sim.raycast import LidarSpec, render_range_image
from labelaudit.sim.scene import SceneSpec, sample_scene


def bench_raycast(frames: int, lidar: LidarSpec) -> None:
    """Scene sampling + ray-casting + points, no files."""
    points = objects = 0
    t0 = time.perf_counter()
    for i in range(frames):
        gens = frame_generators(0, i)
        scene = sample_scene(gens["scene"], SceneSpec(), ground_z=-lidar.sensor_height)
        pts, _ = render_range_image(scene, lidar, None, gens["lidar"]).points()
        points += len(pts)
        objects += len(scene.objects)
    dt = time.perf_counter() - t0
    print(
        f"raycast only   {lidar.beams}x{lidar.columns}: {frames} frames in {dt:6.2f} s = {frames / dt:6.1f} frames/s, "
        f"{points / frames:9.0f} points/frame, {objects / frames:4.1f} objects/frame"
    )


def bench_dataset(frames: int, workers: int, lidar: LidarSpec, keep: Path | None) -> None:
    """simulate_dataset end to end (KITTI files + manifest)."""
    root = Path(tempfile.mkdtemp(prefix="labelaudit-bench-sim-")) if keep is None else keep
    try:
        s = simulate_dataset(
            root / "ds",
            frames=frames,
            seed=0,
            noise=NoiseSpec.benchmark(),
            lidar=lidar,
            workers=workers,
            progress=False,
            overwrite=True,
        )
        size = sum(p.stat().st_size for p in (root / "ds").rglob("*") if p.is_file()) / 1e9
        print(
            f"simulate_dataset workers={workers}: {frames} frames in {s.seconds:6.2f} s = {s.frames_per_second:6.1f} frames/s, "
            f"{s.points_per_frame:9.0f} points/frame, {s.num_labels / frames:4.1f} labels/frame, {size:.2f} GB written"
        )
    finally:
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)


def _points_in_box(points: np.ndarray, box: np.ndarray) -> int:
    d = points[:, :3] - box[:3]
    c, s = np.cos(box[6]), np.sin(box[6])
    u, v = c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]
    return int(
        np.count_nonzero((np.abs(u) <= box[3] / 2) & (np.abs(v) <= box[4] / 2) & (np.abs(d[:, 2]) <= box[5] / 2))
    )


def realism(realdata: Path, frames: int) -> None:
    """Points inside unoccluded vehicle boxes by distance: real KITTI frames vs simulated ones."""
    from labelaudit.datasets.kitti import KittiReader
    from labelaudit.sim.dataset import simulate_frame

    kitti = realdata / "openpcdet-pr653-kitti"
    rows: dict[str, list[tuple[float, int]]] = {"real": [], "sim": []}
    if kitti.is_dir():
        reader = KittiReader(kitti, classes=["Car", "Van", "Truck"])
        for ref in reader.list_units():
            f = next(reader.load_unit(ref))
            for b, occ in zip(f.boxes, f.extras["occluded"]):
                if occ == 0:
                    rows["real"].append((float(np.hypot(b[0], b[1])), _points_in_box(f.points, b)))
    for i in range(frames):
        f = simulate_frame(i, seed=0)
        for j, o in enumerate(f.scene.objects):
            if f.labels.object_index[j] >= 0 and f.labels.occluded[j] == 0 and o.class_name in ("Car", "Van", "Truck"):
                rows["sim"].append((float(np.hypot(o.box[0], o.box[1])), _points_in_box(f.points, o.box)))
    print("points in unoccluded vehicle boxes (median [min, max], count) by distance:")
    _print_by_distance(rows)


def _print_by_distance(rows: dict[str, list[tuple[float, int]]]) -> None:
    """One line per distance bin: median [min, max] and count of the point counts of each source."""
    for lo, hi in ((0, 10), (10, 20), (20, 30), (30, 45), (45, 70)):
        cells = []
        for name in ("real", "sim"):
            a = np.array([n for d, n in rows[name] if lo <= d < hi])
            cells.append(
                f"{name} {np.median(a):6.0f} [{a.min():.0f}, {a.max():.0f}] n={len(a)}"
                if len(a)
                else f"{name} {'-':>6s}"
            )
        print(f"  {lo:2d}-{hi:2d} m: " + "   ".join(cells))


def bench_sequences(fmt: str, sequences: int, frames: int) -> None:
    """simulate_sequences end to end (files + manifest), real sensor resolution."""
    from labelaudit.sim.dataset import simulate_sequences

    root = Path(tempfile.mkdtemp(prefix="labelaudit-bench-seq-"))
    try:
        s = simulate_sequences(
            root / "ds",
            fmt,
            sequences=sequences,
            frames=frames,
            seed=0,
            noise=NoiseSpec.benchmark(),
            size="real",
            progress=False,
        )
        size = sum(p.stat().st_size for p in (root / "ds").rglob("*") if p.is_file()) / 1e9
        print(
            f"simulate {fmt:8s}: {sequences} x {frames} frames in {s.seconds:6.2f} s = {s.frames_per_second:6.1f} frames/s, "
            f"{s.points_per_frame:9.0f} points/frame, {s.num_labels / s.frames:4.1f} labels/frame, {size:.2f} GB written"
        )
    finally:
        shutil.rmtree(root, ignore_errors=True)


def realism_av2(realdata: Path, frames: int) -> None:
    """Points per sweep and in REGULAR_VEHICLE boxes by distance: the real AV2 sweeps vs simulated logs."""
    from labelaudit.datasets import open_dataset
    from labelaudit.sim.av2_writer import simulate_av2_log

    rows: dict[str, list[tuple[float, int]]] = {"real": [], "sim": []}
    sweeps: dict[str, list[int]] = {"real": [], "sim": []}
    root = realdata / "av2-sensor"
    if root.is_dir():
        reader = open_dataset(root, "av2")
        for ref in reader.list_units():
            for f in reader.load_unit(ref):
                if len(f.points):
                    sweeps["real"].append(len(f.points))
                    rows["real"] += [
                        (float(np.hypot(b[0], b[1])), int(n))
                        for b, c, n in zip(f.boxes, f.class_names, f.extras["num_lidar_points_in_box"])
                        if c == "REGULAR_VEHICLE"
                    ]
    log = simulate_av2_log(seed=0, frames=frames, size="real")
    for fr in log.frames:
        sweeps["sim"].append(len(fr.points))
        rows["sim"] += [
            (float(np.hypot(b[0], b[1])), int(n))
            for b, c, n in zip(fr.boxes, fr.categories, fr.num_interior_pts)
            if c == "REGULAR_VEHICLE"
        ]
    print("AV2 points per sweep: " + "   ".join(f"{k} {np.median(v):.0f} (n={len(v)})" for k, v in sweeps.items() if v))
    print("AV2 points in REGULAR_VEHICLE boxes (median [min, max], count) by distance (all boxes, occluded included):")
    _print_by_distance(rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--raycast-frames", type=int, default=100)
    ap.add_argument("--keep", type=Path, default=None, help="write the dataset here and keep it")
    ap.add_argument("--sequences", type=int, default=2, help="Waymo v2 segments / AV2 logs simulated")
    ap.add_argument("--sequence-frames", type=int, default=20, help="frames per simulated sequence")
    ap.add_argument(
        "--realdata",
        type=Path,
        default=Path(__file__).resolve().parents[1].parent / "shared" / "realdata",
        help="real KITTI frames to compare point densities with (skipped when absent)",
    )
    args = ap.parse_args()
    lidar = LidarSpec()
    print(
        f"sensor: {lidar.beams} beams, {lidar.columns} columns ({lidar.azimuth_step_deg:.3f}° step), "
        f"{lidar.max_range:.0f} m; numpy {np.__version__}"
    )
    bench_raycast(args.raycast_frames, lidar)
    realism(args.realdata, 30)
    for w in args.workers:
        bench_dataset(args.frames, w, lidar, args.keep)
    realism_av2(args.realdata, 10)
    for fmt in ("av2", "waymo-v2"):
        bench_sequences(fmt, args.sequences, args.sequence_frames)


if __name__ == "__main__":
    main()

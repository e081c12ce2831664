#!/usr/bin/env python
"""Benchmark the simulator: frames/s and points/frame, ray-casting alone and writing a KITTI dataset.

Usage::

    .venv/bin/python scripts/bench_simulate.py [--frames 500] [--workers 1 2] [--keep DIR]

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

from labelaudit.sim.raycast import LidarSpec, render_range_image
from labelaudit.sim.scene import SceneSpec, sample_scene
from labelaudit.simulate import NoiseSpec, frame_generators, simulate_dataset


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
        s = simulate_dataset(root / "ds", frames=frames, seed=0, noise=NoiseSpec.benchmark(), lidar=lidar,
                             workers=workers, progress=False, overwrite=True)
        size = sum(p.stat().st_size for p in (root / "ds").rglob("*") if p.is_file()) / 1e9
        print(
            f"simulate_dataset workers={workers}: {frames} frames in {s.seconds:6.2f} s = {s.frames_per_second:6.1f} frames/s, "
            f"{s.points_per_frame:9.0f} points/frame, {s.num_labels / frames:4.1f} labels/frame, {size:.2f} GB written"
        )
    finally:
        if keep is None:
            shutil.rmtree(root, ignore_errors=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=500)
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--raycast-frames", type=int, default=100)
    ap.add_argument("--keep", type=Path, default=None, help="write the dataset here and keep it")
    args = ap.parse_args()
    lidar = LidarSpec()
    print(f"sensor: {lidar.beams} beams, {lidar.columns} columns ({lidar.azimuth_step_deg:.3f}° step), "
          f"{lidar.max_range:.0f} m; numpy {np.__version__}")
    bench_raycast(args.raycast_frames, lidar)
    for w in args.workers:
        bench_dataset(args.frames, w, lidar, args.keep)


if __name__ == "__main__":
    main()

"""Decoding speed of the Waymo readers on a simulated segment at Waymo's real size.

TOP lidar 64 × 2650 and FRONT / SIDE_LEFT / SIDE_RIGHT / REAR 200 × 600, two returns each, TOP
per-pixel poses. Prints frames/s for v2 (Parquet) and v1 (TFRecord) decoding into ``Frame``
objects, plus a breakdown (file read vs range image → points).

Usage: ``python scripts/bench_waymo.py [--frames 4] [--repeat 3] [--out DIR]``
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from labelaudit.datasets import open_dataset
from labelaudit.datasets.waymo_common import LidarData, frame_points
from labelaudit.sim.waymo_writer import SIZES, simulate_waymo_segment, write_waymo_v1, write_waymo_v2


def _time_reader(root: Path, fmt: str, repeat: int) -> tuple[float, int, int]:
    reader = open_dataset(root, fmt)
    best, frames, points = float("inf"), 0, 0
    for _ in range(repeat):
        t = time.perf_counter()
        frames = points = 0
        for unit in reader.list_units():
            for f in reader.load_unit(unit):
                frames += 1
                points += len(f.points)
        best = min(best, time.perf_counter() - t)
    return best, frames, points


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None, help="keep the written segment here")
    args = ap.parse_args()

    t = time.perf_counter()
    seg = simulate_waymo_segment(seed=0, frames=args.frames, size="real", chunks=32)
    t_sim = time.perf_counter() - t
    out = args.out or Path(tempfile.mkdtemp(prefix="bench_waymo_"))
    t = time.perf_counter()
    write_waymo_v2(seg, out / "v2", rows_per_group=10)
    t_w2 = time.perf_counter() - t
    t = time.perf_counter()
    write_waymo_v1(seg, out / "v1" / f"{seg.name}.tfrecord")
    t_w1 = time.perf_counter() - t
    size_v2 = sum(p.stat().st_size for p in (out / "v2").rglob("*.parquet"))
    size_v1 = sum(p.stat().st_size for p in (out / "v1").rglob("*.tfrecord"))

    pixels = sum(h * w * 2 for h, w in SIZES["real"].values())
    pts = np.mean([len(f.points) for f in seg.frames])
    print(
        f"segment: {args.frames} frames, {pixels:,} range-image pixels per frame (2 returns), "
        f"{pts:,.0f} points per frame"
    )
    print(
        f"simulate {t_sim:.1f} s; write v2 {t_w2:.2f} s ({size_v2 / 1e6:.1f} MB), v1 {t_w1:.2f} s ({size_v1 / 1e6:.1f} MB)"
    )

    # conversion only (shared by both readers)
    best = float("inf")
    for _ in range(args.repeat):
        t = time.perf_counter()
        for f in seg.frames:
            lidars = [LidarData(n, lid.returns, lid.pixel_pose) for n, lid in f.lidars.items()]
            frame_points(lidars, seg.calibrations, f.pose, "bench", [])
        best = min(best, time.perf_counter() - t)
    print(f"range image -> points only: {args.frames / best:6.2f} frames/s ({best / args.frames * 1e3:.0f} ms/frame)")

    for fmt, root in (("waymo-v2", out / "v2"), ("waymo-v1", out / "v1")):
        sec, frames, points = _time_reader(root, fmt, args.repeat)
        print(
            f"{fmt} decode -> Frame: {frames / sec:6.2f} frames/s ({sec / frames * 1e3:.0f} ms/frame, "
            f"{points / sec / 1e6:.2f} M points/s)"
        )
    if args.out is None:
        import shutil

        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()

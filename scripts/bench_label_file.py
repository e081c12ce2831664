"""Time a frame whose label file has thousands of lines: reading it, and its crop.

Usage: ``python scripts/bench_label_file.py [--lines 100,1000,10000] [--repeat N]``

One simulated KITTI frame (~120k points, the simulator's scene), its label file repeated and
jittered up to the given line counts. Prints, per line count, the time to read the frame and to
crop every box both ways — Open3D per box (K·N: every point against every box) and the BEV grid
that ``crop_frame_pair`` takes from ``CROP_GRID_MIN_BOXES`` boxes on (identical indices) — and
how the time grows with the lines. The model itself is not timed (~13 ms per audited object).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from labelaudit import constants as C
from labelaudit.config import CropParams
from labelaudit.datasets.kitti import KittiReader
from labelaudit.infer import crop
from labelaudit.sim.dataset import simulate_dataset


def _median_s(fn, repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--lines", default="100,1000,10000", help="comma-separated label line counts")
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    counts = [int(v) for v in args.lines.split(",")]
    params = CropParams()
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "sim"
        simulate_dataset(root, frames=1, seed=0, progress=False)
        label = root / "training" / "label_2" / "000000.txt"
        base = [l for l in label.read_text().splitlines() if not l.startswith("DontCare")]
        rng = np.random.default_rng(0)
        print(
            f"{'lines':>6} {'read s':>8} {'Open3D per box s':>17} {'BEV grid s':>11} {'ratio':>6}   (CROP_GRID_MIN_BOXES = {C.CROP_GRID_MIN_BOXES})"
        )
        previous = None
        for n in counts:
            lines = []
            for i in range(n):  # the scene's labels, shifted by up to ±20 m: boxes spread over the cloud
                t = base[i % len(base)].split()
                t[11] = f"{float(t[11]) + rng.uniform(-20, 20):.2f}"
                t[13] = f"{float(t[13]) + rng.uniform(-20, 20):.2f}"
                lines.append(" ".join(t))
            label.write_text("\n".join(lines) + "\n")
            reader = KittiReader(root)
            t_read = _median_s(lambda: reader.load_frame("000000"), args.repeat)
            frame = reader.load_frame("000000")
            boxes = np.ascontiguousarray(frame.boxes)
            wide = replace(params, margin=params.fit_margin)

            def open3d_per_box() -> None:
                fit = crop.crop_frame(frame.points, boxes, wide)
                crop.refine_crop(frame.points, boxes, fit, params)

            t_o3d = _median_s(open3d_per_box, args.repeat)
            t_grid = _median_s(lambda: crop._crop_pair_by_grid(frame.points, boxes, params), args.repeat)
            grow = (
                ""
                if previous is None
                else f"   ×{n / previous[0]:.0f} lines: read ×{t_read / previous[1]:.1f}, grid ×{t_grid / previous[2]:.1f}"
            )
            print(f"{n:>6} {t_read:>8.3f} {t_o3d:>17.3f} {t_grid:>11.3f} {t_o3d / t_grid:>6.1f}{grow}")
            previous = (n, t_read, t_grid)
        shutil.rmtree(root)


if __name__ == "__main__":
    main()

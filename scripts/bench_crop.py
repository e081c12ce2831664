"""Time reading + cropping one frame: Open3D (crop_frame) against the NumPy reference.

Usage: ``python scripts/bench_crop.py [KITTI_ROOT] [--repeat N]``

Without a KITTI root it uses ``../shared/realdata/openpcdet-pr653-kitti`` when present, and a
synthetic 120k-point frame with 20 boxes otherwise (``--synthetic`` forces it). Prints ms per frame.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Callable

import numpy as np

from labelaudit.config import CropParams
from labelaudit.datasets.kitti import KittiReader
from labelaudit.infer.crop import crop_frame, points_in_boxes_numpy

REALDATA = Path(__file__).resolve().parents[2] / "shared" / "realdata" / "openpcdet-pr653-kitti"


def _best_ms(fn: Callable[[], object], repeat: int) -> float:
    """Median wall time of ``fn`` in milliseconds (after one warm-up call)."""
    fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(times))


def synthetic_frame(seed: int = 0, n_points: int = 120_000, n_boxes: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI-sized frame: points over ±60 m with a ground plane, car-sized boxes holding points."""
    rng = np.random.default_rng(seed)
    ground = np.c_[rng.uniform(-60, 60, (n_points // 2, 2)), rng.normal(-1.7, 0.03, n_points // 2)]
    boxes = np.c_[
        rng.uniform(-40, 40, (n_boxes, 2)), np.full(n_boxes, -0.95),
        rng.uniform(3.5, 5.0, n_boxes), rng.uniform(1.6, 2.0, n_boxes), rng.uniform(1.4, 1.7, n_boxes),
        rng.uniform(-np.pi, np.pi, n_boxes),
    ]  # fmt: skip
    per_box = (n_points - len(ground)) // n_boxes
    objs = []
    for b in boxes:
        v = rng.uniform(-0.5, 0.5, (per_box, 3)) * b[3:6]
        c, s = np.cos(b[6]), np.sin(b[6])
        objs.append(np.c_[c * v[:, 0] - s * v[:, 1], s * v[:, 0] + c * v[:, 1], v[:, 2]] + b[:3])
    xyz = np.vstack([ground, *objs])
    return np.c_[xyz, rng.uniform(0, 1, len(xyz))].astype(np.float32), boxes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("root", nargs="?", type=Path, default=None, help="KITTI root (default: the realdata sample)")
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--synthetic", action="store_true", help="use the synthetic 120k-point, 20-box frame")
    args = ap.parse_args()
    params = CropParams()  # the default margin and ground cut
    root = args.root or (REALDATA if REALDATA.is_dir() else None)

    if root is not None and not args.synthetic:
        reader = KittiReader(root)
        refs = reader.list_units()
        frames = [reader.load_frame(r.key) for r in refs]
        read_ms = _best_ms(lambda: [reader.load_frame(r.key) for r in refs], args.repeat) / len(refs)
        # Real KITTI frames hold 1–3 boxes; also time them against 20 copies of their boxes, jittered.
        rng = np.random.default_rng(0)
        cases = [("real boxes", [(f.points, f.boxes) for f in frames])]
        many = []
        for f in frames:
            b = np.repeat(f.boxes, int(np.ceil(20 / max(len(f.boxes), 1))), axis=0)[:20]
            b[:, :2] += rng.normal(0, 5, (len(b), 2))
            many.append((f.points, b))
        cases.append(("20 boxes", many))
        print(f"KITTI {root}: {len(frames)} frames, {np.mean([len(f.points) for f in frames]):,.0f} points on average")
        print(f"  read (velodyne + label + calib):  {read_ms:8.2f} ms/frame")
    else:
        points, boxes = synthetic_frame()
        cases = [("20 boxes", [(points, boxes)])]
        print(f"synthetic frame: {len(points):,} points, {len(boxes)} boxes")

    for name, data in cases:
        o3d_ms = _best_ms(lambda: [crop_frame(p, b, params) for p, b in data], args.repeat) / len(data)
        np_ms = _best_ms(
            lambda: [points_in_boxes_numpy(p, b, params.margin, params.ground_cut) for p, b in data], args.repeat
        ) / len(data)
        k = np.mean([len(b) for _, b in data])
        print(f"  crop, {name} ({k:.1f}/frame): Open3D {o3d_ms:8.2f} ms/frame   NumPy reference {np_ms:8.2f} ms/frame")


if __name__ == "__main__":
    main()

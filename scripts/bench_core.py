"""Benchmark of the core model: median per-object time of inference and of JIoU-GT, BEV and 3D.

Four cases: a near car (l 4.2, w 1.7, h 1.5 at 15 m, 300 points on two faces, 0.05 m
noise), a far car (40 m, 10 points), a single visible face (60 points), 2 points. Prints a table of
medians (ms) and the JIoU-GT values; the last column is the label-error box fit (always 3D
when the points have z), not part of the inference target. Single process, one core; the machine may be shared, so the
median CPU time (``time.process_time``) over a few repetitions is reported.

    python scripts/bench_core.py [--repeat 30]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from labelaudit.config import ModelParams, SpatialParams, load_config
from labelaudit.core import geometry as g
from labelaudit.core.fit import fit_label
from labelaudit.core.posterior import infer_label
from labelaudit.core.spatial import jiou_gt


def points_on_faces(box, faces, n, noise, rng):
    """n points split over the faces (unit-box axis, value), heights spread over the box, plus noise."""
    per = np.array_split(np.arange(n), len(faces))
    out = []
    for (axis, value), idx in zip(faces, per):
        v = rng.uniform(-0.5, 0.5, (len(idx), 3))
        v[:, axis] = value
        out.append(g.unit_to_world(v, box, "3d"))
    pts = np.vstack(out)
    return pts + rng.normal(0.0, noise, pts.shape)


def cases():
    rng = np.random.default_rng(0)
    # Boxes put the sensor (origin) in front of their −x and −y faces.
    near = np.array([15.0, 3.0, 0.75, 4.2, 1.7, 1.5, 0.0])
    far = np.array([40.0, 6.0, 0.75, 4.2, 1.7, 1.5, 0.0])
    two_faces = [(0, -0.5), (1, -0.5)]
    return {
        "near car, 300 pts": (near, points_on_faces(near, two_faces, 300, 0.05, rng)),
        "far car, 10 pts": (far, points_on_faces(far, two_faces, 10, 0.05, rng)),
        "one face, 60 pts": (near, points_on_faces(near, [(0, -0.5)], 60, 0.05, rng)),
        "2 pts": (near, points_on_faces(near, [(0, -0.5)], 2, 0.05, rng)),
    }


def median_ms(fn, repeat):
    """Median CPU time (process_time: not inflated by other processes on a shared machine), ms."""
    fn()  # warm-up: caches (Sobol samples), imports
    times = []
    for _ in range(repeat):
        t0 = time.process_time()
        fn()
        times.append(time.process_time() - t0)
    return 1e3 * statistics.median(times)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=30, help="timed repetitions per cell (median reported)")
    args = ap.parse_args()
    cfg = load_config(None, "kitti")
    spatial: SpatialParams = cfg.spatial
    print(f"cells_per_side={spatial.cells_per_side} num_samples={spatial.num_samples} sigma={cfg.model.sigma}")
    print(f"{'case':<20} {'model':<5} {'infer ms':>9} {'jiou_gt ms':>11} {'total ms':>9} {'jiou_gt':>8} {'fit ms':>7}")
    for name, (box, pts) in cases().items():
        for model in ("bev", "3d"):
            params: ModelParams = ModelParams(**{**cfg.model.__dict__, "model": model})
            t_inf = median_ms(lambda: infer_label(box, pts, "Car", params), args.repeat)
            post = infer_label(box, pts, "Car", params)
            t_j = median_ms(lambda: jiou_gt(post, spatial), args.repeat)
            t_fit = median_ms(lambda: fit_label(box, pts, "Car", params), args.repeat)  # label error
            print(
                f"{name:<20} {model:<5} {t_inf:9.2f} {t_j:11.2f} {t_inf + t_j:9.2f} {jiou_gt(post, spatial):8.4f} {t_fit:7.2f}"
            )


if __name__ == "__main__":
    main()

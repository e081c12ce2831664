"""Test data for the viz tests: a small simulated KITTI dataset audited for real, and an EVAL_DIR.

The EVAL_DIR follows the contract of ``labelaudit eval`` (docs/review.md): ``summary.json`` with
``ap``, ``mean_overlap``, ``counts``, ``dataset``, ``metric``, plus PNG plots.
"""

from __future__ import annotations

import io
import json
from pathlib import Path

from labelaudit.config import resolve_config
from labelaudit.executors import SerialExecutor
from labelaudit.infer.run import InferRequest, run_infer


def simulate_and_infer(root: Path, frames: int = 3, seed: int = 3) -> tuple[Path, Path]:
    """Simulate ``frames`` KITTI frames with injected label errors and run ``infer`` on them (serial)."""
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec

    data, results = root / "sim", root / "results"
    simulate_dataset(data, frames=frames, seed=seed, noise=NoiseSpec(fraction=0.3, gross_fraction=0.1), progress=False)
    run_infer(InferRequest(data, results, "kitti"), resolve_config(None, "kitti"), executor=SerialExecutor())
    return data, results


def tiny_png(colour: str = "#336699") -> bytes:
    """A real 80×60 PNG (matplotlib, Agg)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(0.8, 0.6), dpi=100)
    FigureCanvasAgg(fig)
    fig.patch.set_facecolor(colour)
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


def eval_summary() -> dict:
    """A summary.json as ``labelaudit eval`` writes it: Car at 0.5 and 0.7, Pedestrian at 0.5, R40 and R11."""
    ap = []
    for cls, thresholds in (("Car", (0.5, 0.7)), ("Pedestrian", (0.5,))):
        for thr in thresholds:
            for interp in ("R40", "R11"):
                for metric, base in (("iou", 0.80), ("jiou", 0.70), ("jiou_ratio", 0.75)):
                    for k, diff in enumerate(("Easy", "Moderate", "Hard")):
                        value = (
                            base
                            - 0.1 * k
                            - (0.2 if thr == 0.7 else 0.0)
                            - (0.01 if interp == "R11" else 0.0)
                            - (0.05 if cls == "Pedestrian" else 0.0)
                        )
                        ap.append(
                            {
                                "class": cls,
                                "difficulty": diff,
                                "view": "bev",
                                "metric": metric,
                                "threshold": thr,
                                "interp": interp,
                                "ap": round(value, 4),
                                "num_gt": 40 - 5 * k,
                                "num_det": 55,
                            }
                        )
    overlap = [
        {"difficulty": diff, "distance_bin": b, "metric": m, "mean": 0.7 - 0.05 * i, "count": 10 + i}
        for m in ("iou", "jiou")
        for diff in ("Easy", "Moderate")
        for i, b in enumerate(("0-20 m", "20-40 m", "40+ m"))
    ]
    return {
        "ap": ap,
        "mean_overlap": overlap,
        "counts": {"labels": 120, "detections": 160, "frames": 3},
        "dataset": "sim-kitti",
        "metric": "jiou",
    }


def make_eval_dir(
    path: Path, summary: dict | None = None, plots: tuple[str, ...] = ("pr_curve.png", "jiou_vs_distance.png")
) -> Path:
    """Write an EVAL_DIR fixture: summary.json and real PNG plots."""
    path.mkdir(parents=True, exist_ok=True)
    (path / "summary.json").write_text(json.dumps(summary if summary is not None else eval_summary(), indent=1))
    for i, name in enumerate(plots):
        (path / name).write_bytes(tiny_png(("#336699", "#993366", "#669933")[i % 3]))
    return path


def simulate_with_a_dropped_label(root: Path, frame_id: str = "000001") -> tuple[Path, Path, "object"]:
    """A simulated KITTI dataset whose ``frame_id`` lost the label of its nearest car (its points
    kept), audited for real, with that car's box as missing-label candidate 0 of the frame
    (score 0.93) and a weaker candidate 1 (score 0.55) on open ground; returns (data, results, box).
    The ``missing/`` table is the test's own, whatever the search of ``infer`` found."""
    import shutil

    import numpy as np

    from labelaudit.datasets.kitti import boxes_camera_to_lidar, read_calib, read_label
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec
    from results_factory import add_missing, make_candidate

    data, results = root / "sim", root / "results"
    simulate_dataset(data, frames=3, seed=3, noise=NoiseSpec(fraction=0.3, gross_fraction=0.1), progress=False)
    split = data / "training" if (data / "training").is_dir() else data
    label = split / "label_2" / f"{frame_id}.txt"
    labels = read_label(label)
    boxes = boxes_camera_to_lidar(
        labels.location, labels.dims_hwl, labels.rotation_y, read_calib(split / "calib" / f"{frame_id}.txt")
    )
    cars = [k for k, n in enumerate(labels.class_names) if n == "Car"]
    k = min(cars, key=lambda j: float(np.hypot(*boxes[j, :2])))
    lines = label.read_text().splitlines()
    label.write_text("".join(line + "\n" for j, line in enumerate(lines) if j != k))
    run_infer(InferRequest(data, results, "kitti"), resolve_config(None, "kitti"), executor=SerialExecutor())
    shutil.rmtree(results / "missing", ignore_errors=True)
    b = boxes[k]
    add_missing(
        results,
        [
            [
                make_candidate(
                    frame_id,
                    0,
                    0.93,
                    cx=b[0],
                    cy=b[1],
                    cz=b[2],
                    length=b[3],
                    width=b[4],
                    height=b[5],
                    yaw=b[6],
                    distance=float(np.hypot(b[0], b[1])),
                ),
                make_candidate(
                    frame_id, 1, 0.55, cx=20.0, cy=14.0, distance=float(np.hypot(20.0, 14.0)), num_points=35
                ),
            ]
        ],
    )
    return data, results, b

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
                        value = base - 0.1 * k - (0.2 if thr == 0.7 else 0.0) - (0.01 if interp == "R11" else 0.0) - (0.05 if cls == "Pedestrian" else 0.0)
                        ap.append({"class": cls, "difficulty": diff, "view": "bev", "metric": metric, "threshold": thr, "interp": interp,
                                   "ap": round(value, 4), "num_gt": 40 - 5 * k, "num_det": 55})
    overlap = [
        {"difficulty": diff, "distance_bin": b, "metric": m, "mean": 0.7 - 0.05 * i, "count": 10 + i}
        for m in ("iou", "jiou") for diff in ("Easy", "Moderate") for i, b in enumerate(("0-20 m", "20-40 m", "40+ m"))
    ]
    return {"ap": ap, "mean_overlap": overlap, "counts": {"labels": 120, "detections": 160, "frames": 3}, "dataset": "sim-kitti", "metric": "jiou"}


def make_eval_dir(path: Path, summary: dict | None = None, plots: tuple[str, ...] = ("pr_curve.png", "jiou_vs_distance.png")) -> Path:
    """Write an EVAL_DIR fixture: summary.json and real PNG plots."""
    path.mkdir(parents=True, exist_ok=True)
    (path / "summary.json").write_text(json.dumps(summary if summary is not None else eval_summary(), indent=1))
    for i, name in enumerate(plots):
        (path / name).write_bytes(tiny_png(("#336699", "#993366", "#669933")[i % 3]))
    return path

"""Tiny datasets and the checks of the bad-input contract, shared by test_bad_input.py and test_fuzz.py.

The datasets are small on purpose (three labelled cars with a few hundred LiDAR points per frame,
two-frame Waymo segments of the simulator's "small" lidars), so a fuzz case costs milliseconds.
``run_cli`` runs the real command line in-process and ``check_output`` holds the contract every
run must keep: no exit 3, no traceback or Python warning without ``--debug``, one line on exit 2.
"""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import pyarrow.parquet as pq
from typer.testing import CliRunner

from labelaudit import results as R
from labelaudit.datasets.kitti import (
    Calibration,
    alpha_from_location,
    box_lidar_to_camera,
    format_calib,
    format_label_line,
    project_box_to_image,
    write_velodyne,
)

AXES = np.array([[0.0, -1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
CALIB = Calibration(
    P2=np.array([[700.0, 0, 600, 45], [0, 700, 180, 0], [0, 0, 1, 0.005]]),
    R0_rect=np.eye(3),
    Tr_velo_to_cam=np.c_[AXES, [0.0, -0.08, -0.27]],
)
DONTCARE = "DontCare -1 -1 -10 503.89 169.71 590.61 190.13 -1 -1 -1 -1000 -1000 -1000 -10"


def tiny_frame(seed: int, cars: int = 3, points_per_car: int = 60) -> tuple[np.ndarray, list[str]]:
    """Points (N, 4) float32 on the sensor-facing sides of ``cars`` cars plus ground, and their label lines."""
    rng = np.random.default_rng(seed)
    pts, lines = [rng.uniform([-5, -20, -1.75, 0], [40, 20, -1.7, 1], (150, 4))], []
    for k in range(cars):
        cx, cy, yaw = 8.0 + 9.0 * k + rng.uniform(-1, 1), rng.uniform(-6, 6), rng.uniform(-0.4, 0.4)
        box = np.array([cx, cy, -0.95, 4.2, 1.8, 1.5, yaw])
        u = rng.uniform(-0.5, 0.5, (points_per_car, 3))
        u[: points_per_car // 2, 0] = -0.5  # the rear face (towards the sensor)
        u[points_per_car // 2 :, 1] = -0.5 if cy > 0 else 0.5  # the side facing the sensor
        c, s = np.cos(yaw), np.sin(yaw)
        local = u * box[3:6]
        xyz = np.c_[c * local[:, 0] - s * local[:, 1] + cx, s * local[:, 0] + c * local[:, 1] + cy, local[:, 2] - 0.95]
        pts.append(np.c_[xyz + rng.normal(0, 0.02, xyz.shape), rng.uniform(0, 1, len(xyz))])
        loc, dims, ry = box_lidar_to_camera(box, CALIB)
        bbox = project_box_to_image(box, CALIB)
        lines.append(
            format_label_line("Car", 0.0, int(k % 3), float(alpha_from_location(loc, ry)), bbox, dims, loc, ry)
        )
    return np.concatenate(pts).astype(np.float32), lines


def write_kitti(root: Path, frame_ids: Sequence[str], seed: int = 0, cars: int = 3) -> Path:
    """A KITTI layout under ``root/training`` (velodyne, label_2 with a DontCare row, calib) and ImageSets/val.txt."""
    base = root / "training"
    for sub in ("velodyne", "label_2", "calib"):
        (base / sub).mkdir(parents=True, exist_ok=True)
    for i, fid in enumerate(frame_ids):
        points, lines = tiny_frame(seed * 1000 + i, cars)
        write_velodyne(base / "velodyne" / f"{fid}.bin", points)
        (base / "label_2" / f"{fid}.txt").write_text("\n".join(lines + [DONTCARE]) + "\n")
        (base / "calib" / f"{fid}.txt").write_text(format_calib(CALIB))
    (root / "ImageSets").mkdir(exist_ok=True)
    (root / "ImageSets" / "val.txt").write_text("".join(f"{fid}\n" for fid in frame_ids))
    return root


# --------------------------------------------------------------------------- the command line


runner = CliRunner()
_COMMAND = None  # the Click command of the app, built once (Typer's runner rebuilds it per call: ~50 ms)


@dataclass
class CliRun:
    args: list[str]
    exit_code: int
    stdout: str
    stderr: str
    exception: BaseException | None
    warnings: list[str] = field(default_factory=list)  # Python warnings raised during the run


def run_cli(*args: object) -> CliRun:
    """The real command line, in-process (Typer's runner), stdout and stderr apart."""
    global _COMMAND
    import typer.testing

    from labelaudit.cli import app

    build = typer.testing._get_command
    if _COMMAND is None:
        _COMMAND = build(app)
    argv = [a if isinstance(a, str) else str(a) for a in args]
    typer.testing._get_command = lambda _app: _COMMAND  # type: ignore[assignment]
    try:
        with warnings.catch_warnings(record=True) as caught:  # a user would see these on stderr
            warnings.simplefilter("always")
            r = runner.invoke(app, argv)
    finally:
        typer.testing._get_command = build
    return CliRun(
        argv,
        r.exit_code,
        r.stdout,
        r.stderr,
        r.exception,
        [f"{w.category.__name__}: {w.message} ({w.filename}:{w.lineno})" for w in caught],
    )


_PY_WARNING = re.compile(r"\b\w*Warning: ")


def check_output(run: CliRun, allowed: Sequence[int] = (0, 1, 2)) -> None:
    """The contract of every run without ``--debug``: an allowed exit code (never 3, never a
    crash), no traceback, no Python warning on stderr, and exactly one line on exit 2."""
    where = f"labelaudit {' '.join(run.args)!r}"
    assert run.exit_code != 3, f"{where}: internal error\n{run.stderr}"
    assert run.exit_code in allowed, (
        f"{where}: exit {run.exit_code}, expected {allowed}\n{run.stderr}\n{run.exception!r}"
    )
    if run.exception is not None and not isinstance(run.exception, SystemExit):
        raise AssertionError(f"{where}: raised {run.exception!r}")
    assert "Traceback" not in run.stderr + run.stdout, f"{where}: traceback\n{run.stderr}"
    assert not _PY_WARNING.search(run.stderr), f"{where}: a Python warning on stderr\n{run.stderr}"
    assert not run.warnings, f"{where}: Python warnings (a user sees them on stderr): {run.warnings}"
    if run.exit_code == 2:
        lines = run.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("error: "), (
            f"{where}: exit 2 must print one line 'error: …'\n{run.stderr}"
        )


def rows_by_frame(out: Path) -> dict[str, list[dict]]:
    """The objects table of a results folder, by frame id, rows in object order."""
    out_rows: dict[str, list[dict]] = {}
    for row in sorted(R.read_results(out).to_pylist(), key=lambda r: (r["frame_id"], r["object_index"])):
        out_rows.setdefault(row["frame_id"], []).append(row)
    return out_rows


def errors_of(out: Path) -> list[dict]:
    return pq.read_table(out / R.ERRORS_FILE).to_pylist()


def comparable(rows: list[dict]) -> list[dict]:
    """Rows without the columns that may differ between runs of the same input (none today)."""
    return [dict(r) for r in rows]


# --------------------------------------------------------------------------- a fast stand-in for the core


def quick_audit(
    box, points, class_name, cfg, sensor_origin=(0.0, 0.0, 0.0), *, fit_points=None, evidence=None, clean=False
):
    """Stand-in for :func:`labelaudit.infer.rows.audit_object` with the real input checks and a
    row of the real shape, in microseconds instead of ~13 ms: the fuzz's many cases exercise
    readers, rows and the CLI; one batch per input kind still runs the real core."""
    from labelaudit.core import geometry as g

    y = g.validate_box(box)
    pts = np.asarray(points, dtype=float).reshape(-1, np.shape(points)[1] if np.ndim(points) == 2 else 4)
    n = len(pts)
    status = "no_points" if n == 0 else ("few_points" if n < cfg.model.min_points else "ok")
    row = {
        "status": status,
        "num_points": n,
        "sigma": cfg.model.sigma,
        "jiou_gt": 1.0 - 1.0 / (n + 2.0),
        "label_error": 0.1,
        "sigma_hat": float("nan") if n < 2 else 0.05,
        "fit_offset_m": 0.0,
        "corner_tv": [0.1, 0.2, 0.3, 0.4],
        "cov": list(np.eye(6).ravel()),
        "cov_dim": 6,
        "model": cfg.model.kind,
        "mahalanobis": 0.0,
        "hull_iou": 0.5,
    }
    for name, value in zip(R.BOX_COLUMNS, y):
        row[f"std_{name}"] = 0.1
        row[f"fit_{name}"] = float(value)
    return row

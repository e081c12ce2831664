"""``python -m labelaudit.kernels [status|build [-v]]``: which path this process's kernels take and
why, or compile every kernel ahead of time (:func:`labelaudit.kernels.build`).

The build must see every kernel called at the argument types the commands pass, so it runs the
commands' own work (:func:`workload`): that spans the whole package, from the core to the CLI. It
is therefore this program's, at the top of the layers, never the decorator module's, which every
core module imports.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import sys
import tempfile

import numpy as np

from labelaudit import kernels as K


def workload() -> None:
    """Run what the commands run, in this process, so every kernel is compiled at the types it is
    called with: ``infer`` (KITTI and Waymo, BEV and 3D, rays), ``eval`` (BEV and 3D overlaps,
    JIoU, matching) on a small simulated dataset with detections, the crops of ``show``, and a
    simulated Waymo v2 segment read (its range images)."""
    from labelaudit.cli import app
    from labelaudit.config import load_config, resolve_config
    from labelaudit.datasets import Frame, open_dataset
    from labelaudit.evaluate.warmup import warm_up as eval_warm_up
    from labelaudit.infer.crop import crop_frame
    from labelaudit.infer.missing import find_missing
    from labelaudit.infer.rows import audit_object, process_frame
    from labelaudit.infer.warmup import warm_up
    from labelaudit.sim.dataset import simulate_frame

    warm_up(strict=True)
    eval_warm_up(strict=True)
    sim = simulate_frame(0, seed=0)
    boxes, names = sim.written_boxes, list(sim.scene.class_names)
    for fmt, classes in (
        ("kitti", ("Car", "Van", "Truck", "Pedestrian", "Cyclist")),
        ("waymo", ("Vehicle", "Pedestrian", "Cyclist")),
    ):
        for model in ("bev", "3d"):
            cfg = resolve_config(None, fmt, classes, model)
            mask = np.arange(len(sim.points)) % 2 == 0 if fmt == "waymo" else None  # Waymo: only some points end rays
            as_read = [n if fmt == "kitti" or n in classes else "Vehicle" for n in names]
            frame = Frame("build", sim.points, boxes, as_read, [str(i) for i in range(len(boxes))], ray_mask=mask)
            process_frame(frame, cfg)
            # a box audited from the frame's own float32 rows, as show and the API do (the
            # pipeline hands the model crops it made as float64 itself)
            audit_object(boxes[0], sim.points[:400], as_read[0], cfg, fit_points=sim.points[:600])
            half = len(boxes) // 2  # the missing-label search: half the labels left out, so clusters are boxed
            find_missing(
                Frame("build", sim.points, boxes[:half], as_read[:half], [str(i) for i in range(half)], ray_mask=mask),
                cfg,
            )
    crop_frame(sim.points, boxes, load_config(None, "kitti").crop)
    quiet = (
        contextlib.redirect_stdout(io.StringIO()),
        contextlib.redirect_stderr(io.StringIO()),
    )  # the commands' own reports
    with tempfile.TemporaryDirectory(prefix="labelaudit-kernels-") as tmp, quiet[0], quiet[1]:
        data = f"{tmp}/sim"
        for argv in (
            ["simulate", data, "--frames", "3", "--seed", "1", "--detections", "-q"],
            ["eval", data, f"{data}/detections", "--workers", "1", "-q"],
            ["eval", data, f"{data}/detections", "--workers", "1", "--metric", "3d", "-q"],
            ["simulate", f"{tmp}/waymo", "--dataset-format", "waymo-v2", "--frames", "1", "--size", "small", "-q"],
        ):
            app(argv, standalone_mode=False)
        waymo = open_dataset(f"{tmp}/waymo", "waymo-v2")  # its range images become points
        for ref in waymo.list_units():
            list(waymo.load_unit(ref))


def main(argv: list[str] | None = None) -> int:
    """``python -m labelaudit.kernels [status|build [-v]]``."""
    args = sys.argv[1:] if argv is None else argv
    cmd = args[0] if args else "status"
    if cmd == "build":
        os.environ[K.MODE_ENV] = "jit"  # before the first kernel chooses its path
        if K.kernel_mode()[0] != "jit":
            raise SystemExit("build: this process already loaded the ahead-of-time kernels")
        path = K.build(workload, verbose="-v" in args)
        doc = json.loads(path.read_text(encoding="utf-8"))
        print(
            f"built {doc['functions']} compiled functions of {len(doc['kernels'])} kernels: {path.with_suffix('')}*.so",
            file=sys.stderr,
        )
        return 0
    if cmd == "status":
        mode, why = K.kernel_mode()
        print(f"{mode}: {why}")
        return 0
    print("usage: python -m labelaudit.kernels [status|build [-v]]", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())

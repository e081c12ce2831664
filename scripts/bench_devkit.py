"""KITTI IoU AP of ``labelaudit eval`` beside the official devkit's, on simulated and real frames.

The devkit is not part of labelaudit: this script imports a checkout of a faithful Python port of
``evaluate_object.cpp`` (traveller59/kitti-object-eval-python, the evaluator OpenPCDet and SECOND
ship) from OUTSIDE the project, given with ``--port``:

    git clone https://github.com/traveller59/kitti-object-eval-python /tmp/kitti_eval_port
    python scripts/bench_devkit.py --port /tmp/kitti_eval_port

The port computes rotated-rectangle overlaps with numba.cuda kernels; without a GPU they run in
numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, set here for the port's process only), which is
slow, so the simulated scenes are small (``--frames``, default 40). The port's two imports that do
not resolve outside its home project (SECOND's ``rotate_iou_gpu_eval`` and scikit-image, unused by
the label reader) are pointed at its own ``rotate_iou.py`` and a stub; its code is run unchanged.

Scenes:
  (1) ``labelaudit simulate --detections`` (the synthetic detector), ``--frames`` frames, seed ``--seed``;
  (2) the real KITTI frames of ``../shared/realdata/openpcdet-pr653-kitti`` (or ``$LABELAUDIT_REALDATA``) with the real
      Point-GNN detections of ``pointgnn-kitti-results`` (frames with a result file), when present.

For each scene, view (BEV, 3D), class, difficulty and threshold 0.5:0.05:0.9 it prints the largest
|AP(labelaudit) − AP(devkit)| over R40 and R11, and the headline cells (Car 0.7, Pedestrian and
Cyclist 0.5, moderate). Prints figures only.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
THRESHOLDS = (0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8, 0.85, 0.9)
CLASSES = ("Car", "Pedestrian", "Cyclist")
DIFFICULTIES = ("easy", "moderate", "hard")
REALDATA = Path(os.environ.get("LABELAUDIT_REALDATA", REPO.parent / "shared" / "realdata"))  # as the tests find it


# --------------------------------------------------------------------------- the port, in its own process


def _port_worker(port: str, labels: str, dets: str, ids: list[int]) -> None:
    """Runs in a child process: the port's eval_class for BEV and 3D, precision samples as JSON on stdout."""
    import types

    import numpy as np

    sys.path.insert(0, port)
    import rotate_iou  # the port's own module

    for name in ("second", "second.core", "second.core.non_max_suppression"):
        sys.modules[name] = types.ModuleType(name)
    nms = types.ModuleType("second.core.non_max_suppression.nms_gpu")
    nms.rotate_iou_gpu_eval = rotate_iou.rotate_iou_gpu_eval
    sys.modules[nms.__name__] = nms
    skimage = types.ModuleType("skimage")
    skimage.io = types.ModuleType("skimage.io")
    sys.modules["skimage"], sys.modules["skimage.io"] = skimage, skimage.io
    import importlib

    port_eval = importlib.import_module("eval")
    kc = importlib.import_module("kitti_common")
    gt_annos = kc.get_label_annos(labels, ids)
    dt_annos = kc.get_label_annos(dets, ids)
    # min_overlaps: [threshold, metric (bbox, bev, 3d), class]
    mo = np.array([[[t] * 3] * 3 for t in THRESHOLDS], dtype=float)
    out = {}
    for metric, view in ((1, "bev"), (2, "3d")):
        ret = port_eval.eval_class(gt_annos, dt_annos, [0, 1, 2], [0, 1, 2], metric, mo, num_parts=1)
        out[view] = ret["precision"].tolist()  # [class, difficulty, threshold, 41]
    json.dump(out, sys.stdout)


def port_precision(port: Path, labels: Path, dets: Path, ids: list[int]) -> dict[str, list]:
    env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1"}
    code = f"import sys; sys.path.insert(0, {str(REPO / 'scripts')!r}); import bench_devkit as b; b._port_worker(*sys.argv[1:4], [int(x) for x in sys.argv[4:]])"
    r = subprocess.run(
        [sys.executable, "-c", code, str(port), str(labels), str(dets), *map(str, ids)],
        env=env,
        capture_output=True,
        text=True,
        check=False,
    )
    if r.returncode:
        raise SystemExit(f"the devkit port failed:\n{r.stderr[-3000:]}")
    return json.loads(r.stdout)


# --------------------------------------------------------------------------- labelaudit


def ours(dataset: Path, dets: Path, view: str) -> dict[tuple[str, str, float, str], float | None]:
    import numpy as np

    from labelaudit.config import RunConfig
    from labelaudit.datasets.detections import read_detections
    from labelaudit.datasets.gt import load_ground_truth
    from labelaudit.evaluate.labels import LabelSet
    from labelaudit.evaluate.run import evaluate

    gt = load_ground_truth(dataset, "kitti")
    d = read_detections(dets, gt, view=view)
    n = len(gt.boxes)
    p = 6 if view == "bev" else 8
    labels = LabelSet(np.full((n, p, p), np.nan), np.ones(n), [""] * n, np.ones(n, bool), view, "none", Path("-"))
    s = evaluate(gt, d, labels, CLASSES, view, RunConfig(), metrics=("iou",), workers=1).summary
    return {(r["class"], r["difficulty"], r["threshold"], r["interp"]): r["ap"] for r in s["ap"]}


def compare(name: str, port: Path, dataset: Path, labels: Path, dets: Path, ids: list[int]) -> float:
    import numpy as np

    prec = port_precision(port, labels, dets, ids)
    worst = 0.0
    print(f"== {name}: {len(ids)} frames")
    for view in ("bev", "3d"):
        mine = ours(dataset, dets, view)
        P = np.asarray(prec[view])
        diffs, head = [], []
        for c, cls in enumerate(CLASSES):
            for d, dname in enumerate(DIFFICULTIES):
                for k, t in enumerate(THRESHOLDS):
                    dev = {
                        "R40": float(P[c, d, k, 1:41].sum() / 40 * 100),
                        "R11": float(P[c, d, k, 0:41:4].sum() / 11 * 100),
                    }
                    for interp in ("R40", "R11"):
                        a = mine.get((cls, dname, t, interp))
                        if a is None:  # no GT of the class at this difficulty: the devkit divides by zero (NaN or 0)
                            continue
                        diffs.append(abs(a - dev[interp]))
                        if dname == "moderate" and t == (0.7 if cls == "Car" else 0.5):
                            head.append(f"{cls} {interp} {a:.2f}/{dev[interp]:.2f}")
        m = max(diffs) if diffs else 0.0
        worst = max(worst, m)
        print(
            f"  {view}: {len(diffs)} AP cells, max |labelaudit − devkit| = {m:.4f} AP; moderate headline (labelaudit/devkit): {'; '.join(head)}"
        )
    return worst


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--port",
        type=Path,
        required=True,
        help="checkout of traveller59/kitti-object-eval-python (outside the project)",
    )
    ap.add_argument("--frames", type=int, default=40, help="simulated frames (0: real frames only)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=Path("/tmp/labelaudit-bench-devkit"))
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))

    worst = 0.0
    sim = args.data / f"sim-{args.frames}-{args.seed}"
    if args.frames <= 0:
        sim = None
    if sim is not None and not (sim / "READY").is_file():
        subprocess.run(
            [
                sys.executable,
                "-m",
                "labelaudit",
                "simulate",
                str(sim),
                "--frames",
                str(args.frames),
                "--seed",
                str(args.seed),
                "--detections",
                "--overwrite",
                "-q",
            ],
            check=True,
            env={**os.environ, "PYTHONPATH": str(REPO)},
        )
        (sim / "READY").write_text("")
    if sim is not None:
        labels = sim / "training" / "label_2"
        ids = sorted(int(p.stem) for p in labels.glob("*.txt"))
        with tempfile.TemporaryDirectory() as tmp:
            dets = Path(tmp) / "dets"
            dets.mkdir()
            for i in ids:  # the port reads one file per frame; a frame without detections gets an empty one
                src = sim / "detections" / f"{i:06d}.txt"
                (dets / src.name).write_text(src.read_text() if src.is_file() else "")
            worst = max(
                worst,
                compare(
                    f"simulated ({args.frames} frames, seed {args.seed}, synthetic detector)",
                    args.port,
                    sim,
                    labels,
                    dets,
                    ids,
                ),
            )

    real = REALDATA / "openpcdet-pr653-kitti"
    pg = REALDATA / "pointgnn-kitti-results" / "results" / "data"
    if real.is_dir() and pg.is_dir():
        ids = sorted(int(p.stem) for p in pg.glob("*.txt"))
        with tempfile.TemporaryDirectory() as tmp:
            ds = Path(tmp) / "kitti"
            (ds / "training").mkdir(parents=True)
            (ds / "ImageSets").mkdir()
            (ds / "ImageSets" / "val.txt").write_text("".join(f"{i:06d}\n" for i in ids))
            for sub in ("label_2", "calib"):
                (ds / "training" / sub).mkdir()
                for i in ids:
                    (ds / "training" / sub / f"{i:06d}.txt").symlink_to(real / "training" / sub / f"{i:06d}.txt")
            (ds / "training" / "velodyne").mkdir()
            for i in ids:
                (ds / "training" / "velodyne" / f"{i:06d}.bin").symlink_to(
                    real / "training" / "velodyne" / f"{i:06d}.bin"
                )
            dets = Path(tmp) / "dets"
            dets.mkdir()
            for i in ids:  # the port splits every line, a blank one included (000005.txt is one newline)
                src = pg / f"{i:06d}.txt"
                (dets / src.name).write_text(
                    "".join(line for line in src.read_text().splitlines(keepends=True) if line.strip())
                )
            worst = max(
                worst,
                compare(
                    "real KITTI frames, real Point-GNN detections",
                    args.port,
                    ds,
                    ds / "training" / "label_2",
                    dets,
                    ids,
                ),
            )
    else:
        print(f"(no {REALDATA}: real frames skipped)")
    print(f"largest |AP difference| over every scene, view, class, difficulty, threshold, R40/R11: {worst:.4f}")


if __name__ == "__main__":
    main()

"""Benchmark of ``labelaudit eval`` on a KITTI-val-sized synthetic set.

Prepares once (kept in --data; reused when present): ``labelaudit simulate`` of 3,769 frames with
about 4 labels each (≈ 15k GT) and a lighter LiDAR (1,024 columns: the points only feed ``infer``),
the synthetic detector (≈ 50k detections including low-score false positives) and ``labelaudit
infer --classes all`` for the label covariances. Then times:

(a) the CLI, ``labelaudit eval DATA DETS --results RESULTS -o EVAL_DIR`` in a fresh process (target ≤ 60 s
    on 2 cores), with its stage timings;
(b) the IoU-only part in-process (reading, IoU of all pairs, devkit matching of the IoU cells) —
    what a devkit-style evaluator does;
(c) JIoU per candidate pair (the JIoU stage over the pairs it computed);
(d) LET-3D-AP / APL (``eval --let``) in-process: the Hungarian matching at 101 score cut-offs.

Prints figures only; run it once, not in a loop: ``python scripts/bench_eval.py --data /tmp/bench-eval``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def _cli(*args: str) -> list[str]:
    return [sys.executable, "-m", "labelaudit.cli", *args]


def prepare(data: Path, frames: int, workers: int) -> tuple[Path, Path, Path]:
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.detector import DetectorSpec, simulate_detections
    from labelaudit.sim.noise import NoiseSpec
    from labelaudit.sim.raycast import LidarSpec
    from labelaudit.sim.scene import SceneSpec

    sim, results = data / "sim", data / "results"
    dets = sim / "detections"
    marker = data / "READY.json"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    if marker.is_file() and json.loads(marker.read_text()).get("frames") == frames:
        if not _results_fit(sim, results):  # labelaudit or its constants changed since: audit again
            t = time.perf_counter()
            subprocess.run(
                _cli(
                    "infer",
                    str(sim),
                    "-o",
                    str(results),
                    "--classes",
                    "all",
                    "--workers",
                    str(workers),
                    "--overwrite",
                    "-q",
                ),
                check=True,
                env=env,
            )
            print(f"re-ran infer (results of another labelaudit build): {time.perf_counter() - t:.0f} s")
        return sim, dets, results
    t = time.perf_counter()
    simulate_dataset(
        sim,
        frames=frames,
        seed=0,
        noise=NoiseSpec.benchmark(),
        lidar=LidarSpec(columns=1024),
        scene=SceneSpec(num_vehicles=(2, 7), num_vru=(0, 3)),
        workers=workers,
        progress=True,
        overwrite=True,
    )
    t_sim = time.perf_counter() - t
    t = time.perf_counter()
    det = simulate_detections(sim, DetectorSpec(), seed=0)
    t_det = time.perf_counter() - t
    t = time.perf_counter()
    subprocess.run(
        _cli("infer", str(sim), "-o", str(results), "--classes", "all", "--workers", str(workers), "--overwrite", "-q"),
        check=True,
        env=env,
    )
    t_inf = time.perf_counter() - t
    marker.write_text(
        json.dumps(
            {
                "frames": frames,
                "simulate_s": round(t_sim, 1),
                "detector_s": round(t_det, 1),
                "infer_s": round(t_inf, 1),
                "detections": det.detections,
            }
        )
    )
    print(f"prepared in {data}: simulate {t_sim:.0f} s, detector {t_det:.1f} s, infer {t_inf:.0f} s")
    return sim, dets, results


def _results_fit(sim: Path, results: Path) -> bool:
    from labelaudit.config import resolve_config
    from labelaudit.errors import EvalError, ResultsError
    from labelaudit.evaluate.labels import check_results_match
    from labelaudit.results import open_results

    try:
        check_results_match(open_results(results), sim, "kitti", resolve_config(None, "kitti", None, "bev"))
        return True
    except (EvalError, ResultsError):
        return False


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--data", type=Path, default=Path("/tmp/labelaudit-bench-eval"), help="where the prepared set lives (reused)"
    )
    ap.add_argument("--frames", type=int, default=3769)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args()
    sim, dets, results = prepare(args.data, args.frames, args.workers)
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    import resource

    out = args.data / "eval"
    load0 = os.getloadavg()[0]
    ru0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    subprocess.run(
        _cli(
            "eval", str(sim), str(dets), "--results", str(results), "-o", str(out), "--workers", str(args.workers), "-q"
        ),
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )
    wall = time.perf_counter() - t
    ru1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (ru1.ru_utime - ru0.ru_utime) + (ru1.ru_stime - ru0.ru_stime)
    load1 = os.getloadavg()[0]
    summary = json.loads((out / "summary.json").read_text())
    c, tm = summary["counts"], summary["timings"]
    print(
        f"set: {c['frames']} frames, {c['gt']} GT boxes ({c['labels_used']} with label distributions), {c['detections']} detections, {c['jiou_pairs']} JIoU pairs"
    )
    print(
        f"(a) labelaudit eval (CLI, fresh process, {args.workers} workers): {wall:.1f} s wall — target <= 60 s; "
        f"{cpu:.1f} CPU-s in the process and its waited-for children (fork-server workers may be missing); load average {load0:.1f} → {load1:.1f} on {os.cpu_count()} cores"
    )
    print("    stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in tm.items() if k != "jiou_pairs"))

    import numpy as np

    from labelaudit.config import RunConfig
    from labelaudit.datasets.detections import read_detections
    from labelaudit.datasets.gt import load_ground_truth
    from labelaudit.evaluate.labels import LabelSet
    from labelaudit.evaluate.run import evaluate

    t, c0 = time.perf_counter(), time.process_time()
    gt = load_ground_truth(sim, "kitti")
    d = read_detections(dets, gt)
    t_read = time.perf_counter() - t
    n = len(gt.boxes)
    labels = LabelSet(np.full((n, 6, 6), np.nan), np.ones(n), [""] * n, np.ones(n, bool), "bev", "none", Path("-"))
    tm2: dict[str, float] = {}
    t = time.perf_counter()
    evaluate(gt, d, labels, tuple(summary["classes"]), "bev", RunConfig(), metrics=("iou",), timings=tm2)
    t_eval = time.perf_counter() - t
    print(
        f"(b) IoU-only part, in-process, 1 process: {t_read + t_eval:.1f} s wall, {time.process_time() - c0:.1f} CPU-s (read labels + detections {t_read:.1f} s, "
        f"IoU of all pairs {tm2['iou']:.2f} s, devkit matching of {len(summary['classes'])} classes x 3 difficulties x {len(summary['metric']['map_thresholds'])} thresholds {tm2['matching']:.2f} s)"
    )
    from labelaudit.evaluate.run import let_ap_records

    t, c0 = time.perf_counter(), time.process_time()
    recs = let_ap_records(gt, d, tuple(summary["classes"]))
    print(
        f"(d) LET-3D-AP/APL of {len(summary['classes'])} classes x 3 difficulties ({len(recs)} records), 1 process: "
        f"{time.perf_counter() - t:.1f} s wall, {time.process_time() - c0:.1f} CPU-s"
    )
    pairs = max(c["jiou_pairs"], 1)
    print(
        f"(c) JIoU: {tm['jiou']:.1f} s for {c['jiou_pairs']} pairs on {args.workers} workers = {tm['jiou'] / pairs * 1e3:.2f} ms per pair wall, "
        f"{tm['jiou'] / pairs * 1e3 * args.workers:.2f} ms per pair per core"
    )


if __name__ == "__main__":
    main()

"""Benchmark of the review export, ``labelaudit export RESULTS --format kitti-labels -o review/``.

Simulates N KITTI frames with injected label errors (default 120), audits them with ``infer``
(the missing-label search included), then times :func:`labelaudit.review.export_review` end to end
(read the results and the missing table, read every label and calibration file, convert and write
the suggested boxes and candidates, changes.csv, review.json) with ``--min-label-error 0`` so that
every fitted label gets a line (the most work per frame). Prints the median wall and CPU time of a
few repetitions per frame (the machine may be shared: CPU time is the steadier figure).

    python scripts/bench_review.py [--frames 120] [--repeat 3]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from labelaudit.config import resolve_config
from labelaudit.executors import SerialExecutor
from labelaudit.infer.run import InferRequest, run_infer
from labelaudit.review import export_review
from labelaudit.sim.dataset import simulate_dataset
from labelaudit.sim.noise import NoiseSpec


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-review-") as tmp:
        root = Path(tmp)
        data, results = root / "sim", root / "results"
        simulate_dataset(
            data, frames=args.frames, seed=11, noise=NoiseSpec(fraction=0.3, gross_fraction=0.1), progress=False
        )
        run_infer(InferRequest(data, results, "kitti"), resolve_config(None, "kitti"), executor=SerialExecutor())
        walls, cpus = [], []
        summary = None
        for k in range(args.repeat):
            t, c = time.perf_counter(), time.process_time()
            summary = export_review(results, root / f"review{k}", min_label_error=0.0)
            walls.append(time.perf_counter() - t)
            cpus.append(time.process_time() - c)
        assert summary is not None
        wall, cpu = statistics.median(walls), statistics.median(cpus)
        print(f"export --format kitti-labels: {summary.frames_written} frames, {summary.labels} labels, "
              f"{summary.suggested} suggested boxes, {summary.missing} candidates")  # fmt: skip
        print(f"  median of {args.repeat}: {wall:.2f} s wall ({1e3 * wall / summary.frames_written:.1f} ms/frame), "
              f"{cpu:.2f} s CPU ({1e3 * cpu / summary.frames_written:.1f} ms/frame)")  # fmt: skip


if __name__ == "__main__":
    main()

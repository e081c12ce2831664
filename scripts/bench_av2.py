"""Reading speed of the Argoverse 2 reader: simulated logs at the real sensors' resolution, and the real logs.

A simulated log (two VLP-32C-like lidars, 0.2° azimuth step, ~70k points per sweep; a real sweep
has ~100k) is written and read back into ``Frame`` objects (``load_unit``) and as labels only
(``labels``, what ``eval`` reads). When ``../shared/realdata/av2-sensor`` exists, its two logs are
read too (312 frames, 3 sweeps of ~100k points, the other frames annotation-only).

Usage: ``python scripts/bench_av2.py [--frames 20] [--logs 2] [--repeat 3]``
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from labelaudit.datasets import open_dataset
from labelaudit.sim.av2_writer import simulate_av2_log, write_av2_log


def _time(root: Path, repeat: int, labels_only: bool) -> tuple[float, int, int, int]:
    """Best wall time of reading every frame, and the frames, points and boxes read."""
    reader = open_dataset(root, "av2")
    best, frames, points, boxes = float("inf"), 0, 0, 0
    for _ in range(repeat):
        t = time.perf_counter()
        frames = points = boxes = 0
        for unit in reader.list_units():
            for f in (reader.labels(unit) if labels_only else reader.load_unit(unit)):
                frames += 1
                points += len(f.points)
                boxes += f.num_objects
        best = min(best, time.perf_counter() - t)
    return best, frames, points, boxes


def _report(what: str, root: Path, repeat: int) -> None:
    for labels_only in (False, True):
        dt, frames, points, boxes = _time(root, repeat, labels_only)
        mode = "labels()   " if labels_only else "load_unit()"
        print(f"{what} {mode}: {frames} frames in {dt:6.3f} s = {frames / dt:7.1f} frames/s, {1e3 * dt / frames:6.2f} ms/frame, "
              f"{points / max(frames, 1):8.0f} points/frame, {boxes / max(frames, 1):5.1f} boxes/frame")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per simulated log")
    ap.add_argument("--logs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--realdata", type=Path, default=Path(__file__).resolve().parents[1].parent / "shared" / "realdata")
    args = ap.parse_args()

    root = Path(tempfile.mkdtemp(prefix="labelaudit-bench-av2-"))
    try:
        t = time.perf_counter()
        logs = [simulate_av2_log(seed=i, frames=args.frames, size="real") for i in range(args.logs)]
        t_sim = time.perf_counter() - t
        t = time.perf_counter()
        for log in logs:
            write_av2_log(log, root / "val")
        t_write = time.perf_counter() - t
        n = args.logs * args.frames
        print(f"simulated {args.logs} logs x {args.frames} frames: simulate {1e3 * t_sim / n:.1f} ms/frame, write {1e3 * t_write / n:.1f} ms/frame")
        _report("simulated", root, args.repeat)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    real = args.realdata / "av2-sensor"
    if real.is_dir():
        _report("real     ", real, args.repeat)


if __name__ == "__main__":
    main()

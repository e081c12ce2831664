"""Benchmark of `labelaudit infer` against the read + crop floor (issue 4, "Speed").

Simulates a KITTI-sized sample (default 300 full 360° scans of ~120k points, labels in the camera
view like KITTI), then times in one run:

  (a) reading every frame and cropping every audited box, in one process — the floor no
      implementation can beat (the same reader and Open3D crop that infer uses);
  (a2) the same floor spread over the worker pool (for reference: what 2 cores could do at best);
  (b) `labelaudit infer` on the same data with 2 workers (a fresh results folder).

Target: (b) ≤ 2 × (a). Prints both, their ratio, and objects/s. Timings depend on the machine's
load; on a shared machine run it when it is quiet and repeat.

    .venv/bin/python scripts/bench_infer.py [--frames 300] [--workers 2] [--data DIR]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time
from pathlib import Path


def _read_and_crop(refs_and_cfg: tuple) -> tuple[int, int]:
    """Worker of the floor: read + crop only, return (frames, boxes)."""
    refs, cfg = refs_and_cfg
    from labelaudit.infer.crop import crop_frame
    from labelaudit.infer.rows import wants_class
    from labelaudit.infer.run import _reader

    frames = boxes = 0
    for ref in refs:
        for frame in _reader(ref, ()).load_unit(ref):
            sel = [i for i, c in enumerate(frame.class_names) if wants_class(cfg, c)]
            idx = crop_frame(frame.points, frame.boxes[sel], cfg.crop)
            frames += 1
            boxes += len(idx)
    return frames, boxes


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=300)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--data", type=Path, default=None, help="reuse (or create) the simulated dataset here")
    args = ap.parse_args()

    from labelaudit.executors import PoolExecutor
    from labelaudit.config import resolve_config
    from labelaudit.infer.run import chunk_size_for, InferRequest, plan_chunks, run_infer
    from labelaudit.datasets import open_dataset
    from labelaudit.sim.noise import NoiseSpec
    from labelaudit.sim.dataset import simulate_dataset

    tmp = tempfile.TemporaryDirectory(prefix="bench-infer-")
    data = args.data or Path(tmp.name) / "sim"
    if not (data / "manifest.parquet").is_file():
        t = time.perf_counter()
        s = simulate_dataset(data, frames=args.frames, seed=args.seed, noise=NoiseSpec.benchmark(),
                             workers=args.workers, progress=False)
        print(f"simulated {s.frames} frames, {s.num_points / s.frames:,.0f} points/frame, {s.num_labels} labels in {time.perf_counter() - t:.1f} s")
    cfg = resolve_config(None, "kitti")
    refs = open_dataset(data, "kitti").list_units()[: args.frames]
    print(f"machine: {os.cpu_count()} cores (shared machines give noisy timings); frames {len(refs)}; classes {', '.join(cfg.classes)}")

    # (a) floor: read + crop, one process (after a warm-up frame: imports, file cache)
    _read_and_crop((refs[:1], cfg))
    t = time.perf_counter()
    frames, boxes = _read_and_crop((refs, cfg))
    floor = time.perf_counter() - t
    print(f"(a)  read + crop, 1 process:        {floor:7.2f} s  ({frames / floor:6.1f} frames/s, {boxes / floor:7.0f} boxes/s, {boxes} boxes)")

    # (a2) floor over the pool, same chunks as infer
    chunks = [(c, cfg) for _, c in plan_chunks(refs, chunk_size_for("kitti", len(refs)))]
    ex = PoolExecutor(args.workers)
    t = time.perf_counter()
    list(ex.run(chunks, _read_and_crop))
    floor_pool = time.perf_counter() - t
    print(f"(a2) read + crop, {args.workers} workers:       {floor_pool:7.2f} s  ({frames / floor_pool:6.1f} frames/s)")

    # (b) infer with the pool
    class Clock:
        first = last = None

        def start(self, total_units, done_units):
            pass

        def advance(self, result):
            now = time.perf_counter()
            self.first = self.first or now
            self.last = now

        def stop(self):
            pass

    clock = Clock()
    out = Path(tmp.name) / "results"
    t = time.perf_counter()
    summary = run_infer(InferRequest(data, out, "kitti", limit=args.frames, overwrite=True), cfg, clock, executor=PoolExecutor(args.workers))
    total = time.perf_counter() - t
    print(f"(b)  labelaudit infer, {args.workers} workers:  {total:7.2f} s  ({summary.frames / total:6.1f} frames/s, {summary.objects / total:7.1f} objects/s, {summary.objects} objects)")
    print(f"     of which worker start-up until the first shard: {clock.first - t:.2f} s")
    print(f"ratio (b)/(a) = {total / floor:.2f}  (target ≤ 2);  (b)/(a2) = {total / floor_pool:.2f}")

    # serial cost per object on a sample, after a warm-up frame (imports, caches)
    sample = refs[1 : 1 + max(1, min(len(refs) - 1, 16))]
    _read_and_crop((refs[:1], cfg))
    from labelaudit.infer.run import ChunkTask, process_chunk

    process_chunk(ChunkTask("warm", tuple(refs[:1]), cfg))
    t = time.perf_counter()
    res = process_chunk(ChunkTask("sample", tuple(sample), cfg))
    dt = time.perf_counter() - t
    t = time.perf_counter()
    _, boxes = _read_and_crop((sample, cfg))
    dt_floor = time.perf_counter() - t
    print(
        f"serial, warm, {res.frames} frames: {dt / max(res.objects, 1) * 1e3:.2f} ms per object in total, "
        f"of which read + crop {dt_floor / max(boxes, 1) * 1e3:.2f} ms"
    )
    tmp.cleanup()


if __name__ == "__main__":
    main()

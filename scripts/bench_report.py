"""Benchmark of ``labelaudit report``: 30,000 objects, a 50-picture gallery, ≤ 30 s, HTML ≤ 10 MB.

A real simulated KITTI dataset is audited by ``infer`` (its rows are the gallery's candidates, and
the pictures are recomputed from its frames). The results are then grown to ``--objects`` rows with
the Parquet writer of :mod:`labelaudit.results`: replica k of a frame is a hard link of its files
under a new frame id (``r<k>_<frame>``) and its rows are the frame's rows under that id, so every
row is the exact audit of a frame on disk, the plots run over all rows and each gallery picture
reads and recomputes its own frame (no frame is read twice: the worst case for the gallery).
``--top`` is raised until the two galleries hold at least ``--pictures`` distinct objects.

Prints: the CLI's wall time (a fresh process, imports included), the in-process stage timings,
seconds per picture and the HTML size.

    python scripts/bench_report.py [--objects 30000] [--pictures 50] [--frames 20] [--workers 2]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pyarrow as pa

from labelaudit import results as R
from labelaudit.config import resolve_config
from labelaudit.executors import PoolExecutor, SerialExecutor
from labelaudit.infer.run import InferRequest, run_infer


def grow(src: Path, dst: Path, data: Path, objects: int) -> int:
    """Copy results ``src`` into ``dst`` grown to ``objects`` rows (see the module docstring).

    Replica k of frame F is a hard link of F's files under the frame id ``r<k>_<F>`` in ``data``, and
    its rows are F's rows with that frame id: every row is the exact audit of a frame that exists.
    """
    opened = R.open_results(src)
    base = opened.read()
    n = base.num_rows
    reps = max(0, -(-objects // n) - 1)
    frames = base.column("frame_id").to_pylist()
    training = data / "training"
    parts = {"velodyne": ".bin", "label_2": ".txt", "calib": ".txt"}
    tables = [base]
    for k in range(1, reps + 1):
        new_ids = {fid: f"r{k:04d}_{fid}" for fid in set(frames)}
        for fid, nid in new_ids.items():
            for sub, ext in parts.items():
                target = training / sub / f"{nid}{ext}"
                if not target.exists():
                    os.link(training / sub / f"{fid}{ext}", target)
        t = base
        for name, values in (
            ("frame_id", pa.array([new_ids[f] for f in frames])),
            (
                "object_id",
                pa.array([f"{new_ids[f]}:{i}" for f, i in zip(frames, base.column("object_index").to_pylist())]),
            ),
        ):
            i = t.schema.get_field_index(name)
            t = t.set_column(i, t.schema.field(i), values)
        tables.append(t)
    big = pa.concat_tables(tables).slice(0, max(objects, n))
    meta = opened.manifest
    shard = 4096
    for i in range(0, big.num_rows, shard):
        R.write_parquet_atomic(
            R.with_metadata(big.slice(i, shard), meta), dst / R.OBJECTS_DIR / f"part-{i // shard:05d}.parquet"
        )
    R.write_parquet_atomic(R.with_metadata(opened.errors(), meta), dst / R.ERRORS_FILE)
    R.write_json_atomic(meta, dst / R.MANIFEST_NAME)
    return big.num_rows


def gallery_top(results: Path, pictures: int) -> tuple[int, int]:
    """The smallest --top whose two galleries hold ≥ ``pictures`` distinct objects, and that count."""
    from labelaudit.rank import RankQuery, rank_results
    from labelaudit.viz.objects import AUDITED_STATUSES

    opened = R.open_results(results)
    top = max(1, pictures // 2)
    while True:
        keys = set()
        for by, mp in (("label_error", None), ("jiou_gt", 1)):
            t = rank_results(opened, RankQuery(by=by, top=top, min_points=mp, statuses=AUDITED_STATUSES)).table
            keys |= set(zip(t.column("frame_id").to_pylist(), t.column("object_index").to_pylist()))
        if len(keys) >= pictures or top > 10 * pictures:
            return top, len(keys)
        top += 1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--objects", type=int, default=30_000)
    ap.add_argument("--pictures", type=int, default=50)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--keep", type=Path, default=None, help="work folder to keep (default: a temporary one)")
    args = ap.parse_args()
    from labelaudit.sim.dataset import simulate_dataset
    from labelaudit.sim.noise import NoiseSpec

    tmp = None if args.keep else tempfile.TemporaryDirectory(prefix="bench-report-")
    work = args.keep or Path(tmp.name)
    data, real, big = work / "sim", work / "results-real", work / "results-big"
    t0 = time.perf_counter()
    simulate_dataset(
        data,
        frames=args.frames,
        seed=11,
        noise=NoiseSpec.benchmark(),
        progress=False,
        workers=args.workers,
        overwrite=True,
    )
    executor = PoolExecutor(args.workers) if args.workers > 1 else SerialExecutor()
    run_infer(InferRequest(data, real, "kitti", overwrite=True), resolve_config(None, "kitti"), executor=executor)
    if big.exists():
        import shutil

        shutil.rmtree(big)
    rows = grow(real, big, data, args.objects)
    top, distinct = gallery_top(big, args.pictures)
    print(
        f"setup: {args.frames} simulated frames, {R.open_results(real).dataset.count_rows()} real rows grown to {rows}; "
        f"--top {top} gives {distinct} gallery pictures ({time.perf_counter() - t0:.1f} s)"
    )

    out = work / "report.html"
    t = time.perf_counter()
    child_cpu = resource.getrusage(resource.RUSAGE_CHILDREN)
    cmd = [
        sys.executable,
        "-m",
        "labelaudit.cli",
        "report",
        str(big),
        "-o",
        str(out),
        "--top",
        str(top),
        "--gate",
        "default",
        "--quiet",
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cli_cpu = (after.ru_utime - child_cpu.ru_utime) + (after.ru_stime - child_cpu.ru_stime)
    if proc.returncode != 0:
        sys.exit(f"report failed ({proc.returncode}): {proc.stderr}")
    size = out.stat().st_size
    print(
        f"CLI `labelaudit report` (fresh process): {wall:.1f} s wall, {cli_cpu:.1f} s CPU, HTML {size / 1e6:.2f} MB  [targets ≤ 30 s, ≤ 10 MB]"
    )

    from labelaudit.viz.report import build_report

    cpu = time.process_time()
    s = build_report(big, work / "report2.html", top=top, gate="default")
    cpu = time.process_time() - cpu
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in s.timings.items())
    per, per_cpu = s.timings["gallery"] / max(s.pictures, 1), s.cpu_timings["gallery"] / max(s.pictures, 1)
    print(f"in-process: {s.seconds:.1f} s wall, {cpu:.1f} s CPU (wall per stage: {stages})")
    print(
        f"gallery: {s.pictures} pictures, {per:.3f} s wall / {per_cpu:.3f} s CPU per picture (frame read, crop, model, p_G, drawing)  [target ≤ 0.3 s]"
    )
    print(
        f"machine load average during the run: {' '.join(f'{v:.1f}' for v in os.getloadavg())} on {os.cpu_count()} cores"
    )
    if tmp is not None:
        tmp.cleanup()


if __name__ == "__main__":
    main()

"""Scaling benchmarks of `labelaudit infer`: workers, Dask, memory, and a Waymo-scale projection.

Prints, each repeated ``--repeat`` times (median and range, with the machine's load average):

  workers    480 simulated frames, ``labelaudit infer --workers 1`` and ``--workers 2`` (subprocesses):
             wall time, start-up (until the first shard), CPU of the process tree, speed-up 2 vs 1,
             beside what the machine gives two busy pure-Python loops in the same repeat (2.0 on two
             free cores; a shared VM often gives less, and it varies by the minute). Target: the
             pool's speed-up ≥ 0.9 × the machine's own.
  dask       the same run with ``--scheduler local:2`` (a LocalCluster of 2 worker processes)
             against the 2-worker pool: wall time including the cluster's start, and the span from
             the first to the last shard. Target: within 10 %.
  memory     peak RSS (and PSS, which counts pages shared with the fork server once) of each pool
             worker, the fork server, and each Dask worker, sampled every 50 ms during those runs.
             Target: ≤ 300 MiB per worker.
  waymo      a simulated Waymo v2 segment at the real sensor size (5 lidars, 2 returns): CPU per
             frame in one warm process, split into the frame part (read) and the per-box part
             (crop, model, rows), and the projection to the Waymo Open Dataset (1,150 segments ×
             200 frames, ≈ 12 M boxes): frames/s per worker, worker-hours, workers for ≤ 1 h.

    .venv/bin/python scripts/bench_scale.py [--frames 480] [--repeat 2] [--data DIR] [--only workers,dask,waymo]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_infer import (  # noqa: E402
    REPO,
    become_subreaper,
    like_a_worker,
    load,
    run_tree,
    simulate,
    spread,
    warm_stages,
)

MIB = 1024 * 1024
WAYMO_FRAMES = 1150 * 200  # segments × frames of the Waymo Open Dataset (perception, all splits)
WAYMO_BOXES = 12_000_000  # 3D lidar labels, all classes (≈ 52 per frame)


class MemorySampler:
    """Peak RSS / PSS per descendant process of this one, by role, sampled in a thread."""

    def __init__(self, interval: float = 0.05):
        import psutil

        self.psutil = psutil
        self.me = psutil.Process()
        self.interval = interval
        self.peak: dict[int, tuple[str, float, float]] = {}
        self.before = {p.pid for p in self.me.children()}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _role(self, p) -> str:
        cmd = " ".join(p.cmdline())
        parent = p.parent()
        pcmd = " ".join(parent.cmdline()) if parent else ""
        if "forkserver" in pcmd:  # forked workers keep the server's command line
            return "pool worker"
        if "forkserver" in cmd:
            return "fork server"
        if "resource_tracker" in cmd:
            return "resource tracker"
        if "spawn_main" in cmd:  # LocalCluster: the nannies live in the client, each spawns its worker
            return "dask worker"
        if "-m labelaudit" in cmd:
            return "main (client)"
        return "other"

    def _processes(self) -> list:
        out = []
        for child in self.me.children():
            if child.pid not in self.before:  # not this script's own helpers (e.g. its fork server)
                try:
                    out += [child, *child.children(recursive=True)]
                except (self.psutil.NoSuchProcess, self.psutil.ZombieProcess):  # exited while listed
                    continue
        return out

    def _run(self) -> None:
        while not self._stop.is_set():
            for p in self._processes():
                try:
                    role = self._role(p)
                    mem = p.memory_full_info()
                    rss, pss = mem.rss / MIB, getattr(mem, "pss", mem.rss) / MIB
                except (self.psutil.NoSuchProcess, self.psutil.AccessDenied, self.psutil.ZombieProcess):
                    continue
                old = self.peak.get(p.pid, (role, 0.0, 0.0))
                self.peak[p.pid] = (role, max(old[1], rss), max(old[2], pss))
            self._stop.wait(self.interval)

    def __enter__(self) -> "MemorySampler":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()

    def by_role(self) -> dict[str, list[tuple[float, float]]]:
        out: dict[str, list[tuple[float, float]]] = {}
        for role, rss, pss in self.peak.values():
            out.setdefault(role, []).append((rss, pss))
        return out


def cli_run(data: Path, out: Path, env: dict[str, str], *opts: str) -> tuple[float, float, float, float]:
    """``labelaudit infer`` as a subprocess: (wall s incl. start-up, CPU s of its process tree,
    start-up s until the first shard was written, span s from the first to the last shard)."""
    t0 = time.time()
    wall, _, cpu = run_tree(
        [sys.executable, "-m", "labelaudit", "infer", str(data), "-o", str(out), "--overwrite", "-q", *opts], env
    )
    stamps = sorted(p.stat().st_mtime for p in (out / "objects").glob("*.parquet"))
    return wall, cpu, stamps[0] - t0, stamps[-1] - stamps[0]


_SPIN = "import time\nt = time.perf_counter()\nx = 0\nfor i in range(20_000_000):\n    x += i\nprint(time.perf_counter() - t)"


def machine_speedup() -> float:
    """What this machine gives two busy processes: wall of one pure-Python loop alone, times 2,
    over the wall of two at once (2.0 on two free cores; less where the host shares them)."""
    import subprocess

    t = time.perf_counter()
    subprocess.run([sys.executable, "-c", _SPIN], check=True, capture_output=True)
    one = time.perf_counter() - t
    t = time.perf_counter()
    procs = [subprocess.Popen([sys.executable, "-c", _SPIN], stdout=subprocess.DEVNULL) for _ in range(2)]
    for p in procs:
        p.wait()
    return 2 * one / (time.perf_counter() - t)


def bench_workers_and_dask(data: Path, tmp: Path, repeat: int, with_dask: bool, env: dict[str, str]) -> None:
    frames = len(list((data / "training" / "label_2").glob("*.txt")))
    configs = [("1 worker", ("--workers", "1")), ("2 workers", ("--workers", "2"))]
    if with_dask:
        configs.append(("dask local:2", ("--scheduler", "local:2")))
    runs: dict[str, list[tuple[float, float, float, float]]] = {name: [] for name, _ in configs}
    memory: dict[str, list[tuple[float, float]]] = {}
    ceiling: list[float] = []
    for _ in range(repeat):
        ceiling.append(machine_speedup())
        for name, opts in configs:
            with MemorySampler() as mem:
                runs[name].append(cli_run(data, tmp / "out", env, *opts))
            for role, values in mem.by_role().items():
                memory.setdefault(f"{name}: {role}", []).extend(values)
    print(f"workers, {frames} frames, `labelaudit infer` subprocess ({load()}):")
    for name, rs in runs.items():
        print(
            f"  {name:13s} wall {spread([r[0] for r in rs])} s (start-up to the first shard {spread([r[2] for r in rs])} s, "
            f"then {spread([r[3] for r in rs])} s), CPU {spread([r[1] for r in rs])} s, {statistics.median(frames / r[0] for r in rs):.1f} frames/s"
        )
    w1, w2 = [r[0] for r in runs["1 worker"]], [r[0] for r in runs["2 workers"]]
    speedups = [a / b for a, b in zip(w1, w2)]
    print(
        f"  speed-up 2 vs 1 workers, wall: {spread(speedups)}; the machine's own for two busy loops, "
        f"measured before each repeat: {spread(ceiling)}"
    )
    print(
        f"  pool's speed-up / the machine's own, per repeat: {spread([a / b for a, b in zip(speedups, ceiling)])}   (target ≥ 0.9)"
    )
    if with_dask:
        dk, pool = runs["dask local:2"], runs["2 workers"]
        print(
            f"  dask local:2 / pool of 2, wall incl. start-up: {spread([d[0] / p[0] for d, p in zip(dk, pool)])}; "
            f"first → last shard: {spread([d[3] / p[3] for d, p in zip(dk, pool)])}   (target ≤ 1.10)"
        )
    print("memory, peak per process (MiB):")
    for key, values in sorted(memory.items()):
        if key.endswith(("other", "tracker", "dask nanny")):
            continue
        print(
            f"  {key:28s} RSS {max(v[0] for v in values):5.0f}   PSS {max(v[1] for v in values):5.0f}   "
            f"({len(values)} processes)   (target ≤ 300 MiB per worker)"
        )


def bench_waymo(tmp: Path, frames: int, repeat: int) -> tuple[float, float] | None:
    from labelaudit.sim.waymo_writer import simulate_waymo_segment, write_waymo_v2

    root = tmp / "waymo-v2"
    t = time.perf_counter()
    seg = simulate_waymo_segment(seed=0, frames=frames, size="real", chunks=32)
    write_waymo_v2(seg, root, rows_per_group=10)
    print(
        f"waymo: simulated a real-size v2 segment of {frames} frames in {time.perf_counter() - t:.1f} s "
        f"({sum(len(f.points) for f in seg.frames) / frames:,.0f} points/frame)"
    )
    runs = [warm_stages(root, frames, fmt="waymo-v2", classes=("all",)) for _ in range(repeat)]
    n_frames, n_obj = runs[0][0], runs[0][1]
    per_frame = [r[2]["read"] / r[0] for r in runs]
    per_box = [(r[3] - r[2]["read"]) / r[1] for r in runs]
    print(f"  one warm process, {n_frames} frames, {n_obj / n_frames:.1f} boxes/frame (all classes), CPU ({load()}):")
    print(
        f"    total {spread([r[3] / r[0] * 1e3 for r in runs], '{:.0f}')} ms/frame = read {spread([p * 1e3 for p in per_frame], '{:.0f}')} ms/frame "
        f"+ {spread([b * 1e3 for b in per_box], '{:.2f}')} ms per box (crop, model, rows, Arrow, Parquet)"
    )
    for stage in ("read", "crop", "infer_label", "jiou_gt", "fit_label", "hull_iou", "rows", "arrow", "parquet"):
        print(f"      {stage:14s} {spread([r[2][stage] / r[0] * 1e3 for r in runs], '{:.1f}')} ms/frame")
    return statistics.median(per_frame), statistics.median(per_box)


def project(per_frame: float, per_box: float) -> None:
    """Waymo-scale figures from the measured CPU per frame and per box (one worker = one core)."""
    import math

    boxes_per_frame = WAYMO_BOXES / WAYMO_FRAMES
    for what, share in (("all classes", 1.0), ("vehicles only, the default (≈ 60 % of the boxes, assumed)", 0.6)):
        sec = per_frame + share * boxes_per_frame * per_box
        hours = WAYMO_FRAMES * sec / 3600
        print(
            f"projection to Waymo, {what}: {WAYMO_FRAMES:,} frames × ({per_frame * 1e3:.0f} ms + {share * boxes_per_frame:.0f} boxes × "
            f"{per_box * 1e3:.2f} ms) = {sec * 1e3:.0f} ms CPU per frame → {1 / sec:.2f} frames/s per worker, "
            f"{hours:,.0f} worker-hours, {math.ceil(hours)} workers for ≤ 1 h (at perfect scaling)"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=480)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--waymo-frames", type=int, default=4)
    ap.add_argument("--data", type=Path, default=None, help="reuse (or create) the simulated KITTI dataset here")
    ap.add_argument("--only", default="workers,dask,waymo", help="comma-separated sections (dask needs workers)")
    args = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # figures appear as they are measured
    sections = set(args.only.split(","))
    become_subreaper()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    like_a_worker()
    with tempfile.TemporaryDirectory(prefix="bench-scale-") as name:
        tmp = Path(name)
        print(f"machine: {os.cpu_count()} cores, {load()}")
        if "workers" in sections:
            data = simulate(args.data or tmp / "sim", args.frames, args.seed)
            bench_workers_and_dask(data, tmp, args.repeat, "dask" in sections, env)
        if "waymo" in sections:
            costs = bench_waymo(tmp, args.waymo_frames, args.repeat)
            if costs:
                project(*costs)


if __name__ == "__main__":
    main()

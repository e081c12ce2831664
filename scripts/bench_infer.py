"""Benchmarks of `labelaudit infer` on one machine: start-up, one warm process, the floor ratio.

Prints, each repeated ``--repeat`` times (median and range, with the machine's load average):

  start-up   a 1-frame dataset, ``infer --workers 2`` as a subprocess: wall time until it exits, until
             its stdout/stderr pipes close (what a CI log reader waits for), and the CPU time of the
             whole process tree (main, fork server, workers; reaped as a child subreaper); then
             one more run with each process' CPU read from /proc. Target: wall ≤ 1.0 s.
  warm       one warm process on the simulated frames: ms per frame, every stage listed (read, crop,
             scores, infer_label, jiou_gt, fit_label, hull_iou, rows, Arrow table, Parquet bytes); CPU time.
             `scores`: a BEV run's prior terms, posterior, JIoU-GT and hull IoU in one call
             (posterior.bev_label_scores; infer_label, jiou_gt and hull_iou then read 0).
             Target: ≤ 10 ms per frame on the 9.2-box frames of ``simulate --seed 4``.
  ratio      ``infer --workers 2`` on 120 frames (subprocess, wall time including start-up) against
             two lean single-core floors measured in the same run, the same job both: np.fromfile +
             an Open3D oriented-box query per label over the whole frame (boxes read beforehand).
             *in-process*: in this warm process, imports done (what earlier sessions compared with);
             *fresh process*: ``python -c`` importing NumPy and Open3D, then the job, wall until it
             exits — like infer's own figure, which includes its interpreter start-up and imports.
             Target: ratio ≤ 2.0 ("a lean read + Open3D-crop floor on one core"); both are printed.

Timings depend on the load of the machine: on a shared machine compare CPU times and ratios, and
repeat when it is quiet.

    .venv/bin/python scripts/bench_infer.py [--frames 120] [--seed 4] [--repeat 3] [--data DIR] [--only startup,warm,ratio]
"""

from __future__ import annotations

import argparse
import ctypes
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FORKED_SERVER_NAME, FORKED_TRACKER_NAME = "la-forkserver", "la-rtracker"  # labelaudit.executors': the
# process names of a fork server and a resource tracker forked from the console script (their command
# line is the main process' own)


def load() -> str:
    return "load {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())


def spread(values: list[float], fmt: str = "{:.2f}") -> str:
    """median [min–max] of a few repeats."""
    return f"{fmt.format(statistics.median(values))} [{fmt.format(min(values))}–{fmt.format(max(values))}]"


def like_a_worker() -> None:
    """One BLAS/OpenMP thread in this process, as ``infer``'s workers have (the pool sets it for
    them): OpenBLAS's idle threads would otherwise spin beside the warm process and count in its
    CPU time. Before NumPy is imported; a number the caller set is kept."""
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(k, "1")


def become_subreaper() -> None:
    """Orphaned descendants (the fork server, workers) are re-parented to this process, so their
    CPU time is counted in RUSAGE_CHILDREN once they are reaped (Linux; elsewhere only the
    direct child is counted)."""
    try:
        ctypes.CDLL(None, use_errno=True).prctl(36, 1, 0, 0, 0)  # PR_SET_CHILD_SUBREAPER
    except (OSError, AttributeError):
        pass


def _children() -> set[int]:
    try:
        import psutil

        return {p.pid for p in psutil.Process().children()}
    except ImportError:  # pragma: no cover - psutil comes with distributed
        return set()


def reap_new(before: set[int], timeout: float = 60.0) -> None:
    """Wait for the children that were not there before the run (orphans re-parented to us)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        new = _children() - before
        if not new:
            return
        for pid in new:
            try:
                os.waitpid(pid, 0)
            except ChildProcessError:
                pass


def run_tree(cmd: list[str], env: dict[str, str]) -> tuple[float, float, float]:
    """(wall until the process exits, wall until its pipes close, CPU s of its whole process tree)."""
    before = _children()
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    proc.wait()
    t_exit = time.perf_counter() - t
    _, err = proc.communicate()
    t_eof = time.perf_counter() - t
    reap_new(before)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err.decode()}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return t_exit, t_eof, cpu


def cli(*args: str) -> list[str]:
    return [
        sys.executable,
        "-m",
        "labelaudit",
        "infer",
        *args,
    ]  # what the console script runs (it starts the fork server first)


def simulate(out: Path, frames: int, seed: int) -> Path:
    if not (out / "manifest.parquet").is_file():
        from labelaudit.sim.dataset import simulate_dataset

        t = time.perf_counter()
        s = simulate_dataset(out, frames=frames, seed=seed, workers=2, progress=False)
        print(
            f"simulated {s.frames} frames (seed {seed}): {s.num_points / s.frames:,.0f} points/frame in {time.perf_counter() - t:.1f} s"
        )
    return out


_TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100  # /proc/PID/stat's CPU times are in these


def proc_stat(pid: int) -> tuple[float, float, int] | None:
    """(CPU s used so far, start time in s since boot, minor page faults so far) of a process, from
    /proc/PID/stat; None once gone."""
    try:
        with open(f"/proc/{pid}/stat", "rb") as f:
            fields = f.read().rsplit(b")", 1)[1].split()
    except OSError:
        return None
    return (
        (int(fields[11]) + int(fields[12])) / _TICK,
        int(fields[19]) / _TICK,
        int(fields[7]),
    )  # utime+stime, starttime, minflt


def proc_children(pid: int) -> list[int]:
    try:
        with open(f"/proc/{pid}/task/{pid}/children") as f:
            return [int(c) for c in f.read().split()]
    except OSError:
        return []


class Sampler:
    """Calls :meth:`sample` every ``interval`` s in a thread while used as a context manager."""

    def __init__(self, interval: float):
        self.interval = interval
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def sample(self) -> None:
        raise NotImplementedError

    def _run(self) -> None:
        while True:
            self.sample()
            if self._stop.wait(self.interval):
                return

    def __enter__(self) -> "Sampler":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()


class CpuTimeline(Sampler):
    """CPU time of a process and its descendants, read from /proc every ``interval`` s (Linux):
    ~40 µs per process and sample, where bench_scale's smaps reads (memory) take ~1.5 ms.
    Times are s since ``t0``, taken just before ``root`` was started (start times: the kernel's,
    counted from ``root``'s own, in clock ticks of 10 ms)."""

    def __init__(self, root: int, t0: float, interval: float = 0.02):
        super().__init__(interval)
        self.root, self.t0 = root, t0
        self.samples: dict[int, list[tuple[float, float]]] = {}  # pid → [(s since t0, CPU s)]
        self.parent: dict[int, int] = {}
        self.started: dict[int, float] = {}  # pid → s since t0, from the kernel's start time
        self.faults: dict[int, int] = {}  # pid → minor page faults at its last sample
        self.role: dict[int, str] = {}
        self._root_start: float | None = None

    def _role(self, pid: int) -> str:
        try:
            cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            comm = Path(f"/proc/{pid}/comm").read_text().strip()
        except OSError:
            return "other"
        parent = self.role.get(self.parent.get(pid, -1), "")
        if parent == "fork server":
            return "pool worker"
        # a new interpreter's, or a fork of the console script (named: executors.fork_the_fork_server)
        if "forkserver" in cmd or comm == FORKED_SERVER_NAME:
            return "fork server"
        if "resource_tracker" in cmd or comm == FORKED_TRACKER_NAME:
            return "resource tracker"
        return "main" if pid == self.root else "other"

    def sample(self) -> None:
        now = time.time() - self.t0
        todo = [self.root]
        while todo:
            pid = todo.pop()
            stat = proc_stat(pid)
            if stat is None:
                continue
            if pid not in self.samples:
                self.samples[pid] = []
                if self._root_start is None:
                    self._root_start = stat[1]
                self.started[pid] = stat[1] - self._root_start
            if self.role.get(pid, "other") == "other":  # a fresh child runs its parent's command until it execs
                self.role[pid] = self._role(pid)
            self.samples[pid].append((now, stat[0]))
            self.faults[pid] = stat[2]
            for child in proc_children(pid):
                self.parent.setdefault(child, pid)
                todo.append(child)

    def cpu(self, pid: int, until: float | None = None) -> float:
        """CPU s of ``pid`` at its last sample at or before ``until`` (s since t0; None: its last)."""
        s = [c for t, c in self.samples[pid] if until is None or t <= until]
        return s[-1] if s else 0.0

    def busy(self, pid: int) -> tuple[float, float]:
        """(first, last) sample time at which ``pid`` had used more CPU than at the sample before."""
        s = self.samples[pid]
        moved = [t for (t, c), (_, c0) in zip(s[1:], s) if c > c0]
        return (moved[0], moved[-1]) if moved else (float("nan"), float("nan"))


def traced_run(cmd: list[str], env: dict[str, str], interval: float = 0.02) -> tuple[CpuTimeline, float, float]:
    """Run ``cmd`` with a :class:`CpuTimeline`: (the timeline, wall s until it exited, its exact CPU s,
    from ``wait4``: the timeline's last sample of a process misses up to ``interval`` of its CPU)."""
    before = set(proc_children(os.getpid()))
    with tempfile.TemporaryFile() as err:
        t0 = time.time()
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err)
        with CpuTimeline(proc.pid, t0, interval) as tl:
            _, status, usage = os.wait4(proc.pid, 0)
            wall = time.time() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        reap_new(before)
        if proc.returncode != 0:
            err.seek(0)
            raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err.read().decode()}")
    return tl, wall, usage.ru_utime + usage.ru_stime


# --------------------------------------------------------------------------- start-up


def bench_startup(tmp: Path, seed: int, repeat: int, env: dict[str, str]) -> None:
    data = simulate(tmp / "one-frame", 1, seed)
    rows = [
        run_tree(cli(str(data), "-o", str(tmp / "startup-out"), "--workers", "2", "--overwrite", "-q"), env)
        for _ in range(repeat)
    ]
    print(f"start-up, 1 frame, --workers 2 ({load()}):")
    print(f"  wall until exit        {spread([r[0] for r in rows])} s   (target ≤ 1.0 s)")
    print(f"  wall until pipes close {spread([r[1] for r in rows])} s   (target ≤ 1.0 s)")
    print(f"  CPU, whole tree        {spread([r[2] for r in rows])} s")
    tl, wall, main_cpu = traced_run(  # one more, its processes' CPU read from /proc
        cli(str(data), "-o", str(tmp / "startup-out"), "--workers", "2", "--overwrite", "-q"), env, 0.01
    )
    parts = [f"main {main_cpu:.2f}"] + [
        f"{tl.role[p]} {tl.cpu(p):.2f}" for p in sorted(tl.samples, key=tl.started.__getitem__) if p != tl.root
    ]
    workers = [p for p in tl.samples if tl.role[p] == "pool worker"]
    handed = f"; the worker forked at {min(tl.started[p] for p in workers):.2f} s" if workers else ""
    print(
        f"  CPU by process, one more run (wall {wall:.2f} s{handed}): {', '.join(parts)} s "
        "(read every 10 ms, the main's exact)"
    )


# --------------------------------------------------------------------------- one warm process

WARM_FRAMES = 10  # frames run before the timed ones (fewer when the dataset has no more to spare)
STAGES = (
    "read",
    "crop",
    "scores",
    "infer_label",
    "jiou_gt",
    "fit_label",
    "hull_iou",
    "rows",
    "missing",
    "arrow",
    "parquet",
)
MODEL_STAGES = ("crop", "scores", "infer_label", "jiou_gt", "fit_label", "hull_iou")  # timed inside process_frame


def warm_stages(
    data: Path, frames: int, model: str | None = None, fmt: str = "kitti", classes: tuple[str, ...] | None = None
) -> tuple[int, int, dict[str, float], float]:
    """CPU seconds per stage over ``frames`` frames, in this (warm) process; returns (frames, objects,
    seconds per stage, total seconds).

    The stage functions that :mod:`labelaudit.infer.rows` calls are wrapped with a CPU clock; "rows"
    is what :func:`process_frame` spends around them (selection, row dicts, normalisation). The
    Arrow table and the Parquet bytes are made per chunk, as ``infer`` makes its shards.
    """
    import gc
    import io

    from labelaudit import results as R
    from labelaudit.config import resolve_config
    from labelaudit.datasets import open_dataset
    from labelaudit.infer import rows as rows_mod
    from labelaudit.infer.missing import find_missing
    from labelaudit.infer.run import chunk_size_for

    clock = time.process_time
    acc: dict[str, float] = defaultdict(float)
    write = getattr(R, "write_parquet", None) or (  # a checkout before results.write_parquet: its writer
        lambda table, sink: __import__("pyarrow.parquet").parquet.write_table(table, sink, compression="zstd")
    )
    gc_started = [0.0]

    def gc_clock(phase: str, info: dict) -> None:  # the collector's pauses, whichever stage they fall in
        if phase == "start":
            gc_started[0] = clock()
        else:
            acc["gc (within the stages)"] += clock() - gc_started[0]

    gc.callbacks.append(gc_clock)
    try:  # as a worker does before its first chunk (process_chunk): freed per-box arrays are reused
        from labelaudit.executors import tune_allocator

        tune_allocator()
    except ImportError:  # pragma: no cover - a checkout without it
        pass
    originals = {}
    crop_name = (
        "frame_evidence" if hasattr(rows_mod, "frame_evidence") else "crop_frame_pair"
    )  # crops, ground, neighbours, rays

    def called(name: str) -> str:  # the pipeline calls the *_valid forms on a box it validated once
        return f"{name}_valid" if hasattr(rows_mod, f"{name}_valid") else name

    for name, stage in (
        # a BEV run's prior terms, posterior, JIoU-GT and hull IoU in one call (the general steps
        # below are then not called)
        *((("bev_label_scores", "scores"),) if hasattr(rows_mod, "bev_label_scores") else ()),
        (crop_name, "crop"),
        (called("infer_label"), "infer_label"),
        ("jiou_gt", "jiou_gt"),
        (called("fit_label"), "fit_label"),
        (called("hull_iou"), "hull_iou"),
    ):
        f = originals[name] = getattr(rows_mod, name)

        def timed(*a, _f=f, _stage=stage, **k):
            t = clock()
            try:
                return _f(*a, **k)
            finally:
                acc[_stage] += clock() - t

        setattr(rows_mod, name, timed)
    try:
        cfg = resolve_config(None, fmt, classes, model)
        reader = open_dataset(data, fmt)
        refs = reader.list_units()
        # a Waymo segment: twice; else WARM_FRAMES first, so that one-time costs (a kernel's first call, a
        # class prior's first use) stay out of the figures even when the frames sampled later need them
        w = max(2, min(WARM_FRAMES, len(refs) - frames))
        warm, sample = (refs[:w], refs[w : w + frames]) if len(refs) > 2 else (refs, refs)
        per_chunk = chunk_size_for(fmt, len(refs))
        for phase in (warm, sample):
            acc.clear()
            n_frames = n_obj = 0
            t0 = clock()
            for c in range(0, len(phase), per_chunk):
                chunk_rows: list = []
                for ref in phase[c : c + per_chunk]:
                    t = clock()
                    loaded = list(reader.load_unit(ref))
                    acc["read"] += clock() - t
                    for frame in loaded:
                        t = clock()
                        rows, _ = rows_mod.process_frame(frame, cfg)
                        acc["frame"] += clock() - t
                        if (
                            cfg.missing.enabled
                        ):  # the search for unlabelled objects, as process_chunk runs it after the rows
                            t = clock()
                            find_missing(frame, cfg)
                            acc["missing"] += clock() - t
                        chunk_rows.extend(rows)
                        n_frames += 1
                t = clock()
                table = R.rows_to_table(chunk_rows, normalized=True)
                acc["arrow"] += clock() - t
                t = clock()
                write(table, io.BytesIO())  # as infer writes its shards
                acc["parquet"] += clock() - t
                n_obj += len(chunk_rows)
            total = clock() - t0
    finally:
        gc.callbacks.remove(gc_clock)
        for name, f in originals.items():
            setattr(rows_mod, name, f)
    acc["rows"] = acc.pop("frame") - sum(acc[s] for s in MODEL_STAGES)
    return n_frames, n_obj, dict(acc), total


def bench_warm(data: Path, frames: int, repeat: int) -> None:
    runs = [warm_stages(data, frames) for _ in range(repeat)]
    n_frames, n_obj = runs[0][0], runs[0][1]
    per = lambda key: [r[2].get(key, 0.0) / r[0] * 1e3 for r in runs]  # noqa: E731
    print(f"one warm process, {n_frames} frames, {n_obj / n_frames:.1f} boxes/frame, CPU ms per frame ({load()}):")
    print(
        f"  total                  {spread([r[3] / r[0] * 1e3 for r in runs], '{:.1f}')} ms   (target ≤ 10 ms: the default infer, missing-label search included)"
    )
    print(
        f"  without `missing`      {spread([(r[3] - r[2]['missing']) / r[0] * 1e3 for r in runs], '{:.1f}')} ms   (--no-missing; the search adds the `missing` line, target ≤ 5 ms)"
    )
    for stage in STAGES:
        print(f"    {stage:20s} {spread(per(stage))} ms")
    print(f"    (garbage collector   {spread(per('gc (within the stages)'))} ms, counted in the stages above)")
    from labelaudit import kernels as K

    jitted = [name for name, k in K._REGISTRY.items() if getattr(k, "_jit", None) is not None]
    mode, why = K.kernel_mode()
    print(
        f"    kernels: {mode} ({why}); "
        + (
            f"{len(jitted)} compiled by numba's JIT in this process (the build lacks their argument types; "
            f"each costs its compile or cache load in the first repeat): {', '.join(jitted)}"
            if jitted
            else "none fell to numba's JIT"
        )
    )


# --------------------------------------------------------------------------- ratio to the floor


def floor_jobs(data: Path, refs: list, cfg: object) -> list[tuple[Path, "object"]]:
    """(scan path, selection boxes (K, 7)) of every frame: the audited labels with the model's crop
    margin and ground cut, read with labelaudit's reader (not timed by either floor)."""
    from labelaudit.datasets import open_dataset
    from labelaudit.infer.crop import selection_boxes
    from labelaudit.infer.rows import wants_class

    reader = open_dataset(data, "kitti")
    jobs = []
    for ref in refs:
        for frame in reader.load_unit(ref):
            sel = selection_boxes(
                frame.boxes[[i for i, c in enumerate(frame.class_names) if wants_class(cfg, c)]],
                cfg.crop.margin,  # type: ignore[attr-defined]
                cfg.crop.ground_cut,  # type: ignore[attr-defined]
            )
            jobs.append((data / "training" / "velodyne" / f"{frame.frame_id}.bin", sel))
    return jobs


def lean_floor(jobs: list) -> tuple[float, int, int]:
    """CPU-bound floor on one core, in this process (NumPy and Open3D already imported): np.fromfile
    of each scan + one Open3D oriented-box query per audited label over the whole frame. Returns
    (wall s, frames, boxes)."""
    import numpy as np
    import open3d as o3d

    from labelaudit.core.geometry import rotation_z

    boxes = 0
    t = time.perf_counter()
    for path, sel in jobs:
        pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)
        cloud = o3d.utility.Vector3dVector(pts[:, :3].astype(np.float64))
        for box, R in zip(sel, rotation_z(sel[:, 6])):
            obb = o3d.geometry.OrientedBoundingBox(box[:3], R, box[3:6])
            obb.get_point_indices_within_bounding_box(cloud)
            boxes += 1
    return time.perf_counter() - t, len(jobs), boxes


# The same job as lean_floor as a script of its own: a fresh interpreter imports NumPy and Open3D
# (plainly, as a user's script would), reads the boxes file, then reads and crops every scan.
FRESH_FLOOR = """
import sys, time
t0 = time.perf_counter()
import numpy as np
import open3d as o3d
t1 = time.perf_counter()
z = np.load(sys.argv[1])
paths, boxes, starts = z["paths"], z["boxes"], z["starts"]
for k, path in enumerate(paths):
    pts = np.fromfile(str(path), dtype="<f4").reshape(-1, 4)
    cloud = o3d.utility.Vector3dVector(pts[:, :3].astype(np.float64))
    for box in boxes[starts[k] : starts[k + 1]]:
        c, s = np.cos(box[6]), np.sin(box[6])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        o3d.geometry.OrientedBoundingBox(box[:3], R, box[3:6]).get_point_indices_within_bounding_box(cloud)
print(f"{t1 - t0:.3f} {time.perf_counter() - t1:.3f}", file=sys.stderr)
"""


def fresh_floor(jobs_file: Path, env: dict[str, str]) -> tuple[float, float, float, float]:
    """The lean job in a fresh ``python -c``: (wall until exit, CPU of the process, its imports s, its job s)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    proc = subprocess.run([sys.executable, "-c", FRESH_FLOOR, str(jobs_file)], capture_output=True, env=env)
    wall = time.perf_counter() - t
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if proc.returncode != 0:
        raise SystemExit(f"the fresh-process floor failed ({proc.returncode}):\n{proc.stderr.decode()}")
    imports, job = (float(v) for v in proc.stderr.decode().split()[-2:])
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return wall, cpu, imports, job


def bench_ratio(data: Path, tmp: Path, workers: int, repeat: int, env: dict[str, str]) -> None:
    import numpy as np

    from labelaudit.config import resolve_config
    from labelaudit.datasets import open_dataset

    cfg = resolve_config(None, "kitti")
    jobs = floor_jobs(data, open_dataset(data, "kitti").list_units(), cfg)
    jobs_file = tmp / "floor-jobs.npz"
    np.savez(
        jobs_file,
        paths=np.array([str(p) for p, _ in jobs]),
        boxes=np.concatenate([sel for _, sel in jobs]).reshape(-1, 7),
        starts=np.r_[0, np.cumsum([len(sel) for _, sel in jobs])],
    )
    lean_floor(jobs[:2])  # imports, file cache
    fresh_floor(jobs_file, env)  # Open3D's files in the page cache
    floors, fresh, walls, eofs, cpus = [], [], [], [], []
    for _ in range(repeat):  # the three measured in turn, each repeat
        floor, frames, boxes = lean_floor(jobs)
        fresh.append(fresh_floor(jobs_file, env))
        w, e, c = run_tree(
            cli(str(data), "-o", str(tmp / "ratio-out"), "--workers", str(workers), "--overwrite", "-q"), env
        )
        floors.append(floor)
        walls.append(w)
        eofs.append(e)
        cpus.append(c)
    print(f"ratio, {frames} frames, {boxes} audited boxes, --workers {workers} ({load()}):")
    print(f"  floor, in-process      {spread(floors)} s   (np.fromfile + Open3D box query per label; imports done)")
    print(
        f"  floor, fresh process   {spread([f[0] for f in fresh])} s wall until exit; CPU {spread([f[1] for f in fresh])} s; "
        f"its imports (NumPy, Open3D) {spread([f[2] for f in fresh])} s, the job {spread([f[3] for f in fresh])} s"
    )
    print(
        f"  infer, wall incl. start-up {spread(walls)} s; until pipes close {spread(eofs)} s; CPU whole tree {spread(cpus)} s"
    )
    print(f"  ratio infer / in-process floor     {spread([w / f for w, f in zip(walls, floors)])}   (target ≤ 2.0)")
    print(f"  ratio infer / fresh-process floor  {spread([w / f[0] for w, f in zip(walls, fresh)])}   (target ≤ 2.0)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=120)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--data", type=Path, default=None, help="reuse (or create) the simulated dataset here")
    ap.add_argument("--only", default="startup,warm,ratio", help="comma-separated sections")
    args = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)  # figures appear as they are measured
    become_subreaper()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    like_a_worker()  # after env: the commands measured set their own threads
    sections = set(args.only.split(","))
    with tempfile.TemporaryDirectory(prefix="bench-infer-") as name:
        tmp = Path(name)
        data = simulate(args.data or tmp / "sim", args.frames, args.seed)
        print(f"machine: {os.cpu_count()} cores, {load()}; labelaudit from {REPO}")
        if "startup" in sections:
            bench_startup(tmp, args.seed, args.repeat, env)
        if "warm" in sections:
            bench_warm(data, min(args.frames - 2, 100), args.repeat)
        if "ratio" in sections:
            bench_ratio(data, tmp, args.workers, args.repeat, env)


if __name__ == "__main__":
    main()

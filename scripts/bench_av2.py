"""Reading speed of the Argoverse 2 reader: simulated logs at the real sensors' resolution, and the real logs.

A simulated log (two VLP-32C-like lidars, 0.2° azimuth step, ~70k points per sweep; a real sweep
has ~100k) is written and read back into ``Frame`` objects (``load_unit``) and as labels only
(``labels``, what ``eval`` reads). When ``../shared/realdata/av2-sensor`` exists, its two logs are
read too (312 frames, 3 sweeps of ~100k points, the other frames annotation-only).

``--rays N`` also compares the free-space rays the label-error fit uses on N noisy simulated logs
(3 frames each): every point from the two lidars' midpoint (the reader's choice), the up lidar's
points from its own position, and no rays at all — AUROC of ``label_error`` for jittered and for
grossly wrong vehicle labels against clean ones.

Usage: ``python scripts/bench_av2.py [--frames 20] [--logs 2] [--repeat 3] [--rays 6]``
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from labelaudit import constants as C
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
            for f in reader.labels(unit) if labels_only else reader.load_unit(unit):
                frames += 1
                points += len(f.points)
                boxes += f.num_objects
        best = min(best, time.perf_counter() - t)
    return best, frames, points, boxes


def _report(what: str, root: Path, repeat: int) -> None:
    for labels_only in (False, True):
        dt, frames, points, boxes = _time(root, repeat, labels_only)
        mode = "labels()   " if labels_only else "load_unit()"
        print(
            f"{what} {mode}: {frames} frames in {dt:6.3f} s = {frames / dt:7.1f} frames/s, {1e3 * dt / frames:6.2f} ms/frame, "
            f"{points / max(frames, 1):8.0f} points/frame, {boxes / max(frames, 1):5.1f} boxes/frame"
        )


def _auroc(scores: np.ndarray, positive: np.ndarray, negative: np.ndarray) -> float:
    pos, neg = scores[positive], scores[negative]
    return float((pos[:, None] > neg[None]).mean() + 0.5 * (pos[:, None] == neg[None]).mean())


def rays(logs: int) -> None:
    """label_error AUROC with three choices of free-space rays on noisy simulated logs."""
    from labelaudit.config import resolve_config
    from labelaudit.datasets import Frame
    from labelaudit.infer.rows import process_frame
    from labelaudit.sim.noise import NoiseSpec

    cfg = resolve_config(None, "av2")
    mid = np.mean([C.AV2_LIDAR_MOUNTS[n] for n in ("up_lidar", "down_lidar")], axis=0)
    up = np.asarray(C.AV2_LIDAR_MOUNTS["up_lidar"], dtype=float)
    scores: dict[str, list[tuple[float, str]]] = {
        "both lidars, midpoint": [],
        "up lidar, its position": [],
        "no rays": [],
    }
    for seed in range(logs):
        log = simulate_av2_log(
            seed=100 + seed, frames=3, size="real", label_noise=NoiseSpec(fraction=0.3, gross_fraction=0.15)
        )
        for fr in log.frames:
            for key, mask, origin in (
                ("both lidars, midpoint", None, mid),
                ("up lidar, its position", fr.laser_number < 32, up),
                ("no rays", np.zeros(len(fr.points), bool), mid),
            ):
                frame = Frame(
                    "bench",
                    fr.points,
                    fr.boxes,
                    list(fr.categories),
                    list(fr.track_ids),
                    sensor_origin=origin,
                    ray_mask=mask,
                )
                for row, kind in zip(process_frame(frame, cfg)[0], fr.perturbation):
                    if row["status"] == "ok" and row["class_name"] in cfg.classes:
                        scores[key].append((float(row["label_error"]), kind))
    print(f"free-space rays, label_error AUROC against clean vehicle labels ({logs} simulated logs x 3 frames):")
    for key, pairs in scores.items():
        s = np.array([p[0] for p in pairs])
        kind = np.array([p[1] for p in pairs])
        clean = kind == "none"
        gross = np.isin(kind, ["shift", "swap_lw", "yaw90"])
        print(
            f"  {key:24s} jitter {_auroc(s, kind == 'jitter', clean):.3f} (n={int((kind == 'jitter').sum())})   "
            f"gross {_auroc(s, gross, clean):.3f} (n={int(gross.sum())})   clean n={int(clean.sum())}, ≥ 0.9: {np.mean(s[clean] >= 0.9):.3f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20, help="frames per simulated log")
    ap.add_argument("--logs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--rays", type=int, default=0, help="noisy logs for the free-space ray comparison (0: skip)")
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
        print(
            f"simulated {args.logs} logs x {args.frames} frames: simulate {1e3 * t_sim / n:.1f} ms/frame, write {1e3 * t_write / n:.1f} ms/frame"
        )
        _report("simulated", root, args.repeat)
    finally:
        shutil.rmtree(root, ignore_errors=True)
    real = args.realdata / "av2-sensor"
    if real.is_dir():
        _report("real     ", real, args.repeat)
    if args.rays:
        rays(args.rays)


if __name__ == "__main__":
    main()

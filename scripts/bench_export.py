"""Benchmark of ``labelaudit export`` (target: 30,000 objects in ≤ 5 s).

Synthesises a results folder of N objects (default 30,000: 3,000 KITTI-like frames of 10 audited
objects, shards of 16 frames written by the results writer like a real run, random small SPD
posterior covariances) and an OpenPCDet-style ``kitti_infos_train.pkl`` of the same frames (each
with 2 DontCare and 1 unaudited Pedestrian more), then times :func:`labelaudit.export.export_results`
end to end (read the results, propagate, write) for the Parquet output in every encoding, for
the OpenPCDet and mmdet3d infos copies, and for GLENet's infos + gt-database infos (``--format
glenet``; the gt-database file has one entry per Car and Pedestrian, as OpenPCDet writes it). Prints the median wall and CPU time of a few repetitions
(the machine may be shared: CPU time is the steadier figure).

    python scripts/bench_export.py [--objects 30000] [--repeat 3] [--model bev|3d]
"""

from __future__ import annotations

import argparse
import pickle
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from labelaudit import results as R
from labelaudit.export import export_results

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from infos_factory import mmdet3d_kitti_infos, openpcdet_dbinfos, openpcdet_kitti_infos  # noqa: E402

PER_FRAME = 10


def synthesise(root: Path, n_objects: int, model: str, seed: int = 0) -> dict[str, list]:
    """Write a results folder of ``n_objects`` rows; return the frames (label order) for the infos."""
    rng = np.random.default_rng(seed)
    p = 6 if model == "bev" else 8
    n_frames = -(-n_objects // PER_FRAME)
    meta = R.run_metadata({"model": {"model": model}}, "bench", "/data/kitti", "kitti")
    frames: dict[str, list] = {}
    shard: list[dict] = []
    k = 0
    for f in range(n_frames):
        fid = f"{f:06d}"
        objs = []
        for i in range(min(PER_FRAME, n_objects - k)):
            l, w, h = rng.uniform(3.5, 5.0), rng.uniform(1.5, 2.0), rng.uniform(1.4, 1.8)
            A = rng.normal(0.0, 0.05, (p, p))
            cov = A @ A.T + 1e-4 * np.eye(p)
            x, y = rng.uniform(5, 70), rng.uniform(-20, 20)
            shard.append(
                {
                    "dataset": "kitti", "frame_id": fid, "object_index": i, "object_id": f"{fid}:{i}", "class_name": "Car",
                    "cx": x, "cy": y, "cz": -0.8, "length": l, "width": w, "height": h, "yaw": rng.uniform(-np.pi, np.pi),
                    "distance": float(np.hypot(x, y)), "num_points": int(rng.integers(0, 500)), "status": "ok", "sigma": 0.2,
                    "hull_iou": float(rng.uniform(0, 1)), "cov": cov.ravel(), "cov_dim": p, "model": model, "label_line": i + 1,
                }
            )  # fmt: skip
            objs.append(("Car", l, w, h))
            k += 1
        frames[fid] = objs + [("Pedestrian", 0.8, 0.6, 1.7), ("DontCare", -1, -1, -1), ("DontCare", -1, -1, -1)]
        if (f + 1) % 16 == 0 or f == n_frames - 1:
            R.write_parquet_atomic(R.rows_to_table(shard, meta), root / R.OBJECTS_DIR / f"part-{f:06d}.parquet")
            shard = []
    R.write_json_atomic({**meta, "complete": True}, root / R.MANIFEST_NAME)
    return frames


def median_s(fn, repeat: int) -> tuple[float, float]:
    """Median wall and CPU time (s); CPU time (process_time) is not inflated by other processes on a shared machine."""
    wall, cpu = [], []
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--objects", type=int, default=30_000)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--model", choices=("bev", "3d"), default="bev")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench-export-") as tmp:
        tmp = Path(tmp)
        t0 = time.perf_counter()
        frames = synthesise(tmp / "res", args.objects, args.model)
        kitti_infos = openpcdet_kitti_infos(frames)
        (tmp / "kitti_infos_train.pkl").write_bytes(pickle.dumps(kitti_infos))
        (tmp / "kitti_dbinfos_train.pkl").write_bytes(pickle.dumps(openpcdet_dbinfos(kitti_infos)))
        (tmp / "mmdet3d_infos_train.pkl").write_bytes(pickle.dumps(mmdet3d_kitti_infos(frames)))
        print(
            f"synthesised {args.objects} objects in {len(frames)} frames ({args.model} model) in {time.perf_counter() - t0:.1f} s (not timed)"
        )
        cases = [("parquet", enc, "model") for enc in ("box", "log-size", "pixor", "residual")]
        cases += [
            ("parquet", "log-size", "num_points"),
            ("openpcdet", "residual", "model"),
            ("mmdet3d", "log-size", "model"),
        ]
        cases += [("glenet", None, "model")]
        print(
            f"{'format':<10} {'encoding':<9} {'source':<11} {'objects':>8} {'wall s':>7} {'cpu s':>6} {'objects/s (wall)':>17}"
        )
        for fmt, enc, src in cases:
            infos = (
                None
                if fmt == "parquet"
                else tmp / ("mmdet3d_infos_train.pkl" if fmt == "mmdet3d" else "kitti_infos_train.pkl")
            )
            dbinfos = tmp / "kitti_dbinfos_train.pkl" if fmt == "glenet" else None
            out = tmp / (
                f"out-{fmt}" if fmt == "glenet" else f"out-{fmt}-{enc}.{'parquet' if fmt == 'parquet' else 'pkl'}"
            )

            def run() -> object:
                return export_results(tmp / "res", out, encoding=enc, source=src, fmt=fmt, infos=infos, dbinfos=dbinfos)

            wall, cpu = median_s(run, args.repeat)
            print(
                f"{fmt:<10} {enc or '-':<9} {src:<11} {args.objects:>8} {wall:>7.2f} {cpu:>6.2f} {args.objects / wall:>17.0f}"
            )


if __name__ == "__main__":
    main()

#!/usr/bin/env python
"""Tracks benchmark: does ``track_error`` find the annotator errors inside tracks, and leave the
ordinary per-frame noise alone?

Simulated (default):
1. Simulate ``--segments`` Waymo v2 segments of ``--frames`` frames (10 Hz, small sensor size, half
   the vehicles driving) whose vehicle labels carry the ordinary per-frame noise of labelling every
   frame anew (centre 3 cm, length 3 cm, width 2 cm, yaw 0.02 rad) and, in 5 % of the object-frames,
   one injected error: length ± 0.25–0.5 m, width ± 0.15–0.3 m, heading ± 0.1–0.25 rad or flipped
   by π, centre moved 0.3–0.6 m (``labelaudit.sim.tracknoise``; recorded in manifest.parquet).
2. ``labelaudit infer`` the segments (the real pipeline: rows, then the tracks pass).
3. Join the rows to the manifest on (frame_id, object_id); positive = an injected error.

Real (``--real``): the Argoverse 2 annotations in ``--realdata`` (2 logs × 156 timestamps of real,
smooth tracks): vehicle labels get the same per-frame noise, then the same injected errors. With the
``av2`` reader the noisy logs are written as an AV2 dataset (the real sweeps where they exist;
every other annotated timestamp is a frame without points) and go through ``labelaudit infer``; without it (``--direct``) the
noisy annotations are turned into result rows here and scored by the same tracks pass.

Printed: AUROC of track_error for injected vs clean (overall and per kind, each kind against all
clean labels), the share of clean labels with track_error ≥ 0.9, whether the reported issue
matches the kind, a naive rule beside it (median size of the track; centre and heading
interpolated from the previous and next frame; deviations in units of the same noise floors), and
in the simulation the per-frame ``label_error`` on the same labels.

Usage::

    .venv/bin/python scripts/bench_tracks.py                       # 4 segments × 40 frames, seed 0
    .venv/bin/python scripts/bench_tracks.py --real                # the real AV2 annotations
    .venv/bin/python scripts/bench_tracks.py --real --direct       # … without the AV2 reader
    .venv/bin/python scripts/bench_tracks.py --cost                # what the pass adds to a Waymo-size run
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
import sys
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.sim.benchmark import auroc
from labelaudit.sim.tracknoise import ISSUE_OF_KIND, TRACK_ERROR_KINDS, TrackNoiseSpec, perturb_track_labels

FLAG = C.TRACK_FLAG
AV2_VEHICLES = (
    "REGULAR_VEHICLE",
    "LARGE_VEHICLE",
    "BUS",
    "BOX_TRUCK",
    "TRUCK",
    "TRUCK_CAB",
    "VEHICULAR_TRAILER",
    "ARTICULATED_BUS",
    "SCHOOL_BUS",
    "MESSAGE_BOARD_TRAILER",
)
REALDATA = (
    Path(os.environ.get("LABELAUDIT_REALDATA", Path(__file__).resolve().parents[2] / "shared" / "realdata"))
    / "av2-sensor"
)


# --------------------------------------------------------------------------- scoring


def naive_scores(rows: list[dict[str, Any]]) -> np.ndarray:
    """The naive rule: per track the median size; centre and heading of the previous and next frame
    averaged (the one neighbour at a track's end); the largest deviation in units of the noise floors."""
    f = C.TRACK_NOISE_FLOOR
    out = np.full(len(rows), np.nan)
    tracks: dict[tuple[str, str], list[int]] = defaultdict(list)
    for i, r in enumerate(rows):
        if r["timestamp"] is not None and r["world_cx"] is not None:
            tracks[(r["frame_id"].rsplit(":", 1)[0], r["object_id"])].append(i)
    for idx in tracks.values():
        if len(idx) < C.TRACK_MIN_FRAMES:
            continue
        idx = sorted(idx, key=lambda i: rows[i]["timestamp"])
        size = np.array([[rows[i]["length"], rows[i]["width"]] for i in idx])
        c = np.array([[rows[i]["world_cx"], rows[i]["world_cy"]] for i in idx])
        yaw = np.array([rows[i]["world_yaw"] for i in idx])
        med = np.median(size, axis=0)
        dev_size = np.max(np.abs(size - med) / [f["length"], f["width"]], axis=1)
        prev = np.r_[1, np.arange(len(idx) - 1)]
        nxt = np.r_[np.arange(1, len(idx)), len(idx) - 2]
        c_pred = (c[prev] + c[nxt]) / 2
        y_pred = yaw[prev] + np.angle(np.exp(1j * (yaw[nxt] - yaw[prev]))) / 2
        dev_c = np.hypot(*(c - c_pred).T) / f["center"]
        dev_y = np.abs(np.angle(np.exp(1j * (yaw - y_pred)))) / f["yaw"]
        out[idx] = np.maximum.reduce([dev_size, dev_c, dev_y])
    return out


def report(
    title: str,
    kinds: list[str],
    score: np.ndarray,
    issues: list[str | None],
    naive: np.ndarray,
    per_frame: np.ndarray | None = None,
) -> dict[str, float]:
    """Print the figures; returns them (overall AUROC, worst per-kind AUROC, clean false-alarm share)."""
    kinds_a = np.array(kinds)
    ok = np.isfinite(score)
    pos = (kinds_a != "none") & ok
    neg = (kinds_a == "none") & ok
    print(
        f"\n== {title}: {int(ok.sum())} judged object-frames ({int(pos.sum())} with an injected error, "
        f"{int((~ok).sum())} not judged: tracks of < {C.TRACK_MIN_FRAMES} frames)"
    )
    head = (
        f"{'':16s} {'n':>5s} {'AUROC':>7s} {'naive':>7s}"
        + (f" {'label_error':>11s}" if per_frame is not None else "")
        + f" {'≥ 0.9':>7s} {'issue ok':>8s}"
    )
    print(head)
    out: dict[str, float] = {}

    def line(name: str, sel: np.ndarray) -> float:
        lab = np.r_[np.ones(int(sel.sum())), np.zeros(int(neg.sum()))]
        a = auroc(np.r_[score[sel], score[neg]], lab)
        b = auroc(np.r_[naive[sel], naive[neg]], lab)
        extra = ""
        if per_frame is not None:
            pf = np.r_[per_frame[sel], per_frame[neg]]
            good = np.isfinite(pf)
            extra = (
                f" {auroc(pf[good], lab[good]):11.3f}"
                if good.any() and 0 < lab[good].sum() < good.sum()
                else f" {'–':>11s}"
            )
        hit = np.mean(score[sel] >= FLAG)
        right = np.mean([issues[i] == ISSUE_OF_KIND.get(str(kinds_a[i]), "none") for i in np.flatnonzero(sel)])
        print(f"{name:16s} {int(sel.sum()):5d} {a:7.4f} {b:7.4f}{extra} {hit:7.1%} {right:8.1%}")
        return a

    out["auroc"] = line("all injected", pos)
    per = []
    for k in TRACK_ERROR_KINDS:
        sel = (kinds_a == k) & ok
        if sel.any():
            per.append(line(k, sel))
    out["worst_kind_auroc"] = min(per) if per else float("nan")
    false_alarm = float(np.mean(score[neg] >= FLAG))
    out["clean_flagged"] = false_alarm
    q = np.quantile(score[neg], [0.5, 0.99]) if neg.any() else [np.nan, np.nan]
    print(
        f"{'clean':16s} {int(neg.sum()):5d}   track_error ≥ {FLAG}: {false_alarm:.2%}   median {q[0]:.4f}, 99th percentile {q[1]:.4f}"
    )
    return out


# --------------------------------------------------------------------------- simulated Waymo segments


def run_sim(args: argparse.Namespace) -> dict[str, float]:
    from labelaudit.infer.run import InferRequest, infer_dataset
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    out = Path(args.out)
    key = f"{args.segments} segments x {args.frames} frames, seed {args.seed}, moving {C.SIM_MOVING_FRACTION}, {TrackNoiseSpec()}"
    stamp = out / "bench.txt"
    if not (stamp.is_file() and stamp.read_text() == key):
        shutil.rmtree(out, ignore_errors=True)
        t = time.perf_counter()
        simulate_waymo_dataset(
            out,
            segments=args.segments,
            frames=args.frames,
            seed=args.seed,
            size="small",
            formats=("waymo-v2",),
            track_noise=TrackNoiseSpec(),
            moving_fraction=C.SIM_MOVING_FRACTION,
        )
        stamp.write_text(key)
        print(f"simulated {key} in {time.perf_counter() - t:.0f} s", flush=True)
    t = time.perf_counter()
    infer_dataset(InferRequest(out / "waymo_v2", out / "results", workers=args.workers, overwrite=True))
    print(f"infer (with the tracks pass) in {time.perf_counter() - t:.0f} s", flush=True)
    rows = R.read_results(out / "results").to_pylist()
    truth = {(r["frame_id"], r["object_id"]): r for r in pq.read_table(out / "manifest.parquet").to_pylist()}
    kinds = [truth[(r["frame_id"], r["object_id"])]["track_error_kind"] for r in rows]
    score = np.array([np.nan if r["track_error"] is None else r["track_error"] for r in rows])
    per_frame = np.array([np.nan if r["label_error"] is None else r["label_error"] for r in rows])
    figures = report(
        "simulated Waymo v2 segments", kinds, score, [r["track_issue"] for r in rows], naive_scores(rows), per_frame
    )
    # the points' say in the size posterior: the same rows scored from the labels alone
    from labelaudit.config import resolve_config
    from labelaudit.infer.tracks import score_table

    table = R.read_results(out / "results")
    with_points = score_table(table, resolve_config(None, "waymo-v2")).track_error
    labels_only = score_table(table, None).track_error
    k = np.array(kinds)
    for name, sel in (("length", k == "length"), ("width", k == "width")):
        lab = np.r_[np.ones(int(sel.sum())), np.zeros(int((k == "none").sum()))]
        print(
            f"size posterior, {name}: AUROC with the points' evidence {auroc(np.r_[with_points[sel], with_points[k == 'none']], lab):.4f}, "
            f"labels only {auroc(np.r_[labels_only[sel], labels_only[k == 'none']], lab):.4f}"
        )
    moved = np.abs(with_points - labels_only)
    print(f"the points move track_error by more than 0.01 on {np.mean(moved > 0.01):.2%} of the labels")
    return figures


# --------------------------------------------------------------------------- real Argoverse 2 annotations


def _yaw_of(qw: np.ndarray, qx: np.ndarray, qy: np.ndarray, qz: np.ndarray) -> np.ndarray:
    return np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz))


def _rotation(qw: float, qx: float, qy: float, qz: float) -> np.ndarray:
    return np.array(
        [
            [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qz * qw), 2 * (qx * qz + qy * qw)],
            [2 * (qx * qy + qz * qw), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qx * qw)],
            [2 * (qx * qz - qy * qw), 2 * (qy * qz + qx * qw), 1 - 2 * (qx * qx + qy * qy)],
        ]
    )


def noisy_logs(realdata: Path, seed: int) -> list[tuple[str, pa.Table, pa.Table, list[str], list[float]]]:
    """Per log: its annotations with noise (vehicles only), its poses, and per row the injected kind and size."""
    import pyarrow.feather as feather

    spec = TrackNoiseSpec(classes=AV2_VEHICLES)
    out = []
    for n, log_dir in enumerate(sorted(p for p in (realdata / "val").iterdir() if p.is_dir())):
        ann = feather.read_table(log_dir / "annotations.feather")
        poses = feather.read_table(log_dir / "city_SE3_egovehicle.feather")
        cols = {c: ann.column(c).to_numpy() for c in ann.column_names if c not in ("track_uuid", "category")}
        cats = ann.column("category").to_pylist()
        ts = cols["timestamp_ns"]
        boxes = np.stack(
            [
                cols["tx_m"],
                cols["ty_m"],
                cols["tz_m"],
                cols["length_m"],
                cols["width_m"],
                cols["height_m"],
                _yaw_of(cols["qw"], cols["qx"], cols["qy"], cols["qz"]),
            ],
            axis=1,
        )
        kinds = ["none"] * len(ts)
        sizes = [0.0] * len(ts)
        for f, t in enumerate(np.unique(ts)):
            sel = np.flatnonzero(ts == t)
            written, k, m = perturb_track_labels(
                boxes[sel], [cats[i] for i in sel], spec, np.random.default_rng([seed, n, f])
            )
            boxes[sel] = written
            for j, i in enumerate(sel):
                kinds[i], sizes[i] = k[j], float(m[j])
        half = boxes[:, 6] / 2
        new = ann
        for name, values in (
            ("tx_m", boxes[:, 0]),
            ("ty_m", boxes[:, 1]),
            ("length_m", boxes[:, 3]),
            ("width_m", boxes[:, 4]),
            ("qw", np.cos(half)),
            ("qx", np.zeros(len(ts))),
            ("qy", np.zeros(len(ts))),
            ("qz", np.sin(half)),
        ):
            new = new.set_column(new.schema.get_field_index(name), name, pa.array(values, pa.float64()))
        out.append((log_dir.name, new, poses, kinds, sizes))
    return out


def rows_of_annotations(log: str, ann: pa.Table, poses: pa.Table) -> list[dict[str, Any]]:
    """What the pipeline's rows hold for the tracks pass, from AV2 annotations directly (no sweeps: status no_points)."""
    p = {int(r["timestamp_ns"]): r for r in poses.to_pylist()}
    rows = []
    counters: dict[int, int] = defaultdict(int)
    for r in ann.to_pylist():
        t = int(r["timestamp_ns"])
        q = p[t]
        rot = _rotation(q["qw"], q["qx"], q["qy"], q["qz"])
        c = rot @ np.array([r["tx_m"], r["ty_m"], r["tz_m"]]) + np.array([q["tx_m"], q["ty_m"], q["tz_m"]])
        yaw = float(_yaw_of(np.float64(r["qw"]), np.float64(r["qx"]), np.float64(r["qy"]), np.float64(r["qz"])))
        index = counters[t]
        counters[t] += 1
        rows.append(
            {
                "dataset": "av2",
                "frame_id": f"{log}:{t}",
                "object_index": index,
                "object_id": r["track_uuid"],
                "class_name": r["category"],
                "cx": r["tx_m"],
                "cy": r["ty_m"],
                "cz": r["tz_m"],
                "length": r["length_m"],
                "width": r["width_m"],
                "height": r["height_m"],
                "yaw": yaw,
                "distance": math.hypot(r["tx_m"], r["ty_m"]),
                "status": "no_points",
                "model": "bev",
                "timestamp": t / 1e9,
                "world_cx": float(c[0]),
                "world_cy": float(c[1]),
                "world_cz": float(c[2]),
                "world_yaw": float(np.angle(np.exp(1j * (yaw + math.atan2(rot[1, 0], rot[0, 0]))))),
            }
        )
    return rows


def write_av2(dest: Path, realdata: Path, logs: list[tuple[str, pa.Table, pa.Table, list[str], list[float]]]) -> Path:
    """An AV2 dataset of the noisy logs: annotations, poses, calibration and the real sweeps (other timestamps have none)."""
    import pyarrow.feather as feather

    shutil.rmtree(dest, ignore_errors=True)
    for log, ann, poses, _, _ in logs:
        src, d = realdata / "val" / log, dest / "val" / log
        (d / "sensors" / "lidar").mkdir(parents=True)
        feather.write_feather(ann, d / "annotations.feather")
        feather.write_feather(poses, d / "city_SE3_egovehicle.feather")
        if (src / "calibration").is_dir():
            shutil.copytree(src / "calibration", d / "calibration")
        for sweep in (src / "sensors" / "lidar").glob(
            "*.feather"
        ):  # the reader makes a 0-point frame of every other annotated timestamp
            shutil.copy(sweep, d / "sensors" / "lidar" / sweep.name)
    return dest


def run_real(args: argparse.Namespace) -> dict[str, float]:
    realdata = Path(args.realdata)
    if not (realdata / "val").is_dir():
        sys.exit(f"{realdata}: no Argoverse 2 logs (expected val/<log_id>/annotations.feather)")
    logs = noisy_logs(realdata, args.seed)
    truth = {}
    for log, ann, _, kinds, _ in logs:
        ts, uuid = ann.column("timestamp_ns").to_pylist(), ann.column("track_uuid").to_pylist()
        truth.update({(f"{log}:{t}", u): k for t, u, k in zip(ts, uuid, kinds)})
    from labelaudit.datasets import FORMATS

    if args.direct or "av2" not in FORMATS:
        if not args.direct:
            print("no av2 reader in this build: the noisy annotations are scored directly (--direct)")
        from labelaudit.infer.tracks import score_table

        audited = AV2_VEHICLES
        if "av2" in FORMATS:  # the classes the built-in Argoverse 2 config audits
            from labelaudit.config import resolve_config

            audited = tuple(resolve_config(None, "av2").classes)
        rows = [
            r
            for log, ann, poses, _, _ in logs
            for r in rows_of_annotations(log, ann, poses)
            if r["class_name"] in audited
        ]
        table = R.rows_to_table(rows)  # sorted by (frame_id, object_index): the order of the scores
        t = time.perf_counter()
        s = score_table(table)
        print(f"tracks pass over {len(rows)} rows in {time.perf_counter() - t:.2f} s")
        rows = table.to_pylist()
        score = s.track_error
        issues = s.track_issue
        how = "direct"
    else:
        from labelaudit.infer.run import InferRequest, infer_dataset

        out = Path(args.out)
        root = write_av2(out / "av2", realdata, logs)
        t = time.perf_counter()
        infer_dataset(
            InferRequest(root, out / "results", dataset_format="av2", workers=args.workers, overwrite=True)
        )  # the built-in config's vehicles
        print(f"infer (av2 reader, tracks pass) in {time.perf_counter() - t:.0f} s")
        rows = R.read_results(out / "results").to_pylist()
        score = np.array([np.nan if r["track_error"] is None else r["track_error"] for r in rows])
        issues = [r["track_issue"] for r in rows]
        how = "through the av2 reader and infer"
    kinds = [truth[(r["frame_id"], r["object_id"])] for r in rows]
    return report(
        f"real Argoverse 2 annotations ({how}), vehicles",
        kinds,
        np.asarray(score, dtype=float),
        issues,
        naive_scores(rows),
    )


def run_cost(args: argparse.Namespace) -> None:
    """What the tracks pass adds to a Waymo-size run: infer on real-size simulated frames (per
    frame, with its labels) against the pass over a 200-frame segment's rows (per row × labels per frame)."""
    from labelaudit.config import resolve_config
    from labelaudit.infer.run import InferRequest, infer_dataset
    from labelaudit.infer.tracks import run_tracks_pass
    from labelaudit.sim.waymo_writer import simulate_waymo_dataset

    out = Path(args.out) / "cost"
    shutil.rmtree(out, ignore_errors=True)
    simulate_waymo_dataset(
        out,
        segments=1,
        frames=args.cost_frames,
        seed=args.seed,
        size="real",
        formats=("waymo-v2",),
        track_noise=TrackNoiseSpec(),
        moving_fraction=C.SIM_MOVING_FRACTION,
    )
    t = time.perf_counter()
    infer_dataset(InferRequest(out / "waymo_v2", out / "results", workers=1))
    infer_wall = time.perf_counter() - t
    rows = R.read_results(out / "results").to_pylist()
    per_frame_rows = len(rows) / args.cost_frames
    # a Waymo segment's rows: 200 frames of tracks with ordinary noise (the pass does not look at points)
    rng = np.random.default_rng(args.seed)
    n_frames, n_tracks = 200, int(round(per_frame_rows))
    seg_rows = []
    speed = rng.uniform(0, 12, n_tracks)
    heading = rng.uniform(-np.pi, np.pi, n_tracks)
    for f in range(n_frames):
        ts = 1_600_000_000_000_000 + f * 100_000
        for k in range(n_tracks):
            x = 100 + k * 7 + speed[k] * f * 0.1 * np.cos(heading[k]) + rng.normal(0, 0.03)
            y = -50 + speed[k] * f * 0.1 * np.sin(heading[k]) + rng.normal(0, 0.03)
            seg_rows.append(
                {
                    "dataset": "waymo-v2",
                    "frame_id": f"seg:{ts}",
                    "object_index": k,
                    "object_id": f"trk{k}",
                    "class_name": "Vehicle",
                    "cx": x,
                    "cy": y,
                    "cz": 1.0,
                    "length": 4.5 + rng.normal(0, 0.03),
                    "width": 1.9 + rng.normal(0, 0.02),
                    "height": 1.6,
                    "yaw": heading[k],
                    "distance": 10.0,
                    "status": "ok",
                    "model": "bev",
                    "timestamp": ts / 1e6,
                    "world_cx": x,
                    "world_cy": y,
                    "world_cz": 1.0,
                    "world_yaw": heading[k] + rng.normal(0, 0.02),
                }
            )
    seg = Path(args.out) / "cost-pass"
    shutil.rmtree(seg, ignore_errors=True)
    meta = R.run_metadata({}, "0" * 16, "/seg", "waymo-v2")
    R.write_parquet_atomic(R.rows_to_table(seg_rows, meta), seg / R.OBJECTS_DIR / "part-0.parquet")
    cfg = resolve_config(None, "waymo-v2")
    t = time.perf_counter()
    run_tracks_pass(seg, cfg, meta)
    pass_wall = time.perf_counter() - t
    per_row = pass_wall / len(seg_rows)
    infer_frame = infer_wall / args.cost_frames
    print(
        f"infer at Waymo's real sensor size: {args.cost_frames} frames, {per_frame_rows:.1f} labels per frame, "
        f"{infer_frame * 1e3:.0f} ms per frame (wall, one worker, start-up included)"
    )
    print(
        f"tracks pass over a 200-frame segment of {n_tracks} tracks ({len(seg_rows)} rows): {pass_wall:.2f} s, "
        f"{per_row * 1e3:.3f} ms per row = {per_row * per_frame_rows * 1e3:.1f} ms per frame"
    )
    print(f"the tracks pass adds {per_row * per_frame_rows / infer_frame:.1%} to a Waymo-size run (must hold: ≤ 10 %)")


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--segments", type=int, default=4)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", default="/tmp/labelaudit-bench-tracks")
    ap.add_argument(
        "--real", action="store_true", help="the real Argoverse 2 annotations instead of simulated segments"
    )
    ap.add_argument("--direct", action="store_true", help="--real: score the annotations without the av2 reader")
    ap.add_argument("--realdata", default=str(REALDATA))
    ap.add_argument(
        "--cost", action="store_true", help="what the tracks pass adds to a Waymo-size run (real sensor size)"
    )
    ap.add_argument("--cost-frames", type=int, default=4)
    args = ap.parse_args()
    if args.cost:
        run_cost(args)
        return
    figures = run_real(args) if args.real else run_sim(args)
    print(
        f"\nmust hold: AUROC ≥ 0.97 → {figures['auroc']:.4f}; per kind ≥ 0.95 → {figures['worst_kind_auroc']:.4f}; "
        f"clean ≥ 0.9 ≤ 1 % → {figures['clean_flagged']:.2%}"
    )


if __name__ == "__main__":
    main()

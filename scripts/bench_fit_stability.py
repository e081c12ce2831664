#!/usr/bin/env python
"""Is the label-error fit stable under last-bit changes of its inputs?

Every frame is audited by the pipeline (``labelaudit.infer.rows.process_frame``, built-in KITTI
config) as it is, then again after a change of its inputs far below any measurement's precision:

- ``box_abs``: every label box field moved by ±1e-12 (m, rad; a random sign per field);
- ``box_rel``: every label box field multiplied by 1 ± 1e-12;
- ``points_ulp``: every point coordinate (x, y, z, as float64) moved by one unit in the last place
  (``np.nextafter`` towards a random side);
- ``prior_ulp``: the fit's prior terms (P0, η0 and G of ``box_prior_terms``) multiplied entry by
  entry by 1 ± 1e-15 — what a compiled prior set-up that rounds differently gives the fit.

A fit whose result is a function of its inputs moves ``label_error`` by about the size of the
change (≪ 1e-6); a fit that stops where its path happened to be moves it by far more. Printed per
change: the labels whose ``label_error`` moved by more than 1e-6 / 1e-3 / 0.1, the largest move,
the same for the suggested box (``fit_*``, ``fit_offset_m``), and ``jiou_gt`` as a control (it does
not depend on the fit). Then the fit's cost: ms per fitted label (``fit_label_valid`` timed inside
the pipeline), its iterations and how many fits reached the cap.

The frames: ``--frames`` simulated KITTI frames (``--seed``, the label-error benchmark's label
noise, so wrong labels are included), and the 13 real KITTI frames of ``../shared/realdata`` (or
``$LABELAUDIT_REALDATA``) when present.

Usage::

    .venv/bin/python scripts/bench_fit_stability.py                 # 40 simulated frames, seed 4, + real
    .venv/bin/python scripts/bench_fit_stability.py --frames 10 --skip-real
    .venv/bin/python scripts/bench_fit_stability.py --worst 5       # the labels that moved most
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

import labelaudit.infer.rows as rows_module
from labelaudit import constants as C
from labelaudit.config import resolve_config
from labelaudit.core.posterior import box_prior_terms
from labelaudit.datasets.kitti import KittiReader
from labelaudit.infer.rows import process_frame
from labelaudit.sim.dataset import NoiseSpec, simulate_dataset

REPO = Path(__file__).resolve().parents[1]
REAL = Path(os.environ.get("LABELAUDIT_REALDATA", REPO.parent / "shared" / "realdata"))
REAL_FOLDERS = ("openpcdet-pr653-kitti", "kitti-object-more")
EPS = 1e-12  # size of the box changes
CHANGES = ("box_abs", "box_rel", "points_ulp", "prior_ulp")
FIT_COLUMNS = ("fit_cx", "fit_cy", "fit_cz", "fit_length", "fit_width", "fit_height", "fit_yaw", "fit_offset_m")
LIMIT = 1e-6  # the decided tolerance of label_error after a last-bit change


def load_frames(root: Path) -> list[Any]:
    reader = KittiReader(root)
    return [f for ref in reader.list_units() for f in reader.load_unit(ref)]


def changed(frame: Any, kind: str, rng: np.random.Generator) -> Any:
    """``frame`` with its inputs changed in their last bits (points as float64 either way)."""
    pts = np.asarray(frame.points, dtype=np.float64).copy()
    boxes = np.asarray(frame.boxes, dtype=np.float64).copy()
    if kind == "box_abs":
        boxes = boxes + EPS * rng.choice([-1.0, 1.0], size=boxes.shape)
    elif kind == "box_rel":
        boxes = boxes * (1.0 + EPS * rng.choice([-1.0, 1.0], size=boxes.shape))
    elif kind == "points_ulp":
        side = np.where(rng.random((len(pts), 3)) < 0.5, -np.inf, np.inf)
        pts[:, :3] = np.nextafter(pts[:, :3], side)
    elif kind not in ("none", "prior_ulp"):
        raise ValueError(kind)
    return dataclasses.replace(frame, points=pts, boxes=boxes)


class FitTimer:
    """Wraps the pipeline's ``fit_label_valid``: wall time, iterations and convergence of each fit."""

    def __init__(self) -> None:
        self.seconds = 0.0
        self.iterations: list[int] = []
        self.converged: list[bool] = []
        self._inner = rows_module.fit_label_valid

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        t = time.perf_counter()
        out = self._inner(*args, **kwargs)
        self.seconds += time.perf_counter() - t
        self.iterations.append(out.iterations)
        self.converged.append(out.converged)
        return out

    def __enter__(self) -> FitTimer:
        rows_module.fit_label_valid = self
        return self

    def __exit__(self, *exc: object) -> None:
        rows_module.fit_label_valid = self._inner


class PriorNudge:
    """Wraps the pipeline's ``fit_label_valid``: the label's prior terms of the fit's model, each entry
    of P0, η0 and G multiplied by 1 ± 1e-15 (a random sign per entry)."""

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self._inner = rows_module.fit_label_valid

    def _nudge(self, x: np.ndarray) -> np.ndarray:
        return x * (1.0 + 1e-15 * self.rng.choice([-1.0, 1.0], size=np.shape(x)))

    def __call__(self, y: Any, points: Any, class_name: str, params: Any, free_space: Any = None, **kw: Any) -> Any:
        model = "3d" if points is not None and np.ndim(points) == 2 and np.shape(points)[1] >= 3 else "bev"
        t = box_prior_terms(y, params.prior_for(class_name), params.prior_weight, model)
        kw["prior_terms"] = dataclasses.replace(t, P0=self._nudge(t.P0), eta0=self._nudge(t.eta0), G=self._nudge(t.G))
        return self._inner(y, points, class_name, params, free_space, **kw)

    def __enter__(self) -> PriorNudge:
        rows_module.fit_label_valid = self
        return self

    def __exit__(self, *exc: object) -> None:
        rows_module.fit_label_valid = self._inner


def audit(frames: list[Any], cfg: Any, kind: str, seed: int) -> dict[str, np.ndarray]:
    """Rows of every frame after change ``kind`` (keyed by frame_id:object_index, vehicles with a score)."""
    rng = np.random.default_rng(seed)
    keys, cols = [], {c: [] for c in ("label_error", "jiou_gt", *FIT_COLUMNS)}
    for frame in frames:
        if kind == "prior_ulp":
            with PriorNudge(rng):
                rows, _ = process_frame(changed(frame, kind, rng), cfg)
        else:
            rows, _ = process_frame(changed(frame, kind, rng), cfg)
        for r in rows:
            if r.get("label_error") is None:
                continue
            keys.append(f"{r['frame_id']}:{r['object_index']}")
            for c in cols:
                cols[c].append(np.nan if r.get(c) is None else float(r[c]))
    out = {c: np.array(v) for c, v in cols.items()}
    out["key"] = np.array(keys)
    return out


def report(name: str, frames: list[Any], cfg: Any, seed: int, worst: int) -> None:
    print(f"\n## {name}: {len(frames)} frames", flush=True)
    audit(frames[:1], cfg, "none", seed)  # warm the kernels and caches before timing
    with FitTimer() as timer:
        t = time.perf_counter()
        base = audit(frames, cfg, "none", seed)
        wall = time.perf_counter() - t
    n = len(base["key"])
    it = np.array(timer.iterations)
    print(
        f"{n} scored labels; fit {1000 * timer.seconds / max(len(it), 1):.2f} ms per fit "
        f"({len(it)} fits, {1000 * timer.seconds / len(frames):.2f} ms per frame, whole audit "
        f"{1000 * wall / len(frames):.1f} ms per frame); iterations median {np.median(it):.0f}, "
        f"max {it.max()}, at the cap ({C.FIT_MAX_ITERATIONS}) {int((it >= C.FIT_MAX_ITERATIONS).sum())}, "
        f"not converged {int((~np.array(timer.converged)).sum())}",
        flush=True,
    )
    head = "| change | label_error > 1e-6 | > 1e-3 | > 0.1 | largest | fit_* > 1e-6 | largest fit_* (m, rad) | largest jiou_gt |"
    print(head + "\n|" + "---|" * 8)
    moved_any = np.zeros(n, dtype=bool)
    per_key = np.zeros(n)
    for kind in CHANGES:
        other = audit(frames, cfg, kind, seed + 1)
        if not np.array_equal(other["key"], base["key"]):
            raise SystemExit(f"{kind}: the set of scored labels changed")
        dle = np.abs(np.nan_to_num(other["label_error"] - base["label_error"], nan=np.inf))
        dfit = np.max([np.abs(np.nan_to_num(other[c] - base[c], nan=0.0)) for c in FIT_COLUMNS], axis=0)
        djiou = np.nanmax(np.abs(other["jiou_gt"] - base["jiou_gt"])) if n else 0.0
        moved_any |= dle > LIMIT
        per_key = np.maximum(per_key, dle)
        print(
            f"| {kind} | {int((dle > LIMIT).sum())} of {n} | {int((dle > 1e-3).sum())} | {int((dle > 0.1).sum())} "
            f"| {dle.max():.3g} | {int((dfit > 1e-6).sum())} | {dfit.max():.3g} | {djiou:.3g} |",
            flush=True,
        )
    print(f"labels moved > {LIMIT:g} by any change: {int(moved_any.sum())} of {n}; largest {per_key.max():.3g}")
    for i in np.argsort(-per_key)[:worst]:
        if per_key[i] > LIMIT:
            print(f"  {base['key'][i]}: label_error {base['label_error'][i]:.6f}, moved by {per_key[i]:.3g}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=40, help="simulated frames (default 40)")
    ap.add_argument("--seed", type=int, default=4, help="simulation seed (default 4)")
    ap.add_argument("--skip-real", action="store_true", help="simulated frames only")
    ap.add_argument("--skip-sim", action="store_true", help="real frames only")
    ap.add_argument("--worst", type=int, default=0, help="list this many labels that moved most")
    args = ap.parse_args(argv)
    cfg = resolve_config(None, "kitti")
    if not args.skip_sim and args.frames > 0:
        with tempfile.TemporaryDirectory() as tmp:
            simulate_dataset(
                Path(tmp) / "sim", frames=args.frames, seed=args.seed, noise=NoiseSpec.benchmark(), progress=False
            )
            frames = load_frames(Path(tmp) / "sim")
        report(f"simulated (seed {args.seed})", frames, cfg, args.seed, args.worst)
    if not args.skip_real:
        roots = [REAL / f for f in REAL_FOLDERS if (REAL / f / "training" / "velodyne").is_dir()]
        if not roots:
            print(f"\nreal data: {REAL} not found — skipped")
        else:
            frames = [f for r in roots for f in load_frames(r)]
            report("real KITTI", frames, cfg, args.seed, args.worst)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

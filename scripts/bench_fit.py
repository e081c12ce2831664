#!/usr/bin/env python
"""The label-error fit's cost, alone: where a frame's ``fit_label`` time goes.

The pipeline (``labelaudit.infer.rows.process_frame``, built-in KITTI config, BEV) runs over
``--frames`` simulated frames (``simulate --seed 4``, as ``bench_infer.py --only warm``) and every
call of ``fit_label_valid`` is recorded with its inputs. The recorded calls are then replayed in
this warm process, ``--repeat`` times, each free-space input fresh (its cached kernel layout
dropped, as in the pipeline, where the fit is the first to ask for it):

- CPU ms per frame of the replayed fits (median [range] of the repeats) — the ``fit_label`` stage of
  ``bench_infer.py`` without the rest of the frame;
- the count per label of descents (starts), iterations, points, candidate rays, and what a
  descent's iterations do;
- CPU ms per frame of the fit's parts (each part wrapped with a CPU clock in one further replay:
  the wrappers add ~1 µs per call, so the parts sum to a little more than the total).

Usage::

    .venv/bin/python scripts/bench_fit.py [--frames 100] [--seed 4] [--repeat 5] [--data DIR]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

for _k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):  # one thread, as a worker
    os.environ.setdefault(_k, "1")

import numpy as np  # noqa: E402

WARM = 10  # frames run before the recorded ones


def load() -> str:
    return "load {:.1f} {:.1f} {:.1f}".format(*os.getloadavg())


def spread(values: list[float], fmt: str = "{:.3f}") -> str:
    return f"{fmt.format(statistics.median(values))} [{fmt.format(min(values))}–{fmt.format(max(values))}]"


def record(data: Path, frames: int) -> tuple[list[tuple[tuple, dict]], int]:
    """The fit calls of ``frames`` frames of the pipeline (after WARM frames), with their inputs."""
    from labelaudit.config import resolve_config
    from labelaudit.datasets import open_dataset
    from labelaudit.infer import rows as rows_mod

    cfg = resolve_config(None, "kitti", None, None)
    reader = open_dataset(data, "kitti")
    refs = reader.list_units()
    inner = rows_mod.fit_label_valid
    calls: list[tuple[tuple, dict]] = []

    def rec(*a: Any, **k: Any) -> Any:
        calls.append((a, dict(k)))
        return inner(*a, **k)

    n = 0
    for phase, sample in ((False, refs[:WARM]), (True, refs[WARM : WARM + frames])):
        rows_mod.fit_label_valid = rec if phase else inner
        try:
            for ref in sample:
                for frame in reader.load_unit(ref):
                    rows_mod.process_frame(frame, cfg)
                    n += phase
        finally:
            rows_mod.fit_label_valid = inner
    return calls, n


def fresh(call: tuple[tuple, dict]) -> tuple[tuple, dict]:
    """The call with its FreeSpace copied (no cached kernel layout), as the pipeline first meets it."""
    a, k = call
    a = list(a)
    if len(a) > 4 and a[4] is not None:
        a[4] = dataclasses.replace(a[4])
    elif k.get("free_space") is not None:
        k = {**k, "free_space": dataclasses.replace(k["free_space"])}
    return tuple(a), k


def replay(calls: list[tuple[tuple, dict]]) -> tuple[float, list[Any]]:
    from labelaudit.core.fit import fit_label_valid

    prepared = [fresh(c) for c in calls]
    t = time.process_time()
    out = [fit_label_valid(*a, **k) for a, k in prepared]
    return time.process_time() - t, out


PARTS = (
    # (module, name): the pieces of fit_label_valid and _fit_em
    ("labelaudit.core.fit", "register_validated"),
    ("labelaudit.core.fit", "em_sigma"),
    ("labelaudit.core.fit", "_ray_inputs"),
    ("labelaudit.core.fit", "_fit_em"),
    ("labelaudit.core.fit", "_fit_em_kernel"),
    ("labelaudit.core.fit", "_closest_form"),
    ("labelaudit.core.fit", "_label_distances_kernel"),
    ("labelaudit.core.fit", "_slab_face_gaps"),
    ("labelaudit.core.fit", "prior_cov_extended_cached"),
    ("labelaudit.core.fit", "label_ray_terms"),
    ("labelaudit.core.freespace", "height_layout"),
)


def parts(calls: list[tuple[tuple, dict]], frames: int) -> None:
    import importlib

    clock = time.process_time
    acc: dict[str, float] = defaultdict(float)
    count: dict[str, int] = defaultdict(int)
    saved = []
    for mod_name, name in PARTS:
        mod = importlib.import_module(mod_name)
        f = getattr(mod, name, None)
        if f is None:
            continue
        saved.append((mod, name, f))

        def timed(*a: Any, _f: Any = f, _n: str = name, **k: Any) -> Any:
            t = clock()
            try:
                return _f(*a, **k)
            finally:
                acc[_n] += clock() - t
                count[_n] += 1

        setattr(mod, name, timed)
    try:
        total, _ = replay(calls)
    finally:
        for mod, name, f in saved:
            setattr(mod, name, f)
    print(f"parts, CPU ms per frame (one replay with a clock around each; total {1e3 * total / frames:.3f}):")
    for _, name in PARTS:
        if count[name]:
            print(f"  {name:28s} {1e3 * acc[name] / frames:7.3f} ms   {count[name] / len(calls):5.2f} calls per fit")


def counts(calls: list[tuple[tuple, dict]], fits: list[Any]) -> None:
    from labelaudit.core import fit as F

    inner = F._fit_em_kernel
    per_descent: list[tuple[int, int, int]] = []  # (iterations, points, rays)

    def spy(*a: Any) -> Any:
        out = inner(*a)
        per_descent.append((int(out[2]), a[2].shape[1], a[18].shape[1]))
        return out

    F._fit_em_kernel = spy
    try:
        replay(calls)
    finally:
        F._fit_em_kernel = inner
    it = np.array([d[0] for d in per_descent])
    pts = np.array([d[1] for d in per_descent])
    rays = np.array([d[2] for d in per_descent])
    swapped = sum(f.swapped_start for f in fits)
    print(
        f"{len(calls)} fits, {len(per_descent)} descents ({len(per_descent) / len(calls):.2f} per fit; "
        f"swapped start chosen {swapped}); iterations per descent: mean {it.mean():.2f}, median "
        f"{np.median(it):.0f}, p90 {np.percentile(it, 90):.0f}, max {it.max()}; points per descent mean "
        f"{pts.mean():.0f}, rays {rays.mean():.0f}; point-iterations {np.sum(it * pts) / len(calls):.0f} and "
        f"ray-iterations {np.sum(it * rays) / len(calls):.0f} per fit"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--data", type=Path, default=None, help="reuse (or create) the simulated dataset here")
    args = ap.parse_args()
    sys.stdout.reconfigure(line_buffering=True)
    try:
        from labelaudit.executors import tune_allocator

        tune_allocator()
    except ImportError:  # pragma: no cover
        pass
    with tempfile.TemporaryDirectory(prefix="bench-fit-") as name:
        data = args.data or Path(name) / "sim"
        if not (data / "manifest.parquet").is_file():
            from labelaudit.sim.dataset import simulate_dataset

            simulate_dataset(data, frames=args.frames + WARM, seed=args.seed, workers=2, progress=False)
        calls, frames = record(data, args.frames)
    print(f"{frames} frames, {len(calls)} fits ({len(calls) / frames:.1f} per frame), {load()}")
    replay(calls)  # warm
    runs = [replay(calls) for _ in range(args.repeat)]
    print(f"fit_label, CPU ms per frame: {spread([1e3 * r[0] / frames for r in runs])} ({load()})")
    counts(calls, runs[0][1])
    parts(calls, frames)
    from labelaudit import kernels as K

    jitted = [n for n, k in K._REGISTRY.items() if getattr(k, "_jit", None) is not None]
    print(f"kernels: {K.kernel_mode()[0]}; fallen to the JIT: {', '.join(jitted) or 'none'}")


if __name__ == "__main__":
    main()

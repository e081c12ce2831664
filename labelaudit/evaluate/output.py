"""EVAL_DIR: the files ``labelaudit eval -o EVAL_DIR`` writes, and its plots (matplotlib, Agg).

Contract (read by ``labelaudit report --eval``; docs/eval.md § Outputs):

* ``summary.json`` — exactly the document ``eval --format json`` prints;
* ``detections.parquet`` — one row per detection (matched GT, IoU, JIoU, JIoU-ratio, JIoU-GT,
  outcome per metric and difficulty);
* ``ap_vs_threshold.png`` — AP against the localisation threshold for IoU, JIoU and JIoU-ratio
  (the paper's Fig. 9), ``pr_curves.png`` — precision/recall at the usual thresholds,
  ``mean_overlap_distance.png`` — mean overlaps of matched detections per distance bin (Figs.
  10–11) and, for probabilistic detections, ``recall_gain.png`` (Fig. 12);
* ``label-results/`` — the label inference ``eval`` ran itself when no ``--results`` was given.

Every file is written to a temporary name and renamed. This module only writes what
:mod:`labelaudit.evaluate.run` computed.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from labelaudit.evaluate.run import EvalResult, distance_bins
from labelaudit.results import write_json_atomic, write_parquet_atomic

__all__ = ["PLOT_FILES", "write_eval_dir"]

PLOT_FILES = ("ap_vs_threshold.png", "pr_curves.png", "mean_overlap_distance.png", "recall_gain.png")
_LABELS = {
    "iou": "IoU",
    "jiou": "JIoU",
    "jiou_ratio": "JIoU-ratio",
    "jiou_deterministic": "JIoU (detections as deterministic)",
}
_COLOURS = {"iou": "#1f77b4", "jiou": "#d62728", "jiou_ratio": "#2ca02c", "jiou_deterministic": "#ff7f0e"}


def write_eval_dir(result: EvalResult, out: str | Path) -> list[Path]:
    """Write summary, per-detection table and plots into ``out``; returns the files written."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = [
        write_json_atomic(result.summary, out / "summary.json"),
        write_parquet_atomic(result.detections_table, out / "detections.parquet"),
    ]
    written += write_plots(result.summary, out)
    return written


def _save(fig: Any, path: Path) -> Path:
    tmp = path.with_name(f".{path.stem}.tmp-{os.getpid()}.png")
    fig.savefig(tmp, dpi=110)
    os.replace(tmp, path)
    return path


def _figure(n: int, height: float = 3.6) -> tuple[Any, list[Any]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, max(n, 1), figsize=(max(4.4 * n, 6.5), height), squeeze=False, layout="constrained")
    return fig, list(axes[0])


def write_plots(summary: dict[str, Any], out: Path) -> list[Path]:
    """The PNG figures of one evaluation (see the module docstring)."""
    import matplotlib.pyplot as plt

    classes = summary["classes"]
    meta = summary["metric"]
    diff = meta["headline_difficulty"]
    view = meta["view"].upper()
    ap_all = summary["ap"] + (summary.get("probabilistic_ap") or [])
    metrics = [
        m for m in _LABELS if any(r["metric"] == m for r in ap_all)
    ]  # LET has one threshold per class: in the tables, not these plots
    files = []

    fig, axes = _figure(len(classes))
    for ax, cls in zip(axes, classes):
        for metric in metrics:
            rows = sorted(
                (
                    r
                    for r in ap_all
                    if r["class"] == cls and r["difficulty"] == diff and r["metric"] == metric and r["interp"] == "R40"
                ),
                key=lambda r: r["threshold"],
            )
            xs = [r["threshold"] for r in rows if r["ap"] is not None]
            ys = [r["ap"] for r in rows if r["ap"] is not None]
            if xs:
                ax.plot(
                    xs,
                    ys,
                    "o-" if metric != "jiou_deterministic" else "s--",
                    color=_COLOURS[metric],
                    label=_LABELS[metric],
                    ms=4,
                )
        n_gt = next((r["num_gt"] for r in summary["ap"] if r["class"] == cls and r["difficulty"] == diff), 0)
        ax.set_title(f"{cls} ({diff}, {n_gt} GT)")
        ax.set_xlabel("localisation threshold")
        ax.set_ylim(0, 100)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"AP|R40 (%), {view}")
    axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle("AP vs localisation threshold (IoU, JIoU, JIoU-ratio)")
    files.append(_save(fig, out / "ap_vs_threshold.png"))
    plt.close(fig)

    fig, axes = _figure(len(classes))
    for ax, cls in zip(axes, classes):
        for c in summary["pr_curves"]:
            if c["class"] == cls and c["recall"]:
                ax.step(
                    c["recall"],
                    c["interpolated_precision"][: len(c["recall"])],
                    where="post",
                    color=_COLOURS[c["metric"]],
                    label=f"{_LABELS[c['metric']]} > {c['threshold']:g}",
                )
        ax.set_title(f"{cls} ({diff})")
        ax.set_xlabel("recall")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1.02)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("precision (devkit-interpolated)")
    if axes[0].get_legend_handles_labels()[
        0
    ]:  # no curve (nothing detected): no legend, and no matplotlib warning on stderr
        axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"Precision-recall at the usual thresholds ({view})")
    files.append(_save(fig, out / "pr_curves.png"))
    plt.close(fig)

    fig, axes = _figure(len(classes))
    bins = [b[0] for b in distance_bins()]
    base = [m for m in metrics if m != "jiou_deterministic"]
    width = 0.8 / max(len(base), 1)
    for ax, cls in zip(axes, classes):
        for k, metric in enumerate(base):
            rows = {
                r["distance_bin"]: r
                for r in summary["mean_overlap_by_class"]
                if r["class"] == cls and r["difficulty"] == diff and r["metric"] == metric
            }
            ys = [rows[b]["mean"] if b in rows and rows[b]["mean"] is not None else np.nan for b in bins]
            ax.bar(
                np.arange(len(bins)) + (k - (len(base) - 1) / 2) * width,
                ys,
                width,
                color=_COLOURS[metric],
                label=_LABELS[metric],
            )
        counts = [
            next(
                (
                    r["count"]
                    for r in summary["mean_overlap_by_class"]
                    if r["class"] == cls and r["difficulty"] == diff and r["distance_bin"] == b
                ),
                0,
            )
            for b in bins
        ]
        ax.set_xticks(np.arange(len(bins)), [f"{b} m\n(n={n})" for b, n in zip(bins, counts)])
        ax.set_ylim(0, 1.15)
        ax.set_yticks(np.linspace(0, 1, 6))
        ax.set_title(f"{cls} ({diff})")
        ax.grid(alpha=0.3, axis="y")
    axes[0].set_ylabel("mean over matched detections")
    axes[0].legend(loc="upper center", ncol=len(base), fontsize=8, frameon=False)
    fig.suptitle(f"Mean IoU / JIoU / JIoU-ratio of matched detections by distance ({view})")
    files.append(_save(fig, out / "mean_overlap_distance.png"))
    plt.close(fig)

    if summary.get("probabilistic"):
        fig, axes = _figure(len(classes))
        for ax, cls in zip(axes, classes):
            rows = sorted(
                (r for r in summary["probabilistic"] if r["class"] == cls and r["difficulty"] == diff),
                key=lambda r: r["threshold"],
            )
            xs = [r["threshold"] for r in rows]
            ax.plot(
                xs, [r["recall_probabilistic"] for r in rows], "o-", color=_COLOURS["jiou"], label="own distribution"
            )
            ax.plot(
                xs,
                [r["recall_deterministic"] for r in rows],
                "s--",
                color=_COLOURS["jiou_deterministic"],
                label="as deterministic",
            )
            ax.set_title(f"{cls} ({diff})")
            ax.set_xlabel("JIoU threshold")
            ax.set_ylim(0, 1.02)
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("recall (all detections)")
        axes[0].legend(loc="lower left", fontsize=8)
        fig.suptitle(f"Probabilistic detections: recall at JIoU thresholds ({view})")
        files.append(_save(fig, out / "recall_gain.png"))
        plt.close(fig)
    return files

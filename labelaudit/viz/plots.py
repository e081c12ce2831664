"""The report's aggregate plots, from results columns: the paper's Fig. 7a/7b/7c and score distributions.

- Fig. 7a: mean corner total variance of C1..C4 (nearest the sensor first) per class;
- Fig. 7b: mean JIoU-GT against the distance to the sensor;
- Fig. 7c: mean JIoU-GT against log10 of the number of points;
- histograms of JIoU-GT and of label_error per class.

Every function takes plain NumPy columns (one entry per object) and returns a :class:`Plot` with the
PNG and the numbers drawn, so tests check the numbers, not pixels. It reads no files and computes
no model quantity; binning and means only.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from numpy.typing import NDArray

from labelaudit import constants as C

FloatArray = NDArray[np.float64]

__all__ = ["Plot", "corner_variance_plot", "binned_mean_plot", "distribution_plot", "binned_means"]

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


@dataclass(frozen=True)
class Plot:
    """A rendered plot: PNG bytes, a title and the numbers it shows (``data[class] = …``)."""

    png: bytes
    title: str
    data: dict[str, Any] = field(default_factory=dict)
    note: str = ""


def _figure(size: tuple[int, int] = C.REPORT_PLOT_SIZE) -> tuple[Figure, Any]:
    fig = Figure(figsize=(size[0] / C.VIZ_DPI, size[1] / C.VIZ_DPI), dpi=C.VIZ_DPI)
    FigureCanvasAgg(fig)
    ax = fig.add_axes((0.11, 0.12, 0.85, 0.8))  # fixed margins: a layout engine costs more than the plot
    ax.grid(True, alpha=0.3)
    ax.tick_params(labelsize=8)
    return fig, ax


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=C.VIZ_DPI)
    return buf.getvalue()


def _class_order(classes: NDArray[np.object_]) -> list[str]:
    """Classes by number of objects, most first (ties by name)."""
    names, counts = np.unique(classes.astype(str), return_counts=True)
    return [str(n) for n in names[np.lexsort((names, -counts))]]


def _empty(ax: Any, text: str) -> None:
    ax.text(0.5, 0.5, text, ha="center", va="center", transform=ax.transAxes, fontsize=10, color="#666")


def corner_variance_plot(classes: NDArray[np.object_], corner_tv: FloatArray) -> Plot:
    """Fig. 7a: mean total variance of the corners C1..C4 (C1 nearest the sensor) per class.

    Parameters
    ----------
    classes : (n,) class names; corner_tv : (n, 4) corner total variances (m²), rows with NaN skipped
    """
    title = "Mean corner total variance, C1 nearest the sensor (Fig. 7a)"
    fig, ax = _figure()
    ok = np.all(np.isfinite(corner_tv), axis=1) if len(corner_tv) else np.zeros(0, bool)
    data: dict[str, Any] = {}
    names = _class_order(classes[ok]) if ok.any() else []
    width = 0.8 / max(len(names), 1)
    for k, name in enumerate(names):
        m = ok & (classes == name)
        mean = corner_tv[m].mean(axis=0)
        data[name] = {"mean": mean.tolist(), "count": int(m.sum())}
        ax.bar(
            np.arange(4) + (k - (len(names) - 1) / 2) * width,
            mean,
            width=width * 0.95,
            color=PALETTE[k % len(PALETTE)],
            label=f"{name} (n={int(m.sum())})",
        )
    if not names:
        _empty(ax, "no corner variances")
    else:
        ax.legend(fontsize=8)
    ax.set_xticks(range(4), ["C1", "C2", "C3", "C4"])
    ax.set_ylabel("mean corner total variance (m²)", fontsize=9)
    ax.set_title(title, fontsize=10)
    return Plot(_png(fig), title, data)


def binned_means(
    x: FloatArray, y: FloatArray, edges: FloatArray, min_count: int = C.REPORT_MIN_BIN_COUNT
) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
    """Mean of ``y`` in the bins ``edges`` of ``x`` (NaN where fewer than ``min_count`` values).

    Returns
    -------
    centres : (B,) bin centres; means : (B,); counts : (B,) values per bin
    """
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    b = np.digitize(x, edges) - 1
    inside = (b >= 0) & (b < len(edges) - 1)
    counts = np.bincount(b[inside], minlength=len(edges) - 1)
    sums = np.bincount(b[inside], weights=y[inside], minlength=len(edges) - 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts >= max(min_count, 1), sums / np.maximum(counts, 1), np.nan)
    return 0.5 * (edges[1:] + edges[:-1]), means, counts


def binned_mean_plot(
    classes: NDArray[np.object_],
    x: FloatArray,
    y: FloatArray,
    edges: FloatArray,
    title: str,
    xlabel: str,
    ylabel: str = "mean JIoU-GT",
) -> Plot:
    """Fig. 7b/7c: the mean of ``y`` per bin of ``x``, one line per class (bins with too few objects left out)."""
    fig, ax = _figure()
    data: dict[str, Any] = {}
    names = _class_order(classes) if len(classes) else []
    drawn = 0
    for k, name in enumerate(names):
        m = classes == name
        centres, means, counts = binned_means(x[m], y[m], edges)
        data[name] = {"centres": centres.tolist(), "means": means.tolist(), "counts": counts.tolist()}
        if np.isfinite(means).any():
            ax.plot(
                centres,
                means,
                marker="o",
                markersize=4,
                color=PALETTE[k % len(PALETTE)],
                label=f"{name} (n={int(np.isfinite(x[m] + y[m]).sum())})",
            )
            drawn += 1
    if drawn:
        ax.legend(fontsize=8)
    else:
        _empty(ax, "not enough objects per bin")
    ax.set_xlabel(xlabel, fontsize=9)
    ax.set_ylabel(ylabel, fontsize=9)
    ax.set_title(title, fontsize=10)
    note = f"bins with fewer than {C.REPORT_MIN_BIN_COUNT} objects are left out"
    return Plot(_png(fig), title, data, note)


def distribution_plot(
    classes: NDArray[np.object_], values: FloatArray, title: str, xlabel: str, bins: int = 40, log: bool = False
) -> Plot:
    """Histogram of a score in [0, 1] per class (fraction of the class's objects per bin)."""
    fig, ax = _figure()
    edges = np.linspace(0.0, 1.0, bins + 1)
    data: dict[str, Any] = {}
    ok = np.isfinite(values)
    names = _class_order(classes[ok]) if ok.any() else []
    for k, name in enumerate(names):
        v = values[ok & (classes == name)]
        counts, _ = np.histogram(np.clip(v, 0.0, 1.0), bins=edges)
        frac = counts / max(len(v), 1)
        data[name] = {"counts": counts.tolist(), "median": float(np.median(v)), "count": int(len(v))}
        ax.stairs(
            frac,
            edges,
            color=PALETTE[k % len(PALETTE)],
            linewidth=1.5,
            label=f"{name} (n={len(v)}, median {np.median(v):.3f})",
        )
    if names:
        ax.legend(fontsize=8)
        if log:
            ax.set_yscale("log")
    else:
        _empty(ax, "no values")
    ax.set_xlim(0.0, 1.0)
    ax.set_xlabel(xlabel, fontsize=9)
    ax.set_ylabel("fraction of the class's objects" + (" (log)" if log else ""), fontsize=9)
    ax.set_title(title, fontsize=10)
    return Plot(_png(fig), title, data)


def log_point_edges(num_points: FloatArray) -> FloatArray:
    """Bin edges of log10(number of points) from 0 to past the largest count."""
    top = float(np.log10(np.nanmax(num_points))) if len(num_points) and np.nanmax(num_points) >= 1 else 1.0
    step = C.REPORT_LOG_POINTS_BIN
    return np.arange(0.0, top + step + 1e-9, step)


def distance_edges(distance: FloatArray) -> FloatArray:
    """Bin edges of the distance from 0 to past the largest distance."""
    top = float(np.nanmax(distance)) if len(distance) and np.isfinite(distance).any() else C.REPORT_DISTANCE_BIN
    step = C.REPORT_DISTANCE_BIN
    return np.arange(0.0, top + step + 1e-9, step)


def standard_plots(
    classes: Sequence[str] | NDArray[np.object_],
    jiou: FloatArray,
    label_error: FloatArray,
    distance: FloatArray,
    num_points: FloatArray,
    corner_tv: FloatArray,
) -> list[Plot]:
    """The report's five plots from the columns of the audited objects (one entry per object)."""
    cls = np.asarray(classes, dtype=object)
    n = np.asarray(num_points, dtype=float)
    with np.errstate(divide="ignore"):
        logn = np.where(n >= 1, np.log10(np.maximum(n, 1)), np.nan)
    return [
        corner_variance_plot(cls, corner_tv),
        binned_mean_plot(
            cls,
            distance,
            jiou,
            distance_edges(distance),
            "Mean JIoU-GT vs distance to the sensor (Fig. 7b)",
            "distance (m)",
        ),
        binned_mean_plot(
            cls, logn, jiou, log_point_edges(n), "Mean JIoU-GT vs number of points (Fig. 7c)", "log10(number of points)"
        ),
        distribution_plot(cls, jiou, "Distribution of JIoU-GT per class", "JIoU-GT (1 = certain)"),
        distribution_plot(
            cls, label_error, "Distribution of label_error per class", "label_error (1 = surely wrong)", log=True
        ),
    ]

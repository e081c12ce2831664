"""Bird's-eye-view pictures of labels: one object with its spatial distribution, or a whole frame.

:func:`render_object` draws the paper's Fig. 1 view of one :class:`~labelaudit.viz.objects.ObjectAudit`
in the label's own frame (x along its length): p_G as a heatmap, the crop's points coloured by
height, the labeled box, the 1-σ ellipses of its four corners (C1, nearest the sensor, marked),
the label-error fit's suggested box, the direction to the sensor, a metric scale bar and a caption
with the row's numbers. :func:`render_frame` draws every box of a frame over its points, coloured
by a score, the worst numbered. Both return the arrays they plot next to the PNG bytes, so tests
can check what is drawn. Matplotlib's object API on an Agg canvas (no pyplot state, no display).
This module computes no model quantity itself; it only transforms and draws.
"""

from __future__ import annotations

import io
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.cm import ScalarMappable
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Ellipse, Polygon
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.core import geometry as g
from labelaudit.core.posterior import corner_covariances as corner_cov
from labelaudit.datasets.base import RegionOfInterest, box_problems
from labelaudit.viz.objects import AUDITED_STATUSES, ObjectAudit, TrackView

FloatArray = NDArray[np.float64]

__all__ = [
    "ObjectPicture",
    "FramePicture",
    "CandidatePicture",
    "render_object",
    "render_frame",
    "render_candidate",
    "parse_size",
    "corner_covariances",
    "SCORES",
]

SCORES = {"jiou_gt": "JIoU-GT", "label_error": "label_error"}
"""Scores a frame picture can colour boxes by (low JIoU-GT is bad; high label_error is bad)."""

# Colours: the heatmap is the background, everything drawn over it must stay visible on it.
HEAT_CMAP = "magma"
HEIGHT_CMAP = "cool"  # bright at both ends: visible on the dark surround and on the bright box interior
SCORE_CMAP = {"jiou_gt": "RdYlGn", "label_error": "RdYlGn_r"}
LABEL_COLOUR = "#ffffff"
FIT_COLOUR = "#00e5ff"
ELLIPSE_COLOUR = "#7CFC00"
CONTEXT_COLOUR = "#8a8a8a"
TRACK_CMAP = "coolwarm"  # the track's other frames: blue earlier, red later
EXPECTED_COLOUR = "#ffd400"  # the box the rest of the track expects in this frame
CANDIDATE_COLOUR = (
    "#ff3df5"  # missing-label candidates: magenta, outside the red–yellow–green of the scores and the cool/magma maps
)
REGION_COLOUR = "#ff9800"  # the map's drivable area (Argoverse 2 labels within a margin of it): orange, dashed
OTHER_LABEL_COLOUR = "#5c8fb0"  # labels of classes not audited (they explain their returns): muted blue, thin


def fit_view(
    lo: FloatArray, hi: FloatArray, ax_rect: tuple[float, float, float, float], size: tuple[int, int]
) -> tuple[float, float, float, float]:
    """(x0, x1, y0, y1) around the (2,) corners ``lo``, ``hi`` grown so one metre is as long in x as in y on an
    axes of ``ax_rect`` (figure fractions) in a figure of ``size`` pixels."""
    aspect = (ax_rect[3] * size[1]) / (ax_rect[2] * size[0])
    span_x, span_y = hi[0] - lo[0], hi[1] - lo[1]
    if span_y / span_x < aspect:
        span_y = span_x * aspect
    else:
        span_x = span_y / aspect
    mid = 0.5 * (lo + hi)
    return (
        float(mid[0] - span_x / 2),
        float(mid[0] + span_x / 2),
        float(mid[1] - span_y / 2),
        float(mid[1] + span_y / 2),
    )


def parse_size(text: str) -> tuple[int, int]:
    """``"640x600"`` or ``"640"`` (square) → (width, height) in pixels.

    Raises
    ------
    ValueError
        Not of that form, or a side outside [64, 8192].
    """
    parts = text.lower().replace("×", "x").split("x")
    try:
        w, h = (int(parts[0]), int(parts[-1])) if len(parts) in (1, 2) else (0, 0)
    except ValueError:
        w = h = 0
    if not (64 <= w <= 8192 and 64 <= h <= 8192):
        raise ValueError(
            f"size {text!r}: expected WIDTHxHEIGHT in pixels (e.g. 640x600, or 640 for a square), each 64–8192"
        )
    return w, h


def _figure(size: tuple[int, int]) -> Figure:
    fig = Figure(figsize=(size[0] / C.VIZ_DPI, size[1] / C.VIZ_DPI), dpi=C.VIZ_DPI)
    FigureCanvasAgg(fig)
    return fig


def _png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    # No bbox_inches: the PNG has exactly the requested size. zlib level 1 instead of 6: measured
    # ~25 ms less per gallery picture for ~15 % more bytes.
    fig.savefig(buf, format="png", dpi=C.VIZ_DPI, pil_kwargs={"compress_level": 1})
    return buf.getvalue()


def _to_box_frame(xy: FloatArray, box: FloatArray) -> FloatArray:
    """World BEV points (N, 2) → the box frame (origin at the centre, x along the length)."""
    c, s = math.cos(box[6]), math.sin(box[6])
    d = np.asarray(xy, dtype=float)[:, :2] - box[:2]
    return np.c_[c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]]


def corner_covariances(audit: ObjectAudit) -> FloatArray:
    """BEV covariance (4, 2, 2) of the label's corners, world frame, C1..C4 (nearest the sensor first).

    The x–y blocks of :func:`labelaudit.core.posterior.corner_covariances`, in the posterior's corner order.
    """
    post = audit.posterior
    return corner_cov(post.cov, post.model)[:, :2, :2][post.corner_order]


def _nice_length(span: float) -> float:
    """A round scale-bar length of about a fifth of ``span`` metres."""
    target = span / 5.0
    for v in (0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0, 50.0, 100.0):
        if v >= target:
            return v
    return 100.0


def _fmt(v: Any, spec: str = ".3f", unit: str = "") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return f"{v:{spec}}{unit}"


def _add_scale_bar(ax: Any, view: tuple[float, float, float, float], colour: str) -> float:
    """A metric scale bar in the lower right corner (a plain line and label: cheap to draw)."""
    span_x, span_y = view[1] - view[0], view[3] - view[2]
    length = _nice_length(span_x)
    x1, y = view[1] - 0.04 * span_x, view[2] + 0.06 * span_y
    ax.plot([x1 - length, x1], [y, y], color=colour, linewidth=3, solid_capstyle="butt", zorder=9)
    ax.text(
        x1 - length / 2,
        y + 0.015 * span_y,
        f"{length:g} m",
        color=colour,
        fontsize=8,
        ha="center",
        va="bottom",
        zorder=9,
    )
    return length


def _colour_bar(fig: Figure, mappable: Any, rect: tuple[float, float, float, float], label: str) -> None:
    """A labelled colour bar in its own axes at ``rect`` (figure fractions), small type."""
    cb = fig.colorbar(mappable, cax=fig.add_axes(rect))
    cb.set_label(label, fontsize=7)
    cb.ax.tick_params(labelsize=6)


def _add_sensor_arrow(ax: Any, view: tuple[float, float, float, float], direction: FloatArray, distance: float) -> None:
    """An arrow near the upper-left corner pointing to the sensor (data coordinates keep its angle), with the distance."""
    span_x, span_y = view[1] - view[0], view[3] - view[2]
    start = np.array([view[0] + 0.16 * span_x, view[3] - 0.16 * span_y])
    tip = start + 0.08 * span_x * direction
    ax.annotate(
        "",
        xy=tuple(tip),
        xytext=tuple(start - 0.08 * span_x * direction),
        arrowprops={"arrowstyle": "-|>", "color": "white", "lw": 1.4},
        zorder=8,
    )
    label_at = start - 0.15 * span_x * direction  # behind the arrow's tail, whichever way it points
    label_at = np.clip(
        label_at, [view[0] + 0.08 * span_x, view[2] + 0.05 * span_y], [view[1] - 0.08 * span_x, view[3] - 0.05 * span_y]
    )
    ax.text(
        label_at[0],
        label_at[1],
        f"to sensor\n{distance:.1f} m",
        color="white",
        fontsize=7,
        ha="center",
        va="center",
        zorder=8,
    )


# --------------------------------------------------------------------------- one object


@dataclass(frozen=True)
class ObjectPicture:
    """A rendered object picture and the arrays it shows (box frame: x along the label's length, metres).

    Attributes
    ----------
    png : the PNG file's bytes
    size : (width, height) in pixels
    density : (ny, nx) p_G density as drawn, relative to the label's uniform density 1/(l·w)
        (1 = the density of a certain box); row 0 at ``extent[2]``
    extent : (x0, x1, y0, y1) of the heatmap
    points_xy : (N, 2) the model's points; point_height : (N,) their height above the box bottom (m)
    fit_only_xy : (M, 2) points only the label-error fit saw; context_xy : (K, 2) other nearby points
    label_corners, fit_corners : (4, 2) the labeled and the suggested box (box_corners' order)
    ellipse_centres : (4, 2) the label's corners C1..C4; ellipse_covs : (4, 2, 2) their covariances
    sensor_direction : (2,) unit vector from the box centre towards the sensor
    view : (x0, x1, y0, y1) axes limits
    caption : the caption text
    track_corners : (T, 4, 2) the object's labels in the neighbouring frames of its track (box frame)
    expected_corners : (4, 2) the box the rest of the track expects in this frame (box frame), or (0, 2)
    """

    png: bytes
    size: tuple[int, int]
    density: FloatArray
    extent: tuple[float, float, float, float]
    points_xy: FloatArray
    point_height: FloatArray
    fit_only_xy: FloatArray
    context_xy: FloatArray
    label_corners: FloatArray
    fit_corners: FloatArray
    ellipse_centres: FloatArray
    ellipse_covs: FloatArray
    sensor_direction: FloatArray
    view: tuple[float, float, float, float]
    caption: str
    track_corners: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 2)))
    expected_corners: FloatArray = field(default_factory=lambda: np.zeros((0, 2)))


def _caption(audit: ObjectAudit, track: TrackView | None = None) -> str:
    row = audit.row or {}
    where = f"frame {row['frame_id']} · object {row['object_index']}" if "frame_id" in row else "object"
    status = row.get("status", "")
    first = f"{audit.class_name} · {where} · {audit.distance:.1f} m · {len(audit.points)} points" + (
        f" ({status})" if status and status != "ok" else ""
    )
    second = f"JIoU-GT {_fmt(audit.jiou_gt)}   label_error {_fmt(audit.label_error)}   σ̂ {_fmt(audit.sigma_hat, '.3f', ' m')}"
    if track is not None:
        issue = f" ({track.track_issue})" if track.track_issue not in (None, "none") else ""
        size = (
            ""
            if track.size is None
            else f"   track size {track.size[0]:.2f} × {track.size[1]:.2f} m (label {audit.box[3]:.2f} × {audit.box[4]:.2f})"
        )
        second += f"\ntrack_error {_fmt(track.track_error)}{issue}{size}"
    return f"{first}\n{second}"


def _ellipse(ax: Any, centre: FloatArray, cov: FloatArray, **kw: Any) -> None:
    lam, V = np.linalg.eigh(0.5 * (cov + cov.T))
    lam = np.clip(lam, 0.0, None)
    angle = math.degrees(math.atan2(V[1, 1], V[0, 1]))
    ax.add_patch(Ellipse(tuple(centre), 2 * math.sqrt(lam[1]), 2 * math.sqrt(lam[0]), angle=angle, **kw))


def render_object(
    audit: ObjectAudit,
    size: tuple[int, int] = C.SHOW_SIZE,
    *,
    overlays: bool = True,
    compact: bool = False,
    track: TrackView | None = None,
) -> ObjectPicture:
    """Draw one label with its spatial distribution (the paper's Fig. 1 look).

    Parameters
    ----------
    audit : the recomputed object (:func:`labelaudit.viz.objects.recompute` or ``audit_view``)
    size : (width, height) of the PNG in pixels
    overlays : False draws the heatmap alone (no points, boxes, ellipses, scale or labels), for
        checking the rendered pixels against p_G
    compact : no colour bars, legend, ticks or caption (the report's gallery explains the colours
        once and prints the numbers beside the picture): a larger plot, under half the drawing time
    track : the object's labels in the neighbouring frames of its track
        (:func:`labelaudit.viz.objects.track_view`), drawn as thin outlines coloured by time

    Returns
    -------
    ObjectPicture
    """
    box = audit.box
    grid = audit.grid
    # p_G is computed in the label's frame (grid.ref is the label): the picture is drawn there too.
    cell = np.outer(np.diff(grid.y_edges), np.diff(grid.x_edges))
    density = audit.mass / cell * (box[3] * box[4])
    extent = (float(grid.x_edges[0]), float(grid.x_edges[-1]), float(grid.y_edges[0]), float(grid.y_edges[-1]))

    pts = _to_box_frame(audit.points[:, :2], box) if len(audit.points) else np.zeros((0, 2))
    height = (audit.points[:, 2] - (box[2] - box[5] / 2)) if len(audit.points) else np.zeros(0)
    fit_only, ctx = audit.fit_only, audit.context
    fit_only_xy = _to_box_frame(fit_only[:, :2], box) if len(fit_only) else np.zeros((0, 2))
    context_xy = _to_box_frame(ctx[:, :2], box) if len(ctx) else np.zeros((0, 2))

    label_corners = _to_box_frame(g.box_corners(box, "bev"), box)
    fit_corners = _to_box_frame(g.box_corners(audit.fit.box, "bev"), box)
    covs_world = corner_covariances(audit)
    R = g.rotation_2d(box[6])
    covs = np.einsum("ji,cjk,kl->cil", R, covs_world, R)  # Rᵀ C R: into the box frame
    centres = label_corners[audit.posterior.corner_order]
    to_sensor = audit.sensor_origin[:2] - box[:2]
    sensor_dir = _to_box_frame((audit.sensor_origin[:2])[None], box)[0]
    sensor_dir = sensor_dir / max(float(np.linalg.norm(sensor_dir)), 1e-12)

    # View: the label, the suggested box and the 2-σ corner ellipses, plus a margin; the figure's aspect.
    track_corners = (
        np.array([_to_box_frame(g.box_corners(b, "bev"), box) for b in track.boxes])
        if track is not None and len(track.boxes)
        else np.zeros((0, 4, 2))
    )
    expected_corners = (
        _to_box_frame(g.box_corners(track.expected, "bev"), box)
        if track is not None and track.expected is not None
        else np.zeros((0, 2))
    )
    reach = np.vstack(
        [
            label_corners,
            fit_corners,
            centres + 2 * np.sqrt(covs[:, [0, 1], [0, 1]]),
            centres - 2 * np.sqrt(covs[:, [0, 1], [0, 1]]),
            track_corners.reshape(-1, 2),
            expected_corners,
        ]
    )
    lo, hi = reach.min(axis=0) - C.SHOW_VIEW_MARGIN, reach.max(axis=0) + C.SHOW_VIEW_MARGIN
    fig = _figure(size)
    ax_rect = ((0.01, 0.01, 0.98, 0.98) if compact else (0.1, 0.13, 0.72, 0.74)) if overlays else (0.0, 0.0, 1.0, 1.0)
    ax = fig.add_axes(ax_rect)
    view = fit_view(lo, hi, ax_rect, size)

    heat_norm = Normalize(0.0, max(1.0, float(density.max())))
    heat_cmap = colormaps[HEAT_CMAP]
    ax.set_facecolor(heat_cmap(0.0))  # beyond the grid p_G is 0: the background continues the heatmap
    heat = ax.imshow(
        density, extent=extent, origin="lower", cmap=heat_cmap, norm=heat_norm, interpolation="nearest", zorder=0
    )
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal")
    caption = _caption(audit, track)

    def picture() -> ObjectPicture:  # the figure as drawn so far, with the arrays it shows
        return ObjectPicture(
            _png(fig),
            size,
            density,
            extent,
            pts,
            height,
            fit_only_xy,
            context_xy,
            label_corners,
            fit_corners,
            centres,
            covs,
            sensor_dir,
            view,
            caption,
            track_corners,
            expected_corners,
        )

    if not overlays:
        ax.set_axis_off()
        return picture()

    if len(context_xy):
        ax.plot(
            context_xy[:, 0],
            context_xy[:, 1],
            ls="",
            marker="o",
            markersize=1.4,
            markerfacecolor=CONTEXT_COLOUR,
            markeredgewidth=0,
            zorder=2,
        )
    if len(fit_only_xy):
        ax.plot(
            fit_only_xy[:, 0],
            fit_only_xy[:, 1],
            ls="",
            marker="o",
            markersize=2.4,
            markerfacecolor="none",
            markeredgecolor="#d0d0d0",
            markeredgewidth=0.6,
            zorder=3,
        )
    h_top = max(float(box[5]), 0.5)
    # A dense crop (up to ~10k points) is drawn with an even subsample: the picture looks the same,
    # the marker pass dominated the drawing time. ``points_xy`` keeps every point.
    step = max(1, -(-len(pts) // C.SHOW_MAX_POINTS_DRAWN))
    pts_art = (
        ax.scatter(
            pts[::step, 0],
            pts[::step, 1],
            s=9,
            c=height[::step],
            cmap=HEIGHT_CMAP,
            vmin=0.0,
            vmax=h_top,
            edgecolors="black",
            linewidths=0.3,
            zorder=4,
        )
        if len(pts)
        else None
    )
    if len(track_corners):
        span = max(float(np.abs(track.dt).max()), 1e-9)  # type: ignore[union-attr]
        tcmap = colormaps[TRACK_CMAP]
        for corners, dt in zip(track_corners, track.dt):  # type: ignore[union-attr]
            colour = tcmap(0.5 + 0.5 * dt / span)
            ax.add_patch(
                Polygon(corners, closed=True, fill=False, edgecolor=colour, linewidth=1.0, alpha=0.9, zorder=4.5)
            )
            front = corners[[0, 3]].mean(axis=0)  # box_corners: 0 front-left, 3 front-right
            mid = corners.mean(axis=0)
            ax.plot([mid[0], front[0]], [mid[1], front[1]], color=colour, linewidth=0.8, alpha=0.9, zorder=4.5)
    if len(expected_corners):
        ax.add_patch(
            Polygon(
                expected_corners,
                closed=True,
                fill=False,
                edgecolor=EXPECTED_COLOUR,
                linewidth=1.4,
                linestyle=(0, (1.5, 1.5)),
                zorder=5,
            )
        )
        tip, mid = expected_corners[[0, 3]].mean(axis=0), expected_corners.mean(axis=0)
        ax.plot(
            [mid[0], tip[0]],
            [mid[1], tip[1]],
            color=EXPECTED_COLOUR,
            linewidth=1.0,
            linestyle=(0, (1.5, 1.5)),
            zorder=5,
        )
    ax.add_patch(Polygon(label_corners, closed=True, fill=False, edgecolor=LABEL_COLOUR, linewidth=1.6, zorder=5))
    ax.add_patch(
        Polygon(
            fit_corners, closed=True, fill=False, edgecolor=FIT_COLOUR, linewidth=1.4, linestyle=(0, (4, 2)), zorder=5
        )
    )
    # Heading: a short tick from the centre to the front face.
    ax.plot([0.0, box[3] / 2], [0.0, 0.0], color=LABEL_COLOUR, linewidth=0.8, alpha=0.7, zorder=5)
    for k, (c, cv) in enumerate(zip(centres, covs)):
        _ellipse(ax, c, cv, fill=False, edgecolor=ELLIPSE_COLOUR, linewidth=1.2 if k else 1.8, zorder=6)
    ax.scatter(centres[1:, 0], centres[1:, 1], s=10, c=ELLIPSE_COLOUR, zorder=7)
    ax.scatter(
        centres[:1, 0], centres[:1, 1], s=40, marker="*", c=ELLIPSE_COLOUR, edgecolors="black", linewidths=0.4, zorder=7
    )
    out = centres[0] / max(float(np.linalg.norm(centres[0])), 1e-9)
    ax.annotate(
        "C1",
        xy=tuple(centres[0]),
        xytext=tuple(out * 14),
        textcoords="offset points",
        color=ELLIPSE_COLOUR,
        fontsize=9,
        fontweight="bold",
        ha="center",
        va="center",
        zorder=8,
    )

    _add_sensor_arrow(ax, view, sensor_dir, float(np.hypot(*to_sensor)))
    _add_scale_bar(ax, view, "white")

    if compact:  # the scale bar gives the metres and the report prints the numbers beside the picture: ticks and glyphs cost most of the drawing
        ax.set_xticks([])
        ax.set_yticks([])
        return picture()
    fig.text(ax_rect[0], 0.985, caption, ha="left", va="top", fontsize=9)
    ax.tick_params(labelsize=7)
    ax.set_xlabel("along the label's length (m)", fontsize=8)
    ax.set_ylabel("across (m)", fontsize=8)
    _colour_bar(fig, heat, (0.855, 0.52, 0.025, 0.35), "p_G × l·w (1 = certain box)")
    if pts_art is not None:
        _colour_bar(fig, pts_art, (0.855, 0.13, 0.025, 0.33), "point height above box bottom (m)")
    handles = [
        Line2D([], [], color=LABEL_COLOUR, lw=1.6, label="label"),
        Line2D([], [], color=FIT_COLOUR, lw=1.4, ls=(0, (4, 2)), label="suggested box (fit)"),
        Line2D(
            [],
            [],
            color=ELLIPSE_COLOUR,
            lw=1.2,
            marker="*",
            markersize=7,
            markeredgecolor="black",
            label="corner 1-σ (C1 ★ nearest sensor)",
        ),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            markersize=4,
            markerfacecolor="#8f70ff",
            markeredgecolor="black",
            label="model's points",
        ),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            markersize=4,
            markerfacecolor="none",
            markeredgecolor="#777",
            label="fit-only points",
        ),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            markersize=3,
            markerfacecolor=CONTEXT_COLOUR,
            markeredgecolor="none",
            label="other points",
        ),
    ]
    if len(track_corners):
        handles.append(Line2D([], [], color=colormaps[TRACK_CMAP](0.0), lw=1.0, label="track: earlier"))
        handles.append(Line2D([], [], color=colormaps[TRACK_CMAP](1.0), lw=1.0, label="track: later"))
    if len(expected_corners):
        handles.append(Line2D([], [], color=EXPECTED_COLOUR, lw=1.4, ls=(0, (1.5, 1.5)), label="track expects here"))
    leg = fig.legend(
        handles=handles,
        loc="lower left",
        bbox_to_anchor=(0.06 if len(handles) <= 8 else 0.0, 0.0),
        ncol=3 if len(handles) <= 6 else 4 if len(handles) <= 8 else 5,
        fontsize=6.5,
        frameon=True,
        handlelength=2.2 if len(handles) <= 8 else 1.6,
        columnspacing=1.0 if len(handles) <= 8 else 0.6,
        labelcolor="white",
    )
    leg.get_frame().set_facecolor(heat_cmap(0.0))  # the label's white line needs the heatmap's dark ground
    leg.get_frame().set_edgecolor("none")
    return picture()


# --------------------------------------------------------------------------- a whole frame


@dataclass(frozen=True)
class FramePicture:
    """A rendered frame picture and what it shows (LiDAR frame, metres).

    Attributes
    ----------
    png : PNG bytes; size : (width, height) pixels
    object_indices : (K,) object_index of every drawn box (all rows of the frame)
    corners : (K, 4, 2) BEV corners of those boxes
    scores : (K,) the ``by`` score (NaN for rows without one: skipped, error)
    numbered : object_index of the numbered boxes, worst first (number 1 = worst)
    view : (x0, x1, y0, y1) axes limits
    caption : the caption text
    candidate_indices : (M,) candidate_index of every drawn missing-label candidate
    candidate_corners : (M, 4, 2) their BEV corners
    """

    png: bytes
    size: tuple[int, int]
    object_indices: NDArray[np.int64]
    corners: FloatArray
    scores: FloatArray
    numbered: list[int]
    view: tuple[float, float, float, float]
    caption: str
    candidate_indices: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    candidate_corners: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 2)))


def worst_order(scores: FloatArray, by: str) -> NDArray[np.int64]:
    """Indices of the finite scores, worst first (JIoU-GT ascending, label_error descending); ties by position."""
    ok = np.flatnonzero(np.isfinite(scores))
    key = scores[ok] if by == "jiou_gt" else -scores[ok]
    return ok[np.argsort(key, kind="stable")]


def render_frame(
    frame_id: str,
    points: FloatArray,
    rows: Sequence[Mapping[str, Any]],
    by: str = "jiou_gt",
    size: tuple[int, int] = C.SHOW_FRAME_SIZE,
    worst: int = C.SHOW_FRAME_WORST,
    sensor_origin: FloatArray | None = None,
    candidates: Sequence[Mapping[str, Any]] = (),
    *,
    other_labels: FloatArray | None = None,
    roi: RegionOfInterest | None = None,
) -> FramePicture:
    """Draw every audited box of a frame over its points, coloured by ``by``, the ``worst`` numbered;
    missing-label candidates in their own style (magenta, dashed, ``M<candidate_index>``) with a legend;
    the frame's other labels (classes not audited) thin, and the region where the dataset labels.

    Parameters
    ----------
    frame_id : for the caption
    points : (N, ≥3) the frame's points
    rows : the frame's result rows (box columns, status and the score)
    by : "jiou_gt" or "label_error"
    size : (width, height) pixels
    worst : how many of the worst boxes get a number
    sensor_origin : (3,) sensor position (drawn as a marker)
    candidates : the frame's missing-label candidate rows to draw (box columns, candidate_index, score, class_name)
    other_labels : (K, 7) the frame's labels that have no row (classes not audited): they explain their returns
    roi : the frame's region of interest (Argoverse 2 with its map): its drivable-area polygons, dashed
    """
    if by not in SCORES:
        raise ValueError(f"by must be one of {', '.join(SCORES)}, got {by!r}")
    boxes = np.array(
        [[r[c] for c in ("cx", "cy", "cz", "length", "width", "height", "yaw")] for r in rows], dtype=float
    ).reshape(-1, 7)
    refused = box_problems(boxes, g.BOX_FIELDS)
    drawable = np.array([i not in refused for i in range(len(rows))], dtype=bool)
    if not drawable.all():  # a label the reader refused (NaN, absurd size): an error row with no box to draw
        rows = [r for r, ok in zip(rows, drawable) if ok]
        boxes = boxes[drawable]
    scores = np.array(
        [np.nan if r.get(by) is None or r.get("status") not in AUDITED_STATUSES else float(r[by]) for r in rows],
        dtype=float,
    )
    indices = np.array([int(r["object_index"]) for r in rows], dtype=np.int64)
    corners = np.array([g.box_corners(b, "bev") for b in boxes]).reshape(-1, 4, 2)
    order = worst_order(scores, by)[:worst]
    numbered = [int(indices[k]) for k in order]

    cand_boxes = np.array([[r[c] for c in g.BOX_FIELDS] for r in candidates], dtype=float).reshape(-1, 7)
    cand_corners = np.array([g.box_corners(b, "bev") for b in cand_boxes]).reshape(-1, 4, 2)
    cand_indices = np.array([int(r["candidate_index"]) for r in candidates], dtype=np.int64)

    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=float).reshape(3)
    reach = np.vstack([corners.reshape(-1, 2), cand_corners.reshape(-1, 2), origin[None, :2]])
    lo, hi = reach.min(axis=0) - C.SHOW_FRAME_MARGIN, reach.max(axis=0) + C.SHOW_FRAME_MARGIN
    fig = _figure(size)
    # The caption has a third line when candidates are listed: the axes give it room (≈15 px a line).
    ax_rect = (0.07, 0.08, 0.8, 0.84 - (15.0 / size[1] if len(candidates) else 0.0))
    ax = fig.add_axes(ax_rect)
    view = fit_view(lo, hi, ax_rect, size)

    ax.set_facecolor("#111111")
    pts = np.asarray(points, dtype=float)
    if len(pts):
        inside = (pts[:, 0] >= view[0]) & (pts[:, 0] <= view[1]) & (pts[:, 1] >= view[2]) & (pts[:, 1] <= view[3])
        p = pts[inside]
        if len(p):
            # Ground returns dim, anything standing on it bright: height above the 10th z percentile.
            rise = np.clip((p[:, 2] - np.percentile(p[:, 2], 10)) / 1.5, 0.0, 1.0)
            ax.scatter(
                p[:, 0],
                p[:, 1],
                s=0.5,
                c=0.25 + 0.75 * rise,
                cmap="Greys_r",
                vmin=0.0,
                vmax=1.0,
                linewidths=0,
                rasterized=True,
                zorder=1,
            )
    cmap = colormaps[SCORE_CMAP[by]]
    norm = Normalize(0.0, 1.0)
    for k in range(len(boxes)):
        colour = "#9e9e9e" if not np.isfinite(scores[k]) else cmap(norm(scores[k]))
        ax.add_patch(
            Polygon(
                corners[k],
                closed=True,
                fill=False,
                edgecolor=colour,
                linewidth=1.5,
                linestyle="-" if np.isfinite(scores[k]) else ":",
                zorder=3,
            )
        )
        front = corners[k][[0, 3]].mean(axis=0)
        ax.plot([boxes[k, 0], front[0]], [boxes[k, 1], front[1]], color=colour, linewidth=0.8, zorder=3)
    for n, k in enumerate(order, start=1):
        ax.text(
            boxes[k, 0],
            boxes[k, 1],
            str(n),
            color="white",
            fontsize=9,
            fontweight="bold",
            ha="center",
            va="center",
            zorder=5,
            bbox={
                "boxstyle": "circle,pad=0.2",
                "facecolor": "black",
                "edgecolor": cmap(norm(scores[k])),
                "linewidth": 1.2,
            },
        )
    others = np.zeros((0, 7)) if other_labels is None else np.asarray(other_labels, dtype=float).reshape(-1, 7)
    others = others[np.all(np.isfinite(others), axis=1)]
    for b in others:
        ax.add_patch(
            Polygon(
                g.box_corners(b, "bev"), closed=True, fill=False, edgecolor=OTHER_LABEL_COLOUR, linewidth=0.8, zorder=2
            )
        )
    for poly in roi.polygons if roi is not None else ():
        ax.add_patch(
            Polygon(
                poly, closed=True, fill=False, edgecolor=REGION_COLOUR, linewidth=0.9, linestyle=(0, (5, 3)), zorder=2
            )
        )
    for k, r in enumerate(candidates):
        _draw_candidate(ax, cand_boxes[k, :2], cand_corners[k], f"M{int(r['candidate_index'])} {float(r['score']):.2f}")
    ax.scatter([origin[0]], [origin[1]], marker="^", s=60, c="#00e5ff", edgecolors="black", zorder=6)
    ax.annotate(
        "sensor",
        xy=(origin[0], origin[1]),
        xytext=(6, -10),
        textcoords="offset points",
        color="#00e5ff",
        fontsize=8,
        zorder=6,
    )
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=7)
    ax.set_xlabel("x (m, forward)", fontsize=8)
    ax.set_ylabel("y (m, left)", fontsize=8)
    _add_scale_bar(ax, view, "white")
    _colour_bar(
        fig,
        ScalarMappable(norm=norm, cmap=cmap),
        (0.89, 0.08, 0.02, 0.84),
        f"{SCORES[by]} ({'low' if by == 'jiou_gt' else 'high'} = worse; grey dotted: not audited)",
    )
    listed = "  ".join(
        f"{n}: #{i} ({_fmt(scores[k], '.2f')})" for n, (i, k) in enumerate(zip(numbered, order), start=1)
    )
    caption = f"frame {frame_id} · {len(boxes)} boxes coloured by {SCORES[by]} · worst numbered\n{listed or 'no scored boxes'}"
    if len(candidates):
        caption += f"\n{len(candidates)} possibly missing label(s): " + "  ".join(
            f"M{int(r['candidate_index'])} {r['class_name']} ({float(r['score']):.2f})" for r in candidates
        )
    if len(candidates) or len(others) or roi is not None:
        handles = [Line2D([], [], color=colormaps[SCORE_CMAP[by]](0.8), lw=1.5, label=f"label (colour: {SCORES[by]})")]
        if len(others):
            handles.append(Line2D([], [], color=OTHER_LABEL_COLOUR, lw=0.8, label="label of a class not audited"))
        if roi is not None:
            handles.append(
                Line2D(
                    [],
                    [],
                    color=REGION_COLOUR,
                    lw=0.9,
                    ls=(0, (5, 3)),
                    label=f"drivable area (labels within {roi.margin:g} m of it)",
                )
            )
        if len(candidates):
            handles.append(
                Line2D(
                    [],
                    [],
                    color=CANDIDATE_COLOUR,
                    lw=1.8,
                    ls=(0, (4, 2)),
                    label="possibly missing label (M<candidate>, score)",
                )
            )
        leg = ax.legend(handles=handles, loc="lower left", fontsize=7, labelcolor="white", framealpha=0.75)
        leg.get_frame().set_facecolor("#111111")
        leg.set_zorder(10)
    fig.text(0.07, 0.985, caption, ha="left", va="top", fontsize=9)
    png = _png(fig)
    return FramePicture(png, size, indices, corners, scores, numbered, view, caption, cand_indices, cand_corners)


def _draw_candidate(ax: Any, centre: FloatArray, corners: FloatArray, text: str | None) -> None:
    """A missing-label candidate (centre (2,), BEV corners (4, 2)): dashed magenta outline over a faint fill, its heading tick and a tag."""
    ax.add_patch(Polygon(corners, closed=True, facecolor=CANDIDATE_COLOUR, alpha=0.15, edgecolor="none", zorder=3))
    ax.add_patch(
        Polygon(
            corners, closed=True, fill=False, edgecolor=CANDIDATE_COLOUR, linewidth=1.8, linestyle=(0, (4, 2)), zorder=4
        )
    )
    front = corners[[0, 3]].mean(axis=0)
    ax.plot([centre[0], front[0]], [centre[1], front[1]], color=CANDIDATE_COLOUR, linewidth=1.0, zorder=4)
    if text:
        top = corners[np.argmax(corners[:, 1])]
        ax.annotate(
            text,
            xy=tuple(top),
            xytext=(0, 6),
            textcoords="offset points",
            color=CANDIDATE_COLOUR,
            fontsize=8,
            fontweight="bold",
            ha="center",
            va="bottom",
            zorder=6,
            bbox={"boxstyle": "round,pad=0.15", "facecolor": "#111111", "edgecolor": "none", "alpha": 0.7},
        )


# --------------------------------------------------------------------------- one missing-label candidate


@dataclass(frozen=True)
class CandidatePicture:
    """A rendered missing-label candidate and what it shows (the candidate's frame: x along its length, metres).

    Attributes
    ----------
    png : PNG bytes; size : (width, height) pixels
    box_corners : (4, 2) the candidate's BEV corners
    points_xy : (N, 2) points inside the candidate (BEV, up to its top); point_height : (N,) their height above its bottom (m)
    context_xy : (K, 2) other points in view
    label_corners : (L, 4, 2) labels of the frame in view; label_classes : their classes
    sensor_direction : (2,) unit vector towards the sensor
    view : (x0, x1, y0, y1) axes limits
    caption : the caption text
    """

    png: bytes
    size: tuple[int, int]
    box_corners: FloatArray
    points_xy: FloatArray
    point_height: FloatArray
    context_xy: FloatArray
    label_corners: FloatArray
    label_classes: list[str]
    sensor_direction: FloatArray
    view: tuple[float, float, float, float]
    caption: str


EVIDENCE_COLUMNS = ("size_score", "shape_score", "density_score", "free_space_score", "free_rays", "detection_score")
"""Evidence of a candidate named in its caption when the table has them."""


def _candidate_caption(frame_id: str, row: Mapping[str, Any]) -> str:
    first = (f"possibly missing label · frame {frame_id} · candidate {row['candidate_index']} · looks like {row['class_name']} · "
             f"{float(row['distance']):.1f} m · {row['num_points']} points")  # fmt: skip
    evidence = "   ".join(
        f"{c.replace('_score', '')} {_fmt(row[c], '.2f') if isinstance(row[c], float) else row[c]}"
        for c in EVIDENCE_COLUMNS
        if row.get(c) is not None
    )
    return f"{first}\nscore {_fmt(row['score'], '.3f')}   source {row['source']}" + (
        f"   {evidence}" if evidence else ""
    )


def render_candidate(
    frame_id: str,
    points: FloatArray,
    candidate: Mapping[str, Any],
    rows: Sequence[Mapping[str, Any]] = (),
    size: tuple[int, int] = C.SHOW_SIZE,
    sensor_origin: FloatArray | None = None,
    *,
    compact: bool = False,
) -> CandidatePicture:
    """Draw one missing-label candidate over the frame's points, close up, in its own frame.

    Parameters
    ----------
    frame_id : for the caption
    points : (N, ≥3) the frame's points
    candidate : the candidate's row of the missing-label table
    rows : the frame's label rows (their boxes are drawn when in view: a label next to the candidate)
    size : (width, height) pixels
    sensor_origin : (3,) sensor position
    compact : no legend, ticks or caption (the report prints the numbers beside the picture)
    """
    box = np.array([candidate[c] for c in g.BOX_FIELDS], dtype=float)
    corners = _to_box_frame(g.box_corners(box, "bev"), box)
    lo = corners.min(axis=0) - C.SHOW_CANDIDATE_MARGIN
    hi = corners.max(axis=0) + C.SHOW_CANDIDATE_MARGIN
    fig = _figure(size)
    ax_rect = (0.01, 0.01, 0.98, 0.98) if compact else (0.1, 0.13, 0.8, 0.74)
    ax = fig.add_axes(ax_rect)
    view = fit_view(lo, hi, ax_rect, size)

    pts = np.asarray(points, dtype=float).reshape(len(points), -1)
    xy = _to_box_frame(pts[:, :2], box) if len(pts) else np.zeros((0, 2))
    in_view = (xy[:, 0] >= view[0]) & (xy[:, 0] <= view[1]) & (xy[:, 1] >= view[2]) & (xy[:, 1] <= view[3])
    bottom, top = box[2] - box[5] / 2, box[2] + box[5] / 2
    inside = (
        in_view
        & (np.abs(xy[:, 0]) <= box[3] / 2)
        & (np.abs(xy[:, 1]) <= box[4] / 2)
        & (pts[:, 2] >= bottom)
        & (pts[:, 2] <= top)
    )
    context = in_view & ~inside
    points_xy, height, context_xy = xy[inside], pts[inside, 2] - bottom, xy[context]

    ax.set_facecolor("#111111")
    if len(context_xy):
        ax.plot(
            context_xy[:, 0],
            context_xy[:, 1],
            ls="",
            marker="o",
            markersize=1.4,
            markerfacecolor=CONTEXT_COLOUR,
            markeredgewidth=0,
            zorder=2,
        )
    step = max(1, -(-len(points_xy) // C.SHOW_MAX_POINTS_DRAWN))
    pts_art = ax.scatter(points_xy[::step, 0], points_xy[::step, 1], s=9, c=height[::step], cmap=HEIGHT_CMAP, vmin=0.0, vmax=max(float(box[5]), 0.5),
                         edgecolors="black", linewidths=0.3, zorder=4) if len(points_xy) else None  # fmt: skip
    label_corners, label_classes = [], []
    for r in rows:
        lb = np.array([r[c] for c in g.BOX_FIELDS], dtype=float)
        if not np.isfinite(lb).all():
            continue
        lc = _to_box_frame(g.box_corners(lb, "bev"), box)
        if (
            (lc[:, 0].max() < view[0])
            or (lc[:, 0].min() > view[1])
            or (lc[:, 1].max() < view[2])
            or (lc[:, 1].min() > view[3])
        ):
            continue
        label_corners.append(lc)
        label_classes.append(str(r["class_name"]))
        ax.add_patch(Polygon(lc, closed=True, fill=False, edgecolor=LABEL_COLOUR, linewidth=1.4, zorder=5))
        mid = lc.mean(axis=0)
        if view[0] < mid[0] < view[1] and view[2] < mid[1] < view[3]:  # the tag kept whole inside the axes
            inset = 0.1 * (view[1] - view[0])
            at = np.clip(mid, [view[0] + inset, view[2] + inset], [view[1] - inset, view[3] - inset])
            ax.text(
                at[0],
                at[1],
                f"label #{r['object_index']}",
                color=LABEL_COLOUR,
                fontsize=7,
                ha="center",
                va="center",
                zorder=6,
            )
    _draw_candidate(
        ax,
        np.zeros(2),
        corners,
        None if compact else f"M{candidate['candidate_index']} {float(candidate['score']):.2f}",
    )

    origin = np.zeros(3) if sensor_origin is None else np.asarray(sensor_origin, dtype=float).reshape(3)
    sensor_dir = _to_box_frame(origin[None, :2], box)[0]
    distance = float(np.linalg.norm(sensor_dir))
    sensor_dir = sensor_dir / max(distance, 1e-12)
    _add_sensor_arrow(ax, view, sensor_dir, distance)
    _add_scale_bar(ax, view, "white")
    ax.set_xlim(view[0], view[1])
    ax.set_ylim(view[2], view[3])
    ax.set_aspect("equal")
    caption = _candidate_caption(frame_id, candidate)
    label_arr = np.array(label_corners).reshape(-1, 4, 2)
    if compact:
        ax.set_xticks([])
        ax.set_yticks([])
        return CandidatePicture(
            _png(fig), size, corners, points_xy, height, context_xy, label_arr, label_classes, sensor_dir, view, caption
        )
    fig.text(ax_rect[0], 0.985, caption, ha="left", va="top", fontsize=8.5)
    ax.tick_params(labelsize=7)
    ax.set_xlabel("along the candidate's length (m)", fontsize=8)
    ax.set_ylabel("across (m)", fontsize=8)
    if pts_art is not None:
        _colour_bar(fig, pts_art, (0.915, 0.13, 0.022, 0.74), "point height above the candidate's bottom (m)")
    handles = [
        Line2D([], [], color=CANDIDATE_COLOUR, lw=1.8, ls=(0, (4, 2)), label="possibly missing label (no label here)"),
        Line2D([], [], color=LABEL_COLOUR, lw=1.4, label="labels of the frame"),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            markersize=4,
            markerfacecolor="#8f70ff",
            markeredgecolor="black",
            label="points in the candidate",
        ),
        Line2D(
            [],
            [],
            ls="",
            marker="o",
            markersize=3,
            markerfacecolor=CONTEXT_COLOUR,
            markeredgecolor="none",
            label="other points",
        ),
    ]
    leg = fig.legend(
        handles=handles,
        loc="lower left",
        bbox_to_anchor=(0.06, 0.0),
        ncol=2,
        fontsize=6.5,
        frameon=True,
        labelcolor="white",
    )
    leg.get_frame().set_facecolor("#111111")
    leg.get_frame().set_edgecolor("none")
    return CandidatePicture(
        _png(fig), size, corners, points_xy, height, context_xy, label_arr, label_classes, sensor_dir, view, caption
    )

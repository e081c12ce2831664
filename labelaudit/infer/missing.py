"""Frame → missing-label candidates: objects of the audited classes that no label explains.

:func:`find_missing` returns the rows of the ``missing/`` table (:data:`labelaudit.results.MISSING_SCHEMA`)
for one frame; docs/missing.md describes the method. Model-free: the points alone, plus a
detector's output when one is given. Pure function: no files, no printing.

The search, in compiled passes over the frame (a few milliseconds per KITTI frame):

1. ground: the lowest return of every ``MISSING_GROUND_CELL`` cell, the lowest of its 3 × 3
   neighbourhood is the ground under it (a car never covers a neighbourhood of cells), no higher
   than a grey-scale opening of that grid (``MISSING_GROUND_OPENING``) allows, or a wider one
   (``MISSING_GROUND_OPENING_WIDE``) where the opening's square is mostly shadow;
2. the returns between ``MISSING_BAND`` above that ground, within the labelled range, outside the
   ego zone and outside every label grown by ``MISSING_LABEL_MARGIN`` go into a BEV occupancy grid
   of ``MISSING_CELL`` cells; its 8-connected components are the clusters;
3. a cluster of plausible size gets a box: an L-shape fit (the rectangle whose sides the points
   hug, searched over the heading) grown to the class's size away from the sensor (the hidden
   sides) or where lines of sight show no empty road; a box kept so far is then placed, and its
   length chosen, where the frame's rays let its solid body be (:func:`_place_by_rays`), then the
   label-error fit of :mod:`labelaudit.core.fit` from it;
4. its ``score`` multiplies four factors in [0, 1]: size against the class prior, points on one or
   two vertical faces (planar side / L-shape), points against range, and free space (rays that
   pass through the would-be body).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.config import ALL_CLASSES, RunConfig
from labelaudit.core import geometry as g
from labelaudit.core.fit import fit_label_valid
from labelaudit.core.freespace import ray_counts
from labelaudit.core.iou import bev_iou_exact
from labelaudit.datasets import Frame, in_labelled_region
from labelaudit.infer.evidence import frame_evidence, label_boxes
from labelaudit.kernels import kernel

FloatArray = NDArray[np.float64]

__all__ = ["FrameDetections", "SearchTrace", "find_missing", "search_clusters"]


@dataclass(frozen=True)
class FrameDetections:
    """A detector's boxes of one frame (LiDAR/vehicle frame), already above the score threshold."""

    boxes: FloatArray  # (D, 7)
    scores: FloatArray  # (D,)
    class_names: list[str]
    sources: list[str]  # "file:line" per detection


class _Hidden(NamedTuple):
    """How a partly seen cluster's box was grown over its hidden extent (:func:`_box_cluster`), for
    :func:`_place_by_rays`: the cluster's frame (centre (m) and heading t (rad): axes (cos t, sin t)
    and (−sin t, cos t)), its visible rectangle (a1, b1, a2, b2) on them, the class's mean size
    on them (L1, L2), the low ends of the box as placed (A1, A2), which axis is the length, and the
    class's mean and largest length; ``either_axis``: the visible rectangle fits the class's width
    both ways (a car seen from one end, or most of its side hidden), so the length may lie on the
    other axis."""

    cx: float
    cy: float
    t: float
    vis: tuple[float, float, float, float]
    size: tuple[float, float]
    low: tuple[float, float]
    len_axis1: bool
    mean_length: float
    largest_length: float
    either_axis: bool = False


@dataclass(frozen=True)
class Cluster:
    """One candidate from the points: its box and the evidence behind its score."""

    box: FloatArray  # (7,)
    class_name: str
    num_points: int
    ground_z: float
    size_score: float
    shape_score: float
    density_score: float
    free_space_score: float
    free_rays: int
    end_rays: int
    hidden: _Hidden | None = None  # how its box was grown over a hidden extent (:func:`_place_by_rays`); not written

    @property
    def score(self) -> float:
        return self.size_score * self.shape_score * self.density_score * self.free_space_score


@dataclass
class SearchTrace:
    """What became of every cluster of a frame's search (``find_missing(..., trace=)``): for a
    benchmark to say why an object was not found, not for the results.

    ``groups``: one dict per group of joined components with ``x0, y0, x1, y1`` (its BEV bounding
    rectangle, m), ``points`` and ``fate`` — ``"boxed"`` (``clusters``: the indices of its boxes in
    ``clusters``) or the first rule that left it unboxed: ``"points"`` (fewer than ``min_points``),
    ``"footprint"`` (diagonal beyond the largest class or below ``MISSING_MIN_EXTENT``), ``"tall"``
    (returns above the band), ``"low"`` (highest return under ``MISSING_MIN_TOP``), ``"region"``
    (no fragment where labels exist). ``clusters``: (cluster, fate) per box, the fate one of
    ``"region"``, ``"low score"`` (under ``MISSING_MIN_KEPT_SCORE``), ``"label"`` (overlaps a
    label) or ``"kept"`` (written; the cluster after the fit and its free-space score)."""

    groups: list[dict[str, Any]] = field(default_factory=list)
    clusters: list[tuple[Cluster, str]] = field(default_factory=list)


# --------------------------------------------------------------------------- compiled passes


# A sorting network for 9 values (25 compare-exchanges, the fewest possible): every input comes out ascending
# (checked on all 2⁹ inputs of 0s and 1s, which suffices); the ground grid sorts each 3 × 3
# neighbourhood with it.
_SORT9 = np.array(
    [(0, 3), (1, 7), (2, 5), (4, 8), (0, 7), (2, 4), (3, 8), (5, 6), (0, 2), (1, 3), (4, 5), (7, 8), (1, 4)]
    + [(3, 6), (5, 7), (0, 1), (2, 4), (3, 5), (6, 8), (2, 3), (4, 5), (6, 7), (1, 2), (3, 4), (5, 6)],
    dtype=np.int64,
)


@kernel
def _ground_codes(
    flat, m, ox, oy, oz, x0, y0, cell, inv, n0, n1, reach2, sf2, codes, sky, zs
):  # pragma: no cover - compiled
    """Per return k (x, y, z at ``flat[4·k]``…, ``m`` returns): ``codes[k]`` its ground cell's flat
    index (n0 × n1 grid at x0, y0), −2 for one in the grid the ground leaves out (beyond ``reach2``,
    no height), −1 outside the grid; ``sky[k]``: farther than 2 m and above the elevation whose
    slope squared is ``sf2`` (a top beam's candidate); ``zs[k]`` its z, so that the walk after it
    reads 4 contiguous bytes per return instead of the frame's rows again (which no longer fit in
    the core's cache beside the codes). Selections only, no branch, and a constant stride: the
    compiler vectorises it. ``inv``: 1 / ``cell`` when exact, else 0 (divide)."""
    for k in range(m):
        x, y, z = flat[4 * k], flat[4 * k + 1], flat[4 * k + 2]
        dx, dy = x - ox, y - oy
        r2 = dx * dx + dy * dy
        i = int((x - x0) * inv if inv > 0.0 else (x - x0) / cell)
        j = int((y - y0) * inv if inv > 0.0 else (y - y0) / cell)
        inside = (i >= 0) & (i < n0) & (j >= 0) & (j < n1)
        counted = (r2 <= reach2) & (z == z)
        codes[k] = np.int32(i * n1 + j) if inside & counted else np.int32(-2 if inside else -1)
        zs[k] = z
        dz = z - oz
        # only returns above the sensor's lower beams can be a top beam's (spares a sqrt and an atan2 per return)
        sky[k] = (r2 <= reach2) & (r2 > 4.0) & ((dz >= 0.0) | (dz * dz < sf2 * r2))


@kernel
def _ground_grid(
    pts,
    ox,
    oy,
    oz,
    x0,
    y0,
    cell,
    inv,
    n0,
    n1,
    reach2,
    rank,
    share,
    nbins,
    drop,
    slope_floor,
    reach,
    spread,
    wide,
    min_cells,
    near,
):  # pragma: no cover - compiled
    """Of the returns ``pts`` (N, 4: x, y, z, anything; C-contiguous, :func:`_four_columns`): the
    ground height per cell (n0, n1) (inf where unknown) and, per azimuth bin (nbins,), the steepest
    upward slope (z − oz) / r of a return farther than 2 m: the top beam's elevation there, how
    high the sensor sees at a range (a tilted sensor sees higher on one side than on the other);
    a bin whose top lies more than ``spread`` (radians) under the frame's highest holds some lower
    value (its users take it no lower than that).

    A cell's floor is its ``rank``-th lowest return (a few returns below the road — reflections
    off wet asphalt or glossy paint — are ignored). Near the sensor a cell holds hundreds of
    returns, and a dozen may lie under the road — the road's mirror image of a number plate or a
    tail-light: where fewer than a ``share`` of the cell's returns lie within ``near`` above that
    floor, it is such a layer, and the floor is the return that ``share`` of them lie under
    (:func:`_deep_floors`). The ground under a cell is the lowest floor of the 3 × 3 cells around it
    not more than ``drop`` under their median (one cell of such returns is ignored too), so under a
    vehicle, whose cells hold no road returns, it comes from the road beside it. That ground is then opened
    over squares of side 2·``reach`` + 1 cells, and where such a square holds fewer than
    ``min_cells`` cells with returns (a shadow), over squares of side 2·``wide`` + 1 too. ``inv``:
    1 / ``cell`` when that is exact (:func:`_exact_inverse`), else 0.

    Also returns the returns' runs, for the passes after it: maximal runs of consecutive returns with
    one code — starts (R + 1,), codes (R,): the flat cell (≥ 0) of a return the ground counts, −2 for
    one in the grid it leaves out (beyond ``reach2``, no height), −1 outside the grid — and per run
    the lowest and highest z of its counted returns (R, 2)."""
    if not 1 <= rank <= 3:
        raise ValueError("the ground's rank must be 1 to 3 (a cell's lowest returns are kept in three registers)")
    low = np.full((n0, n1, 3), np.inf)  # per cell its 3 lowest returns, ascending
    num = np.zeros((n0, n1), dtype=np.int64)  # returns per cell
    # the same two by the runs' flat cell index (no division per run)
    low_flat, num_flat = low.reshape(n0 * n1, 3), num.ravel()
    if pts.shape[1] != 4:
        raise ValueError("the ground pass reads rows of 4 (x, y, z, anything): see _four_columns")
    m = pts.shape[0]
    flat = pts.ravel()
    start = np.empty(m + 1, dtype=np.int64)
    code = np.empty(m, dtype=np.int64)
    zs = np.empty((m, 2))
    # each return's code and whether it can be a top beam's, in a pass without branches (vectorised)
    codes = np.empty(m, dtype=np.int32)
    sky = np.empty(m, dtype=np.bool_)
    zk = np.empty(m, dtype=pts.dtype)
    _ground_codes(flat, m, ox, oy, oz, x0, y0, cell, inv, n0, n1, reach2, slope_floor * slope_floor, codes, sky, zk)
    top = np.full(nbins, -np.inf)
    highest, cut = -np.inf, -np.inf
    nr = 0
    cur = -3  # the run's code (none yet)
    # the run's own 3 lowest, ascending (l0 its lowest), its highest and its count, in registers: a
    # cell's returns come one after the other along a beam (19 in 20 returns are in the previous one's
    # cell), and a network on the cell's slots in memory waits on its own stores from one return to the next
    l0 = l1 = l2 = np.inf
    zhi = -np.inf
    cnt = 0
    for k in range(m + 1):
        c = -3  # past the last return: ends the last run
        if k < m:
            c = codes[k]
            z = zk[k]
            if sky[k]:
                dx, dy = flat[4 * k] - ox, flat[4 * k + 1] - oy
                s = (z - oz) / math.sqrt(dx * dx + dy * dy)
                if s > highest:
                    highest = s
                    cut = math.tan(math.atan(highest) - spread)
                # a direction's top beam is used no lower than ``spread`` under the frame's highest: below
                # that its value does not matter (spares the atan2 of most returns)
                if s >= cut:
                    b = min(nbins - 1, int((math.atan2(dy, dx) + math.pi) / (2.0 * math.pi) * nbins))
                    if s > top[b]:
                        top[b] = s
        if c != cur:
            if cur >= 0:  # the run's lowest into its cell's (the same values whatever the order they came in)
                num_flat[cur] += cnt
                for v in (l0, l1, l2):
                    for q in range(2, 0, -1):
                        low_flat[cur, q] = max(low_flat[cur, q - 1], min(low_flat[cur, q], v))
                    low_flat[cur, 0] = min(low_flat[cur, 0], v)
            if nr > 0:
                zs[nr - 1, 0], zs[nr - 1, 1] = l0, zhi
            if k == m:
                break
            start[nr], code[nr] = k, c
            nr += 1
            cur = c
            l0 = l1 = l2 = np.inf
            zhi = -np.inf
            cnt = 0
        if c >= 0:
            # z into the run's sorted lowest without a branch on it (about one return in six is among the
            # lowest so far: an unpredictable branch otherwise), each slot clamped as min(slot, max(slot
            # below, z)) — the value max(slot below, min(slot, z)) gives — so that it waits on its own
            # last value through one operation, not two
            l2 = min(l2, max(l1, z))
            l1 = min(l1, max(l0, z))
            l0 = min(l0, z)
            zhi = max(zhi, z)
            cnt += 1
    start[nr] = m
    runs = (start[: nr + 1].copy(), code[:nr].copy(), zs[:nr].copy())
    floor = np.full((n0, n1), np.inf)
    for i in range(n0):
        for j in range(n1):
            f = np.inf
            for q in range(rank):
                if low[i, j, q] < np.inf:
                    f = low[i, j, q]
            floor[i, j] = f
    _deep_floors(pts, runs, num, rank, share, near, floor)
    ground = np.full((n0, n1), np.inf)
    vals = np.empty(9)
    pad = np.full((n0 + 2, n1 + 2), np.inf)  # the floors with a border of inf: a cell's 3 × 3 without bounds tests
    pad[1 : n0 + 1, 1 : n1 + 1] = floor
    for i in range(n0):
        for j in range(n1):
            if floor[i, j] == np.inf:  # no return here: no height is measured from this cell
                continue
            # the 3 × 3 floors (inf outside the grid or where no return fell) sorted by the network of
            # min/max of _SORT9, its pairs in its order, in registers (no branch on the values): the k
            # finite ones first, as an insertion sort has them
            v0, v1, v2 = pad[i, j], pad[i, j + 1], pad[i, j + 2]
            v3, v4, v5 = pad[i + 1, j], pad[i + 1, j + 1], pad[i + 1, j + 2]
            v6, v7, v8 = pad[i + 2, j], pad[i + 2, j + 1], pad[i + 2, j + 2]
            k = 0
            for v in (v0, v1, v2, v3, v4, v5, v6, v7, v8):
                k += v < np.inf
            v0, v3 = min(v0, v3), max(v0, v3)
            v1, v7 = min(v1, v7), max(v1, v7)
            v2, v5 = min(v2, v5), max(v2, v5)
            v4, v8 = min(v4, v8), max(v4, v8)
            v0, v7 = min(v0, v7), max(v0, v7)
            v2, v4 = min(v2, v4), max(v2, v4)
            v3, v8 = min(v3, v8), max(v3, v8)
            v5, v6 = min(v5, v6), max(v5, v6)
            v0, v2 = min(v0, v2), max(v0, v2)
            v1, v3 = min(v1, v3), max(v1, v3)
            v4, v5 = min(v4, v5), max(v4, v5)
            v7, v8 = min(v7, v8), max(v7, v8)
            v1, v4 = min(v1, v4), max(v1, v4)
            v3, v6 = min(v3, v6), max(v3, v6)
            v5, v7 = min(v5, v7), max(v5, v7)
            v0, v1 = min(v0, v1), max(v0, v1)
            v2, v4 = min(v2, v4), max(v2, v4)
            v3, v5 = min(v3, v5), max(v3, v5)
            v6, v8 = min(v6, v8), max(v6, v8)
            v2, v3 = min(v2, v3), max(v2, v3)
            v4, v5 = min(v4, v5), max(v4, v5)
            v6, v7 = min(v6, v7), max(v6, v7)
            v1, v2 = min(v1, v2), max(v1, v2)
            v3, v4 = min(v3, v4), max(v3, v4)
            v5, v6 = min(v5, v6), max(v5, v6)
            vals[0], vals[1], vals[2], vals[3], vals[4] = v0, v1, v2, v3, v4
            vals[5], vals[6], vals[7], vals[8] = v5, v6, v7, v8
            med = vals[k // 2] if k % 2 else 0.5 * (vals[k // 2 - 1] + vals[k // 2])
            m1 = np.inf
            for q in range(k):
                if vals[q] >= med - drop:  # a floor far below its neighbours' is a cell of stray returns under the road
                    m1 = min(m1, vals[q])
            ground[i, j] = m1
    # an opening (the minimum over a square of side 2·reach + 1 cells, then the maximum of that over
    # the same square; cells without returns ignored) keeps every stretch of ground at least that wide
    # — a slope, a raised pavement, the road — and takes away what is narrower: an object whose 3 × 3
    # cells hold only its own returns (in an occluder's shadow, or between a far object's sparse road
    # rings), whose lowest return would otherwise be taken for the road
    lowest = _opening_negated(ground, reach)
    # where the square holds fewer than ``min_cells`` cells with returns (an object in a shadow wider
    # than the square: its own cells are all the square sees), an opening over a square of side
    # 2·wide + 1 cells too, which reaches the road past the shadow's edge
    seen = np.zeros((n0 + 1, n1 + 1))  # cells with returns, summed from the grid's corner
    for i in range(n0):
        for j in range(n1):
            seen[i + 1, j + 1] = seen[i, j + 1] + seen[i + 1, j] - seen[i, j] + (ground[i, j] < np.inf)
    sparse = np.zeros((n0, n1), dtype=np.bool_)
    any_sparse = False
    for i in range(n0):
        for j in range(n1):
            if ground[i, j] < np.inf:
                a0, a1 = max(0, i - reach), min(n0, i + reach + 1)
                b0, b1 = max(0, j - reach), min(n1, j + reach + 1)
                sparse[i, j] = seen[a1, b1] - seen[a0, b1] - seen[a1, b0] + seen[a0, b0] < min_cells
                any_sparse |= sparse[i, j]
    lowest_w = _opening_negated(ground, wide) if wide > reach and any_sparse else lowest
    out = np.full((n0, n1), np.inf)
    for i in range(n0):
        for j in range(n1):
            if ground[i, j] < np.inf:
                out[i, j] = min(ground[i, j], -lowest[i, j], -lowest_w[i, j] if sparse[i, j] else np.inf)
    return out, top, runs


@kernel
def _opening_negated(ground, reach):  # pragma: no cover - compiled
    """Minus the opening of ``ground`` (n0, n1) over squares of side 2·reach + 1 cells: the lowest
    value over the square, then the highest of those over the same square, as minus the lowest of
    their negatives. Only cells with returns of their own show ground (the others are +inf, never
    the lowest); read it only there."""
    eroded = _square_min(ground, reach)
    g, e = ground.ravel(), eroded.ravel()
    for c in range(g.shape[0]):
        e[c] = -e[c] if g[c] < np.inf else np.inf
    return _square_min(eroded, reach)


@kernel
def _deep_floors(xyz, runs, num, rank, share, near, floor):  # pragma: no cover - compiled
    """In place: a cell's floor (n0, n1), its ``rank``-th lowest return, under which fewer than a
    ``share`` of its ``num`` returns lie within ``near`` (m) is a thin layer of stray returns below
    the road: it becomes the cell's m-th lowest return, m = ⌈share · num⌉ (> ``rank``). ``runs``
    (:func:`_ground_grid`): the returns in runs of one cell each. A pass counting the returns near
    each floor, run by run (a run wholly below or above that height is counted at once); only where
    some cell has too few, one more keeping those cells' m lowest in a max-heap each."""
    start, code, zs = runs
    n1 = floor.shape[1]
    flat = num.ravel()
    floors = floor.ravel()
    m = np.zeros(flat.shape[0], dtype=np.int64)  # the rank wanted per cell (0: the floor stands)
    any_dense = False
    for c in range(flat.shape[0]):
        want = int(math.ceil(share * flat[c])) if share > 0.0 else 0
        if want > rank:
            m[c] = want
            any_dense = True
    if not any_dense:
        return
    close = np.zeros(flat.shape[0], dtype=np.int64)  # returns within ``near`` above the floor
    for r in range(code.shape[0]):
        c = code[r]
        if c < 0 or m[c] == 0:
            continue
        lim = floors[c] + near
        if zs[r, 1] <= lim:
            close[c] += start[r + 1] - start[r]
        elif zs[r, 0] <= lim:
            for k in range(start[r], start[r + 1]):
                close[c] += xyz[k, 2] <= lim
    heap_at = np.zeros(flat.shape[0] + 1, dtype=np.int64)  # each thin-layer cell's heap in ``heap``
    for c in range(flat.shape[0]):
        heap_at[c + 1] = heap_at[c] + (m[c] if 0 < m[c] and close[c] < m[c] else 0)
    if heap_at[-1] == 0:
        return
    heap = np.empty(heap_at[-1])
    size = np.zeros(flat.shape[0], dtype=np.int64)
    for r in range(code.shape[0]):
        c = code[r]
        if c < 0 or heap_at[c + 1] == heap_at[c]:
            continue
        a, w = heap_at[c], heap_at[c + 1] - heap_at[c]
        for k in range(start[r], start[r + 1]):
            z = xyz[k, 2]
            n = size[c]
            if n < w:  # not full: z goes in at the bottom and up while above its parent
                q = n
                while q > 0 and heap[a + (q - 1) // 2] < z:
                    heap[a + q] = heap[a + (q - 1) // 2]
                    q = (q - 1) // 2
                heap[a + q] = z
                size[c] = n + 1
            elif z < heap[a]:  # full: z replaces the top and goes down while below a child
                q = 0
                while True:
                    child = 2 * q + 1
                    if child >= w:
                        break
                    if child + 1 < w and heap[a + child + 1] > heap[a + child]:
                        child += 1
                    if heap[a + child] <= z:
                        break
                    heap[a + q] = heap[a + child]
                    q = child
                heap[a + q] = z
    for c in range(flat.shape[0]):
        if heap_at[c + 1] > heap_at[c]:
            floor[c // n1, c % n1] = heap[heap_at[c]]  # the top: the m-th lowest


@kernel
def _runs_min(src, dst, shift, n):  # pragma: no cover - compiled
    """``dst[j] = min(src[j], src[j + shift])`` for j < ``n`` (a loop the compiler vectorises)."""
    a = src[:n]
    b = src[shift : shift + n]
    for j in range(n):
        dst[j] = min(a[j], b[j])


@kernel
def _square_min(a, reach):  # pragma: no cover - compiled
    """(n0, n1): the lowest value of ``a`` within a square of side w = 2·reach + 1 cells around each
    cell (inf where all are inf). The grid padded with ``reach`` cells of inf (the minimum's
    identity) on every side; along its rows, then its columns, the lowest of runs of 1, 2, 4 … cells,
    then of the two runs of the largest such length s ≤ w that together cover w (the minimum is
    exact: the overlap changes nothing) — whole-grid passes of one comparison per cell each, which
    the compiler vectorises, instead of a scan along each line, whose every step waits on the last."""
    n0, n1 = a.shape
    w = 2 * reach + 1
    m0, m1 = n0 + 2 * reach, n1 + 2 * reach
    p = np.full((m0, m1), np.inf)
    p[reach : reach + n0, reach : reach + n1] = a
    src, dst = p.ravel(), np.full(m0 * m1, np.inf)
    # along the rows, on the flat grid: the cells a padded row's first n1 windows use are its own
    for step in (1, m1):
        span = 1
        while 2 * span <= w:
            _runs_min(src, dst, span * step, m0 * m1 - span * step)
            src, dst = dst, src
            span *= 2
        _runs_min(src, dst, (w - span) * step, m0 * m1 - (w - span) * step)
        src, dst = dst, src
    return src.reshape(m0, m1)[:n0, :n1].copy()


@kernel
def _label_mask(boxes, margin, x0, y0, cell, mask, top):  # pragma: no cover - compiled
    """In place, ``mask`` (nx, ny) uint8 (all 0 before): 1 where the cell's centre lies in a label's
    rectangle grown by ``margin``; ``top`` (nx, ny) float64: there, the highest top (z, m) of those
    labels (elsewhere unset: read it only where the mask is 1). Returns the ranges of cells each
    label visited (B, 4: i0, i1, j0, j1, inclusive; empty when i0 > i1), all the mask was written in."""
    nx, ny = mask.shape
    spans = np.empty((boxes.shape[0], 4), dtype=np.int64)
    for b in range(boxes.shape[0]):
        cx, cy = boxes[b, 0], boxes[b, 1]
        hl, hw = 0.5 * boxes[b, 3] + margin, 0.5 * boxes[b, 4] + margin
        c, s = math.cos(boxes[b, 6]), math.sin(boxes[b, 6])
        ex = abs(c) * hl + abs(s) * hw
        ey = abs(s) * hl + abs(c) * hw
        i0 = max(0, int((cx - ex - x0) / cell))
        i1 = min(nx - 1, int((cx + ex - x0) / cell))
        j0 = max(0, int((cy - ey - y0) / cell))
        j1 = min(ny - 1, int((cy + ey - y0) / cell))
        zt = boxes[b, 2] + 0.5 * boxes[b, 5]
        spans[b, 0], spans[b, 1], spans[b, 2], spans[b, 3] = i0, i1, j0, j1
        for i in range(i0, i1 + 1):
            px = x0 + (i + 0.5) * cell - cx
            for j in range(j0, j1 + 1):
                py = y0 + (j + 0.5) * cell - cy
                if abs(c * px + s * py) <= hl and abs(-s * px + c * py) <= hw:
                    top[i, j] = zt if mask[i, j] == 0 else max(top[i, j], zt)
                    mask[i, j] = 1
    return spans


@kernel
def _occupancy(
    xyz, runs, ox, oy, near2, far2, ground, gx0, gy0, gcell, ginv, mask, x0, y0, cell, lo, hi, tall, counts, over
):  # pragma: no cover - compiled
    """The returns in the search band — their indices, cells (flat index) and heights above the
    ground, (B,) each —, counted in place per cell (``counts`` (nx, ny), all 0 before) and the
    returns above the band up to ``tall`` (``over``, all 0 before), the cells holding band returns
    (flat indices, ascending) and the cells holding returns over the band. All around the sensor,
    whatever the labelled region: a wall that leaves the camera's view is still one wall. ``runs``
    (:func:`_ground_grid`): the returns in runs of one ground cell each; a run whose highest return
    lies below the band, or whose lowest lies above ``tall`` (most runs: the road), is passed over
    whole. ``ginv``: 1 / ``gcell`` when that is exact (:func:`_exact_inverse`), else 0."""
    start, code, zs = runs
    m = xyz.shape[0]
    band_idx = np.empty(m, dtype=np.int64)
    band_cell = np.empty(m, dtype=np.int64)
    band_h = np.empty(m)
    occupied = np.empty(m, dtype=np.int64)
    over_cells = np.empty(m, dtype=np.int64)
    nb = 0
    no = 0
    nu = 0
    nx, ny = counts.shape
    flat = ground.ravel()
    for r in range(code.shape[0]):
        c = code[r]
        if c == -1:  # outside the ground grid
            continue
        g = flat[c] if c >= 0 else 0.0
        # z − g rounds monotonically: the run's extremes bound its returns' heights
        if c >= 0 and (zs[r, 1] - g < lo or zs[r, 0] - g > tall):
            continue
        for k in range(start[r], start[r + 1]):
            if c >= 0:
                h = xyz[k, 2] - g
            else:  # a return the ground left out (beyond its reach, or no height): its cell from x, y
                gi = int((xyz[k, 0] - gx0) * ginv if ginv > 0.0 else (xyz[k, 0] - gx0) / gcell)
                gj = int((xyz[k, 1] - gy0) * ginv if ginv > 0.0 else (xyz[k, 1] - gy0) / gcell)
                h = xyz[k, 2] - ground[gi, gj]
            if h < lo or h > tall:
                continue
            i = int((xyz[k, 0] - x0) / cell)
            j = int((xyz[k, 1] - y0) / cell)
            if i < 0 or j < 0 or i >= nx or j >= ny or mask[i, j]:
                continue
            dx, dy = xyz[k, 0] - ox, xyz[k, 1] - oy
            r2 = dx * dx + dy * dy
            if r2 < near2 or r2 > far2:
                continue
            if h <= hi:
                if counts[i, j] == 0:
                    occupied[no] = i * ny + j
                    no += 1
                counts[i, j] += 1
                band_idx[nb] = k
                band_cell[nb] = i * ny + j
                band_h[nb] = h
                nb += 1
            else:
                if over[i, j] == 0:
                    over_cells[nu] = i * ny + j
                    nu += 1
                over[i, j] += 1
    return band_idx[:nb], band_cell[:nb], band_h[:nb], np.sort(occupied[:no]), over_cells[:nu]


@kernel
def _components(counts, over, occupied, comp):  # pragma: no cover - compiled
    """8-connected components of the occupied cells (``occupied``: their flat indices, ascending):
    in place, their component id in ``comp`` (nx, ny) (all −1 before; only the occupied cells are
    written), and per component (points, over-band points, cells, i0, i1, j0, j1)."""
    nx, ny = counts.shape
    m = occupied.shape[0]
    stack = np.empty(m, dtype=np.int64)
    stats = np.zeros((m, 7), dtype=np.int64)
    k = 0
    for s in range(m):
        i = occupied[s] // ny
        j = occupied[s] % ny
        if comp[i, j] >= 0:
            continue
        comp[i, j] = k
        top = 0
        stack[top] = i * ny + j
        top += 1
        stats[k, 3] = i
        stats[k, 4] = i
        stats[k, 5] = j
        stats[k, 6] = j
        while top > 0:
            top -= 1
            a = stack[top] // ny
            b = stack[top] % ny
            stats[k, 0] += counts[a, b]
            stats[k, 1] += over[a, b]
            stats[k, 2] += 1
            stats[k, 3] = min(stats[k, 3], a)
            stats[k, 4] = max(stats[k, 4], a)
            stats[k, 5] = min(stats[k, 5], b)
            stats[k, 6] = max(stats[k, 6], b)
            for da in range(-1, 2):
                for db in range(-1, 2):
                    u, v = a + da, b + db
                    if 0 <= u < nx and 0 <= v < ny and counts[u, v] > 0 and comp[u, v] < 0:
                        comp[u, v] = k
                        stack[top] = u * ny + v
                        top += 1
        k += 1
    return stats[:k]


@kernel
def _comp_extras(xyz, band_idx, band_cell, band_h, comp_flat, k, ox, oy):  # pragma: no cover - compiled
    """Per component (k, 7): highest return above the ground, azimuth interval seen from the sensor
    (radians, unwrapped about the component's first return), nearest and farthest BEV range, sums
    of x and y."""
    out = np.empty((k, 7))
    ref = np.full(k, np.nan)
    for q in range(k):
        out[q, 0] = 0.0
        out[q, 1] = np.inf
        out[q, 2] = -np.inf
        out[q, 3] = np.inf
        out[q, 4] = -np.inf
        out[q, 5] = 0.0
        out[q, 6] = 0.0
    for b in range(band_idx.shape[0]):
        p = band_idx[b]
        q = comp_flat[band_cell[b]]
        dx, dy = xyz[p, 0] - ox, xyz[p, 1] - oy
        az = math.atan2(dy, dx)
        if ref[q] != ref[q]:
            ref[q] = az
        a = az - ref[q]
        if a > math.pi:
            a -= 2.0 * math.pi
        elif a < -math.pi:
            a += 2.0 * math.pi
        a += ref[q]
        r = math.sqrt(dx * dx + dy * dy)
        if band_h[b] > out[q, 0]:
            out[q, 0] = band_h[b]
        out[q, 1] = min(out[q, 1], a)
        out[q, 2] = max(out[q, 2], a)
        out[q, 3] = min(out[q, 3], r)
        out[q, 4] = max(out[q, 4], r)
        out[q, 5] += xyz[p, 0]
        out[q, 6] += xyz[p, 1]
    return out


@kernel
def _merge_fragments(
    stats, extras, min_points, gap, overlap, side_gap, max_extent, cell
):  # pragma: no cover - compiled
    """Group id per component: fragments of one object seen through gaps of returns are joined
    when the joined footprint stays within ``max_extent`` (m; cells of ``cell`` m) and either one lies
    behind the other within ``gap`` metres of range with azimuth intervals overlapping by at least
    ``overlap`` of the narrower (a car's rear face and its cabin, no return on the trunk between),
    or their footprints are within ``side_gap`` cells of each other (a side broken by a dark panel)."""
    k = stats.shape[0]
    parent = np.arange(k)
    lo_i = stats[:, 3].copy()
    hi_i = stats[:, 4].copy()
    lo_j = stats[:, 5].copy()
    hi_j = stats[:, 6].copy()
    big = np.flatnonzero(stats[:, 0] >= min_points)
    for x in range(big.shape[0]):
        a = big[x]
        for y in range(x + 1, big.shape[0]):
            b = big[y]
            ra, rb = _root(parent, a), _root(parent, b)
            if ra == rb:
                continue
            near = _cell_gap(stats, a, b) <= side_gap
            if not near and (extras[b, 3] - extras[a, 4] > gap or extras[a, 3] - extras[b, 4] > gap):
                continue
            d = 0.0
            ca = 0.5 * (extras[a, 1] + extras[a, 2])
            cb = 0.5 * (extras[b, 1] + extras[b, 2])
            d = cb - ca
            if d > math.pi:
                d -= 2.0 * math.pi
            elif d < -math.pi:
                d += 2.0 * math.pi
            wa = extras[a, 2] - extras[a, 1]
            wb = extras[b, 2] - extras[b, 1]
            inter = min(0.5 * wa, d + 0.5 * wb) - max(-0.5 * wa, d - 0.5 * wb)
            if not near and inter < overlap * min(wa, wb):
                continue
            i0, i1 = min(lo_i[ra], lo_i[rb]), max(hi_i[ra], hi_i[rb])
            j0, j1 = min(lo_j[ra], lo_j[rb]), max(hi_j[ra], hi_j[rb])
            if math.hypot((i1 - i0 + 1) * cell, (j1 - j0 + 1) * cell) > max_extent:
                continue
            parent[rb] = ra
            lo_i[ra], hi_i[ra], lo_j[ra], hi_j[ra] = i0, i1, j0, j1
    _flatten_roots(parent)
    return parent


@kernel(inline="always")
def _root(parent, r):  # pragma: no cover - compiled
    """The root of ``r`` in the union-find forest ``parent`` (k,)."""
    while parent[r] != r:
        r = parent[r]
    return r


@kernel(inline="always")
def _flatten_roots(parent):  # pragma: no cover - compiled
    """In place: every entry of ``parent`` (k,) its root (each root its own)."""
    for q in range(parent.shape[0]):
        parent[q] = _root(parent, q)


@kernel(inline="always")
def _cell_gap(stats, a, b):  # pragma: no cover - compiled
    """Cells between the rectangles of components ``a`` and ``b`` (rows of ``stats``: i0, i1, j0, j1
    in columns 3–6): the largest of the four gaps between their sides (≤ 0 when they touch or overlap)."""
    return max(
        stats[a, 3] - stats[b, 4],
        stats[b, 3] - stats[a, 4],
        stats[a, 5] - stats[b, 6],
        stats[b, 5] - stats[a, 6],
    )


@kernel
def _group_stats(group, stats, extras):  # pragma: no cover - compiled
    """Per group of components (``group`` (k,): each component's root id; ``stats`` (k, 7) of
    :func:`_components`, ``extras`` (k, 7) of :func:`_comp_extras`), indexed by the root's id: (4, k)
    sums of the returns, of the returns over the band and of the cells (rows 0, 1, 3; 0 for an id that
    roots no group) and the highest return above the ground (row 2, no lower than 0); (4, k) the
    rectangle of cells (i0, i1, j0, j1; the largest int64 and 0 for an id that roots none); (k,)
    whether the id roots a group. The sums are of integers, exact in float64 whatever their order."""
    k = group.shape[0]
    sums = np.zeros((4, k))
    rect = np.zeros((4, k), dtype=np.int64)
    present = np.zeros(k, dtype=np.bool_)
    big = np.iinfo(np.int64).max
    for q in range(k):
        rect[0, q] = big
        rect[2, q] = big
    for c in range(k):
        r = group[c]
        present[r] = True
        sums[0, r] += np.float64(stats[c, 0])
        sums[1, r] += np.float64(stats[c, 1])
        sums[3, r] += np.float64(stats[c, 2])
        v, t = extras[c, 0], sums[2, r]
        if v > t or v != v:  # NumPy's maximum: a NaN wins
            if t == t:
                sums[2, r] = v
        rect[0, r] = min(rect[0, r], stats[c, 3])
        rect[1, r] = max(rect[1, r], stats[c, 4])
        rect[2, r] = min(rect[2, r], stats[c, 5])
        rect[3, r] = max(rect[3, r], stats[c, 6])
    return sums, rect, present


def _join_rows(
    stats: NDArray[np.int64],
    extras: NDArray[np.float64],
    group: NDArray[np.int64],
    ox: float,
    oy: float,
    cell: float,
    max_extent: float,
) -> NDArray[np.int64]:
    """Join the groups of small fragments that form one straight row seen at a grazing angle.

    A truck's side seen nearly along the sensor's rays shows as one column of returns per azimuth
    step, 0.4–0.6 m apart: a row of fragments of at most ``MISSING_ROW_CELLS`` cells that the
    fragment merge does not join. Fragments within ``MISSING_ROW_GAP`` cells of each other are
    chained; a chain of at least ``MISSING_ROW_MIN`` whose centres lie within
    ``MISSING_ROW_RESIDUAL`` m of one line running within ``MISSING_ROW_ANGLE`` of the ray to it is
    one object (a corner's second leg turns away from the line; a chain with it is not joined).

    Parameters
    ----------
    stats : (k, 7) int64 — per component: returns, returns above the band, cells, i0, i1, j0, j1.
    extras : (k, 7) float64 — per component (``_comp_extras``); columns 5, 6 sum the returns' x, y.
    group : (k,) int64 — the group (root component) of each component after the fragment merge.
    ox, oy : sensor position (m). cell : grid cell (m). max_extent : largest joined footprint diagonal (m).

    Returns
    -------
    (k,) int64 — the groups with the rows joined (roots stay component ids).
    """
    small = np.flatnonzero((stats[:, 2] <= C.MISSING_ROW_CELLS) & (stats[:, 0] >= C.MISSING_FRAGMENT_POINTS))
    if len(small) < C.MISSING_ROW_MIN:
        return group
    parent = _row_chains(stats, small, C.MISSING_ROW_GAP)
    chains = np.flatnonzero(np.bincount(parent) >= C.MISSING_ROW_MIN)  # (shorter chains are no row)
    if len(chains) == 0:
        return group
    cx = extras[small, 5] / stats[small, 0] - ox
    cy = extras[small, 6] / stats[small, 0] - oy
    group = group.copy()
    cos_max = math.cos(math.radians(C.MISSING_ROW_ANGLE))
    for r in chains:
        mem = np.flatnonzero(parent == r)
        roots = np.sort(group[small[mem]])  # the distinct groups, ascending (np.unique would import numpy.ma)
        roots = roots[np.r_[True, roots[1:] != roots[:-1]]]
        if len(roots) < 2:  # (first: the tests below need a line fitted; none has side effects)
            continue
        px, py = cx[mem], cy[mem]
        mx, my = px.mean(), py.mean()
        cov = np.cov(np.stack([px - mx, py - my]))
        _, v = np.linalg.eigh(cov)
        ux, uy = v[0, 1], v[1, 1]  # the line's direction (largest eigenvalue)
        resid = np.abs(-(px - mx) * uy + (py - my) * ux)
        if resid.max() > C.MISSING_ROW_RESIDUAL:
            continue
        if abs(ux * mx + uy * my) < cos_max * math.hypot(mx, my):
            continue
        inside = (group[:, None] == roots[None, :]).any(axis=1)
        i0, i1 = stats[inside, 3].min(), stats[inside, 4].max()
        j0, j1 = stats[inside, 5].min(), stats[inside, 6].max()
        if math.hypot((i1 - i0 + 1) * cell, (j1 - j0 + 1) * cell) > max_extent:
            continue
        group[inside] = roots[0]
    return group


@kernel
def _row_chains(stats, small, max_gap):  # pragma: no cover - compiled
    """The chains of the components ``small`` (their rows of ``stats`` (k, 7): cells i0, i1, j0, j1
    in columns 3–6): two are linked when their rectangles of cells come within ``max_gap`` cells of
    each other (the largest of the four gaps between their sides). Per component of ``small``, its
    chain's id: the least position in ``small`` among the chain's members."""
    n = small.shape[0]
    parent = np.arange(n)
    for a in range(n):
        sa = small[a]
        for b in range(a + 1, n):
            if _cell_gap(stats, sa, small[b]) > max_gap:
                continue
            ra, rb = _root(parent, a), _root(parent, b)
            if ra != rb:
                parent[max(ra, rb)] = min(ra, rb)
    _flatten_roots(parent)
    return parent


@kernel
def _gather(band_cell, comp_flat, wanted, starts):  # pragma: no cover - compiled
    """Positions (into the band arrays) of the returns of the wanted components, component by
    component (a counting sort): component ``c`` (with ``wanted[c]`` = its slot s ≥ 0) owns
    ``out[starts[s]:starts[s + 1]]``."""
    fill = starts[:-1].copy()
    out = np.empty(starts[-1], dtype=np.int64)
    for k in range(band_cell.shape[0]):
        s = wanted[comp_flat[band_cell[k]]]
        if s >= 0:
            out[fill[s]] = k
            fill[s] += 1
    return out


@kernel
def _owners(comp, occupied, label):  # pragma: no cover - compiled
    """In place: the component id of every occupied cell of ``comp`` (nx, ny) (the flat indices
    ``occupied``) replaced by ``label`` of it (per component); the empty cells (−1) stay. Only
    the occupied cells are visited (a few hundred of a grid of 10⁵)."""
    ny = comp.shape[1]
    for s in range(occupied.shape[0]):
        i = occupied[s] // ny
        j = occupied[s] % ny
        comp[i, j] = label[comp[i, j]]
    return comp


@kernel
def _faces(xy, h, lo, hi, steps, width, tie, min_lower):  # pragma: no cover - compiled
    """The heading θ ∈ [0, π/2) whose axes best explain the lower-body returns (heights in
    [lo, hi]; all returns when fewer than ``min_lower``) as vertical faces: the share of them that fall in the
    two densest ``width``-wide slices across either axis (a side, a rear and the cabin's rear behind
    it, an L-shape). Returns (θ, share, a1, b1, a2, b2) with the extents of all returns along
    (cos θ, sin θ) and (−sin θ, cos θ)."""
    m = xy.shape[0]
    sel = np.empty(m, dtype=np.int64)  # the lower-body returns
    n = 0
    for k in range(m):
        if lo <= h[k] <= hi:
            sel[n] = k
            n += 1
    if n < min_lower:
        sel = np.arange(m)
        n = m
    sel = sel[:n]
    shares = np.empty(steps)
    # the selected returns' coordinates along the two axes of a heading
    p = np.empty(n)
    q = np.empty(n)
    slices = np.empty((2, n), dtype=np.int64)
    counts = np.empty((2, 128), dtype=np.int64)
    for s in range(steps):
        t = 0.5 * math.pi * s / steps
        c, sn = math.cos(t), math.sin(t)
        for x in range(n):
            k = sel[x]
            p[x] = c * xy[k, 0] + sn * xy[k, 1]
            q[x] = -sn * xy[k, 0] + c * xy[k, 1]
        shares[s] = _face_share(p, q, width, slices, counts)
    # among the headings that explain the faces nearly as well as the best, the tightest rectangle
    # (a rear face with the roof above it, curved bumper corners: several headings tie on faces);
    # the rectangle of all returns is measured for those headings only
    best = shares.max()
    best_s, best_area = 0, np.inf
    for s in range(steps):
        if shares[s] >= best - tie:
            a1, b1, a2, b2 = _extents(xy, 0.5 * math.pi * s / steps)
            area = (b1 - a1) * (b2 - a2)
            if area < best_area:
                best_s, best_area = s, area
    best_t = 0.5 * math.pi * best_s / steps
    a1, b1, a2, b2 = _extents(xy, best_t)
    return best_t, best, a1, b1, a2, b2


@kernel
def _extents(xy, t):  # pragma: no cover - compiled
    """(a1, b1, a2, b2): the extents of the returns ``xy`` (M, 2) along (cos t, sin t) and
    (−sin t, cos t)."""
    c, sn = math.cos(t), math.sin(t)
    a1, b1, a2, b2 = np.inf, -np.inf, np.inf, -np.inf
    for k in range(xy.shape[0]):
        pk = c * xy[k, 0] + sn * xy[k, 1]
        qk = -sn * xy[k, 0] + c * xy[k, 1]
        a1, b1, a2, b2 = min(a1, pk), max(b1, pk), min(a2, qk), max(b2, qk)
    return a1, b1, a2, b2


@kernel
def _face_share(p, q, width, slices, counts):  # pragma: no cover - compiled
    """Share of the selected returns (their coordinates ``p``, ``q`` (n,) along two square axes) in
    the densest ``width`` slice across either axis (one face square to each axis: a side, a rear, an
    L-shape). ``slices`` (2, n) and ``counts`` (2, 128): scratch."""
    n = p.shape[0]
    nb = counts.shape[1]
    lo1, lo2 = np.inf, np.inf
    for x in range(n):
        lo1 = min(lo1, p[x])
        lo2 = min(lo2, q[x])
    counts[:] = 0
    for x in range(n):
        i = min(nb - 1, int((p[x] - lo1) / width))
        j = min(nb - 1, int((q[x] - lo2) / width))
        slices[0, x] = i
        slices[1, x] = j
        counts[0, i] += 1
        counts[1, j] += 1
    i1 = np.argmax(counts[0])
    j1 = np.argmax(counts[1])
    inside = 0
    for x in range(n):
        if slices[0, x] == i1 or slices[1, x] == j1:
            inside += 1
    return inside / max(n, 1)


@kernel
def _roughness(xyz, ox, oy, oz, gap, step, min_returns):  # pragma: no cover - compiled
    """The median distance (m, bird's-eye) of a cluster's returns ``xyz`` (M, 3) from the line their
    neighbours along the same beam make, or −1 when fewer than ``min_returns`` returns have such
    neighbours. A beam's returns are those within ``gap`` (radians) of each other in elevation seen
    from the sensor (``ox``, ``oy``, ``oz``) — a return lies along its ray whatever its depth, so its
    elevation is its beam's —, in azimuth order; a neighbour more than ``step`` (radians) away in
    azimuth is on another surface. Each return's distance is the least from three lines: through its
    two nearest neighbours, through the two before it, through the two after it (a return at a
    surface's edge, or next to one seen through glass, continues one of its sides). A solid surface
    gives the range noise (a few cm); foliage returns from anywhere in its depth (tens of cm)."""
    m = xyz.shape[0]
    el = np.empty(m)
    az = np.empty(m)
    ref = math.atan2(xyz[0, 1] - oy, xyz[0, 0] - ox) if m > 0 else 0.0
    for k in range(m):
        dx, dy = xyz[k, 0] - ox, xyz[k, 1] - oy
        el[k] = math.atan2(xyz[k, 2] - oz, math.sqrt(dx * dx + dy * dy))
        a = math.atan2(dy, dx) - ref  # about the first return's azimuth: no wrap within a cluster
        if a > math.pi:
            a -= 2.0 * math.pi
        elif a < -math.pi:
            a += 2.0 * math.pi
        az[k] = a
    order = np.argsort(el, kind="mergesort")
    devs = np.empty(m)
    n = 0
    start = 0
    for e in range(1, m + 1):
        if e < m and el[order[e]] - el[order[e - 1]] <= gap:
            continue
        ring = order[start:e]
        start = e
        w = ring.shape[0]
        if w < 3:
            continue
        ring = ring[np.argsort(az[ring], kind="mergesort")]
        for q in range(w):
            best = np.inf
            for lo, hi in ((q - 1, q + 1), (q - 2, q - 1), (q + 1, q + 2)):
                if lo < 0 or hi >= w:
                    continue
                if max(abs(az[ring[lo]] - az[ring[q]]), abs(az[ring[hi]] - az[ring[q]])) > step:
                    continue
                ax, ay = xyz[ring[lo], 0], xyz[ring[lo], 1]
                ex, ey = xyz[ring[hi], 0] - ax, xyz[ring[hi], 1] - ay
                norm = math.sqrt(ex * ex + ey * ey)
                if norm > 0.0:
                    best = min(best, abs(ex * (xyz[ring[q], 1] - ay) - ey * (xyz[ring[q], 0] - ax)) / norm)
            if best < np.inf:
                devs[n] = best
                n += 1
    if n < min_returns:
        return -1.0
    return np.median(devs[:n])


# --------------------------------------------------------------------------- the search


def class_sizes(cfg: RunConfig) -> dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]]:
    """The audited classes the search looks for: name → (mean, largest) (length, width, height), m.

    Only classes with an entry in :data:`~labelaudit.constants.MISSING_CLASS_SIZES` (vehicles) are
    looked for; ``classes = ["all"]`` looks for every class there."""
    table = C.MISSING_CLASS_SIZES
    names = list(table) if ALL_CLASSES in cfg.classes else [c for c in cfg.classes if c in table]
    return {c: (tuple(table[c][0]), tuple(table[c][1])) for c in names}


def _ramp(x: float, lo: float, hi: float) -> float:
    """0 at or below ``lo``, 1 at or above ``hi``, linear between."""
    if hi <= lo:
        return 1.0 if x >= hi else 0.0
    return min(1.0, max(0.0, (x - lo) / (hi - lo)))


def _size_match(
    vis_l: float,
    vis_w: float,
    top: float,
    top_seen: bool,
    ceiling: float,
    mean: tuple[float, float, float],
    largest: tuple[float, float, float],
    gap: float = 0.0,
    min_top: float | None = None,
) -> float:
    """How well visible extents (m) and the seen top (m above ground) fit a class: 1 inside its
    largest size, falling to 0 at ``MISSING_SIZE_SLACK`` beyond. Returns that reach as high as the
    beams go at that range (``top_seen`` false) while the beams there (``ceiling``, m above ground)
    would pass over such a vehicle are no vehicle of the class (a wall, a pole). ``gap``: the height
    between two beams at the cluster's range, by which the highest return may lie under the top.
    ``min_top`` (m): a class whose roof is at least this high (a truck) needs returns that high, or
    as high as the beams reach there (a fence or a low wall as long as a truck is none)."""
    L, W, H = largest
    slack = C.MISSING_SIZE_SLACK
    s = 1.0 - _ramp(vis_l, L, L + slack)
    s *= 1.0 - _ramp(vis_w, W, W + slack)
    s *= 1.0 - _ramp(top, H, H + slack)
    s *= _ramp(top + gap, C.MISSING_MIN_TOP[0], C.MISSING_MIN_TOP[1])  # kerbs, low walls, debris
    s *= _ramp(vis_l, C.MISSING_MIN_EXTENT[0], C.MISSING_MIN_EXTENT[1])  # poles, signs, people
    if min_top is not None:
        need = min(min_top, ceiling - C.MISSING_TOP_CLEARANCE)
        s *= _ramp(top + gap, need - C.MISSING_SIZE_SLACK, need)
    if not top_seen and ceiling > mean[2] + C.MISSING_TALL_MARGIN + C.MISSING_TOP_CLEARANCE:
        s *= C.MISSING_UNSEEN_TOP_FACTOR
    return s


def _rear_view(
    vis_l: float,
    facing: bool,
    top: float,
    fill: float,
    width: float,
    rear_width: float | None,
    min_top: float | None,
) -> bool:
    """Whether a cluster is a class seen from behind or ahead by its face alone: its longer visible
    side (m) as wide as the class (at least ``rear_width``, at most its largest ``width``) and
    ``facing`` the sensor (the line of sight nearer that side's normal than the side itself: a rear
    seen from behind; a wall seen at a grazing angle is a side), its returns reaching the class's
    roof (``top`` ≥ ``min_top``, m above the ground; near the sensor the beams' reach says nothing:
    a car reaches it there) and sending back at least ``MISSING_REAR_FILL`` returns per ray
    (``fill``, :func:`_fill`). A truck's rear is wider than any van's, as high as a truck and one
    solid panel square to the rays; its side is hidden behind it, so it shows no L-shape."""
    return (
        rear_width is not None
        and min_top is not None
        and facing
        and rear_width <= vis_l <= width
        and top >= min_top
        and fill >= C.MISSING_REAR_FILL
    )


def _grow(a: float, b: float, size: float, sensor: float) -> tuple[float, float]:
    """Grow the visible extent [a, b] along one axis to ``size``, away from the sensor (its
    projection ``sensor``): the sides the sensor cannot see are behind the visible ones."""
    if b - a >= size:
        return a, b
    if sensor <= a:
        return a, a + size
    if sensor >= b:
        return b - size, b
    mid = 0.5 * (a + b)
    return mid - 0.5 * size, mid + 0.5 * size


def _place(
    sight: tuple,
    centre: FloatArray,
    c: float,
    s: float,
    ox: float,
    oy: float,
    vis: tuple[float, float, float, float],
    size: tuple[float, float],
    start: tuple[float, float],
    oz: float,
    aim: float,
) -> tuple[float, float]:
    """Where the hidden extent of a partly seen object goes: the low ends (A1, A2) on the axes
    (cos θ, sin θ) and (−sin θ, cos θ) about ``centre`` of the box of ``size`` (L1, L2) (m) that
    holds the visible rectangle ``vis`` (a1, b1, a2, b2) and covers the fewest spots the sensor
    sees empty: a spot is seen when the straight line from the sensor (``ox``, ``oy``, ``oz``) to
    it, at the height ``aim`` (z, m) there, crosses no cell holding band returns nor a label whose
    top is above the line where it crosses (``sight``: counts (nx, ny), label mask (nx, ny), label
    tops (nx, ny), x0, y0, cell) and holds none itself. A car hidden behind another reaches towards
    it, not into the open road beside its visible part; a parked car the line passes over hides
    nothing. Ties keep ``start`` (the growth away from the sensor): an object in full view keeps
    its box."""
    a1, b1, a2, b2 = vis
    spans = [(a1, b1, size[0]), (a2, b2, size[1])]
    if all(b - a >= L - C.MISSING_PLACE_MIN_HIDDEN for a, b, L in spans):  # seen nearly whole
        return start
    counts, mask, top, x0, y0, cell = sight
    step = C.MISSING_PLACE_STEP
    lows = [
        np.linspace(b - L, a, int(math.ceil((L - b + a) / step)) + 1) if b - a < L else np.array([a])
        for a, b, L in spans
    ]
    # spots on a grid over every placement's footprint, outside the visible rectangle
    spot = C.MISSING_PLACE_SPOT
    u = np.arange(lows[0][0] + 0.5 * spot, lows[0][-1] + max(spans[0][2], b1 - a1), spot)
    v = np.arange(lows[1][0] + 0.5 * spot, lows[1][-1] + max(spans[1][2], b2 - a2), spot)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    px = centre[0] + c * uu - s * vv
    py = centre[1] + s * uu + c * vv
    dx, dy = px - ox, py - oy
    r = np.hypot(dx, dy)
    # march each spot's line of sight a cell at a time, from the ego radius to the spot
    n = int(math.ceil(float(r.max()) / cell)) + 1
    f = np.linspace(0.0, 1.0, n)
    seen_empty, empties = _sight_counts(
        dx, dy, r, f, ox, oy, oz, aim, x0, y0, cell, counts, mask, top, C.MISSING_EGO_RADIUS, uu, vv, *vis, *lows, *size
    )
    # the placement with the fewest seen-empty spots, the nearest to the growth away from the sensor
    # among equals; that growth stays unless clearly worse (nothing tells where in an occluder's
    # shadow the object lies, and most objects are seen from their near side)
    dist = np.abs(lows[0] - start[0])[:, None] + np.abs(lows[1] - start[1])[None, :]
    k = np.lexsort((dist.ravel(), empties.ravel()))[0]
    k1, k2 = divmod(int(k), empties.shape[1])
    if empties[k1, k2] + C.MISSING_PLACE_MARGIN > _empty_at(seen_empty, uu, vv, start, spans):
        return start
    return float(lows[0][k1]), float(lows[1][k2])


@kernel
def _sight_counts(
    dx,
    dy,
    r,
    f,
    ox,
    oy,
    oz,
    aim,
    x0,
    y0,
    cell,
    counts,
    mask,
    top,
    ego,
    uu,
    vv,
    a1,
    b1,
    a2,
    b2,
    lows1,
    lows2,
    size1,
    size2,
):  # pragma: no cover - compiled
    """:func:`_place`'s spots seen empty and its placements' counts of them. A spot (``uu``, ``vv``
    (U, V) in the cluster's frame; ``dx``, ``dy``, ``r`` (U, V) from the sensor at ``ox``, ``oy``,
    ``oz``; the line aimed at the height ``aim``) is seen empty when no step ``f`` (K,) of its line
    of sight at least ``ego`` m from the sensor lies in a cell (``cell`` m from ``x0``, ``y0``)
    holding band returns (``counts``) or a label (``mask``) whose top (``top``) is above the line
    there, and it lies outside the visible rectangle [a1, b1] × [a2, b2]. Returns that (U, V) and,
    per placement (low ends ``lows1`` × ``lows2``, extents ``size1`` × ``size2``), the seen-empty
    spots it covers."""
    nu, nv = dx.shape
    nx, ny = counts.shape
    seen = np.zeros((nu, nv), dtype=np.bool_)
    for a in range(nu):
        for b in range(nv):
            empty = True
            for k in range(f.shape[0]):  # a cell at a time, from the sensor to the spot
                if not f[k] * r[a, b] >= ego:
                    continue
                i = int((ox + dx[a, b] * f[k] - x0) / cell)
                j = int((oy + dy[a, b] * f[k] - y0) / cell)
                if (
                    0 <= i < nx
                    and 0 <= j < ny
                    and (counts[i, j] > 0 or (mask[i, j] != 0 and top[i, j] > oz + (aim - oz) * f[k]))
                ):
                    empty = False
                    break
            seen[a, b] = empty and not (a1 <= uu[a, b] <= b1 and a2 <= vv[a, b] <= b2)
    empties = np.zeros((lows1.shape[0], lows2.shape[0]), dtype=np.int64)
    for p in range(lows1.shape[0]):
        hi1 = lows1[p] + size1
        for q in range(lows2.shape[0]):
            hi2 = lows2[q] + size2
            n = 0
            for a in range(nu):
                for b in range(nv):
                    if seen[a, b] and lows1[p] <= uu[a, b] <= hi1 and lows2[q] <= vv[a, b] <= hi2:
                        n += 1
            empties[p, q] = n
    return seen, empties


def _empty_at(seen_empty: NDArray, uu: NDArray, vv: NDArray, low: tuple[float, float], spans: list) -> int:
    inb = (uu >= low[0]) & (uu <= low[0] + spans[0][2]) & (vv >= low[1]) & (vv <= low[1] + spans[1][2])
    return int(np.count_nonzero(seen_empty & inb))


def _fill(
    n: int,
    corners: FloatArray,
    ox: float,
    oy: float,
    z_lo: float,
    z_hi: float,
    rays_per_rad2: float,
    elevations: tuple[float, float] = (-math.pi / 2, math.pi / 2),
) -> float:
    """Returns per ray that the visible rectangle (``corners`` (4, 2)) between the heights
    ``z_lo`` and ``z_hi`` (relative to the sensor) sends back: about 1 for a solid surface, less for
    a porous one (vegetation, fences) or a loose fragment: the points against what the range allows.
    The rays are counted over the rectangle's sides that face the sensor, each direction at its own
    range (beside the sensor a car's near end subtends several times the angle of its far end),
    outside the ego zone (whose returns are not searched) and within the sensor's beams
    (``elevations``, radians: its lowest and highest): there a car's lower body lies under the
    lowest beam, which sends no ray to it."""
    rel = corners - np.array([ox, oy])
    # the sides facing the sensor (the outward normal of a counter-clockwise side points away from
    # the rectangle's inside; the sensor lies on its outer side)
    if (rel[1, 0] - rel[0, 0]) * (rel[2, 1] - rel[0, 1]) - (rel[1, 1] - rel[0, 1]) * (rel[2, 0] - rel[0, 0]) < 0:
        rel = rel[::-1]
    t = np.linspace(0.0, 1.0, C.MISSING_FILL_SAMPLES)[:, None]
    pts = []
    for k in range(4):
        e = rel[(k + 1) % 4] - rel[k]
        if e[0] * rel[k, 1] - e[1] * rel[k, 0] > 0:  # the sensor (the origin) lies right of the side: outside
            pts.append(rel[k] + t * e)
    if not pts:
        return 0.0
    xy = np.vstack(pts)
    az = np.arctan2(xy[:, 1], xy[:, 0])
    az = (az - az[0] + np.pi) % (2 * np.pi) - np.pi
    d = np.hypot(xy[:, 0], xy[:, 1])
    el = np.minimum(np.arctan2(z_hi, d), elevations[1]) - np.maximum(np.arctan2(z_lo, d), elevations[0])
    el[d < C.MISSING_EGO_RADIUS] = 0.0  # no return there is searched (the ego zone)
    order = np.argsort(az, kind="stable")
    az, el = az[order], np.maximum(el[order], 0.0)
    solid = float(np.sum(0.5 * (el[1:] + el[:-1]) * np.diff(az)))
    return n / max(solid * rays_per_rad2, 1.0)


def _exact_inverse(cell: float) -> float:
    """1 / ``cell`` when multiplying by it gives what dividing by ``cell`` gives, bit for bit (a
    power of two: both are the correctly rounded x·2⁻ᵏ), else 0 (the kernels divide)."""
    return 1.0 / cell if math.frexp(cell)[0] == 0.5 else 0.0


def _four_columns(points: NDArray) -> NDArray:
    """The points as C-contiguous rows of 4 (x, y, z, then anything): the frame's own array when it
    is so (KITTI's x, y, z, intensity: no copy), else a copy of x, y, z (its dtype kept, so every
    value is the same); the ground pass reads them with a constant stride."""
    if points.shape[1] == 4 and points.flags.c_contiguous:
        return points
    out = np.zeros((len(points), 4), dtype=points.dtype)
    out[:, :3] = points[:, :3]
    return out


class _Grids:
    """The search's 0.2 m grids of one thread (label mask and tops, band and over-band counts,
    component ids), kept from frame to frame: allocating and zeroing them (a few MB) cost more than
    the search's use of them, which writes a few thousand cells. Each use records the cells it
    wrote (``spans``, ``cells``) and :meth:`give_back` puts back those alone; grids a failed search
    did not give back are dropped, never reused."""

    _local = threading.local()

    def __init__(self, nx: int, ny: int):
        self.mask = np.zeros((nx, ny), dtype=np.uint8)
        self.top = np.empty((nx, ny))
        self.counts = np.zeros((nx, ny), dtype=np.int32)
        self.over = np.zeros((nx, ny), dtype=np.int32)
        self.comp = np.full((nx, ny), -1, dtype=np.int32)
        self.spans: NDArray | None = None  # the label mask's cells written (B, 4: i0, i1, j0, j1)
        self.cells: tuple[NDArray, NDArray] | None = None  # band cells and over-band cells written (flat)

    @classmethod
    def take(cls, nx: int, ny: int) -> _Grids:
        """This thread's grids of (nx, ny) cells, clean, now in use (until given back)."""
        grids = getattr(cls._local, "grids", None)
        if grids is None or grids.mask.shape != (nx, ny):
            grids = cls(nx, ny)
        cls._local.grids = None
        return grids

    def give_back(self) -> None:
        """Put back the recorded cells (mask 0, counts 0, component −1) and keep the grids."""
        none = np.zeros(0, dtype=np.int64)
        spans = np.zeros((0, 4), dtype=np.int64) if self.spans is None else self.spans
        band, over = (none, none) if self.cells is None else self.cells
        _clear_grids(self.mask, self.counts, self.comp, self.over, spans, band, over)
        self.spans = self.cells = None
        type(self)._local.grids = self


@kernel
def _clear_grids(mask, counts, comp, over, spans, band, over_cells):  # pragma: no cover - compiled
    """In place: the label mask 0 over the cell ranges ``spans`` (B, 4: i0, i1, j0, j1, inclusive;
    empty when i0 > i1), the counts 0 and the component ids −1 at the flat cells ``band``, the
    over-band counts 0 at the flat cells ``over_cells``."""
    for b in range(spans.shape[0]):
        for i in range(spans[b, 0], spans[b, 1] + 1):
            for j in range(spans[b, 2], spans[b, 3] + 1):
                mask[i, j] = 0
    ny = counts.shape[1]
    for c in band:
        counts[c // ny, c % ny] = 0
        comp[c // ny, c % ny] = -1
    for c in over_cells:
        over[c // ny, c % ny] = 0


def search_clusters(frame: Frame, cfg: RunConfig, trace: SearchTrace | None = None) -> list[Cluster]:
    """The point-cloud search of one frame: clusters no label explains, boxed and scored.

    Returns every cluster of a plausible size (scores may be low); the caller keeps those in the
    labelled region. Deterministic: the same frame gives the same clusters. ``trace`` (optional)
    receives every group of components and what became of it (:class:`SearchTrace`).
    """
    sizes = class_sizes(cfg)
    pts = frame.points
    if not sizes or len(pts) == 0:
        return []
    params = cfg.missing
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    ox, oy, oz = float(o[0]), float(o[1]), float(o[2])
    reach = params.max_range + C.MISSING_GROUND_CELL * 2
    cell = C.MISSING_CELL
    x0, y0 = ox - reach, oy - reach
    x1, y1 = ox + reach, oy + reach
    view = frame.image_view
    if (
        view is not None
    ):  # a camera looking along +x (KITTI): the grids need not reach behind it (but walls run on past its edge)
        d = np.asarray(view.projection, dtype=float)[2, :3]
        if d[0] > C.MISSING_FORWARD_COS * float(np.linalg.norm(d)):
            x0 = ox - C.MISSING_CONTINUATION - C.MISSING_EGO_RADIUS
    gcell = C.MISSING_GROUND_CELL
    opening = int(round(0.5 * (C.MISSING_GROUND_OPENING / gcell - 1)))
    # the ground cells the search grid needs, and the opening's reach around them (cells anchored at ox − reach)
    skip = max(0, math.floor((x0 - (opening + 2) * gcell - (ox - reach)) / gcell))
    gx0, gy0 = ox - reach + skip * gcell, oy - reach
    ground, top_slope, runs = _ground_grid(
        _four_columns(pts),
        ox,
        oy,
        oz,
        gx0,
        gy0,
        gcell,
        _exact_inverse(gcell),
        int(math.ceil((x1 - gx0) / gcell)),
        int(math.ceil((y1 - gy0) / gcell)),
        reach * reach,
        C.MISSING_GROUND_RANK,
        C.MISSING_GROUND_SHARE,
        C.MISSING_CEILING_BINS,
        C.MISSING_GROUND_DROP,
        math.tan(math.radians(C.MISSING_CEILING_FLOOR)),
        opening,
        math.radians(C.MISSING_CEILING_SPREAD),
        int(round(0.5 * (C.MISSING_GROUND_OPENING_WIDE / gcell - 1))),
        C.MISSING_GROUND_MIN_CELLS * (2 * opening + 1) ** 2,
        C.MISSING_BAND[0],
    )
    nx, ny = int(math.ceil((x1 - x0) / cell)), int(math.ceil((y1 - y0) / cell))
    grids = _Grids.take(nx, ny)
    out = _boxed_clusters(frame, cfg, trace, grids, ground, runs, top_slope, (x0, y0, gx0, gy0))
    grids.give_back()  # (a search that fails does not: its grids are dropped)
    return out


def _boxed_clusters(
    frame: Frame,
    cfg: RunConfig,
    trace: SearchTrace | None,
    grids: _Grids,
    ground: FloatArray,
    runs: tuple,
    top_slope: FloatArray,
    corners: tuple[float, float, float, float],
) -> list[Cluster]:
    """The rest of :func:`search_clusters`, on the frame's ground (``ground``, ``runs``,
    ``top_slope`` of :func:`_ground_grid`; ``corners``: the search grid's and the ground grid's
    x0, y0) and in ``grids`` (clean; every cell written is recorded in them)."""
    sizes = class_sizes(cfg)
    params = cfg.missing
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    ox, oy, oz = float(o[0]), float(o[1]), float(o[2])
    xyz = frame.points[:, :3]
    x0, y0, gx0, gy0 = corners
    cell, gcell = C.MISSING_CELL, C.MISSING_GROUND_CELL
    mask, label_top, counts, over, comp = grids.mask, grids.top, grids.counts, grids.over, grids.comp
    labels = np.ascontiguousarray(frame.boxes[np.all(np.isfinite(frame.boxes), axis=1)], dtype=float).reshape(-1, 7)
    grids.spans = _label_mask(labels, C.MISSING_LABEL_MARGIN, x0, y0, cell, mask, label_top)
    lo, hi = C.MISSING_BAND
    band_idx, band_cell, band_h, occupied, over_cells = _occupancy(
        xyz,
        runs,
        ox,
        oy,
        C.MISSING_EGO_RADIUS**2,
        (params.max_range + C.MISSING_CONTINUATION) ** 2,
        ground,
        gx0,
        gy0,
        gcell,
        _exact_inverse(gcell),
        mask,
        x0,
        y0,
        cell,
        lo,
        hi,
        C.MISSING_TALL,
        counts,
        over,
    )
    grids.cells = (occupied, over_cells)
    stats = _components(counts, over, occupied, comp)
    if len(stats) == 0:
        return []
    extras = _comp_extras(xyz, band_idx, band_cell, band_h, comp.ravel(), len(stats), ox, oy)
    largest = max(v[1][0] for v in sizes.values())
    max_diag = math.hypot(largest, 3.0) + C.MISSING_SIZE_SLACK
    group = _merge_fragments(
        stats,
        extras,
        C.MISSING_FRAGMENT_POINTS,
        C.MISSING_MERGE_GAP,
        C.MISSING_MERGE_OVERLAP,
        C.MISSING_MERGE_SIDE_CELLS,
        max_diag,
        cell,
    )
    group = _join_rows(stats, extras, group, ox, oy, cell, max_diag)
    k = len(stats)
    # per group (by its root's id): returns, returns over the band, highest return, cells, rectangle of cells
    sums, rect_all, present = _group_stats(group, stats, extras)
    roots = np.flatnonzero(present)
    g_points, g_over, g_top = sums[0, roots], sums[1, roots], sums[2, roots]
    i0, i1, j0, j1 = rect_all
    diag = np.hypot((i1[roots] - i0[roots] + 1) * cell, (j1[roots] - j0[roots] + 1) * cell)
    keep = (g_points >= params.min_points) & (diag <= max_diag) & (diag >= C.MISSING_MIN_EXTENT[0])
    keep &= g_over <= C.MISSING_MAX_OVER_SHARE * g_points  # walls, poles, trunks: they go on above the band
    keep &= g_top >= C.MISSING_MIN_TOP[0]  # kerbs, low walls, debris
    if keep.any():  # only where labels exist (the exact test is on the boxes; this spares boxing the rest)
        # a group is kept when one of its fragments lies there: a car at the camera's edge merged with
        # the hedge beside it has its centroid outside the view, its own returns inside (it is split later)
        member = keep[np.searchsorted(roots, group)] & (stats[:, 0] >= C.MISSING_FRAGMENT_POINTS)
        probe = np.zeros((int(member.sum()), 7))
        probe[:, 0] = extras[member, 5] / stats[member, 0]
        probe[:, 1] = extras[member, 6] / stats[member, 0]
        probe[:, 3:6] = 1.0
        inside = in_labelled_region(
            probe,
            frame,
            params.max_range + C.MISSING_REGION_SLACK,
            dontcare=False,
            slack_px=C.MISSING_IMAGE_SLACK,
            slack_m=C.MISSING_REGION_SLACK,
        )
        hit = np.zeros(len(roots), dtype=bool)
        hit[np.searchsorted(roots, group[member])[inside]] = True
        keep &= hit
    if trace is not None:
        traced, slots = len(trace.groups), np.flatnonzero(keep)
        rect = np.stack([i0[roots], j0[roots], i1[roots] + 1, j1[roots] + 1], axis=1) * cell + [x0, y0, x0, y0]
        _trace_groups(trace, rect, g_points, g_over, g_top, diag, max_diag, params.min_points, keep)
    chosen_roots = roots[keep]
    if len(chosen_roots) == 0:
        return []
    slot_of_root = np.full(k, -1, dtype=np.int64)
    slot_of_root[chosen_roots] = np.arange(len(chosen_roots))
    wanted = slot_of_root[group]  # component → slot of its group (−1: not searched)
    starts = np.concatenate([[0], np.cumsum(g_points[keep])]).astype(np.int64)
    chosen = chosen_roots
    order = _gather(band_cell, comp.ravel(), wanted, starts)
    # rays per steradian of the sensor, from the frame: its returns over the band of elevations it covers
    rays_per_rad2, elevations = _rays_per_rad2(xyz, ox, oy, oz)
    out = []
    solid = (
        sums[0, group] >= C.MISSING_FRAGMENT_POINTS
    )  # components of groups with a few returns at least (not stray ones)
    # the group of every occupied cell (−1: none), in place of its component (comp is not needed after)
    owner = _owners(comp, occupied, np.where(solid, group, -1).astype(np.int32))
    # + each group's cells and its rectangle of cells (indexed by group)
    grid = (owner, x0, y0, cell, sums[3], rect_all)
    sight = (counts, mask, label_top, x0, y0, cell)

    def returns(g: int) -> FloatArray | None:
        slot = int(slot_of_root[g])
        return None if slot < 0 else xyz[band_idx[order[starts[slot] : starts[slot + 1]]]].astype(float)

    scene = _Scene(sizes, ox, oy, oz, top_slope, rays_per_rad2, elevations, grid, sight, returns, {})
    for s in range(len(chosen)):
        pos = order[starts[s] : starts[s + 1]]
        first = len(out)
        out += _box_cluster(xyz[band_idx[pos]].astype(float), band_h[pos], scene, int(chosen[s]), C.MISSING_SPLITS)
        if trace is not None:
            trace.groups[traced + int(slots[s])]["clusters"] = list(range(first, len(out)))
    return out


def _trace_groups(
    trace: SearchTrace,
    rect: FloatArray,
    points: FloatArray,
    over: FloatArray,
    top: FloatArray,
    diag: FloatArray,
    max_diag: float,
    min_points: int,
    boxed: NDArray,
) -> None:
    """Record every group (BEV rectangles ``rect`` (G, 4), per-group statistics (G,)) with the
    first rule of :func:`search_clusters` that left it unboxed, in the order the rules apply."""
    for k in range(len(rect)):
        if boxed[k]:
            fate = "boxed"
        elif points[k] < min_points:
            fate = "points"
        elif not C.MISSING_MIN_EXTENT[0] <= diag[k] <= max_diag:
            fate = "footprint"
        elif over[k] > C.MISSING_MAX_OVER_SHARE * points[k]:
            fate = "tall"
        elif top[k] < C.MISSING_MIN_TOP[0]:
            fate = "low"
        else:
            fate = "region"
        x0, y0, x1, y1 = (float(v) for v in rect[k])
        trace.groups.append(
            {"x0": x0, "y0": y0, "x1": x1, "y1": y1, "points": int(points[k]), "fate": fate, "clusters": []}
        )


def _rays_per_rad2(xyz: NDArray, ox: float, oy: float, oz: float) -> tuple[float, tuple[float, float]]:
    """The sensor's returns per steradian and the elevations its beams cover (radians, lowest and
    highest; the 1 % and 99 % quantiles of a sample of the frame's returns)."""
    sub = np.asarray(xyz[:: max(1, len(xyz) // C.MISSING_RATE_SAMPLE)], dtype=float)
    r = np.hypot(sub[:, 0] - ox, sub[:, 1] - oy)
    el = np.arctan2(sub[:, 2] - oz, np.maximum(r, 1e-6))
    lo, hi = _quantiles(el, (0.01, 0.99))
    return len(xyz) / max(2 * np.pi * float(hi - lo), 1e-6), (float(lo), float(hi))


def _median(values: FloatArray) -> float:
    """``np.median(values)`` (``values`` (n ≥ 1,) float64), the same value bit for bit, computed as
    NumPy computes it: one partition at the same positions, then the mean of the middle value or
    of the two middle ones, summed from +0.0; NaN when a value is NaN. Without ``np.median``'s NaN check, whose
    first call imports ``numpy.ma`` (see :func:`_quantiles`)."""
    n = len(values)
    kth = [n // 2 - 1, n // 2] if n % 2 == 0 else [(n - 1) // 2]
    part = np.partition(values, [*kth, -1])
    if np.isnan(part[-1]):
        return math.nan
    if n % 2:  # (NumPy's mean adds from +0.0: a lone −0.0 comes out +0.0)
        return float((0.0 + part[n // 2]) / 1)
    return float((0.0 + part[n // 2 - 1] + part[n // 2]) / 2)


def _quantiles(values: FloatArray, qs: tuple[float, ...]) -> list[float]:
    """``np.quantile(values, qs)`` (its default, linear method; ``values`` (n ≥ 1,) float64), the
    same values bit for bit, computed as NumPy computes them: the order statistics around each
    virtual index (n − 1)·q from one partition with the same positions, then NumPy's interpolation
    (``a + (b − a)·γ``, or ``b − (b − a)·(1 − γ)`` for γ ≥ 0.5); NaN when a value is NaN. Without
    ``np.quantile``'s ``np.unique``, whose first call imports ``numpy.ma`` (~13 ms, in the fork
    server's start-up before any worker forks)."""
    n = len(values)
    virtual = [(n - 1) * q for q in qs]
    prev = [-1 if v >= n - 1 else int(math.floor(v)) for v in virtual]
    nxt = [-1 if v >= n - 1 else int(math.floor(v)) + 1 for v in virtual]
    part = np.partition(values, sorted({0, -1, *prev, *nxt}))
    if np.isnan(part[-1]):
        return [math.nan] * len(qs)
    out = []
    for v, i, j in zip(virtual, prev, nxt):
        a, b = part[i], part[j]
        t = v - i
        d = b - a
        out.append(float(b - d * (1 - t)) if t >= 0.5 else float(a + d * t))
    return out


def _continues(
    grid: tuple,
    own: int,
    centre: FloatArray,
    c: float,
    s: float,
    a1: float,
    b1: float,
    a2: float,
    b2: float,
    along1: bool,
    po: float,
    qo: float,
    body: tuple[float, float, float, float] | None = None,
    fragment: int | None = None,
    extra: float = 0.0,
    whole: tuple[float, float, float, float] | None = None,
    skip: NDArray | None = None,
) -> bool:
    """Whether the cluster's longer face (the side facing the sensor, at ``po``, ``qo`` in the
    cluster's frame) goes on beyond it through returns of other clusters no label explains: a
    stretch of a wall or a hedge, not an object of its own. ``grid``: (owner (nx, ny), x0, y0,
    cell, cells per group). A group of at most ``fragment`` cells (default
    ``MISSING_OWN_FRAGMENT_CELLS``) inside ``body`` (A1, B1, A2, B2: the box the cluster would
    become, in its frame) is the object's own far end or roof edge seen past a gap, not a structure
    going on (:func:`_continues_kernel`), and so is a group of any size whose every cell touches
    ``whole`` (the box the cluster would become, in its frame): its far end or far side seen past a
    gap or an occluder's shadow, while a wall's pieces run on beyond it. The
    line is followed ``MISSING_CONTINUATION`` + ``extra`` (m) past the face's ends (past a ``body``
    reaching farther than the face). Groups in ``skip`` (ids) are no structure either."""
    fragment = C.MISSING_OWN_FRAGMENT_CELLS if fragment is None else fragment
    owner, x0, y0, cell, group_cells, group_rect = grid
    A1, B1, A2, B2 = body if body is not None else (np.inf, -np.inf, np.inf, -np.inf)
    W1, V1, W2, V2 = whole if whole is not None else (np.inf, -np.inf, np.inf, -np.inf)
    known = np.full(group_rect.shape[1], -1, dtype=np.int8)
    if skip is not None:
        known[skip] = 1
    step = 0.5 * cell
    half = C.MISSING_MERGE_SIDE_CELLS * cell
    return bool(
        _continues_kernel(
            owner,
            x0,
            y0,
            cell,
            own,
            float(centre[0]),
            float(centre[1]),
            c,
            s,
            a1,
            b1,
            a2,
            b2,
            bool(along1),
            po,
            qo,
            np.arange(step, C.MISSING_CONTINUATION + extra + step, step),
            np.linspace(-half, half, 5),
            np.asarray(group_cells, dtype=float),
            group_rect,
            known,
            float(A1),
            float(B1),
            float(A2),
            float(B2),
            float(W1),
            float(V1),
            float(W2),
            float(V2),
            fragment,
            C.MISSING_CONTINUATION_CELLS,
            C.MISSING_CONTINUATION_RUN,
            C.MISSING_CORNER_START,
            C.MISSING_CORNER_DEPTH,
        )
    )


@kernel
def _other_group(o, own, group_cells, fragment, p, q, A1, B1, A2, B2, inside):  # pragma: no cover - compiled
    """Whether the owner ``o`` of a cell is another group than ``own``, less the object's own
    fragments: a group of at most ``fragment`` cells (``group_cells`` per group) with the spot
    (``p``, ``q``) inside the box [A1, B1] × [A2, B2] (the cluster's frame), or a group whose
    every cell lies inside the vehicle (``inside[o]`` = 1, :func:`_inside_whole`)."""
    if o < 0 or o == own:
        return False
    if o < inside.shape[0] and inside[o] == 1:
        return False
    small = o < group_cells.shape[0] and group_cells[o] <= fragment
    return not (small and p >= A1 and p <= B1 and q >= A2 and q <= B2)


@kernel
def _inside_whole(owner, x0, y0, cell, o, rect, cx, cy, c, s, W1, V1, W2, V2):  # pragma: no cover - compiled
    """Whether every cell of group ``o`` (its rectangle of cells ``rect[:, o]``: i0, i1, j0, j1)
    touches the box [W1, V1] × [W2, V2] of the frame about (``cx``, ``cy``) with axes (c, s) and
    (−s, c): its centre within half a cell's diagonal of it (a group on the line of the box's side
    straddles it)."""
    tol = 0.5 * cell * math.sqrt(2.0)
    W1, V1, W2, V2 = W1 - tol, V1 + tol, W2 - tol, V2 + tol
    for i in range(rect[0, o], rect[1, o] + 1):
        for j in range(rect[2, o], rect[3, o] + 1):
            if owner[i, j] != o:
                continue
            dx = x0 + (i + 0.5) * cell - cx
            dy = y0 + (j + 0.5) * cell - cy
            p = c * dx + s * dy
            q = -s * dx + c * dy
            if p < W1 or p > V1 or q < W2 or q > V2:
                return False
    return True


@kernel
def _continues_kernel(
    owner,
    x0,
    y0,
    cell,
    own,
    cx,
    cy,
    c,
    s,
    a1,
    b1,
    a2,
    b2,
    along1,
    po,
    qo,
    ts,
    across,
    group_cells,
    group_rect,
    known,
    A1,
    B1,
    A2,
    B2,
    W1,
    V1,
    W2,
    V2,
    fragment,
    min_cells,
    min_run,
    start,
    deep,
):  # pragma: no cover - compiled
    """:func:`_continues` on the owner grid ``owner`` (nx, ny) (group per cell, −1 none; cells of
    ``cell`` m from ``x0``, ``y0``), for the cluster ``own`` about (``cx``, ``cy``) with axes (c, s)
    and (−s, c) and extents [a1, b1] × [a2, b2]; ``ts`` (T,): the steps beyond the face's ends,
    ``across`` (5,): the offsets across a corner's line; ``group_cells``, ``fragment``, A1…B2, the
    groups wholly inside W1…V2 (``group_rect`` (4, G): each group's rectangle of cells) and those
    ``known`` (G,) to be none (1): what :func:`_other_group` leaves out."""
    nx, ny = owner.shape
    nt = ts.shape[0]
    # per group: 1 when not another structure (known, or wholly inside W1…V2), 0 when it is, −1 not
    # yet looked at
    inside = known.copy()
    if W1 > V1:
        inside[inside < 0] = 0
    if along1:  # the face runs along axis 1, on the side of axis 2 nearer the sensor
        face = a2 if qo < 0.5 * (a2 + b2) else b2
    else:
        face = a1 if po < 0.5 * (a1 + b1) else b1
    seen = np.empty(9 * nt, dtype=np.int64)
    for end in range(2):
        n = 0
        lo, hi = np.inf, -np.inf  # the steps along the line with returns of another cluster beside them
        for t in range(nt):
            if along1:
                p = b1 + ts[t] if end == 0 else a1 - ts[t]
                q = face
            else:
                p = face
                q = b2 + ts[t] if end == 0 else a2 - ts[t]
            x = cx + c * p - s * q
            y = cy + s * p + c * q
            i = int((x - x0) / cell)
            j = int((y - y0) / cell)
            if i < 0 or i >= nx or j < 0 or j >= ny:
                continue
            for di in range(-1, 2):
                for dj in range(-1, 2):
                    ii = min(max(i + di, 0), nx - 1)
                    jj = min(max(j + dj, 0), ny - 1)
                    o = owner[ii, jj]
                    if 0 <= o < inside.shape[0] and o != own and inside[o] < 0:
                        inside[o] = (
                            1 if _inside_whole(owner, x0, y0, cell, o, group_rect, cx, cy, c, s, W1, V1, W2, V2) else 0
                        )
                    if _other_group(o, own, group_cells, fragment, p, q, A1, B1, A2, B2, inside):
                        lo, hi = min(lo, ts[t]), max(hi, ts[t])
                        seen[n] = ii * ny + jj
                        n += 1
        # the returns must run along the line (a wall going on), not cross it (a wall behind, square to the face)
        if n > 0 and hi - lo >= min_run:
            cells = np.sort(seen[:n])
            distinct = 1
            for k in range(1, n):
                distinct += cells[k] != cells[k - 1]
            if distinct >= min_cells:
                return True
    # a corner: at an end of the face, other returns run away from the sensor, square to the face
    # (the end wall of a building whose front the cluster is), deeper than a vehicle is wide
    if along1:
        away = 1.0 if face == a2 else -1.0
    else:
        away = 1.0 if face == a1 else -1.0
    for e in (a1, b1) if along1 else (a2, b2):
        lo, hi = np.inf, -np.inf
        for u in range(across.shape[0]):
            for t in range(nt):
                if along1:
                    p = e + across[u] + 0.0 * ts[t]
                    q = face + away * ts[t] + 0.0 * across[u]
                else:
                    p = face + away * ts[t] + 0.0 * across[u]
                    q = e + across[u] + 0.0 * ts[t]
                x = cx + c * p - s * q
                y = cy + s * p + c * q
                i = min(max(int((x - x0) / cell), 0), nx - 1)
                j = min(max(int((y - y0) / cell), 0), ny - 1)
                o = owner[i, j]
                if 0 <= o < inside.shape[0] and o != own and inside[o] < 0:
                    inside[o] = (
                        1 if _inside_whole(owner, x0, y0, cell, o, group_rect, cx, cy, c, s, W1, V1, W2, V2) else 0
                    )
                if _other_group(o, own, group_cells, fragment, p, q, A1, B1, A2, B2, inside):
                    lo, hi = min(lo, ts[t]), max(hi, ts[t])
        # from the face's end on (a building's end wall meets its front; a hedge behind a car begins
        # only beyond the car's width)
        if lo <= start and hi - lo >= deep:
            return True
    return False


class _Scene(NamedTuple):
    """What every cluster of one frame is boxed against (:func:`_box_cluster`)."""

    sizes: dict  # class → (mean, largest) size (:func:`class_sizes`)
    ox: float  # the sensor (m)
    oy: float
    oz: float
    top_slope: FloatArray  # (B,) the highest return's slope per azimuth bin (the ceiling)
    rays_per_rad2: float  # returns per steradian of the frame (:func:`_rays_per_rad2`)
    elevations: tuple[float, float]  # the lowest and highest elevation its beams cover (radians)
    grid: tuple | None  # (owner (nx, ny), x0, y0, cell, cells per group): the continuation test
    sight: (
        tuple | None
    )  # (band returns per cell, label mask, label tops, x0, y0, cell): what blocks the view (:func:`_place`)
    returns: Callable[[int], FloatArray | None] | None = None  # a searched group's returns (M, 3), else None
    rough: dict | None = None  # group → its roughness (:func:`_roughness`), as measured


def _box_cluster(xyz: FloatArray, h: FloatArray, scene: _Scene, own: int = -1, splits: int = 0) -> list[Cluster]:
    """Box and score one cluster (its returns (M, 3) and their heights above the ground (M,)) of
    group ``own`` in the frame ``scene``.

    A cluster that fits no class is split, up to ``splits`` times, at the emptiest slice across one
    of its axes when that slice is a gap (:func:`_split`): two cars parked side by side, a car and
    the hedge beside it. Each part is boxed on its own, the other part
    counting as returns beside it (a wall broken by a doorway is still one wall to the continuation
    test), and the parts replace the whole when one of them scores higher than the whole.
    """
    sizes, ox, oy, oz, top_slope, rays_per_rad2, elevations, grid, sight = scene[:9]
    centre = xyz[:, :2].mean(axis=0)
    xy = np.ascontiguousarray(xyz[:, :2] - centre)
    lo, hi = C.MISSING_FACE_BAND
    t, share, a1, b1, a2, b2 = _faces(
        xy, h, lo, hi, C.MISSING_HEADINGS, C.MISSING_FACE_WIDTH, C.MISSING_FACE_TIE, C.MISSING_FACE_MIN_LOWER
    )
    c, s = math.cos(t), math.sin(t)
    e1, e2 = b1 - a1, b2 - a2
    rx, ry = ox - centre[0], oy - centre[1]  # the sensor in the cluster's frame
    po, qo = c * rx + s * ry, -s * rx + c * ry
    top = float(h.max())
    near = float(np.min(np.hypot(xyz[:, 0] - ox, xyz[:, 1] - oy)))
    ground_z = _median(xyz[:, 2] - h)
    nb = len(top_slope)
    bins = np.minimum(
        nb - 1, ((np.arctan2(xyz[:, 1] - oy, xyz[:, 0] - ox) + np.pi) / (2 * np.pi) * nb).astype(np.int64)
    )
    # the lowest top beam over the cluster's directions, but no lower than the sensor's tilt allows
    # below its highest: a direction whose top beams hit nothing (open sky) holds only lower beams
    highest = float(np.max(top_slope))
    slope = max(float(np.min(top_slope[bins])), math.tan(math.atan(highest) - math.radians(C.MISSING_CEILING_SPREAD)))
    ceiling = (
        oz - ground_z
    ) + near * slope  # the highest the beams reach at the cluster's nearest range, above the ground
    top_seen = top < ceiling - C.MISSING_TOP_CLEARANCE
    vis_l, vis_w = max(e1, e2), min(e1, e2)
    # the smallest class that explains the visible extents (a larger one fits any fragment of a
    # smaller and would place the box far off), else the best-fitting one
    gap = near * math.tan(math.radians(C.MISSING_BEAM_GAP))
    corner = min(_face_lengths(xy, c, s, C.MISSING_FACE_WIDTH))  # the shorter leg of an L-shape (≈ 0: one face)
    rect = np.array([[a1, a2], [b1, a2], [b1, b2], [a1, b2]])
    corners = centre + rect @ np.array([[c, s], [-s, c]])
    fill = _fill(
        len(xyz), corners, ox, oy, ground_z + C.MISSING_BAND[0] - oz, ground_z + top - oz, rays_per_rad2, elevations
    )
    facing = (e1 >= e2) != (abs(po) >= abs(qo))  # the longer side square to the line of sight (a rear, not a side)
    fits = []
    for name, (mean, largest) in sorted(sizes.items(), key=lambda kv: kv[1][0][0]):
        min_top = C.MISSING_CLASS_MIN_TOP.get(name)
        m = _size_match(vis_l, vis_w, top, top_seen, ceiling, mean, largest, gap, min_top)
        rear = _rear_view(vis_l, facing, top + gap, fill, largest[1], C.MISSING_CLASS_REAR_WIDTH.get(name), min_top)
        if not rear:
            m *= _ramp(corner, *C.MISSING_CLASS_MIN_CORNER.get(name, (0.0, 0.0)))
        fits.append((m, name, rear))
    size_score, best_name = next(
        ((m, name) for m, name, rear in fits if rear and m >= C.MISSING_CLASS_FIT),
        next(((m, name) for m, name, _ in fits if m >= C.MISSING_CLASS_FIT), max(fits, key=lambda f: f[0])[:2]),
    )  # a class seen from behind first, then the smallest that fits (ties: the smaller)
    mean, _ = sizes[best_name]
    # which axis is the length: the longer visible one, unless both fit in a width (a car seen
    # head-on or from behind): then the axis nearer the line of sight
    if vis_l > mean[1] + C.MISSING_SIZE_SLACK:
        len_axis1 = e1 >= e2
    else:
        len_axis1 = abs(po) * 1.0 >= abs(qo)
    L1, L2 = (mean[0], mean[1]) if len_axis1 else (mean[1], mean[0])
    A1, B1 = _grow(a1, b1, L1, po)
    A2, B2 = _grow(a2, b2, L2, qo)
    if sight is not None and size_score >= C.MISSING_CLASS_FIT:  # (only a box that may become a candidate)
        aim = ground_z + C.MISSING_PLACE_SIGHT_HEIGHT * min(top, mean[2])  # where the object would be seen
        A1, A2 = _place(sight, centre, c, s, ox, oy, (a1, b1, a2, b2), (L1, L2), (A1, A2), oz, aim)
        B1, B2 = A1 + max(L1, e1), A2 + max(L2, e2)
    mx, my = 0.5 * (A1 + B1), 0.5 * (A2 + B2)
    cx, cy = centre[0] + c * mx - s * my, centre[1] + s * mx + c * my
    length, width, yaw = (B1 - A1, B2 - A2, t) if len_axis1 else (B2 - A2, B1 - A1, t + 0.5 * math.pi)
    height = top if top_seen else max(top, mean[2])
    box = np.array([cx, cy, ground_z + 0.5 * height, length, width, height, float(g.normalize_angle(yaw))])
    # judged on all its returns, a car's cabin (windows, roof), set back from its body's ends and
    # sides, is on no face of the body: its share is lower than a boxy van's or truck's
    on_all = int(np.count_nonzero((h >= lo) & (h <= hi))) < C.MISSING_FACE_MIN_LOWER
    ramp = C.MISSING_FACE_SHARE_ALL.get(best_name, C.MISSING_FACE_SHARE) if on_all else C.MISSING_FACE_SHARE
    shape_score = _ramp(share, *ramp)
    density_score = _ramp(fill, *C.MISSING_FILL)
    density_score *= _ramp(len(xyz), *C.MISSING_POINTS_RAMP)
    body = (A1, B1, A2, B2)
    # a truck's cab seen past the gap between cab and box, or its far end past an occluder, is a group
    # in line with its side but its own: within the class's largest length nothing counts as a wall
    # going on; past it the test looks on as usual
    reach, fragment, extra, own_box = body, C.MISSING_OWN_FRAGMENT_CELLS, 0.0, None
    if size_score >= C.MISSING_CLASS_FIT:
        # a group of any size wholly inside the box is the vehicle's own far end or far side seen past
        # a gap or an occluder's shadow; a wall's pieces run on beyond it, where the line is followed
        own_box = body
        if e1 >= e2:
            extra = max(B1 - b1, a1 - A1, 0.0)
        else:
            extra = max(B2 - b2, a2 - A2, 0.0)
    if best_name in C.MISSING_CLASS_OWN_REACH and size_score >= C.MISSING_CLASS_FIT:
        longest = sizes[best_name][1][0]
        if len_axis1:
            reach = (*_grow(A1, B1, longest, po), A2, B2)
        else:
            reach = (A1, B1, *_grow(A2, B2, longest, qo))
        fragment = np.iinfo(np.int64).max
        if e1 >= e2:
            extra = max(reach[1] - b1, a1 - reach[0], 0.0)
        else:
            extra = max(reach[3] - b2, a2 - reach[2], 0.0)
    rough = None
    if grid is not None and _continues(
        grid, own, centre, c, s, a1, b1, a2, b2, e1 >= e2, po, qo, reach, fragment, extra, own_box
    ):
        # foliage in line with a solid surface is not a structure the surface is part of (a car
        # parked with a bush in line with its side); a hedge's own piece is no solid surface
        foliage: list[int] = []
        if size_score * shape_score * density_score >= C.MISSING_MIN_KEPT_SCORE:
            rough = _surface_roughness(xyz, scene)
            if 0.0 <= rough < C.MISSING_SURFACE_ROUGH[0]:
                # (the test looks this far from the visible rectangle: along the line, and across a corner's)
                near = (a1, b1, a2, b2, C.MISSING_CONTINUATION + extra + C.MISSING_MERGE_SIDE_CELLS * C.MISSING_CELL)
                foliage = _foliage_near(scene, own, centre, c, s, near)
        if not foliage or _continues(
            grid, own, centre, c, s, a1, b1, a2, b2, e1 >= e2, po, qo, reach, fragment, extra, own_box, foliage
        ):
            shape_score = 0.0
    # a class seen as an L-shape (a truck): its short leg ends too (a building's end wall, broken into
    # pieces by windows or an occluder, goes on in line with it)
    if (
        grid is not None
        and best_name in C.MISSING_CLASS_MIN_CORNER
        and _continues(grid, own, centre, c, s, a1, b1, a2, b2, e1 < e2, po, qo, body)
    ):
        shape_score = 0.0
    # a vehicle's body is a solid surface: along each beam its returns lie on a smooth line (foliage
    # returns from anywhere in its depth). Measured only where it can matter: a score already under
    # the kept minimum stays under it (no row changes, and a part replaces such a whole only when
    # neither is kept or the part is kept either way)
    if size_score * shape_score * density_score >= C.MISSING_MIN_KEPT_SCORE:
        if rough is None:
            rough = _surface_roughness(xyz, scene)
        if rough >= 0.0:
            shape_score *= 1.0 - _ramp(rough, *C.MISSING_SURFACE_ROUGH)
    hidden = None
    if size_score >= C.MISSING_CLASS_FIT and any(
        b - a < L - C.MISSING_PLACE_MIN_HIDDEN for a, b, L in ((a1, b1, L1), (a2, b2, L2))
    ):
        largest = sizes[best_name][1][0]
        hidden = _Hidden(
            float(centre[0]),
            float(centre[1]),
            t,
            (a1, b1, a2, b2),
            (L1, L2),
            (A1, A2),
            len_axis1,
            mean[0],
            largest,
            not vis_l > mean[1] + C.MISSING_SIZE_SLACK,  # the length may lie on either axis
        )
    whole = Cluster(box, best_name, len(xyz), ground_z, size_score, shape_score, density_score, 1.0, 0, 0, hidden)
    if splits > 0 and size_score < C.MISSING_CLASS_FIT:  # no class fits: maybe two objects
        parts = _split(xy, c, s)
        if parts is not None:
            out = []
            for mine, other in (parts, parts[::-1]):
                with _others_marked(grid, own, xyz[other]):
                    out += _box_cluster(xyz[mine], h[mine], scene, own, splits - 1)
            if out and max(p.score for p in out) > whole.score:  # two objects explain the returns better than one
                return out
    return [whole]


def _surface_roughness(xyz: FloatArray, scene: _Scene) -> float:
    """:func:`_roughness` of returns ``xyz`` (M, 3) seen from the scene's sensor (−1: too few)."""
    return float(
        _roughness(
            xyz,
            scene.ox,
            scene.oy,
            scene.oz,
            math.radians(C.MISSING_SURFACE_BEAM_GAP),
            math.radians(C.MISSING_SURFACE_STEP),
            C.MISSING_SURFACE_MIN_RETURNS,
        )
    )


def _foliage_near(
    scene: _Scene, own: int, centre: FloatArray, c: float, s: float, near: tuple[float, float, float, float, float]
) -> list[int]:
    """The searched groups other than ``own`` within ``near`` = (a1, b1, a2, b2, reach): the
    rectangle [a1, b1] × [a2, b2] of the frame about ``centre`` with axes (c, s), (−s, c) grown by
    ``reach`` m, whose returns are foliage: as rough as the surface factor's end
    (``MISSING_SURFACE_ROUGH[1]``), where it takes a cluster's shape score to 0."""
    if scene.grid is None or scene.returns is None or scene.rough is None:
        return []
    _, x0, y0, cell, _, rect = scene.grid
    a1, b1, a2, b2, r = near
    corners = np.array([[a1 - r, a2 - r], [b1 + r, a2 - r], [b1 + r, b2 + r], [a1 - r, b2 + r]])
    xy = centre + corners @ np.array([[c, s], [-s, c]])
    lo_i, hi_i = (xy[:, 0].min() - x0) / cell, (xy[:, 0].max() - x0) / cell
    lo_j, hi_j = (xy[:, 1].min() - y0) / cell, (xy[:, 1].max() - y0) / cell
    hit = (rect[1] >= lo_i) & (rect[0] <= hi_i) & (rect[3] >= lo_j) & (rect[2] <= hi_j)
    out = []
    for other in np.flatnonzero(hit).tolist():
        if other == own:
            continue
        if other not in scene.rough:
            pts = scene.returns(other)
            scene.rough[other] = -1.0 if pts is None else _surface_roughness(pts, scene)
        if scene.rough[other] >= C.MISSING_SURFACE_ROUGH[1]:
            out.append(other)
    return out


def _face_lengths(xy: FloatArray, c: float, s: float, width: float) -> tuple[float, float]:
    """Lengths (m) of the densest ``width``-wide face square to each axis (cos θ, sin θ) and
    (−sin θ, cos θ) of the returns ``xy`` (M, 2): a side and a rear of a vehicle seen from a corner
    are both long (an L-shape), a stretch of wall has one long face and one as short as it is thick."""
    p = c * xy[:, 0] + s * xy[:, 1]
    q = -s * xy[:, 0] + c * xy[:, 1]
    out = []
    for across, along in ((p, q), (q, p)):
        idx = ((across - across.min()) / width).astype(np.int64)
        on = idx == int(np.argmax(np.bincount(idx)))
        out.append(float(np.ptp(along[on])))
    return out[0], out[1]


def _split(xy: FloatArray, c: float, s: float) -> tuple[NDArray, NDArray] | None:
    """Indices of the two parts of a cluster (returns ``xy`` (M, 2) about its centre) on either side
    of its emptiest ``MISSING_SPLIT_BIN`` slice across the axis (cos θ, sin θ) or (−sin θ, cos θ),
    each part at least ``MISSING_SPLIT_MIN_PART`` long on that axis; ``None`` when that slice holds
    more than ``MISSING_SPLIT_GAP`` of the returns of an average occupied slice (no gap: one object)
    or a part has fewer than ``MISSING_SPLIT_MIN_POINTS`` returns."""
    width = C.MISSING_SPLIT_BIN
    k0 = int(round(C.MISSING_SPLIT_MIN_PART / width))
    best = None
    for proj in (c * xy[:, 0] + s * xy[:, 1], -s * xy[:, 0] + c * xy[:, 1]):
        lo = float(proj.min())
        idx = ((proj - lo) / width).astype(np.int64)
        hist = np.bincount(idx)
        if len(hist) <= 2 * k0:
            continue
        k = k0 + int(np.argmin(hist[k0 : len(hist) - k0]))
        level = hist[k] / float(hist[hist > 0].mean())
        if level <= C.MISSING_SPLIT_GAP and (best is None or level < best[0]):
            best = (level, idx <= k)
    if best is None:
        return None
    first = np.flatnonzero(best[1])
    second = np.flatnonzero(~best[1])
    if min(len(first), len(second)) < C.MISSING_SPLIT_MIN_POINTS:
        return None
    return first, second


class _others_marked:
    """Within the block, the cells of ``xyz`` (M, 3) hold returns of another cluster in ``grid``'s
    owner map (so the continuation test sees a part's sibling as returns beside it); restored after."""

    def __init__(self, grid: tuple | None, own: int, xyz: FloatArray):
        self.grid, self.own, self.xyz, self.saved = grid, own, xyz, None

    def __enter__(self) -> None:
        if self.grid is None:
            return
        owner, x0, y0, cell = self.grid[:4]
        i = np.clip(((self.xyz[:, 0] - x0) / cell).astype(np.int64), 0, owner.shape[0] - 1)
        j = np.clip(((self.xyz[:, 1] - y0) / cell).astype(np.int64), 0, owner.shape[1] - 1)
        self.saved = (i, j, owner[i, j].copy())
        owner[i, j] = np.where(owner[i, j] == self.own, np.iinfo(owner.dtype).max, owner[i, j])

    def __exit__(self, *exc: object) -> None:
        if self.saved is not None:
            i, j, values = self.saved
            self.grid[0][i, j] = values


# --------------------------------------------------------------------------- against the labels
# (where a dataset labels at all is the reader's to say: labelaudit.datasets.in_labelled_region)


def _max_iou(box: FloatArray, others: FloatArray) -> float:
    best = 0.0
    for o in others:
        if math.hypot(o[0] - box[0], o[1] - box[1]) < 0.5 * (math.hypot(o[3], o[4]) + math.hypot(box[3], box[4])):
            best = max(best, bev_iou_exact(box, o))
    return best


def _rect_box(hid: _Hidden, low: tuple[float, float], ext: tuple[float, float], z: float, h: float) -> FloatArray:
    """The box (7,) spanning ``low`` + [0, ``ext``] on the cluster's axes, yaw its heading."""
    c, s = math.cos(hid.t), math.sin(hid.t)
    mx, my = low[0] + 0.5 * ext[0], low[1] + 0.5 * ext[1]
    return np.array([hid.cx + c * mx - s * my, hid.cy + s * mx + c * my, z, ext[0], ext[1], h, hid.t])


def _lows(a: float, b: float, size: float) -> FloatArray:
    """The low ends of every placement of an extent ``size`` that holds the visible [a, b] on one
    axis, ``MISSING_PLACE_STEP`` apart (just ``a`` when nothing of it is hidden)."""
    if b - a < size:
        return np.linspace(b - size, a, int(math.ceil((size - b + a) / C.MISSING_PLACE_STEP)) + 1)
    return np.array([a])


def _variants(hid: _Hidden) -> list[tuple[bool, float, FloatArray, FloatArray, tuple[float, float]]]:
    """Every (way the length lies, length) :func:`_place_by_rays` weighs, in its order: the length
    from the class's mean down to the visible length in ``MISSING_PLACE_STEP`` steps (no shorter than
    the mean less as much as the largest lies above it: the prior's support), on the axis
    :func:`_box_cluster` chose and, where the visible rectangle fits the class's width both ways, on
    the other too. Per entry: whether the length lies on the first axis, the length, the low ends on
    either axis and the box's extents on them."""
    out = []
    a1, b1, a2, b2 = hid.vis
    step = C.MISSING_PLACE_STEP
    for len_axis1 in (hid.len_axis1, not hid.len_axis1) if hid.either_axis else (hid.len_axis1,):
        size = hid.size if len_axis1 == hid.len_axis1 else hid.size[::-1]
        ax = 0 if len_axis1 else 1
        shortest = max((b1 - a1, b2 - a2)[ax], 2.0 * hid.mean_length - hid.largest_length)
        lengths = [size[ax]]
        if shortest < size[ax]:
            lengths += np.arange(size[ax] - step, shortest, -step).tolist() + [shortest]
        other = _lows(a2, b2, size[1]) if ax == 0 else _lows(a1, b1, size[0])
        for length in lengths:
            ext = (
                (max(length, b1 - a1), max(size[1], b2 - a2))
                if ax == 0
                else (max(size[0], b1 - a1), max(length, b2 - a2))
            )
            lows = _lows(a1, b1, length) if ax == 0 else _lows(a2, b2, length)
            out.append((len_axis1, float(length), *((lows, other) if ax == 0 else (other, lows)), ext))
    return out


@kernel(inline="always")
def _count_below(g, first, num, g0, d, v, strict):  # pragma: no cover - compiled
    """How many of the ascending low ends ``g[first:first + num]`` (about ``g0`` + i ``d``, as
    ``np.linspace`` writes them) lie below ``v`` (``strict``) or at ``v`` or below (else): a guess
    from the step, corrected on the values themselves (a binary search's answer)."""
    i = 0
    if num > 1 and d > 0.0:
        f = (v - g0) / d
        if f >= num:
            i = num
        elif f > 0.0:
            i = int(f)
    while i > 0 and (g[first + i - 1] >= v if strict else g[first + i - 1] > v):
        i -= 1
    while i < num and (g[first + i] < v if strict else g[first + i] <= v):
        i += 1
    return i


@kernel
def _placement_counts(
    flat, m, mask, ox, oy, oz, env, bands_f, bands_i, rows_f, rows_i, grids, tau, tau_in, object_height
):  # pragma: no cover - compiled
    """Per placement of :func:`_place_by_rays`, its rays through the solid lower body that end
    behind it plus its returns inside that body, in one pass over the frame per cluster.

    The placements of one cluster are rectangles on its axes (u, v). A *band* (``bands_f`` (B, 2):
    its extent across the swept axis and its low end there; ``bands_i`` (B, 4): the swept axis, 0
    for u and 1 for v, its rows' range and its cluster) holds those that share their extent and
    position across the swept axis; a row of it (``rows_f`` (R, 3): the extent along the swept
    axis, the first low end and the step between them; ``rows_i`` (R, 2): where its ascending low
    ends start in ``grids``, their number) those that share their extent along it too and differ
    only in their low end. ``env`` (H, 17) per cluster: centre x, y, cos and sin of its heading, the
    envelope of its placements (u0, u1, v0, v1), the ground's z (flat), the slab's bottom and top
    above it, the box's top z, the cone of azimuths the envelope fills seen from the sensor (its
    edges' directions: x, y clockwise, then x, y anticlockwise) and the envelope's least squared
    distance from the sensor (0: the sensor is inside, every direction).

    A return of the frame (``flat``: ``m`` rows of 4, x, y, z and anything; ``mask`` (m,) or empty:
    which end a ray from the sensor) counts against a placement when (a) its ray passes through the
    slab deeper than ``tau`` inside the rectangle and it does not end on or in it (within ``tau`` of
    the rectangle, at least ``object_height`` above the ground and at most ``tau`` over the box's
    top) — the free rays of :func:`labelaudit.core.freespace.ray_counts` —, or (b) it lies in the
    slab deeper than ``tau_in`` inside the rectangle. Each return is projected once on the
    cluster's axes and its ray clipped once per band; per row the low ends for which it counts form
    an interval (less the interval where it ends on the box), added to a difference array: O(rows)
    per return instead of a test per placement. Returns the counts, in the layout of ``grids``."""
    diff = np.zeros(grids.shape[0] + rows_i.shape[0], dtype=np.int64)
    use_mask = mask.shape[0] == m
    near = np.empty(m, dtype=np.bool_)
    b = 0
    for h in range(env.shape[0]):
        cx, cy, c, s = env[h, 0], env[h, 1], env[h, 2], env[h, 3]
        u0, u1, v0, v1 = env[h, 4], env[h, 5], env[h, 6], env[h, 7]
        gz, slo, shi, top = env[h, 8], env[h, 9], env[h, 10], env[h, 11]
        lx, ly, hx, hy, near2 = env[h, 12], env[h, 13], env[h, 14], env[h, 15], env[h, 16]
        b0 = b
        while b < bands_i.shape[0] and bands_i[b, 3] == h:
            b += 1
        b1 = b
        rx, ry = ox - cx, oy - cy
        su, sv, sh = c * rx + s * ry, -s * rx + c * ry, oz - gz
        # the returns in the envelope's cone, not nearer than it (no branch, a constant stride: vectorised)
        for k in range(m):
            dx, dy = np.float64(flat[4 * k]) - ox, np.float64(flat[4 * k + 1]) - oy
            near[k] = (dx * dx + dy * dy >= near2) & (lx * dy - ly * dx >= 0.0) & (dx * hy - dy * hx >= 0.0)
        if not near2 > 0.0:
            near[:] = True
        for k in range(m):
            if not near[k]:
                continue
            x, y, z = np.float64(flat[4 * k]), np.float64(flat[4 * k + 1]), np.float64(flat[4 * k + 2])
            if not (x == x and y == y and z == z):
                continue
            hp = z - gz
            qx, qy = x - cx, y - cy
            pu, pv = c * qx + s * qy, -s * qx + c * qy
            # (b) a return in the slab inside the envelope
            inside = slo <= hp <= shi and u0 + tau_in < pu < u1 - tau_in and v0 + tau_in < pv < v1 - tau_in
            # (a) its ray's stretch in the slab [t0, t1], when it passes the envelope shrunk by tau there
            t0, t1 = 0.0, 1.0
            ray = not use_mask or mask[k]
            if ray:
                dh = hp - sh
                if dh == 0.0:
                    ray = slo <= sh <= shi
                else:
                    ta, tb = (slo - sh) / dh, (shi - sh) / dh
                    t0, t1 = max(t0, min(ta, tb)), min(t1, max(ta, tb))
                    ray = t0 < t1
            if ray:
                for lo, hi, start, d in ((u0 + tau, u1 - tau, su, pu - su), (v0 + tau, v1 - tau, sv, pv - sv)):
                    if d == 0.0:
                        ray = ray and lo < start < hi
                    else:
                        ta, tb = (lo - start) / d, (hi - start) / d
                        ray = ray and max(t0, min(ta, tb)) < min(t1, max(ta, tb))
            if not ray and not inside:
                continue
            on = hp >= object_height and z <= top + tau
            for q in range(b0, b1):
                eo, other = bands_f[q, 0], bands_f[q, 1]
                if bands_i[q, 0] == 0:
                    ps, po, ss, so = pu, pv, su, sv
                else:
                    ps, po, ss, so = pv, pu, sv, su
                r0, r1 = bands_i[q, 1], bands_i[q, 2]
                if inside and other + tau_in < po < other + eo - tau_in:
                    for r in range(r0, r1):  # low ends p with p + tau_in < ps < p + es − tau_in
                        es, g0, d = rows_f[r, 0], rows_f[r, 1], rows_f[r, 2]
                        first, num = rows_i[r, 0], rows_i[r, 1]
                        i0 = _count_below(grids, first, num, g0, d, ps - es + tau_in, False)
                        i1 = _count_below(grids, first, num, g0, d, ps - tau_in, True)
                        if i0 < i1:
                            diff[first + r + i0] += 1
                            diff[first + r + i1] -= 1
                if not ray:
                    continue
                # the stretch where the ray lies across the band deeper than tau, and its span along it
                d_o = po - so
                a, e = t0, t1
                if d_o == 0.0:
                    if not other + tau < so < other + eo - tau:
                        continue
                else:
                    ta, tb = (other + tau - so) / d_o, (other + eo - tau - so) / d_o
                    a, e = max(a, min(ta, tb)), min(e, max(ta, tb))
                    if not a < e:
                        continue
                d_s = ps - ss
                sa, sb = ss + a * d_s, ss + e * d_s
                smin, smax = min(sa, sb), max(sa, sb)
                ends_on = on and other - tau <= po <= other + eo + tau  # its end in the band grown by tau
                for r in range(r0, r1):
                    es, g0, d = rows_f[r, 0], rows_f[r, 1], rows_f[r, 2]
                    first, num = rows_i[r, 0], rows_i[r, 1]
                    # low ends p with smin < p + es − tau and p + tau < smax
                    i0 = _count_below(grids, first, num, g0, d, smin - es + tau, False)
                    i1 = _count_below(grids, first, num, g0, d, smax - tau, True)
                    if i0 >= i1:
                        continue
                    diff[first + r + i0] += 1
                    diff[first + r + i1] -= 1
                    if ends_on:  # less those whose rectangle grown by tau holds its end: p − tau ≤ ps ≤ p + es + tau
                        j0 = max(i0, _count_below(grids, first, num, g0, d, ps - es - tau, True))
                        j1 = min(i1, _count_below(grids, first, num, g0, d, ps + tau, False))
                        if j0 < j1:
                            diff[first + r + j0] -= 1
                            diff[first + r + j1] += 1
    counts = np.zeros(grids.shape[0], dtype=np.int64)
    for r in range(rows_i.shape[0]):
        first, num = rows_i[r, 0], rows_i[r, 1]
        run = 0
        for i in range(num):
            run += diff[first + r + i]
            counts[first + i] = run
    return counts


def _cone(su: float, sv: float, c: float, s: float, rect: tuple[float, float, float, float]) -> tuple[float, ...]:
    """The rectangle ``rect`` (u0, u1, v0, v1) on a cluster's axes (heading cos ``c``, sin ``s``)
    seen from the sensor at (``su``, ``sv``) on them: the directions (x, y) of its clockwise-most and
    anticlockwise-most corners and its least squared distance (a hair less; 0 when the sensor is
    inside), as :func:`_placement_counts` reads them."""
    u0, u1, v0, v1 = rect
    du, dv = max(u0 - su, su - u1, 0.0), max(v0 - sv, sv - v1, 0.0)
    near2 = (du * du + dv * dv) * (1.0 - 1e-9)
    corners = [(u - su, v - sv) for u, v in ((u0, v0), (u1, v0), (u1, v1), (u0, v1))]
    dirs = [(c * u - s * v, s * u + c * v) for u, v in corners]
    mid = math.atan2(sum(d[1] for d in dirs), sum(d[0] for d in dirs))
    rel = [math.remainder(math.atan2(y, x) - mid, 2.0 * math.pi) for x, y in dirs]
    lo, hi = dirs[rel.index(min(rel))], dirs[rel.index(max(rel))]
    return (lo[0], lo[1], hi[0], hi[1], near2)


class _Weighed(NamedTuple):
    """The placements of one partly hidden cluster that :func:`_placement_costs` counts: the
    rectangle holding all of them on the cluster's axes (u0, u1, v0, v1), and per group of them the
    low ends on either axis (P, Q) and the extents (on u, on v) they share."""

    cluster: Cluster
    envelope: tuple[float, float, float, float]
    groups: list[tuple[FloatArray, FloatArray, tuple[float, float]]]


def _placement_costs(frame: Frame, cfg: RunConfig, weighed: list[_Weighed]) -> list[list[NDArray]]:
    """Per cluster of ``weighed``, per group, the count (|P|, |Q|) of every placement's rays through
    its solid lower body that end behind it and returns inside that body (:func:`_placement_counts`,
    one pass over the frame per cluster; the slab over the cluster's ground, flat)."""
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    ox, oy, oz = float(o[0]), float(o[1]), float(o[2])
    env, bands_f, bands_i, rows_f, rows_i, grids = [], [], [], [], [], []
    used = 0
    where = []  # per cluster, per group and low end across the swept axis: where its counts start
    for h, w in enumerate(weighed):
        hid, box = w.cluster.hidden, w.cluster.box
        c, s = math.cos(hid.t), math.sin(hid.t)
        rx, ry = ox - hid.cx, oy - hid.cy
        height = float(box[5])
        env.append(
            [hid.cx, hid.cy, c, s, *w.envelope, w.cluster.ground_z, C.FREE_SPACE_SLAB[0]]
            + [C.FREE_SPACE_SLAB[1] * height, float(box[2]) + 0.5 * height]
            + list(_cone(c * rx + s * ry, -s * rx + c * ry, c, s, w.envelope))
        )
        # a band per low end across the axis with more placements (shared by the groups of one extent
        # across it), a row per group in it, along that axis
        bands: dict[tuple[int, float, float], list[tuple[int, int, FloatArray, float]]] = {}
        for v, (P, Q, ext) in enumerate(w.groups):
            along_u = len(P) >= len(Q)
            swept, across, es, eo = (P, Q, ext[0], ext[1]) if along_u else (Q, P, ext[1], ext[0])
            for j, other in enumerate(across.tolist()):
                bands.setdefault((0 if along_u else 1, eo, other), []).append((v, j, swept, es))
        at: dict[tuple[int, int], int] = {}
        for (axis, eo, other), rows in bands.items():
            r0 = len(rows_f)
            for v, j, swept, es in rows:
                g0, num = float(swept[0]), len(swept)
                rows_f.append((es, g0, (float(swept[-1]) - g0) / (num - 1) if num > 1 else 0.0))
                rows_i.append((used, num))
                grids.append(swept)
                at[v, j] = used
                used += num
            bands_f.append((eo, other))
            bands_i.append((axis, r0, len(rows_f), h))
        where.append(at)
    mask = np.zeros(0, dtype=np.bool_) if frame.ray_mask is None else np.asarray(frame.ray_mask, dtype=np.bool_)
    counts = _placement_counts(
        _four_columns(frame.points).ravel(),
        len(frame.points),
        mask,
        ox,
        oy,
        oz,
        np.array(env),
        np.array(bands_f),
        np.array(bands_i, dtype=np.int64),
        np.array(rows_f),
        np.array(rows_i, dtype=np.int64),
        np.concatenate(grids),
        C.FREE_SPACE_TOLERANCE,
        C.FREE_SPACE_INSIDE_TOLERANCE,
        float(cfg.crop.ground_cut),
    )
    out = []
    for w, at in zip(weighed, where):
        per = []
        for v, (P, Q, _) in enumerate(w.groups):
            if len(P) >= len(Q):  # a row along P per low end on Q
                per.append(np.stack([counts[at[v, j] : at[v, j] + len(P)] for j in range(len(Q))], axis=1))
            else:
                per.append(np.stack([counts[at[v, j] : at[v, j] + len(Q)] for j in range(len(P))], axis=0))
        out.append(per)
    return out


def _place_by_rays(frame: Frame, clusters: list[Cluster], cfg: RunConfig) -> list[Cluster]:
    """The clusters with each partly hidden box placed where the frame's rays let it be.

    A ray that passes through a vehicle's solid lower body (the label-error fit's slab,
    ``FREE_SPACE_SLAB``, over the cluster's ground) and ends behind it says the body is not there,
    unless it went through a slit (``FREE_SPACE_SLIT_PROB``: the gap between a truck's cab and box);
    a ray an occluder stopped says nothing; a return deeper than ``FREE_SPACE_INSIDE_TOLERANCE``
    inside the body was reached through it. Among the placements of the hidden extent
    (:func:`_variants`, every ``MISSING_PLACE_STEP``) the box takes the most probable: each such
    ray or return costs −log ``FREE_SPACE_SLIT_PROB``, and a length short of the class's mean costs
    what a normal prior on the length says (its spread from the class's mean and largest,
    ``MISSING_LENGTH_SPREAD``). So a box keeps an end that is seen — the space past it is crossed
    by rays — and reaches over what no ray crossed (an occluder's shadow), towards the sensor too;
    where rays cross the space past both ends, the length is what they leave. Where the visible
    rectangle fits the class's width both ways, the placements with the length on the other axis
    are weighed too (:func:`_box_cluster` chose the axis nearer the line of sight: a car seen from
    one end; the rays tell a car seen from its corner with most of its side hidden). The placement
    of :func:`_box_cluster` stays unless another costs at least ``MISSING_PLACE_RAY_MARGIN`` rays
    less (among equals, the nearest to it).

    Weighed only for clusters whose score before the free space reaches ``MISSING_PLACE_MIN_SCORE``
    (the free-space factor only lowers it), and only where the placement :func:`_box_cluster` made
    costs at least that margin itself (no placement costs less than nothing): that one is counted
    first, alone, the others where it costs (:func:`_placement_costs`)."""
    todo = [k for k, c in enumerate(clusters) if c.hidden is not None and c.score >= C.MISSING_PLACE_MIN_SCORE]
    if not todo:
        return clusters
    made = []
    for k in todo:
        cl = clusters[k]
        hid = cl.hidden
        a1, b1, a2, b2 = hid.vis
        ext = (max(hid.size[0], b1 - a1), max(hid.size[1], b2 - a2))
        (A1, A2) = hid.low
        made.append(_Weighed(cl, (A1, A1 + ext[0], A2, A2 + ext[1]), [(np.array([A1]), np.array([A2]), ext)]))
    own = {k: int(c[0][0, 0]) for k, c in zip(todo, _placement_costs(frame, cfg, made))}
    weighed, lengths, which = [], [], []
    for k in todo:
        if own[k] < C.MISSING_PLACE_RAY_MARGIN:
            continue
        cl = clusters[k]
        hid = cl.hidden
        a1, b1, a2, b2 = hid.vis
        variants = _variants(hid)
        L1, L2 = (max(hid.size),) * 2 if hid.either_axis else hid.size  # every placement lies within
        envelope = (min(a1, b1 - L1), max(b1, a1 + L1), min(a2, b2 - L2), max(b2, a2 + L2))
        weighed.append(_Weighed(cl, envelope, [(P, Q, ext) for _, _, P, Q, ext in variants]))
        lengths.append(variants)
        which.append(k)
    if not weighed:
        return clusters
    ray_cost = -math.log(C.FREE_SPACE_SLIT_PROB)
    out = list(clusters)
    for k, w, variants, counts in zip(which, weighed, lengths, _placement_costs(frame, cfg, weighed)):
        cl = w.cluster
        hid = cl.hidden
        spread = (hid.largest_length - hid.mean_length) / C.MISSING_LENGTH_SPREAD
        cost = np.concatenate(
            [
                (n * ray_cost + 0.5 * ((length - hid.mean_length) / spread) ** 2).ravel()
                for (_, length, _, _, _), n in zip(variants, counts)
            ]
        )
        dist = np.concatenate(
            [(np.abs(P - hid.low[0])[:, None] + np.abs(Q - hid.low[1])[None, :]).ravel() for _, _, P, Q, _ in variants]
        )
        best = int(np.lexsort((dist, cost))[0])
        if cost[best] + C.MISSING_PLACE_RAY_MARGIN * ray_cost <= own[k] * ray_cost:
            sizes = np.cumsum([len(P) * len(Q) for _, _, P, Q, _ in variants])
            v = int(np.searchsorted(sizes, best, side="right"))  # the variant of placement ``best``
            len_axis1, _, P, Q, ext = variants[v]
            best -= int(sizes[v - 1]) if v else 0
            p, q = float(P[best // len(Q)]), float(Q[best % len(Q)])
            box = _rect_box(hid, (p, q), ext, float(cl.box[2]), float(cl.box[5]))
            if not len_axis1:  # the length on the second axis
                box[3], box[4], box[6] = ext[1], ext[0], hid.t + 0.5 * math.pi
            box[6] = float(g.normalize_angle(box[6]))
            out[k] = replace(cl, box=box)
    return out


def with_free_space(frame: Frame, clusters: list[Cluster], cfg: RunConfig) -> list[Cluster]:
    """The clusters with their free-space evidence: the label-error fit of :mod:`labelaudit.core.fit`
    moves each box onto its points (free-space rays included, as for a label), then the rays
    through the lower body of the fitted box that end behind it (``free_rays``) against the rays
    that end on or in it (``end_rays``) give ``free_space_score``: a car stops the rays that reach
    it, a hedge or a fence lets many through, and a box grown over empty road is crossed by them."""
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    boxes = np.array([c.box for c in clusters])
    with np.errstate(all="ignore"):
        evidence = frame_evidence(
            frame.points, boxes, o, cfg.crop, others=label_boxes(frame.boxes), ray_mask=frame.ray_mask
        )
        out = []
        for c, ev in zip(clusters, evidence):
            box = c.box
            if C.MISSING_REFINE:
                fit = fit_label_valid(box, frame.points[ev.fit_idx], c.class_name, cfg.model, free_space=ev.free_space)
                if np.all(np.isfinite(fit.box)):
                    box = fit.box
            free, end = ray_counts(box, ev.free_space, frame.points[ev.near_idx])
            ratio = free / max(free + end, 1)
            score = 1.0 - _ramp(ratio, *C.MISSING_FREE_SHARE)
            out.append(replace(c, box=box, free_space_score=score, free_rays=int(free), end_rays=int(end)))
    return out


def find_missing(
    frame: Frame, cfg: RunConfig, detections: FrameDetections | None = None, trace: SearchTrace | None = None
) -> list[dict[str, Any]]:
    """Candidate objects without a label in ``frame``: rows of the ``missing/`` table.

    Parameters
    ----------
    frame : points (N, ≥3) and every label of the frame (all classes), LiDAR/vehicle frame
    cfg : run configuration (``cfg.missing``, the audited classes)
    detections : the frame's detections above ``cfg.missing.detection_min_score`` (``--detections``)
    trace : when given (empty, one per frame), it receives what became of every cluster (:class:`SearchTrace`)

    Returns
    -------
    One dict per candidate with the columns of :data:`labelaudit.results.MISSING_SCHEMA`, nearest
    to the sensor first (``candidate_index``). Clusters of the points (``source`` "points") and
    detections (``"detections"``) overlapping no label (BEV IoU < ``MISSING_LABEL_IOU``) that overlap
    each other (BEV IoU ≥ ``MISSING_MERGE_IOU``) are one candidate, ``source`` "both", with the
    detection's box.
    """
    if not cfg.missing.enabled:
        return []
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    labels = np.asarray(frame.boxes, dtype=float).reshape(-1, 7)
    labels = labels[np.all(np.isfinite(labels), axis=1)]
    regions = labels
    found = search_clusters(frame, cfg, trace)
    fates = ["region"] * len(found)
    clusters: list[Cluster] = []
    if found:
        inside = in_labelled_region(np.array([c.box for c in found]), frame, cfg.missing.max_range)
        for k, (c, ok) in enumerate(zip(found, inside)):
            if ok and c.score >= C.MISSING_MIN_KEPT_SCORE:
                clusters.append(c)
                fates[k] = "kept"
            elif ok:
                fates[k] = "low score"
    if clusters:
        clusters = _place_by_rays(frame, clusters, cfg)
        clusters = with_free_space(frame, clusters, cfg)
    fitted = iter(clusters)
    rows: list[dict[str, Any]] = []
    for k, fate in enumerate(fates):
        if fate != "kept":
            if trace is not None:
                trace.clusters.append((found[k], fate))
            continue
        c = next(fitted)
        iou = _max_iou(c.box, regions)
        # a label covers it, only not where its returns are: a wrong label (label_error), not a missing one
        if iou >= C.MISSING_LABEL_IOU:
            fate = "label"
        else:
            rows.append(_row(frame, cfg, c.box, c.class_name, c.num_points, c.score, "points", c, iou))
        if trace is not None:
            trace.clusters.append((c, fate))
    if detections is not None and len(detections.scores):
        inside = in_labelled_region(detections.boxes, frame, cfg.missing.max_range)
        for k in np.flatnonzero(inside):
            box = np.asarray(detections.boxes[k], dtype=float)
            iou = _max_iou(box, regions)
            if iou >= C.MISSING_LABEL_IOU:
                continue
            det_score = float(min(1.0, max(0.0, detections.scores[k])))
            match = None
            for r in rows:
                if (
                    r["source"] == "points"
                    and bev_iou_exact(box, np.array([r[f] for f in g.BOX_FIELDS])) >= C.MISSING_MERGE_IOU
                ):
                    match = r
                    break
            evidence = {
                "detection_score": float(detections.scores[k]),
                "detection_class": detections.class_names[k],
                "detection_source": detections.sources[k],
            }
            if match is not None:
                both = 1.0 - (1.0 - match["score"]) * (1.0 - det_score)
                match.update(
                    dict(zip(g.BOX_FIELDS, box.tolist())), score=both, source="both", max_label_iou=iou, **evidence
                )
                match["distance"] = float(math.hypot(box[0] - o[0], box[1] - o[1]))
            else:
                n = _points_in_box(frame.points, box)
                cls = (
                    detections.class_names[k]
                    if detections.class_names[k] in class_sizes(cfg)
                    else _nearest_class(box, cfg)
                )
                row = _row(frame, cfg, box, cls, n, det_score, "detections", None, iou)
                row.update(evidence)
                rows.append(row)
    rows.sort(key=lambda r: (r["distance"], r["cx"], r["cy"]))
    for i, r in enumerate(rows):
        r["candidate_index"] = i
    return rows


def _nearest_class(box: FloatArray, cfg: RunConfig) -> str:
    sizes = class_sizes(cfg)
    if not sizes:
        return cfg.classes[0]
    return min(sizes, key=lambda c: abs(sizes[c][0][0] - box[3]) + abs(sizes[c][0][1] - box[4]))


def _points_in_box(points: NDArray, box: FloatArray) -> int:
    c, s = math.cos(box[6]), math.sin(box[6])
    dx, dy = points[:, 0] - box[0], points[:, 1] - box[1]
    u, v = c * dx + s * dy, -s * dx + c * dy
    inside = (np.abs(u) <= 0.5 * box[3]) & (np.abs(v) <= 0.5 * box[4]) & (np.abs(points[:, 2] - box[2]) <= 0.5 * box[5])
    return int(inside.sum())


def _row(
    frame: Frame,
    cfg: RunConfig,
    box: FloatArray,
    class_name: str,
    num_points: int,
    score: float,
    source: str,
    cluster: Cluster | None,
    max_label_iou: float,
) -> dict[str, Any]:
    o = np.asarray(frame.sensor_origin, dtype=float).reshape(3)
    labels = np.asarray(frame.boxes, dtype=float).reshape(-1, 7)
    nearest = float(np.min(np.hypot(labels[:, 0] - box[0], labels[:, 1] - box[1]))) if len(labels) else None
    row: dict[str, Any] = {
        "frame_id": frame.frame_id,
        "candidate_index": 0,
        "class_name": class_name,
        **dict(zip(g.BOX_FIELDS, np.asarray(box, dtype=float).tolist())),
        "num_points": int(num_points),
        "distance": float(math.hypot(box[0] - o[0], box[1] - o[1])),
        "score": float(score),
        "source": source,
        "dataset": cfg.dataset_format,
        "nearest_label_m": nearest,
        "max_label_iou": float(max_label_iou),
    }
    if cluster is not None:
        row.update(
            points_score=cluster.score,
            size_score=cluster.size_score,
            shape_score=cluster.shape_score,
            density_score=cluster.density_score,
            free_space_score=cluster.free_space_score,
            free_rays=cluster.free_rays,
            end_rays=cluster.end_rays,
            ground_z=cluster.ground_z,
        )
    return row

"""The KITTI object devkit's matching rules (``evaluate_object.cpp``), for any overlap measure.

What the devkit does, and what this module reproduces step for step (docs/eval.md lists each
rule with the test that checks it):

* **Difficulty filter** (``cleanData``). A ground-truth box of the evaluated class is *ignored*
  (neither TP nor FN, but it may absorb a detection) when its occlusion or truncation exceeds the
  level's maximum or its 2D box is not *taller* than the level's minimum height; a box of the
  *neighbouring* class (Van for Car, Person_sitting for Pedestrian) is always ignored; every other
  class is not part of the evaluation. A detection lower than the minimum height is ignored —
  whatever its class, a quirk of the devkit kept on purpose —, else it counts when of the class.
* **Recall thresholds** (``getThresholds``): pass 1 matches each GT (in file order) to the
  highest-scoring unassigned detection over the minimum overlap; the scores of the true positives
  are sampled at 41 recall steps (0, 1/40, …, 1), which gives up to 41 score thresholds.
* **Precision per threshold** (``computeStatistics``): pass 2, for each threshold, ignores the
  detections scoring below it and matches each GT to the unassigned detection of *largest
  overlap* (an ignored detection only when no counted one overlaps enough). Matches to ignored
  GTs or by ignored detections are neither TP nor FP; unmatched counted detections are FP unless
  their overlap with a DontCare region, relative to their own size, exceeds the minimum overlap.
* Overlaps are strictly greater than the minimum (``overlap > MIN_OVERLAP``).

Waymo has no 2D boxes: its difficulty levels come from the labels (:func:`waymo_ignored_gt`) and
there are no neighbouring classes or DontCare regions; the procedure is otherwise the same.

The passes run compiled over all frames of a (class, difficulty, overlap, threshold) cell at once;
frames are concatenated and addressed through offset arrays. This module owns the rules, never
files or the overlap measures themselves.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.kernels import kernel

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

__all__ = [
    "Cell",
    "FrameBlocks",
    "OUTCOMES",
    "first_pass",
    "kitti_ignored_det",
    "kitti_ignored_gt",
    "recall_thresholds",
    "second_pass",
    "assign",
    "waymo_ignored_gt",
]

NO_DETECTION = -10000000.0  # the devkit's "no candidate" marker (a score below it is never a candidate)

OUTCOMES = ("fp", "tp", "ignored", "dontcare", "not_evaluated")
"""Per-detection outcome codes of :func:`assign`: 0 false positive, 1 true positive, 2 matched to an
ignored GT (or an ignored detection that matched), 3 inside a DontCare region, 4 not part of the
cell (another class, below the minimum height, or scoring below the threshold)."""


def _lower(names: Sequence[str]) -> NDArray[np.object_]:
    return np.array([str(n).lower() for n in names], dtype=object)


def kitti_ignored_gt(
    class_names: Sequence[str],
    height: FloatArray,
    occluded: NDArray[np.integer],
    truncated: FloatArray,
    current: str,
    difficulty: int,
) -> NDArray[np.int8]:
    """The devkit's ``ignored_gt`` of one frame's (or many frames') GT boxes.

    Parameters
    ----------
    class_names : K class names (compared case-insensitively, like ``strcasecmp``)
    height : (K,) 2D box height in pixels (bottom − top)
    occluded : (K,) occlusion level
    truncated : (K,) truncation
    current : the evaluated class
    difficulty : 0 Easy, 1 Moderate, 2 Hard

    Returns
    -------
    (K,) int8: 0 counted, 1 ignored (neighbouring class, or too hard for the level), −1 not evaluated
    """
    names = _lower(class_names)
    cur = current.lower()
    neighbours = {n.lower() for n in C.EVAL_NEIGHBOUR_CLASSES.get(_canonical(current), ())}
    valid = (
        np.where(names == cur, 1, np.where(np.isin(names, list(neighbours)), 0, -1)) if len(names) else np.zeros(0, int)
    )
    h = np.asarray(height, dtype=float)
    hard = (
        (np.asarray(occluded) > C.KITTI_MAX_OCCLUSION[difficulty])
        | (np.asarray(truncated, dtype=float) > C.KITTI_MAX_TRUNCATION[difficulty])
        | (h <= C.KITTI_MIN_HEIGHT[difficulty])
    )
    out = np.full(len(names), -1, dtype=np.int8)
    out[(valid == 1) & ~hard] = 0
    out[(valid == 0) | ((valid == 1) & hard)] = 1
    return out


def kitti_ignored_det(
    class_names: Sequence[str], height: FloatArray, current: str, difficulty: int
) -> NDArray[np.int8]:
    """The devkit's ``ignored_det``: 1 when lower than the level's minimum height (any class), 0 when
    of the evaluated class, −1 otherwise. The devkit truncates the height to an integer first; for
    the integer minimum heights that gives the same comparison."""
    names = _lower(class_names)
    h = np.trunc(np.abs(np.asarray(height, dtype=float)))
    out = np.where(names == current.lower(), 0, -1).astype(np.int8) if len(names) else np.zeros(0, np.int8)
    out[h < C.KITTI_MIN_HEIGHT[difficulty]] = 1
    return out


def waymo_ignored_gt(
    class_names: Sequence[str],
    level: NDArray[np.integer],
    num_points: NDArray[np.integer],
    current: str,
    difficulty: int,
) -> NDArray[np.int8]:
    """``ignored_gt`` for Waymo: ``difficulty`` 0 = LEVEL_1 (LEVEL_2 boxes ignored), 1 = LEVEL_2 (all
    counted); boxes without any LiDAR point are ignored at both levels (Waymo drops them)."""
    names = _lower(class_names)
    out = np.where(names == current.lower(), 0, -1).astype(np.int8) if len(names) else np.zeros(0, np.int8)
    own = out == 0
    too_hard = np.asarray(level) > difficulty + 1
    out[own & (too_hard | (np.asarray(num_points) == 0))] = 1
    return out


def _canonical(name: str) -> str:
    for key in C.EVAL_NEIGHBOUR_CLASSES:
        if key.lower() == name.lower():
            return key
    return name


@dataclass
class FrameBlocks:
    """Frames concatenated: GT rows, detections and their per-frame overlap blocks.

    Attributes
    ----------
    gt_off : (F+1,) GT rows of frame f are ``gt_off[f]:gt_off[f+1]`` (file order)
    det_off : (F+1,) detections of frame f
    ov_off : (F+1,) frame f's overlaps start at ``ov_off[f]``: a (D_f, K_f) row-major block
    dc_off : (F+1,) DontCare regions of frame f (their count)
    dcov_off : (F+1,) frame f's detection × DontCare block (D_f, M_f), overlap over the detection
    dcov : flat detection × DontCare overlaps
    """

    gt_off: IntArray
    det_off: IntArray
    ov_off: IntArray
    dc_off: IntArray
    dcov_off: IntArray
    dcov: FloatArray

    @classmethod
    def build(
        cls, gt_counts: Sequence[int], det_counts: Sequence[int], dc_counts: Sequence[int], dcov: FloatArray
    ) -> "FrameBlocks":
        g = np.asarray(gt_counts, dtype=np.int64)
        d = np.asarray(det_counts, dtype=np.int64)
        m = np.asarray(dc_counts, dtype=np.int64)
        cum = lambda x: np.concatenate([[0], np.cumsum(x)]).astype(np.int64)  # noqa: E731
        return cls(cum(g), cum(d), cum(g * d), cum(m), cum(d * m), np.ascontiguousarray(dcov, dtype=np.float64))

    @property
    def num_frames(self) -> int:
        return len(self.gt_off) - 1


@dataclass
class Cell:
    """The rows one (class, difficulty) cell needs, with their own frame blocks.

    GT rows and detections that the cell never looks at (``ignored == -1``) are dropped, so the
    compiled passes loop over the relevant pairs only. ``pairs`` indexes the full overlap array
    (``ov[cell.pairs]`` is the cell's), ``gt_rows`` / ``det_rows`` map back to the full rows.
    """

    blocks: FrameBlocks
    pairs: IntArray
    gt_rows: IntArray
    det_rows: IntArray
    gt_ign: NDArray[np.int8]
    det_ign: NDArray[np.int8]

    @classmethod
    def build(cls, blocks: FrameBlocks, gt_ign: NDArray[np.int8], det_ign: NDArray[np.int8]) -> "Cell":
        gt_keep = np.asarray(gt_ign) != -1
        det_keep = np.asarray(det_ign) != -1
        nf = blocks.num_frames
        ng, nd, nm = np.diff(blocks.gt_off), np.diff(blocks.det_off), np.diff(blocks.dc_off)
        # per-pair frame, local det and GT index of the detection-major blocks
        sizes = ng * nd
        f = np.repeat(np.arange(nf), sizes)
        local = np.arange(int(sizes.sum())) - np.repeat(blocks.ov_off[:-1], sizes)
        ngf = np.maximum(ng[f], 1)
        j = blocks.det_off[:-1][f] + local // ngf
        i = blocks.gt_off[:-1][f] + local % ngf
        pairs = np.flatnonzero(det_keep[j] & gt_keep[i]) if len(f) else np.zeros(0, np.int64)
        dsizes = nd * nm
        fd = np.repeat(np.arange(nf), dsizes)
        dlocal = np.arange(int(dsizes.sum())) - np.repeat(blocks.dcov_off[:-1], dsizes)
        nmf = np.maximum(nm[fd], 1)
        dj = blocks.det_off[:-1][fd] + dlocal // nmf
        dc_pairs = np.flatnonzero(det_keep[dj]) if len(fd) else np.zeros(0, np.int64)
        gt_rows, det_rows = np.flatnonzero(gt_keep), np.flatnonzero(det_keep)
        cg = np.concatenate([[0], np.cumsum(gt_keep)])
        cd = np.concatenate([[0], np.cumsum(det_keep)])
        g_count = cg[blocks.gt_off[1:]] - cg[blocks.gt_off[:-1]]
        d_count = cd[blocks.det_off[1:]] - cd[blocks.det_off[:-1]]
        sub = FrameBlocks.build(g_count, d_count, nm, blocks.dcov[dc_pairs])
        return cls(
            sub, pairs.astype(np.int64), gt_rows, det_rows, np.asarray(gt_ign)[gt_rows], np.asarray(det_ign)[det_rows]
        )


@kernel
def _first_pass(gt_off, det_off, ov_off, ov, gt_ign, det_ign, score, min_ov):  # pragma: no cover - compiled
    nf = gt_off.shape[0] - 1
    v = np.empty(gt_ign.shape[0])
    nv = 0
    n_gt = 0
    for f in range(nf):
        g0, g1, d0, d1 = gt_off[f], gt_off[f + 1], det_off[f], det_off[f + 1]
        nd, ng = d1 - d0, g1 - g0
        assigned = np.zeros(nd, dtype=np.bool_)
        base = ov_off[f]
        for i in range(ng):
            gi = gt_ign[g0 + i]
            if gi == 0:
                n_gt += 1
            if gi == -1:
                continue
            det_idx = -1
            valid = NO_DETECTION
            for j in range(nd):
                dj = det_ign[d0 + j]
                if dj == -1 or assigned[j]:
                    continue
                o = ov[base + j * ng + i]
                if o > min_ov and score[d0 + j] > valid:
                    det_idx = j
                    valid = score[d0 + j]
            if valid == NO_DETECTION:
                continue
            if gi == 1 or det_ign[d0 + det_idx] == 1:
                assigned[det_idx] = True
            else:
                v[nv] = score[d0 + det_idx]
                nv += 1
                assigned[det_idx] = True
    return v[:nv], n_gt


@kernel
def _thresholds(v_desc, n_gt, n_points):  # pragma: no cover - compiled
    out = np.empty(v_desc.shape[0])
    m = 0
    current = 0.0
    n = v_desc.shape[0]
    for i in range(n):
        l_recall = (i + 1) / n_gt
        r_recall = (i + 2) / n_gt if i < n - 1 else l_recall
        if (r_recall - current) < (current - l_recall) and i < n - 1:
            continue
        out[m] = v_desc[i]
        m += 1
        current += 1.0 / (n_points - 1.0)
    return out[:m]


@kernel
def _match_frame(
    f,
    gt_off,
    det_off,
    ov_off,
    ov,
    dc_off,
    dcov_off,
    dcov,
    gt_ign,
    det_ign,
    score,
    min_ov,
    thresh,
    assigned,
    matched,
    dc_hit,
):  # pragma: no cover - compiled
    """Pass 2 on frame f at one score threshold; fills assigned/matched/dc_hit (length D_f); returns tp, fp, fn."""
    g0, g1, d0, d1 = gt_off[f], gt_off[f + 1], det_off[f], det_off[f + 1]
    nd, ng = d1 - d0, g1 - g0
    base = ov_off[f]
    tp = fp = fn = 0
    for j in range(nd):
        assigned[j] = False
        matched[j] = -1
        dc_hit[j] = False
    for i in range(ng):
        gi = gt_ign[g0 + i]
        if gi == -1:
            continue
        det_idx = -1
        valid = NO_DETECTION
        max_ov = 0.0
        assigned_ignored = False
        for j in range(nd):
            dj = det_ign[d0 + j]
            if dj == -1 or assigned[j] or score[d0 + j] < thresh:
                continue
            o = ov[base + j * ng + i]
            if o > min_ov and (o > max_ov or assigned_ignored) and dj == 0:
                max_ov = o
                det_idx = j
                valid = 1.0
                assigned_ignored = False
            elif o > min_ov and valid == NO_DETECTION and dj == 1:
                det_idx = j
                valid = 1.0
                assigned_ignored = True
        if valid == NO_DETECTION:
            if gi == 0:
                fn += 1
        elif gi == 1 or det_ign[d0 + det_idx] == 1:
            assigned[det_idx] = True
            matched[det_idx] = g0 + i
        else:
            tp += 1
            assigned[det_idx] = True
            matched[det_idx] = g0 + i
    for j in range(nd):
        dj = det_ign[d0 + j]
        if not (assigned[j] or dj == -1 or dj == 1 or score[d0 + j] < thresh):
            fp += 1
    m0, m1 = dc_off[f], dc_off[f + 1]
    nm = m1 - m0
    dbase = dcov_off[f]
    nstuff = 0
    for m in range(nm):
        for j in range(nd):
            dj = det_ign[d0 + j]
            if assigned[j] or dj == -1 or dj == 1 or score[d0 + j] < thresh:
                continue
            if dcov[dbase + j * nm + m] > min_ov:
                assigned[j] = True
                dc_hit[j] = True
                nstuff += 1
    return tp, fp - nstuff, fn


@kernel
def _frame_buffers(det_off):  # pragma: no cover - compiled
    """The per-frame work arrays of :func:`_match_frame` (assigned, matched, DontCare hit), sized for
    the frame with the most detections and reused frame after frame."""
    maxd = 0
    for f in range(det_off.shape[0] - 1):
        maxd = max(maxd, det_off[f + 1] - det_off[f])
    return np.zeros(maxd, dtype=np.bool_), np.zeros(maxd, dtype=np.int64), np.zeros(maxd, dtype=np.bool_)


@kernel
def _second_pass(
    gt_off, det_off, ov_off, ov, dc_off, dcov_off, dcov, gt_ign, det_ign, score, min_ov, thresholds
):  # pragma: no cover - compiled
    nt = thresholds.shape[0]
    nf = gt_off.shape[0] - 1
    tp = np.zeros(nt, dtype=np.int64)
    fp = np.zeros(nt, dtype=np.int64)
    fn = np.zeros(nt, dtype=np.int64)
    assigned, matched, dc_hit = _frame_buffers(det_off)
    for f in range(nf):
        if gt_off[f + 1] == gt_off[f] and det_off[f + 1] == det_off[f]:
            continue
        for t in range(nt):
            a, b, c = _match_frame(
                f,
                gt_off,
                det_off,
                ov_off,
                ov,
                dc_off,
                dcov_off,
                dcov,
                gt_ign,
                det_ign,
                score,
                min_ov,
                thresholds[t],
                assigned,
                matched,
                dc_hit,
            )
            tp[t] += a
            fp[t] += b
            fn[t] += c
    return tp, fp, fn


@kernel
def _assign(
    gt_off, det_off, ov_off, ov, dc_off, dcov_off, dcov, gt_ign, det_ign, score, min_ov, thresh
):  # pragma: no cover - compiled
    nf = gt_off.shape[0] - 1
    nd_all = det_ign.shape[0]
    outcome = np.full(nd_all, 4, dtype=np.int8)
    matched_all = np.full(nd_all, -1, dtype=np.int64)
    assigned, matched, dc_hit = _frame_buffers(det_off)
    for f in range(nf):
        _match_frame(
            f,
            gt_off,
            det_off,
            ov_off,
            ov,
            dc_off,
            dcov_off,
            dcov,
            gt_ign,
            det_ign,
            score,
            min_ov,
            thresh,
            assigned,
            matched,
            dc_hit,
        )
        d0 = det_off[f]
        for j in range(det_off[f + 1] - d0):
            dj = det_ign[d0 + j]
            matched_all[d0 + j] = matched[j]
            if dj == -1 or score[d0 + j] < thresh:
                continue
            if matched[j] >= 0:
                outcome[d0 + j] = 1 if (dj == 0 and gt_ign[matched[j]] == 0) else 2
            elif dc_hit[j]:
                outcome[d0 + j] = 3
            elif dj == 1:
                continue
            else:
                outcome[d0 + j] = 0
    return outcome, matched_all


def _c(a: np.ndarray, dtype: type) -> np.ndarray:
    return np.ascontiguousarray(a, dtype=dtype)


def first_pass(
    blocks: FrameBlocks,
    ov: FloatArray,
    gt_ign: NDArray[np.int8],
    det_ign: NDArray[np.int8],
    score: FloatArray,
    min_overlap: float,
) -> tuple[FloatArray, int]:
    """Pass 1: scores of the true positives (highest-scoring candidate per GT) and the number of counted GTs."""
    v, n_gt = _first_pass(
        blocks.gt_off,
        blocks.det_off,
        blocks.ov_off,
        _c(ov, np.float64),
        _c(gt_ign, np.int8),
        _c(det_ign, np.int8),
        _c(score, np.float64),
        float(min_overlap),
    )
    return v, int(n_gt)


def recall_thresholds(tp_scores: FloatArray, n_gt: int, n_points: int = C.EVAL_RECALL_POINTS) -> FloatArray:
    """The devkit's ``getThresholds``: score thresholds sampling recall at ``n_points`` steps.

    The scores are sorted in descending order; score i stands for recall (i+1)/n_gt and is kept
    when it approximates the next recall step (0, 1/(n−1), 2/(n−1), …) better than score i+1.
    With fewer than ``n_points − 1`` GT boxes each true positive becomes one step, so the recall
    axis is sampled by *index*, not by recall — the devkit's AP of a tiny set is then not 100
    even for perfect detections (docs/eval.md).
    """
    if n_gt <= 0 or len(tp_scores) == 0:
        return np.zeros(0)
    v = np.sort(np.asarray(tp_scores, dtype=float))[::-1].copy()
    return _thresholds(v, int(n_gt), float(n_points))


def second_pass(
    blocks: FrameBlocks,
    ov: FloatArray,
    gt_ign: NDArray[np.int8],
    det_ign: NDArray[np.int8],
    score: FloatArray,
    min_overlap: float,
    thresholds: FloatArray,
) -> tuple[IntArray, IntArray, IntArray]:
    """Pass 2: TP, FP, FN summed over frames at each score threshold, each (T,)."""
    if len(thresholds) == 0:
        z = np.zeros(0, dtype=np.int64)
        return z, z, z
    return _second_pass(
        blocks.gt_off,
        blocks.det_off,
        blocks.ov_off,
        _c(ov, np.float64),
        blocks.dc_off,
        blocks.dcov_off,
        blocks.dcov,
        _c(gt_ign, np.int8),
        _c(det_ign, np.int8),
        _c(score, np.float64),
        float(min_overlap),
        _c(thresholds, np.float64),
    )


def assign(
    blocks: FrameBlocks,
    ov: FloatArray,
    gt_ign: NDArray[np.int8],
    det_ign: NDArray[np.int8],
    score: FloatArray,
    min_overlap: float,
    thresh: float = -np.inf,
) -> tuple[NDArray[np.int8], IntArray]:
    """Pass 2 at one score threshold, per detection: outcome code (:data:`OUTCOMES`) and matched GT row (−1 none).

    The matched GT is given for true positives and for matches that do not count (ignored GT or
    ignored detection); the index is into the concatenated GT rows.
    """
    return _assign(
        blocks.gt_off,
        blocks.det_off,
        blocks.ov_off,
        _c(ov, np.float64),
        blocks.dc_off,
        blocks.dcov_off,
        blocks.dcov,
        _c(gt_ign, np.int8),
        _c(det_ign, np.int8),
        _c(score, np.float64),
        float(min_overlap),
        float(thresh),
    )

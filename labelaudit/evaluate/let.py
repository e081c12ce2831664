"""Waymo's longitudinal-error-tolerant AP: LET-3D-AP and LET-3D-APL (``labelaudit eval --let``).

A camera sees the direction of an object well and its depth badly. LET (Hung et al., "Let-3D-AP",
2022; Waymo's camera-only 3D detection challenge) forgives a detection its error *along the line
of sight* up to a tolerance, and APL then charges what was forgiven:

* ranges are measured from the camera, at c (KITTI: the image_2 camera's centre from the frame's
  calibration; Waymo: (1.43, 0, 2.18) m in the vehicle frame; Argoverse 2: ring_front_center);
  G and P are the GT and prediction centres relative to c, r = max(|G|, ε);
* longitudinal error e = |G·P / r − r| (the prediction's range projected on the GT's direction),
  tolerance τ = max(0.1·r, 0.5 m), affinity a = clamp(1 − e/τ, 0, 1); 0 between classes;
* the prediction is moved along its own line of sight to the point nearest the GT,
  P' = (G·P / |P|²)·P (size and heading kept), and LET-IoU is the 3D IoU of that box with the GT;
* a pair may match when a > 0 and LET-IoU ≥ 0.5 (vehicles) or 0.3 (pedestrians, cyclists); per
  frame and score cut-off, the Hungarian algorithm picks the matching of largest Σ LET-IoU·a
  (weights quantised to 10⁻⁶ as Waymo's matcher does);
* at each cut-off 0, 0.01, …, 1 (detections scoring at least the cut-off): precision TP/(TP+FP),
  APL's precision Σa/(TP+FP) over the true positives, recall TP/(TP+FN); AP integrates the
  curve as Waymo's ``ComputeMeanAveragePrecision`` (:func:`waymo_average_precision`).

Waymo's rules hold for every format: a detection matched to a GT box that does not count at the
difficulty (Waymo LEVEL_2 in LEVEL_1, a KITTI box harder than the level) is a true positive, an
unmatched such box is not a false negative; there are no DontCare regions, neighbouring classes or
2D-height filters. Boxes are the dataset's LiDAR/vehicle-frame boxes (3D IoU with heights on z).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from labelaudit import constants as C
from labelaudit.evaluate.cells import LET_INTERP, LET_METRICS
from labelaudit.evaluate.overlap import pair_overlaps

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

__all__ = [
    "LetCurve",
    "camera_centre",
    "let_curves",
    "let_min_iou",
    "let_origins",
    "let_records",
    "longitudinal_affinity",
    "range_aligned_centres",
    "score_cutoffs",
    "waymo_average_precision",
]


def camera_centre(calib: Any) -> FloatArray:
    """Centre of KITTI's image_2 camera in the LiDAR frame, (3,).

    P2 = K·[R | t] maps rectified camera coordinates to the image; its centre is the null vector of
    P2, −M⁻¹·p₄ with M = P2[:, :3], taken back to the LiDAR frame with the calibration.
    """
    P2 = np.asarray(calib.P2, dtype=float)
    c_rect = -np.linalg.solve(P2[:, :3], P2[:, 3])
    T = calib.T_velo_cam
    return T[:3, :3] @ c_rect + T[:3, 3]


def let_origins(dataset_format: str, calibs: Sequence[Any]) -> FloatArray:
    """The camera position LET measures range from, per frame, (F, 3) in the LiDAR/vehicle frame.

    Raises
    ------
    ValueError
        A KITTI frame without calibration, or a format without a known camera.
    """
    n = len(calibs)
    if dataset_format == "kitti":
        out = np.empty((n, 3))
        for f, calib in enumerate(calibs):
            if calib is None:
                raise ValueError(f"KITTI frame {f} has no calibration: LET needs its camera position")
            out[f] = camera_centre(calib)
        return out
    if dataset_format.startswith("waymo"):
        return np.tile(np.asarray(C.EVAL_LET_WAYMO_CAMERA, dtype=float), (n, 1))
    if dataset_format == "av2":
        return np.tile(np.asarray(C.EVAL_LET_AV2_CAMERA, dtype=float), (n, 1))
    raise ValueError(f"LET: no camera position known for dataset format {dataset_format!r}")


def let_min_iou(class_name: str) -> float:
    """LET-IoU a match needs: 0.5 for vehicles, 0.3 for every other class (case-insensitive)."""
    for k, v in C.EVAL_LET_MIN_IOU.items():
        if k.lower() == class_name.lower():
            return float(v)
    return float(C.EVAL_LET_DEFAULT_MIN_IOU)


def score_cutoffs() -> FloatArray:
    """0, 0.01, …, 1 (:data:`~labelaudit.constants.EVAL_LET_SCORE_CUTOFFS` values)."""
    return np.round(np.linspace(0.0, 1.0, C.EVAL_LET_SCORE_CUTOFFS), 10)


def longitudinal_affinity(G: ArrayLike, P: ArrayLike) -> FloatArray:
    """a = clamp(1 − |G·P/r − r| / max(0.1·r, 0.5 m), 0, 1) with r = max(|G|, ε), shape (n,).

    Parameters
    ----------
    G, P : (n, 3) GT and prediction centres relative to the camera
    """
    g = np.asarray(G, dtype=float).reshape(-1, 3)
    p = np.asarray(P, dtype=float).reshape(-1, 3)
    r = np.maximum(np.linalg.norm(g, axis=1), C.EVAL_LET_EPSILON)
    err = np.abs(np.einsum("ij,ij->i", g, p) / r - r)
    tol = np.maximum(C.EVAL_LET_TOLERANCE_FRACTION * r, C.EVAL_LET_MIN_TOLERANCE)
    return np.clip(1.0 - err / tol, 0.0, 1.0)


def range_aligned_centres(G: ArrayLike, P: ArrayLike) -> FloatArray:
    """P' = (G·P / max(|P|², ε))·P: the point of the prediction's line of sight nearest the GT centre, (n, 3).

    Relative to the camera, like ``G`` and ``P``. A negative factor (G and P on opposite sides of the
    camera) is kept, as Waymo keeps it.
    """
    g = np.asarray(G, dtype=float).reshape(-1, 3)
    p = np.asarray(P, dtype=float).reshape(-1, 3)
    k = np.einsum("ij,ij->i", g, p) / np.maximum(np.einsum("ij,ij->i", p, p), C.EVAL_LET_EPSILON)
    return k[:, None] * p


def waymo_average_precision(
    precision: ArrayLike, recall: ArrayLike, recall_delta: float = C.EVAL_LET_RECALL_DELTA
) -> float:
    """Area under a PR curve as Waymo's metrics integrate it (a fraction in [0, 1]).

    Each recall keeps its largest precision (recall 0 starts at precision 1); walking from the
    highest recall down, precision becomes the running maximum, and wherever two recalls are more
    than ``recall_delta`` apart points are inserted every ``recall_delta`` (at the running maximum);
    the point at recall 0 takes the precision of the point before it; trapezoids sum the area.
    """
    p = np.asarray(precision, dtype=float).reshape(-1)
    r = np.asarray(recall, dtype=float).reshape(-1)
    if len(p) != len(r):
        raise ValueError(f"precision and recall differ in length: {len(p)} vs {len(r)}")
    if not len(p):
        return 0.0
    best: dict[float, float] = {0.0: 1.0}
    for pi, ri in zip(p.tolist(), r.tolist()):
        best[ri] = max(best.get(ri, 0.0), pi)
    keys = sorted(best)
    pts: list[tuple[float, float]] = []  # (precision, recall), recall descending
    last = keys[0]
    run = 0.0
    for rk in reversed(keys):
        while last - rk > recall_delta + 1e-6:
            last -= recall_delta
            pts.append((run, last))
        run = max(best[rk], run)
        pts.append((run, rk))
        last = rk
    if len(pts) >= 2:
        pts[-1] = (pts[-2][0], pts[-1][1])
    return float(sum(0.5 * (pts[i - 1][1] - pts[i][1]) * (pts[i - 1][0] + pts[i][0]) for i in range(1, len(pts))))


@dataclass(frozen=True)
class LetCurve:
    """Counts and PR points of one (class, difficulty) at every score cut-off.

    Attributes
    ----------
    cutoffs : (K,) score cut-offs
    tp, fp, fn : (K,) counts
    sum_affinity : (K,) Σ a over the true positives
    num_gt : GT boxes that count at the difficulty
    num_det : detections of the class
    threshold : the LET-IoU a match needed
    """

    cutoffs: FloatArray
    tp: IntArray
    fp: IntArray
    fn: IntArray
    sum_affinity: FloatArray
    num_gt: int
    num_det: int
    threshold: float

    @property
    def recall(self) -> FloatArray:
        d = self.tp + self.fn
        return np.where(d > 0, self.tp / np.maximum(d, 1), 0.0)

    def precision(self, longitudinal: bool = False) -> FloatArray:
        """TP/(TP+FP), or Σa/(TP+FP) for APL; 0 without detections, 1 where recall is 0 (Waymo's convention)."""
        d = self.tp + self.fp
        num = self.sum_affinity if longitudinal else self.tp.astype(float)
        p = np.where(d > 0, num / np.maximum(d, 1), 0.0)
        return np.where(self.recall == 0.0, 1.0, p)

    @property
    def ap(self) -> float:
        """LET-3D-AP in percent."""
        return 100.0 * waymo_average_precision(self.precision(False), self.recall)

    @property
    def apl(self) -> float:
        """LET-3D-APL in percent."""
        return 100.0 * waymo_average_precision(self.precision(True), self.recall)


def _frame_matches(
    w: IntArray, ok: NDArray[np.bool_], det_scores: FloatArray, cutoffs: FloatArray
) -> tuple[IntArray, IntArray]:
    """One frame: for each score cut-off, the Hungarian matching of the detections scoring at least it.

    Parameters
    ----------
    w : (D, G) quantised weights LET-IoU·a (0 where the pair may not match)
    ok : (D, G) pairs that may match
    det_scores : (D,)
    cutoffs : (K,) ascending

    Returns
    -------
    subset_of_cutoff : (K,) index into the distinct matchings (detection sets are nested, so one
        per number of detections kept)
    matches : (S, D) matched GT column of each detection per distinct matching (−1 none)
    """
    from scipy.optimize import linear_sum_assignment

    kept = det_scores[None, :] >= cutoffs[:, None]  # (K, D)
    counts = kept.sum(axis=1)
    distinct, subset_of_cutoff = np.unique(counts, return_inverse=True)
    matches = np.full((len(distinct), len(det_scores)), -1, dtype=np.int64)
    for s, n in enumerate(distinct):
        if n == 0:
            continue
        rows = np.flatnonzero(kept[int(np.argmax(counts == n))])
        ri, ci = linear_sum_assignment(w[rows], maximize=True)
        good = ok[rows[ri], ci]
        matches[s, rows[ri[good]]] = ci[good]
    return subset_of_cutoff, matches


def _offsets(counts: IntArray) -> IntArray:
    return np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)


def let_curves(
    gt_boxes: FloatArray,
    gt_frame: IntArray,
    gt_class: Sequence[str],
    gt_counted: NDArray[np.bool_],
    gt_in_pool: NDArray[np.bool_],
    det_boxes: FloatArray,
    det_frame: IntArray,
    det_class: Sequence[str],
    det_scores: FloatArray,
    origins: FloatArray,
    classes: Sequence[str],
) -> dict[tuple[str, int], LetCurve]:
    """LET counts at every score cut-off for each class and difficulty.

    Parameters
    ----------
    gt_boxes : (N, 7) GT boxes (LiDAR/vehicle frame); gt_frame : (N,) their frame
    gt_class : N class names
    gt_counted : (L, N) whether each GT counts (may be a false negative) at each of L difficulties
    gt_in_pool : (N,) GTs that take part in the matching at all (Waymo drops boxes without points)
    det_boxes : (M, 7), det_frame : (M,), det_class : M names, det_scores : (M,)
    origins : (F, 3) camera position per frame (:func:`let_origins`)
    classes : evaluated classes (compared case-insensitively)

    Returns
    -------
    (class, difficulty index) → :class:`LetCurve`
    """
    gt_boxes = np.asarray(gt_boxes, dtype=float).reshape(-1, 7)
    det_boxes = np.asarray(det_boxes, dtype=float).reshape(-1, 7)
    gt_frame = np.asarray(gt_frame, dtype=np.int64)
    det_frame = np.asarray(det_frame, dtype=np.int64)
    det_scores = np.asarray(det_scores, dtype=float)
    counted = np.asarray(gt_counted, dtype=bool).reshape(-1, len(gt_boxes))
    n_levels = counted.shape[0]
    gcls = np.array([c.lower() for c in gt_class], dtype=object)
    dcls = np.array([c.lower() for c in det_class], dtype=object)
    cuts = score_cutoffs()
    out: dict[tuple[str, int], LetCurve] = {}
    n_frames = len(origins)
    for cls in classes:
        thr = let_min_iou(cls)
        gi = (
            np.flatnonzero((gcls == cls.lower()) & np.asarray(gt_in_pool, dtype=bool))
            if len(gcls)
            else np.zeros(0, np.int64)
        )
        di = np.flatnonzero(dcls == cls.lower()) if len(dcls) else np.zeros(0, np.int64)
        gi = gi[np.argsort(gt_frame[gi], kind="stable")]  # frame by frame
        di = di[np.argsort(det_frame[di], kind="stable")]
        tp = np.zeros(len(cuts), np.int64)
        sum_a = np.zeros(len(cuts))
        matched_counted = np.zeros((n_levels, len(cuts)), np.int64)
        # every (detection, GT) pair of a frame: frame f's block is (D_f, G_f) row-major
        nd = np.bincount(det_frame[di], minlength=n_frames)
        ng = np.bincount(gt_frame[gi], minlength=n_frames)
        d_off, g_off = _offsets(nd), _offsets(ng)
        p_off = _offsets(nd * ng)
        f_of = np.repeat(np.arange(n_frames), nd * ng)
        local = np.arange(int(p_off[-1])) - p_off[f_of]
        pd_ = d_off[f_of] + local // np.maximum(ng[f_of], 1)  # positions in di
        pg_ = g_off[f_of] + local % np.maximum(ng[f_of], 1)  # positions in gi
        if len(pd_):
            o = origins[f_of]
            G = gt_boxes[gi[pg_], :3] - o
            P = det_boxes[di[pd_], :3] - o
            aff = longitudinal_affinity(G, P)
            aligned = det_boxes[di[pd_]].copy()
            aligned[:, :3] = o + range_aligned_centres(G, P)
            idx = np.arange(len(pd_))
            _, let_iou, _ = pair_overlaps(aligned, gt_boxes[gi[pg_]], idx, idx, "3d")
            ok = (aff > 0.0) & (let_iou >= thr)
            weight = np.where(ok, np.round(let_iou * aff * C.EVAL_LET_WEIGHT_SCALE), 0).astype(np.int64)
            for f in np.unique(f_of[ok]):
                block = slice(p_off[f], p_off[f + 1])
                OK = ok[block].reshape(nd[f], ng[f])
                keep = np.flatnonzero(
                    OK.any(axis=1)
                )  # a detection without a possible match is a false positive at every cut-off
                OK = OK[keep]
                W = weight[block].reshape(nd[f], ng[f])[keep]
                A = aff[block].reshape(nd[f], ng[f])[keep]
                subset_of_cut, matches = _frame_matches(W, OK, det_scores[di[d_off[f] + keep]], cuts)
                for s in range(matches.shape[0]):
                    hit = np.flatnonzero(matches[s] >= 0)
                    if not len(hit):
                        continue
                    cols = matches[s, hit]
                    at = subset_of_cut == s
                    tp[at] += len(hit)
                    sum_a[at] += float(A[hit, cols].sum())
                    matched_counted[:, at] += counted[:, gi[g_off[f] + cols]].sum(axis=1)[:, None]
        n_kept = (det_scores[di][None, :] >= cuts[:, None]).sum(axis=1) if len(di) else np.zeros(len(cuts), np.int64)
        fp = n_kept - tp
        for lvl in range(n_levels):
            n_gt = int(counted[lvl, gi].sum())
            out[(cls, lvl)] = LetCurve(
                cuts,
                tp.copy(),
                fp.astype(np.int64),
                (n_gt - matched_counted[lvl]).astype(np.int64),
                sum_a.copy(),
                n_gt,
                int(len(di)),
                thr,
            )
    return out


def let_records(curves: dict[tuple[str, int], LetCurve], difficulties: Sequence[str]) -> list[dict[str, Any]]:
    """The ``ap`` records of LET: metric ``let`` (LET-3D-AP) and ``let_apl`` (LET-3D-APL), interp ``waymo``."""
    out: list[dict[str, Any]] = []
    for (cls, lvl), c in curves.items():
        for metric in LET_METRICS:
            ap: float | None = c.ap if metric == "let" else c.apl
            note = None
            if c.num_gt == 0:
                ap, note = None, "no ground truth of this class at this difficulty"
            elif c.num_det == 0:
                note = "no detections of this class: AP 0"
            out.append(
                {
                    "class": cls,
                    "difficulty": difficulties[lvl],
                    "view": "3d",
                    "metric": metric,
                    "threshold": c.threshold,
                    "interp": LET_INTERP,
                    "ap": None if ap is None else round(float(ap), 4),
                    "num_gt": c.num_gt,
                    "num_det": c.num_det,
                    "max_recall": round(float(c.recall[0]), 6),
                    "note": note,
                }
            )
    return out

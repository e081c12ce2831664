"""``labelaudit eval`` end to end: labels + detections + label uncertainty → AP tables, overlaps, EVAL_DIR.

Steps (docs/eval.md): read the GT labels (:mod:`~labelaudit.datasets.gt`) and the detections
(:mod:`~labelaudit.datasets.detections`); get the labels' posterior covariances from an ``infer``
results folder, or infer them (:mod:`~labelaudit.evaluate.labels`); compute, once per
(detection, GT) pair of a frame, the IoU (BEV or 3D, :mod:`~labelaudit.evaluate.overlap`) and,
for the pairs whose distributions can touch, the JIoU (:mod:`~labelaudit.evaluate.jiou`); then
run the devkit's matching (:mod:`~labelaudit.evaluate.matching`) for every class × difficulty ×
metric × threshold cell and turn its counts into AP (:mod:`~labelaudit.evaluate.ap`). The result
is one JSON-able summary (what ``--format json`` prints and ``EVAL_DIR/summary.json`` holds), a
per-detection Arrow table and the PR curves. No printing here: the CLI shows the summary.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pyarrow as pa
from numpy.typing import NDArray

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit.config import RunConfig
from labelaudit.datasets.detections import Detections, read_detections
from labelaudit.datasets.gt import GroundTruth, load_ground_truth
from labelaudit.errors import EvalError
from labelaudit.evaluate.ap import PrecisionCurve, precision_curve
from labelaudit.evaluate.cells import DIFFICULTIES, INTERPS, LET_METRICS, METRICS, family, usual_threshold
from labelaudit.evaluate.jiou import pair_jious
from labelaudit.evaluate.labels import LabelSet, check_results_match, infer_labels, label_uncertainty, needed_rows
from labelaudit.evaluate.let import let_curves, let_min_iou, let_origins, let_records
from labelaudit.evaluate.matching import (
    OUTCOMES,
    Cell,
    FrameBlocks,
    assign,
    first_pass,
    kitti_ignored_det,
    kitti_ignored_gt,
    recall_thresholds,
    second_pass,
    waymo_ignored_gt,
)
from labelaudit.evaluate.overlap import kitti_devkit_boxes, pair_overlaps

FloatArray = NDArray[np.float64]

__all__ = ["DIFFICULTIES", "METRICS", "EvalRequest", "EvalResult", "evaluate", "run_eval", "usual_threshold"]

HEADLINE_DIFFICULTY = {"kitti": "moderate", "waymo": "level_2", "av2": "all"}
SUMMARY_VERSION = "1"


def thresholds_for(class_name: str) -> list[float]:
    """Every threshold evaluated for a class: 0.5:0.05:0.9 and its usual one."""
    ts = sorted({round(float(t), 4) for t in (*C.EVAL_MAP_THRESHOLDS, usual_threshold(class_name))})
    return ts


def distance_bins() -> list[tuple[str, float, float]]:
    """(name, lo, hi) of the distance bins, e.g. ("0-20", 0, 20), …, ("40+", 40, inf)."""
    edges = [0.0, *C.EVAL_DISTANCE_BINS, math.inf]
    out = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        out.append((f"{lo:g}-{hi:g}" if math.isfinite(hi) else f"{lo:g}+", lo, hi))
    return out


# --------------------------------------------------------------------------- request / result


@dataclass(frozen=True)
class EvalRequest:
    """The options of ``labelaudit eval``.

    Attributes
    ----------
    dataset : labelled dataset (as ``infer`` reads it)
    detections : detections file or folder
    results : an ``infer`` results folder with the labels' covariances (None: infer them)
    output : EVAL_DIR (None: nothing written; inferred labels then go to a temporary folder)
    dataset_format : "auto", "kitti", "waymo-v2", "waymo-v1", "av2"
    detections_format : "auto", "kitti", "waymo", "parquet", "av2"
    classes : classes to evaluate (None: the format's classes that are detected at least once)
    view : "bev" or "3d"
    config : model config TOML (None: the built-in one of the format)
    split, limit : frame selection, as for ``infer``
    workers : processes for the JIoU pairs and the label inference
    strict : a bad detection line or label file stops the run (else the frame is left out, recorded)
    let : add Waymo's LET-3D-AP and LET-3D-APL records (:mod:`~labelaudit.evaluate.let`)
    """

    dataset: Path
    detections: Path
    results: Path | None = None
    output: Path | None = None
    dataset_format: str = "auto"
    detections_format: str = "auto"
    classes: tuple[str, ...] | None = None
    view: str = "bev"
    config: Path | None = None
    split: str | None = None
    limit: int | None = None
    workers: int | None = None
    strict: bool = True
    debug: bool = False
    let: bool = False


@dataclass
class EvalResult:
    """What an evaluation produced.

    Attributes
    ----------
    summary : the JSON document (``--format json``, ``EVAL_DIR/summary.json``)
    detections_table : one row per detection (``EVAL_DIR/detections.parquet``)
    curves : (class, difficulty, metric, threshold) → :class:`PrecisionCurve`
    timings : seconds per stage
    """

    summary: dict[str, Any]
    detections_table: pa.Table
    curves: dict[tuple[str, str, str, float], PrecisionCurve]
    timings: dict[str, float] = field(default_factory=dict)


class Progress:
    """Receives stage messages and pair counts (the CLI shows them on stderr); default silent."""

    def stage(self, message: str) -> None:
        pass

    def pairs(self, done: int, total: int) -> None:
        pass

    def infer_progress(self) -> Any:
        return None


# --------------------------------------------------------------------------- geometry of the pairs


def frame_pairs(a_off: NDArray[np.int64], b_off: NDArray[np.int64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """All (a, b) pairs within each frame, a-major: frame f's block is (A_f, B_f) row-major."""
    na, nb = np.diff(a_off), np.diff(b_off)
    sizes = na * nb
    total = int(sizes.sum())
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    f = np.repeat(np.arange(len(na)), sizes)
    start = np.concatenate([[0], np.cumsum(sizes)])[:-1]
    local = np.arange(total) - start[f]
    nbf = nb[f]
    return a_off[:-1][f] + local // nbf, b_off[:-1][f] + local % nbf


def corner_std(cov: FloatArray, model: str) -> FloatArray:
    """Largest BEV corner std (m) of φ covariances (N, p, p); 0 for NaN rows."""
    from labelaudit.core.posterior import corner_variances

    n = len(cov)
    out = np.zeros(n)
    ok = ~np.isnan(cov).any(axis=(1, 2)) if n else np.zeros(0, bool)
    if not ok.any():
        return out
    c = cov[ok]
    if model == "3d":
        keep = [0, 1, 3, 4, 5, 6]
        c = c[:, keep][:, :, keep]
    tv = corner_variances(c, "bev")
    out[ok] = np.sqrt(np.clip(tv.max(axis=1), 0.0, None))
    return out


def box_cov_corner_std(cov: FloatArray, boxes: FloatArray) -> FloatArray:
    """Approximate largest corner std (m) of box-parameter covariances (N, k, k), k = 5 or 7; 0 for NaN rows."""
    n = len(cov)
    out = np.zeros(n)
    if not n:
        return out
    ok = ~np.isnan(cov).any(axis=(1, 2))
    k = cov.shape[1]
    idx = {"cx": 0, "cy": 1, "l": 2, "w": 3, "yaw": 4} if k == 5 else {"cx": 0, "cy": 1, "l": 3, "w": 4, "yaw": 6}
    var = lambda name: cov[:, idx[name], idx[name]]  # noqa: E731
    half_diag2 = (boxes[:, 3] ** 2 + boxes[:, 4] ** 2) / 4.0
    tv = var("cx") + var("cy") + var("l") / 4 + var("w") / 4 + half_diag2 * var("yaw")
    out[ok] = np.sqrt(np.clip(tv[ok], 0.0, None))
    return out


# --------------------------------------------------------------------------- main entry


def run_eval(request: EvalRequest, progress: Progress | None = None) -> EvalResult:
    """Evaluate detections against a labelled dataset (``labelaudit eval``).

    Raises
    ------
    EvalError
        Bad options, results that do not fit the dataset, nothing to evaluate.
    DatasetError
        Unreadable labels or (``strict``) a bad detection line; the message names file, line, field.
    """
    from labelaudit.config import resolve_config
    from labelaudit.datasets import DatasetError, resolve_format

    progress = progress or Progress()
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    if request.view not in ("bev", "3d"):
        raise EvalError(f"--metric: expected bev or 3d, got {request.view!r}")
    try:
        fmt = resolve_format(Path(request.dataset), request.dataset_format)
    except DatasetError as exc:
        raise EvalError(str(exc)) from None
    fam = family(fmt)

    progress.stage(f"reading labels of {request.dataset} ({fmt})")
    try:
        gt = load_ground_truth(request.dataset, fmt, split=request.split, limit=request.limit, strict=request.strict)
    except TypeError as exc:
        raise EvalError(f"{request.dataset}: option not supported by the {fmt} reader ({exc})") from None
    if gt.num_frames == 0:
        raise EvalError(
            f"{request.dataset}: no frames to evaluate (format {fmt}{', split ' + request.split if request.split else ''})"
        )
    progress.stage(f"reading detections {request.detections}")
    dets = read_detections(request.detections, gt, request.detections_format, strict=request.strict, view=request.view)
    failed = {e["frame_id"] for e in dets.errors if e.get("frame_id")}
    if failed:
        gt, dets = _drop_frames(gt, dets, failed)
    timings["read"] = time.perf_counter() - t0

    classes = _classes(request.classes, fam, dets, gt)
    try:
        cfg = resolve_config(request.config, fmt, None, request.view)
    except ValueError as exc:
        raise EvalError(str(exc)) from None

    t1 = time.perf_counter()
    needed = needed_rows(gt, classes)
    labels = _labels(request, gt, fmt, cfg, classes, needed, progress)
    timings["labels"] = time.perf_counter() - t1

    result = evaluate(
        gt,
        dets,
        labels,
        classes,
        request.view,
        cfg,
        workers=request.workers,
        progress=progress,
        timings=timings,
        let=request.let,
    )
    result.summary["dataset"] = {
        "path": str(Path(request.dataset).resolve()),
        "format": fmt,
        "split": request.split,
        "limit": request.limit,
    }
    result.summary["detections_source"] = {"path": str(Path(request.detections).resolve()), "format": dets.format}
    timings["total"] = time.perf_counter() - t0
    result.summary["timings"] = {k: round(v, 3) for k, v in timings.items()}
    return result


def _classes(requested: Sequence[str] | None, fam: str, dets: Detections, gt: GroundTruth) -> tuple[str, ...]:
    if requested:
        return tuple(requested)
    detected = {n.lower() for n in dets.class_names}
    chosen = tuple(c for c in C.EVAL_CLASSES[fam] if c.lower() in detected)
    if not chosen:
        found = sorted(set(dets.class_names))
        what = f"detections of {', '.join(found)}" if found else "no detections at all"
        raise EvalError(
            f"nothing to evaluate: the devkit evaluates a class only when it is detected at least once, and the detections hold {what} "
            f"(evaluated classes: {', '.join(C.EVAL_CLASSES[fam])}); pass --classes to evaluate others"
        )
    return chosen


def _drop_frames(gt: GroundTruth, dets: Detections, frames: set[str]) -> tuple[GroundTruth, Detections]:
    keep = [i for i, f in enumerate(gt.frame_ids) if f not in frames]
    return _subset_gt(gt, keep), _subset_dets(dets, keep)


def _rows(off: NDArray[np.int64], keep: Sequence[int]) -> NDArray[np.int64]:
    return (
        np.concatenate([np.arange(off[i], off[i + 1]) for i in keep]).astype(np.int64)
        if keep
        else np.zeros(0, np.int64)
    )


def _offsets(off: NDArray[np.int64], keep: Sequence[int]) -> NDArray[np.int64]:
    return np.concatenate([[0], np.cumsum(np.diff(off)[list(keep)])]).astype(np.int64)


def _subset_gt(gt: GroundTruth, keep: Sequence[int]) -> GroundTruth:
    r, dc = _rows(gt.gt_off, keep), _rows(gt.dc_off, keep)
    return replace(
        gt,
        frame_ids=[gt.frame_ids[i] for i in keep],
        gt_off=_offsets(gt.gt_off, keep),
        boxes=gt.boxes[r],
        class_names=[gt.class_names[i] for i in r],
        object_index=gt.object_index[r],
        height=gt.height[r],
        occluded=gt.occluded[r],
        truncated=gt.truncated[r],
        difficulty=gt.difficulty[r],
        num_points=gt.num_points[r],
        distance=gt.distance[r],
        dc_off=_offsets(gt.dc_off, keep),
        dontcare=gt.dontcare[dc],
        calibs=[gt.calibs[i] for i in keep],
        sources=[gt.sources[i] for i in keep],
    )


def _subset_dets(d: Detections, keep: Sequence[int]) -> Detections:
    r = _rows(d.det_off, keep)
    return replace(
        d,
        det_off=_offsets(d.det_off, keep),
        boxes=d.boxes[r],
        class_names=[d.class_names[i] for i in r],
        scores=d.scores[r],
        height=d.height[r],
        cov=None if d.cov is None else d.cov[r],
        has_cov=d.has_cov[r],
        source=[d.source[i] for i in r],
    )


def _labels(
    request: EvalRequest,
    gt: GroundTruth,
    fmt: str,
    cfg: RunConfig,
    classes: Sequence[str],
    needed: NDArray[np.bool_],
    progress: Progress,
) -> LabelSet:
    from labelaudit.results import open_results

    if request.results is not None:
        results = open_results(request.results)
        check_results_match(results, Path(request.dataset), fmt, cfg)
        return label_uncertainty(results, gt, needed, request.view, "results")
    infer_classes = tuple(sorted({gt.class_names[i] for i in np.flatnonzero(needed)} | set(classes)))
    cfg_inf = cfg.with_overrides(classes=infer_classes)
    if request.output is not None:
        folder = Path(request.output) / "label-results"
        tmp = None
    else:
        import tempfile

        tmp = tempfile.TemporaryDirectory(prefix="labelaudit-eval-labels-")
        folder = Path(tmp.name) / "label-results"
    progress.stage(
        f"no --results: inferring the label uncertainty of {int(needed.sum())} GT boxes (classes {', '.join(infer_classes)}; "
        f"{'built-in config' if request.config is None else request.config}, model {request.view}) into {folder}"
    )
    try:
        results = infer_labels(
            Path(request.dataset),
            fmt,
            cfg_inf,
            folder,
            split=request.split,
            limit=request.limit,
            workers=request.workers,
            progress=progress.infer_progress(),
            debug=request.debug,
        )
        labels = label_uncertainty(results, gt, needed, request.view, "inferred")
    finally:
        if tmp is not None:
            tmp.cleanup()
    if tmp is not None:
        labels.path = Path("(temporary)")
    return labels


# --------------------------------------------------------------------------- the evaluation proper


def _ignored(
    gt: GroundTruth, dets: Detections, fam: str, cls: str, d: int
) -> tuple[NDArray[np.int8], NDArray[np.int8]]:
    if fam == "kitti":
        return (
            kitti_ignored_gt(gt.class_names, gt.height, gt.occluded, gt.truncated, cls, d),
            kitti_ignored_det(dets.class_names, dets.height, cls, d),
        )
    gi = waymo_ignored_gt(gt.class_names, gt.difficulty, gt.num_points, cls, d)
    di = np.array([0 if n.lower() == cls.lower() else -1 for n in dets.class_names], dtype=np.int8)
    return gi, di


def _counted_at(gt: GroundTruth, fam: str, d: int) -> NDArray[np.bool_]:
    """GT rows that count (are not ignored) at difficulty d, whatever their class."""
    if fam == "kitti":
        return (gt.difficulty >= 0) & (gt.difficulty <= d)
    return (gt.difficulty <= d + 1) & (gt.num_points != 0)


@dataclass
class PairOverlaps:
    """Every (detection, GT) pair of a frame, detection-major blocks, with the devkit's frame blocks.

    Attributes
    ----------
    pd, pg : (P,) detection and GT row of each pair
    iou : (P,) IoU in the view (KITTI: the devkit's camera-frame geometry)
    blocks : the frames' blocks (GT, detections, DontCare overlaps over the detection)
    """

    pd: NDArray[np.int64]
    pg: NDArray[np.int64]
    iou: FloatArray
    blocks: FrameBlocks


def overlap_geometry(gt: GroundTruth, dets: Detections) -> tuple[FloatArray, FloatArray, FloatArray]:
    """GT, detection and DontCare boxes as the overlaps are taken on them.

    KITTI: the devkit's geometry (rectangles in the rectified camera's x–z plane, heights along
    camera y; :func:`~labelaudit.evaluate.overlap.kitti_devkit_boxes`). Every other format: the
    LiDAR/vehicle-frame boxes themselves (Waymo's own 3D IoU).
    """
    if gt.dataset_format != "kitti":
        return gt.boxes, dets.boxes, gt.dontcare
    dc_frame = np.repeat(np.arange(gt.num_frames), np.diff(gt.dc_off))
    try:
        return (
            kitti_devkit_boxes(gt.boxes, gt.frame_of_row, gt.calibs),
            kitti_devkit_boxes(dets.boxes, dets.frame_of_row, gt.calibs),
            kitti_devkit_boxes(gt.dontcare, dc_frame, gt.calibs),
        )
    except ValueError as exc:
        raise EvalError(f"KITTI overlaps are taken in the camera frame, as the devkit does: {exc}") from None


def pair_ious(gt: GroundTruth, dets: Detections, view: str) -> PairOverlaps:
    """IoU of every (detection, GT) pair of a frame and the detections' overlap with DontCare regions."""
    gt_boxes, det_boxes, dc_boxes = overlap_geometry(gt, dets)
    pd, pg = frame_pairs(dets.det_off, gt.gt_off)
    _, iou, _ = pair_overlaps(det_boxes, gt_boxes, pd, pg, view)
    dd, dm = frame_pairs(dets.det_off, gt.dc_off)
    _, _, dc_over = pair_overlaps(det_boxes, dc_boxes, dd, dm, view)
    blocks = FrameBlocks.build(np.diff(gt.gt_off), np.diff(dets.det_off), np.diff(gt.dc_off), dc_over)
    return PairOverlaps(pd, pg, iou, blocks)


def jiou_overlaps(
    gt: GroundTruth,
    dets: Detections,
    labels: LabelSet,
    classes: Sequence[str],
    view: str,
    cfg: RunConfig,
    pairs: PairOverlaps,
    metrics: Sequence[str],
    workers: int | None,
    progress: Progress,
) -> tuple[dict[str, FloatArray], int]:
    """The overlap of every pair under each metric (``jiou_deterministic`` added for probabilistic
    detections), and the number of pairs whose JIoU was computed.

    JIoU is computed only for pairs whose distributions can touch (boxes grown by ``support_std``
    corner stds intersect) and that some evaluated cell looks at; every other pair has JIoU 0.
    """
    pd, pg, iou = pairs.pd, pairs.pg, pairs.iou
    with_jiou = len(metrics) > 1
    fam = family(gt.dataset_format)
    grow_gt = cfg.spatial.support_std * corner_std(labels.cov, view)
    grow_det = np.zeros(dets.num)
    if dets.cov is not None:
        grow_det = cfg.spatial.support_std * (
            corner_std(dets.cov, view) if dets.cov_on == "phi" else box_cov_corner_std(dets.cov, dets.boxes)
        )
    wanted = np.isin([n.lower() for n in dets.class_names], [c.lower() for c in classes])
    if fam == "kitti":  # a detection lower than the minimum height is ignored, not dropped: it may absorb a GT
        wanted = wanted | (np.trunc(np.abs(dets.height)) < max(C.KITTI_MIN_HEIGHT))
    det_relevant = np.asarray(wanted, dtype=bool).reshape(-1)
    use = labels.needed[pg] & det_relevant[pd] if (len(pd) and with_jiou) else np.zeros(len(pd), bool)
    inter_grown, _, _ = pair_overlaps(dets.boxes, gt.boxes, pd[use], pg[use], "bev", grow_a=grow_det, grow_b=grow_gt)
    cand = np.flatnonzero(use)[inter_grown > 0]

    def candidate_jious(deterministic: bool) -> NDArray[np.float64]:
        """JIoU of every pair (0 outside the candidates); ``deterministic``: the detections taken as certain."""
        out = np.zeros(len(pd))
        # two certain boxes: JIoU is the IoU handed in (the devkit's, for KITTI)
        out[cand] = pair_jious(
            view,
            cfg.spatial,
            gt.boxes,
            labels.cov,
            dets.boxes,
            dets.cov,
            dets.cov_on,
            pg[cand],
            pd[cand],
            iou[cand],
            deterministic=deterministic,
            workers=workers,
            progress=progress.pairs,
        )
        return out

    if with_jiou:
        progress.stage(f"JIoU of {len(cand)} candidate (detection, label) pairs")
    jiou = candidate_jious(deterministic=False)
    jgt = labels.jiou_gt[pg] if len(pg) else np.zeros(0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(jgt > 0, jiou / jgt, 0.0)
    overlaps = {m: {"iou": iou, "jiou": jiou, "jiou_ratio": ratio}[m] for m in metrics}
    if dets.probabilistic and with_jiou:
        overlaps["jiou_deterministic"] = candidate_jious(deterministic=True)
    return overlaps, len(cand)


def ap_cells(
    gt: GroundTruth,
    dets: Detections,
    classes: Sequence[str],
    view: str,
    blocks: FrameBlocks,
    overlaps: dict[str, FloatArray],
) -> tuple[list[dict[str, Any]], dict[tuple[str, str, str, float], PrecisionCurve], dict[tuple[str, int], Cell]]:
    """The devkit's two passes for every class × difficulty × metric × threshold cell: AP records
    (R40 and R11), the PR curves and each (class, difficulty)'s :class:`Cell`."""
    fam = family(gt.dataset_format)
    ap_records: list[dict[str, Any]] = []
    curves: dict[tuple[str, str, str, float], PrecisionCurve] = {}
    cells: dict[tuple[str, int], Cell] = {}
    for cls in classes:
        for d, dname in enumerate(DIFFICULTIES[fam]):
            gi, di = _ignored(gt, dets, fam, cls, d)
            cell = cells[(cls, d)] = Cell.build(blocks, gi, di)  # only the rows this cell looks at
            scores = dets.scores[cell.det_rows]
            num_det = int(np.count_nonzero(di == 0))
            for metric, ov in overlaps.items():
                ovc = ov[cell.pairs]
                for t in thresholds_for(cls):
                    v, n_gt = first_pass(cell.blocks, ovc, cell.gt_ign, cell.det_ign, scores, t)
                    ths = recall_thresholds(v, n_gt)
                    tp, fp, fn = second_pass(cell.blocks, ovc, cell.gt_ign, cell.det_ign, scores, t, ths)
                    curve = precision_curve(tp, fp, fn, ths)
                    curves[(cls, dname, metric, t)] = curve
                    for interp in INTERPS:
                        ap_records.append(_ap_record(cls, dname, view, metric, t, interp, curve, n_gt, num_det))
    return ap_records, curves, cells


def associate(
    gt: GroundTruth, dets: Detections, classes: Sequence[str], pairs: PairOverlaps
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Which GT row each detection localises (−1 none) and the index of that pair.

    The devkit's matching at :data:`~labelaudit.constants.EVAL_ASSOCIATION_MIN_IOU`, where every GT
    of the class or a neighbouring class may take the detection.
    """
    matched_gt = np.full(dets.num, -1, dtype=np.int64)
    matched_pair = np.full(dets.num, -1, dtype=np.int64)
    gt_lower = np.array([n.lower() for n in gt.class_names], dtype=object)
    det_lower = np.array([n.lower() for n in dets.class_names], dtype=object)
    for cls in classes:
        own = [
            cls.lower(),
            *(n.lower() for k, nb in C.EVAL_NEIGHBOUR_CLASSES.items() if k.lower() == cls.lower() for n in nb),
        ]
        gi = np.where(np.isin(gt_lower, own), 0, -1).astype(np.int8)
        di = np.where(det_lower == cls.lower(), 0, -1).astype(np.int8)
        cell = Cell.build(pairs.blocks, gi, di)
        _, m = assign(
            cell.blocks,
            pairs.iou[cell.pairs],
            cell.gt_ign,
            cell.det_ign,
            dets.scores[cell.det_rows],
            C.EVAL_ASSOCIATION_MIN_IOU,
        )
        hit = m >= 0
        matched_gt[cell.det_rows[hit]] = cell.gt_rows[m[hit]]
    if dets.num:
        fr = dets.frame_of_row
        has = matched_gt >= 0
        j_local = np.arange(dets.num) - dets.det_off[fr]
        g_local = matched_gt - gt.gt_off[fr]
        ng = np.diff(gt.gt_off)[fr]
        matched_pair[has] = pairs.blocks.ov_off[fr[has]] + j_local[has] * ng[has] + g_local[has]
    return matched_gt, matched_pair


def outcomes_at_usual_threshold(
    dets: Detections,
    classes: Sequence[str],
    difficulties: Sequence[str],
    cells: dict[tuple[str, int], Cell],
    overlaps: dict[str, FloatArray],
) -> dict[str, NDArray[np.int8]]:
    """Per detection, its outcome code (:data:`OUTCOMES`) under each metric and difficulty at its class's usual threshold."""
    det_lower = np.array([n.lower() for n in dets.class_names], dtype=object)
    outcomes: dict[str, NDArray[np.int8]] = {}
    for metric in (m for m in overlaps if m in METRICS):
        for d, dname in enumerate(difficulties):
            col = np.full(dets.num, 4, dtype=np.int8)
            for cls in classes:
                cell = cells[(cls, d)]
                oc, _ = assign(
                    cell.blocks,
                    overlaps[metric][cell.pairs],
                    cell.gt_ign,
                    cell.det_ign,
                    dets.scores[cell.det_rows],
                    usual_threshold(cls),
                )
                own = det_lower[cell.det_rows] == cls.lower()
                col[cell.det_rows[own]] = oc[own]
            outcomes[f"outcome_{metric}_{dname}"] = col
    return outcomes


def evaluate(
    gt: GroundTruth,
    dets: Detections,
    labels: LabelSet,
    classes: Sequence[str],
    view: str,
    cfg: RunConfig,
    *,
    workers: int | None = None,
    progress: Progress | None = None,
    timings: dict[str, float] | None = None,
    metrics: Sequence[str] = METRICS,
    let: bool = False,
) -> EvalResult:
    """The evaluation on data already in memory (the library entry point behind :func:`run_eval`).

    Parameters
    ----------
    gt, dets : aligned frames (same order)
    labels : per GT row covariance and JIoU-GT (rows not needed may be NaN)
    classes : evaluated classes
    view : "bev" or "3d"
    cfg : run configuration (its ``spatial`` parameters define p_G)
    metrics : overlaps to evaluate; ``("iou",)`` skips JIoU altogether (a plain devkit run)
    let : add LET-3D-AP / LET-3D-APL records (metrics ``let`` and ``let_apl``)
    """
    progress = progress or Progress()
    timings = timings if timings is not None else {}
    unknown = set(metrics) - set(METRICS)
    if unknown or "iou" not in metrics:
        raise ValueError(f"metrics must include 'iou' and be among {METRICS}, got {tuple(metrics)}")
    fam = family(gt.dataset_format)
    difficulties = DIFFICULTIES[fam]

    t0 = time.perf_counter()
    pairs = pair_ious(gt, dets, view)
    timings["iou"] = time.perf_counter() - t0

    t1 = time.perf_counter()
    overlaps, n_cand = jiou_overlaps(gt, dets, labels, classes, view, cfg, pairs, metrics, workers, progress)
    timings["jiou"] = time.perf_counter() - t1
    timings["jiou_pairs"] = float(n_cand)

    t2 = time.perf_counter()
    progress.stage(
        f"matching: {len(classes)} classes × {len(difficulties)} difficulties × {len(overlaps)} metrics × {len(C.EVAL_MAP_THRESHOLDS)}+ thresholds"
    )
    ap_records, curves, cells = ap_cells(gt, dets, classes, view, pairs.blocks, overlaps)
    timings["matching"] = time.perf_counter() - t2
    if let:
        t_let = time.perf_counter()
        progress.stage(
            f"LET-3D-AP: Hungarian matching of {len(classes)} classes at {C.EVAL_LET_SCORE_CUTOFFS} score cut-offs"
        )
        ap_records += let_ap_records(gt, dets, classes)
        timings["let"] = time.perf_counter() - t_let

    t3 = time.perf_counter()
    matched_gt, matched_pair = associate(gt, dets, classes, pairs)
    outcomes = outcomes_at_usual_threshold(dets, classes, difficulties, cells, overlaps)
    mean_records = _mean_overlaps(gt, dets, fam, classes, difficulties, overlaps, matched_gt, matched_pair)
    timings["association"] = time.perf_counter() - t3

    table = _detections_table(gt, dets, labels, overlaps, matched_gt, matched_pair, outcomes, difficulties)
    summary = _summary(gt, dets, labels, classes, view, cfg, ap_records, mean_records, curves, fam, n_cand)
    if let:
        summary["metric"]["let"] = let_parameters(gt, classes)
        outside = int(np.count_nonzero((dets.scores < 0.0) | (dets.scores > 1.0)))
        if outside:
            summary["notes"].append(
                f"{outside} detections score outside [0, 1]: LET's score cut-offs are 0, 0.01, …, 1, so scores above 1 count at every cut-off "
                "and negative ones at none; rescale such scores to probabilities for a meaningful LET-3D-AP"
            )
    return EvalResult(summary, table, curves, timings)


def let_ap_records(gt: GroundTruth, dets: Detections, classes: Sequence[str]) -> list[dict[str, Any]]:
    """LET-3D-AP and LET-3D-APL records of every class × difficulty (:mod:`~labelaudit.evaluate.let`).

    A GT box counts (may be a false negative) at a difficulty as in the devkit cells; Waymo and
    Argoverse 2 boxes without any LiDAR point take no part, as in Waymo's metrics.
    """
    fam = family(gt.dataset_format)
    try:
        origins = let_origins(gt.dataset_format, gt.calibs)
    except ValueError as exc:
        raise EvalError(f"--let: {exc}") from None
    counted = (
        np.stack([_counted_at(gt, fam, d) for d in range(len(DIFFICULTIES[fam]))])
        if len(gt.boxes)
        else np.zeros((len(DIFFICULTIES[fam]), 0), bool)
    )
    in_pool = gt.num_points != 0 if fam in ("waymo", "av2") else np.ones(len(gt.boxes), bool)
    curves = let_curves(
        gt.boxes,
        gt.frame_of_row,
        gt.class_names,
        counted,
        in_pool,
        dets.boxes,
        dets.frame_of_row,
        dets.class_names,
        dets.scores,
        origins,
        classes,
    )
    return let_records(curves, DIFFICULTIES[fam])


def let_parameters(gt: GroundTruth, classes: Sequence[str]) -> dict[str, Any]:
    """What the LET records were computed with (``summary.metric.let``)."""
    fam = family(gt.dataset_format)
    camera = {
        "kitti": "image_2 camera centre from each frame's calibration (P2)",
        "waymo": list(C.EVAL_LET_WAYMO_CAMERA),
        "av2": list(C.EVAL_LET_AV2_CAMERA),
    }[fam]
    return {
        "camera": camera,
        "tolerance_fraction": C.EVAL_LET_TOLERANCE_FRACTION,
        "min_tolerance_m": C.EVAL_LET_MIN_TOLERANCE,
        "min_let_iou": {c: let_min_iou(c) for c in classes},
        "score_cutoffs": C.EVAL_LET_SCORE_CUTOFFS,
        "recall_delta": C.EVAL_LET_RECALL_DELTA,
        "matching": "Hungarian, maximum sum of LET-IoU x affinity per frame and cut-off",
        "boxes": "LiDAR/vehicle frame, 3D IoU",
    }


def _ap_record(
    cls: str, dname: str, view: str, metric: str, t: float, interp: str, curve: PrecisionCurve, n_gt: int, num_det: int
) -> dict[str, Any]:
    note = None
    ap: float | None = curve.ap_r40 if interp == "R40" else curve.ap_r11
    if n_gt == 0:
        ap, note = None, "no ground truth of this class at this difficulty"
    elif num_det == 0:
        note = "no detections of this class at this difficulty: AP 0"
    elif n_gt < C.EVAL_RECALL_POINTS - 1:
        note = f"fewer than {C.EVAL_RECALL_POINTS - 1} GT boxes: the devkit samples recall by true positive, AP is coarse (docs/eval.md)"
    return {
        "class": cls,
        "difficulty": dname,
        "view": view,
        "metric": metric,
        "threshold": t,
        "interp": interp,
        "ap": None if ap is None else round(float(ap), 4),
        "num_gt": int(n_gt),
        "num_det": int(num_det),
        "max_recall": round(curve.max_recall, 6),
        "note": note,
    }


def _mean_overlaps(
    gt: GroundTruth,
    dets: Detections,
    fam: str,
    classes: Sequence[str],
    difficulties: Sequence[str],
    overlaps: dict[str, FloatArray],
    matched_gt: NDArray[np.int64],
    matched_pair: NDArray[np.int64],
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """Mean overlap of the matched detections per difficulty × distance bin × metric: pooled over the
    evaluated classes (one record per cell, the EVAL_DIR contract's ``mean_overlap``) and per class."""
    pooled: list[dict[str, Any]] = []
    by_class: list[dict[str, Any]] = []
    has = matched_gt >= 0
    bins = [("all", 0.0, math.inf), *distance_bins()]
    gcls = np.array([n.lower() for n in gt.class_names], dtype=object)
    metrics = [m for m in overlaps if m in METRICS]
    for d, dname in enumerate(difficulties):
        counted = _counted_at(gt, fam, d)
        dist_all = gt.distance[np.maximum(matched_gt, 0)] if len(gt.distance) else np.zeros(len(matched_gt))
        sel_any = np.zeros(len(matched_gt), bool)
        for scope in [*classes, None]:
            if scope is None:
                sel = sel_any
            else:
                sel = has.copy()
                sel[has] &= counted[matched_gt[has]] & (gcls[matched_gt[has]] == scope.lower())
                sel_any = sel_any | sel
            for bname, lo, hi in bins:
                in_bin = sel & (dist_all >= lo) & (dist_all < hi)
                for metric in metrics:
                    vals = overlaps[metric][matched_pair[in_bin]] if in_bin.any() else np.zeros(0)
                    rec = {
                        "class": "all" if scope is None else scope,
                        "difficulty": dname,
                        "distance_bin": bname,
                        "metric": metric,
                        "mean": None if not len(vals) else round(float(np.mean(vals)), 6),
                        "count": int(len(vals)),
                    }
                    (pooled if scope is None else by_class).append(rec)
    return pooled, by_class


def _detections_table(
    gt: GroundTruth,
    dets: Detections,
    labels: LabelSet,
    overlaps: dict[str, FloatArray],
    matched_gt: NDArray[np.int64],
    matched_pair: NDArray[np.int64],
    outcomes: dict[str, NDArray[np.int8]],
    difficulties: Sequence[str],
) -> pa.Table:
    n = dets.num
    fr = dets.frame_of_row
    has = matched_gt >= 0
    mg = np.maximum(matched_gt, 0)
    mp = np.maximum(matched_pair, 0)

    def masked(values: FloatArray) -> pa.Array:
        return pa.array(np.where(has, values, np.nan), pa.float64(), mask=~has)

    cols: dict[str, pa.Array] = {
        "frame_id": pa.array([gt.frame_ids[f] for f in fr], pa.string()),
        "det_index": pa.array(np.arange(n) - dets.det_off[fr] if n else np.zeros(0, np.int64), pa.int32()),
        "class_name": pa.array(dets.class_names, pa.string()),
        "score": pa.array(dets.scores, pa.float64()),
    }
    for k, name in enumerate(("cx", "cy", "cz", "length", "width", "height", "yaw")):
        cols[name] = pa.array(dets.boxes[:, k] if n else np.zeros(0), pa.float64())
    cols["probabilistic"] = pa.array(dets.has_cov, pa.bool_())
    cols["source"] = pa.array(dets.source, pa.string())
    cols["matched_object_index"] = pa.array(
        np.where(has, gt.object_index[mg] if len(gt.object_index) else 0, 0), pa.int32(), mask=~has
    )
    cols["matched_class"] = pa.array([gt.class_names[g] if h else None for g, h in zip(mg, has)], pa.string())
    diff_names = {"kitti": {-1: "none", 0: "easy", 1: "moderate", 2: "hard"}, "av2": {1: "all"}}.get(
        family(gt.dataset_format), {1: "level_1", 2: "level_2"}
    )
    cols["matched_difficulty"] = pa.array(
        [diff_names.get(int(gt.difficulty[g]), "none") if h else None for g, h in zip(mg, has)], pa.string()
    )
    cols["matched_distance"] = masked(gt.distance[mg] if len(gt.distance) else np.zeros(n))
    for name in ("iou", "jiou", "jiou_ratio"):
        if name in overlaps:
            cols[name] = masked(overlaps[name][mp] if len(overlaps[name]) else np.zeros(n))
    cols["jiou_gt"] = masked(labels.jiou_gt[mg] if len(labels.jiou_gt) else np.ones(n))
    if "jiou_deterministic" in overlaps:
        cols["jiou_deterministic"] = masked(overlaps["jiou_deterministic"][mp])
    for name, codes in outcomes.items():
        cols[name] = pa.array([OUTCOMES[int(c)] for c in codes], pa.string())
    return pa.table(cols)


def _summary(
    gt: GroundTruth,
    dets: Detections,
    labels: LabelSet,
    classes: Sequence[str],
    view: str,
    cfg: RunConfig,
    ap_all: list[dict[str, Any]],
    mean_records: tuple[list[dict[str, Any]], list[dict[str, Any]]],
    curves: dict[tuple[str, str, str, float], PrecisionCurve],
    fam: str,
    n_pairs: int,
) -> dict[str, Any]:
    difficulties = DIFFICULTIES[fam]
    # the contract's ``ap`` holds the three metrics (and LET with --let); the deterministic baseline of probabilistic
    # detections goes to ``probabilistic_ap`` (same records)
    ap_records = [r for r in ap_all if r["metric"] in METRICS + LET_METRICS]
    ap_baseline = [r for r in ap_all if r["metric"] not in METRICS + LET_METRICS]
    maps: list[dict[str, Any]] = []
    for cls in classes:
        for dname in difficulties:
            for metric in {r["metric"] for r in ap_all} - set(
                LET_METRICS
            ):  # LET has one threshold: no mean over thresholds
                for interp in INTERPS:
                    sel = [
                        r
                        for r in ap_all
                        if r["class"] == cls
                        and r["difficulty"] == dname
                        and r["metric"] == metric
                        and r["interp"] == interp
                        and any(abs(r["threshold"] - t) < 1e-9 for t in C.EVAL_MAP_THRESHOLDS)
                    ]
                    vals = [r["ap"] for r in sel]
                    maps.append(
                        {
                            "class": cls,
                            "difficulty": dname,
                            "view": view,
                            "metric": metric,
                            "interp": interp,
                            "map": None if any(v is None for v in vals) or not vals else round(float(np.mean(vals)), 4),
                            "thresholds": [float(t) for t in C.EVAL_MAP_THRESHOLDS],
                        }
                    )
    maps.sort(key=lambda r: (r["class"], r["difficulty"], r["metric"], r["interp"]))
    gt_counts = {c: int(sum(1 for n in gt.class_names if n.lower() == c.lower())) for c in classes}
    det_counts = {c: int(sum(1 for n in dets.class_names if n.lower() == c.lower())) for c in classes}
    counts = {
        "frames": gt.num_frames,
        "gt": int(len(gt.boxes)),
        "gt_by_class": gt_counts,
        "detections": int(dets.num),
        "detections_by_class": det_counts,
        "probabilistic_detections": int(dets.has_cov.sum()),
        "missing_detection_files": len(dets.frames_without_file) if dets.format == "kitti" else 0,
        "frames_without_detections": int(np.count_nonzero(np.diff(dets.det_off) == 0)),
        "unmatched_frames": len(dets.unknown_frames),
        "detections_in_unmatched_frames": int(sum(dets.unknown_frames.values())),
        "failed_frames": len(gt.errors) + len({e.get("frame_id") for e in dets.errors}),
        "dontcare_rows": gt.dontcare_rows,
        "dontcare_regions_3d": int(len(gt.dontcare)),
        "labels_used": int(labels.needed.sum()),
        "labels_without_covariance": labels.without_cov,
        "jiou_pairs": int(n_pairs),
    }
    notes = []
    if dets.format == "kitti" and dets.frames_without_file:
        shown = ", ".join(dets.frames_without_file[:5])
        notes.append(
            f"{len(dets.frames_without_file)} frames have no detection file (no detections, like the devkit): {shown}{' …' if len(dets.frames_without_file) > 5 else ''}"
        )
    if dets.unknown_frames:
        shown = ", ".join(list(dets.unknown_frames)[:5])
        notes.append(
            f"{len(dets.unknown_frames)} frames with {sum(dets.unknown_frames.values())} detections are not in the dataset and were not evaluated: {shown}{' …' if len(dets.unknown_frames) > 5 else ''}"
        )
    if labels.without_cov:
        notes.append(
            f"{labels.without_cov} GT boxes have no covariance in the label results (skipped or failed there) and count as certain labels (JIoU = IoU)"
        )
    if counts["failed_frames"]:
        notes.append(f"{counts['failed_frames']} frames could not be read and were left out (see 'errors')")
    for c in classes:
        if det_counts[c] == 0:
            notes.append(f"no detections of class {c}: its AP is 0 because nothing was detected")
        if gt_counts[c] == 0:
            notes.append(f"no ground truth of class {c}: its AP is undefined (null)")
    errors = [dict(e) for e in (gt.errors + dets.errors)]
    pr_curves = []
    headline = HEADLINE_DIFFICULTY[fam]
    for cls in classes:
        for metric in METRICS:
            curve = curves.get((cls, headline, metric, usual_threshold(cls)))  # absent metrics are skipped
            if curve is not None:
                pr_curves.append(
                    {
                        "class": cls,
                        "difficulty": headline,
                        "metric": metric,
                        "threshold": usual_threshold(cls),
                        "recall": [round(float(x), 6) for x in curve.recall],
                        "precision": [round(float(x), 6) for x in curve.raw_precision],
                        "interpolated_precision": [round(float(x), 6) for x in curve.precision],
                    }
                )
    prob = _probabilistic(ap_all, classes, difficulties, view) if ap_baseline else None
    return {
        "tool": "labelaudit",
        "tool_version": __version__,
        "summary_version": SUMMARY_VERSION,
        "metric": {
            "view": view,
            "metrics": list(dict.fromkeys(r["metric"] for r in ap_all)),
            "interp": list(INTERPS),
            "difficulties": list(difficulties),
            "headline_difficulty": headline,
            "map_thresholds": [float(t) for t in C.EVAL_MAP_THRESHOLDS],
            "usual_thresholds": {c: usual_threshold(c) for c in classes},
            "distance_bins": [b[0] for b in distance_bins()],
            "association_min_iou": C.EVAL_ASSOCIATION_MIN_IOU,
            "recall_points": C.EVAL_RECALL_POINTS,
            "spatial": {
                "cells_per_side": cfg.spatial.cells_per_side,
                "num_samples": cfg.spatial.num_samples,
                "support_std": cfg.spatial.support_std,
            },
        },
        "dataset": {
            "path": None,
            "format": gt.dataset_format,
            "split": None,
            "limit": None,
        },  # run_eval fills in the path
        "labels": {
            "source": labels.source,
            "path": str(labels.path),
            "param_hash": labels.param_hash,
            "model": labels.model,
        },
        "classes": list(classes),
        "ap": ap_records,
        "map": maps,
        "mean_overlap": mean_records[0],
        "mean_overlap_by_class": mean_records[1],
        "probabilistic": prob,
        "probabilistic_ap": ap_baseline or None,
        "pr_curves": pr_curves,
        "counts": counts,
        "notes": notes,
        "errors": errors,
    }


def _probabilistic(
    ap_records: list[dict[str, Any]], classes: Sequence[str], difficulties: Sequence[str], view: str
) -> list[dict[str, Any]]:
    """Recall (and AP) at each JIoU threshold with the detections' own distributions vs the same detections as deterministic boxes."""
    idx = {(r["class"], r["difficulty"], r["metric"], r["threshold"], r["interp"]): r for r in ap_records}
    out = []
    for cls in classes:
        for dname in difficulties:
            for t in thresholds_for(cls):
                p = idx.get((cls, dname, "jiou", t, "R40"))
                q = idx.get((cls, dname, "jiou_deterministic", t, "R40"))
                if p is None or q is None:
                    continue
                out.append(
                    {
                        "class": cls,
                        "difficulty": dname,
                        "view": view,
                        "threshold": t,
                        "recall_probabilistic": p["max_recall"],
                        "recall_deterministic": q["max_recall"],
                        "recall_gain": round(p["max_recall"] - q["max_recall"], 6),
                        "ap_probabilistic": p["ap"],
                        "ap_deterministic": q["ap"],
                    }
                )
    return out


def nothing_evaluated(summary: dict[str, Any]) -> bool:
    """True when no cell had a single counted GT box (the CLI then exits 2)."""
    return not any(r["num_gt"] > 0 for r in summary["ap"])

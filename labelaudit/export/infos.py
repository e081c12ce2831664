"""Targets into OpenPCDet (KITTI, Waymo) and mmdetection3d v2 (KITTI) infos structures, in the file's own object order.

Each infos frame is parsed into its objects' keys (the non-DontCare ordinal for KITTI, the laser
object id for Waymo), classes and sizes; :func:`align_frames` finds every object's result row and
refuses an infos file that describes other labels (another class or size, an object the infos
lack). :func:`attach_to_infos` then adds the std, covariance and validity of the targets.
"""

from __future__ import annotations

from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Literal, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from labelaudit import constants as C
from labelaudit.errors import ExportError, InfosMismatchError
from labelaudit.export.arrays import ResultArrays
from labelaudit.export.targets import INFOS_KEYS, ExportTargets

FloatArray = NDArray[np.float64]

__all__ = [
    "DONTCARE",
    "INFOS_META_KEY",
    "FrameObjects",
    "ResultIndex",
    "align_frames",
    "attach_to_infos",
    "detect_infos_format",
    "kitti_frame_id",
    "malformed",
    "openpcdet_frames",
]

INFOS_META_KEY = "label_uncertainty"
"""Key of the description (encoding, targets, source, tool) added to each OpenPCDet frame info and to mmdet3d ``metainfo``."""
DONTCARE = "DontCare"


@dataclass
class FrameObjects:
    """One frame of an infos file: its id, and per object (file order) the key, class and l/w/h."""

    frame_id: str
    keys: list[Any]  # results key per object, None for DontCare
    names: list[str]
    dims_lwh: FloatArray  # (K, 3), NaN where unknown


class ResultIndex:
    """Result rows by frame, then by object key (object_index for KITTI, object_id for Waymo)."""

    def __init__(self, arrays: ResultArrays, key: Literal["object_index", "object_id"]):
        self.by_frame: dict[str, dict[Any, int]] = {}
        keys = arrays.object_index.tolist() if key == "object_index" else arrays.object_id.tolist()
        for row, (fid, k) in enumerate(zip(arrays.frame_id.tolist(), keys)):
            self.by_frame.setdefault(fid, {})[k] = row
        self.key = key


def kitti_frame_id(value: Any) -> str:
    """KITTI frame id ``'000123'`` of an infos ``lidar_idx`` / ``image_idx`` (int or str)."""
    if isinstance(value, (int, np.integer)):
        return f"{int(value):06d}"
    return str(value)


def openpcdet_frames(infos: Any, path: str) -> tuple[str, list[FrameObjects]]:
    """Parse an OpenPCDet infos list: ('kitti' | 'waymo', frames)."""
    if not isinstance(infos, list):
        raise ExportError(f"{path}: an OpenPCDet infos file is a list of frame dicts, got {type(infos).__name__}")
    frames: list[FrameObjects] = []
    kinds = set()
    for i, info in enumerate(infos):
        where = f"{path}: frame entry {i}"
        with malformed(where):
            kind, frame = _openpcdet_frame(info, where)
        kinds.add(kind)
        if len(kinds) > 1:
            raise ExportError(f"{where}: mixes KITTI and Waymo frame entries")
        frames.append(frame)
    return (kinds.pop() if kinds else "kitti"), frames


@contextmanager
def malformed(where: str) -> Iterator[None]:
    """Turn a type/shape error while reading one infos entry into an ExportError naming it."""
    try:
        yield
    except ExportError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        raise ExportError(f"{where}: malformed entry ({type(exc).__name__}: {exc})") from None


def _openpcdet_frame(info: Any, where: str) -> tuple[str, FrameObjects]:
    if not isinstance(info, dict) or "point_cloud" not in info:
        raise ExportError(f"{where}: expected a dict with 'point_cloud' and 'annos' (OpenPCDet infos)")
    annos = info.get("annos")
    if not isinstance(annos, dict) or "name" not in annos:
        raise ExportError(
            f"{where}: no 'annos' with 'name' (a test-split infos file has no labels to attach targets to)"
        )
    names = [str(n) for n in np.asarray(annos["name"]).reshape(-1).tolist()]
    k = len(names)
    dims = np.asarray(annos.get("dimensions", np.full((k, 3), np.nan)), dtype=float).reshape(k, 3)
    pc_info = info["point_cloud"]
    if "lidar_sequence" in pc_info or "obj_ids" in annos:
        md = info.get("metadata") or {}
        if "context_name" not in md or "timestamp_micros" not in md:
            raise ExportError(
                f"{where}: Waymo infos need 'metadata' with context_name and timestamp_micros to find the frame"
            )
        if "obj_ids" not in annos:
            raise ExportError(f"{where}: Waymo 'annos' have no 'obj_ids' (laser object ids) to align objects by")
        keys: list[Any] = [str(x) for x in np.asarray(annos["obj_ids"]).reshape(-1).tolist()]
        if len(keys) != k:
            raise ExportError(f"{where}: 'obj_ids' has {len(keys)} entries, 'name' {k}")
        # Waymo 'dimensions' are l, w, h
        return "waymo", FrameObjects(f"{md['context_name']}:{int(md['timestamp_micros'])}", keys, names, dims)
    if "lidar_idx" not in pc_info:
        raise ExportError(f"{where}: 'point_cloud' has no 'lidar_idx' (the KITTI frame id)")
    not_dc = np.array([n != DONTCARE for n in names], dtype=bool)
    ordinal = np.cumsum(not_dc) - 1  # position among the non-DontCare rows = results object_index
    keys = [int(o) if nd else None for o, nd in zip(ordinal, not_dc)]
    # OpenPCDet KITTI 'dimensions' are l, h, w (camera order)
    return "kitti", FrameObjects(kitti_frame_id(pc_info["lidar_idx"]), keys, names, dims[:, [0, 2, 1]])


def _mmdet3d_frames(infos: Any, path: str) -> list[FrameObjects]:
    """Parse an mmdetection3d v2 info dict (KITTI): frames in ``data_list`` with ``instances``."""
    meta = infos.get("metainfo") or {}
    if str(meta.get("dataset", "kitti")).lower() not in ("kitti", ""):
        raise ExportError(
            f"{path}: mmdet3d infos of dataset {meta.get('dataset')!r}: only KITTI v2 infos can be aligned "
            "(mmdet3d's Waymo infos keep no laser object ids); use --format openpcdet or parquet"
        )
    with malformed(f"{path}: metainfo"):
        label_name = {int(v): str(k) for k, v in (meta.get("categories") or {}).items() if int(v) >= 0}
    frames = []
    for i, item in enumerate(infos.get("data_list") or []):
        where = f"{path}: data_list[{i}]"
        with malformed(where):
            frames.append(_mmdet3d_frame(item, label_name, where))
    return frames


def _mmdet3d_frame(item: Any, label_name: Mapping[int, str], where: str) -> FrameObjects:
    if not isinstance(item, dict) or "instances" not in item:
        raise ExportError(f"{where}: expected a dict with 'instances' (mmdet3d v2 info)")
    lidar = item.get("lidar_points") or {}
    if lidar.get("lidar_path"):
        fid = Path(str(lidar["lidar_path"])).stem
    elif "sample_idx" in item:
        fid = kitti_frame_id(item["sample_idx"])
    else:
        raise ExportError(f"{where}: neither lidar_points.lidar_path nor sample_idx names the frame")
    keys, names, dims = [], [], []
    ordinal = -1
    for inst in item["instances"]:
        label = int(inst.get("bbox_label_3d", inst.get("bbox_label", -1)))
        if "index" in inst:
            idx = int(inst["index"])
        else:  # DontCare is the only KITTI class mmdet3d labels -1
            idx = ordinal + 1 if label >= 0 else -1
        ordinal = max(ordinal, idx)
        keys.append(idx if idx >= 0 else None)
        names.append(label_name.get(label, DONTCARE if idx < 0 else f"label{label}"))
        bb = inst.get("bbox_3d")
        # mmdet3d KITTI bbox_3d: camera x, y, z, l, h, w, ry
        dims.append([bb[3], bb[5], bb[4]] if bb is not None and len(bb) >= 7 else [np.nan] * 3)
    return FrameObjects(fid, keys, names, np.asarray(dims, dtype=float).reshape(-1, 3))


def align_frames(
    frames: Sequence[FrameObjects], arrays: ResultArrays, reason: NDArray[np.object_], index: ResultIndex, path: str
) -> tuple[list[NDArray[np.int64]], dict[str, Any]]:
    """Result row of every infos object (−1 where none), checking that the infos describe the results.

    ``reason`` (one per result row, "" when it has values) says why a matched object has none;
    the others have none because they are DontCare, of a class not audited, or without a row.
    ``stats["object_reasons"]`` holds, per frame, each object's reason ("" = has values) and
    ``stats["reasons"]`` their counts.

    Raises
    ------
    InfosMismatchError
        At the first frame (in file order) whose objects disagree with its result rows: an object
        the infos lack, another class, or other sizes.
    """
    audited_classes = set(arrays.class_name.tolist())
    why: list[str] = []  # per object, file order
    first_extra: tuple[int, str] | None = None  # (frame position, message) of a result row the infos lack
    frames_without = 0
    per_frame: list[list[int]] = []
    for f, fr in enumerate(frames):
        results = index.by_frame.get(fr.frame_id)
        if results is None:
            frames_without += 1
            results = {}
        present = {k for k in fr.keys if k is not None}
        if first_extra is None:
            extra_keys = [
                k
                for k in results.keys() - present
                if not (index.key == "object_id" and arrays.class_name[results[k]] == "Unknown")
            ]
            if extra_keys:
                key = min(extra_keys, key=str)
                what = f"object_index {key}" if index.key == "object_index" else f"object id {key!r}"
                first_extra = (f, f"frame {fr.frame_id}: the results have {what} ({arrays.class_name[results[key]]}) but the infos "
                               f"list {len(present)} non-DontCare object(s) there")  # fmt: skip
        rows = [-2 if k is None else results.get(k, -1) for k in fr.keys]  # -2: DontCare, -1: no row
        for j, r in enumerate(rows):
            if r == -2:
                why.append("DontCare")
            elif r >= 0:
                why.append("")  # the result row's own reason, below
            elif fr.frame_id not in index.by_frame:
                why.append("frame not in the results")
            elif fr.names[j] not in audited_classes:
                why.append(f"class {fr.names[j]} not audited")
            else:
                why.append("no result row")
        per_frame.append(rows)

    # class and size of every matched object at once; the earliest disagreement in file order wins
    sizes = [len(r) for r in per_frame]
    flat = np.array([r for rows in per_frame for r in rows], dtype=np.int64)
    frame_of = np.repeat(np.arange(len(frames)), sizes)
    hit = np.flatnonzero(flat >= 0)
    first_bad: tuple[int, str] | None = None
    why_arr = np.array(why, dtype=object)
    if len(hit):
        names = np.array([n for fr in frames for n in fr.names], dtype=object)[hit]
        dims = np.concatenate([fr.dims_lwh for fr in frames])[hit]
        res_rows = flat[hit]
        lwh = arrays.boxes[res_rows, 3:6]
        off = np.where(np.isfinite(dims), np.abs(dims - lwh), 0.0).max(axis=1)
        bad = np.flatnonzero((names != arrays.class_name[res_rows]) | (off > C.INFOS_DIMENSION_TOLERANCE))
        if len(bad):
            i = int(bad[0])
            f = int(frame_of[hit[i]])
            j = int(hit[i] - np.sum(sizes[:f]))
            first_bad = (f, f"frame {frames[f].frame_id} object {j} (key {frames[f].keys[j]}): infos say {names[i]} l,w,h = "
                         f"{', '.join(f'{v:.3f}' for v in dims[i])}, the results say {arrays.class_name[res_rows[i]]} "
                         f"{', '.join(f'{v:.3f}' for v in lwh[i])}")  # fmt: skip
        why_arr[hit] = reason[res_rows]
    errors = [e for e in (first_extra, first_bad) if e is not None]
    if errors:
        raise InfosMismatchError(f"{path}: {min(errors)[1]}; the infos file does not belong to these results")
    if frames and frames_without == len(frames):
        first_res = next(iter(index.by_frame), "?")
        raise InfosMismatchError(
            f"{path}: none of its {len(frames)} frames is in the results (first infos frame {frames[0].frame_id}, "
            f"first results frame {first_res}); the infos file does not belong to these results"
        )
    seen_frames = {fr.frame_id for fr in frames}
    rows_out = np.split(np.where(flat >= 0, flat, -1), np.cumsum(sizes)[:-1]) if sizes else []
    extra = {
        "frames_without_results": frames_without,
        "reasons": dict(Counter(w for w in why_arr.tolist() if w)),
        "object_reasons": np.split(why_arr, np.cumsum(sizes)[:-1]) if sizes else [],
        "results_frames_not_in_infos": len(set(index.by_frame) - seen_frames),
        "results_rows_not_in_infos": len(arrays) - len(hit),
    }
    return list(rows_out), extra


def _gather(
    targets: ExportTargets, rows: NDArray[np.int64]
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
    Tn = targets.encoding.size
    std = np.full((len(rows), Tn), np.nan, dtype=np.float32)
    cov = np.full((len(rows), Tn, Tn), np.nan, dtype=np.float32)
    valid = np.zeros(len(rows), dtype=bool)
    hit = rows >= 0
    if hit.any():
        r = rows[hit]
        std[hit] = targets.std[r]
        cov[hit] = targets.cov[r]
        valid[hit] = targets.valid[r]
    return std, cov, valid


def attach_to_infos(
    infos: Any,
    fmt: Literal["openpcdet", "mmdet3d"],
    arrays: ResultArrays,
    targets: ExportTargets,
    path: str = "<infos>",
) -> tuple[Any, dict[str, Any]]:
    """Add the targets to every object of an infos structure, in the file's own object order (in place).

    OpenPCDet: each frame's ``annos`` gains ``label_std`` (K, T) float32, ``label_cov`` (K, T, T)
    float32 and ``label_std_valid`` (K,) bool, K = every object of the frame including DontCare
    (so OpenPCDet's ``drop_info_with_name`` keeps them aligned); each frame gets ``label_uncertainty``
    (the description). mmdet3d v2: every instance dict gains the same three keys as a (T,) and a
    (T, T) float32 array and a bool; ``metainfo`` gets ``label_uncertainty``. Objects without
    targets (DontCare, classes not audited, missing rows) get NaN and False.

    Returns
    -------
    infos : the same object, modified
    stats : counts for :class:`ExportSummary`
    """
    if fmt == "openpcdet":
        kind, frames = openpcdet_frames(infos, path)
        index = ResultIndex(arrays, "object_id" if kind == "waymo" else "object_index")
    else:
        if not isinstance(infos, dict) or "data_list" not in infos:
            raise ExportError(
                f"{path}: an mmdet3d v2 info file is a dict with 'metainfo' and 'data_list'; got {type(infos).__name__}"
            )
        frames = _mmdet3d_frames(infos, path)
        index = ResultIndex(arrays, "object_index")
    rows, extra = align_frames(frames, arrays, targets.reason, index, path)
    meta = targets.metadata()
    n_obj = n_with = 0
    if fmt == "openpcdet":
        for info, r in zip(infos, rows):
            std, cov, valid = _gather(targets, r)
            annos = info["annos"]
            annos[INFOS_KEYS[0]], annos[INFOS_KEYS[1]], annos[INFOS_KEYS[2]] = std, cov, valid
            info[INFOS_META_KEY] = meta  # one shared dict: pickled once
            n_obj += len(r)
            n_with += int(valid.sum())
    else:
        infos.setdefault("metainfo", {})[INFOS_META_KEY] = meta
        flat = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        hit = flat >= 0
        valid = np.zeros(len(flat), dtype=bool)
        valid[hit] = targets.valid[flat[hit]]
        take = np.where(hit, flat, 0)
        # float32 arrays, one per instance (not nested lists: half the size, ~8× faster to load); NaN where none
        stds = np.where(valid[:, None], targets.std[take], np.nan).astype(np.float32)
        covs = np.where(valid[:, None, None], targets.cov[take], np.nan).astype(np.float32)
        instances = (inst for item in infos["data_list"] for inst in item["instances"])
        for i, (inst, v) in enumerate(zip(instances, valid.tolist())):
            inst[INFOS_KEYS[0]], inst[INFOS_KEYS[1]], inst[INFOS_KEYS[2]] = stds[i].copy(), covs[i].copy(), v
        n_obj, n_with = len(flat), int(valid.sum())
    extra.update(frames=len(frames), objects=n_obj, objects_with_targets=n_with)
    return infos, extra


def detect_infos_format(infos: Any) -> Literal["openpcdet", "mmdet3d"]:
    """``openpcdet`` for a list of frame dicts, ``mmdet3d`` for a v2 dict with ``data_list``."""
    if isinstance(infos, dict) and "data_list" in infos:
        return "mmdet3d"
    return "openpcdet"

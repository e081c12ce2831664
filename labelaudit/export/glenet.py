"""GLENet's label uncertainty files: OpenPCDet infos and gt-database infos with an ``uncertainty`` per object.

GLENet (Zhang et al., IJCV 2023; github.com/Eaphan/GLENet) trains probabilistic detectors with a
KL-divergence loss whose target is a 7-vector of label variances per object. Its OpenPCDet fork
reads them from two files (``pcdet/datasets/kitti/kitti_dataset.py``, ``waymo/waymo_dataset.py``,
``augmentor/database_sampler.py``):

- every frame's ``info['annos']['uncertainty']``, (K, 7), one row per ``annos`` entry in annos
  order, DontCare included (the dataset drops DontCare from every annos array together);
- every gt-database entry's ``db_infos[class][i]['uncertainty']``, (7,), for the objects that gt
  sampling pastes into other scenes; the entry names its frame (KITTI ``image_idx``; Waymo
  ``sequence_name`` and ``sample_idx``) and its object (``gt_idx``: the non-DontCare ordinal for
  KITTI, the annos row for Waymo).

The values are :func:`labelaudit.training.glenet_variances` of each label's covariance in the
residual encoding of its class anchor; objects without one get −1 in every entry, as GLENet's
own converter writes them. A BEV posterior has no z and h: their variances come from the class
prior (counted in the summary). Both copies are built in memory, checked against each other and
the results, and only then written: every file to a temporary name, then all renamed.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit import results as R
from labelaudit import training as T
from labelaudit.errors import ExportError, InfosMismatchError
from labelaudit.export.arrays import ResultArrays, read_result_arrays
from labelaudit.export.infos import FrameObjects, ResultIndex, align_frames, kitti_frame_id, malformed, openpcdet_frames
from labelaudit.export.pickles import dump_infos_all, load_infos
from labelaudit.export.summary import ExportSummary, reasons_text
from labelaudit.export.targets import box_covariances, prior_variances

FloatArray = NDArray[np.float64]

__all__ = [
    "GLENET_KEY",
    "GLENET_META_NAME",
    "GlenetValues",
    "attach_glenet_dbinfos",
    "attach_glenet_infos",
    "export_glenet",
    "glenet_values",
]

GLENET_KEY = "uncertainty"
"""The key GLENet reads in ``annos`` and in each gt-database entry."""
GLENET_META_NAME = "labelaudit-glenet.json"
"""The description written beside the two files (targets, anchors, source, counts)."""
_CZ, _H = 2, 5


@dataclass
class GlenetValues:
    """GLENet's seven variances of every result row.

    Attributes
    ----------
    values : (N, 7) :data:`labelaudit.training.GLENET_TARGETS` variances, all > 0 where valid,
        :data:`labelaudit.constants.EXPORT_GLENET_MISSING` elsewhere
    valid : (N,) the row has values
    reason : (N,) why a row has none ("" when valid)
    prior_filled : (N,) z and h variances taken from the class prior (a BEV posterior)
    source : where the covariance came from
    anchor_sizes : class → (l, w, h) used
    """

    values: FloatArray
    valid: NDArray[np.bool_]
    reason: NDArray[np.object_]
    prior_filled: NDArray[np.bool_]
    source: T.VarianceSource
    anchor_sizes: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    def metadata(self) -> dict[str, Any]:
        """JSON-able description written beside the files."""
        return {
            "tool": "labelaudit",
            "tool_version": __version__,
            "format": "glenet",
            "key": GLENET_KEY,
            "targets": list(T.GLENET_TARGETS),
            "source": str(self.source),
            "anchor_sizes": {k: list(v) for k, v in self.anchor_sizes.items()},
            "missing_value": C.EXPORT_GLENET_MISSING,
            "objects_with_z_h_from_prior": int(self.prior_filled.sum()),
        }


def glenet_values(
    arrays: ResultArrays,
    source: str | T.VarianceSource = "model",
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
) -> GlenetValues:
    """GLENet's variances of every row (rows without get −1 and a reason).

    The covariance of y comes from :func:`labelaudit.export.targets.box_covariances`; where it
    lacks z and h (a BEV posterior) their variances are the class prior's, uncorrelated with the
    rest. ``fixed:VAR`` gives VAR in all seven. Values are at least
    :data:`labelaudit.constants.EXPORT_GLENET_MIN_VARIANCE` (GLENet takes their log).

    Raises
    ------
    ExportError
        Unknown source, or a source whose column is null in every audited row.
    """
    bc = box_covariances(arrays, source, anchor_sizes, needs_anchor=True)
    n = len(arrays)
    values = np.full((n, 7), C.EXPORT_GLENET_MISSING)
    ok = np.flatnonzero(bc.reason == "")
    prior_filled = np.zeros(n, dtype=bool)
    if len(ok) and bc.source.kind == "fixed":
        values[ok] = float(bc.source.value)  # type: ignore[arg-type]
    elif len(ok):
        cov = bc.cov[ok].copy()
        avail = bc.available[ok]
        prior = prior_variances(arrays)[ok]
        for k in (_CZ, _H):
            fill = ~avail[:, k]
            cov[fill, k, :] = 0.0
            cov[fill, :, k] = 0.0
            cov[fill, k, k] = prior[fill, k]
        prior_filled[ok] = ~avail.all(axis=1)
        v = T.glenet_variances(arrays.boxes[ok], cov, bc.anchor[ok])
        values[ok] = np.maximum(v, C.EXPORT_GLENET_MIN_VARIANCE)
    return GlenetValues(values, bc.reason == "", bc.reason, prior_filled, bc.source, bc.anchor_sizes)


# --------------------------------------------------------------------------- infos


def _frame_values(rows: NDArray[np.int64], gv: GlenetValues) -> NDArray[np.float32]:
    """(K, 7) float32 values of one frame's objects (−1 for objects without a row or values)."""
    out = np.full((len(rows), 7), C.EXPORT_GLENET_MISSING, dtype=np.float32)
    hit = rows >= 0
    hit[hit] = gv.valid[rows[hit]]
    out[hit] = gv.values[rows[hit]]
    return out


def attach_glenet_infos(
    infos: list[Any], arrays: ResultArrays, gv: GlenetValues, path: str = "<infos>"
) -> tuple[str, list[FrameObjects], list[NDArray[np.float32]], dict[str, Any]]:
    """Set ``info['annos']['uncertainty']`` of every frame of an OpenPCDet infos list (in place).

    Returns
    -------
    kind : ``kitti`` or ``waymo``
    frames : the parsed frames, in file order
    values : per frame its (K, 7) float32 array (the one stored)
    stats : counts (frames, objects, objects with values, reasons of the others) and per frame
        each object's reason (``object_reasons``, "" = has values)

    Raises
    ------
    InfosMismatchError, ExportError
        As :func:`labelaudit.export.infos.align_frames`: the infos describe other labels.
    """
    kind, frames = openpcdet_frames(infos, path)
    index = ResultIndex(arrays, "object_id" if kind == "waymo" else "object_index")
    rows, extra = align_frames(frames, arrays, gv.reason, index, path)
    values = []
    n_with = 0
    for info, r in zip(infos, rows):
        v = _frame_values(r, gv)
        info["annos"][GLENET_KEY] = v
        values.append(v)
        n_with += int((v[:, 0] > 0).sum())
    extra.update(frames=len(frames), objects=sum(len(r) for r in rows), objects_with_targets=n_with)
    return kind, frames, values, extra


def _frame_key(kind: str, info: Mapping[str, Any]) -> Any:
    """How a gt-database entry names the frame of this infos entry."""
    pc_info = info["point_cloud"]
    if kind == "waymo":
        return str(pc_info["lidar_sequence"]), int(pc_info["sample_idx"])
    return kitti_frame_id(pc_info["lidar_idx"])


def attach_glenet_dbinfos(
    dbinfos: Any,
    kind: str,
    infos: Sequence[Mapping[str, Any]],
    frames: Sequence[FrameObjects],
    values: Sequence[NDArray[np.float32]],
    reasons: Sequence[Sequence[str]],
    path: str = "<dbinfos>",
) -> dict[str, Any]:
    """Set ``uncertainty`` of every gt-database entry to its frame's row (in place).

    ``reasons`` are the frames' per-object reasons of :func:`attach_glenet_infos` (an entry
    without values is counted under its object's). Entries of frames the infos do not hold get
    −1 (counted); an entry whose object the frame does not have, or has with another class or
    size, is an error.

    Raises
    ------
    InfosMismatchError
        The first such entry, by class then position.
    ExportError
        Not a dict of class → list of entries, or an entry without its frame or ``gt_idx``.
    """
    if not isinstance(dbinfos, dict) or not all(isinstance(v, list) for v in dbinfos.values()):
        raise ExportError(
            f"{path}: a gt-database infos file is a dict of class name → list of entries; got {type(dbinfos).__name__}"
        )
    by_frame: dict[Any, int] = {}
    for f, info in enumerate(infos):
        by_frame[_frame_key(kind, info)] = f
    ordinal_pos = [{k: j for j, k in enumerate(fr.keys) if k is not None} for fr in frames] if kind == "kitti" else None
    stats: Counter[str] = Counter()
    nan3 = np.full(3, np.nan)
    # one pass over the entries for their keys; the checks and the values then go at once
    matched, where, at, names, dims = [], [], [], [], []
    n = 0
    for cls, entries in dbinfos.items():
        for i, entry in enumerate(entries):
            with malformed(f"{path}: {cls}[{i}]"):
                if kind == "waymo":
                    fkey: Any = (str(entry["sequence_name"]), int(entry["sample_idx"]))
                else:
                    fkey = kitti_frame_id(entry["image_idx"])
                gt_idx = int(entry["gt_idx"])
                name = str(entry.get("name", cls))
                box = entry.get("box3d_lidar")
                d = nan3 if box is None or len(box) < 6 else box[3:6]
            n += 1
            f = by_frame.get(fkey)
            if f is None:
                entry[GLENET_KEY] = np.full(7, C.EXPORT_GLENET_MISSING, dtype=np.float32)
                stats["frame not in the infos"] += 1
                continue
            j = ordinal_pos[f].get(gt_idx, -1) if ordinal_pos is not None else gt_idx
            matched.append(entry)
            where.append((cls, i, fkey, gt_idx))
            at.append((f, j if 0 <= j < len(frames[f].names) else -1))
            names.append(name)
            dims.append(d)
    if not matched:
        return {"objects": n, "objects_with_targets": 0, "reasons": dict(stats)}

    offsets = np.concatenate([[0], np.cumsum([len(fr.names) for fr in frames])])
    pos = np.array(at, dtype=np.int64).reshape(-1, 2)
    in_range = pos[:, 1] >= 0
    flat = np.where(in_range, offsets[pos[:, 0]] + pos[:, 1], 0)
    all_names = np.array([nm for fr in frames for nm in fr.names], dtype=object)
    all_dims = np.concatenate([fr.dims_lwh for fr in frames]).reshape(-1, 3)
    ours = np.asarray(dims, dtype=float).reshape(-1, 3)
    theirs = all_dims[flat]
    off = np.where(np.isfinite(ours) & np.isfinite(theirs), np.abs(ours - theirs), 0.0).max(axis=1)
    bad = ~in_range | (np.array(names, dtype=object) != all_names[flat]) | (off > C.INFOS_DIMENSION_TOLERANCE)
    if bad.any():
        k = int(np.flatnonzero(bad)[0])
        cls, i, fkey, gt_idx = where[k]
        f = int(pos[k, 0])
        frame_name = fkey if kind == "kitti" else f"{fkey[0]} sample {fkey[1]}"
        if not in_range[k]:
            raise InfosMismatchError(f"{path}: {cls}[{i}]: gt_idx {gt_idx}, but frame {frame_name} of the infos has no such object "
                                     f"({len(frames[f].names)} annos entries); the gt-database file does not belong to these infos")  # fmt: skip
        raise InfosMismatchError(
            f"{path}: {cls}[{i}]: {names[k]} l,w,h = {', '.join(f'{v:.3f}' for v in ours[k])} of frame {frame_name} gt_idx {gt_idx}, "
            f"but the infos list {all_names[flat[k]]} l,w,h = {', '.join(f'{v:.3f}' for v in theirs[k])} there; the gt-database "
            "file does not belong to these infos"
        )
    got = np.concatenate(values).reshape(-1, 7)[flat]  # a copy: every entry its own row of it
    for entry, v in zip(matched, got):
        entry[GLENET_KEY] = v
    with_values = got[:, 0] > 0
    all_reasons = (
        np.concatenate([np.asarray(r, dtype=object) for r in reasons]) if len(reasons) else np.zeros(0, dtype=object)
    )
    stats.update(str(r) or "no value" for r in all_reasons[flat[~with_values]].tolist())
    return {"objects": n, "objects_with_targets": int(with_values.sum()), "reasons": dict(stats)}


# --------------------------------------------------------------------------- the whole export


def _infos_files(infos: Path, output_dir: Path) -> list[tuple[Path, Path]]:
    """(input, output) pickles: one file, or a folder of OpenPCDet's per-sequence Waymo infos ``<seq>/<seq>.pkl``."""
    if infos.is_dir():
        found = sorted(p for p in infos.glob("*/*.pkl") if p.stem == p.parent.name)
        if not found:
            raise ExportError(
                f"{infos}: a folder of infos holds <sequence>/<sequence>.pkl files (OpenPCDet's Waymo layout); found none"
            )
        return [(p, output_dir / p.relative_to(infos)) for p in found]
    if not infos.is_file():
        raise ExportError(f"{infos}: infos file not found")
    return [(infos, output_dir / infos.name)]


def export_glenet(
    results: str | Path | ResultArrays,
    output_dir: str | Path,
    infos: str | Path,
    dbinfos: str | Path | None = None,
    *,
    source: str = "model",
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
) -> ExportSummary:
    """Write GLENet's infos (and gt-database infos) with label variances into ``output_dir``.

    Parameters
    ----------
    results : results folder of ``labelaudit infer`` (or one Parquet file of rows, or its arrays)
    output_dir : folder of the copies; the file names (and a Waymo folder's ``<seq>/<seq>.pkl``
        layout) are the inputs', plus :data:`GLENET_META_NAME`
    infos : OpenPCDet ``kitti_infos_train.pkl`` / Waymo infos file, or a folder of per-sequence
        Waymo infos
    dbinfos : OpenPCDet ``kitti_dbinfos_train.pkl`` / Waymo ``…_waymo_dbinfos_train_sampled_1.pkl``
    source, anchor_sizes : see :func:`glenet_values`

    Raises
    ------
    ExportError
        Bad options or input (:class:`~labelaudit.errors.InfosMismatchError`,
        :class:`~labelaudit.errors.UnsafePickleError`), an output that would overwrite an input,
        or no object with values; nothing is written then.
    """
    output_dir = Path(output_dir)
    if output_dir.exists() and not output_dir.is_dir():
        raise ExportError(f"{output_dir}: is a file; --format glenet writes a folder (-o DIR)")
    pairs = _infos_files(Path(infos), output_dir)
    if dbinfos is not None:
        if not Path(dbinfos).is_file():
            raise ExportError(f"{dbinfos}: gt-database infos file not found")
        pairs_db = (Path(dbinfos), output_dir / Path(dbinfos).name)
        if pairs_db[1].name in {dst.name for _, dst in pairs if dst.parent == output_dir}:
            raise ExportError(f"{dbinfos}: has the same file name as the infos; both would be written to {pairs_db[1]}")
    for src, dst in pairs + ([pairs_db] if dbinfos is not None else []):
        if dst.resolve() == src.resolve():
            raise ExportError(f"{dst}: the output would overwrite the input {src}; write the copies to another folder")

    arrays = results if isinstance(results, ResultArrays) else read_result_arrays(results)
    gv = glenet_values(arrays, source, anchor_sizes)
    summary = ExportSummary(
        output=str(output_dir),
        format="glenet",
        encoding="glenet",
        source=str(gv.source),
        results_rows=len(arrays),
        rows_with_targets=int(gv.valid.sum()),
        rows_without_targets=dict(Counter(r for r in gv.reason.tolist() if r)),
        infos=str(infos),
    )
    if arrays.manifest and not arrays.manifest.get("complete", True):
        summary.notes.append(f"{results} is incomplete (infer was stopped); objects of frames not yet audited get -1")
    if summary.rows_with_targets == 0:
        raise ExportError(
            f"{results}: no result row has values ({reasons_text(summary.rows_without_targets)}); nothing written"
        )

    data = [load_infos(src) for src, _ in pairs]
    merged: list[Any] = []
    for (src, _), d in zip(pairs, data):
        if not isinstance(d, list):
            raise ExportError(f"{src}: an OpenPCDet infos file is a list of frame dicts, got {type(d).__name__}")
        merged.extend(d)
    where = str(infos) if len(pairs) == 1 else f"{infos} ({len(pairs)} files)"
    kind, frames, values, stats = attach_glenet_infos(merged, arrays, gv, where)
    if stats["objects_with_targets"] == 0:
        raise ExportError(
            f"{where}: no object of the infos got values ({reasons_text(stats['reasons'])}); nothing written"
        )
    db_data = None
    if dbinfos is not None:
        db_data = load_infos(dbinfos)
        db_stats = attach_glenet_dbinfos(db_data, kind, merged, frames, values, stats["object_reasons"], str(dbinfos))
        summary.dbinfos = str(dbinfos)
        summary.dbinfos_objects = db_stats["objects"]
        summary.dbinfos_objects_with_targets = db_stats["objects_with_targets"]
        summary.dbinfos_objects_without_targets = db_stats["reasons"]

    # everything checked: write
    writes = [(d, dst) for (_, dst), d in zip(pairs, data)]
    if db_data is not None:
        writes.append((db_data, pairs_db[1]))
    summary.outputs += [str(p) for p in dump_infos_all(writes)]  # all or none
    meta = {**gv.metadata(), "results_param_hash": arrays.manifest.get("param_hash"), "results_input": arrays.manifest.get("input"),
            "infos": [str(s) for s, _ in pairs], "dbinfos": None if dbinfos is None else str(dbinfos)}  # fmt: skip
    R.write_json_atomic(meta, output_dir / GLENET_META_NAME)
    summary.outputs.append(str(output_dir / GLENET_META_NAME))

    summary.add_infos_stats(stats)
    summary.objects_z_h_from_prior = int(gv.prior_filled.sum())
    if summary.objects_z_h_from_prior:
        summary.notes.append(
            f"{summary.objects_z_h_from_prior} object(s) have a BEV posterior: their z and h variances (zt, dzt) are the class "
            "prior's; `labelaudit infer --model 3d` infers them"
        )
    return summary

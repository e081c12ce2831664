"""Label uncertainty for evaluation: the GT boxes' posterior covariances from an ``infer`` results folder.

A results folder is used only when it was made from *this* dataset with the parameters ``eval``
would use itself (same ``--config`` / model; its own class selection is kept): the check is the
one ``infer --resume`` applies (:func:`labelaudit.results.resume_mismatch` — versions, model
constants, parameters, input path and format, parameter hash). Every GT box the evaluation needs
must have a row (joined by ``(frame_id, object_index)`` and checked to be the same box). Without a
results folder, :func:`infer_labels` runs the label inference on the GT boxes through the normal
``infer`` pipeline. Rows whose inference was skipped or failed carry no covariance; those labels
are treated as certain (counted and reported). This module never touches detections.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from labelaudit import results as R
from labelaudit.config import RunConfig, hash_inputs
from labelaudit.datasets.gt import GroundTruth
from labelaudit.errors import EvalError

FloatArray = NDArray[np.float64]

__all__ = ["EvalError", "LabelSet", "check_results_match", "expected_metadata", "infer_labels", "label_uncertainty"]


@dataclass
class LabelSet:
    """Per GT row: φ covariance (NaN-filled when none), JIoU-GT (1 when none), status.

    Attributes
    ----------
    cov : (N, p, p)
    jiou_gt : (N,)
    status : N result statuses ("" for rows not needed by the evaluation)
    needed : (N,) rows the evaluation uses
    model : "bev" or "3d"
    source : "results" (a given folder) or "inferred" (eval ran the inference)
    path : the results folder
    param_hash : its parameter hash
    """

    cov: FloatArray
    jiou_gt: FloatArray
    status: list[str]
    needed: NDArray[np.bool_]
    model: str
    source: str
    path: Path
    param_hash: str | None = None
    notes: list[str] = field(default_factory=list)

    @property
    def without_cov(self) -> int:
        """Needed rows that have no covariance (treated as certain labels)."""
        return int(np.count_nonzero(self.needed & np.isnan(self.cov).any(axis=(1, 2))))


def expected_metadata(dataset: Path, dataset_format: str, cfg: RunConfig) -> dict[str, Any]:
    """The manifest fields an ``infer`` run of ``cfg`` on ``dataset`` would write (for the match check)."""
    inputs = hash_inputs(cfg)
    return R.run_metadata(
        inputs["params"],
        cfg.param_hash(),
        str(Path(dataset).resolve()),
        dataset_format,
        constants_digest=inputs["constants_digest"],
    )


def check_results_match(results: R.Results, dataset: Path, dataset_format: str, cfg: RunConfig) -> None:
    """Raise :class:`EvalError` when ``results`` was not made from ``dataset`` with ``cfg``'s parameters.

    The results' own class selection is taken over (a folder audited with ``--classes all`` fits
    any evaluated classes); everything else must match, as for ``infer --resume``.
    """
    where = results.root
    if results.root.is_file() or not results.manifest:
        raise EvalError(
            f"{where}: --results needs a results folder with {R.MANIFEST_NAME} (written by `labelaudit infer`), so that its input and parameters can be checked"
        )
    if not results.complete:
        raise EvalError(
            f"{where}: the results folder is incomplete (an infer run is in progress or stopped); rerun `labelaudit infer` to finish it"
        )
    classes = tuple((results.manifest.get("params") or {}).get("classes") or cfg.classes)
    expected = expected_metadata(dataset, dataset_format, cfg.with_overrides(classes=classes))
    why = R.resume_mismatch(results.manifest, expected)
    if why is not None:
        raise EvalError(
            f"{where}: these results do not fit {dataset}: {why}. Pass the --config/--metric that infer used, "
            f"or rerun `labelaudit infer {dataset} -o {where} --overwrite`, or leave out --results to infer the labels here"
        )


def label_uncertainty(
    results: R.Results, gt: GroundTruth, needed: NDArray[np.bool_], model: str, source: str = "results"
) -> LabelSet:
    """Covariance and JIoU-GT of the needed GT rows from a results folder.

    Raises
    ------
    EvalError
        Rows missing for needed GT boxes (names how many, an example and the fix), or rows whose box
        differs from the label (the dataset changed since ``infer``).
    """
    p = 6 if model == "bev" else 8
    n = len(gt.boxes)
    cols = ["frame_id", "object_index", "class_name", *R.BOX_COLUMNS, "status", "cov", "cov_dim", "model", "jiou_gt"]
    table = results.read(cols)
    wanted = {fid for fid, k in zip(np.repeat(gt.frame_ids, np.diff(gt.gt_off)), needed) if k} if n else set()
    if table.num_rows and wanted:
        table = table.filter(pc.is_in(table.column("frame_id"), value_set=pa.array(sorted(wanted))))
    frame_ids = table.column("frame_id").to_pylist()
    obj = table.column("object_index").to_numpy(zero_copy_only=False)
    row_of = {(f, int(o)): i for i, (f, o) in enumerate(zip(frame_ids, obj))}
    boxes = (
        np.stack([table.column(c).to_numpy(zero_copy_only=False).astype(float) for c in R.BOX_COLUMNS], axis=1)
        if table.num_rows
        else np.zeros((0, 7))
    )
    covs = table.column("cov").to_pylist()
    dims = table.column("cov_dim").to_pylist()
    models = table.column("model").to_pylist()
    jg = table.column("jiou_gt").to_pylist()
    status_col = table.column("status").to_pylist()

    cov = np.full((n, p, p), np.nan)
    jiou_gt = np.ones(n)
    status = [""] * n
    frame_of = gt.frame_of_row
    missing: list[int] = []
    for g in np.flatnonzero(needed):
        key = (gt.frame_ids[frame_of[g]], int(gt.object_index[g]))
        r = row_of.get(key)
        if r is None:
            missing.append(int(g))
            continue
        if np.max(np.abs(boxes[r] - gt.boxes[g])) > 1e-6:
            raise EvalError(
                f"{results.root}: the row of frame {key[0]} object {key[1]} holds box {np.round(boxes[r], 3).tolist()} but the label is "
                f"{np.round(gt.boxes[g], 3).tolist()}; the dataset changed since infer — rerun `labelaudit infer --overwrite`"
            )
        status[g] = status_col[r]
        if covs[r] is not None:
            if models[r] != model or dims[r] != p:
                raise EvalError(
                    f"{results.root}: label covariances of the {models[r]} model, but --metric {model} needs the {model} model (`labelaudit infer --model {model}`)"
                )
            cov[g] = np.asarray(covs[r], dtype=float).reshape(p, p)
            jiou_gt[g] = float(jg[r]) if jg[r] is not None else 1.0
    if missing:
        g = missing[0]
        classes = sorted({gt.class_names[i] for i in missing})
        raise EvalError(
            f"{results.root}: no results rows for {len(missing)} GT boxes the evaluation needs (classes {', '.join(classes)}; "
            f"first: frame {gt.frame_ids[frame_of[g]]} object {int(gt.object_index[g])}); audit them with "
            f"`labelaudit infer --classes {','.join(classes)}` (or --classes all), or evaluate fewer --classes"
        )
    return LabelSet(
        cov,
        jiou_gt,
        status,
        np.asarray(needed, dtype=bool),
        model,
        source,
        results.root,
        results.manifest.get("param_hash"),
    )


def infer_labels(
    dataset: Path,
    dataset_format: str,
    cfg: RunConfig,
    output: Path,
    *,
    split: str | None = None,
    limit: int | None = None,
    workers: int | None = None,
    progress: Any = None,
    debug: bool = False,
) -> R.Results:
    """Run ``infer`` on the dataset's GT boxes of ``cfg.classes`` into ``output``; returns the opened results.

    Same pipeline and resume rules as ``labelaudit infer`` (a folder of the same run is resumed);
    ``progress`` is an infer progress sink (:class:`labelaudit.infer.run.Progress`), default silent.
    """
    from labelaudit.infer.run import InferRequest, run_infer

    request = InferRequest(Path(dataset), Path(output), dataset_format, split, workers, limit, False, False, debug)
    run_infer(request, cfg, progress)
    return R.open_results(output)


def needed_rows(gt: GroundTruth, classes: Sequence[str]) -> NDArray[np.bool_]:
    """GT rows whose label distribution the evaluation uses: the evaluated classes and their neighbours."""
    from labelaudit import constants as C

    want = {c.lower() for c in classes}
    for c in classes:
        for key, nb in C.EVAL_NEIGHBOUR_CLASSES.items():
            if key.lower() == c.lower():
                want |= {n.lower() for n in nb}
    return np.array([n.lower() in want for n in gt.class_names], dtype=bool)

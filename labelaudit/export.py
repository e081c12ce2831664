"""``labelaudit export``: σ_p training targets from a results folder into Parquet or detector infos files.

This module owns the I/O of the export (docs/training.md): reading the result rows it needs,
turning them into arrays for :mod:`labelaudit.training` (which does all the mathematics), writing
the Parquet table of targets, and adding the targets to a copy of an OpenPCDet (KITTI, Waymo) or
mmdetection3d (v2 ``instances``, KITTI) infos pickle, aligned with that file's own object order.
Infos pickles are read with a restricted unpickler (numpy arrays and builtin containers only).
Every file is written to a temporary name and renamed. It computes no statistics of its own (that
is :mod:`labelaudit.training`) and prints nothing: the CLI (:mod:`labelaudit.cli.export`) shows the
:class:`ExportSummary`.
"""

from __future__ import annotations

import io
import json
import math
import os
import pickle
import warnings
from collections import Counter
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal, Mapping, Sequence

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
from numpy.typing import NDArray

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit import results as R
from labelaudit import training as T
from labelaudit.errors import ExportError, InfosMismatchError, UnsafePickleError

FloatArray = NDArray[np.float64]

__all__ = [
    "ExportError",
    "ExportSummary",
    "ExportTargets",
    "InfosMismatchError",
    "UnsafePickleError",
    "attach_to_infos",
    "compute_targets",
    "dump_infos",
    "export_results",
    "load_infos",
    "parse_anchor_sizes",
    "read_result_arrays",
    "targets_to_table",
]

INFOS_KEYS = ("label_std", "label_cov", "label_std_valid")
"""Names of the per-object entries added to each infos object: std (T,), covariance (T, T), mask."""
INFOS_META_KEY = "label_uncertainty"
"""Key of the description (encoding, targets, source, tool) added to each OpenPCDet frame info and to mmdet3d ``metainfo``."""
AUDITED_STATUSES = ("ok", "few_points", "no_points")
"""Statuses whose rows carry a posterior (the others were not inferred)."""
DONTCARE = "DontCare"

Format = Literal["parquet", "openpcdet", "mmdet3d"]


# --------------------------------------------------------------------------- results → arrays

_RESULT_COLUMNS = (
    "dataset", "frame_id", "object_index", "object_id", "class_name", "status",
    *R.BOX_COLUMNS, "num_points", "hull_iou", "cov", "cov_dim", "model", "label_line",
)  # fmt: skip


@dataclass
class ResultArrays:
    """The columns of a results table the export needs, as NumPy arrays (N rows).

    ``cov`` holds each row's flattened φ covariance start offset and length in ``cov_values``
    (null lists have length 0); ``num_points`` / ``hull_iou`` are NaN where null.
    """

    dataset: NDArray[np.object_]
    frame_id: NDArray[np.object_]
    object_index: NDArray[np.int64]
    object_id: NDArray[np.object_]
    class_name: NDArray[np.object_]
    status: NDArray[np.object_]
    boxes: FloatArray
    num_points: FloatArray
    hull_iou: FloatArray
    cov_dim: NDArray[np.int64]
    cov_start: NDArray[np.int64]
    cov_len: NDArray[np.int64]
    cov_values: FloatArray
    model: NDArray[np.object_]
    label_line: NDArray[np.int64]
    manifest: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frame_id)

    def cov_phi(self, rows: NDArray[np.int64], p: int) -> FloatArray:
        """(len(rows), p, p) covariances of rows whose list has p² entries."""
        idx = self.cov_start[rows, None] + np.arange(p * p)[None, :]
        return self.cov_values[idx].reshape(len(rows), p, p)


def _np(col: pa.ChunkedArray, fill: Any = None) -> np.ndarray:
    if fill is not None:
        col = col.fill_null(fill)
    return col.to_numpy(zero_copy_only=False)


def read_result_arrays(results: str | Path | pa.Table) -> ResultArrays:
    """Read the rows of a results folder (or one Parquet file, or a table) into :class:`ResultArrays`.

    Raises
    ------
    labelaudit.results.ResultsError
        Unreadable or missing results.
    ExportError
        No rows, or a (frame_id, object_index) key that appears twice.
    """
    manifest: dict[str, Any] = {}
    if isinstance(results, pa.Table):
        missing = [c for c in _RESULT_COLUMNS if c not in results.column_names]
        table = results
        for c in missing:
            table = table.append_column(c, pa.nulls(table.num_rows, R.SCHEMA.field(c).type))
        table = table.select(list(_RESULT_COLUMNS))
        where = "<table>"
    else:
        opened = R.open_results(results)
        manifest = opened.manifest
        table = opened.read(list(_RESULT_COLUMNS))
        where = str(results)
    if table.num_rows == 0:
        raise ExportError(f"{where}: the results hold no objects; nothing to export")
    cov = table.column("cov").combine_chunks()
    lengths = pc.list_value_length(cov).fill_null(0).to_numpy(zero_copy_only=False).astype(np.int64)
    values = pc.list_flatten(cov).to_numpy(zero_copy_only=False).astype(float)  # null entries → NaN
    starts = np.concatenate([[0], np.cumsum(lengths)[:-1]]).astype(np.int64)
    arrays = ResultArrays(
        dataset=_np(table.column("dataset"), ""),
        frame_id=_np(table.column("frame_id")),
        object_index=_np(table.column("object_index"), -1).astype(np.int64),
        object_id=_np(table.column("object_id"), ""),
        class_name=_np(table.column("class_name"), ""),
        status=_np(table.column("status"), ""),
        boxes=np.stack([_np(table.column(c).cast(pa.float64())).astype(float) for c in R.BOX_COLUMNS], axis=1),
        num_points=_np(table.column("num_points").cast(pa.float64())).astype(float),
        hull_iou=_np(table.column("hull_iou").cast(pa.float64())).astype(float),
        cov_dim=_np(table.column("cov_dim"), -1).astype(np.int64),
        cov_start=starts,
        cov_len=lengths,
        cov_values=values if len(values) else np.zeros(1),
        model=_np(table.column("model"), ""),
        label_line=_np(table.column("label_line"), -1).astype(np.int64),
        manifest=manifest,
    )
    keys = Counter(zip(arrays.frame_id.tolist(), arrays.object_index.tolist()))
    dup = next((k for k, n in keys.items() if n > 1), None)
    if dup is not None:
        raise ExportError(f"{where}: frame {dup[0]} object_index {dup[1]} appears {keys[dup]} times; results must have one row per object")
    return arrays


# --------------------------------------------------------------------------- targets


@dataclass
class ExportTargets:
    """σ_p targets of every result row.

    Attributes
    ----------
    encoding : the encoding
    source : where σ_p came from
    std : (N, T) per-target std (NaN where not available)
    cov : (N, T, T) target covariance (NaN where not available)
    valid : (N,) the row has targets
    reason : (N,) why a row has no targets ("" when valid)
    anchor_sizes : class → (l, w, h) used by ``residual`` (empty otherwise)
    """

    encoding: T.Encoding
    source: T.VarianceSource
    std: FloatArray
    cov: FloatArray
    valid: NDArray[np.bool_]
    reason: NDArray[np.object_]
    anchor_sizes: dict[str, tuple[float, float, float]] = field(default_factory=dict)

    def reasons(self) -> dict[str, int]:
        """Count of rows without targets, by reason."""
        return dict(Counter(r for r in self.reason.tolist() if r))

    def metadata(self) -> dict[str, Any]:
        """JSON-able description stored with every output."""
        return {
            "tool": "labelaudit",
            "tool_version": __version__,
            "encoding": self.encoding.name,
            "targets": list(self.encoding.targets),
            "source": str(self.source),
            "anchor_sizes": {k: list(v) for k, v in self.anchor_sizes.items()},
            "std_keys": {"std": INFOS_KEYS[0], "cov": INFOS_KEYS[1], "valid": INFOS_KEYS[2]},
        }


def _prior_std(arrays: ResultArrays) -> tuple[FloatArray, float]:
    """(N, 7) class prior std per row and the prior weight, from the run manifest (defaults without one)."""
    params = (arrays.manifest.get("params") or {}).get("model")
    params = params if isinstance(params, dict) else {}  # no manifest (a bare Parquet file): built-in priors
    priors = dict(C.DEFAULT_PRIORS)
    priors.update(params.get("priors") or {})
    weight = float(params.get("prior_weight", C.DEFAULT_PRIOR_WEIGHT))
    table: dict[str, list[float]] = {}
    for name, p in priors.items():
        try:
            table[name] = [p["center"], p["center"], p["center"], p["length"], p["width"], p["height"], p["yaw"]]
        except (KeyError, TypeError):
            raise ExportError(f"results manifest: prior of class {name!r} lacks center/length/width/height/yaw ({p!r})") from None
    default = table["default"]
    return np.array([table.get(c, default) for c in arrays.class_name.tolist()], dtype=float).reshape(-1, 7), weight


def parse_anchor_sizes(specs: Iterable[str]) -> dict[str, tuple[float, float, float]]:
    """Parse ``CLASS=l,w,h`` strings (``--anchor-size``).

    Raises
    ------
    ExportError
        A malformed spec or a non-positive size; the message quotes it.
    """
    out: dict[str, tuple[float, float, float]] = {}
    for spec in specs:
        name, sep, rest = spec.partition("=")
        parts = rest.split(",")
        try:
            sizes = tuple(float(v) for v in parts)
        except ValueError:
            sizes = ()
        if not sep or not name.strip() or len(sizes) != 3 or not all(math.isfinite(v) and v > 0 for v in sizes):
            raise ExportError(f"--anchor-size {spec!r}: expected CLASS=l,w,h with three sizes > 0 in metres, e.g. Car=3.9,1.6,1.56")
        out[name.strip()] = sizes  # type: ignore[assignment]
    return out


def default_anchor_sizes(datasets: Iterable[str]) -> dict[str, tuple[float, float, float]]:
    """The KITTI or Waymo anchor sizes of :data:`labelaudit.constants.DEFAULT_ANCHOR_SIZES` for the results' dataset."""
    kinds = {"waymo" if str(d).startswith("waymo") else "kitti" for d in datasets}
    out: dict[str, tuple[float, float, float]] = {}
    for kind in sorted(kinds):
        out.update(C.DEFAULT_ANCHOR_SIZES[kind])
    return out


def compute_targets(
    arrays: ResultArrays,
    encoding: str | T.Encoding = "box",
    source: str | T.VarianceSource = "model",
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
) -> ExportTargets:
    """σ_p targets of every row: covariance on y from the source, then :func:`labelaudit.training.propagate`.

    Parameters
    ----------
    arrays : from :func:`read_result_arrays`
    encoding : ``box``, ``log-size`` (= ``centerpoint``), ``pixor`` or ``residual``
    source : ``model`` (posterior covariance of φ), ``num_points``, ``hull_iou`` or ``fixed:VAR``
    anchor_sizes : class → (l, w, h) for ``residual``; None = the defaults for the results'
        dataset, extended/overridden by what is given

    Raises
    ------
    ExportError
        Unknown encoding or source, or a source whose column is null in every row.
    """
    try:
        enc = T.get_encoding(encoding)
        src = source if isinstance(source, T.VarianceSource) else T.parse_source(source)
    except ValueError as exc:
        raise ExportError(str(exc)) from None
    n = len(arrays)
    reason = np.full(n, "", dtype=object)
    audited = np.isin(arrays.status, AUDITED_STATUSES)
    reason[~audited] = [f"status {s}" for s in arrays.status[~audited]]
    b = arrays.boxes
    bad_box = audited & ~(np.all(np.isfinite(b), axis=1) & np.all(b[:, 3:6] > 0, axis=1))
    reason[bad_box] = "invalid box"

    anchors_used: dict[str, tuple[float, float, float]] = {}
    anchor = np.full((n, 3), np.nan)
    if enc.needs_anchor:
        sizes = default_anchor_sizes(arrays.dataset.tolist())
        sizes.update({k: tuple(float(x) for x in v) for k, v in (anchor_sizes or {}).items()})  # type: ignore[misc]
        for name in np.unique(arrays.class_name[reason == ""]).tolist():
            rows = (arrays.class_name == name) & (reason == "")
            if name in sizes:
                anchor[rows] = sizes[name]
                anchors_used[name] = sizes[name]  # type: ignore[assignment]
            else:
                reason[rows] = f"no anchor size for class {name} (--anchor-size {name}=l,w,h)"

    if src.kind == "num_points":
        missing = np.isnan(arrays.num_points)
        what = "num_points"
    elif src.kind == "hull_iou":
        missing = np.isnan(arrays.hull_iou)
        what = "hull_iou"
    elif src.kind == "model":
        p_ok = ((arrays.cov_dim == 6) | (arrays.cov_dim == 8)) & (arrays.cov_len == arrays.cov_dim**2)
        missing = ~p_ok
        what = "cov"
    else:
        missing = np.zeros(n, dtype=bool)
        what = ""
    if what and np.all(missing[audited]) and audited.any():
        raise ExportError(f"source {src}: the column {what!r} is null in every audited row; rerun `labelaudit infer` with this version")
    reason[(reason == "") & missing] = f"no {what}"

    Tn = enc.size
    cov = np.full((n, Tn, Tn), np.nan)
    ok = np.flatnonzero(reason == "")
    if len(ok):
        if src.kind == "fixed":
            cov[ok] = T.fixed_target_covariance(len(ok), enc, float(src.value))  # type: ignore[arg-type]
        elif src.kind == "model":
            for p, model in ((6, "bev"), (8, "3d")):
                rows = ok[arrays.cov_dim[ok] == p]
                if not len(rows):
                    continue
                S = arrays.cov_phi(rows, p)
                finite = np.all(np.isfinite(S.reshape(len(rows), -1)), axis=1)
                reason[rows[~finite]] = "non-finite cov"
                rows, S = rows[finite], S[finite]
                cov_y = T.box_covariance_from_phi(b[rows], S, model)  # type: ignore[arg-type]
                cov[rows] = T.propagate(b[rows], cov_y, enc, anchor_sizes=anchor[rows], available=T.available_params(model))  # type: ignore[arg-type]
        else:
            prior_std, weight = _prior_std(arrays)
            prior_var = T.prior_box_variance(prior_std[ok], weight)
            if src.kind == "num_points":
                scale = T.num_points_scale(np.clip(arrays.num_points[ok], 0, None))
            else:
                scale = T.hull_iou_scale(np.clip(arrays.hull_iou[ok], 0.0, 1.0))
            cov_y = T.heuristic_box_covariance(prior_var, scale)
            cov[ok] = T.propagate(b[ok], cov_y, enc, anchor_sizes=anchor[ok])
    valid = reason == ""
    cov[~valid] = np.nan
    return ExportTargets(enc, src, T.target_std(cov), cov, valid, reason, anchors_used)


# --------------------------------------------------------------------------- Parquet output


def targets_to_table(arrays: ResultArrays, targets: ExportTargets) -> pa.Table:
    """The Parquet table: keys, validity, ``std_<target>`` columns and the covariance (row-major T×T).

    NaN std become null (Parquet's "not applicable"); the covariance list keeps NaN entries for the
    targets a valid row lacks (z and h of a BEV model) and is null for rows without targets.
    """
    n, Tn = len(arrays), targets.encoding.size
    cols: dict[str, pa.Array] = {
        "frame_id": pa.array(arrays.frame_id.tolist(), pa.string()),
        "object_index": pa.array(arrays.object_index, pa.int32()),
        "object_id": pa.array(arrays.object_id.tolist(), pa.string()),
        "class_name": pa.array(arrays.class_name.tolist(), pa.string()),
        "status": pa.array(arrays.status.tolist(), pa.string()),
        "label_line": pa.array(arrays.label_line, pa.int32(), mask=arrays.label_line < 0),
        "valid": pa.array(targets.valid, pa.bool_()),
        "reason": pa.array([r or None for r in targets.reason.tolist()], pa.string()),
    }
    for t, name in enumerate(targets.encoding.targets):
        v = targets.std[:, t]
        cols[f"std_{name}"] = pa.array(v, pa.float64(), mask=np.isnan(v))
    flat = pa.array(targets.cov.reshape(-1), pa.float64())
    offsets = pa.array(np.arange(n + 1, dtype=np.int32) * (Tn * Tn), pa.int32())
    cov = pa.ListArray.from_arrays(offsets, flat, mask=pa.array(~targets.valid))
    cols["cov"] = cov
    cols["cov_dim"] = pa.array(np.full(n, Tn, dtype=np.int32), pa.int32())
    table = pa.table(cols)
    order = np.lexsort((arrays.object_index, arrays.frame_id.astype(str)))
    table = table.take(pa.array(order))
    meta = {**targets.metadata(), "results_param_hash": arrays.manifest.get("param_hash"), "results_input": arrays.manifest.get("input")}
    return table.replace_schema_metadata({b"labelaudit_export": json.dumps(meta, sort_keys=True).encode()})


# --------------------------------------------------------------------------- infos pickles: reading

_ALLOWED_GLOBALS = frozenset(
    {
        ("numpy.core.multiarray", "_reconstruct"),
        ("numpy._core.multiarray", "_reconstruct"),
        ("numpy.core.multiarray", "scalar"),
        ("numpy._core.multiarray", "scalar"),
        ("numpy.core.numeric", "_frombuffer"),
        ("numpy._core.numeric", "_frombuffer"),
        ("numpy", "ndarray"),
        ("numpy", "dtype"),
        ("collections", "OrderedDict"),
        ("builtins", "set"),
        ("builtins", "frozenset"),
        ("builtins", "slice"),
        ("builtins", "complex"),
        ("builtins", "bytearray"),
    }
)
"""Globals an infos pickle may reference: numpy arrays, dtypes and scalars, and builtin containers."""


class _InfosUnpickler(pickle.Unpickler):
    def __init__(self, file: io.BufferedIOBase, source: str) -> None:
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        if (module, name) not in _ALLOWED_GLOBALS:
            raise UnsafePickleError(
                f"{self.source}: refused to load the global {module}.{name}: an infos file holds only numpy arrays, "
                "numbers, strings and containers; this pickle is not an infos file or was tampered with"
            )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)  # numpy.core.* names of NumPy-1 pickles
            return super().find_class(module, name)


def load_infos(path: str | Path) -> Any:
    """Load an OpenPCDet or mmdet3d infos pickle with the restricted unpickler.

    Raises
    ------
    UnsafePickleError
        The pickle references a global outside :data:`_ALLOWED_GLOBALS`.
    ExportError
        Missing or unreadable file, not a pickle.
    """
    path = Path(path)
    if not path.is_file():
        raise ExportError(f"{path}: infos file not found")
    try:
        with open(path, "rb") as f:
            return _InfosUnpickler(f, str(path)).load()  # type: ignore[arg-type]
    except UnsafePickleError:
        raise
    except (pickle.UnpicklingError, EOFError, ValueError, TypeError, AttributeError, ImportError, IndexError, KeyError, OSError) as exc:
        raise ExportError(f"{path}: not a readable infos pickle ({type(exc).__name__}: {exc})") from None


# --------------------------------------------------------------------------- infos pickles: writing


@contextmanager
def _numpy1_global_names() -> Iterator[None]:
    """Pickle NumPy-2 arrays and scalars under their ``numpy.core.multiarray`` names while inside.

    NumPy 2 pickles name ``numpy._core.multiarray._reconstruct``, which NumPy < 1.26 cannot import;
    ``numpy.core.multiarray`` holds the same two functions in every NumPy (1.x, and 2.x's
    compatibility module), so the file loads everywhere. Their ``__module__`` is set for the
    duration of the dump only (the C pickler takes the name from it) and restored afterwards.
    """
    import numpy.core.multiarray as legacy  # noqa: F401 - must resolve for the pickler's identity check

    funcs = [f for f in (getattr(legacy, "_reconstruct", None), getattr(legacy, "scalar", None)) if f is not None]
    saved = [f.__module__ for f in funcs]
    try:
        for f in funcs:
            f.__module__ = "numpy.core.multiarray"
        yield
    finally:
        for f, m in zip(funcs, saved):
            f.__module__ = m


def dump_infos(obj: Any, path: str | Path) -> Path:
    """Pickle ``obj`` to ``path`` atomically (temporary file + rename), loadable with NumPy 1.x and 2.x."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}{R.TMP_MARKER}{os.getpid()}")
    try:
        with open(tmp, "wb") as f, warnings.catch_warnings(), _numpy1_global_names():
            warnings.simplefilter("ignore", DeprecationWarning)
            pickle.dump(obj, f, protocol=C.INFOS_PICKLE_PROTOCOL)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


# --------------------------------------------------------------------------- infos: alignment


@dataclass
class ExportSummary:
    """What an export did (printed by the CLI; ``--json`` prints :meth:`to_dict`)."""

    output: str
    format: str
    encoding: str
    source: str
    results_rows: int
    rows_with_targets: int
    rows_without_targets: dict[str, int]
    infos: str | None = None
    infos_frames: int = 0
    infos_frames_without_results: int = 0
    infos_objects: int = 0
    infos_objects_with_targets: int = 0
    infos_objects_without_targets: dict[str, int] = field(default_factory=dict)
    results_frames_not_in_infos: int = 0
    results_rows_not_in_infos: int = 0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        from dataclasses import asdict

        return asdict(self)


@dataclass
class _FrameObjects:
    """One frame of an infos file: its id, and per object (file order) the key, class and l/w/h."""

    frame_id: str
    keys: list[Any]  # results key per object, None for DontCare
    names: list[str]
    dims_lwh: FloatArray  # (K, 3), NaN where unknown


class _ResultIndex:
    """Result rows by frame, then by object key (object_index for KITTI, object_id for Waymo)."""

    def __init__(self, arrays: ResultArrays, key: Literal["object_index", "object_id"]):
        self.by_frame: dict[str, dict[Any, int]] = {}
        keys = arrays.object_index.tolist() if key == "object_index" else arrays.object_id.tolist()
        for row, (fid, k) in enumerate(zip(arrays.frame_id.tolist(), keys)):
            self.by_frame.setdefault(fid, {})[k] = row
        self.key = key


def _kitti_frame_id(value: Any) -> str:
    if isinstance(value, (int, np.integer)):
        return f"{int(value):06d}"
    return str(value)


def _openpcdet_frames(infos: Any, path: str) -> tuple[str, list[_FrameObjects]]:
    """Parse an OpenPCDet infos list: ('kitti' | 'waymo', frames)."""
    if not isinstance(infos, list):
        raise ExportError(f"{path}: an OpenPCDet infos file is a list of frame dicts, got {type(infos).__name__}")
    frames: list[_FrameObjects] = []
    kinds = set()
    for i, info in enumerate(infos):
        where = f"{path}: frame entry {i}"
        with _malformed(where):
            kind, frame = _openpcdet_frame(info, where)
        kinds.add(kind)
        if len(kinds) > 1:
            raise ExportError(f"{where}: mixes KITTI and Waymo frame entries")
        frames.append(frame)
    return (kinds.pop() if kinds else "kitti"), frames


@contextmanager
def _malformed(where: str) -> Iterator[None]:
    """Turn a type/shape error while reading one infos entry into an ExportError naming it."""
    try:
        yield
    except ExportError:
        raise
    except (TypeError, ValueError, KeyError, IndexError, AttributeError) as exc:
        raise ExportError(f"{where}: malformed entry ({type(exc).__name__}: {exc})") from None


def _openpcdet_frame(info: Any, where: str) -> tuple[str, _FrameObjects]:
    if not isinstance(info, dict) or "point_cloud" not in info:
        raise ExportError(f"{where}: expected a dict with 'point_cloud' and 'annos' (OpenPCDet infos)")
    annos = info.get("annos")
    if not isinstance(annos, dict) or "name" not in annos:
        raise ExportError(f"{where}: no 'annos' with 'name' (a test-split infos file has no labels to attach targets to)")
    names = [str(n) for n in np.asarray(annos["name"]).reshape(-1).tolist()]
    k = len(names)
    dims = np.asarray(annos.get("dimensions", np.full((k, 3), np.nan)), dtype=float).reshape(k, 3)
    pc_info = info["point_cloud"]
    if "lidar_sequence" in pc_info or "obj_ids" in annos:
        md = info.get("metadata") or {}
        if "context_name" not in md or "timestamp_micros" not in md:
            raise ExportError(f"{where}: Waymo infos need 'metadata' with context_name and timestamp_micros to find the frame")
        if "obj_ids" not in annos:
            raise ExportError(f"{where}: Waymo 'annos' have no 'obj_ids' (laser object ids) to align objects by")
        keys: list[Any] = [str(x) for x in np.asarray(annos["obj_ids"]).reshape(-1).tolist()]
        if len(keys) != k:
            raise ExportError(f"{where}: 'obj_ids' has {len(keys)} entries, 'name' {k}")
        # Waymo 'dimensions' are l, w, h
        return "waymo", _FrameObjects(f"{md['context_name']}:{int(md['timestamp_micros'])}", keys, names, dims)
    if "lidar_idx" not in pc_info:
        raise ExportError(f"{where}: 'point_cloud' has no 'lidar_idx' (the KITTI frame id)")
    not_dc = np.array([n != DONTCARE for n in names], dtype=bool)
    ordinal = np.cumsum(not_dc) - 1  # position among the non-DontCare rows = results object_index
    keys = [int(o) if nd else None for o, nd in zip(ordinal, not_dc)]
    # OpenPCDet KITTI 'dimensions' are l, h, w (camera order)
    return "kitti", _FrameObjects(_kitti_frame_id(pc_info["lidar_idx"]), keys, names, dims[:, [0, 2, 1]])


def _mmdet3d_frames(infos: Any, path: str) -> list[_FrameObjects]:
    """Parse an mmdetection3d v2 info dict (KITTI): frames in ``data_list`` with ``instances``."""
    meta = infos.get("metainfo") or {}
    if str(meta.get("dataset", "kitti")).lower() not in ("kitti", ""):
        raise ExportError(
            f"{path}: mmdet3d infos of dataset {meta.get('dataset')!r}: only KITTI v2 infos can be aligned "
            "(mmdet3d's Waymo infos keep no laser object ids); use --format openpcdet or parquet"
        )
    with _malformed(f"{path}: metainfo"):
        label_name = {int(v): str(k) for k, v in (meta.get("categories") or {}).items() if int(v) >= 0}
    frames = []
    for i, item in enumerate(infos.get("data_list") or []):
        where = f"{path}: data_list[{i}]"
        with _malformed(where):
            frames.append(_mmdet3d_frame(item, label_name, where))
    return frames


def _mmdet3d_frame(item: Any, label_name: Mapping[int, str], where: str) -> _FrameObjects:
    if not isinstance(item, dict) or "instances" not in item:
        raise ExportError(f"{where}: expected a dict with 'instances' (mmdet3d v2 info)")
    lidar = item.get("lidar_points") or {}
    if lidar.get("lidar_path"):
        fid = Path(str(lidar["lidar_path"])).stem
    elif "sample_idx" in item:
        fid = _kitti_frame_id(item["sample_idx"])
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
    return _FrameObjects(fid, keys, names, np.asarray(dims, dtype=float).reshape(-1, 3))


def _align(
    frames: Sequence[_FrameObjects], arrays: ResultArrays, targets: ExportTargets, index: _ResultIndex, path: str
) -> tuple[list[NDArray[np.int64]], dict[str, Any]]:
    """Result row of every infos object (−1 where none), checking that the infos describe the results.

    Raises
    ------
    InfosMismatchError
        At the first frame (in file order) whose objects disagree with its result rows: an object
        the infos lack, another class, or other sizes.
    """
    audited_classes = set(arrays.class_name.tolist())
    stats: Counter[str] = Counter()
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
            extra_keys = [k for k in results.keys() - present if not (index.key == "object_id" and arrays.class_name[results[k]] == "Unknown")]
            if extra_keys:
                key = min(extra_keys, key=str)
                what = f"object_index {key}" if index.key == "object_index" else f"object id {key!r}"
                first_extra = (f, f"frame {fr.frame_id}: the results have {what} ({arrays.class_name[results[key]]}) but the infos "
                               f"list {len(present)} non-DontCare object(s) there")  # fmt: skip
        rows = [-2 if k is None else results.get(k, -1) for k in fr.keys]  # -2: DontCare, -1: no row
        for j, r in enumerate(rows):
            if r == -2:
                stats["DontCare"] += 1
            elif r == -1:
                name = fr.names[j]
                if fr.frame_id not in index.by_frame:
                    stats["frame not in the results"] += 1
                elif name not in audited_classes:
                    stats[f"class {name} not audited"] += 1
                else:
                    stats["no result row"] += 1
        per_frame.append(rows)

    # class and size of every matched object at once; the earliest disagreement in file order wins
    sizes = [len(r) for r in per_frame]
    flat = np.array([r for rows in per_frame for r in rows], dtype=np.int64)
    frame_of = np.repeat(np.arange(len(frames)), sizes)
    hit = np.flatnonzero(flat >= 0)
    first_bad: tuple[int, str] | None = None
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
        stats.update(r for r in targets.reason[res_rows].tolist() if r)
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
        "reasons": dict(stats),
        "results_frames_not_in_infos": len(set(index.by_frame) - seen_frames),
        "results_rows_not_in_infos": len(arrays) - len(hit),
    }
    return list(rows_out), extra


def _gather(targets: ExportTargets, rows: NDArray[np.int64]) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.bool_]]:
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
    infos: Any, fmt: Literal["openpcdet", "mmdet3d"], arrays: ResultArrays, targets: ExportTargets, path: str = "<infos>"
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
        kind, frames = _openpcdet_frames(infos, path)
        index = _ResultIndex(arrays, "object_id" if kind == "waymo" else "object_index")
    else:
        if not isinstance(infos, dict) or "data_list" not in infos:
            raise ExportError(f"{path}: an mmdet3d v2 info file is a dict with 'metainfo' and 'data_list'; got {type(infos).__name__}")
        frames = _mmdet3d_frames(infos, path)
        index = _ResultIndex(arrays, "object_index")
    rows, extra = _align(frames, arrays, targets, index, path)
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


# --------------------------------------------------------------------------- the whole export


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{n} {r}" for r, n in sorted(reasons.items(), key=lambda kv: -kv[1])) or "no objects"


def export_results(
    results: str | Path,
    output: str | Path,
    *,
    encoding: str = "box",
    source: str = "model",
    fmt: Format = "parquet",
    infos: str | Path | None = None,
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
) -> ExportSummary:
    """Export σ_p targets of a results folder (see docs/training.md).

    Parameters
    ----------
    results : results folder of ``labelaudit infer`` (or one Parquet file of rows)
    output : the Parquet file, or the infos copy to write
    encoding, source, anchor_sizes : see :func:`compute_targets`
    fmt : ``parquet`` (keyed by frame_id, object_index, object_id), ``openpcdet`` or ``mmdet3d``
    infos : the OpenPCDet / mmdet3d infos pickle to copy (required for those formats)

    Raises
    ------
    ExportError
        Bad options or input (:class:`InfosMismatchError`, :class:`UnsafePickleError`);
        :class:`labelaudit.results.ResultsError` for unreadable results.
    """
    output = Path(output)
    if fmt not in ("parquet", "openpcdet", "mmdet3d"):
        raise ExportError(f"unknown format {fmt!r}; expected parquet, openpcdet or mmdet3d")
    if fmt == "parquet" and infos is not None:
        raise ExportError("--infos is for --format openpcdet or mmdet3d; the Parquet output needs none")
    if fmt != "parquet" and infos is None:
        raise ExportError(f"--format {fmt} writes a copy of an infos file: give it with --infos FILE")
    if infos is not None and output.resolve() == Path(infos).resolve():
        raise ExportError(f"{output}: the output would overwrite the input infos file; write the copy to another path")
    if output.is_dir():
        raise ExportError(f"{output}: is a folder; -o/--output takes a file name")
    arrays = read_result_arrays(results)
    targets = compute_targets(arrays, encoding, source, anchor_sizes)
    summary = ExportSummary(
        output=str(output),
        format=fmt,
        encoding=targets.encoding.name,
        source=str(targets.source),
        results_rows=len(arrays),
        rows_with_targets=int(targets.valid.sum()),
        rows_without_targets=targets.reasons(),
    )
    if arrays.manifest and not arrays.manifest.get("complete", True):
        summary.notes.append(f"{results} is incomplete (infer was stopped); objects of frames not yet audited have no targets")
    if summary.rows_with_targets == 0:
        raise ExportError(f"{results}: no result row has targets ({_reasons_text(summary.rows_without_targets)}); nothing written")
    if fmt == "parquet":
        R.write_parquet_atomic(targets_to_table(arrays, targets), output)
        return summary
    data = load_infos(infos)  # type: ignore[arg-type]
    found = detect_infos_format(data)
    if found != fmt:
        raise ExportError(f"{infos}: this is an {found} infos file, not {fmt}; use --format {found}")
    data, stats = attach_to_infos(data, fmt, arrays, targets, str(infos))
    if stats["objects_with_targets"] == 0:
        raise ExportError(f"{infos}: no object of the infos got targets ({_reasons_text(stats['reasons'])}); nothing written")
    dump_infos(data, output)
    summary.infos = str(infos)
    summary.infos_frames = stats["frames"]
    summary.infos_frames_without_results = stats["frames_without_results"]
    summary.infos_objects = stats["objects"]
    summary.infos_objects_with_targets = stats["objects_with_targets"]
    summary.infos_objects_without_targets = stats["reasons"]
    summary.results_frames_not_in_infos = stats["results_frames_not_in_infos"]
    summary.results_rows_not_in_infos = stats["results_rows_not_in_infos"]
    return summary

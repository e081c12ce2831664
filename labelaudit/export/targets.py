"""σ_p targets of every result row (:class:`ExportTargets`): the source's covariance on y, propagated to an encoding.

The mathematics (encodings, Jacobians, heuristic sources) is :mod:`labelaudit.training`'s; this
module picks, per row, what enters it — the posterior covariance of φ, a heuristic scale of the
class prior or a fixed value, the anchor size of the row's class — and records why a row gets no
targets.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import NDArray

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit import training as T
from labelaudit.errors import ExportError
from labelaudit.export.arrays import ResultArrays

FloatArray = NDArray[np.float64]

__all__ = [
    "AUDITED_STATUSES",
    "INFOS_KEYS",
    "BoxCovariances",
    "ExportTargets",
    "box_covariances",
    "compute_targets",
    "default_anchor_sizes",
    "parse_anchor_sizes",
    "prior_variances",
]

INFOS_KEYS = ("label_std", "label_cov", "label_std_valid")
"""Names of the per-object entries added to each infos object: std (T,), covariance (T, T), mask."""
AUDITED_STATUSES = ("ok", "few_points", "no_points")
"""Statuses whose rows carry a posterior (the others were not inferred)."""


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
            raise ExportError(
                f"results manifest: prior of class {name!r} lacks center/length/width/height/yaw ({p!r})"
            ) from None
    default = table["default"]
    return np.array([table.get(c, default) for c in arrays.class_name.tolist()], dtype=float).reshape(-1, 7), weight


def prior_variances(arrays: ResultArrays) -> FloatArray:
    """(N, 7) variance of y under each row's class prior (std² / w), from the run's manifest."""
    std, weight = _prior_std(arrays)
    return T.prior_box_variance(std, weight)


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
            raise ExportError(
                f"--anchor-size {spec!r}: expected CLASS=l,w,h with three sizes > 0 in metres, e.g. Car=3.9,1.6,1.56"
            )
        out[name.strip()] = sizes  # type: ignore[assignment]
    return out


def default_anchor_sizes(datasets: Iterable[str]) -> dict[str, tuple[float, float, float]]:
    """The KITTI or Waymo anchor sizes of :data:`labelaudit.constants.DEFAULT_ANCHOR_SIZES` for the results' dataset."""
    kinds = {"waymo" if str(d).startswith("waymo") else "kitti" for d in datasets}
    out: dict[str, tuple[float, float, float]] = {}
    for kind in sorted(kinds):
        out.update(C.DEFAULT_ANCHOR_SIZES[kind])
    return out


@dataclass
class BoxCovariances:
    """Covariance of the box parameters y = (cx, cy, cz, l, w, h, yaw) of every result row, before any encoding.

    Attributes
    ----------
    source : where it came from
    cov : (N, 7, 7) covariance of y; NaN for rows without one, and for every row of a ``fixed``
        source (its variance is given on the targets, not on y)
    available : (N, 7) the parameters ``cov`` really holds (a BEV posterior has no cz and h)
    anchor : (N, 3) anchor l, w, h of each row's class; NaN where no anchor was asked for
    reason : (N,) why a row has no covariance ("" when it has one)
    anchor_sizes : class → (l, w, h) used
    """

    source: T.VarianceSource
    cov: FloatArray
    available: NDArray[np.bool_]
    anchor: FloatArray
    reason: NDArray[np.object_]
    anchor_sizes: dict[str, tuple[float, float, float]] = field(default_factory=dict)


def box_covariances(
    arrays: ResultArrays,
    source: str | T.VarianceSource = "model",
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
    *,
    needs_anchor: bool = False,
) -> BoxCovariances:
    """Covariance of y of every row from the source, and why a row has none.

    A row has none when it was not audited (status), its box is not finite or not positive, its
    class has no anchor size (only with ``needs_anchor``), the source's column is null in it, or
    its posterior covariance is not finite.

    Parameters
    ----------
    arrays : from :func:`read_result_arrays`
    source : ``model`` (posterior covariance of φ, mapped to y with the exact Jacobian at the
        label), ``num_points``, ``hull_iou`` (the class prior scaled) or ``fixed:VAR``
    anchor_sizes : class → (l, w, h); None = the defaults for the results' dataset, extended or
        overridden by what is given
    needs_anchor : look up each row's anchor size (rows of a class without one get none)

    Raises
    ------
    ExportError
        Unknown source, or a source whose column is null in every audited row.
    """
    try:
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
    if needs_anchor:
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
        raise ExportError(
            f"source {src}: the column {what!r} is null in every audited row; rerun `labelaudit infer` with this version"
        )
    reason[(reason == "") & missing] = f"no {what}"

    cov = np.full((n, 7, 7), np.nan)
    available = np.ones((n, 7), dtype=bool)
    ok = np.flatnonzero(reason == "")
    if len(ok) and src.kind == "model":
        for p, model in ((6, "bev"), (8, "3d")):
            rows = ok[arrays.cov_dim[ok] == p]
            if not len(rows):
                continue
            S = arrays.cov_phi(rows, p)
            finite = np.all(np.isfinite(S.reshape(len(rows), -1)), axis=1)
            reason[rows[~finite]] = "non-finite cov"
            rows, S = rows[finite], S[finite]
            cov[rows] = T.box_covariance_from_phi(b[rows], S, model)  # type: ignore[arg-type]
            available[rows] = T.available_params(model)  # type: ignore[arg-type]
    elif len(ok) and src.kind in ("num_points", "hull_iou"):
        prior_var = prior_variances(arrays)[ok]
        if src.kind == "num_points":
            scale = T.num_points_scale(np.clip(arrays.num_points[ok], 0, None))
        else:
            scale = T.hull_iou_scale(np.clip(arrays.hull_iou[ok], 0.0, 1.0))
        cov[ok] = T.heuristic_box_covariance(prior_var, scale)
    return BoxCovariances(src, cov, available, anchor, reason, anchors_used)


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
    source, anchor_sizes : see :func:`box_covariances`

    Raises
    ------
    ExportError
        Unknown encoding or source, or a source whose column is null in every row.
    """
    try:
        enc = T.get_encoding(encoding)
    except ValueError as exc:
        raise ExportError(str(exc)) from None
    bc = box_covariances(arrays, source, anchor_sizes, needs_anchor=enc.needs_anchor)
    Tn = enc.size
    cov = np.full((len(arrays), Tn, Tn), np.nan)
    ok = np.flatnonzero(bc.reason == "")
    if len(ok) and bc.source.kind == "fixed":
        cov[ok] = T.fixed_target_covariance(len(ok), enc, float(bc.source.value))  # type: ignore[arg-type]
    elif len(ok):
        b = arrays.boxes[ok]
        cov[ok] = T.propagate(b, bc.cov[ok], enc, anchor_sizes=bc.anchor[ok], available=bc.available[ok])
    return ExportTargets(enc, bc.source, T.target_std(cov), cov, bc.reason == "", bc.reason, bc.anchor_sizes)

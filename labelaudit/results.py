"""The results contract (docs/results-schema.md): Arrow schema, atomic Parquet shards, manifest and reader.
It is the only module that knows the folder layout and the columns; it computes no scores.

A results folder looks like this::

    labelaudit-results/
      manifest.json            run parameters, their hash, tool/schema version, input, completeness
      objects/part-<h>.parquet one shard per chunk of units (h = hash of the chunk's unit keys)
      missing/part-<h>.parquet candidate objects without a label found in that chunk (when the search ran)
      errors/part-<h>.parquet  frame-level errors of that chunk (only when there were any)
      errors.parquet           all frame-level errors of the run, gathered at the end (may be empty)
      tracks.parquet           one row per track (datasets with track ids), written by the tracks pass

Every shard carries the same metadata as the manifest (key ``labelaudit`` in the Parquet schema
metadata). Files are written under a temporary dot-name and renamed, so readers (which ignore
dot-files) only ever see whole files. Readers select columns by name, never by position.

Examples
--------
Audit one simulated frame, then read its rows back by column name:

>>> import tempfile
>>> from pathlib import Path
>>> from labelaudit import InferRequest, load_config, run_infer, simulate_dataset
>>> tmp = tempfile.TemporaryDirectory()
>>> data, out = Path(tmp.name) / "data", Path(tmp.name) / "results"
>>> _ = simulate_dataset(data, frames=1, progress=False)
>>> _ = run_infer(InferRequest(data, out, "kitti", workers=1), load_config(None, "kitti"))
>>> table = open_results(out).read(["frame_id", "object_index", "status", "jiou_gt"])
>>> table.column_names
['frame_id', 'object_index', 'status', 'jiou_gt']
>>> set(table.column("status").to_pylist()) <= set(STATUSES)
True
>>> read_results(out, ["jiou_gt"]).num_rows == table.num_rows > 0
True
>>> read_missing(out).schema.names == MISSING_SCHEMA.names  # the candidates of unlabelled objects
True
>>> tmp.cleanup()
"""

from __future__ import annotations

import json
import math
import os
import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator, Mapping, NamedTuple, Sequence

import numpy as np
import pyarrow as pa

from labelaudit import SCHEMA_VERSION, __version__
from labelaudit.core.params import BOX_FIELDS
from labelaudit.errors import InferError, ResultsError, one_line

if TYPE_CHECKING:
    import pyarrow.dataset as pads

MANIFEST_NAME = "manifest.json"
OBJECTS_DIR = "objects"
MISSING_DIR = "missing"
ERRORS_DIR = "errors"
ERRORS_FILE = "errors.parquet"
TRACKS_FILE = "tracks.parquet"
METADATA_KEY = b"labelaudit"
TMP_MARKER = ".tmp-"

STATUSES = ("ok", "few_points", "no_points", "skipped", "error")
"""Per-object status values: inferred with ≥ min_points / with fewer / with none; not audited
because the box is outside the configured length range; inference raised (see ``message``)."""

BOX_COLUMNS = BOX_FIELDS  # the 7 box parameters, in the order of a box array
STD_COLUMNS = tuple(f"std_{c}" for c in BOX_COLUMNS)


class Column(NamedTuple):
    """One column of the objects table."""

    name: str
    type: pa.DataType
    nullable: bool
    unit: str
    description: str
    source: str  # who fills it: identity / box (infer.rows from the Frame), model (audit_object), row, extra (Frame.extras), track (the tracks pass)


# The box columns after cx, and the sensor distance, as the objects and the missing tables both have them.
_BOX_AFTER_CX: tuple[Column, ...] = (
    Column("cy", pa.float64(), False, "m", "box centre y", "box"),
    Column("cz", pa.float64(), False, "m", "box centre z", "box"),
    Column("length", pa.float64(), False, "m", "box length (along the heading)", "box"),
    Column("width", pa.float64(), False, "m", "box width", "box"),
    Column("height", pa.float64(), False, "m", "box height", "box"),
    Column("yaw", pa.float64(), False, "rad", "heading about +z, in [-π, π)", "box"),
)
_DISTANCE = Column(
    "distance", pa.float64(), False, "m", "horizontal (BEV) distance from the sensor origin to the box centre", "box"
)


# The single definition of the results table. docs/results-schema.md documents the same list;
# tests/test_results.py checks they agree.
COLUMNS: tuple[Column, ...] = (
    Column("dataset", pa.string(), False, "", "dataset format: kitti, waymo-v2, waymo-v1 or av2", "identity"),
    Column(
        "frame_id",
        pa.string(),
        False,
        "",
        "frame id (KITTI '000123', Waymo '<segment>:<timestamp>', Argoverse 2 '<log_id>:<timestamp_ns>')",
        "identity",
    ),
    Column(
        "object_index",
        pa.int32(),
        False,
        "",
        "position of the box among the frame's labels (0-based, DontCare excluded)",
        "identity",
    ),
    Column(
        "object_id",
        pa.string(),
        False,
        "",
        "Waymo laser_object_id, Argoverse 2 track_uuid, else '<frame_id>:<object_index>'",
        "identity",
    ),
    Column("class_name", pa.string(), False, "", "class as written by the dataset", "identity"),
    Column("cx", pa.float64(), False, "m", "box centre x (LiDAR/vehicle frame, geometric centre)", "box"),
    *_BOX_AFTER_CX,
    _DISTANCE,
    Column(
        "num_points",
        pa.int32(),
        True,
        "",
        "LiDAR points cropped for the box (after margin and ground cut); null when skipped",
        "model",
    ),
    Column("status", pa.string(), False, "", "ok | few_points | no_points | skipped | error", "model"),
    Column("message", pa.string(), True, "", "why the status is skipped or error; null otherwise", "row"),
    Column("sigma", pa.float64(), True, "m", "LiDAR noise std σ used by the model", "model"),
    Column(
        "jiou_gt",
        pa.float64(),
        True,
        "",
        "JIoU between the labeled box and its spatial distribution; 1 = no uncertainty",
        "model",
    ),
    Column(
        "label_error",
        pa.float64(),
        True,
        "",
        "how likely the label is wrong (higher = worse); null for classes it is not validated for (constants.LABEL_ERROR_CLASSES, docs/label-error.md)",
        "model",
    ),
    Column(
        "sigma_hat",
        pa.float64(),
        True,
        "m",
        "per-object RMS fit residual of the points to the box (EM σ̂); null with < 2 points",
        "model",
    ),
    Column(
        "fit_offset_m",
        pa.float64(),
        True,
        "m",
        "distance between the labeled box and the model's fitted box; null until computed",
        "model",
    ),
    Column(
        "corner_tv",
        pa.list_(pa.float64()),
        True,
        "m²",
        "total variance of the 4 BEV corners, nearest to the sensor first (C1..C4)",
        "model",
    ),
    Column("std_cx", pa.float64(), True, "m", "posterior std of cx", "model"),
    Column("std_cy", pa.float64(), True, "m", "posterior std of cy", "model"),
    Column("std_cz", pa.float64(), True, "m", "posterior std of cz (null for the BEV model)", "model"),
    Column("std_length", pa.float64(), True, "m", "posterior std of the length", "model"),
    Column("std_width", pa.float64(), True, "m", "posterior std of the width", "model"),
    Column("std_height", pa.float64(), True, "m", "posterior std of the height (null for the BEV model)", "model"),
    Column("std_yaw", pa.float64(), True, "rad", "posterior std of the yaw", "model"),
    Column(
        "cov", pa.list_(pa.float64()), True, "SI", "posterior covariance of φ, row-major cov_dim × cov_dim", "model"
    ),
    Column("cov_dim", pa.int32(), True, "", "dimension of φ: 6 (BEV) or 8 (3D)", "model"),
    Column("model", pa.string(), False, "", "bev or 3d", "model"),
    # Diagnostics of the core beyond the paper (docs/label-error.md); null when the core does not report them.
    Column(
        "fit_cx",
        pa.float64(),
        True,
        "m",
        "centre x of the box the model fits to the points (its suggested box)",
        "model",
    ),
    Column("fit_cy", pa.float64(), True, "m", "centre y of the suggested box", "model"),
    Column("fit_cz", pa.float64(), True, "m", "centre z of the suggested box (null when not fitted in 3D)", "model"),
    Column("fit_length", pa.float64(), True, "m", "length of the suggested box", "model"),
    Column("fit_width", pa.float64(), True, "m", "width of the suggested box", "model"),
    Column("fit_height", pa.float64(), True, "m", "height of the suggested box (null when not fitted in 3D)", "model"),
    Column("fit_yaw", pa.float64(), True, "rad", "yaw of the suggested box", "model"),
    Column(
        "mahalanobis",
        pa.float64(),
        True,
        "",
        "distance between the labeled and the suggested box in posterior std (Mahalanobis)",
        "model",
    ),
    Column(
        "face_gap",
        pa.float64(),
        True,
        "m",
        "of the side faces of the label the sensor sees, the one furthest from where a right label's lies: how far it lies beyond its lower body's outer surface (positive: beyond the points, a label too long or wide there; negative: points outside it); null when no side face is seen",
        "model",
    ),
    Column(
        "hull_iou",
        pa.float64(),
        True,
        "",
        "BEV IoU between the box and the convex hull of its points (baseline; 0 below 3 points)",
        "model",
    ),
    # Free space, neighbours and ground (docs/label-error.md); null when audited without the frame around the box.
    Column(
        "free_rays",
        pa.int32(),
        True,
        "",
        "LiDAR rays that pass through the label's solid lower body (deeper than the tolerance) and end behind it: empty space inside the label (Waymo: rays of the TOP lidar's first returns only)",
        "model",
    ),
    Column(
        "end_rays",
        pa.int32(),
        True,
        "",
        "LiDAR rays that end on or in the label (within the tolerance, above the ground cut) (Waymo: TOP first returns only)",
        "model",
    ),
    Column("fit_free_rays", pa.int32(), True, "", "free_rays of the suggested box", "model"),
    Column("fit_end_rays", pa.int32(), True, "", "end_rays of the suggested box", "model"),
    Column(
        "through_rays",
        pa.int32(),
        True,
        "",
        "rays through the label's solid lower body that passed beyond its own returns in the same direction (under a chassis, through glass) or are second returns (another point nearer on the same ray): not counted in free_rays",
        "model",
    ),
    Column(
        "neighbour_points",
        pa.int32(),
        True,
        "",
        "points of the fit crop dropped because they lie inside another label of the frame",
        "model",
    ),
    Column(
        "scenery_points",
        pa.int32(),
        True,
        "",
        "points of the fit crop dropped because they belong to an unlabelled surface beside the label that runs out of the crop (wall, hedge)",
        "model",
    ),
    Column(
        "ground_z",
        pa.float64(),
        True,
        "m",
        "height of the local ground plane under the box centre; null when too few ground points (fixed cut used)",
        "model",
    ),
    # KITTI extras (null for other formats)
    Column("truncated", pa.float64(), True, "", "KITTI truncation fraction in [0, 1]", "extra"),
    Column("occluded", pa.int32(), True, "", "KITTI occlusion level 0..3 (3 = unknown)", "extra"),
    Column(
        "difficulty",
        pa.string(),
        True,
        "",
        "KITTI difficulty (devkit definition): Easy, Moderate, Hard or unknown",
        "extra",
    ),
    Column("label_line", pa.int32(), True, "", "1-based line of the box in its KITTI label file", "extra"),
    # Waymo extras (null for KITTI)
    Column(
        "num_lidar_points_in_box",
        pa.int32(),
        True,
        "",
        "the dataset's own point count of the box (Waymo num_lidar_points_in_box, Argoverse 2 num_interior_pts; all lidars), to compare with num_points",
        "extra",
    ),
    Column(
        "detection_difficulty",
        pa.int32(),
        True,
        "",
        "Waymo detection difficulty level (0 unknown, 1 LEVEL_1, 2 LEVEL_2)",
        "extra",
    ),
    Column("tracking_difficulty", pa.int32(), True, "", "Waymo tracking difficulty level", "extra"),
    Column("speed_x", pa.float64(), True, "m/s", "Waymo object speed along x (vehicle frame)", "extra"),
    Column("speed_y", pa.float64(), True, "m/s", "Waymo object speed along y", "extra"),
    # Sequences (datasets with ego poses and track ids: Waymo, Argoverse 2); null for KITTI object.
    Column(
        "timestamp",
        pa.float64(),
        True,
        "s",
        "capture time of the frame (Waymo / Argoverse 2 timestamp in seconds); null without one",
        "box",
    ),
    Column(
        "world_cx",
        pa.float64(),
        True,
        "m",
        "box centre x in the world frame (the dataset's ego pose applied); null without a pose",
        "box",
    ),
    Column("world_cy", pa.float64(), True, "m", "box centre y in the world frame", "box"),
    Column("world_cz", pa.float64(), True, "m", "box centre z in the world frame", "box"),
    Column("world_yaw", pa.float64(), True, "rad", "heading about the world z axis, in [-π, π)", "box"),
    Column(
        "track_error",
        pa.float64(),
        True,
        "",
        "probability in [0, 1] that the label contradicts its own track (size, heading or trajectory of the object's other frames); null without a track of ≥ 3 frames",
        "track",
    ),
    Column(
        "track_issue",
        pa.string(),
        True,
        "",
        "what the label contradicts most: size | heading | position | none (below 0.5); null where track_error is null",
        "track",
    ),
)

SCHEMA = pa.schema([pa.field(c.name, c.type, nullable=c.nullable) for c in COLUMNS])
"""Arrow schema of the objects table (one row per labeled box)."""

COLUMN_NAMES: tuple[str, ...] = tuple(SCHEMA.names)
FLOAT_COLUMNS = frozenset(n for n, t, *_ in COLUMNS if pa.types.is_floating(t))
INT_COLUMNS = frozenset(n for n, t, *_ in COLUMNS if pa.types.is_integer(t))
REQUIRED_FLOAT_COLUMNS = frozenset(c.name for c in COLUMNS if pa.types.is_floating(c.type) and not c.nullable)
LIST_COLUMNS = frozenset(n for n, t, *_ in COLUMNS if pa.types.is_list(t))
NUMERIC_COLUMNS = FLOAT_COLUMNS | INT_COLUMNS
IDENTITY_COLUMNS: tuple[str, ...] = tuple(c.name for c in COLUMNS if c.source == "identity")
"""dataset, frame_id, object_index, object_id, class_name: what names an object."""
TRACK_COLUMNS: tuple[str, ...] = tuple(c.name for c in COLUMNS if c.source == "track")
"""track_error, track_issue: filled by the tracks pass over the written shards (:mod:`labelaudit.infer.tracks`), null before it."""
WORLD_COLUMNS = ("timestamp", "world_cx", "world_cy", "world_cz", "world_yaw")
"""The frame's time and the box in the world frame: what the tracks pass reads besides the label."""
KEY_COLUMNS = ("frame_id", "object_index")
"""The key of a row: joins with the dataset's labels (object_index = position in the frame's labels)."""
MODEL_COLUMNS: tuple[str, ...] = tuple(c.name for c in COLUMNS if c.source == "model")
"""The keys :func:`labelaudit.infer.rows.audit_object` returns (status, scores, covariance, fit …)."""
KITTI_EXTRA_COLUMNS = ("truncated", "occluded", "difficulty", "label_line")
WAYMO_EXTRA_COLUMNS = ("num_lidar_points_in_box", "detection_difficulty", "tracking_difficulty", "speed_x", "speed_y")
EXTRA_COLUMNS = KITTI_EXTRA_COLUMNS + WAYMO_EXTRA_COLUMNS
"""Per-object ``Frame.extras`` copied into the results under the same name (others are not kept)."""

ERRORS_SCHEMA = pa.schema(
    [
        pa.field(
            "unit", pa.string(), nullable=False
        ),  # unit key (KITTI frame id, Waymo segment file, Argoverse 2 log folder)
        pa.field("frame_id", pa.string()),  # null when the unit failed before a frame was read
        pa.field("file", pa.string()),  # offending file, when known
        pa.field("line", pa.int64()),  # 1-based line in a text file, when known
        pa.field("level", pa.string(), nullable=False),  # "error" (frame failed) or "warning" (frame kept)
        pa.field("message", pa.string(), nullable=False),
    ]
)
"""Arrow schema of ``errors.parquet``: one row per failed frame (or per warning about a frame)."""


MISSING_SOURCES = ("points", "detections", "both")
"""Where a missing-label candidate comes from: the point-cloud search, a detector's output, or both."""

# The single definition of the missing-label table (``missing/``): one row per candidate object
# that no label explains. The first 14 columns are the contract other commands read; the rest are
# the evidence behind ``score``. docs/results-schema.md documents the same list (a test checks it).
MISSING_COLUMNS: tuple[Column, ...] = (
    Column("frame_id", pa.string(), False, "", "frame id, as in the objects table", "identity"),
    Column(
        "candidate_index",
        pa.int32(),
        False,
        "",
        "position of the candidate among the frame's candidates (0-based, nearest to the sensor first)",
        "identity",
    ),
    Column(
        "class_name",
        pa.string(),
        False,
        "",
        "the audited class the candidate most resembles (by size; the detector's class for detections)",
        "identity",
    ),
    Column(
        "cx",
        pa.float64(),
        False,
        "m",
        "box centre x (LiDAR/vehicle frame, geometric centre), as in the objects table",
        "box",
    ),
    *_BOX_AFTER_CX,
    Column("num_points", pa.int32(), False, "", "LiDAR points of the candidate (above the ground)", "model"),
    _DISTANCE,
    Column(
        "score",
        pa.float64(),
        False,
        "",
        "how likely an object of the audited classes is here without a label, in [0, 1] (higher = more likely)",
        "model",
    ),
    Column("source", pa.string(), False, "", "points | detections | both", "model"),
    # evidence
    Column("dataset", pa.string(), False, "", "dataset format: kitti, waymo-v2, waymo-v1 or av2", "identity"),
    Column(
        "points_score",
        pa.float64(),
        True,
        "",
        "score of the point-cloud evidence alone (product of the four factors below); null for a detection no cluster supports",
        "model",
    ),
    Column(
        "size_score", pa.float64(), True, "", "how well the box size matches the class size prior, in [0, 1]", "model"
    ),
    Column(
        "shape_score",
        pa.float64(),
        True,
        "",
        "how much of the points lie on one or two vertical faces (planar side / L-shape) of the box, in [0, 1]",
        "model",
    ),
    Column(
        "density_score", pa.float64(), True, "", "points against what a car at this range returns, in [0, 1]", "model"
    ),
    Column(
        "free_space_score",
        pa.float64(),
        True,
        "",
        "1 − share of the rays into the box's lower body that pass through it (a real car stops them), in [0, 1]",
        "model",
    ),
    Column(
        "free_rays",
        pa.int32(),
        True,
        "",
        "LiDAR rays that pass through the candidate's lower body and end behind it",
        "model",
    ),
    Column("end_rays", pa.int32(), True, "", "LiDAR rays that end on or in the candidate", "model"),
    Column("ground_z", pa.float64(), True, "m", "height of the ground under the candidate", "model"),
    Column(
        "nearest_label_m",
        pa.float64(),
        True,
        "m",
        "BEV distance from the candidate's centre to the nearest label of the frame (any class); null when the frame has none",
        "model",
    ),
    Column(
        "max_label_iou",
        pa.float64(),
        False,
        "",
        "largest BEV IoU between the candidate and any label of the frame (any class; KITTI's DontCare regions have no 3D box and are applied in the image)",
        "model",
    ),
    Column(
        "detection_score",
        pa.float64(),
        True,
        "",
        "the detector's confidence (source detections / both); null for points-only candidates",
        "model",
    ),
    Column("detection_class", pa.string(), True, "", "the detector's class (source detections / both)", "model"),
    Column("detection_source", pa.string(), True, "", "file and line (or row) of the detection", "model"),
)

MISSING_SCHEMA = pa.schema([pa.field(c.name, c.type, nullable=c.nullable) for c in MISSING_COLUMNS])
"""Arrow schema of the missing-label table (one row per candidate object without a label)."""

MISSING_COLUMN_NAMES: tuple[str, ...] = tuple(MISSING_SCHEMA.names)
MISSING_KEY_COLUMNS = ("frame_id", "candidate_index")
"""The key of a candidate row."""

# --------------------------------------------------------------------------- rows → Arrow


_FLOAT_TYPE = frozenset((float,))


def _clean_list(value: Any) -> list[float | None] | None:
    if value is None:
        return None
    if type(value) is list and set(map(type, value)) <= _FLOAT_TYPE:  # the model's lists: no round trip through NumPy
        return [None if v != v else v for v in value] if any(map(math.isnan, value)) else value.copy()
    return [None if v != v else v for v in np.asarray(value, dtype=float).ravel().tolist()]  # v != v: NaN


_KIND_OF = {  # how normalize_row coerces each column, looked up once per column
    n: "F"
    if n in REQUIRED_FLOAT_COLUMNS
    else "f"
    if n in FLOAT_COLUMNS
    else "i"
    if n in INT_COLUMNS
    else "l"
    if n in LIST_COLUMNS
    else "s"
    for n in COLUMN_NAMES
}
_KIND_OF_ITEMS = tuple(_KIND_OF.items())


def normalize_row(row: Mapping[str, Any]) -> dict[str, Any]:
    """Coerce one result row to plain Python values of the schema's types.

    NaN floats become null (NaN means "not applicable" in the core, e.g. std_cz of a BEV model;
    null is what Parquet consumers expect), except in the label's own non-nullable columns (box,
    distance), where a NaN read from the label file is kept as written (its row has status
    ``error``). A NaN in an integer column (an extra the reader could not read) becomes null.
    Keys outside the schema are dropped; missing keys are null.
    """
    out: dict[str, Any] = {}
    get = row.get
    for name, kind in _KIND_OF_ITEMS:
        value = get(name)
        if value is None:
            out[name] = None
        elif kind == "f":
            v = float(value)
            out[name] = None if v != v else v  # NaN → null
        elif kind == "F":  # the label's own columns: as written, NaN included
            out[name] = float(value)
        elif kind == "i":
            out[name] = None if isinstance(value, float) and value != value else int(value)
        elif kind == "l":
            out[name] = _clean_list(value)
        else:
            out[name] = str(value)
    return out


_STRUCT_OF: dict[int, tuple[pa.Schema, pa.StructType]] = {}  # id(schema) → (schema, its struct type)


def table_of_rows(rows: Sequence[Mapping[str, Any]], schema: pa.Schema) -> pa.Table:
    """``pa.Table.from_pylist(rows, schema=schema)``: the same table (columns, types, nulls, and
    the same errors for values the schema cannot hold), converted as one struct array — Arrow's
    converter reads each dict's values once, where ``from_pylist`` gathers a Python list per column
    first (~40 % less time for a shard's few dozen rows of ~70 columns). Keys outside the schema
    are ignored, missing keys are null, as there."""
    cached = _STRUCT_OF.get(id(schema))
    if cached is None or cached[0] is not schema:
        cached = _STRUCT_OF[id(schema)] = (schema, pa.struct(list(schema)))
    return pa.Table.from_batches([pa.RecordBatch.from_struct_array(pa.array(rows, type=cached[1]))], schema=schema)


def rows_to_table(
    rows: Iterable[Mapping[str, Any]], metadata: Mapping[str, Any] | None = None, *, normalized: bool = False
) -> pa.Table:
    """Build the objects table from row dicts, sorted by (frame_id, object_index) for reproducibility.

    ``normalized=True``: the rows already come from :func:`normalize_row` (as
    ``pipeline.process_frame``'s do), so they are not coerced a second time.
    """
    clean = sorted(
        rows if normalized else (normalize_row(r) for r in rows), key=lambda r: (r["frame_id"], r["object_index"])
    )
    try:
        table = table_of_rows(clean, SCHEMA)
    except (pa.ArrowException, UnicodeError, OverflowError, TypeError, ValueError):
        # A value the schema cannot hold (a file name that is not UTF-8, an integer beyond int32,
        # a null in a required column) must not sink the chunk: fix up the rows that hold one.
        table = table_of_rows([storable_row(r) for r in clean], SCHEMA)
    return table.replace_schema_metadata(_encode_metadata(metadata)) if metadata else table


def safe_text(text: str) -> str:
    """``text`` as valid UTF-8: bytes of a non-UTF-8 file name (surrogate escapes) become ``\\xNN``."""
    try:
        text.encode("utf-8")
        return text
    except UnicodeEncodeError:
        pass
    try:
        return text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")
    except UnicodeEncodeError:  # a lone surrogate that is no escaped byte
        return text.encode("utf-8", "backslashreplace").decode("utf-8")


def storable_row(row: Mapping[str, Any]) -> dict[str, Any]:
    """A normalised row whose every value fits :data:`SCHEMA`.

    Text is made valid UTF-8 (:func:`safe_text`, not an error). A value the schema cannot hold
    otherwise (an integer beyond int32, a null in a required column) is replaced by null (NaN /
    empty in a required column), and the row gets status ``error`` with a message naming the
    column and the value, so nothing is lost silently.
    """
    out = {k: safe_text(v) if isinstance(v, str) else v for k, v in row.items()}
    bad = []
    for f in SCHEMA:
        value = out.get(f.name)
        try:
            if value is None and not f.nullable:
                raise ValueError("null in a required column")
            pa.array([value], type=f.type)
        except (pa.ArrowException, OverflowError, TypeError, ValueError):
            bad.append(f"{f.name}={value!r}")
            if f.nullable:
                out[f.name] = None
            elif pa.types.is_floating(f.type):
                out[f.name] = math.nan
            else:
                out[f.name] = -1 if pa.types.is_integer(f.type) else ""
    if bad:
        before = f"; {out['message']}" if out.get("message") else ""
        out["status"] = "error"
        out["message"] = f"value(s) the results table cannot hold: {', '.join(bad)}{before}"
    return out


def missing_rows_to_table(rows: Iterable[Mapping[str, Any]], metadata: Mapping[str, Any] | None = None) -> pa.Table:
    """Build the missing-label table from row dicts, sorted by (frame_id, candidate_index).

    NaN in a nullable float column becomes null; keys outside :data:`MISSING_SCHEMA` are dropped.
    """
    clean = []
    for row in rows:
        out: dict[str, Any] = {}
        for f in MISSING_SCHEMA:
            value = row.get(f.name)
            if value is not None and pa.types.is_floating(f.type):
                value = float(value)
                if value != value and f.nullable:
                    value = None
            elif value is not None and pa.types.is_integer(f.type):
                value = int(value)
            elif value is not None:
                value = safe_text(str(value))
            out[f.name] = value
        clean.append(out)
    clean.sort(key=lambda r: (r["frame_id"], r["candidate_index"]))
    table = table_of_rows(clean, MISSING_SCHEMA)
    return table.replace_schema_metadata(_encode_metadata(metadata)) if metadata else table


def errors_to_table(errors: Iterable[Mapping[str, Any]], metadata: Mapping[str, Any] | None = None) -> pa.Table:
    """Build the errors table (schema :data:`ERRORS_SCHEMA`) from dicts."""
    names = ERRORS_SCHEMA.names
    clean = [{n: e.get(n) for n in names} for e in errors]
    for e in clean:
        e["level"] = e["level"] or "error"
        e["message"] = str(e["message"])
        if e["line"] is not None:
            e["line"] = int(e["line"])
        for key in ("unit", "frame_id", "file", "message"):  # file names need not be UTF-8
            if e[key] is not None:
                e[key] = safe_text(str(e[key]))
    clean.sort(key=lambda e: (e["unit"], e["frame_id"] or "", e["message"]))
    table = pa.Table.from_pylist(clean, schema=ERRORS_SCHEMA)
    return table.replace_schema_metadata(_encode_metadata(metadata)) if metadata else table


# --------------------------------------------------------------------------- metadata & atomic writes


def run_metadata(
    params: Mapping[str, Any], param_hash: str, input_path: str, dataset_format: str, **extra: Any
) -> dict[str, Any]:
    """The metadata stored in the manifest and in every shard."""
    return {
        "tool": "labelaudit",
        "tool_version": __version__,
        "schema_version": SCHEMA_VERSION,
        "param_hash": param_hash,
        "params": dict(params),
        "input": input_path,
        "format": dataset_format,
        **extra,
    }


def _flatten(d: Any, prefix: str = "") -> dict[str, Any]:
    if not isinstance(d, Mapping):
        return {prefix: d}
    out: dict[str, Any] = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}.{k}" if prefix else str(k)))
    return out


def resume_mismatch(manifest: Mapping[str, Any], metadata: Mapping[str, Any]) -> str | None:
    """Why a results folder (its ``manifest``) cannot be resumed by a run of ``metadata``; None if it can.

    The versions are compared first and on their own: a folder written by another labelaudit or
    schema version is never resumed into, whatever its hash says. Then the fixed numbers
    (``constants_digest``), the parameters (naming the keys that differ), the input, and last
    the hash itself (which covers all of them).
    """
    for key, what in (("tool_version", "labelaudit version"), ("schema_version", "results schema version")):
        if manifest.get(key) != metadata.get(key):
            return f"written by {what} {manifest.get(key)!r}, running {metadata.get(key)!r}"
    if manifest.get("constants_digest") != metadata.get("constants_digest"):
        return (
            f"computed with other model constants (constants_digest {manifest.get('constants_digest')!r}, "
            f"now {metadata.get('constants_digest')!r}: labelaudit/constants.py or its data changed)"
        )
    old, new = _flatten(manifest.get("params", {})), _flatten(metadata.get("params", {}))
    differ = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
    if differ:
        shown = "; ".join(f"{k} {old.get(k)!r} → {new.get(k)!r}" for k in differ[:5])
        more = f" and {len(differ) - 5} more" if len(differ) > 5 else ""
        return f"computed with other parameters ({shown}{more}; set by --config/--classes/--model)"
    for key, what in (("input", "input dataset (DATASET)"), ("format", "dataset format (--format)")):
        if manifest.get(key) != metadata.get(key):
            return f"holds results for another {what}: {manifest.get(key)!r}, now {metadata.get(key)!r}"
    if manifest.get("param_hash") != metadata.get("param_hash"):
        return f"parameter hash {manifest.get('param_hash')!r} differs from this run's {metadata.get('param_hash')!r}"
    return None


def _encode_metadata(metadata: Mapping[str, Any]) -> dict[bytes, bytes]:
    return {METADATA_KEY: json.dumps(metadata, sort_keys=True).encode()}


def with_metadata(table: pa.Table, metadata: Mapping[str, Any]) -> pa.Table:
    """``table`` with the labelaudit run metadata attached (stored in the Parquet footer)."""
    return table.replace_schema_metadata(_encode_metadata(metadata))


def shard_metadata(path: str | Path) -> dict[str, Any]:
    """The labelaudit metadata of one Parquet file (empty dict when absent)."""
    import pyarrow.parquet as pq

    meta = pq.read_schema(path).metadata or {}
    raw = meta.get(METADATA_KEY)
    return json.loads(raw) if raw else {}


def _tmp_name(path: Path) -> Path:
    return path.with_name(f".{path.name}{TMP_MARKER}{os.getpid()}")


def write_parquet(table: pa.Table, sink: Any) -> None:
    """Write ``table`` as Parquet to ``sink`` (a path or a file object), as every results file is
    written: Snappy (zstd creates a compression context per column, about half of a small shard's
    write, for files only 2–11 % smaller), dictionary encoding for the text columns only (a float
    column is all distinct values: its dictionary pages cost about a third of the write and make
    the file larger)."""
    import pyarrow.parquet as pq

    text = [f.name for f in table.schema if pa.types.is_string(f.type) or pa.types.is_large_string(f.type)]
    pq.write_table(table, sink, compression="snappy", use_dictionary=text)


def parquet_bytes(table: pa.Table) -> bytes:
    """``table`` as the bytes of a Parquet file, exactly as :func:`write_parquet` writes it to a file
    (a worker encodes its chunk's shards so the process that writes them only stores bytes:
    :func:`write_bytes_atomic`)."""
    sink = pa.BufferOutputStream()
    write_parquet(table, sink)
    return sink.getvalue().to_pybytes()


def _write_atomic(path: str | Path, write: Callable[[Path], object]) -> Path:
    """``write`` a temporary dot-file beside ``path``, then :func:`os.replace` it onto ``path``; no
    temporary is left on failure (a killed writer leaves at most a dot-file readers ignore)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _tmp_name(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return path


def write_parquet_atomic(table: pa.Table, path: str | Path) -> Path:
    """Write ``table`` to ``path`` through a temporary dot-file and :func:`os.replace` (:func:`write_parquet`).

    A killed writer leaves at most a dot-file that readers ignore and the next run removes.
    """
    return _write_atomic(path, lambda tmp: write_parquet(table, tmp))


def write_json_atomic(data: Mapping[str, Any], path: str | Path) -> Path:
    """Write JSON through a temporary file and rename (same guarantee as Parquet shards)."""
    return write_text_atomic(json.dumps(data, indent=2, sort_keys=True) + "\n", path)


def write_bytes_atomic(data: bytes, path: str | Path) -> Path:
    """Write ``data`` (e.g. :func:`parquet_bytes`) through a temporary dot-file and :func:`os.replace`
    (no temporary is left on failure)."""
    return _write_atomic(path, lambda tmp: tmp.write_bytes(data))


def write_text_atomic(text: str, path: str | Path) -> Path:
    """Write UTF-8 text through a temporary dot-file and :func:`os.replace` (no temporary is left on failure)."""
    return _write_atomic(path, lambda tmp: tmp.write_text(text, encoding="utf-8"))


def remove_temp_files(root: str | Path) -> list[Path]:
    """Delete temporary files a killed run may have left in a results folder; returns what was removed."""
    root = Path(root)
    removed = []
    for sub in (root, root / OBJECTS_DIR, root / ERRORS_DIR, root / MISSING_DIR):
        if sub.is_dir():
            for p in sub.glob(f".*{TMP_MARKER}*"):
                _remove(p)
                removed.append(p)
    return removed


def damaged(path: Path, what: str) -> ResultsError:
    """The error of a damaged results folder: names the path, what is wrong and the fix."""
    return ResultsError(
        f"{path}: {what} — the results folder is damaged; rerun `labelaudit infer` with --overwrite to replace it, "
        "or choose another -o/--output"
    )


def read_manifest(root: str | Path) -> dict[str, Any] | None:
    """The manifest of a results folder, or None when there is none.

    Raises
    ------
    ResultsError
        The manifest exists but is not a file, not UTF-8, not valid JSON or not a JSON object.
    """
    path = Path(root) / MANIFEST_NAME
    if not os.path.lexists(path):
        return None
    if not path.is_file():
        raise damaged(path, "the manifest is not a file")
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except OSError as exc:
        raise damaged(path, f"cannot read the manifest ({exc.strerror or exc})") from None
    except UnicodeDecodeError as exc:
        raise damaged(path, f"the manifest is not UTF-8 text (byte offset {exc.start})") from None
    except json.JSONDecodeError as exc:
        raise damaged(path, f"the manifest is not valid JSON ({exc})") from None
    if not isinstance(data, dict):
        raise damaged(path, f"the manifest is JSON {type(data).__name__}, expected an object")
    return data


# --------------------------------------------------------------------------- reading


@dataclass
class Results:
    """An opened results folder (or a single Parquet file of objects).

    Attributes
    ----------
    root : the folder (or file) that was opened
    dataset : pyarrow dataset over the object shards
    manifest : the run manifest (empty dict for a bare Parquet file)
    """

    root: Path
    dataset: pads.Dataset
    manifest: dict[str, Any]

    @property
    def columns(self) -> list[str]:
        return list(self.dataset.schema.names)

    @property
    def complete(self) -> bool:
        """False when the manifest says the run stopped before all shards were written."""
        return bool(self.manifest.get("complete", True))

    def read(self, columns: Sequence[str] | None = None) -> pa.Table:
        """Read the given columns (all when None); missing optional columns come back as nulls."""
        if columns is None:
            return self.dataset.to_table()
        present = [c for c in columns if c in self.dataset.schema.names]
        table = self.dataset.to_table(columns=present)
        for c in columns:
            if c not in present:
                typ = SCHEMA.field(c).type if c in COLUMN_NAMES else pa.null()
                table = table.append_column(c, pa.nulls(table.num_rows, typ))
        return table.select(list(columns))

    def errors(self) -> pa.Table:
        """Frame-level errors and warnings (empty table when there were none)."""
        if self.root.is_file():
            return ERRORS_SCHEMA.empty_table()
        path = self.root / ERRORS_FILE
        if os.path.lexists(path):
            return read_error_tables([path])
        parts = sorted((self.root / ERRORS_DIR).glob("*.parquet")) if (self.root / ERRORS_DIR).is_dir() else []
        if parts:
            return read_error_tables(parts)
        return ERRORS_SCHEMA.empty_table()

    def missing(self) -> pa.Table:
        """The missing-label candidates (:func:`read_missing`; empty when the search did not run)."""
        return read_missing(self.root)

    def tracks(self) -> pa.Table | None:
        """``tracks.parquet`` (one row per track), or None when the run has none (KITTI, a bare file)."""
        import pyarrow.parquet as pq

        path = self.root / TRACKS_FILE
        if self.root.is_file() or not os.path.lexists(path):
            return None
        try:
            return pq.read_table(path)
        except (pa.ArrowException, OSError) as exc:
            raise damaged(path, f"unreadable tracks table ({one_line(str(exc))})") from None

    def failed_frames(self) -> int:
        """Number of frames (or units) that failed as a whole."""
        import pyarrow.compute as pc

        errs = self.errors()
        return int(pc.sum(pc.equal(errs["level"], "error")).as_py() or 0) if errs.num_rows else 0


def read_error_tables(paths: Sequence[Path]) -> pa.Table:
    """The errors tables of ``paths`` as one table; a damaged file is a :class:`ResultsError` naming it."""
    import pyarrow.parquet as pq

    tables = []
    for p in paths:
        try:
            if not p.is_file():
                raise damaged(p, "not a file")
            tables.append(pq.read_table(p).cast(ERRORS_SCHEMA))
        except (pa.ArrowException, OSError, ValueError) as exc:
            raise damaged(p, f"unreadable errors table ({one_line(str(exc))})") from None
    return pa.concat_tables(tables) if tables else ERRORS_SCHEMA.empty_table()


def read_missing(results_dir: str | Path) -> pa.Table:
    """The missing-label table of a results folder: one row per candidate object without a label.

    Columns are those of :data:`MISSING_SCHEMA` (in that order; a column an older shard lacks
    comes back as nulls), rows sorted by (``frame_id``, ``candidate_index``). A folder without
    ``missing/`` (the search was off, ``--no-missing``, or results of an older build) or a single
    Parquet file of objects gives an empty table with the schema.

    Raises
    ------
    ResultsError
        The path does not exist, or a shard of ``missing/`` is not a readable Parquet file.

    An example that runs: the module's docstring.
    """
    import pyarrow.parquet as pq

    root = Path(results_dir)
    try:
        exists = root.exists()
    except OSError as exc:
        raise ResultsError(f"{root}: cannot open ({exc.strerror or exc})") from None
    if not exists:
        raise ResultsError(f"{root}: no such results folder; run `labelaudit infer DATASET -o {root}` first")
    folder = root / MISSING_DIR
    if root.is_file() or not folder.is_dir():
        return MISSING_SCHEMA.empty_table()
    tables = []
    for part in sorted(p for p in folder.glob("*.parquet") if not p.name.startswith((".", "_"))):
        try:
            if not part.is_file():
                raise damaged(part, "a shard that is not a file")
            t = pq.read_table(part)
        except (pa.ArrowException, OSError) as exc:
            raise damaged(part, f"unreadable missing-label shard ({one_line(str(exc))})") from None
        cols = []
        for f in MISSING_SCHEMA:
            if f.name in t.column_names:
                cols.append(t.column(f.name).cast(f.type))
            else:
                cols.append(pa.nulls(t.num_rows, f.type))
        tables.append(pa.Table.from_arrays(cols, schema=MISSING_SCHEMA))
    if not tables:
        return MISSING_SCHEMA.empty_table()
    table = pa.concat_tables(tables)
    return table.sort_by([(k, "ascending") for k in MISSING_KEY_COLUMNS])


def open_results(path: str | Path) -> Results:
    """Open a results folder written by ``labelaudit infer`` (or one Parquet file of objects).

    Raises
    ------
    ResultsError
        Path missing, no shards, or files that are not Parquet.
    """
    import pyarrow.dataset as pads
    import pyarrow.parquet as pq

    root = Path(path)
    try:
        exists = root.exists()
    except OSError as exc:  # e.g. a name too long for the file system
        raise ResultsError(f"{root}: cannot open ({exc.strerror or exc})") from None
    if not exists:
        raise ResultsError(f"{root}: no such results folder; run `labelaudit infer DATASET -o {root}` first")
    try:
        if root.is_file():
            return Results(root, pads.dataset(root, format="parquet", schema=None), {})
        manifest = read_manifest(root) or {}
        shard_dir = root / OBJECTS_DIR
        files = (
            sorted(p for p in shard_dir.glob("*.parquet") if not p.name.startswith((".", "_")))
            if shard_dir.is_dir()
            else []
        )
        if not files:
            raise ResultsError(
                f"{root}: no result shards in {shard_dir}; is this a labelaudit results folder? "
                "Run `labelaudit infer DATASET -o FOLDER` first"
            )
        # One schema for all shards: the current SCHEMA plus whatever columns the files add, so
        # shards of an older build (fewer columns) read as nulls instead of hiding columns.
        schema = pa.unify_schemas([SCHEMA] + [pq.read_schema(f) for f in files]).with_metadata(
            pq.read_schema(files[0]).metadata
        )
        dataset = pads.dataset([str(f) for f in files], format="parquet", schema=schema)
        return Results(root, dataset, manifest)
    except (pa.ArrowException, OSError) as exc:
        raise ResultsError(
            f"{root}: unreadable results ({one_line(str(exc))}); rerun `labelaudit infer --overwrite`"
        ) from None


# --------------------------------------------------------------------------- writing: lock and resume


def is_whole_parquet(path: Path) -> bool:
    """Whether ``path`` is a complete Parquet file (its footer reads)."""
    import pyarrow.parquet as pq

    try:
        pq.read_metadata(path)
        return True
    except Exception:
        return False


LOCK_NAME = ".labelaudit.lock"
"""Lock file of a results folder while ``infer`` writes to it (holds the writer's pid)."""


def check_output_folder(output: Path) -> None:
    """Refuse an output path ``infer`` cannot use, with a one-line reason (:class:`InferError`).

    Refused: a dangling symbolic link, a file, a path under a file, a name the file system cannot
    hold (too long …), a non-empty folder that is not a results folder.
    """
    try:
        if output.is_symlink() and not output.exists():
            raise InferError(
                f"{output}: is a symbolic link to {os.readlink(output)}, which does not exist; choose another -o/--output"
            )
        if output.exists() and not output.is_dir():
            raise InferError(f"{output}: exists and is not a folder; choose another -o/--output")
        if output.is_dir():
            if not os.path.lexists(output / MANIFEST_NAME) and any(p.name != LOCK_NAME for p in output.iterdir()):
                raise InferError(
                    f"{output}: folder is not empty and has no {MANIFEST_NAME} (not a labelaudit results folder); "
                    "choose a new or empty -o/--output"
                )
            return
        for parent in output.absolute().parents:  # the first one that exists must be a folder
            if os.path.lexists(parent):
                if not parent.is_dir():
                    raise InferError(f"{output}: {parent} is not a folder; choose another -o/--output")
                break
    except OSError as exc:
        raise InferError(
            f"{output}: cannot use this results folder ({exc.strerror or exc}); choose another -o/--output"
        ) from None


def make_output_folder(output: Path) -> None:
    """Create ``output`` (and its parents); an OS refusal becomes a one-line :class:`InferError`."""
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InferError(
            f"{output}: cannot create the results folder ({exc.strerror or exc}); choose another -o/--output"
        ) from None


def _pid_alive(pid: int) -> bool:
    if pid <= 0:  # 0 and negative numbers address process groups, not a writer
        return False
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):
        return False
    except PermissionError:  # exists, owned by someone else
        return True
    return True


def _remove(path: Path) -> None:
    """Delete a file, a symbolic link or a folder tree (never through a link)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    elif os.path.lexists(path):
        path.unlink()


@contextmanager
def output_lock(output: Path, overwrite: bool = False) -> Iterator[None]:
    """Hold ``output/.labelaudit.lock`` for the duration of a run.

    A second ``infer`` on the same folder stops with :class:`InferError` instead of interleaving
    shards; a lock left by a killed run (its pid is gone) is taken over. A lock path that is not a
    file (damage) is a :class:`ResultsError`, or removed with ``overwrite``. Same-machine only.
    """
    make_output_folder(output)
    path = output / LOCK_NAME
    if os.path.lexists(path) and (path.is_symlink() or not path.is_file()):
        if not overwrite:
            raise damaged(path, "the lock is not a file")
        _remove(path)
    for _ in range(3):
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
        except FileExistsError:
            try:
                pid = int(path.read_text().strip() or 0)
            except (OSError, ValueError):
                pid = 0
            if pid and pid != os.getpid() and _pid_alive(pid):
                raise InferError(
                    f"{output}: another labelaudit infer (pid {pid}) is writing to this folder; wait for it or choose another -o/--output"
                ) from None
            path.unlink(missing_ok=True)  # stale: its writer is gone
            continue
        except OSError as exc:
            raise InferError(
                f"{path}: cannot take the lock ({exc.strerror or exc}); choose another -o/--output"
            ) from None
        with os.fdopen(fd, "w") as f:
            f.write(str(os.getpid()))
        break
    else:
        raise InferError(f"{output}: cannot take the lock {path}")
    try:
        yield
    finally:
        path.unlink(missing_ok=True)


def check_layout(output: Path) -> None:
    """Refuse a results folder whose parts have the wrong kind (:class:`ResultsError` naming the path).

    ``manifest.json`` (checked by :func:`read_manifest`) and ``errors.parquet`` must be files,
    ``objects/``, ``errors/`` and ``missing/`` folders, and every shard in them a file. A truncated shard is not
    damage: its chunk is recomputed (:func:`chunk_state`).
    """
    for name in (OBJECTS_DIR, ERRORS_DIR, MISSING_DIR):
        sub = output / name
        if os.path.lexists(sub):
            if not sub.is_dir():
                raise damaged(sub, "expected a folder of Parquet shards, found a file")
            for part in sub.glob("*.parquet"):
                if not part.name.startswith(".") and not part.is_file():
                    raise damaged(part, "a shard that is not a file")
    if os.path.lexists(output / ERRORS_FILE) and not (output / ERRORS_FILE).is_file():
        raise damaged(output / ERRORS_FILE, "expected the errors table (a Parquet file), found a folder")


def chunk_record(table: pa.Table, errors: Sequence[Mapping[str, Any]]) -> dict[str, int]:
    """What a chunk's object shard records about the chunk (key ``chunk`` of its metadata), so a
    resumed run can tell a clean chunk from one to run again without its errors part."""
    failed_objects = (
        table.column("status").to_pylist().count("error")
    )  # (not pyarrow.compute: its import is 0.1 s of a short run)
    return {
        "notes": len(errors),
        "failed_frames": sum(1 for e in errors if e.get("level") == "error"),
        "failed_objects": failed_objects,
    }


def chunk_state(shard: Path, error_part: Path, missing_part: Path | None = None) -> str:
    """Whether a chunk of an earlier run can be kept: ``"done"``, ``"missing"`` or ``"retry"``.

    ``missing``: no whole object shard (never written, or truncated by a kill). ``retry``: the
    shard is whole but the chunk had a failed frame or an object with status ``error`` — the
    input may have been fixed since, so ``--resume`` runs it again and its stale errors go with
    its old rows — or its errors part is missing, unreadable or of another run (the shard's
    :func:`chunk_record` says how many rows it must have). ``missing_part``: the chunk's
    missing-label shard when the run searches for unlabelled objects; not a whole Parquet file:
    ``missing`` (the shard is written before the object shard, so this only follows damage).
    """
    import pyarrow.parquet as pq

    if missing_part is not None and not is_whole_parquet(missing_part):
        return "missing"
    try:
        footer = pq.read_metadata(shard)
        meta = json.loads((footer.metadata or {}).get(METADATA_KEY, b"{}"))
    except Exception:  # truncated, not Parquet, a folder …
        return "missing"
    record = meta.get("chunk") if isinstance(meta, dict) else None
    if not isinstance(record, dict):  # a shard of an older run: look at the rows themselves
        return _chunk_state_from_rows(shard, error_part)
    if record.get("failed_frames") or record.get("failed_objects"):
        return "retry"
    notes = record.get("notes", 0)
    if not os.path.lexists(error_part):
        return "retry" if notes else "done"
    try:
        return "done" if notes and pq.read_metadata(error_part).num_rows == notes else "retry"
    except Exception:
        return "retry"


def _chunk_state_from_rows(shard: Path, error_part: Path) -> str:
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    if os.path.lexists(error_part):
        try:
            levels = pq.read_table(error_part, columns=["level"]).column("level")
        except (pa.ArrowException, OSError, KeyError):
            return "retry"
        if pc.any(pc.equal(levels, "error")).as_py():
            return "retry"
    try:
        status = pq.read_table(shard, columns=["status"]).column("status")
    except (pa.ArrowException, OSError, KeyError):
        return "retry"
    return "retry" if pc.any(pc.equal(status, "error")).as_py() else "done"


def prepare_output(output: Path, metadata: Mapping[str, Any], overwrite: bool) -> None:
    """Create, reset (``--overwrite``) or check for resume a results folder.

    With ``overwrite`` the results of the folder (manifest, shards, errors) are deleted whatever
    state they are in, so a damaged folder can always be replaced.

    Raises
    ------
    InferError
        The folder is not a results folder, or holds results of other parameters / another input
        (unless ``overwrite``).
    ResultsError
        The folder is damaged (:func:`read_manifest`, :func:`check_layout`), unless ``overwrite``.
    """
    check_output_folder(output)
    if overwrite:
        for name in (OBJECTS_DIR, ERRORS_DIR, MISSING_DIR, ERRORS_FILE, TRACKS_FILE, MANIFEST_NAME):
            try:
                _remove(output / name)
            except OSError as exc:
                raise InferError(f"{output / name}: cannot remove it for --overwrite ({exc.strerror or exc})") from None
    else:
        manifest = read_manifest(output) if output.is_dir() else None
        if manifest is not None:
            why = resume_mismatch(manifest, metadata)
            if why is not None:
                raise InferError(
                    f"{output}: cannot resume: {why}; pass --overwrite to replace these results, or choose another -o/--output"
                )
        if output.is_dir():
            check_layout(output)
    make_output_folder(output)
    remove_temp_files(output)


def read_results(path: str | Path, columns: Sequence[str] | None = None) -> pa.Table:
    """The objects table of a results folder (or one Parquet file) as one Arrow table.

    Shorthand for ``open_results(path).read(columns)``; missing optional columns come back as nulls
    (an example that runs: the module's docstring).
    """
    return open_results(path).read(columns)

"""The tracks pass: after every chunk is written, judge each label against its own track.

A track (one object id within one Waymo segment / Argoverse 2 log) may span chunks, so the pass
runs once over the written rows, never inside a worker: it reads the columns it needs from every
shard, scores every track whole (:mod:`labelaudit.core.track`), rewrites each shard atomically
with ``track_error`` / ``track_issue`` filled (the rows themselves are still defined only by
:mod:`labelaudit.results` and :mod:`labelaudit.infer.rows`) and writes ``tracks.parquet``, one
row per track. The pass depends only on the rows, never on how they were chunked or on the worker
count, so it is bit-identical across both; a killed pass is simply run again by ``--resume``.

The ordinary per-frame label noise is the run's own, pooled per class (robust: 1.4826 × the
median absolute standardised residual), never below :data:`~labelaudit.constants.TRACK_NOISE_FLOOR`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pyarrow as pa

from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.config import RunConfig
from labelaudit.core import track as T
from labelaudit.core.geometry import normalize_angle

NEEDED_COLUMNS = (
    "dataset", "frame_id", "object_index", "object_id", "class_name", "status",
    "length", "width", "height", *R.WORLD_COLUMNS,
    "fit_length", "fit_width", "fit_height", "std_length", "std_width", "std_height",
)
"""What the pass reads from the shards."""

_NOISE_KEYS = ("center", "length", "width", "height", "yaw")


@dataclass
class TrackScores:
    """Scores of every row of a results table (row order of the table the pass read).

    Attributes
    ----------
    track_error : (R,) float, NaN where the row has no scored track
    track_issue : R values from :data:`labelaudit.core.track.ISSUES` or ``none``; None where unscored
    tracks : one dict per track (the columns of :data:`TRACKS_SCHEMA`)
    noise : class → the per-frame label noise used (centre, length, width, height, yaw)
    """

    track_error: np.ndarray
    track_issue: list[str | None]
    tracks: list[dict[str, Any]]
    noise: dict[str, dict[str, float]]


TRACKS_SCHEMA = pa.schema(
    [
        pa.field("log_id", pa.string(), nullable=False),  # Waymo segment / Argoverse 2 log: frame_id before its last ':'
        pa.field("object_id", pa.string(), nullable=False),  # the dataset's track id
        pa.field("class_name", pa.string(), nullable=False),  # the most frequent class of the track's labels
        pa.field("frames", pa.int32(), nullable=False),  # labelled frames of the track that were judged
        pa.field("first_frame_id", pa.string(), nullable=False),
        pa.field("last_frame_id", pa.string(), nullable=False),
        pa.field("duration", pa.float64(), nullable=False),  # s, last minus first timestamp
        pa.field("length", pa.float64()),  # m, posterior mean of the track's (rigid) size …
        pa.field("width", pa.float64()),
        pa.field("height", pa.float64()),
        pa.field("std_length", pa.float64()),  # m, … and its posterior std
        pa.field("std_width", pa.float64()),
        pa.field("std_height", pa.float64()),
        pa.field("mean_speed", pa.float64()),  # m/s, mean BEV speed of the centre from the local fits
        pa.field("heading_vs_motion", pa.float64()),  # rad, circular mean of heading − direction of motion over the moving frames (≈ ±π: labelled backwards or reversing); null when never moving
        pa.field("flagged", pa.int32(), nullable=False),  # frames with track_error ≥ TRACK_FLAG
        pa.field("max_track_error", pa.float64()),  # the worst frame's track_error (null: too short to judge)
        pa.field("worst_frame_id", pa.string()),  # frame_id and object_index of that frame
        pa.field("worst_object_index", pa.int32()),
        pa.field("worst_issue", pa.string()),  # its track_issue
    ]
)
"""Arrow schema of ``tracks.parquet`` (one row per track; docs/results-schema.md)."""


def log_of(frame_id: str) -> str:
    """The segment / log of a frame id ``'<log>:<timestamp>'`` (the whole id when it has no ':')."""
    return frame_id.rsplit(":", 1)[0]


def _column(table: pa.Table, name: str) -> np.ndarray:
    return np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)


def _eligible(table: pa.Table) -> np.ndarray:
    """Rows that take part: a tracked format, a time, a world box, a real track id, a usable label."""
    n = table.num_rows
    fmt = table.column("dataset").to_pylist()
    frame = table.column("frame_id").to_pylist()
    index = table.column("object_index").to_pylist()
    oid = table.column("object_id").to_pylist()
    status = table.column("status").to_pylist()
    finite = np.ones(n, dtype=bool)
    for c in (*R.WORLD_COLUMNS, "length", "width", "height"):
        finite &= np.isfinite(_column(table, c))
    ok = np.array(
        [fmt[i] in C.TRACK_FORMATS and status[i] != "error" and oid[i] != f"{frame[i]}:{index[i]}" for i in range(n)], dtype=bool
    ) if n else np.zeros(0, dtype=bool)
    return ok & finite


def _noise_from(values: Mapping[str, float]) -> T.TrackNoise:
    return T.TrackNoise(np.full(3, values["center"]), np.array([values["length"], values["width"], values["height"]]), values["yaw"])


def _size_evidence(table: pa.Table, rows: np.ndarray, cfg: RunConfig | None, class_name: str) -> tuple[np.ndarray, np.ndarray] | None:
    """Each frame's fitted size and its data precision (per-frame posterior minus the prior), 0 without points."""
    if cfg is None:
        return None
    prior = cfg.model.prior_for(class_name)
    w = cfg.model.prior_weight
    fit = np.stack([_column(table, f"fit_{d}")[rows] for d in ("length", "width", "height")], axis=1)
    std = np.stack([_column(table, f"std_{d}")[rows] for d in ("length", "width", "height")], axis=1)
    prior_prec = w / np.array([prior.length, prior.width, prior.height]) ** 2
    status = np.array(table.column("status").to_pylist(), dtype=object)[rows]
    with np.errstate(divide="ignore", invalid="ignore"):
        data = 1.0 / (std * std) - prior_prec
    ok = (status == "ok")[:, None] & np.isfinite(fit) & np.isfinite(data)
    return np.where(ok, fit, np.nan), np.where(ok, np.maximum(data, 0.0), 0.0)


def _groups(table: pa.Table, rows: np.ndarray) -> list[np.ndarray]:
    """Row indices of each track (sorted by log, object id, then time; repeated times left out)."""
    frame = table.column("frame_id").to_pylist()
    oid = table.column("object_id").to_pylist()
    ts = _column(table, "timestamp")
    keys = sorted(((log_of(frame[i]), oid[i], float(ts[i]), int(i)) for i in np.flatnonzero(rows)))
    out: list[np.ndarray] = []
    current: list[int] = []
    last: tuple[str, str] | None = None
    last_t = None
    for log, obj, t, i in keys:
        if (log, obj) != last:
            if current:
                out.append(np.array(current, dtype=np.intp))
            current, last, last_t = [], (log, obj), None
        if t == last_t:  # the same track twice in one frame: only its first label is judged
            continue
        current.append(i)
        last_t = t
    if current:
        out.append(np.array(current, dtype=np.intp))
    return out


def _residuals(table: pa.Table, rows: np.ndarray, noise: T.TrackNoise, params: T.TrackParams, evidence: Any) -> T.TrackResiduals:
    t = _column(table, "timestamp")[rows]
    centre = np.stack([_column(table, c)[rows] for c in ("world_cx", "world_cy", "world_cz")], axis=1)
    yaw = _column(table, "world_yaw")[rows]
    size = np.stack([_column(table, c)[rows] for c in ("length", "width", "height")], axis=1)
    return T.track_residuals(t - t[0], centre, yaw, size, noise, params, evidence)


def score_table(table: pa.Table, cfg: RunConfig | None = None, params: T.TrackParams | None = None) -> TrackScores:
    """Score every row of an objects table against its track.

    Parameters
    ----------
    table : the objects table (at least :data:`NEEDED_COLUMNS`)
    cfg : the run's configuration (its priors turn the per-frame posteriors into size evidence);
        None: the labels alone
    params : the track model (default :func:`labelaudit.core.track.default_params`)
    """
    params = params or T.default_params()
    n = table.num_rows
    error = np.full(n, np.nan)
    issue: list[str | None] = [None] * n
    if n == 0:
        return TrackScores(error, issue, [], {})
    rows = _eligible(table)
    groups = [g for g in _groups(table, rows) if len(g) >= params.min_frames]
    classes = table.column("class_name").to_pylist()
    track_class = [max(sorted({classes[i] for i in g}), key=[classes[i] for i in g].count) for g in groups]
    evidence = [_size_evidence(table, g, cfg, c) for g, c in zip(groups, track_class)]

    # pass 1 at the floor: the run's own noise per class, pooled over its tracks
    floor = dict(C.TRACK_NOISE_FLOOR)
    pooled: dict[str, dict[str, list[np.ndarray]]] = {}
    for g, c, ev in zip(groups, track_class, evidence):
        r = _residuals(table, g, _noise_from(floor), params, ev)
        p = pooled.setdefault(c, {k: [] for k in _NOISE_KEYS})
        p["center"].append(r.position.ravel())
        for j, k in enumerate(("length", "width", "height")):
            p[k].append(r.size[:, j])
        p["yaw"].append(r.heading)
    noise: dict[str, dict[str, float]] = {}
    for c, p in sorted(pooled.items()):
        noise[c] = {}
        for k in _NOISE_KEYS:
            z = np.abs(np.concatenate(p[k]))
            scale = 1.4826 * float(np.median(z)) if len(z) >= C.TRACK_NOISE_MIN_SAMPLES else 1.0
            noise[c][k] = float(floor[k] * max(1.0, scale))

    frame = table.column("frame_id").to_pylist()
    index = table.column("object_index").to_pylist()
    oid = table.column("object_id").to_pylist()
    ts = _column(table, "timestamp")
    tracks: list[dict[str, Any]] = []
    for g, c, ev in zip(groups, track_class, evidence):
        r = _residuals(table, g, _noise_from(noise[c]), params, ev)
        scores = T.kind_scores(r, params)
        err = scores.max(axis=1)
        kinds = T.issue_of(scores, C.TRACK_ISSUE_MIN)
        error[g] = err
        for j, i in enumerate(g):
            issue[i] = kinds[j]
        worst = int(np.argmax(err))
        speed = np.hypot(r.velocity[:, 0], r.velocity[:, 1])
        moving = speed > C.TRACK_MOVING_SPEED
        yaw = _column(table, "world_yaw")[g]
        if moving.any():
            diff = yaw[moving] - np.arctan2(r.velocity[moving, 1], r.velocity[moving, 0])
            vs_motion: float | None = float(normalize_angle(float(np.arctan2(np.sin(diff).mean(), np.cos(diff).mean()))))
        else:
            vs_motion = None
        tracks.append({
            "log_id": log_of(frame[g[0]]), "object_id": oid[g[0]], "class_name": c, "frames": len(g),
            "first_frame_id": frame[g[0]], "last_frame_id": frame[g[-1]], "duration": float(ts[g[-1]] - ts[g[0]]),
            **{d: float(v) for d, v in zip(("length", "width", "height"), r.size_mean)},
            **{f"std_{d}": float(v) for d, v in zip(("length", "width", "height"), r.size_std)},
            "mean_speed": float(speed.mean()), "heading_vs_motion": vs_motion,
            "flagged": int(np.sum(err >= C.TRACK_FLAG)), "max_track_error": float(err[worst]),
            "worst_frame_id": frame[g[worst]], "worst_object_index": int(index[g[worst]]), "worst_issue": kinds[worst],
        })
    return TrackScores(error, issue, tracks, noise)


def tracks_table(scores: TrackScores, metadata: Mapping[str, Any] | None = None) -> pa.Table:
    """``tracks.parquet``'s table: one row per track, sorted by log and object id."""
    rows = sorted(scores.tracks, key=lambda r: (r["log_id"], r["object_id"]))
    table = pa.Table.from_pylist(rows, schema=TRACKS_SCHEMA)
    return R.with_metadata(table, {**metadata, "track_noise": scores.noise}) if metadata is not None else table


def run_tracks_pass(output: Path, cfg: RunConfig, metadata: Mapping[str, Any]) -> int:
    """Score every track of a results folder and write the scores into its shards and ``tracks.parquet``.

    Shards are rewritten atomically, keeping their metadata (the chunk records ``--resume`` reads);
    a shard whose scores are already the ones written is left alone. Returns the number of tracks scored.
    Formats without tracks (KITTI) write no ``tracks.parquet`` (an old one is removed).
    """
    import pyarrow.parquet as pq

    tracks_path = output / R.TRACKS_FILE
    shard_dir = output / R.OBJECTS_DIR
    files = sorted(p for p in shard_dir.glob("*.parquet") if not p.name.startswith(".")) if shard_dir.is_dir() else []
    if metadata.get("format") not in C.TRACK_FORMATS or not files:
        tracks_path.unlink(missing_ok=True)
        return 0
    parts = [pq.read_table(f, columns=[*NEEDED_COLUMNS, *R.TRACK_COLUMNS]) for f in files]
    table = pa.concat_tables(parts) if parts else R.SCHEMA.empty_table().select(list(NEEDED_COLUMNS))
    scores = score_table(table, cfg)
    start = 0
    for f, part in zip(files, parts):
        stop = start + part.num_rows
        err = scores.track_error[start:stop]
        kinds = scores.track_issue[start:stop]
        start = stop
        new_err = pa.array([None if v != v else float(v) for v in err], pa.float64())
        new_issue = pa.array(kinds, pa.string())
        if part.column("track_error").combine_chunks().equals(new_err) and part.column("track_issue").combine_chunks().equals(new_issue):
            continue  # already written (a resumed run whose rows did not change)
        shard = pq.read_table(f)
        meta = shard.schema.metadata
        shard = shard.set_column(shard.schema.get_field_index("track_error"), R.SCHEMA.field("track_error"), new_err)
        shard = shard.set_column(shard.schema.get_field_index("track_issue"), R.SCHEMA.field("track_issue"), new_issue)
        R.write_parquet_atomic(shard.replace_schema_metadata(meta), f)
    R.write_parquet_atomic(tracks_table(scores, metadata), tracks_path)
    return len(scores.tracks)

"""The tracks pass: after every chunk is written, judge each label against its own track.

A track (one object id within one Waymo segment / Argoverse 2 log) may span chunks, so the pass
runs once over the written rows, never inside a worker: it reads the columns it needs from every
shard, scores every track whole (:mod:`labelaudit.core.track`), rewrites each shard atomically
with ``track_error`` / ``track_issue`` filled (the rows themselves are still defined only by
:mod:`labelaudit.results` and :mod:`labelaudit.infer.rows`) and writes ``tracks.parquet``, one
row per track. The pass depends only on the rows, never on how they were chunked or on the worker
count, so it is bit-identical across both; a killed pass is simply run again by ``--resume``.

The pass holds one group of shards at a time (the shards that share a log: one Waymo segment or
Argoverse 2 log per shard with the built-in chunking), reading each twice: first for the run's
ordinary per-frame label noise, pooled per class (robust: 1.4826 × the median absolute
standardised residual, from a histogram of the residuals, so memory does not grow with the run),
never below :data:`~labelaudit.constants.TRACK_NOISE_FLOOR`; then to score and rewrite.
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

NUMERIC_COLUMNS = (
    *R.WORLD_COLUMNS,
    "length",
    "width",
    "height",
    "fit_length",
    "fit_width",
    "fit_height",
    "std_length",
    "std_width",
    "std_height",
)
"""The float columns of the shards the pass computes with."""
NEEDED_COLUMNS = ("dataset", "frame_id", "object_index", "object_id", "class_name", "status", *NUMERIC_COLUMNS)
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
        pa.field(
            "log_id", pa.string(), nullable=False
        ),  # Waymo segment / Argoverse 2 log: frame_id before its last ':'
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
        pa.field(
            "heading_vs_motion", pa.float64()
        ),  # rad, circular mean of heading − direction of motion over the moving frames (≈ ±π: labelled backwards or reversing); null when never moving
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


@dataclass
class _Rows:
    """The columns the pass uses, converted once (NumPy / Python lists)."""

    frame: list[str]
    index: list[int]
    oid: list[str]
    classes: list[str]
    status: np.ndarray
    num: dict[str, np.ndarray]

    @classmethod
    def of(cls, table: pa.Table) -> "_Rows":
        return cls(
            table.column("frame_id").to_pylist(),
            table.column("object_index").to_pylist(),
            table.column("object_id").to_pylist(),
            table.column("class_name").to_pylist(),
            np.array(table.column("status").to_pylist(), dtype=object),
            {c: _column(table, c) for c in NUMERIC_COLUMNS},
        )


def _eligible(rows: _Rows, fmt: list[str]) -> np.ndarray:
    """Rows that take part: a tracked format, a time, a world box, a real track id, a usable label."""
    n = len(rows.frame)
    finite = np.ones(n, dtype=bool)
    for c in (*R.WORLD_COLUMNS, "length", "width", "height"):
        finite &= np.isfinite(rows.num[c])
    ok = (
        np.array(
            [
                fmt[i] in C.TRACK_FORMATS
                and rows.status[i] != "error"
                and rows.oid[i] != f"{rows.frame[i]}:{rows.index[i]}"
                for i in range(n)
            ],
            dtype=bool,
        )
        if n
        else np.zeros(0, dtype=bool)
    )
    return ok & finite


def _noise_from(values: Mapping[str, float]) -> T.TrackNoise:
    return T.TrackNoise(
        np.full(3, values["center"]), np.array([values["length"], values["width"], values["height"]]), values["yaw"]
    )


def _size_evidence(
    rows: _Rows, idx: np.ndarray, cfg: RunConfig | None, class_name: str
) -> tuple[np.ndarray, np.ndarray] | None:
    """Each frame's fitted size and its data precision (per-frame posterior minus the prior), 0 without points."""
    if cfg is None:
        return None
    prior = cfg.model.prior_for(class_name)
    w = cfg.model.prior_weight
    fit = np.stack([rows.num[f"fit_{d}"][idx] for d in ("length", "width", "height")], axis=1)
    std = np.stack([rows.num[f"std_{d}"][idx] for d in ("length", "width", "height")], axis=1)
    prior_prec = w / np.array([prior.length, prior.width, prior.height]) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        data = 1.0 / (std * std) - prior_prec
    ok = (rows.status[idx] == "ok")[:, None] & np.isfinite(fit) & np.isfinite(data)
    return np.where(ok, fit, np.nan), np.where(ok, np.maximum(data, 0.0), 0.0)


def _groups(rows: _Rows, eligible: np.ndarray) -> list[np.ndarray]:
    """Row indices of each track (sorted by log, object id, then time; repeated times left out)."""
    ts = rows.num["timestamp"]
    keys = sorted(((log_of(rows.frame[i]), rows.oid[i], float(ts[i]), int(i)) for i in np.flatnonzero(eligible)))
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


@dataclass
class _Tracks:
    """The tracks of one table, ready to score."""

    rows: _Rows
    groups: list[np.ndarray]
    classes: list[str]
    evidence: list[Any]

    @classmethod
    def of(cls, table: pa.Table, cfg: RunConfig | None, params: T.TrackParams) -> "_Tracks":
        rows = _Rows.of(table)
        groups = [
            g
            for g in _groups(rows, _eligible(rows, table.column("dataset").to_pylist()))
            if len(g) >= params.min_frames
        ]
        classes = [max(sorted({rows.classes[i] for i in g}), key=[rows.classes[i] for i in g].count) for g in groups]
        return cls(rows, groups, classes, [_size_evidence(rows, g, cfg, c) for g, c in zip(groups, classes)])

    def residuals(self, k: int, noise: T.TrackNoise, params: T.TrackParams) -> T.TrackResiduals:
        g, num = self.groups[k], self.rows.num
        t = num["timestamp"][g]
        centre = np.stack([num[c][g] for c in ("world_cx", "world_cy", "world_cz")], axis=1)
        size = np.stack([num[c][g] for c in ("length", "width", "height")], axis=1)
        return T.track_residuals(t - t[0], centre, num["world_yaw"][g], size, noise, params, self.evidence[k])


NoiseCounts = dict[str, dict[str, np.ndarray]]
"""class → noise key → histogram of |standardised residual| at the floor (bins of ``TRACK_NOISE_BIN``)."""


def _bins() -> int:
    return int(round(C.TRACK_NOISE_RANGE / C.TRACK_NOISE_BIN))


def _noise_counts(tracks: _Tracks, params: T.TrackParams) -> NoiseCounts:
    """Pass 1: every track at the noise floor; the histograms of its standardised residuals per class."""
    floor = _noise_from(C.TRACK_NOISE_FLOOR)
    out: NoiseCounts = {}
    nb = _bins()
    for k, c in enumerate(tracks.classes):
        r = tracks.residuals(k, floor, params)
        hist = out.setdefault(c, {key: np.zeros(nb + 1, dtype=np.int64) for key in _NOISE_KEYS})
        for key, z in (
            ("center", r.position.ravel()),
            ("length", r.size[:, 0]),
            ("width", r.size[:, 1]),
            ("height", r.size[:, 2]),
            ("yaw", r.heading),
        ):
            b = np.minimum(
                (np.abs(z) / C.TRACK_NOISE_BIN).astype(np.int64), nb
            )  # the last bin holds everything beyond the range
            hist[key] += np.bincount(b, minlength=nb + 1)
    return out


def _merge_counts(parts: list[NoiseCounts]) -> NoiseCounts:
    """The histograms of several groups added up."""
    out: NoiseCounts = {}
    for part in parts:
        for c, hists in part.items():
            mine = out.setdefault(c, {k: np.zeros_like(v) for k, v in hists.items()})
            for k, v in hists.items():
                mine[k] += v
    return out


def _noise_of(counts: NoiseCounts) -> dict[str, dict[str, float]]:
    """Per class the ordinary label noise: floor × max(1, 1.4826 × median |z|), the median from the
    histogram (the centre of the bin where half the residuals are reached); the floor below
    ``TRACK_NOISE_MIN_SAMPLES`` residuals."""
    floor = C.TRACK_NOISE_FLOOR
    out: dict[str, dict[str, float]] = {}
    for c, hists in sorted(counts.items()):
        out[c] = {}
        for k in _NOISE_KEYS:
            h = hists[k]
            total = int(h.sum())
            scale = 1.0
            if total >= C.TRACK_NOISE_MIN_SAMPLES:
                median_bin = int(np.searchsorted(np.cumsum(h), (total + 1) / 2.0))
                scale = 1.4826 * (median_bin + 0.5) * C.TRACK_NOISE_BIN
            out[c][k] = float(floor[k] * max(1.0, scale))
    return out


def _score(tracks: _Tracks, noise: Mapping[str, Mapping[str, float]], params: T.TrackParams) -> TrackScores:
    """Pass 2: every track with its class's noise (the floor for a class the noise does not know)."""
    rows = tracks.rows
    n = len(rows.frame)
    error = np.full(n, np.nan)
    issue: list[str | None] = [None] * n
    out: list[dict[str, Any]] = []
    ts = rows.num["timestamp"]
    for k, (g, c) in enumerate(zip(tracks.groups, tracks.classes)):
        r = tracks.residuals(k, _noise_from(noise.get(c, C.TRACK_NOISE_FLOOR)), params)
        scores = T.kind_scores(r, params)
        err = scores.max(axis=1)
        kinds = T.issue_of(scores, C.TRACK_ISSUE_MIN)
        error[g] = err
        for j, i in enumerate(g):
            issue[i] = kinds[j]
        worst = int(np.argmax(err))
        speed = np.hypot(r.velocity[:, 0], r.velocity[:, 1])
        moving = speed > C.TRACK_MOVING_SPEED
        if moving.any():
            diff = rows.num["world_yaw"][g][moving] - np.arctan2(r.velocity[moving, 1], r.velocity[moving, 0])
            vs_motion: float | None = float(
                normalize_angle(float(np.arctan2(np.sin(diff).mean(), np.cos(diff).mean())))
            )
        else:
            vs_motion = None
        first, last, w = g[0], g[-1], g[worst]
        out.append(
            {
                "log_id": log_of(rows.frame[first]),
                "object_id": rows.oid[first],
                "class_name": c,
                "frames": len(g),
                "first_frame_id": rows.frame[first],
                "last_frame_id": rows.frame[last],
                "duration": float(ts[last] - ts[first]),
                **{d: float(v) for d, v in zip(("length", "width", "height"), r.size_mean)},
                **{f"std_{d}": float(v) for d, v in zip(("length", "width", "height"), r.size_std)},
                "mean_speed": float(speed.mean()),
                "heading_vs_motion": vs_motion,
                "flagged": int(np.sum(err >= C.TRACK_FLAG)),
                "max_track_error": float(err[worst]),
                "worst_frame_id": rows.frame[w],
                "worst_object_index": int(rows.index[w]),
                "worst_issue": kinds[worst],
            }
        )
    return TrackScores(error, issue, out, dict(noise))


def score_table(
    table: pa.Table,
    cfg: RunConfig | None = None,
    params: T.TrackParams | None = None,
    noise: Mapping[str, Mapping[str, float]] | None = None,
) -> TrackScores:
    """Score every row of an objects table against its track.

    Parameters
    ----------
    table : the objects table (at least :data:`NEEDED_COLUMNS`)
    cfg : the run's configuration (its priors turn the per-frame posteriors into size evidence);
        None: the labels alone
    params : the track model (default :func:`labelaudit.core.track.default_params`)
    noise : class → the ordinary label noise (per class, as in ``tracks.parquet``'s metadata ``track_noise``); None: estimated from this table
    """
    params = params or T.default_params()
    tracks = _Tracks.of(table, cfg, params)
    if noise is None:
        noise = _noise_of(_noise_counts(tracks, params))
    return _score(tracks, noise, params)


def expected_boxes(
    table: pa.Table,
    cfg: RunConfig | None = None,
    noise: Mapping[str, Mapping[str, float]] | None = None,
    params: T.TrackParams | None = None,
    only: np.ndarray | None = None,
) -> np.ndarray:
    """Per row the box the rest of its track expects in this frame, in the row's own LiDAR/vehicle frame.

    The centre and heading are those the track model predicts for the frame from its neighbouring
    frames, the frame itself left out (the predictions its ``track_error`` judges the label by); the
    size is the track's fused size (``tracks.parquet``'s length, width, height). Same tracks, noise
    and model as :func:`score_table`.

    Parameters
    ----------
    table : the objects table (at least :data:`NEEDED_COLUMNS` and the box ``cx … yaw``)
    cfg, params, noise : as :func:`score_table` (``noise``: ``tracks.parquet``'s metadata ``track_noise``
        to reproduce a run's scores; None: estimated from this table)
    only : (R,) bool; when given, only the tracks holding at least one of these rows are computed

    Returns
    -------
    (R, 7) cx, cy, cz, length, width, height, yaw; NaN for a row without a scored track (or not in ``only``'s tracks)
    """
    params = params or T.default_params()
    tracks = _Tracks.of(table, cfg, params)
    if noise is None:
        noise = _noise_of(_noise_counts(tracks, params))
    out = np.full((table.num_rows, 7), np.nan)
    label = np.stack([_column(table, b) for b in R.BOX_COLUMNS], axis=1).reshape(-1, 7)
    label_world = np.stack(
        [tracks.rows.num[w] for w in ("world_cx", "world_cy", "world_cz", "world_yaw")], axis=1
    ).reshape(-1, 4)
    for k, (g, c) in enumerate(zip(tracks.groups, tracks.classes)):
        if only is not None and not only[g].any():
            continue
        r = tracks.residuals(k, _noise_from(noise.get(c, C.TRACK_NOISE_FLOOR)), params)
        world = r.expected.copy()
        world[:, 3:6] = r.size_mean
        out[g] = T.to_frame(world, label[g], label_world[g])
    return out


def tracks_table(scores: TrackScores, metadata: Mapping[str, Any] | None = None) -> pa.Table:
    """``tracks.parquet``'s table: one row per track, sorted by log and object id."""
    rows = sorted(scores.tracks, key=lambda r: (r["log_id"], r["object_id"]))
    table = pa.Table.from_pylist(rows, schema=TRACKS_SCHEMA)
    return R.with_metadata(table, {**metadata, "track_noise": scores.noise}) if metadata is not None else table


def shard_groups(files: list[Path]) -> list[list[Path]]:
    """The shards that must be scored together: those that share a log (a track never leaves its log).
    With the built-in chunking (one Waymo segment / Argoverse 2 log per shard) every shard is alone."""
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    owner: dict[str, int] = {}
    parent = list(range(len(files)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, f in enumerate(files):
        frames = pc.unique(pq.read_table(f, columns=["frame_id"]).column("frame_id")).to_pylist()
        for log in {log_of(x) for x in frames}:
            if log in owner:
                a, b = root(owner[log]), root(i)
                parent[max(a, b)] = min(a, b)
            else:
                owner[log] = i
    groups: dict[int, list[Path]] = {}
    for i, f in enumerate(files):
        groups.setdefault(root(i), []).append(f)
    return [groups[k] for k in sorted(groups)]


def run_tracks_pass(output: Path, cfg: RunConfig, metadata: Mapping[str, Any]) -> int:
    """Score every track of a results folder and write the scores into its shards and ``tracks.parquet``.

    One group of shards (:func:`shard_groups`) in memory at a time, read twice: the noise
    histograms of every group first, then the scores. Shards are rewritten atomically, keeping
    their metadata (the chunk records ``--resume`` reads); a shard whose scores are already the
    ones written is left alone. Returns the number of tracks scored. Formats without tracks
    (KITTI) write no ``tracks.parquet`` (an old one is removed).
    """
    import pyarrow.parquet as pq

    tracks_path = output / R.TRACKS_FILE
    shard_dir = output / R.OBJECTS_DIR
    files = sorted(p for p in shard_dir.glob("*.parquet") if not p.name.startswith(".")) if shard_dir.is_dir() else []
    if metadata.get("format") not in C.TRACK_FORMATS or not files:
        tracks_path.unlink(missing_ok=True)
        return 0
    params = T.default_params()
    groups = shard_groups(files)

    def read(group: list[Path]) -> list[pa.Table]:
        return [pq.read_table(f, columns=[*NEEDED_COLUMNS, *R.TRACK_COLUMNS]) for f in group]

    noise = _noise_of(
        _merge_counts([_noise_counts(_Tracks.of(pa.concat_tables(read(g)), cfg, params), params) for g in groups])
    )
    all_tracks: list[dict[str, Any]] = []
    for group in groups:
        parts = read(group)
        scores = _score(_Tracks.of(pa.concat_tables(parts), cfg, params), noise, params)
        all_tracks.extend(scores.tracks)
        start = 0
        for f, part in zip(group, parts):
            stop = start + part.num_rows
            new_err = pa.array([None if v != v else float(v) for v in scores.track_error[start:stop]], pa.float64())
            new_issue = pa.array(scores.track_issue[start:stop], pa.string())
            start = stop
            if part.column("track_error").combine_chunks().equals(new_err) and part.column(
                "track_issue"
            ).combine_chunks().equals(new_issue):
                continue  # already written (a resumed run whose rows did not change)
            shard = pq.read_table(f)
            meta = shard.schema.metadata
            shard = shard.set_column(
                shard.schema.get_field_index("track_error"), R.SCHEMA.field("track_error"), new_err
            )
            shard = shard.set_column(
                shard.schema.get_field_index("track_issue"), R.SCHEMA.field("track_issue"), new_issue
            )
            R.write_parquet_atomic(shard.replace_schema_metadata(meta), f)
    R.write_parquet_atomic(tracks_table(TrackScores(np.zeros(0), [], all_tracks, noise), metadata), tracks_path)
    return len(all_tracks)

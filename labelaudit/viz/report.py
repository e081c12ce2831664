"""``labelaudit report``: one self-contained HTML review page of a results folder.

The page (template ``templates/report.html.j2``, rendered by jinja2 with autoescaping, so every
user string is escaped by the template engine) holds the run summary (dataset, parameters hash,
objects by class and status, failed frames from ``errors.parquet``), the gate verdict when a gate
file is given, the paper's Fig. 7a/7b/7c plots and the score distributions (from Parquet columns
only), a tracks section (datasets with tracks: labels that contradict their own track, the worst
tracks from ``tracks.parquet``), a gallery of the worst labels by label_error and by JIoU-GT
(and by track_error where there are tracks) — each with its ``show``
picture, its numbers and a stable anchor ``#<frame_id>-<object_index>`` — and, with an eval
folder, the detector evaluation. Images are PNG data URIs: no network, no JavaScript. The file is
written atomically (temporary name, then rename). This module assembles; the pictures come from
:mod:`labelaudit.viz.show`, the plots from :mod:`labelaudit.viz.plots`.
"""

from __future__ import annotations

import base64
import datetime as dt
import math
import shlex
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.dataset as pads

from labelaudit import __version__
from labelaudit import constants as C
from labelaudit import results as R
from labelaudit.errors import DatasetError
from labelaudit.viz.objects import AUDITED_STATUSES, ViewError

__all__ = ["ReportSummary", "build_report", "render_report", "anchor_of", "missing_anchor", "open_for_report"]

TEMPLATE_DIR = Path(__file__).with_name("templates")
TEMPLATE_NAME = "report.html.j2"
GALLERY_COLUMNS = (
    "class_name",
    "status",
    "distance",
    "num_points",
    "jiou_gt",
    "label_error",
    "sigma_hat",
    "fit_offset_m",
    "mahalanobis",
    "face_gap",
    "hull_iou",
    "track_error",
    "track_issue",
)
GALLERIES = (  # (key, ranking column, title, points needed)
    ("label_error", "label_error", "Worst labels by label_error (most likely wrong)", None),
    ("jiou_gt", "jiou_gt", "Worst labels by JIoU-GT (least certain, boxes with points)", 1),
)

Progress = Callable[[int, int], None]
"""Called as ``progress(done, total)`` after each gallery picture."""


@dataclass(frozen=True)
class ReportSummary:
    """What :func:`build_report` wrote.

    Attributes
    ----------
    path : the HTML file; size_bytes : its size
    objects : rows in the results; evaluated : rows with status ok, few_points or no_points
    pictures : gallery pictures rendered (each object once, even when in both galleries)
    gallery : entries per gallery key (``label_error``, ``jiou_gt``)
    gate_verdict : PASS / FAIL / ERROR, or None without a gate
    seconds : wall time
    timings : wall seconds per stage (read, summary, gate, plots, gallery, missing, html)
    cpu_timings : CPU seconds of this process per stage (the same keys)
    missing_pictures : missing-label candidates pictured
    missing_counted : candidates with a score of at least ``REPORT_MISSING_MIN_SCORE`` (None: the run did not search)
    """

    path: Path
    size_bytes: int
    objects: int
    evaluated: int
    pictures: int
    gallery: dict[str, int]
    gate_verdict: str | None
    seconds: float
    timings: dict[str, float]
    cpu_timings: dict[str, float]
    missing_pictures: int = 0
    missing_counted: int | None = None


def anchor_of(frame_id: str, object_index: int) -> str:
    """The stable anchor of an object in the report: ``<frame_id>-<object_index>`` (``000123-4``).

    Whitespace (not allowed in an HTML id) becomes ``_``; everything else is kept, so the anchor
    reads like the ids ``rank`` prints.
    """
    return "".join("_" if ch.isspace() else ch for ch in f"{frame_id}-{int(object_index)}")


def data_uri(png: bytes) -> str:
    """A PNG as a ``data:image/png;base64,…`` URI."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def open_for_report(path: str | Path) -> R.Results:
    """Open a results folder; one whose run wrote no shard (all frames failed) opens as empty.

    Raises
    ------
    ResultsError
        The path is missing, or a folder that is not a results folder (no manifest either).
    """
    root = Path(path)
    try:
        return R.open_results(root)
    except R.ResultsError:
        manifest = R.read_manifest(root) if root.is_dir() else None
        if manifest is None:
            raise
        return R.Results(root, pads.dataset(R.SCHEMA.empty_table()), manifest)


# --------------------------------------------------------------------------- sections


def _floats(table: pa.Table, name: str) -> np.ndarray:
    return np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)


def _corner_tv(table: pa.Table) -> np.ndarray:
    col = table.column("corner_tv").combine_chunks()
    out = np.full((table.num_rows, 4), np.nan)
    valid = (
        np.asarray(col.is_valid().to_numpy(zero_copy_only=False), dtype=bool) if table.num_rows else np.zeros(0, bool)
    )
    if valid.any():
        lengths = np.asarray(pc.list_value_length(col).fill_null(0).to_numpy(zero_copy_only=False))
        ok = valid & (lengths == 4)
        flat = np.asarray(pc.list_flatten(col.filter(pa.array(ok))).to_numpy(zero_copy_only=False), dtype=float)
        out[ok] = flat.reshape(-1, 4)
    return out


def _median(v: np.ndarray) -> float | None:
    v = v[np.isfinite(v)]
    return float(np.median(v)) if len(v) else None


def _summary(results: R.Results, table: pa.Table) -> dict[str, Any]:
    m = results.manifest
    params = m.get("params") if isinstance(m.get("params"), dict) else {}
    model = params.get("model") if isinstance(params.get("model"), dict) else {"model": params.get("model", "–")}
    classes = np.asarray(table.column("class_name").to_pylist(), dtype=object)
    status = np.asarray(table.column("status").to_pylist(), dtype=object)
    jiou, lerr = _floats(table, "jiou_gt"), _floats(table, "label_error")
    names, counts = np.unique(classes.astype(str), return_counts=True) if len(classes) else (np.array([]), np.array([]))
    by_class = []
    for name in names[np.lexsort((names, -counts))] if len(names) else []:
        sel = classes == name
        ev = sel & np.isin(status, AUDITED_STATUSES)
        by_class.append(
            {
                "name": str(name),
                "total": int(sel.sum()),
                "statuses": [int(np.sum(sel & (status == s))) for s in R.STATUSES],
                "median_jiou_gt": _median(jiou[ev]),
                "median_label_error": _median(lerr[ev]),
            }
        )
    errors = results.errors()
    levels = errors.column("level").to_pylist() if errors.num_rows else []
    failed = [r for r, lv in zip(errors.to_pylist(), levels) if lv == "error"]
    run = [
        ("dataset", m.get("input", "–")),
        ("format", m.get("format", "–")),
        ("split / limit", f"{m.get('split') or 'all'} / {m.get('limit') or 'none'}"),
        (
            "model",
            f"{model.get('kind', model.get('model', '–'))}, σ = {model.get('sigma', '–')} m, prior weight {model.get('prior_weight', '–')}, estimate σ: {model.get('estimate_sigma', '–')}",
        ),
        ("classes", ", ".join(params.get("classes", []) or []) or "–"),
        ("parameters hash", m.get("param_hash", "–")),
        ("labelaudit / schema", f"{m.get('tool_version', '–')} / {m.get('schema_version', '–')}"),
        (
            "run complete",
            "yes" if results.complete else "NO — the run stopped before all shards were written; rerun infer to finish",
        ),
        ("units / shards", f"{m.get('units', '–')} / {m.get('chunks', '–')}"),
    ]
    return {
        "run": run,
        "statuses": list(R.STATUSES),
        "by_class": by_class,
        "status_totals": [int(np.sum(status == s)) for s in R.STATUSES],
        "objects": int(table.num_rows),
        "evaluated": int(np.isin(status, AUDITED_STATUSES).sum()),
        "failed_frames": failed[: C.REPORT_MAX_ERROR_ROWS],
        "failed_total": len(failed),
        "warnings_total": len(levels) - len(failed),
        "complete": results.complete,
    }


def _gate(results: R.Results, gate_path: str | Path | None) -> dict[str, Any] | None:
    if gate_path is None:
        return None
    from labelaudit.gate import evaluate_gate, load_gate
    from labelaudit.gate import format_number as _fmt

    gate = load_gate(None if str(gate_path) == "default" else gate_path)  # a bad gate file fails the command (exit 2)
    try:
        report = evaluate_gate(results, gate)
    except R.ResultsError as exc:
        return {"source": gate.source, "verdict": "NOT EVALUATED", "error": str(exc), "rules": [], "absent": []}
    rules = [
        {
            "scope": r.scope,
            "rule": r.rule,
            "value": _fmt(r.value),
            "threshold": f"{r.comparison} {_fmt(r.threshold)}",
            "objects": r.objects,
            "status": r.status,
            "note": r.note,
        }
        for r in report.results
    ]
    return {
        "source": report.source,
        "verdict": report.verdict,
        "error": "",
        "rules": rules,
        "absent": report.absent_classes,
    }


def _plots(table: pa.Table) -> list[dict[str, Any]]:
    from labelaudit.viz.plots import standard_plots

    status = np.asarray(table.column("status").to_pylist(), dtype=object)
    ev = np.isin(status, AUDITED_STATUSES)
    t = table.filter(pa.array(ev)) if table.num_rows else table
    plots = standard_plots(
        np.asarray(t.column("class_name").to_pylist(), dtype=object),
        _floats(t, "jiou_gt"),
        _floats(t, "label_error"),
        _floats(t, "distance"),
        _floats(t, "num_points"),
        _corner_tv(t),
    )
    return [{"title": p.title, "src": data_uri(p.png), "note": p.note} for p in plots]


def _gallery(
    results: R.Results, top: int, dataset: str | Path | None, progress: Progress | None
) -> tuple[list[dict[str, Any]], int]:
    """Both galleries: the worst ``top`` by each score, each object pictured once."""
    from labelaudit.rank import RankQuery, rank_results
    from labelaudit.viz.objects import open_source, recompute, track_view
    from labelaudit.viz.show import render_object

    ranked = []
    for key, by, title, min_points in GALLERIES + ((TRACK_GALLERY,) if results.tracks() is not None else ()):
        if by not in results.columns:
            ranked.append((key, title, []))
            continue
        rows = rank_results(
            results, RankQuery(by=by, top=top, min_points=min_points, statuses=AUDITED_STATUSES)
        ).table.to_pylist()
        ranked.append((key, title, rows))
    unique: dict[str, Mapping[str, Any]] = {}
    for _, _, rows in ranked:
        for r in rows:
            unique.setdefault(anchor_of(r["frame_id"], r["object_index"]), r)
    pictures: dict[str, dict[str, Any]] = {}
    if unique:
        source = open_source(results, dataset)
        # Pictures frame by frame: each frame is read once.
        order = sorted(unique, key=lambda a: (str(unique[a]["frame_id"]), int(unique[a]["object_index"])))
        for done, anchor in enumerate(order, start=1):
            row = unique[anchor]
            try:
                audit = recompute(source, row)
                pic = render_object(audit, C.REPORT_GALLERY_SIZE, compact=True, track=track_view(results, row))
                mism = audit.mismatches(rtol=1e-6)
                pictures[anchor] = {
                    "src": data_uri(pic.png),
                    "error": "",
                    "mismatch": ", ".join(f"{k}: row {a} vs {b}" for k, (a, b) in mism.items()),
                }
            except ViewError as exc:
                pictures[anchor] = {"src": "", "error": str(exc), "mismatch": ""}
            if progress is not None:
                progress(done, len(order))
    root = shlex.quote(str(results.root))
    galleries = []
    seen: set[str] = set()
    for key, title, rows in ranked:
        entries = []
        for rank, r in enumerate(rows, start=1):
            anchor = anchor_of(r["frame_id"], r["object_index"])
            entries.append(
                {
                    "rank": rank,
                    "anchor": anchor,
                    "id": None if anchor in seen else anchor,  # one HTML id per object: its first appearance
                    "frame_id": r["frame_id"],
                    "object_index": r["object_index"],
                    "object_id": r["object_id"],
                    "class_name": r["class_name"],
                    "numbers": [(c, r.get(c)) for c in GALLERY_COLUMNS],
                    "command": f"labelaudit show {root} {shlex.quote(str(r['frame_id']))} {r['object_index']} -o {shlex.quote(anchor)}.png",
                    **pictures[anchor],
                }
            )
            seen.add(anchor)
        galleries.append({"key": key, "title": title, "entries": entries})
    return galleries, len(pictures)


TRACK_GALLERY = ("track_error", "track_error", "Worst labels by track_error (contradict their own track)", None)
"""The third gallery, on runs with tracks (Waymo, Argoverse 2)."""


def _tracks(results: R.Results, top: int) -> dict[str, Any] | None:
    """The tracks section: how many labels contradict their track, by kind, and the worst tracks (tracks.parquet)."""
    tracks = results.tracks()
    if tracks is None:
        return None
    t = results.read(["track_error", "track_issue"])
    err = _floats(t, "track_error")
    judged = np.isfinite(err)
    issue = np.asarray(t.column("track_issue").to_pylist(), dtype=object)
    flagged = judged & (err >= C.TRACK_FLAG)
    by_issue = [(k, int(np.sum(flagged & (issue == k)))) for k in ("size", "heading", "position")]
    rows = sorted(
        tracks.to_pylist(), key=lambda r: (-(r["max_track_error"] or 0.0), -r["flagged"], r["log_id"], r["object_id"])
    )[:top]
    meta = R.shard_metadata(results.root / R.TRACKS_FILE) if (results.root / R.TRACKS_FILE).is_file() else {}
    noise = meta.get("track_noise") or {}
    return {
        "tracks": tracks.num_rows,
        "judged": int(judged.sum()),
        "flagged": int(flagged.sum()),
        "threshold": C.TRACK_FLAG,
        "by_issue": by_issue,
        "tracks_flagged": int(sum(1 for r in tracks.column("flagged").to_pylist() if r)),
        "noise": [(c, ", ".join(f"{k} {v:.3f}" for k, v in sorted(n.items()))) for c, n in sorted(noise.items())],
        "worst": [
            {
                "log_id": r["log_id"],
                "object_id": r["object_id"],
                "class_name": r["class_name"],
                "frames": r["frames"],
                "size": f"{r['length']:.2f} × {r['width']:.2f} × {r['height']:.2f} m (± {r['std_length']:.3f}, {r['std_width']:.3f}, {r['std_height']:.3f})",
                "speed": r["mean_speed"],
                "flagged": r["flagged"],
                "max_track_error": r["max_track_error"],
                "worst_frame_id": r["worst_frame_id"],
                "worst_object_index": r["worst_object_index"],
                "worst_issue": r["worst_issue"],
                "anchor": anchor_of(r["worst_frame_id"], r["worst_object_index"]),
            }
            for r in rows
        ],
    }


def missing_anchor(frame_id: str, candidate_index: int) -> str:
    """The stable anchor of a missing-label candidate in the report: ``missing-<frame_id>-<candidate_index>``."""
    return "missing-" + anchor_of(frame_id, candidate_index)


def _missing(results: R.Results, top: int, dataset: str | Path | None, progress: Progress | None) -> dict[str, Any]:
    """The "possibly missing labels" section: counts, and the ``top`` likeliest candidates pictured."""
    from labelaudit.rank import MissingQuery, rank_missing, read_candidates
    from labelaudit.viz.objects import frame_label_rows, load_frame, open_source
    from labelaudit.viz.show import EVIDENCE_COLUMNS, render_candidate

    table = read_candidates(results)
    if table is None:
        return {
            "searched": False,
            "entries": [],
            "total": 0,
            "counted": 0,
            "frames": 0,
            "by_class": [],
            "min_score": C.REPORT_MISSING_MIN_SCORE,
        }
    scores = np.asarray(table.column("score").to_numpy(zero_copy_only=False), dtype=float)
    counted = scores >= C.REPORT_MISSING_MIN_SCORE
    classes = np.asarray(table.column("class_name").to_pylist(), dtype=object)
    sources = np.asarray(table.column("source").to_pylist(), dtype=object)
    by_class = [
        {"name": str(name), "counted": int(np.sum(counted & (classes == name))), "total": int(np.sum(classes == name)),
         "sources": [int(np.sum(counted & (classes == name) & (sources == src))) for src in ("points", "detections", "both")]}
        for name in sorted(set(classes.tolist()))
    ]  # fmt: skip
    frames = len(set(np.asarray(table.column("frame_id").to_pylist(), dtype=object)[counted].tolist()))
    rows = (
        rank_missing(results, MissingQuery(top=top, min_score=C.REPORT_MISSING_MIN_SCORE)).table.to_pylist()
        if counted.any()
        else []
    )
    source = open_source(results, dataset) if rows else None
    root = shlex.quote(str(results.root))
    entries = []
    for done, r in enumerate(rows, start=1):
        anchor = missing_anchor(r["frame_id"], r["candidate_index"])
        entry = {
            "rank": done,
            "anchor": anchor,
            "frame_id": r["frame_id"],
            "candidate_index": r["candidate_index"],
            "class_name": r["class_name"],
            "numbers": [
                (c, r.get(c))
                for c in ("score", "source", "num_points", "distance", "length", "width", "height", *EVIDENCE_COLUMNS)
                if c in r
            ],
            "command": f"labelaudit show {root} {shlex.quote(str(r['frame_id']))} --candidate {r['candidate_index']} -o {shlex.quote(anchor)}.png",
            "src": "",
            "error": "",
        }
        try:
            assert source is not None
            frame = load_frame(source, r["frame_id"])
            pic = render_candidate(
                r["frame_id"],
                frame.points,
                r,
                frame_label_rows(frame),
                C.REPORT_GALLERY_SIZE,
                frame.sensor_origin,
                compact=True,
            )
            entry["src"] = data_uri(pic.png)
        except (ViewError, DatasetError) as exc:
            entry["error"] = str(exc)
        entries.append(entry)
        if progress is not None:
            progress(done, len(rows))
    return {"searched": True, "entries": entries, "total": int(table.num_rows), "counted": int(counted.sum()), "frames": frames,
            "by_class": by_class, "min_score": C.REPORT_MISSING_MIN_SCORE}  # fmt: skip


def _eval(eval_dir: str | Path | None) -> dict[str, Any] | None:
    if eval_dir is None:
        return None
    from labelaudit.viz.evalsection import read_eval_dir

    ev = read_eval_dir(eval_dir)
    return {
        "root": str(ev.root),
        "dataset": ev.dataset,
        "metric": ev.metric,
        "counts": ev.counts,
        "ap_columns": ev.ap_columns,
        "ap_rows": ev.ap_rows,
        "interp": C.REPORT_AP_INTERP,
        "overlap_columns": ev.overlap_columns,
        "overlap_rows": ev.overlap_rows,
        "plots": [{"name": name, "src": data_uri(blob)} for name, blob in ev.plots],
    }


# --------------------------------------------------------------------------- rendering


def _num(value: Any, digits: int = 3) -> str:
    """Cell text: floats with ``digits`` decimals, integers as they are, null/NaN as an en dash."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def render_report(context: Mapping[str, Any]) -> str:
    """The HTML text of a report context (jinja2, autoescaped)."""
    import jinja2

    env = jinja2.Environment(
        loader=jinja2.FileSystemLoader(str(TEMPLATE_DIR)),
        autoescape=True,  # every value is escaped unless the template says otherwise (it never does)
        undefined=jinja2.StrictUndefined,
        trim_blocks=True,
        lstrip_blocks=True,
    )
    env.filters["num"] = _num
    return env.get_template(TEMPLATE_NAME).render(**context)


def build_report(
    results_path: str | Path,
    output: str | Path,
    *,
    gate: str | Path | None = None,
    top: int = C.REPORT_TOP,
    eval_dir: str | Path | None = None,
    dataset: str | Path | None = None,
    progress: Progress | None = None,
) -> ReportSummary:
    """Write the HTML review page of a results folder.

    Parameters
    ----------
    results_path : results folder written by ``labelaudit infer``
    output : the HTML file to write
    gate : a gate TOML (``"default"``: the built-in one) whose verdict the page shows
    top : gallery entries per ranking (worst by label_error, worst by JIoU-GT) and missing-label candidates pictured
    eval_dir : an output folder of ``labelaudit eval`` to include
    dataset : the dataset's current path when it moved since ``infer``
    progress : called as ``progress(done, total)`` after each gallery picture

    Raises
    ------
    ResultsError
        Not a results folder.
    ViewError
        The dataset is not where the manifest says (pass ``dataset``), a bad eval folder, ``top`` < 1.
    ConfigError
        A bad gate file.
    """
    start = time.perf_counter()
    if top < 1:
        raise ViewError(f"--top must be ≥ 1, got {top}")
    timings: dict[str, float] = {}
    cpu_timings: dict[str, float] = {}
    t, c = time.perf_counter(), time.process_time()

    def lap(name: str) -> None:
        nonlocal t, c
        now, cpu = time.perf_counter(), time.process_time()
        timings[name], cpu_timings[name] = now - t, cpu - c
        t, c = now, cpu

    results = open_for_report(results_path)
    eval_section = _eval(eval_dir)  # bad inputs fail before the expensive part
    table = results.read(["class_name", "status", "jiou_gt", "label_error", "distance", "num_points", "corner_tv"])
    lap("read")
    summary = _summary(results, table)
    lap("summary")
    gate_section = _gate(results, gate)
    lap("gate")
    plots = _plots(table) if summary["evaluated"] else []
    lap("plots")
    tracks_section = _tracks(results, top)
    lap("tracks")
    galleries, pictures = (
        _gallery(results, top, dataset, progress)
        if summary["evaluated"]
        else ([{"key": k, "title": title, "entries": []} for k, _, title, _ in GALLERIES], 0)
    )
    lap("gallery")
    missing = _missing(
        results,
        top,
        dataset,
        None if progress is None else (lambda done, total: progress(pictures + done, pictures + total)),
    )
    lap("missing")
    context = {
        "title": f"labelaudit report — {Path(str(results.manifest.get('input', results.root))).name or results.root}",
        "results_root": str(results.root),
        "generated": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "version": __version__,
        "summary": summary,
        "gate": gate_section,
        "plots": plots,
        "galleries": galleries,
        "missing": missing,
        "top": top,
        "gallery_size": C.REPORT_GALLERY_SIZE,
        "eval": eval_section,
        "tracks": tracks_section,
    }
    html = render_report(context)
    out = Path(output)
    R.write_text_atomic(html, out)
    lap("html")
    return ReportSummary(
        out,
        out.stat().st_size,
        summary["objects"],
        summary["evaluated"],
        pictures,
        {g["key"]: len(g["entries"]) for g in galleries},
        None if gate_section is None else gate_section["verdict"],
        time.perf_counter() - start,
        timings,
        cpu_timings,
        missing_pictures=len(missing["entries"]),
        missing_counted=missing["counted"] if missing["searched"] else None,
    )

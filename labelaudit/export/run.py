"""The whole export: options checked, results read, targets computed, the output written (:func:`export_results`)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Mapping, Sequence

from labelaudit import results as R
from labelaudit.errors import ExportError
from labelaudit.export.arrays import read_result_arrays
from labelaudit.export.glenet import export_glenet
from labelaudit.export.infos import attach_to_infos, detect_infos_format
from labelaudit.export.parquet import targets_to_table
from labelaudit.export.pickles import dump_infos, load_infos
from labelaudit.export.summary import ExportSummary, reasons_text
from labelaudit.export.targets import compute_targets

__all__ = ["FORMATS", "Format", "export_results"]

Format = Literal["parquet", "openpcdet", "mmdet3d", "glenet"]
FORMATS = ("parquet", "openpcdet", "mmdet3d", "glenet")


def export_results(
    results: str | Path,
    output: str | Path,
    *,
    encoding: str | None = None,
    source: str = "model",
    fmt: Format = "parquet",
    infos: str | Path | None = None,
    anchor_sizes: Mapping[str, Sequence[float]] | None = None,
    dbinfos: str | Path | None = None,
) -> ExportSummary:
    """Export σ_p targets of a results folder (see docs/training.md).

    Parameters
    ----------
    results : results folder of ``labelaudit infer`` (or one Parquet file of rows)
    output : the Parquet file, or the infos copy to write; the folder of the copies for ``glenet``
    encoding, source, anchor_sizes : see :func:`compute_targets` (encoding None = ``box``;
        ``glenet`` has its own and takes none)
    fmt : ``parquet`` (keyed by frame_id, object_index, object_id), ``openpcdet``, ``mmdet3d`` or
        ``glenet`` (:func:`labelaudit.export.glenet.export_glenet`)
    infos : the OpenPCDet / mmdet3d infos pickle to copy (required for those formats; for
        ``glenet`` also a folder of per-sequence Waymo infos)
    dbinfos : the gt-database infos pickle to copy (``glenet`` only)

    Raises
    ------
    ExportError
        Bad options or input (:class:`InfosMismatchError`, :class:`UnsafePickleError`);
        :class:`labelaudit.results.ResultsError` for unreadable results.
    """
    output = Path(output)
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r}; expected {', '.join(FORMATS)}")
    if dbinfos is not None and fmt != "glenet":
        raise ExportError(f"--dbinfos is for --format glenet; --format {fmt} writes no gt-database file")
    if fmt == "glenet":
        if infos is None:
            raise ExportError(
                "--format glenet writes copies of the infos files: give them with --infos FILE (and --dbinfos FILE)"
            )
        if encoding is not None:
            raise ExportError(
                f"--encoding {encoding}: --format glenet has its own targets (GLENet's residual variances); drop --encoding"
            )
        return export_glenet(results, output, infos, dbinfos, source=source, anchor_sizes=anchor_sizes)
    if fmt == "parquet" and infos is not None:
        raise ExportError("--infos is for --format openpcdet or mmdet3d; the Parquet output needs none")
    if fmt != "parquet" and infos is None:
        raise ExportError(f"--format {fmt} writes a copy of an infos file: give it with --infos FILE")
    if infos is not None and output.resolve() == Path(infos).resolve():
        raise ExportError(f"{output}: the output would overwrite the input infos file; write the copy to another path")
    if output.is_dir():
        raise ExportError(f"{output}: is a folder; -o/--output takes a file name")
    arrays = read_result_arrays(results)
    targets = compute_targets(arrays, encoding or "box", source, anchor_sizes)
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
        summary.notes.append(
            f"{results} is incomplete (infer was stopped); objects of frames not yet audited have no targets"
        )
    if summary.rows_with_targets == 0:
        raise ExportError(
            f"{results}: no result row has targets ({reasons_text(summary.rows_without_targets)}); nothing written"
        )
    if fmt == "parquet":
        R.write_parquet_atomic(targets_to_table(arrays, targets), output)
        return summary
    data = load_infos(infos)  # type: ignore[arg-type]
    found = detect_infos_format(data)
    if found != fmt:
        raise ExportError(f"{infos}: this is an {found} infos file, not {fmt}; use --format {found}")
    data, stats = attach_to_infos(data, fmt, arrays, targets, str(infos))
    if stats["objects_with_targets"] == 0:
        raise ExportError(
            f"{infos}: no object of the infos got targets ({reasons_text(stats['reasons'])}); nothing written"
        )
    dump_infos(data, output)
    summary.infos = str(infos)
    summary.add_infos_stats(stats)
    return summary

"""``labelaudit export``: σ_p training targets from a results folder into Parquet or detector infos files.

The package owns the I/O of the export (docs/training.md); all mathematics is
:mod:`labelaudit.training`'s. One module per job:

- :mod:`~labelaudit.export.arrays` — the result rows it needs, as NumPy arrays;
- :mod:`~labelaudit.export.targets` — per row, the covariance that enters the encoding and why a row has none;
- :mod:`~labelaudit.export.parquet` — the Parquet table of targets;
- :mod:`~labelaudit.export.pickles` — infos pickles: restricted loading, atomic NumPy-1-loadable writing;
- :mod:`~labelaudit.export.infos` — alignment with an OpenPCDet / mmdet3d infos file's own object order;
- :mod:`~labelaudit.export.glenet` — GLENet's infos and gt-database infos with label variances;
- :mod:`~labelaudit.export.run` — the whole export (:func:`export_results`);
- :mod:`~labelaudit.export.summary` — what an export did (:class:`ExportSummary`).

It prints nothing: the CLI (:mod:`labelaudit.cli.export`) shows the :class:`ExportSummary`.
"""

from __future__ import annotations

from labelaudit.errors import ExportError, InfosMismatchError, UnsafePickleError
from labelaudit.export.arrays import ResultArrays, read_result_arrays
from labelaudit.export.glenet import export_glenet, glenet_values
from labelaudit.export.infos import DONTCARE, INFOS_META_KEY, attach_to_infos, detect_infos_format
from labelaudit.export.parquet import targets_to_table
from labelaudit.export.pickles import dump_infos, load_infos
from labelaudit.export.run import Format, export_results
from labelaudit.export.summary import ExportSummary
from labelaudit.export.targets import (
    AUDITED_STATUSES,
    INFOS_KEYS,
    ExportTargets,
    compute_targets,
    default_anchor_sizes,
    parse_anchor_sizes,
)

__all__ = [
    "AUDITED_STATUSES",
    "DONTCARE",
    "INFOS_KEYS",
    "INFOS_META_KEY",
    "ExportError",
    "ExportSummary",
    "ExportTargets",
    "Format",
    "InfosMismatchError",
    "ResultArrays",
    "UnsafePickleError",
    "attach_to_infos",
    "compute_targets",
    "default_anchor_sizes",
    "detect_infos_format",
    "dump_infos",
    "export_glenet",
    "export_results",
    "glenet_values",
    "load_infos",
    "parse_anchor_sizes",
    "read_result_arrays",
    "targets_to_table",
]

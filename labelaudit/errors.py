"""Every error labelaudit raises on purpose: bad input, a bad config, an unusable folder.

All of them subclass :class:`LabelAuditError`; the CLI turns any ``LabelAuditError`` into a one-line
message and exit code 2, so a new error class needs no registration anywhere. Anything else that
escapes is a bug (exit 3, traceback with ``--debug``). This module only defines the classes and
:func:`one_line`, the form every message is shown in.
"""

from __future__ import annotations

from pathlib import Path


def one_line(message: str) -> str:
    """``message`` on one line: every run of whitespace (the newlines of an embedded array repr,
    Click's wrapped text) becomes one space."""
    return " ".join(str(message).split())


class LabelAuditError(Exception):
    """Base of all expected errors; the message names the file or option and the fix."""


class ConfigError(LabelAuditError, ValueError):
    """A model or gate config is unreadable, has an unknown key or a value out of range."""


class DatasetError(LabelAuditError, ValueError):
    """Bad input: the message names the file (and line for text files) and what was expected."""

    def __init__(self, path: str | Path, message: str, line: int | None = None):
        self.path = str(path)
        self.line = line
        where = f"{path}:{line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {message}")


class ResultsError(LabelAuditError, ValueError):
    """A results folder is missing, unreadable or incompatible; the message names the path and the fix."""


class InferError(LabelAuditError, ValueError):
    """Bad input, output folder or options for ``infer``; the message names the path and the fix."""


class StrictError(LabelAuditError, RuntimeError):
    """``--strict``: a frame or an object failed; the message says which and why."""


class WorkerCrashed(LabelAuditError, RuntimeError):
    """A worker process died (killed, out of memory, a crash in native code)."""


class ClusterError(LabelAuditError, RuntimeError):
    """A Dask scheduler is unreachable, has no workers, or its workers run another labelaudit."""


class OutputExistsError(LabelAuditError, FileExistsError):
    """An output folder already holds what a command would write, and overwriting was not asked for."""


class UsageError(LabelAuditError, ValueError):
    """A command-line value the library cannot use (for checks the CLI itself makes)."""


class ExportError(LabelAuditError, ValueError):
    """Bad input to ``export`` (results, infos file, options); the message names the file and what was expected."""


class InfosMismatchError(ExportError):
    """An infos file does not describe the frames and objects of the results; the message names the first frame."""


class UnsafePickleError(ExportError):
    """An infos pickle references a global outside the numpy/builtin allow-list (refused before it runs)."""


class EvalError(LabelAuditError, ValueError):
    """``eval`` cannot run as asked: options, results that do not fit the dataset, nothing to evaluate."""


class DetectionsError(DatasetError):
    """A detections file is unreadable or holds a bad value; the message names file, line/row/object and field."""

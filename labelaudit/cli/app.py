"""The Typer application, its exit codes, the two consoles and the one error handler of every command.

Data goes to stdout (:func:`out`), progress and logs to stderr (:func:`err`). Exit codes: 0 success /
gate passed, 1 gate failed, 2 usage, config or input error — any
:class:`~labelaudit.errors.LabelAuditError`, shown as one line naming the file and the fix —, 3 an
internal error (a bug; ``--debug`` shows the traceback). Commands live in their own modules
(``cli/<command>.py``) and register on :data:`app`; nothing here knows a command.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator

import typer
from rich.console import Console
from rich.markup import escape
from typer.exceptions import TyperException

from labelaudit import __version__
from labelaudit.errors import LabelAuditError

EXIT_OK, EXIT_GATE_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3

app = typer.Typer(
    name="labelaudit",
    help=(
        "Audit 3D LiDAR box labels (KITTI, Waymo) from the point cloud itself: per-label spatial "
        "uncertainty (JIoU-GT), ranking of the worst labels and a CI gate.\n\n"
        "[bold]Examples[/bold]\n\n"
        "  labelaudit demo\n\n"
        "  labelaudit infer /data/kitti -o results/ && labelaudit rank results/ && labelaudit check results/"
    ),
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
)


def out() -> Console:
    """The data console (stdout)."""
    # Built per call: Typer's test runner swaps sys.stdout between invocations.
    # Not a terminal (pipe, CI log): wide enough that tables do not wrap.
    return Console(file=sys.stdout, highlight=False, width=None if sys.stdout.isatty() else 140)


def err() -> Console:
    """The log console (stderr)."""
    return Console(file=sys.stderr, stderr=True, highlight=False)


@contextmanager
def handle_errors(debug: bool) -> Iterator[None]:
    """Turn library errors into a one-line message and exit code 2 (bugs: 3, traceback with --debug)."""
    try:
        yield
    except (typer.Exit, TyperException):
        raise
    except LabelAuditError as exc:
        if debug:
            raise
        err().print(f"[red]error:[/red] {escape(str(exc))}", markup=True, highlight=False, soft_wrap=True)
        raise typer.Exit(EXIT_USAGE) from None
    except KeyboardInterrupt:
        err().print("interrupted; rerun the same command to resume")
        raise typer.Exit(130) from None
    except Exception as exc:
        if debug:
            raise
        err().print(f"[red]internal error:[/red] {type(exc).__name__}: {escape(str(exc))} (rerun with --debug for the traceback)", soft_wrap=True)
        raise typer.Exit(EXIT_INTERNAL) from None


def split_list(values: list[str] | None) -> tuple[str, ...]:
    """Repeated and comma-separated option values as one tuple (``--class Car,Van --class Truck``)."""
    items: list[str] = []
    for v in values or []:
        items.extend(s.strip() for s in v.split(",") if s.strip())
    return tuple(items)


def _version(value: bool) -> None:
    if value:
        typer.echo(f"labelaudit {__version__}")
        raise typer.Exit()


@app.callback()
def _main(
    version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Print the version and exit."),
) -> None:
    """Audit 3D LiDAR box labels from the point cloud itself."""

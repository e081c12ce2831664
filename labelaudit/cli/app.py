"""The Typer application, its exit codes, the two consoles and the one error handler of every command.

Data goes to stdout (:func:`out`), progress and logs to stderr (:func:`err`). Exit codes: 0 success /
gate passed, 1 gate failed, 2 usage, config or input error — any
:class:`~labelaudit.errors.LabelAuditError`, shown as one line naming the file and the fix —, 3 an
internal error (a bug; ``--debug`` shows the traceback). Commands live in their own modules
(``cli/<command>.py``) and register on :data:`app`; nothing here knows a command.
"""

from __future__ import annotations

import gc
import sys
from contextlib import contextmanager
from enum import Enum
from typing import Any, Iterator

import typer
from rich.console import Console
from rich.markup import escape
from typer.core import TyperGroup
from typer.exceptions import TyperException

from labelaudit import __version__
from labelaudit.cli import coerce
from labelaudit.errors import LabelAuditError, one_line

coerce.install()  # plain option values without pydantic (~45 ms of every command's start-up)

EXIT_OK, EXIT_GATE_FAILED, EXIT_USAGE, EXIT_INTERNAL = 0, 1, 2, 3


# Click's base error class, whether Typer vendors Click (≥ 0.29) or uses the click package.
_CLICK_EXCEPTION: type[Exception] = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


class OneLineErrors(TyperGroup):
    """The command group, with Click's usage errors (bad ``--workers``, unknown option, missing
    argument …) printed as one line ``error: … (see `labelaudit X --help`)`` and exit 2, like every
    other input error — Typer would draw a multi-line box."""

    def main(self, *args: Any, standalone_mode: bool = True, **kwargs: Any) -> Any:  # type: ignore[override]
        if not standalone_mode:
            return super().main(*args, standalone_mode=False, **kwargs)
        try:
            code = super().main(*args, standalone_mode=False, **kwargs)
        except _CLICK_EXCEPTION as exc:
            ctx = getattr(exc, "ctx", None)
            if type(exc).__name__ == "NoArgsIsHelpError" and ctx is not None:  # bare `labelaudit [command]`: its help
                typer.echo(ctx.get_help(), err=True)
                sys.exit(EXIT_USAGE)
            hint = f" (see `{ctx.command_path} --help`)" if ctx is not None else ""
            err().print(f"[red]error:[/red] {escape(one_line(exc.format_message()))}{escape(hint)}", soft_wrap=True)  # type: ignore[attr-defined]
            sys.exit(getattr(exc, "exit_code", EXIT_USAGE))
        except typer.Abort:
            err().print("aborted")
            sys.exit(EXIT_GATE_FAILED)
        sys.exit(code if isinstance(code, int) else EXIT_OK)


app = typer.Typer(
    cls=OneLineErrors,
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
        err().print(f"[red]error:[/red] {escape(one_line(str(exc)))}", markup=True, highlight=False, soft_wrap=True)
        raise typer.Exit(EXIT_USAGE) from None
    except KeyboardInterrupt:
        err().print("interrupted; rerun the same command to resume")
        raise typer.Exit(130) from None
    except Exception as exc:
        if debug:
            raise
        err().print(
            f"[red]internal error:[/red] {type(exc).__name__}: {escape(one_line(str(exc)))} (rerun with --debug for the traceback)",
            soft_wrap=True,
        )
        raise typer.Exit(EXIT_INTERNAL) from None


class DatasetFormat(str, Enum):
    """``--dataset-format`` of the commands that read a dataset: ``auto`` or one of
    :data:`labelaudit.datasets.FORMATS` (spelled out here: the CLI's start-up imports no reader)."""

    auto = "auto"
    kitti = "kitti"
    waymo_v2 = "waymo-v2"
    waymo_v1 = "waymo-v1"
    av2 = "av2"


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
    version: bool = typer.Option(
        False, "--version", callback=_version, is_eager=True, help="Print the version and exit."
    ),
) -> None:
    """Audit 3D LiDAR box labels from the point cloud itself."""
    if not gc.isenabled():  # the console script's start-up (labelaudit/__main__.py): its objects live on
        gc.freeze()
        gc.enable()

"""The ``labelaudit`` command line: a thin Typer layer over the library (docs/cli.md).

Command X lives in ``cli/X.py``: it parses options, calls the library module for X and prints
with Rich (:mod:`labelaudit.cli.display`). Heavy modules are imported inside the commands, so
``--help`` stays fast. The CLI never computes anything a library function could.
"""

from __future__ import annotations

from labelaudit.cli.app import app

# Importing a command module registers its command; the order here is the order of `--help`.
# isort: off
from labelaudit.cli import infer, rank, check, show, report, export, eval, simulate, demo  # noqa: F401
# isort: on

__all__ = ["app", "main"]


def main() -> None:
    """Console-script entry point."""
    app(prog_name="labelaudit")


if __name__ == "__main__":
    main()

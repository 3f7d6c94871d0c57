"""Entry point of the ``apmgsrn`` command: builds the sub-commands and turns user errors into exit 2.

Building the parser imports only the command modules and :mod:`apmgsrn.choices` (no torch, no numpy), so
``--help`` answers at once; a command's run function imports what it needs.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import warnings

from apmgsrn.cli import bench, decode, evaluate, export, grids, info, pack, render, train, verify, view
from apmgsrn.cli.flags import cli_message, register_number_types
from apmgsrn.cli.paths import CommandPaths, check_paths
from apmgsrn.errors import ApmgsrnError, ApmgsrnNote

# Each module defines ``register(subparsers)``, which adds its parser and sets ``func=run`` (and ``paths``,
# what the command reads and writes, for the commands that write).
COMMAND_MODULES = (train, pack, evaluate, decode, export, info, verify, render, bench, grids, view)


class ArgumentParser(argparse.ArgumentParser):
    """argparse, with its own errors (unknown option, bad number, missing argument) in the product's form:
    one line ``error: ...`` and exit code 2, no usage block; numbers checked as they are parsed."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        register_number_types(self)

    def error(self, message: str) -> None:
        self.exit(2, f"error: {message} (see '{self.prog} --help')\n")


def build_parser() -> argparse.ArgumentParser:
    parser = ArgumentParser(
        prog="apmgsrn",
        description="Fit adaptively placed multi-grid scene representation networks to scientific volumes.",
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for module in COMMAND_MODULES:
        module.register(subparsers)
    return parser


@contextlib.contextmanager
def notes_as_lines():
    """Print the library's notes (:class:`~apmgsrn.errors.ApmgsrnNote`) as one line ``note: ...``, other
    warnings as Python does."""
    python_format = warnings.formatwarning

    def format_warning(message, category, filename, lineno, line=None):
        if issubclass(category, ApmgsrnNote):
            return f"note: {message}\n"
        return python_format(message, category, filename, lineno, line)

    warnings.formatwarning = format_warning
    try:
        yield
    finally:
        warnings.formatwarning = python_format


def main(argv: list[str] | None = None) -> int:
    with notes_as_lines():
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help (0) or a parse error, already printed (2)
        return exc.code if isinstance(exc.code, int) else 2
    try:
        check_paths(args.paths(args) if hasattr(args, "paths") else CommandPaths())
        code = args.func(args)
    except ApmgsrnError as exc:
        print(f"error: {cli_message(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader stopped early (`| head`): no traceback, as a SIGPIPE'd tool exits
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # Python's flush at exit stays quiet
        return 141
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())

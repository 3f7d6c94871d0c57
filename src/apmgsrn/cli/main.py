"""Entry point of the ``apmgsrn`` command: builds the sub-commands and turns user errors into exit 2.

Building the parser imports only the command modules and :mod:`apmgsrn.choices` (no torch, no numpy), so
``--help`` answers at once; a command's run function imports what it needs.
"""

from __future__ import annotations

import argparse
import sys

from apmgsrn.cli import bench, decode, evaluate, export, grids, info, render, train, view
from apmgsrn.cli.flags import cli_message
from apmgsrn.cli.paths import CommandPaths, check_paths
from apmgsrn.errors import ApmgsrnError

# Each module defines ``register(subparsers)``, which adds its parser and sets ``func=run`` (and ``paths``,
# what the command reads and writes, for the commands that write).
COMMAND_MODULES = (train, evaluate, decode, export, info, render, bench, grids, view)


class ArgumentParser(argparse.ArgumentParser):
    """argparse, with its own errors (unknown option, bad number, missing argument) in the product's form:
    one line ``error: ...`` and exit code 2, no usage block."""

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


def main(argv: list[str] | None = None) -> int:
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
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())

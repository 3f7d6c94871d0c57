"""Entry point of the ``apmgsrn`` command: builds the sub-commands and turns user errors into exit 2."""

from __future__ import annotations

import argparse
import importlib
import sys

from apmgsrn.errors import ApmgsrnError

# Each module defines ``register(subparsers)``, which adds its parser and sets ``func=run``.
COMMAND_MODULES = [
    "apmgsrn.cli.train",
    "apmgsrn.cli.evaluate",
    "apmgsrn.cli.decode",
    "apmgsrn.cli.info",
    "apmgsrn.cli.render",
    "apmgsrn.cli.bench",
    "apmgsrn.cli.grids",
    "apmgsrn.cli.view",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="apmgsrn",
        description="Fit adaptively placed multi-grid scene representation networks to scientific volumes.",
    )
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except ApmgsrnError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())

"""``apmgsrn verify``: check model files, checkpoints and brick folders for damage without evaluating them."""

from __future__ import annotations

import argparse


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "verify", help="check a model file, checkpoint or brick folder for damage (nothing is evaluated)",
        description="Check every file of a model as its loader reads it: the header, the checksum of the "
                    "description and of every tensor, the description (the network is built, not evaluated); "
                    "for a brick folder also the manifest, each brick against it (brick, box, run, checksum) "
                    "and the folder as a whole. Prints one line per file; exit code 0 when every file is good, "
                    "2 when any is not.",
    )
    parser.add_argument("models", nargs="+", metavar="MODEL", help="model file, training checkpoint or model folder")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from apmgsrn.api import verify

    good = True
    for model in args.models:
        for check in verify(model):
            print(check.line(), flush=True)
            good = good and check.ok
    return 0 if good else 2

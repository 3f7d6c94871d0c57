"""``apmgsrn export``: write a model's network in a format other tools run (ONNX)."""

from __future__ import annotations

import argparse

from apmgsrn.choices import EXPORT_FORMATS
from apmgsrn.cli.paths import CommandPaths, Output


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "export", help="write a model's network as ONNX",
        description="Write the network of a model file or brick-model folder as an ONNX graph: input 'points' "
                    "[N, 3] float32 (x, y, z) in [-1, 1]^3, output 'values' [N, 1] in data units.",
    )
    parser.add_argument("model", help="model file or brick-model folder")
    parser.add_argument("--format", choices=EXPORT_FORMATS, default="onnx", help="output format (default onnx)")
    parser.add_argument("--out", required=True,
                        help="output file (.onnx); a file of that name is replaced once it is complete, unless "
                             "it is the model or another apmgsrn model")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    return CommandPaths(reads=[args.model], writes=[Output(args.out, "--out", "ONNX model", suffixes=(".onnx",))])


def run(args: argparse.Namespace) -> int:
    import apmgsrn

    model = apmgsrn.load(args.model)
    out = model.export_onnx(args.out)
    print(f"wrote {out} (ONNX, input 'points' [N, 3] in [-1, 1]^3, output 'values' [N, 1])")
    return 0

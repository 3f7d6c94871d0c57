"""``apmgsrn export``: write a model's network in a format other tools run (ONNX), or as a web page that renders it."""

from __future__ import annotations

import argparse

from apmgsrn.choices import EXPORT_FORMATS
from apmgsrn.cli.paths import CommandPaths, Output


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "export", help="write a model's network as ONNX, or as a web page that renders it",
        description="Write the network of a model file or brick-model folder as an ONNX graph: input 'points' "
                    "[N, 3] float32 (x, y, z) in [-1, 1]^3, output 'values' [N, 1] in data units. --format html "
                    "writes one self-contained page that renders a model file in a browser (WebGL2; docs/web.md).",
    )
    parser.add_argument("model", help="model file or brick-model folder")
    parser.add_argument("--format", choices=EXPORT_FORMATS, default="onnx", help="output format (default onnx)")
    parser.add_argument("--out", required=True,
                        help="output file (.onnx, or .html with --format html); a file of that name is replaced "
                             "once it is complete, unless it is the model or another apmgsrn model")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    if args.format == "html":
        return CommandPaths(reads=[args.model], writes=[Output(args.out, "--out", "web page", suffixes=(".html",))])
    return CommandPaths(reads=[args.model], writes=[Output(args.out, "--out", "ONNX model", suffixes=(".onnx",))])


def run(args: argparse.Namespace) -> int:
    import apmgsrn

    model = apmgsrn.load(args.model)
    if args.format == "html":
        from apmgsrn.web import export_html

        written = export_html(model, args.out, args.model)
        print(f"wrote {written['path']} (web page, {written['bytes'] / 1000:.0f} KB; open it in a browser)")
        for note in written["notes"]:
            print(f"note: {note}")
        return 0
    out = model.export_onnx(args.out)
    print(f"wrote {out} (ONNX, input 'points' [N, 3] in [-1, 1]^3, output 'values' [N, 1])")
    return 0

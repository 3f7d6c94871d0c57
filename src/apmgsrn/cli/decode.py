"""``apmgsrn decode``: reconstruct the volume from a model to NetCDF, raw or .npy, chunk by chunk."""

from __future__ import annotations

import argparse
from pathlib import Path

import apmgsrn
from apmgsrn.cli.common import add_device_argument, parse_triple
from apmgsrn.cli.paths import CommandPaths, Output


def register(subparsers) -> None:
    parser = subparsers.add_parser("decode", help="reconstruct a volume file from a model")
    parser.add_argument("model", help="model file")
    parser.add_argument("--out", required=True,
                        help="output volume (.nc, .raw or .npy); a file of that name is replaced once the volume "
                             "is complete, unless it is the model or another apmgsrn model")
    parser.add_argument("--shape", help="X,Y,Z output resolution (default: the training volume's)")
    parser.add_argument("--batch-size", type=int, default=2**18, help="points per forward pass")
    add_device_argument(parser)
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    return CommandPaths(reads=[args.model], writes=[Output(args.out, "--out", "decoded volume")])


def run(args: argparse.Namespace) -> int:
    from apmgsrn.device import resolve_device
    from apmgsrn.inference.decode import decode_volume

    model = apmgsrn.load(args.model, device=resolve_device(args.device))
    if args.shape:
        x, y, z = parse_triple(args.shape, "--shape")
        shape = (z, y, x)
    else:
        shape = model.description.volume_shape
    out = Path(args.out)
    decode_volume(model.field, out, shape, batch_size=args.batch_size, progress=True,
                  attributes={"source_model": Path(args.model).name})
    print(f"wrote {out} ({shape[2]}x{shape[1]}x{shape[0]} x*y*z, float32)")
    return 0

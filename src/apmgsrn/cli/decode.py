"""``apmgsrn decode``: reconstruct the volume from a model to NetCDF, raw or .npy, chunk by chunk."""

from __future__ import annotations

import argparse
from pathlib import Path

from apmgsrn.cli.common import add_device_argument, parse_triple, time_option
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    parser = subparsers.add_parser("decode", help="reconstruct a volume file from a model")
    parser.add_argument("model", help="model file")
    parser.add_argument("--out", required=True, help="output volume (.nc, .raw or .npy)")
    parser.add_argument("--shape", help="X,Y,Z output resolution (default: the training volume's)")
    parser.add_argument("--batch-size", type=int, default=2**18, help="points per forward pass")
    parser.add_argument("--time", type=time_option, metavar="K|all|A:B[:S]",
                        help="time-series model: step K, or several steps: to one file with a time axis (.nc, "
                             ".raw, .npy), or one file per step when --out holds {step}")
    add_device_argument(parser)
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import apmgsrn
    from apmgsrn.device import resolve_device
    from apmgsrn.inference.decode import decode_volume

    model = apmgsrn.load(args.model, device=resolve_device(args.device))
    if args.shape:
        x, y, z = parse_triple(args.shape, "--shape")
        shape = (z, y, x)
    else:
        shape = model.description.volume_shape
    if model.description.series is not None:
        from apmgsrn.cli.series import run_series_decode

        return run_series_decode(args, model, shape)
    if args.time is not None:
        raise ApmgsrnError(f"{args.model}: --time applies to time-series models; this one holds one volume")
    out = Path(args.out)
    decode_volume(model.field, out, shape, batch_size=args.batch_size, progress=True,
                  attributes={"source_model": Path(args.model).name})
    print(f"wrote {out} ({shape[2]}x{shape[1]}x{shape[0]} x*y*z, float32)")
    return 0

"""``apmgsrn eval``: PSNR and error figures of a model against its volume, streamed over the volume."""

from __future__ import annotations

import argparse
import json
import math

from apmgsrn.cli.common import add_data_arguments, add_device_argument, format_bytes, open_data


def register(subparsers) -> None:
    parser = subparsers.add_parser("eval", help="compare a model with a volume (PSNR, errors, size)")
    parser.add_argument("model", help="model file")
    parser.add_argument("data", help="ground-truth volume")
    add_data_arguments(parser)
    add_device_argument(parser)
    parser.add_argument("--batch-size", type=int, default=2**18, help="points per forward pass")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import apmgsrn
    from apmgsrn.device import resolve_device
    from apmgsrn.errors import ApmgsrnError
    from apmgsrn.inference.evaluate import evaluate

    device = resolve_device(args.device)
    model = apmgsrn.load(args.model, device=device)
    volume = open_data(args, args.data)
    from apmgsrn.data import check_finite

    check_finite(volume)
    trained_shape = model.description.volume_shape
    if trained_shape != tuple(volume.shape):
        raise ApmgsrnError(
            f"{args.data}: volume is {volume.shape[2]}x{volume.shape[1]}x{volume.shape[0]} (x*y*z) but the model "
            f"was trained on {trained_shape[2]}x{trained_shape[1]}x{trained_shape[0]}; pass the matching volume"
        )
    result = evaluate(model.field, volume, model_bytes=model.description.file_bytes, batch_size=args.batch_size)
    if args.json:
        values = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in result.to_dict().items()}
        print(json.dumps(values))
        return 0
    print(f"PSNR              {result.psnr:.2f} dB")
    print(f"MSE               {result.mse:.6g}")
    print(f"max abs error     {result.max_abs_error:.6g}")
    print(f"value range       [{result.data_min:.6g}, {result.data_max:.6g}]")
    print(f"model size        {format_bytes(result.model_bytes)} ({result.model_bytes:,} bytes)")
    print(f"raw float32 size  {format_bytes(result.raw_bytes)}")
    print(f"compression ratio {result.compression_ratio:.1f}x")
    return 0

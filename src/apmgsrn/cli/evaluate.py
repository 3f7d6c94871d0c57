"""``apmgsrn eval``: PSNR and error figures of a model against its volume, streamed over the volume."""

from __future__ import annotations

import argparse
import json
import math

import apmgsrn
from apmgsrn.cli.common import (
    add_data_arguments,
    add_device_argument,
    add_precision_argument,
    compression_figures,
    compression_text,
    format_bytes,
    open_data,
    percent_of_range,
)


def register(subparsers) -> None:
    parser = subparsers.add_parser("eval", help="compare a model with a volume (PSNR, errors, size)")
    parser.add_argument("model", help="model file")
    parser.add_argument("data", nargs="+",
                        help="ground-truth volume; for a time-series model its series (several files, a quoted glob, "
                             "a .pvd, or one file with --time all)")
    add_data_arguments(parser)
    add_device_argument(parser)
    add_precision_argument(parser, "float32", ": PSNR of the float32 network")
    parser.add_argument("--batch-size", type=int, default=2**18, help="points per forward pass")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from apmgsrn.device import resolve_device
    from apmgsrn.inference.evaluate import evaluate

    device = resolve_device(args.device)
    model = apmgsrn.load(args.model, device=device, precision=args.precision)
    if model.description.series is not None:
        from apmgsrn.cli.series import run_series_eval

        return run_series_eval(args, model)
    from apmgsrn.cli.series import single_input

    volume = open_data(args, single_input(args))
    result = evaluate(model.field, volume, trained_shape=model.description.volume_shape, progress=True,
                      batch_size=args.batch_size)
    model_bytes = model.description.file_bytes
    compression = compression_figures(math.prod(volume.shape), str(volume.dtype), volume.dtype.itemsize, model_bytes)
    figures = {**result.to_dict(), "model_bytes": model_bytes, **compression}
    packing = model.description.packing
    bound = packing.max_error if packing is not None else None
    if bound is not None:  # the promise is checked here, on every voxel of the volume given
        figures.update(max_error=bound, bound_holds=result.max_abs_error <= bound,
                       corrected_voxels=packing.corrected_voxels, correction_bytes=packing.correction_bytes)
    if args.json:
        finite = {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in figures.items()}
        print(json.dumps(finite))
        return 0 if figures.get("bound_holds", True) else 1
    print(f"PSNR              {result.psnr:.2f} dB")
    share = percent_of_range(result.max_abs_error, result.data_min, result.data_max)
    print(f"max abs error     {result.max_abs_error:.6g} ({share})")
    print(f"MSE               {result.mse:.6g}")
    print(f"value range       [{result.data_min:.6g}, {result.data_max:.6g}]")
    print(f"model size        {format_bytes(model_bytes)} ({model_bytes:,} bytes)")
    print(f"data size         {format_bytes(volume.stored_bytes)} as stored ({volume.dtype}), "
          f"{format_bytes(compression['float32_bytes'])} as float32")
    print(f"compression ratio {compression_text(compression)}")
    if bound is not None:
        verdict = "holds at every voxel" if figures["bound_holds"] else "VIOLATED (is this the volume it was packed on?)"
        print(f"error bound       {bound:.6g}: {verdict}; {packing.corrected_voxels:,} voxels corrected, "
              f"{packing.correction_bytes:,} bytes of the file ({100 * packing.correction_bytes / model_bytes:.1f} %)")
        return 0 if figures["bound_holds"] else 1
    return 0

"""``apmgsrn train``: fit a model to a volume with one command."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

from apmgsrn.cli.common import compression_figures, compression_text, format_bytes, percent_of_range
from apmgsrn.cli.pack import packing_lines
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.cli.train_bricks import run_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.options import BRICKS, DEVICE, INPUT, MODEL, PACKING, SERIES, TRAINING, add_option_arguments

#: What ``--out`` may replace; README.md and docs/security.md say the same.
OUT_HELP = (
    "model file to write (a folder with --bricks). An existing apmgsrn model there is replaced atomically "
    "when training succeeds; any other file, and the input itself, are refused"
)


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "train",
        help="fit a model to a volume",
        description="Fit an adaptive multi-grid network to a volume and save it as one safe model file.",
    )
    parser.add_argument("data", nargs="+",
                        help="volume file (.nc, .h5, .zarr, .raw, .npy, .vti, .vtr); several files, a quoted glob "
                             "or a .pvd for a time series")
    parser.add_argument("--out", help=OUT_HELP + " (required unless --dry-run)")
    add_option_arguments(parser, (INPUT, MODEL, TRAINING, PACKING, BRICKS, SERIES, DEVICE),
                         titles={PACKING: "packing (any of these packs the model at the end of training; --out is "
                                          "then the packed file)"})
    parser.add_argument("--resume", action="store_true",
                        help="continue an interrupted run from MODEL.ckpt (only with the same data file, "
                             "unchanged, and the same options)")
    parser.add_argument("--dry-run", action="store_true",
                        help="print the resolved plan (model, sizes, training, packing) and train nothing")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    """The volume (or every file of a series) is read; the model (and, for one model, its training checkpoint
    ``MODEL.ckpt``) written."""
    from apmgsrn.series.data import input_files

    if args.out is None:
        if not args.dry_run:
            raise ApmgsrnError("--out is required: the model file to write (or --dry-run to see the plan)")
        return CommandPaths(reads=input_files(args.data))
    writes = [Output(args.out, "--out", "model", model=True)]
    if not args.bricks:
        writes.append(Output(f"{args.out}.ckpt", "--out", "training checkpoint", model=True))
    return CommandPaths(reads=input_files(args.data), writes=writes)


def resumed_model(out: Path, bricks: bool) -> str | None:
    """The model kind of the unfinished run at ``out`` (a checkpoint ``out.ckpt``, or with ``bricks`` a brick
    folder's manifest), or None (none there, or one that does not say: the run then names what is wrong)."""
    from apmgsrn.choices import MODEL_KINDS
    from apmgsrn.io.brick_folder import manifest_path, read_manifest
    from apmgsrn.io.container import read_header
    from apmgsrn.training.checkpoint import checkpoint_path_for

    try:
        if bricks:
            settings = read_manifest(out).get("settings") if manifest_path(out).is_file() else None
        else:
            checkpoint = checkpoint_path_for(out)
            settings = read_header(checkpoint).description.get("fingerprint") if checkpoint.is_file() else None
    except ApmgsrnError:
        return None
    field = settings.get("field") if isinstance(settings, dict) else None
    model = field.get("model") if isinstance(field, dict) else None
    return model if model in MODEL_KINDS else None


def train_plan(args: argparse.Namespace):
    """The plan of the command line (:func:`apmgsrn.planning.resolve`); a resumed run keeps the model kind its
    checkpoint names."""
    from apmgsrn.options import TrainOptions
    from apmgsrn.planning import resolve

    options = TrainOptions.from_namespace(args)
    if options.model is None and (args.resume or args.bricks) and args.out is not None:
        options = replace(options, model=resumed_model(Path(args.out), args.bricks is not None))
    return resolve(args.data, options)


def print_plan(plan, as_json: bool) -> None:
    """``--dry-run``: the plan, as JSON or as lines of ``key  value``."""
    values = plan.to_dict()
    if as_json:
        print(json.dumps(values))
        return
    for key, value in values.items():
        print(f"{key:<13} {json.dumps(value)}")


def run(args: argparse.Namespace) -> int:
    plan = train_plan(args)
    if args.dry_run:
        print_plan(plan, args.json)
        return 0
    if plan.input == "series":
        from apmgsrn.cli.series import run_series_train

        if plan.bricks is not None:
            from apmgsrn.cli.train_bricks import run_series_bricks

            return run_series_bricks(args, plan)
        return run_series_train(args, plan)
    if plan.bricks is not None:
        return run_bricks(args, plan)
    import torch

    from apmgsrn.training.fit import fit_volume
    from apmgsrn.training.trainer import TrainingInterrupted

    device = torch.device(plan.device)
    volume, field_config, train_config, packing = plan.source, plan.field, plan.training, plan.packing
    if packing is not None and packing.target_bytes is not None and args.resolution is None and not args.json:
        from apmgsrn.training.sizing import sized_words

        size, options = sized_words(field_config)
        print(f"model size  {size}, "
              f"decoder {field_config.decoder.hidden_layers} x {field_config.decoder.width}, chosen to pack "
              f"into {packing.target_bytes:,} bytes ({options} to choose yourself)"
              + (", one grid anchored over the domain" if train_config.anchored_grids else ""))
    out = Path(args.out)
    try:
        result = fit_volume(
            volume, field_config, train_config, out, device,
            transform=plan.transform, log_offset=plan.log_offset, resume=args.resume, plan=plan.record(),
            progress=not args.json, minutes=plan.minutes,
        )
    except TrainingInterrupted as exc:
        print(f"{exc}; run the same command with --resume to continue")
        return 130
    voxels = math.prod(volume.shape)
    compression = compression_figures(voxels, str(volume.dtype), volume.dtype.itemsize, result.model_bytes)
    packed = None
    if packing is not None:
        from apmgsrn.training.packing import pack_volume_model

        kept = result.packed_summary(train_config.batch_size, device)
        try:
            packed = pack_volume_model(result.field, volume, packing, kept, device, out,
                                       log=(lambda line: None) if args.json else print)
        except ApmgsrnError as exc:  # the trained float32 model is at out: say so, so that no one re-trains
            raise ApmgsrnError(f"{exc} (the trained model is kept, not packed, at {out}: `apmgsrn pack {out} "
                               "DATA --out FILE` packs it)", arguments=exc.arguments) from None
        compression = compression_figures(voxels, str(volume.dtype), volume.dtype.itemsize, packed.file_bytes)
    summary = {
        "model": str(out),
        "psnr": result.psnr,
        "max_abs_error": result.max_abs_error,
        "model_bytes": packed.file_bytes if packed else result.model_bytes,
        "parameters": result.field.parameter_count(),
        **compression,
        "seconds": result.seconds,
        "iterations": result.iterations,
        "ms_per_iteration": 1000 * result.seconds / max(result.iterations, 1),
        "grids_frozen_at": result.frozen_at,
    }
    if packed is not None:
        summary.update(unpacked_model_bytes=result.model_bytes, packing=packed.report)
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"model       {out} ({format_bytes(summary['model_bytes'])}{', packed' if packed else ''}, "
              f"{summary['parameters']:,} parameters)")
        print(f"data        {volume.describe()} ({format_bytes(volume.stored_bytes)} as stored)")
        evaluation = result.evaluation
        print(f"PSNR        {evaluation.psnr:.2f} dB over all {voxels:,} voxels; "
              f"max abs error {evaluation.max_abs_error:.4g} "
              f"({percent_of_range(evaluation.max_abs_error, evaluation.data_min, evaluation.data_max)})")
        print(f"compression {compression_text(compression)}")
        if result.iterations == 0:
            print("training    none needed: every voxel has the same value")
        else:
            print(f"training    {result.iterations} iterations in {result.seconds:.1f} s "
                  f"({summary['ms_per_iteration']:.1f} ms/iteration), grids frozen at {result.frozen_at}")
        if packed is not None:
            print("\n".join(packing_lines(packed.report, packed.file_bytes, compression)))
    return 0

"""``apmgsrn train``: fit a model to a volume with one command."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from apmgsrn.cli.common import (
    add_data_arguments,
    add_device_argument,
    format_bytes,
    open_data,
    parse_triple,
    percent_of_range,
)
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    from apmgsrn.cli.series import add_series_arguments
    from apmgsrn.cli.train_bricks import add_brick_arguments
    from apmgsrn.models.encoders.adaptive_multigrid import GRID_INITS
    from apmgsrn.models.registry import ENCODERS
    from apmgsrn.models.value_transform import TRANSFORMS
    from apmgsrn.training.trainer import DECODER_PRECISIONS, DENSITY_NORMALIZATIONS, LR_SCHEDULES

    parser = subparsers.add_parser(
        "train",
        help="fit a model to a volume",
        description="Fit an adaptive multi-grid network to a volume and save it as one safe model file.",
    )
    parser.add_argument("data", nargs="+",
                        help="volume file (.nc, .h5, .zarr, .raw, .npy, .vti, .vtr); several files, a quoted glob "
                             "or a .pvd for a time series")
    parser.add_argument("--out", required=True, help="model file to write")
    add_data_arguments(parser)
    parser.add_argument("--transform", choices=TRANSFORMS, default="none", help="value transform before fitting")
    parser.add_argument("--log-offset", type=float, default=0.0, help="offset added before --transform log10")
    model = parser.add_argument_group("model")
    model.add_argument("--model", choices=sorted(ENCODERS), default="apmgsrn")
    model.add_argument("--preset", choices=["small", "medium", "large"], default="small")
    model.add_argument("--grids", type=int, help="number of grids M")
    model.add_argument("--features", type=int, help="features per grid C (per level for ngp)")
    model.add_argument("--resolution", help="grid resolution R or D,H,W")
    model.add_argument("--hidden-layers", type=int, help="decoder hidden layers (default 2)")
    model.add_argument("--width", type=int, help="decoder width (default 64)")
    model.add_argument("--grid-init", choices=GRID_INITS, help="grid initialisation")
    model.add_argument("--backend", help="sampling backend: auto (default), torch, cpu, triton; ngp: torch "
                       "(default), tcnn (tiny-cuda-nn on a GPU) or auto")
    model.add_argument("--levels", type=int, help="ngp: resolution levels L")
    model.add_argument("--log2-table-size", type=int, help="ngp: log2 of the hash table entries per level T")
    model.add_argument("--base-resolution", type=int, help="ngp: coarsest level resolution")
    model.add_argument("--finest-resolution", type=int, help="ngp: finest level resolution")
    model.add_argument("--frequencies", type=int, help="fvsrn: Fourier frequencies (default 6)")
    training = parser.add_argument_group("training")
    training.add_argument("--iterations", type=int, help="default: 3000 on CPU, 50000 on GPU")
    training.add_argument("--batch-size", type=int, help="points per iteration (default: 32768 CPU, 100000 GPU)")
    training.add_argument("--lr", type=float, default=0.01)
    training.add_argument("--transform-lr", type=float, default=0.001, help="learning rate of the grid transforms")
    training.add_argument("--lr-schedule", choices=LR_SCHEDULES,
                          help="cosine: anneal after the grids stop (default for every model, bricks too); "
                               "constant; plateau (paper; a brick ends after the third cut); "
                               "steps: x0.33 at 40/60/80%% (NGP/fVSRN reference code)")
    training.add_argument("--density-start", type=int,
                          help="iteration where the grids start moving (default: 5%% of the budget; paper 500)")
    training.add_argument("--freeze-fraction", type=float, default=0.5,
                          help="grids stop moving by this fraction of the budget (default 0.5; paper 0.8)")
    training.add_argument("--density-normalization", choices=DENSITY_NORMALIZATIONS, default="mass",
                          help="mass (default): share of all grid features; batch: the paper's rho / sum rho")
    training.add_argument("--decoder-precision", choices=DECODER_PRECISIONS, default="auto",
                          help="decoder hidden layers while training: auto (default: bfloat16 on CPUs with "
                               "native bfloat16, else float32), float32, bfloat16")
    training.add_argument("--seed", type=int, default=0)
    training.add_argument("--checkpoint-every", type=int, default=250)
    training.add_argument("--resume", action="store_true", help="continue an interrupted run from MODEL.ckpt")
    add_brick_arguments(parser)
    add_series_arguments(parser)
    add_device_argument(parser)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.set_defaults(func=run)


def build_configs(args: argparse.Namespace, device, steps: int | None = None):
    """(FieldConfig, TrainConfig) from the command line, presets overridden by explicit flags.

    Args:
        args: the parsed command line.
        device: the training device (sizes the default budget).
        steps: the number of steps of a time series (None: one volume); sizes the default budget.
    """
    from apmgsrn.models.registry import DEFAULT_LR_SCHEDULES, preset_config
    from apmgsrn.training.trainer import TrainConfig, default_budget, series_budget

    iterations, batch_size = default_budget(device)
    if steps is not None:
        iterations = series_budget(iterations, steps)
    overrides = {
        "grids": args.grids,
        "features": args.features,
        "resolution": parse_triple(args.resolution, "--resolution") if args.resolution else None,
        "init": args.grid_init,
        "backend": args.backend,
        "hidden_layers": args.hidden_layers,
        "width": args.width,
        "levels": getattr(args, "levels", None),
        "log2_table_size": getattr(args, "log2_table_size", None),
        "base_resolution": getattr(args, "base_resolution", None),
        "finest_resolution": getattr(args, "finest_resolution", None),
        "frequencies": getattr(args, "frequencies", None),
    }
    try:
        field_config = preset_config(args.model, args.preset, **overrides)
        train_config = TrainConfig(
            iterations=args.iterations or iterations,
            batch_size=args.batch_size or batch_size,
            lr=args.lr,
            transform_lr=args.transform_lr,
            lr_schedule=args.lr_schedule or DEFAULT_LR_SCHEDULES.get(args.model, "cosine"),
            density_start=args.density_start,
            freeze_fraction=args.freeze_fraction,
            density_normalization=args.density_normalization,
            decoder_precision=args.decoder_precision,
            seed=args.seed,
            checkpoint_every=args.checkpoint_every,
            **({"steps_per_iteration": args.steps_per_iteration} if getattr(args, "steps_per_iteration", None) else {}),
        )
    except (TypeError, ValueError) as exc:
        raise ApmgsrnError(f"invalid model or training options: {exc}") from None
    return field_config, train_config


def run(args: argparse.Namespace) -> int:
    from apmgsrn.cli.series import is_series, open_series_data, run_series_train, single_input
    from apmgsrn.device import resolve_device

    if is_series(args):
        if getattr(args, "bricks", None):
            from apmgsrn.cli.train_bricks import run_series_bricks

            return run_series_bricks(args)
        series = open_series_data(args)
        return run_series_train(args, series, *build_configs(args, resolve_device(args.device), steps=len(series)))
    args.data = single_input(args)
    if getattr(args, "bricks", None):
        from apmgsrn.cli.train_bricks import run_bricks

        return run_bricks(args)
    from apmgsrn.training.fit import fit_volume
    from apmgsrn.training.trainer import TrainingInterrupted

    device = resolve_device(args.device)
    field_config, train_config = build_configs(args, device)
    volume = open_data(args, args.data)
    out = Path(args.out)
    try:
        result = fit_volume(
            volume, field_config, train_config, out, device,
            transform=args.transform, log_offset=args.log_offset, resume=args.resume,
        )
    except TrainingInterrupted as exc:
        print(f"{exc}; run the same command with --resume to continue")
        return 130
    raw_bytes = volume.raw_bytes
    summary = {
        "model": str(out),
        "psnr": result.psnr,
        "max_abs_error": result.max_abs_error,
        "model_bytes": result.model_bytes,
        "parameters": result.field.parameter_count(),
        "raw_bytes": raw_bytes,
        "compression_ratio": raw_bytes / result.model_bytes,
        "seconds": result.seconds,
        "iterations": result.iterations,
        "ms_per_iteration": 1000 * result.seconds / max(result.iterations, 1),
        "grids_frozen_at": result.frozen_at,
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"model       {out} ({format_bytes(result.model_bytes)}, {summary['parameters']:,} parameters)")
        print(f"data        {volume.describe()} ({format_bytes(raw_bytes)} as float32)")
        evaluation = result.evaluation
        print(f"PSNR        {evaluation.psnr:.2f} dB over all {volume.raw_bytes // 4:,} voxels; "
              f"max abs error {evaluation.max_abs_error:.4g} "
              f"({percent_of_range(evaluation.max_abs_error, evaluation.data_min, evaluation.data_max)})")
        print(f"compression {summary['compression_ratio']:.1f}x")
        if result.iterations == 0:
            print("training    none needed: every voxel has the same value")
        else:
            print(f"training    {result.iterations} iterations in {result.seconds:.1f} s "
                  f"({summary['ms_per_iteration']:.1f} ms/iteration), grids frozen at {result.frozen_at}")
    return 0

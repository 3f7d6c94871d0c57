"""The model and training options of ``train`` (single models and bricks alike) and the configs they make."""

from __future__ import annotations

import argparse

from apmgsrn.choices import (
    BACKENDS,
    DECODER_PRECISIONS,
    DEFAULT_MODEL,
    DENSITY_NORMALIZATIONS,
    GRID_INITS,
    HYBRID_GRID_INITS,
    LR_SCHEDULES,
    MODEL_KINDS,
    SIZE_PRESETS,
)
from apmgsrn.cli.common import parse_triple
from apmgsrn.errors import ApmgsrnError


def add_fit_arguments(parser: argparse.ArgumentParser) -> None:
    """The ``model`` and ``training`` option groups."""
    backends = tuple(dict.fromkeys(name for names in BACKENDS.values() for name in names))
    model = parser.add_argument_group("model")
    model.add_argument("--model", choices=MODEL_KINDS,
                       help=f"default {DEFAULT_MODEL} (docs/models.md); apmgsrn for a joint time series or "
                            "--ratio/--size; apmgsrn is the paper's model")
    model.add_argument("--preset", choices=SIZE_PRESETS, default="small")
    model.add_argument("--grids", type=int, help="number of grids M")
    model.add_argument("--features", type=int, help="features per grid C (per level for ngp and hybrid)")
    model.add_argument("--resolution", help="grid resolution R or D,H,W")
    model.add_argument("--hidden-layers", type=int, help="decoder hidden layers (default 2)")
    model.add_argument("--width", type=int, help="decoder width (default 64)")
    model.add_argument("--grid-init", choices=tuple(dict.fromkeys(GRID_INITS + HYBRID_GRID_INITS)),
                       help=f"grid initialisation: apmgsrn {', '.join(GRID_INITS)}; "
                            f"hybrid {', '.join(HYBRID_GRID_INITS)}")
    model.add_argument("--backend", choices=backends,
                       help="kernel backend: " + "; ".join(f"{kind}: {', '.join(names)}"
                                                           for kind, names in BACKENDS.items())
                       + " (default: the first; auto picks the fastest usable one, tcnn is tiny-cuda-nn on a GPU)")
    model.add_argument("--levels", type=int, help="ngp, hybrid: resolution levels L")
    model.add_argument("--log2-table-size", type=int, help="ngp, hybrid: log2 of the hash table entries per level T")
    model.add_argument("--base-resolution", type=int, help="ngp: coarsest level resolution")
    model.add_argument("--finest-resolution", type=int, help="ngp: finest level resolution")
    model.add_argument("--frequencies", type=int, help="fvsrn: Fourier frequencies (default 6)")
    training = parser.add_argument_group("training")
    training.add_argument("--iterations", type=int, help="default: 3000 on CPU, 50000 on GPU")
    training.add_argument("--batch-size", type=int, help="points per iteration (default: 32768 CPU, 100000 GPU)")
    training.add_argument("--lr", type=float, default=0.01)
    training.add_argument("--placement-lr", type=float, default=0.001, help="learning rate of the grid placements")
    training.add_argument("--lr-schedule", choices=LR_SCHEDULES,
                          help="cosine: anneal after the grids stop (default for every model, bricks too); "
                               "constant; plateau (paper; a brick ends after the third cut); "
                               "steps: x0.33 at 40/60/80%% (NGP/fVSRN reference code)")
    training.add_argument("--voxel-fraction", type=float,
                          help="share of every batch drawn on voxels (their own values) instead of uniform points "
                               "with trilinear targets, 0..1 (default: 0.5 for hybrid and for a stepwise series, 0 "
                               "for the paper's models; a stepwise series' other steps draw half as many of theirs "
                               "between the voxels)")
    training.add_argument("--error-sampling", type=float,
                          help="share of the voxel points drawn where the model is wrong (in proportion to its error "
                               "there, measured 20 times in the run) instead of uniformly, 0..1 (default: 1 for "
                               "hybrid, 0 for the paper's models); nothing changes with --voxel-fraction 0")
    training.add_argument("--anchored-grids", type=int,
                          help="the first N adaptive grids keep their starting placement, over the whole domain "
                               "(default 0, the paper's training; 1 for a time series and for models of 8 grids or "
                               "fewer sized by --ratio/--size)")
    training.add_argument("--density-start", type=int,
                          help="iteration where the grids start moving (default: 5%% of the budget; paper 500)")
    training.add_argument("--freeze-fraction", type=float, default=0.5,
                          help="grids stop moving by this fraction of the budget (default 0.5; paper 0.8)")
    training.add_argument("--density-normalization", choices=DENSITY_NORMALIZATIONS, default="mass",
                          help="mass (default): share of all grid features; batch: the paper's rho / sum rho")
    training.add_argument("--decoder-precision", choices=DECODER_PRECISIONS, default="float32",
                          help="decoder hidden layers while training: float32 (default), bfloat16, or auto "
                               "(bfloat16 on CPUs with native bfloat16: 1.5x faster there, but up to 0.75 dB "
                               "lower PSNR on accurate models)")
    training.add_argument("--seed", type=int, default=0)
    training.add_argument("--checkpoint-every", type=int, default=250)
    training.add_argument("--resume", action="store_true",
                          help="continue an interrupted run from MODEL.ckpt (only with the same data file, "
                               "unchanged, and the same options)")


def build_configs(args: argparse.Namespace, device, steps: int | None = None):
    """(FieldConfig, TrainConfig) from the command line, presets overridden by explicit flags.

    Args:
        args: the parsed command line.
        device: the training device (sizes the default budget).
        steps: the number of steps of a time series (None: one volume); sizes the default budget.

    Raises:
        ApmgsrnError: an option out of range (the configs refuse it), or an invalid model size.
    """
    from apmgsrn.choices import default_model
    from apmgsrn.models.registry import preset_config, training_defaults
    from apmgsrn.training.series_steps import STEPWISE_VOXEL_FRACTION
    from apmgsrn.training.trainer import SERIES_ANCHORED_GRIDS, TrainConfig, default_budget, series_budget

    iterations, batch_size = default_budget(device)
    stepwise = steps is not None and getattr(args, "series_training", "joint") == "stepwise"
    if steps is not None and not stepwise:  # stepwise: the budget is the start step's, as for one volume
        iterations = series_budget(iterations, steps)
    voxel_fraction = args.voxel_fraction
    if stepwise and voxel_fraction is None:
        voxel_fraction = STEPWISE_VOXEL_FRACTION
    if args.model is None:  # resolved once: the rest of the command reads args.model
        args.model = default_model(series=steps is not None,
                                   byte_target=getattr(args, "size", None) is not None
                                   or getattr(args, "ratio", None) is not None,
                                   joint=not stepwise)
    overrides = {
        "grids": args.grids,
        "features": args.features,
        "resolution": parse_triple(args.resolution, "--resolution") if args.resolution else None,
        "init": args.grid_init,
        "backend": args.backend,
        "hidden_layers": args.hidden_layers,
        "width": args.width,
        "levels": args.levels,
        "log2_table_size": args.log2_table_size,
        "base_resolution": args.base_resolution,
        "finest_resolution": args.finest_resolution,
        "frequencies": args.frequencies,
        # --storage: a time series' grids (SeriesConfig), or one hybrid's feature tables
        "storage": getattr(args, "storage", None) if args.model == "hybrid" and steps is None else None,
    }
    try:
        field_config = preset_config(args.model, args.preset, **overrides)
        anchored = args.anchored_grids
        if anchored is None and steps is not None and args.model == "apmgsrn":
            anchored = SERIES_ANCHORED_GRIDS  # a time series' shared placement must cover moving structures
        train_config = TrainConfig(
            iterations=iterations if args.iterations is None else args.iterations,
            batch_size=batch_size if args.batch_size is None else args.batch_size,
            lr=args.lr,
            placement_lr=args.placement_lr,
            **training_defaults(args.model, lr_schedule=args.lr_schedule, voxel_fraction=voxel_fraction,
                                error_sampling=args.error_sampling),
            density_start=args.density_start,
            freeze_fraction=args.freeze_fraction,
            density_normalization=args.density_normalization,
            decoder_precision=args.decoder_precision,
            seed=args.seed,
            checkpoint_every=args.checkpoint_every,
            **({"steps_per_iteration": args.steps_per_iteration}
               if getattr(args, "steps_per_iteration", None) is not None else {}),
            **({"anchored_grids": anchored} if anchored is not None else {}),
        )
    except ApmgsrnError:
        raise  # names the option already (translated by the command line)
    except (TypeError, ValueError) as exc:
        raise ApmgsrnError(f"invalid model or training options: {exc}") from None
    return field_config, train_config

"""What a user may ask of a run: one frozen dataclass, from which the command line's flags and the Python API's
keyword arguments are both derived.

Every field of :class:`TrainOptions` is an option of ``apmgsrn train`` (``--name-with-dashes``) and a keyword of
:func:`apmgsrn.fit` / :func:`apmgsrn.plan` (``name_with_underscores``). ``None`` means "the default": the plan
(:mod:`apmgsrn.plan`) resolves it, from the recipes (:mod:`apmgsrn.recipes`) and the data. Other commands take
groups of these options (``pack`` the packing group, every reading command the input group) through
:func:`add_option_arguments`, so each option is written once.

Imports nothing heavy: the command line builds its parser from this module before torch is imported.
"""

from __future__ import annotations

import argparse
import dataclasses
from dataclasses import dataclass, field

from apmgsrn.choices import (
    BACKENDS,
    DECODER_PRECISIONS,
    DEFAULT_MODEL,
    DENSITY_NORMALIZATIONS,
    GRID_INITS,
    HYBRID_GRID_INITS,
    LR_SCHEDULES,
    MODEL_KINDS,
    SERIES_COEFFICIENTS,
    SERIES_STORAGE,
    SERIES_TRAINING,
    SIZE_PRESETS,
    VALUE_TRANSFORMS,
)
from apmgsrn.arguments import (
    FLOAT32_MAX,
    MAX_BATCH_SIZE,
    MAX_ITERATIONS,
    check_int,
    check_number,
    int_type,
    number_type,
)
from apmgsrn import recipes
from apmgsrn.errors import ApmgsrnError
from apmgsrn.limits import LIMITS

INPUT = "input volume"
MODEL = "model"
TRAINING = "training"
PACKING = "packing"
BRICKS = "domain decomposition (one model per brick; --out is then a folder)"
SERIES = ("time series (DATA: several files, a quoted glob such as 'run/*.vti', a .pvd, or --time all|A:B[:S])")
DEVICE = "device"


def time_value(text: str):
    """``--time``: an index, ``all`` or ``A:B[:S]`` (argparse type; a bad value is a usage error)."""
    from apmgsrn.series.data import parse_time

    try:
        return parse_time(text)
    except ApmgsrnError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def option(default=None, *, group: str, help: str | None = None, type=None, choices=None, metavar=None,
           low=None, high=None, low_open: bool = False):
    """A field of :class:`TrainOptions` with what its command-line flag needs.

    Args:
        default: the value when not given (None: resolved by the plan).
        group: the option group of the help text (also selects which commands take it).
        help: one line for ``--help``.
        type: how the command line parses it (int, float, a function; None: text; bool: a switch).
        choices: the values allowed.
        metavar: the name shown for its value.
        low, high: the range of an int or float option (inclusive; None: int64's end, or unbounded for a
            float, which is always finite), checked as the command line parses it and by
            :meth:`TrainOptions.from_kwargs`; where the config the option feeds has a range of its own
            (model sizes), the config checks it.
        low_open: ``low`` itself is excluded (a float that must be positive).
    """
    return field(default=default, metadata={"group": group, "help": help, "type": type, "choices": choices,
                                            "metavar": metavar, "low": low, "high": high, "low_open": low_open})


#: Ranges shared by several options.
ITERATIONS = {"low": 1, "high": MAX_ITERATIONS}
SOME_ITERATIONS = {"low": 0, "high": MAX_ITERATIONS}  # a fine-tune that 0 turns off
SHARE = {"low": 0.0, "high": 1.0}
LEARNING_RATE = {"low": 0.0, "low_open": True, "high": 1e3}  # Adam steps beyond 1 already diverge
FLOAT32 = {"low": -FLOAT32_MAX, "high": FLOAT32_MAX}  # a value stored next to float32 data
COUNT = {"low": 1}


_BACKEND_NAMES = tuple(dict.fromkeys(name for names in BACKENDS.values() for name in names))


@dataclass(frozen=True)
class TrainOptions:
    """Every option of a training run, as the user gives it (None: the plan's default)."""

    # input
    variable: str | None = option(group=INPUT, help="variable / dataset / array name (default: the only 3-D one)")
    time: object = option(group=INPUT, type=time_value, metavar="K|all|A:B[:S]",
                          help="index along a leading time dimension, or of a time-series model's steps; all or "
                               "A:B[:S] (stop exclusive) for several steps")
    shape: str | None = option(group=INPUT,
                               help="X,Y,Z dimensions of a raw file (else parsed from NAME_XxYxZ_dtype.raw)")
    dtype: str | None = option(group=INPUT, help="element type of a raw file (uint8, int16, float32, ...)")
    fill_nonfinite: float | None = option(group=INPUT, type=float, **FLOAT32, metavar="VALUE",
                                          help="replace NaN/Inf voxels by VALUE instead of refusing the volume")
    transform: str = option("none", group=MODEL, choices=VALUE_TRANSFORMS, help="value transform before fitting")
    log_offset: float = option(0.0, group=MODEL, type=float, **FLOAT32, help="offset added before --transform log10")
    # model
    model: str | None = option(group=MODEL, choices=MODEL_KINDS,
                               help=f"default {DEFAULT_MODEL} (docs/models.md); apmgsrn for a joint time series or "
                                    f"a --ratio/--size under {recipes.PACKING.hybrid_min_bytes:,} bytes "
                                    "(docs/packing.md); apmgsrn is the paper's model")
    preset: str = option("small", group=MODEL, choices=SIZE_PRESETS, help="size preset (default small)")
    grids: int | None = option(group=MODEL, type=int, help="number of grids M")
    features: int | None = option(group=MODEL, type=int, help="features per grid C (per level for ngp and hybrid)")
    resolution: object = option(group=MODEL, help="grid resolution R or D,H,W")
    hidden_layers: int | None = option(group=MODEL, type=int, help="decoder hidden layers (default 2)")
    width: int | None = option(group=MODEL, type=int, help="decoder width (default 64)")
    grid_init: str | None = option(group=MODEL, choices=tuple(dict.fromkeys(GRID_INITS + HYBRID_GRID_INITS)),
                                   help=f"grid initialisation: apmgsrn {', '.join(GRID_INITS)}; "
                                        f"hybrid {', '.join(HYBRID_GRID_INITS)}")
    backend: str | None = option(group=MODEL, choices=_BACKEND_NAMES,
                                 help="kernel backend: " + "; ".join(f"{kind}: {', '.join(names)}"
                                                                     for kind, names in BACKENDS.items())
                                      + " (default: the first; auto picks the fastest usable one, tcnn is "
                                        "tiny-cuda-nn on a GPU)")
    levels: int | None = option(group=MODEL, type=int, help="ngp, hybrid: resolution levels L")
    log2_table_size: int | None = option(group=MODEL, type=int,
                                         help="ngp, hybrid: log2 of the hash table entries per level T")
    base_resolution: int | None = option(group=MODEL, type=int, help="ngp: coarsest level resolution")
    finest_resolution: int | None = option(group=MODEL, type=int, help="ngp: finest level resolution")
    frequencies: int | None = option(group=MODEL, type=int, help="fvsrn: Fourier frequencies (default 6)")
    # training
    iterations: int | None = option(group=TRAINING, type=int, **ITERATIONS,
                                    help="default: the recipe's budget for the device (3000 on CPU, 50000 on GPU)")
    minutes: float | None = option(group=TRAINING, type=float, metavar="M", low=0.0, low_open=True,
                                   high=LIMITS.minutes,
                                   help="train for about M minutes instead of --iterations: the iterations are "
                                        "sized to this machine from a few steps timed before training (one "
                                        "volume)")
    batch_size: int | None = option(group=TRAINING, type=int, low=1, high=MAX_BATCH_SIZE,
                                    help="points per iteration (default: 32768 CPU, 100000 GPU)")
    lr: float = option(0.01, group=TRAINING, type=float, **LEARNING_RATE, help="learning rate (default 0.01)")
    placement_lr: float = option(0.001, group=TRAINING, type=float, **LEARNING_RATE,
                                 help="learning rate of the grid placements (default 0.001)")
    lr_schedule: str | None = option(group=TRAINING, choices=LR_SCHEDULES,
                                     help="cosine: anneal after the grids stop (default for every model, bricks "
                                          "too); constant; plateau (paper; a brick ends after the third cut); "
                                          "steps: x0.33 at 40/60/80%% (NGP/fVSRN reference code)")
    voxel_fraction: float | None = option(group=TRAINING, type=float, **SHARE,
                                          help="share of every batch drawn on voxels (their own values) instead of "
                                               "uniform points with trilinear targets, 0..1 (default: the model "
                                               "kind's recipe, 0.5 for hybrid and a stepwise series, 0 for the "
                                               "paper's models)")
    error_sampling: float | None = option(group=TRAINING, type=float, **SHARE,
                                          help="share of the voxel points drawn where the model is wrong (in "
                                               "proportion to its error there) instead of uniformly, 0..1 "
                                               "(default: 1 for hybrid, 0 for the paper's models)")
    anchored_grids: int | None = option(group=TRAINING, type=int, low=0,
                                        help="the first N adaptive grids keep their starting placement, over the "
                                             "whole domain (default 0; 1 for an APMGSRN time series and for models "
                                             "of 8 grids or fewer sized by --ratio/--size)")
    density_start: int | None = option(group=TRAINING, type=int, **SOME_ITERATIONS,
                                       help="iteration where the grids start moving (default: 5%% of the budget; "
                                            "paper 500)")
    freeze_fraction: float = option(0.5, group=TRAINING, type=float, **SHARE,
                                    help="grids stop moving by this fraction of the budget (default 0.5; paper 0.8)")
    density_normalization: str = option("mass", group=TRAINING, choices=DENSITY_NORMALIZATIONS,
                                        help="mass (default): share of all grid features; batch: the paper's "
                                             "rho / sum rho")
    decoder_precision: str = option("float32", group=TRAINING, choices=DECODER_PRECISIONS,
                                    help="decoder hidden layers while training: float32 (default), bfloat16, or "
                                         "auto (bfloat16 on CPUs with native bfloat16: faster there, lower PSNR "
                                         "on accurate models)")
    seed: int = option(0, group=TRAINING, type=int, low=0, high=2**32 - 1,
                       help="seeds initialisation and point draws (default 0)")
    checkpoint_every: int = option(250, group=TRAINING, type=int, **ITERATIONS,
                                   help="iterations between training checkpoints (default 250)")
    # packing
    bits: int | None = option(group=PACKING, type=int, metavar="B", low=1, high=32,
                              help="bit width of every stored feature and weight (2..16; 32 keeps float32, coded "
                                   "losslessly, e.g. for --max-error alone)")
    psnr_loss: float | None = option(group=PACKING, type=float, metavar="DB", low=0.0, low_open=True, high=100.0,
                                     help="largest PSNR cost allowed: each tensor's steps follow its effect on the "
                                          "output (the default, at 0.1 dB, when no other packing option sets the "
                                          "size)")
    size: int | None = option(group=PACKING, type=int, metavar="BYTES", low=1, help="pack to at most this many bytes")
    ratio: float | None = option(group=PACKING, type=float, metavar="R", low=0.0, low_open=True, high=1e12,
                                 help="pack to at most the data's stored bytes / R (e.g. 1000 for 1000:1)")
    max_error: float | None = option(group=PACKING, type=float, metavar="E", low=0.0, low_open=True,
                                     high=FLOAT32_MAX,
                                     help="guarantee |model - data| <= E (data units) at every voxel with a stored "
                                          "sparse correction; eval verifies it")
    qat_iterations: int | None = option(group=PACKING, type=int, metavar="N", **SOME_ITERATIONS,
                                        help="quantisation-aware fine-tune iterations before coding (default 0); "
                                             "for a stepwise time series, iterations per step (train of a hybrid "
                                             "series: by default the recipe's share of --iterations, 0 turns it "
                                             "off) (docs/time_series.md)")
    # bricks
    bricks: str | None = option(group=BRICKS, metavar="I,J,K",
                                help="train one model per brick of an I x J x K grid over x, y, z (e.g. 2,2,2 or 4)")
    ghost_cells: int = option(1, group=BRICKS, type=int, metavar="G", low=0,
                              help="voxels each brick overlaps its neighbours beyond the shared border (default 1)")
    workers: int | None = option(group=BRICKS, type=int, metavar="N", low=1, high=4096,
                                 help="local workers (default: one per visible GPU, else one per CPU core, at most 4)")
    scheduler: str | None = option(group=BRICKS, metavar="ADDRESS|FILE",
                                   help="join a running Dask cluster: tcp://host:port or its scheduler JSON file")
    retries: int = option(2, group=BRICKS, type=int, metavar="N", low=0, high=1000,
                          help="extra attempts of a brick whose job raised (default 2)")
    blend: bool = option(False, group=BRICKS, type=bool,
                         help="at inference, blend neighbouring bricks across their shared ghost region (no seams)")
    group_steps: int | None = option(group=BRICKS, type=int, metavar="S", **COUNT,
                                     help="a time series: one job per (brick, group of S consecutive steps) "
                                          "(default: every step)")
    # time series
    series_training: str | None = option(group=SERIES, choices=SERIES_TRAINING,
                                         help="stepwise (default): a model of the step with the most detail, then "
                                              "every other step's own grids fine-tuned from its neighbour's, "
                                              "decoder shared, stored packed within the recipe's size (--bits, "
                                              "--size, --ratio to choose); joint: one model of all steps trained "
                                              "at once (the joint options below)")
    start_step: object = option(group=SERIES, metavar="auto|first|last|K",
                                help="stepwise: the step the first model is trained on (default auto: the most "
                                     "detail)")
    step_iterations: int | None = option(group=SERIES, type=int, metavar="N", **SOME_ITERATIONS,
                                         help="stepwise: fine-tune iterations of every other step (default: the "
                                              "recipe's share of --iterations)")
    step_lr: float | None = option(group=SERIES, type=float, metavar="LR", **LEARNING_RATE,
                                   help="stepwise: learning rate of every other step's fine-tune (default: the "
                                        "recipe's share of --lr)")
    step_sparsity: float | None = option(group=SERIES, type=float, metavar="S", low=0.0, high=FLOAT32_MAX,
                                         help="stepwise: pull every step's features back to its neighbour's while "
                                              "it is fine-tuned (an L1 proximal step of S x the learning rate; "
                                              "default: the recipe's, 0 for APMGSRN and where the file's size holds "
                                              "every step packed alone) (docs/time_series.md)")
    decoder_iterations: int | None = option(group=SERIES, type=int, metavar="N", **SOME_ITERATIONS,
                                            help="stepwise, packed: iterations of a fine-tune of the shared decoder "
                                                 "to the grids as the file stores them (default: the recipe's "
                                                 "share of --iterations for a hybrid series, none for APMGSRN; 0 "
                                                 "turns it off)")
    basis: int | None = option(group=SERIES, type=int, metavar="K", **COUNT,
                               help="joint: basis grids shared by the steps (at most the steps)")
    coefficients: str | None = option(group=SERIES, choices=SERIES_COEFFICIENTS,
                                      help="joint: learned: every step mixes the basis its own way (default); "
                                           "keyframes: linear interpolation in time between K keyframes")
    residual: int | None = option(group=SERIES, type=int, metavar="R", low=0,
                                  help="joint: per-step residual grids of R^3 nodes (0: none)")
    steps_per_iteration: int | None = option(group=SERIES, type=int, metavar="G", **COUNT,
                                             help="joint: steps each iteration's points are spread over (default 4)")
    storage: str | None = option(group=SERIES, choices=SERIES_STORAGE,
                                 help="store the feature grids unpacked in this dtype (stepwise series: packed "
                                      "unless given; joint: float32); of one volume, the hybrid's feature tables "
                                      "(default float16)")
    # device
    device: str = option("auto", group=DEVICE, help="auto (default), cpu, cuda or cuda:I")

    @classmethod
    def from_namespace(cls, args: argparse.Namespace) -> TrainOptions:
        """The options of a parsed command line (fields its parser lacks keep their defaults)."""
        return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)})

    @classmethod
    def from_kwargs(cls, **kwargs) -> TrainOptions:
        """The options of a Python call.

        Raises:
            ApmgsrnError: a keyword that is no option, a number out of its range or a value not among its choices.
        """
        names = option_names()
        unknown = sorted(set(kwargs) - set(names))
        if unknown:
            raise ApmgsrnError(f"unknown option{'s' if len(unknown) > 1 else ''} {', '.join(unknown)}: the options "
                               f"are {', '.join(names)}", arguments=tuple(unknown))
        specs = {spec.name: spec for spec in dataclasses.fields(cls)}
        for name, value in kwargs.items():
            if value is None:
                continue
            check_option_number(specs[name], value)
            choices = specs[name].metadata.get("choices")
            if choices is not None and value not in choices:
                raise ApmgsrnError(f"{name}={value!r}: must be one of {', '.join(map(str, choices))}",
                                   arguments=(name,))
        return cls(**kwargs)


def read_options(options, allow_series: bool = False) -> dict:
    """Keyword arguments of :func:`~apmgsrn.data.open_volume` (or, with ``allow_series``,
    :func:`~apmgsrn.series.data.open_series`) from the input options of ``options`` (:class:`TrainOptions`, or
    any command's parsed arguments: options a command lacks are None).

    Raises:
        ApmgsrnError: a time selection of several steps where one volume is read.
    """
    time = getattr(options, "time", None)
    if not allow_series and time is not None and not isinstance(time, int):
        raise ApmgsrnError(f"time={time} selects several steps, but this reads one volume; pass time=INDEX",
                           arguments=("time",))
    from apmgsrn.data import parse_shape

    shape = getattr(options, "shape", None)
    return {"variable": getattr(options, "variable", None), "time": time,
            "shape": parse_shape(shape) if isinstance(shape, str) else (tuple(shape) if shape else None),
            "dtype": getattr(options, "dtype", None), "fill_nonfinite": getattr(options, "fill_nonfinite", None)}


def check_option_number(spec: dataclasses.Field, value) -> None:
    """Check a Python caller's value of an int or float option against its range (:func:`option`).

    Raises:
        InvalidArgument: not a number of the option's kind, or out of its range (named as ``name=``).
    """
    meta = spec.metadata
    if meta["type"] is int:
        check_int(spec.name, value, meta["low"], meta["high"])
    elif meta["type"] is float:
        check_number(spec.name, value, meta["low"], meta["high"], low_open=meta["low_open"])


def number_parser(spec: dataclasses.Field):
    """The argparse ``type`` of an int or float option with a range (:func:`option`), else its plain type (the
    command line's parser makes a plain ``int`` an int64 and a plain ``float`` finite)."""
    meta = spec.metadata
    if meta["low"] is None and meta["high"] is None:
        return meta["type"]
    if meta["type"] is int:
        return int_type(meta["low"], meta["high"])
    return number_type(meta["low"], meta["high"], low_open=meta["low_open"])


def option_names(group: str | None = None) -> tuple[str, ...]:
    """The option names (of one group, or all), in their order."""
    return tuple(f.name for f in dataclasses.fields(TrainOptions) if group is None or f.metadata["group"] == group)


def flag(name: str) -> str:
    """The command-line flag of an option: ``step_iterations`` -> ``--step-iterations``."""
    return "--" + name.replace("_", "-")


def add_option_arguments(parser: argparse.ArgumentParser, groups: tuple[str, ...], titles: dict | None = None,
                         skip: tuple[str, ...] = ()) -> None:
    """Add the options of ``groups`` to ``parser``, one argument group each.

    Args:
        parser: the command's parser.
        groups: which groups (:data:`INPUT`, :data:`MODEL`, ...), in the order they are shown.
        titles: another title for a group in this command (group -> text).
        skip: options this command does not take.
    """
    for group in groups:
        arguments = parser.add_argument_group((titles or {}).get(group, group))
        for spec in dataclasses.fields(TrainOptions):
            if spec.metadata["group"] != group or spec.name in skip:
                continue
            meta = spec.metadata
            if meta["type"] is bool:
                arguments.add_argument(flag(spec.name), action="store_true", help=meta["help"])
                continue
            extra = {key: meta[key] for key in ("type", "choices", "metavar") if meta[key] is not None}
            if meta["type"] in (int, float):
                extra["type"] = number_parser(spec)
            arguments.add_argument(flag(spec.name), default=spec.default, help=meta["help"], **extra)

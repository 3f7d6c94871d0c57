"""The plan: everything a training run will do, resolved from the user's options, the recipes and the data, in one
frozen, serialisable object, before anything is trained.

``apmgsrn train DATA ... --dry-run --json`` prints it, :func:`apmgsrn.plan` returns it, ``train`` and
:func:`apmgsrn.fit` run it, and the model file records it (``info`` shows it). Every default of a run is decided
here and only here: the model kind, its size (a preset, or sized for a byte target), the iteration budget for the
device, the point draws, the way a time series is trained and packed, the bricks.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from apmgsrn import recipes
from apmgsrn.arguments import parse_triple
from apmgsrn.choices import default_model
from apmgsrn.data import Volume, open_volume
from apmgsrn.decomposition.planner import DecompositionConfig
from apmgsrn.device import resolve_device
from apmgsrn.errors import ApmgsrnError
from apmgsrn.io import SourceInfo
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.options import TrainOptions, read_options
from apmgsrn.series.data import TimeSelection, VolumeSeries, is_series_input, open_series
from apmgsrn.series.field import series_config
from apmgsrn.series.fit import series_budget
from apmgsrn.series.packing import SeriesPacking, default_series_decoder, default_series_packing, default_series_qat
from apmgsrn.series.steps import StepwiseConfig, stepwise_config
from apmgsrn.training.packing import PackConfig, packed_overhead
from apmgsrn.training.sizing import anchored_grids_for, config_for_bytes
from apmgsrn.training.trainer import TrainConfig, default_budget

#: The packing options: a model is packed when any of them is given.
PACK_OPTIONS = ("bits", "psnr_loss", "size", "ratio", "max_error", "qat_iterations")
#: Options that shape a joint series model / that only a stepwise series takes.
JOINT_OPTIONS = ("basis", "coefficients", "residual", "steps_per_iteration")
STEPWISE_OPTIONS = ("start_step", "step_iterations", "step_lr", "step_sparsity", "decoder_iterations")


def joint_series_qat() -> ApmgsrnError:
    """Why ``qat_iterations`` is refused for a joint series (``train`` and ``pack``)."""
    return ApmgsrnError("qat_iterations=: fine-tunes every step of a stepwise series; a joint series has no grids "
                        "of its own per step", arguments=("qat_iterations",))


@dataclass(frozen=True)
class Plan:
    """What a training run does.

    Attributes:
        input: ``"volume"`` or ``"series"``.
        data: the files read (empty for an array in memory).
        shape: ``(D, H, W)`` of the volume, or of every step.
        steps: the number of steps of a series (None: one volume).
        stored_bytes: the data's bytes as stored (a series: as float32); ``--ratio`` divides them.
        device: where training runs.
        model: the model kind.
        field: the model's config (a :class:`~apmgsrn.models.registry.FieldConfig`, or for a series a
            :class:`~apmgsrn.series.field.SeriesFieldConfig`).
        training: the start model's training (:class:`~apmgsrn.training.trainer.TrainConfig`).
        transform, log_offset: the value transform before fitting.
        stepwise: how a stepwise series trains its other steps (None otherwise).
        packing: how the file is packed (:class:`~apmgsrn.training.packing.PackConfig` for a volume,
            :class:`~apmgsrn.series.packing.SeriesPacking` for a series; None: a float file).
        bricks: the domain decomposition (None: one model).
        workers, scheduler, retries, group_steps: how bricks are run (with ``bricks``).
        minutes: a time budget: ``training.iterations`` is sized to the machine when the run starts
            (:mod:`apmgsrn.training.timing`); None: the iterations are ``training.iterations``.
        source: the opened volume or series (not part of the plan's value).
    """

    input: str
    data: tuple[str, ...]
    shape: tuple[int, int, int]
    steps: int | None
    stored_bytes: int
    device: str
    model: str
    field: object
    training: TrainConfig
    transform: str = "none"
    log_offset: float = 0.0
    stepwise: StepwiseConfig | None = None
    packing: object = None
    bricks: DecompositionConfig | None = None
    workers: int | None = None
    scheduler: str | None = None
    retries: int = 2
    group_steps: int | None = None
    minutes: float | None = None
    source: object = field(default=None, compare=False, repr=False)

    def to_dict(self) -> dict:
        """The plan as plain JSON values (what ``--dry-run --json`` prints and a model file records)."""
        values = {}
        for spec in dataclasses.fields(self):
            if spec.name == "source":
                continue
            value = getattr(self, spec.name)
            if hasattr(value, "to_dict"):
                values[spec.name] = value.to_dict()
            elif hasattr(value, "settings"):  # a config that carries its recipe: the recipe is the code's
                values[spec.name] = _plain(value.settings())
            else:
                values[spec.name] = _plain(value)
        values["packing_kind"] = type(self.packing).__name__ if self.packing is not None else None
        return values

    def record(self) -> dict:
        """The plan as a model file keeps it: :meth:`to_dict` less the list of files read (the file's source
        says where its data came from; a long series would make the list long)."""
        values = self.to_dict()
        values["files"] = len(values.pop("data"))
        return values


def _plain(value):
    """A dataclass, tuple or number as JSON values (non-finite numbers as text)."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, TimeSelection):
        return str(value)
    return value


def resolve(data, options: TrainOptions | None = None) -> Plan:
    """The plan of training on ``data`` with ``options``.

    Args:
        data: a volume file, several files / a glob / a ``.pvd`` (a series), or an opened
            :class:`~apmgsrn.data.volume.Volume` (an array in memory).
        options: what the user asked for (None: every default).

    Raises:
        ApmgsrnError: unreadable data, options that contradict each other or are out of range.
    """
    options = options or TrainOptions()
    device = resolve_device(options.device)
    if isinstance(data, Volume):
        return _volume_plan(data, (), options, device)
    paths = [str(data)] if isinstance(data, (str, Path)) else [str(p) for p in data]
    if not paths:
        raise ApmgsrnError("no input given: name a volume file, several files or a glob")
    if is_series_input(paths, options.time):
        return _series_plan(paths, options, device)
    if len(paths) != 1:
        raise ApmgsrnError(f"{len(paths)} inputs given where one volume is read; name one file")
    _refuse_series_options(options)
    # Brick workers reopen the file by path, possibly from another folder.
    volume = open_volume(os.path.abspath(paths[0]) if options.bricks else paths[0], **read_options(options))
    return _volume_plan(volume, (paths[0],), options, device)


def volume_configs(options: TrainOptions):
    """(FieldConfig, TrainConfig) of one volume before its data is seen (no byte target): what a plan of a
    volume holds for the same options (``bench series`` trains each step's own model with them).

    Raises:
        ApmgsrnError: an invalid option.
    """
    return _configs(options, options.model or default_model(), resolve_device(options.device), None, False)


def packing_requested(options) -> bool:
    """Whether any packing option was given."""
    return any(getattr(options, name, None) is not None for name in PACK_OPTIONS)


def target_bytes(options, stored_bytes: int) -> int | None:
    """The file size ``size`` or ``ratio`` (of ``stored_bytes``) asks for; None when neither is given.

    Raises:
        ApmgsrnError: both given, or a ratio that is not a positive number.
    """
    if options.size is not None and options.ratio is not None:
        raise ApmgsrnError("size= and ratio= both set the file size: give one of them", arguments=("size", "ratio"))
    if options.ratio is None:
        return options.size
    if not (math.isfinite(options.ratio) and options.ratio > 0):
        raise ApmgsrnError(f"ratio={options.ratio}: must be a positive number such as 1000", arguments=("ratio",))
    return max(int(stored_bytes / options.ratio), 1)


def pack_config(options, stored_bytes: int) -> PackConfig:
    """How a volume's model is packed (``bits``, ``psnr_loss``, ``size``/``ratio``, ``max_error``,
    ``qat_iterations``).

    Raises:
        ApmgsrnError: options that contradict each other or are out of range.
    """
    values = {"bits": options.bits, "target_bytes": target_bytes(options, stored_bytes),
              "max_error": options.max_error, "qat_iterations": options.qat_iterations or 0}
    if options.psnr_loss is not None:
        values["psnr_loss"] = options.psnr_loss
    return PackConfig(**values)


def series_packing(options, raw_bytes: int) -> SeriesPacking | None:
    """The packing ``bits``, ``size`` or ``ratio`` ask of a series (with ``qat_iterations``); None when none of the
    first three is given.

    Raises:
        ApmgsrnError: another packing option (a series packs to a bit width or a size only), or both a size
            and a ratio.
    """
    for name in PACK_OPTIONS:
        if name not in ("bits", "size", "ratio", "qat_iterations") and getattr(options, name, None) is not None:
            raise ApmgsrnError(f"{name}=: a time series packs to a bit width or a size only (bits=, size=, ratio=, "
                               f"with qat_iterations=); drop {name}=",
                               arguments=(name, "bits", "size", "ratio", "qat_iterations"))
    qat = options.qat_iterations or 0
    if qat < 0:
        raise ApmgsrnError(f"qat_iterations={qat}: must be 0 or more", arguments=("qat_iterations",))
    size = target_bytes(options, raw_bytes)
    if size is not None:
        bits = {"bits": options.bits} if options.bits is not None else {}  # else the packing's own default
        return SeriesPacking(target_bytes=size, qat_iterations=qat, **bits)
    if options.bits is not None:
        return SeriesPacking(options.bits, min_bits=options.bits, qat_iterations=qat)
    return None


def _refuse_series_options(options: TrainOptions) -> None:
    """The options only a time series takes, refused for one volume (``storage`` is also the hybrid's tables).

    Raises:
        ApmgsrnError: such an option given.
    """
    hybrid = options.model in (None, "hybrid")
    for name in (*JOINT_OPTIONS, *(() if hybrid else ("storage",)), "series_training", *STEPWISE_OPTIONS,
                 "group_steps"):
        if getattr(options, name) is not None:
            also = " or a hybrid model" if name == "storage" else ""
            raise ApmgsrnError(f"{name}= applies to a time series (several files, a glob, a .pvd or time=all)"
                               f"{also}; drop {name}= for one volume", arguments=(name, "time"))


def _configs(options: TrainOptions, model: str, device: torch.device, steps: int | None, stepwise: bool):
    """(FieldConfig, TrainConfig) of the options: the preset and the recipes, overridden by what is given.

    Args:
        steps: the steps of a time series (None: one volume), which size a joint series' budget.
        stepwise: a stepwise series (its start model trains with one volume's budget).

    Raises:
        ApmgsrnError: an option out of range (the configs refuse it), or an invalid model size.
    """
    iterations, batch_size = default_budget(device)
    if steps is not None and not stepwise:
        iterations = series_budget(iterations, steps)
    voxel_fraction = options.voxel_fraction
    if stepwise and voxel_fraction is None:
        voxel_fraction = recipes.SERIES.voxel_fraction
    overrides = {
        "grids": options.grids,
        "features": options.features,
        "resolution": parse_triple(options.resolution, "resolution") if options.resolution is not None else None,
        "init": options.grid_init,
        "backend": options.backend,
        "hidden_layers": options.hidden_layers,
        "width": options.width,
        "levels": options.levels,
        "log2_table_size": options.log2_table_size,
        "base_resolution": options.base_resolution,
        "finest_resolution": options.finest_resolution,
        "frequencies": options.frequencies,
        # storage: a time series' grids (its SeriesConfig), or one hybrid's feature tables
        "storage": options.storage if model == "hybrid" and steps is None else None,
    }
    anchored = options.anchored_grids
    if anchored is None and steps is not None and model == "apmgsrn":
        anchored = recipes.SERIES.anchored_grids  # a series' shared placement must cover moving structures
    try:
        field_config = preset_config(model, options.preset, **overrides)
        train_config = TrainConfig(
            iterations=iterations if options.iterations is None else options.iterations,
            batch_size=batch_size if options.batch_size is None else options.batch_size,
            lr=options.lr,
            placement_lr=options.placement_lr,
            **training_defaults(model, lr_schedule=options.lr_schedule, voxel_fraction=voxel_fraction,
                                error_sampling=options.error_sampling),
            density_start=options.density_start,
            freeze_fraction=options.freeze_fraction,
            density_normalization=options.density_normalization,
            decoder_precision=options.decoder_precision,
            seed=options.seed,
            checkpoint_every=options.checkpoint_every,
            **({"steps_per_iteration": options.steps_per_iteration}
               if options.steps_per_iteration is not None else {}),
            **({"anchored_grids": anchored} if anchored is not None else {}),
        )
    except ApmgsrnError:
        raise  # names the option already
    except (TypeError, ValueError) as exc:
        raise ApmgsrnError(f"invalid model or training options: {exc}") from None
    return field_config, train_config


def _bricks(options: TrainOptions) -> DecompositionConfig | None:
    if options.bricks is None:
        return None
    if packing_requested(options):
        raise ApmgsrnError("packing options (bits=, max_error=, ...) apply to single models and time series, "
                           "not bricks=", arguments=("bits", "max_error", "bricks"))
    return DecompositionConfig(parse_triple(options.bricks, "bricks"), options.ghost_cells, options.blend)


def _volume_plan(volume: Volume, paths: tuple[str, ...], options: TrainOptions, device: torch.device) -> Plan:
    """The plan of one volume (or its bricks)."""
    bricks = _bricks(options)
    packing = pack_config(options, volume.stored_bytes) if packing_requested(options) else None
    byte_target = packing is not None and packing.target_bytes is not None
    model = options.model or default_model(series=False, byte_target=packing.target_bytes if byte_target else None)
    field_config, train_config = _configs(options, model, device, None, False)
    if byte_target and options.resolution is None:
        given = {"grids": options.grids, "levels": options.levels, "log2_table_size": options.log2_table_size,
                 "decoder": options.width if options.width is not None else options.hidden_layers}
        fixed = tuple(name for name, value in given.items() if value is not None)
        overhead = packed_overhead(field_config, tuple(volume.shape), SourceInfo.of_volume(volume))
        field_config = config_for_bytes(field_config, packing.target_bytes, fixed, overhead=overhead,
                                        volume_shape=tuple(volume.shape))
        if options.anchored_grids is None:
            train_config = replace(train_config, anchored_grids=anchored_grids_for(field_config))
    return Plan("volume", paths, tuple(volume.shape), None, volume.stored_bytes, str(device), model, field_config,
                train_config, options.transform, options.log_offset, None, packing, bricks,
                *_brick_run(options, bricks), minutes=_minutes(options, bricks), source=volume)


def _minutes(options: TrainOptions, bricks) -> float | None:
    """The time budget of one volume's run; refused beside ``iterations`` or with bricks."""
    if options.minutes is None:
        return None
    if options.iterations is not None:
        raise ApmgsrnError(f"minutes={options.minutes:g} and iterations={options.iterations}: give one of them; "
                           "minutes= sizes the iterations", arguments=("minutes", "iterations"))
    if bricks is not None:
        raise ApmgsrnError(f"minutes={options.minutes:g}: a time budget sizes one model's training; give "
                           "iterations= for bricks", arguments=("minutes", "bricks"))
    return options.minutes


def _brick_run(options: TrainOptions, bricks) -> tuple:
    if bricks is None:
        return None, None, options.retries, None
    if options.group_steps is not None and options.group_steps < 1:
        raise ApmgsrnError(f"group_steps={options.group_steps}: must be 1 or more", arguments=("group_steps",))
    return options.workers, options.scheduler, options.retries, options.group_steps


def _series_plan(paths: list[str], options: TrainOptions, device: torch.device) -> Plan:
    """The plan of a time series (or its bricks: each group of steps trains with its own steps' budget)."""
    if options.minutes is not None:
        raise ApmgsrnError(f"minutes={options.minutes:g}: a time budget sizes one volume's training; give "
                           "iterations= for a time series", arguments=("minutes", "iterations"))
    training_kind = options.series_training or "stepwise"
    stepwise = training_kind == "stepwise"
    for name in JOINT_OPTIONS if stepwise else STEPWISE_OPTIONS:
        if getattr(options, name) is not None:
            raise ApmgsrnError(f"{name}= shapes a joint series model; add series_training=joint or drop {name}="
                               if stepwise else
                               f"{name}= applies to series_training=stepwise; drop it for a joint model",
                               arguments=(name, "series_training"))
    bricks = _bricks(options)
    run = _brick_run(options, bricks)
    series = open_series(paths, **read_options(options, allow_series=True))
    if bricks is not None:
        series = series.absolute()  # workers reopen the steps by path
    steps = len(series)
    budget_steps = steps
    if bricks is not None and options.group_steps:
        budget_steps = min(steps, options.group_steps)
    model = options.model or default_model(series=True, joint=not stepwise)
    field_config, train_config = _configs(options, model, device, budget_steps, stepwise)
    try:
        if stepwise:
            config = stepwise_config(field_config, steps, options.storage or "float32")
        else:
            config = series_config(field_config, steps, options.basis, options.coefficients, options.residual,
                                   options.storage)
    except ApmgsrnError:
        raise
    except ValueError as exc:  # a model kind a series cannot extend
        raise ApmgsrnError(f"invalid time-series options: {exc}") from None
    step_plan, packing = _series_training(options, stepwise, config, series, train_config.iterations)
    return Plan("series", tuple(str(step.path) for step in series.steps), tuple(series.shape), steps,
                series.raw_bytes, str(device), model, config, train_config, options.transform, options.log_offset,
                step_plan, packing, bricks, *run, source=series)


def _series_training(options: TrainOptions, stepwise: bool, config, series: VolumeSeries, iterations: int):
    """(StepwiseConfig or None for a joint model, SeriesPacking or None for a float file).

    Raises:
        ApmgsrnError: a packing option a series does not take, packing with ``storage``, or a bad start step.
    """
    packing = series_packing(options, series.raw_bytes)
    qat, decoder = options.qat_iterations, options.decoder_iterations  # None: the model kind's default
    if (packing is not None or qat or decoder) and options.storage is not None:
        raise ApmgsrnError("bits=, size=, ratio=, qat_iterations= and decoder_iterations= pack the grids, storage= "
                           "keeps them unpacked: give one",
                           arguments=("bits", "size", "ratio", "qat_iterations", "decoder_iterations", "storage"))
    if not stepwise:
        if qat:
            raise joint_series_qat()
        return None, packing
    start = options.start_step if options.start_step is not None else "auto"
    if isinstance(start, str) and start not in ("auto", "first", "last"):
        try:
            start = int(start)
        except ValueError:
            raise ApmgsrnError(f"start_step={start}: must be auto, first, last or a step index",
                               arguments=("start_step",)) from None
    step_plan = StepwiseConfig(start=start, step_iterations=options.step_iterations, step_lr=options.step_lr,
                               step_sparsity=options.step_sparsity)
    if qat is None:
        qat = default_series_qat(config.field.model, iterations)
    if decoder is None:
        decoder = default_series_decoder(config.field.model, iterations)
    if packing is None and options.storage is None:
        packing = default_series_packing(config, series.shape, iterations)
    if packing is not None:
        packing = replace(packing, qat_iterations=qat, decoder_iterations=decoder)
    return step_plan, packing

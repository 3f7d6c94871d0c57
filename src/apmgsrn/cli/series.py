"""Time series on the command line: the options and runs of ``train``, ``eval``, ``decode`` and ``info`` for a
series (several files, a quoted glob, a ``.pvd`` collection, or one file with ``--time all|A:B[:S]``).

Wiring only: the series is read by :mod:`apmgsrn.data.series`, modelled by
:mod:`apmgsrn.models.series_field`, fitted by :func:`apmgsrn.training.fit.fit_series` and measured by
:func:`apmgsrn.inference.evaluate.evaluate_series`.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

from apmgsrn.cli.common import format_bytes, percent_of_range, volume_options
from apmgsrn.errors import ApmgsrnError

#: Placeholder of ``decode --time all --out``: one file per step.
STEP_FIELD = "{step}"
#: Options of a joint series model (refused for stepwise training).
JOINT_OPTIONS = ("basis", "coefficients", "residual", "steps_per_iteration")
#: Options of a stepwise series (refused for a joint one).
STEPWISE_OPTIONS = ("start_step", "step_iterations", "step_sparsity", "decoder_iterations")


def add_series_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``train`` on a time series (the model and training options apply as for one volume)."""
    from apmgsrn.choices import SERIES_COEFFICIENTS, SERIES_STORAGE, SERIES_TRAINING
    from apmgsrn.models.series_options import SERIES_DEFAULTS

    group = parser.add_argument_group(
        "time series (DATA: several files, a quoted glob such as 'run/*.vti', a .pvd, or --time all|A:B[:S])"
    )
    group.add_argument("--series-training", choices=SERIES_TRAINING,
                       help="stepwise (default): a model of the step with the most detail, then every other step's "
                            "own grids fine-tuned from its neighbour's, decoder shared, placement shared unless a "
                            "step drifts, stored packed (--bits, default 10, lowered to 6 at most to stay within 5 "
                            "single-step models, or a sixth of the steps' beyond 30 steps; or --size, --ratio; with "
                            "--bricks, every brick and group of steps "
                            "so, at the default packing); joint: one model of all steps trained at once (the "
                            "options below)")
    group.add_argument("--start-step", metavar="auto|first|last|K",
                       help="stepwise: the step the first model is trained on (default auto: the most detail)")
    group.add_argument("--step-iterations", type=int, metavar="N",
                       help="stepwise: fine-tune iterations of every other step, at the start model's batch "
                            "(default: a tenth of --iterations; a hybrid series on a CPU runs 0.9 of their points "
                            "at 0.375 of the batch)")
    group.add_argument("--step-sparsity", type=float, metavar="S",
                       help="stepwise: pull every step's features back to its neighbour's while it is fine-tuned "
                            "(an L1 proximal step of S x the learning rate per iteration, weaker on fine-tunes over "
                            "twice the base; default 0.01 for a hybrid series, 0 for APMGSRN and where the file's size "
                            "holds every step packed alone): fewer bytes per step in the packed file, a looser fit "
                            "(docs/time_series.md)")
    group.add_argument("--decoder-iterations", type=int, metavar="N",
                       help="stepwise, packed: iterations of a fine-tune of the shared decoder alone to the grids as "
                            "the file stores them, on all steps at once (default: 0.15 x --iterations for a hybrid "
                            "series, none for APMGSRN; 0 turns it off): no extra bytes, about 10 s more on a CPU "
                            "(docs/time_series.md)")
    group.add_argument("--basis", type=int, metavar="K",
                       help=f"joint: basis grids shared by the steps (default {SERIES_DEFAULTS['basis']}, at most "
                            "the steps)")
    group.add_argument("--coefficients", choices=SERIES_COEFFICIENTS,
                       help="joint: learned: every step mixes the basis its own way (default); keyframes: linear "
                            "interpolation in time between K evenly spaced keyframes")
    group.add_argument("--residual", type=int, metavar="R",
                       help="joint: per-step residual grids of R^3 nodes (0: none; default "
                            f"{SERIES_DEFAULTS['residual']})")
    group.add_argument("--steps-per-iteration", type=int, metavar="G",
                       help="joint: steps each iteration's points are spread over (default 4)")
    group.add_argument("--storage", choices=SERIES_STORAGE,
                       help="store the feature grids unpacked in this dtype (default: joint "
                            f"{SERIES_DEFAULTS['storage']}; stepwise packed, see --bits); of one volume, the "
                            "hybrid's feature tables (default float16)")


def is_series(args: argparse.Namespace) -> bool:
    """Whether the command's DATA names a series rather than one volume."""
    from apmgsrn.data.series import is_series_input

    return is_series_input(args.data, getattr(args, "time", None))


def single_input(args: argparse.Namespace) -> str:
    """The one DATA path of a command that reads one volume (several name a series); the options that only a
    series takes are refused.

    Raises:
        ApmgsrnError: several inputs, or a series option given.
    """
    if len(args.data) != 1:
        raise ApmgsrnError(f"{len(args.data)} inputs given where one volume is read; name one file")
    hybrid = getattr(args, "model", None) in (None, "hybrid")  # --storage: the hybrid's tables (None: default)
    for option in (*JOINT_OPTIONS, *(() if hybrid else ("storage",)), "series_training", *STEPWISE_OPTIONS):
        if getattr(args, option, None) is not None:
            flag = "--" + option.replace("_", "-")
            also = " or a hybrid model" if option == "storage" else ""
            raise ApmgsrnError(f"{flag} applies to a time series (several files, a glob, a .pvd or --time all)"
                               f"{also}; drop {flag} for one volume")
    return args.data[0]


def open_series_data(args: argparse.Namespace):
    """The series DATA names, with the data options of ``args``."""
    from apmgsrn.data.series import open_series

    options = volume_options(args, allow_series=True)
    return open_series(args.data, **options)


def run_series_train(args: argparse.Namespace, series, field_config, train_config) -> int:
    """``apmgsrn train`` on a series: one model for every step.

    Args:
        args: the command line.
        series: the opened series.
        field_config, train_config: from the command line (the budget sized for the series).
    """
    from apmgsrn.device import resolve_device
    from apmgsrn.training.series_fit import fit_series
    from apmgsrn.training.trainer import TrainingInterrupted

    device = resolve_device(args.device)  # the same device build_configs sized the budget for
    config = build_series_config(args, field_config, len(series))
    stepwise, packing = series_training(args, config, series.raw_bytes, series.shape, train_config.iterations)
    out = Path(args.out)
    try:
        result = fit_series(series, config, train_config, out, device, transform=args.transform,
                            log_offset=args.log_offset, resume=args.resume, stepwise=stepwise, packing=packing)
    except TrainingInterrupted as exc:
        print(f"{exc}; run the same command with --resume to continue")
        return 130
    evaluation = result.evaluation
    raw_bytes = series.raw_bytes
    summary = {
        "model": str(out),
        "steps": len(series),
        "psnr": evaluation.psnr,
        "min_step_psnr": min(e.psnr for e in evaluation.steps),
        "max_abs_error": evaluation.max_abs_error,
        "model_bytes": result.model_bytes,
        "parameters": result.field.parameter_count(),
        "raw_bytes": raw_bytes,
        "compression_ratio": raw_bytes / result.model_bytes,
        "seconds": result.seconds,
        "iterations": result.iterations,
        "ms_per_iteration": 1000 * result.seconds / max(result.iterations, 1),
        "grids_frozen_at": result.frozen_at,
        "per_step": step_rows(series.labels, [series.step_name(t) for t in range(len(series))], evaluation),
    }
    if packing is not None and packing.target_bytes is not None and result.model_bytes > packing.target_bytes:
        summary["over_target"] = {"target_bytes": packing.target_bytes, "bits": packing.min_bits}
    stepwise = result.training.get("stepwise") or {}
    start = stepwise.get("start")
    if start is not None:
        summary["start_step"] = start
        summary["placement_moved_steps"] = stepwise.get("tracked_steps", [])
        summary["drifted_steps"] = drifted_steps(evaluation, start)
    if args.json:
        print(json.dumps(strict_json(summary)))
        return 0
    print(f"model       {out} ({format_bytes(result.model_bytes)}, {summary['parameters']:,} parameters, "
          f"{len(series)} steps)")
    print(f"data        {series.describe()} ({format_bytes(raw_bytes)} as float32)")
    print_evaluation(evaluation, series.labels)
    print(f"compression {summary['compression_ratio']:.1f}x")
    if result.iterations:
        print(f"training    {result.iterations} iterations in {result.seconds:.1f} s "
              f"({summary['ms_per_iteration']:.1f} ms/iteration), grids frozen at {result.frozen_at}")
    if summary.get("over_target"):
        from apmgsrn.training.series_packing import DEFAULT_SERIES_MODELS, series_growth

        over = summary["over_target"]
        files = DEFAULT_SERIES_MODELS * series_growth(len(series))
        print(f"note        the file is over the default size, {files:.3g} single-step files "
              f"({format_bytes(over['target_bytes'])}): the {len(series)} steps' grids take more even at "
              f"{over['bits']} bits; --size or --bits sets the size yourself (docs/time_series.md)")
    if summary.get("placement_moved_steps"):
        from apmgsrn.training.series_steps import TRACK_DB

        moved = summary["placement_moved_steps"]
        print(f"placement   moved with the structures at {len(moved)} step(s) ({_listed(moved)}), which fit more "
              f"than {TRACK_DB:g} dB worse than the start step with the start's")
    if summary.get("drifted_steps"):
        drifted = summary["drifted_steps"]
        print(f"note        {len(drifted)} step(s) ({_listed(drifted)}) fit more than {DRIFT_DB:g} dB worse than the "
              f"start step {start}: their structures may have changed more than the shared decoder follows "
              "(docs/time_series.md, 'Where it fails')")
    return 0


def _listed(steps: list[int]) -> str:
    """At most eight step indices, comma-separated."""
    return ", ".join(map(str, steps[:8])) + (" ..." if len(steps) > 8 else "")


#: A stepwise step this many dB below the start step's PSNR is reported as drifted.
DRIFT_DB = 6.0


def drifted_steps(evaluation, start: int) -> list[int]:
    """Steps of a stepwise series whose PSNR is more than :data:`DRIFT_DB` below the start step's."""
    reference = evaluation.steps[start].psnr
    return [t for t, e in enumerate(evaluation.steps) if reference - e.psnr > DRIFT_DB]


def series_training(args: argparse.Namespace, config, raw_bytes: int, shape: tuple[int, int, int],
                    iterations: int):
    """(StepwiseConfig or None for a joint model, SeriesPacking or None for a float file) of the command line.

    Args:
        args: the command line.
        config: the series model (sizes the default packing).
        raw_bytes: the series' bytes as float32 (``--ratio`` divides them).
        shape: ``(D, H, W)`` of every step (sizes a hybrid's tables, hence the default packing).
        iterations: the start model's (the default quantisation-aware and decoder fine-tunes are shares of them).

    Raises:
        ApmgsrnError: a packing option a series does not take, packing with --storage, or a bad --start-step.
    """
    from apmgsrn.cli.pack import JOINT_SERIES_QAT, series_packing
    from apmgsrn.training.series_packing import default_series_decoder, default_series_packing, default_series_qat
    from apmgsrn.training.series_steps import StepwiseConfig

    packing = series_packing(args, raw_bytes)
    qat = args.qat_iterations  # None: the model kind's default
    decoder = args.decoder_iterations  # None: the model kind's default
    if (packing is not None or qat or decoder) and args.storage is not None:
        raise ApmgsrnError("--bits, --size, --ratio, --qat-iterations and --decoder-iterations pack the grids, "
                           "--storage keeps them unpacked: give one")
    if args.series_training == "joint":
        if qat:
            raise ApmgsrnError(JOINT_SERIES_QAT)
        return None, packing
    start = args.start_step or "auto"
    if start not in ("auto", "first", "last"):
        try:
            start = int(start)
        except ValueError:
            raise ApmgsrnError(f"--start-step {start}: must be auto, first, last or a step index") from None
    stepwise = StepwiseConfig(start=start, step_iterations=args.step_iterations, step_sparsity=args.step_sparsity)
    if qat is None:
        qat = default_series_qat(config.field.model, iterations)
    if decoder is None:
        decoder = default_series_decoder(config.field.model, iterations)
    if packing is None and args.storage is None:
        packing = default_series_packing(config, shape, iterations)
    return stepwise, packing if packing is None else replace(packing, qat_iterations=qat, decoder_iterations=decoder)


def build_series_config(args: argparse.Namespace, field_config, steps: int):
    """The time-series model the command line asks for (defaults where options are not given).

    Raises:
        ApmgsrnError: options out of range.
    """
    from apmgsrn.models.series_field import series_config
    from apmgsrn.training.series_steps import stepwise_config

    stepwise = args.series_training == "stepwise"
    for option in JOINT_OPTIONS if stepwise else STEPWISE_OPTIONS:
        if getattr(args, option, None) is not None:
            flag = "--" + option.replace("_", "-")
            raise ApmgsrnError(f"{flag} shapes a joint series model; add --series-training joint or drop {flag}"
                               if stepwise else
                               f"{flag} applies to --series-training stepwise; drop it for a joint model")
    try:
        if stepwise:
            return stepwise_config(field_config, steps, args.storage or "float32")
        return series_config(field_config, steps, args.basis, args.coefficients, args.residual, args.storage)
    except ApmgsrnError:
        raise  # names the option already (translated by the command line)
    except ValueError as exc:
        raise ApmgsrnError(f"invalid time-series options: {exc}") from None


def step_rows(labels, names, evaluation) -> list[dict]:
    """One JSON-able row per evaluated step: index, number, file, PSNR, largest error, value range."""
    rows = []
    for index, result in zip(evaluation.indices, evaluation.steps):
        label = labels[index]
        rows.append({"step": index, "label": int(label) if float(label).is_integer() else label,
                     "name": names[index], **result.to_dict()})
    return rows


def strict_json(value):
    """``value`` with every non-finite float (an exact step's infinite PSNR) as null."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: strict_json(v) for k, v in value.items()}
    if isinstance(value, list):
        return [strict_json(v) for v in value]
    return value


def print_evaluation(evaluation, labels) -> None:
    """The per-step table and the figures over the whole series."""
    overall = evaluation.overall
    print(f"{'step':>6} {'number':>8} {'PSNR dB':>8} {'max abs error':>14}")
    for index, result in zip(evaluation.indices, evaluation.steps):
        print(f"{index:>6} {labels[index]:>8g} {result.psnr:>8.2f} {result.max_abs_error:>14.6g}")
    worst = evaluation.worst_step
    print(f"PSNR        {overall.psnr:.2f} dB over all voxels of {len(evaluation.steps)} steps; lowest step "
          f"{worst} ({evaluation.steps[evaluation.indices.index(worst)].psnr:.2f} dB)")
    share = percent_of_range(overall.max_abs_error, overall.data_min, overall.data_max)
    print(f"max abs err {overall.max_abs_error:.6g} ({share})")


def run_series_eval(args: argparse.Namespace, model) -> int:
    """``apmgsrn eval`` of a time-series model against its series."""
    from apmgsrn.inference.evaluate import evaluate_series

    layout = model.description.series
    series = open_series_data(args)
    if len(series) != len(layout.steps):
        raise ApmgsrnError(
            f"{args.model}: the model holds {len(layout.steps)} steps but the data names {len(series)}; "
            "pass the series it was trained on"
        )
    evaluation = evaluate_series(model.field.step_field, series, trained_shape=model.description.volume_shape,
                                 progress=True, batch_size=args.batch_size)
    raw_bytes, model_bytes = series.raw_bytes, model.description.file_bytes
    if args.json:
        figures = {**evaluation.overall.to_dict(), "steps": len(series), "model_bytes": model_bytes,
                   "raw_bytes": raw_bytes, "compression_ratio": raw_bytes / model_bytes,
                   "per_step": step_rows(series.labels, [series.step_name(t) for t in range(len(series))], evaluation)}
        print(json.dumps(strict_json(figures)))
        return 0
    print_evaluation(evaluation, series.labels)
    print(f"model size  {format_bytes(model_bytes)} ({model_bytes:,} bytes)")
    print(f"raw float32 {format_bytes(raw_bytes)} ({len(series)} steps)")
    print(f"compression {raw_bytes / model_bytes:.1f}x")
    return 0


def model_step(model, time, option: str = "--time") -> int:
    """The step ``--time K`` picks of a time-series model (required: a series has no default step)."""
    layout = model.description.series
    if time is None:
        raise ApmgsrnError(f"the model holds {len(layout.steps)} time steps; pass {option} K (0..{len(layout.steps) - 1})"
                           " or --time all")
    return layout.step_index(time)


def selected_steps(model, time) -> list[int]:
    """Step indices of ``--time``: one index, ``all`` or ``A:B[:S]`` over the model's steps."""
    from apmgsrn.data.series import TimeSelection

    if isinstance(time, TimeSelection):
        return list(time.indices(len(model.description.series.steps), "model"))
    return [model_step(model, time)]


def run_series_decode(args: argparse.Namespace, model, shape, region) -> int:
    """``apmgsrn decode`` of several steps of a time-series model: one file per step (``--out`` holds
    ``{step}``), or one file with a time axis.

    Args:
        args: the command line.
        model: the opened :class:`apmgsrn.Model`.
        shape: ``(D, H, W)`` samples, or None (the training volume's spacing over the region).
        region: the box to decode, or None (all of it).
    """
    from apmgsrn.cli.paths import CommandPaths, Output, check_paths
    from apmgsrn.inference.decode import decode_series

    layout = model.description.series
    indices = selected_steps(model, args.time)
    out = str(args.out)
    plan = model.plan_decode(shape=shape, region=region, time=indices[0])
    d, h, w = plan.shape
    if STEP_FIELD in out:
        width = len(str(len(layout.steps) - 1))
        targets = [Path(out.replace(STEP_FIELD, f"{index:0{width}d}")) for index in indices]
    else:
        targets = [Path(out)]
    # The step files are known only now: each gets the checks --out had (never onto the model or a model).
    check_paths(CommandPaths(reads=[args.model], writes=[Output(t, "--out", "decoded volume") for t in targets]))
    report = {"out": [str(t) for t in targets], "written": not args.dry_run, "steps": indices,
              "shape_xyz": [w, h, d], "variable": plan.variable, "time_steps": len(layout.steps)}
    if not args.dry_run and STEP_FIELD in out:
        for index, target in zip(indices, targets):
            model.save_decoded(target, shape=shape, region=region, time=index, batch_size=args.batch_size,
                               progress=not args.json)
    elif not args.dry_run:
        options = plan.writer_options()
        options["attributes"] = {"source_model": Path(args.model).name}
        decode_series(model.step_field, targets[0], plan.shape, indices,
                      time_values=[layout.steps[i].label for i in indices], batch_size=args.batch_size,
                      progress=not args.json, box=plan.grid.box(), **options)
    if args.json:
        print(json.dumps(report))
        return 0
    verb = "would write" if args.dry_run else "wrote"
    if len(targets) > 1:
        print(f"{verb} {len(indices)} files {out} ({w}x{h}x{d} x*y*z each, float32, variable {plan.variable})")
    else:
        print(f"{verb} {out} ({len(indices)} steps x {w}x{h}x{d} x*y*z, float32, time first)")
    return 0


def describe_series(model) -> dict:
    """What ``info`` adds for a time-series model: the time axis and each step's figures from training."""
    layout = model.description.series
    per_step = model.description.training.get("steps") or []
    steps = []
    for index, step in enumerate(layout.steps):
        figures = per_step[index] if index < len(per_step) and isinstance(per_step[index], dict) else {}
        steps.append({**step.to_dict(), "psnr": figures.get("psnr"), "max_abs_error": figures.get("max_abs_error")})
    stepwise = model.description.training.get("stepwise")
    return {"kind": "series", **layout.config.to_dict(), "per_step": steps,
            "stepwise": stepwise if isinstance(stepwise, dict) else None}


def print_series_info(info: dict) -> None:
    """The time axis of ``info``'s text output."""
    stepwise = info.get("stepwise") or {}
    counts = [n for n in stepwise.get("step_iterations") or [] if isinstance(n, int) and n > 0]
    if isinstance(stepwise.get("start"), int) and counts:
        sparsity = stepwise.get("step_sparsity")
        pulled = (f", pulled towards its neighbour at {sparsity:g}" if isinstance(sparsity, (int, float)) and sparsity
                  else "")
        full = stepwise.get("step_pull_iterations")  # longer fine-tunes are pulled less (series_steps.step_pull)
        weaker = [t for t in stepwise.get("weaker_pull_steps") or [] if isinstance(t, int)]
        if pulled and isinstance(full, int) and weaker:
            pulled += f" (less on {len(weaker)} fine-tuned past {full} iterations)"
        start_iterations = stepwise.get("start_iterations")
        trained = (f" ({start_iterations} iterations)" if isinstance(start_iterations, int) and start_iterations > 0
                   else "")
        print(f"time        {info['steps']} steps, each with its own grids: trained stepwise from step "
              f"{stepwise['start']}{trained}, {min(counts)} to {max(counts)} iterations per other step{pulled}")
        scale = stepwise.get("budget_scale")
        if isinstance(scale, (int, float)) and 0 < scale < 1:
            print(f"            every step's fine-tunes shortened to {scale:.2f} of their base share, "
                  "to stay within the budget")
        moved = [t for t in stepwise.get("tracked_steps") or [] if isinstance(t, int)]
        if moved:
            print(f"            grids placed per step; moved with the structures at {len(moved)} step(s) "
                  f"({_listed(moved)})")
    elif info.get("placement") == "per_step":  # stepwise bricks: each brick and group of steps has its own start
        print(f"time        {info['steps']} steps, each with its own grids and placement: trained stepwise")
    else:
        print(f"time        {info['steps']} steps; {info['basis']} basis grids per grid, {info['coefficients']} "
              "weights" + (f", per-step residual {info['residual']}^3" if info["residual"] else ""))
    print(f"  {'step':>5}  {'number':>8}  {'file':<32}  {'PSNR dB':>8}  {'value range'}")
    for index, step in enumerate(info["per_step"]):
        psnr = step["psnr"]
        psnr_text = f"{psnr:.2f}" if isinstance(psnr, (int, float)) and math.isfinite(psnr) else "?"
        print(f"  {index:>5}  {step['label']:>8g}  {step['name'][:32]:<32}  {psnr_text:>8}  "
              f"[{step['value_min']:.4g}, {step['value_max']:.4g}]")


def render_steps(args: argparse.Namespace) -> tuple[dict, int | None, list[int]]:
    """How ``render`` reads its input over time.

    Returns:
        ``(volume options, first step, steps)``: for a time-series model ``--time`` picks its step (default
        0) or, with several steps, ``steps`` lists the frames of an animation over time; for anything else
        ``--time`` stays a volume option (one index along a time dimension) and there are no steps.
    """
    from apmgsrn.data.series import TimeSelection
    from apmgsrn.io import model_kind
    from apmgsrn.io.container import SERIES_FILE_KINDS

    if model_kind(args.input) not in SERIES_FILE_KINDS:
        return volume_options(args), None, []
    options = volume_options(argparse.Namespace(**{**vars(args), "time": None}))
    if not isinstance(args.time, TimeSelection):
        return options, args.time, []
    from apmgsrn.io.series_file import declared_steps

    steps = list(args.time.indices(declared_steps(args.input), args.input))
    return options, steps[0], (steps if len(steps) > 1 else [])

"""Time series on the command line: the options and runs of ``train``, ``eval``, ``decode`` and ``info`` for a
series (several files, a quoted glob, a ``.pvd`` collection, or one file with ``--time all|A:B[:S]``).

Wiring only: the series is read by :mod:`apmgsrn.series.data`, modelled by
:mod:`apmgsrn.series.field`, fitted by :func:`apmgsrn.training.fit.fit_series` and measured by
:func:`apmgsrn.series.evaluate.evaluate_series`.
"""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

from apmgsrn.cli.common import format_bytes, percent_of_range, volume_options
from apmgsrn.errors import ApmgsrnError
from apmgsrn.recipes import PACKING, SERIES

#: Placeholder of ``decode --time all --out``: one file per step.
STEP_FIELD = "{step}"


def single_input(args: argparse.Namespace) -> str:
    """The one DATA path of a command that reads one volume (several name a series).

    Raises:
        ApmgsrnError: several inputs.
    """
    if len(args.data) != 1:
        raise ApmgsrnError(f"{len(args.data)} inputs given where one volume is read; name one file")
    return args.data[0]


def open_series_data(args: argparse.Namespace):
    """The series DATA names, with the data options of ``args``."""
    from apmgsrn.series.data import open_series

    options = volume_options(args, allow_series=True)
    return open_series(args.data, **options)


def run_series_train(args: argparse.Namespace, plan) -> int:
    """``apmgsrn train`` on a series: one model for every step, as the plan (:mod:`apmgsrn.planning`) says."""
    import torch

    from apmgsrn.series.fit import fit_series
    from apmgsrn.training.trainer import TrainingInterrupted

    series, packing = plan.source, plan.packing
    out = Path(args.out)
    try:
        result = fit_series(series, plan.field, plan.training, out, torch.device(plan.device),
                            transform=plan.transform, log_offset=plan.log_offset, resume=args.resume,
                            stepwise=plan.stepwise, packing=packing, plan=plan.record())
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
        from apmgsrn.series.packing import series_growth

        over = summary["over_target"]
        files = PACKING.series_models * series_growth(len(series))
        print(f"note        the file is over the default size, {files:.3g} single-step files "
              f"({format_bytes(over['target_bytes'])}): the {len(series)} steps' grids take more even at "
              f"{over['bits']} bits; --size or --bits sets the size yourself (docs/time_series.md)")
    if summary.get("placement_moved_steps"):
        moved = summary["placement_moved_steps"]
        print(f"placement   moved with the structures at {len(moved)} step(s) ({_listed(moved)}), which fit more "
              f"than {SERIES.track_db:g} dB worse than the start step with the start's")
    if summary.get("drifted_steps"):
        drifted = summary["drifted_steps"]
        print(f"note        {len(drifted)} step(s) ({_listed(drifted)}) fit more than {SERIES.drift_db:g} dB worse "
              f"than the start step {start}: their structures may have changed more than the shared decoder follows "
              "(docs/time_series.md, 'Where it fails')")
    return 0


def _listed(steps: list[int]) -> str:
    """At most eight step indices, comma-separated."""
    return ", ".join(map(str, steps[:8])) + (" ..." if len(steps) > 8 else "")


def drifted_steps(evaluation, start: int) -> list[int]:
    """Steps of a stepwise series whose PSNR is more than ``SERIES.drift_db`` below the
    start step's."""
    reference = evaluation.steps[start].psnr
    return [t for t, e in enumerate(evaluation.steps) if reference - e.psnr > SERIES.drift_db]


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
    from apmgsrn.series.evaluate import evaluate_series

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
    from apmgsrn.series.data import TimeSelection

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
    from apmgsrn.series.decode import decode_series

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
    from apmgsrn.series.data import TimeSelection  # the series package: model_kind then knows its kinds
    from apmgsrn.io import model_kind
    from apmgsrn.io.container import SERIES_FILE_KINDS

    if model_kind(args.input) not in SERIES_FILE_KINDS:
        return volume_options(args), None, []
    options = volume_options(argparse.Namespace(**{**vars(args), "time": None}))
    if not isinstance(args.time, TimeSelection):
        return options, args.time, []
    from apmgsrn.series.file import declared_steps

    steps = list(args.time.indices(declared_steps(args.input), args.input))
    return options, steps[0], (steps if len(steps) > 1 else [])

"""``apmgsrn info``: what a model file holds."""

from __future__ import annotations

import argparse
import dataclasses
import json
import math

import apmgsrn
from apmgsrn.atomic import atomic_write
from apmgsrn.cli.common import compression_figures, compression_text, format_bytes
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.errors import ApmgsrnError


def register(subparsers) -> None:
    parser = subparsers.add_parser("info", help="describe a model file")
    parser.add_argument("model", help="model file")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--plot", metavar="FILE.png",
                        help="also draw the training curves to this image (a file of that name is replaced, "
                             "unless it is an apmgsrn model)")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    writes = [Output(args.plot, "--plot", "plot", suffixes=(".png",))] if args.plot else []
    return CommandPaths(reads=[args.model], writes=writes)


def plot_training_curves(training: dict, out: str) -> None:
    """Reconstruction and density loss and learning rate against iteration, grid freeze marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    history = training.get("history") or {}
    if not history.get("iteration"):
        raise ApmgsrnError(f"{out}: the model holds no training history to plot")
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(7, 6), sharex=True)
    top.semilogy(history["iteration"], history["reconstruction"], label="reconstruction (MSE, [0,1] units)")
    density = [(i, d) for i, d in zip(history["iteration"], history["density"]) if d == d]
    if density:
        top.semilogy(*zip(*density), label="feature density (KL)")
    bottom.plot(history["iteration"], history["lr"], color="tab:green", label="network learning rate")
    frozen = training.get("frozen_at")
    for axis in (top, bottom):
        if frozen:
            axis.axvline(frozen, color="gray", linestyle="--", label=f"grids frozen ({frozen})")
        axis.legend(loc="upper right", fontsize=8)
        axis.grid(alpha=0.3)
    bottom.set_xlabel("iteration")
    top.set_title(f"training: {training.get('iterations')} iterations, PSNR {training.get('psnr', float('nan')):.2f} dB")
    fig.tight_layout()
    try:
        atomic_write(out, lambda temp: fig.savefig(temp, dpi=110, format="png"), "plot")
    finally:
        plt.close(fig)


def describe_field(field, description) -> dict:
    """A JSON-able description of a single-field model.

    Args:
        field: the :class:`~apmgsrn.models.field.NeuralField`.
        description: its file's :class:`~apmgsrn.io.ModelDescription`.
    """
    from apmgsrn.models.registry import stored_bytes

    config = description.config  # the spatial network (of every step, for a time-series model)
    info = {
        "model": config.model,
        "encoder": {k: v for k, v in config.to_dict()["encoder"].items()},
        "decoder": dataclasses.asdict(config.decoder),
        "parameters": field.parameter_count(),
        "parameter_bytes": stored_bytes(field.config),
        "file_bytes": description.file_bytes,
        "volume_shape_xyz": list(reversed(description.volume_shape)),
        "value_range": list(description.value_range),
        "transform": dataclasses.asdict(field.transform),
        "source": description.source.to_dict(),
        **_compression(description),
    }
    if description.packing is not None:
        info["packing"] = describe_packing(description.packing)
    training = dict(description.training)
    history = training.pop("history", None)
    if history and history.get("reconstruction"):
        info["final_reconstruction_loss"] = history["reconstruction"][-1]
    info["training"] = training
    if config.model == "ngp":  # hash grid: what each level really stores
        info["levels"] = [
            {"resolution": r, "table_entries": n, "dense": r**3 <= n}
            for r, n in zip(config.encoder.level_resolutions(), config.encoder.level_table_sizes())
        ]
    boxes = field.encoder.grid_boxes()  # [M, 8, 3] or None
    if boxes is not None:
        info["grids"] = [
            {"center": [round(v, 4) for v in box.mean(0).tolist()],
             "extent": [round(v, 4) for v in (box.max(0).values - box.min(0).values).tolist()]}
            for box in boxes
        ]
    return info


def describe_packing(packing) -> dict:
    """A packed file's parts (bytes, bits per value), what packing measured and its error bound, JSON-able."""
    return {
        "parts": [{**dataclasses.asdict(part), "bits_per_value": part.bits_per_value} for part in packing.parts],
        "container_bytes": packing.container_bytes,
        "float32_parameter_bytes": packing.float32_bytes,
        "max_error": packing.max_error,
        "corrected_voxels": packing.corrected_voxels,
        "correction_bytes": packing.correction_bytes,
        "report": packing.report,
    }


def packing_lines(packing: dict) -> list[str]:
    """``info``'s lines about a packed file."""
    report = packing["report"]
    lines = [f"packing         {report.get('mode')}: PSNR {report.get('psnr', float('nan')):.2f} dB packed, "
             f"{report.get('float32_psnr', float('nan')):.2f} dB float32 (cost {report.get('psnr_cost', float('nan')):.3f}"
             f" dB, measured when packed), fine-tune {report.get('qat_iterations') or 0} iterations"
             + (f" (undone on {report['qat_restored_steps']} step(s) to fit the size)"
                if isinstance(report.get("qat_restored_steps"), int) and report["qat_restored_steps"] > 0 else "")
             + (f", decoder fine-tuned {report['decoder_iterations']} iterations"
                if isinstance(report.get("decoder_iterations"), int) and report["decoder_iterations"] > 0 else "")]
    if packing["max_error"] is not None:
        lines.append(f"error bound     |model - data| <= {packing['max_error']:.6g} at every voxel: "
                     f"{packing['corrected_voxels']:,} voxels corrected, {packing['correction_bytes']:,} bytes")
    lines.append(f"  {'part':<24}  {'encoding':<9}  {'values':>9}  {'bytes':>9}  {'bits/value':>10}  {'max bits':>8}")
    for part in packing["parts"]:
        per_value = f"{part['bits_per_value']:.2f}" if part["bits_per_value"] is not None else "-"
        lines.append(f"  {part['name']:<24}  {part['encoding']:<9}  {part['values']:>9,}  {part['bytes']:>9,}  "
                     f"{per_value:>10}  {part['bits'] if part['bits'] is not None else '-':>8}")
    lines.append(f"  {'container framing':<24}  {'':<9}  {'':>9}  {packing['container_bytes']:>9,}")
    return lines


def _compression(description) -> dict:
    """Compression figures of the file against its training volume (every step of a series; stored dtype when
    the file records it)."""
    from apmgsrn.io.description import time_steps

    return compression_figures(math.prod(description.volume_shape) * time_steps(description), description.source.dtype,
                               description.source.itemsize, description.file_bytes)


def run(args: argparse.Namespace) -> int:

    model = apmgsrn.load(args.model)
    if model.description.bricks is not None:
        return _run_bricks(args, model)
    series = None
    if model.description.series is not None:
        from apmgsrn.cli.series import describe_series, print_series_info, strict_json

        series = describe_series(model)
    info = describe_field(model.field, model.description)
    if series is not None:
        info["series"] = series
    if args.plot:
        plot_training_curves(model.description.training, args.plot)
    if args.json:
        print(json.dumps(info if series is None else strict_json(info)))
        return 0
    enc = info["encoder"]
    t = info["training"]
    print(f"file            {args.model} ({format_bytes(info['file_bytes'])})")
    print(f"model           {info['model']}: " + ", ".join(f"{k}={v}" for k, v in enc.items()))
    print(f"decoder         {info['decoder']['hidden_layers']} x {info['decoder']['width']}, ReLU, no bias")
    print(f"parameters      {info['parameters']:,} ({format_bytes(info['parameter_bytes'])} as stored)")
    x, y, z = info["volume_shape_xyz"]
    print(f"volume          {x}x{y}x{z} (x*y*z) from {info['source'].get('description') or '?'}")
    print(f"value range     [{info['value_range'][0]:.6g}, {info['value_range'][1]:.6g}], transform {info['transform']['kind']}")
    _print_source_metadata(model.description)
    print(f"compression     {compression_text(info)}")
    if "packing" in info:
        print("\n".join(packing_lines(info["packing"])))
    if t:
        psnr = f", PSNR {t['psnr']:.2f} dB" if isinstance(t.get("psnr"), (int, float)) else ""
        config = t.get("config") if isinstance(t.get("config"), dict) else {}
        fraction = config.get("voxel_fraction")
        voxels = f" ({fraction:g} of each on voxels)" if isinstance(fraction, (int, float)) and fraction > 0 else ""
        guided = config.get("error_sampling")
        if voxels and isinstance(guided, (int, float)) and guided > 0:
            voxels = f" ({fraction:g} of each on voxels, {guided:g} of those where the error was)"
        print(f"training        {t.get('iterations')} iterations x {t.get('batch_size')} points{voxels}, "
              f"{t.get('seconds')} s on {t.get('device')}{psnr}")
        if "final_reconstruction_loss" in info:  # a packed file keeps no loss history
            print(f"final losses    reconstruction {info['final_reconstruction_loss']:.3e}, "
                  f"density {t.get('final_density_loss')}")
        anchored = config.get("anchored_grids")
        anchored = f" ({anchored} anchored over the domain)" if isinstance(anchored, int) and anchored > 0 else ""
        print(f"grids frozen at iteration {t.get('frozen_at')}{anchored}")
        if isinstance(t.get("plan"), dict):
            print(f"plan            {plan_line(t['plan'])} (info --json has all of it)")
    levels = info.get("levels")
    if levels:
        dense = sum(level["dense"] for level in levels)
        print(f"hash levels     {len(levels)}: resolution {levels[0]['resolution']}..{levels[-1]['resolution']}, "
              f"table entries {min(v['table_entries'] for v in levels):,}..{max(v['table_entries'] for v in levels):,} "
              f"per level ({dense} stored densely)")
    if series is not None:
        print_series_info(series)
    for i, grid in enumerate(info.get("grids", [])):
        c, e = grid["center"], grid["extent"]
        print(f"  grid {i:2d}  center ({c[0]:+.3f}, {c[1]:+.3f}, {c[2]:+.3f})  extent ({e[0]:.3f}, {e[1]:.3f}, {e[2]:.3f})")
    return 0


def plan_line(plan: dict) -> str:
    """One line of the plan a model was trained with (:meth:`apmgsrn.planning.Plan.record`)."""
    training = plan.get("training") if isinstance(plan.get("training"), dict) else {}
    packing = plan.get("packing") if isinstance(plan.get("packing"), dict) else None
    steps = f" of {plan['steps']} steps" if isinstance(plan.get("steps"), int) else ""
    parts = [f"{plan.get('model')} {plan.get('input')}{steps} on {plan.get('device')}",
             f"{training.get('iterations')} iterations x {training.get('batch_size')} points, seed {training.get('seed')}"]
    if plan.get("stepwise"):
        parts.append("stepwise")
    if packing is not None:
        target = packing.get("target_bytes")
        parts.append(f"packed ({plan.get('packing_kind')}" + (f", to {target:,} bytes)" if isinstance(target, int)
                                                               else ")"))
    return ", ".join(parts)


def _print_source_metadata(description) -> None:
    """The variable's units and the coordinates of its axes, as the input had them (what decode writes back)."""
    source = description.source
    metadata = source.metadata
    if metadata.units is not None:
        print(f"variable        {source.variable or 'value'} in {metadata.units}")
    if metadata.coordinates is None:
        return
    parts = []
    for axis in (2, 1, 0):
        coordinates = metadata.axis(axis)
        first, last = coordinates.at([0.0, description.volume_shape[axis] - 1.0])
        units = coordinates.attributes.get("units")
        spacing = "even" if coordinates.even else "uneven"
        parts.append(f"{coordinates.name} {first:.6g}..{last:.6g}{f' {units}' if units else ''} ({spacing})")
    print(f"coordinates     {', '.join(parts)}")


def describe_bricks(model) -> dict:
    """A JSON-able description of a brick model (an :class:`apmgsrn.Model` of kind ``bricks``): grid, ghost
    cells, blend and per-brick figures."""
    from apmgsrn.models.registry import stored_bytes

    description = model.description
    layout = description.bricks
    first = model.field.bricks[0]
    info = {
        "kind": "bricks",
        "bricks": list(layout.counts),
        "ghost_cells": layout.ghost_cells,
        "blend": layout.blend,
        "brick_model": describe_field(first, description) | {"training": {}, "grids": None},
        "parameters": description.parameters,
        "parameter_bytes": sum(stored_bytes(brick.config) for brick in model.field.bricks),
        "file_bytes": description.file_bytes,
        "volume_shape_xyz": list(reversed(description.volume_shape)),
        "value_range": list(description.value_range),
        "source": description.source.to_dict(),
        **_compression(description),
        "training": description.training,
        "per_brick": [],
    }
    for entry in layout.entries:
        summary = entry.summary
        info["per_brick"].append({
            "name": entry.name,
            "position": list(entry.position),
            "voxels_zyx": [list(entry.start), list(entry.stop)],
            **{k: summary.get(k) for k in ("psnr", "iterations", "stopped_early", "seconds", "value_min",
                                           "value_max", "bytes", "device")},
        })
    return info


def _run_bricks(args: argparse.Namespace, model) -> int:
    info = describe_bricks(model)
    series = None
    if model.description.series is not None:
        from apmgsrn.cli.series import describe_series, print_series_info

        series = info["series"] = describe_series(model)
    if args.json:
        # Strict JSON: an exact (constant) brick's infinite PSNR becomes null.
        for brick in info["per_brick"]:
            if isinstance(brick["psnr"], float) and brick["psnr"] in (float("inf"), float("-inf")):
                brick["psnr"] = None
        print(json.dumps(info))
        return 0
    i, j, k = info["bricks"]
    each = info["brick_model"]
    print(f"folder          {args.model} ({format_bytes(info['file_bytes'])} in {i * j * k + 1} files)")
    print(f"bricks          {i} x {j} x {k} (x, y, z), ghost cells {info['ghost_cells']}, "
          f"blend {'on' if info['blend'] else 'off'}")
    print(f"brick model     {each['model']}: " + ", ".join(f"{key}={v}" for key, v in each["encoder"].items()))
    print(f"parameters      {info['parameters']:,} in all ({format_bytes(info['parameter_bytes'])} as stored), "
          f"{each['parameters']:,} per brick")
    x, y, z = info["volume_shape_xyz"]
    print(f"volume          {x}x{y}x{z} (x*y*z) from {info['source'].get('description') or '?'}")
    print(f"value range     [{info['value_range'][0]:.6g}, {info['value_range'][1]:.6g}]")
    _print_source_metadata(model.description)
    print(f"compression     {compression_text(info)}")
    t = info["training"] or {}
    if t:
        print(f"last run        {t.get('last_run_trained')} brick(s) in {t.get('last_run_seconds')} s on "
              f"{t.get('last_run_where')}")
    print(f"  {'brick':<17}  {'x voxels':>9}  {'y voxels':>9}  {'z voxels':>9}  {'PSNR dB':>8}  {'iterations':>10}  "
          f"{'seconds':>8}")
    for brick in info["per_brick"]:
        (z0, y0, x0), (z1, y1, x1) = brick["voxels_zyx"]
        psnr = brick["psnr"]
        psnr_text = "exact" if psnr == float("inf") else (f"{psnr:.2f}" if isinstance(psnr, (int, float)) else "?")
        early = " (early stop)" if brick["stopped_early"] and brick["iterations"] else ""
        iterations = brick["iterations"] if brick["iterations"] is not None else "?"
        seconds = f"{brick['seconds']:.1f}" if isinstance(brick["seconds"], (int, float)) else "?"
        print(f"  {brick['name']:<17}  {f'{x0}:{x1}':>9}  {f'{y0}:{y1}':>9}  {f'{z0}:{z1}':>9}  {psnr_text:>8}  "
              f"{iterations:>10}  {seconds:>8}{early}")
    if series is not None:
        print_series_info(series)
    return 0

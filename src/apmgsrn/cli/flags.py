"""Library argument names -> command-line options: how an error's advice reaches a CLI user; and the number
gate of every option.

The library names its own arguments in errors (``pass fill_nonfinite=VALUE``), which is right for a
Python caller; the command line says the same with its options (``pass --fill-nonfinite VALUE``). This
table is the one place that knows both names.

Every number a command line gives is checked as it is parsed (:func:`register_number_types`): an ``int``
option takes int64 at most, a ``float`` option a finite number (no NaN, no infinity, no ``1e400``); options
with a range of their own check it there too (:mod:`apmgsrn.options`, :func:`apmgsrn.arguments.int_type`).
"""

from __future__ import annotations

import argparse
import re

from apmgsrn.arguments import int_type, number_type
from apmgsrn.errors import ApmgsrnError


def register_number_types(parser: argparse.ArgumentParser) -> None:
    """Make ``type=int`` parse an int64 and ``type=float`` a finite float, in ``parser`` (its argument groups
    share the table; a subparser of the same class registers its own)."""
    parser.register("type", int, int_type())
    parser.register("type", float, number_type())

#: library argument -> the option that sets it (every option named here exists in some subcommand).
FLAGS = {
    # data
    "variable": "--variable",
    "time": "--time",
    "shape": "--shape",
    "dtype": "--dtype",
    "fill_nonfinite": "--fill-nonfinite",
    # decoding and export
    "region": "--region",
    "region_units": "--region-units",
    "format": "--format",
    # fitting
    "out": "--out",
    "resume": "--resume",
    "transform": "--transform",
    "log_offset": "--log-offset",
    "backend": "--backend",
    "grids": "--grids",
    "features": "--features",
    "resolution": "--resolution",
    "init": "--grid-init",
    "hidden_layers": "--hidden-layers",
    "levels": "--levels",
    "log2_table_size": "--log2-table-size",
    "base_resolution": "--base-resolution",
    "finest_resolution": "--finest-resolution",
    "frequencies": "--frequencies",
    "iterations": "--iterations",
    "minutes": "--minutes",
    "batch_size": "--batch-size",
    "lr": "--lr",
    "placement_lr": "--placement-lr",
    "lr_schedule": "--lr-schedule",
    "voxel_fraction": "--voxel-fraction",
    "error_sampling": "--error-sampling",
    "anchored_grids": "--anchored-grids",
    "density_start": "--density-start",
    "freeze_fraction": "--freeze-fraction",
    "density_normalization": "--density-normalization",
    "decoder_precision": "--decoder-precision",
    "precision": "--precision",
    "seed": "--seed",
    "checkpoint_every": "--checkpoint-every",
    "device": "--device",
    # time series
    "basis": "--basis",
    "coefficients": "--coefficients",
    "residual": "--residual",
    "storage": "--storage",
    "steps_per_iteration": "--steps-per-iteration",
    "series_training": "--series-training",
    "start": "--start-step",
    "start_step": "--start-step",
    "step_lr": "--step-lr",
    "step_iterations": "--step-iterations",
    "step_sparsity": "--step-sparsity",
    "decoder_iterations": "--decoder-iterations",
    # packing
    "bits": "--bits",
    "psnr_loss": "--psnr-loss",
    "target_bytes": "--size",
    "size": "--size",
    "ratio": "--ratio",
    "max_error": "--max-error",
    "qat_iterations": "--qat-iterations",
    # bricks
    "bricks": "--bricks",
    "ghost_cells": "--ghost-cells",
    "workers": "--workers",
    "scheduler": "--scheduler",
    "retries": "--retries",
    "group_steps": "--group-steps",
    "blend": "--blend",
    # rendering
    "width": "--width",
    "height": "--height",
    "azimuth": "--azimuth",
    "elevation": "--elevation",
    "distance": "--distance",
    "fov": "--fov",
    "samples_per_ray": "--spp",
    "reference_samples": "--reference-samples",
    "early_termination": "--early-termination",
    "macro_cells": "--macro-cells",
    "background": "--background",
    "value_range": "--range",
    "colormap": "--colormap",
    "preset_name": "--preset-name",
    "opacity": "--opacity",
    "units": "--preset-units",
    "preset_units": "--preset-units",
    "frames": "--frames",
    "fps": "--fps",
    # benchmarks and pictures
    "models": "--models",
    "model": "--model",
    "sizes": "--sizes",
    "preset": "--preset",
    "compressors": "--compressors",
    "seeds": "--seeds",
    "bounds": "--bounds",
    "precisions": "--precisions",
    "rates": "--rates",
    "psnrs": "--psnrs",
    "ratios": "--ratios",
    "ratio_tolerance": "--ratio-tolerance",
    "query_points": "--query-points",
    "compress_seconds": "--compress-seconds",
    "every": "--every",
}


def cli_message(error: ApmgsrnError) -> str:
    """The error's message with the library arguments it names written as options.

    ``name=True`` and a bare ``name=`` (before a space or the end) become the flag alone (``resume=True`` ->
    ``--resume``); ``name=VALUE`` becomes ``--flag VALUE``. Only the names the error lists in ``arguments`` are rewritten, so a file name or a
    stored value that happens to contain ``name=`` is left as it is.
    """
    message = str(error)
    for name in getattr(error, "arguments", ()):
        flag = FLAGS.get(name)
        if flag is None:
            continue
        message = re.sub(rf"(?<![\w-]){re.escape(name)}=(True\b|(?=[\s,;:)]|$))", flag, message)
        message = re.sub(rf"(?<![\w-]){re.escape(name)}=", f"{flag} ", message)
    return message

"""``apmgsrn pack``: a trained model into a small packed file, optionally with an error bound; a time-series model
at a bit width or to a size; and the packing options ``train`` shares (training then packs its model at the end)."""

from __future__ import annotations

import argparse
import json
import math
from dataclasses import replace
from pathlib import Path

from apmgsrn.cli.common import (
    add_data_arguments,
    add_device_argument,
    compression_figures,
    compression_text,
    format_bytes,
    open_data,
    volume_options,
)
from apmgsrn.cli.paths import CommandPaths, Output
from apmgsrn.errors import ApmgsrnError
from apmgsrn.options import PACKING, add_option_arguments

#: Why ``pack --decoder-iterations`` is refused for a joint series.
JOINT_SERIES_DECODER = ("--decoder-iterations: fine-tunes the decoder to every step's own packed grids; a joint "
                        "series has no grids of its own per step")


def packing_lines(report: dict, file_bytes: int, compression: dict) -> list[str]:
    """What ``pack`` and ``train`` print about a packed file."""
    lines = [
        f"packed      {format_bytes(file_bytes)} ({file_bytes:,} bytes; float32 parameters "
        f"{format_bytes(report['float32_parameter_bytes'])}), {compression_text(compression)}",
        f"PSNR        {report['psnr']:.2f} dB packed, {report['float32_psnr']:.2f} dB float32 "
        f"(cost {report['psnr_cost']:.3f} dB); max abs error {report['max_abs_error']:.4g}",
    ]
    if report.get("corrected_voxels") is not None:
        lines.append(f"error bound {report['max_error']:.6g}: max abs error {report['bounded_max_abs_error']:.6g} "
                     f"over every voxel ({report['corrected_voxels']:,} voxels corrected), "
                     f"PSNR {report['bounded_psnr']:.2f} dB")
    return lines


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "pack",
        help="pack a model into a small file (quantised, entropy-coded, optional error bound)",
        description="Quantise and entropy-code a trained model against the volume it was trained on; the file "
                    "loads like any model. The volume measures the PSNR cost (stored in the file) and makes "
                    "the correction of --max-error. A time-series model packs at --bits (default 10) or to "
                    "--size / --ratio (the largest bit width that fits) and is measured on its series.",
    )
    parser.add_argument("model", help="trained model file (float32 or packed; one volume or a time series)")
    parser.add_argument("data", nargs="+",
                        help="the volume the model was trained on; for a time-series model its series (several "
                             "files, a quoted glob, a .pvd, or one file with --time all)")
    parser.add_argument("--out", required=True,
                        help="packed model file to write (an existing apmgsrn model there is replaced atomically)")
    add_data_arguments(parser)
    add_option_arguments(parser, (PACKING,))
    parser.add_argument("--decoder-iterations", type=int, metavar="N",
                        help="a stepwise time series: iterations of a fine-tune of the shared decoder alone to the "
                             "grids as the file stores them, on all steps at once, from the training settings the "
                             "file recorded (default, as train: 0.15 x its --iterations for a hybrid series, none "
                             "for APMGSRN or where no settings are recorded; 0 turns it off)")
    add_device_argument(parser)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.set_defaults(func=run, paths=paths)


def paths(args: argparse.Namespace) -> CommandPaths:
    return CommandPaths(reads=[args.model, *args.data], writes=[Output(args.out, "--out", "packed model", model=True)])


def run(args: argparse.Namespace) -> int:
    import apmgsrn
    from apmgsrn.device import resolve_device
    from apmgsrn.inference.evaluate import check_volume_shape

    device = resolve_device(args.device)
    model = apmgsrn.load(args.model, device=device)
    if model.description.bricks is not None:
        raise ApmgsrnError(f"{args.model}: is a brick model; pack a single model file")
    if model.description.series is not None:
        return run_series_pack(args, model)
    if args.decoder_iterations is not None:
        raise ApmgsrnError("--decoder-iterations: fine-tunes the decoder a time series' steps share; "
                           f"{args.model} is a model of one volume")
    if len(args.data) != 1:
        raise ApmgsrnError(f"{len(args.data)} inputs given where one volume is read; name one file")
    volume = open_data(args, args.data[0])
    check_volume_shape(volume.shape, model.description.volume_shape, str(args.data))
    from apmgsrn.planning import pack_config
    from apmgsrn.training.packing import pack_volume_model

    config = pack_config(args, volume.stored_bytes)
    field = model.field
    if model.description.packing is not None and model.description.packing.max_error is not None:
        raise ApmgsrnError(f"{args.model}: already carries an error bound; pack its float32 model instead")
    out = Path(args.out)
    result = pack_volume_model(field, volume, config, model.description.training, device, out,
                        log=(lambda line: None) if args.json else print)
    compression = compression_figures(math.prod(volume.shape), str(volume.dtype), volume.dtype.itemsize,
                                      result.file_bytes)
    if args.json:
        print(json.dumps({"model": str(out), "file_bytes": result.file_bytes, **result.report, **compression}))
        return 0
    print(f"model       {out}")
    for line in packing_lines(result.report, result.file_bytes, compression):
        print(line)
    return 0


def run_series_pack(args: argparse.Namespace, model) -> int:
    """``apmgsrn pack`` of a time-series model: every grid at ``--bits`` (or the largest bit width that fits
    ``--size`` / ``--ratio``), with ``--qat-iterations`` every step of a stepwise series fine-tuned towards its
    packed grids first, then, as ``train`` packs it, the shared decoder fine-tuned to the grids as coded
    (``--decoder-iterations``, by default :func:`~apmgsrn.series.packing.default_series_decoder`; both from
    the training settings the file recorded), the PSNR cost measured on every step of its series (per step in the
    file, which ``info`` shows).

    Imports nothing of :mod:`apmgsrn.cli.series`, which imports this module (the packing options).
    """
    from apmgsrn.series.data import open_series
    from apmgsrn.series.evaluate import evaluate_series
    from apmgsrn.training.packing import fitted_values
    from apmgsrn.series.decoder import fine_tune_decoder
    from apmgsrn.series.packing import (
        SeriesPacking,
        packed_series_field,
        series_overhead,
        series_packing_report,
        write_packed_series,
    )
    from apmgsrn.planning import joint_series_qat, series_packing
    from apmgsrn.series.qat import fine_tune_rounded, stored_train_config

    layout = model.description.series
    series = open_series(args.data, **volume_options(args, allow_series=True))
    if len(series) != len(layout.steps):
        raise ApmgsrnError(f"{args.model}: the model holds {len(layout.steps)} steps but the data names "
                           f"{len(series)}; pass the series it was trained on")
    packing = series_packing(args, series.raw_bytes) or SeriesPacking(qat_iterations=args.qat_iterations or 0)
    field = model.field.cpu().eval()
    log = (lambda line: None) if args.json else print
    packing = replace(packing, decoder_iterations=_decoder_iterations(args, model, field))
    if packing.qat_iterations or packing.decoder_iterations:  # refused before any work: no settings, no steps' grids
        config = stored_train_config(model.description.training, str(args.model),
                                     "a quantisation-aware fine-tune" if packing.qat_iterations
                                     else "the decoder's fine-tune")
        if not field.config.series.per_step_grids:
            raise joint_series_qat() if packing.qat_iterations else ApmgsrnError(JOINT_SERIES_DECODER)
    values = None
    packed = packing.pack(field, series_overhead(field, model.description.source, model.description.training,
                                                 list(layout.steps)))
    options = dict(trained_shape=model.description.volume_shape, progress=not args.json)
    log(f"measuring the float32 model on {len(series)} steps")
    before = evaluate_series(field.step_field, series, **options)

    def tune(packed, iterations: int) -> None:
        log(f"fine-tuning every step towards its packed grids, {iterations} iterations each"
            + (f" (of {packing.qat_iterations}: the packing left too few bytes free for more)"
               if iterations < packing.qat_iterations else ""))
        fine_tune_rounded(field, training_values(), packed, config, iterations, show_progress=not args.json)

    def training_values():  # read once, for whichever fine-tune needs them first
        nonlocal values
        if values is None:
            values = fitted_values(field, series.to_numpy())
        return values

    def decoder(iterations: int) -> int:
        log(f"fine-tuning the shared decoder to the packed grids, {iterations} iterations")
        return fine_tune_decoder(field, training_values(), config, iterations, show_progress=not args.json)[0]

    packed, tuned = packing.fine_tune(field, packed, tune)
    if packing.qat_iterations and not tuned:
        log("no fine-tune towards the packed grids: the packing left no bytes free for it")
    packed, decoder_tuned = packing.tune_decoder(field, packed, decoder)
    if packing.decoder_iterations and not decoder_tuned:
        log("the decoder kept as it was: its fine-tune did not fit the packed grids closer, or its weights "
            "coded past the size")
    log(f"measuring the packed model on {len(series)} steps")
    after = evaluate_series(packed_series_field(field, packed).step_field, series, **options)
    report = series_packing_report(field, packed.bit_width, before, after, packing.target_bytes,
                                   tuned, len(packed.restored), decoder_tuned)
    training = {**model.description.training,
                "steps": [{"psnr": e.psnr, "max_abs_error": e.max_abs_error} for e in after.steps]}
    out = Path(args.out)
    file_bytes = write_packed_series(out, field, packed, model.description.source, training, list(layout.steps),
                                     report)
    compression = compression_figures(math.prod(series.shape) * len(series), str(series.dtype),
                                      series.dtype.itemsize, file_bytes)
    if args.json:
        rows = [{"step": t, "psnr": _finite(e.psnr), "max_abs_error": e.max_abs_error}
                for t, e in enumerate(after.steps)]
        figures = {k: _finite(v) if isinstance(v, float) else v for k, v in {**report, **compression}.items()}
        print(json.dumps({"model": str(out), "file_bytes": file_bytes, **figures, "per_step": rows}))
        return 0
    print(f"model       {out} ({len(series)} steps)")
    for line in packing_lines(report, file_bytes, compression):
        print(line)
    print(f"worst step  {report['worst_step_psnr_cost']:.3f} dB below its float32 PSNR")
    return 0


def _decoder_iterations(args: argparse.Namespace, model, field) -> int:
    """The decoder fine-tune of ``pack`` of a series ``model`` (its loaded ``field``): ``--decoder-iterations``,
    else what ``train`` gives a stepwise series of its kind from the iterations the file recorded (none for a joint
    series or a file that records no settings)."""
    from apmgsrn.series.packing import default_series_decoder

    if args.decoder_iterations is not None:
        if args.decoder_iterations < 0:
            raise ApmgsrnError(f"--decoder-iterations {args.decoder_iterations}: must be 0 or more")
        return args.decoder_iterations
    stored = model.description.training.get("config") if isinstance(model.description.training, dict) else None
    iterations = stored.get("iterations") if isinstance(stored, dict) else None
    if not field.config.series.per_step_grids or not isinstance(iterations, int) or iterations < 1:
        return 0
    return default_series_decoder(field.config.field.model, iterations)


def _finite(value: float) -> float | None:
    """``value``, or None (JSON null) for an exact step's infinite PSNR."""
    return value if math.isfinite(value) else None

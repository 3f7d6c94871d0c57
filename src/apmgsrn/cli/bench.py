"""``apmgsrn bench quality|compress|rd|series``: compare APMGSRN with fVSRN, NGP, SZ3, ZFP, SPERR and TTHRESH on your
volumes, and one model for a whole time series with one model per step on your series."""

from __future__ import annotations

import argparse
from pathlib import Path

from apmgsrn.bench.datasets import parse_data_spec
from apmgsrn.choices import COMPRESSORS, LR_SCHEDULES, MODEL_KINDS, PAPER_MODELS, SIZE_PRESETS, VALUE_TRANSFORMS
from apmgsrn.cli.common import add_data_arguments, add_device_argument
from apmgsrn.cli.paths import CommandPaths, Output

OUT_HELP = ("results folder (default bench-results); its CSV is extended, its tables and chart rewritten, "
            "and its models reused")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="compare models and compressors on your volumes",
        description="Reproducible comparisons: PSNR, real size and time of every model and size preset "
        "(bench quality), networks against SZ3, ZFP, SPERR and TTHRESH (bench compress), and one model for a "
        "time series against "
        "one model per step (bench series).",
    )
    commands = parser.add_subparsers(dest="bench_command", required=True, metavar="BENCHMARK")

    quality = commands.add_parser(
        "quality",
        help="train every model x size x seed on every volume; table in the form of the paper's Table 1",
        description="Train every combination and write OUT/quality.csv (one row per run), OUT/quality.md "
        "(PSNR, real size, training time; best per size in bold) and OUT/quality.png. Runs already in the "
        "CSV are skipped, so the same command extends or resumes a benchmark.",
    )
    quality.add_argument("data", nargs="+", metavar="DATA", help="volume files, as PATH or PATH:VARIABLE")
    quality.add_argument("--models", nargs="+", choices=MODEL_KINDS, default=list(MODEL_KINDS),
                         help="default: all four (the default model against the paper's and its baselines)")
    quality.add_argument("--sizes", nargs="+", choices=SIZE_PRESETS, default=["small", "medium"])
    quality.add_argument("--seeds", type=int, default=1, help="seeds 0..K-1 per combination (mean and spread)")
    _add_budget(quality, LR_SCHEDULES, VALUE_TRANSFORMS)
    quality.add_argument("--out", default="bench-results", help=OUT_HELP)
    add_device_argument(quality)
    quality.set_defaults(func=run_quality_command, paths=quality_paths)

    compress = commands.add_parser(
        "compress",
        help="networks against SZ3, ZFP, SPERR and TTHRESH: rate-distortion, compression time, decompression "
        "and queries",
        description="Compress one volume with SZ3, ZFP and SPERR's point-wise mode at several error bounds "
        "(relative to the value range), with ZFP's fixed-precision mode at several bit-plane counts, SPERR's "
        "fixed-rate mode at several bits per value and TTHRESH at several PSNR targets (or every compressor at "
        "the --ratios asked), and train the networks (or "
        "take --model-files); write OUT/compress_NAME.csv, .md and a rate-distortion chart .png. Query cost: "
        "a compressor decompresses the whole volume before it can answer random points; a network evaluates "
        "them directly.",
    )
    compress.add_argument("data", metavar="DATA", help="volume file, as PATH or PATH:VARIABLE")
    compress.add_argument("--models", nargs="*", choices=MODEL_KINDS, default=list(PAPER_MODELS),
                          help="networks to train (default: the paper's three); none: the compressors alone")
    compress.add_argument("--sizes", nargs="+", choices=SIZE_PRESETS, default=["small"])
    compress.add_argument("--model-files", nargs="+", default=[], metavar="MODEL",
                          help="use these trained models of DATA instead of training --models")
    compress.add_argument("--compressors", nargs="+", choices=COMPRESSORS, default=list(COMPRESSORS))
    compress.add_argument("--bounds", nargs="+", type=float,
                          help="error bounds relative to the value range (default: 1e-1 ... 1e-4)")
    compress.add_argument("--precisions", nargs="+", type=int,
                          help="bit planes of ZFP's fixed-precision mode, zfp-precision (default: 1 ... 8)")
    compress.add_argument("--rates", nargs="+", type=float,
                          help="bits per value of SPERR's fixed-rate mode, sperr (default: 2 ... 0.003)")
    compress.add_argument("--psnrs", nargs="+", type=float,
                          help="target PSNRs (dB) of TTHRESH, tthresh (default: 80 ... 30)")
    compress.add_argument("--ratios", nargs="+", type=float,
                          help="run every compressor at these compression ratios instead, its setting found by "
                               "bisection; a ratio a compressor cannot reach is skipped")
    compress.add_argument("--ratio-tolerance", type=float,
                          help="how near the search for a ratio aims, relative (default 0.01); else the nearest "
                               "setting tried is kept if within 5 %%")
    compress.add_argument("--query-points", type=int, default=2**20, help="random points of the query test")
    _add_budget(compress, None, None)
    compress.add_argument("--out", default="bench-results", help=OUT_HELP)
    add_device_argument(compress)
    compress.set_defaults(func=run_compress_command, paths=compress_paths)

    rd = commands.add_parser(
        "rd",
        help="the rate-distortion page: every compressor and network at the same ratios, crossovers, access cost",
        description="For each volume (default: the shared volumes of 128^3 and more that no compressor made, "
        "and a 128^3 turbulence computed here), every compressor at each ratio against float32 (its setting "
        "found by bisection) and each network kind trained by 'apmgsrn train --ratio'; PSNR, largest error, "
        "the crossover of each network with each compressor, the points/s of a random query and the time of a "
        "64^3 region. Writes the page (--page) and its charts (images/ beside it); OUT keeps bench compress's "
        "CSV of each volume and the models, so the same command measures only what is missing.",
    )
    rd.add_argument("data", nargs="*", metavar="DATA",
                    help="volume files (PATH or PATH:VARIABLE) or registered volume names (default: c60, "
                         "richtmyer-meshkov, turbulence-vorticity-128)")
    rd.add_argument("--ratios", nargs="+", type=float,
                    help="ratios against float32 bytes (default 30 100 300 1000 3000 10000; --quick 100 1000)")
    rd.add_argument("--quick", action="store_true",
                    help="two ratios and 200 iterations unless given: to try the page out")
    rd.add_argument("--models", nargs="+", choices=MODEL_KINDS,
                    help="network kinds, each trained by train --model KIND --ratio R (default: the default "
                         "model and apmgsrn)")
    rd.add_argument("--compressors", nargs="+", choices=COMPRESSORS, default=list(COMPRESSORS))
    _add_budget(rd, None, None)
    rd.set_defaults(iterations=None)
    rd.add_argument("--seed", type=int, default=0, help="the networks' training seed (default 0)")
    rd.add_argument("--query-points", type=int, help="random points of the query test (default 2^18)")
    rd.add_argument("--region", type=int, help="side of the decoded region (default 64)")
    rd.add_argument("--compress-seconds", type=float, metavar="S",
                    help="leave out a compressor on a volume once one compression takes longer than S seconds "
                         "(its ratio search compresses up to 40 times; default: no limit)")
    rd.add_argument("--out", default="bench-results/rate_distortion", help=OUT_HELP.replace(
        "bench-results", "bench-results/rate_distortion"))
    rd.add_argument("--page", help="Markdown page to write (default OUT/rate_distortion.md); charts in images/ "
                                   "beside it")
    add_device_argument(rd)
    rd.set_defaults(func=run_rd_command, paths=rd_paths)

    series = commands.add_parser(
        "series",
        help="one model for a whole time series against one model per step: PSNR per step, file size, time",
        description="Train the series as apmgsrn train does (stepwise, packed within five single-step files), "
        "then an independent model of each measured step with the same budget (after the series, on the same "
        "machine: their median time is one step's); write OUT/series.csv (one row per step and model), "
        "OUT/series.md (the criteria: every measured step at least its own model's PSNR, the file within five "
        "own models, the training within five times one step) and OUT/series.png. What the CSV holds is not "
        "trained again, and an interrupted series resumes.",
    )
    series.add_argument("data", nargs="+", metavar="DATA",
                        help="the series: several files, a quoted glob such as 'run/*.vti', a .pvd, or one file "
                             "with --time all|A:B[:S]")
    add_data_arguments(series)
    series.add_argument("--model", choices=MODEL_KINDS, help="model kind (default: the train command's)")
    series.add_argument("--preset", choices=SIZE_PRESETS, default="small")
    series.add_argument("--steps", type=_step_list, metavar="K,K,...",
                        help="step indices measured against their own models (default: 7 evenly spaced, the "
                             "first and last among them; every step of a shorter series)")
    series.add_argument("--seeds", type=int, default=1,
                        help="train the series and every own model with seeds 0..K-1 and compare their means "
                             "(default 1)")
    _add_budget(series, None, None)
    series.add_argument("--out", default="bench-series", help="results folder (default bench-series); "
                        "its CSV is extended, its report and chart rewritten, and its models reused")
    add_device_argument(series)
    series.set_defaults(func=run_series_command, paths=series_paths)


def _step_list(text: str) -> tuple[int, ...]:
    """``--steps``: comma-separated step indices (argparse type; a bad value is a usage error)."""
    try:
        steps = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: give step indices separated by commas, e.g. 0,10,29") from None
    if any(step < 0 for step in steps):
        raise argparse.ArgumentTypeError(f"{text!r}: step indices start at 0")
    return tuple(dict.fromkeys(steps))


def _add_budget(parser: argparse.ArgumentParser, schedules, transforms) -> None:
    parser.add_argument("--iterations", type=int, default=2000, help="training iterations per run (default 2000)")
    parser.add_argument("--batch-size", type=int, default=32768, help="points per iteration (default 32768)")
    if schedules is not None:
        parser.add_argument("--lr-schedule", choices=schedules,
                            help="one schedule for every model (default: each model's own)")
        parser.add_argument("--voxel-fraction", type=float,
                            help="one share of voxel points for every model, 0..1 (default: each model's own)")
    if transforms is not None:
        parser.add_argument("--transform", choices=transforms, default="none",
                            help="value transform for every volume")
        parser.add_argument("--log-offset", type=float, default=0.0, help="offset added before log10")


def quality_paths(args: argparse.Namespace) -> CommandPaths:
    """The volumes are read; the results folder written."""
    reads = [parse_data_spec(text).path for text in args.data]
    return CommandPaths(reads=reads, writes=[Output(args.out, "--out", "results folder")])


def compress_paths(args: argparse.Namespace) -> CommandPaths:
    """The volume and the given models are read; the results folder written."""
    reads = [parse_data_spec(args.data).path, *args.model_files]
    return CommandPaths(reads=reads, writes=[Output(args.out, "--out", "results folder")])


def rd_paths(args: argparse.Namespace) -> CommandPaths:
    """The volumes are read (a registered one still to be computed is not there yet); the results folder and
    the page written."""
    from apmgsrn.bench.rate_distortion import DEFAULT_VOLUMES, page_path, pending_volume

    reads = [parse_data_spec(text).path for text in (args.data or DEFAULT_VOLUMES) if not pending_volume(text)]
    return CommandPaths(reads=reads, writes=[Output(args.out, "--out", "results folder"),
                                             Output(page_path(args.out, args.page), "--page", "page")])


def series_paths(args: argparse.Namespace) -> CommandPaths:
    """The series' files are read; the results folder written."""
    from apmgsrn.series.data import input_files

    return CommandPaths(reads=input_files(args.data), writes=[Output(args.out, "--out", "results folder")])


def run_quality_command(args: argparse.Namespace) -> int:
    from apmgsrn.bench.quality import QualityPlan, quality_paths, run_quality
    from apmgsrn.device import resolve_device

    plan = QualityPlan(
        datasets=tuple(parse_data_spec(text) for text in args.data),
        models=tuple(dict.fromkeys(args.models)),
        sizes=tuple(dict.fromkeys(args.sizes)),
        seeds=args.seeds,
        iterations=args.iterations,
        batch_size=args.batch_size,
        lr_schedule=args.lr_schedule,
        voxel_fraction=args.voxel_fraction,
        transform=args.transform,
        log_offset=args.log_offset,
    )
    out = Path(args.out)
    run_quality(plan, out, resolve_device(args.device), log=_log)
    return _print_report(quality_paths(out))


def run_compress_command(args: argparse.Namespace) -> int:
    from apmgsrn.bench.compress import CompressPlan, run_compress
    from apmgsrn.device import resolve_device

    plan = CompressPlan(
        dataset=parse_data_spec(args.data),
        models=tuple(dict.fromkeys(args.models)),
        sizes=tuple(dict.fromkeys(args.sizes)),
        model_files=tuple(Path(p) for p in args.model_files),
        compressors=tuple(dict.fromkeys(args.compressors)),
        iterations=args.iterations,
        batch_size=args.batch_size,
        query_points=args.query_points,
        **({"bounds": tuple(args.bounds)} if args.bounds else {}),
        **({"precisions": tuple(args.precisions)} if args.precisions else {}),
        **({"rates": tuple(args.rates)} if args.rates else {}),
        **({"psnrs": tuple(args.psnrs)} if args.psnrs else {}),
        **({"ratios": tuple(args.ratios)} if args.ratios else {}),
        **({"ratio_tolerance": args.ratio_tolerance} if args.ratio_tolerance is not None else {}),
    )
    report = run_compress(plan, Path(args.out), resolve_device(args.device), log=_log)
    print(report.markdown.read_text())
    for reason in report.skipped:
        print(f"note: skipped {reason}")
    print(f"wrote {report.csv}, {report.markdown}" + (f" and {report.chart}" if report.rows else ""))
    return 0


def run_rd_command(args: argparse.Namespace) -> int:
    from apmgsrn.bench.rate_distortion import (
        DEFAULT_VOLUMES, QUICK_ITERATIONS, QUICK_RATIOS, RateDistortionPlan, page_path, resolve_volume,
        run_rate_distortion)
    from apmgsrn.device import resolve_device

    # The plan's defaults, --quick's where asked, then what the command line gives.
    options = {"ratios": QUICK_RATIOS, "iterations": QUICK_ITERATIONS} if args.quick else {}
    options.update({name: getattr(args, name) for name in ("iterations", "query_points", "region", "compress_seconds")
                    if getattr(args, name) is not None})
    options.update({name: tuple(dict.fromkeys(getattr(args, name))) for name in ("ratios", "models")
                    if getattr(args, name)})
    plan = RateDistortionPlan(datasets=tuple(resolve_volume(text) for text in (args.data or DEFAULT_VOLUMES)),
                              compressors=tuple(dict.fromkeys(args.compressors)), batch_size=args.batch_size,
                              seed=args.seed, **options)
    report = run_rate_distortion(plan, Path(args.out), page_path(args.out, args.page), resolve_device(args.device),
                                 log=_log)
    print(f"wrote {report.page}" + (f" and {', '.join(str(c) for c in report.charts)}" if report.charts else ""))
    return 0


def run_series_command(args: argparse.Namespace) -> int:
    from apmgsrn.bench.series import SeriesPlan, run_series_bench, series_bench_paths
    from apmgsrn.cli.common import volume_options
    from apmgsrn.device import resolve_device

    plan = SeriesPlan(data=tuple(args.data), **volume_options(args, allow_series=True), model=args.model,
                      preset=args.preset, iterations=args.iterations, batch_size=args.batch_size, seeds=args.seeds,
                      steps=args.steps)
    out = Path(args.out)
    run_series_bench(plan, out, resolve_device(args.device), log=_log)
    return _print_report(series_bench_paths(out))


def _log(line: str) -> None:
    print(line, flush=True)


def _print_report(paths: dict[str, Path]) -> int:
    """Print a benchmark's Markdown report and where its files went; the command's exit code."""
    print(paths["markdown"].read_text())
    print(f"wrote {paths['csv']}, {paths['markdown']} and {paths['chart']}")
    return 0

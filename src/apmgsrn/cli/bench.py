"""``apmgsrn bench quality|compress``: compare APMGSRN with fVSRN, NGP, SZ3 and ZFP on your volumes."""

from __future__ import annotations

import argparse
from pathlib import Path

from apmgsrn.bench.datasets import parse_data_spec
from apmgsrn.choices import COMPRESSORS, LR_SCHEDULES, MODEL_KINDS, PAPER_MODELS, SIZE_PRESETS, VALUE_TRANSFORMS
from apmgsrn.cli.common import add_device_argument
from apmgsrn.cli.paths import CommandPaths, Output

OUT_HELP = ("results folder (default bench-results); its CSV is extended, its tables and chart rewritten, "
            "and its models reused")


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "bench",
        help="compare models and compressors on your volumes",
        description="Reproducible comparisons: PSNR, real size and time of every model and size preset "
        "(bench quality), and networks against SZ3 and ZFP (bench compress).",
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
        help="networks against SZ3 and ZFP: rate-distortion, compression time, decompression and queries",
        description="Compress one volume with SZ3 and ZFP at several error bounds (relative to the value "
        "range), and with ZFP's fixed-precision mode at several bit-plane counts, and train the networks (or "
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
    compress.add_argument("--query-points", type=int, default=2**20, help="random points of the query test")
    _add_budget(compress, None, None)
    compress.add_argument("--out", default="bench-results", help=OUT_HELP)
    add_device_argument(compress)
    compress.set_defaults(func=run_compress_command, paths=compress_paths)


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
    run_quality(plan, out, resolve_device(args.device), log=lambda line: print(line, flush=True))
    paths = quality_paths(out)
    print(paths["markdown"].read_text())
    print(f"wrote {paths['csv']}, {paths['markdown']} and {paths['chart']}")
    return 0


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
    )
    report = run_compress(plan, Path(args.out), resolve_device(args.device),
                          log=lambda line: print(line, flush=True))
    print(report.markdown.read_text())
    for reason in report.skipped:
        print(f"note: skipped {reason}")
    print(f"wrote {report.csv}, {report.markdown}" + (f" and {report.chart}" if report.rows else ""))
    return 0

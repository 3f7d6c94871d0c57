"""``apmgsrn train --bricks I,J,K``: the domain-decomposition options of ``train`` and their run (wiring only)."""

from __future__ import annotations

import argparse
import json
import math
import os
from pathlib import Path

from apmgsrn.cli.common import compression_figures, compression_text, format_bytes, open_data, parse_triple
from apmgsrn.cli.fit_options import build_configs
from apmgsrn.errors import ApmgsrnError


def add_brick_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of a brick (domain decomposition) run; every other ``train`` option applies per brick."""
    group = parser.add_argument_group(
        "domain decomposition (one model per brick; --out is then a folder)",
    )
    group.add_argument("--bricks", metavar="I,J,K",
                       help="train one model per brick of an I x J x K grid over x, y, z (e.g. 2,2,2 or 4)")
    group.add_argument("--ghost-cells", type=int, default=1, metavar="G",
                       help="voxels each brick overlaps its neighbours beyond the shared border (default 1)")
    group.add_argument("--workers", type=int, metavar="N",
                       help="local workers (default: one per visible GPU, else one per CPU core, at most 4)")
    group.add_argument("--scheduler", metavar="ADDRESS|FILE",
                       help="join a running Dask cluster: tcp://host:port or its scheduler JSON file")
    group.add_argument("--retries", type=int, default=2, metavar="N",
                       help="extra attempts of a brick whose job raised (default 2)")
    group.add_argument("--blend", action="store_true",
                       help="at inference, blend neighbouring bricks across their shared ghost region (no seams)")
    group.add_argument("--group-steps", type=int, metavar="S",
                       help="a time series: one job per (brick, group of S consecutive steps) (default: every step)")


def run_bricks(args: argparse.Namespace) -> int:
    """Train (or finish) a brick model; the same command after a crash trains only missing bricks."""
    from apmgsrn.decomposition.coordinator import BrickProgress, train_bricks
    from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue
    from apmgsrn.decomposition.planner import DecompositionConfig
    from apmgsrn.device import resolve_device

    counts = parse_triple(args.bricks, "--bricks")
    decomposition = DecompositionConfig(counts, args.ghost_cells, args.blend)
    executor = ExecutorConfig(scheduler=args.scheduler, workers=args.workers, retries=args.retries)
    # The coordinator only sizes the budget; workers resolve --device themselves (auto: their own GPU).
    # How a brick trains beyond these options (the plateau schedule's early stop) is decided by
    # decomposition.brick_training.brick_policy.
    field_config, train_config = build_configs(args, resolve_device(args.device))
    # Workers reopen the file by path, possibly from another folder or machine.
    volume = open_data(args, os.path.abspath(args.data))
    out = Path(args.out)
    with open_job_queue(executor) as queue:
        summary = train_bricks(
            volume, decomposition, field_config, train_config, out, queue,
            transform=args.transform, log_offset=args.log_offset, device=args.device,
            progress=BrickProgress(),
        )
    trained = [r for r in summary.trained if r.ok]
    compression = compression_figures(math.prod(volume.shape), str(volume.dtype), volume.dtype.itemsize,
                                      summary.model_bytes)
    result = {
        "model": str(out),
        "bricks": list(summary.plan.counts),
        "complete": summary.complete,
        "trained": len(trained),
        "reused": len(summary.reused),
        "failed": summary.failed,
        "model_bytes": summary.model_bytes,
        **compression,
        "seconds": summary.seconds,
        "coordinator_peak_rss_bytes": summary.coordinator_peak_rss_bytes,
        "worker_peak_rss_bytes": summary.worker_peak_rss_bytes,
        "brick_psnr": {r.name: (r.psnr if math.isfinite(r.psnr) else None) for r in trained},
    }
    if args.json:
        print(json.dumps(result))
    else:
        i, j, k = summary.plan.counts
        print(f"model       {out}/ ({i}x{j}x{k} bricks, {format_bytes(summary.model_bytes)})")
        print(f"data        {volume.describe()} ({format_bytes(volume.stored_bytes)} as stored)")
        if summary.model_bytes:
            print(f"compression {compression_text(compression)}")
        print(f"time        {summary.seconds:.1f} s for {len(trained)} brick(s); {len(summary.reused)} done earlier")
        worker_peak = max(summary.worker_peak_rss_bytes.values(), default=0)
        print(f"peak memory coordinator {format_bytes(summary.coordinator_peak_rss_bytes)}, "
              f"workers up to {format_bytes(worker_peak)}")
        if summary.complete:
            print(f"evaluate    apmgsrn eval {out} {args.data}")
    if summary.failed:
        names = ", ".join(sorted(summary.failed))
        raise ApmgsrnError(
            f"{out}: {len(summary.failed)} brick(s) failed: {names} (reasons above); the others are saved: "
            "run the same command again to retry the failed ones"
        )
    return 0


def run_series_bricks(args: argparse.Namespace) -> int:
    """Train (or finish) a time-series brick model: one job per (brick, group of ``--group-steps`` steps), each
    stepwise from the group's own start step (packed) unless ``--series-training joint``."""
    from apmgsrn.cli.series import build_series_config, open_series_data, series_training
    from apmgsrn.decomposition.coordinator import BrickProgress
    from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue
    from apmgsrn.decomposition.planner import DecompositionConfig
    from apmgsrn.decomposition.series_bricks import step_groups, train_series_bricks
    from apmgsrn.device import resolve_device

    counts = parse_triple(args.bricks, "--bricks")
    if args.group_steps is not None and args.group_steps < 1:
        raise ApmgsrnError(f"--group-steps {args.group_steps}: must be 1 or more")
    series = open_series_data(args).absolute()  # workers reopen the steps by path
    groups = step_groups(len(series), args.group_steps)
    # Each group trains with the budget of its own number of steps.
    field_config, train_config = build_configs(args, resolve_device(args.device), steps=len(groups[0]))
    config = build_series_config(args, field_config, len(series))
    stepwise, packing = series_training(args, config, series.raw_bytes, series.shape, train_config.iterations)
    out = Path(args.out)
    executor = ExecutorConfig(scheduler=args.scheduler, workers=args.workers, retries=args.retries)
    with open_job_queue(executor) as queue:
        summary = train_series_bricks(
            series, DecompositionConfig(counts, args.ghost_cells, args.blend), config, train_config, out, queue,
            group_steps=args.group_steps, transform=args.transform, log_offset=args.log_offset, device=args.device,
            progress=BrickProgress(), stepwise=stepwise, packing=packing,
        )
    result = {"model": str(out), "bricks": list(counts), "steps": len(series), "groups": len(groups),
              "complete": summary.complete, "failed": summary.failed, "model_bytes": summary.model_bytes,
              "raw_bytes": series.raw_bytes, "seconds": summary.seconds}
    if args.json:
        print(json.dumps(result))
    else:
        print(f"model       {out}/ ({len(series)} steps in {len(groups)} group(s), {counts[0]}x{counts[1]}x{counts[2]} "
              f"bricks, {format_bytes(summary.model_bytes)})")
        print(f"data        {series.describe()} ({format_bytes(series.raw_bytes)} as float32)")
        print(f"time        {summary.seconds:.1f} s")
    if summary.failed:
        names = ", ".join(sorted(summary.failed))
        raise ApmgsrnError(f"{out}: {len(summary.failed)} job(s) failed: {names} (reasons above); the others are "
                           "saved: run the same command again to retry the failed ones")
    return 0

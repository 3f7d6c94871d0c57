"""``apmgsrn train --bricks I,J,K``: the run of a brick plan (wiring only; the options are in :mod:`apmgsrn.options`)."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

from apmgsrn.cli.common import compression_figures, compression_text, format_bytes
from apmgsrn.errors import ApmgsrnError


def run_bricks(args: argparse.Namespace, plan) -> int:
    """Train (or finish) a brick model as the plan (:mod:`apmgsrn.planning`) says; the same command after a crash
    trains only missing bricks."""
    from apmgsrn.decomposition.coordinator import BrickProgress, train_bricks
    from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue

    decomposition = plan.bricks
    counts = decomposition.bricks
    executor = ExecutorConfig(scheduler=plan.scheduler, workers=plan.workers, retries=plan.retries)
    # The plan only sizes the budget; workers resolve --device themselves (auto: their own GPU). How a brick
    # trains beyond these options (the plateau schedule's early stop) is decided by
    # decomposition.brick_training.brick_policy.
    volume = plan.source  # opened by its absolute path: workers reopen it, possibly from another folder
    out = Path(args.out)
    with open_job_queue(executor) as queue:
        summary = train_bricks(
            volume, decomposition, plan.field, plan.training, out, queue,
            transform=plan.transform, log_offset=plan.log_offset, device=args.device,
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


def run_series_bricks(args: argparse.Namespace, plan) -> int:
    """Train (or finish) a time-series brick model: one job per (brick, group of ``--group-steps`` steps), each
    stepwise from the group's own start step (packed) unless ``--series-training joint``."""
    from apmgsrn.decomposition.coordinator import BrickProgress
    from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue
    from apmgsrn.series.bricks import step_groups, train_series_bricks

    counts = plan.bricks.bricks
    series = plan.source  # opened by absolute paths: workers reopen the steps
    groups = step_groups(len(series), plan.group_steps)
    out = Path(args.out)
    executor = ExecutorConfig(scheduler=plan.scheduler, workers=plan.workers, retries=plan.retries)
    with open_job_queue(executor) as queue:
        summary = train_series_bricks(
            series, plan.bricks, plan.field, plan.training, out, queue,
            group_steps=plan.group_steps, transform=plan.transform, log_offset=plan.log_offset, device=args.device,
            progress=BrickProgress(), stepwise=plan.stepwise, packing=plan.packing,
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

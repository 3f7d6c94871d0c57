"""Voxel points drawn where the model is wrong (``--error-sampling``) against uniformly drawn ones.

For every volume, share and seed asked, trains one model under the CPU protocol (2,000 iterations x 32,768
points, the model kind's own training defaults, small preset, one thread) through the ``train`` command's code,
and appends its PSNR and largest error over every voxel and its training time to ``--csv`` (a row already
there is not trained again: the run resumes). ``report`` writes the table, one row per volume with the gain of
each share over share 0 at the same seed, to ``--out``.

Usage::

    python benchmarks/bench_error_sampling.py run --csv benchmarks/results/error_sampling.csv --shares 0 1 \\
        --seeds 0 1 ../shared/data/hcci_oh_187.nc:oh ../shared/data/neghip_64x64x64_uint8.raw
    python benchmarks/bench_error_sampling.py report --csv benchmarks/results/error_sampling.csv \\
        --out docs/results_error_sampling.md
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

import torch

from apmgsrn.atomic import atomic_write_text
from apmgsrn.bench.datasets import open_spec, parse_data_spec
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.training.fit import fit_volume
from apmgsrn.training.trainer import TrainConfig

FIELDS = ["volume", "kind", "error_sampling", "seed", "psnr", "max_abs_error", "seconds", "iterations",
          "batch_size", "threads", "load_average", "cpu"]


def _rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _append(path: Path, row: dict) -> None:
    new = not path.exists()
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        if new:
            writer.writeheader()
        writer.writerow(row)


def run(args: argparse.Namespace) -> None:
    torch.set_num_threads(args.threads)
    for spec_text in args.volumes:
        spec = parse_data_spec(spec_text)
        name = spec.path.name + (f":{spec.variable}" if spec.variable else "")
        for seed in args.seeds:
            for share in args.shares:
                done = {(r["volume"], r["kind"], float(r["error_sampling"]), int(r["seed"])) for r in _rows(args.csv)}
                if (name, args.kind, share, seed) in done:
                    continue
                config = TrainConfig(iterations=args.iterations, batch_size=args.batch_size, lr=0.01, seed=seed,
                                     **{**training_defaults(args.kind), "error_sampling": share})
                with tempfile.TemporaryDirectory() as tmp:
                    result = fit_volume(open_spec(spec), preset_config(args.kind, "small"), config,
                                        Path(tmp) / "m.apmgsrn", torch.device("cpu"), progress=False)
                row = {"volume": name, "kind": args.kind, "error_sampling": f"{share:g}", "seed": seed,
                       "psnr": f"{result.psnr:.4f}", "max_abs_error": f"{result.max_abs_error:.6g}",
                       "seconds": f"{result.seconds:.2f}", "iterations": result.iterations,
                       "batch_size": args.batch_size, "threads": torch.get_num_threads(),
                       "load_average": f"{os.getloadavg()[0]:.2f}", "cpu": platform.processor() or platform.machine()}
                _append(args.csv, row)
                print(" ".join(f"{k}={v}" for k, v in row.items() if k != "cpu"), flush=True)


def report(args: argparse.Namespace) -> None:
    rows = _rows(args.csv)
    by = {(r["volume"], r["kind"], float(r["error_sampling"]), int(r["seed"])): r for r in rows}
    volumes = list(dict.fromkeys((r["volume"], r["kind"]) for r in rows))
    shares = sorted({float(r["error_sampling"]) for r in rows} - {0.0})
    head = (["volume", "kind", "seeds", "PSNR, uniform voxels"] + [f"error sampling {s:g}: PSNR (gain)" for s in shares]
            + ["max error, uniform"] + [f"max error, {s:g}" for s in shares]
            + ["time, uniform"] + [f"time, {s:g}" for s in shares])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    gains = {s: [] for s in shares}
    for volume, kind in volumes:
        seeds = sorted(seed for (v, k, s, seed) in by if (v, k, s) == (volume, kind, 0.0)
                       and all((volume, kind, share, seed) in by for share in shares))
        if not seeds:
            continue

        def mean(share, field):
            return statistics.mean(float(by[(volume, kind, share, seed)][field]) for seed in seeds)

        cells = [volume, kind, ",".join(map(str, seeds)), f"{mean(0.0, 'psnr'):.2f}"]
        for share in shares:
            gain = [float(by[(volume, kind, share, s)]["psnr"]) - float(by[(volume, kind, 0.0, s)]["psnr"])
                    for s in seeds]
            gains[share].append(statistics.mean(gain))
            spread = f", {min(gain):+.2f}..{max(gain):+.2f}" if len(gain) > 1 else ""
            cells.append(f"{mean(share, 'psnr'):.2f} ({statistics.mean(gain):+.2f}{spread})")
        cells += [f"{mean(0.0, 'max_abs_error'):.4g}"] + [f"{mean(s, 'max_abs_error'):.4g}" for s in shares]
        cells += [f"{mean(0.0, 'seconds'):.0f} s"] + [f"{mean(s, 'seconds'):.0f} s" for s in shares]
        lines.append("| " + " | ".join(cells) + " |")
    summary = "; ".join(f"share {s:g}: mean gain {statistics.mean(g):+.2f} dB over {len(g)} volumes, "
                        f"{min(g):+.2f} to {max(g):+.2f}" for s, g in gains.items() if g)
    command = "python benchmarks/bench_error_sampling.py " + " ".join(sys.argv[1:])
    text = ("# Voxel points drawn where the model is wrong\n\n"
            "`--error-sampling S`: a share S of each batch's voxel points drawn in proportion to the model's absolute "
            "error at the voxels (measured 20 times in a run), against all of them drawn uniformly (S = 0). CPU "
            "protocol: 2,000 iterations x 32,768 points, small preset, the model kind's training defaults, one "
            "thread; PSNR and max error over every voxel (data units); gain against S = 0 at the same seed, mean "
            f"over the seeds (and its range). Times are the training loop's, with other runs on the machine.\n\n"
            f"Summary: {summary}.\n\n" + "\n".join(lines) + f"\n\nCommand: `{command}`; rows: `{args.csv}`.\n")
    if args.out:
        atomic_write_text(args.out, text)
    print(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    runner = sub.add_parser("run", help="train and append rows")
    runner.add_argument("volumes", nargs="+", help="PATH or PATH:VARIABLE")
    runner.add_argument("--csv", type=Path, required=True)
    runner.add_argument("--kind", default="hybrid")
    runner.add_argument("--shares", type=float, nargs="+", default=[0.0, 1.0])
    runner.add_argument("--seeds", type=int, nargs="+", default=[0])
    runner.add_argument("--iterations", type=int, default=2000)
    runner.add_argument("--batch-size", type=int, default=32768)
    runner.add_argument("--threads", type=int, default=1)
    reporter = sub.add_parser("report", help="the table")
    reporter.add_argument("--csv", type=Path, required=True)
    reporter.add_argument("--out", type=Path)
    args = parser.parse_args()
    run(args) if args.command == "run" else report(args)


if __name__ == "__main__":
    main()

"""Warm-started steps for a time series: the measurement that chose stepwise training (issue 16), kept to
reproduce docs/time_series.md "How stepwise training was found"; the product path is
``apmgsrn.series.steps`` (``apmgsrn train`` on a series, ``bench_time_series.py series``).

    python benchmarks/bench_series_warm_start.py --csv benchmarks/results/series_warm_start.csv
    python benchmarks/bench_series_warm_start.py --start first --csv ...   # start from step 0 instead
    python benchmarks/bench_series_warm_start.py --store-bits 8,10 --csv ... # and what the steps cost stored

What it trains, on the 30 steps of ``viscous_fingers_run01`` (1 thread, batch 32,768, voxel fraction 0.5,
one anchored grid, seed ``--seed``, 0 by default):

1. A single-step small model trained 2,000 iterations on the start step alone (the last step by default:
   the fingers have spread furthest there, so its grid placement covers what the earlier steps need).
2. Then one step after another, moving away from the start, each step's feature grids start from its
   neighbour's and are fine-tuned ``--step-iterations`` iterations on that step alone (lr ``--lr``,
   cosine); the grid placement and the decoder stay the start model's, shared by every step.

Every step's PSNR (every voxel) and the seconds are written to the CSV. With ``--store-bits``, each step's
grids are quantised with one step size per grid and channel, shared by every time step (the packed format's
:func:`~apmgsrn.io.quantization.steps_for_bits` and ``quantize``), the integers coded with its LZMA layout
(:func:`~apmgsrn.io.codec.encode_levels`) after a difference along time, and the PSNR of the
quantised steps measured: what a packed series file of these grids would cost.
"""

from __future__ import annotations

import argparse
import csv
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.series.data import open_series
from apmgsrn.inference.evaluate import evaluate
from apmgsrn.io import codec
from apmgsrn.io.quantization import quantize, steps_for_bits
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.training.fit import prepare_values, train_prepared
from apmgsrn.training.trainer import TrainConfig, Trainer

ROOT = Path(__file__).resolve().parents[1]
SERIES = ROOT.parent / "shared" / "data" / "viscous_fingers_run01"
FIELDS = ["step", "psnr", "seconds", "what"]


def start_model(args, prepared) -> tuple[NeuralField, float]:
    """A single-step model trained 2,000 iterations on the start step alone (the ``train`` pipeline's
    :func:`~apmgsrn.training.fit.train_prepared`, with the whole series' value scaling), and its seconds."""
    start = time.perf_counter()
    config = TrainConfig(iterations=2000, voxel_fraction=0.5, anchored_grids=1, seed=args.seed)
    step = replace(prepared, values=prepared.values[args.start_step])
    trained = train_prepared(step, preset_config("apmgsrn", "small"), config, tuple(step.values.shape), None, {}, [])
    return trained.field, time.perf_counter() - start


def stored_cost(field: NeuralField, grids: np.ndarray, data: np.ndarray, bits: int) -> tuple[int, list[float]]:
    """Bytes of every step's grids ``[T, M, C, D, H, W]`` quantised to ``bits`` and coded, and each step's
    PSNR with the quantised grids."""
    by_grid = np.moveaxis(grids, 0, 2)  # [M, C, T, D, H, W]: one quantisation group per grid and channel
    group = by_grid[0, 0].size
    quantized = quantize(by_grid, steps_for_bits(by_grid, group, bits), group)
    levels = np.moveaxis(quantized.levels.reshape(by_grid.shape), 2, 0)  # [T, M, C, D, H, W]
    residuals = np.diff(levels, axis=0, prepend=0)  # what changes from one step to the next
    coded, _ = codec.encode_levels(residuals, residuals.shape, "none")
    restored = np.moveaxis(quantized.dequantize().numpy(), 2, 0)  # [T, M, C, D, H, W]
    psnrs = []
    for t in range(len(grids)):
        with torch.no_grad():
            field.encoder.grids.copy_(torch.from_numpy(restored[t]))
        psnrs.append(evaluate(field.eval(), data[t]).psnr)
    return len(coded) + quantized.steps.nbytes, psnrs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, default=SERIES)
    parser.add_argument("--start", choices=("first", "last"), default="last",
                        help="the step whose own model every other step starts from")
    parser.add_argument("--step-iterations", type=int, default=200)
    parser.add_argument("--lr", type=float, default=0.003)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--store-bits", default="", help="bit widths to cost the stored steps at, e.g. 8,10")
    parser.add_argument("--csv", type=Path, required=True)
    args = parser.parse_args()
    torch.set_num_threads(1)
    files = sorted(args.data.glob("*.vti"))
    data = open_series([str(f) for f in files]).to_numpy()  # [T, D, H, W]
    prepared = prepare_values(data, "none", 0.0, str(args.data), torch.device("cpu"))
    args.start_step = 0 if args.start == "first" else len(data) - 1
    field, seconds = start_model(args, prepared)
    rows = [{"step": args.start_step, "psnr": f"{evaluate(field.eval(), data[args.start_step]).psnr:.4f}",
             "seconds": f"{seconds:.2f}", "what": "start: 2000 iterations"}]
    print(rows[-1], flush=True)
    for prm in [*field.encoder.placement_parameters(), *field.decoder.parameters()]:
        prm.requires_grad_(False)
    order = sorted(range(len(data)), key=lambda t: abs(t - args.start_step))[1:]  # away from the start
    grids = {args.start_step: field.encoder.grids.detach().numpy().copy()}
    for t in order:
        start = time.perf_counter()
        config = TrainConfig(iterations=args.step_iterations, lr=args.lr, voxel_fraction=0.5,
                             density_start=args.step_iterations + 1, anchored_grids=1, seed=args.seed)
        Trainer(field.train(), prepared.values[t], config, None, {}, []).run()
        seconds = time.perf_counter() - start
        grids[t] = field.encoder.grids.detach().numpy().copy()
        rows.append({"step": t, "psnr": f"{evaluate(field.eval(), data[t]).psnr:.4f}", "seconds": f"{seconds:.2f}",
                     "what": f"step_iterations={args.step_iterations} lr={args.lr:g}"})
        print(rows[-1], flush=True)
    for bits in [int(b) for b in args.store_bits.split(",") if b]:
        size, psnrs = stored_cost(field, np.stack([grids[t] for t in range(len(data))]), data, bits)
        rows += [{"step": t, "psnr": f"{p:.4f}", "seconds": "", "what": f"stored bits={bits} grid_bytes={size}"}
                 for t, p in enumerate(psnrs)]
        print(f"bits {bits}: {size:,} bytes of grids, PSNR {min(psnrs):.2f} .. {max(psnrs):.2f}", flush=True)
    args.csv.parent.mkdir(parents=True, exist_ok=True)
    with args.csv.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, FIELDS)
        writer.writeheader()
        writer.writerows(rows)


if __name__ == "__main__":
    main()

"""Milliseconds per training step (forward, backward, Adam; no density step) of every model and size.

    python benchmarks/bench_baseline_steps.py [--threads 2] [--batch-size 32768] [--sizes small medium] \
        [--shape 187,187,187]

``--shape`` is the (D, H, W) of the volume the models are built for: only the hybrid model's layout depends
on it (its domain levels follow the voxel lattice).
"""

from __future__ import annotations

import argparse
import time

import torch

from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import ENCODERS, preset_config


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--threads", type=int, default=torch.get_num_threads())
    parser.add_argument("--batch-size", type=int, default=32768)
    parser.add_argument("--sizes", nargs="+", default=["small", "medium"])
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--shape", default="187,187,187", help="D,H,W of the volume (default: HCCI's)")
    args = parser.parse_args()
    shape = tuple(int(n) for n in args.shape.split(","))
    torch.set_num_threads(args.threads)
    points = torch.rand(args.batch_size, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    for size in args.sizes:
        for model in ENCODERS:
            field = NeuralField(preset_config(model, size), volume_shape=shape)
            optimizer = torch.optim.Adam(field.parameters(), lr=0.01)
            times = []
            for step in range(args.steps + 1):  # the first step warms up
                start = time.perf_counter()
                loss = field.normalized(points).square().mean()
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                if step:
                    times.append(time.perf_counter() - start)
            times.sort()
            print(f"{model:8s} {size:7s} median {1000 * times[len(times) // 2]:7.1f} ms/step "
                  f"({args.threads} threads, {args.batch_size} points)", flush=True)


if __name__ == "__main__":
    main()

"""Milliseconds per iteration of a series step's fine-tune with the updates after its gradients made by
PyTorch, and by the CPU kernels of :mod:`apmgsrn.ops.optimizer_cpu` and the guide's table of voxel positions.

A step's fine-tune (the hybrid's small preset, decoder frozen, level table and grids trained at the steps' batch,
pulled towards where it started, its voxel points drawn where it is wrong) runs one fused pass per iteration
(:mod:`apmgsrn.ops.field_train_cpu`); around it come the draw of the batch, Adam's step and the pull. This times
whole iterations of ``Trainer.run`` both ways, in alternating rounds (median of the rounds) so that load from
other processes hits both alike, and checks that both end with the same parameters bit for bit.

    python benchmarks/bench_step_updates.py --threads 1 2 --rounds 5

It prints a markdown table, and with ``--out`` writes it there (docs/benchmarks_step_updates.md).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from dataclasses import replace
from pathlib import Path

import torch

from apmgsrn.data import open_volume
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.series import steps as series_steps
from apmgsrn.training import points, trainer
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.optimizer import CpuAdam, pull_towards, pull_towards_reference
from apmgsrn.recipes import HYBRID
from apmgsrn.series.steps import PullTowardsStart, StepwiseConfig
from apmgsrn.training.trainer import TrainConfig, Trainer

ROOT = Path(__file__).resolve().parents[1]
STEP = ROOT.parent / "shared" / "data" / "viscous_fingers_run01" / "045_density_045_064_2.0.vti"
GUIDE_POINTS = points.ErrorGuide.voxel_points


def use_kernels(on: bool) -> None:
    """The updates by the kernels (``on``) or as PyTorch made them before."""
    trainer.CpuAdam = CpuAdam if on else torch.optim.Adam
    series_steps.pull_towards = pull_towards if on else pull_towards_reference
    points.ErrorGuide.voxel_points = GUIDE_POINTS if on else (
        lambda guide, index: points.voxel_points(index, guide.volume.shape))


def fine_tune(values: torch.Tensor, shape, config: TrainConfig) -> tuple[float, NeuralField]:
    """Seconds per iteration of one step's fine-tune from a fresh small hybrid, and the field it ends with."""
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=shape, generator=torch.Generator().manual_seed(0))
    field.requires_grad_(False)
    features = [field.encoder.level_table, field.encoder.grids]
    for parameter in features:
        parameter.requires_grad_(True)
    run = Trainer(field, values, config, None, {}, [PullTowardsStart(features, 0.01)], warm=True)
    began = time.perf_counter()
    run.run()
    return (time.perf_counter() - began) / config.iterations, field


def part_times(field: NeuralField, shape, calls: int) -> dict[str, tuple[float, float]]:
    """Milliseconds per call of each update both ways (PyTorch's, the kernel's): Adam's step and the pull on the
    step's trained tensors, and the positions of a batch's guided voxel points."""
    features = [field.encoder.level_table.detach(), field.encoder.grids.detach()]

    def adam(kind) -> float:
        params = [p.clone().requires_grad_(True) for p in features]
        optimizer = kind(params, lr=0.01, betas=(0.9, 0.99))
        for p in params:
            p.grad = torch.randn(p.shape, generator=torch.Generator().manual_seed(0)) * 1e-3
        return timed(optimizer.step, calls)

    def pull(function) -> float:
        params = [p.clone() for p in features]
        starts = [p + 1e-3 for p in params]
        return timed(lambda: [function(p, s, 1e-4) for p, s in zip(params, starts)], calls)

    guide = points.ErrorGuide(torch.zeros(shape))
    guide.measure(lambda xyz: torch.zeros(len(xyz)), torch.Generator())
    index = torch.randint(0, math.prod(shape), (9216,), generator=torch.Generator().manual_seed(0))
    return {"Adam's step": (adam(torch.optim.Adam), adam(CpuAdam)),
            "pull towards the start": (pull(pull_towards_reference), pull(pull_towards)),
            "guided voxel positions": (timed(lambda: points.voxel_points(index, shape), calls),
                                       timed(lambda: GUIDE_POINTS(guide, index), calls))}


def timed(call, calls: int) -> float:
    """Milliseconds per call of ``call`` (after a few untimed ones)."""
    for _ in range(5):
        call()
    began = time.perf_counter()
    for _ in range(calls):
        call()
    return (time.perf_counter() - began) / calls * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volume", type=Path, default=STEP)
    parser.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    volume = open_volume(args.volume)
    values = prepare_values(volume.to_numpy(), "none", 0.0, str(args.volume), torch.device("cpu")).values
    start = TrainConfig(iterations=2000, batch_size=32768, seed=0, **training_defaults("hybrid"))
    step = StepwiseConfig().step_config(start, batch_share=HYBRID.step_batch_share,
                                        point_share=HYBRID.step_point_share)
    step = replace(step, iterations=args.iterations, density_start=args.iterations + 1)
    lines = [f"The updates alone (median of {args.rounds} rounds of 500 calls; 9,216 guided voxel points: the "
             "steps' batch times their voxel share)", "",
             "| threads | update | PyTorch ms | kernel ms |", "|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for threads in args.threads:
        torch.set_num_threads(threads)
        _, field = fine_tune(values, volume.shape, replace(step, iterations=20))
        rounds = [part_times(field, tuple(volume.shape), 500) for _ in range(args.rounds)]
        for name in rounds[0]:
            before, after = (statistics.median(r[name][way] for r in rounds) for way in (0, 1))
            lines.append(f"| {threads} | {name} | {before:.3f} | {after:.3f} |")
            print(lines[-1], flush=True)
    lines += ["", f"Whole iterations of {args.volume.name}'s fine-tune (hybrid small, batch {step.batch_size:,}, "
              f"{args.iterations} iterations, median of {args.rounds} alternating rounds)", "",
              "| threads | PyTorch updates ms/iteration | kernels ms/iteration | saved | same parameters |",
              "|---|---|---|---|---|"]
    print("\n".join(lines[-5:]), flush=True)
    for threads in args.threads:
        torch.set_num_threads(threads)
        times: dict[bool, list[float]] = {False: [], True: []}
        ends: dict[bool, NeuralField] = {}
        for _ in range(args.rounds):
            for on in (False, True):
                use_kernels(on)
                seconds, ends[on] = fine_tune(values, volume.shape, step)
                times[on].append(seconds)
        use_kernels(True)
        same = all(torch.equal(a, b) for a, b in zip(ends[False].state_dict().values(),
                                                     ends[True].state_dict().values()))
        before, after = (statistics.median(times[on]) * 1000 for on in (False, True))
        line = f"| {threads} | {before:.2f} | {after:.2f} | {100 * (1 - after / before):.1f} % | {same} |"
        lines.append(line)
        print(line, flush=True)
    if args.out:
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        command = " ".join(["python", "benchmarks/bench_step_updates.py", *sys.argv[1:]])
        text = (f"# A series step's updates on the CPU\n\nMachine: CPU {platform.machine()}, torch {torch.__version__}, "
                f"{time.strftime('%Y-%m-%d')}, load average {load} at the end. Command: `{command}`. Both ways "
                "end with the same parameters bit for bit (last column); the kernels are "
                "`src/apmgsrn/ops/optimizer_cpu.py` and the error guide's table of voxel positions.\n\n"
                + "\n".join(lines) + "\n")
        args.out.write_text(text)


if __name__ == "__main__":
    main()

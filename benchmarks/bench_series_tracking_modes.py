"""How a step's fine-tune can follow structures that moved: the ways measured before choosing one.

    python benchmarks/bench_series_tracking_modes.py --data DIR --mode frozen --steps 3
    python benchmarks/bench_series_tracking_modes.py --data DIR --mode joint --steps 3

``DIR`` holds one volume file per step (``bench_time_series.py moving --out DIR``). As ``apmgsrn train`` does
on a series, a small model of the start step the data choose (2,000 iterations x 32,768 points, half of each
batch on voxels, one anchored grid, seed 0; cached in ``DIR/start_K.pt``), then the first ``--steps`` other
steps, each fine-tuned from its neighbour with the adaptive budget of
:meth:`~apmgsrn.series.steps.StepwiseConfig.step_config`, the decoder frozen, in one of these ways:

- ``frozen``: the grids only (the placement stays the start model's);
- ``register``: first 200 iterations moving the placement alone by the reconstruction error, then the grids;
- ``joint``: grids and placement together, both moved by the reconstruction error, the whole fine-tune
  (placement learning rate 0.002, cosine like the grids': what ``apmgsrn train`` does for a step that drifts);
- ``subset``: as ``joint``, but the placement's gradient from 4,096 of the batch's points only (cheaper);
- ``quarter``: ``joint`` for the first quarter of the fine-tune, then the grids alone;
- ``density``: the feature-density loss moves the placement from the first iteration (as for one volume).

Each step's PSNR (every voxel, float32) is printed as it is trained; nothing is stored.

``--timing N`` instead times N trainer iterations of a step's fine-tune (small preset, 32,768 points, on the
first step's data), alternating three rounds of: the grids only; the placement following the error through
the fused CPU kernel (what ``apmgsrn train`` runs); the same through the PyTorch reference.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from bench_series_moving_placement import load_series_folder

from apmgsrn.inference.evaluate import evaluate
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.multigrid import multigrid_features_reference
from apmgsrn.training.fit import train_prepared
from apmgsrn.training.points import draw_batch
from apmgsrn.series.steps import (StepwiseConfig, change, change_factor,
                                           choose_start, step_order)
from apmgsrn.recipes import SERIES
from apmgsrn.training.trainer import TrainConfig, Trainer

MODES = ("frozen", "register", "joint", "subset", "quarter", "density")
PLACEMENT_LR = 0.002


def joint_fine_tune(field, values: torch.Tensor, iterations: int, lr: float, subset: int, generator) -> None:
    """Grids and placement moved by the reconstruction error (``lr = 0``: the placement alone), cosine to 1 %."""
    encoder = field.encoder
    groups = [{"params": [encoder.matrices, encoder.translations], "lr": PLACEMENT_LR}]
    if lr > 0:
        groups.append({"params": [encoder.grids], "lr": lr})
    optimizer = torch.optim.Adam(groups, betas=(0.9, 0.99))
    base = [group["lr"] for group in optimizer.param_groups]
    for iteration in range(iterations):
        factor = 0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * iteration / iterations))
        for group, rate in zip(optimizer.param_groups, base):
            group["lr"] = rate * factor
        points, target = draw_batch(values, 32768, SERIES.voxel_fraction, generator)
        if subset:
            loss = (field.normalized(points, detach_placement=True).view(-1) - target).square().mean()
            features = multigrid_features_reference(points[:subset], encoder.matrices, encoder.translations,
                                                    encoder.grids.detach())
            loss = loss + (field.decoder(features).view(-1) - target[:subset]).square().mean()
        else:
            loss = (field.normalized(points).view(-1) - target).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def fine_tune(field, values: torch.Tensor, config: TrainConfig, mode: str, generator) -> None:
    """One step's fine-tune of ``field`` (decoder frozen) in ``mode``."""
    encoder = field.encoder
    placement = (encoder.matrices, encoder.translations)
    for parameter in (*placement, encoder.grids):
        parameter.requires_grad_(mode != "frozen")
    encoder.grids.requires_grad_(True)
    if mode == "frozen":
        Trainer(field.train(), values, config, None, {}, []).run()
    elif mode == "register":
        joint_fine_tune(field, values, 200, 0.0, 0, generator)
        for parameter in placement:
            parameter.requires_grad_(False)
        Trainer(field.train(), values, config, None, {}, []).run()
    elif mode in ("joint", "subset"):
        joint_fine_tune(field, values, config.iterations, config.lr, 4096 if mode == "subset" else 0, generator)
    elif mode == "quarter":
        first = max(1, round(config.iterations / 4))
        joint_fine_tune(field, values, first, config.lr, 0, generator)
        for parameter in placement:
            parameter.requires_grad_(False)
        rest = config.iterations - first
        Trainer(field.train(), values, replace(config, iterations=rest, density_start=rest + 1), None, {}, []).run()
    else:  # density
        for parameter in encoder.placement_parameters():
            parameter.requires_grad_(True)
        Trainer(field.train(), values, replace(config, density_start=0), None, {}, []).run()
    field.requires_grad_(False)


def time_fine_tunes(values: torch.Tensor, iterations: int, rounds: int = 3) -> None:
    """Print ms per trainer iteration of a step's fine-tune, grids only and with the placement following the
    error (fused kernel, then reference), interleaved over ``rounds`` rounds; the medians."""
    from apmgsrn.series.steps import tracking_config

    config = StepwiseConfig().step_config(TrainConfig(iterations=2000, voxel_fraction=SERIES.voxel_fraction,
                                                      anchored_grids=SERIES.anchored_grids))
    config = replace(config, iterations=iterations)
    cases = {"grids only": ("auto", config), "placement follows, fused": ("auto", tracking_config(config)),
             "placement follows, reference": ("torch", tracking_config(config))}
    times = {name: [] for name in cases}
    for _ in range(rounds):
        for name, (backend, step_config) in cases.items():
            field = train_prepared_shell(values, backend)
            field.requires_grad_(False)
            field.encoder.grids.requires_grad_(True)
            for parameter in field.encoder.placement_parameters():
                parameter.requires_grad_(step_config.placement_loss == "reconstruction")
            trainer = Trainer(field.train(), values, step_config, None, {}, [])
            trainer.step()  # warm-up (builds the kernel once)
            began = time.perf_counter()
            for _ in range(iterations):
                trainer.step()
                trainer.state.iteration += 1
            times[name].append(1000 * (time.perf_counter() - began) / iterations)
    for name, samples in times.items():
        rounds_text = ", ".join(f"{t:.1f}" for t in samples)
        print(f"{name:32s} {sorted(samples)[len(samples) // 2]:7.1f} ms/iteration  ({rounds_text})")


def train_prepared_shell(values: torch.Tensor, backend: str):
    """A small-preset field for ``values`` (its initial parameters: the timing does not depend on them)."""
    from apmgsrn.models.field import NeuralField

    config = preset_config("apmgsrn", "small", backend=backend)
    return NeuralField(config, volume_shape=tuple(values.shape), generator=torch.Generator().manual_seed(0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True, help="a folder of volume files, one per step")
    parser.add_argument("--mode", choices=MODES, help="how a step's fine-tune moves the placement")
    parser.add_argument("--timing", type=int, metavar="N", help="time N iterations of each way instead")
    parser.add_argument("--steps", type=int, default=3, help="fine-tune this many steps after the start")
    args = parser.parse_args()
    torch.set_num_threads(1)
    data, prepared = load_series_folder(args.data)
    if args.timing:
        time_fine_tunes(prepared.values[0], args.timing)
        return
    if args.mode is None:
        parser.error("--mode or --timing is required")
    config = TrainConfig(iterations=2000, voxel_fraction=SERIES.voxel_fraction, anchored_grids=SERIES.anchored_grids)
    start = choose_start(prepared.values, "auto")
    single = replace(prepared, values=prepared.values[start])
    cache = args.data / f"start_{start}.pt"
    if cache.exists():
        field = train_prepared(single, preset_config("apmgsrn", "small"), replace(config, iterations=1),
                               tuple(data.shape[1:]), None, {}, []).field
        state, error = torch.load(cache)
        field.load_state_dict(state)
    else:
        first = train_prepared(single, preset_config("apmgsrn", "small"), config, tuple(data.shape[1:]), None, {}, [])
        field, error = first.field, float(np.sqrt(first.state.history["reconstruction"][-1]))
        torch.save(({k: v.clone() for k, v in field.state_dict().items()}, error), cache)
    print(f"start step {start}: {evaluate(field.eval(), data[start]).psnr:.2f} dB", flush=True)
    states = {start: {k: v.clone() for k, v in field.state_dict().items()}}
    field.requires_grad_(False)
    generator = torch.Generator().manual_seed(1)
    for step, neighbour in step_order(start, len(data))[: args.steps]:
        began = time.perf_counter()
        field.load_state_dict(states[neighbour])
        factor = change_factor(change(prepared.values, step, neighbour), error)
        step_config = StepwiseConfig().step_config(config, factor)
        fine_tune(field, prepared.values[step], step_config, args.mode, generator)
        states[step] = {k: v.clone() for k, v in field.state_dict().items()}
        print(f"{args.mode} step {step}: {step_config.iterations} iterations, "
              f"{evaluate(field.eval(), data[step]).psnr:.2f} dB, {time.perf_counter() - began:.0f} s", flush=True)


if __name__ == "__main__":
    main()

"""Where the default model's CPU training step spends its time: a per-phase table, fused step and autograd path.

    OMP_NUM_THREADS=1 python benchmarks/profile_step.py --threads 1
    python benchmarks/profile_step.py --volume examples/data/hcci_oh_187.nc --threads 2 --rounds 6

The model is ``preset_config("hybrid", "small")`` trained as ``apmgsrn train`` trains it (its recipe's
``training_defaults``, ``--batch`` points a step). Steps run from iteration ``--start`` (200: the density step
moves the grids), then with the grids frozen (no density step). Each phase is timed by wrapping the function
that does it (exclusive wall time: a phase nested in another counts once); the backward of the reconstruction
loss is split where the gradient reaches the encoder's output (a tensor hook):

- point draws: ``draw_batch`` and the spatial sort, with the error guide's periodic measure;
- encoder forward / decoder forward: the modules' ``forward``;
- backward: decoder / backward: encoder: the reconstruction loss's backward before and after the hook;
- fused step: the encoder's fused training kernel (encoder and decoder, forward and backward, in one pass);
- density forward / density backward: the feature density with its loss, and that loss's backward;
- optimiser: both optimisers' ``step`` and ``zero_grad``;
- other: the rest of ``Trainer.step`` (the loss, the learning rate, Python).

The two paths (``Trainer.fused_step`` True and False: the fused kernel, or the level kernel, PyTorch's matrix
products and autograd) alternate in rounds of ``--steps`` steps on one trainer, so load from other processes
hits both alike; each cell is the median over rounds of the round's mean ms per step.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from collections import defaultdict
from pathlib import Path

import torch

import apmgsrn
from apmgsrn.data import open_volume
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.training import trainer as trainer_module
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.trainer import TrainConfig, Trainer

PHASES = ("point draws", "encoder forward", "decoder forward", "backward: decoder", "backward: encoder",
          "fused step", "density forward", "density backward", "optimiser", "other")


class PhaseClock:
    """Exclusive wall time per phase: a phase entered inside another is taken out of the outer one."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = defaultdict(float)
        self._stack: list[list] = []  # [name, start, time of nested phases]

    def enter(self, name: str) -> None:
        self._stack.append([name, time.perf_counter(), 0.0])

    def leave(self) -> None:
        name, start, nested = self._stack.pop()
        elapsed = time.perf_counter() - start
        self.totals[name] += elapsed - nested
        if self._stack:
            self._stack[-1][2] += elapsed

    def add(self, name: str, seconds: float) -> None:
        """Time measured by hand (the split backward), outside any phase."""
        self.totals[name] += seconds
        if self._stack:
            self._stack[-1][2] += seconds

    def wrap(self, name: str, function):
        def timed(*args, **kwargs):
            self.enter(name)
            try:
                return function(*args, **kwargs)
            finally:
                self.leave()
        return timed


def instrument(trainer: Trainer, clock: PhaseClock) -> None:
    """Wraps the functions of every phase (module globals of the trainer, the instances' methods)."""
    field, encoder = trainer.field, trainer.field.encoder
    for name in ("draw_batch", "spatially_ordered"):
        setattr(trainer_module, name, clock.wrap("point draws", getattr(trainer_module, name)))
    if trainer.error_guide is not None:
        trainer.error_guide.measure = clock.wrap("point draws", trainer.error_guide.measure)
    marks: list[float] = []
    encoder_forward = encoder.forward

    def forward(*args, **kwargs):
        out = encoder_forward(*args, **kwargs)
        if out.requires_grad:
            out.register_hook(lambda grad: marks.append(time.perf_counter()))
        return out

    encoder.forward = clock.wrap("encoder forward", forward)
    field.decoder.forward = clock.wrap("decoder forward", field.decoder.forward)
    field.fused_mse_step = clock.wrap("fused step", field.fused_mse_step)
    encoder.feature_density = clock.wrap("density forward", encoder.feature_density)
    density_losses: list[torch.Tensor] = []
    density_loss = trainer_module.feature_density_loss

    def loss(*args, **kwargs):
        value = density_loss(*args, **kwargs)
        density_losses.append(value)
        return value

    trainer_module.feature_density_loss = clock.wrap("density forward", loss)
    for optimizer in (trainer.network_optimizer, trainer.placement_optimizer):
        if optimizer is not None:
            optimizer.step = clock.wrap("optimiser", optimizer.step)
            optimizer.zero_grad = clock.wrap("optimiser", optimizer.zero_grad)
    backward = torch.Tensor.backward

    def timed_backward(tensor, *args, **kwargs):
        start = time.perf_counter()
        marks.clear()
        backward(tensor, *args, **kwargs)
        end = time.perf_counter()
        if density_losses and tensor is density_losses[-1]:
            density_losses.clear()
            clock.add("density backward", end - start)
        else:
            split = marks[0] if marks else end
            clock.add("backward: decoder", split - start)
            clock.add("backward: encoder", end - split)

    torch.Tensor.backward = timed_backward


def build_trainer(volume_path: str, batch: int, start: int) -> Trainer:
    volume = open_volume(volume_path)
    prepared = prepare_values(volume.to_numpy(), "none", 0.0, "x", torch.device("cpu"))
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=volume.shape,
                        generator=torch.Generator().manual_seed(0))
    config = TrainConfig(iterations=3000, batch_size=batch, seed=0, **training_defaults("hybrid"))
    trainer = Trainer(field, prepared.values, config)
    trainer.state.iteration = start
    return trainer


def run_round(trainer: Trainer, clock: PhaseClock, steps: int) -> dict[str, float]:
    """Mean ms per step of every phase (and ``total``) over ``steps`` steps."""
    clock.totals.clear()
    begin = time.perf_counter()
    for _ in range(steps):
        trainer.step()
        trainer.state.iteration += 1
    total = time.perf_counter() - begin
    row = {name: 1000 * clock.totals.get(name, 0.0) / steps for name in PHASES if name != "other"}
    row["other"] = 1000 * total / steps - sum(row.values())
    row["total"] = 1000 * total / steps
    return row


def profile(trainer: Trainer, clock: PhaseClock, rounds: int, steps: int) -> dict[bool, dict[str, float]]:
    """Per path (fused True/False), the median over rounds of each phase's ms per step."""
    results: dict[bool, list[dict[str, float]]] = {True: [], False: []}
    for fused in (True, False):  # warm-up: kernels built, allocator warm
        trainer.fused_step = fused
        run_round(trainer, clock, 2)
    for _ in range(rounds):
        for fused in (False, True):
            trainer.fused_step = fused
            results[fused].append(run_round(trainer, clock, steps))
    return {fused: {name: statistics.median(r[name] for r in rows) for name in rows[0]}
            for fused, rows in results.items()}


def print_table(title: str, medians: dict[bool, dict[str, float]]) -> None:
    print(f"\n{title}\n")
    print("| phase | autograd path, ms | fused step, ms |")
    print("|---|---:|---:|")
    for name in (*PHASES, "total"):
        old, new = medians[False][name], medians[True][name]
        if name != "total" and old < 0.05 and new < 0.05:
            continue
        label = f"**{name}**" if name == "total" else name
        print(f"| {label} | {old:.1f} | {new:.1f} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--volume", default="examples/data/hcci_oh_187.nc")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--batch", type=int, default=32768)
    parser.add_argument("--start", type=int, default=200, help="iteration the steps start at (grids moving)")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--steps", type=int, default=8, help="steps per round")
    parser.add_argument("--json", help="also write the medians there ({grids: {path: {phase: ms}}})")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    trainer = build_trainer(args.volume, args.batch, args.start)
    clock = PhaseClock()
    instrument(trainer, clock)
    print(f"hybrid small, {args.batch} points a step, {args.threads} thread(s), {args.volume}, "
          f"apmgsrn from {Path(apmgsrn.__file__).parent}")
    results = {"moving": profile(trainer, clock, args.rounds, args.steps)}
    print_table("grids moving (density step on)", results["moving"])
    trainer.state.frozen_at = trainer.state.iteration
    for parameter in trainer.field.encoder.placement_parameters():
        parameter.requires_grad_(False)
    results["frozen"] = profile(trainer, clock, args.rounds, args.steps)
    print_table("grids frozen (no density step)", results["frozen"])
    if args.json:
        named = {grids: {"fused" if fused else "autograd": row for fused, row in paths.items()}
                 for grids, paths in results.items()}
        Path(args.json).write_text(json.dumps(named, indent=1))


if __name__ == "__main__":
    main()

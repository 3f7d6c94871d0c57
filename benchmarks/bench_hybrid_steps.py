"""Milliseconds per training iteration of the hybrid model against APMGSRN, as the trainer runs them.

Each iteration is the trainer's own step (reconstruction step; density step while the grids move) on a
real volume, timed separately in the two phases of a protocol run (grids moving: iterations 100-1000 of
2,000; frozen: 1000-2000) and combined with those weights (the 5 % before the grids move are counted as
frozen ones). Models are timed in alternating rounds so that load from other processes hits all alike.

    python benchmarks/bench_hybrid_steps.py --volume ../shared/data/neghip_64x64x64_uint8.raw \
        --threads 1 --sizes small --steps 50 --rounds 2 --skip-reference
    python benchmarks/bench_hybrid_steps.py --volume ../shared/data/hcci_oh_187.nc --variable oh --device cuda

On a GPU the Triton kernels run, and each step is timed between two synchronisations.

The table it prints goes into docs/models.md by hand, with the date and the machine's load.
"""

from __future__ import annotations

import argparse
import json
import statistics

import torch

from apmgsrn.data import open_volume
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.timing import median_step_seconds
from apmgsrn.training.trainer import Trainer, TrainConfig

# (label, model, encoder overrides)
CASES = [
    ("apmgsrn (fused kernel)", "apmgsrn", {}),
    ("hybrid (fused kernel)", "hybrid", {}),
    ("hybrid (PyTorch reference)", "hybrid", {"backend": "torch"}),
]


def phase_times(trainer: Trainer, steps: int) -> float:
    """Median seconds of ``steps`` trainer steps from the trainer's current state (a GPU is synchronised
    around each step, so a step's time is its own)."""
    return median_step_seconds(trainer, 0.0, steps, steps)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volume", required=True)
    parser.add_argument("--variable")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--device", default="cpu", help="cpu (fused C kernels) or cuda (Triton kernels)")
    parser.add_argument("--sizes", nargs="+", default=["small", "medium"])
    parser.add_argument("--steps", type=int, default=10, help="timed steps per phase and round")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--skip-reference", action="store_true", help="leave out the slow PyTorch reference")
    parser.add_argument("--hybrid-variant", action="append", default=[], metavar="JSON",
                        help='another hybrid to time, its preset overridden (e.g. \'{"levels": 16}\'); repeatable')
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    volume = open_volume(args.volume, variable=args.variable)
    device = torch.device(args.device)
    prepared = prepare_values(volume.to_numpy(), "none", 0.0, str(args.volume), device)
    cases = [c for c in CASES if not (args.skip_reference and c[2].get("backend") == "torch")]
    for text in args.hybrid_variant:
        cases.append((f"hybrid {text}", "hybrid", json.loads(text)))
    where = torch.cuda.get_device_name(device) if device.type == "cuda" else f"CPU, {args.threads} threads"
    print(f"{volume.path.name}, {where}, 32,768 points per iteration")
    print("| model | size | grids moving ms | frozen ms | protocol ms/iteration |")
    print("|---|---|---|---|---|")
    for size in args.sizes:
        results: dict[str, list[tuple[float, float]]] = {label: [] for label, _, _ in cases}
        for _ in range(args.rounds):
            for label, model, overrides in cases:
                field = NeuralField(preset_config(model, size, **overrides), volume_shape=volume.shape,
                                    generator=torch.Generator().manual_seed(0)).to(device)
                # Each kind's own training defaults (the hybrid draws half of every batch on voxels).
                config = TrainConfig(iterations=2000, batch_size=32768, seed=0, **training_defaults(model))
                trainer = Trainer(field, prepared.values, config)
                trainer.state.iteration = 100  # grids move from here (density step every iteration)
                phase_times(trainer, 2)  # warm-up (kernel build, allocator)
                moving = phase_times(trainer, args.steps)
                trainer.state.frozen_at = trainer.state.iteration
                for p in field.encoder.placement_parameters():
                    p.requires_grad_(False)
                frozen = phase_times(trainer, args.steps)
                results[label].append((moving, frozen))
        for label, _, _ in cases:
            moving = statistics.median(m for m, _ in results[label]) * 1000
            frozen = statistics.median(f for _, f in results[label]) * 1000
            protocol = 0.45 * moving + 0.55 * frozen
            print(f"| {label} | {size} | {moving:.1f} | {frozen:.1f} | {protocol:.1f} |", flush=True)


if __name__ == "__main__":
    main()

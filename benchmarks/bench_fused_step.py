"""Milliseconds of the hybrid's fused training step and of the level kernel beneath it, on a trained model.

The fused step (:mod:`apmgsrn.ops.field_train_cpu`) gives the prediction and the gradient of the squared error
with respect to the level tables and grids under a frozen decoder: every iteration of a time series' step
fine-tunes and of their fine-tune towards the packing. The level kernel (:mod:`apmgsrn.ops.level_grids_cpu`)
encodes and scatters for one volume's training, whose decoder learns through PyTorch. Both share the level
kernel's tile code (``encode_tile``, ``scatter_tile``).

    python benchmarks/bench_fused_step.py --volume ../shared/data/viscous_fingers_t050.vti --threads 1
    python benchmarks/bench_fused_step.py --volume ... --before /tmp/old/src   # A/B with another checkout

The model is the small hybrid fitted for ``--fit`` iterations (so its decoder's ReLUs are as sparse as a trained
one's); points are drawn uniformly in the domain, ``--points`` of them (12,288: a series step's batch on a CPU).
Rows are timed in alternating rounds (median of ``--calls`` calls per round, then the median over rounds), so
load from other processes hits all alike. With ``--before SRC`` (the ``src`` folder of another checkout) the
same rows also run on that checkout's kernel sources, and their outputs are compared with this checkout's bit
for bit. The table it prints goes into docs by hand, with the date and the machine's load.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import time
from pathlib import Path

import torch

from apmgsrn.data import open_volume
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config, training_defaults
from apmgsrn.ops import field_train_cpu, level_grids_cpu
from apmgsrn.ops.kernel_cache import CompiledLibrary
from apmgsrn.ops.level_grids import level_grid_mse_step_reference
from apmgsrn.training.fit import prepare_values
from apmgsrn.training.trainer import TrainConfig, Trainer


def sources_of(src: Path) -> tuple[str, str]:
    """The level kernel's C source and the fused step's whole C source (level kernel, lane table, decoder, step)
    of the checkout whose package folder is ``src``."""
    texts = []
    parts = (("level_grids_cpu", "C_SOURCE"), ("multigrid_cpu", "LANE_LUT_SOURCE"), ("field_cpu", "MLP_SOURCE"),
             ("field_train_cpu", "TRAIN_SOURCE"))
    for module, attribute in parts:
        path = src / "apmgsrn" / "ops" / f"{module}.py"
        spec = importlib.util.spec_from_file_location(f"before_{module}", path)
        loaded = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(loaded)
        texts.append(getattr(loaded, attribute))
    return texts[0], "".join(texts)


def libraries(label: str, level_source: str, step_source: str) -> tuple[CompiledLibrary, CompiledLibrary]:
    """The level kernel and the fused step built from these sources."""
    level = CompiledLibrary(f"bench_level_{label}", level_source, level_grids_cpu._declare)
    step = CompiledLibrary(f"bench_step_{label}", step_source, field_train_cpu._declare)
    return level, step


def median_ms(run, calls: int) -> float:
    run()  # warm-up (build, allocator)
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return statistics.median(times) * 1000


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volume", required=True)
    parser.add_argument("--variable")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--points", type=int, default=12288)
    parser.add_argument("--fit", type=int, default=300, help="iterations the model is fitted for first")
    parser.add_argument("--calls", type=int, default=60)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--before", type=Path, help="the src folder of another checkout to compare with")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    volume = open_volume(args.volume, variable=args.variable)
    prepared = prepare_values(volume.to_numpy(), "none", 0.0, str(args.volume), torch.device("cpu"))
    field = NeuralField(preset_config("hybrid", "small"), volume_shape=volume.shape,
                        generator=torch.Generator().manual_seed(0))
    Trainer(field, prepared.values, TrainConfig(iterations=args.fit, batch_size=32768, seed=0,
                                                **training_defaults("hybrid"))).run()
    encoder, weights = field.encoder, field.decoder.weights()
    weights = [w.detach() for w in weights]
    table = torch.cat([encoder.level_table, encoder.grids.reshape(-1)]).detach().contiguous()
    maps = encoder.maps().detach()
    points = torch.rand(args.points, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
    target = torch.rand(args.points, generator=torch.Generator().manual_seed(2))
    upstream = torch.randn(args.points, encoder.layout.out_features, generator=torch.Generator().manual_seed(3))

    versions = {"this checkout": (level_grids_cpu.LIBRARY, field_train_cpu.LIBRARY)}
    if args.before is not None:
        versions = {"before": libraries("before", *sources_of(args.before)), **versions}

    def use(version: str) -> None:
        level_grids_cpu.LIBRARY, field_train_cpu.LIBRARY = versions[version]

    def step():
        return field_train_cpu.level_grid_mse_step_cpu(points, maps, table, encoder.layout, weights, target)

    def encode():
        return level_grids_cpu.level_grid_features_cpu(points, maps, table, encoder.layout)

    def encode_and_scatter():
        learning = table.clone().requires_grad_(True)
        level_grids_cpu.level_grid_features_cpu(points, maps, learning, encoder.layout).backward(upstream)
        return learning.grad

    def reference():
        return level_grid_mse_step_reference(points, maps, table, encoder.layout, weights, target)

    rows = {"fused step (prediction, table gradient)": step, "level kernel forward": encode,
            "level kernel forward + backward": encode_and_scatter, "PyTorch reference of the fused step": reference}
    if args.before is not None:
        outputs = {}
        for version in versions:
            use(version)
            outputs[version] = (step(), encode_and_scatter())
        (a, ga), (b, gb) = outputs.values()
        same = torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and torch.equal(ga, gb)
        print(f"before and this checkout give the same prediction and gradients to the bit: {same}")
    timed: dict[tuple[str, str], list[float]] = {}
    for _ in range(args.rounds):
        for version in versions:
            use(version)
            for name, run in rows.items():
                if name.startswith("PyTorch") and version == "before":
                    continue  # the reference is the same code in both
                timed.setdefault((name, version), []).append(median_ms(run, args.calls))
    use("this checkout")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"{volume.path.name}, small hybrid fitted {args.fit} iterations, {args.points:,} points, "
          f"CPU, {args.threads} thread(s), load average {load:.2f}")
    header = " | ".join(f"{version} ms" for version in versions)
    print(f"| | {header} |")
    print("|---|" + "---|" * len(versions))
    for name in rows:
        cells = [f"{statistics.median(timed[(name, v)]):.2f}" if (name, v) in timed else "" for v in versions]
        print(f"| {name} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()

"""PSNR of the default model under the CPU protocol through each path of its training step.

The paths: ``autograd`` (the level kernel, PyTorch's matrix products and autograd: the step as it was before
the fused kernel, bit for bit), ``vector`` (the fused kernel on the vector unit in float32) and ``tile`` (the
fused kernel's products on AMX's tile unit, where the CPU has one; else the same as ``vector``). Everything
else is ``apmgsrn.fit`` as ``apmgsrn train`` runs it: the recipe's settings, 2,000 iterations x 32,768 points
(the CPU protocol of docs/results_protocol_cpu.md), seeds as given. Prints a table, the difference of each
fused path's PSNR from autograd's, and the median over seeds.

    OMP_NUM_THREADS=2 python benchmarks/step_paths_psnr.py --volumes ../shared/data/hcci_oh_187.nc:oh \\
        ../shared/data/miranda_density_256.nc:density --seeds 0 1
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import apmgsrn
from apmgsrn.ops import field_train_cpu
from apmgsrn.training import trainer as trainer_module

PATHS = ("autograd", "vector", "tile")


ORIGINAL_INIT = trainer_module.Trainer.__init__
ORIGINAL_TAKES = field_train_cpu.tile_unit_takes


def use_path(path: str) -> None:
    """Point the trainer and the fused kernel at one path (process-wide)."""

    def init(self, *args, **kwargs):
        ORIGINAL_INIT(self, *args, **kwargs)
        self.fused_step = path != "autograd"

    trainer_module.Trainer.__init__ = init
    field_train_cpu.tile_unit_takes = ORIGINAL_TAKES if path == "tile" else (lambda *args: False)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volumes", nargs="+", required=True, help="FILE[:VARIABLE]")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--paths", nargs="+", choices=PATHS, default=list(PATHS))
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--preset", default="small")
    args = parser.parse_args()
    print(f"torch threads {torch.get_num_threads()}, tile unit here: "
          f"{bool(field_train_cpu.LIBRARY.load_or_raise().amx_ready())}, {time.strftime('%Y-%m-%d')}")
    print("| volume | seed | " + " | ".join(f"{p} dB" for p in args.paths) + " | " +
          " | ".join(f"{p} - autograd" for p in args.paths if p != "autograd") + " |")
    differences: dict[str, list[float]] = {p: [] for p in args.paths if p != "autograd"}
    for spec in args.volumes:
        path, _, variable = spec.partition(":")
        for seed in args.seeds:
            psnr = {}
            for p in args.paths:
                use_path(p)
                model = apmgsrn.fit(path, preset=args.preset, iterations=args.iterations, batch_size=32768,
                                    device="cpu", progress=False, seed=seed, **({"variable": variable} if variable else {}))
                psnr[p] = float(model.description.training["psnr"])
            gaps = [psnr[p] - psnr["autograd"] for p in differences] if "autograd" in psnr else []
            for p, gap in zip(differences, gaps):
                differences[p].append(gap)
            print(f"| {path.rsplit('/', 1)[-1]} | {seed} | " + " | ".join(f"{psnr[p]:.3f}" for p in args.paths)
                  + " | " + " | ".join(f"{g:+.3f}" for g in gaps) + " |", flush=True)
    for p, gaps in differences.items():
        if gaps:
            print(f"{p} - autograd: median {statistics.median(gaps):+.3f} dB, mean {statistics.mean(gaps):+.3f} dB")


if __name__ == "__main__":
    main()

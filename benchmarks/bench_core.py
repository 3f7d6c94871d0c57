"""Core speed table: ms per training iteration, decode throughput and peak memory, small and medium.

Each configuration runs in a fresh subprocess so its peak memory is its own (CPU: peak RSS; CUDA: peak
allocated device memory). Training steps run on a real volume (miranda density 256^3 when available).

    python benchmarks/bench_core.py                      # CPU, plus CUDA when present
    python benchmarks/bench_core.py --out docs/benchmarks_core.md
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"


def measure(preset: str, device_name: str, batch: int, steps: int, decode_batch: int, data: Path) -> dict:
    """Time training steps and decoding for one preset on one device (run in its own process)."""
    from apmgsrn.data import open_volume
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import preset_config
    from apmgsrn.training.trainer import Trainer, TrainConfig

    device = torch.device(device_name)
    if data.exists():
        values = torch.from_numpy(open_volume(data).to_numpy())
        values = (values - values.min()) / (values.max() - values.min())
    else:
        values = torch.rand(128, 128, 128)
    values = values.to(device)
    field = NeuralField(preset_config("apmgsrn", preset), 0.0, 1.0).to(device)
    # Grids moving (density step on) for the whole measurement: the costlier half of training.
    trainer = Trainer(field, values, TrainConfig(iterations=10**6, batch_size=batch, density_start=0,
                                                 freeze_fraction=1.0))

    def sync():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(5):
        trainer.step()
    sync()
    start = time.perf_counter()
    for _ in range(steps):
        trainer.step()
    sync()
    ms_per_iteration = 1000 * (time.perf_counter() - start) / steps
    field.eval()
    points = torch.rand(decode_batch, 3, device=device) * 2 - 1
    with torch.no_grad():
        for _ in range(2):
            field(points)
        sync()
        repeats = 5 if device.type == "cpu" else 50
        start = time.perf_counter()
        for _ in range(repeats):
            field(points)
        sync()
        points_per_second = repeats * decode_batch / (time.perf_counter() - start)
    if device.type == "cuda":
        peak = torch.cuda.max_memory_allocated(device)
    else:
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    return {"ms_per_iteration": ms_per_iteration, "points_per_second": points_per_second, "peak_bytes": peak}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--presets", nargs="+", default=["small", "medium"])
    parser.add_argument("--devices", nargs="+", default=["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--data", type=Path, default=SHARED / "miranda_density_256.nc")
    parser.add_argument("--out", type=Path)
    parser.add_argument("--one", nargs=2, metavar=("PRESET", "DEVICE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one:
        preset, device = args.one
        batch = 32768 if device == "cpu" else 100_000
        print(json.dumps(measure(preset, device, batch, args.steps if device == "cpu" else 200, 262_144, args.data)))
        return
    rows = ["| device | preset | batch | ms / iteration | decode M points/s | peak memory MB |", "|---|---|---|---|---|---|"]
    for device in args.devices:
        for preset in args.presets:
            output = subprocess.run([sys.executable, __file__, "--one", preset, device, "--steps", str(args.steps),
                                     "--data", str(args.data)], capture_output=True, text=True, check=True).stdout
            result = json.loads(output.strip().splitlines()[-1])
            batch = 32768 if device == "cpu" else 100_000
            row = (f"| {device} | {preset} | {batch:,} | {result['ms_per_iteration']:.1f} | "
                   f"{result['points_per_second'] / 1e6:.2f} | {result['peak_bytes'] / 2**20:.0f} |")
            print(row, flush=True)
            rows.append(row)
    cpu = f"{platform.processor() or platform.machine()}, {torch.get_num_threads()} threads"
    gpu = torch.cuda.get_device_name() if torch.cuda.is_available() else "none"
    text = ("# Core: training step, decoding and memory (issue 2)\n\n"
            f"Machine: CPU {cpu}; GPU {gpu}; torch {torch.__version__}. Command: "
            f"`python benchmarks/bench_core.py {' '.join(sys.argv[1:])}`.\n"
            "Training step = reconstruction step + density step (grids moving), default trainer settings "
            "(on CPUs with native bfloat16 the decoder's hidden layers train in bfloat16); decode = random "
            "points in batches of 262,144 after warm-up, float32, device synchronised; peak memory = peak RSS "
            "of the process on CPU (torch, the 256^3 volume and the model), peak allocated memory on CUDA.\n\n"
            + "\n".join(rows) + "\n\n"
            "The authors' code on the same 2-core CPU (REFERENCE.md): about 68 ms per small iteration; decoding "
            "0.96 M (small) and 0.77 M (medium) points/s.\n")
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()

"""PSNR and training time of every shared volume under the CPU protocol of REFERENCE.md.

Protocol: 2,000 iterations x 32,768 points, lr 0.01, seed 0, small and medium presets, PSNR over every
voxel at native resolution. Runs through the same code as ``apmgsrn train``; the device is recorded
(PSNR does not depend on it beyond noise; times do).

    python benchmarks/cpu_protocol.py --device cpu --volumes hcci_oh_187.nc:oh miranda_density_256.nc:density
    python benchmarks/cpu_protocol.py --device cuda            # every shared volume
"""

from __future__ import annotations

import argparse
import platform
import sys
import tempfile
from pathlib import Path

import torch

from apmgsrn.data import open_volume
from apmgsrn.device import resolve_device
from apmgsrn.models.registry import preset_config
from apmgsrn.training.fit import fit_volume
from apmgsrn.training.trainer import TrainConfig

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
# file[:variable[:transform]]
VOLUMES = [
    "hcci_oh_187.nc:oh",
    "miranda_density_256.nc:density",
    "channel_pressure_640x240x48.nc:pressure",
    "richtmyer_meshkov_t20_256x256x256_uint8.raw",
    "c60_128x128x128_uint8.raw",
    "neghip_64x64x64_uint8.raw",
    "darkmatter_density_64.h5:densityfield:log10",
    "cth_armor_penetration.vtr:Pressure",
    "viscous_fingers_t050.vti",
]
AUTHORS = {  # REFERENCE.md: the authors' code under the same protocol on this 2-core CPU
    ("hcci_oh_187.nc", "small"): (49.90, 114), ("hcci_oh_187.nc", "medium"): (50.89, 157),
    ("miranda_density_256.nc", "small"): (26.15, 127), ("miranda_density_256.nc", "medium"): (28.88, 169),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=SHARED)
    parser.add_argument("--volumes", nargs="+", default=VOLUMES)
    parser.add_argument("--presets", nargs="+", default=["small", "medium"])
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--batch-size", type=int, default=32768)
    parser.add_argument("--device", default="auto")
    parser.add_argument("--out", type=Path, help="Markdown file to write the table to")
    args = parser.parse_args()
    device = resolve_device(args.device)
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else f"{platform.processor() or 'CPU'}, {torch.get_num_threads()} threads"
    rows = ["| volume | preset | PSNR dB | train s | ms/it | grids frozen at | authors' PSNR / s |", "|---|---|---|---|---|---|---|"]
    print(f"device: {device} ({name})")
    with tempfile.TemporaryDirectory() as tmp:
        for spec in args.volumes:
            parts = spec.split(":")
            file, variable = parts[0], (parts[1] if len(parts) > 1 else None)
            transform = parts[2] if len(parts) > 2 else "none"
            path = args.data / file
            if not path.exists():
                print(f"skip {file}: not found")
                continue
            try:
                volume = open_volume(path, variable=variable)
                volume.to_numpy()
            except Exception as exc:  # a reader's optional package may be missing on this machine
                print(f"skip {file}: {exc}")
                continue
            for preset in args.presets:
                config = TrainConfig(iterations=args.iterations, batch_size=args.batch_size, seed=0)
                result = fit_volume(volume, preset_config("apmgsrn", preset), config, Path(tmp) / "m.apmgsrn",
                                    device, transform=transform, progress=False)
                ref = AUTHORS.get((file, preset))
                ref_text = f"{ref[0]:.2f} / {ref[1]}" if ref else ""
                label = f"{file}" + (f" ({transform})" if transform != "none" else "")
                row = (f"| {label} | {preset} | {result.psnr:.2f} | {result.seconds:.1f} | "
                       f"{1000 * result.seconds / result.iterations:.1f} | {result.frozen_at} | {ref_text} |")
                print(row, flush=True)
                rows.append(row)
    table = "\n".join(rows)
    if args.out:
        command = "python benchmarks/cpu_protocol.py " + " ".join(sys.argv[1:])
        args.out.write_text(
            f"# The protocol on {device.type.upper()}: PSNR and training time\n\n"
            f"Device: {device} ({name}); torch {torch.__version__}; {args.iterations} iterations x "
            f"{args.batch_size} points, seed 0. Train s: the training loop, as the authors' figures count it. "
            f"Command: `{command}`.\n\n{table}\n"
        )


if __name__ == "__main__":
    main()

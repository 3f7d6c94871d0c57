"""Quality sweep of training-schedule variants under the CPU protocol (2,000 iterations x 32,768 points).

Used to choose the trainer's defaults; runs on any device (PSNR does not depend on the device beyond
noise). Reads NetCDF through h5py so it also runs where netCDF4 is not installed.

    python benchmarks/sweep_schedule.py --volumes hcci_oh_187.nc:oh miranda_density_256.nc:density
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import h5py
import numpy as np
import torch

from apmgsrn.inference.evaluate import evaluate
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.training.trainer import Trainer, TrainConfig

VARIANTS = {
    "paper": dict(density_normalization="batch", lr_schedule="constant"),
    "paper+cosine": dict(density_normalization="batch"),
    "mass-constant": dict(lr_schedule="constant"),
    "default": dict(),
    "plr5e-4": dict(placement_lr=5e-4),
    "plr2e-3": dict(placement_lr=2e-3),
    "no-grid-motion": dict(density_start=10**9),
}


def run(data: np.ndarray, preset: str, variant: dict, device: torch.device, iterations: int, model_kw: dict) -> tuple[float, float]:
    mn, mx = float(data.min()), float(data.max())
    volume = torch.from_numpy((data - mn) / (mx - mn)).to(device)
    config = TrainConfig(iterations=iterations, batch_size=32768, seed=0, **variant)
    field = NeuralField(preset_config("apmgsrn", preset, **model_kw), mn, mx, volume_shape=data.shape,
                        generator=torch.Generator().manual_seed(0)).to(device)
    start = time.perf_counter()
    Trainer(field, volume, config).run()
    seconds = time.perf_counter() - start
    return evaluate(field, data).psnr, seconds


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--data", default=str(Path(__file__).resolve().parents[2] / "shared" / "data"))
    parser.add_argument("--volumes", nargs="+", default=["hcci_oh_187.nc:oh", "miranda_density_256.nc:density"])
    parser.add_argument("--presets", nargs="+", default=["small"])
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS))
    parser.add_argument("--extra", default="{}", help="JSON dict of variants to add")
    parser.add_argument("--iterations", type=int, default=2000)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = parser.parse_args()
    variants = {**VARIANTS, **json.loads(args.extra)}
    names = args.variants + [k for k in json.loads(args.extra) if k not in args.variants]
    device = torch.device(args.device)
    for spec in args.volumes:
        name, var = spec.split(":")
        with h5py.File(Path(args.data) / name, "r") as f:
            data = np.asarray(f[var][()], dtype=np.float32)
        for preset in args.presets:
            for variant in names:
                kw = dict(variants[variant])
                model_kw = {"backend": "torch", **kw.pop("model", {})}
                psnr, seconds = run(data, preset, kw, device, args.iterations, model_kw)
                print(f"{name:28s} {preset:6s} {variant:22s} PSNR {psnr:6.2f} dB  {seconds:6.1f} s", flush=True)


if __name__ == "__main__":
    main()

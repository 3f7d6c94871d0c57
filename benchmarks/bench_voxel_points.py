"""Training on voxels against uniform points (``--voxel-fraction``): PSNR at the voxels and between them.

For every volume, model kind and share of voxel points asked, trains one model under the CPU protocol
(``apmgsrn train --iterations 2000 --batch-size 32768 --device cpu``, one seed) unless its file is already in
``--models``, then measures:

- the PSNR and largest error over every voxel (what ``eval``, ``decode`` and compression ratios measure);
- the PSNR at 2^21 uniformly random points against the volume's trilinear interpolation there (what a ray
  marcher samples between voxels; the same points for every model of a volume).

Writes the table (markdown) to ``--out`` and prints it. Nothing is timed (runs may share the machine).

Usage::

    python benchmarks/bench_voxel_points.py --models /tmp/voxel-models --out docs/results_voxel_points.md \\
        --kinds apmgsrn,hybrid --fractions 0,0.5 \\
        ../shared/data/hcci_oh_187.nc:oh ../shared/data/neghip_64x64x64_uint8.raw
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

import apmgsrn
from apmgsrn.atomic import atomic_write_text
from apmgsrn.bench.datasets import open_spec, parse_data_spec
from apmgsrn.ops.trilinear import sample_volume

PROTOCOL = ["--iterations", "2000", "--batch-size", "32768", "--device", "cpu", "--preset", "small"]
OFF_LATTICE_POINTS = 1 << 21


def model_path(folder: Path, spec_text: str, kind: str, fraction: float, seed: int,
               error_sampling: float | None = None) -> Path:
    stem = Path(parse_data_spec(spec_text).path).stem
    guided = "" if error_sampling is None else f"_e{error_sampling:g}"
    return folder / f"{stem}_{kind}_v{fraction:g}{guided}_s{seed}.apmgsrn"


def train(spec_text: str, kind: str, fraction: float, seed: int, out: Path,
          error_sampling: float | None = None) -> None:
    spec = parse_data_spec(spec_text)
    command = [sys.executable, "-m", "apmgsrn", "train", str(spec.path), *PROTOCOL, "--model", kind,
               "--voxel-fraction", str(fraction), "--seed", str(seed), "--out", str(out), "--json"]
    if error_sampling is not None:
        command += ["--error-sampling", str(error_sampling)]
    if spec.variable:
        command += ["--variable", spec.variable]
    print(" ".join(command[2:]), flush=True)
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)


def measure(path: Path, truth: torch.Tensor, points: torch.Tensor, between: torch.Tensor, span: float) -> dict:
    model = apmgsrn.load(path, precision="float32")
    training = model.description.training
    with torch.no_grad():
        predicted = torch.cat([model(chunk).view(-1) for chunk in points.split(1 << 16)])
    mse = float((predicted - between).square().mean())
    return {
        "psnr": training["psnr"],
        "max_abs_error": training["max_abs_error"],
        "off_lattice_psnr": 20 * math.log10(span) - 10 * math.log10(mse),
        "parameters": model.field.parameter_count(),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", nargs="+", help="VOLUME[:VARIABLE]")
    parser.add_argument("--kinds", default="apmgsrn,hybrid")
    parser.add_argument("--fractions", default="0,0.5")
    parser.add_argument("--error-sampling", default="",
                        help="comma-separated shares of the voxel points drawn where the model is wrong (default: "
                             "each kind's own, not named in the model files)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--models", type=Path, required=True, help="folder of the trained models (reused)")
    parser.add_argument("--out", type=Path, help="markdown table to write")
    args = parser.parse_args()
    args.models.mkdir(parents=True, exist_ok=True)
    kinds = args.kinds.split(",")
    fractions = [float(f) for f in args.fractions.split(",")]
    guides = [float(g) for g in args.error_sampling.split(",")] if args.error_sampling else [None]
    lines = ["| volume | model | voxel fraction | error sampling | PSNR at voxels dB | max error | "
             "PSNR between voxels dB | parameters |", "|---|---|---|---|---|---|---|---|"]
    for spec_text in args.data:
        volume = open_spec(parse_data_spec(spec_text))
        truth = torch.from_numpy(np.ascontiguousarray(volume.to_numpy(), dtype=np.float32))
        span = float(truth.max() - truth.min())
        points = torch.rand(OFF_LATTICE_POINTS, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1
        between = sample_volume(truth, points)
        for kind in kinds:
            for fraction in fractions:
                for guide in guides:
                    path = model_path(args.models, spec_text, kind, fraction, args.seed, guide)
                    if not path.exists():
                        train(spec_text, kind, fraction, args.seed, path, guide)
                    row = measure(path, truth, points, between, span)
                    print(json.dumps({"volume": spec_text, "kind": kind, "fraction": fraction, "error_sampling": guide,
                                      **row}), flush=True)
                    lines.append(
                        f"| {Path(spec_text).name} | {kind} | {fraction:g} | "
                        f"{'default' if guide is None else f'{guide:g}'} | {row['psnr']:.2f} | "
                        f"{row['max_abs_error']:.3g} | {row['off_lattice_psnr']:.2f} | {row['parameters']:,} |"
                    )
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        atomic_write_text(args.out, table, "results table")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

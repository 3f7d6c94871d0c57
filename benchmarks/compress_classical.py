"""The classical compressors alone (SZ3, ZFP, SPERR, TTHRESH) at matched ratios on registered volumes that no
compressor made: `apmgsrn bench compress --models --ratios ...` on each, the turbulence volumes made first
when missing.

    python benchmarks/compress_classical.py --out bench-results/classical
    python benchmarks/compress_classical.py --volumes turbulence-vorticity-128 --ratios 100 300 1000 --out OUT

Each volume gets OUT/compress_NAME.csv, .md and .png (bench compress's files); a ratio a compressor cannot
reach is listed as skipped with what it can reach.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import torch

from apmgsrn.bench.compress import CompressPlan, run_compress
from apmgsrn.bench.datasets import CHECKOUT, benchmark_volume
from apmgsrn.choices import COMPRESSORS

# The registered volumes of 128^3 and larger that no compressor produced.
VOLUMES = ["turbulence-vorticity-128", "turbulence-velocity-x-128", "richtmyer-meshkov", "c60"]
RATIOS = [30, 100, 300, 1000, 3000, 10000]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--volumes", nargs="+", default=VOLUMES, help="registered names (bench/datasets.py)")
    parser.add_argument("--ratios", nargs="+", type=float, default=RATIOS)
    parser.add_argument("--compressors", nargs="+", choices=COMPRESSORS, default=list(COMPRESSORS))
    parser.add_argument("--query-points", type=int, default=2**20)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    for name in args.volumes:
        volume = benchmark_volume(name)
        if not volume.path().exists() and volume.make:
            print(f"making {name}: {volume.make}", flush=True)
            subprocess.run([sys.executable, *volume.make.split()[1:]], cwd=CHECKOUT, check=True)
        plan = CompressPlan(volume.spec(), models=(), compressors=tuple(args.compressors),
                            ratios=tuple(args.ratios), query_points=args.query_points)
        report = run_compress(plan, args.out, torch.device("cpu"))
        print(report.markdown.read_text())
        for reason in report.skipped:
            print(f"note: skipped {reason}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

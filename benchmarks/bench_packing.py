"""Packed model files against float32 ones (issue 15): bytes, ratio and PSNR cost on real volumes.

For every ``MODEL=VOLUME[:VARIABLE]`` pair given, the trained float32 model is packed in each mode asked
(``psnr0.1``: steps from each tensor's effect on the output at a 0.1 dB budget, the default of ``pack``;
``bitsB``: a fixed bit width B; ``boundS``: the default packing plus ``--max-error`` at a share S of the
value range), and the table gives the float32 file's bytes, the packed file's bytes, how many times
smaller it is, both PSNRs over every voxel and the cost. Nothing is timed. Writes
``docs/results_packing.md`` (the table and the command line) and ``benchmarks/results/packing.csv``.

Usage::

    python benchmarks/bench_packing.py --modes psnr0.1,bits8 \\
        /tmp/models/hcci.apmgsrn=../shared/data/hcci_oh_187.nc:oh ...
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from pathlib import Path

import torch

import apmgsrn
from apmgsrn.bench.datasets import open_spec, parse_data_spec
from apmgsrn.io import SourceInfo
from apmgsrn.training.packing import PackConfig, pack_field

REPO = Path(__file__).resolve().parents[1]
COLUMNS = ("volume", "shape", "mode", "float32_bytes", "packed_bytes", "smaller", "ratio_stored", "float32_psnr",
           "packed_psnr", "psnr_cost", "max_abs_error", "bound", "corrected_voxels", "correction_bytes", "seconds")


def mode_config(mode: str, span: float) -> PackConfig:
    """``psnr0.1`` / ``bits8`` / ``bound0.01`` -> the packing of that mode."""
    if mode.startswith("psnr"):
        return PackConfig(psnr_loss=float(mode[4:]))
    if mode.startswith("bits"):
        return PackConfig(bits=int(mode[4:]))
    if mode.startswith("bound"):
        return PackConfig(max_error=float(mode[5:]) * span)
    raise SystemExit(f"unknown mode {mode!r}: psnrDB, bitsB or boundSHARE")


def measure(model_path: Path, spec_text: str, mode: str) -> dict:
    spec = parse_data_spec(spec_text)
    volume = open_spec(spec)
    truth = volume.to_numpy()
    model = apmgsrn.load(model_path)
    span = float(truth.max() - truth.min())
    start = time.perf_counter()
    result = pack_field(model.field, truth, mode_config(mode, span), SourceInfo.of_volume(volume),
                        model.description.training)
    report = result.report
    bounded = report.get("max_error") is not None
    # The correction's two sections, as the file stores them.
    correction = sum(len(part) for part in result.correction.encode()[:2]) if bounded else 0
    return {
        "volume": spec.label, "shape": "x".join(str(s) for s in reversed(truth.shape)), "mode": mode,
        "float32_bytes": model.description.file_bytes, "packed_bytes": result.file_bytes,
        "smaller": model.description.file_bytes / result.file_bytes,
        "ratio_stored": volume.stored_bytes / result.file_bytes,
        "float32_psnr": report["float32_psnr"],
        "packed_psnr": report["bounded_psnr"] if bounded else report["psnr"],
        "psnr_cost": report["psnr_cost"],
        "max_abs_error": report["bounded_max_abs_error"] if bounded else report["max_abs_error"],
        "bound": report.get("max_error"), "corrected_voxels": report.get("corrected_voxels"),
        "correction_bytes": correction, "seconds": time.perf_counter() - start,
    }


def table(rows: list[dict]) -> str:
    lines = ["| volume | x*y*z | mode | float32 file | packed file | smaller | ratio vs stored | PSNR float32 | "
             "PSNR packed | cost dB | max abs error |",
             "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['volume']} | {r['shape']} | {r['mode']} | {r['float32_bytes']:,} | {r['packed_bytes']:,} | "
                     f"{r['smaller']:.2f}x | {r['ratio_stored']:.0f}:1 | {r['float32_psnr']:.2f} | "
                     f"{r['packed_psnr']:.2f} | {r['psnr_cost']:.3f} | {r['max_abs_error']:.4g} |")
    return "\n".join(lines)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("pairs", nargs="+", metavar="MODEL=VOLUME[:VARIABLE]")
    parser.add_argument("--modes", default="psnr0.1", help="comma-separated: psnrDB, bitsB, boundSHARE")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--csv", default=str(REPO / "benchmarks" / "results" / "packing.csv"))
    parser.add_argument("--doc", default=str(REPO / "docs" / "results_packing.md"))
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    for pair in args.pairs:
        model, _, spec = pair.partition("=")
        for mode in args.modes.split(","):
            row = measure(Path(model), spec, mode)
            rows.append(row)
            print(f"{row['volume']:<40} {mode:<10} {row['float32_bytes']:>8} -> {row['packed_bytes']:>7} B "
                  f"({row['smaller']:.2f}x), PSNR {row['float32_psnr']:.2f} -> {row['packed_psnr']:.2f} "
                  f"({row['seconds']:.0f} s)", flush=True)
    with open(args.csv, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=COLUMNS)
        writer.writeheader()
        writer.writerows(rows)
    command = "python benchmarks/bench_packing.py " + " ".join(sys.argv[1:])
    Path(args.doc).write_text(
        "# Packed model files against float32 files (generated by benchmarks/bench_packing.py)\n\n"
        "Every PSNR and maximum error is over every voxel of the volume, in data units. `smaller`: float32 file "
        "bytes / packed file bytes (both whole files, description included). `ratio vs stored`: the volume's "
        "stored bytes / packed file bytes.\n\n" + table(rows) + f"\n\nCommand:\n\n```\n{command}\n```\n")
    print(table(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())

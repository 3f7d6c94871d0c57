"""One model for a whole simulation run against one small model per step (issue 16).

    python benchmarks/bench_time_series.py baseline --threads 1   # 30 independent small models -> CSV
    python benchmarks/bench_time_series.py series --threads 1     # one time-series model -> CSV
    python benchmarks/bench_time_series.py report                 # docs/time_series_results.md + chart

Protocol (REFERENCE.md, CPU): 2,000 iterations x 32,768 points, lr 0.01, seed 0, the small preset, PSNR
over every voxel of each step at native resolution. Rows are appended as they finish, so a killed run
continues where it stopped; each row records the 1-minute load average of the machine when it ended.
"""

from __future__ import annotations

import argparse
import csv
import os
import platform
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
SERIES = ROOT.parent / "shared" / "data" / "viscous_fingers_run01"
RESULTS = ROOT / "benchmarks" / "results"
BASELINE_CSV = RESULTS / "time_series_baseline.csv"
BASELINE_FIELDS = ["step", "file", "psnr", "max_abs_error", "seconds", "iterations", "model_bytes", "parameters",
                   "threads", "load_average", "cpu"]


def _cpu() -> str:
    return platform.processor() or platform.machine()


def _done_rows(path: Path) -> list[dict]:
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _append(path: Path, fields: list[str], row: dict) -> None:
    new = not path.exists()
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=fields)
        if new:
            writer.writeheader()
        writer.writerow(row)


def run_baseline(args: argparse.Namespace) -> None:
    """One independent small model per step, trained on that step alone under the protocol."""
    from apmgsrn.data import open_volume
    from apmgsrn.models.registry import preset_config
    from apmgsrn.training.fit import fit_volume
    from apmgsrn.training.trainer import TrainConfig

    files = sorted(p for p in Path(args.data).iterdir() if p.suffix == ".vti")
    done = {row["file"] for row in _done_rows(args.csv)}
    config = TrainConfig(iterations=args.iterations, batch_size=args.batch_size, lr=0.01, seed=0)
    with tempfile.TemporaryDirectory() as tmp:
        for step, path in enumerate(files):
            if path.name in done:
                continue
            volume = open_volume(path)
            result = fit_volume(volume, preset_config("apmgsrn", "small"), config, Path(tmp) / "m.apmgsrn",
                                torch.device("cpu"), progress=False)
            row = {"step": step, "file": path.name, "psnr": f"{result.psnr:.4f}",
                   "max_abs_error": f"{result.max_abs_error:.6g}", "seconds": f"{result.seconds:.2f}",
                   "iterations": result.iterations, "model_bytes": result.model_bytes,
                   "parameters": result.field.parameter_count(), "threads": torch.get_num_threads(),
                   "load_average": f"{os.getloadavg()[0]:.2f}", "cpu": _cpu()}
            _append(args.csv, BASELINE_FIELDS, row)
            print(" ".join(f"{k}={v}" for k, v in row.items() if k != "cpu"), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    base = sub.add_parser("baseline", help="one small model per step")
    base.add_argument("--csv", type=Path, default=BASELINE_CSV)
    for p in (base,):
        p.add_argument("--data", type=Path, default=SERIES)
        p.add_argument("--threads", type=int, default=1)
        p.add_argument("--iterations", type=int, default=2000)
        p.add_argument("--batch-size", type=int, default=32768)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    if args.command == "baseline":
        run_baseline(args)
    print(f"done in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()

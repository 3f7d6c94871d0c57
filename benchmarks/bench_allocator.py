"""Training and decoding speed under three settings of glibc's allocator (apmgsrn.allocator).

Each run is a fresh process (the allocator's settings are per process): glibc's own defaults; what apmgsrn set
before, and only where ``train_prepared`` ran (a 1 GB mmap threshold and a 2 GB trim threshold, which this glibc
accepts: the same effect as now); and what it sets now, on ``import apmgsrn`` (``keep_freed_memory``). Work: a hybrid small model's iterations on a
viscous-finger step (as a time series' step fine-tunes them: half the batch, voxel points drawn where it is
wrong; and as a single model: the CPU protocol's batch, uniform draws), an APMGSRN small model's, and one
measurement of the error at every voxel (what guides the draws; also what ``eval`` does: since the hybrid's fused
CPU kernel it allocates nothing of size, so the allocator no longer matters there). Median of the repeats; minor
page faults per unit of work.

    python benchmarks/bench_allocator.py --threads 1 --out docs/benchmarks_allocator.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data" / "viscous_fingers_run01" / "035_density_035_064_2.0.vti"
BUNDLED = ROOT / "tests" / "data" / "viscous_fingers_run01"
MODES = {
    "glibc defaults": "",
    "apmgsrn before": ("import ctypes; libc = ctypes.CDLL('libc.so.6'); libc.mallopt(-3, 1 << 30); "
                       "libc.mallopt(-1, ctypes.c_int(2**31 - 1))"),
    "apmgsrn now": "from apmgsrn.allocator import keep_freed_memory; assert keep_freed_memory()",
}
# name -> (model kind, batch, error-guided share, iterations); "measure" times the error guide's measurement.
WORK = {
    "hybrid step fine-tune (16,384 points, guided)": ("hybrid", 16384, 1.0, 200),
    "hybrid single model (32,768 points, uniform)": ("hybrid", 32768, 0.0, 100),
    "apmgsrn single model (32,768 points)": ("apmgsrn", 32768, 0.0, 100),
    "error at every voxel (64^3, the fused kernel)": ("hybrid", 0, 0.0, 20),
}


def data_file() -> Path:
    return SHARED if SHARED.exists() else sorted(BUNDLED.glob("*.vti"))[0]


def child(work: str, threads: int) -> dict:
    """Time one kind of work (run in its own process, after the mode's setup)."""
    import numpy as np
    import torch

    from apmgsrn.data.readers import open_volume
    from apmgsrn.models.field import NeuralField
    from apmgsrn.models.registry import preset_config, training_defaults
    from apmgsrn.training.points import ErrorGuide
    from apmgsrn.training.trainer import TrainConfig, Trainer

    torch.set_num_threads(threads)
    kind, batch, guided, units = WORK[work]
    values = torch.from_numpy(np.asarray(open_volume(data_file()).read(), dtype=np.float32))
    values = (values - values.min()) / (values.max() - values.min())
    field = NeuralField(preset_config(kind, "small"), fit_min=0, fit_max=1, volume_shape=tuple(values.shape),
                        generator=torch.Generator().manual_seed(0))

    def faults() -> int:
        return resource.getrusage(resource.RUSAGE_SELF).ru_minflt

    if batch == 0:
        guide, generator = ErrorGuide(values), torch.Generator().manual_seed(0)
        guide.measure(field.normalized, generator)
        began, before = time.perf_counter(), faults()
        for _ in range(units):
            guide.measure(field.normalized, generator)
    else:
        defaults = training_defaults(kind)
        config = TrainConfig(iterations=units + 10, batch_size=batch, seed=0, history_every=None,
                             voxel_fraction=defaults.get("voxel_fraction", 0.0), error_sampling=guided)
        trainer = Trainer(field, values, config, None, {}, [])
        for _ in range(10):  # warm-up: kernels built, first blocks mapped
            trainer.step()
            trainer.state.iteration += 1
        began, before = time.perf_counter(), faults()
        for _ in range(units):
            trainer.step()
            trainer.state.iteration += 1
    seconds = time.perf_counter() - began
    return {"ms": 1e3 * seconds / units, "faults": (faults() - before) / units}


def run(mode: str, work: str, threads: int) -> dict:
    code = f"{MODES[mode]}\nimport json, sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n" \
           f"from bench_allocator import child\nprint(json.dumps(child({work!r}, {threads})))"
    env = {k: v for k, v in os.environ.items() if k not in ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_")}
    if mode != "apmgsrn now":
        env["GLIBC_TUNABLES"] = ""  # apmgsrn's import leaves the allocator alone
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    rows = []
    for work in WORK:
        timings = {}
        for _ in range(args.repeats):  # modes interleaved, so a change in the machine's load hits them alike
            for mode in MODES:
                timings.setdefault(mode, []).append(run(mode, work, args.threads))
        row = [work]
        for mode in MODES:
            ms = statistics.median(t["ms"] for t in timings[mode])
            faults = statistics.median(t["faults"] for t in timings[mode])
            row.append(f"{ms:.1f} ms, {faults:,.0f} faults")
        now = statistics.median(t["ms"] for t in timings["apmgsrn now"])
        row.append(" / ".join(f"{statistics.median(t['ms'] for t in timings[m]) / now:.2f}x"
                              for m in ("glibc defaults", "apmgsrn before")))
        rows.append(row)
        print(" | ".join(row), flush=True)
    unit = "per iteration (per measurement in the last row)"
    lines = ["# Training speed and glibc's allocator", "",
             f"Made by `python benchmarks/bench_allocator.py --threads {args.threads} --repeats {args.repeats}`"
             f" on {platform.machine()}, {os.cpu_count()} cores, {args.threads} torch thread(s), "
             f"load average {os.getloadavg()[0]:.2f} at the end; data: `{data_file().name}`; each cell the median "
             f"of {args.repeats} fresh processes, time {unit} and minor page faults per unit.", "",
             "| work | glibc defaults | apmgsrn before | apmgsrn now | now faster than defaults / before |",
             "|---|---|---|---|---|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    lines += ["", "See `src/apmgsrn/allocator.py` for what the settings are and why."]
    text = "\n".join(lines) + "\n"
    if args.out:
        args.out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()

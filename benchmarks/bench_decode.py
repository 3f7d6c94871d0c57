"""Decoding as a user decodes (issue 18): a trained model loaded with ``apmgsrn.load`` in a fresh process,
library defaults, 2^18 random points per call under ``torch.no_grad()``, beside the CPU's measured limit.
Models: APMGSRN's small and medium presets and the hybrid's (``--models``).

Rows, each in its own fresh process (what ``import apmgsrn`` sets, nothing more):
- ``default``: ``apmgsrn.load(FILE)`` then ``model(points)``: the library's own path (float32, as ``decode``
  and ``eval`` run by default; on CPUs the fused encoder + decoder kernel).
- ``auto``: ``apmgsrn.load(FILE, precision="auto")``: bfloat16 hidden layers where the CPU multiplies them
  natively (AVX512-BF16 or AMX) and the model has no fused float32 kernel, else the same as ``default`` (until
  2026-11-27 it chose bfloat16 on such CPUs for every model: the ``bfloat16`` row).
- ``float32 unfused``: the path before the fused kernels (issue 18 for APMGSRN, 2026-11-27 for the hybrid):
  the encoder's CPU kernel, then the decoder's matrix products in PyTorch
  (``field.decoder(field.encoder(points))``).
- ``bfloat16``: ``apmgsrn.load(FILE, precision="bfloat16")``: hidden layers in bfloat16 (fast only where the
  CPU has AVX512-BF16 or AMX; emulated, slowly, elsewhere).
- ``encoder only``: the encoder's CPU kernel alone (features, no decoder): the ceiling of any
  decoding path with this encoder on these points.

PSNR: each row's values on the training volume's whole lattice against the volume (value range of the
volume), so the cost of a faster path shows in dB. Limit: GFLOP/s of a float32 and a bfloat16 matrix
product ``[65536, 64] x [64, 64]`` on the same threads, divided by the decoder's dense FLOP per point (the
fused kernel skips zero inputs, so it may pass that line; the encoder's gathers are not counted).

    python benchmarks/bench_decode.py                          # prints the table
    python benchmarks/bench_decode.py --out docs/benchmarks_decode.md
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared" / "data"
VOLUME = ("c60_128x128x128_uint8.raw", (128, 128, 128))
PRESETS = ("small", "medium")
KINDS = ("apmgsrn", "hybrid")
ROWS = ("default", "auto", "float32 unfused", "bfloat16", "encoder only")
POINTS = 2**18


def trained_model(folder: Path, kind: str, preset: str, iterations: int) -> Path:
    """A ``kind`` model of ``preset`` trained ``iterations`` on the c60 volume with the command line (made once)."""
    path = folder / f"c60_{preset}_{iterations}.apmgsrn" if kind == "apmgsrn" else \
        folder / f"c60_{kind}_{preset}_{iterations}.apmgsrn"
    if not path.exists():
        name, shape = VOLUME
        command = [sys.executable, "-m", "apmgsrn", "train", str(SHARED / name), "--shape",
                   ",".join(map(str, shape)), "--dtype", "uint8", "--model", kind, "--preset", preset,
                   "--iterations", str(iterations), "--device", "cpu", "--out", str(path)]
        print("$", " ".join(command), flush=True)
        subprocess.run(command, check=True, capture_output=True, env=dict(os.environ, PYTHONPATH=str(REPO / "src")))
    return path


def _median_seconds(fn, repeats: int) -> tuple[float, float]:
    """Median wall seconds and median CPU seconds (all threads of this process) of a call."""
    for _ in range(3):
        fn()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return statistics.median(wall), statistics.median(cpu)


def child_decode(model_path: str, row: str, repeats: int) -> dict:
    import numpy as np

    import apmgsrn
    import torch
    from apmgsrn.inference.decode import decode_array

    model = apmgsrn.load(model_path, **({"precision": row} if row in ("auto", "bfloat16") else {}))
    field = model.field
    if row == "encoder only":
        run = field.encoder
    elif row == "float32 unfused":
        def run(points):
            normalized = field.decoder(field.encoder(points))
            return field.transform.inverse(normalized * (field.fit_max - field.fit_min) + field.fit_min)
    else:
        run = model
    points = torch.rand(POINTS, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    with torch.no_grad():
        seconds, cpu_seconds = _median_seconds(lambda: run(points), repeats)
    config = field.config
    widths = [field.encoder.out_features] + [config.decoder.width] * config.decoder.hidden_layers + [1]
    flop = 2 * sum(a * b for a, b in zip(widths[:-1], widths[1:]))
    result = {"mpps": POINTS / seconds / 1e6, "cpu_mpps": POINTS / cpu_seconds / 1e6, "psnr": None, "flop": flop,
              "threads": torch.get_num_threads()}
    if row == "encoder only":
        return result  # features, not values: no PSNR

    class Callable(torch.nn.Module):  # decode_array wants a module: the row's path on the lattice
        def __init__(self):
            super().__init__()
            self.anchor = torch.nn.Parameter(torch.zeros(1), requires_grad=False)

        def forward(self, p):
            return run(p)

    name, shape = VOLUME
    truth = np.fromfile(SHARED / name, dtype=np.uint8).reshape(shape).astype(np.float64)
    decoded = decode_array(Callable(), shape).astype(np.float64)
    mse = float(np.mean((decoded - truth) ** 2))
    value_range = float(truth.max() - truth.min())
    result["psnr"] = 10 * np.log10(value_range**2 / mse)
    return result


def child_matmul(repeats: int) -> dict:
    import torch

    out = {}
    for name, dtype in (("float32", torch.float32), ("bfloat16", torch.bfloat16)):
        a = torch.rand(65536, 64).to(dtype)
        b = torch.rand(64, 64).to(dtype)
        seconds, cpu_seconds = _median_seconds(lambda: a @ b, repeats)
        out[name] = 2 * 65536 * 64 * 64 / seconds / 1e9
        out[name + "_cpu"] = 2 * 65536 * 64 * 64 / cpu_seconds / 1e9
    out["threads"] = torch.get_num_threads()
    return out


def in_fresh_process(*arguments: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO / "src"))
    result = subprocess.run([sys.executable, __file__, *arguments], env=env, check=True, capture_output=True,
                            text=True)
    return json.loads(result.stdout.strip().splitlines()[-1])


def cpu_name() -> str:
    try:
        return next(line.split(":", 1)[1].strip() for line in open("/proc/cpuinfo") if line.startswith("model name"))
    except (OSError, StopIteration):
        return platform.processor() or platform.machine()


def cpu_flags() -> str:
    try:
        flags = next(line.split() for line in open("/proc/cpuinfo") if line.startswith("flags"))
    except (OSError, StopIteration):
        return "unknown"
    wanted = ("avx2", "avx512f", "avx512_bf16", "amx_bf16")
    return ", ".join(f"{f} {'yes' if f in flags else 'no'}" for f in wanted)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--child", choices=("decode", "matmul"))
    parser.add_argument("--model", default="")
    parser.add_argument("--row", choices=ROWS, default="default")
    parser.add_argument("--repeats", type=int, default=10, help="timed calls per row (median)")
    parser.add_argument("--iterations", type=int, default=500, help="training iterations of the models")
    parser.add_argument("--models-dir", default=str(Path(tempfile.gettempdir()) / "apmgsrn-bench-models"))
    parser.add_argument("--out", default=None, help="markdown file to write")
    parser.add_argument("--models", default=",".join(KINDS), help="model kinds, comma-separated")
    args = parser.parse_args()
    if args.child == "decode":
        print(json.dumps(child_decode(args.model, args.row, args.repeats)))
        return
    if args.child == "matmul":
        print(json.dumps(child_matmul(args.repeats * 5)))
        return
    folder = Path(args.models_dir)
    folder.mkdir(parents=True, exist_ok=True)
    kinds = [kind for kind in args.models.split(",") if kind]
    models = {(kind, preset): trained_model(folder, kind, preset, args.iterations) for kind in kinds for preset in PRESETS}
    load_start = os.getloadavg()[0]
    limits = in_fresh_process("--child", "matmul", "--repeats", str(args.repeats))
    lines = [f"Matrix product [65536, 64] x [64, 64], {limits['threads']} threads: float32 {limits['float32']:.1f} "
             f"GFLOP/s ({limits['float32_cpu']:.1f} per CPU-second), bfloat16 {limits['bfloat16']:.1f} GFLOP/s "
             f"({limits['bfloat16_cpu']:.1f} per CPU-second).", "",
             "| model | preset | path | M points/s | M points per CPU-s | PSNR dB (128^3 lattice) | decoder FLOP/point | "
             "limit f32 M/s | limit bf16 M/s | limit f32 per CPU-s | limit bf16 per CPU-s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for (kind, preset), model in models.items():
        for row in ROWS:
            r = in_fresh_process("--child", "decode", "--model", str(model), "--row", row,
                                 "--repeats", str(args.repeats))
            psnr = "-" if r["psnr"] is None else f"{r['psnr']:.2f}"
            line = (f"| {kind} | {preset} | {row} | {r['mpps']:.2f} | {r['cpu_mpps']:.2f} | {psnr} | {r['flop']:,} | "
                    f"{limits['float32'] * 1e3 / r['flop']:.2f} | {limits['bfloat16'] * 1e3 / r['flop']:.2f} | "
                    f"{limits['float32_cpu'] * 1e3 / r['flop']:.2f} | {limits['bfloat16_cpu'] * 1e3 / r['flop']:.2f} |")
            lines.append(line)
            print(line, flush=True)
    load_end = os.getloadavg()[0]
    if args.out:
        import torch

        text = f"""# Decoding as a user decodes (issue 18)

Machine: {cpu_name()}, {os.cpu_count()} cores ({cpu_flags()}), torch {torch.__version__}, Python
{platform.python_version()}; 1-minute load average {load_start:.1f} at the start, {load_end:.1f} at the end (the
machine is shared with other jobs: a load above 2 means the cores were not ours alone, and every figure
here is lower than on an idle machine). Command: `python benchmarks/bench_decode.py --repeats {args.repeats}
--models {args.models} --out {args.out}`. No GPU was lent to this session: GPU rows are left for a session that has one.

Models: the small and medium presets of {", ".join(kinds)} trained {args.iterations} iterations on c60 128^3
(uint8) with `apmgsrn train`; each row in a fresh process, `apmgsrn.load(FILE)` with the library's defaults (no
allocator or thread settings of the benchmark's own), {POINTS:,} random points per call under `torch.no_grad()`, median of
{args.repeats} calls after 3 warm-ups. The authors' code on the same kind of 2-core CPU: 0.96 M (small) and
0.77 M (medium) points/s (REFERENCE.md), for APMGSRN.

{chr(10).join(lines)}

"per CPU-s": points per second of CPU time this process got (all its threads), which the other jobs on
the machine disturb far less than wall time; on an idle 2-core machine the wall rate would be up to twice
it. "limit": the matrix-product rate divided by the decoder's dense FLOP per point: what a dense decoder
could reach if the encoder cost nothing. The fused kernel adds only the non-zero inputs of each layer (zero
features outside a grid, ReLU zeros), so it is not bound by that line. "encoder only": the grids' look-ups
alone, no decoder (PSNR "-": features are not values); where it is close to `default`, the encoder's
gathers from the grids bound the whole path (APMGSRN's medium preset samples 16 grids of 2 x 32^3 values, 8
corners each, at random points; encoding blocks of tiles grid by grid, so that a grid stays in cache,
gained at most 8 % here, so it is the number and latency of the gathers rather than cache capacity).
"""
        Path(args.out).write_text(text)
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()

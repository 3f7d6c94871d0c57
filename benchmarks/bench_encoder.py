"""Benchmark of the multi-grid encoder backends (issue 7): time, throughput and peak memory.

Prints tables and writes them as a Markdown section of ``docs/benchmarks_encoder.md`` (one section per
device kind, replaced on every run, so a CPU run and a GPU run can fill the same file), plus the chart
``docs/images/encoder_scaling.png`` (time per training iteration and forward peak memory against the
number of grids ``M``, reference ("before") and fused backend ("after")).

What is measured (all on uniformly random points in ``[-1, 1]^3``, maps at the SPEC initialisation):
- encoder forward and forward+backward (gradient for the grids) per backend, preset and batch size;
- peak memory of one encoder forward pass (CPU: resident-set high-water mark with every large block
  mmapped, so freed memory leaves the count; CUDA: ``max_memory_allocated``), output included;
- decode throughput of the whole model (encoder + 2 x 64 decoder), no gradients;
- one reconstruction training step (encoder + decoder forward, MSE, backward, Adam step) and one
  density step (feature density forward and backward); the trainer's ground-truth sampling is not in
  these figures;
- on CUDA also: the training step captured in a CUDA graph, and decoding ray samples of a 512 x 512
  image with 256 samples per ray (field evaluation only: an upper bound on render frame rate).

Usage::

    python benchmarks/bench_encoder.py                 # CPU, all threads torch uses
    python benchmarks/bench_encoder.py --device cuda   # GPU section
    python benchmarks/bench_encoder.py --quick         # fewer repetitions, no chart
"""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import math
import os
import platform
import re
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import nn

from apmgsrn.ops import multigrid
from apmgsrn.ops.multigrid import feature_density, multigrid_features

REPO = Path(__file__).resolve().parents[1]
PRESETS = {"small": (16, 1, 16), "medium": (16, 2, 32), "large": (16, 4, 64)}
AUTHORS_DECODE = {"small": 0.96e6, "medium": 0.77e6}  # their code, this CPU, 2 threads (REFERENCE.md)
AUTHORS_ITERATION_MS = 68.0  # their code, small preset, 32,768 points, this CPU


# ----------------------------------------------------------------------------------------- helpers


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_ms(fn, device: torch.device, repeats: int, warmup: int = 3) -> float:
    """Median wall time of ``fn()`` in milliseconds, device synchronised."""
    for _ in range(warmup):
        fn()
    sync(device)
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        sync(device)
        samples.append((time.perf_counter() - start) * 1e3)
    return statistics.median(samples)


_libc = None


def _mallopt(param: int, value: int) -> None:
    global _libc
    try:
        _libc = _libc or ctypes.CDLL("libc.so.6")
        _libc.mallopt(param, value)
    except (OSError, AttributeError):
        pass


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3


def exact_memory_mode() -> None:
    """Make every block over 64 KiB its own mmap, so a free returns it to the OS at once and the
    resident-set high-water mark is the true peak of live memory. Set before any large allocation:
    a large free block already in the heap would be reused without counting."""
    _mallopt(M_MMAP_THRESHOLD, 64 << 10)
    _mallopt(M_TRIM_THRESHOLD, 64 << 10)


def fast_allocation_mode() -> None:
    """As the trainer: freed blocks stay mapped, so large allocations do not page-fault every time."""
    _mallopt(M_MMAP_THRESHOLD, 1 << 30)
    _mallopt(M_TRIM_THRESHOLD, 1 << 31)


def _status_kib(field: str) -> int:
    text = Path("/proc/self/status").read_text()
    return int(re.search(rf"^{field}:\s+(\d+) kB", text, re.M).group(1))


def peak_memory_mib(fn, device: torch.device) -> float:
    """Peak memory of ``fn()`` above what was allocated before it, in MiB (its result included)."""
    if device.type == "cuda":
        sync(device)
        torch.cuda.reset_peak_memory_stats(device)
        base = torch.cuda.memory_allocated(device)
        result = fn()
        sync(device)
        peak = torch.cuda.max_memory_allocated(device) - base
        del result
        return peak / 2**20
    fn()  # warm: lazily built kernels and caches are not the op's memory
    try:
        Path("/proc/self/clear_refs").write_text("5")  # reset the high-water mark
    except OSError:
        return float("nan")
    base = _status_kib("VmRSS")
    result = fn()
    peak = _status_kib("VmHWM") - base
    del result
    return peak / 1024


@dataclass
class Model:
    """An APMGSRN-shaped model: grids, maps (SPEC initialisation) and a 2 x 64 bias-free decoder."""

    grids: nn.Parameter
    matrices: torch.Tensor
    translations: torch.Tensor
    decoder: nn.Sequential

    @classmethod
    def build(cls, m: int, c: int, res: int, device: torch.device, seed: int = 0) -> "Model":
        g = torch.Generator().manual_seed(seed)
        grids = nn.Parameter((torch.rand(m, c, res, res, res, generator=g) * 2e-4 - 1e-4).to(device))
        matrices = (torch.eye(3) + torch.randn(m, 3, 3, generator=g) * 0.05).to(device)
        translations = (torch.randn(m, 3, generator=g) * 0.05).to(device)
        decoder = nn.Sequential(
            nn.Linear(m * c, 64, bias=False), nn.ReLU(), nn.Linear(64, 64, bias=False), nn.ReLU(),
            nn.Linear(64, 1, bias=False),
        ).to(device)
        return cls(grids, matrices, translations, decoder)

    def encode(self, points: torch.Tensor, backend: str) -> torch.Tensor:
        return multigrid_features(points, self.matrices, self.translations, self.grids, backend=backend)

    def __call__(self, points: torch.Tensor, backend: str) -> torch.Tensor:
        return self.decoder(self.encode(points, backend))

    def parameters(self) -> list[nn.Parameter]:
        return [self.grids, *self.decoder.parameters()]


def random_points(n: int, device: torch.device, seed: int = 1) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 3, generator=g) * 2 - 1).to(device)


def fmt(value: float, digits: int = 2) -> str:
    if value != value:  # NaN
        return "n/a"
    if value >= 100:
        return f"{value:,.0f}"
    return f"{value:.{digits}f}"


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return "\n".join(lines)


def machine_description(device: torch.device) -> str:
    if device.type == "cuda":
        name = torch.cuda.get_device_name(device)
        return f"{name}, torch {torch.__version__}, CUDA {torch.version.cuda}"
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (
        f"{cpu}, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads, torch {torch.__version__}, "
        f"Python {platform.python_version()}; 1-minute load average at start {load:.2f}"
    )


# ------------------------------------------------------------------------------------- measurements


def measure_memory(device, backends, sizes, counts, scaling_n):
    """Forward peak memory of every configuration, before any timing (see :func:`exact_memory_mode`)."""
    memory = {}
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        model = Model.build(m, c, res, device)
        for n in sizes:
            points = random_points(n, device)
            for backend in backends:
                memory[(backend, preset, n)] = peak_memory_mib(encode_fn(model, points, backend), device)
    points = random_points(scaling_n, device)
    for m in counts:
        model = Model.build(m, 1, 16, device)
        for backend in backends:
            memory[("M", backend, m)] = peak_memory_mib(encode_fn(model, points, backend), device)
    return memory


def encode_fn(model: "Model", points: torch.Tensor, backend: str):
    def forward():
        with torch.no_grad():
            return model.encode(points, backend)

    return forward


def encoder_table(device, backends, repeats, sizes, memory):
    rows = []
    print("\nencoder: backend x preset x N")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        model = Model.build(m, c, res, device)
        for n in sizes:
            points = random_points(n, device)
            for backend in backends:

                def forward_backward():
                    out = model.encode(points, backend)
                    out.backward(torch.ones_like(out))
                    model.grids.grad = None

                fwd = time_ms(encode_fn(model, points, backend), device, repeats)
                fwd_bwd = time_ms(forward_backward, device, repeats)
                mem = memory[(backend, preset, n)]
                out_mib = n * m * c * 4 / 2**20
                row = [backend, preset, f"{n:,}", fmt(fwd), fmt(fwd_bwd), fmt(n / fwd / 1e3), fmt(mem, 1), fmt(out_mib, 1)]
                print("  " + " | ".join(row))
                rows.append(row)
    header = ["backend", "preset", "N", "forward ms", "fwd+bwd ms", "forward M points/s", "forward peak MiB", "output MiB"]
    return markdown_table(header, rows)


def train_step_fn(model: Model, points: torch.Tensor, target: torch.Tensor, backend: str):
    optimiser = torch.optim.Adam(model.parameters(), lr=0.01, betas=(0.9, 0.99))

    def step():
        optimiser.zero_grad(set_to_none=True)
        loss = torch.nn.functional.mse_loss(model(points, backend), target)
        loss.backward()
        optimiser.step()

    return step


def density_step_fn(model: Model, points: torch.Tensor, backend: str):
    matrices = model.matrices.clone().requires_grad_(True)
    translations = model.translations.clone().requires_grad_(True)
    optimiser = torch.optim.Adam([matrices, translations], lr=1e-3)
    density_backend = "torch" if backend == "torch" else "auto"
    error = torch.rand(points.shape[0], device=points.device)

    def step():
        optimiser.zero_grad(set_to_none=True)
        rho = feature_density(points, matrices, translations, backend=density_backend)
        rho = rho / rho.sum()
        target = torch.exp(error.mean() / (error + 1e-16) * torch.log(rho.detach() + 1e-16))
        target = target / target.sum()
        loss = (target * torch.log(target / rho + 1e-16)).mean()
        loss.backward()
        optimiser.step()

    return step


def training_table(device, backends, repeats, n):
    rows = []
    print(f"\ntraining steps, {n:,} points")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        points = random_points(n, device)
        target = torch.rand(n, 1, device=device)
        for backend in backends:
            model = Model.build(m, c, res, device)
            rec = time_ms(train_step_fn(model, points, target, backend), device, repeats)
            den = time_ms(density_step_fn(model, points, backend), device, repeats)
            row = [backend, preset, fmt(rec), fmt(den), fmt(rec + den)]
            print("  " + " | ".join(row))
            rows.append(row)
    header = ["backend", "preset", "reconstruction step ms", "density step ms", "sum ms"]
    return markdown_table(header, rows)


def decode_table(device, backends, repeats, batch, batches):
    rows = []
    print(f"\ndecode throughput, whole model, batches of {batch:,}")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        model = Model.build(m, c, res, device)
        points = random_points(batch * batches, device).split(batch)
        for backend in backends:

            def decode():
                with torch.no_grad():
                    for chunk in points:
                        model(chunk, backend)

            ms = time_ms(decode, device, repeats, warmup=1)
            rate = batch * batches / ms * 1e3
            authors = AUTHORS_DECODE.get(preset) if device.type == "cpu" else None
            ratio = fmt(rate / authors) + "x" if authors else "-"
            row = [backend, preset, fmt(rate / 1e6), ratio]
            print("  " + " | ".join(row))
            rows.append(row)
    header = ["backend", "preset", "M points/s", "vs authors' code (this CPU)"]
    return markdown_table(header, rows)


def scaling(device, backends, repeats, n, counts, memory):
    """Training step time and forward peak memory against M (C = 1, 16^3 grids)."""
    results = {b: {"ms": [], "mib": []} for b in backends}
    print(f"\nscaling with M, {n:,} points, 1 x 16^3 grids")
    points = random_points(n, device)
    target = torch.rand(n, 1, device=device)
    for m in counts:
        for backend in backends:
            model = Model.build(m, 1, 16, device)
            ms = time_ms(train_step_fn(model, points, target, backend), device, repeats)
            mib = memory[("M", backend, m)]
            results[backend]["ms"].append(ms)
            results[backend]["mib"].append(mib)
            print(f"  M={m:3d} {backend:7s} step {ms:8.2f} ms  forward peak {mib:8.1f} MiB")
    rows = []
    for i, m in enumerate(counts):
        row = [str(m)]
        for backend in backends:
            row += [fmt(results[backend]["ms"][i]), fmt(results[backend]["mib"][i], 1)]
        row.append(fmt(n * m * 4 / 2**20, 1))
        rows.append(row)
    header = ["M"] + [f"{b} {what}" for b in backends for what in ("step ms", "fwd peak MiB")] + ["N x M x C output MiB"]
    return markdown_table(header, rows), results


def draw_chart(path: Path, counts, results, n, device_label, output_mib):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_time, ax_mem) = plt.subplots(1, 2, figsize=(10, 4))
    labels = {"torch": "before: PyTorch reference", "cpu": "after: fused CPU kernel", "triton": "after: Triton"}
    for backend, res in results.items():
        ax_time.plot(counts, res["ms"], marker="o", label=labels.get(backend, backend))
        ax_mem.plot(counts, res["mib"], marker="o", label=labels.get(backend, backend))
    ax_mem.plot(counts, output_mib, linestyle="--", color="gray", label="N x M x C features alone")
    for ax in (ax_time, ax_mem):
        ax.set_xscale("log", base=2)
        ax.set_xticks(counts, [str(c) for c in counts])
        ax.set_xlabel("grids M (1 x 16^3 each)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    ax_time.set_ylabel(f"training step ms ({n:,} points)")
    ax_mem.set_ylabel("forward peak memory MiB")
    ax_time.set_title("time per iteration")
    ax_mem.set_title("memory of one forward pass")
    fig.suptitle(f"Multi-grid encoder scaling with M ({device_label})", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ----------------------------------------------------------------------------------------- CUDA only


def cuda_extras(device, repeats):
    """Graph-captured training step, big-batch decode in several precisions, ray-sample decoding."""
    lines = []
    n = 100_000
    rows = []
    print(f"\nCUDA training step, {n:,} points (reconstruction step captured in a CUDA graph)")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        for backend in ("torch", "triton"):
            model = Model.build(m, c, res, device)
            points = torch.empty(n, 3, device=device)
            target = torch.empty(n, 1, device=device)
            optimiser = torch.optim.Adam(model.parameters(), lr=0.01, betas=(0.9, 0.99), capturable=True)

            def step():
                points.uniform_(-1, 1)  # a fresh batch every replay
                target.copy_(points[:, :1])
                optimiser.zero_grad(set_to_none=False)
                loss = torch.nn.functional.mse_loss(model(points, backend), target)
                loss.backward()
                optimiser.step()

            eager = time_ms(step, device, repeats)
            stream = torch.cuda.Stream()
            stream.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(stream):
                for _ in range(3):
                    step()
            torch.cuda.current_stream().wait_stream(stream)
            graph = torch.cuda.CUDAGraph()
            try:
                with torch.cuda.graph(graph):
                    step()
                graphed = time_ms(graph.replay, device, repeats * 5)
            except Exception as err:  # noqa: BLE001 - report, do not abort the benchmark
                print(f"  graph capture failed for {backend}: {err}")
                graphed = float("nan")
            best = min(eager, graphed) if graphed == graphed else eager
            row = [backend, preset, fmt(eager, 3), fmt(graphed, 3), fmt(best * 50_000 / 1e3, 1)]
            print("  " + " | ".join(row))
            rows.append(row)
    lines.append(f"Training step, {n:,} random points, reconstruction step (forward, MSE, backward, Adam):")
    lines.append("")
    lines.append(markdown_table(["backend", "preset", "eager ms", "CUDA graph ms", "50,000 iterations s (best)"], rows))

    rows = []
    batch = 1 << 21
    print(f"\nCUDA decode, batches of {batch:,}")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        model = Model.build(m, c, res, device)
        points = random_points(batch, device)
        for label, backend, grids_dtype, mlp_dtype in (
            ("reference, fp32", "torch", torch.float32, None),
            ("triton, fp32", "triton", torch.float32, None),
            ("triton, fp32 encoder only", "triton", torch.float32, "none"),
            ("triton, fp16 grids + bf16 MLP", "triton", torch.float16, torch.bfloat16),
            ("triton, fp16 grids encoder only", "triton", torch.float16, "none"),
        ):
            grids = model.grids.detach().to(grids_dtype)

            def decode():
                with torch.no_grad():
                    feats = multigrid_features(points, model.matrices, model.translations, grids, backend=backend)
                    if mlp_dtype == "none":
                        return feats
                    if mlp_dtype is None:
                        return model.decoder(feats)
                    with torch.autocast("cuda", dtype=mlp_dtype):
                        return model.decoder(feats)

            ms = time_ms(decode, device, repeats)
            row = [label, preset, fmt(batch / ms / 1e6, 2)]
            print("  " + " | ".join(row))
            rows.append(row)
    lines.append("")
    lines.append(f"Decode throughput, random points, batches of {batch:,}:")
    lines.append("")
    lines.append(markdown_table(["path", "preset", "G points/s"], rows))

    rows = []
    width = height = 512
    samples = 256
    print(f"\nCUDA ray-sample decoding, {width}x{height}, {samples} samples per ray")
    for preset in ("small", "medium"):
        m, c, res = PRESETS[preset]
        model = Model.build(m, c, res, device)
        # Orthographic rays along z through the box, ray-major sample order as a marcher produces.
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height, device=device), torch.linspace(-1, 1, width, device=device), indexing="ij")
        zs = torch.linspace(-1, 1, samples, device=device)
        chunk_rays = 4096
        rays = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1)  # [R, 2]
        for label, grids_dtype, mlp_dtype in (("fp32", torch.float32, None), ("fp16 grids + bf16 MLP", torch.float16, torch.bfloat16)):
            grids = model.grids.detach().to(grids_dtype)

            def frame():
                with torch.no_grad():
                    for start in range(0, rays.shape[0], chunk_rays):
                        r = rays[start : start + chunk_rays]
                        pts = torch.cat(
                            [r[:, None, :].expand(-1, samples, 2), zs[None, :, None].expand(r.shape[0], -1, 1)], dim=2
                        ).reshape(-1, 3)  # [R * S, 3]
                        feats = multigrid_features(pts, model.matrices, model.translations, grids, backend="triton")
                        if mlp_dtype is None:
                            model.decoder(feats)
                        else:
                            with torch.autocast("cuda", dtype=mlp_dtype):
                                model.decoder(feats)

            ms = time_ms(frame, device, max(3, repeats // 2), warmup=1)
            row = [preset, label, fmt(ms, 1), fmt(1e3 / ms, 1)]
            print("  " + " | ".join(row))
            rows.append(row)
    lines.append("")
    lines.append(
        f"Field evaluation for one {width}x{height} frame, {samples} samples per ray ({width * height * samples:,} "
        "samples, chunks of 4,096 rays; no compositing, empty-space skipping or early termination, so an upper "
        "bound on the frame cost of the field):"
    )
    lines.append("")
    lines.append(markdown_table(["preset", "precision", "ms per frame", "frames/s"], rows))
    return "\n".join(lines)


def triton_block_sweep(device, repeats):
    """Time the Triton forward and backward for a few block sizes (to choose the default)."""
    from apmgsrn.ops import multigrid_triton as mt

    original = mt._block
    rows = []
    print("\nTriton block sweep (medium, 2^21 points)")
    m, c, res = PRESETS["medium"]
    model = Model.build(m, c, res, device)
    points = random_points(1 << 21, device)
    try:
        for block, warps in ((128, 4), (256, 4), (512, 4), (512, 8), (1024, 8)):
            mt._block = lambda ch, b=block, w=warps: (b, triton_next_pow2(ch), w)

            def forward():
                with torch.no_grad():
                    return model.encode(points, "triton")

            def forward_backward():
                out = model.encode(points, "triton")
                out.backward(torch.ones_like(out))
                model.grids.grad = None

            row = [str(block), str(warps), fmt(time_ms(forward, device, repeats), 3), fmt(time_ms(forward_backward, device, repeats), 3)]
            print("  " + " | ".join(row))
            rows.append(row)
    finally:
        mt._block = original
    return markdown_table(["block", "warps", "forward ms", "fwd+bwd ms"], rows)


def triton_next_pow2(x: int) -> int:
    return 1 << max(0, math.ceil(math.log2(x)))


# ---------------------------------------------------------------------------------------------- main


def write_section(path: Path, key: str, body: str) -> None:
    """Replace (or append) the section between ``<!-- bench_encoder:key -->`` markers."""
    begin, end = f"<!-- bench_encoder:{key} -->", f"<!-- /bench_encoder:{key} -->"
    text = path.read_text() if path.exists() else "# Multi-grid encoder benchmarks\n\nWritten by `benchmarks/bench_encoder.py`.\n"
    block = f"{begin}\n{body.rstrip()}\n{end}"
    if begin in text and end in text:
        text = text[: text.index(begin)] + block + text[text.index(end) + len(end) :]
    else:
        text = text.rstrip() + "\n\n" + block + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--threads", type=int, default=None, help="torch threads (CPU)")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions, no scaling chart")
    parser.add_argument("--output", type=Path, default=REPO / "docs" / "benchmarks_encoder.md")
    parser.add_argument("--chart", type=Path, default=REPO / "docs" / "images" / "encoder_scaling.png")
    parser.add_argument("--no-chart", action="store_true")
    args = parser.parse_args(argv)

    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    if device.type == "cpu":
        exact_memory_mode()
    repeats = 5 if args.quick else 20
    fast = multigrid.resolve_backend("auto", device)
    backends = ["torch", fast] if fast != "torch" else ["torch"]
    machine = machine_description(device)
    print(f"machine: {machine}\nbackends: {backends}")
    if device.type == "cpu":
        sizes, counts, scaling_n = [32_768, 262_144], [4, 8, 16, 32, 64], 32_768
    else:
        sizes, counts, scaling_n = [1 << 20, 1 << 22], [4, 8, 16, 32, 64], 100_000
    if args.quick:
        counts = []
    memory = measure_memory(device, backends, sizes, counts, scaling_n)
    if device.type == "cpu":
        fast_allocation_mode()

    sections = [f"### {'GPU' if device.type == 'cuda' else 'CPU'}: {machine}", ""]
    sections.append(f"Command: `python benchmarks/bench_encoder.py --device {args.device}`. Medians of {repeats} runs.")
    sections.append("")
    sections += [
        "Encoder alone (forward: no gradients; fwd+bwd: gradient for the grids; peak: one forward pass, "
        "its output included):",
        "",
        encoder_table(device, backends, repeats, sizes, memory),
        "",
    ]
    if device.type == "cpu":
        sections += [
            f"Training steps, 32,768 points (the authors' code: about {AUTHORS_ITERATION_MS:.0f} ms per iteration for the "
            "small preset on this CPU, ground-truth sampling included):",
            "",
            training_table(device, backends, repeats, 32_768),
            "",
        ]
        sections += [
            "Decode throughput, whole model (encoder + 2 x 64 decoder), batches of 262,144:",
            "",
            decode_table(device, backends, max(3, repeats // 4), 262_144, 4),
            "",
        ]
    elif "triton" in backends:
        sections += ["Triton block sweep:", "", triton_block_sweep(device, repeats), ""]
        sections += [cuda_extras(device, repeats), ""]
    if counts:
        table, results = scaling(device, backends, repeats, scaling_n, counts, memory)
        sections += [
            f"Scaling with the number of grids M (1 x 16^3 grids, {scaling_n:,} points; training step as above; "
            "forward peak memory):",
            "",
            table,
            "",
        ]
        if not args.no_chart:
            label = "GPU" if device.type == "cuda" else "CPU"
            chart = args.chart if device.type == "cpu" else args.chart.with_name(args.chart.stem + "_gpu.png")
            draw_chart(chart, counts, results, scaling_n, f"{label}: {machine.split(',')[0]}", [scaling_n * m * 4 / 2**20 for m in counts])
            rel = os.path.relpath(chart, args.output.parent)
            sections += [f"![time and memory against M]({rel})", ""]
            print(f"chart: {chart}")
    if device.type == "cpu":
        sections.append(f"1-minute load average at the end: {os.getloadavg()[0]:.2f} (other jobs share this machine).")
    write_section(args.output, "gpu" if device.type == "cuda" else "cpu", "\n".join(sections))
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Benchmark of domain decomposition (issue 3): bricks against one model, scaling, memory, seams, speed.

For each volume:
- quality: a 2x2x2 brick model (``--preset`` per brick) against one model with the same total parameter
  count (same features per grid, grids twice the resolution, grid count rounded to match), the same
  iterations per model and the same trainer; PSNR over all voxels and wall time;
- scaling: wall time of the brick run with each worker count of ``--workers`` (local Dask cluster; on a
  GPU machine the workers share the visible GPUs round robin);
- peak memory: resident-set high-water mark of the coordinator and of every worker;
- seams: error on brick-border voxels (within one voxel of a cut between bricks) against the other
  voxels, routed and blended;
- speed: points per second of the brick model against one model of the per-brick size (the same
  preset), uniform random points, after warm-up, device synchronised.
With ``--memory``, also a raw volume several times larger than each worker's memory limit (built by
repeating every voxel of Richtmyer-Meshkov 4x along each axis) trained as 4x4x4 bricks.

Prints tables and writes them as a Markdown section of ``docs/benchmarks_bricks.md`` (one section per
device kind, replaced on every run).

Usage::

    python benchmarks/bench_bricks.py                       # CPU, 256^3 volumes, 1 and 2 workers
    python benchmarks/bench_bricks.py --device cuda --iterations 5000 --batch-size 65536
    python benchmarks/bench_bricks.py --memory --skip-quality
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.api import load
from apmgsrn.data import open_volume
from apmgsrn.decomposition.coordinator import BrickProgress, train_bricks
from apmgsrn.decomposition.executor import ExecutorConfig, open_job_queue
from apmgsrn.decomposition.planner import DecompositionConfig
from apmgsrn.inference.evaluate import evaluate, psnr_from_mse
from apmgsrn.recipes import RUNTIME
from apmgsrn.inference.query import query
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import preset_config
from apmgsrn.ops.trilinear import voxel_coordinates
from apmgsrn.training.fit import fit_volume
from apmgsrn.training.trainer import TrainConfig

REPO = Path(__file__).resolve().parents[1]
DEFAULT_VOLUMES = ["richtmyer_meshkov_t20_256x256x256_uint8.raw", "miranda_density_256.nc"]


def matched_single_config(preset: str, bricks: int, brick_parameters: int):
    """One model with (about) the parameters of ``bricks`` brick models: grids at cbrt(bricks) times the
    resolution, grid count chosen so the totals differ least."""
    base = preset_config("apmgsrn", preset)
    scale = round(bricks ** (1 / 3))
    resolution = tuple(r * scale for r in base.encoder.resolution)
    best = None
    for grids in range(1, 4 * base.encoder.grids + 1):
        config = preset_config("apmgsrn", preset, grids=grids, resolution=resolution)
        count = NeuralField(config).parameter_count()
        gap = abs(count - bricks * brick_parameters)
        if best is None or gap < best[0]:
            best = (gap, config, count)
    return best[1], best[2]


def border_mask(shape: tuple[int, int, int], counts_xyz: tuple[int, int, int], z: slice) -> np.ndarray:
    """Voxels of z-slab ``z`` within one voxel of a cut between bricks (the routing planes)."""
    d, h, w = shape
    masks = []
    for n, count, index in ((w, counts_xyz[0], np.arange(w)), (h, counts_xyz[1], np.arange(h)),
                            (d, counts_xyz[2], np.arange(d)[z])):
        cuts = np.array([j * (n - 1) / count for j in range(1, count)])
        near = np.zeros(len(index), dtype=bool) if len(cuts) == 0 else (
            np.abs(index[:, None] - cuts[None, :]).min(1) <= 1.0)
        masks.append(near)
    near_x, near_y, near_z = masks
    return near_z[:, None, None] | near_y[None, :, None] | near_x[None, None, :]


def seam_errors(model, volume, counts_xyz) -> dict:
    """Squared error sums on border and interior voxels, routed and blended."""
    shape = volume.shape
    sums = {(blend, part): [0.0, 0] for blend in (False, True) for part in ("border", "interior")}
    data_min, data_max = math.inf, -math.inf
    for z, block in volume.iter_slabs(RUNTIME.slab_voxels):
        points = voxel_coordinates(shape, z)
        mask = border_mask(shape, counts_xyz, z).reshape(-1)
        truth = block.reshape(-1).astype(np.float64)
        data_min, data_max = min(data_min, truth.min()), max(data_max, truth.max())
        for blend in (False, True):
            model.blend = blend
            error = (query(model, points).numpy().astype(np.float64) - truth) ** 2
            for part, selected in (("border", mask), ("interior", ~mask)):
                sums[blend, part][0] += float(error[selected].sum())
                sums[blend, part][1] += int(selected.sum())
    model.blend = False
    return {key: psnr_from_mse(total / max(count, 1), data_max - data_min) for key, (total, count) in sums.items()} | {
        "border_fraction": sums[False, "border"][1] / (sums[False, "border"][1] + sums[False, "interior"][1])}


def sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@torch.no_grad()
def points_per_second(model, device: torch.device, batch: int = 2**18, repeats: int = 5) -> float:
    """Best of three timings of ``repeats`` batches (the best resists other programs on shared cores)."""
    points = torch.rand(batch, 3, device=device) * 2 - 1
    for _ in range(2):
        model(points)
    best = math.inf
    for _ in range(3):
        sync(device)
        start = time.perf_counter()
        for _ in range(repeats):
            model(points)
        sync(device)
        best = min(best, time.perf_counter() - start)
    return batch * repeats / best


def volume_spec(text: str, data_dir: Path):
    name, _, variable = text.partition(":")
    return open_volume(data_dir / name, variable=variable or None)


def run_bricks(volume, field_config, train_config, out: Path, workers: int, device: str, grid=(2, 2, 2),
               memory_limit=None, psnr_voxels=None):
    shutil.rmtree(out, ignore_errors=True)
    config = ExecutorConfig(workers=workers, memory_limit=memory_limit)
    with open_job_queue(config) as queue:
        return train_bricks(volume, DecompositionConfig(grid, 1), field_config, train_config, out, queue,
                            device=device, progress=BrickProgress(), psnr_voxels=psnr_voxels)


def mib(count: float) -> str:
    return f"{count / 2**20:.0f} MiB"


def quality_section(args, device: torch.device, work: Path) -> list[str]:
    lines = []
    brick_field = preset_config("apmgsrn", args.preset)
    per_brick = NeuralField(brick_field).parameter_count()
    single_field, single_parameters = matched_single_config(args.preset, 8, per_brick)
    base = TrainConfig(iterations=args.iterations, batch_size=args.batch_size, seed=0)
    quality = ["| volume | model | schedule | parameters | bytes | PSNR dB | wall s |", "|---|---|---|---:|---:|---:|---:|"]
    scaling = ["| volume | workers | wall s | speed-up |", "|---|---:|---:|---:|"]
    memory = ["| volume | workers | coordinator peak RSS | worker peak RSS (max) |", "|---|---:|---:|---:|"]
    seams = ["| volume | border voxels | routed: border / interior PSNR dB | blended: border / interior PSNR dB |",
             "|---|---:|---|---|"]
    speed = ["| volume | one model (per-brick size) pts/s | 2x2x2 brick model pts/s | ratio |", "|---|---:|---:|---:|"]
    for spec in args.volumes:
        volume = volume_spec(spec, args.data_dir)
        name = Path(spec.split(":")[0]).stem
        print(f"== {volume.describe()}", flush=True)
        walls = {}
        for schedule in args.schedules:
            train = replace(base, lr_schedule=schedule)  # plateau: brick_policy ends a brick after its 3rd cut
            for workers in (args.workers if schedule == args.schedules[0] else [max(args.workers)]):
                out = work / f"{name}_bricks_{schedule}_{workers}"
                summary = run_bricks(volume, brick_field, train, out, workers, args.device_name)
                opened = load(out, device=device)
                model = opened.field
                result = evaluate(model, volume)
                stops = sum(r.stopped_early for r in summary.trained)
                label = f"{schedule}" + (" (stop after 3rd cut)" if schedule == "plateau" else "")
                if workers == max(args.workers):
                    quality.append(f"| {name} | 2x2x2 bricks, {args.preset} each | {label} | {model.parameter_count():,} | "
                                   f"{opened.description.file_bytes:,} | {result.psnr:.2f} | {summary.seconds:.1f} |"
                                   + (f" ({stops} of 8 stopped early)" if stops else ""))
                if schedule == args.schedules[0] and not args.quality_only:
                    walls[workers] = summary.seconds
                    # The coordinator's high-water mark is only its own before this script evaluates
                    # anything in-process: the first run's figure is the coordinator's.
                    memory.append(f"| {name} | {workers} | {mib(summary.coordinator_peak_rss_bytes)} | "
                                  f"{mib(max(summary.worker_peak_rss_bytes.values(), default=0))} |")
                    if workers == max(args.workers):
                        errors = seam_errors(model, volume, (2, 2, 2))
                        seams.append(f"| {name} | {100 * errors['border_fraction']:.1f} % | "
                                     f"{errors[False, 'border']:.2f} / {errors[False, 'interior']:.2f} | "
                                     f"{errors[True, 'border']:.2f} / {errors[True, 'interior']:.2f} |")
                        one = NeuralField(brick_field).to(device).eval()
                        threads = torch.get_num_threads()
                        for count in sorted({1, threads}) if device.type == "cpu" else [threads]:
                            torch.set_num_threads(count)
                            one_rate = points_per_second(one, device)
                            brick_rate = points_per_second(model, device)
                            label = f"{name} ({count} thread{'s' if count > 1 else ''})" if device.type == "cpu" else name
                            speed.append(f"| {label} | {one_rate:,.0f} | {brick_rate:,.0f} | {brick_rate / one_rate:.2f} |")
                        torch.set_num_threads(threads)
        # Single model of the same total size, same trainer, same iterations (cosine, the single default),
        # trained after the brick runs so that the coordinator's peak memory above is the coordinator's own.
        single = fit_volume(volume, single_field, base, work / f"{name}_single.apmgsrn", device, progress=False)
        quality.append(f"| {name} | one model {single_field.encoder.grids} x {single_field.encoder.resolution[0]}^3 "
                       f"| cosine | {single_parameters:,} | {single.model_bytes:,} | {single.psnr:.2f} | "
                       f"{single.seconds:.1f} |")
        for workers, wall in sorted(walls.items()):
            first = walls[min(walls)]
            scaling.append(f"| {name} | {workers} | {wall:.1f} | {first / wall:.2f} |")
    iterations = f"{args.iterations} iterations x {args.batch_size} points per model"
    lines += [f"### Bricks against one model ({iterations})", "", *quality, ""]
    if args.quality_only:
        return lines
    lines += ["### Scaling (wall time of the 2x2x2 brick run)", "", *scaling, "",
              "### Peak memory", "", *memory, "",
              "### Seams: PSNR on brick-border voxels (within one voxel of a cut) and on the others", "", *seams, "",
              "### Evaluation speed (uniform random points, batches of 262,144)", "", *speed, ""]
    return lines


def make_large_raw(source: Path, factor: int, target: Path) -> None:
    """Repeat every voxel ``factor`` times along each axis (float32), streamed one source slice at a time."""
    volume = open_volume(source)
    d, h, w = volume.shape
    if target.exists() and target.stat().st_size == d * h * w * factor**3 * 4:
        return
    tmp = target.with_suffix(".part")
    with open(tmp, "wb") as f:
        for z in range(d):
            plane = volume.read(slice(z, z + 1))[0]
            big = np.repeat(np.repeat(plane, factor, axis=0), factor, axis=1).astype(np.float32)
            for _ in range(factor):
                f.write(big.tobytes())
    tmp.rename(target)


def memory_section(args, work: Path) -> list[str]:
    factor = args.memory_factor
    n = 256 * factor
    target = work / f"rm_repeated_{n}x{n}x{n}_float32.raw"
    make_large_raw(args.data_dir / "richtmyer_meshkov_t20_256x256x256_uint8.raw", factor, target)
    volume = open_volume(target)
    limit = args.memory_limit
    field = preset_config("apmgsrn", args.preset)
    train = TrainConfig(iterations=args.memory_iterations, batch_size=args.batch_size, seed=0)
    summary = run_bricks(volume, field, train, work / "large_bricks", max(args.workers), args.device_name,
                         grid=(4, 4, 4), memory_limit=limit, psnr_voxels=2**20)
    worst = max(summary.worker_peak_rss_bytes.values(), default=0)
    psnrs = [r.psnr for r in summary.trained]
    return [
        "### Larger than a worker's memory",
        "",
        "| volume (float32 raw file) | worker memory limit | bricks | workers | coordinator peak RSS | "
        "worker peak RSS (max) | wall s | brick PSNR dB (min / median, 2^20-voxel sample) |",
        "|---|---:|---|---:|---:|---:|---:|---|",
        f"| {n}^3 = {target.stat().st_size / 2**30:.1f} GiB | {limit} | 4x4x4, {summary.plan.bricks[0].shape[0]}^3 "
        f"each | {max(args.workers)} | {mib(summary.coordinator_peak_rss_bytes)} | {mib(worst)} | "
        f"{summary.seconds:.1f} | {min(psnrs):.2f} / {float(np.median(psnrs)):.2f} |",
        "",
        f"All {len(summary.plan)} bricks finished: {summary.complete}; failed: {summary.failed or 'none'}.",
        "",
    ]


def write_section(path: Path, title: str, lines: list[str]) -> None:
    header = "# Domain decomposition benchmarks\n\nWritten by `benchmarks/bench_bricks.py`; one section per device kind.\n"
    text = path.read_text() if path.exists() else header
    section = f"## {title}\n\n" + "\n".join(lines).rstrip() + "\n"
    pattern = re.compile(rf"^## {re.escape(title)}\n.*?(?=^## |\Z)", re.S | re.M)
    text = pattern.sub(section + "\n", text) if pattern.search(text) else text.rstrip() + "\n\n" + section
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--volumes", nargs="+", default=DEFAULT_VOLUMES, help="FILE[:VARIABLE] in --data-dir")
    parser.add_argument("--data-dir", type=Path, default=REPO.parent / "shared" / "data")
    parser.add_argument("--device", default="cpu", help="cpu or cuda")
    parser.add_argument("--preset", default="small")
    parser.add_argument("--iterations", type=int, default=1000)
    parser.add_argument("--batch-size", type=int, default=8192)
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--schedules", nargs="+", default=["cosine", "plateau"],
                        help="brick learning-rate schedules; the first is used for scaling, memory and seams")
    parser.add_argument("--skip-quality", action="store_true")
    parser.add_argument("--quality-only", action="store_true",
                        help="only bricks against one model (no scaling, memory, seam or speed tables)")
    parser.add_argument("--memory", action="store_true", help="also train a raw volume larger than a worker's memory")
    parser.add_argument("--memory-factor", type=int, default=4, help="repeat RM 256^3 this many times per axis")
    parser.add_argument("--memory-limit", default="1GiB", help="Dask memory limit per worker for --memory")
    parser.add_argument("--memory-iterations", type=int, default=100)
    parser.add_argument("--work", type=Path, default=REPO / ".bench_data" / "bricks")
    parser.add_argument("--docs", type=Path, default=REPO / "docs" / "benchmarks_bricks.md")
    args = parser.parse_args()
    device = torch.device(args.device)
    args.device_name = args.device
    args.work.mkdir(parents=True, exist_ok=True)
    lines = []
    if device.type == "cuda":
        title = f"GPU: {torch.cuda.get_device_name(device)}"
    else:
        title = f"CPU: {os.cpu_count()} cores ({platform.processor() or platform.machine()})"
    if args.quality_only:
        title += ", bricks against one model"  # its own section: the full run's tables stay
    lines.append(f"Run: `python benchmarks/bench_bricks.py {' '.join(sys.argv[1:])}`; torch {torch.__version__}.")
    lines.append("")
    if not args.skip_quality:
        lines += quality_section(args, device, args.work)
    if args.memory:
        lines += memory_section(args, args.work)
    print("\n".join(lines))
    write_section(args.docs, title, lines)


if __name__ == "__main__":
    main()

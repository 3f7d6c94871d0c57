"""Rendering benchmark (issue 4): models of the shared 256^3 volumes rendered at 512 x 512.

For each volume: the raw-volume render (the reference) and, for each model size present (small, medium),
the time to compute the macro-cell value bounds (once per model), the time to the first progressive image
(the stride-8 pass), the full-frame time at 256 samples per ray with and without empty-space skipping,
the field evaluations of each, and the image PSNR/SSIM of the model render against the reference.

Prints a table and writes its section (one per device kind) of ``docs/benchmarks_render.md`` and
``docs/results_render.md``, plus comparison images ``docs/images/render_<volume>.png``.

Usage::

    python benchmarks/bench_render.py --device cpu --models-dir models/
    python benchmarks/bench_render.py --device cuda --models-dir models/ --train-iterations 5000

Models are expected as ``<models-dir>/<volume>_<size>.apm``; with ``--train-iterations`` missing ones are
trained first with ``apmgsrn train`` (not timed here).
"""

from __future__ import annotations

import argparse
import os
import platform
import re
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class BenchVolume:
    name: str
    file: str
    colormap: str
    opacity: tuple[tuple[float, float], ...]
    azimuth: float = 30.0
    elevation: float = 20.0


VOLUMES = (
    BenchVolume("miranda", "miranda_density_256.nc", "Cool to Warm", ((0.0, 0.0), (0.55, 0.0), (1.0, 0.5))),
    BenchVolume(
        "richtmyer_meshkov", "richtmyer_meshkov_t20_256x256x256_uint8.raw", "plasma", ((0.0, 0.0), (0.3, 0.0), (1.0, 0.6))
    ),
)
SIZES = ("small", "medium")


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def _timed(device: torch.device, function):
    _sync(device)
    start = time.perf_counter()
    result = function()
    _sync(device)
    return result, time.perf_counter() - start


def _best_of(repeats: int, device: torch.device, function):
    best, result = float("inf"), None
    for _ in range(repeats):
        result, seconds = _timed(device, function)
        best = min(best, seconds)
    return result, best


def _device_name(device: torch.device) -> str:
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"CPU ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, {torch.get_num_threads()} torch threads)"


def _train(data: Path, out: Path, size: str, iterations: int, device: str) -> None:
    command = [sys.executable, "-m", "apmgsrn", "train", str(data), "--out", str(out), "--model", "apmgsrn",
               "--preset", size,
               "--iterations", str(iterations), "--device", device]
    print("$", " ".join(command), flush=True)
    subprocess.run(command, check=True)


def bench_volume(args, spec: BenchVolume, device: torch.device, batch_size: int, first_batch: bool) -> list[dict]:
    import apmgsrn
    from apmgsrn.data import open_volume
    from apmgsrn.rendering import (
        Camera,
        RendererConfig,
        VolumeRenderer,
        extent_from_shape,
        image_psnr,
        image_ssim,
        make_transfer_function,
        render_progressive,
    )

    data_path = Path(args.data_dir) / spec.file
    volume = open_volume(data_path)
    array = volume.to_numpy()
    stats = volume.stats()
    tf = make_transfer_function(spec.colormap, (stats.min, stats.max), opacity=spec.opacity)
    extent = extent_from_shape(volume.shape)
    camera = Camera.orbit(spec.azimuth, spec.elevation, None, 30.0, args.width, args.height, extent)
    warm_camera = Camera.orbit(spec.azimuth, spec.elevation, None, 30.0, 32, 32, extent)

    def config(skipping: bool) -> RendererConfig:
        return RendererConfig(samples_per_ray=args.spp, batch_size=batch_size, empty_space_skipping=skipping)

    rows = []
    images = {}
    # The reference: trilinear interpolation of the voxels, exact bounds.
    for skipping in (True, False):
        renderer, setup_s = _timed(
            device, lambda: VolumeRenderer.for_volume(array, tf, config(skipping), extent=extent, device=device)
        )  # copies the voxels to the device and, with skipping, pools the macro-cell bounds
        renderer.render(warm_camera)
        first, first_s = _best_of(args.repeats, device, lambda: next(render_progressive(renderer, camera)))
        result, frame_s = _best_of(args.repeats, device, lambda: renderer.render(camera))
        if skipping:
            reference = result.image
            images["raw volume"] = reference
            row = dict(volume=spec.name, field="raw volume", params="-", batch=batch_size, bounds_s=setup_s, first_s=first_s,
                       frame_skip_s=frame_s, evals_skip=result.statistics.field_evaluations,
                       samples=result.statistics.samples_in_box, visible=renderer.visible_fraction)
        else:
            row.update(frame_plain_s=frame_s, evals_plain=result.statistics.field_evaluations,
                       max_diff=float((result.image - reference).abs().max()))
    rows.append(row)

    for size in SIZES:
        model_path = Path(args.models_dir) / f"{spec.name}_{size}.apm"
        if not model_path.exists() and args.train_iterations and first_batch:
            model_path.parent.mkdir(parents=True, exist_ok=True)
            _train(data_path, model_path, size, args.train_iterations, str(device))
        if not model_path.exists():
            print(f"skipping {model_path}: not found (give --train-iterations to train it)")
            continue
        model = apmgsrn.load(model_path, device=device).eval()
        params = sum(p.numel() for p in model.parameters())
        training = getattr(model, "training_summary", {}) or {}
        skip_renderer = VolumeRenderer(model, tf, config(True), extent=extent, device=device)
        _, bounds_s = _timed(device, skip_renderer.ensure_bounds)
        skip_renderer.render(warm_camera)
        first, first_s = _best_of(args.repeats, device, lambda: next(render_progressive(skip_renderer, camera)))
        skipped, frame_skip_s = _best_of(args.repeats, device, lambda: skip_renderer.render(camera))
        plain_renderer = VolumeRenderer(model, tf, config(False), extent=extent, device=device)
        plain_renderer.render(warm_camera)
        plain, frame_plain_s = _best_of(args.repeats, device, lambda: plain_renderer.render(camera))
        images[f"{size} model"] = skipped.image
        rows.append(dict(
            volume=spec.name, field=f"{size} model", params=f"{params:,}", batch=batch_size, bounds_s=bounds_s,
            first_s=first_s,
            frame_skip_s=frame_skip_s, frame_plain_s=frame_plain_s,
            evals_skip=skipped.statistics.field_evaluations, evals_plain=plain.statistics.field_evaluations,
            samples=skipped.statistics.samples_in_box, visible=skip_renderer.visible_fraction,
            max_diff=float((skipped.image - plain.image).abs().max()),
            psnr=image_psnr(skipped.image, reference), ssim=image_ssim(skipped.image, reference),
            iterations=training.get("iterations"), volume_psnr=training.get("psnr"),
            trained_on=training.get("device"),
        ))
    if args.images and first_batch:
        _save_panel(images, Path(args.images) / f"render_{spec.name}.png", tf_name=spec.colormap)
    return rows


def _save_panel(images: dict, path: Path, tf_name: str) -> None:
    """Panels side by side (reference first), each halved in size, with a caption strip."""
    import numpy as np
    from PIL import Image, ImageDraw

    from apmgsrn.rendering.images import as_uint8

    tiles = []
    for label, image in images.items():
        tile = Image.fromarray(as_uint8(image))
        tile = tile.resize((tile.width // 2, tile.height // 2), Image.LANCZOS)
        canvas = Image.new("RGB", (tile.width, tile.height + 18), "white")
        canvas.paste(tile, (0, 18))
        ImageDraw.Draw(canvas).text((4, 3), label, fill=(0, 0, 0))
        tiles.append(np.asarray(canvas))
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(tiles, axis=1)).save(path, optimize=True)
    print(f"wrote {path} ({tf_name})")


def _fmt(value, digits=2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _tables(rows: list[dict], args, device: torch.device) -> tuple[str, str]:
    command = "python benchmarks/bench_render.py " + " ".join(args.argv)
    head = (f"Device: {_device_name(device)}. Image {args.width}x{args.height}, {args.spp} samples per ray across the "
            f"box, early termination at transmittance 1e-3, 32^3 macro cells; best of {args.repeats}. "
            f"Command: `{command}`.\n\n")
    bench = [head,
             "| volume | field | parameters | batch | bounds, once (s) | first progressive image (s) "
             "| frame, skipping (s) | frame, no skipping (s) | skipping speed-up | field evaluations skipping / not "
             "| visible cells |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        speed = r["frame_plain_s"] / r["frame_skip_s"] if r.get("frame_plain_s") else None
        bench.append(
            f"| {r['volume']} | {r['field']} | {r['params']} | 2^{r['batch'].bit_length() - 1} | {_fmt(r['bounds_s'])} "
            f"| {_fmt(r['first_s'], 3)} "
            f"| {_fmt(r['frame_skip_s'])} | {_fmt(r.get('frame_plain_s'))} | {_fmt(speed)}x "
            f"| {r['evals_skip'] / 1e6:.1f} M / {r['evals_plain'] / 1e6:.1f} M | {100 * (r['visible'] or 0):.0f}% |"
        )
    bench.append("")
    bench.append("Largest per-channel difference between the skipping and non-skipping images: "
                 + ", ".join(f"{r['volume']} {r['field']} {r['max_diff']:.1e}" for r in rows if r["batch"] == rows[0]["batch"])
                 + ".")
    results = [head,
               "| volume | model | parameters | training iterations | volume PSNR (dB) | image PSNR (dB) | image SSIM |",
               "|---|---|---|---|---|---|---|"]
    seen = set()
    for r in rows:
        if "psnr" not in r or (r["volume"], r["field"]) in seen:
            continue
        seen.add((r["volume"], r["field"]))
        results.append(
            f"| {r['volume']} | {r['field']} | {r['params']} | {_fmt(r.get('iterations'))} "
            f"(on {_fmt(r.get('trained_on'))}) | {_fmt(r.get('volume_psnr'))} | {_fmt(r['psnr'])} | {_fmt(r['ssim'], 4)} |"
        )
    return "\n".join(bench) + "\n", "\n".join(results) + "\n"


def write_section(path: Path, key: str, title: str, body: str) -> None:
    """Replace (or append) the section between this benchmark's markers for ``key`` in ``path``."""
    begin, end = f"<!-- bench_render:{key}:begin -->", f"<!-- bench_render:{key}:end -->"
    block = f"{begin}\n### {title}\n\n{body}{end}\n"
    text = path.read_text() if path.exists() else ""
    pattern = re.compile(re.escape(begin) + r".*?" + re.escape(end) + r"\n?", re.S)
    text = pattern.sub(lambda _: block, text) if pattern.search(text) else (text + ("\n" if text else "") + block)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    print(f"wrote section {key} of {path}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--data-dir", default=str(REPO.parent / "shared" / "data"))
    parser.add_argument("--models-dir", default=str(REPO / "models"))
    parser.add_argument("--train-iterations", type=int, default=0, help="train missing models with this many iterations")
    parser.add_argument("--volumes", default=",".join(v.name for v in VOLUMES))
    parser.add_argument("--width", type=int, default=512)
    parser.add_argument("--height", type=int, default=512)
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--batch-sizes", default=str(1 << 18), help="comma-separated points per field call")
    parser.add_argument("--repeats", type=int, default=1)
    parser.add_argument("--images", default=str(REPO / "docs" / "images"), help="folder for images ('' for none)")
    parser.add_argument("--docs", default=str(REPO / "docs"), help="folder of the markdown files ('' for none)")
    args = parser.parse_args(argv)
    args.argv = argv if argv is not None else sys.argv[1:]
    from apmgsrn.device import resolve_device

    device = resolve_device(args.device)
    wanted = args.volumes.split(",")
    rows = []
    batches = [int(b) for b in args.batch_sizes.split(",")]
    for spec in VOLUMES:
        if spec.name in wanted:
            for i, batch in enumerate(batches):
                rows.extend(bench_volume(args, spec, device, batch, first_batch=i == 0))
    bench, results = _tables(rows, args, device)
    print(bench)
    print(results)
    if args.docs:
        key = device.type
        title = f"Rendering on {'the GPU' if device.type == 'cuda' else 'the CPU'}: {_device_name(device)}"
        write_section(Path(args.docs) / "benchmarks_render.md", key, title, bench)
        write_section(Path(args.docs) / "results_render.md", "results", "Model renders against the raw-volume render", results)
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""The render reference scenes of ``test_render_reference.py``, and the script that wrote their images.

The reference images were rendered by main at 50ca313 (before the renderer was split into stages), so
the test shows that later code draws the same pixels. Running this again with newer code would only
copy that code's output: do it only on purpose, when a change of the images is deliberate and named.

What it writes into ``tests/data``:

* ``neghip_32x32x32_uint8.npy``: every second voxel of the shared ``neghip_64x64x64_uint8.raw``
  (a real CT-like volume, see ``../shared/data/README.md``), 32 KB.
* ``render_reference_model.apmgsrn``: a tiny APMGSRN model (2 grids of 4^3, 1 hidden layer of 16) fitted
  to that volume for 300 iterations on a CPU, seed 0.
* ``render_reference_bricks/``: the same model type as a 2 x 1 x 1 brick model.
* ``render_reference_preset.json``: a ParaView preset in RGB with its own opacity.
* ``render_reference.npz``: the images (float32 from the library, uint8 from the CLI and the viewer).

Usage: ``PYTHONPATH=src python tests/render_reference.py [--images-only]``.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

DATA = Path(__file__).resolve().parent / "data"
SHARED = DATA.parents[1].parent / "shared" / "data"
VOLUME = DATA / "neghip_32x32x32_uint8.npy"
MODEL = DATA / "render_reference_model.apmgsrn"
BRICKS = DATA / "render_reference_bricks"
PRESET = DATA / "render_reference_preset.json"
REFERENCE = DATA / "render_reference.npz"
TINY = ["--grids", "2", "--features", "2", "--resolution", "4", "--hidden-layers", "1", "--width", "16",
        "--iterations", "300", "--batch-size", "4096", "--seed", "0", "--device", "cpu"]
PRESET_JSON = [
    {
        "Name": "reference reds and blues",
        "ColorSpace": "RGB",
        "RGBPoints": [0.0, 0.1, 0.2, 0.8, 0.5, 0.9, 0.9, 0.3, 1.0, 0.8, 0.1, 0.1],
        "Points": [0.0, 0.0, 0.5, 0.0, 0.25, 0.0, 0.5, 0.0, 1.0, 0.7, 0.5, 0.0],
    }
]


def _cli(*argv: str) -> None:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}  # one thread, as the test
    subprocess.run([sys.executable, "-m", "apmgsrn", *argv], check=True, stdout=subprocess.DEVNULL, env=env)


def make_inputs() -> None:
    raw = np.fromfile(SHARED / "neghip_64x64x64_uint8.raw", dtype=np.uint8).reshape(64, 64, 64)
    np.save(VOLUME, np.ascontiguousarray(raw[::2, ::2, ::2]))
    PRESET.write_text(json.dumps(PRESET_JSON, indent=1), encoding="utf-8")
    _cli("train", str(VOLUME), "--out", str(MODEL), *TINY)
    shutil.rmtree(BRICKS, ignore_errors=True)
    _cli("train", str(VOLUME), "--out", str(BRICKS), "--bricks", "2,1,1", "--workers", "1", *TINY)


def library_images() -> dict[str, np.ndarray]:
    """Renders through the Python API: the raw volume (exact bounds) and the models (sampled bounds)."""
    import apmgsrn
    from apmgsrn.rendering import Camera, RendererConfig, VolumeRenderer, render_progressive
    from apmgsrn.rendering.transfer_function import ColorMap, OpacityMap, TransferFunction

    tf = TransferFunction(
        color_map=ColorMap(((0.0, 0.1, 0.2, 0.8), (120.0, 0.9, 0.9, 0.3), (255.0, 0.8, 0.1, 0.1))),
        opacity_map=OpacityMap(((0.0, 0.0, 0.5, 0.0), (60.0, 0.0, 0.5, 0.0), (255.0, 0.6, 0.5, 0.0))),
    )
    volume = np.load(VOLUME).astype(np.float32)
    extent = (1.0, 0.75, 0.9)
    camera = Camera.orbit(40.0, 25.0, None, 30.0, 48, 40, extent)
    images = {}
    skipping = RendererConfig(samples_per_ray=64, batch_size=512, macro_cells=8, jitter=True, seed=3)
    images["volume_skipping_jitter"] = VolumeRenderer.for_volume(volume, tf, skipping, extent).render(camera).image
    plain = RendererConfig(
        samples_per_ray=40, batch_size=2048, empty_space_skipping=False, early_termination=0.0,
        background=(0.0, 0.0, 0.0),
    )
    side = Camera.orbit(-60.0, 10.0, 3.5, 35.0, 48, 40, extent)
    images["volume_plain"] = VolumeRenderer.for_volume(volume, tf, plain, extent).render(side).image
    model_config = RendererConfig(samples_per_ray=64, batch_size=1024, macro_cells=8, samples_per_cell=2)
    for name, path in (("model", MODEL), ("bricks", BRICKS)):
        field = apmgsrn.load(path)
        renderer = VolumeRenderer(field, tf, model_config, extent=extent)
        images[name] = renderer.render(camera).image
        images[f"{name}_progressive_final"] = list(render_progressive(renderer, camera))[-1].image
    return {k: v.numpy() for k, v in images.items()}


def cli_images(folder: Path) -> dict[str, np.ndarray]:
    """``apmgsrn render`` of the volume and of the models, PNG pixels (run in this process)."""
    from PIL import Image

    from apmgsrn.cli.main import main

    images = {}
    common = ["--width", "48", "--height", "40", "--spp", "48", "--macro-cells", "8", "--batch-size", "1024",
              "--device", "cpu", "--colormap", str(PRESET)]
    for name, path, extra in (
        ("cli_volume", VOLUME, ["--jitter", "--seed", "5", "--azimuth", "120"]),
        ("cli_model", MODEL, ["--range", "10,230", "--background", "0.1,0.1,0.1"]),
        ("cli_bricks", BRICKS, ["--elevation", "-30"]),
    ):
        out = folder / f"{name}.png"
        assert main(["render", str(path), "--out", str(out), *common, *extra]) == 0
        images[name] = np.asarray(Image.open(out).convert("RGB"))
    return images


def viewer_images(folder: Path) -> dict[str, np.ndarray]:
    """The viewer session's final frame of the volume and of the model (uint8, overlay off and on)."""
    from apmgsrn.viewer.catalog import Catalog
    from apmgsrn.viewer.session import ViewerConfig, ViewerSession

    served = folder / "served"
    served.mkdir()
    shutil.copy(VOLUME, served / VOLUME.name)
    shutil.copy(MODEL, served / MODEL.name)
    shutil.copytree(BRICKS, served / BRICKS.name)
    shutil.copy(PRESET, served / PRESET.name)
    config = ViewerConfig(image_width=48, image_height=40, samples_per_ray=48, batch_size=2048, chunk_pixels=300)
    session = ViewerSession(Catalog(served), "cpu", config)
    key = session.add_presets(served / PRESET.name, PRESET.name)[0]
    images = {}
    for name, entry in (("viewer_volume", VOLUME.name), ("viewer_model", MODEL.name), ("viewer_bricks", BRICKS.name)):
        session.open_now(entry)
        session.set_colormap(key)
        session.orbit(0.1, -0.05)
        session.end_interaction()
        session.run_until_idle()
        images[name] = session.last_frame.image.copy()
        session.set_overlay(True)
        session.run_until_idle()
        images[f"{name}_overlay"] = session.last_frame.image.copy()
        session.set_overlay(False)
    return images


def main() -> None:
    torch.set_num_threads(1)  # the test renders on one thread too
    if "--images-only" not in sys.argv:
        make_inputs()
    scratch = DATA / "_scratch"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        images = {**library_images(), **cli_images(scratch), **viewer_images(scratch)}
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    np.savez_compressed(REFERENCE, **images)
    for name, image in images.items():
        print(f"{name}: {image.shape} {image.dtype} mean {image.astype(np.float64).mean():.4f}")


if __name__ == "__main__":
    main()

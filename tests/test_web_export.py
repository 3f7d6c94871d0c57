"""``apmgsrn export --format html``: the page renders what ``apmgsrn render`` renders (headless Chromium with
software WebGL2), for float32, packed and time-series models, fetches nothing, and a bad model is refused
before any page is written."""

from __future__ import annotations

import base64
import io
import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from apmgsrn.cli.main import main
from apmgsrn.rendering import image_ssim

CHROMIUM = "/usr/bin/chromium"
# Software WebGL2 (SwiftShader through ANGLE): the same pixels on any machine, no GPU needed.
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                 "--ignore-gpu-blocklist", "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--no-first-run"]
# Small frames: the software renderer runs the network at every sample.
SIZE, SPP = 48, 64
SETTINGS = {"width": SIZE, "height": SIZE, "samples_per_ray": SPP}
HYBRID = ["--model", "hybrid", "--levels", "5", "--log2-table-size", "9", "--grids", "2", "--resolution", "8",
          "--features", "2", "--width", "16", "--hidden-layers", "1", "--batch-size", "2048", "--device", "cpu"]

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def models(tmp_path_factory, test_data):
    """A float32 hybrid and its packed file (c60), the committed APMGSRN reference model (neghip), the NGP and
    fV-SRN baselines (neghip) and a time-series hybrid (viscous fingers, 4 steps), each trained for a few
    iterations."""
    folder = tmp_path_factory.mktemp("web_models")
    c60 = test_data / "c60_80x64x48_uint8.raw"
    hybrid = folder / "hybrid.apmgsrn"
    assert main(["train", str(c60), "--out", str(hybrid), *HYBRID, "--iterations", "80"]) == 0
    packed = folder / "hybrid_packed.apmgsrn"
    assert main(["pack", str(hybrid), str(c60), "--out", str(packed), "--bits", "8"]) == 0
    series = folder / "series.apmgsrn"
    assert main(["train", str(test_data / "viscous_fingers_run01" / "*.vti"), "--out", str(series), *HYBRID,
                 "--iterations", "40"]) == 0
    neghip = test_data / "neghip_32x32x32_uint8.npy"
    baselines = {}
    for kind, size in (("ngp", ["--levels", "5", "--log2-table-size", "9"]), ("fvsrn", ["--resolution", "8"])):
        baselines[kind] = folder / f"{kind}.apmgsrn"
        assert main(["train", str(neghip), "--out", str(baselines[kind]), "--model", kind, *size, "--features", "2",
                     "--width", "16", "--hidden-layers", "1", "--iterations", "40", "--batch-size", "2048",
                     "--device", "cpu"]) == 0
    return {"hybrid": hybrid, "packed": packed, "apmgsrn": test_data / "render_reference_model.apmgsrn",
            "series": series, **baselines}


@pytest.fixture(scope="module")
def browser():
    if not Path(CHROMIUM).exists():
        pytest.skip("needs Debian's chromium (apt-get install chromium)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="needs playwright (the [test] extra)")
    with sync_api.sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        yield launched
        launched.close()


def _export(model: Path, out: Path) -> dict:
    import apmgsrn
    from apmgsrn.web import export_html

    return export_html(apmgsrn.load(model), out, model, settings=SETTINGS)


def _png(data_url: str) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(data_url.split(",", 1)[1]))).convert("RGB"))


def _page_images(browser, page_path: Path, steps: tuple[int, ...] = ()) -> tuple[list[np.ndarray], list[str], list]:
    """The page's first frame (and the frames of ``steps``), the URLs it asked for outside its own file, and
    its errors."""
    page = browser.new_page(viewport={"width": 900, "height": 700})
    outside, errors = [], []
    page.on("request", lambda r: None if r.url.startswith(("file://", "data:", "blob:")) else outside.append(r.url))
    page.on("pageerror", lambda e: errors.append(str(e)))
    try:
        page.goto(page_path.as_uri())
        page.evaluate("() => window.apmgsrn.ready")
        images = [_png(page.evaluate("() => window.apmgsrn.snapshot()"))]
        for step in steps:
            page.evaluate("(s) => window.apmgsrn.render({step: s})", step)
            images.append(_png(page.evaluate("() => window.apmgsrn.snapshot()")))
    finally:
        page.close()
    return images, outside, errors


def _cli_image(model: Path, out: Path, step: int | None = None) -> np.ndarray:
    extra = ["--time", str(step)] if step is not None else []
    assert main(["render", str(model), "--out", str(out), "--width", str(SIZE), "--height", str(SIZE),
                 "--spp", str(SPP), *extra]) == 0
    return np.asarray(Image.open(out).convert("RGB"))


def _ssim(a: np.ndarray, b: np.ndarray) -> float:
    return image_ssim(torch.tensor(a, dtype=torch.float32) / 255, torch.tensor(b, dtype=torch.float32) / 255)


@pytest.mark.browser
@pytest.mark.parametrize("kind", ["hybrid", "packed", "apmgsrn", "ngp", "fvsrn"])
def test_page_renders_what_render_renders(browser, models, kind, tmp_path):
    page_path = tmp_path / "view.html"
    written = _export(models[kind], page_path)
    assert written["bytes"] == page_path.stat().st_size
    (image,), outside, errors = _page_images(browser, page_path)
    assert errors == [] and outside == []
    reference = _cli_image(models[kind], tmp_path / "cpu.png")
    assert image.shape == reference.shape == (SIZE, SIZE, 3)
    assert image.std() > 1.0  # something is drawn, not a blank frame
    assert _ssim(image, reference) >= 0.98


@pytest.mark.browser
def test_series_page_renders_first_and_last_step(browser, models, tmp_path):
    page_path = tmp_path / "series.html"
    _export(models["series"], page_path)
    last = 3
    (first, final), outside, errors = _page_images(browser, page_path, steps=(last,))
    assert errors == [] and outside == []
    assert _ssim(first, _cli_image(models["series"], tmp_path / "s0.png", 0)) >= 0.98
    assert _ssim(final, _cli_image(models["series"], tmp_path / "s3.png", last)) >= 0.98
    assert not np.array_equal(first, final)


def test_packed_page_is_small_and_self_contained(models, tmp_path):
    out = tmp_path / "packed.html"
    assert main(["export", str(models["packed"]), "--format", "html", "--out", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    assert out.stat().st_size < 400_000
    # Nothing from elsewhere: no URL to load, and a policy that forbids every fetch.
    assert "http://" not in text and "https://" not in text and "<script src" not in text
    assert "default-src 'none'" in text
    scene = json.loads(text.split('id="apm-scene">', 1)[1].split("</script>", 1)[0])
    # The packed integers travel as integers (not float32) in a page of a packed file.
    assert any(blob["encoding"] == "quantized" for blob in scene["blobs"].values())


def test_export_refuses_a_truncated_or_foreign_file(models, tmp_path, capsys):
    data = models["packed"].read_bytes()
    truncated = tmp_path / "truncated.apmgsrn"
    truncated.write_bytes(data[: len(data) // 2])
    foreign = tmp_path / "foreign.apmgsrn"
    foreign.write_bytes(b"\x10\x00\x00\x00\x00\x00\x00\x00{\"a\": 1}" + bytes(64))
    for bad in (truncated, foreign):
        out = tmp_path / f"{bad.stem}.html"
        capsys.readouterr()
        assert main(["export", str(bad), "--format", "html", "--out", str(out)]) == 2
        error = capsys.readouterr().err.strip()
        assert error.startswith("error:") and "\n" not in error and str(bad) in error
        assert not out.exists()


def test_export_refuses_a_brick_model_and_a_wrong_suffix(test_data, models, tmp_path, capsys):
    bricks = tmp_path / "bricks"
    shutil.copytree(test_data / "render_reference_bricks", bricks)
    assert main(["export", str(bricks), "--format", "html", "--out", str(tmp_path / "b.html")]) == 2
    assert "brick model" in capsys.readouterr().err
    assert not (tmp_path / "b.html").exists()
    assert main(["export", str(models["hybrid"]), "--format", "html", "--out", str(tmp_path / "v.png")]) == 2
    assert not (tmp_path / "v.png").exists()

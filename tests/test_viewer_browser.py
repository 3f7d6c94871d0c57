"""End to end in headless Chromium: ``apmgsrn view`` serves a page that loads, shows an image, follows
a drag and a colour-map change, saves a PNG, refuses a path outside its folder and survives a broken
model, loading nothing from outside 127.0.0.1."""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from viewer_data import make_viewer_folder
from viewer_server import running_viewer

pytestmark = pytest.mark.browser
pytest.importorskip("trame", reason="needs the [viewer] extra")
pytest.importorskip("playwright.sync_api", reason="needs playwright (the [test] extra)")

CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
FRAME = "#apm-frame"


@pytest.fixture()
def server(tmp_path):
    """``apmgsrn view`` on a free loopback port, in its own process; stopped with Ctrl-C afterwards."""
    folder = make_viewer_folder(tmp_path)
    saves = tmp_path / "saves"
    with running_viewer(folder, tmp_path, "--save-dir", str(saves)) as viewer:
        yield {"url": viewer.url, "saves": saves, "process": viewer.process, "folder": folder}


def _wait_for_complete_frame(page, other_than: str | None = None, timeout_ms: int = 60000) -> str:
    """Wait for a finished (stride 1) image of a generation other than ``other_than``; return its generation."""
    condition = (
        f"(() => {{ const i = document.querySelector('{FRAME}');"
        " return i && i.getAttribute('data-stride') === '1'"
        " && (i.getAttribute('src') || '').startsWith('data:image/png')"
        f" && i.getAttribute('data-generation') !== {repr(str(other_than))}; }})()"
    )
    page.wait_for_function(condition, timeout=timeout_ms)
    return page.get_attribute(FRAME, "data-generation")


def test_viewer_page_end_to_end(server, tmp_path):
    from playwright.sync_api import sync_playwright

    outside_requests = []
    page_errors = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path="/usr/bin/chromium", args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1100, "height": 720}, accept_downloads=True)
            page.on("pageerror", lambda error: page_errors.append(str(error)))
            page.on(
                "request",
                lambda request: None
                if request.url.startswith((server["url"], "data:", "blob:", "ws://127.0.0.1"))
                else outside_requests.append(request.url),
            )
            page.goto(server["url"])

            # The page loads and the first entry (the blob volume) appears, refined to the full image.
            generation = _wait_for_complete_frame(page)
            first = page.get_attribute(FRAME, "src")
            assert "a_blob.npy" in page.inner_text("#apm-source")
            assert "passes 4/4" in page.inner_text("#apm-stats")
            # The link out of the folder is not listed, and the page says so.
            page.click("#apm-skipped summary")
            assert "link_out.npy: symbolic link to a place outside" in page.inner_text("#apm-skipped")

            # A drag changes the image.
            box = page.locator("#apm-viewport").bounding_box()
            x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
            page.mouse.move(x, y)
            page.mouse.down()
            for step in range(1, 8):
                page.mouse.move(x + 25 * step, y + 6 * step)
                time.sleep(0.03)
            page.mouse.up()
            generation = _wait_for_complete_frame(page, other_than=generation)
            dragged = page.get_attribute(FRAME, "src")
            assert dragged != first

            # A colour-map change changes the image.
            page.click("#apm-colormap-select", force=True)
            page.get_by_role("option", name="grayscale", exact=True).click()
            generation = _wait_for_complete_frame(page, other_than=generation)
            assert page.get_attribute(FRAME, "src") != dragged

            # Saving the frame downloads a PNG and keeps a copy on the server.
            with page.expect_download() as download_info:
                page.click("#apm-save-frame")
            downloaded = Path(download_info.value.path())
            assert downloaded.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
            copies = list(server["saves"].glob("*.png"))
            assert len(copies) == 1 and copies[0].read_bytes() == downloaded.read_bytes()

            # The opacity editor: a click on empty space adds a point, a double-click deletes it, and each
            # edit re-renders.
            points = page.locator("#apm-tf-editor circle")
            count = points.count()
            editor = page.locator("#apm-tf-svg").bounding_box()
            page.mouse.click(editor["x"] + editor["width"] * 0.6, editor["y"] + editor["height"] * 0.2)
            page.wait_for_function(f"document.querySelectorAll('#apm-tf-editor circle').length === {count + 1}")
            generation = _wait_for_complete_frame(page, other_than=generation)
            assert len(page.evaluate("window.trame.state.get('opacity_points')")) == count + 1
            added = page.locator("#apm-tf-editor circle").nth(count - 1)  # sorted: before the last node
            added.dblclick()
            page.wait_for_function(f"window.trame.state.get('opacity_points').length === {count}")

            # A ParaView preset upload is parsed and offered, and the transfer function saves as JSON.
            preset = tmp_path / "upload_me.json"
            preset.write_text(
                '[{"Name": "Greens", "ColorSpace": "RGB", "RGBPoints": [0, 0, 0.2, 0, 1, 0.4, 1, 0.4]}]',
                encoding="utf-8",
            )
            page.set_input_files("#apm-upload", str(preset))
            page.wait_for_function("window.trame.state.get('colormap') === 'Greens (uploaded upload_me.json)'")
            generation = _wait_for_complete_frame(page, other_than=generation)
            # An upload over the limit is refused in the page, before it is sent.
            too_large = tmp_path / "too_large.json"
            too_large.write_text(" " * (2 << 20), encoding="utf-8")
            page.set_input_files("#apm-upload", str(too_large))
            page.wait_for_selector("#apm-upload-error", timeout=10000)
            assert "over the upload limit" in page.inner_text("#apm-upload-error")
            with page.expect_download() as download_info:
                page.click("#apm-save-tf")
            saved_tf = json.loads(Path(download_info.value.path()).read_text(encoding="utf-8"))
            assert saved_tf[0]["RGBPoints"][1:4] == [0.0, 0.2, 0.0]  # the uploaded colours (r, g, b)

            # A path outside the folder is refused, in the page, and nothing is opened.
            page.evaluate("window.trame.trigger('viewer_open', ['../secret.npy'])")
            page.wait_for_selector("#apm-error", timeout=10000)
            assert "refused" in page.inner_text("#apm-error")
            assert "a_blob.npy" in page.inner_text("#apm-source")

            # A model that fails to load shows an error; the server keeps serving and rendering.
            page.click("#apm-error .v-alert__close button, #apm-error button")
            page.evaluate("window.trame.trigger('viewer_open', ['broken.apmgsrn'])")
            page.wait_for_function(
                "(() => { const e = document.querySelector('#apm-error');"
                " return e && e.innerText.includes('broken'); })()",
                timeout=30000,
            )
            assert server["process"].poll() is None
            page.click("#apm-reset")
            generation = _wait_for_complete_frame(page, other_than=generation)

            # A model opens from the picker; the grid overlay draws its two grids' twelve edges each.
            page.click("#apm-source-select", force=True)
            page.get_by_role("option", name="tiny.apmgsrn  (model)").click()
            page.wait_for_function("document.querySelector('#apm-source').innerText.includes('tiny.apmgsrn')")
            generation = _wait_for_complete_frame(page, other_than=generation)
            page.click("#apm-overlay-switch")
            page.wait_for_function("document.querySelectorAll('#apm-overlay-svg line').length >= 12")
            assert page.locator("#apm-overlay-svg line").count() <= 24
        finally:
            browser.close()
    assert not page_errors, page_errors
    assert not outside_requests, outside_requests

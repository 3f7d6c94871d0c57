"""Write the web page of a model, open it in headless Chromium (software WebGL2) and report its size, its
load time and its frame time; optionally save a screenshot of the page (docs/web.md's figures).

    .venv/bin/python benchmarks/web_page_measure.py MODEL [--size 256] [--spp 256] \
        [--screenshot docs/images/web_export.png]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

CHROMIUM = "/usr/bin/chromium"
ARGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("--size", type=int, default=256, help="frame width and height (default 256)")
    parser.add_argument("--spp", type=int, default=256, help="samples per ray (default 256)")
    parser.add_argument("--screenshot", help="save a screenshot of the page here (.png)")
    args = parser.parse_args()

    import apmgsrn
    from apmgsrn.web import export_html
    from playwright.sync_api import sync_playwright

    with tempfile.TemporaryDirectory() as folder:
        page_path = Path(folder) / "view.html"
        start = time.perf_counter()
        written = export_html(apmgsrn.load(args.model), page_path, args.model,
                              settings={"width": args.size, "height": args.size, "samples_per_ray": args.spp})
        export_seconds = time.perf_counter() - start
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": args.size + 360, "height": max(args.size + 40, 560)})
            start = time.perf_counter()
            page.goto(page_path.as_uri())
            timings = page.evaluate("() => window.apmgsrn.ready")
            open_seconds = time.perf_counter() - start
            again = page.evaluate("() => window.apmgsrn.render({view: {azimuth: 40}})")
            page.evaluate("() => window.apmgsrn.render({view: {azimuth: 30}})")
            if args.screenshot:
                page.screenshot(path=args.screenshot)
            browser.close()
    print(json.dumps({
        "model": args.model, "model_file_bytes": Path(args.model).stat().st_size, "page_bytes": written["bytes"],
        "page_model_bytes": written["model_bytes"], "export_seconds": round(export_seconds, 2),
        "load_ms": round(timings["loadMs"]), "first_frame_ms": round(timings["frameMs"]), "frame_ms": round(again),
        "open_seconds": round(open_seconds, 2), "size": args.size, "spp": args.spp,
    }))


if __name__ == "__main__":
    main()

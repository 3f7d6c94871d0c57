"""``apmgsrn export MODEL --format html``: one self-contained HTML file that renders a model in a browser.

The page holds the model's arrays (:mod:`apmgsrn.web.scene`), the colour maps the CLI knows baked over
``[0, 1]``, the render settings of ``apmgsrn render``'s defaults, and its own code (``assets/``: the HTML,
the style and the WebGL2 viewer, which writes its GLSL from the model's sizes). It loads nothing: no server,
no network, no code from anywhere else (its Content-Security-Policy forbids every fetch).
"""

from __future__ import annotations

import base64
import json
import os
import zlib
from importlib import resources
from pathlib import Path

import numpy as np

from apmgsrn.atomic import atomic_write, check_output_path, check_suffix
from apmgsrn.errors import ApmgsrnError
from apmgsrn.web.scene import DEFLATE_LEVEL, build_scene, check_finite

#: Entries of each baked colour map over [0, 1] (the page interpolates them linearly, as the renderer's table).
COLORMAP_ENTRIES = 256
#: The render settings of the page, ``apmgsrn render``'s defaults (cli/render.py, rendering.RendererConfig).
DEFAULT_SETTINGS = {
    "width": 512, "height": 512, "samples_per_ray": 256, "reference_samples": 256, "early_termination": 1e-3,
    "background": [1.0, 1.0, 1.0], "colormap": "Cool to Warm", "opacity": [[0.0, 0.0], [1.0, 1.0]],
    "view": {"azimuth": 30.0, "elevation": 20.0, "distance": None, "fov": 30.0},
}


def colormap_names() -> tuple[str, ...]:
    """The colour maps a page offers: the CLI's built-ins."""
    from apmgsrn.rendering.colormaps import BUILTIN_COLORMAPS

    return BUILTIN_COLORMAPS


def baked_colormaps(names: tuple[str, ...] = ()) -> dict:
    """Every built-in colour map evaluated at :data:`COLORMAP_ENTRIES` points of ``[0, 1]``, uint16 RGB,
    deflated into one base64 blob."""
    from apmgsrn.rendering.colormaps import builtin_colormap

    names = names or colormap_names()
    xs = np.linspace(0.0, 1.0, COLORMAP_ENTRIES)
    tables = [np.clip(builtin_colormap(name).evaluate(xs), 0.0, 1.0) for name in names]
    data = np.rint(np.stack(tables) * 65535).astype("<u2").tobytes()
    return {"names": list(names), "entries": COLORMAP_ENTRIES,
            "data": base64.b64encode(zlib.compress(data, DEFLATE_LEVEL)).decode("ascii")}


def _asset(name: str) -> str:
    return resources.files("apmgsrn.web").joinpath("assets", name).read_text(encoding="utf-8")


def _script_json(element_id: str, value) -> str:
    """A JSON value inside a ``<script type="application/json">`` element (``<`` escaped, so no text in it can
    close the element)."""
    text = json.dumps(value, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    return f'<script type="application/json" id="{element_id}">{text}</script>'


def _escape(text: str) -> str:
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;").replace('"', "&quot;")


def page_html(scene: dict, settings: dict, colormaps: dict) -> str:
    """The page's text: the assets with the model, its colour maps and its settings in place."""
    data = "\n".join([_script_json("apm-scene", scene), _script_json("apm-colormaps", colormaps),
                      _script_json("apm-settings", settings)])
    parts = {"@TITLE@": _escape(scene["name"]), "@STYLE@": _asset("page.css"), "@SCRIPT@": _asset("viewer.js"),
             "@DATA@": data}
    text = _asset("page.html")
    for marker, value in parts.items():
        head, sep, tail = text.partition(marker)
        text = head + value + tail if sep else text
    return text


def describe(description) -> str:
    """One line about the model for the page."""
    shape = description.volume_shape
    text = f"{description.model} model of a {shape[2]}x{shape[1]}x{shape[0]} volume"
    if description.series is not None:
        text += f", {len(description.series.steps)} time steps"
    if description.packing is not None:
        text += ", packed"
    low, high = description.value_range
    return text + f"; values {low:.6g} to {high:.6g}"


def export_html(model, path: str | os.PathLike, source: str | os.PathLike, settings: dict | None = None) -> dict:
    """Write the page of a model, atomically.

    Args:
        model: the opened model (``field`` and ``description``, as :func:`apmgsrn.load` gives it).
        path: the ``.html`` file.
        source: the model file it came from (a packed file's integers are read from it again).
        settings: render settings replacing :data:`DEFAULT_SETTINGS`' entries.

    Returns:
        What was written: ``bytes`` (the page), ``model_bytes`` (its coded arrays, before base64), ``notes``.

    Raises:
        ApmgsrnError: a path that is not a new or replaceable ``.html`` file; a brick model; a model kind the
            page cannot render.
    """
    check_suffix(path, (".html",), "web page")
    check_output_path(path, "web page")
    settings = {**DEFAULT_SETTINGS, **(settings or {})}
    scene, blobs, notes = build_scene(Path(source), model, Path(source).name)
    check_finite(scene)
    if settings["colormap"] not in colormap_names():
        raise ApmgsrnError(f"colour map {settings['colormap']!r}: a page offers {', '.join(colormap_names())}")
    scene["blobs"] = blobs.entries
    scene["notes"] = notes
    scene["about"] = describe(model.description)
    text = page_html(scene, settings, baked_colormaps())
    data = text.encode("utf-8")

    def write(temporary: str) -> None:
        Path(temporary).write_bytes(data)

    atomic_write(path, write, "web page")
    return {"path": Path(path), "bytes": len(data), "model_bytes": blobs.coded_bytes, "notes": notes}

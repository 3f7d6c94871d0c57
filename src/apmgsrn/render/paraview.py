"""ParaView colour-map presets (JSON) in and out.

ParaView writes a JSON list of objects; each has ``Name``, ``ColorSpace`` and ``RGBPoints`` (flat
``x, r, g, b`` quadruples), and may have ``Points`` (flat ``x, alpha, midpoint, sharpness`` quadruples,
the opacity), ``NanColor``, ``NanOpacity`` and other keys this module ignores (``Creator``,
``DefaultMap``, annotations). Built-in ParaView presets sit on ``[0, 1]`` and are stretched to the data
range when applied; a transfer function exported from a session keeps its nodes in data units.
:func:`load_transfer_function` tells them apart by the span of ``RGBPoints`` (``units="auto"``).
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path

from apmgsrn.errors import ApmgsrnError
from apmgsrn.render.transfer_function import (
    ColorMap,
    OpacityMap,
    TransferFunction,
    normalize_color_space,
    opacity_from_normalized,
)


@dataclass(frozen=True)
class ParaViewPreset:
    """One entry of a ParaView preset file, node positions as stored in the file."""

    name: str
    color_map: ColorMap
    opacity_map: OpacityMap | None
    nan_opacity: float | None

    @property
    def is_normalized(self) -> bool:
        """True when the colour nodes span exactly [0, 1] (a preset rather than a session export)."""
        lo, hi = self.color_map.span
        return abs(lo) < 1e-9 and abs(hi - 1.0) < 1e-9


def read_presets(path: str | os.PathLike) -> list[ParaViewPreset]:
    """Read every colour-map preset in a ParaView JSON file.

    Args:
        path: a ``.json`` file as ParaView exports it (a list of objects, or a single object).

    Returns:
        The presets with ``RGBPoints``, in file order.

    Raises:
        ApmgsrnError: unreadable file, invalid JSON, or no usable preset.
    """
    path = Path(path)
    try:
        document = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ApmgsrnError(f"{path}: no such file; give an existing ParaView preset .json file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc}); give a ParaView preset .json file") from None
    except json.JSONDecodeError as exc:
        raise ApmgsrnError(
            f"{path}: not valid JSON (line {exc.lineno}: {exc.msg}); export the preset again from ParaView"
        ) from None
    entries = document if isinstance(document, list) else [document]
    presets = []
    for index, entry in enumerate(entries):
        if not isinstance(entry, dict) or "RGBPoints" not in entry:
            continue  # categorical (IndexedColors-only) presets and foreign objects are skipped
        presets.append(_parse_entry(path, index, entry))
    if not presets:
        raise ApmgsrnError(
            f"{path}: no preset with RGBPoints found; export a continuous colour map from ParaView "
            "(categorical presets are not supported)"
        )
    return presets


def _parse_entry(path: Path, index: int, entry: dict) -> ParaViewPreset:
    name = str(entry.get("Name", f"preset {index}"))
    where = f"{path}: preset {name!r}"
    rgb = _numbers(entry["RGBPoints"], where, "RGBPoints")
    if len(rgb) == 0 or len(rgb) % 4:
        raise ApmgsrnError(f"{where}: RGBPoints must hold x,r,g,b quadruples; fix the file or export it again")
    nodes = sorted(tuple(rgb[i : i + 4]) for i in range(0, len(rgb), 4))
    for node in nodes:
        if not all(0.0 <= c <= 1.0 for c in node[1:]):
            raise ApmgsrnError(f"{where}: RGBPoints colours must lie in [0, 1]; fix the file")
    try:
        space = normalize_color_space(str(entry.get("ColorSpace", "RGB")))
    except ValueError as exc:
        raise ApmgsrnError(f"{where}: {exc}") from None
    nan = entry.get("NanColor", [1.0, 1.0, 0.0])
    nan_values = _numbers(nan, where, "NanColor")
    if len(nan_values) < 3:
        raise ApmgsrnError(f"{where}: NanColor must be r,g,b; fix the file")
    color_map = ColorMap(
        points=tuple(nodes), color_space=space, name=name, nan_color=tuple(nan_values[:3])
    )
    opacity = None
    if entry.get("Points"):
        values = _numbers(entry["Points"], where, "Points")
        if len(values) % 4:
            raise ApmgsrnError(
                f"{where}: Points must hold x,alpha,midpoint,sharpness quadruples; fix the file"
            )
        quads = sorted(tuple(values[i : i + 4]) for i in range(0, len(values), 4))
        try:
            opacity = OpacityMap(tuple(quads))
        except ValueError as exc:
            raise ApmgsrnError(f"{where}: {exc}; fix the Points list") from None
    nan_opacity = entry.get("NanOpacity")
    return ParaViewPreset(
        name=name,
        color_map=color_map,
        opacity_map=opacity,
        nan_opacity=None if nan_opacity is None else float(nan_opacity),
    )


def _numbers(values: object, where: str, key: str) -> list[float]:
    if not isinstance(values, list):
        raise ApmgsrnError(f"{where}: {key} must be a list of numbers; fix the file")
    try:
        out = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ApmgsrnError(f"{where}: {key} must be a list of numbers; fix the file") from None
    if not all(math.isfinite(v) for v in out):
        raise ApmgsrnError(f"{where}: {key} holds a non-finite number; fix the file")
    return out


def load_transfer_function(
    path: str | os.PathLike,
    value_range: tuple[float, float] | None,
    name: str | None = None,
    units: str = "auto",
    default_opacity: tuple[tuple[float, float], ...] = ((0.0, 0.0), (1.0, 1.0)),
) -> TransferFunction:
    """A transfer function from a ParaView preset file.

    Args:
        path: the ``.json`` file.
        value_range: the data range ``(min, max)`` a normalised preset is stretched to (None: keep).
        name: which preset of the file (default: the first with ``RGBPoints``).
        units: ``"auto"`` (nodes spanning exactly [0, 1] are a preset and get stretched, other spans are
            data units and kept), ``"normalized"`` (always stretch) or ``"data"`` (never stretch).
        default_opacity: ``(position, alpha)`` pairs on [0, 1] of the final range, used when the preset
            has no ``Points``.

    Returns:
        The transfer function, nodes in data units.

    Raises:
        ApmgsrnError: bad file, unknown preset name, unknown ``units``.
    """
    if units not in ("auto", "normalized", "data"):
        raise ApmgsrnError(f"unknown preset units {units!r}: use auto, normalized or data")
    presets = read_presets(path)
    if name is None:
        preset = presets[0]
    else:
        matches = [p for p in presets if p.name == name] or [
            p for p in presets if p.name.lower() == name.lower()
        ]
        if not matches:
            names = ", ".join(repr(p.name) for p in presets[:10])
            raise ApmgsrnError(f"{path}: no preset named {name!r}; the file has {names}")
        preset = matches[0]
    color_map = preset.color_map
    span = color_map.span
    opacity_span = span if span[1] > span[0] else (span[0], span[0] + 1.0)
    opacity = preset.opacity_map or opacity_from_normalized(default_opacity, opacity_span)
    tf = TransferFunction(
        color_map=color_map,
        opacity_map=opacity,
        nan_opacity=preset.nan_opacity if preset.nan_opacity is not None else 0.0,
        name=preset.name,
    )
    stretch = units == "normalized" or (units == "auto" and preset.is_normalized)
    if stretch and value_range is not None:
        tf = tf.rescaled(*value_range)
    return tf


def transfer_function_to_preset(tf: TransferFunction, name: str | None = None) -> dict:
    """The ParaView preset object for ``tf`` (nodes in data units, like a ParaView session export).

    Args:
        tf: the transfer function.
        name: the ``Name`` to store (default: the transfer function's or colour map's name).

    Returns:
        A JSON-ready dict with Name, ColorSpace, RGBPoints, Points, NanColor and NanOpacity.
    """
    rgb_points = [float(v) for node in tf.color_map.points for v in node]
    opacity_points = [float(v) for node in tf.opacity_map.points for v in node]
    return {
        "Creator": "apmgsrn",
        "Name": name or tf.name or tf.color_map.name,
        "ColorSpace": tf.color_map.color_space,
        "NanColor": [float(c) for c in tf.color_map.nan_color],
        "NanOpacity": float(tf.nan_opacity),
        "RGBPoints": rgb_points,
        "Points": opacity_points,
    }


def _format_presets(presets: list[dict]) -> str:
    """JSON like ParaView writes it: one key per line, number lists on a single line each."""
    blocks = []
    for preset in presets:
        lines = [f"    {json.dumps(key)} : {json.dumps(value)}" for key, value in preset.items()]
        blocks.append("  {\n" + ",\n".join(lines) + "\n  }")
    return "[\n" + ",\n".join(blocks) + "\n]"


def save_transfer_function(tf: TransferFunction, path: str | os.PathLike, name: str | None = None) -> Path:
    """Write ``tf`` as a ParaView preset file (a one-entry list), atomically.

    ParaView's "Import" in the colour-map preset dialog loads it; since the nodes are in data units, tick
    "use preset range" there to keep them.

    Args:
        tf: the transfer function.
        path: the ``.json`` file to write.
        name: the preset's ``Name``.

    Returns:
        The path written.
    """
    path = Path(path)
    text = _format_presets([transfer_function_to_preset(tf, name)])
    directory = path.parent if str(path.parent) else Path(".")
    if not directory.is_dir():
        raise ApmgsrnError(f"{path}: folder {directory} does not exist; create it or choose another path")
    handle, temporary = tempfile.mkstemp(prefix=".tf-", suffix=".json", dir=directory)
    try:
        with os.fdopen(handle, "w", encoding="utf-8") as out:
            out.write(text + "\n")
        os.replace(temporary, path)
    except BaseException:
        Path(temporary).unlink(missing_ok=True)
        raise
    return path

"""ParaView colour-map presets in and out, applied to a value range exactly as ParaView applies them.

Formats read:

- JSON as ParaView writes it: a list of objects (or one object) with ``Name``, ``ColorSpace``,
  ``RGBPoints`` (flat ``x, r, g, b`` quadruples), optional ``Points`` (flat ``x, alpha, midpoint,
  sharpness`` quadruples: the opacity), ``NanColor``, ``NanOpacity``, ``HSVWrap`` and ``UseLogScale``;
  other keys are ignored. Like ParaView's own reader it accepts ``//`` and ``/* */`` comments and trailing
  commas.
- ParaView's legacy XML: ``<ColorMaps>`` holding ``<ColorMap name=".." space="..">`` elements (or one
  ``<ColorMap>``) with ``<Point x r g b o/>`` and ``<NaN r g b/>`` children; ``space="Wrapped"`` is HSV
  with ``HSVWrap``, a missing ``space`` keeps the lookup table's own.

Categorical presets (``IndexedColors`` and no ``RGBPoints``, XML ``indexedLookup="true"``) are skipped:
ParaView applies them by switching the lookup table to categories (annotated values), not to scalar
colouring. A preset with both is read for its ``RGBPoints``: ParaView switches the table to categories for
surfaces, but its volume lookup (like this renderer) uses the nodes.

Applying (:func:`apply_preset`), as ParaView's ``ApplyPreset(name, rescale=True)`` followed by
``RescaleTransferFunction(min, max)``: the colour nodes are sorted by position (nodes at one position keep
their file order), normalised by their own span (in log10 if the preset says ``UseLogScale`` and its span
is positive) and spread linearly over the range; ``Points`` likewise by their own span. ``units="data"``
keeps the nodes where they are (ParaView's "use preset range", ``rescale=False``); there ParaView also
switches the lookup table to log scale when the preset says ``UseLogScale``.

ParaView reads the flags two ways and so does this module: stretching reads ``UseLogScale`` as a boolean
(``true`` or a non-zero number), but the settings it copies onto the lookup table (``UseLogScale`` when
kept in data units, ``HSVWrap`` always) take effect only as numbers (``1``, what ParaView writes), a JSON
``true`` being ignored there. ``HSVWrap`` is off unless the preset sets it. ``ColorSpace`` is matched as
ParaView matches it: exactly ``RGB``, ``HSV``, ``Lab``, ``Diverging`` or ``Step`` (or their number in
ParaView's list); any other spelling is applied as RGB (ParaView does so with its own "CIELAB" preset) and
a missing one as Diverging (the space of ParaView's default lookup table). ``Lab/CIEDE2000`` is refused:
ParaView follows a shortest path through the colour space there, which is not implemented.
"""

from __future__ import annotations

import json
import math
import os
import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass, replace
from pathlib import Path

from apmgsrn.atomic import atomic_write_text
from apmgsrn.choices import PRESET_UNITS
from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.color_spaces import PARAVIEW_COLOR_SPACES
from apmgsrn.rendering.transfer_function import (
    ColorMap,
    OpacityMap,
    TransferFunction,
    opacity_from_normalized,
    stretch_nodes,
)

PRESET_SUFFIXES = (".json", ".xml")

# ParaView's lookup-table defaults for what a preset leaves out.
_DEFAULT_COLOR_SPACE = "Diverging"

# A JSON string, or a comment / a comma right before a closing bracket: what ParaView's reader tolerates.
# An unterminated string or block comment runs to the end of the text: matching it there (instead of failing
# and retrying at every later position) keeps the scan linear on hostile text; json.loads then refuses it.
_STRING = r'"(?:[^"\\]|\\[\s\S]?)*(?:"|\Z)'
_STRING_OR_COMMENT = re.compile(_STRING + r'|//[^\n]*|/\*[\s\S]*?(?:\*/|\Z)')
_STRING_OR_TRAILING_COMMA = re.compile(_STRING + r'|,(?=\s*[\]}])')


@dataclass(frozen=True)
class ParaViewPreset:
    """One continuous entry of a preset file, node positions as stored in the file.

    ``color_map`` holds the nodes sorted by position (ties in file order) and is linear. ParaView's two
    readings of the preset's ``UseLogScale``: ``stretch_in_log`` (normalise the nodes in log10 when
    stretching them over a range) and ``log_scale`` (the lookup table's log scale when the nodes are kept
    in data units).
    """

    name: str
    color_map: ColorMap
    opacity_map: OpacityMap | None
    nan_opacity: float | None
    stretch_in_log: bool = False
    log_scale: bool = False


def read_presets(path: str | os.PathLike) -> list[ParaViewPreset]:
    """Read every continuous colour-map preset of a ParaView JSON or XML file.

    Args:
        path: a ``.json`` file as ParaView exports it (a list of objects, or one object), or a ``.xml``
            file in ParaView's legacy colour-map format.

    Returns:
        The presets with colour nodes, in file order (categorical ones left out).

    Raises:
        ApmgsrnError: unreadable file, invalid JSON/XML, a malformed preset, or no continuous preset.
    """
    path = Path(path)
    return _continuous(path, _read_entries(path))


def parse_presets(text: str, name: str) -> list[ParaViewPreset]:
    """Every continuous preset of a preset file's text, as :func:`read_presets` reads a file.

    Args:
        text: the file's content (e.g. an upload: nothing is written to disk).
        name: the file's name: ``.xml`` selects ParaView's legacy XML, anything else JSON; errors name it.

    Returns:
        The presets with colour nodes, in order.

    Raises:
        ApmgsrnError: invalid JSON/XML, a malformed preset, or no continuous preset.
    """
    label = Path(name)
    return _continuous(label, _parse_entries(label, text))


def _continuous(path: Path, entries: list[ParaViewPreset | str]) -> list[ParaViewPreset]:
    presets = [entry for entry in entries if isinstance(entry, ParaViewPreset)]
    if not presets:
        raise ApmgsrnError(
            f"{path}: no preset with RGBPoints found; export a continuous colour map from ParaView "
            "(categorical presets colour annotated values only and are not supported)"
        )
    return presets


def apply_preset(
    preset: ParaViewPreset,
    value_range: tuple[float, float] | None,
    units: str = "normalized",
    default_opacity: tuple[tuple[float, float], ...] = ((0.0, 0.0), (1.0, 1.0)),
) -> TransferFunction:
    """The transfer function ParaView makes of a preset applied to a range (see the module notes).

    Args:
        preset: from :func:`read_presets`.
        value_range: ``(min, max)``, ``min < max``, in data units; None keeps the preset's own span.
        units: ``"normalized"`` (ParaView's default: stretch the preset over ``value_range``) or
            ``"data"`` (keep the preset's node positions, as saved from a session).
        default_opacity: ``(position, alpha)`` pairs on [0, 1] of the colour range, used when the preset
            has no ``Points``.

    Returns:
        The transfer function, nodes in data units.

    Raises:
        ApmgsrnError: unknown ``units``.
    """
    if units not in PRESET_UNITS:
        raise ApmgsrnError(f"unknown preset units {units!r}: use {' or '.join(PRESET_UNITS)}")
    color_map, opacity_map = preset.color_map, preset.opacity_map
    if units == "normalized" and value_range is not None:
        lo, hi = value_range
        color_map = replace(color_map, points=stretch_nodes(color_map.points, lo, hi, preset.stretch_in_log))
        if opacity_map is not None:
            opacity_map = replace(opacity_map, points=stretch_nodes(opacity_map.points, lo, hi, preset.stretch_in_log))
    elif preset.log_scale:  # kept in data units: ParaView turns the table's log scale on
        color_map = replace(color_map, log_scale=True)
        if opacity_map is not None:
            opacity_map = replace(opacity_map, log_scale=True)
    if opacity_map is None:
        lo, hi = color_map.span
        opacity_map = opacity_from_normalized(default_opacity, (lo, hi if hi > lo else lo + 1.0))
    return TransferFunction(
        color_map=color_map,
        opacity_map=opacity_map,
        nan_opacity=preset.nan_opacity if preset.nan_opacity is not None else 0.0,
        name=preset.name,
    )


def load_transfer_function(
    path: str | os.PathLike,
    value_range: tuple[float, float] | None,
    name: str | None = None,
    units: str = "normalized",
    default_opacity: tuple[tuple[float, float], ...] = ((0.0, 0.0), (1.0, 1.0)),
) -> TransferFunction:
    """A transfer function from a ParaView preset file, applied to a range as ParaView applies it.

    Args:
        path: the ``.json`` or ``.xml`` file.
        value_range: the data range ``(min, max)`` the preset is stretched over (None: keep its span).
        name: which preset of the file (default: the first continuous one). Matched exactly first, then
            ignoring case; like ParaView, the first preset of that name is taken.
        units: ``"normalized"`` or ``"data"``, see :func:`apply_preset`.
        default_opacity: ``(position, alpha)`` pairs on [0, 1] of the colour range, used when the preset
            has no ``Points``.

    Returns:
        The transfer function, nodes in data units.

    Raises:
        ApmgsrnError: bad file, unknown or categorical preset name, unknown ``units``.
    """
    path = Path(path)
    if name is None:
        preset = read_presets(path)[0]
    else:
        entries = _read_entries(path)
        names = [entry.name if isinstance(entry, ParaViewPreset) else entry for entry in entries]
        matches = [i for i, n in enumerate(names) if n == name] or [
            i for i, n in enumerate(names) if n.lower() == name.lower()
        ]
        if not matches:
            listed = ", ".join(repr(n) for n in names[:10])
            raise ApmgsrnError(f"{path}: no preset named {name!r}; the file has {listed}")
        preset = entries[matches[0]]
        if not isinstance(preset, ParaViewPreset):
            raise ApmgsrnError(
                f"{path}: preset {name!r} is categorical (indexed colours), which ParaView applies to "
                "annotated values only, not to scalar colouring; pick a continuous preset"
            )
    return apply_preset(preset, value_range, units, default_opacity)


# ---------------------------------------------------------------------------------------------- reading
def _read_entries(path: Path) -> list[ParaViewPreset | str]:
    """Every preset of a file in order: continuous ones parsed, categorical ones as their name."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ApmgsrnError(f"{path}: no such file; give an existing ParaView preset .json or .xml file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ApmgsrnError(f"{path}: cannot read ({exc}); give a ParaView preset .json or .xml file") from None
    return _parse_entries(path, text)


def _parse_entries(path: Path, text: str) -> list[ParaViewPreset | str]:
    """:func:`_read_entries` of a file's text; ``path`` picks the format and names the file in errors."""
    raw = _xml_entries(path, text) if path.suffix.lower() == ".xml" else _json_entries(path, text)
    entries: list[ParaViewPreset | str] = []
    for index, entry in enumerate(raw):
        if not isinstance(entry, dict):
            continue  # foreign objects in the list
        if "RGBPoints" in entry:
            entries.append(_parse_entry(path, index, entry))
        elif "IndexedColors" in entry:
            entries.append(str(entry.get("Name", f"preset {index}")))
    return entries


def _json_entries(path: Path, text: str) -> list:
    def blank(match: re.Match) -> str:  # keep strings; blank comments, keeping line breaks for messages
        found = match.group(0)
        return found if found.startswith('"') else re.sub(r"[^\n]", " ", found)

    text = _STRING_OR_COMMENT.sub(blank, text)
    text = _STRING_OR_TRAILING_COMMA.sub(lambda m: m.group(0) if m.group(0).startswith('"') else " ", text)
    try:
        document = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ApmgsrnError(
            f"{path}: not valid JSON (line {exc.lineno}: {exc.msg}); export the preset again from ParaView"
        ) from None
    except RecursionError:  # a preset is a list of flat objects; thousands of nested brackets are no preset
        raise ApmgsrnError(f"{path}: JSON nested too deeply to be a ParaView preset; export it again") from None
    return document if isinstance(document, list) else [document]


def _xml_entries(path: Path, text: str) -> list[dict]:
    """ParaView's legacy XML colour maps as the JSON objects ParaView converts them to."""
    try:
        root = ElementTree.fromstring(text)
    except ElementTree.ParseError as exc:
        raise ApmgsrnError(f"{path}: not valid XML ({exc}); export the colour map again") from None
    if root.tag == "ColorMap":
        elements = [root]
    elif root.tag == "ColorMaps":
        elements = [e for e in root if e.tag == "ColorMap" and e.get("name") is not None]
    else:
        raise ApmgsrnError(f"{path}: expected <ColorMaps> or <ColorMap> at the top, found <{root.tag}>")
    entries = []
    for element in elements:
        name = element.get("name", "")
        where = f"{path}: colour map {name!r}"
        if element.get("indexedLookup", "false") == "true":
            entries.append({"Name": name, "IndexedColors": []})
            continue
        entry: dict = {"Name": name}
        space = element.get("space")
        if space == "Wrapped":
            entry.update(ColorSpace="HSV", HSVWrap=1)
        elif space is not None:
            entry["ColorSpace"] = space
        nan = element.find("NaN")
        if nan is not None and all(nan.get(c) is not None for c in "rgb"):
            entry["NanColor"] = [_xml_number(nan, c, where) for c in "rgb"]
        points = [
            [_xml_number(p, c, where) for c in "xrgb"]
            for p in element
            if p.tag == "Point" and all(p.get(c) is not None for c in "xrgb")
        ]
        if points:
            entry["RGBPoints"] = [v for point in sorted(points, key=lambda p: p[0]) for v in point]
        entries.append(entry)
    return entries


def _xml_number(element: ElementTree.Element, attribute: str, where: str) -> float:
    try:
        return float(element.get(attribute))
    except ValueError:
        raise ApmgsrnError(
            f"{where}: <{element.tag}> attribute {attribute}={element.get(attribute)!r} is not a number; fix the file"
        ) from None


def _parse_entry(path: Path, index: int, entry: dict) -> ParaViewPreset:
    name = str(entry.get("Name", f"preset {index}"))
    where = f"{path}: preset {name!r}"
    rgb = _numbers(entry["RGBPoints"], where, "RGBPoints")
    if len(rgb) == 0 or len(rgb) % 4:
        raise ApmgsrnError(f"{where}: RGBPoints must hold x,r,g,b quadruples; fix the file or export it again")
    # Sorted by position only, so nodes sharing a position keep their file order (ParaView does the same).
    nodes = sorted((tuple(rgb[i : i + 4]) for i in range(0, len(rgb), 4)), key=lambda node: node[0])
    for node in nodes:
        if not all(0.0 <= c <= 1.0 for c in node[1:]):
            raise ApmgsrnError(f"{where}: RGBPoints colours must lie in [0, 1]; fix the file")
    if len(nodes) > 1 and nodes[0][0] == nodes[-1][0]:
        raise ApmgsrnError(f"{where}: all RGBPoints sit at {nodes[0][0]:g}; give nodes at two or more positions")
    nan_values = _numbers(entry.get("NanColor", [1.0, 1.0, 0.0]), where, "NanColor")  # ParaView's: yellow
    if len(nan_values) < 3:
        raise ApmgsrnError(f"{where}: NanColor must be r,g,b; fix the file")
    color_map = ColorMap(
        points=tuple(nodes),
        color_space=_color_space(entry.get("ColorSpace"), where),
        name=name,
        nan_color=tuple(nan_values[:3]),
        hsv_wrap=_setting(entry.get("HSVWrap")),
    )
    opacity = None
    if entry.get("Points"):
        values = _numbers(entry["Points"], where, "Points")
        if len(values) % 4:
            raise ApmgsrnError(f"{where}: Points must hold x,alpha,midpoint,sharpness quadruples; fix the file")
        quads = sorted((tuple(values[i : i + 4]) for i in range(0, len(values), 4)), key=lambda node: node[0])
        if len(quads) > 1 and quads[0][0] == quads[-1][0]:
            raise ApmgsrnError(f"{where}: all Points sit at {quads[0][0]:g}; give nodes at two or more positions")
        try:
            opacity = OpacityMap(tuple(quads))
        except ValueError as exc:
            raise ApmgsrnError(f"{where}: {exc}; fix the Points list") from None
    nan_opacity = entry.get("NanOpacity")
    if nan_opacity is not None:
        nan_opacity = _numbers([nan_opacity], where, "NanOpacity")[0]
    return ParaViewPreset(
        name=name,
        color_map=color_map,
        opacity_map=opacity,
        nan_opacity=nan_opacity,
        stretch_in_log=_boolean(entry.get("UseLogScale", False), where, "UseLogScale"),
        log_scale=_setting(entry.get("UseLogScale")),
    )


def _color_space(value: object, where: str) -> str:
    """ParaView's reading of ``ColorSpace``: its exact names or their number; anything else is RGB."""
    if value is None:
        return _DEFAULT_COLOR_SPACE
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < len(PARAVIEW_COLOR_SPACES):
        value = PARAVIEW_COLOR_SPACES[value]
    if value == "Lab/CIEDE2000":
        raise ApmgsrnError(
            f"{where}: colour space Lab/CIEDE2000 is not supported (ParaView follows a shortest path through "
            "Lab there); choose Lab in ParaView and export the preset again"
        )
    return value if value in PARAVIEW_COLOR_SPACES else "RGB"


def _boolean(value: object, where: str, key: str) -> bool:
    """A flag as ParaView reads it when stretching: true/false or a number (non-zero: on)."""
    if value is None or isinstance(value, (bool, int, float)):
        return bool(value)
    raise ApmgsrnError(f"{where}: {key} must be true/false or a number (ParaView writes 0 or 1); fix the file")


def _setting(value: object) -> bool:
    """A flag as ParaView copies it onto its lookup table: a number or numeric text; true/false are ignored."""
    if isinstance(value, bool) or value is None:
        return False
    try:
        return float(value) != 0.0
    except (TypeError, ValueError):
        return False


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


# ---------------------------------------------------------------------------------------------- writing
def transfer_function_to_preset(tf: TransferFunction, name: str | None = None) -> dict:
    """The ParaView preset object for ``tf`` (nodes in data units, like a ParaView session export).

    Args:
        tf: the transfer function.
        name: the ``Name`` to store (default: the transfer function's or colour map's name).

    Returns:
        A JSON-ready dict with Name, ColorSpace, RGBPoints, Points, NanColor and NanOpacity, plus HSVWrap
        and UseLogScale when they are on.
    """
    preset = {
        "Creator": "apmgsrn",
        "Name": name or tf.name or tf.color_map.name,
        "ColorSpace": tf.color_map.color_space,
        "NanColor": [float(c) for c in tf.color_map.nan_color],
        "NanOpacity": float(tf.nan_opacity),
        "RGBPoints": [float(v) for node in tf.color_map.points for v in node],
        "Points": [float(v) for node in tf.opacity_map.points for v in node],
    }
    if tf.color_map.hsv_wrap:
        preset["HSVWrap"] = 1
    if tf.color_map.log_scale:
        preset["UseLogScale"] = True
    return preset


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
    "use preset range" there (here: ``units="data"``) to keep them.

    Args:
        tf: the transfer function.
        path: the ``.json`` file to write.
        name: the preset's ``Name``.

    Returns:
        The path written.
    """
    text = _format_presets([transfer_function_to_preset(tf, name)])
    return atomic_write_text(path, text + "\n", "transfer function")

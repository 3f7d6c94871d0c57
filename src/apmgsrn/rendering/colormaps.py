"""Built-in colour maps, each with nodes on [0, 1] (a preset, stretched to the data range when used), and
:func:`make_transfer_function`, which turns a map name or a ParaView preset file into a transfer function.

ParaView's default "Cool to Warm" has the nodes and Diverging space of ParaView's own preset (its two
end colours and the light grey between them). "grayscale" is a linear RGB ramp. The matplotlib maps
(viridis, plasma, inferno, magma, cividis, coolwarm, jet, turbo, and any other name matplotlib knows) are
sampled at 256 nodes with RGB interpolation; matplotlib is imported only when one of them is asked for.
Cool to Warm, grayscale, viridis, plasma, inferno, magma and turbo give ParaView's colours for its presets
of those names within 1/255 (tested against ParaView); matplotlib's jet and coolwarm are not ParaView's
"Jet" and "Cool to Warm" (use ParaView's preset file for those).
"""

from __future__ import annotations

import re

import numpy as np

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.paraview import PRESET_SUFFIXES, load_transfer_function
from apmgsrn.rendering.transfer_function import ColorMap, TransferFunction, opacity_from_normalized

# ParaView's default colour map ("Cool to Warm" preset): three nodes, Diverging space.
COOL_TO_WARM = ColorMap(
    points=(
        (0.0, 0.23137254902, 0.298039215686, 0.752941176471),
        (0.5, 0.865, 0.865, 0.865),
        (1.0, 0.705882352941, 0.0156862745098, 0.149019607843),
    ),
    color_space="Diverging",
    name="Cool to Warm",
    nan_color=(1.0, 1.0, 0.0),
)

GRAYSCALE = ColorMap(
    points=((0.0, 0.0, 0.0, 0.0), (1.0, 1.0, 1.0, 1.0)),
    color_space="RGB",
    name="Grayscale",
    nan_color=(1.0, 0.0, 0.0),
)

_MATPLOTLIB_MAPS = ("viridis", "plasma", "inferno", "magma", "cividis", "coolwarm", "jet", "turbo")

# Names a user may type (compared without case, spaces, dashes, underscores or a "(matplotlib)" suffix).
_ALIASES = {
    "cooltowarm": "Cool to Warm",
    "paraview": "Cool to Warm",
    "default": "Cool to Warm",
    "grayscale": "Grayscale",
    "greyscale": "Grayscale",
    "gray": "Grayscale",
    "grey": "Grayscale",
    **{name: name for name in _MATPLOTLIB_MAPS},
}

BUILTIN_COLORMAPS = ("Cool to Warm", "grayscale", *_MATPLOTLIB_MAPS)


def _key(name: str) -> str:
    name = re.sub(r"\(matplotlib\)", "", name.lower())
    return re.sub(r"[\s_\-]+", "", name)


def builtin_colormap(name: str) -> ColorMap:
    """A built-in colour map by name, nodes on [0, 1].

    Args:
        name: e.g. ``"viridis"``, ``"Cool to Warm"``, ``"grayscale"``, ``"jet"``, or any matplotlib name.

    Returns:
        The colour map.

    Raises:
        ApmgsrnError: when no such map exists.
    """
    canonical = _ALIASES.get(_key(name))
    if canonical == "Cool to Warm":
        return COOL_TO_WARM
    if canonical == "Grayscale":
        return GRAYSCALE
    return _from_matplotlib(canonical or name.strip())


def _from_matplotlib(name: str) -> ColorMap:
    import matplotlib  # about a second to import: only when one of its maps is asked for

    try:
        cmap = matplotlib.colormaps[name]
    except KeyError:
        raise ApmgsrnError(
            f"unknown colour map {name!r}: use one of {', '.join(BUILTIN_COLORMAPS)}, "
            "another matplotlib name, or a ParaView preset .json file"
        ) from None
    xs = np.linspace(0.0, 1.0, 256)
    rgba = cmap(xs)  # [256, 4]
    points = tuple((float(x), float(c[0]), float(c[1]), float(c[2])) for x, c in zip(xs, rgba))
    bad = cmap.get_bad()
    return ColorMap(points=points, color_space="RGB", name=name, nan_color=(float(bad[0]), float(bad[1]), float(bad[2])))


def make_transfer_function(
    colormap: str = "Cool to Warm",
    value_range: tuple[float, float] = (0.0, 1.0),
    opacity: tuple[tuple[float, float], ...] | None = None,
    preset_name: str | None = None,
    preset_units: str = "normalized",
    default_opacity: tuple[tuple[float, float], ...] = ((0.0, 0.0), (1.0, 1.0)),
) -> TransferFunction:
    """A transfer function from a colour-map name or a ParaView preset file, over a value range.

    Args:
        colormap: a built-in name (see ``BUILTIN_COLORMAPS``), a matplotlib name, or a path to a ParaView
            ``.json`` or ``.xml`` preset file.
        value_range: ``(min, max)`` in data units the map is stretched to (unless ``preset_units`` is
            ``"data"``).
        opacity: ``(position, alpha)`` pairs on [0, 1] of the final range; None keeps a preset's own
            opacity, else uses ``default_opacity``.
        preset_name: which preset of a multi-preset file.
        preset_units: ``normalized`` (ParaView's default) or ``data`` (keep a preset's own node positions,
            as saved from a session); see ``paraview.apply_preset``.
        default_opacity: the opacity of a built-in map, and of a preset that has none: a linear ramp over the
            range, transparent at the minimum.

    Returns:
        The transfer function, nodes in data units.
    """
    lo, hi = value_range
    if not hi > lo:
        hi = lo + 1.0  # a constant volume: any non-empty range shows it
    if colormap.lower().endswith(PRESET_SUFFIXES):
        tf = load_transfer_function(
            colormap, (lo, hi), name=preset_name, units=preset_units, default_opacity=default_opacity
        )
    else:
        color_map = builtin_colormap(colormap)
        tf = TransferFunction(
            color_map=color_map,
            opacity_map=opacity_from_normalized(default_opacity, color_map.span),
            name=color_map.name,
        ).rescaled(lo, hi)
    if opacity is not None:
        tf = tf.with_opacity(opacity_from_normalized(opacity, tf.value_range))
    return tf

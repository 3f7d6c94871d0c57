"""What the viewer's image depends on besides the camera and the source: the settings the page sends, checked,
and the colour maps on offer, turned into a transfer function."""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering import BUILTIN_COLORMAPS, OpacityMap, RendererConfig, TransferFunction, make_transfer_function
from apmgsrn.rendering.paraview import ParaViewPreset, apply_preset
from apmgsrn.rendering.progressive import check_strides
from apmgsrn.rendering.transfer_function import stretch_nodes
from apmgsrn.sources import SourceOptions

# An opacity node as the viewer keeps it: (position on [0, 1] of the value range, opacity, midpoint,
# sharpness). Midpoint and sharpness shape the curve to the next node as in ParaView (0.5, 0: a line).
OpacityNode = tuple[float, float, float, float]


@dataclass(frozen=True)
class PageLimits:
    """What the page may ask for (the session refuses anything else), and the sizes its menus offer."""

    samples_per_ray: tuple[int, int] = (1, 4096)
    batch_size: tuple[int, int] = (16, 1 << 24)
    image_size: tuple[int, int] = (16, 2048)
    opacity_nodes: int = 256
    image_sizes: tuple[int, ...] = (128, 192, 256, 384, 512, 768, 1024)
    batch_sizes: tuple[int, ...] = tuple(1 << k for k in range(12, 23))  # 4096 .. 4194304 points per forward pass


PAGE = PageLimits()


def _viewer_sources() -> SourceOptions:
    # Raw volumes are held in memory: refuse larger ones (512 MiB float32). The histogram is drawn under
    # the opacity editor.
    return SourceOptions(max_volume_voxels=1 << 27, histogram_bins=64, histogram_lattice=40)


@dataclass(frozen=True)
class ViewerConfig:
    """What the viewer starts with and how it schedules work."""

    image_width: int = 256
    image_height: int = 256
    samples_per_ray: int = 128
    batch_size: int = 1 << 16
    strides: tuple[int, ...] = (8, 4, 2, 1)  # lattice strides of the progressive passes
    interactive_seconds: float = 0.15  # time budget of one image while the view moves
    rest_seconds: float = 0.35  # the view rests this long after its last camera event
    chunk_pixels: int = 2048  # pixels rendered between two checks for a newer generation
    macro_cells: int = 16  # empty-space skipping cells per axis (coarse: bounds of a model are sampled)
    colormap: str = "Cool to Warm"
    # the lowest fifth of the range (mostly background in scientific volumes) transparent, then a ramp, so the
    # first image shows structure rather than a fog
    opacity: tuple[tuple[float, float], ...] = ((0.0, 0.0), (0.2, 0.0), (1.0, 0.8))
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    source: SourceOptions = field(default_factory=_viewer_sources)

    def __post_init__(self) -> None:
        check_strides(self.strides)


@dataclass(frozen=True)
class RenderSettings:
    """Everything except the camera and the source that decides the image."""

    colormap: str
    opacity: tuple[OpacityNode, ...]
    value_range: tuple[float, float]
    samples_per_ray: int
    batch_size: int
    image_width: int
    image_height: int
    overlay: bool = False

    @classmethod
    def initial(cls, config: ViewerConfig) -> "RenderSettings":
        """The settings a viewer starts with."""
        return cls(
            colormap=config.colormap,
            opacity=linear_nodes(config.opacity),
            value_range=(0.0, 1.0),
            samples_per_ray=config.samples_per_ray,
            batch_size=config.batch_size,
            image_width=config.image_width,
            image_height=config.image_height,
        )

    def renderer_config(self, config: ViewerConfig) -> RendererConfig:
        """The renderer settings of these settings under a viewer config."""
        return RendererConfig(
            samples_per_ray=self.samples_per_ray,
            batch_size=self.batch_size,
            macro_cells=config.macro_cells,
            background=config.background,
        )


@dataclass(frozen=True)
class ColormapChoice:
    """A colour map the page offers: a built-in one, or a preset of a ParaView file (parsed once)."""

    key: str  # what the page shows and sends back
    builtin: str | None = None
    preset: ParaViewPreset | None = None
    opacity: tuple[OpacityNode, ...] | None = None  # the preset's own opacity, nodes on [0, 1]


class ColormapLibrary:
    """The colour maps on offer (built-ins first, then presets as they are added); safe from any thread."""

    def __init__(self, max_choices: int = 4096) -> None:
        """Args:
        max_choices: colour maps offered at most (a preset file may hold thousands; the list goes to
            every page).
        """
        self.max_choices = max_choices
        self._lock = threading.Lock()
        self._choices: dict[str, ColormapChoice] = {
            name: ColormapChoice(name, builtin=name) for name in BUILTIN_COLORMAPS
        }

    def keys(self) -> list[str]:
        """Names of the colour maps on offer, built-ins first."""
        with self._lock:
            return list(self._choices)

    def choice(self, key: str) -> ColormapChoice:
        """The colour map of a key.

        Raises:
            ApmgsrnError: unknown key.
        """
        with self._lock:
            choice = self._choices.get(key) if isinstance(key, str) else None
        if choice is None:
            raise ApmgsrnError(f"unknown colour map {key!r}; pick one from the list")
        return choice

    def add_presets(self, presets: list[ParaViewPreset], label: str) -> list[str]:
        """Offer presets read from a ParaView file.

        Args:
            presets: from :func:`apmgsrn.rendering.read_presets`.
            label: shown after each preset's name (e.g. the file's catalog name).

        Returns:
            The new colour-map keys (a key offered before is replaced).

        Raises:
            ApmgsrnError: the library would hold more than ``max_choices`` colour maps.
        """
        choices = []
        for preset in presets:
            opacity = None
            if preset.opacity_map is not None:
                # ParaView stretches a preset's opacity by the opacity nodes' own span (in log10 when the
                # preset says UseLogScale), whatever the colour nodes span: normalise it the same way.
                opacity = tuple(
                    (float(x), float(a), float(m), float(s))
                    for x, a, m, s in stretch_nodes(preset.opacity_map.points, 0.0, 1.0, preset.stretch_in_log)
                )
            key = f"{preset.name} ({label})"
            choices.append(ColormapChoice(key, preset=preset, opacity=opacity))
        with self._lock:
            added = {choice.key for choice in choices} - set(self._choices)
            if len(self._choices) + len(added) > self.max_choices:
                raise ApmgsrnError(
                    f"{label}: {len(added)} more colour maps would pass the limit of {self.max_choices}; "
                    "keep fewer presets beside the data"
                )
            for choice in choices:
                self._choices[choice.key] = choice
        return [choice.key for choice in choices]

    def transfer_function(self, settings: RenderSettings) -> TransferFunction:
        """The transfer function of some settings, in data units.

        A preset's colours are applied as ``apmgsrn render --colormap FILE`` applies them (ParaView's
        apply-and-rescale over the value range); the opacity is the settings' nodes over the same range.

        Raises:
            ApmgsrnError: unknown colour map.
        """
        choice = self.choice(settings.colormap)
        low, high = settings.value_range
        if choice.preset is not None:
            tf = apply_preset(choice.preset, (low, high))
        else:
            tf = make_transfer_function(choice.builtin or choice.key, (low, high))
        return with_opacity_nodes(tf, settings.opacity)


def linear_nodes(pairs) -> tuple[OpacityNode, ...]:
    """Opacity nodes joined by straight lines from ``(position, opacity)`` pairs."""
    return tuple((float(x), float(a), 0.5, 0.0) for x, a in pairs)


def editor_points(nodes: tuple[OpacityNode, ...]) -> list[list[float]]:
    """The ``[position, opacity]`` pairs the page's opacity editor shows for some nodes."""
    return [[node[0], node[1]] for node in nodes]


def with_opacity_nodes(tf: TransferFunction, opacity: tuple[OpacityNode, ...]) -> TransferFunction:
    """``tf`` with opacity nodes given on [0, 1] of its value range.

    Args:
        tf: a transfer function (its colour map's span is the value range).
        opacity: ``(position, alpha, midpoint, sharpness)`` nodes, positions on [0, 1].

    Returns:
        The transfer function with an opacity map through those nodes, in data units.
    """
    low, high = tf.value_range
    # The arithmetic of ParaView's rescale (position * span + low), so nodes land where 'render' puts them.
    nodes = tuple((x * (high - low) + low, a, m, s) for x, a, m, s in opacity)
    return tf.with_opacity(OpacityMap(nodes))


def finite_number(value) -> float:
    """A finite float from what the page sent, or a user error."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ApmgsrnError(f"expected a number, got {value!r}") from None
    if not math.isfinite(number):
        raise ApmgsrnError(f"expected a finite number, got {value!r}")
    return number


def whole_number(value, low: int, high: int, what: str) -> int:
    """An integer in ``[low, high]`` from what the page sent, or a user error naming ``what``."""
    count = int(finite_number(value))
    if not low <= count <= high:
        raise ApmgsrnError(f"{what} {count} is outside {low}..{high}")
    return count


def opacity_points(points) -> tuple[tuple[float, float], ...]:
    """Opacity nodes from the page: 1 to 256 ``(position, opacity)`` pairs, clamped to [0, 1], sorted."""
    if not isinstance(points, (list, tuple)) or not points or len(points) > PAGE.opacity_nodes:
        raise ApmgsrnError(f"opacity needs 1 to {PAGE.opacity_nodes} points (position, opacity)")
    clean = []
    for point in points:
        if not isinstance(point, (list, tuple)) or len(point) != 2:
            raise ApmgsrnError(f"opacity point {point!r} is not a (position, opacity) pair")
        x, a = finite_number(point[0]), finite_number(point[1])
        clean.append((min(1.0, max(0.0, x)), min(1.0, max(0.0, a))))
    return tuple(sorted(clean, key=lambda p: p[0]))


def usable_range(value_range: tuple[float, float]) -> tuple[float, float]:
    """A data range widened to a non-empty one (a constant volume gets ``[v, v + 1]``)."""
    low, high = float(value_range[0]), float(value_range[1])
    return (low, high) if high > low else (low, low + 1.0)

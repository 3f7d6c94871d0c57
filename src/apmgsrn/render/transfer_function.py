"""Transfer functions: a colour map and a piecewise opacity map over the value range, in data units.

A :class:`TransferFunction` is a plain value (frozen dataclass) in ParaView's terms: colour nodes
``(x, r, g, b)`` with a colour space for the interpolation between them, and opacity nodes
``(x, alpha, midpoint, sharpness)``. The renderer never evaluates it node by node: it bakes it into a
:class:`TransferTable` (a dense lookup table on the device, as VTK's volume mappers do) and interpolates
that table linearly. Every question the empty-space skipping asks ("is the opacity zero over this value
interval?") is answered from the same table, so a skipped sample is exactly a sample whose opacity is 0.

Opacity meaning: ``alpha`` is the opacity of a slab one *reference step* thick (see ``RendererConfig``);
the renderer corrects it for the actual step length.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from apmgsrn.render.color_spaces import SUPPORTED_COLOR_SPACES, interpolate_colors

_SPACE_ALIASES = {
    "rgb": "RGB",
    "lab": "Lab",
    "cielab": "Lab",
    "lab/ciede2000": "Lab",  # approximated by plain Lab interpolation
    "diverging": "Diverging",
    "hsv": "HSV",
    "step": "Step",
}


def normalize_color_space(name: str) -> str:
    """Canonical spelling of a colour-space name (ParaView's ``ColorSpace``), case-insensitive.

    Args:
        name: e.g. ``"RGB"``, ``"lab"``, ``"Diverging"``.

    Returns:
        One of ``SUPPORTED_COLOR_SPACES``.

    Raises:
        ValueError: for a name not in the list.
    """
    key = name.strip().lower()
    if key not in _SPACE_ALIASES:
        raise ValueError(
            f"unknown colour space {name!r}: use one of {', '.join(SUPPORTED_COLOR_SPACES)}"
        )
    return _SPACE_ALIASES[key]


@dataclass(frozen=True)
class ColorMap:
    """Colour nodes ``(x, r, g, b)`` (x ascending, colours sRGB in [0, 1]) and how to blend between them."""

    points: tuple[tuple[float, float, float, float], ...]
    color_space: str = "RGB"
    name: str = "custom"
    nan_color: tuple[float, float, float] = (1.0, 1.0, 0.0)

    def __post_init__(self) -> None:
        if len(self.points) == 0:
            raise ValueError("a colour map needs at least one point")
        xs = [p[0] for p in self.points]
        if any(b < a for a, b in zip(xs, xs[1:])):
            raise ValueError("colour map points must be sorted by value")
        object.__setattr__(self, "color_space", normalize_color_space(self.color_space))

    @property
    def span(self) -> tuple[float, float]:
        return float(self.points[0][0]), float(self.points[-1][0])

    def evaluate(self, values: np.ndarray) -> np.ndarray:
        """Colours at values (clamped to the end nodes beyond the span).

        Args:
            values: ``[N]`` values in the map's units.

        Returns:
            ``[N, 3]`` sRGB in [0, 1], float64.
        """
        values = np.asarray(values, dtype=np.float64)
        nodes = np.asarray(self.points, dtype=np.float64)  # [P, 4]
        if len(nodes) == 1:
            return np.repeat(nodes[:1, 1:], len(values), axis=0)
        segment, t = _locate(nodes[:, 0], values)
        out = np.empty((len(values), 3))
        for k in np.unique(segment):
            mask = segment == k
            out[mask] = interpolate_colors(nodes[k, 1:], nodes[k + 1, 1:], t[mask], self.color_space)
        return np.clip(out, 0.0, 1.0)

    def mapped(self, old: tuple[float, float], new: tuple[float, float]) -> "ColorMap":
        """The same map with its node positions moved linearly from range ``old`` to range ``new``."""
        return replace(self, points=tuple((_remap(p[0], old, new), *p[1:]) for p in self.points))


@dataclass(frozen=True)
class OpacityMap:
    """Opacity nodes ``(x, alpha, midpoint, sharpness)`` as ParaView's ``Points`` (x ascending).

    Between two nodes the curve follows VTK's piecewise function: ``midpoint`` (0..1) is where the curve
    reaches half way, ``sharpness`` 0 is linear and 1 a step. With the defaults 0.5 / 0 it is linear.
    """

    points: tuple[tuple[float, float, float, float], ...]

    def __post_init__(self) -> None:
        if len(self.points) == 0:
            raise ValueError("an opacity map needs at least one point")
        clean = []
        for p in self.points:
            x, a = float(p[0]), float(p[1])
            mid = float(p[2]) if len(p) > 2 else 0.5
            sharp = float(p[3]) if len(p) > 3 else 0.0
            if not 0.0 <= a <= 1.0:
                raise ValueError(f"opacity {a} is outside [0, 1]")
            clean.append((x, a, min(max(mid, 1e-5), 1.0 - 1e-5), min(max(sharp, 0.0), 1.0)))
        if any(b[0] < a[0] for a, b in zip(clean, clean[1:])):
            raise ValueError("opacity points must be sorted by value")
        object.__setattr__(self, "points", tuple(clean))

    @property
    def span(self) -> tuple[float, float]:
        return float(self.points[0][0]), float(self.points[-1][0])

    def evaluate(self, values: np.ndarray) -> np.ndarray:
        """Opacity at values (clamped to the end nodes beyond the span).

        Args:
            values: ``[N]`` values in the map's units.

        Returns:
            ``[N]`` opacities in [0, 1], float64.
        """
        values = np.asarray(values, dtype=np.float64)
        nodes = np.asarray(self.points, dtype=np.float64)  # [P, 4]
        if len(nodes) == 1:
            return np.full(len(values), nodes[0, 1])
        segment, s = _locate(nodes[:, 0], values)
        y0, y1 = nodes[segment, 1], nodes[segment + 1, 1]
        mid, sharp = nodes[segment, 2], nodes[segment, 3]
        # Move the half-way point to `mid` (VTK's vtkPiecewiseFunction convention).
        s = np.where(s < mid, 0.5 * s / mid, 0.5 + 0.5 * (s - mid) / (1.0 - mid))
        linear = (1.0 - s) * y0 + s * y1
        step = np.where(s < 0.5, y0, y1)
        # Sharpness in (0, 1): squeeze s towards the ends, then a Hermite blend whose end slopes shrink
        # with the sharpness; the curve stays monotone between the two node values.
        power = 1.0 + 10.0 * sharp
        squeezed = np.where(
            s < 0.5,
            0.5 * np.power(np.clip(2.0 * s, 0.0, None), power),
            1.0 - 0.5 * np.power(np.clip(2.0 * (1.0 - s), 0.0, None), power),
        )
        ss, sss = squeezed**2, squeezed**3
        h1 = 2 * sss - 3 * ss + 1
        h2 = -2 * sss + 3 * ss
        h3 = sss - 2 * ss + squeezed
        h4 = sss - ss
        tangent = (1.0 - sharp) * (y1 - y0)
        hermite = h1 * y0 + h2 * y1 + (h3 + h4) * tangent
        hermite = np.clip(hermite, np.minimum(y0, y1), np.maximum(y0, y1))
        out = np.where(sharp < 0.01, linear, np.where(sharp > 0.99, step, hermite))
        return np.clip(out, 0.0, 1.0)

    def mapped(self, old: tuple[float, float], new: tuple[float, float]) -> "OpacityMap":
        """The same map with its node positions moved linearly from range ``old`` to range ``new``."""
        return OpacityMap(tuple((_remap(p[0], old, new), *p[1:]) for p in self.points))


@dataclass(frozen=True)
class TransferFunction:
    """A colour map plus an opacity map, both with node positions in data units.

    ``nan_opacity`` is the opacity given to NaN samples (colour: the colour map's ``nan_color``).
    """

    color_map: ColorMap
    opacity_map: OpacityMap
    nan_opacity: float = 0.0
    name: str = field(default="")

    @property
    def value_range(self) -> tuple[float, float]:
        """The colour map's span: what ParaView calls the transfer function's range."""
        return self.color_map.span

    def rescaled(self, value_min: float, value_max: float) -> "TransferFunction":
        """Stretch colour and opacity nodes together so the colour map spans ``[value_min, value_max]``.

        Args:
            value_min, value_max: the new range in data units (``value_max > value_min``).

        Returns:
            A new transfer function (ParaView's "rescale to data range").
        """
        if not (math.isfinite(value_min) and math.isfinite(value_max)) or value_max <= value_min:
            raise ValueError(f"invalid value range {value_min}, {value_max}: need MIN < MAX")
        old = self.value_range
        new = (float(value_min), float(value_max))
        return replace(self, color_map=self.color_map.mapped(old, new), opacity_map=self.opacity_map.mapped(old, new))

    def with_opacity(self, opacity_map: OpacityMap) -> "TransferFunction":
        """The same colours with another opacity map (its nodes in data units)."""
        return replace(self, opacity_map=opacity_map)

    def table(self, size: int = 4096, device: torch.device | str = "cpu") -> "TransferTable":
        """Bake into a lookup table of ``size`` entries on ``device``."""
        return TransferTable.from_transfer_function(self, size=size, device=device)


def opacity_from_normalized(
    pairs: list[tuple[float, float]] | tuple[tuple[float, float], ...], value_range: tuple[float, float]
) -> OpacityMap:
    """An opacity map from ``(position, alpha)`` pairs with positions in [0, 1] of ``value_range``.

    Args:
        pairs: ``[(x0, a0), (x1, a1), ...]``, x ascending in [0, 1] (0 = range minimum).
        value_range: ``(min, max)`` in data units.

    Returns:
        The opacity map in data units, linear between the nodes.
    """
    lo, hi = value_range
    return OpacityMap(tuple((lo + float(x) * (hi - lo), float(a), 0.5, 0.0) for x, a in pairs))


@dataclass
class TransferTable:
    """A transfer function baked for the renderer: ``size`` entries evenly over ``[value_min, value_max]``.

    Values are mapped to a fractional entry index and the table interpolated linearly between entries;
    outside the range the end entries hold (clamping, as ParaView does).
    """

    colors: torch.Tensor  # [T, 3]
    opacity: torch.Tensor  # [T]
    value_min: float
    value_max: float
    nan_color: torch.Tensor  # [3]
    nan_opacity: float
    _nonzero_prefix: torch.Tensor  # [T + 1] count of entries with opacity > 0 before each index

    def __post_init__(self) -> None:
        # Colour and opacity side by side, so a lookup gathers one row per neighbouring entry.
        self._rgba = torch.cat([self.colors, self.opacity[:, None]], dim=1).contiguous()  # [T, 4]
        nan_opacity = torch.tensor([self.nan_opacity], dtype=torch.float32, device=self.colors.device)
        self._nan_rgba = torch.cat([self.nan_color, nan_opacity])  # [4]

    @classmethod
    def from_transfer_function(
        cls, tf: TransferFunction, size: int = 4096, device: torch.device | str = "cpu"
    ) -> "TransferTable":
        """Sample ``tf`` on ``size`` values spanning both its colour and opacity nodes."""
        if size < 2:
            raise ValueError("a transfer table needs at least 2 entries")
        lo = min(tf.color_map.span[0], tf.opacity_map.span[0])
        hi = max(tf.color_map.span[1], tf.opacity_map.span[1])
        if hi <= lo:  # a single value: any width works, the map is constant on both sides
            hi = lo + 1.0
        xs = np.linspace(lo, hi, size)
        colors = torch.tensor(tf.color_map.evaluate(xs), dtype=torch.float32, device=device)
        opacity = torch.tensor(tf.opacity_map.evaluate(xs), dtype=torch.float32, device=device)
        prefix = torch.zeros(size + 1, dtype=torch.int64, device=device)
        prefix[1:] = torch.cumsum((opacity > 0).to(torch.int64), dim=0)
        return cls(
            colors=colors,
            opacity=opacity,
            value_min=float(lo),
            value_max=float(hi),
            nan_color=torch.tensor(tf.color_map.nan_color, dtype=torch.float32, device=device),
            nan_opacity=float(tf.nan_opacity),
            _nonzero_prefix=prefix,
        )

    @property
    def size(self) -> int:
        return int(self.opacity.shape[0])

    def entry_position(self, values: torch.Tensor) -> torch.Tensor:
        """Fractional table index of each value, clamped to ``[0, size - 1]`` (NaN stays NaN)."""
        scale = (self.size - 1) / (self.value_max - self.value_min)
        return ((values - self.value_min) * scale).clamp(0.0, self.size - 1)

    def lookup(self, values: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Colour and (reference-step) opacity of each value.

        Args:
            values: ``[N]`` float values in data units.

        Returns:
            ``([N, 3] colours, [N] opacities)``.
        """
        position = self.entry_position(values)
        nan = torch.isnan(position)
        # Branch-free NaN handling: asking whether any NaN is present would stall a GPU every call.
        position = torch.where(nan, torch.zeros_like(position), position)
        low = position.to(torch.int64).clamp_(max=self.size - 2)  # truncation is floor: position >= 0
        frac = (position - low.to(position.dtype))[:, None]  # [N, 1]
        rgba = torch.lerp(self._rgba[low], self._rgba[low + 1], frac)  # [N, 4]
        rgba = torch.where(nan[:, None], self._nan_rgba, rgba)
        colors, opacity = rgba[:, :3], rgba[:, 3]
        return colors, opacity

    def opacity_nonzero_between(self, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        """Whether any value in ``[low, high]`` can get a non-zero opacity from :meth:`lookup`.

        The interpolated table is zero on an interval exactly when every entry it touches is zero; the
        entry range is widened by one on each side so rounding in the field's own arithmetic can never
        push a value onto a non-zero entry unnoticed. NaN bounds count as visible when NaN is.

        Args:
            low, high: ``[M]`` interval ends in data units.

        Returns:
            ``[M]`` bool, True where the interval may be visible.
        """
        start = self.entry_position(low).nan_to_num(0.0).floor().to(torch.int64) - 1
        stop = self.entry_position(high).nan_to_num(float(self.size - 1)).ceil().to(torch.int64) + 1
        start = start.clamp(0, self.size - 1)
        stop = stop.clamp(0, self.size - 1)
        visible = (self._nonzero_prefix[stop + 1] - self._nonzero_prefix[start]) > 0
        if self.nan_opacity > 0:
            visible |= torch.isnan(low) | torch.isnan(high)
        return visible


def _locate(xs: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Segment index ``[N]`` and position in it ``[N]`` (0..1) of each value among sorted nodes ``xs``."""
    clamped = np.clip(values, xs[0], xs[-1])
    segment = np.clip(np.searchsorted(xs, clamped, side="right") - 1, 0, len(xs) - 2)
    x0, x1 = xs[segment], xs[segment + 1]
    width = x1 - x0
    t = np.where(width > 0, (clamped - x0) / np.where(width > 0, width, 1.0), 1.0)
    return segment, np.clip(t, 0.0, 1.0)


def _remap(x: float, old: tuple[float, float], new: tuple[float, float]) -> float:
    if old[1] == old[0]:
        return new[0] if x <= old[0] else new[1]
    return new[0] + (float(x) - old[0]) * (new[1] - new[0]) / (old[1] - old[0])

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

from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.color_spaces import SUPPORTED_COLOR_SPACES, interpolate_colors

_SPACE_ALIASES = {name.lower(): name for name in SUPPORTED_COLOR_SPACES} | {"cielab": "Lab"}


def normalize_color_space(name: str) -> str:
    """Canonical spelling of a colour-space name, case-insensitive (for names typed in code or a CLI).

    Preset files are read by ParaView's stricter rules instead (see ``paraview.py``).

    Args:
        name: e.g. ``"RGB"``, ``"lab"``, ``"Diverging"``.

    Returns:
        One of ``SUPPORTED_COLOR_SPACES``.

    Raises:
        ValueError: for a name not in the list.
    """
    key = name.strip().lower()
    if key not in _SPACE_ALIASES:
        raise ValueError(f"unknown colour space {name!r}: use one of {', '.join(SUPPORTED_COLOR_SPACES)}")
    return _SPACE_ALIASES[key]


def rescale_positions(
    xs: np.ndarray, value_min: float, value_max: float, from_log: bool = False, to_log: bool = False
) -> np.ndarray:
    """Node positions stretched onto ``[value_min, value_max]`` the way ParaView does it.

    ParaView normalises the nodes to [0, 1] by their own span (in log10 when ``from_log`` and the span is
    positive; a span of exactly [0, 1] is left as it is), then maps [0, 1] onto the new range (in log10
    when ``to_log``). The arithmetic is ParaView's, so node positions agree with its own to the last bit
    and a value exactly on a node gets the same side of it.

    Args:
        xs: ``[P]`` sorted node positions, ``P >= 2``, not all equal.
        value_min, value_max: the new range, ``value_min < value_max``.
        from_log: the nodes are spaced in log10 (a preset's ``UseLogScale``).
        to_log: space them in log10 over the new range (a log-scale colour map).

    Returns:
        ``[P]`` new positions.

    Raises:
        ApmgsrnError: ``to_log`` with a range that is not positive.
    """
    xs = np.asarray(xs, dtype=np.float64)
    if from_log and not (xs[0] > 0 and xs[-1] > 0):
        from_log = False  # ParaView: "range not valid for log", taken as linear
    t = np.log10(xs) if from_log else xs.copy()
    if not (t[0] == 0.0 and t[-1] == 1.0):
        t = (t - t[0]) / (t[-1] - t[0])
    if not to_log:
        return t * (value_max - value_min) + value_min
    if not (value_min > 0 and value_max > 0):
        raise ApmgsrnError(
            f"value range {value_min:g}..{value_max:g} is not positive, but this transfer function uses a log "
            "scale; give a positive range (value_range=(MIN, MAX)) or a linear preset", arguments=("value_range",)
        )
    low, high = math.log10(value_min), math.log10(value_max)
    return np.power(10.0, t * (high - low) + low)


def _segments(xs: np.ndarray, values: np.ndarray, log_scale: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each value falls among sorted nodes, by VTK's rules.

    A value at or below the first node takes the first node, one above the last the last; any other
    value lies in the segment ending at the first node at or above it, so a value exactly on a node (or
    on the first of several nodes at one position) belongs to the segment below. With a log scale (and
    positive nodes) the position within the segment is measured in log10, as VTK does.

    Args:
        xs: ``[P]`` sorted node positions, ``P >= 2``.
        values: ``[N]`` finite values.
        log_scale: measure positions in log10.

    Returns:
        ``upper [N]`` index of the first node at or above each value (0: at or below the first node,
        ``P``: above the last), ``inside [N]`` whether a value is strictly inside the nodes' span or on a
        node after the first, and ``t [N]`` its position in its segment (0..1; 0 where not inside).
    """
    upper = np.searchsorted(xs, values, side="left")
    inside = (upper > 0) & (upper < len(xs))
    k = np.clip(upper, 1, len(xs) - 1)
    x0, x1 = xs[k - 1], xs[k]  # x0 < x1 wherever inside
    v = values
    if log_scale and xs[0] > 0:  # every node positive, and so every value inside a segment
        v, x0, x1 = np.log10(np.where(inside, values, 1.0)), np.log10(x0), np.log10(x1)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(inside, (v - x0) / np.where(inside, x1 - x0, 1.0), 0.0)
    return upper, inside, t


@dataclass(frozen=True)
class ColorMap:
    """Colour nodes ``(x, r, g, b)`` (x ascending, colours sRGB in [0, 1]) and how to blend between them.

    Several nodes may share a position (a sharp change): they keep their given order, the first one
    colouring the value itself and the segment below, the last one the segment above. ``hsv_wrap`` makes
    the HSV space take the short way round the hue circle; ``log_scale`` measures positions between
    nodes in log10 (ParaView's "use log scale when mapping data to colours").
    """

    points: tuple[tuple[float, float, float, float], ...]
    color_space: str = "RGB"
    name: str = "custom"
    nan_color: tuple[float, float, float] = (1.0, 1.0, 0.0)
    hsv_wrap: bool = False
    log_scale: bool = False

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
        """Colours at values, as ParaView's lookup table gives them (VTK's ``GetTable``).

        Values beyond the span take the end nodes' colours; NaN takes ``nan_color``.

        Args:
            values: ``[N]`` values in the map's units.

        Returns:
            ``[N, 3]`` sRGB in [0, 1], float64.
        """
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        nodes = np.asarray(self.points, dtype=np.float64)  # [P, 4]
        out = np.repeat(nodes[:1, 1:], len(values), axis=0)  # [N, 3]; also the answer for a single node
        nan = np.isnan(values)
        out[nan] = self.nan_color
        if len(nodes) > 1:
            finite = np.flatnonzero(~nan)
            upper, inside, t = _segments(nodes[:, 0], values[finite], self.log_scale)
            out[finite[upper >= len(nodes)]] = nodes[-1, 1:]
            k = upper[inside]
            out[finite[inside]] = interpolate_colors(
                nodes[k - 1, 1:], nodes[k, 1:], t[inside], self.color_space, self.hsv_wrap
            )
        return out

    def rescaled(self, value_min: float, value_max: float) -> "ColorMap":
        """The same map stretched over ``[value_min, value_max]`` as ParaView's "rescale" does it.

        Nodes are normalised by their own span and spread over the new range (in log10 with
        ``log_scale``). A range equal to the span leaves the map as it is; a single node becomes two, one
        at each end.
        """
        return replace(self, points=_rescaled_nodes(self.points, value_min, value_max, self.log_scale))


def stretch_nodes(
    points: tuple, value_min: float, value_max: float, from_log: bool = False, to_log: bool = False
) -> tuple:
    """Nodes (position first) spread over ``[value_min, value_max]`` with :func:`rescale_positions`.

    A single node becomes two, one at each end, as in ParaView.

    Raises:
        ApmgsrnError: several nodes all at one position (nothing to stretch), or see :func:`rescale_positions`.
    """
    if len(points) == 1:
        ends = rescale_positions([0.0, 1.0], value_min, value_max, to_log=to_log)
        return tuple((float(x), *points[0][1:]) for x in ends)
    xs = np.array([p[0] for p in points], dtype=np.float64)
    if not xs[-1] > xs[0]:
        raise ApmgsrnError(
            f"all {len(points)} nodes sit at {xs[0]:g}, so they cannot be stretched over a range; "
            "give nodes at two or more positions"
        )
    moved = rescale_positions(xs, value_min, value_max, from_log, to_log)
    return tuple((float(x), *p[1:]) for x, p in zip(moved, points))


def _rescaled_nodes(points: tuple, value_min: float, value_max: float, log_scale: bool) -> tuple:
    """ParaView's "rescale" of a function: untouched when already on the range, else :func:`stretch_nodes`."""
    if len(points) > 1 and points[0][0] == value_min and points[-1][0] == value_max:
        return points
    return stretch_nodes(points, value_min, value_max, log_scale, log_scale)


@dataclass(frozen=True)
class OpacityMap:
    """Opacity nodes ``(x, alpha, midpoint, sharpness)`` as ParaView's ``Points`` (x ascending).

    Between two nodes the curve follows VTK's piecewise function: ``midpoint`` (0..1) is where the curve
    reaches half way, ``sharpness`` 0 is linear and 1 a step. With the defaults 0.5 / 0 it is linear.
    ``log_scale`` measures positions in log10, as a ParaView opacity function with ``UseLogScale`` does.
    """

    points: tuple[tuple[float, float, float, float], ...]
    log_scale: bool = False

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
            if not (0.0 <= mid <= 1.0 and 0.0 <= sharp <= 1.0):
                raise ValueError(f"midpoint {mid} and sharpness {sharp} must lie in [0, 1]")
            clean.append((x, a, mid, sharp))
        if any(b[0] < a[0] for a, b in zip(clean, clean[1:])):
            raise ValueError("opacity points must be sorted by value")
        object.__setattr__(self, "points", tuple(clean))

    @property
    def span(self) -> tuple[float, float]:
        return float(self.points[0][0]), float(self.points[-1][0])

    def evaluate(self, values: np.ndarray) -> np.ndarray:
        """Opacity at values (the end nodes' beyond the span; NaN gives NaN, the caller decides).

        Args:
            values: ``[N]`` values in the map's units.

        Returns:
            ``[N]`` opacities in [0, 1], float64.
        """
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        nodes = np.asarray(self.points, dtype=np.float64)  # [P, 4]
        out = np.full(len(values), nodes[0, 1])
        out[np.isnan(values)] = np.nan
        if len(nodes) == 1:
            return out
        finite = np.flatnonzero(~np.isnan(values))
        upper, inside, s = _segments(nodes[:, 0], values[finite], self.log_scale)
        out[finite[upper >= len(nodes)]] = nodes[-1, 1]
        k = upper[inside]
        s = s[inside]
        y0, y1 = nodes[k - 1, 1], nodes[k, 1]
        # The segment's shape comes from its lower node; VTK keeps the midpoint off the very ends.
        mid = np.clip(nodes[k - 1, 2], 1e-5, 1.0 - 1e-5)
        sharp = nodes[k - 1, 3]
        s = np.where(s < mid, 0.5 * s / mid, 0.5 + 0.5 * (s - mid) / (1.0 - mid))
        linear = (1.0 - s) * y0 + s * y1
        step = np.where(s < 0.5, y0, y1)
        # Sharpness in (0, 1): squeeze s towards the ends, then a Hermite blend whose end slopes shrink
        # with the sharpness.
        power = 1.0 + 10.0 * sharp
        squeezed = np.where(
            s < 0.5,
            0.5 * np.power(np.clip(2.0 * s, 0.0, None), power),
            np.where(s > 0.5, 1.0 - 0.5 * np.power(np.clip(2.0 * (1.0 - s), 0.0, None), power), s),
        )
        ss, sss = squeezed**2, squeezed**3
        tangent = (1.0 - sharp) * (y1 - y0)
        hermite = (2 * sss - 3 * ss + 1) * y0 + (-2 * sss + 3 * ss) * y1 + (2 * sss - 3 * ss + squeezed) * tangent
        hermite = np.clip(hermite, np.minimum(y0, y1), np.maximum(y0, y1))  # VTK keeps it between the nodes
        out[finite[inside]] = np.where(sharp > 0.99, step, np.where(sharp < 0.01, linear, hermite))
        return np.clip(out, 0.0, 1.0)

    def rescaled(self, value_min: float, value_max: float) -> "OpacityMap":
        """The same map stretched over ``[value_min, value_max]`` by its own span, as ParaView does."""
        return replace(self, points=_rescaled_nodes(self.points, value_min, value_max, self.log_scale))


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
        """Stretch colour and opacity nodes over ``[value_min, value_max]`` (ParaView's "rescale").

        As in ParaView, each map is stretched by its own span, so both end up spanning the new range.

        Args:
            value_min, value_max: the new range in data units (``value_max > value_min``).

        Returns:
            A new transfer function.
        """
        if not (math.isfinite(value_min) and math.isfinite(value_max)) or value_max <= value_min:
            raise ValueError(f"invalid value range {value_min}, {value_max}: need MIN < MAX")
        return replace(
            self,
            color_map=self.color_map.rescaled(value_min, value_max),
            opacity_map=self.opacity_map.rescaled(value_min, value_max),
        )

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
    """A transfer function baked for the renderer: ``size`` entries over ``[value_min, value_max]``.

    Entries are evenly spaced in value, or in log10 of the value for a log-scale colour map over a positive
    range (so every decade gets its share). Values are mapped to a fractional entry index and the table
    interpolated linearly between entries; outside the range the end entries hold (clamping, as ParaView
    does).
    """

    colors: torch.Tensor  # [T, 3]
    opacity: torch.Tensor  # [T]
    value_min: float
    value_max: float
    nan_color: torch.Tensor  # [3]
    nan_opacity: float
    _nonzero_prefix: torch.Tensor  # [T + 1] count of entries with opacity > 0 before each index
    log_scale: bool = False

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
        log_scale = tf.color_map.log_scale and lo > 0
        xs = np.logspace(math.log10(lo), math.log10(hi), size) if log_scale else np.linspace(lo, hi, size)
        xs[0], xs[-1] = lo, hi  # exactly the ends, whatever the rounding of logspace
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
            log_scale=log_scale,
        )

    @property
    def size(self) -> int:
        return int(self.opacity.shape[0])

    def entry_position(self, values: torch.Tensor) -> torch.Tensor:
        """Fractional table index of each value, clamped to ``[0, size - 1]`` (NaN stays NaN)."""
        if self.log_scale:
            # Values at or below 0 clamp to the first entry, as VTK's log lookup does; NaN stays NaN.
            low = math.log10(self.value_min)
            scale = (self.size - 1) / (math.log10(self.value_max) - low)
            tiny = torch.finfo(values.dtype).tiny
            return ((torch.log10(values.clamp_min(tiny)) - low) * scale).clamp(0.0, self.size - 1)
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

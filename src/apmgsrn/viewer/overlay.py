"""Wire-frame boxes drawn over a rendered frame: the learned feature grids (the paper's figure 1) and the
brick borders of a brick model.

Box corners are projected with the very camera that rendered the frame (pinhole model of
:class:`apmgsrn.rendering.Camera`: pixel centres at ``(column + 0.5, row + 0.5)`` of the image plane), so an
edge lands exactly where the volume's features are. Edges that cross behind the camera are clipped at a
near plane instead of being dropped, so a box the camera sits inside still shows its visible part.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from apmgsrn.rendering import Camera

# The 12 edges of a box: corner pairs whose indices differ in exactly one bit (x: 1, y: 2, z: 4).
BOX_EDGES = tuple((a, a | bit) for a in range(8) for bit in (1, 2, 4) if not a & bit)

# Distinct colours for the grids (Okabe-Ito palette: readable for colour-blind viewers).
GRID_COLORS = (
    (230, 159, 0),
    (86, 180, 233),
    (0, 158, 115),
    (240, 228, 66),
    (0, 114, 178),
    (213, 94, 0),
    (204, 121, 167),
)


@dataclass(frozen=True)
class OverlayConfig:
    """How the boxes are drawn."""

    line_width: int = 1
    near: float = 1e-3  # clip plane in front of the camera, world units
    brick_color: tuple[int, int, int] = (0, 0, 0)  # black, a colour no grid gets


def project(camera: Camera, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Image positions of world points.

    Args:
        camera: the camera that rendered the frame.
        points: ``[N, 3]`` world coordinates.

    Returns:
        ``(positions [N, 2] as (column, row) in pixel-index units, depth [N] along the view direction)``;
        positions are meaningless where depth <= 0.
    """
    forward, right, up = camera.basis()
    relative = points.to(torch.float64) - torch.tensor(camera.position, dtype=torch.float64)  # [N, 3]
    depth = relative @ forward  # [N]
    x = relative @ right
    y = relative @ up
    half_height = math.tan(math.radians(camera.fov) / 2.0)
    half_width = half_height * camera.width / camera.height
    safe = torch.where(depth.abs() < 1e-12, torch.full_like(depth, 1e-12), depth)
    u = x / (safe * half_width)  # [-1, 1] across the image
    v = y / (safe * half_height)
    # Inverse of Camera.rays: u = ((column + 0.5) / W * 2 - 1) * half_width, v likewise from the top row.
    column = (u + 1.0) * 0.5 * camera.width - 0.5
    row = (1.0 - v) * 0.5 * camera.height - 0.5
    return torch.stack([column, row], dim=1), depth


def box_segments(
    camera: Camera, boxes: torch.Tensor, near: float = 1e-3
) -> list[tuple[int, tuple[float, float, float, float]]]:
    """Image-space line segments of the edges of boxes, clipped to the space in front of the camera.

    Args:
        camera: the view.
        boxes: ``[B, 8, 3]`` world corners (corner ``k``: x from bit 0, y from bit 1, z from bit 2).
        near: distance of the clip plane.

    Returns:
        ``(box index, (column0, row0, column1, row1))`` per visible edge.
    """
    if boxes.numel() == 0:
        return []
    corners = boxes.reshape(-1, 3).to(torch.float64)
    forward, _, _ = camera.basis()
    eye = torch.tensor(camera.position, dtype=torch.float64)
    depth = (corners - eye) @ forward  # [B * 8]
    segments = []
    for box in range(boxes.shape[0]):
        for a, b in BOX_EDGES:
            i, j = box * 8 + a, box * 8 + b
            p, q = corners[i], corners[j]
            dp, dq = float(depth[i]), float(depth[j])
            if dp < near and dq < near:
                continue
            # Move the end behind the clip plane onto it (linear in depth along the edge).
            if dp < near:
                p = p + (q - p) * ((near - dp) / (dq - dp))
            elif dq < near:
                q = q + (p - q) * ((near - dq) / (dp - dq))
            ends, _ = project(camera, torch.stack([p, q]))
            segments.append((box, (float(ends[0, 0]), float(ends[0, 1]), float(ends[1, 0]), float(ends[1, 1]))))
    return segments


def overlay_lines(
    camera: Camera,
    grid_boxes: torch.Tensor | None = None,
    brick_boxes: torch.Tensor | None = None,
    extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
    config: OverlayConfig = OverlayConfig(),
) -> list[tuple[float, float, float, float, tuple[int, int, int]]]:
    """The overlay's line segments in image coordinates, clipped to (just beyond) the image.

    Args:
        camera: the camera of the frame.
        grid_boxes: ``[M, 8, 3]`` feature-grid corners in field coordinates ([-1, 1]^3), or None.
        brick_boxes: ``[B, 8, 3]`` brick corners in field coordinates, or None.
        extent: half sizes of the drawn box (world = field coordinates * extent), as the renderer used.
        config: clip-plane settings and the bricks' colour.

    Returns:
        ``(column0, row0, column1, row1, rgb)`` per edge, pixel-index units (pixel ``c`` is centred on
        ``c``); brick edges first, grid edges after them (drawn on top).
    """
    scale = torch.tensor(extent, dtype=torch.float32)
    layers = []
    if brick_boxes is not None:
        layers.append((brick_boxes, lambda index: config.brick_color))
    if grid_boxes is not None:
        layers.append((grid_boxes, lambda index: GRID_COLORS[index % len(GRID_COLORS)]))
    lines = []
    for boxes, color_of in layers:
        for index, segment in box_segments(camera, boxes.float().cpu() * scale, config.near):
            # Ends far off the image (a corner next to the eye) would overflow integer drawing.
            clipped = clip_segment(segment, (-2.0, -2.0, camera.width + 1.0, camera.height + 1.0))
            if clipped is not None:
                lines.append((*clipped, color_of(index)))
    return lines


def draw_boxes(
    image: np.ndarray,
    camera: Camera,
    grid_boxes: torch.Tensor | None = None,
    brick_boxes: torch.Tensor | None = None,
    extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
    config: OverlayConfig = OverlayConfig(),
) -> np.ndarray:
    """Draw grid and brick boxes onto a frame (what a saved frame holds; the page draws them as SVG).

    Args:
        image: ``[H, W, 3]`` uint8 frame rendered with ``camera``.
        camera, grid_boxes, brick_boxes, extent, config: as for :func:`overlay_lines`.

    Returns:
        A new ``[H, W, 3]`` uint8 image with the boxes drawn (bricks first, grids on top).
    """
    from PIL import Image, ImageDraw

    canvas = Image.fromarray(np.ascontiguousarray(image, dtype=np.uint8))
    draw = ImageDraw.Draw(canvas)
    for x0, y0, x1, y1, color in overlay_lines(camera, grid_boxes, brick_boxes, extent, config):
        # Pixel-index coordinates: the nearest pixel centre (PIL would truncate).
        ends = [(int(round(x0)), int(round(y0))), (int(round(x1)), int(round(y1)))]
        draw.line(ends, fill=color, width=config.line_width)
    return np.asarray(canvas).copy()


def clip_segment(
    segment: tuple[float, float, float, float], window: tuple[float, float, float, float]
) -> tuple[float, float, float, float] | None:
    """Clip a 2-D segment to a rectangle (Liang-Barsky).

    Args:
        segment: ``(x0, y0, x1, y1)``.
        window: ``(x_min, y_min, x_max, y_max)``.

    Returns:
        The part inside the rectangle, or None when none is.
    """
    x0, y0, x1, y1 = segment
    dx, dy = x1 - x0, y1 - y0
    t_low, t_high = 0.0, 1.0
    for p, q in ((-dx, x0 - window[0]), (dx, window[2] - x0), (-dy, y0 - window[1]), (dy, window[3] - y0)):
        if p == 0.0:
            if q < 0.0:
                return None  # parallel to this border and outside it
            continue
        t = q / p
        if p < 0.0:
            t_low = max(t_low, t)
        else:
            t_high = min(t_high, t)
        if t_low > t_high:
            return None
    return (x0 + t_low * dx, y0 + t_low * dy, x0 + t_high * dx, y0 + t_high * dy)

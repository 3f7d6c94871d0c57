"""Grid and brick boxes over a frame: projection consistent with the renderer's rays, clipping, drawing."""

from __future__ import annotations

import numpy as np
import torch

from apmgsrn.rendering import Camera
from apmgsrn.viewer.overlay import BOX_EDGES, box_segments, clip_segment, draw_boxes, project
from apmgsrn.sources import routing_boxes


def _cube(half: float = 1.0) -> torch.Tensor:
    corners = [[(-half, half)[(k >> axis) & 1] for axis in range(3)] for k in range(8)]
    return torch.tensor([corners], dtype=torch.float32)  # [1, 8, 3]


def test_projection_inverts_the_cameras_rays():
    camera = Camera.orbit(35.0, 25.0, 4.0, fov=40.0, width=64, height=48)
    pixels = torch.tensor([0, 17, 64 * 20 + 31, 64 * 48 - 1])
    origins, directions = camera.rays(pixels)
    points = origins + 2.5 * directions  # somewhere along each pixel's ray
    positions, depth = project(camera, points)
    expected = torch.stack([pixels % 64, pixels // 64], dim=1).to(torch.float64)
    assert torch.allclose(positions, expected, atol=1e-3)
    assert (depth > 0).all()


def test_a_cube_in_front_gives_twelve_edges_and_a_camera_inside_clips_them():
    outside = Camera.orbit(30.0, 20.0, 5.0, width=32, height=32)
    assert len(box_segments(outside, _cube())) == len(BOX_EDGES) == 12
    inside = Camera(position=(0.0, -0.5, 0.0), target=(0.0, 1.0, 0.0), width=32, height=32)
    segments = box_segments(inside, _cube())
    # Edges entirely behind the eye are dropped; edges crossing the eye's plane are kept, clipped.
    assert 4 <= len(segments) < 12
    assert all(np.isfinite(s).all() for _, s in segments)


def test_draw_boxes_marks_the_projected_edges_only():
    camera = Camera.orbit(0.0, 0.0, 6.0, width=64, height=64)
    white = np.full((64, 64, 3), 255, dtype=np.uint8)
    drawn = draw_boxes(white, camera, grid_boxes=_cube(0.5))
    changed = (drawn != 255).any(axis=2)
    assert changed.any()
    # Seen straight from -y, the cube's front face is a square around the centre; its left edge sits
    # at the projected x = -0.5 corner, and the centre stays clean.
    corners, _ = project(camera, torch.tensor([[-0.5, -0.5, 0.5], [-0.5, -0.5, -0.5]]))
    left_column = int(round(float(corners[0, 0])))
    top, bottom = int(corners[0, 1]) + 1, int(corners[1, 1])
    assert bottom - top > 15
    assert changed[top:bottom, left_column].all()
    assert not changed[28:36, 28:36].any()
    assert (white == 255).all()  # the input is left alone


def test_brick_boxes_tile_the_domain():
    boxes = routing_boxes((2, 1, 3))
    assert boxes.shape == (6, 8, 3)
    assert torch.allclose(boxes.amin(dim=(0, 1)), torch.tensor([-1.0, -1.0, -1.0]))
    assert torch.allclose(boxes.amax(dim=(0, 1)), torch.tensor([1.0, 1.0, 1.0]))
    volumes = (boxes.amax(dim=1) - boxes.amin(dim=1)).prod(dim=1)
    assert torch.allclose(volumes.sum(), torch.tensor(8.0))  # no overlap, no gap


def test_clip_segment():
    window = (0.0, 0.0, 10.0, 10.0)
    assert clip_segment((-5.0, 5.0, 15.0, 5.0), window) == (0.0, 5.0, 10.0, 5.0)
    assert clip_segment((2.0, 2.0, 3.0, 3.0), window) == (2.0, 2.0, 3.0, 3.0)
    assert clip_segment((-5.0, -5.0, -1.0, 20.0), window) is None
    assert clip_segment((1e9, 5.0, -1e9, 5.0), window) == (10.0, 5.0, 0.0, 5.0)

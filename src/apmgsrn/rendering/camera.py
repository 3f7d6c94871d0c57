"""Pinhole cameras and the rays through their pixels.

World space is the space of the volume's box. With ``extent = (1, 1, 1)`` it is the field's own
``[-1, 1]^3``; a non-cubic volume is drawn with its true proportions by a box ``[-e, e]`` with
``e = extent`` (longest side 1), the field being queried at ``world / extent``.

Orbit convention (``Camera.orbit``): +z is up; azimuth 0 and elevation 0 look from -y towards +y with
+x to the right; positive azimuth turns the camera counter-clockwise seen from above, positive elevation
raises it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from apmgsrn.limits import LIMITS
from apmgsrn.arguments import check_int, check_number
from apmgsrn.errors import InvalidArgument


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: where it is, what it looks at, vertical field of view, image size in pixels."""

    position: tuple[float, float, float]
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    fov: float = 30.0
    width: int = 512
    height: int = 512

    def __post_init__(self) -> None:
        check_int("width", self.width, 1, LIMITS.image_side)
        check_int("height", self.height, 1, LIMITS.image_side)
        check_number("fov", self.fov, 0.0, 180.0, low_open=True, high_open=True)
        for name in ("position", "target", "up"):
            vector = getattr(self, name)
            if len(vector) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in vector):
                raise InvalidArgument(f"{name}={vector!r}: must be three finite numbers", arguments=(name,))
        if math.dist(self.position, self.target) == 0.0:
            raise ValueError("camera position and target coincide")

    @classmethod
    def orbit(
        cls,
        azimuth: float = 30.0,
        elevation: float = 20.0,
        distance: float | None = None,
        fov: float = 30.0,
        width: int = 512,
        height: int = 512,
        extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
    ) -> "Camera":
        """A camera on a sphere around the box centre, looking at it.

        Args:
            azimuth: degrees around +z (0: from -y).
            elevation: degrees above the xy plane.
            distance: from the centre, world units; None fits the box's bounding sphere in the view.
            fov: vertical field of view, degrees.
            width, height: image size in pixels.
            extent: the box's half sizes (for the automatic distance).

        Returns:
            The camera.
        """
        check_number("azimuth", azimuth)
        check_number("elevation", elevation)
        check_number("fov", fov, 0.0, 180.0, low_open=True, high_open=True)
        check_int("width", width, 1, LIMITS.image_side)
        check_int("height", height, 1, LIMITS.image_side)
        if distance is None:
            distance = fit_distance(fov, width, height, extent)
        check_number("distance", distance, 0.0, low_open=True)
        az, el = math.radians(azimuth), math.radians(elevation)
        position = (
            distance * math.cos(el) * math.sin(az),
            -distance * math.cos(el) * math.cos(az),
            distance * math.sin(el),
        )
        # Looking straight down or up: +z cannot be the up vector, use the azimuth's forward direction.
        up = (0.0, 0.0, 1.0)
        if abs(math.cos(el)) < 1e-6:
            up = (-math.sin(az) * math.copysign(1.0, el), math.cos(az) * math.copysign(1.0, el), 0.0)
        return cls(position=position, up=up, fov=fov, width=width, height=height)

    def basis(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Unit vectors ``(forward, right, up)`` of the view, float64 ``[3]`` each."""
        eye = torch.tensor(self.position, dtype=torch.float64)
        forward = torch.tensor(self.target, dtype=torch.float64) - eye
        forward = forward / forward.norm()
        up = torch.tensor(self.up, dtype=torch.float64)
        right = torch.linalg.cross(forward, up)
        if right.norm() < 1e-9:
            raise ValueError("camera up vector is parallel to the viewing direction")
        right = right / right.norm()
        true_up = torch.linalg.cross(right, forward)
        return forward, right, true_up

    def rays(
        self, pixels: torch.Tensor, device: torch.device | str = "cpu"
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays through pixel centres.

        Args:
            pixels: ``[N]`` int64 linear pixel indices, ``row * width + column``, row 0 at the top.
            device: where to put the rays.

        Returns:
            ``(origins [N, 3], directions [N, 3])`` float32, directions of unit length.
        """
        forward, right, up = (v.to(device) for v in self.basis())
        pixels = pixels.to(device)
        row = torch.div(pixels, self.width, rounding_mode="floor").to(torch.float64)
        column = (pixels % self.width).to(torch.float64)
        half_height = math.tan(math.radians(self.fov) / 2.0)
        half_width = half_height * self.width / self.height
        u = ((column + 0.5) / self.width * 2.0 - 1.0) * half_width  # [N]
        v = (1.0 - (row + 0.5) / self.height * 2.0) * half_height  # [N]
        directions = forward[None, :] + u[:, None] * right[None, :] + v[:, None] * up[None, :]  # [N, 3]
        directions = directions / directions.norm(dim=1, keepdim=True)
        origins = torch.tensor(self.position, dtype=torch.float64, device=device).expand_as(directions)
        return origins.to(torch.float32).contiguous(), directions.to(torch.float32)


def fit_distance(
    fov: float, width: int, height: int, extent: tuple[float, float, float] = (1.0, 1.0, 1.0)
) -> float:
    """Distance at which the box's bounding sphere just fits the narrower side of the view.

    Args:
        fov: vertical field of view, degrees.
        width, height: image size (the horizontal field of view follows from the aspect ratio).
        extent: the box's half sizes.

    Returns:
        The distance from the box centre.
    """
    radius = math.sqrt(sum(e * e for e in extent))
    half = math.radians(fov) / 2.0
    half_narrow = math.atan(math.tan(half) * min(1.0, width / height))
    # The box corners rarely all reach the sphere's silhouette: 0.9 of the sphere fit frames it snugly.
    return 0.9 * radius / math.sin(half_narrow)


def extent_from_shape(shape: tuple[int, int, int]) -> tuple[float, float, float]:
    """Half sizes ``(x, y, z)`` of the box of a ``(D, H, W)`` volume with cubic voxels, longest side 1.

    Args:
        shape: volume shape ``(D, H, W)``.

    Returns:
        ``(ex, ey, ez)`` with the largest equal to 1.
    """
    depth, height, width = shape
    spans = [max(n - 1, 1) for n in (width, height, depth)]  # corner-aligned: n voxels span n - 1 gaps
    longest = max(spans)
    return tuple(s / longest for s in spans)  # type: ignore[return-value]

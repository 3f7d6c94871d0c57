"""The viewer's camera as the user steers it: orbit around a target, pan, zoom (no web code)."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

from apmgsrn.rendering import Camera


@dataclass(frozen=True)
class OrbitView:
    """An orbiting camera as the user steers it: angles around the target, distance, pan.

    ``distance_scale`` multiplies the distance that fits the box in the view, so the same value suits any
    image size and volume proportions. Angles follow :meth:`apmgsrn.rendering.Camera.orbit`.
    """

    azimuth: float = 30.0
    elevation: float = 20.0
    distance_scale: float = 1.0
    target: tuple[float, float, float] = (0.0, 0.0, 0.0)
    fov: float = 30.0

    # Degrees turned by a drag across the whole viewport.
    DEGREES_PER_VIEWPORT = 180.0
    MIN_DISTANCE_SCALE = 0.05
    MAX_DISTANCE_SCALE = 20.0

    def camera(self, width: int, height: int, extent: tuple[float, float, float]) -> Camera:
        """The camera of this view.

        Args:
            width, height: image size in pixels.
            extent: half sizes of the volume's box.

        Returns:
            The camera, looking at ``target``.
        """
        fitted = Camera.orbit(self.azimuth, self.elevation, None, self.fov, width, height, extent)
        distance = math.dist(fitted.position, fitted.target) * self.distance_scale
        around = Camera.orbit(self.azimuth, self.elevation, distance, self.fov, width, height, extent)
        position = tuple(p + t for p, t in zip(around.position, self.target))
        return Camera(position=position, target=self.target, up=around.up, fov=self.fov, width=width, height=height)

    def orbited(self, dx: float, dy: float) -> "OrbitView":
        """Turn the camera around the target by a drag.

        Args:
            dx, dy: drag as fractions of the viewport's width and height (right and down positive).

        Returns:
            The new view; the object follows the pointer, elevation stays within (-90, 90) degrees.
        """
        azimuth = (self.azimuth - self.DEGREES_PER_VIEWPORT * dx) % 360.0
        elevation = min(89.5, max(-89.5, self.elevation + self.DEGREES_PER_VIEWPORT * dy))
        return replace(self, azimuth=azimuth, elevation=elevation)

    def panned(self, dx: float, dy: float, width: int, height: int, extent: tuple[float, float, float]) -> "OrbitView":
        """Slide the target in the view plane so the object follows the pointer.

        Args:
            dx, dy: drag as fractions of the viewport (right and down positive).
            width, height: image size (for the aspect ratio).
            extent: the box's half sizes.

        Returns:
            The new view.
        """
        camera = self.camera(width, height, extent)
        _, right, up = camera.basis()
        distance = math.dist(camera.position, camera.target)
        visible_height = 2.0 * distance * math.tan(math.radians(self.fov) / 2.0)  # at the target's depth
        visible_width = visible_height * width / height
        shift = -dx * visible_width * right + dy * visible_height * up  # [3], world units
        target = tuple(float(t + s) for t, s in zip(self.target, shift))
        return replace(self, target=target)

    def zoomed(self, steps: float) -> "OrbitView":
        """Move closer (``steps < 0``) or away (``steps > 0``); one step is a factor of 1.1.

        Args:
            steps: wheel steps (a browser's ``deltaY / 100``).

        Returns:
            The new view, distance kept within sane limits.
        """
        scale = self.distance_scale * 1.1 ** max(-100.0, min(100.0, float(steps)))  # no float overflow
        return replace(self, distance_scale=min(self.MAX_DISTANCE_SCALE, max(self.MIN_DISTANCE_SCALE, scale)))

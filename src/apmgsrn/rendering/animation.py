"""Turntable animations: the camera circles the volume, frames written as GIF (Pillow) or MP4 (imageio).

MP4 needs the optional packages ``imageio`` and ``imageio-ffmpeg`` (extra ``[video]``); GIF needs only
Pillow.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from apmgsrn.limits import LIMITS
from apmgsrn.arguments import check_int, check_number
from apmgsrn.atomic import atomic_write, check_output_path
from apmgsrn.errors import ApmgsrnError
from apmgsrn.rendering.camera import Camera
from apmgsrn.rendering.images import as_uint8
from apmgsrn.rendering.raymarch import VolumeRenderer

ANIMATION_SUFFIXES = (".gif", ".mp4")


def turntable_cameras(
    frames: int,
    azimuth: float = 30.0,
    elevation: float = 20.0,
    distance: float | None = None,
    fov: float = 30.0,
    width: int = 512,
    height: int = 512,
    extent: tuple[float, float, float] = (1.0, 1.0, 1.0),
) -> list[Camera]:
    """``frames`` orbit cameras a full turn around +z, starting at ``azimuth`` (no repeated end frame).

    Args:
        frames: number of frames (>= 1).
        azimuth, elevation, distance, fov, width, height, extent: as for ``Camera.orbit``.

    Returns:
        The cameras in order.
    """
    check_int("frames", frames, 1, LIMITS.frames)
    return [
        Camera.orbit(azimuth + 360.0 * i / frames, elevation, distance, fov, width, height, extent)
        for i in range(frames)
    ]


def render_frames(renderer: VolumeRenderer, cameras: Iterable[Camera]) -> Iterator[np.ndarray]:
    """Render each camera; yields ``[H, W, 3]`` uint8 frames."""
    for camera in cameras:
        yield as_uint8(renderer.render(camera).image)


def write_animation(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 15.0) -> Path:
    """Write frames as an animated GIF or an MP4, chosen by the file suffix.

    Args:
        frames: ``[H, W, 3]`` uint8 frames.
        path: ``.gif`` or ``.mp4`` file.
        fps: frames per second.

    Returns:
        The path written.

    Raises:
        ApmgsrnError: unknown suffix, missing folder, MP4 without imageio-ffmpeg, or a failed write (the file
            is written atomically: nothing partial is left under ``path``).
    """
    check_number("fps", fps, 0.0, 1000.0, low_open=True)
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in ANIMATION_SUFFIXES:
        raise ApmgsrnError(f"{path}: an animation must be a .gif or .mp4 file; choose another path")
    check_output_path(path, "animation")
    if suffix == ".gif":
        frames = list(frames)  # rendered before the file is opened
        return atomic_write(path, lambda temp: _write_gif(frames, temp, fps), "animation")
    _check_mp4_writer(path)
    return atomic_write(path, lambda temp: _write_mp4(frames, temp, fps), "animation")


def _write_gif(frames: list[np.ndarray], path: str, fps: float) -> None:
    from PIL import Image

    if not frames:
        raise ValueError("no frames to write")
    images = [Image.fromarray(f).convert("P", palette=Image.Palette.ADAPTIVE, colors=256) for f in frames]
    images[0].save(
        path,
        save_all=True,
        append_images=images[1:],
        duration=max(1, int(round(1000.0 / fps))),
        loop=0,
        disposal=1,
    )


def _check_mp4_writer(path: Path) -> None:
    try:
        import imageio.v2  # noqa: F401
        import imageio_ffmpeg  # noqa: F401  (imageio's ffmpeg plug-in needs it)
    except ImportError:
        raise ApmgsrnError(
            f"{path}: writing MP4 needs imageio and imageio-ffmpeg; run "
            "`pip install 'apmgsrn[video]'` or write a .gif instead"
        ) from None


def _write_mp4(frames: Iterable[np.ndarray], path: str, fps: float) -> None:
    import imageio.v2 as imageio

    # H.264 with yuv420p wants even sizes; pad the last row/column by edge replication if needed.
    writer = imageio.get_writer(path, fps=fps, codec="libx264", quality=8, macro_block_size=1, pixelformat="yuv420p")
    try:
        for frame in frames:
            h, w = frame.shape[:2]
            frame = np.pad(frame, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
            writer.append_data(frame)
    finally:
        writer.close()


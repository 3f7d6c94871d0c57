"""Neural volume rendering (docs/method.md §7): ray marching any field ``[N, 3] -> [N, 1]`` with a transfer
function, empty-space skipping, early ray termination and progressive refinement, on any torch device.

Stages, each usable on its own: ``bounds`` (box intersection, macro-cell value bounds and occupancy),
``sampling`` (where a ray's samples lie and the length each stands for), ``field`` (batched evaluation,
the raw volume as a field), ``compositing`` (step-corrected opacity, front-to-back compositing, early
termination), ``raymarch`` (:class:`VolumeRenderer`, composing them) and ``progressive`` (the
coarse-to-fine pixel schedule). The renderer knows fields only, never models or training.

Typical use::

    from apmgsrn.rendering import Camera, VolumeRenderer, make_transfer_function
    tf = make_transfer_function("viridis", (vmin, vmax), opacity=((0, 0), (1, 0.5)))
    image = VolumeRenderer(field, tf).render(Camera.orbit(width=512, height=512)).image  # [H, W, 3]
"""

from apmgsrn.rendering.bounds import Occupancy, ValueBounds
from apmgsrn.rendering.camera import Camera, extent_from_shape
from apmgsrn.rendering.colormaps import BUILTIN_COLORMAPS, builtin_colormap, make_transfer_function
from apmgsrn.rendering.field import Field, VolumeField
from apmgsrn.rendering.images import as_uint8
from apmgsrn.rendering.metrics import image_psnr, image_ssim
from apmgsrn.rendering.paraview import load_transfer_function, read_presets, save_transfer_function
from apmgsrn.rendering.progressive import ProgressiveImage, ProgressiveRender, render_progressive
from apmgsrn.rendering.raymarch import RendererConfig, RenderResult, RenderStatistics, VolumeRenderer
from apmgsrn.rendering.transfer_function import ColorMap, OpacityMap, TransferFunction, TransferTable

__all__ = [
    "BUILTIN_COLORMAPS",
    "Camera",
    "ColorMap",
    "Field",
    "Occupancy",
    "OpacityMap",
    "ProgressiveImage",
    "ProgressiveRender",
    "RenderResult",
    "RenderStatistics",
    "RendererConfig",
    "TransferFunction",
    "TransferTable",
    "ValueBounds",
    "VolumeField",
    "VolumeRenderer",
    "as_uint8",
    "builtin_colormap",
    "extent_from_shape",
    "image_psnr",
    "image_ssim",
    "load_transfer_function",
    "make_transfer_function",
    "read_presets",
    "render_progressive",
    "save_transfer_function",
]

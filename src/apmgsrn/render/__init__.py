"""Neural volume rendering (SPEC section 7): ray marching any field ``[N, 3] -> [N, 1]`` with a transfer
function, empty-space skipping, early ray termination and progressive refinement, on any torch device.

Stages, each usable on its own: ``bounds`` (box intersection, macro-cell value bounds and occupancy),
``sampling`` (where a ray's samples lie and the length each stands for), ``field`` (batched evaluation,
the raw volume as a field), ``compositing`` (step-corrected opacity, front-to-back compositing, early
termination), ``raymarch`` (:class:`VolumeRenderer`, composing them) and ``progressive`` (the
coarse-to-fine pixel schedule). The renderer knows fields only, never models or training.

Typical use::

    from apmgsrn.render import Camera, VolumeRenderer, make_transfer_function
    tf = make_transfer_function("viridis", (vmin, vmax), opacity=((0, 0), (1, 0.5)))
    image = VolumeRenderer(field, tf).render(Camera.orbit(width=512, height=512)).image  # [H, W, 3]

The package is also callable: ``apmgsrn.render(model, ...)`` is the notebook API's :func:`apmgsrn.api.render`
(an RGBA image of a model). Python sets ``apmgsrn.render`` to this package once it is imported, so the
function users type and the package must be one object.
"""

import importlib
import sys
import types

from apmgsrn.render.bounds import Occupancy, ValueBounds
from apmgsrn.render.camera import Camera, extent_from_shape
from apmgsrn.render.colormaps import BUILTIN_COLORMAPS, builtin_colormap, make_transfer_function
from apmgsrn.render.field import Field, VolumeField
from apmgsrn.render.images import as_uint8
from apmgsrn.render.metrics import image_psnr, image_ssim
from apmgsrn.render.paraview import load_transfer_function, read_presets, save_transfer_function
from apmgsrn.render.progressive import ProgressiveImage, ProgressiveRender, render_progressive
from apmgsrn.render.raymarch import RendererConfig, RenderResult, RenderStatistics, VolumeRenderer
from apmgsrn.render.transfer_function import ColorMap, OpacityMap, TransferFunction, TransferTable

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


class _CallablePackage(types.ModuleType):
    """This package, callable as :func:`apmgsrn.api.render`."""

    def __call__(self, *args, **kwargs):
        # Looked up at call time: the renderer knows fields only and imports nothing of the layers above it.
        return importlib.import_module("apmgsrn.api").render(*args, **kwargs)


sys.modules[__name__].__class__ = _CallablePackage

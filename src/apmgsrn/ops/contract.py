"""The answer of every point operation at points outside ``[-1, 1]^3`` and at non-finite points, in one place
(the rule itself is stated in :mod:`apmgsrn.ops`).

The pure-PyTorch references use these helpers; the C and Triton kernels implement the same rule inside
themselves, in floating point before any integer conversion.
"""

from __future__ import annotations

import torch

#: The finite coordinate a larger or infinite one reads as where a reference maps points into its grids:
#: ``±inf`` (and anything beyond) reads as ``±FAR``. Far beyond every grid (any grid or level is outside it,
#: so the answer is that of the point itself), and small enough that ``FAR`` times a map coefficient stays
#: finite in float32, so no ``inf * 0`` or ``inf - inf`` arises.
FAR = 2.0**64


def nan_points(points: torch.Tensor) -> torch.Tensor:
    """``[N]`` bool: which points ``[N, 3]`` have a NaN coordinate."""
    return torch.isnan(points).any(-1)


def nan_where_nan(points: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``values`` (``[N]`` or ``[N, C]``) with every row of a point with a NaN coordinate set to NaN.

    A ``torch.where``: the gradient of a NaN point's row is zero, so it adds nothing to any gradient (as long
    as what computed ``values`` there was finite, which the references make sure of).
    """
    mask = nan_points(points)
    if values.dim() == 2:
        mask = mask[:, None]
    return torch.where(mask, torch.tensor(float("nan"), dtype=values.dtype, device=values.device), values)


def finite_stand_in(points: torch.Tensor) -> torch.Tensor:
    """``points`` clamped to ``[-FAR, FAR]`` (``±inf`` included) and NaN read as 0: what a reference maps into
    its grids, so that neither the answer nor the maps' gradient meets ``0 * inf`` or ``inf - inf``. A NaN
    point's own answer is set to NaN afterwards (:func:`nan_where_nan`), which also zeroes its gradient.
    Clip, IsNaN and Where only, so the ONNX export takes it."""
    zero = torch.zeros((), dtype=points.dtype, device=points.device)
    return torch.where(torch.isnan(points), zero, points.clamp(-FAR, FAR))


def outside_for_non_finite(values: torch.Tensor, limit: float) -> torch.Tensor:
    """``values`` with everything not in ``[-limit, limit]`` (NaN, ``±inf``, huge) replaced by ``limit``.

    For coordinates where every value beyond ``limit`` gives the same answer as ``limit`` itself (outside
    a zero-padded grid): the result is unchanged for every finite input, and no integer conversion after it
    can overflow. NaN compares false, so it lands on ``limit`` too.
    """
    return torch.where(values.abs() <= limit, values, torch.tensor(limit, dtype=values.dtype, device=values.device))

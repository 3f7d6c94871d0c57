"""Uniform scalar quantisation of named parameters, one step size per group of elements.

Every stored parameter (of any model kind: nothing here knows encoders) is cut into *groups*: contiguous
runs of its C-order elements, chosen from its shape alone by :func:`group_size`. Each group has one step
``s``; an element ``x`` is stored as the integer ``q = round(x / s)`` and restored as ``q * s``. Steps are
stored as float16 and the integers are computed with the float16-rounded step, so what is restored is
exactly what the packer evaluated. There is no offset: the integers are entropy-coded afterwards
(:mod:`apmgsrn.io.codec`), so only the step sets the cost, not where the values sit.

Steps come from a bit width (``max |x| / (2^(B-1) - 1)``: every integer fits in ``B`` signed bits) or from
the caller (the packer sets them by each group's effect on the output).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

#: A group holds at least this many elements (its float16 step then costs at most 1/512 of a byte each).
MIN_GROUP = 1024
#: At most this many groups per tensor (larger tensors get larger groups).
MAX_GROUPS = 1 << 16
#: Largest magnitude of a stored integer: residuals of the 3-D predictor (8 terms) stay inside int32.
MAX_LEVEL = (1 << 27) - 1
#: Smallest and largest step float16 holds as a normal number.
MIN_STEP, MAX_STEP = float(np.finfo(np.float16).tiny), float(np.finfo(np.float16).max)
#: Bit widths a caller may ask for.
MIN_BITS, MAX_BITS = 2, 16


def group_size(shape: tuple[int, ...]) -> int:
    """Elements per quantisation group of a tensor of ``shape`` (the last group may be shorter).

    A group is the block of the trailing axes ``shape[k:]`` for the largest ``k`` whose block holds at
    least :data:`MIN_GROUP` elements (a grid ``[M, C, D, H, W]`` of 16^3 cells: one group per grid and
    channel); when only the whole tensor is that large, blocks of whole rows of axis 0 (a hash table
    ``[E, F]``, a weight matrix); a tensor smaller than :data:`MIN_GROUP` is one group.

    Args:
        shape: the tensor's shape.

    Returns:
        Group size ``g >= 1``; the tensor has ``ceil(numel / g)`` groups, at most :data:`MAX_GROUPS`.
    """
    numel = math.prod(shape)
    if numel <= MIN_GROUP:
        return max(numel, 1)
    size = numel
    for k in range(len(shape) - 1, 0, -1):
        block = math.prod(shape[k:])
        if block >= MIN_GROUP:
            size = block
            break
    else:
        row = math.prod(shape[1:])
        size = -(-MIN_GROUP // row) * row
    # Few enough groups: merge neighbours (whole multiples of the block, so groups stay aligned to it).
    groups = -(-numel // size)
    if groups > MAX_GROUPS:
        size *= -(-groups // MAX_GROUPS)
    return size


def group_count(numel: int, size: int) -> int:
    """Groups of ``size`` elements covering ``numel`` elements."""
    return -(-numel // size) if numel else 0


def group_ids(numel: int, size: int) -> np.ndarray:
    """``[numel]`` group index of every element."""
    return np.arange(numel, dtype=np.int64) // size


def group_max_abs(values: np.ndarray, size: int) -> np.ndarray:
    """``[G]`` largest magnitude in each group of a flat array."""
    flat = np.abs(np.asarray(values, dtype=np.float32).reshape(-1))
    count = group_count(flat.size, size)
    padded = np.zeros(count * size, dtype=np.float32)
    padded[: flat.size] = flat
    return padded.reshape(count, size).max(axis=1)


def steps_for_bits(values: np.ndarray, size: int, bits: int) -> np.ndarray:
    """Steps that fit every integer of a group in ``bits`` signed bits: ``max |x| / (2^(bits-1) - 1)``.

    Args:
        values: the tensor (any shape, C order).
        size: group size.
        bits: bit width, :data:`MIN_BITS`..:data:`MAX_BITS`.

    Returns:
        ``[G]`` float16 steps, rounded up to the next float16 so that no integer leaves the ``bits`` (an
        all-zero group gets the smallest step: it stores zeros).
    """
    levels = (1 << (bits - 1)) - 1
    wanted = group_max_abs(values, size).astype(np.float64) / levels
    steps = round_steps(wanted)
    low = steps.astype(np.float64) < wanted
    steps[low] = np.nextafter(steps[low], np.float16(np.inf))
    return np.minimum(steps, np.float16(MAX_STEP))  # values beyond float16 steps are clipped by the packer


def round_steps(steps: np.ndarray) -> np.ndarray:
    """Steps as stored: positive float16 (a zero, tiny or non-finite step becomes the nearest usable one)."""
    steps = np.nan_to_num(np.asarray(steps, dtype=np.float64), nan=MAX_STEP, posinf=MAX_STEP)
    return np.clip(steps, MIN_STEP, MAX_STEP).astype(np.float16)


@dataclass(frozen=True)
class QuantizedTensor:
    """A tensor as integers and per-group steps.

    Attributes:
        shape: the tensor's shape.
        group: elements per group (:func:`group_size` of the shape when it was packed).
        steps: ``[G]`` float16 steps.
        levels: ``[numel]`` int32 integers, C order.
    """

    shape: tuple[int, ...]
    group: int
    steps: np.ndarray
    levels: np.ndarray

    def dequantize(self) -> torch.Tensor:
        """The float32 tensor ``levels * step`` (float32 arithmetic, the same on every machine)."""
        return dequantize(self.levels, self.steps, self.group, self.shape)


def quantize(tensor: torch.Tensor | np.ndarray, steps: np.ndarray, size: int | None = None) -> QuantizedTensor:
    """Quantise a tensor with one step per group.

    Args:
        tensor: float values.
        steps: ``[G]`` steps (rounded to float16 here).
        size: group size (default :func:`group_size` of the shape).

    Returns:
        The integers and the stored steps; integers are clipped to ``+-MAX_LEVEL`` (a step that small
        would be a caller's bug: no bit width reaches it).
    """
    values = tensor.detach().cpu().numpy() if isinstance(tensor, torch.Tensor) else np.asarray(tensor)
    shape = tuple(values.shape)
    size = group_size(shape) if size is None else size
    stored = round_steps(steps)
    per_element = stored.astype(np.float32)[group_ids(values.size, size)]  # [numel]
    levels = np.rint(values.reshape(-1).astype(np.float32) / per_element)
    levels = np.clip(levels, -MAX_LEVEL, MAX_LEVEL).astype(np.int32)
    return QuantizedTensor(shape, size, stored, levels)


def dequantize(levels: np.ndarray, steps: np.ndarray, size: int, shape: tuple[int, ...]) -> torch.Tensor:
    """``levels * steps[group]`` as a float32 tensor of ``shape``."""
    per_element = np.asarray(steps, dtype=np.float16).astype(np.float32)[group_ids(levels.size, size)]
    values = levels.astype(np.float32) * per_element
    return torch.from_numpy(values.reshape(shape))

"""The one search to a byte budget and the one overhead model, shared by every packer (docs/method.md §10.3).

A packer has one knob that trades bytes for error: the sensitivity scale of a single field's steps
(:mod:`apmgsrn.training.packing`), the bit width of a series' shared steps (:mod:`apmgsrn.series.packing`).
Both put that knob on an integer lattice ``k`` (larger ``k``: finer steps, more bytes) and ask for the
largest ``k`` whose file fits the target: :func:`largest_fitting`.

The file's bytes are the coded parameters plus an overhead: the description (the model's config, the source's
metadata, the training summary, one entry per tensor and per step, coded) and the container's framing. The
overhead is measured, never modelled: the packer builds the file once with its real description
(placeholders of the same length for the figures packing has not measured yet) and subtracts the coded
sections (:func:`overhead_bytes`); the search then compares ``coded + overhead`` with the target, and the
file is built and measured again at the end.
"""

from __future__ import annotations

import math
from collections.abc import Callable


def overhead_bytes(file_bytes: int, sections: list[bytes]) -> int:
    """Bytes of a file of ``file_bytes`` that are not its coded ``sections``: the description and framing."""
    return max(0, file_bytes - sum(len(s) for s in sections))


def coded_budget(target_bytes: int, overhead: int) -> int:
    """Bytes the coded parameters may take in a file of ``target_bytes`` whose overhead is ``overhead``."""
    return max(1, target_bytes - overhead)


def largest_fitting(size: Callable[[int], int], budget: int, low: int, high: int, high_size: int
                    ) -> tuple[int, int] | None:
    """The largest lattice point ``k`` in ``[low, high)`` with ``size(k) <= budget``, given that ``high`` does
    not fit (``high_size = size(high) > budget``) and that ``size`` grows with ``k``.

    Bytes grow nearly linearly with the knob over a short span, so each trial is taken where the line through
    the bracket's ends meets the budget (the first where the line from zero through ``high`` does, then
    ``low`` if that did not fit), on the lattice, strictly inside the bracket. Where one end moved twice in a
    row, the other end's distance from the budget counts half (the Illinois rule), so a curved size never
    makes the search creep one lattice point at a time.

    Returns:
        ``(k, size(k))``, or None when not even ``low`` fits.
    """
    if low >= high:
        return None
    high_excess = float(high_size - budget)
    k = min(max(math.floor(high * budget / high_size) if high_size > 0 else low, low), high - 1)
    best, low_spare, moved = None, 0.0, None
    while True:
        tried = size(k)
        side = "low" if tried <= budget else "high"
        if side == "low":
            low, best, low_spare = k, (k, tried), float(budget - tried)
        else:
            high, high_excess = k, float(tried - budget)
        if best is None:  # nothing fits yet: the lowest point does, or none
            if k == low:
                return None
            k = low
            continue
        if high - low <= 1:
            return best
        if side == moved:  # the Illinois rule
            if side == "low":
                high_excess /= 2
            else:
                low_spare /= 2
        moved = side
        share = low_spare / (low_spare + high_excess) if low_spare + high_excess > 0 else 0.5
        k = min(max(low + math.floor((high - low) * share), low + 1), high - 1)

"""Sizing a model for a byte target: the model ``train --ratio R`` / ``--size BYTES`` builds (docs/packing.md).

The target is turned into a parameter budget, ``(target - overhead) * 8 / bits_per_parameter`` (the file's
overhead measured by :func:`~apmgsrn.training.packing.packed_overhead`, the bits per parameter the packer
reaches at a small PSNR cost), and the budget into sizes, from the bytes alone, never from the data. Every kind
first takes its decoder from the packing recipe's ``decoder_ladder``: the largest whose weights take at most
``decoder_share`` of the budget. The encoder gets the rest:

- **apmgsrn, fvsrn**: the number of grids (apmgsrn) halved, not below ``min_grids``, while each would be coarser
  than ``min_resolution`` (the decoder chosen again for each count, its input being narrower); then the largest
  resolution that fits, one axis finer at a time.
- **ngp**: the largest hash table (``2^T`` rows per level) that fits, the levels and resolutions kept.
- **hybrid**: the domain levels take ``hybrid_level_share`` of the encoder's budget: the largest table
  ``2^T`` (at most the preset's) that fits with the preset's levels; where even ``2^hybrid_min_log2_table``
  rows do not, the levels are fewer (down to none). The adaptive grids get the rest: halved while coarser than
  ``min_resolution`` (the decoder kept), then the largest cube that fits.

The packer then meets the target with finer or coarser steps, so the sizes need only be about right.
"""

from __future__ import annotations

import math
from dataclasses import replace

from apmgsrn.errors import ApmgsrnError
from apmgsrn.recipes import PACKING
from apmgsrn.training.packing import packed_overhead

#: Encoder fields a caller may hold fixed (``fixed=``): given on the command line, they are kept.
FIXABLE = ("grids", "decoder", "levels", "log2_table_size")


def anchored_grids_for(config) -> int:
    """Grids to anchor when training ``config``, a model :func:`config_for_bytes` sized: 1 for an APMGSRN model
    of at most ``PACKING.anchor_max_grids`` grids, else 0 (the hybrid's domain levels cover the domain already)."""
    return 1 if config.model == "apmgsrn" and config.encoder.grids <= PACKING.anchor_max_grids else 0


def sized_words(config) -> tuple[str, str]:
    """What :func:`config_for_bytes` chose, in words (``"4 grids of 8x8x7"``), and the options to choose it by hand."""
    encoder = config.encoder
    if config.model in ("apmgsrn", "fvsrn"):
        grids = getattr(encoder, "grids", None)
        shape = "x".join(str(r) for r in reversed(encoder.resolution))  # x*y*z
        return f"{f'{grids} grids' if grids else 'a grid'} of {shape}", "--resolution, --grids, --width"
    if config.model == "ngp":
        return f"{encoder.levels} levels of 2^{encoder.log2_table_size} rows", "--log2-table-size, --width"
    levels = f"{encoder.levels} levels of 2^{encoder.log2_table_size} rows" if encoder.levels else "no domain levels"
    return (f"{levels} and {encoder.grids} grids of {encoder.grid_resolution}^3",
            "--levels, --log2-table-size, --grids, --resolution, --width")


def parameter_count(config) -> int:
    """Parameters of a field config (a hybrid's must hold its lattice)."""
    return sum(math.prod(shape) for shape in config.parameter_shapes().values())


def config_for_bytes(config, target_bytes: int, fixed: tuple[str, ...] = (),
                     bits_per_parameter: float = PACKING.bits_per_parameter, overhead: int | None = None,
                     volume_shape: tuple[int, int, int] = (256, 256, 256)):
    """A config like ``config`` (a :class:`~apmgsrn.models.registry.FieldConfig` of any kind) whose packed file
    comes to about ``target_bytes`` (the rule: this module's docstring).

    Args:
        config: the preset to resize; features and every setting the rule does not name stay as given.
        target_bytes: the file size asked for.
        fixed: sizes to keep (:data:`FIXABLE`): ``"grids"``, ``"decoder"``, ``"levels"``, ``"log2_table_size"``.
        bits_per_parameter: stored bits per parameter expected after packing.
        overhead: the file's bytes beside its coded parameters (None: :func:`packed_overhead` of ``config``).
        volume_shape: ``(D, H, W)`` of the volume (the hybrid's domain levels follow its lattice).

    Raises:
        ApmgsrnError: not even the smallest model of the kind fits ``target_bytes``.
    """
    fitted = config.fitted_to(tuple(volume_shape))
    overhead = packed_overhead(fitted, tuple(volume_shape)) if overhead is None else overhead
    budget = max(target_bytes - overhead, 0) * 8 / bits_per_parameter  # parameters
    sized = _sized(fitted, budget, fixed)
    if sized is None or parameter_count(sized) > budget:
        smallest, what = (sized, f"the {config.model} model of the sizes given") if sized else _smallest(fitted)
        raise ApmgsrnError(f"target_bytes={target_bytes}: even {what} take about "
                           f"{parameter_count(smallest) * bits_per_parameter / 8 + overhead:.0f} bytes; pass a larger "
                           "target (a lower ratio), or fewer grids or a narrower decoder", arguments=("target_bytes",))
    if config.model == "hybrid":
        sized = replace(sized, encoder=replace(sized.encoder, lattice=config.encoder.lattice))
    return sized


def _encoder(candidate, **fields):
    return replace(candidate, encoder=replace(candidate.encoder, **fields))


def _sized(config, budget: float, fixed: tuple[str, ...]):
    """The rule's model (the module's docstring); None: nothing fits."""
    size = {"apmgsrn": _grids_sized, "fvsrn": _grids_sized, "ngp": _hash_sized, "hybrid": _hybrid_sized}[config.model]
    return size(_with_decoder(config, budget, fixed), budget, fixed, config)


def _with_decoder(config, budget: float, fixed: tuple[str, ...]):
    """``config`` with the largest decoder of the ladder (no larger than its own) within ``decoder_share`` of the
    budget."""
    if "decoder" in fixed:
        return config
    current = (config.decoder.hidden_layers, config.decoder.width)
    ladder = [size for size in PACKING.decoder_ladder if size[0] <= current[0] and size[1] <= current[1]] or [current]
    for layers, width in ladder:
        decoder = replace(config.decoder, hidden_layers=layers, width=width)
        weights = sum(math.prod(s) for s in decoder.parameter_shapes(config.encoder.out_features).values())
        if weights <= PACKING.decoder_share * budget:
            break
    return replace(config, decoder=decoder)


def _smallest(config):
    """The smallest model of the rule's family like ``config``, and what it is in words (a refusal's message)."""
    if config.model in ("apmgsrn", "fvsrn"):
        return _encoder(config, resolution=(2, 2, 2)), f"grids of 2^3 ({config.model})"
    if config.model == "ngp":
        return _encoder(config, log2_table_size=1), "ngp tables of 2 rows"
    return (_encoder(config, levels=0, grid_resolution=2),
            f"{config.encoder.grids} grids of 2^3 and no domain levels (hybrid)")


def _largest_resolution(candidate, budget: float) -> tuple[int, int, int] | None:
    """The largest of 2^3, 2x2x3, 2x3x3, 3^3, ... 256^3 (D, H, W) that fits: one axis finer at a time, so a
    small budget is filled to within a few percent, not to within a cube."""
    best = None
    for side in range(2, 257):
        for resolution in ((side, side, side), (side, side, side + 1), (side, side + 1, side + 1)):
            if max(resolution) > 256 or parameter_count(_encoder(candidate, resolution=resolution)) > budget:
                return best
            best = resolution
    return best


def _grids_sized(candidate, budget: float, fixed: tuple[str, ...], start):
    """apmgsrn, fvsrn: fewer grids while they would be too coarse (the decoder chosen again for each count: fewer
    grids, a narrower input), then the largest resolution."""
    resolution = _largest_resolution(candidate, budget)
    while ("grids" not in fixed and hasattr(candidate.encoder, "grids")
           and candidate.encoder.grids // 2 >= PACKING.min_grids
           and (resolution is None or min(resolution) < PACKING.min_resolution)):
        candidate = _with_decoder(_encoder(start, grids=candidate.encoder.grids // 2), budget, fixed)
        resolution = _largest_resolution(candidate, budget)
    return None if resolution is None else _encoder(candidate, resolution=resolution)


def _hash_sized(candidate, budget: float, fixed: tuple[str, ...], start=None):
    """ngp: the largest table that fits (down to 2 rows a level)."""
    if "log2_table_size" in fixed:
        return candidate
    best = None
    for log2 in range(1, 31):
        sized = _encoder(candidate, log2_table_size=log2)
        if parameter_count(sized) > budget:
            break
        best = sized
        if all(r**3 <= 2**log2 for r in sized.encoder.level_resolutions()):
            break  # every level dense already: a larger table adds nothing
    return best


def _hybrid_sized(candidate, budget: float, fixed: tuple[str, ...], start=None):
    """hybrid: the domain levels within their share of the encoder's budget, then the adaptive grids."""
    decoder = sum(math.prod(s) for n, s in candidate.parameter_shapes().items() if n.startswith("decoder."))
    if {"levels", "log2_table_size"} <= set(fixed):
        return _hybrid_grids(candidate, budget, fixed)
    share = PACKING.hybrid_level_share * (budget - decoder)
    return _hybrid_grids(_hybrid_levels(candidate, share, fixed), budget, fixed)


def _hybrid_grids(candidate, budget: float, fixed: tuple[str, ...]):
    """The hybrid's adaptive grids in what its levels and decoder leave: halved while coarser than
    ``min_resolution``, then the largest cube that fits."""
    def largest_cube(sized):
        best = None
        for side in range(2, 257):
            if parameter_count(_encoder(sized, grid_resolution=side)) > budget:
                break
            best = side
        return best

    if candidate.encoder.grids == 0:
        return candidate
    side = largest_cube(candidate)
    while ("grids" not in fixed and candidate.encoder.grids // 2 >= PACKING.min_grids
           and (side is None or side < PACKING.min_resolution)):
        candidate = _encoder(candidate, grids=candidate.encoder.grids // 2)
        side = largest_cube(candidate)
    return None if side is None else _encoder(candidate, grid_resolution=side)


def _hybrid_levels(candidate, budget: float, fixed: tuple[str, ...]):
    """The domain levels' table ``2^T`` (at most the candidate's) and level count within ``budget`` parameters."""
    encoder = candidate.encoder

    def table(levels: int, log2: int) -> int:
        return math.prod(_encoder(candidate, levels=levels, log2_table_size=log2).encoder.parameter_shapes()
                         ["level_table"])

    if "log2_table_size" not in fixed:
        for log2 in range(encoder.log2_table_size, PACKING.hybrid_min_log2_table - 1, -1):
            if table(encoder.levels, log2) <= budget:
                return _encoder(candidate, log2_table_size=log2)
    log2 = encoder.log2_table_size if "log2_table_size" in fixed else PACKING.hybrid_min_log2_table
    if "levels" in fixed:
        return _encoder(candidate, log2_table_size=log2)
    levels = encoder.levels
    while levels > 0 and table(levels, log2) > budget:
        levels -= 1
    return _encoder(candidate, levels=levels, log2_table_size=log2)

"""Packing a time-series field into a small file (kind ``packed-series``, :mod:`apmgsrn.series.packed_file`).

At a bit width ``B`` the feature grids are quantised uniformly (:mod:`apmgsrn.io.quantization`):

- the basis grids ``[K, M, C, D, H, W]`` take one step per grid and channel ``(m, c)``, shared by all ``K``
  slices (``max |x|`` over the slices, as :func:`~apmgsrn.io.quantization.steps_for_bits`). With keyframe
  weights and ``K = T`` each slice is one step's grid set; consecutive steps are close, so with a shared
  step their integers are close too, and the ``time`` predictor (the difference along ``K``,
  :mod:`apmgsrn.io.codec`) leaves small residuals. The file stores the steps as ordinary per-group steps:
  groups of ``D * H * W`` elements, each shared step repeated ``K`` times (2 bytes per slice, grid and
  channel), so the tensor reads back like any packed one;
- a hybrid series' per-step tensors the same way: its level tables ``[T, P]`` one step per run of about
  ``PACKING.level_table_group`` values, its grids ``[T, M, R, R, R, C]`` one per grid, shared by all steps;
- per-step residual grids, if any, take one step per group (:func:`~apmgsrn.io.quantization.group_size`);
- the learned weights, the grid placement and the decoder are kept exactly (float32, LZMA): they are small.

The shared steps follow each group's effect on the output (:func:`sensitivity_steps`, the single-field packer's
allocation, :mod:`apmgsrn.training.packing`): ``s_g`` proportional to ``1 / sqrt(sens_g)``, the mean squared
derivative of the output with respect to the group's elements, measured on the first, middle and last step,
and scaled so that the steps' mean ``log2`` over all elements is that of the uniform ``B``-bit steps (about
the same bytes). Uniform steps spend as many bits on a fine level's hash entry as on a coarse level's, whose
entries each reach far more voxels: the 30 viscous-finger steps' default hybrid series lost 0.52 dB to
uniform steps at 8 bits and loses 0.10 dB to these, in 2 % fewer bytes (APMGSRN's at 10 bits: no change).

A size target (:class:`SeriesPacking`) takes the finest bit width that fits on a lattice of sixteenths of a bit
(every step of a whole width made finer by ``2^-k/16``, :meth:`SeriesPacking._search`): a whole bit is about a
fifth of the bytes, and the default hybrid series of the viscous-finger steps landed at 4.4 of its five files at 7
bits, 1.1 dB below float32; at 7.25 bits, 4.7 files, 0.79 dB (docs/time_series.md).

Each quantised tensor is coded with whichever predictor codes it smallest (``time`` and the spatial ones).
On the 30 viscous-fingering steps at 64^3 (per-step grids) the grids take about 0.81 MB at 8 bits and 1.24 MB
at 10; the PSNR costs 0.4-0.5 dB at 8 bits and about 0.03 dB at 10. A hybrid series of the same steps, unpulled,
takes 2.59 MB at 10 bits (0.06 dB) and 1.80 MB at 8 (0.97 dB) (all with uniform steps).
"""

from __future__ import annotations

import copy
import math
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from dataclasses import field as dataclass_field

import numpy as np
import torch

from apmgsrn.arguments import check_int
from apmgsrn.errors import InvalidArgument
from apmgsrn.io import SeriesStepInfo, SourceInfo
from apmgsrn.io.packed import PackedTensor, encode_float32, encode_quantized_all
from apmgsrn.series.packed_file import packed_series_bytes, save_packed_series, series_predictors
from apmgsrn.io.quantization import (
    MAX_BITS,
    MAX_GROUPS,
    MIN_BITS,
    MIN_STEP,
    group_count,
    group_size,
    quantize,
    round_steps,
    steps_for_bits,
)
from apmgsrn.models.registry import stored_bytes
from apmgsrn.series.evaluate import SeriesEvaluation
from apmgsrn.series.field import SeriesField
from apmgsrn.recipes import PACKING, SERIES, PackingRecipe, SeriesRecipe, model_recipe
from apmgsrn.training.budget import coded_budget, largest_fitting, overhead_bytes
from apmgsrn.training.packing import group_means, parameter_sensitivity

#: Per-step tensors whose groups share one step over all steps (what the ``time`` predictor needs).
SHARED_STEP_TENSORS = ("encoder.grids", "encoder.level_table")


@dataclass(frozen=True)
class PackedSeries:
    """A series field's parameters as a packed file stores them.

    Attributes:
        tensors: every parameter packed, in the config's order.
        state: name -> the float32 tensor a loader restores (dequantised, or the exact value).
        bits: the bit width of the quantised tensors.
        finer: their steps are ``2^finer`` times finer than those of ``bits`` (0 <= finer < 1;
            :meth:`SeriesPacking.pack` refines a size target's bit width this way).
        steps: name -> ``[K * G]`` float16 steps of each of :data:`SHARED_STEP_TENSORS` as quantised (what a
            quantisation-aware fine-tune, :mod:`apmgsrn.series.qat`, trains towards).
        restored: the steps whose values from before a quantisation-aware fine-tune were packed instead, so that
            the file fits its target (:meth:`SeriesPacking.repack`).
        overhead: the bytes the file's description and framing take beside :attr:`parameter_bytes`, as the
            packing measured them (:func:`series_overhead`; None: not measured, a packing without a target).
    """

    tensors: list[PackedTensor]
    state: dict[str, torch.Tensor]
    bits: int
    finer: float = 0.0
    steps: dict[str, np.ndarray] = dataclass_field(default_factory=dict)
    restored: tuple[int, ...] = ()
    overhead: int | None = None

    @property
    def bit_width(self) -> float:
        """The effective bit width: :attr:`bits`, the steps made ``2^finer`` times finer."""
        return self.bits + self.finer

    @property
    def parameter_bytes(self) -> int:
        """Bytes of the coded parameters (the description and container framing come on top)."""
        return sum(len(t.data) for t in self.tensors)


def shared_steps(grids: np.ndarray, bits: int, group: int | None = None) -> tuple[np.ndarray, int]:
    """Steps that each group of a per-step tensor shares over its ``K`` slices (steps, or basis grids).

    Args:
        grids: ``[K, ...]``: APMGSRN's basis grids ``[K, M, C, D, H, W]``, or any per-step tensor.
        bits: bit width, :data:`~apmgsrn.io.quantization.MIN_BITS`..:data:`~apmgsrn.io.quantization.MAX_BITS`.
        group: elements per group within a slice, a divisor of the slice's size (None: one group per grid and
            channel, ``D * H * W`` elements, of APMGSRN's grids).

    Returns:
        ``([K * G] float16 steps, group size)``: ``G`` groups per slice, each step repeated for every slice;
        should ``K * G`` exceed :data:`~apmgsrn.io.quantization.MAX_GROUPS`, neighbouring groups merge.
    """
    slices = grids.shape[0]
    size = math.prod(grids.shape[1:])
    group = math.prod(grids.shape[3:]) if group is None else group
    groups = size // group
    merged = next((n for n in range(1, groups + 1) if groups % n == 0 and slices * (groups // n) <= MAX_GROUPS), None)
    if merged is None:
        raise InvalidArgument(f"steps={slices}: a packed series holds at most {MAX_GROUPS} steps; store it unpacked",
                              arguments=("steps",))
    group *= merged
    blocks = grids.reshape(slices, size // group, group).transpose(1, 0, 2)  # [G, K, group]
    steps = steps_for_bits(blocks, slices * group, bits)  # [G], one per group over all slices
    return np.tile(steps, slices), group  # [K * G], in the C order of the slices' groups


def slice_group(model: str, name: str, shape: tuple[int, ...]) -> int | None:
    """Elements per quantisation group of one step of a per-step tensor of a ``model`` series
    (:func:`shared_steps`): one per adaptive grid of the hybrid's ``grids`` ``[T, M, R, R, R, C]``; runs of about
    ``PACKING.level_table_group`` values of its ``level_table`` ``[T, P]`` (a divisor of ``P``; the coarse levels
    are about that size); None for APMGSRN's grids."""
    if name == "encoder.level_table":
        size = shape[1]
        fewest = -(-size // PACKING.level_table_group)
        return next((size // n for n in range(fewest, 4 * fewest + 1) if size % n == 0), size)
    if model == "hybrid" and name == "encoder.grids":
        return math.prod(shape[2:])
    return None


def series_sensitivity(field: SeriesField, points: int = 1 << 18) -> dict[str, np.ndarray]:
    """Mean squared derivative of the output with respect to every element of one step's per-step tensors
    (:data:`SHARED_STEP_TENSORS`), averaged over the first, middle and last step, each as a single-step field
    (:func:`~apmgsrn.training.packing.parameter_sensitivity`): name -> ``[slice numel]`` float64."""
    probed = sorted({0, field.steps // 2, field.steps - 1})
    total: dict[str, np.ndarray] = {}
    for t in probed:
        for name, values in parameter_sensitivity(field.step_field(t), points, names=SHARED_STEP_TENSORS).items():
            total[name] = total.get(name, 0.0) + values / len(probed)
    return total


def sensitivity_steps(uniform: dict[str, tuple[np.ndarray, int]],
                      sensitivity: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Shared steps ``c / sqrt(sens_g)`` in place of uniform ones (module docstring).

    Args:
        uniform: name -> (``[K * G]`` uniform steps of :func:`shared_steps`, group size): ``K`` slices (steps,
            or a joint series' basis grids) of ``G`` groups.
        sensitivity: name -> ``[slice numel]`` (:func:`series_sensitivity`).

    Returns:
        name -> ``[K * G]`` float16 steps. ``c`` makes the mean ``log2`` step over every element of these
        tensors that of the uniform steps (no finer than ``PACKING.finest_share_bits`` below them); a group no
        probed point reaches keeps its uniform step.
    """
    counts = {name: group_count(sensitivity[name].size, group) for name, (_, group) in uniform.items()}
    raw, reached, logs, weights = {}, {}, [], []
    for name, (steps, group) in uniform.items():
        count = counts[name]
        means = group_means(sensitivity[name], group)[:count]
        reached[name] = (means > 0) & (steps[:count] > MIN_STEP)  # an all-zero group has the smallest step
        raw[name] = 1 / np.sqrt(np.where(reached[name], means, 1.0))
        logs.append(np.log2(steps[:count].astype(np.float64)[reached[name]] / raw[name][reached[name]]))
        weights.append(np.full(int(reached[name].sum()), group))
    logs, weights = np.concatenate(logs), np.concatenate(weights)
    if not weights.size:
        return {name: steps for name, (steps, _) in uniform.items()}
    scale = 2 ** (np.sum(logs * weights) / np.sum(weights))
    out = {}
    for name, (steps, _) in uniform.items():
        count = counts[name]
        uniform_steps = steps[:count].astype(np.float64)
        # At most finest_share_bits bits finer than the uniform step: integers stay far inside MAX_LEVEL.
        chosen = np.where(reached[name], np.maximum(scale * raw[name], uniform_steps / 2**PACKING.finest_share_bits),
                          uniform_steps)
        out[name] = np.tile(round_steps(chosen), len(steps) // count)
    return out


def pack_series(field: SeriesField, bits: int = PACKING.series_bits,
                sensitivity: dict[str, np.ndarray] | None = None, finer: float = 0.0,
                steps: dict[str, np.ndarray] | None = None,
                predictors: dict[str, tuple[str, ...]] | None = None) -> PackedSeries:
    """Quantise and code a series field's parameters at ``bits`` (see the module docstring); nothing written.

    Args:
        field: the trained series field (not changed).
        bits: bit width of the grids and residuals.
        sensitivity: :func:`series_sensitivity` of the field: the shared steps follow it
            (:func:`sensitivity_steps`); None: uniform steps of ``bits``.
        finer: every step of ``bits`` divided by ``2^finer``, ``0 <= finer < 1`` (a bit width between ``bits``
            and ``bits + 1``).
        steps: the steps of :data:`SHARED_STEP_TENSORS` as :attr:`PackedSeries.steps` gave them (``bits``,
            ``sensitivity`` and ``finer`` then only label them): a field fine-tuned towards those steps is
            packed on exactly them.
        predictors: name -> the predictors a quantised tensor may be coded with (None, or a name not there:
            every one that applies, the smallest kept; :func:`chosen_predictors`).

    Returns:
        The packed tensors and the values a loader restores (load them into a copy of ``field``, see
        :func:`packed_series_field`, to measure what the file gives back).

    Raises:
        InvalidArgument: ``bits`` outside :data:`~apmgsrn.io.quantization.MIN_BITS`..:data:`MAX_BITS`.
    """
    check_int("bits", bits, MIN_BITS, MAX_BITS)
    if not 0 <= finer < 1:
        raise InvalidArgument(f"finer={finer}: must be in [0, 1)", arguments=("finer",))
    parameters = {name: p.detach().cpu().float() for name, p in field.named_parameters()}
    shared = {name: shared_steps(values.numpy(), bits, slice_group(field.config.field.model, name,
                                                                   tuple(values.shape)))
              for name, values in parameters.items() if name in SHARED_STEP_TENSORS}
    if steps is None:
        allocated = ({name: uniform for name, (uniform, _) in shared.items()} if sensitivity is None
                     else sensitivity_steps(shared, sensitivity))
        if finer:
            allocated = {name: round_steps(chosen.astype(np.float64) * 2.0**-finer)
                         for name, chosen in allocated.items()}
    else:
        allocated = steps
    tensors, state, to_code = {}, {}, []
    for name in field.config.parameter_shapes():
        values = parameters[name]
        if name in SHARED_STEP_TENSORS:
            group_steps, group = allocated[name], shared[name][1]
        elif name == "encoder.residuals":
            group = group_size(tuple(values.shape))
            group_steps = steps_for_bits(values.numpy(), group, bits)
            if finer:
                group_steps = round_steps(group_steps.astype(np.float64) * 2.0**-finer)
        else:  # weights, grid placement and decoder: small, kept exactly
            tensors[name] = encode_float32(name, values)
            state[name] = values.clone()
            continue
        quantized = quantize(values, group_steps, group)
        to_code.append((name, quantized, (predictors or {}).get(name) or series_predictors(name, quantized.shape)))
        state[name] = quantized.dequantize()
    tensors.update((packed.name, packed) for packed in encode_quantized_all(to_code))  # coded side by side
    return PackedSeries([tensors[name] for name in field.config.parameter_shapes()], state, bits, finer,
                        {name: allocated[name] for name in shared})


def packed_group(packed: PackedSeries, name: str, shape: tuple[int, ...]) -> int:
    """Elements per quantisation group of one step's slice of the per-step tensor ``name`` of ``shape``
    ``[T, ...]`` as ``packed`` quantised it (its :attr:`PackedSeries.steps` hold ``T`` times each group's step)."""
    per_slice = packed.steps[name].size // shape[0]
    return math.prod(shape[1:]) // per_slice


def step_tensors(field: SeriesField) -> dict[str, torch.Tensor]:
    """Copies of a series field's per-step tensors that packing quantises with shared steps
    (:data:`SHARED_STEP_TENSORS`): what :meth:`SeriesPacking.repack` may restore steps from."""
    return {name: p.detach().clone() for name, p in field.named_parameters() if name in SHARED_STEP_TENSORS}


def chosen_predictors(packed: PackedSeries) -> dict[str, tuple[str, ...]]:
    """The predictor each quantised tensor of ``packed`` was coded with (the ``predictors`` of :func:`pack_series`)."""
    return {t.name: (t.predictor,) for t in packed.tensors if t.encoding == "quantized"}


@dataclass(frozen=True)
class SeriesPacking:
    """How a series is packed: at ``bits``, or at the largest bit width from ``bits`` down to ``min_bits`` whose
    coded parameters fit in ``target_bytes``.

    Attributes:
        bits: the bit width (the largest tried, with a target).
        target_bytes: bytes the file may take (None: no limit; the description and framing are allowed for,
            as measured: :func:`series_overhead`).
        min_bits: the smallest bit width tried for a target.
        strict: refuse to pack when not even ``min_bits`` fits (False: pack at ``min_bits`` anyway, as the
            default cap of ``train`` does).
        qat_iterations: a quantisation-aware fine-tune of every step before coding, this many iterations each
            (:mod:`apmgsrn.series.qat`; 0: none). Needs the data: ``train`` runs it.
        decoder_iterations: a fine-tune of the shared decoder to the grids as coded, on all steps at once, this
            many iterations (:mod:`apmgsrn.series.decoder`; 0: none). Needs the data: ``train`` runs it.
        recipe: the packing's margins and search lattice (a run's fingerprint leaves them out: :meth:`settings`).
    """

    bits: int = PACKING.series_bits
    target_bytes: int | None = None
    min_bits: int = MIN_BITS
    strict: bool = True
    qat_iterations: int = 0
    decoder_iterations: int = 0
    recipe: PackingRecipe = dataclass_field(default=PACKING, repr=False)

    def __post_init__(self) -> None:
        """Refuse values packing cannot run with (:class:`~apmgsrn.errors.InvalidArgument`)."""
        check_int("bits", self.bits, MIN_BITS, MAX_BITS)
        check_int("min_bits", self.min_bits, MIN_BITS, self.bits)
        check_int("qat_iterations", self.qat_iterations, 0)
        check_int("decoder_iterations", self.decoder_iterations, 0)
        if self.target_bytes is not None:
            check_int("target_bytes", self.target_bytes, 1)

    def settings(self) -> dict:
        """The fields as a run's fingerprint records them: all but :attr:`recipe`, which the code fixes."""
        return {name: value for name, value in asdict(self).items() if name != "recipe"}

    def pack(self, field: SeriesField, overhead: int | None = None) -> PackedSeries:
        """The packed field (with a target the finest bit width from ``bits`` down to ``min_bits``, in
        ``PACKING.finer_resolution`` of a bit, whose coded parameters fit: :meth:`_search`).

        With :attr:`qat_iterations` the field is to be fine-tuned towards these steps and packed on them again
        (:meth:`repack`): a target is then met within ``PACKING.tuned_bytes_margin`` less, where it can be, so that
        the fine-tuned values, which code a little larger, still fit; and the width kept is not coded with every
        predictor again, since only its steps are used.

        Args:
            overhead: the bytes the file's description and framing take (:func:`series_overhead` with what the
                file will describe; None: measured with placeholders of the same length).
        """
        if self.target_bytes is None:
            return self._pack(field, None, final=not self.qat_iterations, overhead=None)
        overhead = series_overhead(field) if overhead is None else overhead
        if self.qat_iterations:
            try:
                margin = self.recipe.tuned_bytes_margin
                return self._pack(field, max(1, round(self.target_bytes * (1 - margin))), final=False,
                                  overhead=overhead)
            except InvalidArgument:  # fits the target only without the margin
                pass
        return self._pack(field, self.target_bytes, final=not self.qat_iterations, overhead=overhead)

    def tune_iterations(self, packed: PackedSeries) -> int:
        """The quantisation-aware fine-tune's iterations per step towards ``packed`` (:meth:`pack`):
        :attr:`qat_iterations`, shortened in proportion where the packing could not leave
        ``PACKING.tuned_bytes_margin`` of the target free for what the fine-tuned values code larger (its bit width
        at ``min_bits``), none where it left nothing free.

        A fine-tune whose values do not fit is undone on as many steps as it takes (:meth:`repack`), and the
        iterations it ran on them are lost; where the margin is free every iteration counts (docs/time_series.md)."""
        if not self.qat_iterations or self.target_bytes is None:
            return self.qat_iterations
        free = coded_budget(self.target_bytes, packed.overhead or 0) - packed.parameter_bytes
        share = free / (self.recipe.tuned_bytes_margin * self.target_bytes)
        return self.qat_iterations if share >= 1 else max(0, round(self.qat_iterations * share))

    def fine_tune(self, field: SeriesField, packed: PackedSeries, tune: Callable[[PackedSeries, int], object]
                  ) -> tuple[PackedSeries, int]:
        """``field`` fine-tuned towards ``packed`` (:meth:`pack` of it) for :meth:`tune_iterations`, by
        ``tune(packed, iterations)`` (each step, in place), then packed on the same steps (:meth:`repack`).

        Returns:
            (the packing, the fine-tune's iterations per step: 0, and ``packed`` itself, where none ran).
        """
        iterations = self.tune_iterations(packed)
        if iterations:
            before = step_tensors(field)
            tune(packed, iterations)
            packed = self.repack(field, packed, before)
        return packed, iterations

    def tune_decoder(self, field: SeriesField, packed: PackedSeries, tune: Callable[[int], int]
                     ) -> tuple[PackedSeries, int]:
        """``field`` set to what ``packed`` (its final packing) gives back, its decoder fine-tuned for
        :attr:`decoder_iterations` by ``tune(iterations)`` (which returns the iterations it kept: 0 where it put
        the decoder back), and packed again on the same integers with the new decoder.

        The decoder is stored exactly, so the file changes by no more than LZMA's coding of other float32 weights
        may differ (:meth:`pack` leaves room for it); should that take it past the target (or, where ``packed``
        was past it already, at :attr:`min_bits` of a packing that is not strict, past ``packed`` by more than
        that room), the decoder is put back.

        Returns:
            (the packing, the decoder's iterations: 0, and ``packed`` itself, where none were kept).
        """
        field.load_state_dict(packed.state)
        if not self.decoder_iterations:
            return packed, 0
        kept = {name: value.clone() for name, value in field.decoder.state_dict().items()}
        iterations = tune(self.decoder_iterations)
        if not iterations:
            return packed, 0
        again = replace(pack_series(field, packed.bits, finer=packed.finer, steps=packed.steps,
                                    predictors=chosen_predictors(packed)), restored=packed.restored,
                        overhead=packed.overhead)
        if self.target_bytes is not None:
            # a packing already past the target (at min_bits, not strict) may grow by as much as one within it
            limit = max(coded_budget(self.target_bytes, _overhead(field, packed)),
                        packed.parameter_bytes + self._decoder_margin(field))
            if again.parameter_bytes > limit:
                field.decoder.load_state_dict(kept)
                return packed, 0
        return again, iterations

    def repack(self, field: SeriesField, packed: PackedSeries,
               before: dict[str, torch.Tensor] | None = None) -> PackedSeries:
        """``field`` packed on the steps of ``packed`` (an earlier packing of it, which a quantisation-aware
        fine-tune then trained it towards), every tensor coded with the predictor ``packed`` chose (the
        fine-tune moves the integers by a step or so; on the viscous-finger series the ``time`` predictor codes
        them 20-30 % smaller than any other).

        Should the result no longer fit the target: with ``before`` (:func:`step_tensors` of the field before
        the fine-tune, which ``packed`` held) the steps whose integers the fine-tune moved most get their values
        from before it back, as few as fit (a bisection on their number; all of them are ``packed`` itself),
        and the field keeps what was packed (:attr:`PackedSeries.restored` names them); without, the field is
        packed anew (:meth:`pack`, the fine-tune lost)."""
        predictors = chosen_predictors(packed)
        again = replace(pack_series(field, packed.bits, finer=packed.finer, steps=packed.steps, predictors=predictors),
                        overhead=packed.overhead)
        budget = (None if self.target_bytes is None
                  else self._coded_budget(self.target_bytes, field, _overhead(field, packed)))
        if budget is None or again.parameter_bytes <= budget:
            return again
        if before is None:
            return replace(self, qat_iterations=0).pack(field, _overhead(field, packed))
        tuned = step_tensors(field)
        moved = np.zeros(field.steps)
        for name, values in tuned.items():
            group = packed_group(packed, name, tuple(values.shape))
            levels = [quantize(v.cpu(), packed.steps[name], group).levels.reshape(field.steps, -1)
                      for v in (values, before[name])]
            moved += (levels[0] != levels[1]).sum(axis=1)
        order = [int(t) for t in np.argsort(-moved, kind="stable")]
        parameters = dict(field.named_parameters())

        @torch.no_grad()
        def restore(count: int) -> None:
            for name, values in tuned.items():
                parameters[name].copy_(values)
                parameters[name][order[:count]] = before[name][order[:count]].to(values.device)

        def restoring(count: int) -> PackedSeries:
            restore(count)
            return replace(pack_series(field, packed.bits, finer=packed.finer, steps=packed.steps,
                                       predictors=predictors), restored=tuple(sorted(order[:count])),
                           overhead=packed.overhead)

        low, high = 0, field.steps  # restoring `high` steps fits (all of them: `packed`), `low` does not
        best = replace(packed, restored=tuple(range(field.steps)))
        while high - low > 1:
            middle = (low + high) // 2
            tried = restoring(middle)
            if tried.parameter_bytes <= budget:
                high, best = middle, tried
            else:
                low = middle
        restore(high)  # the field holds what was packed
        return best

    def holds_every_step_alone(self, field_config, steps: int) -> bool:
        """Whether the target holds the step tensors (:data:`SHARED_STEP_TENSORS`) of a series of ``field_config``
        (a :class:`SeriesFieldConfig` fitted to its steps' shape) of ``steps`` steps at :attr:`bits` a value, each
        step as if coded with nothing taken from its neighbour: then the packing never has to narrow the bits for
        what consecutive steps do not share, and the steps need not be pulled towards each other
        (:func:`~apmgsrn.series.qat.budgeted`). False without a target. Decided before any training, so against
        the whole target: the description and framing are a few hundred bytes of it."""
        if self.target_bytes is None:
            return False
        shapes = field_config.parameter_shapes()
        values = sum(math.prod(shapes[name]) for name in SHARED_STEP_TENSORS if name in shapes)  # every step's
        return values * self.bits / 8 <= self.target_bytes

    def _coded_budget(self, target_bytes: int, field: SeriesField, overhead: int) -> int:
        """Bytes the coded parameters of ``field`` may take in a file of ``target_bytes`` whose description and
        framing take ``overhead`` (:func:`~apmgsrn.training.budget.coded_budget`), less, where the decoder is
        fine-tuned after coding (:meth:`tune_decoder`), ``PACKING.decoder_bytes_margin`` of its float32 bytes: its
        new weights code a few bytes larger or smaller."""
        return max(1, coded_budget(target_bytes, overhead) - self._decoder_margin(field))

    def _decoder_margin(self, field: SeriesField) -> int:
        """``PACKING.decoder_bytes_margin`` of ``field``'s decoder's float32 bytes where it is fine-tuned after coding,
        else 0."""
        if not self.decoder_iterations:
            return 0
        return math.ceil(self.recipe.decoder_bytes_margin * 4 * sum(p.numel() for p in field.decoder.parameters()))

    def _pack(self, field: SeriesField, target_bytes: int | None, final: bool, overhead: int | None
              ) -> PackedSeries:
        """:meth:`pack` to ``target_bytes`` with ``overhead`` bytes of description and framing; ``final``: the
        width a search kept coded with every predictor (else with those of its trials)."""
        budget = None if target_bytes is None else self._coded_budget(target_bytes, field, overhead)
        sensitivity = series_sensitivity(field)
        packed = replace(pack_series(field, self.bits, sensitivity), overhead=overhead)
        if budget is None or packed.parameter_bytes <= budget:
            return packed
        # The trials below code every tensor with the predictor this first one chose (LZMA, one predictor
        # instead of each: most of a trial's time); the width kept is coded with each again, never larger.
        best = self._search(field, packed, sensitivity, budget, self.min_bits, self.recipe.finer_resolution)
        if best is not None:
            return replace(pack_series(field, best.bits, sensitivity, best.finer) if final else best,
                           overhead=overhead)
        if self.strict:
            raise InvalidArgument(f"target_bytes={target_bytes}: the series' parameters alone take "
                                  f"{pack_series(field, self.min_bits, sensitivity).parameter_bytes:,} bytes even "
                                  f"at {self.min_bits} bits; allow more bytes or train a smaller model",
                                  arguments=("target_bytes",))
        return replace(pack_series(field, self.min_bits, sensitivity), overhead=overhead)

    @staticmethod
    def _search(field: SeriesField, top: PackedSeries, sensitivity: dict[str, np.ndarray], budget: int,
                min_bits: int, resolution: float) -> PackedSeries | None:
        """The finest packing from ``min_bits`` up to below ``top``'s width (which does not fit the ``budget``)
        on the lattice of ``PACKING.finer_resolution`` that fits (:func:`~apmgsrn.training.budget.largest_fitting`),
        its trials coded with ``top``'s predictors; None if not even ``min_bits`` fits."""
        predictors = chosen_predictors(top)
        unit = round(1 / resolution)
        fitting: dict[int, PackedSeries] = {}  # the finest trial that fits so far (the search only moves up)

        def size(k: int) -> int:
            tried = pack_series(field, k // unit, sensitivity, (k % unit) / unit, predictors=predictors)
            if tried.parameter_bytes <= budget:
                fitting.clear()
                fitting[k] = tried
            return tried.parameter_bytes

        found = largest_fitting(size, budget, min_bits * unit, round(top.bit_width * unit), top.parameter_bytes)
        return None if found is None else fitting[found[0]]


def _overhead(field: SeriesField, packed: PackedSeries) -> int:
    """The overhead ``packed`` measured, or, for a packing without a target, that of ``field`` with placeholders."""
    return series_overhead(field) if packed.overhead is None else packed.overhead


def series_growth(steps: int, recipe: SeriesRecipe = SERIES) -> float:
    """How many times the default size and the steps' training budget of a series of up to
    ``SERIES.share_steps`` steps a series of ``steps`` gets: 1 up to that length, in
    proportion beyond it."""
    return max(1.0, steps / recipe.share_steps)


def default_series_qat(model: str, iterations: int) -> int:
    """Quantisation-aware fine-tune iterations per step of a stepwise ``model`` series whose start model trains
    ``iterations`` (``ModelRecipe.series_qat_share``; at least one where the kind has a share)."""
    share = model_recipe(model).series_qat_share
    return max(1, round(share * iterations)) if share > 0 else 0


def default_series_decoder(model: str, iterations: int) -> int:
    """Decoder fine-tune iterations of a stepwise ``model`` series whose start model trains ``iterations``
    (``ModelRecipe.series_decoder_share``; at least one where the kind has a share)."""
    share = model_recipe(model).series_decoder_share
    return max(1, round(share * iterations)) if share > 0 else 0


def default_series_packing(field_config, volume_shape: tuple[int, int, int], iterations: int) -> SeriesPacking:
    """How ``train`` packs a stepwise series of ``field_config`` (a :class:`SeriesFieldConfig`) of
    ``(D, H, W)`` steps by default: within ``PACKING.series_models`` single-step files of its preset (times
    :func:`series_growth` of its steps), each counted at the bytes its parameters are stored in (float16 tables of
    the hybrid presets), lowering the bit width to fit down to ``ModelRecipe.series_min_bits`` (a hybrid series:
    ``ModelRecipe.series_min_bits``), every step fine-tuned towards its packing first where the kind does so
    (:func:`default_series_qat` of the start model's ``iterations``)."""
    single = stored_bytes(field_config.field.fitted_to(volume_shape))
    model = field_config.field.model
    lowest = model_recipe(model).series_min_bits
    target = round(PACKING.series_models * single * series_growth(field_config.series.steps))
    return SeriesPacking(PACKING.series_bits, target, lowest, strict=False,
                         qat_iterations=default_series_qat(model, iterations),
                         decoder_iterations=default_series_decoder(model, iterations))


def series_overhead(field: SeriesField, source: SourceInfo | None = None, training: dict | None = None,
                    steps: list[SeriesStepInfo] | None = None) -> int:
    """The bytes a packed series file of ``field`` takes beside its coded parameters: the description and the
    container's framing (:func:`~apmgsrn.training.budget.overhead_bytes`), measured on the file itself with no
    parameter bytes, every figure packing has not measured yet a placeholder of the same length.

    Args:
        source, training, steps: what the file will describe (None: placeholders, a source and step names as long
            as usual files', a training summary of every entry a packed series keeps).
    """
    count = field.steps
    draws = np.random.default_rng(0)

    def figure(digits: int = 17) -> float:  # as long, and as little compressible, as a measured figure
        return float(f"{100 * draws.random() + 10:.{digits}g}")

    source = source or SourceInfo(f"{'step':_<24}.vti", "v" * 8, f"{'step':_<24}.vti 256x256x256 (x*y*z) float32",
                                  "float32")
    steps = steps or [SeriesStepInfo(t, f"{'step':_<20}{t:04d}.vti", (figure(), figure())) for t in range(count)]
    training = {"iterations": 10**6, "batch_size": 1 << 15, "seconds": figure(), "frozen_at": 10**6,
                "stopped_early": False, "device": "cpu", "psnr": figure(), "max_abs_error": figure(),
                **(training or {}), "steps": [{"psnr": figure(), "max_abs_error": figure()} for _ in range(count)]}
    report = {"mode": "size", "bits": figure(6), "target_bytes": 10**9, "float32_psnr": figure(6),
              "float32_max_abs_error": figure(6), "float32_parameter_bytes": 10**9, "qat_iterations": 10**4,
              "qat_restored_steps": count, "decoder_iterations": 10**4, "psnr": figure(6),
              "max_abs_error": figure(6), "psnr_cost": figure(6), "worst_step_psnr_cost": figure(6)}
    tensors = [PackedTensor(name, "quantized", b"", group_size(shape), "lorenzo", 2)
               if name in (*SHARED_STEP_TENSORS, "encoder.residuals") else PackedTensor(name, "float32", b"")
               for name, shape in field.config.parameter_shapes().items()]
    return overhead_bytes(len(packed_series_bytes(field, tensors, source, training, steps, report)), [])


def packed_series_field(field: SeriesField, packed: PackedSeries) -> SeriesField:
    """A copy of ``field`` (CPU, eval) holding the packed values: what the packed file loads as."""
    restored = copy.deepcopy(field).cpu().eval()
    restored.load_state_dict(packed.state, strict=True)
    return restored


def write_packed_series(path: str | os.PathLike, field: SeriesField, packed: PackedSeries, source: SourceInfo,
                        training: dict, steps: list[SeriesStepInfo], report: dict) -> int:
    """Write a packed series file atomically (replacing an older series file of either kind).

    Args:
        path: the model file.
        field: the series field that was packed.
        packed: its packed parameters (:func:`pack_series`).
        source: where the data came from.
        training: the training summary (its loss history is dropped; ``steps``, per-step figures, is kept:
            give those of the packed field).
        steps: one entry per step, in order.
        report: what packing measured (numbers, strings or None).

    Returns:
        Bytes written.
    """
    return save_packed_series(path, packed_series_bytes(field, packed.tensors, source, training, steps, report))


def series_packing_report(field: SeriesField, bits: float, before: SeriesEvaluation, after: SeriesEvaluation,
                          target_bytes: int | None = None, qat_iterations: int = 0,
                          qat_restored_steps: int = 0, decoder_iterations: int = 0) -> dict:
    """What packing a series at ``bits`` cost, as the file's ``packing`` entry (``info`` shows it).

    Args:
        field: the series field (its float32 parameter count).
        bits: the bit width packed to (:attr:`PackedSeries.bit_width`: fractional where a size target refined it).
        before, after: the field measured on every step before and after packing.
        target_bytes: the bytes the coded parameters were to fit in, if any.
        qat_iterations: each step's quantisation-aware fine-tune (``before`` is the field before it).
        qat_restored_steps: steps packed with their values from before that fine-tune, to fit the target
            (:attr:`PackedSeries.restored`).
        decoder_iterations: the fine-tune of the decoder to the coded grids (:meth:`SeriesPacking.tune_decoder`).
    """
    bits = int(bits) if float(bits).is_integer() else bits
    report = {"mode": "bits" if target_bytes is None else "size", "bits": bits, "target_bytes": target_bytes,
              "float32_psnr": before.psnr, "float32_max_abs_error": before.max_abs_error,
              "float32_parameter_bytes": 4 * field.parameter_count(), "qat_iterations": qat_iterations,
              "qat_restored_steps": qat_restored_steps, "decoder_iterations": decoder_iterations,
              "psnr": after.psnr, "max_abs_error": after.max_abs_error, "psnr_cost": _cost(before.psnr, after.psnr),
              "worst_step_psnr_cost": max(_cost(b.psnr, a.psnr) for b, a in zip(before.steps, after.steps))}
    return {k: float(f"{v:.6g}") if isinstance(v, float) else v for k, v in report.items()}


def _cost(reference: float, psnr: float) -> float:
    """PSNR lost against ``reference`` (0 where both are exact)."""
    return 0.0 if reference == psnr else reference - psnr

"""Packing a trained field into a small file, and an error bound at every voxel (docs/method.md §10).

1. **Steps.** Every parameter is quantised uniformly, one step per group (:mod:`apmgsrn.io.quantization`).
   With a bit width ``B`` the steps fit each group in ``B`` signed bits. Otherwise they follow each group's
   effect on the output: for a step ``s`` the rounding noise (variance ``s^2 / 12``) adds about
   ``sens * s^2 / 12`` to the output's mean squared error, where ``sens`` is the mean of
   ``(d output / d parameter)^2`` over the domain. Steps ``s_g = scale / sqrt(sens_g)`` make every group
   cost the same error per stored bit (the classic high-rate allocation), so one number, ``scale``, trades
   size against PSNR: it is searched for the size asked (``target_bytes``) or for the PSNR cost allowed
   (``psnr_loss``). ``sens`` is estimated without the data: random points, random signs and autograd
   (``E[(sum_p r_p g_p)^2] = sum_p g_p^2`` for signs ``r_p`` of mean 0 and variance 1). Features that no
   point reaches (grid cells outside the domain) are stored as zero.
2. **Quantisation-aware fine-tune** (optional, inside the training budget): a few iterations in which the
   forward pass sees the quantised parameters and the update lands on the float ones (straight-through).
3. **Coding**: predictor, byte planes and LZMA (:mod:`apmgsrn.io.codec`), written by
   :mod:`apmgsrn.io.packed`.
4. **Error bound** ``max_error``: the packed network is evaluated at every voxel; where it misses the data
   by more than the bound, the residual is stored quantised with a step just under ``2 * max_error``, so
   ``|network + correction - data| <= max_error`` at every voxel. The result is verified on every voxel
   before the file is written.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch

from apmgsrn.arguments import check_int, check_number
from apmgsrn.errors import ApmgsrnError, InvalidArgument
from apmgsrn.inference.evaluate import Evaluation, ErrorAccumulator, evaluate
from apmgsrn.inference.slabs import field_slabs
from apmgsrn.io import SourceInfo
from apmgsrn.io.packed import (
    PackedTensor,
    VoxelCorrection,
    build_field,
    encode_float32,
    encode_quantized_all,
    packed_file_bytes,
    save_packed,
)
from apmgsrn.io.field_file import FieldDescription
from apmgsrn.io.quantization import (
    MAX_BITS,
    MAX_LEVEL,
    MIN_BITS,
    QuantizedTensor,
    group_count,
    group_ids,
    group_size,
    round_steps,
    steps_for_bits,
)
from apmgsrn.models.corrected_field import CorrectedField
from apmgsrn.models.field import NeuralField
from apmgsrn.recipes import PACKING, model_recipe
from apmgsrn.training.budget import coded_budget, largest_fitting, overhead_bytes
from apmgsrn.training.points import draw_batch

#: ``bits=FLOAT32_BITS`` keeps every parameter exactly (float32, entropy-coded): for an error bound alone.
FLOAT32_BITS = 32


@dataclass(frozen=True)
class PackConfig:
    """How to pack a field.

    Attributes:
        bits: fixed bit width of every quantised value (2..16), or 32 to keep float32 (an error bound
            alone); None: steps follow each parameter's effect on the output (``target_bytes`` or
            ``psnr_loss`` sets how fine).
        target_bytes: the file size to land at or just under (the error bound's correction comes on top).
        psnr_loss: with neither ``bits`` nor ``target_bytes``: the largest PSNR cost allowed (dB).
        max_error: guarantee ``|model - data| <= max_error`` (data units) at every voxel; None: no bound.
        qat_iterations: quantisation-aware fine-tune iterations (the caller takes them from its budget).
        qat_lr: peak learning rate of the fine-tune (cosine to zero).
        sensitivity_points: random points of the sensitivity estimate.
        measure_voxels: voxels compared while searching for ``psnr_loss`` (a regular subset).
        seed: seeds the sensitivity points and the fine-tune.
    """

    bits: int | None = None
    target_bytes: int | None = None
    psnr_loss: float = 0.1
    max_error: float | None = None
    qat_iterations: int = 0
    qat_lr: float = PACKING.qat_lr
    sensitivity_points: int = PACKING.sensitivity_points
    measure_voxels: int = PACKING.measure_voxels
    seed: int = 0

    def __post_init__(self) -> None:
        if self.bits is not None and self.bits != FLOAT32_BITS:
            check_int("bits", self.bits, MIN_BITS, MAX_BITS)
        if self.target_bytes is not None:
            check_int("target_bytes", self.target_bytes, 1)
            if self.bits is not None:
                raise InvalidArgument(f"bits={self.bits} and target_bytes={self.target_bytes}: give one of them; "
                                      "a size target chooses the steps itself", arguments=("bits", "target_bytes"))
        check_number("psnr_loss", self.psnr_loss, 0.0, low_open=True)
        if self.max_error is not None:
            check_number("max_error", self.max_error, 0.0, low_open=True)
        check_int("qat_iterations", self.qat_iterations, 0)
        if self.qat_iterations and self.bits == FLOAT32_BITS:
            raise InvalidArgument(f"qat_iterations={self.qat_iterations}: nothing to fine-tune when bits=32 keeps "
                                  "float32",
                                  arguments=("qat_iterations", "bits"))
        check_number("qat_lr", self.qat_lr, 0.0, low_open=True)
        check_int("sensitivity_points", self.sensitivity_points, 1)
        check_int("measure_voxels", self.measure_voxels, 1)
        check_int("seed", self.seed, 0, 2**63 - 1)

    @property
    def mode(self) -> str:
        """``float32``, ``bits``, ``size`` or ``psnr-loss``."""
        if self.bits == FLOAT32_BITS:
            return "float32"
        if self.bits is not None:
            return "bits"
        return "size" if self.target_bytes is not None else "psnr-loss"


def packed_overhead(config, volume_shape: tuple[int, int, int] = (256, 256, 256),
                    source: SourceInfo | None = None) -> int:
    """The bytes a packed file of a model of ``config`` fitted to ``volume_shape`` takes beside its coded
    parameters: the description and framing (:func:`~apmgsrn.training.budget.overhead_bytes`), measured on
    such a file with no parameter bytes, every figure training and packing record a placeholder of the same
    length. ``source``: the data it will describe (None: a name and text of usual length)."""
    draws = np.random.default_rng(0)
    figures = [float(f"{10 + 100 * v:.17g}") for v in draws.random(4)]  # as long as measured ones
    field = NeuralField(config, *figures, volume_shape=volume_shape)
    source = source or SourceInfo(f"{'volume':_<24}.nc", "v" * 8, f"{'volume':_<24}.nc 256x256x256 (x*y*z) float32",
                                  "float32")
    tensors = [PackedTensor(name, "quantized", b"", group_size(shape), "lorenzo", 2)
               for name, shape in field.config.parameter_shapes().items()]
    training = {"iterations": 10**6, "batch_size": 1 << 15, "seconds": figures[0] * 10, "frozen_at": 10**6,
                "stopped_early": False, "device": "cpu"}
    return overhead_bytes(len(packed_file_bytes(field, tensors, source, training,
                                                _placeholder_report("size", None, 10**9))), [])


def _placeholder_report(mode: str, bits: int | None, target_bytes: int | None) -> dict:
    """A packing report as long as the one :func:`pack_field` writes (a size search counts its bytes)."""
    report = {"mode": mode, "bits": bits, "target_bytes": target_bytes, "float32_psnr": math.pi,
              "float32_max_abs_error": math.pi, "float32_parameter_bytes": 10**9, "qat_iterations": 0,
              "scale": math.pi, "psnr": math.pi, "max_abs_error": math.pi, "psnr_cost": math.pi}
    return _rounded(report)


# ------------------------------------------------------------------------------------------ quantiser
@dataclass
class Quantizer:
    """Steps, dead parameters and level bound of every parameter of a field.

    Attributes:
        steps: name -> ``[G]`` float16 steps.
        groups: name -> group size.
        dead: name -> ``[numel]`` bool, parameters stored as zero (or None).
        bound: largest integer magnitude (``2^(B-1) - 1`` with a bit width).
    """

    steps: dict[str, np.ndarray]
    groups: dict[str, int]
    dead: dict[str, np.ndarray | None]
    bound: int = MAX_LEVEL

    def levels(self, name: str, values: torch.Tensor) -> np.ndarray:
        """``[numel]`` int32 integers of one parameter."""
        x = values.detach().cpu().numpy().reshape(-1).astype(np.float32)
        step = self.steps[name].astype(np.float32)[group_ids(x.size, self.groups[name])]
        levels = np.clip(np.rint(x / step), -self.bound, self.bound)
        if self.dead[name] is not None:
            levels[self.dead[name]] = 0
        return levels.astype(np.int32)

    def quantize(self, field: NeuralField) -> dict[str, QuantizedTensor]:
        """Every parameter of ``field`` quantised."""
        return {name: QuantizedTensor(tuple(p.shape), self.groups[name], self.steps[name], self.levels(name, p))
                for name, p in field.named_parameters()}

    def fake(self, name: str, values: torch.Tensor) -> torch.Tensor:
        """The values as they will be restored (quantised and dequantised), same device and shape."""
        levels = torch.from_numpy(self.levels(name, values)).to(values.device, torch.float32)
        step = torch.from_numpy(self.steps[name].astype(np.float32)).to(values.device)
        index = torch.arange(values.numel(), device=values.device) // self.groups[name]
        return (levels * step[index]).view(values.shape)


def parameter_sensitivity(field: NeuralField, points: int = 1 << 18, batch: int = 1 << 15,
                          seed: int = 0, names: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Mean squared derivative of the fitted output with respect to every parameter, over the domain.

    Args:
        field: the network (its parameters are not changed; gradients are cleared afterwards).
        points: random points in ``[-1, 1]^3`` (uniform, as the voxels of a PSNR are).
        batch: points per backward pass.
        seed: seeds the points and signs.
        names: only these parameters (None: all). The others then take no gradient, so that the encoder's
            fused kernels can run where they give gradients for features only (the grid placement fixed).

    Returns:
        name -> ``[numel]`` float64 ``mean_p (d m(p) / d theta)^2`` (``m``: the decoder output in ``[0, 1]``).
    """
    generator = torch.Generator().manual_seed(seed)
    device = next(field.parameters()).device
    every = dict(field.named_parameters())
    named = {name: p for name, p in every.items() if names is None or name in names}
    sums = {name: torch.zeros_like(p, dtype=torch.float64) for name, p in named.items()}
    requires = {name: p.requires_grad for name, p in every.items()}
    for name, p in every.items():
        p.requires_grad_(name in named)
    done = 0
    try:
        while done < points:
            n = min(batch, points - done)
            coordinates = (torch.rand(n, 3, generator=generator) * 2 - 1).to(device)
            signs = (torch.randint(0, 2, (n,), generator=generator) * 2 - 1).to(device, torch.float32)
            field.zero_grad(set_to_none=True)
            (field.normalized(coordinates).view(-1) * signs).sum().backward()
            for name, p in named.items():
                if p.grad is not None:
                    sums[name] += p.grad.double() ** 2
            done += n
    finally:
        field.zero_grad(set_to_none=True)
        for name, p in every.items():
            p.requires_grad_(requires[name])
    return {name: (total / points).cpu().numpy().reshape(-1) for name, total in sums.items()}


def group_means(values: np.ndarray, size: int) -> np.ndarray:
    """``[G]`` means of ``values`` over its groups of ``size`` elements (the last may be shorter)."""
    count = group_count(values.size, size)
    if count == 0:  # an empty tensor (a hybrid sized without domain levels): no groups
        return np.zeros(0)
    padded = np.zeros(count * size)
    padded[: values.size] = values
    members = np.full(count, size)
    members[-1] = values.size - (count - 1) * size
    return padded.reshape(count, size).sum(axis=1) / members


def sensitivity_quantizer(field: NeuralField, sensitivity: dict[str, np.ndarray], scale: float) -> Quantizer:
    """Steps ``scale / sqrt(mean sensitivity of the group)``; encoder features no sampled point reaches are
    stored as zero.

    Only features (grid cells, hash entries: the output is linear in each, through interpolation weights
    that are exactly zero away from it) are dropped, and only at exactly zero sensitivity. A decoder weight
    of zero sensitivity is kept: it can hold a ReLU unit off where the unit must stay off, and zeroing it
    turns the unit on (measured: 0.7 dB lost on a viscous-fingers model).
    """
    placed = {id(p) for p in field.encoder.placement_parameters()}
    steps, groups, dead = {}, {}, {}
    for name, p in field.named_parameters():
        size = group_size(tuple(p.shape))
        s = sensitivity[name]
        groups[name] = size
        steps[name] = round_steps(scale / np.sqrt(group_means(s, size) + 1e-300))
        dead[name] = s == 0 if name.startswith("encoder.") and id(p) not in placed else None
    return Quantizer(steps, groups, dead)


def bits_quantizer(field: NeuralField, bits: int) -> Quantizer:
    """Steps that fit every group in ``bits`` signed bits (no parameter is dropped)."""
    steps, groups = {}, {}
    for name, p in field.named_parameters():
        size = group_size(tuple(p.shape))
        groups[name] = size
        steps[name] = round_steps(steps_for_bits(p.detach().cpu().numpy(), size, bits))
    return Quantizer(steps, groups, {name: None for name in steps}, (1 << (bits - 1)) - 1)


def encode_field(field: NeuralField, quantizer: Quantizer | None, predictors: dict[str, str] | None = None
                 ) -> tuple[list[PackedTensor], dict[str, torch.Tensor]]:
    """Every parameter packed (float32 when ``quantizer`` is None) and the values a loader will restore.

    Args:
        field: the network.
        quantizer: steps of every parameter, or None to keep float32.
        predictors: name -> the predictor to use (default: whichever codes smallest).
    """
    if quantizer is None:
        return ([encode_float32(name, p) for name, p in field.named_parameters()],
                {name: p.detach().cpu().float().clone() for name, p in field.named_parameters()})
    to_code, state = [], {}
    for name, p in field.named_parameters():
        quantized = QuantizedTensor(tuple(p.shape), quantizer.groups[name], quantizer.steps[name],
                                    quantizer.levels(name, p))
        to_code.append((name, quantized, (predictors[name],) if predictors else None))
        state[name] = quantized.dequantize()
    return encode_quantized_all(to_code), state  # coded side by side


def _with_parameters(field: NeuralField, state: dict[str, torch.Tensor]) -> NeuralField:
    """A copy of ``field`` (plain :class:`NeuralField`, CPU, eval) holding ``state``, built as a loader does."""
    description = FieldDescription(field.config, (field.fit_min, field.fit_max), (field.value_min, field.value_max),
                                   field.transform, field.volume_shape, SourceInfo(), {})
    return build_field(description, state, None)


# ------------------------------------------------------------------------------------------ fine-tune
def fitted_values(field: NeuralField, truth: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """The data as ``field`` was trained on it: its value transform, then its own output scaling to ``[0, 1]``.

    Args:
        field: the trained field (its transform and fitted range are used, not refitted on ``truth``).
        truth: ``[D, H, W]`` data units.
        device: where to put the result.

    Returns:
        ``[D, H, W]`` float32 fitted values, the fine-tune's target.
    """
    span = field.fit_max - field.fit_min
    fitted = np.asarray(field.transform.apply(truth), dtype=np.float32)
    scaled = (fitted - np.float32(field.fit_min)) / np.float32(span if span > 0 else 1.0)
    return torch.from_numpy(np.ascontiguousarray(scaled, dtype=np.float32)).to(device)


def quantization_aware_fine_tune(field: NeuralField, values: torch.Tensor, quantizer: Quantizer, iterations: int,
                                 batch_size: int, lr: float, seed: int = 0, voxel_fraction: float = 0.0) -> None:
    """Fine-tune ``field`` in place so that its quantised parameters fit ``values`` well.

    Each iteration evaluates the field with every parameter replaced by its quantised value, and applies
    the gradient to the float parameters (straight-through estimator); Adam, learning rate ``lr`` falling
    to zero on a half cosine. Grid placements (the density loss's parameters) stay where they are. The points
    are drawn as the model's kind trains (``voxel_fraction`` of them on voxels): a hybrid fine-tuned on uniform
    points alone loses what its voxel points taught it (docs/packing.md, "How it works").

    Args:
        field: the trained field (on the training device).
        values: ``[D, H, W]`` fitted values in ``[0, 1]`` (as the trainer sees them), same device.
        quantizer: the steps the file will use.
        iterations: fine-tune iterations.
        batch_size: random points per iteration.
        lr: peak learning rate.
        seed: seeds the points.
        voxel_fraction: share of each batch drawn at voxel centres (:func:`~apmgsrn.training.points.draw_batch`).
    """
    if iterations <= 0:
        return
    device = values.device
    placed = {id(p) for p in field.encoder.placement_parameters()}
    named = {name: p for name, p in field.named_parameters() if id(p) not in placed}
    fixed = {name: p for name, p in field.named_parameters() if id(p) in placed}
    optimizer = torch.optim.Adam(list(named.values()), lr=lr, betas=(0.9, 0.99))
    generator = torch.Generator(device=device).manual_seed(seed)
    field.train()
    with torch.no_grad():  # placements are stored quantised too: fine-tune against those
        for name, p in fixed.items():
            p.copy_(quantizer.fake(name, p))
    requires = {name: p.requires_grad for name, p in fixed.items()}
    for p in fixed.values():
        p.requires_grad_(False)
    try:
        for iteration in range(iterations):
            for group in optimizer.param_groups:
                group["lr"] = lr * 0.5 * (1 + math.cos(math.pi * iteration / iterations))
            points, target = draw_batch(values, batch_size, voxel_fraction, generator)  # [B, 3], [B]
            saved = {}
            with torch.no_grad():
                for name, p in named.items():
                    saved[name] = p.detach().clone()
                    p.copy_(quantizer.fake(name, p))
            loss = (field.normalized(points, detach_placement=True).view(-1) - target).square().mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            with torch.no_grad():
                for name, p in named.items():
                    p.copy_(saved[name])
            optimizer.step()
    finally:
        for name, p in fixed.items():
            p.requires_grad_(requires[name])
        field.eval()


# ------------------------------------------------------------------------------------------ error bound
def voxel_correction(field: NeuralField, truth: np.ndarray, max_error: float) -> VoxelCorrection:
    """The sparse correction that brings ``field`` within ``max_error`` of ``truth`` at every voxel.

    Args:
        field: the (packed) network, data units.
        truth: ``[D, H, W]`` the data, data units.
        max_error: the bound (data units).

    Raises:
        ApmgsrnError: ``max_error`` is below what float32 values of this magnitude can resolve.
    """
    magnitude = max(abs(field.value_min), abs(field.value_max), field.value_max - field.value_min)
    if max_error < magnitude * 2.0**-16:
        raise ApmgsrnError(
            f"max_error={max_error:g}: too small for float32 values up to {magnitude:.6g} (at least "
            f"{magnitude * 2.0**-16:.3g}); pass a larger max_error=", arguments=("max_error",)
        )
    # a bound this much tighter than promised: float32 rounding of network + correction stays inside it
    step = 2 * max_error * (1 - PACKING.bound_margin)
    plane = truth.shape[1] * truth.shape[2]
    indices, levels = [], []
    for z, predicted in field_slabs(field, truth.shape):
        residual = truth[z].astype(np.float64) - predicted.numpy().astype(np.float64)
        level = np.rint(residual / step).reshape(-1)
        where = np.flatnonzero(level)
        indices.append(where + z.start * plane)
        levels.append(level[where].astype(np.int64))
    return VoxelCorrection(float(max_error), float(step), np.concatenate(indices), np.concatenate(levels))


def _bounded(field: NeuralField, correction: VoxelCorrection) -> CorrectedField:
    corrected = CorrectedField(field.config, fit_min=field.fit_min, fit_max=field.fit_max,
                               value_min=field.value_min, value_max=field.value_max, transform=field.transform,
                               volume_shape=field.volume_shape, max_error=correction.max_error)
    corrected.load_state_dict(field.state_dict(), strict=True)
    corrected.set_correction(torch.from_numpy(correction.indices), correction.values())
    return corrected.eval()


def _worst_voxels(field: NeuralField, truth: np.ndarray, bound: float) -> tuple[Evaluation, np.ndarray]:
    """Errors over every voxel, and the flat indices of voxels off by more than ``bound``."""
    errors = ErrorAccumulator()
    plane = truth.shape[1] * truth.shape[2]
    over = []
    for z, predicted in field_slabs(field, truth.shape):
        block = truth[z]
        errors.add(predicted.numpy(), block)
        miss = np.abs(predicted.numpy().astype(np.float64) - block.astype(np.float64)).reshape(-1) > bound
        over.append(np.flatnonzero(miss) + z.start * plane)
    return errors.result(), np.concatenate(over)


# ------------------------------------------------------------------------------------------ packing
@dataclass(frozen=True)
class PackResult:
    """A packed model and what packing measured.

    Attributes:
        field: the packed field as a loader restores it (a ``CorrectedField`` with an error bound).
        data: the file's bytes.
        report: what the file's ``packing`` entry holds.
        correction: the error bound's correction, or None.
    """

    field: NeuralField
    data: bytes
    report: dict
    correction: VoxelCorrection | None

    @property
    def file_bytes(self) -> int:
        return len(self.data)


def pack_field(
    field: NeuralField,
    truth: np.ndarray,
    config: PackConfig,
    source: SourceInfo,
    training: dict,
    values: torch.Tensor | None = None,
    batch_size: int = 1 << 15,
    float32: Evaluation | None = None,
    log: Callable[[str], None] | None = None,
) -> PackResult:
    """Quantise, (fine-tune,) code and bound a trained field; nothing is written.

    Args:
        field: the trained float32 field (a fine-tune changes it in place).
        truth: ``[D, H, W]`` the data in data units (PSNR cost, correction, verification).
        config: how to pack.
        source: where the data came from (saved in the file).
        training: the training summary (saved without its loss history).
        values: ``[D, H, W]`` fitted values in ``[0, 1]`` on the field's device, for the fine-tune.
        batch_size: points per fine-tune iteration.
        float32: the float32 field's errors over every voxel, if already measured.
        log: receives a line per stage.

    Returns:
        The packed field, file bytes and report.

    Raises:
        ApmgsrnError: the size target is below what the smallest steps reach, or the bound is too tight.
    """
    say = log or (lambda line: None)
    field = field.eval()
    if float32 is None:
        float32 = evaluate(field, truth)
    report = {"mode": config.mode, "bits": config.bits, "target_bytes": config.target_bytes,
              "float32_psnr": float32.psnr, "float32_max_abs_error": float32.max_abs_error,
              "float32_parameter_bytes": 4 * field.parameter_count(), "qat_iterations": 0}
    # What the final report adds, with values as long as the real ones: a size target counts them.
    placeholder = _rounded({**report, **{k: v for k, v in _placeholder_report(config.mode, config.bits,
                                                                               config.target_bytes).items()
                                         if k not in report}})
    quantizer, sensitivity, target = None, None, config.target_bytes
    if config.mode == "bits":
        quantizer = bits_quantizer(field, config.bits)
    elif config.mode != "float32":
        sensitivity = parameter_sensitivity(field.cpu(), config.sensitivity_points, seed=config.seed)
        if config.mode == "size":
            scale = _scale_for_size(field, sensitivity, target, source, training, placeholder)
        else:
            scale = _scale_for_psnr_loss(field, sensitivity, truth, float32, config)
        quantizer = sensitivity_quantizer(field, sensitivity, scale)
        report["scale"] = scale
    if quantizer is not None and config.qat_iterations and values is not None:
        say(f"quantisation-aware fine-tune: {config.qat_iterations} iterations")
        field.to(values.device)
        quantization_aware_fine_tune(field, values, quantizer, config.qat_iterations, batch_size, config.qat_lr,
                                     config.seed, model_recipe(field.config.model).voxel_fraction)
        field.cpu()
        report["qat_iterations"] = config.qat_iterations
    field = field.cpu().eval()
    for attempt in range(8):
        if config.mode == "size":  # after a fine-tune, or when the description came out longer: fit again
            report["scale"] = _scale_for_size(field, sensitivity, target, source, training, placeholder,
                                              low=report["scale"])
            quantizer = sensitivity_quantizer(field, sensitivity, report["scale"])
        tensors, state = encode_field(field, quantizer)
        packed = _with_parameters(field, state)
        network = evaluate(packed, truth)
        report.update(psnr=network.psnr, max_abs_error=network.max_abs_error,
                      psnr_cost=_cost(float32.psnr, network.psnr))
        data = packed_file_bytes(field, tensors, source, training, _rounded(report))
        if config.mode != "size" or len(data) <= config.target_bytes:
            break
        # The search sized the file with a placeholder report; the real one codes a few bytes differently.
        target -= (len(data) - config.target_bytes) << attempt
    if config.mode == "size" and len(data) > config.target_bytes:
        raise ApmgsrnError(f"target_bytes={config.target_bytes}: the packed file came out at {len(data)} bytes; "
                           "pass a slightly larger target", arguments=("target_bytes",))
    say(f"packed network: {len(data):,} bytes, PSNR {network.psnr:.2f} dB "
        f"(cost {report['psnr_cost']:.2f} dB against float32)")
    correction = None
    if config.max_error is not None:
        correction, packed, bounded = _bound(packed, truth, config.max_error)
        report.update(max_error=config.max_error, bounded_psnr=bounded.psnr,
                      bounded_max_abs_error=bounded.max_abs_error,
                      corrected_voxels=int(correction.indices.size))
        say(f"error bound {config.max_error:g}: {correction.indices.size:,} voxels corrected, max abs error "
            f"{bounded.max_abs_error:.6g}")
    report = _rounded(report)
    data = packed_file_bytes(field, tensors, source, training, report, correction)
    return PackResult(packed, data, report, correction)


def _rounded(report: dict) -> dict:
    """Floats to six significant digits (what a report needs, and a description of steady length)."""
    return {k: float(f"{v:.6g}") if isinstance(v, float) else v for k, v in report.items()}


def _cost(reference: float, psnr: float) -> float:
    if math.isinf(reference) and math.isinf(psnr):
        return 0.0
    return reference - psnr


def _bound(packed: NeuralField, truth: np.ndarray, max_error: float):
    """The correction, the corrected field and its errors; verified at every voxel (and mended where float32
    rounding pushed a voxel over, which the margin makes rare)."""
    correction = voxel_correction(packed, truth, max_error)
    for _ in range(3):
        corrected = _bounded(packed, correction)
        errors, over = _worst_voxels(corrected, truth, max_error)
        if not over.size:
            return correction, corrected, errors
        correction = _mend(correction, corrected, truth, over)
    raise ApmgsrnError(f"max_error={max_error:g}: {over.size} voxels stay over the bound after correction (float32 "
                       "rounding at this magnitude); pass a larger max_error=", arguments=("max_error",))


def _mend(correction: VoxelCorrection, corrected: CorrectedField, truth: np.ndarray,
          over: np.ndarray) -> VoxelCorrection:
    """Re-quantise the correction at voxels still over the bound, from their measured error."""
    shape = truth.shape
    z, rest = np.divmod(over, shape[1] * shape[2])
    y, x = np.divmod(rest, shape[2])
    points = torch.stack([torch.from_numpy(c.astype(np.float32)) * (2.0 / max(n - 1, 1)) - 1.0
                          for c, n in ((x, shape[2]), (y, shape[1]), (z, shape[0]))], dim=1)
    with torch.no_grad():
        output = corrected(points).view(-1).double().numpy()
    change = np.rint((truth.reshape(-1)[over].astype(np.float64) - output) / correction.step).astype(np.int64)
    levels = dict(zip(correction.indices.tolist(), correction.levels.tolist()))
    for index, delta in zip(over.tolist(), change.tolist()):
        levels[index] = levels.get(index, 0) + delta
    kept = sorted((i, v) for i, v in levels.items() if v)
    indices = np.array([i for i, _ in kept], dtype=np.int64)
    return VoxelCorrection(correction.max_error, correction.step, indices,
                           np.array([v for _, v in kept], dtype=np.int64))


def _lattice_scale(k: int) -> float:
    """The sensitivity scale at lattice point ``k`` (0: the coarsest; larger: finer steps, more bytes)."""
    return 10.0 ** (PACKING.scale_lattice[0] - k * PACKING.scale_lattice[2])


def _lattice_point(scale: float) -> int:
    """The lattice point of ``scale`` (rounded towards coarser steps)."""
    return max(0, math.floor((PACKING.scale_lattice[0] - math.log10(scale)) / PACKING.scale_lattice[2] + 1e-9))


def _scale_for_size(field, sensitivity, target: int, source, training, report, low: float | None = None) -> float:
    """The smallest scale (finest steps) on the lattice whose file fits in ``target`` bytes
    (:func:`~apmgsrn.training.budget.largest_fitting`, the file's overhead measured once:
    :func:`~apmgsrn.training.budget.overhead_bytes`).

    The predictors are chosen at the coarsest and finest probes and kept while searching (each probe then codes
    every tensor once); a second search, in a narrow bracket, uses those that suit the first one's answer. The
    final coding may only pick smaller ones.

    Args:
        low: a scale known to be no finer than the answer (a search before a fine-tune): the search starts there.

    Raises:
        ApmgsrnError: not even the coarsest steps fit (the description alone, or a network too large).
    """
    predictors: dict[str, str] = {}

    def coded(k: int, choose: bool = False) -> list[PackedTensor]:
        tensors, _ = encode_field(field, sensitivity_quantizer(field, sensitivity, _lattice_scale(k)),
                                  None if choose else predictors)
        if choose:
            predictors.update({t.name: t.predictor for t in tensors})
        return tensors

    def size(k: int, choose: bool = False) -> int:
        return sum(len(t.data) for t in coded(k, choose))

    coarsest = coded(0, choose=True)
    file_bytes = len(packed_file_bytes(field, coarsest, source, training, report))
    overhead = overhead_bytes(file_bytes, [t.data for t in coarsest])
    budget = coded_budget(target, overhead)
    if file_bytes > target:
        raise ApmgsrnError(
            f"target_bytes={target}: even with every parameter at its coarsest this model packs to "
            f"{file_bytes} bytes; pass a larger target (a lower ratio) or a smaller model",
            arguments=("target_bytes",),
        )
    finest = _lattice_point(low if low else 10.0 ** PACKING.scale_lattice[1])
    finest_size = size(finest, choose=True)
    if finest_size <= budget:
        return _lattice_scale(finest)
    found = largest_fitting(size, budget, 0, finest, finest_size)[0]
    # Again with the predictors that suit the answer, in a bracket of 50 lattice points each side.
    size(found, choose=True)
    below, above = max(found - 50, 0), min(found + 50, finest)
    while below > 0 and size(below) > budget:
        below = max(below - 50, 0)
    above_size = size(above)
    while above < finest and above_size <= budget:
        above = min(above + 50, finest)
        above_size = size(above)
    if above_size <= budget:
        return _lattice_scale(above)
    again = largest_fitting(size, budget, below, above, above_size)
    return _lattice_scale(again[0] if again is not None else found)


def _scale_for_psnr_loss(field, sensitivity, truth, float32: Evaluation, config: PackConfig) -> float:
    """The largest scale whose PSNR cost (measured on a voxel subset) stays within ``config.psnr_loss``.

    Starts from the scale the sensitivities predict (``scale^2 * parameters / 12`` of added squared error)
    and corrects it with measurements, taking the added error to grow as ``scale^2``.
    """
    reference = evaluate(field, truth, max_voxels=config.measure_voxels)
    if not math.isfinite(reference.psnr):
        return 1.0  # an exact (constant) field: nothing to lose
    allowed = reference.mse * (10 ** (config.psnr_loss / 10) - 1)  # added squared error, data units
    span = max(float32.data_max - float32.data_min, 1e-30)
    parameters = max(sum(v.size for v in sensitivity.values()), 1)
    # In fitted [0, 1] units the added error is scale^2 * parameters / 12; data units scale by the range.
    scale = math.sqrt(12 * allowed / parameters) / span
    best = None
    for _ in range(6):
        quantizer = sensitivity_quantizer(field, sensitivity, scale)
        _, state = encode_field(field, quantizer)
        measured = evaluate(_with_parameters(field, state), truth, max_voxels=config.measure_voxels)
        added = max(measured.mse - reference.mse, 1e-300)
        cost = reference.psnr - measured.psnr
        if cost <= config.psnr_loss:
            best = scale if best is None else max(best, scale)
            if cost >= 0.7 * config.psnr_loss:
                break
        scale *= min(max(math.sqrt(allowed * 0.85 / added), 0.25), 4.0)
        if best is not None and scale <= best:
            break
    for _ in range(8):  # never met: finer steps until it is (the report states the cost measured either way)
        if best is not None:
            break
        scale /= 2
        quantizer = sensitivity_quantizer(field, sensitivity, scale)
        _, state = encode_field(field, quantizer)
        measured = evaluate(_with_parameters(field, state), truth, max_voxels=config.measure_voxels)
        if reference.psnr - measured.psnr <= config.psnr_loss:
            best = scale
    return best if best is not None else scale


def write_packed(path: str | Path, result: PackResult) -> int:
    """Write a :class:`PackResult` atomically to ``path`` (replacing an older model file of either kind)."""
    return save_packed(path, result.data)


def pack_volume_model(field: NeuralField, volume, config: PackConfig, training: dict, device, out: Path,
                      log: Callable[[str], None] = print) -> PackResult:
    """Pack ``field`` against ``volume`` (a :class:`~apmgsrn.data.volume.Volume`) and write it to ``out``
    (replacing an older model file of either kind): ``train`` and ``pack`` of one volume, and :func:`apmgsrn.fit`.
    """
    truth = volume.to_numpy()
    values = fitted_values(field, truth, device) if config.qat_iterations else None
    result = pack_field(field.to(device), truth, config, SourceInfo.of_volume(volume), training, values=values,
                        log=log)
    write_packed(out, result)
    return result

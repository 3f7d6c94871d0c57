"""A time-varying field: one network for T steps of a simulation run (docs/method.md §10).

The adaptive grids extend into time through a small basis. Every grid ``i`` holds ``K`` basis grids
``B_ik`` (``[K, M, C, D, H, W]`` in all); the features of step ``t`` are the per-grid combination
``F_i(t) = sum_k w_tik B_ik`` with weights ``w`` ``[T, M, C, K]``. The grid placement (``A_i``, ``t_i``) and
the decoder are shared by every step (with one grid set per step, the placement may be per step too: series
whose structures travel, see :mod:`apmgsrn.series.steps`). Two ways to set the weights:

- ``"keyframes"``: fixed hat functions over ``K`` evenly spaced keyframes: the grids are 4-D and step ``t``
  interpolates its two neighbouring keyframes linearly in time (the paper's future-work grids).
- ``"learned"``: the weights are parameters (initialised to those hat functions), so every step and
  every grid chooses its own mix of the basis; with ``K = T`` this is one small grid set per step.

A series of the hybrid model (:mod:`apmgsrn.series.hybrid`) has no basis: every step holds all its own
encoder parameters (level table, grids, placement), filled step by step; the decoder is shared the same way.

Step ``t`` of ``T`` sits at time coordinate ``-1 + 2 t / (T - 1)``, corner-aligned like space; between two
steps the weights are interpolated linearly. Because a step's features are one ordinary ``[M, C, D, H, W]``
grid set, :meth:`SeriesField.step_field` materialises them once into a plain
:class:`~apmgsrn.models.field.NeuralField`: decoding or rendering a step costs what a single-step model costs.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
from torch import nn

from apmgsrn.arguments import check_choice, check_int
from apmgsrn.errors import InvalidArgument
from apmgsrn.models.decoder import Decoder
from apmgsrn.models.encoders.adaptive_multigrid import (
    MAX_RESOLUTION,
    AdaptiveMultiGridConfig,
    AdaptiveMultiGridEncoder,
    placed_boxes,
)
from apmgsrn.models.encoders.base import STORAGE_DTYPES, Encoder
from apmgsrn.models.field import NeuralField
from apmgsrn.models.registry import FieldConfig
from apmgsrn.series.hybrid import SeriesHybridEncoder
from apmgsrn.series.options import (
    COEFFICIENT_KINDS,
    MAX_BASIS,
    MAX_STEPS,
    PLACEMENT_KINDS,
    SERIES_DEFAULTS,
    STORAGE_KINDS,
)
from apmgsrn.models.value_transform import ValueTransform
from apmgsrn.ops.multigrid import multigrid_features

#: The parameters stored in ``SeriesConfig.storage`` (the rest is float32).
GRID_PARAMETERS = ("encoder.grids", "encoder.residuals", "encoder.coefficients", "encoder.level_table")
#: Model kinds a series extends: APMGSRN's grids (joint or stepwise), the hybrid's tables (stepwise).
SERIES_MODELS = ("apmgsrn", "hybrid")


@dataclass(frozen=True)
class SeriesConfig:
    """How a field extends over the steps of a series.

    Attributes:
        steps: number of time steps ``T``.
        basis: basis grids per grid ``K`` (at most ``T``; ``K = T`` gives every step its own grids).
        coefficients: ``"learned"`` (per step, grid and channel), ``"keyframes"`` (fixed hat functions:
            linear interpolation in time between ``K`` evenly spaced keyframes) or ``"cumulative"`` (the same
            interpolation parametrised by what changes at each keyframe; residuals summed over the steps).
        residual: resolution ``r`` of per-step residual grids ``[T, M, C, r, r, r]``, upsampled to the grids
            and added (0: none).
        storage: dtype the grids (and learned weights) are stored in (``"float32"`` or ``"float16"``).
        mixing: learned weights only: an ``r^3`` lattice of weights over each grid (trilinear between its nodes),
            so that each part of a grid mixes the basis its own way; 1: one weight per grid.
        placement: ``"shared"`` (one ``A_i, t_i`` for every step) or ``"per_step"`` (``[T, M, 3, 3]`` and
            ``[T, M, 3]``: every step places its grids itself; one grid set per step only).
    """

    steps: int
    basis: int = 4
    coefficients: str = "learned"
    residual: int = 0
    storage: str = "float32"
    mixing: int = 1
    placement: str = "shared"

    def __post_init__(self) -> None:
        """Refuse sizes and kinds the model cannot be built with (:class:`~apmgsrn.errors.InvalidArgument`)."""
        check_int("steps", self.steps, 1, MAX_STEPS)
        check_int("basis", self.basis, 1, min(self.steps, MAX_BASIS))
        check_choice("coefficients", self.coefficients, COEFFICIENT_KINDS)
        check_choice("storage", self.storage, STORAGE_KINDS)
        check_choice("placement", self.placement, PLACEMENT_KINDS)
        if self.placement == "per_step" and not self.per_step_grids:
            raise InvalidArgument("placement=per_step: needs one grid set per step (basis = steps, keyframes)",
                                  arguments=("placement",))
        if self.basis == 1 and self.steps > 1 and self.coefficients == "keyframes":
            raise InvalidArgument("basis=1: keyframes need at least 2 basis grids for a series of several steps",
                                  arguments=("basis",))
        if check_int("residual", self.residual, 0, MAX_RESOLUTION) == 1:
            raise InvalidArgument(f"residual=1: must be 0 (none) or 2..{MAX_RESOLUTION}", arguments=("residual",))
        if check_int("mixing", self.mixing, 1, MAX_RESOLUTION) > 1 and self.coefficients != "learned":
            raise InvalidArgument(f"mixing={self.mixing}: a lattice of weights needs coefficients=learned",
                                  arguments=("mixing", "coefficients"))

    @property
    def per_step_grids(self) -> bool:
        """Every step has its own grid set (keyframes at every step): what stepwise training fills."""
        return self.coefficients == "keyframes" and self.basis == self.steps

    def to_dict(self) -> dict:
        data = {"steps": self.steps, "basis": self.basis, "coefficients": self.coefficients, "residual": self.residual,
                "storage": self.storage, "mixing": self.mixing}
        if self.placement != "shared":  # files of shared placement read as before
            data["placement"] = self.placement
        return data


@dataclass(frozen=True)
class SeriesFieldConfig:
    """What to build for a series: the spatial field (an ``apmgsrn`` model) and its extension in time."""

    field: FieldConfig
    series: SeriesConfig

    def __post_init__(self) -> None:
        if self.field.model not in SERIES_MODELS:
            raise ValueError(f"a time-series model extends adaptive grids (apmgsrn) or the hybrid model, not "
                             f"{self.field.model!r}")
        if self.field.model == "hybrid" and not (self.series.per_step_grids and self.series.placement == "per_step"):
            raise ValueError("a time series of hybrid models has one grid set and placement per step "
                             "(trained stepwise)")

    def to_dict(self) -> dict:
        return {"field": self.field.to_dict(), "series": self.series.to_dict()}

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter, named as in the field's ``state_dict``."""
        shapes = self.field.parameter_shapes()
        if self.field.model == "hybrid":  # every encoder parameter per step
            return {name: (self.series.steps, *shape) if name.startswith("encoder.") else shape
                    for name, shape in shapes.items()}
        grids = shapes["encoder.grids"]
        shapes["encoder.grids"] = (self.series.basis, *grids)  # [K, M, C, D, H, W]
        m, c = grids[:2]
        if self.series.coefficients == "learned":
            lattice = (self.series.mixing,) * 3 if self.series.mixing > 1 else ()
            shapes["encoder.coefficients"] = (self.series.steps, m, c, self.series.basis, *lattice)  # [T, M, C, K(, r^3)]
        if self.series.residual:
            shapes["encoder.residuals"] = (self.series.steps, m, c, *(self.series.residual,) * 3)  # [T, M, C, r, r, r]
        if self.series.placement == "per_step":
            for name in ("encoder.matrices", "encoder.translations"):
                shapes[name] = (self.series.steps, *shapes[name])  # [T, M, 3, 3], [T, M, 3]
        return shapes

    def stored_dtypes(self) -> dict[str, torch.dtype]:
        """The dtype every parameter is stored in: the grids (basis and residuals) in ``series.storage``, the
        rest (weights, maps, decoder) in float32."""
        grids = STORAGE_DTYPES[self.series.storage]
        return {name: grids if name in GRID_PARAMETERS else torch.float32 for name in self.parameter_shapes()}

    def fitted_to(self, volume_shape: tuple[int, int, int]) -> "SeriesFieldConfig":
        """This config for a series of ``(D, H, W)`` steps (the hybrid's layout follows their lattice)."""
        return replace(self, field=self.field.fitted_to(volume_shape))


def series_config(field: FieldConfig, steps: int, basis: int | None = None, coefficients: str | None = None,
                  residual: int | None = None, storage: str | None = None) -> SeriesFieldConfig:
    """A series model's config: the spatial field extended over ``steps`` steps, defaults where None.

    The basis never exceeds the steps (a short series gets one basis grid per step).

    Raises:
        ValueError: options out of range, or a field that is not an ``apmgsrn`` model.
    """
    chosen = {"basis": basis, "coefficients": coefficients, "residual": residual, "storage": storage}
    options = {k: SERIES_DEFAULTS[k] if v is None else v for k, v in chosen.items()}
    if basis is None:
        options["basis"] = min(options["basis"], steps)
    return SeriesFieldConfig(field, SeriesConfig(steps=steps, **options))


def step_time(step: int | float, steps: int) -> float:
    """Time coordinate of step ``step`` of ``steps``: ``-1 + 2 t / (T - 1)`` (0 for a single step)."""
    return 0.0 if steps <= 1 else -1.0 + 2.0 * float(step) / (steps - 1)


def time_position(time: float, steps: int) -> float:
    """Fractional step index ``(time + 1) / 2 * (T - 1)`` of a time coordinate, clamped to the series."""
    return min(max((float(time) + 1.0) * 0.5 * (steps - 1), 0.0), float(steps - 1))


def keyframe_weights(steps: int, keyframes: int) -> torch.Tensor:
    """Hat functions over evenly spaced keyframes: the linear-in-time interpolation weights ``[T, K]``.

    Keyframe ``k`` sits at fractional step ``k (T - 1) / (K - 1)``; each row sums to 1 and has at most two
    non-zero entries (the two keyframes around the step). With ``K = T`` it is the identity.
    """
    if keyframes == 1:
        return torch.ones(steps, 1)
    position = torch.arange(steps, dtype=torch.float64) * (keyframes - 1) / max(steps - 1, 1)  # [T] in keyframes
    knots = torch.arange(keyframes, dtype=torch.float64)  # [K]
    return (1.0 - (position[:, None] - knots[None, :]).abs()).clamp(min=0.0).float()  # [T, K]


def cumulative(weights: torch.Tensor, dim: int) -> torch.Tensor:
    """Sums from the end along ``dim``: entry ``k`` becomes the sum of entries ``k, k+1, ...``.

    Applied to keyframe weights ``[T, K]`` it gives step ``t`` every keyframe increment up to it (1 for the
    keyframes before, the interpolation weight for the next): the same interpolation, parametrised by what
    changes at each keyframe. Applied to per-step residuals over ``T`` (dim 0) read the other way, step ``t``
    holds the sum of the increments of steps ``0 .. t``.
    """
    if dim == 0:
        return torch.cumsum(weights, dim=0)
    return torch.flip(torch.cumsum(torch.flip(weights, (dim,)), dim), (dim,))


class SeriesMultiGridEncoder(AdaptiveMultiGridEncoder):
    """Adaptive grids whose features vary over the steps of a series (see the module docstring).

    Parameters: ``grids`` ``[K, M, C, D, H, W]`` (the basis), ``coefficients`` ``[T, M, C, K]`` when learned
    (a buffer of hat functions for keyframes), ``matrices`` ``[M, 3, 3]`` and ``translations`` ``[M, 3]``
    shared by every step (per-step placement: ``[T, M, 3, 3]`` and ``[T, M, 3]``). Initialisation is
    docs/method.md §2's (the basis grids like one grid set, every step's placement the same), the weights start as the
    keyframe hat functions.
    """

    def __init__(self, config: AdaptiveMultiGridConfig, series: SeriesConfig, generator: torch.Generator | None = None):
        Encoder.__init__(self)  # the parameters' shapes differ from a single grid set's
        self.config = config
        self.series = series
        self.out_features = config.out_features
        shapes = config.parameter_shapes()
        self.grids = nn.Parameter(torch.empty((series.basis, *shapes["grids"])))  # [K, M, C, D, H, W]
        self.matrices = nn.Parameter(torch.empty(shapes["matrices"]))
        self.translations = nn.Parameter(torch.empty(shapes["translations"]))
        self.reset_parameters(generator)
        if series.placement == "per_step":
            self.matrices = nn.Parameter(self.matrices.detach().expand(series.steps, -1, -1, -1).clone())
            self.translations = nn.Parameter(self.translations.detach().expand(series.steps, -1, -1).clone())
        if series.residual:
            # Zero: a step starts as its basis mix; the residual learns what the basis cannot share.
            self.residuals = nn.Parameter(torch.zeros(series.steps, *shapes["grids"][:2], *(series.residual,) * 3))
        if series.per_step_grids:
            # The keyframe weights would be the identity [T, M, C, T]: a step reads its own slice instead.
            self.register_buffer("coefficients", torch.ones(series.steps, 1, 1, 1), persistent=False)
            return
        weights = keyframe_weights(series.steps, series.basis)  # [T, K]
        if series.coefficients == "cumulative":
            weights = cumulative(weights, dim=1)
        weights = weights[:, None, None, :].expand(series.steps, config.grids, config.features, series.basis)
        if series.mixing > 1:  # the same weights at every node of the lattice
            weights = weights[..., None, None, None].expand(*weights.shape, *(series.mixing,) * 3)
        if series.coefficients == "learned":
            self.coefficients = nn.Parameter(weights.clone())  # [T, M, C, K] or [T, M, C, K, r, r, r]
        else:
            self.register_buffer("coefficients", weights.clone(), persistent=False)

    def _upsampled(self, lattices: torch.Tensor) -> torch.Tensor:
        """Lattices at the grid resolution: ``[G, ..., r, r, r]`` -> ``[G, ..., D, H, W]`` (residuals, weights).

        Trilinear and corner-aligned, like the grids themselves, so a lattice node sits where a grid node does.
        """
        lead = lattices.shape[:-3]
        flat = lattices.reshape(lead[0], -1, *lattices.shape[-3:])  # [G, channels, r, r, r]
        up = nn.functional.interpolate(flat, size=self.config.resolution, mode="trilinear", align_corners=True)
        return up.view(*lead, *self.config.resolution)

    def step_grids(self, steps: torch.Tensor) -> torch.Tensor:
        """Feature grids of whole steps: ``steps`` ``[G]`` indices -> ``[G, M, C, D, H, W]``."""
        if self.series.per_step_grids:
            grids = self.grids[steps]  # one grid set per step
        elif self.series.mixing == 1:
            grids = torch.einsum("gmck,kmcdhw->gmcdhw", self.coefficients[steps], self.grids)  # weights [G, M, C, K]
        else:
            # Every node mixes the basis with the weights of the lattice around it ([G, M, C, K, r, r, r]).
            grids = (self._upsampled(self.coefficients[steps]) * self.grids.permute(1, 2, 0, 3, 4, 5)).sum(3)
        if self.series.residual:
            residuals = cumulative(self.residuals, dim=0) if self.series.coefficients == "cumulative" else self.residuals
            grids = grids + self._upsampled(residuals[steps])
        return grids

    step_parameters = ("grids", "matrices", "translations")
    step_features = ("grids",)

    def step_state(self, step: int) -> dict[str, torch.Tensor]:
        """Step ``step``'s grids and placement, named and shaped as a single grid set's."""
        grids = self.step_grids(torch.tensor([int(step)], device=self.grids.device))[0]
        return {"grids": grids, **dict(zip(("matrices", "translations"), self.step_placement(step)))}

    def step_placement(self, step: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Placement ``(A [M, 3, 3], t [M, 3])`` of the grids at step ``step``."""
        if self.series.placement == "per_step":
            return self.matrices[step], self.translations[step]
        return self.matrices, self.translations

    @torch.no_grad()
    def grid_boxes(self, step: int = 0) -> torch.Tensor:
        """Corners ``[M, 8, 3]`` of the grids at step ``step`` (the same at every step unless placed per step)."""
        return placed_boxes(*self.step_placement(step))

    def grids_at(self, position: float) -> torch.Tensor:
        """Feature grids ``[M, C, D, H, W]`` at a fractional step index: the two steps around it, mixed linearly
        (everything a step's grids are made of is linear in its weights and residuals)."""
        low = min(int(position), self.series.steps - 1)
        high = min(low + 1, self.series.steps - 1)
        fraction = position - low
        steps = torch.tensor([low, high] if fraction > 0 and high > low else [low], device=self.grids.device)
        grids = self.step_grids(steps)  # [1 or 2, M, C, D, H, W]
        return grids[0] if len(grids) == 1 else torch.lerp(grids[0], grids[1], fraction)

    def forward(self, points: torch.Tensor, steps: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features of groups of points, each group at one step.

        Args:
            points: ``[G * n, 3]`` global coordinates, group ``g`` in rows ``g n .. (g + 1) n``.
            steps: ``[G]`` step index of each group.
            detach_placement: as for :class:`AdaptiveMultiGridEncoder`.

        Returns:
            ``[G * n, M * C]`` features.
        """
        grids = self.step_grids(steps)  # [G, M, C, D, H, W]
        groups = points.view(len(steps), -1, 3)  # [G, n, 3]
        features = []
        for group, grid, step in zip(groups, grids, steps.tolist()):
            matrices, translations = self.step_placement(step)
            if detach_placement:
                matrices, translations = matrices.detach(), translations.detach()
            features.append(multigrid_features(group, matrices, translations, grid, backend=self.config.backend))
        return torch.cat(features)  # [G * n, M * C]

    def thread_invariant(self, threads: int) -> bool:
        """Not shown for the per-step mixing kernels: a series run keeps its thread count."""
        return False

    def decoded(self, points: torch.Tensor, weights: list[torch.Tensor]) -> torch.Tensor | None:
        """No fused kernel for a series (a step materialised as a single field has one)."""
        return None

    def feature_parameters(self) -> list[nn.Parameter]:
        """The parameters the reconstruction loss moves."""
        return [p for p in (self.grids, self.coefficients, getattr(self, "residuals", None)) if isinstance(p, nn.Parameter)]

    def check_parameters(self) -> str | None:
        """As for a single grid set, plus finite keyframe weights (a buffer, not among the parameters)."""
        problem = super().check_parameters()
        if problem is None and not bool(torch.isfinite(self.coefficients).all()):
            problem = "basis weights hold NaN or Inf"
        return problem


class SeriesField(nn.Module):
    """Maps points and a step to values: the field of every step of a series in one network.

    ``forward`` takes ``[N, 4]`` points ``(x, y, z, t)`` with the time coordinate ``t`` in ``[-1, 1]``; the
    trainer calls :meth:`normalized` with groups of points at whole steps; decoding and rendering use
    :meth:`step_field` / :meth:`time_field`, which materialise one step as a plain
    :class:`~apmgsrn.models.field.NeuralField`.

    Attributes:
        config: what was built.
        fit_min, fit_max: value range of the whole series in fitted units (after the value transform).
        value_min, value_max: value range of the whole series in data units.
        volume_shape: ``(D, H, W)`` of every step.
        transform: the value transform (one for the series).
    """

    def __init__(
        self,
        config: SeriesFieldConfig,
        fit_min: float = 0.0,
        fit_max: float = 1.0,
        value_min: float | None = None,
        value_max: float | None = None,
        transform: ValueTransform = ValueTransform(),
        volume_shape: tuple[int, int, int] = (0, 0, 0),
        generator: torch.Generator | None = None,
    ):
        super().__init__()
        self.volume_shape = tuple(int(s) for s in volume_shape)
        config = config.fitted_to(self.volume_shape)
        self.config = config
        if config.field.model == "hybrid":
            self.encoder = SeriesHybridEncoder(config.field.encoder, config.series.steps, generator=generator)
        else:
            self.encoder = SeriesMultiGridEncoder(config.field.encoder, config.series, generator=generator)
        self.decoder = Decoder(self.encoder.out_features, config.field.decoder, generator=generator)
        self.fit_min, self.fit_max = float(fit_min), float(fit_max)
        self.value_min = float(fit_min if value_min is None else value_min)
        self.value_max = float(fit_max if value_max is None else value_max)
        self.transform = transform

    @property
    def steps(self) -> int:
        """Number of time steps ``T``."""
        return self.config.series.steps

    def normalized(
        self,
        points: torch.Tensor,
        steps: torch.Tensor,
        detach_placement: bool = False,
        hidden_dtype: torch.dtype | None = None,
    ) -> torch.Tensor:
        """Decoder output ``m(y)`` ``[G * n, 1]`` for groups of points at steps ``[G]`` (see the encoder)."""
        return self.decoder(self.encoder(points, steps, detach_placement=detach_placement), hidden_dtype)

    def _materialise(self, state: dict[str, torch.Tensor]) -> NeuralField:
        """A single-step field with these encoder parameters (named and shaped as a single field's) and the
        shared decoder."""
        # Building the shell initialises weights it then overwrites; nn.Linear draws from the global random
        # generator, so fork it: decoding a step must not change what a caller's seed gives.
        with torch.random.fork_rng(devices=[]):
            field = NeuralField(
                self.config.field,
                fit_min=self.fit_min,
                fit_max=self.fit_max,
                value_min=self.value_min,
                value_max=self.value_max,
                transform=self.transform,
                volume_shape=self.volume_shape,
                generator=torch.Generator(),
            )
        device = self.decoder[0].weight.device
        with torch.no_grad():
            for name, value in state.items():
                getattr(field.encoder, name).copy_(value)
            field.decoder.load_state_dict(self.decoder.state_dict())
        return field.to(device).eval().requires_grad_(False)

    def step_field(self, step: int) -> NeuralField:
        """Step ``step`` (``0 .. T-1``) as a single-step field, its features materialised once.

        Raises:
            IndexError: ``step`` outside the series.
        """
        if not 0 <= int(step) < self.steps:
            raise IndexError(f"step {step} is outside the series of {self.steps} steps")
        with torch.no_grad():
            return self._materialise(self.encoder.step_state(int(step)))

    def time_field(self, time: float) -> NeuralField:
        """The field at time coordinate ``time`` in ``[-1, 1]`` (between steps: grids interpolated linearly).

        Raises:
            ValueError: a per-step placement between two steps (their grids sit in different places; the
                values are interpolated instead, :meth:`forward`).
        """
        position = time_position(time, self.steps)
        if self.config.series.placement == "per_step":
            if position != int(position):
                raise ValueError("steps placed apart have no grids between them; interpolate their values")
            return self.step_field(int(position))
        with torch.no_grad():
            return self._materialise({**self.encoder.step_state(0), "grids": self.encoder.grids_at(position)})

    def _values_at(self, time: float, points: torch.Tensor) -> torch.Tensor:
        """Values ``[N, 1]`` at ``[N, 3]`` points at time coordinate ``time``: shared placement, the field of
        the interpolated grids; per-step placement, the two steps' values interpolated linearly."""
        position = time_position(time, self.steps)
        if self.config.series.placement == "shared" or position == int(position):
            return self.time_field(time)(points)
        low = int(position)
        return torch.lerp(self.step_field(low)(points), self.step_field(low + 1)(points), position - low)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Values in data units ``[N, 1]`` at ``[N, 4]`` points ``(x, y, z, t)``, all in ``[-1, 1]``."""
        if points.dim() != 2 or points.shape[1] != 4:
            raise ValueError(f"a series field takes [N, 4] points (x, y, z, t), got {list(points.shape)}")
        out = torch.empty(points.shape[0], 1, dtype=points.dtype, device=points.device)
        times, inverse = torch.unique(points[:, 3], return_inverse=True)
        for index, time in enumerate(times.tolist()):
            rows = inverse == index
            out[rows] = self._values_at(time, points[rows, :3].contiguous())
        return out

    def parameter_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    # The same checks as a single field's: they read only the encoder and the decoder; the same rounding.
    check_parameters = NeuralField.check_parameters
    round_to_storage = NeuralField.round_to_storage

"""Hybrid encoder: a multiresolution hash grid on the volume's own lattice, plus adaptively placed grids.

Two kinds of feature grids, read the same way (:mod:`apmgsrn.ops.level_grids`):

- ``levels`` *domain levels* span the whole volume. They follow its voxel lattice: the finest level has one
  vertex per voxel on every axis (so it can hold the ground truth's trilinear interpolation exactly), the
  coarsest ``coarsest`` vertices on the longest axis, geometric in between, with per-axis vertex counts in
  the volume's aspect ratio (a 512x64x64 volume gets 8x more vertices along x than along y and z). A level is
  stored densely when its vertices fit ``2^T`` rows, hashed into ``2^T`` rows otherwise (Instant-NGP's
  hash); the hash table's collisions resolve where the data needs them, which on sparse volumes acts as
  an implicit adaptivity.
- ``grids`` *adaptive grids*, dense ``R^3`` grids placed by learned affine maps exactly as APMGSRN's
  (docs/method.md §2): the feature-density loss (docs/method.md §3) moves them towards the error, through the
  same encoder methods as :class:`~apmgsrn.models.encoders.adaptive_multigrid.AdaptiveMultiGridEncoder`.
  :meth:`HybridGridEncoder.initialize_from_volume` starts them on the box that holds the volume's
  gradient mass instead of the whole domain.

The layout follows the lattice of the volume the model is fitted to: the config's ``lattice``, which
:class:`~apmgsrn.models.field.NeuralField` fills in from the volume's shape, so every model file holds it and
:meth:`HybridGridConfig.parameter_shapes` knows every stored shape before anything is built.

The features of all grids are concatenated (domain levels first, coarse to fine, then the adaptive grids)
for the shared decoder. The domain levels' table learns ``level_lr_scale`` times faster than the rest
(per-component learning rates, :meth:`HybridGridEncoder.learning_rate_multipliers`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from apmgsrn.arguments import check_choice
from apmgsrn.models.encoders.adaptive_multigrid import AdaptiveMultiGridEncoder
from apmgsrn.models.encoders.base import STORAGE_DTYPES, Encoder
from apmgsrn.ops.level_grids import (
    LEVEL_GRID_BACKENDS,
    index_space_maps,
    level_grid_decoded,
    level_grid_features,
    level_grid_mse_step,
    level_grid_train_step,
)
from apmgsrn.ops.level_layout import LevelLayout
from apmgsrn.recipes import RUNTIME

GRID_INITS = ("volume", "default")
#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_LEVELS, MAX_FEATURES, MAX_GRIDS, MAX_RESOLUTION, MAX_AXIS = 64, 64, 4096, 4096, 1 << 20
#: ``lattice`` of a config not yet fitted to a volume.
NO_LATTICE = (0, 0, 0)


@dataclass(frozen=True)
class HybridGridConfig:
    """What to build.

    Attributes:
        levels: domain levels ``L`` (0: none).
        features: features per domain level.
        log2_table_size: ``T``: a domain level holds at most ``2^T`` rows (hashed beyond).
        coarsest: vertices along the volume's longest axis at the coarsest domain level.
        grids: adaptive grids ``M`` (0: none).
        grid_features: features per adaptive grid.
        grid_resolution: vertices per axis of every adaptive grid.
        grid_init: ``"volume"`` (grids start on the box holding 99 % of the volume's gradient mass, per axis;
            :meth:`HybridGridEncoder.initialize_from_volume`) or ``"default"`` (near the domain, APMGSRN's
            initialisation, docs/method.md §2).
        level_lr_scale: learning-rate multiplier of the domain levels.
        grid_lr_scale: learning-rate multiplier of the adaptive grids' features.
        storage: dtype the feature tables (domain levels and adaptive grids) are stored in, ``"float32"`` or
            ``"float16"`` (the presets: twice the features for the bytes; training runs in float32 and
            rounds when it ends). Placement maps and the decoder stay float32.
        lattice: ``(D, H, W)`` of the volume the domain levels follow (:data:`NO_LATTICE` until
            :class:`~apmgsrn.models.field.NeuralField` fits the config to a volume).
        backend: sampling backend of :func:`apmgsrn.ops.level_grids.level_grid_features`.
    """

    levels: int = 16
    features: int = 2
    log2_table_size: int = 10
    coarsest: int = 8
    grids: int = 8
    grid_features: int = 1
    grid_resolution: int = 16
    grid_init: str = "volume"
    level_lr_scale: float = 3.0
    grid_lr_scale: float = 1.0
    storage: str = "float32"
    lattice: tuple[int, int, int] = NO_LATTICE
    backend: str = "auto"

    def __post_init__(self) -> None:
        object.__setattr__(self, "lattice", tuple(self.lattice))
        if (
            not 0 <= self.levels <= MAX_LEVELS
            or not 0 <= self.grids <= MAX_GRIDS
            or self.levels + self.grids < 1
            or not 1 <= self.features <= MAX_FEATURES
            or not 1 <= self.log2_table_size <= 30
            or not 2 <= self.coarsest <= MAX_AXIS
            or not 1 <= self.grid_features <= MAX_FEATURES
            or not 2 <= self.grid_resolution <= MAX_RESOLUTION
        ):
            raise ValueError(
                f"invalid hybrid-grid size: {self} (0..{MAX_LEVELS} levels and 0..{MAX_GRIDS} grids, not both 0; "
                f"1..{MAX_FEATURES} features; log2 table size 1..30; coarsest 2..{MAX_AXIS}; grid resolution "
                f"2..{MAX_RESOLUTION})"
            )
        if len(self.lattice) != 3 or not (
            self.lattice == NO_LATTICE or all(isinstance(n, int) and 1 <= n <= MAX_AXIS for n in self.lattice)
        ):
            raise ValueError(f"hybrid-grid lattice must be 3 sizes in 1..{MAX_AXIS}, not {self.lattice}")
        if self.grid_init not in GRID_INITS:
            raise ValueError(f"grid init must be one of {GRID_INITS}, not {self.grid_init!r}")
        if not (0 < self.level_lr_scale <= 1000 and 0 < self.grid_lr_scale <= 1000):
            raise ValueError(f"learning-rate scales must be in (0, 1000]: {self}")
        if self.storage not in STORAGE_DTYPES:
            raise ValueError(f"hybrid-grid storage must be one of {tuple(STORAGE_DTYPES)}, not {self.storage!r}")
        check_choice("backend", self.backend, LEVEL_GRID_BACKENDS)

    @property
    def out_features(self) -> int:
        """Width of the encoding: ``L F + M C``."""
        return self.levels * self.features + self.grids * self.grid_features

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter (checked against a model file before anything is built)."""
        layout = self.layout()
        level_floats = sum(s * f for s, f in zip(layout.sizes[: self.levels], layout.features))
        m, r, c = self.grids, self.grid_resolution, self.grid_features
        return {"level_table": (level_floats,), "grids": (m, r, r, r, c), "matrices": (m, 3, 3), "translations": (m, 3)}

    def stored_dtypes(self) -> dict[str, torch.dtype]:
        """The dtype each parameter is stored in: the feature tables in ``storage``, the maps in float32."""
        tables = STORAGE_DTYPES[self.storage]
        return {"level_table": tables, "grids": tables, "matrices": torch.float32, "translations": torch.float32}

    def level_resolutions(self) -> list[tuple[int, int, int]]:
        """Vertices ``(R_x, R_y, R_z)`` of every domain level, coarse to fine.

        Level ``l`` keeps a fraction ``s_l`` of the voxel lattice's cells on every axis: ``s`` runs
        geometrically from ``(coarsest - 1) / (longest - 1)`` to 1 (the lattice itself).

        Raises:
            ValueError: the config has no lattice yet.
        """
        if self.lattice == NO_LATTICE:
            raise ValueError("hybrid-grid config has no lattice: build the model through NeuralField(volume_shape=)")
        dims = [max(2, n) for n in reversed(self.lattice)]  # x, y, z vertices
        longest = max(dims)
        coarse = min(1.0, (self.coarsest - 1) / (longest - 1))
        out = []
        for level in range(self.levels):
            s = 1.0 if self.levels == 1 else coarse ** (1 - level / (self.levels - 1))
            out.append(tuple(max(2, round((n - 1) * s) + 1) for n in dims))
        return out

    def layout(self) -> LevelLayout:
        """Where every level and grid lives in the flat feature table (domain levels first)."""
        cap = 2**self.log2_table_size
        resolutions, features, hashed, sizes = [], [], [], []
        for res in self.level_resolutions():
            vertices = math.prod(res)
            resolutions.append(res)
            features.append(self.features)
            hashed.append(vertices > cap)
            sizes.append(cap if vertices > cap else vertices)
        r = self.grid_resolution
        for _ in range(self.grids):
            resolutions.append((r, r, r))
            features.append(self.grid_features)
            hashed.append(False)
            sizes.append(r**3)
        return LevelLayout(tuple(resolutions), tuple(features), tuple(hashed), tuple(sizes))


class HybridGridEncoder(Encoder):
    """Encodes points ``[N, 3]`` to ``[N, L F + M C]`` (domain levels, then adaptive grids).

    Parameters: ``level_table`` (flat, every domain level), ``grids`` ``[M, R, R, R, C]`` (z, y, x, then the
    channels: the kernels read a vertex's channels together), ``matrices`` ``[M, 3, 3]`` and
    ``translations`` ``[M, 3]`` (the maps ``G_i(p) = A_i p + t_i`` into each grid's ``[-1, 1]^3``, moved by the
    feature-density loss only). All start ``U(-1e-4, 1e-4)`` like the other encoders' features.

    The layout follows ``config.lattice`` (saved in every model file), so a model rebuilt from its file
    has exactly the trained parameters.
    """

    def __init__(self, config: HybridGridConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.config = config
        self.layout = config.layout()
        self.out_features = config.out_features
        shapes = config.parameter_shapes()
        self.level_table = nn.Parameter(torch.empty(shapes["level_table"]))
        self.grids = nn.Parameter(torch.empty(shapes["grids"]))
        self.matrices = nn.Parameter(torch.empty(shapes["matrices"]))
        self.translations = nn.Parameter(torch.empty(shapes["translations"]))
        # Domain levels span [-1, 1]^3 with the identity map; constants, rebuilt from the config.
        resolutions = torch.tensor(self.layout.resolutions, dtype=torch.float32)  # [L + M, 3]
        self.register_buffer("resolutions", resolutions, persistent=False)
        identity = torch.eye(3).expand(config.levels, 3, 3)
        self.register_buffer(
            "level_maps", index_space_maps(identity, torch.zeros(config.levels, 3), resolutions[: config.levels]),
            persistent=False,
        )  # [L, 3, 4]
        self.reset_parameters(generator)

    @torch.no_grad()
    def reset_parameters(self, generator: torch.Generator | None = None) -> None:
        """Features ``U(-1e-4, 1e-4)``; grid maps as APMGSRN's init (docs/method.md §2: diag(A) ~ N(1, 0.05),
        rest N(0, 0.05))."""
        m = self.config.grids
        self.level_table.uniform_(-1e-4, 1e-4, generator=generator)
        self.grids.uniform_(-1e-4, 1e-4, generator=generator)
        noise = torch.randn(m, 3, 3, generator=generator) * 0.05
        self.matrices.copy_(torch.eye(3) + noise)
        self.translations.copy_(torch.randn(m, 3, generator=generator) * 0.05)

    @torch.no_grad()
    def initialize_from_volume(self, values: torch.Tensor) -> None:
        """Start the adaptive grids where the volume varies (``grid_init="volume"``; else nothing happens).

        Per axis, the box runs from the 0.5 % to the 99.5 % quantile of the gradient magnitude's mass
        (one voxel of margin, at least 5 % of the domain wide). Every grid's map is rescaled and shifted
        so that its local ``[-1, 1]^3`` covers that box, 5 % larger; the initial noise of each map is kept, so
        the grids still differ. On a volume with detail everywhere the box is the domain, as in APMGSRN.

        Args:
            values: ``[D, H, W]`` the training volume scaled to ``[0, 1]``.
        """
        if self.config.grid_init != "volume" or self.config.grids == 0 or min(values.shape) < 2:
            return
        volume = values.detach().float()
        magnitude = torch.stack(torch.gradient(volume), dim=0).norm(dim=0)  # [D, H, W]
        total = magnitude.sum()
        if not total > 0:  # constant volume: nothing to follow
            return
        low, high = [], []
        for axis in range(3):  # z, y, x of the volume
            profile = magnitude.sum(dim=tuple(a for a in range(3) if a != axis))  # [n]
            cdf = torch.cumsum(profile, 0) / total
            n = profile.shape[0]
            first = max(int((cdf < 0.005).sum()) - 1, 0)
            last = min(int((cdf < 0.995).sum()) + 1, n - 1)
            low.append(-1 + 2 * first / (n - 1))
            high.append(-1 + 2 * last / (n - 1))
        low_xyz = torch.tensor(low[::-1], device=self.matrices.device)
        high_xyz = torch.tensor(high[::-1], device=self.matrices.device)
        centre = (low_xyz + high_xyz) / 2
        scale = 1 / (((high_xyz - low_xyz) / 2).clamp_min(0.05) * 1.05)  # [3] local units per global unit
        # local = S (A0 p + t0 - c): the box maps onto [-1, 1]^3, each grid keeps its own noise.
        self.matrices.mul_(scale[None, :, None])
        self.translations.copy_(scale * (self.translations - centre))

    def maps(self, detach_placement: bool = False, matrices: torch.Tensor | None = None,
             translations: torch.Tensor | None = None) -> torch.Tensor:
        """Index-space maps ``[L + M, 3, 4]`` of every level and grid (the grids placed by ``matrices`` and
        ``translations``, by default the encoder's own)."""
        if self.config.grids == 0:
            return self.level_maps
        matrices = self.matrices if matrices is None else matrices
        translations = self.translations if translations is None else translations
        if detach_placement:
            matrices, translations = matrices.detach(), translations.detach()
        grid_maps = index_space_maps(matrices, translations, self.resolutions[self.config.levels :])  # [M, 3, 4]
        return torch.cat([self.level_maps, grid_maps], dim=0)

    def forward(self, points: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features at ``points`` ``[N, 3]`` -> ``[N, L F + M C]``.

        Args:
            points: global coordinates in ``[-1, 1]^3``.
            detach_placement: True on the reconstruction path (docs/method.md §4, step 1), so only the
                features and the decoder learn from the reconstruction error.
        """
        return self.features_of(points, self.level_table, self.grids, self.matrices, self.translations,
                                detach_placement)

    def decoded(self, points: torch.Tensor, weights: list[torch.Tensor]) -> torch.Tensor | None:
        """Encoder and decoder in one pass on the CPU when no gradient is wanted (see
        :func:`~apmgsrn.ops.level_grids.level_grid_decoded`); None elsewhere."""
        table = torch.cat([self.level_table, self.grids.reshape(-1)])
        return level_grid_decoded(points, self.maps(), table, self.layout, weights, self.config.backend)

    def fused_mse_step(self, points: torch.Tensor, target: torch.Tensor,
                       weights: list[torch.Tensor]) -> torch.Tensor | None:
        """The fused CPU training step where it runs and the table or the grids learn; None elsewhere.

        Under a frozen decoder it is :func:`~apmgsrn.ops.level_grids.level_grid_mse_step`; with a learning one
        :func:`~apmgsrn.ops.level_grids.level_grid_train_step`, which also stores the gradient of every decoder
        weight that requires one as its ``.grad`` (replacing it), as autograd through the reference would.
        """
        learning = self.level_table.requires_grad or self.grids.requires_grad
        if not learning:
            return None
        decoder_learns = any(w.requires_grad for w in weights)
        with torch.no_grad():
            table = torch.cat([self.level_table, self.grids.reshape(-1)])
            args = (points, self.maps(), table, self.layout, weights, target, self.config.backend)
            step = level_grid_train_step(*args) if decoder_learns else level_grid_mse_step(*args)
        if step is None:
            return None
        prediction, grad = step[0], step[1]
        split = self.level_table.numel()
        for parameter, part in ((self.level_table, grad[:split]), (self.grids, grad[split:])):
            if parameter.requires_grad:
                parameter.grad = part.view_as(parameter)
        if decoder_learns:
            for weight, weight_grad in zip(weights, step[2]):
                if weight.requires_grad:
                    weight.grad = weight_grad
        return prediction

    def features_of(self, points: torch.Tensor, level_table: torch.Tensor, grids: torch.Tensor,
                    matrices: torch.Tensor, translations: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features at ``points`` of this layout holding the given parameters (shaped as the encoder's own;
        a time series passes one step's, :mod:`apmgsrn.series.hybrid`)."""
        table = torch.cat([level_table, grids.reshape(-1)])  # the layout's flat table
        maps = self.maps(detach_placement, matrices, translations)
        return level_grid_features(points, maps, table, self.layout, self.config.backend)

    # The adaptive grids are APMGSRN's (same parameters, same maps): their feature density (docs/method.md §3),
    # its mean over the domain and the grids' boxes are computed the same way.
    feature_density = AdaptiveMultiGridEncoder.feature_density
    mean_feature_density = AdaptiveMultiGridEncoder.mean_feature_density
    grid_boxes = AdaptiveMultiGridEncoder.grid_boxes

    def prefers_ordered_batches(self) -> bool:
        # Measured on a 2-core EPYC (docs/models.md, "Time per iteration"): the small preset's 0.5 MB of
        # tables gain about what the sort costs (1.1 ms), the medium preset's 7 MB gain 7-10 ms a step.
        return 4 * sum(p.numel() for p in (self.level_table, self.grids)) > RUNTIME.ordered_batch_table_bytes

    def placement_parameters(self) -> list[nn.Parameter]:
        """The parameters the density loss moves (none without adaptive grids)."""
        return [self.matrices, self.translations] if self.config.grids else []

    def learning_rate_multipliers(self) -> dict[nn.Parameter, float]:
        """Learning-rate multipliers of the domain levels' table and the adaptive grids' features."""
        return {self.level_table: self.config.level_lr_scale, self.grids: self.config.grid_lr_scale}

    def check_parameters(self) -> str | None:
        """NaN/Inf parameters, or a singular placement matrix (its inverse places the grid in the domain)."""
        problem = super().check_parameters()
        if problem is None and not bool((torch.linalg.det(self.matrices.detach().double()).abs() > 1e-12).all()):
            problem = "a grid's placement matrix is singular"
        return problem

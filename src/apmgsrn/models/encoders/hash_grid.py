"""Multiresolution hash-grid encoder (the NGP baseline of docs/method.md §5), in pure PyTorch.

Each of ``L`` levels is a grid of resolution ``N_l`` whose ``N_l^3`` vertices are stored in a table of at
most ``2^T`` entries of ``F`` features: densely (vertex ``x + N_l y + N_l^2 z``) when the level fits, through
a spatial hash otherwise. A point's feature at a level is the trilinear interpolation of the 8 surrounding
vertices' table entries; the encoding concatenates the levels, level-major, to ``[N, L * F]``.

Index conventions follow tiny-cuda-nn's ``HashGrid`` encoding, so that the same parameter vector gives the
same outputs with either implementation (the optional ``backend="tcnn"``):

- input ``u = (p + 1) / 2`` in ``[0, 1]^3``; growth factor ``b = exp((ln finest - ln base) / (L - 1))``;
- level scale ``s_l = base * b^l - 1``, resolution ``N_l = ceil(s_l) + 1``;
- vertex position ``u * s_l + 0.5``, floored for the lower corner (vertices sit at half-cell offsets);
- table entries per level ``min(round_up(N_l^3, 8), 2^T)``;
- hash ``(x * 1) xor (y * 2654435761) xor (z * 805459861)`` in 32-bit arithmetic, modulo the table size;
- parameters: one flat vector, level after level, each level entry-major with its ``F`` features adjacent.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from apmgsrn.models.encoders.base import Encoder
from apmgsrn.ops.contract import nan_where_nan
from apmgsrn.ops.level_layout import HASH_PRIMES

#: Vertex coordinates are limited to ``±2^62`` before their int64 conversion (defined for every input; a
#: position beyond it, only from a point absurdly far outside, ``±inf`` included, reads as the limit).
POSITION_LIMIT = 2.0**62

HASH_BACKENDS = ("torch", "tcnn", "auto")

#: Sanity bounds of a config (a model file claiming more is refused before anything is allocated).
MAX_LEVELS, MAX_FEATURES, MAX_RESOLUTION = 64, 64, 1 << 20


@dataclass(frozen=True)
class HashGridConfig:
    """What to build (docs/method.md §5, NGP column).

    Attributes:
        levels: number of resolution levels ``L``.
        features: features per level ``F``.
        log2_table_size: ``T``: at most ``2^T`` table entries per level.
        base_resolution: resolution of the coarsest level.
        finest_resolution: resolution of the finest level (geometric growth in between).
        backend: ``"torch"`` (pure PyTorch, everywhere) or ``"tcnn"`` / ``"auto"`` (tiny-cuda-nn for points on
            a CUDA device when the ``tinycudann`` package is importable, else the PyTorch path, which holds the
            same parameters; ``"tcnn"`` warns when it has to fall back).
    """

    levels: int = 17
    features: int = 2
    log2_table_size: int = 11
    base_resolution: int = 8
    finest_resolution: int = 256
    backend: str = "torch"

    def __post_init__(self) -> None:
        if (
            not 1 <= self.levels <= MAX_LEVELS
            or not 1 <= self.features <= MAX_FEATURES
            or not 1 <= self.log2_table_size <= 30
        ):
            raise ValueError(
                f"invalid hash-grid size: {self} (1..{MAX_LEVELS} levels, 1..{MAX_FEATURES} features, "
                "log2 table size 1..30)"
            )
        if not 2 <= self.base_resolution <= self.finest_resolution <= MAX_RESOLUTION:
            raise ValueError(f"hash-grid resolutions must satisfy 2 <= base <= finest <= {MAX_RESOLUTION}: {self}")
        if self.backend not in HASH_BACKENDS:
            raise ValueError(f"hash-grid backend must be one of {HASH_BACKENDS}, not {self.backend!r}")

    @property
    def growth_factor(self) -> float:
        """Per-level scale ``b`` between the base and finest resolutions."""
        if self.levels == 1:
            return 1.0
        return math.exp((math.log(self.finest_resolution) - math.log(self.base_resolution)) / (self.levels - 1))

    def level_scales(self) -> list[float]:
        """``s_l`` per level: input ``u`` in ``[0, 1]`` maps to vertex coordinate ``u * s_l + 0.5``."""
        b = self.growth_factor
        # Computed as exp2(l * log2 b) in float32, like tiny-cuda-nn, so both agree on every floor().
        log2_b = torch.tensor(math.log2(b), dtype=torch.float32)
        return [
            float(torch.exp2(log2_b * level) * self.base_resolution - 1.0) for level in range(self.levels)
        ]

    def level_resolutions(self) -> list[int]:
        """Vertices per axis ``N_l`` of every level."""
        return [math.ceil(scale) + 1 for scale in self.level_scales()]

    @property
    def out_features(self) -> int:
        """Width of the encoding: ``L * F``."""
        return self.levels * self.features

    def parameter_shapes(self) -> dict[str, tuple[int, ...]]:
        """Shape of every stored parameter (checked against a model file before anything is built)."""
        return {"table": (sum(self.level_table_sizes()), self.features)}

    def level_table_sizes(self) -> list[int]:
        """Table entries per level: ``2^T``, or the (8-aligned) dense vertex count where that is smaller."""
        sizes = []
        for resolution in self.level_resolutions():
            dense = -(-(resolution**3) // 8) * 8
            sizes.append(min(dense, 2**self.log2_table_size))
        return sizes


def tcnn_available() -> bool:
    """True when the ``tinycudann`` package is importable and a CUDA device exists (imports it)."""
    if not torch.cuda.is_available():
        return False
    try:
        import tinycudann  # noqa: F401
    except ImportError:
        return False
    return True


class HashGridEncoder(Encoder):
    """Encodes points ``[N, 3]`` in ``[-1, 1]^3`` to ``[N, levels * features]`` (level-major).

    Parameter: ``table`` ``[E, F]``, the tables of all levels stacked (``E = sum_l table size_l``),
    initialised ``U(-1e-4, 1e-4)``. Flattened it is exactly tiny-cuda-nn's parameter vector.
    """

    def __init__(self, config: HashGridConfig, generator: torch.Generator | None = None):
        super().__init__()
        self.config = config
        self.out_features = config.out_features
        sizes = config.level_table_sizes()
        offsets = [0]
        for size in sizes[:-1]:
            offsets.append(offsets[-1] + size)
        self.table = nn.Parameter(torch.empty(config.parameter_shapes()["table"]))
        # Per-level constants, as buffers so they follow .to(device); not saved (rebuilt from the config).
        scales = torch.tensor(config.level_scales(), dtype=torch.float32)
        self.register_buffer("level_scales", scales, persistent=False)
        self.register_buffer("level_resolutions", torch.tensor(config.level_resolutions()), persistent=False)
        self.register_buffer("level_sizes", torch.tensor(sizes), persistent=False)
        self.register_buffer("level_offsets", torch.tensor(offsets), persistent=False)
        # Levels stored densely; on them the hash is never used.
        dense = [r**3 <= s for r, s in zip(config.level_resolutions(), sizes)]
        self.register_buffer("level_dense", torch.tensor(dense), persistent=False)
        with torch.no_grad():
            self.table.uniform_(-1e-4, 1e-4, generator=generator)

    def forward(self, points: torch.Tensor, detach_placement: bool = False) -> torch.Tensor:
        """Features at ``points`` ``[N, 3]`` -> ``[N, L * F]``.

        Args:
            points: global coordinates in ``[-1, 1]^3``.
            detach_placement: ignored (this encoder places no grids).
        """
        if self._use_tcnn(points):
            return self._forward_tcnn(points)
        return hash_grid_features(
            points, self.table, self.level_scales, self.level_resolutions, self.level_sizes,
            self.level_offsets, self.level_dense,
        )

    def _use_tcnn(self, points: torch.Tensor) -> bool:
        backend = self.config.backend
        if backend == "torch" or not points.is_cuda:
            # tiny-cuda-nn runs on CUDA only; the parameters are the same, so CPU inputs take the PyTorch path.
            return False
        if tcnn_available():
            return True
        if backend == "tcnn" and not self.__dict__.get("_tcnn_warned"):
            import warnings

            warnings.warn(
                "hash-grid backend 'tcnn' asked for, but the tinycudann package is not importable; "
                "using the PyTorch implementation (same parameters, same outputs)",
                stacklevel=3,
            )
            self.__dict__["_tcnn_warned"] = True  # once per model
        return False

    def _forward_tcnn(self, points: torch.Tensor) -> torch.Tensor:
        import tinycudann as tcnn

        module = self.__dict__.get("_tcnn_module")
        if module is None:
            cfg = self.config
            module = tcnn.Encoding(
                3,
                {
                    "otype": "HashGrid",
                    "n_levels": cfg.levels,
                    "n_features_per_level": cfg.features,
                    "log2_hashmap_size": cfg.log2_table_size,
                    "base_resolution": cfg.base_resolution,
                    "per_level_scale": cfg.growth_factor,
                    "interpolation": "Linear",
                },
                dtype=torch.float32,
            )
            if module.params.numel() != self.table.numel():
                raise RuntimeError(
                    f"tinycudann hash grid holds {module.params.numel()} parameters, "
                    f"the PyTorch one {self.table.numel()}"
                )
            # tcnn's module reads ``self.params`` on every call: drop its own copy and hand it ours below,
            # so optimisers, state dicts and parameter counts see one table.
            del module.params
            # Kept out of ``_modules`` so that it adds nothing to the state dict.
            self.__dict__["_tcnn_module"] = module
        module.params = self.table.view(-1)  # a view keeps the autograd path to ``table``
        unit = (points + 1) * 0.5  # tcnn works in [0, 1]^3
        return nan_where_nan(points, module(unit.contiguous()).float())  # [N, L * F]


def hash_grid_features(
    points: torch.Tensor,
    table: torch.Tensor,
    scales: torch.Tensor,
    resolutions: torch.Tensor,
    sizes: torch.Tensor,
    offsets: torch.Tensor,
    dense: torch.Tensor,
) -> torch.Tensor:
    """Multiresolution hash encoding (all levels at once), trilinear within each level.

    Args:
        points: ``[N, 3]`` in ``[-1, 1]^3`` (no gradient flows to them).
        table: ``[E, F]`` stacked tables.
        scales: ``[L]`` float, ``s_l``.
        resolutions: ``[L]`` int, ``N_l``.
        sizes: ``[L]`` int, table entries of each level.
        offsets: ``[L]`` int, first row of each level in ``table``.
        dense: ``[L]`` bool, levels indexed densely.

    Returns:
        ``[N, L * F]`` features, column ``l * F + f`` is feature ``f`` of level ``l``; a point outside
        ``[-1, 1]^3`` reads the wrapped (dense) or hashed vertices its position gives, as tiny-cuda-nn does; a
        point with a NaN coordinate has NaN features and adds to no gradient (the contract of
        :mod:`apmgsrn.ops`).
    """
    n = points.shape[0]
    levels = scales.shape[0]
    features = table.shape[1]
    rows, weights = hash_grid_corners(points, scales, resolutions, sizes, offsets, dense)  # [L, 8, N] each
    per_level = _WeightedGather.apply(table, rows, weights)  # [L, N, F]
    return nan_where_nan(points, per_level.permute(1, 0, 2).reshape(n, levels * features))  # [N, L * F]


def hash_grid_corners(
    points: torch.Tensor,
    scales: torch.Tensor,
    resolutions: torch.Tensor,
    sizes: torch.Tensor,
    offsets: torch.Tensor,
    dense: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Table rows and trilinear weights of the 8 cell corners around every point at every level.

    Args: as :func:`hash_grid_features`.

    Returns:
        (rows ``[L, 8, N]`` int32 into the stacked table, weights ``[L, 8, N]`` float32); corner ``k`` has
        offsets ``(k & 1, k >> 1 & 1, k >> 2)`` in (x, y, z).
    """
    # Points last everywhere: every elementwise op below then runs over long contiguous rows of N values
    # (with the 2 or 8 corners innermost, broadcasting would run inner loops of length 2 and crawl).
    unit = (points.detach().float().t() + 1) * 0.5  # [3, N] in [0, 1]
    position = unit[None] * scales[:, None, None] + 0.5  # [L, 3, N]
    # In float before the integer conversion: anything beyond the limit (inf included) reads as the limit, NaN
    # (a NaN point, whose features are NaN in the end) as the lower one.
    position = torch.where(position >= -POSITION_LIMIT, position.clamp(max=POSITION_LIMIT), -POSITION_LIMIT)
    lower = torch.floor(position)
    fraction = position - lower  # [L, 3, N]
    levels, _, n = position.shape
    # Work per axis on the two candidate vertices (lower, lower + 1), then combine the three axes by
    # broadcasting into the 2x2x2 corners: 3 x 2 values per point instead of 8 x 3.
    step = torch.arange(2, device=points.device)[:, None]  # [2, 1]
    axis_vertex = lower.to(torch.int64)[:, :, None, :] + step  # [L, 3, 2, N]
    axis_weight = torch.stack([1 - fraction, fraction], dim=2)  # [L, 3, 2, N]
    wx, wy, wz = axis_weight.unbind(1)  # [L, 2, N] each
    weights = (wz[:, :, None] * wy[:, None, :])[:, :, :, None] * wx[:, None, None, :]  # [L, 2, 2, 2, N]

    # Rows are int32 (tables hold at most 2^30 entries); every big tensor below is written once.
    rows = torch.empty(levels, 2, 2, 2, n, dtype=torch.int32, device=points.device)
    level_dense = dense.tolist()
    first_hashed = level_dense.index(False) if False in level_dense else levels
    if first_hashed > 0:  # coarse levels: dense row-major vertex index (x fastest)
        vx, vy, vz = axis_vertex[:first_hashed].unbind(1)  # [Ld, 2, N] each
        r = resolutions[:first_hashed, None, None]
        yz = (vz * (r * r))[:, :, None] + (vy * r)[:, None, :]  # [Ld, 2, 2, N]
        linear = yz[:, :, :, None] + vx[:, None, None, :]  # [Ld, 2, 2, 2, N]
        # The vertex one past the far border (u = 1) wraps around, as in tiny-cuda-nn.
        level = (slice(0, first_hashed), None, None, None, None)
        rows[:first_hashed] = linear % sizes[level] + offsets[level]
    if first_hashed < levels:  # fine levels: 32-bit multiply-xor hash, modulo the power-of-two table
        # Masking each term by (2^T - 1) before the xor equals masking the xor: all fits in int32.
        mask = sizes[first_hashed:, None, None] - 1
        vx, vy, vz = axis_vertex[first_hashed:].unbind(1)  # [Lh, 2, N] each
        hx = ((vx * HASH_PRIMES[0]) & mask).to(torch.int32)
        hy = ((vy * HASH_PRIMES[1]) & mask).to(torch.int32)
        hz = ((vz * HASH_PRIMES[2]) & mask).to(torch.int32)
        yz = hz[:, :, None] ^ hy[:, None, :]  # [Lh, 2, 2, N]
        hashed = rows[first_hashed:]
        torch.bitwise_xor(yz[:, :, :, None], hx[:, None, None, :], out=hashed)  # [Lh, 2, 2, 2, N]
        hashed += offsets[first_hashed:, None, None, None, None].to(torch.int32)
    return rows.view(levels, 8, n), weights.view(levels, 8, n)


class _WeightedGather(torch.autograd.Function):
    """``out[l, b] = sum_k weights[l, k, b] * table[rows[l, k, b]]`` -> ``[L, N, F]``.

    One corner at a time (8 gathers of ``L * N`` rows), so no ``[L, 8, N, F]`` temporary exists. The
    backward sums into the table with ``bincount`` (``embedding_bag``'s backward sorts all rows first and
    ``index_add_`` is slower on CPU).
    """

    @staticmethod
    def forward(ctx, table: torch.Tensor, rows: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        levels, corners, n = rows.shape
        features = table.shape[1]
        out = torch.zeros(levels * n, features, dtype=table.dtype, device=table.device)
        for k in range(corners):
            gathered = table.index_select(0, rows[:, k].reshape(-1))  # [L * N, F]
            out.addcmul_(gathered, weights[:, k].reshape(-1, 1).to(table.dtype))
        ctx.save_for_backward(rows, weights)
        ctx.table_shape = table.shape
        return out.view(levels, n, features)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        rows, weights = ctx.saved_tensors
        levels, corners, n = rows.shape
        entries, features = ctx.table_shape
        flat_rows = rows.reshape(-1)  # [L * 8 * N]
        columns = []
        for f in range(features):
            # d out[l, b, f] / d table[rows[l, k, b], f] = weights[l, k, b]; bincount sums the
            # contributions per row (measured 2-3x faster on CPU than index_add_ or scatter_add_).
            contribution = weights * grad_out[:, :, f].reshape(levels, 1, n)  # [L, 8, N]
            columns.append(torch.bincount(flat_rows, weights=contribution.reshape(-1), minlength=entries))
        return torch.stack(columns, dim=1).to(grad_out.dtype), None, None

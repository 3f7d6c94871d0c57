"""Multi-level grid encoding: many feature grids ("levels"), each dense or hashed, each reached by an affine map.

Level ``l`` is a lattice of ``R_x x R_y x R_z`` vertices holding ``F_l`` features per vertex. A point
``p`` in ``[-1, 1]^3`` reaches it through an affine map in *index units*, ``f = A'_l p + t'_l`` (vertex
``(i, j, k)`` sits at ``f = (i, j, k)``), and reads the trilinear interpolation of the 8 vertices
around ``f``. A vertex outside the lattice contributes zero (zero padding, as in
:mod:`apmgsrn.ops.multigrid`), so a level placed over part of the domain fades out at its border.

Storage: a level whose ``R_x R_y R_z`` vertices fit its table is *dense* (vertex ``x + R_x (y + R_y z)``);
a larger one is *hashed* into a power-of-two table with Instant-NGP's spatial hash
``(x * 1) xor (y * 2654435761) xor (z * 805459861)`` (32-bit), modulo the table size.

All levels share one flat parameter vector ``table``: level ``l`` occupies ``sizes[l] * F_l`` floats from
``offsets[l]``, vertex-major with its ``F_l`` features adjacent. The encoding concatenates the levels'
features, level-major, to ``[N, sum_l F_l]``.

This module is the pure-PyTorch reference (differentiable with respect to the table, the maps and the
points); fused backends must match it in forward and backward, at every input (the contract of
:mod:`apmgsrn.ops`: a point with a NaN coordinate has NaN features and adds to no gradient; a non-finite index
coordinate, from an infinite point, is outside every level).
"""

from __future__ import annotations

import torch

from apmgsrn import choices
from apmgsrn.ops import level_grids_cpu
from apmgsrn.ops.contract import finite_stand_in, nan_where_nan, outside_for_non_finite
from apmgsrn.ops.level_layout import HASH_PRIMES, LevelLayout


def vertex_rows(
    vertex: torch.Tensor, resolution: tuple[int, int, int], size: int, hashed: bool
) -> torch.Tensor:
    """Table rows of integer vertices ``[..., 3]`` (x, y, z) inside the lattice -> ``[...]`` int64."""
    x, y, z = vertex.unbind(-1)
    if hashed:
        terms = (x * HASH_PRIMES[0], y * HASH_PRIMES[1], z * HASH_PRIMES[2])
        if torch.jit.is_tracing():
            return _xor_low_bits(terms, size)
        # int64 products are exact; their low 32 bits are the 32-bit products, and size <= 2^32.
        return (terms[0] ^ terms[1] ^ terms[2]) & (size - 1)
    return x + resolution[0] * (y + resolution[1] * z)


def _xor_low_bits(terms: tuple[torch.Tensor, ...], size: int) -> torch.Tensor:
    """``(a ^ b ^ c) & (size - 1)`` of non-negative int64 tensors, ``size`` a power of two, by integer
    division and remainder only: the ONNX exporter (:mod:`apmgsrn.export`) has no integer xor. Bit ``k`` of
    the xor is the parity of the terms' bits ``k``."""
    low = [t % size for t in terms]
    rows = torch.zeros_like(low[0])
    for k in range(size.bit_length() - 1):
        rows = rows + (sum(torch.div(t, 1 << k, rounding_mode="floor") % 2 for t in low) % 2) * (1 << k)
    return rows


def level_corners(
    local: torch.Tensor, resolution: tuple[int, int, int], size: int, hashed: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows and trilinear weights of the 8 vertices around index-space points.

    Args:
        local: ``[N, 3]`` index-space coordinates ``f`` (x, y, z) of one level.
        resolution: the level's ``(R_x, R_y, R_z)``.
        size: its table rows.
        hashed: its storage.

    Returns:
        (rows ``[8, N]`` int64, weights ``[8, N]``); corner ``k`` is offset ``(k & 1, k >> 1 & 1, k >> 2)``;
        a corner outside the lattice has weight 0 and row 0, and so has every corner of a non-finite or huge
        coordinate (read as one just beyond the lattice: the same zero weights, a defined integer conversion).
    """
    local = outside_for_non_finite(local, float(max(resolution) + 1))
    lower = torch.floor(local)
    frac = local - lower  # [N, 3]; differentiable in local
    base = lower.detach().to(torch.int64)  # [N, 3]
    limit = torch.tensor(resolution, device=local.device)  # [3]
    rows, weights = [], []
    for k in range(8):
        offset = torch.tensor([k & 1, (k >> 1) & 1, k >> 2], device=local.device)  # [3]
        vertex = base + offset  # [N, 3]
        inside = ((vertex >= 0) & (vertex < limit)).all(-1)  # [N]
        axis_weight = torch.where(offset.bool(), frac, 1 - frac)  # [N, 3]
        weights.append(axis_weight.prod(-1) * inside)
        rows.append(torch.where(inside, vertex_rows(vertex.clamp(min=0), resolution, size, hashed), 0))
    return torch.stack(rows), torch.stack(weights)  # [8, N] each


def index_space_maps(matrices: torch.Tensor, translations: torch.Tensor, resolutions: torch.Tensor) -> torch.Tensor:
    """Fold corner-aligned unnormalisation into maps from ``[-1, 1]^3`` to each level's index units.

    A level spanning local coordinates ``[-1, 1]^3`` (reached by ``A p + t``) has vertex ``i`` of ``R``
    at local ``-1 + 2 i / (R - 1)``, so its index coordinate is ``(A p + t + 1) (R - 1) / 2``.

    Args:
        matrices: ``[L, 3, 3]`` the ``A`` of every level (row ``k`` gives local axis ``k`` = x, y, z).
        translations: ``[L, 3]`` the ``t``.
        resolutions: ``[L, 3]`` vertices per axis (x, y, z).

    Returns:
        ``[L, 3, 4]`` maps ``[A' | t']`` with ``f = A' p + t'``.
    """
    half = (resolutions.to(matrices.dtype) - 1) / 2  # [L, 3]
    a = matrices * half[:, :, None]  # [L, 3, 3]
    t = (translations + 1) * half  # [L, 3]
    return torch.cat([a, t[:, :, None]], dim=2)  # [L, 3, 4]


def level_grid_features_reference(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout
) -> torch.Tensor:
    """Concatenated features of every level at the points (pure PyTorch, fully differentiable).

    Args:
        points: ``[N, 3]`` global coordinates ``(x, y, z)``.
        maps: ``[L, 3, 4]`` index-space maps (see :func:`index_space_maps`).
        table: ``[T]`` flat parameters (``layout.table_size`` floats).
        layout: the levels.

    Returns:
        ``[N, sum_l F_l]`` features, level-major.
    """
    out = []
    mapped = finite_stand_in(points)  # NaN points are NaN in the end; infinite ones far outside every level
    for level in range(layout.levels):
        res, f = layout.resolutions[level], layout.features[level]
        size, hashed = layout.sizes[level], layout.hashed[level]
        local = mapped @ maps[level, :, :3].t() + maps[level, :, 3]  # [N, 3]
        rows, weights = level_corners(local, res, size, hashed)  # [8, N] each
        start = layout.offsets[level]
        values = table[start : start + size * f].view(size, f)  # [size, F]
        gathered = values[rows]  # [8, N, F]
        out.append((gathered * weights[:, :, None]).sum(0))  # [N, F]
    return nan_where_nan(points, torch.cat(out, dim=1))  # [N, sum F]


LEVEL_GRID_BACKENDS = ("auto", *choices.LEVEL_GRID_BACKENDS)


def level_grid_features(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, backend: str = "auto"
) -> torch.Tensor:
    """Concatenated level features through the chosen backend.

    The fused kernels, C/OpenMP on CPU (:mod:`apmgsrn.ops.level_grids_cpu`) and Triton on CUDA
    (:mod:`apmgsrn.ops.level_grids_triton`), give gradients for ``table`` only; when the points or maps
    require grad, the tensors are not float32, or no kernel can run there, this runs the reference, so
    autograd stays exact.

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps.
        table: ``[T]`` flat parameters.
        layout: the levels.
        backend: ``"auto"`` (the fused kernel of the tensors' device where it applies, else the reference),
            ``"torch"``, ``"cpu"`` or ``"triton"``.

    Returns:
        ``[N, sum_l F_l]`` features, level-major.

    Raises:
        ValueError: unknown backend.
        RuntimeError: ``"cpu"`` asked for where it cannot run.
    """
    if backend not in LEVEL_GRID_BACKENDS:
        raise ValueError(f"unknown level-grid backend {backend!r}; use one of {LEVEL_GRID_BACKENDS}")
    if backend == "torch":
        return level_grid_features_reference(points, maps, table, layout)
    device = points.device.type
    fusable = (
        all(t.dtype == torch.float32 for t in (points, maps, table))
        and not (torch.is_grad_enabled() and (points.requires_grad or maps.requires_grad))
    )
    if backend in ("auto", "cpu") and device == "cpu" and fusable:
        if level_grids_cpu.is_available():
            return level_grids_cpu.level_grid_features_cpu(points, maps, table, layout)
        if backend == "cpu":
            raise RuntimeError(f"level-grid backend 'cpu' cannot run here: {level_grids_cpu.load_error()}")
    if backend in ("auto", "triton") and device == "cuda" and fusable:
        from apmgsrn.ops import level_grids_triton  # imports Triton: only for CUDA tensors

        if level_grids_triton.is_available():
            return level_grids_triton.level_grid_features_triton(points, maps, table, layout)
        if backend == "triton":
            raise RuntimeError(f"level-grid backend 'triton' cannot run here: {level_grids_triton.load_error()}")
    if backend != "auto":
        raise RuntimeError(f"level-grid backend {backend!r} needs float32 {'CUDA' if backend == 'triton' else 'CPU'} "
                           "tensors and no gradient for points or maps")
    return level_grid_features_reference(points, maps, table, layout)


def _float32_on_cpu(backend: str, points: torch.Tensor, *tensors: torch.Tensor) -> bool:
    """Whether a fused CPU kernel may take these tensors: ``backend`` allows it (``"auto"`` or ``"cpu"``), the
    points are on the CPU, and they and every other tensor are float32."""
    return (backend in ("auto", "cpu") and points.device.type == "cpu"
            and all(t.dtype == torch.float32 for t in (points, *tensors)))


def level_grid_decoded(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor],
    backend: str = "auto",
) -> torch.Tensor | None:
    """``decoder(level_grid_features(points, ...))`` fused in one pass where a kernel can (inference only).

    The fused CPU kernel (:func:`apmgsrn.ops.field_cpu.level_grid_decoder_cpu`) runs when ``backend`` is
    ``"auto"`` or ``"cpu"``, the points are on the CPU, no gradient is wanted, every tensor is float32 and the
    sizes fit; elsewhere this returns ``None`` and the caller runs encoder and decoder as usual (the reference).

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps.
        table: ``[T]`` flat parameters.
        layout: the levels.
        weights: the decoder's bias-free linear layers ``[out, in]`` in order, ReLU between them, the last
            ``[1, in]``.
        backend: as :func:`level_grid_features`.

    Returns:
        ``[N]`` decoder outputs, or ``None``.
    """
    if torch.is_grad_enabled() or not _float32_on_cpu(backend, points, maps, table, *weights):
        return None
    from apmgsrn.ops import field_cpu

    if not field_cpu.fusable(layout.out_features, [w.shape[0] for w in weights[:-1]], field_cpu.LEVEL_LIBRARY):
        return None
    return field_cpu.level_grid_decoder_cpu(points, maps, table, layout, weights)


def level_grid_mse_step_reference(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor],
    target: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The prediction ``[N]`` of ``decoder(level_grid_features(points))`` and the gradient ``[T]`` of its mean
    squared error to ``target`` ``[N]`` with respect to ``table`` alone, by autograd through the reference
    (what :func:`level_grid_mse_step`'s fused kernel must match)."""
    with torch.enable_grad():
        leaf = table.detach().requires_grad_(True)
        x = level_grid_features_reference(points.detach(), maps.detach(), leaf, layout)
        for weight in weights[:-1]:
            x = torch.relu(x @ weight.detach().t())
        prediction = (x @ weights[-1].detach().t()).view(-1)
        (grad,) = torch.autograd.grad((prediction - target.detach().view(-1)).square().mean(), leaf)
    return prediction.detach(), grad


def level_grid_mse_step(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor],
    target: torch.Tensor, backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """One training step's numbers for a table under a frozen decoder, fused in one pass where a kernel can:
    the prediction ``[N]`` and the gradient ``[T]`` of its mean squared error to ``target`` with respect to
    ``table`` (as :func:`level_grid_mse_step_reference`).

    The fused CPU kernel (:func:`apmgsrn.ops.field_train_cpu.level_grid_mse_step_cpu`) runs when ``backend`` is
    ``"auto"`` or ``"cpu"``, the points are on the CPU and every tensor is float32; elsewhere this returns
    ``None`` and the caller runs the step through autograd.

    Args:
        points: ``[N, 3]``.
        maps: ``[L, 3, 4]`` index-space maps (constants here).
        table: ``[T]`` flat parameters.
        layout: the levels.
        weights: the decoder's bias-free linear layers ``[out, in]`` in order (constants here).
        target: ``[N]`` the values to fit.
        backend: as :func:`level_grid_features`.
    """
    if not _float32_on_cpu(backend, points, maps, table, target, *weights):
        return None
    from apmgsrn.ops import field_train_cpu

    if not field_train_cpu.trainable(layout.out_features, [w.shape[0] for w in weights[:-1]]):
        return None
    return field_train_cpu.level_grid_mse_step_cpu(points, maps, table, layout, weights, target)


def level_grid_train_step_reference(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor],
    target: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """The prediction ``[N]`` of ``decoder(level_grid_features(points))`` and the gradients of its mean squared
    error to ``target`` ``[N]`` with respect to ``table`` ``[T]`` and every decoder weight (shaped as it), by
    autograd through the reference (what :func:`level_grid_train_step`'s fused kernel must match; the points
    and maps are constants)."""
    with torch.enable_grad():
        leaf = table.detach().requires_grad_(True)
        leaves = [w.detach().requires_grad_(True) for w in weights]
        x = level_grid_features_reference(points.detach(), maps.detach(), leaf, layout)
        for weight in leaves[:-1]:
            x = torch.relu(x @ weight.t())
        prediction = (x @ leaves[-1].t()).view(-1)
        loss = (prediction - target.detach().view(-1)).square().mean()
        grad, *weight_grads = torch.autograd.grad(loss, [leaf, *leaves])
    return prediction.detach(), grad, list(weight_grads)


def level_grid_train_step(
    points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout, weights: list[torch.Tensor],
    target: torch.Tensor, backend: str = "auto",
) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]] | None:
    """One reconstruction step's numbers for a table and a learning decoder, fused in one pass where a kernel
    can: the prediction ``[N]`` and the gradients of its mean squared error to ``target`` with respect to
    ``table`` ``[T]`` and to every decoder weight (as :func:`level_grid_train_step_reference`).

    The fused CPU kernel (:func:`apmgsrn.ops.field_train_cpu.level_grid_train_step_cpu`) runs under the
    conditions of :func:`level_grid_mse_step`; elsewhere this returns ``None`` and the caller runs the step
    through autograd.
    """
    if not _float32_on_cpu(backend, points, maps, table, target, *weights):
        return None
    from apmgsrn.ops import field_train_cpu

    if not field_train_cpu.trainable(layout.out_features, [w.shape[0] for w in weights[:-1]]):
        return None
    prediction, grad, weight_grads = field_train_cpu.level_grid_train_step_cpu(
        points, maps, table, layout, weights, target, decoder_learns=True)
    return prediction, grad, weight_grads

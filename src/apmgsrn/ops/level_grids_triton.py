"""GPU backend of the multi-level grid encoding (the hybrid model): fused Triton kernels, forward and backward.

One program evaluates a block of points on one level (``program_id(1)``): the level's index-space map, the
floor and fractions, and for each of the 8 corners its table row (dense ``x + R_x (y + R_y z)`` or
Instant-NGP's hash of :func:`apmgsrn.ops.level_grids.vertex_rows`), a masked load of the corner's ``F``
features and the trilinear weight. A corner outside the level's lattice loads nothing and weighs 0, as in
:func:`~apmgsrn.ops.level_grids.level_corners`. The backward pass recomputes rows and weights and scatters
the incoming gradient into the table with atomic adds (float32); the maps and points get no gradient here
(the dispatcher runs the reference when they need one, as for the CPU kernel). Every input is defined (the
contract of :mod:`apmgsrn.ops`): a non-finite or far index coordinate fails the bounds test before the integer
cast, and a point with a NaN coordinate gets NaN features and scatters nothing.

Each level's shape comes from a small int64 tensor (``[L, 8]``: resolution x, y, z, rows, hashed, first
float, features, first output column) and its map from ``[L, 3, 4]``, so one compiled kernel serves every
layout; ``FP``, the largest feature count padded to a power of two, is the only shape it is compiled for.

``TRITON_INTERPRET=1`` runs these kernels on CPU tensors (slowly), which the tests use without a GPU.
Importing this module imports Triton but compiles nothing and does not touch CUDA.
"""

from __future__ import annotations

import functools

import torch

from apmgsrn.ops.level_layout import HASH_PRIMES, LevelLayout
# is_available and load_error are this backend's (the dispatcher asks this module).
from apmgsrn.ops.triton_support import IMPORT_ERROR, is_available, load_error, tl, triton  # noqa: F401

if triton is not None:

    @triton.jit
    def _level_corner(points_ptr, maps_ptr, info_ptr, n, nmask, level):
        """Shared by both kernels: a level's lattice, storage and map, and each point's lower corner and
        fractions in its index space."""
        info = info_ptr + level * 8
        rx = tl.load(info + 0)
        ry = tl.load(info + 1)
        rz = tl.load(info + 2)
        rows = tl.load(info + 3)
        hashed = tl.load(info + 4)
        start = tl.load(info + 5)
        features = tl.load(info + 6)
        column = tl.load(info + 7)
        m = maps_ptr + level * 12
        px = tl.load(points_ptr + n * 3 + 0, mask=nmask, other=0.0)
        py = tl.load(points_ptr + n * 3 + 1, mask=nmask, other=0.0)
        pz = tl.load(points_ptr + n * 3 + 2, mask=nmask, other=0.0)
        fx = px * tl.load(m + 0) + py * tl.load(m + 1) + pz * tl.load(m + 2) + tl.load(m + 3)
        fy = px * tl.load(m + 4) + py * tl.load(m + 5) + pz * tl.load(m + 6) + tl.load(m + 7)
        fz = px * tl.load(m + 8) + py * tl.load(m + 9) + pz * tl.load(m + 10) + tl.load(m + 11)
        # Far outside (or NaN): no corner is inside; clamp before the integer cast so it cannot overflow.
        inside = nmask & (fx > -1.0) & (fx < rx) & (fy > -1.0) & (fy < ry) & (fz > -1.0) & (fz < rz)
        fx = tl.where(inside, fx, 0.0)
        fy = tl.where(inside, fy, 0.0)
        fz = tl.where(inside, fz, 0.0)
        flx = tl.floor(fx)
        fly = tl.floor(fy)
        flz = tl.floor(fz)
        # px + py + pz is NaN wherever a coordinate is: the value a NaN point's features take.
        return (rx, ry, rz, rows, hashed, start, features, column, inside,
                flx.to(tl.int64), fly.to(tl.int64), flz.to(tl.int64), fx - flx, fy - fly, fz - flz,
                (px != px) | (py != py) | (pz != pz), px + py + pz)

    @triton.jit
    def _corner_row(x0, y0, z0, tx, ty, tz, corner: tl.constexpr, rx, ry, rz, rows, hashed, inside,
                    P1: tl.constexpr, P2: tl.constexpr):
        """Row, weight and validity of one of the 8 corners (corner ``k`` is offset ``(k & 1, k >> 1 & 1,
        k >> 2)``)."""
        dx = corner & 1
        dy = (corner >> 1) & 1
        dz = corner >> 2
        xi = x0 + dx
        yi = y0 + dy
        zi = z0 + dz
        wx = dx * tx + (1 - dx) * (1.0 - tx)  # dx is a compile-time 0 or 1
        wy = dy * ty + (1 - dy) * (1.0 - ty)
        wz = dz * tz + (1 - dz) * (1.0 - tz)
        valid = inside & (xi >= 0) & (xi < rx) & (yi >= 0) & (yi < ry) & (zi >= 0) & (zi < rz)
        hashed_row = (xi ^ (yi * P1) ^ (zi * P2)) & (rows - 1)
        dense_row = xi + rx * (yi + ry * zi)
        row = tl.where(hashed != 0, hashed_row, dense_row)
        return tl.where(valid, row, 0), wx * wy * wz, valid

    @triton.jit
    def _forward_kernel(points_ptr, maps_ptr, info_ptr, table_ptr, out_ptr, N, out_width,
                        FP: tl.constexpr, BLOCK: tl.constexpr, P1: tl.constexpr, P2: tl.constexpr):
        level = tl.program_id(1)
        n = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        nmask = n < N
        rx, ry, rz, rows, hashed, start, features, column, inside, x0, y0, z0, tx, ty, tz, nanp, nanv = (
            _level_corner(points_ptr, maps_ptr, info_ptr, n, nmask, level))
        ch = tl.arange(0, FP)
        cmask = ch < features
        acc = tl.zeros([BLOCK, FP], dtype=tl.float32)
        for corner in tl.static_range(8):
            row, weight, valid = _corner_row(x0, y0, z0, tx, ty, tz, corner, rx, ry, rz, rows, hashed, inside,
                                             P1, P2)
            ptrs = table_ptr + start + row[:, None] * features + ch[None, :]
            v = tl.load(ptrs, mask=valid[:, None] & cmask[None, :], other=0.0).to(tl.float32)
            acc += v * weight[:, None]
        acc = tl.where(nanp[:, None], nanv[:, None] + acc * 0.0, acc)
        tl.store(out_ptr + n[:, None] * out_width + column + ch[None, :], acc, mask=nmask[:, None] & cmask[None, :])

    @triton.jit
    def _backward_kernel(points_ptr, maps_ptr, info_ptr, grad_out_ptr, grad_ptr, N, out_width,
                         FP: tl.constexpr, BLOCK: tl.constexpr, P1: tl.constexpr, P2: tl.constexpr):
        level = tl.program_id(1)
        n = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        nmask = n < N
        rx, ry, rz, rows, hashed, start, features, column, inside, x0, y0, z0, tx, ty, tz, nanp, nanv = (
            _level_corner(points_ptr, maps_ptr, info_ptr, n, nmask, level))
        ch = tl.arange(0, FP)
        cmask = ch < features
        go = tl.load(grad_out_ptr + n[:, None] * out_width + column + ch[None, :],
                     mask=inside[:, None] & cmask[None, :], other=0.0)
        for corner in tl.static_range(8):
            row, weight, valid = _corner_row(x0, y0, z0, tx, ty, tz, corner, rx, ry, rz, rows, hashed, inside,
                                             P1, P2)
            ptrs = grad_ptr + start + row[:, None] * features + ch[None, :]
            tl.atomic_add(ptrs, go * weight[:, None], mask=valid[:, None] & cmask[None, :], sem="relaxed")


@functools.lru_cache(maxsize=64)
def layout_info(layout: LevelLayout, device: torch.device) -> torch.Tensor:
    """``[L, 8]`` int64 per level: resolution x, y, z, table rows, hashed, first float, features, first
    output column (what the kernels read). Cached: layouts are frozen and few, so a training step does not
    copy it to the device again in every forward and backward pass."""
    rows = [(*res, size, int(hashed), start, f, column) for res, size, hashed, start, f, column in zip(
        layout.resolutions, layout.sizes, layout.hashed, layout.offsets, layout.features, layout.columns)]
    return torch.tensor(rows, dtype=torch.int64, device=device).reshape(-1, 8)


def _launch(kernel, points, maps, layout: LevelLayout, data, out, n: int, block: int = 256) -> None:
    """Run ``kernel`` on ``n`` points, ``block`` points per program and one program row per level."""
    if triton is None:
        raise RuntimeError(IMPORT_ERROR)
    if layout.table_size >= 2**31:
        raise ValueError("tables of 2^31 floats or more are not supported by the Triton backend")
    info = layout_info(layout, points.device)
    fp = triton.next_power_of_2(max(layout.features))
    kernel[(triton.cdiv(n, block), layout.levels)](
        points, maps, info, data, out, n, layout.out_features,
        FP=fp, BLOCK=block, P1=HASH_PRIMES[1], P2=HASH_PRIMES[2], num_warps=4,
    )


def forward_features(points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout
                     ) -> torch.Tensor:
    """Fused forward pass (no autograd): ``[N, sum_l F_l]`` float32 features, as the reference."""
    n = points.shape[0]
    out = torch.empty(n, layout.out_features, device=points.device, dtype=torch.float32)
    if n and layout.levels:
        _launch(_forward_kernel, points.detach().contiguous(), maps.detach().contiguous(), layout,
                table.detach().contiguous(), out, n)
    return out


def backward_table(points: torch.Tensor, maps: torch.Tensor, grad_out: torch.Tensor, layout: LevelLayout
                   ) -> torch.Tensor:
    """Gradient w.r.t. the flat table (float32): ``grad_out`` scattered with the trilinear weights."""
    n = points.shape[0]
    grad = torch.zeros(layout.table_size, device=points.device, dtype=torch.float32)
    if n and layout.levels:
        _launch(_backward_kernel, points, maps, layout, grad_out.to(torch.float32).contiguous(), grad, n)
    return grad


class _LevelGridFunction(torch.autograd.Function):
    """Autograd wrapper: gradients for the table only."""

    @staticmethod
    def forward(ctx, points, maps, table, layout):  # type: ignore[override]
        pts = points.detach().contiguous()
        mps = maps.detach().contiguous()
        out = forward_features(pts, mps, table, layout)
        ctx.save_for_backward(pts, mps)
        ctx.layout = layout
        ctx.table_dtype = table.dtype
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        pts, mps = ctx.saved_tensors
        grad_table = None
        if ctx.needs_input_grad[2]:
            grad_table = backward_table(pts, mps, grad_out, ctx.layout).to(ctx.table_dtype)
        return None, None, grad_table, None


def level_grid_features_triton(points: torch.Tensor, maps: torch.Tensor, table: torch.Tensor, layout: LevelLayout
                               ) -> torch.Tensor:
    """Fused Triton level-grid features with gradients for ``table`` only.

    Args:
        points: ``[N, 3]`` float32 (CUDA, or CPU under ``TRITON_INTERPRET=1``).
        maps: ``[L, 3, 4]`` float32 index-space maps (no gradient flows to them).
        table: ``[T]`` float32 (or float16) flat table.
        layout: the levels.

    Returns:
        ``[N, sum_l F_l]`` float32 features, as :func:`~apmgsrn.ops.level_grids.level_grid_features_reference`.
    """
    return _LevelGridFunction.apply(points, maps, table, layout)

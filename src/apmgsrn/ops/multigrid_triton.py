"""GPU backend of the multi-grid encoder: fused Triton kernels (forward and backward).

One program evaluates a block of (point, grid) pairs, flattened point-major (``e = n * M + i``), so the
``[N, M * C]`` output is written in order and fully coalesced, for any ``M`` (no padding to a power of
two). Per pair: the map ``G_i(p) = A_i p + t_i``, the bounds test, the corner-aligned unnormalisation,
eight trilinear weights and ``8 C`` masked loads; a pair whose point lies outside grid ``i`` loads
nothing (its lanes are masked off), so once the grids have moved to the features a point costs only
the grids that cover it. Nothing ``[M, N, 3]``-sized is ever stored. The backward pass recomputes the
weights and scatters the incoming gradient into the grids with atomic adds (float32 accumulation);
the grid placements get no gradient here (they keep the density-loss path). Every input is defined (the
contract of :mod:`apmgsrn.ops`): a non-finite or far index coordinate fails the bounds test before the integer
cast, and a point with a NaN coordinate gets NaN features and scatters nothing.

Grids may be float32, float16 or bfloat16 (half the bytes per gather); arithmetic and the returned
features are float32. Grids are read through their strides, so a channel-last view (corners' ``C``
features adjacent) needs no copy.

``TRITON_INTERPRET=1`` runs these kernels on CPU tensors (slowly), which the tests use without a GPU.
Importing this module imports Triton but compiles nothing and does not touch CUDA.
"""

from __future__ import annotations

import torch

# is_available and load_error are this backend's (the dispatcher asks this module).
from apmgsrn.ops.triton_support import IMPORT_ERROR, is_available, load_error, tl, triton  # noqa: F401

if triton is not None:

    @triton.jit
    def _pair_corners(points_ptr, mat_ptr, trans_ptr, e, emask, M, D, H, W, s_m, s_z, s_y, s_x):
        """Shared by both kernels: for pairs ``e`` return grid base offset, index-space integer corner
        ``(x0, y0, z0)``, fractions ``(tx, ty, tz)`` and the 'touches the grid' mask."""
        n = e // M
        g = e - n * M
        px = tl.load(points_ptr + n * 3 + 0, mask=emask, other=0.0)
        py = tl.load(points_ptr + n * 3 + 1, mask=emask, other=0.0)
        pz = tl.load(points_ptr + n * 3 + 2, mask=emask, other=0.0)
        a = mat_ptr + g * 9
        lx = px * tl.load(a + 0, mask=emask, other=0.0) + py * tl.load(a + 1, mask=emask, other=0.0)
        lx += pz * tl.load(a + 2, mask=emask, other=0.0) + tl.load(trans_ptr + g * 3 + 0, mask=emask, other=0.0)
        ly = px * tl.load(a + 3, mask=emask, other=0.0) + py * tl.load(a + 4, mask=emask, other=0.0)
        ly += pz * tl.load(a + 5, mask=emask, other=0.0) + tl.load(trans_ptr + g * 3 + 1, mask=emask, other=0.0)
        lz = px * tl.load(a + 6, mask=emask, other=0.0) + py * tl.load(a + 7, mask=emask, other=0.0)
        lz += pz * tl.load(a + 8, mask=emask, other=0.0) + tl.load(trans_ptr + g * 3 + 2, mask=emask, other=0.0)
        # Corner-aligned unnormalisation, written as grid_sample writes it: ((x + 1) / 2) * (size - 1).
        fx = ((lx + 1.0) / 2.0) * (W - 1)
        fy = ((ly + 1.0) / 2.0) * (H - 1)
        fz = ((lz + 1.0) / 2.0) * (D - 1)
        # Some corner is inside iff floor(f) is in [-1, size - 1]; NaN compares false.
        inside = emask & (fx > -1.0) & (fx < W) & (fy > -1.0) & (fy < H) & (fz > -1.0) & (fz < D)
        fx = tl.where(inside, fx, 0.0)
        fy = tl.where(inside, fy, 0.0)
        fz = tl.where(inside, fz, 0.0)
        flx = tl.floor(fx)
        fly = tl.floor(fy)
        flz = tl.floor(fz)
        # px + py + pz is NaN wherever a coordinate is: the value a NaN point's features take.
        return (
            g * s_m, flx.to(tl.int32), fly.to(tl.int32), flz.to(tl.int32),
            fx - flx, fy - fly, fz - flz, inside, (px != px) | (py != py) | (pz != pz), px + py + pz,
        )

    @triton.jit
    def _forward_kernel(
        points_ptr, mat_ptr, trans_ptr, grids_ptr, out_ptr,
        total, D, H, W, s_m, s_c, s_z, s_y, s_x,
        M: tl.constexpr, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr,
    ):
        # M is a compile-time constant so that e // M is a multiply and shift, not a division.
        e = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)  # [B] pair index n * M + g
        emask = e < total
        base, x0, y0, z0, tx, ty, tz, inside, nanp, nanv = _pair_corners(
            points_ptr, mat_ptr, trans_ptr, e, emask, M, D, H, W, s_m, s_z, s_y, s_x
        )
        ch = tl.arange(0, CP)
        cmask = ch < C
        acc = tl.zeros([BLOCK, CP], dtype=tl.float32)
        for corner in tl.static_range(8):
            dx = corner & 1
            dy = (corner >> 1) & 1
            dz = corner >> 2
            xi = x0 + dx
            yi = y0 + dy
            zi = z0 + dz
            wx = dx * tx + (1 - dx) * (1.0 - tx)  # dx is a compile-time 0 or 1
            wy = dy * ty + (1 - dy) * (1.0 - ty)  # dy is a compile-time 0 or 1
            wz = dz * tz + (1 - dz) * (1.0 - tz)  # dz is a compile-time 0 or 1
            valid = inside & (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H) & (zi >= 0) & (zi < D)
            off = base + zi * s_z + yi * s_y + xi * s_x  # [B]
            ptrs = grids_ptr + off[:, None] + ch[None, :] * s_c  # [B, CP]
            v = tl.load(ptrs, mask=valid[:, None] & cmask[None, :], other=0.0).to(tl.float32)
            acc += v * (wx * wy * wz)[:, None]
        acc = tl.where(nanp[:, None], nanv[:, None] + acc * 0.0, acc)
        # Pair e owns output elements [e * C, e * C + C): row n, columns g * C + c.
        tl.store(out_ptr + e[:, None] * C + ch[None, :], acc, mask=emask[:, None] & cmask[None, :])

    @triton.jit
    def _backward_kernel(
        points_ptr, mat_ptr, trans_ptr, grad_out_ptr, grad_ptr,
        total, D, H, W, s_m, s_c, s_z, s_y, s_x,
        M: tl.constexpr, C: tl.constexpr, CP: tl.constexpr, BLOCK: tl.constexpr,
    ):
        e = tl.program_id(0).to(tl.int64) * BLOCK + tl.arange(0, BLOCK)
        emask = e < total
        base, x0, y0, z0, tx, ty, tz, inside, nanp, nanv = _pair_corners(
            points_ptr, mat_ptr, trans_ptr, e, emask, M, D, H, W, s_m, s_z, s_y, s_x
        )
        ch = tl.arange(0, CP)
        cmask = ch < C
        go = tl.load(grad_out_ptr + e[:, None] * C + ch[None, :], mask=inside[:, None] & cmask[None, :], other=0.0)
        for corner in tl.static_range(8):
            dx = corner & 1
            dy = (corner >> 1) & 1
            dz = corner >> 2
            xi = x0 + dx
            yi = y0 + dy
            zi = z0 + dz
            wx = dx * tx + (1 - dx) * (1.0 - tx)  # dx is a compile-time 0 or 1
            wy = dy * ty + (1 - dy) * (1.0 - ty)  # dy is a compile-time 0 or 1
            wz = dz * tz + (1 - dz) * (1.0 - tz)  # dz is a compile-time 0 or 1
            valid = inside & (xi >= 0) & (xi < W) & (yi >= 0) & (yi < H) & (zi >= 0) & (zi < D)
            off = base + zi * s_z + yi * s_y + xi * s_x
            ptrs = grad_ptr + off[:, None] + ch[None, :] * s_c
            tl.atomic_add(ptrs, go * (wx * wy * wz)[:, None], mask=valid[:, None] & cmask[None, :], sem="relaxed")


def _block(c: int) -> tuple[int, int, int]:
    """(BLOCK pairs, CP padded channels, warps) per program: about 1024 sampled values per program."""
    cp = triton.next_power_of_2(c)
    return max(64, 1024 // cp), cp, 4


def _check(points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor, grids: torch.Tensor) -> None:
    if triton is None:
        raise RuntimeError(IMPORT_ERROR)
    if grids.numel() >= 2**31:
        raise ValueError("grids of 2^31 elements or more are not supported by the Triton backend")


def forward_features(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor, grids: torch.Tensor
) -> torch.Tensor:
    """Fused forward pass (no autograd).

    Args:
        points: ``[N, 3]`` float32.
        matrices: ``[M, 3, 3]`` float32.
        translations: ``[M, 3]`` float32.
        grids: ``[M, C, D, H, W]`` float32/float16/bfloat16, any strides.

    Returns:
        ``[N, M * C]`` float32 features, as the reference.
    """
    _check(points, matrices, translations, grids)
    m, c, d, h, w = grids.shape
    n = points.shape[0]
    if c > 1 and grids.stride(1) != 1:
        # Channel-last: a corner's C features in one memory sector. The copy is one pass over the grids,
        # microseconds at GPU bandwidth.
        grids = grids.detach().permute(0, 2, 3, 4, 1).contiguous().permute(0, 4, 1, 2, 3)
    pts = points.detach().contiguous()
    mat = matrices.detach().contiguous()
    trans = translations.detach().contiguous()
    out = torch.empty(n, m * c, device=points.device, dtype=torch.float32)
    total = n * m
    if total == 0:
        return out
    block, cp, warps = _block(c)
    _forward_kernel[(triton.cdiv(total, block),)](
        pts, mat, trans, grids.detach(), out, total, d, h, w, *grids.stride(),
        M=m, C=c, CP=cp, BLOCK=block, num_warps=warps,
    )
    return out


def backward_grids(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grad_out: torch.Tensor,
    shape: tuple[int, ...],
) -> torch.Tensor:
    """Gradient w.r.t. the grids (float32).

    Args:
        points: ``[N, 3]`` float32 contiguous.
        matrices: ``[M, 3, 3]`` float32 contiguous.
        translations: ``[M, 3]`` float32 contiguous.
        grad_out: ``[N, M * C]``.
        shape: ``(M, C, D, H, W)``.

    Returns:
        The scatter of ``grad_out`` with the trilinear weights, ``[M, C, D, H, W]`` stored channel-last
        (a corner's C atomic adds land in one sector); autograd lays it out like the parameter.
    """
    m, c, d, h, w = shape
    n = points.shape[0]
    grad = torch.zeros((m, d, h, w, c), device=points.device, dtype=torch.float32).permute(0, 4, 1, 2, 3)
    total = n * m
    if total == 0:
        return grad
    go = grad_out.to(torch.float32).contiguous()
    block, cp, warps = _block(c)
    _backward_kernel[(triton.cdiv(total, block),)](
        points, matrices, translations, go, grad, total, d, h, w, *grad.stride(),
        M=m, C=c, CP=cp, BLOCK=block, num_warps=warps,
    )
    return grad


class _MultigridFunction(torch.autograd.Function):
    """Autograd wrapper: gradients for the grids only."""

    @staticmethod
    def forward(ctx, points, matrices, translations, grids):  # type: ignore[override]
        pts = points.detach().contiguous()
        mat = matrices.detach().contiguous()
        trans = translations.detach().contiguous()
        out = forward_features(pts, mat, trans, grids)
        ctx.save_for_backward(pts, mat, trans)
        ctx.grid_shape = tuple(grids.shape)
        ctx.grid_dtype = grids.dtype
        return out

    @staticmethod
    def backward(ctx, grad_out):  # type: ignore[override]
        pts, mat, trans = ctx.saved_tensors
        grad_grids = None
        if ctx.needs_input_grad[3]:
            grad_grids = backward_grids(pts, mat, trans, grad_out, ctx.grid_shape).to(ctx.grid_dtype)
        return None, None, None, grad_grids


def multigrid_features_triton(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor, grids: torch.Tensor
) -> torch.Tensor:
    """Fused Triton multi-grid features with gradients for ``grids`` only.

    Args:
        points: ``[N, 3]`` float32 (CUDA, or CPU under ``TRITON_INTERPRET=1``).
        matrices: ``[M, 3, 3]`` float32 (no gradient flows to them).
        translations: ``[M, 3]`` float32 (no gradient flows to them).
        grids: ``[M, C, D, H, W]`` float32, float16 or bfloat16.

    Returns:
        ``[N, M * C]`` float32 features, as
        :func:`~apmgsrn.ops.multigrid.multigrid_features_reference` on ``grids.float()``.
    """
    return _MultigridFunction.apply(points, matrices, translations, grids)

"""Adaptive multi-grid encoding (docs/method.md §2) and feature density (docs/method.md §3).

Reference implementation in pure PyTorch: every point is mapped into all ``M`` local grid frames and
sampled with one batched ``grid_sample``. Sampling is *zero-padded trilinear* (corner-aligned): a corner
outside the grid contributes zero, so a feature fades to zero over the half cell beyond the grid's border,
and is exactly zero one cell beyond it. Accelerated backends must match this function in forward and
backward, at every input (the contract of :mod:`apmgsrn.ops`: a point with a NaN coordinate has NaN features
and density and adds to no gradient; an infinite one is outside every grid).

:func:`multigrid_features` dispatches to the fused backends: ``"cpu"`` (C/OpenMP, :mod:`.multigrid_cpu`,
built on first use) and ``"triton"`` (CUDA, :mod:`.multigrid_triton`, imported only for CUDA tensors since
importing Triton takes a second); importing this module builds, compiles and initialises nothing. They
compute the grid map, bounds test, trilinear weights, gather and concatenation in one pass per point and skip
the grids that do not cover it, so beyond the ``[N, M * C]`` output their memory does not grow with ``M``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from apmgsrn.choices import MULTIGRID_BACKENDS
from apmgsrn.ops import multigrid_cpu
from apmgsrn.ops.contract import finite_stand_in, nan_where_nan, outside_for_non_finite

#: A local coordinate beyond ``±LOCAL_OUTSIDE`` is outside every grid (of 2 vertices or more per axis, a cell
#: spans at most 2 local units, and zero padding fades over one cell): the reference reads every such
#: coordinate (and NaN, from a NaN point or ``inf * 0``) as this one, which gives the same zero features and
#: keeps ``grid_sample``'s integer conversions defined.
LOCAL_OUTSIDE = 3.0


def local_coordinates(
    points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor
) -> torch.Tensor:
    """Map global points into every grid's local frame, ``G_i(p) = A_i p + t_i``.

    Args:
        points: ``[N, 3]`` global coordinates in ``[-1, 1]^3``.
        matrices: ``[M, 3, 3]`` the ``A_i``.
        translations: ``[M, 3]`` the ``t_i``.

    Returns:
        ``[M, N, 3]`` local coordinates; the grid occupies ``[-1, 1]^3`` there.
    """
    return torch.matmul(points, matrices.transpose(1, 2)) + translations[:, None, :]  # [M, N, 3]


def multigrid_features_reference(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
) -> torch.Tensor:
    """Concatenated features of all grids at the points, grid-major.

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]`` feature grids.

    Returns:
        ``[N, M * C]`` features; column ``i * C + c`` is channel ``c`` of grid ``i``.
    """
    m, c = grids.shape[:2]
    n = points.shape[0]
    local = local_coordinates(finite_stand_in(points), matrices, translations)  # [M, N, 3]
    local = outside_for_non_finite(local, LOCAL_OUTSIDE)
    sampled = F.grid_sample(
        grids, local.view(m, n, 1, 1, 3), mode="bilinear", padding_mode="zeros", align_corners=True
    )  # [M, C, N, 1, 1]
    return nan_where_nan(points, sampled.view(m * c, n).t())  # [N, M * C]


BACKENDS = MULTIGRID_BACKENDS
"""Backend names accepted besides ``"auto"``: the pure-PyTorch reference, the fused C/OpenMP CPU
kernel (:mod:`apmgsrn.ops.multigrid_cpu`) and the fused Triton GPU kernels
(:mod:`apmgsrn.ops.multigrid_triton`)."""


def backend_available(name: str, device: torch.device | str = "cpu") -> bool:
    """Whether a backend can run on tensors of ``device`` here (builds the CPU kernel on first ask).

    Args:
        name: one of :data:`BACKENDS`.
        device: where the tensors live.

    Returns:
        True when the backend is usable; ``"torch"`` always is.
    """
    device = torch.device(device)
    if name == "torch":
        return True
    if name == "cpu":
        if device.type != "cpu":
            return False
        return multigrid_cpu.is_available()
    if name == "triton":
        if device.type != "cuda":
            return False
        from apmgsrn.ops import multigrid_triton

        return multigrid_triton.is_available()
    raise ValueError(f"unknown multigrid backend {name!r}; use auto or one of {BACKENDS}")


def resolve_backend(name: str, device: torch.device | str) -> str:
    """The backend ``name`` stands for on ``device``: ``"auto"`` picks the fastest usable one.

    Args:
        name: ``"auto"`` or one of :data:`BACKENDS`.
        device: where the tensors live.

    Returns:
        A name from :data:`BACKENDS`.

    Raises:
        ValueError: unknown name.
        RuntimeError: an explicitly named backend cannot run here (not installed, no compiler,
            wrong device).
    """
    device = torch.device(device)
    if name == "auto":
        fast = "triton" if device.type == "cuda" else "cpu" if device.type == "cpu" else None
        return fast if fast is not None and backend_available(fast, device) else "torch"
    if name not in BACKENDS:
        raise ValueError(f"unknown multigrid backend {name!r}; use auto or one of {BACKENDS}")
    if not backend_available(name, device):
        reason = ""
        if name == "cpu" and device.type == "cpu":
            reason = f": {multigrid_cpu.load_error()}"
        elif name == "triton" and device.type == "cuda":
            from apmgsrn.ops import multigrid_triton

            reason = f": {multigrid_triton.load_error()}"
        raise RuntimeError(f"multigrid backend {name!r} cannot run on {device.type} tensors here{reason}")
    return name


def _needs_reference(points: torch.Tensor, matrices: torch.Tensor, translations: torch.Tensor,
                     placement_gradient: bool = False) -> bool:
    """Cases a fused kernel does not cover: gradients for the points, or for the maps unless it gives them
    (``placement_gradient``: the CPU kernel does), or non-float32 inputs."""
    inputs = (points, matrices, translations)
    if torch.is_grad_enabled():
        wanted = (points,) if placement_gradient else inputs
        if any(t.requires_grad for t in wanted):
            return True
    return any(t.dtype != torch.float32 for t in inputs)


def multigrid_features(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
    backend: str = "auto",
) -> torch.Tensor:
    """Concatenated multi-grid features through the chosen backend.

    Same shapes and semantics as :func:`multigrid_features_reference`. The fused CPU backend gives
    gradients for ``grids``, ``matrices`` and ``translations`` (the last two when the reconstruction error
    moves the placement, ``TrainConfig.placement_loss="reconstruction"``), the Triton backend for ``grids``
    only: when ``points`` (or, on Triton, the maps) require grad, or the inputs are not float32, this runs
    the reference instead, so autograd stays exact. The Triton backend also reads float16/bfloat16 grids
    (features come out float32).

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]``; a channel-last view (``grids.permute(0, 2, 3, 4, 1).contiguous()
            .permute(0, 4, 1, 2, 3)``) is read as is, which spares the fused kernels a per-call
            conversion when ``C > 1``.
        backend: ``"auto"`` (fastest usable for the tensors' device: ``"triton"`` on CUDA,
            ``"cpu"`` on CPU, else the reference), ``"torch"``, ``"cpu"`` or ``"triton"``.

    Returns:
        ``[N, M * C]`` features, grid-major.

    Raises:
        ValueError: unknown backend name.
        RuntimeError: an explicitly named backend cannot run here.
    """
    name = resolve_backend(backend, points.device)
    if name == "torch":
        return multigrid_features_reference(points, matrices, translations, grids)
    if name == "triton":
        half = grids.dtype in (torch.float16, torch.bfloat16)
        if _needs_reference(points, matrices, translations) or not (half or grids.dtype == torch.float32):
            # grid_sample wants one dtype: half grids are read at the points' precision
            return multigrid_features_reference(
                points, matrices, translations, grids.to(points.dtype) if half else grids
            )
        from apmgsrn.ops.multigrid_triton import multigrid_features_triton

        return multigrid_features_triton(points, matrices, translations, grids)
    if _needs_reference(points, matrices, translations, placement_gradient=True) or grids.dtype != torch.float32:
        return multigrid_features_reference(points, matrices, translations, grids)
    return multigrid_cpu.multigrid_features_cpu(points, matrices, translations, grids)


def multigrid_decoded(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    grids: torch.Tensor,
    weights: list[torch.Tensor],
    backend: str = "auto",
) -> torch.Tensor | None:
    """``decoder(multigrid_features(points, ...))`` fused in one pass where a kernel can (inference only).

    The fused CPU kernel (:mod:`apmgsrn.ops.field_cpu`) runs when ``backend`` resolves to ``"cpu"``, no
    gradient is wanted, every tensor is float32 and the sizes fit; elsewhere this returns ``None`` and the
    caller runs encoder and decoder as usual (the reference).

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        grids: ``[M, C, D, H, W]``.
        weights: the decoder's bias-free linear layers ``[out, in]`` in order, ReLU between them, the
            last ``[1, in]``.
        backend: as :func:`multigrid_features`.

    Returns:
        ``[N]`` decoder outputs, or ``None``.
    """
    if torch.is_grad_enabled() or resolve_backend(backend, points.device) != "cpu":
        return None
    if any(t.dtype != torch.float32 for t in (points, matrices, translations, grids, *weights)):
        return None
    from apmgsrn.ops import field_cpu

    if not field_cpu.fusable(grids.shape[0] * grids.shape[1], [w.shape[0] for w in weights[:-1]]):
        return None
    return field_cpu.multigrid_decoder_cpu(points, matrices, translations, grids, weights)


def feature_density_reference(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    power: int = 10,
) -> torch.Tensor:
    """Pure-PyTorch feature density; see :func:`feature_density`."""
    # Beyond this on any axis the falloff is exactly 0 in float32 (exp(-128) underflows): the coordinate is
    # read as the limit itself, the same density, and a zero gradient instead of 0 * inf (and NaN, from a
    # NaN point or inf * 0, reads as far away too; a NaN point gets NaN below).
    limit = 128.0 ** (1.0 / (2 * power))
    local = outside_for_non_finite(local_coordinates(finite_stand_in(points), matrices, translations), limit)
    falloff = torch.exp(-local.pow(2 * power).sum(-1))  # [M, N]
    det = torch.linalg.det(matrices)  # [M]
    return nan_where_nan(points, (det[:, None] * falloff).sum(0))  # [N]


def feature_density(
    points: torch.Tensor,
    matrices: torch.Tensor,
    translations: torch.Tensor,
    power: int = 10,
    backend: str = "auto",
) -> torch.Tensor:
    """Flat-top Gaussian feature density ``rho(p) = sum_i det(A_i) exp(-sum_d G_i(p)_d^(2P))``.

    On CPU float32 tensors ``"auto"`` uses the fused kernel of :mod:`apmgsrn.ops.multigrid_cpu`
    (one pass per point, no ``[M, N, 3]`` intermediates; gradients for ``matrices`` and
    ``translations``); gradients for ``points``, other dtypes, devices or powers above 63 use the
    reference.

    Args:
        points: ``[N, 3]``.
        matrices: ``[M, 3, 3]``.
        translations: ``[M, 3]``.
        power: ``P`` of the super-Gaussian (docs/method.md: 10).
        backend: ``"auto"``, ``"torch"`` or ``"cpu"``.

    Returns:
        ``[N]`` unnormalised density.
    """
    if backend not in ("auto", "torch", "cpu"):
        raise ValueError(f"unknown feature density backend {backend!r}; use auto, torch or cpu")
    fused = (
        backend != "torch"
        and points.device.type == "cpu"
        and 1 <= power <= 63
        and not (torch.is_grad_enabled() and points.requires_grad)
        and all(t.dtype == torch.float32 for t in (points, matrices, translations))
    )
    if fused:
        fused = backend_available("cpu", "cpu")
        if not fused and backend == "cpu":
            resolve_backend("cpu", "cpu")  # raises with the reason
    if not fused:
        return feature_density_reference(points, matrices, translations, power)
    return multigrid_cpu.feature_density_cpu(points, matrices, translations, power)


def feature_mass(power: int = 10) -> float:
    """Integral of one grid's density ``det(A) exp(-sum_d G(p)_d^(2P))`` over all space.

    The ``det(A)`` factor cancels the change of variables, so every grid carries this same mass,
    ``(2 Gamma(1 + 1 / (2P)))^3``, wherever it is placed and however it is scaled.
    """
    import math

    return (2.0 * math.gamma(1.0 + 1.0 / (2 * power))) ** 3

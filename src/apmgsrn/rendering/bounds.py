"""Where rays can meet something: the box, and the macro cells a transfer function may show.

Rays are clipped to boxes with the slab method (:func:`intersect_box`). For empty-space skipping the box
``[-1, 1]^3`` is cut into ``Gz x Gy x Gx`` macro cells. :class:`ValueBounds` holds, per cell, a lower and
upper bound of every value the field can take inside it. Given a transfer table, a cell is *transparent*
when the opacity is zero over its whole ``[low, high]`` interval; :class:`Occupancy` holds that
classification and the box around the visible cells, and the renderer drops every sample in a transparent
cell without evaluating the field. Bounds are computed once per field; the classification is cheap and is
redone whenever the transfer function changes.

Two sources of bounds:

* :meth:`ValueBounds.from_volume`: min/max pooling of the voxels whose trilinear support touches the
  cell (plus one voxel of guard on each side). Exact: a trilinear value is a convex combination of those
  voxels, so skipping never changes the image.
* :meth:`ValueBounds.from_field`: the field sampled once on a lattice of ``samples_per_cell`` steps per
  cell edge (cell corners included), widened by the largest change between neighbouring lattice samples
  in the cell. Approximate: a network can peak between lattice points by more than that guard, which
  would lose a faint feature; raise ``samples_per_cell`` if a render shows it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from apmgsrn.rendering.field import Field
from apmgsrn.rendering.transfer_function import TransferTable


def intersect_box(
    origins: torch.Tensor, directions: torch.Tensor, low: torch.Tensor, high: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab-method ray/box intersection.

    Args:
        origins, directions: ``[R, 3]`` rays.
        low, high: ``[3]`` box corners.

    Returns:
        ``(t_enter [R], t_exit [R])``; a miss has exit < enter.
    """
    # Division by a zero component gives +-inf, which the min/max below handle (a parallel ray inside the
    # slab keeps (-inf, inf); outside it gets an empty interval).
    inverse = 1.0 / directions
    t0 = (low - origins) * inverse  # [R, 3]
    t1 = (high - origins) * inverse
    t_small = torch.minimum(t0, t1).nan_to_num(nan=-math.inf)
    t_large = torch.maximum(t0, t1).nan_to_num(nan=math.inf)
    return t_small.amax(dim=1), t_large.amin(dim=1)


@dataclass
class ValueBounds:
    """Per-macro-cell value bounds, ``low``/``high`` ``[Gz, Gy, Gx]`` float32 in data units."""

    low: torch.Tensor
    high: torch.Tensor
    exact: bool

    @property
    def cells(self) -> tuple[int, int, int]:
        """Cells per axis ``(Gz, Gy, Gx)``."""
        return tuple(self.low.shape)  # type: ignore[return-value]

    def to(self, device: torch.device | str) -> "ValueBounds":
        return ValueBounds(self.low.to(device), self.high.to(device), self.exact)

    @classmethod
    def from_volume(cls, volume: torch.Tensor, cells: int = 32) -> "ValueBounds":
        """Exact bounds of the trilinear interpolant of a volume.

        Args:
            volume: ``[D, H, W]`` values (C order, x fastest).
            cells: macro cells along each axis (at most one per voxel gap).

        Returns:
            The bounds, ``[Gz, Gy, Gx]``.
        """
        if volume.dim() != 3:
            raise ValueError(f"volume must be [D, H, W], got shape {tuple(volume.shape)}")
        low = volume.to(torch.float32)
        high = low
        # Min/max are separable over a box: reduce x, then y, then z (dims 2, 1, 0).
        for dim in (2, 1, 0):
            n = volume.shape[dim]
            count = max(1, min(cells, n - 1))
            ranges = _voxel_ranges(n, count)
            low = torch.stack([low.narrow(dim, a, b - a).amin(dim) for a, b in ranges], dim=dim)
            high = torch.stack([high.narrow(dim, a, b - a).amax(dim) for a, b in ranges], dim=dim)
        return cls(low=low.contiguous(), high=high.contiguous(), exact=True)

    @classmethod
    @torch.no_grad()
    def from_field(
        cls,
        field: Field,
        cells: int = 32,
        samples_per_cell: int = 4,
        batch_size: int = 1 << 18,
        device: torch.device | str = "cpu",
    ) -> "ValueBounds":
        """Bounds of any field, from one dense sampling (see the module notes: approximate).

        Args:
            field: callable ``[N, 3] -> [N, 1]`` on points in ``[-1, 1]^3``.
            cells: macro cells along each axis.
            samples_per_cell: lattice steps per cell edge; ``(cells * samples_per_cell + 1)^3`` evaluations.
            batch_size: points per field call.
            device: where the points are made.

        Returns:
            The bounds, ``[cells, cells, cells]``.
        """
        s = max(1, int(samples_per_cell))
        n = cells * s + 1
        axis = torch.linspace(-1.0, 1.0, n, device=device)
        values = torch.empty(n * n * n, dtype=torch.float32, device=device)
        for start in range(0, n * n * n, batch_size):
            index = torch.arange(start, min(start + batch_size, n * n * n), device=device)
            # Lattice point of each linear index, C order (z, y, x), x fastest.
            points = torch.stack([axis[index % n], axis[(index // n) % n], axis[index // (n * n)]], dim=1)  # [B, 3]
            values[start : start + len(index)] = field(points).reshape(-1).to(torch.float32)
        values = values.view(n, n, n)
        grid = values[None, None]  # [1, 1, n, n, n]
        window, stride = s + 1, s
        high = F.max_pool3d(grid, window, stride)[0, 0]
        low = -F.max_pool3d(-grid, window, stride)[0, 0]
        # Guard: the largest step between neighbouring lattice samples inside the cell, along any axis.
        guard = torch.zeros_like(low)
        for dim, kernel in ((2, (s, window, window)), (3, (window, s, window)), (4, (window, window, s))):
            step = (grid.narrow(dim, 1, n - 1) - grid.narrow(dim, 0, n - 1)).abs()
            guard = torch.maximum(guard, F.max_pool3d(step, kernel, stride)[0, 0])
        return cls(low=(low - guard).contiguous(), high=(high + guard).contiguous(), exact=False)

    def visible_cells(self, table: TransferTable) -> torch.Tensor:
        """Which cells may be visible under a transfer table.

        Args:
            table: the baked transfer function (on the bounds' device).

        Returns:
            ``[Gz, Gy, Gx]`` bool, False where the opacity is zero for every value the cell can hold.
        """
        visible = table.opacity_nonzero_between(self.low.reshape(-1), self.high.reshape(-1))
        return visible.view(self.low.shape)


def occupied_box(occupancy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Bounding box of the visible cells, in ``[-1, 1]^3`` coordinates ``(x, y, z)``.

    Args:
        occupancy: ``[Gz, Gy, Gx]`` bool.

    Returns:
        ``(low [3], high [3])`` float32, or None when no cell is visible.
    """
    index = occupancy.nonzero()  # [K, 3] as (z, y, x)
    if index.numel() == 0:
        return None
    counts = torch.tensor(occupancy.shape, device=occupancy.device).flip(0).to(torch.float32)  # (Gx,Gy,Gz)
    first = index.amin(0).flip(0).to(torch.float32)  # (x, y, z)
    last = index.amax(0).flip(0).to(torch.float32) + 1.0
    return -1.0 + 2.0 * first / counts, -1.0 + 2.0 * last / counts


class Occupancy:
    """The macro cells a transfer table may show, the box around them, and the per-sample cell test.

    Attributes:
        cells: ``[Gz, Gy, Gx]`` bool, False where the opacity is zero for every value the cell can hold.
        box: ``(low [3], high [3])`` around the visible cells in field coordinates ``(x, y, z)``, or None
            when no cell is visible.
    """

    def __init__(self, bounds: ValueBounds, table: TransferTable) -> None:
        """Args:
        bounds: the field's value bounds.
        table: the baked transfer function, on the bounds' device.
        """
        self.cells = bounds.visible_cells(table)
        self.box = occupied_box(self.cells)
        counts = self.cells.shape[::-1]  # (Gx, Gy, Gz)
        device = self.cells.device
        self._scale = 0.5 * torch.tensor(counts, dtype=torch.float32, device=device)  # field -> cell units
        self._last = torch.tensor(counts, dtype=torch.float32, device=device) - 1.0
        self._stride = torch.tensor([1, counts[0], counts[0] * counts[1]], device=device)  # flat (z, y, x) index
        self._flat = self.cells.reshape(-1)

    @property
    def visible_fraction(self) -> float:
        """Fraction of the cells the transfer table may show."""
        return float(self.cells.float().mean())

    def cell_rays(self, origins: torch.Tensor, directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Rays in macro-cell units (``[0, G]`` per axis) from rays in field coordinates.

        Args:
            origins, directions: ``[R, 3]`` in field coordinates (``[-1, 1]^3`` is the box).

        Returns:
            ``(origins [R, 3], directions [R, 3])`` in cell units, so a sample's cell is the floor of its position.
        """
        return (origins + 1.0) * self._scale, directions * self._scale

    def visible(self, cell_origins: torch.Tensor, cell_directions: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """Whether samples lie in cells the transfer table may show.

        Args:
            cell_origins, cell_directions: ``[A, 3]`` rays from :meth:`cell_rays`.
            t: ``[A, K]`` ray parameters of the samples.

        Returns:
            ``[A, K]`` bool.
        """
        cell = cell_origins[:, None, :] + t[..., None] * cell_directions[:, None, :]  # [A, K, 3]
        cell = torch.minimum(cell.clamp_(min=0.0), self._last).to(torch.int64)  # floor: all >= 0
        return self._flat[(cell * self._stride).sum(dim=-1)]


def _voxel_ranges(n: int, cells: int) -> list[tuple[int, int]]:
    """Per cell, the half-open voxel range ``[a, b)`` its trilinear values depend on, one voxel of guard."""
    ranges = []
    for c in range(cells):
        lo = c * (n - 1) / cells
        hi = (c + 1) * (n - 1) / cells
        a = max(0, int(lo) - 1)
        b = min(n, int(-(-hi // 1)) + 2)  # ceil(hi) + 1, exclusive end
        ranges.append((a, b))
    return ranges

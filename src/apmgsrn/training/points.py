"""Where a training batch looks at the volume: uniform points with trilinear targets, voxels, or a mix.

docs/method.md §4 draws points uniformly in the domain and takes the trilinearly interpolated volume there as
the target. The data, though, are the voxels, and PSNR, maximum error, decoded volumes and compression
ratios are all measured on them. :func:`draw_batch` can give a fraction of each batch at voxel positions
(their exact values, no interpolation): the network then fits the samples it is judged on, while the
uniform rest keeps it close to the trilinear interpolant between them, which is what renders ray-march.
docs/models.md ("Voxel points") has the measurements behind the model defaults.

:class:`ErrorGuide` draws voxel points where the model is wrong rather than uniformly: in proportion to its
absolute error, measured now and then. A series' step fine-tuned from its neighbour's grids is wrong mostly
where the data moved, and there it learns fastest (docs/time_series.md).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch

from apmgsrn.io.description import DescriptionError
from apmgsrn.ops.sorted_search_cpu import LIBRARY as SEARCH_LIBRARY
from apmgsrn.ops.sorted_search_cpu import ascending_search_cpu, guided_voxels_cpu
from apmgsrn.ops.trilinear import axis_coordinates, sample_volume
from apmgsrn.recipes import RUNTIME, VOLUME


def voxel_count(batch: int, fraction: float) -> int:
    """Points of a batch of ``batch`` that sit on voxels when a ``fraction`` of it should."""
    return min(batch, round(batch * fraction))


class ErrorGuide:
    """Voxel draws in proportion to the model's absolute error.

    :meth:`measure` evaluates the model at every voxel of a volume of at most ``pool`` voxels, else at
    one random voxel of every block of ``b^3`` (the smallest ``b`` that leaves at most that many blocks), and
    keeps the errors (with ``parts`` > 1, after the first time, at one of ``parts`` interleaved parts of them
    in turn: ``parts`` times cheaper, the rest as last measured); :meth:`draw` then gives voxel indices, each
    voxel (or block) about ``count * error / total error`` times (systematic sampling: one random offset, the
    voxels in memory order, so the batch is spread over the volume and a voxel of large error is drawn at every
    draw), a block's draws each at a voxel drawn at random inside it, so that every voxel of a block that is
    wrong is fitted, not only the one measured. Voxels the model already fits exactly are not drawn; the
    trainer's uniform points keep the whole domain in every batch.
    """

    def __init__(self, volume: torch.Tensor, parts: int = 1, pool: int = VOLUME.error_pool):
        self.volume = volume
        self.parts = parts
        d, h, w = volume.shape
        self.block = 1
        while math.ceil(d / self.block) * math.ceil(h / self.block) * math.ceil(w / self.block) > pool:
            self.block += 1
        self.blocks = tuple(math.ceil(n / self.block) for n in (d, h, w))
        self.block_count = math.prod(self.blocks)
        self.cumulative: torch.Tensor | None = None  # [P] the blocks' errors' running sum, normalised to end at 1
        self.errors: torch.Tensor | None = None  # [P] float64 the blocks' errors as last measured
        self._every_voxel: tuple[torch.Tensor, torch.Tensor] | None = None  # (index, points) when block == 1

    def _voxels(self, block_index: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
        """A voxel (flat index) drawn at random in each of the blocks ``[N]`` (in a block the volume's edge cuts,
        the draws past the edge land on the edge voxel)."""
        if self.block == 1:  # a block is its voxel: its flat index is the voxel's
            return block_index
        d, h, w = self.volume.shape
        _, bh, bw = self.blocks
        corner = (block_index // (bh * bw), block_index // bw % bh, block_index % bw)
        offset = torch.randint(0, self.block, (3, len(block_index)), generator=generator, device=block_index.device)
        z, y, x = ((c * self.block + o).clamp_max(n - 1) for c, o, n in zip(corner, offset, (d, h, w)))
        return (z * h + y) * w + x

    @torch.no_grad()
    def measure(self, predict: Callable[[torch.Tensor], torch.Tensor], generator: torch.Generator,
                turn: int = 0) -> None:
        """The errors of ``predict`` (``[N, 3]`` points to ``[N]`` values in the volume's units) at the voxels:
        at every one the first time, then, with ``parts`` > 1, at part ``turn % parts`` of them only (every
        ``parts``-th voxel or block in memory order), the others keeping the errors they were last measured at."""
        device = self.volume.device
        if self.block == 1 and self._every_voxel is not None:  # every voxel, in memory order: always the same
            index, points = self._every_voxel
        else:
            index = self._voxels(torch.arange(self.block_count, device=device), generator)
            points = voxel_points(index, self.volume.shape)
            if self.block == 1:
                self._every_voxel = index, points
        part = slice(None) if self.errors is None or self.parts == 1 else slice(turn % self.parts, None, self.parts)
        index, points = index[part], points[part]
        # on a CPU a chunk's hidden activations stay in cache
        chunk = RUNTIME.cpu_measure_chunk if device.type == "cpu" else 1 << 16
        error = torch.cat([(predict(chunk_points).view(-1) - self.volume.reshape(-1)[chunk_index]).abs()
                           for chunk_points, chunk_index in zip(points.split(chunk), index.split(chunk))]).double()
        if part == slice(None):
            self.errors = error
        else:
            self.errors[part] = error
        cumulative = self.errors.cumsum(0)
        if not float(cumulative[-1]) > 0:  # fitted exactly everywhere measured: draw uniformly
            cumulative = torch.arange(1, self.block_count + 1, device=device, dtype=torch.float64)
        self.cumulative = cumulative / cumulative[-1]

    def restore(self, cumulative: torch.Tensor, errors: torch.Tensor | None = None) -> None:
        """Take a measurement saved with a training checkpoint (``cumulative`` and, measured in parts,
        ``errors``, as :meth:`measure` leaves them).

        Raises:
            DescriptionError: values that are not a running sum from 0 to 1, or errors that are not finite and
                at least 0 (a damaged checkpoint).
        """
        if not (bool(torch.isfinite(cumulative).all()) and bool((cumulative.diff() >= 0).all())
                and float(cumulative[0]) >= 0 and float(cumulative[-1]) == 1.0):
            raise DescriptionError("error_guide is not a running sum of errors from 0 to 1")
        if errors is not None and not (bool(torch.isfinite(errors).all()) and bool((errors >= 0).all())):
            raise DescriptionError("error_guide_errors are not finite errors of at least 0")
        self.cumulative, self.errors = cumulative, errors

    def voxel_points(self, index: torch.Tensor) -> torch.Tensor:
        """:func:`voxel_points` of the volume's voxels ``index`` ``[N]``: rows of the table of every voxel's
        position where a measurement made one (a gather instead of a dozen operations at every draw)."""
        if self._every_voxel is not None:
            return self._every_voxel[1].index_select(0, index)
        return voxel_points(index, self.volume.shape)

    def draw_voxels(self, count: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`draw`'s ``[count]`` voxel indices with their points ``[count, 3]`` and values ``[count]``: on a
        CPU in one pass (:func:`apmgsrn.ops.sorted_search_cpu.guided_voxels_cpu`, the same numbers to the bit
        from the same random draws), elsewhere through :meth:`draw` and :meth:`voxel_points`."""
        if self.cumulative is None:
            raise RuntimeError("ErrorGuide.draw before measure")
        if (self.volume.device.type == "cpu" and self.volume.dtype == torch.float32
                and self.cumulative.dtype == torch.float64 and SEARCH_LIBRARY.available()):
            offset = torch.rand((), generator=generator, dtype=torch.float64)
            offsets = (torch.randint(0, self.block, (3, count), generator=generator)
                       if self.block > 1 else None)
            return guided_voxels_cpu(self.cumulative, float(offset), count, self.block, self.volume, offsets)
        index = self.draw(count, generator)
        return index, self.voxel_points(index), self.volume.reshape(-1)[index]

    def draw(self, count: int, generator: torch.Generator) -> torch.Tensor:
        """``[count]`` voxel indices (flat) drawn in proportion to the measured errors."""
        if self.cumulative is None:
            raise RuntimeError("ErrorGuide.draw before measure")
        offset = torch.rand((), generator=generator, device=self.volume.device, dtype=torch.float64)
        # Draw j lands in the first block whose running sum reaches (j + 1 - offset) / count: searched (on a CPU in
        # one walk through the running sum, the draws ascending), not tensor operations over every block (4.7x
        # slower on 2^18 voxels, 8,192 draws, than a search per draw).
        positions = (torch.arange(1, count + 1, device=offset.device, dtype=torch.float64) - offset) / count
        blocks = search_ascending(self.cumulative, positions).clamp_max(self.block_count - 1)
        return self._voxels(blocks, generator)


def search_sorted(sorted_values: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """``torch.searchsorted(sorted_values, queries)`` (the first position whose value is not below each query);
    on a CPU through NumPy, whose search starts each query where the last ended when the queries ascend, as
    a guide's draws do: 0.34 ms against 0.62 for 8,192 draws among 2^18 voxels, the same indices."""
    if sorted_values.device.type != "cpu":
        return torch.searchsorted(sorted_values, queries)
    return torch.from_numpy(np.searchsorted(sorted_values.numpy(), queries.numpy()))


def search_ascending(sorted_values: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """:func:`search_sorted` for ascending ``queries`` (a guide's draws): on a CPU one merge walk through the
    sorted values in C where the kernel builds (:mod:`apmgsrn.ops.sorted_search_cpu`: 0.16 against 0.37 ms for
    6,144 draws among 2^18 voxels, the same indices), else :func:`search_sorted`."""
    if (sorted_values.device.type == "cpu" and sorted_values.dtype == queries.dtype == torch.float64
            and SEARCH_LIBRARY.available()):
        return ascending_search_cpu(sorted_values, queries)
    return search_sorted(sorted_values, queries)


def voxel_points(index: torch.Tensor, shape: tuple[int, int, int]) -> torch.Tensor:
    """Positions ``[N, 3]`` (x, y, z in ``[-1, 1]``) of flat voxel indices ``[N]`` of a ``(D, H, W)`` volume."""
    _, h, w = shape
    z, y, x = index // (h * w), index // w % h, index % w
    return torch.stack([axis_coordinates(x, w), axis_coordinates(y, h), axis_coordinates(z, shape[0])], dim=1)


def draw_batch(
    volume: torch.Tensor, count: int, voxel_fraction: float, generator: torch.Generator,
    guide: ErrorGuide | None = None, guided_share: float = 0.0,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Training points ``[count, 3]`` in ``[-1, 1]^3`` and their targets ``[count]``.

    Args:
        volume: ``[D, H, W]`` values (corner-aligned: voxel ``i`` of ``n`` at ``-1 + 2 i / (n - 1)``).
        count: points to draw.
        voxel_fraction: share of the points drawn at voxel positions (uniformly over the voxels, with the
            voxel's value as target); the others are uniform in the domain with trilinear targets. 0 draws
            exactly what docs/method.md §4 (and every version before this option) draws.
        generator: the trainer's generator (same seed, same batches).
        guide: where the voxel points of ``guided_share`` come from (measured already), the others uniform.
        guided_share: share of the voxel points drawn by ``guide``.
    """
    on_voxels = voxel_count(count, voxel_fraction)
    uniform = torch.rand(count - on_voxels, 3, generator=generator, device=volume.device) * 2 - 1
    if on_voxels == 0:
        return uniform, sample_volume(volume, uniform)
    d, h, w = volume.shape
    guided = voxel_count(on_voxels, guided_share) if guide is not None else 0
    index = torch.randint(0, d * h * w, (on_voxels - guided,), generator=generator, device=volume.device)
    voxels = voxel_points(index, volume.shape) if guide is None else guide.voxel_points(index)
    if not guided:
        return torch.cat([voxels, uniform]), torch.cat([volume.reshape(-1)[index], sample_volume(volume, uniform)])
    _, guided_points, guided_values = guide.draw_voxels(guided, generator)
    points = torch.cat([guided_points, voxels, uniform])
    targets = torch.cat([guided_values, volume.reshape(-1)[index], sample_volume(volume, uniform)])
    return points, targets


def spatially_ordered(
    points: torch.Tensor, targets: torch.Tensor, cells: int = 64
) -> tuple[torch.Tensor, torch.Tensor]:
    """The batch's points ``[B, 3]`` and targets ``[B]`` reordered by the cell of a ``cells^3`` lattice they fall
    in (z, then y, then x; a stable sort, so the same batch always gives the same order).

    Neighbouring points then read neighbouring rows of large feature tables, which saves cache misses in
    the encoder's forward and backward. The loss is a mean over the batch, so only the order of its sums
    changes.
    """
    cell = ((points.clamp(-1, 1) + 1) * (0.5 * (cells - 1))).round().long()  # [B, 3] (x, y, z)
    key = (cell[:, 2] * cells + cell[:, 1]) * cells + cell[:, 0]  # [B]
    order = torch.argsort(key, stable=True)
    return points[order], targets[order]

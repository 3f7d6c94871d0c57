"""Split a volume into a grid of overlapping bricks (docs/method.md §6). Pure: shapes in, boxes out.

Axis conventions: the user types the brick counts ``I,J,K`` along ``x, y, z`` (as for every shape on the
command line), bricks are numbered ``i + I j + I J k``, and voxel boxes are stored in the volume's C order
``(z, y, x)`` so that ``volume.read(*brick.slices())`` reads exactly one brick.
"""

from __future__ import annotations

from dataclasses import dataclass

from apmgsrn.arguments import check_int
from apmgsrn.errors import ApmgsrnError, InvalidArgument


@dataclass(frozen=True)
class DecompositionConfig:
    """How to cut a volume into bricks.

    Attributes:
        bricks: brick counts ``(I, J, K)`` along ``(x, y, z)``.
        ghost_cells: voxels each brick reaches into its neighbours beyond the one shared border voxel
            (paper default 1; 16 hides seams at a cost of about 1 dB).
        blend: at inference, blend neighbouring bricks across their shared ghost region instead of
            routing every point to exactly one brick.
    """

    bricks: tuple[int, int, int] = (2, 2, 2)
    ghost_cells: int = 1
    blend: bool = False

    def __post_init__(self) -> None:
        if len(self.bricks) != 3:
            raise InvalidArgument(f"bricks={self.bricks!r}: must be three brick counts (x, y, z)",
                                  arguments=("bricks",))
        object.__setattr__(self, "bricks", tuple(check_int("bricks", n, 1) for n in self.bricks))
        check_int("ghost_cells", self.ghost_cells, 0)


@dataclass(frozen=True)
class Brick:
    """One brick: its place in the brick grid and its voxel box (ghost cells included).

    Attributes:
        index: flat index ``i + I j + I J k``.
        position: ``(i, j, k)`` along ``(x, y, z)``.
        start: first voxel of the box, ``(z, y, x)``.
        stop: one past the last voxel of the box, ``(z, y, x)``.
        core_start: first voxel this brick owns without ghost cells, ``(z, y, x)``.
        core_stop: one past the last voxel it owns, ``(z, y, x)``.
    """

    index: int
    position: tuple[int, int, int]
    start: tuple[int, int, int]
    stop: tuple[int, int, int]
    core_start: tuple[int, int, int]
    core_stop: tuple[int, int, int]

    @property
    def name(self) -> str:
        """``brick_III_JJJ_KKK`` (x, y, z): the name in messages and of the brick's model file."""
        i, j, k = self.position
        return f"brick_{i:03d}_{j:03d}_{k:03d}"

    @property
    def shape(self) -> tuple[int, int, int]:
        """``(D, H, W)`` of the box, ghost cells included."""
        return tuple(b - a for a, b in zip(self.start, self.stop))

    @property
    def voxels(self) -> int:
        d, h, w = self.shape
        return d * h * w

    def slices(self) -> tuple[slice, slice, slice]:
        """``(z, y, x)`` slices of the box, for :meth:`apmgsrn.data.Volume.read`."""
        return tuple(slice(a, b) for a, b in zip(self.start, self.stop))


@dataclass(frozen=True)
class BrickPlan:
    """The bricks of one volume.

    Attributes:
        volume_shape: ``(D, H, W)`` of the whole volume.
        config: the decomposition asked for.
        bricks: every brick, in flat-index order.
    """

    volume_shape: tuple[int, int, int]
    config: DecompositionConfig
    bricks: tuple[Brick, ...]

    @property
    def counts(self) -> tuple[int, int, int]:
        """Brick counts ``(I, J, K)`` along ``(x, y, z)``."""
        return self.config.bricks

    def __len__(self) -> int:
        return len(self.bricks)

    def by_name(self, name: str) -> Brick:
        for brick in self.bricks:
            if brick.name == name:
                return brick
        raise KeyError(name)


def axis_ranges(n: int, count: int, ghost_cells: int) -> list[tuple[int, int, int, int]]:
    """Voxel ranges of ``count`` bricks along an axis of ``n`` voxels.

    Brick ``i`` owns ``[floor(i n / count), floor((i + 1) n / count))`` and its box reaches ``g = ghost + 1``
    voxels further on each side (clipped): the extra voxel makes neighbours share their border voxels,
    so every point the router sends to a brick lies inside the box the brick was trained on.

    Args:
        n: voxels along the axis.
        count: bricks along the axis.
        ghost_cells: ghost cells per side.

    Returns:
        ``[(box_start, box_stop, core_start, core_stop)]`` per brick, stops exclusive.
    """
    reach = ghost_cells + 1
    ranges = []
    for i in range(count):
        core_start, core_stop = (i * n) // count, ((i + 1) * n) // count
        ranges.append((max(core_start - reach, 0), min(core_stop + reach, n), core_start, core_stop))
    return ranges


def plan_bricks(volume_shape: tuple[int, int, int], config: DecompositionConfig, source: str = "") -> BrickPlan:
    """Cut a ``(D, H, W)`` volume into ``I x J x K`` bricks.

    Args:
        volume_shape: ``(D, H, W)`` of the volume.
        config: brick counts (x, y, z) and ghost cells.
        source: the volume file, for messages.

    Returns:
        The plan, bricks in flat-index order ``i + I j + I J k``.

    Raises:
        ApmgsrnError: more bricks along an axis than that axis has voxels.
    """
    depth, height, width = (int(n) for n in volume_shape)
    counts_xyz = config.bricks
    sizes_xyz = (width, height, depth)
    for axis, count, n in zip("xyz", counts_xyz, sizes_xyz):
        if count > n:
            where = f"{source}: " if source else ""
            raise ApmgsrnError(
                f"{where}{count} bricks along {axis} but the volume has only {n} voxels there; "
                f"choose at most {n} bricks along {axis} in bricks=", arguments=("bricks",),
            )
    ranges_x, ranges_y, ranges_z = (axis_ranges(n, c, config.ghost_cells) for n, c in zip(sizes_xyz, counts_xyz))
    bricks = []
    count_x, count_y, _ = counts_xyz
    for k, rz in enumerate(ranges_z):
        for j, ry in enumerate(ranges_y):
            for i, rx in enumerate(ranges_x):
                bricks.append(
                    Brick(
                        index=i + count_x * j + count_x * count_y * k,
                        position=(i, j, k),
                        start=(rz[0], ry[0], rx[0]),
                        stop=(rz[1], ry[1], rx[1]),
                        core_start=(rz[2], ry[2], rx[2]),
                        core_stop=(rz[3], ry[3], rx[3]),
                    )
                )
    return BrickPlan((depth, height, width), config, tuple(bricks))

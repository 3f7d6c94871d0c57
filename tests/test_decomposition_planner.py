"""Brick planning and routing: bricks tile the volume, routed points land in their brick's box, the
routed and blended brick model reproduce analytic fields exactly, and each brick runs once per batch."""

import itertools

import pytest
import torch
from torch import nn

from apmgsrn.decomposition.bricked_field import BrickedField
from apmgsrn.decomposition.planner import DecompositionConfig, axis_ranges, plan_bricks
from apmgsrn.errors import ApmgsrnError
from apmgsrn.ops.trilinear import voxel_coordinates

SHAPES_AND_GRIDS = [
    ((64, 64, 64), (2, 2, 2), 1),
    ((48, 240, 640), (4, 3, 2), 0),  # the channel volume's (z, y, x), uneven splits
    ((7, 11, 5), (5, 3, 2), 2),  # bricks of one or two voxels, ghost reach beyond the volume
]


@pytest.mark.parametrize("shape, grid, ghost", SHAPES_AND_GRIDS)
def test_bricks_tile_the_volume_exactly(shape, grid, ghost):
    plan = plan_bricks(shape, DecompositionConfig(grid, ghost))
    assert len(plan) == grid[0] * grid[1] * grid[2]
    owned = torch.zeros(shape, dtype=torch.int32)
    for brick in plan.bricks:
        i, j, k = brick.position
        assert brick.index == i + grid[0] * j + grid[0] * grid[1] * k
        core = tuple(slice(a, b) for a, b in zip(brick.core_start, brick.core_stop))
        owned[core] += 1
        for axis in range(3):
            reach = ghost + 1
            assert brick.start[axis] == max(brick.core_start[axis] - reach, 0)
            assert brick.stop[axis] == min(brick.core_stop[axis] + reach, shape[axis])
    assert bool((owned == 1).all()), "every voxel belongs to exactly one brick core"


def test_neighbours_share_border_voxels_even_without_ghost_cells():
    (a0, b0, _, c0), (a1, b1, c1, _) = axis_ranges(10, 2, 0)
    assert c0 == c1 == 5
    assert b0 > a1, "the boxes overlap"
    assert b0 - a1 == 2  # one shared voxel on each side of the cut


def test_more_bricks_than_voxels_is_refused():
    with pytest.raises(ApmgsrnError, match="choose at most 3 bricks along y in bricks="):
        plan_bricks((8, 3, 8), DecompositionConfig((2, 4, 2), 1), "data.raw")


class LinearBrick(nn.Module):
    """Stands in for a trained brick: returns ``f`` of the *global* point it is asked about, computed
    from the local coordinate through the brick's own box (so a wrong map gives a wrong value)."""

    def __init__(self, brick, volume_shape, offset=0.0):
        super().__init__()
        self.low = torch.tensor(list(reversed(brick.start)), dtype=torch.float64)
        self.high = torch.tensor([s - 1 for s in reversed(brick.stop)], dtype=torch.float64)
        self.extent = torch.tensor([n - 1 for n in reversed(volume_shape)], dtype=torch.float64)
        self.offset = offset
        self.value_min, self.value_max = 0.0, 1.0
        self.calls = 0
        self.anchor = nn.Parameter(torch.zeros(1))  # gives the module a device

    def forward(self, local):
        self.calls += 1
        assert bool((local.abs() <= 1 + 1e-6).all()), "brick asked outside its box"
        voxel = self.low + (local.double() + 1) / 2 * (self.high - self.low)
        global_point = voxel / self.extent * 2 - 1
        return (linear(global_point) + self.offset).float()[:, None]


def voxel_points(shape, count):
    """Coordinates of ``count`` random voxels (exact voxel positions, where brick borders fall)."""
    extent = torch.tensor([n - 1 for n in reversed(shape)], dtype=torch.float32)
    index = (torch.rand(count, 3) * (extent + 1)).floor()
    return index / extent * 2 - 1


def linear(points):
    return 0.5 + 2 * points[:, 0] - 3 * points[:, 1] + 0.25 * points[:, 2]


@pytest.mark.parametrize("shape, grid, ghost", SHAPES_AND_GRIDS)
@pytest.mark.parametrize("blend", [False, True])
def test_routing_and_local_maps_reproduce_a_field_exactly(shape, grid, ghost, blend):
    plan = plan_bricks(shape, DecompositionConfig(grid, ghost))
    model = BrickedField(plan, [LinearBrick(b, shape) for b in plan.bricks], blend=blend)
    points = torch.cat([torch.rand(5000, 3) * 2 - 1, voxel_points(shape, 5000)])
    torch.testing.assert_close(model(points)[:, 0].double(), linear(points.double()), atol=2e-5, rtol=1e-5)


def test_routed_points_lie_in_their_bricks_box():
    shape, grid = (33, 20, 17), (3, 4, 2)
    plan = plan_bricks(shape, DecompositionConfig(grid, 1))
    model = BrickedField(plan, [LinearBrick(b, shape) for b in plan.bricks])
    points = voxel_coordinates(shape)
    index = model.brick_index(points)
    # Spec formula per axis, then i + I j + I J k.
    expected_axes = [((points[:, a] + 1) / 2 * grid[a]).clamp(0, grid[a] - 1).floor().long() for a in range(3)]
    expected = expected_axes[0] + grid[0] * expected_axes[1] + grid[0] * grid[1] * expected_axes[2]
    assert torch.equal(index, expected)
    voxel = ((points + 1) / 2 * torch.tensor([16.0, 19.0, 32.0])).round().long()  # (x, y, z) voxel indices
    for brick in plan.bricks:
        mine = voxel[index == brick.index]
        for axis, zyx in ((0, 2), (1, 1), (2, 0)):
            assert bool((mine[:, axis] >= brick.start[zyx]).all() and (mine[:, axis] < brick.stop[zyx]).all())


def test_each_brick_runs_once_per_batch_and_empty_bricks_not_at_all():
    shape = (32, 32, 32)
    plan = plan_bricks(shape, DecompositionConfig((2, 2, 2), 1))
    bricks = [LinearBrick(b, shape) for b in plan.bricks]
    model = BrickedField(plan, bricks)
    points = torch.rand(20000, 3) * 2 - 1
    points[:, 2] = -points[:, 2].abs()  # only the lower z half: bricks k = 1 get nothing
    model(points)
    assert [b.calls for b in bricks] == [1, 1, 1, 1, 0, 0, 0, 0]


def test_blending_makes_the_brick_border_continuous():
    # Bricks that disagree by a constant (as trained bricks do a little): routing jumps at the border,
    # blending ramps across the shared region.
    shape = (8, 8, 64)
    plan = plan_bricks(shape, DecompositionConfig((2, 1, 1), 1))
    bricks = [LinearBrick(b, shape, offset=10.0 * b.index) for b in plan.bricks]
    x = torch.linspace(-0.3, 0.3, 6001)
    points = torch.stack([x, torch.zeros_like(x), torch.zeros_like(x)], 1)
    routed = BrickedField(plan, bricks, blend=False)(points)[:, 0]
    blended = BrickedField(plan, bricks, blend=True)(points)[:, 0]
    step = float(x[1] - x[0])
    slope = 2.0  # d linear / dx
    assert float(routed.diff().abs().max()) > 9.0
    # Ramp across the 3-voxel overlap (ghost 1): 10 over 3 voxels of 2/63 each.
    ramp = 10.0 / (3 * 2 / 63)
    assert float(blended.diff().abs().max()) <= (slope + ramp) * step * 1.01
    # Away from the overlap both agree with the bricks' own values.
    far = x.abs() > 0.1
    torch.testing.assert_close(routed[far], blended[far])


def test_brick_counts_along_x_y_z_follow_the_command_line_order():
    plan = plan_bricks((10, 20, 40), DecompositionConfig((4, 2, 1), 0))
    widths = {b.position: b.shape for b in plan.bricks}
    assert set(itertools.product(range(4), range(2), range(1))) == set(widths)
    assert all(shape[2] < 40 and shape[1] < 20 and shape[0] == 10 for shape in widths.values())

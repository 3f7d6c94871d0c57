"""The brick model as one field: route each point to its brick's network (docs/method.md §6).

Routing is vectorised: a batch of points is sorted by brick, each brick's network runs once on its
contiguous run of points, and the values are scattered back. No Python loop touches single points;
the only loop is over the bricks that received points in the batch.
"""

from __future__ import annotations

import torch
from torch import nn

from apmgsrn.decomposition.planner import BrickPlan


class BrickedField(nn.Module):
    """Maps points ``[N, 3]`` in ``[-1, 1]^3`` to values ``[N, 1]`` in data units with one network per brick.

    Without blending, point ``p`` goes to brick ``floor(clamp((p + 1) / 2 * I, 0, I - 1))`` per axis
    (flat index ``i + I j + I J k``) and is evaluated in that brick's own corner-aligned ``[-1, 1]^3``.
    With ``blend`` set, points inside the region two neighbours share (their ghost cells plus the common
    border voxel) take a weighted mean of both networks; each weight falls linearly from 1 to 0 across
    the overlap and reaches 0 exactly at the edge of the brick's box, so values are continuous across
    brick borders (no seam) and every network is only asked where it was trained.

    Args:
        plan: the bricks (their boxes give each brick's coordinate map).
        fields: one module per brick, in flat-index order, each ``[N, 3] -> [N, 1]`` in data units over
            its own box.
        blend: start with blending on (the ``blend`` attribute may be changed later).

    Attributes:
        plan, blend, volume_shape ``(D, H, W)``, value_min, value_max (data units, over all bricks).
    """

    def __init__(self, plan: BrickPlan, fields: list[nn.Module], blend: bool = False):
        super().__init__()
        if len(fields) != len(plan.bricks):
            raise ValueError(f"{len(plan.bricks)} bricks need {len(plan.bricks)} fields, got {len(fields)}")
        self.plan = plan
        self.blend = bool(blend)
        self.bricks = nn.ModuleList(fields)
        self.volume_shape = tuple(plan.volume_shape)
        self.value_min = float(min(f.value_min for f in fields))
        self.value_max = float(max(f.value_max for f in fields))

        depth, height, width = plan.volume_shape
        sizes = [width, height, depth]  # x, y, z
        counts = list(plan.counts)  # x, y, z
        self.register_buffer("counts", torch.tensor(counts, dtype=torch.long), persistent=False)
        self.register_buffer("extent", torch.tensor([n - 1 for n in sizes], dtype=torch.float32), persistent=False)

        # Per brick: local = p * scale + offset maps global [-1, 1] onto the brick box's own corner-aligned
        # [-1, 1]. With box voxels [a, b] (inclusive) of an axis of n voxels, global p sits at voxel
        # (p + 1) (n - 1) / 2, so scale = (n - 1) / (b - a) and offset = (n - 1 - 2 a) / (b - a) - 1.
        scales, offsets = [], []
        for brick in plan.bricks:
            low = list(reversed(brick.start))  # x, y, z
            high = [s - 1 for s in reversed(brick.stop)]
            scales.append([(n - 1) / (b - a) for n, a, b in zip(sizes, low, high)])
            offsets.append([(n - 1 - 2 * a) / (b - a) - 1 for n, a, b in zip(sizes, low, high)])
        self.register_buffer("brick_scales", torch.tensor(scales, dtype=torch.float32), persistent=False)  # [B, 3]
        self.register_buffer("brick_offsets", torch.tensor(offsets, dtype=torch.float32), persistent=False)

        # Per axis and brick position: box [low, high] in voxels, and the widths of the ramps shared with
        # the previous and next brick (the overlap of the two boxes); a missing neighbour has no ramp.
        longest = max(counts)
        low_table = torch.zeros(3, longest)
        high_table = torch.zeros(3, longest)
        for axis in range(3):
            zyx = 2 - axis
            by_position = {}
            for brick in plan.bricks:
                by_position.setdefault(brick.position[axis], (brick.start[zyx], brick.stop[zyx] - 1))
            for position, (a, b) in by_position.items():
                low_table[axis, position], high_table[axis, position] = a, b
        self.register_buffer("box_low", low_table, persistent=False)  # [3, max count]
        self.register_buffer("box_high", high_table, persistent=False)
        # Where a brick is alone (no neighbour's weight): from the previous brick's box end to the next
        # brick's box start; empty for bricks thinner than their overlaps.
        solo_low = torch.full((3, longest), -float("inf"))
        solo_high = torch.full((3, longest), float("inf"))
        for axis in range(3):
            solo_low[axis, 1 : counts[axis]] = high_table[axis, : counts[axis] - 1]
            solo_high[axis, : counts[axis] - 1] = low_table[axis, 1 : counts[axis]]
        self.register_buffer("solo_low", solo_low, persistent=False)
        self.register_buffer("solo_high", solo_high, persistent=False)

    # ------------------------------------------------------------------------------------------ routing
    def route(self, points: torch.Tensor) -> torch.Tensor:
        """Brick position ``(i, j, k)`` of each point, docs/method.md §6.

        Args:
            points: ``[N, 3]`` global ``(x, y, z)``.

        Returns:
            ``[N, 3]`` long.
        """
        counts = self.counts.to(points.dtype)
        scaled = ((points + 1) * 0.5 * counts).clamp(min=0)
        return torch.minimum(scaled, counts - 1).floor().long()

    def brick_index(self, points: torch.Tensor) -> torch.Tensor:
        """Flat brick index ``i + I j + I J k`` of each point, ``[N]`` long."""
        return self._flat(self.route(points))

    def _flat(self, position: torch.Tensor) -> torch.Tensor:
        count_x, count_y = int(self.counts[0]), int(self.counts[1])
        return position[..., 0] + count_x * position[..., 1] + count_x * count_y * position[..., 2]

    def _local(self, points: torch.Tensor, brick_ids: torch.Tensor) -> torch.Tensor:
        # Clamped: with 0 ghost cells a routed point may sit a fraction of a voxel beyond the box, where
        # the ground truth the brick was fitted to is its border value.
        return (points * self.brick_scales[brick_ids] + self.brick_offsets[brick_ids]).clamp(-1.0, 1.0)

    def _evaluate_grouped(self, local: torch.Tensor, brick_ids: torch.Tensor) -> torch.Tensor:
        """Values ``[P]`` of brick ``brick_ids[q]`` at ``local[q]``, each brick evaluated once."""
        order = torch.argsort(brick_ids)
        counts = torch.bincount(brick_ids, minlength=len(self.bricks)).tolist()  # one host sync per batch
        grouped = local[order]  # [P, 3], bricks contiguous
        outputs = []
        start = 0
        for index, count in enumerate(counts):
            if count:
                outputs.append(self.bricks[index](grouped[start : start + count]).reshape(-1))
                start += count
        values = torch.empty(local.shape[0], dtype=outputs[0].dtype if outputs else local.dtype, device=local.device)
        if outputs:
            values[order] = torch.cat(outputs)
        return values

    # ------------------------------------------------------------------------------------------ forward
    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Values in data units ``[N, 1]`` at ``points`` ``[N, 3]``."""
        if points.shape[0] == 0:
            return torch.empty(0, 1, dtype=points.dtype, device=points.device)
        # A NaN coordinate routes nowhere: the point is evaluated at the origin and answered NaN, as every
        # field answers it (apmgsrn.ops); infinite ones clamp to the outer bricks like any far point.
        nan = torch.isnan(points).any(dim=1)
        points = torch.where(nan[:, None], torch.zeros_like(points), points)
        if self.blend:
            values = self._blended(points)
        else:
            brick_ids = self.brick_index(points)  # [N]
            values = self._evaluate_grouped(self._local(points, brick_ids), brick_ids)
        return torch.where(nan, torch.full_like(values, float("nan")), values)[:, None]

    def axis_weights(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Blend candidates and weights per axis: the routed brick and its two neighbours.

        Args:
            points: ``[N, 3]`` global ``(x, y, z)``.

        Returns:
            ``(positions [N, 3 candidates, 3 axes] long, weights [N, 3, 3])``; weights sum to 1 over the
            candidates of each axis and are 0 for a candidate outside the grid or whose box misses the point.
        """
        points = points.clamp(-1.0, 1.0)
        voxel = (points + 1) * 0.5 * self.extent  # [N, 3] continuous voxel coordinates
        routed = self.route(points)  # [N, 3]
        shifts = torch.tensor([-1, 0, 1], device=points.device)
        candidates = routed[:, None, :] + shifts[None, :, None]  # [N, 3, 3]
        inside = (candidates >= 0) & (candidates < self.counts)
        clipped = torch.minimum(candidates.clamp(min=0), self.counts - 1)
        axes = torch.arange(3, device=points.device).expand_as(clipped)
        low = self.box_low[axes, clipped]  # [N, 3, 3]
        high = self.box_high[axes, clipped]
        has_previous = clipped > 0
        has_next = clipped < self.counts - 1
        # Ramp up across the overlap with the previous brick: from its low end (weight 0) to the previous
        # brick's high end (weight 1); ramp down across the overlap with the next brick likewise.
        previous_high = self.box_high[axes, (clipped - 1).clamp(min=0)]
        next_low = self.box_low[axes, torch.minimum(clipped + 1, self.counts - 1)]
        x = voxel[:, None, :]
        up = torch.where(has_previous, (x - low) / (previous_high - low).clamp(min=1e-6), torch.ones_like(x))
        down = torch.where(has_next, (high - x) / (high - next_low).clamp(min=1e-6), torch.ones_like(x))
        weights = up.clamp(0, 1) * down.clamp(0, 1) * inside * (x >= low) * (x <= high)
        total = weights.sum(1, keepdim=True)  # [N, 1, 3]
        # Degenerate overlaps (bricks thinner than their ghost reach) could leave no weight: fall back
        # to the routed brick alone there.
        empty = total <= 0
        weights = torch.where(empty, (shifts == 0)[None, :, None].to(weights.dtype).expand_as(weights), weights)
        weights = weights / weights.sum(1, keepdim=True)
        return clipped, weights

    def _blended(self, points: torch.Tensor) -> torch.Tensor:
        n = points.shape[0]
        points = points.clamp(-1.0, 1.0)
        # Most points lie where their routed brick is alone: they give one (point, brick, 1) pair; only
        # points in an overlap get the full weights and expand to their 2-8 bricks.
        routed = self.route(points)  # [N, 3]
        voxel = (points + 1) * 0.5 * self.extent
        axes = torch.arange(3, device=points.device).expand_as(routed)
        alone = ((voxel >= self.solo_low[axes, routed]) & (voxel <= self.solo_high[axes, routed])).all(dim=1)
        alone_index = alone.nonzero(as_tuple=True)[0]
        shared_index = (~alone).nonzero(as_tuple=True)[0]
        pp, pw = self.axis_weights(points[shared_index])  # [S, 3 candidates, 3 axes]
        s = shared_index.shape[0]
        combined = (pw[:, :, None, None, 0] * pw[:, None, :, None, 1] * pw[:, None, None, :, 2]).reshape(s, 27)
        ids = self._flat(torch.stack(torch.broadcast_tensors(
            pp[:, :, None, None, 0], pp[:, None, :, None, 1], pp[:, None, None, :, 2]), -1)).reshape(s, 27)
        row, combination = (combined > 0).nonzero(as_tuple=True)  # pairs with weight
        point_index = torch.cat([alone_index, shared_index[row]])  # [P]
        brick_ids = torch.cat([self._flat(routed[alone_index]), ids[row, combination]])
        pair_weights = torch.cat([torch.ones(alone_index.shape[0], device=points.device, dtype=combined.dtype),
                                  combined[row, combination]])
        values = self._evaluate_grouped(self._local(points[point_index], brick_ids), brick_ids)  # [P]
        out = torch.zeros(n, dtype=values.dtype, device=points.device)
        return out.index_add_(0, point_index, values * pair_weights.to(values.dtype))

    def parameter_count(self) -> int:
        """Parameters of all bricks together."""
        return sum(p.numel() for p in self.parameters())

    def extra_repr(self) -> str:
        i, j, k = self.plan.counts
        return f"bricks={i}x{j}x{k}, ghost_cells={self.plan.config.ghost_cells}, blend={self.blend}"

"""Where the levels of a multi-level grid encoding live in one flat table (:mod:`apmgsrn.ops.level_grids`).

Shared by the reference and the fused CPU kernel, which both read the table through this layout.
"""

from __future__ import annotations

from dataclasses import dataclass

#: Spatial-hash primes of Instant-NGP (Teschner et al. 2003) that hashed levels use; the first is 1 for cache
#: coherence.
HASH_PRIMES = (1, 2654435761, 805459861)

@dataclass(frozen=True)
class LevelLayout:
    """Shapes of the levels and where each lives in the flat table.

    Attributes:
        resolutions: vertices per axis ``(R_x, R_y, R_z)`` of every level.
        features: features per vertex ``F_l`` of every level.
        hashed: whether a level is hashed (else dense).
        sizes: table rows (vertices or hash slots) of every level; a power of two where hashed,
            ``R_x R_y R_z`` where dense.
    """

    resolutions: tuple[tuple[int, int, int], ...]
    features: tuple[int, ...]
    hashed: tuple[bool, ...]
    sizes: tuple[int, ...]

    def __post_init__(self) -> None:
        n = len(self.resolutions)
        if not (len(self.features) == len(self.hashed) == len(self.sizes) == n):
            raise ValueError("level layout: one resolution, feature count, storage and size per level")
        for res, hashed, size, f in zip(self.resolutions, self.hashed, self.sizes, self.features):
            if len(res) != 3 or min(res) < 2 or f < 1:
                raise ValueError(f"level layout: invalid level {res} x {f}")
            vertices = res[0] * res[1] * res[2]
            if hashed and (size & (size - 1) or size < 1):
                raise ValueError(f"level layout: hashed table size {size} is not a power of two")
            if not hashed and size != vertices:
                raise ValueError(f"level layout: dense level {res} needs {vertices} rows, not {size}")

    @property
    def levels(self) -> int:
        return len(self.resolutions)

    @property
    def offsets(self) -> tuple[int, ...]:
        """First float of every level in the flat table."""
        out, total = [], 0
        for size, f in zip(self.sizes, self.features):
            out.append(total)
            total += size * f
        return tuple(out)

    @property
    def columns(self) -> tuple[int, ...]:
        """First output column of every level."""
        out, total = [], 0
        for f in self.features:
            out.append(total)
            total += f
        return tuple(out)

    @property
    def table_size(self) -> int:
        """Floats in the flat table."""
        return sum(s * f for s, f in zip(self.sizes, self.features))

    @property
    def out_features(self) -> int:
        return sum(self.features)

"""The simplifier interface: a tile's points in, kept core indices in priority order out."""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from model.rules import capped_twins, morton_order, most_twins, voxel_edge_for


@dataclass(frozen=True)
class FillLoss:
    """Where a tile's fill should keep more: each point's curvature loss over the tile's mean, and that mean.

    relative: (n,) >= 0, or None for equal chances; level: the mean absolute loss (K units), which
    makes tiles comparable, so a run can weigh tile against tile as one pass over the scan would."""

    relative: np.ndarray | None
    level: float


@dataclass(frozen=True)
class FillContext:
    """What the whole scan decides for one tile's fill (a pipeline run sets it from every tile's survey).

    Keep weights are 1 + detail_scale * loss.relative (detail_scale: the tile's loss level over the
    scan's); holes are points farther than cover_radius (scan units) from every pick. `kept` is how many
    picks the run keeps (the tile's budget): fill and cover are planned for that prefix, and picks asked
    beyond it (the stitch's seam reserve) come after it, so cutting the reserve never opens a hole.
    `cover_count`: the picks farthest point sampling (model.cover.cover_order) needs to cover the core at
    cover_radius (model.cover; 0: not counted)."""

    loss: FillLoss
    detail_scale: float
    cover_radius: float
    kept: int | None = None
    cover_count: int = 0


@dataclass(frozen=True, eq=False)
class VoxelCounts:
    """A tile's occupied voxels at doubling edges, as a run's survey counted them over its core (voxels
    aligned to its lowest core point): a method that searches a voxel edge for its budget starts there.
    Compared by identity (eq=False), so a job holding it stays hashable, as arrays are not."""

    sizes: np.ndarray  # (levels,) ascending voxel edges, scan units
    counts: np.ndarray  # (levels,) occupied voxels at each

    def edge_for(self, count: int) -> float:
        """About the voxel edge at which the core occupies `count` voxels."""
        return voxel_edge_for(self.counts, self.sizes, count)


@dataclass(frozen=True)
class Tile:
    """A tile as a simplifier sees it: centred xyz of core and halo points, and which are core.

    `centre` is what was subtracted (scan coordinates = xyz + centre), so a method can align a grid
    across tiles; `seed` is the tile's own seed, fixed by the run seed and the tile id; `context`, what
    a run decided for this tile from every tile's survey, and `voxels`, what that survey counted (both None
    for a tile on its own).
    """

    xyz: np.ndarray
    core: np.ndarray
    centre: np.ndarray
    seed: int
    context: FillContext | None = None
    voxels: VoxelCounts | None = None

    @property
    def core_count(self) -> int:
        """How many points the tile owns."""
        return int(self.core.sum())

    @cached_property
    def core_order(self) -> np.ndarray:
        """(c,) the order of the core points (np.flatnonzero(core)) along a Z-order curve: worked out once,
        for the survey's queries, its trial fills and the fill (each a sort of every core point)."""
        return morton_order(self.xyz[self.core])

    @cached_property
    def fill_mask(self) -> np.ndarray | None:
        """(n,) bool: the core points a fill may pick, all but exact twins past the first (by index) at a position,
        or None where the core has no twins (every core point may). A twin adds no shape to the output: a
        scanner's no-return spot of 400,000 returns kept 18,435 of them in a 2M-point scan's default output
        at 0.1 (bench/twins.py), 9 % of the count."""
        core = np.flatnonzero(self.core)
        core_xyz = self.xyz[core]
        if most_twins(core_xyz) <= 1:
            return None
        mask = np.zeros(len(self.xyz), dtype=bool)
        mask[core[capped_twins(core_xyz, 1)]] = True
        return mask

    @property
    def positions(self) -> int:
        """How many core points a fill may pick (fill_mask): the tile's core but for exact twins."""
        return self.core_count if self.fill_mask is None else int(self.fill_mask.sum())

    @cached_property
    def fillable(self) -> np.ndarray:
        """(positions,) ascending indices of the core points a fill or a hole cover may pick (fill_mask)."""
        return np.flatnonzero(self.core if self.fill_mask is None else self.fill_mask)

    @cached_property
    def curve(self) -> np.ndarray:
        """(c,) indices of the core points, in tile order, along the Z-order curve (the survey's trial fills
        and the fill each walk it)."""
        return np.flatnonzero(self.core)[self.core_order]


@dataclass(frozen=True)
class Selection:
    """Kept points: indices into the tile (all core) in priority order, and their (centred) xyz.

    A prefix of the order is a coarser simplification; xyz differs from the source only where a
    method refines positions. Attributes never pass through here: the stitch copies them by index.
    """

    indices: np.ndarray
    xyz: np.ndarray

    @classmethod
    def of(cls, tile: Tile, indices: np.ndarray) -> "Selection":
        """A selection that keeps source positions."""
        indices = np.asarray(indices, dtype=np.int64)
        return cls(indices, tile.xyz[indices])


def topped_up(order: np.ndarray, core: np.ndarray, budget: int, rng: np.random.Generator) -> np.ndarray:
    """`order` (distinct core indices) cut to `budget`, or followed by the other core points in random order
    when it is short: exact duplicates, which neither FPS nor voxels can tell apart, fill the count last."""
    if len(order) >= budget:
        return order[:budget]
    rest = np.setdiff1d(core, order, assume_unique=True)
    return np.concatenate([order, rng.permutation(rest)])[:budget]

"""The simplifier interface: a tile's points in, kept core indices in priority order out."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class Tile:
    """A tile as a simplifier sees it: centred xyz of core and halo points, and which are core.

    `centre` is what was subtracted (scan coordinates = xyz + centre), so a method can align a grid
    across tiles; `seed` is the tile's own seed, fixed by the run seed and the tile id.
    """

    xyz: np.ndarray
    core: np.ndarray
    centre: np.ndarray
    seed: int

    @property
    def core_count(self) -> int:
        """How many points the tile owns."""
        return int(self.core.sum())


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


def kept_count(ratio: float, total: int) -> int:
    """round(ratio * N), halves up, for whole clouds and meshes: tiling.budgets.target_count's rule
    (model may not import tiling)."""
    return min(total, int(np.floor(ratio * total + 0.5)))


class Simplifier(Protocol):
    """Picks `budget` core points of a tile (fewer only if the tile has fewer core points)."""

    def __call__(self, tile: Tile, budget: int) -> Selection: ...


def topped_up(order: np.ndarray, core: np.ndarray, budget: int, rng: np.random.Generator) -> np.ndarray:
    """`order` (distinct core indices) cut to `budget`, or followed by the other core points in random order
    when it is short: exact duplicates, which neither FPS nor voxels can tell apart, fill the count last."""
    if len(order) >= budget:
        return order[:budget]
    rest = np.setdiff1d(core, order, assume_unique=True)
    return np.concatenate([order, rng.permutation(rest)])[:budget]

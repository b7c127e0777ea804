"""The tile plan: a fine XY density grid, tiles made of whole grid cells, split until under a point budget.

Each point falls in exactly one grid cell (floor of its offset, clipped to the grid), and each cell in
at most one tile, so core membership is a half-open partition that floating-point rounding cannot break.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

CELLS_PER_TILE = 8       # a nominal tile is 8x8 cells: three quadtree splits before a tile is one cell
MAX_GRID_CELLS = 2048    # per axis; caps the density grid at 4 M counters whatever the extent


@dataclass(frozen=True)
class DensityGrid:
    """A regular XY grid over the scan's extent; `cell_of` maps coordinates to flat cell ids."""

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, mins: np.ndarray, maxs: np.ndarray, tile_size: float) -> "DensityGrid":
        """A grid of tile_size/8 cells over [mins, maxs], coarsened if the extent would need too many."""
        extent = np.maximum(np.asarray(maxs[:2], float) - np.asarray(mins[:2], float), 0.0)
        cell = max(tile_size / CELLS_PER_TILE, float(extent.max()) / MAX_GRID_CELLS, 1e-9)
        shape = tuple(int(n) for n in np.maximum(np.ceil(extent / cell), 1).astype(int))
        return cls((float(mins[0]), float(mins[1])), cell, shape)

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Flat (row-major, x first) cell id of each point; points past the edges go to the edge cells."""
        ij = np.floor((xy[:, :2] - np.asarray(self.origin)) / self.cell)
        i = np.clip(ij[:, 0], 0, self.shape[0] - 1).astype(np.int64)
        j = np.clip(ij[:, 1], 0, self.shape[1] - 1).astype(np.int64)
        return i * self.shape[1] + j

    def count(self, xy_chunks: Iterable[np.ndarray]) -> np.ndarray:
        """Points per cell, shape (nx, ny), accumulated over a stream of xy chunks."""
        counts = np.zeros(self.shape[0] * self.shape[1], dtype=np.int64)
        for xy in xy_chunks:
            counts += np.bincount(self.cell_of(xy), minlength=counts.size)
        return counts.reshape(self.shape)


@dataclass(frozen=True)
class TileRect:
    """A tile's core: cells [i0, i1) x [j0, j1), and its point count."""

    i0: int
    i1: int
    j0: int
    j1: int
    count: int


@dataclass(frozen=True)
class TilePlan:
    """Tiles in a fixed order (row-major base tiles, then quadtree order), and the cell -> tile lookup."""

    grid: DensityGrid
    tiles: tuple[TileRect, ...]
    cell_tile: np.ndarray  # (nx*ny,) int32 tile id per cell, -1 where no tile (empty cells)

    def tile_of(self, xy: np.ndarray) -> np.ndarray:
        """The id of the tile whose core holds each point."""
        return self.cell_tile[self.grid.cell_of(xy)]

    def bounds(self, tile_id: int) -> tuple[float, float, float, float]:
        """Core rectangle (xmin, ymin, xmax, ymax) in scan coordinates, half-open on the max side."""
        t = self.tiles[tile_id]
        (ox, oy), c = self.grid.origin, self.grid.cell
        return ox + t.i0 * c, oy + t.j0 * c, ox + t.i1 * c, oy + t.j1 * c

    def all_bounds(self) -> np.ndarray:
        """(T, 4) array of every tile's core rectangle."""
        return np.array([self.bounds(t) for t in range(len(self.tiles))], dtype=np.float64).reshape(-1, 4)

    def neighbours(self, overlap: float) -> list[np.ndarray]:
        """For each tile, the other tiles whose cores come within `overlap` of it (its halo sources)."""
        b = self.all_bounds()
        result = []
        for t in range(len(b)):
            near = ((b[:, 0] < b[t, 2] + overlap) & (b[:, 2] > b[t, 0] - overlap)
                    & (b[:, 1] < b[t, 3] + overlap) & (b[:, 3] > b[t, 1] - overlap))
            near[t] = False
            result.append(np.flatnonzero(near))
        return result


def plan_tiles(grid: DensityGrid, counts: np.ndarray, max_points: int) -> TilePlan:
    """Cut the grid into nominal tiles of 8x8 cells, quarter any holding more than max_points, drop empty ones."""
    summed = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1), dtype=np.int64)
    summed[1:, 1:] = counts.cumsum(0).cumsum(1)

    def rect_count(i0: int, i1: int, j0: int, j1: int) -> int:
        return int(summed[i1, j1] - summed[i0, j1] - summed[i1, j0] + summed[i0, j0])

    def split(i0: int, i1: int, j0: int, j1: int) -> list[TileRect]:
        n = rect_count(i0, i1, j0, j1)
        if n == 0:
            return []
        if n <= max_points or (i1 - i0 == 1 and j1 - j0 == 1):
            return [TileRect(i0, i1, j0, j1, n)]
        im, jm = (i0 + i1 + 1) // 2, (j0 + j1 + 1) // 2
        parts = []
        for a0, a1 in ((i0, im), (im, i1)):
            for b0, b1 in ((j0, jm), (jm, j1)):
                if a1 > a0 and b1 > b0:
                    parts += split(a0, a1, b0, b1)
        return parts

    nx, ny = grid.shape
    tiles: list[TileRect] = []
    for i0 in range(0, nx, CELLS_PER_TILE):
        for j0 in range(0, ny, CELLS_PER_TILE):
            tiles += split(i0, min(i0 + CELLS_PER_TILE, nx), j0, min(j0 + CELLS_PER_TILE, ny))
    cell_tile = np.full((nx, ny), -1, dtype=np.int32)
    for tile_id, t in enumerate(tiles):
        cell_tile[t.i0:t.i1, t.j0:t.j1] = tile_id
    return TilePlan(grid, tuple(tiles), cell_tile.ravel())

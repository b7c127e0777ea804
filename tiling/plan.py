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
    """A tile's core: cells [i0, i1) x [j0, j1), its point count and how many of its cells hold points."""

    i0: int
    i1: int
    j0: int
    j1: int
    count: int
    occupied: int


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

    def halo_cell_ranges(self, tile_id: int, overlap: float) -> np.ndarray:
        """Flat cell-id ranges [lo, hi), one per grid row, of every cell within `overlap` of the tile's core."""
        t, ring = self.tiles[tile_id], int(np.ceil(overlap / self.grid.cell))
        nx, ny = self.grid.shape
        i0, i1 = max(t.i0 - ring, 0), min(t.i1 + ring, nx)
        j0, j1 = max(t.j0 - ring, 0), min(t.j1 + ring, ny)
        rows = np.arange(i0, i1, dtype=np.int64) * ny
        return np.column_stack([rows + j0, rows + j1])

    def core_mask(self, tile_id: int, xyz: np.ndarray) -> np.ndarray:
        """Which points the tile owns (tile_of's rule, so ownership has one definition)."""
        return self.tile_of(xyz) == tile_id

    def halo_mask(self, core: np.ndarray, tile_id: int, xyz: np.ndarray, overlap: float) -> np.ndarray:
        """Core points plus those within `overlap` of the core rectangle: what the tile's simplifier sees."""
        x0, y0, x1, y1 = self.bounds(tile_id)
        x, y = xyz[:, 0], xyz[:, 1]
        return core | ((x >= x0 - overlap) & (x < x1 + overlap) & (y >= y0 - overlap) & (y < y1 + overlap))


def plan_tiles(grid: DensityGrid, counts: np.ndarray, max_points: int) -> TilePlan:
    """Cut the grid into nominal tiles of 8x8 cells, quarter any holding more than max_points, drop empty ones."""
    points, cells = summed_table(counts), summed_table(counts > 0)

    def rect_count(i0: int, i1: int, j0: int, j1: int, summed: np.ndarray = points) -> int:
        return int(summed[i1, j1] - summed[i0, j1] - summed[i1, j0] + summed[i0, j0])

    def split(i0: int, i1: int, j0: int, j1: int) -> list[TileRect]:
        n = rect_count(i0, i1, j0, j1)
        if n == 0:
            return []
        if n <= max_points or (i1 - i0 == 1 and j1 - j0 == 1):
            return [TileRect(i0, i1, j0, j1, n, rect_count(i0, i1, j0, j1, cells))]
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


def summed_table(values: np.ndarray) -> np.ndarray:
    """(nx+1, ny+1) int64 summed-area table: any rectangle's total from four look-ups."""
    summed = np.zeros((values.shape[0] + 1, values.shape[1] + 1), dtype=np.int64)
    summed[1:, 1:] = values.astype(np.int64).cumsum(0).cumsum(1)
    return summed

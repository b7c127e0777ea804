"""The tile plan: a fine XY density grid, tiles made of whole grid cells, split until under a point budget.

Each point falls in exactly one grid cell (floor of its offset, clipped to the grid), and each cell in
at most one tile, so core membership is a half-open partition that floating-point rounding cannot break.
The grid is sparse: only occupied cells are counted and looked up, so its cells stay tile_size / 8
whatever the extent (two sites 200 km apart, a 100 km corridor) and tiles stay within the point budget.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

import numpy as np

CELLS_PER_TILE = 8       # a nominal tile is 8x8 cells: three quadtree splits before a tile is one cell
MAX_AXIS_CELLS = 2**31   # per axis, so flat cell ids (i * ny + j) fit int64


@dataclass(frozen=True)
class DensityGrid:
    """A regular XY grid over the scan's extent; `cell_of` maps coordinates to flat cell ids."""

    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]

    @classmethod
    def covering(cls, mins: np.ndarray, maxs: np.ndarray, tile_size: float) -> "DensityGrid":
        """A grid of tile_size/8 cells over [mins, maxs] (only its occupied cells are ever stored)."""
        extent = np.maximum(np.asarray(maxs[:2], float) - np.asarray(mins[:2], float), 0.0)
        cell = max(tile_size / CELLS_PER_TILE, 1e-9)
        cells = np.maximum(np.ceil(extent / cell), 1)
        if (cells > MAX_AXIS_CELLS).any():
            raise ValueError(f"an extent of {extent.max():g} needs more than {MAX_AXIS_CELLS} cells of {cell:g} per axis")
        return cls((float(mins[0]), float(mins[1])), cell, (int(cells[0]), int(cells[1])))

    def cell_of(self, xy: np.ndarray) -> np.ndarray:
        """Flat (row-major, x first) cell id of each point; points past the edges go to the edge cells."""
        ij = np.floor((xy[:, :2] - np.asarray(self.origin)) / self.cell)
        i = np.clip(ij[:, 0], 0, self.shape[0] - 1).astype(np.int64)
        j = np.clip(ij[:, 1], 0, self.shape[1] - 1).astype(np.int64)
        return i * self.shape[1] + j

    def count(self, xy_chunks: Iterable[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """Occupied cells (sorted flat ids) and their point counts, over a stream of xy chunks."""
        parts = [np.unique(self.cell_of(xy), return_counts=True) for xy in xy_chunks]
        return summed_cells([cells for cells, _ in parts], [counts for _, counts in parts])


def summed_cells(cells: list[np.ndarray], counts: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Sorted distinct cell ids and the sum of their counts over several (cells, counts) parts."""
    if not cells:
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    unique, inverse = np.unique(np.concatenate(cells).astype(np.int64), return_inverse=True)
    sums = np.zeros(len(unique), dtype=np.int64)
    np.add.at(sums, inverse, np.concatenate(counts).astype(np.int64))
    return unique, sums


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
    cells: np.ndarray       # (occupied,) sorted flat ids of the occupied cells
    cell_tiles: np.ndarray  # (occupied,) int32 id of the tile holding each

    def tile_of(self, xy: np.ndarray) -> np.ndarray:
        """The id of the tile whose core holds each point (-1 for a point in a cell no tile holds)."""
        ids = self.grid.cell_of(xy)
        if len(self.cells) == 0:
            return np.full(len(ids), -1, dtype=np.int32)
        at = np.minimum(np.searchsorted(self.cells, ids), len(self.cells) - 1)
        return np.where(self.cells[at] == ids, self.cell_tiles[at], -1).astype(np.int32)

    def bounds(self, tile_id: int) -> tuple[float, float, float, float]:
        """Core rectangle (xmin, ymin, xmax, ymax) in scan coordinates, half-open on the max side."""
        t = self.tiles[tile_id]
        (ox, oy), c = self.grid.origin, self.grid.cell
        return ox + t.i0 * c, oy + t.j0 * c, ox + t.i1 * c, oy + t.j1 * c

    def halo_cell_rect(self, tile_id: int, overlap: float) -> tuple[int, int, int, int]:
        """Cells [i0, i1) x [j0, j1) within `overlap` of the tile's core, clipped to the grid."""
        t, ring = self.tiles[tile_id], int(np.ceil(overlap / self.grid.cell))
        nx, ny = self.grid.shape
        return max(t.i0 - ring, 0), min(t.i1 + ring, nx), max(t.j0 - ring, 0), min(t.j1 + ring, ny)

    def halo_cell_ranges(self, tile_id: int, overlap: float) -> np.ndarray:
        """Flat cell-id ranges [lo, hi), one per grid row, of every cell within `overlap` of the tile's core."""
        i0, i1, j0, j1 = self.halo_cell_rect(tile_id, overlap)
        rows = np.arange(i0, i1, dtype=np.int64) * self.grid.shape[1]
        return np.column_stack([rows + j0, rows + j1])

    def core_mask(self, tile_id: int, xyz: np.ndarray) -> np.ndarray:
        """Which points the tile owns (tile_of's rule, so ownership has one definition)."""
        return self.tile_of(xyz) == tile_id

    def halo_mask(self, core: np.ndarray, tile_id: int, xyz: np.ndarray, overlap: float) -> np.ndarray:
        """Core points plus those within `overlap` of the core rectangle: what the tile's simplifier sees."""
        x0, y0, x1, y1 = self.bounds(tile_id)
        x, y = xyz[:, 0], xyz[:, 1]
        return core | ((x >= x0 - overlap) & (x < x1 + overlap) & (y >= y0 - overlap) & (y < y1 + overlap))


def plan_tiles(grid: DensityGrid, cells: np.ndarray, counts: np.ndarray, max_points: int) -> TilePlan:
    """Cut the grid into nominal tiles of 8x8 cells, quarter any holding more than max_points, drop empty ones.

    cells: (occupied,) sorted flat cell ids; counts: their points. Only occupied nominal tiles are visited,
    in row-major order, so the work and memory follow the occupied area, not the extent."""
    nx, ny = grid.shape
    cells, counts = np.asarray(cells, dtype=np.int64), np.asarray(counts, dtype=np.int64)
    keep = counts > 0
    cells, counts = cells[keep], counts[keep]
    i, j = cells // ny, cells % ny
    blocks = (i // CELLS_PER_TILE) * (-(-ny // CELLS_PER_TILE)) + j // CELLS_PER_TILE
    order = np.argsort(blocks, kind="stable")
    starts = np.flatnonzero(np.diff(blocks[order], prepend=-1))
    tiles: list[TileRect] = []
    cell_tiles = np.full(len(cells), -1, dtype=np.int32)
    for members in np.split(order, starts[1:]):
        i0, j0 = int(i[members[0]] // CELLS_PER_TILE * CELLS_PER_TILE), int(j[members[0]] // CELLS_PER_TILE * CELLS_PER_TILE)
        local = np.zeros((min(CELLS_PER_TILE, nx - i0), min(CELLS_PER_TILE, ny - j0)), dtype=np.int64)
        local[i[members] - i0, j[members] - j0] = counts[members]
        for rect in split_block(local, max_points):
            tile = TileRect(rect.i0 + i0, rect.i1 + i0, rect.j0 + j0, rect.j1 + j0, rect.count, rect.occupied)
            inside = (i[members] >= tile.i0) & (i[members] < tile.i1) & (j[members] >= tile.j0) & (j[members] < tile.j1)
            cell_tiles[members[inside]] = len(tiles)
            tiles.append(tile)
    return TilePlan(grid, tuple(tiles), cells, cell_tiles)


def split_block(counts: np.ndarray, max_points: int) -> list[TileRect]:
    """Rectangles (in the block's own cells) covering every non-empty cell of a block's counts, quartered
    while they hold more than max_points, in quadtree order."""
    points, occupied = summed_table(counts), summed_table(counts > 0)

    def rect_count(i0: int, i1: int, j0: int, j1: int, summed: np.ndarray = points) -> int:
        return int(summed[i1, j1] - summed[i0, j1] - summed[i1, j0] + summed[i0, j0])

    def split(i0: int, i1: int, j0: int, j1: int) -> list[TileRect]:
        n = rect_count(i0, i1, j0, j1)
        if n == 0:
            return []
        if n <= max_points or (i1 - i0 == 1 and j1 - j0 == 1):
            return [TileRect(i0, i1, j0, j1, n, rect_count(i0, i1, j0, j1, occupied))]
        im, jm = (i0 + i1 + 1) // 2, (j0 + j1 + 1) // 2
        parts = []
        for a0, a1 in ((i0, im), (im, i1)):
            for b0, b1 in ((j0, jm), (jm, j1)):
                if a1 > a0 and b1 > b0:
                    parts += split(a0, a1, b0, b1)
        return parts

    return split(0, counts.shape[0], 0, counts.shape[1])


def summed_table(values: np.ndarray) -> np.ndarray:
    """(nx+1, ny+1) int64 summed-area table: any rectangle's total from four look-ups."""
    summed = np.zeros((values.shape[0] + 1, values.shape[1] + 1), dtype=np.int64)
    summed[1:, 1:] = values.astype(np.int64).cumsum(0).cumsum(1)
    return summed

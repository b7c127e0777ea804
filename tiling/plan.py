"""The tile plan: a fine XY density grid, tiles made of whole grid cells, split until under a point budget.

Each point falls in exactly one grid cell (floor of its offset, clipped to the grid), and each cell in
at most one tile, so core membership is a half-open partition that floating-point rounding cannot break.
The grid is sparse: only occupied cells are counted and looked up, so its cells stay tile_size / 8
whatever the extent (two sites 200 km apart, a 100 km corridor) and tiles stay within the point budget.
A cell that alone holds more than the budget (a terrestrial scanner's standpoint) is split the same way
on a grid of SUB_CELLS x SUB_CELLS sub-cells, each point's sub-cell found by the same floor rule.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterable

import numpy as np

CELLS_PER_TILE = 8       # a nominal tile is 8x8 cells: three quadtree splits before a tile is one cell
MERGE_SPAN = 4           # sparse nominal tiles merge within aligned squares of 4 x 4 of them (tile size x 4 a side)
MAX_AXIS_CELLS = 2**31   # per axis, so flat cell ids (i * ny + j) fit int64
SUB_CELLS = 64           # a crowded cell is split on 64 x 64 sub-cells (tile_size / 512 a side)
SPLIT = -2               # cell_tiles' mark for a split cell: its sub-cells name the tiles
HALO_SPACINGS = 64       # a halo reaches into a split cell at most this many of the cell's mean point spacings


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
        i, j = self.cell_ij(xy)
        return i * self.shape[1] + j

    def sub_cell_of(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's (i, j) sub-cell (0..SUB_CELLS-1) inside its own cell: the same floor rule, one level down."""
        offset = (xy[:, :2] - np.asarray(self.origin)) / self.cell
        i, j = self.cell_ij(xy)
        si = np.clip(np.floor((offset[:, 0] - i) * SUB_CELLS), 0, SUB_CELLS - 1).astype(np.int64)
        sj = np.clip(np.floor((offset[:, 1] - j) * SUB_CELLS), 0, SUB_CELLS - 1).astype(np.int64)
        return si, sj

    def sub_count(self, xy: np.ndarray, cells: np.ndarray) -> np.ndarray:
        """(len(cells), SUB_CELLS, SUB_CELLS) points of `xy` in each sub-cell of the given sorted cells."""
        ids = self.cell_of(xy)
        at = np.minimum(np.searchsorted(cells, ids), max(len(cells) - 1, 0))
        inside = np.flatnonzero(cells[at] == ids) if len(cells) else np.empty(0, dtype=np.int64)
        si, sj = self.sub_cell_of(xy[inside])
        flat = (at[inside] * SUB_CELLS + si) * SUB_CELLS + sj
        return np.bincount(flat, minlength=len(cells) * SUB_CELLS**2).reshape(len(cells), SUB_CELLS, SUB_CELLS)

    def cell_ij(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Each point's cell row i and column j, an axis at a time (3x faster than on the (n, 2) slice)."""
        i, j = (np.clip(np.floor((xy[:, axis] - self.origin[axis]) / self.cell), 0, self.shape[axis] - 1)
                .astype(np.int64) for axis in (0, 1))
        return i, j

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
    """A tile's core: cells [i0, i1) x [j0, j1), its point count and the grid-cell area its points occupy;
    for part of a split cell, also the sub-cells [si0, si1) x [sj0, sj1) of cell (i0, j0) it holds."""

    i0: int
    i1: int
    j0: int
    j1: int
    count: int
    occupied: float
    sub: tuple[int, int, int, int] | None = None


@dataclass(frozen=True)
class TilePlan:
    """Tiles in a fixed order (row-major base tiles, then quadtree order), and the cell -> tile lookup."""

    grid: DensityGrid
    tiles: tuple[TileRect, ...]
    cells: np.ndarray       # (occupied,) sorted flat ids of the occupied cells
    cell_tiles: np.ndarray  # (occupied,) int32 id of the tile holding each (SPLIT for a split cell)
    split_cells: np.ndarray = field(default_factory=lambda: np.empty(0, dtype=np.int64))  # (k,) sorted flat ids
    sub_tiles: np.ndarray = field(default_factory=lambda: np.empty((0, SUB_CELLS, SUB_CELLS), dtype=np.int32))
    split_reach: np.ndarray = field(default_factory=lambda: np.empty(0))  # (k,) HALO_SPACINGS of each one's spacing

    def tile_of(self, xy: np.ndarray) -> np.ndarray:
        """The id of the tile whose core holds each point (-1 for a point in a cell no tile holds)."""
        ids = self.grid.cell_of(xy)
        if len(self.cells) == 0:
            return np.full(len(ids), -1, dtype=np.int32)
        at = np.minimum(np.searchsorted(self.cells, ids), len(self.cells) - 1)
        tiles = np.where(self.cells[at] == ids, self.cell_tiles[at], -1).astype(np.int32)
        split = np.flatnonzero(tiles == SPLIT)
        if len(split):
            si, sj = self.grid.sub_cell_of(xy[split])
            tiles[split] = self.sub_tiles[np.searchsorted(self.split_cells, ids[split]), si, sj]
        return tiles

    def bounds(self, tile_id: int) -> tuple[float, float, float, float]:
        """Core rectangle (xmin, ymin, xmax, ymax) in scan coordinates, half-open on the max side."""
        t = self.tiles[tile_id]
        (ox, oy), c = self.grid.origin, self.grid.cell
        if t.sub is None:
            return ox + t.i0 * c, oy + t.j0 * c, ox + t.i1 * c, oy + t.j1 * c
        si0, si1, sj0, sj1 = t.sub
        s = c / SUB_CELLS
        return (ox + t.i0 * c + si0 * s, oy + t.j0 * c + sj0 * s, ox + t.i0 * c + si1 * s, oy + t.j0 * c + sj1 * s)

    def budget_groups(self) -> np.ndarray:
        """(tiles,) a group id per tile: the tiles of one split cell share one (their cell's first tile), every
        other tile is its own group (tiling.budgets.grouped_budgets)."""
        groups = np.arange(len(self.tiles))
        first: dict[tuple[int, int], int] = {}
        for tile_id, tile in enumerate(self.tiles):
            if tile.sub is not None:
                groups[tile_id] = first.setdefault((tile.i0, tile.j0), tile_id)
        return groups

    def per_tile(self, per_cell: np.ndarray, per_sub_cell: np.ndarray | None = None) -> np.ndarray:
        """(tiles,) sums of a count given per occupied cell (occupied,) and, for split cells, per sub-cell
        (k, SUB_CELLS, SUB_CELLS): the tiles' share of it."""
        whole = self.cell_tiles >= 0
        totals = np.bincount(self.cell_tiles[whole], weights=np.asarray(per_cell)[whole],
                             minlength=len(self.tiles)).astype(np.float64)  # int64 where no cell is whole
        if per_sub_cell is not None and len(self.split_cells):
            named = self.sub_tiles >= 0
            totals += np.bincount(self.sub_tiles[named], weights=per_sub_cell[named], minlength=len(self.tiles))
        return totals.astype(np.int64)

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

    def halo_sub_rect(self, tile_id: int, cell: int, overlap: float) -> tuple[int, int, int, int]:
        """Sub-cells [si0, si1) x [sj0, sj1) of split cell `cell` (a flat id) that the tile's halo reaches
        (halo_mask), one sub-cell wider on each side than the arithmetic says, so rounding never leaves one out."""
        x0, y0, x1, y1 = self.bounds(tile_id)
        i, j = divmod(cell, self.grid.shape[1])
        (ox, oy), c = self.grid.origin, self.grid.cell
        sub = c / SUB_CELLS
        reach = min(overlap, float(self.split_reach[np.searchsorted(self.split_cells, cell)]))

        def span(lo: float, hi: float, start: float) -> tuple[int, int]:
            first = int(np.clip(np.floor((lo - reach - start) / sub) - 1, 0, SUB_CELLS))
            return first, int(np.clip(np.floor((hi + reach - start) / sub) + 2, first, SUB_CELLS))

        return (*span(x0, x1, ox + i * c), *span(y0, y1, oy + j * c))

    def core_mask(self, tile_id: int, xyz: np.ndarray) -> np.ndarray:
        """Which points the tile owns: tile_of(xyz) == tile_id. A tile of whole cells owns every occupied
        cell in its rectangle (quarters, merged squares and split cells partition the grid), so its mask is
        the points' cell rows and columns tested against that rectangle, without looking each cell up
        (bcts voxel on one worker: 0.39 s of lookups, 0.06 s this way); a tile of sub-cells asks tile_of."""
        t = self.tiles[tile_id]
        if t.sub is not None:
            return self.tile_of(xyz) == tile_id
        i, j = self.grid.cell_ij(xyz)
        return (i >= t.i0) & (i < t.i1) & (j >= t.j0) & (j < t.j1)

    def halo_mask(self, core: np.ndarray, tile_id: int, xyz: np.ndarray, overlap: float) -> np.ndarray:
        """Core points plus those within `overlap` of the core rectangle: what the tile's simplifier sees.
        Of a split cell's points, only those within its `split_reach` (if nearer): its points are so dense
        that `overlap` would hold many times a tile's limit, and their neighbours lie far closer."""
        x0, y0, x1, y1 = self.bounds(tile_id)
        reach: float | np.ndarray = overlap
        if len(self.split_cells):  # a reach per point only where a cell is split (no cost on other scans)
            ids = self.grid.cell_of(xyz)
            at = np.minimum(np.searchsorted(self.split_cells, ids), len(self.split_cells) - 1)
            reach = np.where(self.split_cells[at] == ids, np.minimum(overlap, self.split_reach[at]), overlap)
        x, y = xyz[:, 0], xyz[:, 1]
        return core | ((x >= x0 - reach) & (x < x1 + reach) & (y >= y0 - reach) & (y < y1 + reach))


def plan_tiles(grid: DensityGrid, cells: np.ndarray, counts: np.ndarray, max_points: int,
               sub_counts: np.ndarray | None = None, merge_points: int = 0) -> TilePlan:
    """Cut the grid into nominal tiles of 8x8 cells, quarter any holding more than max_points, drop empty ones.

    cells: (occupied,) sorted flat cell ids; counts: their points. Only occupied nominal tiles are visited,
    in row-major order, so the work and memory follow the occupied area, not the extent. A single cell
    still over max_points is quartered in turn on its sub-cells, where `sub_counts` gives them:
    (crowded, SUB_CELLS, SUB_CELLS) points per sub-cell of each cell in crowded_cells(cells, counts, max_points).
    With `merge_points`, sparse nominal tiles are merged first (merged_blocks): a tile has fixed costs (its
    task, its loads, its trees and files) that a few thousand points do not repay."""
    nx, ny = grid.shape
    cells, counts = np.asarray(cells, dtype=np.int64), np.asarray(counts, dtype=np.int64)
    keep = counts > 0
    cells, counts = cells[keep], counts[keep]
    crowded = crowded_cells(cells, counts, max_points) if sub_counts is not None else np.empty(0, dtype=np.int64)
    i, j = cells // ny, cells % ny
    blocks = (i // CELLS_PER_TILE) * (-(-ny // CELLS_PER_TILE)) + j // CELLS_PER_TILE
    order = np.argsort(blocks, kind="stable")
    starts = np.flatnonzero(np.diff(blocks[order], prepend=-1))
    tiles: list[TileRect] = []
    cell_tiles = np.full(len(cells), -1, dtype=np.int32)
    sub_tiles = np.full((len(crowded), SUB_CELLS, SUB_CELLS), -1, dtype=np.int32)
    block_members = np.split(order, starts[1:]) if len(order) else []
    first = order[starts]  # a cell of each nominal tile
    block_ij = np.column_stack([i[first] // CELLS_PER_TILE, j[first] // CELLS_PER_TILE])
    block_counts = np.add.reduceat(counts[order], starts) if len(order) else np.empty(0, dtype=np.int64)
    for group, (bi0, bj0, side) in merged_blocks(block_ij, block_counts, merge_points):
        if side > 1:  # one tile of whole nominal tiles: the aligned square of them, clipped to the grid
            members = np.concatenate([block_members[b] for b in group])
            cell_tiles[members] = len(tiles)
            tiles.append(TileRect(bi0 * CELLS_PER_TILE, min((bi0 + side) * CELLS_PER_TILE, nx),
                                  bj0 * CELLS_PER_TILE, min((bj0 + side) * CELLS_PER_TILE, ny),
                                  int(counts[members].sum()), len(members)))
            continue
        members = block_members[group[0]]
        i0, j0 = bi0 * CELLS_PER_TILE, bj0 * CELLS_PER_TILE
        local = np.zeros((min(CELLS_PER_TILE, nx - i0), min(CELLS_PER_TILE, ny - j0)), dtype=np.int64)
        local[i[members] - i0, j[members] - j0] = counts[members]
        for rect in split_block(local, max_points):
            tile = TileRect(rect.i0 + i0, rect.i1 + i0, rect.j0 + j0, rect.j1 + j0, rect.count, rect.occupied)
            inside = (i[members] >= tile.i0) & (i[members] < tile.i1) & (j[members] >= tile.j0) & (j[members] < tile.j1)
            split = np.searchsorted(crowded, tile.i0 * ny + tile.j0) if len(crowded) else 0
            if tile.count > max_points and split < len(crowded) and crowded[split] == tile.i0 * ny + tile.j0:
                cell_tiles[members[inside]] = SPLIT
                tiles += split_cell(tile, sub_counts[split], max_points, sub_tiles[split], len(tiles))
                continue
            cell_tiles[members[inside]] = len(tiles)
            tiles.append(tile)
    return TilePlan(grid, tuple(tiles), cells, cell_tiles, crowded, sub_tiles,
                    split_reach(grid, sub_counts) if len(crowded) else np.empty(0))


def merged_blocks(block_ij: np.ndarray, block_counts: np.ndarray,
                  merge_points: int) -> list[tuple[list[int], tuple[int, int, int]]]:
    """Groups of nominal tiles (positions in `block_ij`: (b, 2) nominal-tile rows and columns in row-major
    order, with their (b,) point counts), each group one tile, in tile order, with the aligned square of
    nominal tiles it fills (first row, first column, side). With merge_points 0, each nominal tile on its
    own (side 1), in row-major order. Otherwise, within aligned squares of MERGE_SPAN x MERGE_SPAN nominal
    tiles (row-major), the largest aligned quarter holding at most merge_points points is one group, in
    quadtree order; a nominal tile no quarter takes stays on its own, quartered under max_points as before."""
    if merge_points <= 0 or len(block_ij) == 0:
        return [([b], (int(bi), int(bj), 1)) for b, (bi, bj) in enumerate(block_ij.tolist())]
    at = {(bi, bj): b for b, (bi, bj) in enumerate(block_ij.tolist())}
    groups: list[tuple[list[int], tuple[int, int, int]]] = []

    def quarter(i0: int, j0: int, side: int) -> None:
        inside = [at[(i, j)] for i in range(i0, i0 + side) for j in range(j0, j0 + side) if (i, j) in at]
        if not inside:
            return
        if side == 1 or block_counts[inside].sum() <= merge_points:
            groups.append((inside, (i0, j0, side)))
            return
        half = side // 2
        for di, dj in ((0, 0), (0, half), (half, 0), (half, half)):
            quarter(i0 + di, j0 + dj, half)

    for si, sj in sorted({(bi // MERGE_SPAN, bj // MERGE_SPAN) for bi, bj in at}):
        quarter(si * MERGE_SPAN, sj * MERGE_SPAN, MERGE_SPAN)
    return groups


def split_cell(cell: TileRect, sub_counts: np.ndarray, max_points: int, sub_tiles: np.ndarray,
               first_id: int) -> list[TileRect]:
    """The tiles of one crowded cell (a 1x1 TileRect): its (SUB_CELLS, SUB_CELLS) sub-cell counts quartered
    like cells; each occupied sub-cell's entry of `sub_tiles` is set to its tile's id, from `first_id`."""
    parts = split_block(sub_counts, max_points)
    for tile_id, part in enumerate(parts, start=first_id):
        rows, columns = slice(part.i0, part.i1), slice(part.j0, part.j1)
        sub_tiles[rows, columns][sub_counts[rows, columns] > 0] = tile_id
    return [TileRect(cell.i0, cell.i1, cell.j0, cell.j1, part.count, part.occupied / SUB_CELLS**2,
                     (part.i0, part.i1, part.j0, part.j1)) for part in parts]


def split_reach(grid: DensityGrid, sub_counts: np.ndarray) -> np.ndarray:
    """(k,) how far a halo reaches into each split cell: HALO_SPACINGS of its mean point spacing, the
    square root of its occupied sub-cells' area per point."""
    area = (sub_counts > 0).sum(axis=(1, 2)) * (grid.cell / SUB_CELLS) ** 2
    return HALO_SPACINGS * np.sqrt(area / np.maximum(sub_counts.sum(axis=(1, 2)), 1))


def crowded_cells(cells: np.ndarray, counts: np.ndarray, max_points: int) -> np.ndarray:
    """The sorted cells (of sorted `cells`, with their point `counts`) that alone hold more than max_points:
    the cells plan_tiles splits, given their sub-cell counts."""
    return np.asarray(cells, dtype=np.int64)[np.asarray(counts) > max_points]


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

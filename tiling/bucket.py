"""The bucketing pass, fused with the density count: each piece of the scan is written once, its rows
sorted by fine grid cell, so any tile's core+halo is a few row ranges of each piece (one input decode
instead of two; halo points are not duplicated on disk). A piece's rows in crowded cells (split by the
plan) are also copied sorted by sub-cell, so a tile reads only the sub-cells it needs of them."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiling.plan import SUB_CELLS, DensityGrid, TilePlan
from tiling.store import Slice, encode_rows


@dataclass(frozen=True)
class CellBuckets:
    """A piece's rows sorted by cell: cell cells[k] is rows[starts[k]:starts[k+1]]."""

    rows: np.ndarray
    cells: np.ndarray
    starts: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """Points per occupied cell (the piece's share of the density grid)."""
        return np.diff(self.starts)


def bucket_by_cell(records: np.ndarray, xyz: np.ndarray, first: int, grid: DensityGrid) -> CellBuckets:
    """Sort a piece (global indices first, first+1, ...) by grid cell, file order kept within a cell."""
    cell = grid.cell_of(xyz)
    order = stable_order(cell)
    sorted_cells = cell[order]
    starts = np.flatnonzero(np.diff(sorted_cells, prepend=-1))
    return CellBuckets(encode_rows(records, first + np.arange(len(records)), order), sorted_cells[starts],
                       np.append(starts, len(sorted_cells)))


@dataclass(frozen=True)
class SubCellIndex:
    """Where a piece's copy of its rows in the crowded cells holds each sub-cell: the rows are sorted by
    cell, then by sub-cell along a Z-order curve (so a quadtree tile's sub-cells are one run of rows, and
    a halo's a few): sub-cell (si, sj) of crowded cell c is rows starts[b]:starts[b + 1], b = c *
    SUB_CELLS**2 + z_order(si, sj); `protected`: (crowded, SUB_CELLS, SUB_CELLS) points a class rule
    keeps whole per sub-cell."""

    starts: np.ndarray
    protected: np.ndarray

    @property
    def counts(self) -> np.ndarray:
        """(crowded, SUB_CELLS, SUB_CELLS) points per sub-cell."""
        si, sj = np.meshgrid(np.arange(SUB_CELLS), np.arange(SUB_CELLS), indexing="ij")
        along_curve = np.diff(self.starts).reshape(len(self.protected), SUB_CELLS**2)
        return along_curve[:, z_order(si, sj)]


def bucket_by_sub_cell(records: np.ndarray, index: np.ndarray, xyz: np.ndarray, protected: np.ndarray,
                       grid: DensityGrid, crowded: np.ndarray) -> tuple[np.ndarray, SubCellIndex]:
    """A piece's rows in the sorted `crowded` cells (all of `records`, global `index`, `xyz` lie in them)
    encoded and sorted by sub-cell, their order kept within a sub-cell, and where each sub-cell's rows
    are; `protected`: (n,) kept whole by a class rule."""
    si, sj = grid.sub_cell_of(xyz)
    cell = np.searchsorted(crowded, grid.cell_of(xyz))
    bucket = cell * SUB_CELLS**2 + z_order(si, sj)
    order = stable_order(bucket)
    slots = len(crowded) * SUB_CELLS**2
    starts = np.searchsorted(bucket[order], np.arange(slots + 1))
    flat = (cell * SUB_CELLS + si) * SUB_CELLS + sj
    kept_whole = np.bincount(flat[protected], minlength=slots).reshape(len(crowded), SUB_CELLS, SUB_CELLS)
    return encode_rows(records, index, order), SubCellIndex(starts, kept_whole)


def stable_order(keys: np.ndarray) -> np.ndarray:
    """np.argsort(keys, kind="stable") of (n,) integer keys, sorted as 16-bit offsets from their least where
    they span fewer than 2**16 values (numpy radix-sorts those: a 500k-point bcts piece's cells in 3.5
    against 10 ms), as they do within a piece of all but the widest scans."""
    if len(keys):
        least = keys.min()
        if int(keys.max()) - int(least) < 2**16:
            keys = (keys - least).astype(np.uint16)
    return np.argsort(keys, kind="stable")


def z_order(si: np.ndarray, sj: np.ndarray) -> np.ndarray:
    """The position of sub-cells (si, sj) along a Z-order (Morton) curve over SUB_CELLS x SUB_CELLS: their
    bits interleaved, si's first."""
    code = np.zeros(np.shape(si), dtype=np.int64)
    for bit in range(int(np.log2(SUB_CELLS))):
        code |= ((np.asarray(si) >> bit) & 1) << (2 * bit + 1) | ((np.asarray(sj) >> bit) & 1) << (2 * bit)
    return code


def halo_slices(plan: TilePlan, tile_id: int, overlap: float, piece: int, cells: np.ndarray, starts: np.ndarray,
                crowded: SubCellIndex | None) -> list[Slice]:
    """The slices of one piece (its occupied `cells` and their row `starts`, as CellBuckets) holding a
    tile's core and halo, a superset of what plan.halo_mask keeps: the piece's rows in the halo's cells,
    and of cells the plan split only the sub-cells the halo reaches, from the piece's crowded copy."""
    cell_ranges = plan.halo_cell_ranges(tile_id, overlap)
    slices = [Slice(piece, int(lo), int(hi))
              for lo, hi in row_ranges(cells, starts, without_cells(cell_ranges, plan.split_cells))]
    if crowded is None:
        return slices
    for k in cells_within(plan.split_cells, cell_ranges):
        si0, si1, sj0, sj1 = plan.halo_sub_rect(tile_id, int(plan.split_cells[k]), overlap)
        si, sj = np.meshgrid(np.arange(si0, si1), np.arange(sj0, sj1), indexing="ij")
        bucket = k * SUB_CELLS**2 + np.sort(z_order(si.ravel(), sj.ravel()))
        ranges = np.column_stack([crowded.starts[bucket], crowded.starts[bucket + 1]])
        slices += [Slice(piece, int(lo), int(hi), crowded=True) for lo, hi in merged(ranges)]
    return slices


def cells_within(cells: np.ndarray, cell_ranges: np.ndarray) -> np.ndarray:
    """Positions in sorted `cells` of those inside the ascending, disjoint flat ranges (n, 2) [lo, hi)."""
    first, last = np.searchsorted(cells, cell_ranges[:, 0]), np.searchsorted(cells, cell_ranges[:, 1])
    return np.concatenate([np.arange(a, b) for a, b in zip(first.tolist(), last.tolist()) if b > a] or
                          [np.empty(0, dtype=np.int64)])


def without_cells(cell_ranges: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Flat cell ranges (n, 2) [lo, hi), ascending and disjoint, with the given sorted cells cut out."""
    cut = cells[cells_within(cells, cell_ranges)]
    if len(cut) == 0:
        return cell_ranges
    edges = np.sort(np.concatenate([cell_ranges.ravel(), cut, cut + 1]))  # each cut cell ends one range, starts one
    pieces = edges.reshape(-1, 2)
    return pieces[pieces[:, 1] > pieces[:, 0]]


def row_ranges(cells: np.ndarray, starts: np.ndarray, cell_ranges: np.ndarray) -> np.ndarray:
    """Row ranges (n, 2) of a piece covering flat cell ranges [lo, hi), empty and adjacent ones merged."""
    lo = starts[np.searchsorted(cells, cell_ranges[:, 0])]
    hi = starts[np.searchsorted(cells, cell_ranges[:, 1])]
    return merged(np.column_stack([lo, hi]))


def merged(ranges: np.ndarray) -> np.ndarray:
    """Row ranges (n, 2) in ascending order with the empty ones dropped and adjacent ones joined."""
    lo, hi = ranges[:, 0], ranges[:, 1]
    keep = hi > lo
    lo, hi = lo[keep], hi[keep]
    if len(lo) == 0:
        return np.empty((0, 2), dtype=np.int64)
    joined = np.concatenate([[True], lo[1:] != hi[:-1]])  # a range starts where it does not continue the last
    group = np.cumsum(joined) - 1
    merged_hi = np.zeros(group[-1] + 1, dtype=np.int64)
    np.maximum.at(merged_hi, group, hi)
    return np.column_stack([lo[joined], merged_hi])


def cell_boxes(piece_cells: list[np.ndarray], ny: int) -> np.ndarray:
    """(pieces, 4) cells [i0, i1) x [j0, j1) bounding each piece's occupied cells (flat ids i * ny + j);
    an empty piece gets an empty box. A tile's halo meets only the pieces whose boxes it meets."""
    boxes = np.zeros((len(piece_cells), 4), dtype=np.int64)
    for k, cells in enumerate(piece_cells):
        if len(cells):
            i, j = np.divmod(cells, ny)
            boxes[k] = i.min(), i.max() + 1, j.min(), j.max() + 1
    return boxes

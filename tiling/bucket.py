"""The bucketing pass, fused with the density count: each piece of the scan is written once, its rows
sorted by fine grid cell, so any tile's core+halo is a few row ranges of each piece (one input decode
instead of two; halo points are not duplicated on disk)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiling.plan import DensityGrid
from tiling.store import encode_rows


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
    order = np.argsort(cell, kind="stable")
    sorted_cells = cell[order]
    starts = np.flatnonzero(np.diff(sorted_cells, prepend=-1))
    return CellBuckets(encode_rows(records[order], first + order), sorted_cells[starts],
                       np.append(starts, len(sorted_cells)))


def row_ranges(cells: np.ndarray, starts: np.ndarray, cell_ranges: np.ndarray) -> np.ndarray:
    """Row ranges (n, 2) of a piece covering flat cell ranges [lo, hi), empty and adjacent ones merged."""
    lo = starts[np.searchsorted(cells, cell_ranges[:, 0])]
    hi = starts[np.searchsorted(cells, cell_ranges[:, 1])]
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

"""Kept-to-expected density maps: per XY cell, the points an output kept there divided by its fair share
(ratio x the source's points there, ratio = output points / source points). 1 means the cell kept its
share; a method that starves an area (and the small objects in it) shows below 1 there.

Counts are streamed over the files in chunks (pipeline.io.points.xyz_chunks), so memory is the grid, not the scan.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from pipeline.io.points import Cells, point_count, xyz_chunks

CELLS_LONG = 150  # cells along the longer side of the source's XY box
MIN_CELL_POINTS = 200  # source points per cell of the box, on average, at the least: fewer makes the map noise


@dataclass(frozen=True)
class DensityMap:
    """One output's map: `ratio[iy, ix]` (ny, nx) float64, NaN where the source has no point; `grid` (x-major
    keys, shape (nx, ny)) places cell (iy, ix) at origin + (ix, iy) * side."""

    output: Path
    grid: Cells
    ratio: np.ndarray  # (ny, nx) kept / expected
    kept_share: float  # output points / source points

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x0, x1, y0, y1) of the grid, in the scan's coordinates."""
        x0, y0 = self.grid.origin
        nx, ny = self.grid.shape
        return x0, x0 + nx * self.grid.side, y0, y0 + ny * self.grid.side


def xy_bounds(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """(2,) lower and upper XY corners of a file's points, from one streamed pass."""
    low, high = np.full(2, np.inf), np.full(2, -np.inf)
    for xyz in xyz_chunks(path):
        low, high = np.minimum(low, xyz[:, :2].min(axis=0)), np.maximum(high, xyz[:, :2].max(axis=0))
    return low, high


def density_grid(source: Path, cells_long: int = CELLS_LONG, min_cell_points: int = MIN_CELL_POINTS) -> Cells:
    """Square cells over the source's XY box: `cells_long` along its longer side, or fewer and bigger where the
    box would otherwise hold under `min_cell_points` source points per cell."""
    low, high = xy_bounds(source)
    extent = np.maximum(high - low, 1e-9)
    side = max(float(extent.max()) / cells_long, float(np.sqrt(extent.prod() * min_cell_points / point_count(source))))
    shape = tuple(int(v) for v in np.maximum(np.ceil(extent / side), 1))
    return Cells(low, side, shape, np.empty(0, dtype=np.int64))


def cell_counts(path: Path, grid: Cells) -> np.ndarray:
    """(ny, nx) int64 points of a file per cell (points off the grid count in the nearest edge cell)."""
    counts = np.zeros(grid.shape[0] * grid.shape[1], dtype=np.int64)
    for xyz in xyz_chunks(path):
        counts += np.bincount(grid.keys(xyz), minlength=len(counts))
    return counts.reshape(grid.shape).T


def kept_to_expected(source_counts: np.ndarray, kept_counts: np.ndarray, kept_share: float) -> np.ndarray:
    """(ny, nx) kept / (kept_share x source) per cell, NaN where the source has no point."""
    expected = kept_share * source_counts.astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(source_counts > 0, kept_counts / expected, np.nan)


def density_maps(source: Path, outputs: Sequence[Path], grid: Cells | None = None) -> list[DensityMap]:
    """The map of every output on one grid (`density_grid(source)` unless given); the source is counted once."""
    grid = grid or density_grid(source)
    source_counts = cell_counts(source, grid)
    total = int(source_counts.sum())
    maps = []
    for output in outputs:
        kept = cell_counts(output, grid)
        share = int(kept.sum()) / total
        maps.append(DensityMap(output, grid, kept_to_expected(source_counts, kept, share), share))
    return maps


def density_map(source: Path, output: Path, grid: Cells | None = None) -> DensityMap:
    """One output's kept-to-expected map against its source (see `density_maps`)."""
    return density_maps(source, [output], grid)[0]

"""The region a report shows in 3-D, and a bounded, seeded sample of a file's points in it with the values
they are coloured by (elevation, classification or RGB), read in chunks so a big scan never loads whole."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import laspy
import numpy as np

from pipeline.apps.visual.density_map import xy_bounds
from pipeline.engine.classes import classification
from pipeline.errors import PipelineError
from pipeline.io.points import CHUNK, covering_grid, point_count, xyz_chunks, zarr_group
from pipeline.io.scan import Scan

REGION_POINTS = 20_000  # source points per cell of the grid the automatic region is a cell of: a building or two
RGB = ("red", "green", "blue")


@dataclass(frozen=True)
class Region:
    """An XY square [x0, x0 + size) x [y0, y0 + size) in the scan's coordinates."""

    x0: float
    y0: float
    size: float

    def contains(self, xyz: np.ndarray) -> np.ndarray:
        """(m,) mask of the points of an (m, 3) array inside the square."""
        dx, dy = xyz[:, 0] - self.x0, xyz[:, 1] - self.y0
        return (dx >= 0) & (dx < self.size) & (dy >= 0) & (dy < self.size)

    def describe(self) -> str:
        """The region as `--region` takes it (centre x, centre y, side)."""
        half = self.size / 2
        return f"{self.x0 + half:.2f},{self.y0 + half:.2f},{self.size:.4g}"


def parse_region(text: str) -> Region:
    """`--region X,Y,SIZE`: a square of side SIZE centred on (X, Y), in the scan's units."""
    try:
        x, y, size = (float(v) for v in text.split(","))
    except ValueError:
        raise PipelineError(f"--region must be X,Y,SIZE (centre and side in the scan's units), got {text!r}") from None
    if not size > 0:
        raise PipelineError(f"--region SIZE must be positive, got {size:g}")
    return Region(x - size / 2, y - size / 2, size)


def find_region(source: Path) -> Region:
    """The cell (of a grid holding about REGION_POINTS source points per cell) with the most structure:
    points times their elevation spread, so facades, poles and trees win over flat ground. Deterministic."""
    grid = covering_grid(*xy_bounds(source), max(1, point_count(source) // REGION_POINTS))
    sums = np.zeros((3, grid.shape[0] * grid.shape[1]))  # points, sum of z, sum of z^2 per cell
    for xyz in xyz_chunks(source):
        keys, z = grid.keys(xyz), xyz[:, 2]
        for row, weights in enumerate((None, z, z * z)):
            sums[row] += np.bincount(keys, weights=weights, minlength=sums.shape[1])
    count = np.maximum(sums[0], 1)
    spread = np.sqrt(np.maximum(sums[2] / count - (sums[1] / count) ** 2, 0))
    ix, iy = divmod(int(np.argmax(sums[0] * spread)), grid.shape[1])
    return Region(float(grid.origin[0] + ix * grid.side), float(grid.origin[1] + iy * grid.side), grid.side)


@dataclass(frozen=True)
class RegionSample:
    """Up to a cap of a file's points in a region, drawn uniformly; `total` is how many the region holds."""

    xyz: np.ndarray  # (m, 3) float64, scan coordinates
    values: np.ndarray  # (m,) z or class code, or (m, 3) RGB as stored
    total: int


def colour_chunks(path: Path, color: str) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(xyz (m, 3), values) of consecutive points: values are z, class codes (m,) or stored RGB (m, 3)."""
    if color == "elevation":
        yield from ((xyz, xyz[:, 2]) for xyz in xyz_chunks(path))
    elif path.suffix.lower() == ".zarr":
        group = zarr_group(path)
        names = ["classification"] if color == "classification" else list(RGB)
        if any(name not in group for name in names):
            raise PipelineError(f"{path}: has no {color} to colour by")
        for start, xyz in zip(range(0, point_count(path), CHUNK), xyz_chunks(path)):
            values = np.column_stack([np.asarray(group[n][start:start + CHUNK]) for n in names])
            yield xyz, values[:, 0] if color == "classification" else values
    else:
        scan = Scan([path])
        if color == "rgb" and "red" not in scan.point_format.dimension_names:
            raise PipelineError(f"{path}: point format {scan.point_format.id} has no RGB to colour by")
        for piece in scan.pieces(CHUNK):
            chunk = scan.read(piece)
            if color == "classification":
                yield chunk.xyz, classification(chunk.records)
            else:
                record = laspy.PackedPointRecord(chunk.records, scan.point_format)
                yield chunk.xyz, np.column_stack([np.asarray(record[n]) for n in RGB])


def sample_region(path: Path, region: Region, color: str, cap: int, seed: int = 0) -> RegionSample:
    """A uniform sample of at most `cap` of the file's points inside `region`, with their colour values:
    every point gets a seeded random key and the `cap` smallest keys are kept, chunk by chunk (bounded memory)."""
    keys, xyz, values, total = np.empty(0), np.empty((0, 3)), None, 0
    for number, (chunk_xyz, chunk_values) in enumerate(colour_chunks(path, color)):
        inside = region.contains(chunk_xyz)
        total += int(inside.sum())
        chunk_keys = np.random.default_rng([seed, number]).random(int(inside.sum()))
        keys = np.concatenate([keys, chunk_keys])
        xyz = np.concatenate([xyz, chunk_xyz[inside]])
        values = chunk_values[inside] if values is None else np.concatenate([values, chunk_values[inside]])
        if len(keys) > cap:
            keep = np.argpartition(keys, cap)[:cap]
            keys, xyz, values = keys[keep], xyz[keep], values[keep]
    if values is None:
        raise PipelineError(f"{path}: has no points")
    return RegionSample(xyz, values, total)

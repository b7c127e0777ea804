"""Coordinates of a scan or an output (LAS/LAZ/PLY, or a zarr store's x, y, z), streamed in chunks and
optionally cropped to a set of XY grid cells, so evaluation never holds more of a big scan than it uses."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np

from pipeline.errors import PipelineError
from pipeline.io.crs import LengthUnit, crs_from_wkt, crs_length_unit, length_unit, parsed_crs
from pipeline.io.scan import Scan

if TYPE_CHECKING:
    import pyproj
    import zarr

CHUNK = 1_000_000


@dataclass(frozen=True)
class Cells:
    """Chosen cells of a square XY grid (row-major keys); a point belongs if its cell is chosen.

    Points outside the grid count in the nearest edge cell, so a refined point that strayed a little
    past the reference's bounds is not lost.
    """

    origin: np.ndarray  # (2,) lower-left corner
    side: float
    shape: tuple[int, int]
    chosen: np.ndarray  # sorted int64 keys

    def keys(self, xyz: np.ndarray) -> np.ndarray:
        """The grid key of each point."""
        ij = np.floor((xyz[:, :2] - self.origin) / self.side).astype(np.int64)
        ij = np.clip(ij, 0, np.array(self.shape) - 1)
        return ij[:, 0] * self.shape[1] + ij[:, 1]

    def contains(self, xyz: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """Mask of the points inside the chosen cells, or within `margin` (under a cell side, along x and
        y) of one: the corners of a point's margin square then lie in every cell the square touches."""
        inside = np.isin(self.keys(xyz), self.chosen)
        for dx in (-margin, margin) if margin > 0 else ():
            for dy in (-margin, margin):
                inside |= np.isin(self.keys(xyz[:, :2] + (dx, dy)), self.chosen)
        return inside


def covering_grid(low: np.ndarray, high: np.ndarray, cells: int) -> Cells:
    """A grid of about `cells` square cells over the XY box [low, high], none chosen yet; at most `cells` along a
    box thinner than a cell (a scan of one line along x or y), whose cells would otherwise shrink to nothing."""
    extent = np.maximum(high[:2] - low[:2], 1e-9)
    side = max(float(np.sqrt(extent[0] * extent[1] / cells)), float(extent.max()) / cells) or 1.0
    shape = tuple(int(v) for v in np.maximum(np.ceil(extent / side), 1))
    return Cells(np.asarray(low[:2], dtype=np.float64), side, shape, np.empty(0, dtype=np.int64))


def point_count(path: Path) -> int:
    """Points in a file or zarr store, from its header or array shape."""
    if _is_zarr(path):
        return int(_zarr_xyz(path)[0].shape[0])
    return Scan([path]).point_count


def length_unit_of(path: Path) -> LengthUnit:
    """The horizontal unit of a file's coordinates: its header's CRS, or a zarr output's `crs_wkt` attribute."""
    if not _is_zarr(path):
        return length_unit(Scan([path]).header)
    return crs_length_unit(crs_from_wkt(zarr_group(path).attrs.get("crs_wkt")))


def crs_of(path: Path) -> pyproj.CRS | None:
    """A file's CRS as pyproj reads its header, or a zarr output's `crs_wkt` attribute; None without one."""
    if not _is_zarr(path):
        return parsed_crs(Scan([path]).header)
    return crs_from_wkt(zarr_group(path).attrs.get("crs_wkt"))


def chunk_count(path: Path) -> int:
    """How many chunks xyz_chunks yields for a file: the steps of a pass over it."""
    return -(-point_count(path) // CHUNK)


def xyz_chunks(path: Path, on_chunk: Callable[[int], None] = lambda points: None) -> Iterator[np.ndarray]:
    """Float64 (m, 3) coordinates of consecutive points, CHUNK at a time; `on_chunk` hears each chunk's size."""
    if _is_zarr(path):
        arrays = _zarr_xyz(path)
        for start in range(0, arrays[0].shape[0], CHUNK):
            chunk = np.column_stack([np.asarray(a[start:start + CHUNK], dtype=np.float64) for a in arrays])
            on_chunk(len(chunk))
            yield chunk
        return
    scan = Scan([path])
    for piece in scan.pieces(CHUNK):
        chunk = scan.read(piece).xyz
        on_chunk(len(chunk))
        yield chunk


def load_xyz(path: Path, cells: Cells | None = None, margin: float = 0.0,
             on_chunk: Callable[[int], None] = lambda points: None) -> np.ndarray:
    """All coordinates of a file, or those inside `cells` (grown by `margin`)."""
    parts = [xyz if cells is None else xyz[cells.contains(xyz, margin)] for xyz in xyz_chunks(path, on_chunk)]
    return np.concatenate(parts) if parts else np.empty((0, 3))


def _is_zarr(path: Path) -> bool:
    return path.suffix.lower() == ".zarr"


def _zarr_xyz(path: Path) -> list[zarr.Array]:
    """The x, y, z arrays of a zarr output (one group, one 1-D array per dimension)."""
    group = zarr_group(path)
    return [group[name] for name in "xyz"]


def zarr_group(path: Path) -> zarr.Group:
    """A zarr output's group, checked to hold x, y, z arrays (a clear error for a store that is not ours).
    zarr is imported here: 0.25 s that a run of LAS/LAZ files never needs."""
    import zarr

    if not path.is_dir():
        raise PipelineError(f"{path}: no such zarr store")
    try:
        group = zarr.open_group(str(path), mode="r")
        for name in "xyz":
            if not isinstance(group[name], zarr.Array):
                raise KeyError(name)
        return group
    except (KeyError, FileNotFoundError, ValueError, zarr.errors.BaseZarrError) as exc:
        raise PipelineError(f"{path}: not a zarr point store with x, y, z arrays ({exc})") from None

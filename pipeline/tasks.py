"""The work Dask workers do: bucket a piece into the store (counting its density), simplify a tile.

Each function takes plain picklable data and touches only its own piece or tile, so any worker of a
local or remote cluster can run it, in any order, with the same result.
"""
from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from model import Tile, get_simplifier
from pipeline.scan import Piece, Scan, scaled_xyz
from pipeline.workdir import WorkDir, save_npz, write_atomically
from tiling.bucket import bucket_by_cell
from tiling.budgets import occupied_voxels
from tiling.plan import DensityGrid, TilePlan
from tiling.store import Slice, TileStore


@dataclass(frozen=True)
class TileJob:
    """Everything a worker needs for one tile."""

    store_path: str
    result_path: str
    tile_id: int
    slices: tuple[Slice, ...]
    overlap: float
    cache_bytes: int
    budget: int
    reserve: int
    method: str
    seed: int


@dataclass(frozen=True)
class TileOutcome:
    """What a finished tile reports back: counts and time; the picks stay on disk."""

    tile_id: int
    points: int
    kept: int
    seconds: float


def bucket_piece(piece: Piece, scan: Scan, grid: DensityGrid, work_path: str) -> tuple[np.ndarray, np.ndarray]:
    """Read one piece once, store its rows sorted by grid cell, record it as done in the work folder;
    return its occupied cells and row starts."""
    chunk = scan.read(piece)
    buckets = bucket_by_cell(chunk.records, chunk.xyz, piece.first, grid)
    work = WorkDir(Path(work_path))
    TileStore.open(work.store_path).write_piece(piece.number, buckets.rows)
    work.save_piece(piece.number, buckets.cells, buckets.starts)
    return buckets.cells, buckets.starts


def tile_seed(run_seed: int, tile_id: int) -> int:
    """A tile's own seed: fixed by the run seed and the tile id, whatever worker runs it."""
    return int(np.random.SeedSequence([run_seed, tile_id]).generate_state(1)[0])


def simplify_tile(job: TileJob, plan: TilePlan) -> TileOutcome:
    """Pick budget+reserve core points of one tile in priority order; save their rows and xyz to result_path.

    Rows are positions in what `TileStore.load(job.slices)` returns, so the stitch can fetch the records.
    """
    started = time.perf_counter()
    store = TileStore.open(Path(job.store_path))
    attrs = store.attrs
    xyz = scaled_xyz(store.load(job.slices, job.cache_bytes).records, np.asarray(attrs["scales"]),
                     np.asarray(attrs["offsets"]))
    core = plan.core_mask(job.tile_id, xyz)
    seen = np.flatnonzero(plan.halo_mask(core, job.tile_id, xyz, job.overlap))
    xyz, core = xyz[seen], core[seen]
    centre = xyz[core].mean(axis=0)
    tile = Tile(xyz - centre, core, centre, tile_seed(job.seed, job.tile_id))
    selection = get_simplifier(job.method)(tile, min(job.budget + job.reserve, tile.core_count))
    write_atomically(Path(job.result_path),
                     lambda tmp: save_npz(tmp, rows=seen[selection.indices], xyz=selection.xyz + centre))
    return TileOutcome(job.tile_id, len(xyz), len(selection.indices), time.perf_counter() - started)


@dataclass(frozen=True)
class CoverageJob:
    """One tile's points to count occupied voxels of, at each of `sizes` (scan units)."""

    store_path: str
    tile_id: int
    slices: tuple[Slice, ...]
    cache_bytes: int
    sizes: tuple[float, ...]


def tile_coverage(job: CoverageJob, plan: TilePlan) -> np.ndarray:
    """Occupied voxels of the tile's core points at each size: what a scan-wide even spacing gives it."""
    store = TileStore.open(Path(job.store_path))
    xyz = scaled_xyz(store.load(job.slices, job.cache_bytes).records, np.asarray(store.attrs["scales"]),
                     np.asarray(store.attrs["offsets"]))
    core = xyz[plan.core_mask(job.tile_id, xyz)]
    return occupied_voxels(core, np.asarray(job.sizes))  # voxels count from the points' minimum: no centring needed

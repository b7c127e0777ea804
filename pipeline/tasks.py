"""The work Dask workers do: count a piece's density, bucket a piece into the store, simplify a tile.

Each function takes plain picklable data and touches only its own piece or tile, so any worker of a
local or remote cluster can run it, in any order, with the same result.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from model import Tile, get_simplifier
from pipeline.scan import Piece, Scan
from tiling.bucket import Halos, bucket_piece
from tiling.plan import DensityGrid, TilePlan
from tiling.store import Slice, TileStore


@dataclass(frozen=True)
class TileJob:
    """Everything a worker needs for one tile."""

    store_path: str
    result_path: str
    tile_id: int
    slices: tuple[Slice, ...]
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


def count_piece(piece: Piece, scan: Scan, grid: DensityGrid) -> tuple[np.ndarray, np.ndarray]:
    """Occupied grid cells of one piece and their point counts (sparse, so results stay small)."""
    cells = grid.cell_of(scan.read(piece).xyz)
    occupied, counts = np.unique(cells, return_counts=True)
    return occupied, counts


def bucket_into_store(piece: Piece, scan: Scan, plan: TilePlan, halos: Halos, store_path: str) -> np.ndarray:
    """Write one piece's rows, grouped by tile, to the store; return the tile row offsets and core counts."""
    chunk = scan.read(piece)
    bucketed = bucket_piece(chunk.records, chunk.xyz, piece.first, plan, halos)
    TileStore.open(Path(store_path)).write_piece(piece.number, bucketed.rows)
    return np.vstack([bucketed.offsets[:-1], bucketed.offsets[1:], bucketed.core_counts])


def tile_seed(run_seed: int, tile_id: int) -> int:
    """A tile's own seed: fixed by the run seed and the tile id, whatever worker runs it."""
    return int(np.random.SeedSequence([run_seed, tile_id]).generate_state(1)[0])


def simplify_tile(job: TileJob) -> TileOutcome:
    """Pick budget+reserve core points of one tile in priority order; save their rows and xyz to result_path."""
    started = time.perf_counter()
    store = TileStore.open(Path(job.store_path))
    points = store.load(job.slices)
    scales = np.asarray(store.attrs["scales"], dtype=np.float64)
    offsets = np.asarray(store.attrs["offsets"], dtype=np.float64)
    ints = np.column_stack([points.records["X"], points.records["Y"], points.records["Z"]]).astype(np.float64)
    xyz = ints * scales + offsets
    centre = xyz[points.core].mean(axis=0)
    tile = Tile(xyz - centre, points.core, centre, tile_seed(job.seed, job.tile_id))
    selection = get_simplifier(job.method)(tile, min(job.budget + job.reserve, tile.core_count))
    temporary = f"{job.result_path}.tmp-{os.getpid()}.npz"
    np.savez(temporary, rows=selection.indices, xyz=selection.xyz + centre)
    os.replace(temporary, job.result_path)
    return TileOutcome(job.tile_id, len(xyz), len(selection.indices), time.perf_counter() - started)

"""The work of one Dask task: load a tile from the store, simplify it, persist the picks."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from model import Tile, get_simplifier
from tiling.store import TileStore


@dataclass(frozen=True)
class TileJob:
    """Everything a worker needs for one tile; plain data so it pickles to any worker."""

    store_path: str
    result_path: str
    tile_id: int
    budget: int
    reserve: int
    method: str
    seed: int


@dataclass(frozen=True)
class TileOutcome:
    """What a finished task reports back: counts and time, the picks stay on disk."""

    tile_id: int
    points: int
    kept: int
    seconds: float


def tile_seed(run_seed: int, tile_id: int) -> int:
    """A tile's own seed: fixed by the run seed and the tile id, whatever worker runs it."""
    return int(np.random.SeedSequence([run_seed, tile_id]).generate_state(1)[0])


def simplify_tile(job: TileJob) -> TileOutcome:
    """Pick budget+reserve core points of one tile in priority order and save rows and xyz to result_path."""
    started = time.perf_counter()
    store = TileStore.open(Path(job.store_path))
    points = store.load(job.tile_id)
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

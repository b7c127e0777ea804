"""The out-of-core bucketing pass: stream the scan once, send each point to its core tile and to
the halos of neighbouring tiles within `overlap`, flushing to the tile store in bounded memory."""
from __future__ import annotations

from typing import Iterable

import numpy as np

from tiling.plan import TilePlan
from tiling.store import TileStore


def bucket_points(chunks: Iterable[tuple[np.ndarray, np.ndarray]], plan: TilePlan, overlap: float,
                  store: TileStore, buffer_bytes: int) -> np.ndarray:
    """Write every (records, xyz) chunk into the store; return the core point count of each tile."""
    bounds = plan.all_bounds()
    neighbours = plan.neighbours(overlap)
    core_counts = np.zeros(len(plan.tiles), dtype=np.int64)
    start = 0
    for records, xyz in chunks:
        owner = plan.tile_of(xyz)
        if (owner < 0).any():
            raise ValueError("a point fell outside every tile: the input changed between the density and bucketing passes")
        order = np.argsort(owner, kind="stable")
        edges = np.searchsorted(owner[order], np.arange(len(plan.tiles) + 1))
        core_counts += np.diff(edges)
        for tile_id in range(len(plan.tiles)):
            core_rows = order[edges[tile_id]:edges[tile_id + 1]]
            halo_rows = _halo_rows(tile_id, xyz, order, edges, neighbours[tile_id], bounds[tile_id], overlap)
            if len(core_rows) == 0 and len(halo_rows) == 0:
                continue
            rows = np.sort(np.concatenate([core_rows, halo_rows]))
            core = np.isin(rows, core_rows, assume_unique=True)
            store.add(tile_id, records[rows], start + rows, core)
        start += len(records)
        if store.pending_bytes > buffer_bytes:
            store.flush()
    store.flush()
    return core_counts


def _halo_rows(tile_id: int, xyz: np.ndarray, order: np.ndarray, edges: np.ndarray, near: np.ndarray,
               rect: np.ndarray, overlap: float) -> np.ndarray:
    """Rows owned by neighbouring tiles that lie within `overlap` of this tile's core rectangle."""
    if overlap <= 0 or len(near) == 0:
        return np.empty(0, dtype=np.int64)
    candidates = np.concatenate([order[edges[n]:edges[n + 1]] for n in near])
    x, y = xyz[candidates, 0], xyz[candidates, 1]
    inside = ((x >= rect[0] - overlap) & (x < rect[2] + overlap) & (y >= rect[1] - overlap) & (y < rect[3] + overlap))
    return candidates[inside]

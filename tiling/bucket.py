"""Bucketing one piece of the scan: each point goes to its core tile and to the halos of neighbouring
tiles within `overlap`; rows come out grouped by tile, so a tile is one slice of the piece's array."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tiling.plan import TilePlan
from tiling.store import encode_rows


@dataclass(frozen=True)
class Halos:
    """What the bucketing needs of the plan besides the cell lookup: core rectangles and neighbours."""

    bounds: np.ndarray
    neighbours: list[np.ndarray]
    overlap: float

    @classmethod
    def of(cls, plan: TilePlan, overlap: float) -> "Halos":
        """Precompute once per run (workers get it once, not once per piece)."""
        return cls(plan.all_bounds(), plan.neighbours(overlap), overlap)


@dataclass(frozen=True)
class BucketedPiece:
    """A piece's rows grouped by tile: tile t is rows[offsets[t]:offsets[t+1]]."""

    rows: np.ndarray
    offsets: np.ndarray
    core_counts: np.ndarray


def bucket_piece(records: np.ndarray, xyz: np.ndarray, first: int, plan: TilePlan, halos: Halos) -> BucketedPiece:
    """Group a piece's points (global indices first, first+1, ...) by core tile plus halo membership."""
    tiles = len(plan.tiles)
    owner = plan.tile_of(xyz)
    if (owner < 0).any():
        raise ValueError("a point fell outside every tile: the input changed between the density and bucketing passes")
    order = np.argsort(owner, kind="stable")
    edges = np.searchsorted(owner[order], np.arange(tiles + 1))
    parts, offsets = [], np.zeros(tiles + 1, dtype=np.int64)
    for tile_id in range(tiles):
        core_rows = order[edges[tile_id]:edges[tile_id + 1]]
        halo_rows = _halo_rows(xyz, order, edges, halos.neighbours[tile_id], halos.bounds[tile_id], halos.overlap)
        if len(halo_rows):
            rows = np.sort(np.concatenate([core_rows, halo_rows]))
            core = np.isin(rows, core_rows, assume_unique=True)
        else:
            rows, core = np.sort(core_rows), np.ones(len(core_rows), dtype=bool)
        parts.append(encode_rows(records[rows], first + rows, core))
        offsets[tile_id + 1] = offsets[tile_id] + len(rows)
    return BucketedPiece(np.concatenate(parts), offsets, np.diff(edges))


def _halo_rows(xyz: np.ndarray, order: np.ndarray, edges: np.ndarray, near: np.ndarray, rect: np.ndarray,
               overlap: float) -> np.ndarray:
    """Rows owned by neighbouring tiles that lie within `overlap` of this tile's core rectangle."""
    if overlap <= 0 or len(near) == 0:
        return np.empty(0, dtype=np.int64)
    candidates = np.concatenate([order[edges[n]:edges[n + 1]] for n in near])
    x, y = xyz[candidates, 0], xyz[candidates, 1]
    inside = (x >= rect[0] - overlap) & (x < rect[2] + overlap) & (y >= rect[1] - overlap) & (y < rect[3] + overlap)
    return candidates[inside]

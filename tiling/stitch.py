"""The stitch's seam pass: kept points of different tiles closer than a tolerance keep one.

Tiles are resolved in tile order. A candidate near its tile's border is rejected if a point already
accepted for an earlier tile lies within the tolerance; the tile then takes the next candidates of
its own priority order, so every tile still delivers exactly its budget.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from pykdtree.kdtree import KDTree

from model.rules import sorted_distinct


@dataclass(frozen=True)
class SeamBand:
    """A tile's candidates that lie within the tolerance of its core border: their ranks and xyz."""

    tile_id: int
    ranks: np.ndarray
    xyz: np.ndarray


def band_mask(xyz: np.ndarray, rect: Sequence[float], tolerance: float) -> np.ndarray:
    """Points closer than `tolerance` to the rectangle's border in XY, or outside it."""
    x, y = xyz[:, 0], xyz[:, 1]
    inner = np.minimum.reduce([x - rect[0], rect[2] - x, y - rect[1], rect[3] - y])
    return inner < tolerance


def close_pairs(xyz: np.ndarray, tolerance: float) -> np.ndarray:
    """Every pair (i, j), i < j, of the (N, 3) points at most `tolerance` apart, shape (P, 2): what scipy's
    cKDTree.query_pairs returns, with the same rule for a pair exactly at the tolerance (squared distance
    summed x, y, z, compared with tolerance squared), but from pykdtree's bounded kNN, so a run never
    imports scipy (0.3 s). Rows whose k-th neighbour is still within reach ask again with twice the k,
    so a cluster of duplicates costs only its own rows."""
    points = np.ascontiguousarray(xyz, dtype=np.float64)
    count = len(points)
    if count < 2:
        return np.empty((0, 2), dtype=np.int64)
    tree = KDTree(points)
    reach = float(np.nextafter(tolerance, np.inf)) * (1 + 1e-9)  # a margin; the exact rule is applied below
    rows, k, found = np.arange(count), min(2, count), []
    while len(rows):
        neighbours = tree.query(points[rows], k=k, distance_upper_bound=reach)[1].reshape(len(rows), k)
        complete = (neighbours[:, -1] >= count) | (k == count)
        first = np.repeat(rows[complete], k)
        second = neighbours[complete].ravel().astype(np.int64)
        ordered = (second < count) & (first < second)
        found.append(np.stack([first[ordered], second[ordered]], axis=1))
        rows, k = rows[~complete], min(2 * k, count)
    pairs = np.concatenate(found)
    offset = points[pairs[:, 0]] - points[pairs[:, 1]]
    squared = offset[:, 0] * offset[:, 0] + offset[:, 1] * offset[:, 1] + offset[:, 2] * offset[:, 2]
    return pairs[squared <= tolerance * tolerance]


def first_accepted(candidates: int, budget: int, rejected: np.ndarray) -> np.ndarray:
    """The first `budget` candidate ranks that are not rejected; rejected ones fill in only if too few remain."""
    keep = np.ones(candidates, dtype=bool)
    keep[rejected] = False
    ranks = np.flatnonzero(keep)[:budget]
    if len(ranks) < budget:
        ranks = np.sort(np.concatenate([ranks, np.sort(rejected)[:budget - len(ranks)]]))
    return ranks


def resolve_seams(bands: Sequence[SeamBand], candidate_counts: np.ndarray, budgets: np.ndarray,
                  tolerance: float) -> dict[int, np.ndarray]:
    """Ranks each tile must reject so that no two kept points of different tiles are closer than tolerance."""
    bands = [b for b in bands if len(b.ranks)]
    if not bands or tolerance <= 0:
        return {}
    xyz = np.concatenate([b.xyz for b in bands])
    tile = np.concatenate([np.full(len(b.ranks), b.tile_id) for b in bands])
    rank = np.concatenate([b.ranks for b in bands])
    pairs = close_pairs(xyz, tolerance)
    pairs = pairs[tile[pairs[:, 0]] != tile[pairs[:, 1]]]
    # orient each pair from the later tile (which decides) to the earlier one (already decided)
    later = np.where(tile[pairs[:, 0]] > tile[pairs[:, 1]], pairs[:, 0], pairs[:, 1])
    earlier = np.where(tile[pairs[:, 0]] > tile[pairs[:, 1]], pairs[:, 1], pairs[:, 0])
    accepted = np.zeros(len(xyz), dtype=bool)
    rejections: dict[int, np.ndarray] = {}
    for tile_id in sorted_distinct(tile):
        members = np.flatnonzero(tile == tile_id)
        clash = np.isin(later, members) & accepted[earlier]
        rejected = sorted_distinct(rank[later[clash]])
        chosen = first_accepted(int(candidate_counts[tile_id]), int(budgets[tile_id]), rejected)
        accepted[members] = np.isin(rank[members], chosen)
        if len(rejected):
            rejections[int(tile_id)] = rejected
    return rejections

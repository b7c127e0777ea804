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

from model.rules import identical_runs, sorted_distinct


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
    """Ranks each tile must reject so that no two kept points of different tiles are closer than tolerance.
    Points of one tile at one position are paired as one (identical_groups): a scan with thousands of
    returns at one spot (a sensor's origin, a duplicated export) made close_pairs list every pair among them,
    20k duplicates 4 minutes, though pairs within a tile are never a seam's."""
    bands = [b for b in bands if len(b.ranks)]
    if not bands or tolerance <= 0:
        return {}
    xyz = np.concatenate([b.xyz for b in bands])
    tile = np.concatenate([np.full(len(b.ranks), b.tile_id) for b in bands])
    rank = np.concatenate([b.ranks for b in bands])
    group, first = identical_groups(xyz, tile)
    pairs = close_pairs(xyz[first], tolerance)
    pairs = pairs[tile[first[pairs[:, 0]]] != tile[first[pairs[:, 1]]]]
    # orient each pair from the later tile (which decides) to the earlier one (already decided)
    later_first = tile[first[pairs[:, 0]]] > tile[first[pairs[:, 1]]]
    later = np.where(later_first, pairs[:, 0], pairs[:, 1])
    earlier = np.where(later_first, pairs[:, 1], pairs[:, 0])
    accepted = np.zeros(len(first), dtype=bool)  # by group: any of its points accepted
    rejections: dict[int, np.ndarray] = {}
    for tile_id in sorted_distinct(tile):
        members = np.flatnonzero(tile == tile_id)
        clashing = np.zeros(len(first), dtype=bool)
        clashing[later[accepted[earlier]]] = True
        rejected = sorted_distinct(rank[members[clashing[group[members]]]])
        chosen = first_accepted(int(candidate_counts[tile_id]), int(budgets[tile_id]), rejected)
        accepted[group[members[np.isin(rank[members], chosen)]]] = True
        if len(rejected):
            rejections[int(tile_id)] = rejected
    return rejections


def identical_groups(xyz: np.ndarray, tile: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) each point's group among the (n, 3) points `xyz` of (n,) tiles `tile`, and (groups,) each group's
    first point: a group's points share their tile and coordinates (model.rules.identical_runs: a hash
    collision at most splits a group, which only costs a few more pairs)."""
    order, starts = identical_runs(xyz, tile)
    group = np.empty(len(order), dtype=np.int64)
    group[order] = np.cumsum(starts) - 1
    return group, order[starts]

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
    """Ranks each tile must reject so that no two kept points of different tiles are closer than tolerance:
    tile by tile in id order, a candidate is rejected where a point an earlier tile accepted lies within
    tolerance of it (squared distance summed x, y, z, at most tolerance squared: a pair exactly at the
    tolerance is one, as scipy's query_pairs has it). Each candidate asks for the nearest accepted point of
    each earlier tile whose band reaches its own, so a dense cluster on a seam costs its own points, not their
    pairs (listing every pair within tolerance, a 3 mm blob of 100,000 returns on a tile corner took 261 s);
    a tile's points at one position ask once (identical_groups)."""
    bands = tile_bands(bands) if tolerance > 0 else []
    reach = float(np.nextafter(tolerance, np.inf)) * (1 + 1e-9)  # a margin; the exact rule is applied below
    lows, highs = np.empty((len(bands), 3)), np.empty((len(bands), 3))  # bounds of the accepted bands so far
    trees: list[tuple[np.ndarray, KDTree]] = []
    rejections: dict[int, np.ndarray] = {}
    for band in bands:
        group, first = identical_groups(band.xyz)
        spots = np.ascontiguousarray(band.xyz[first], dtype=np.float64)
        low, high = spots.min(axis=0) - reach, spots.max(axis=0) + reach
        clashing = np.zeros(len(first), dtype=bool)
        reached = np.all(lows[:len(trees)] <= high, axis=1) & np.all(highs[:len(trees)] >= low, axis=1)
        for accepted, tree in (trees[i] for i in np.flatnonzero(reached)):
            _, index = tree.query(spots, k=1, distance_upper_bound=reach)
            found = np.flatnonzero(index < len(accepted))
            offset = spots[found] - accepted[index[found]]
            squared = offset[:, 0] * offset[:, 0] + offset[:, 1] * offset[:, 1] + offset[:, 2] * offset[:, 2]
            clashing[found[squared <= tolerance * tolerance]] = True
        rejected = sorted_distinct(band.ranks[clashing[group]])
        chosen = first_accepted(int(candidate_counts[band.tile_id]), int(budgets[band.tile_id]), rejected)
        accepted = spots[sorted_distinct(group[np.isin(band.ranks, chosen)])]
        if len(accepted):
            lows[len(trees)], highs[len(trees)] = accepted.min(axis=0), accepted.max(axis=0)
            trees.append((accepted, KDTree(accepted)))
        if len(rejected):
            rejections[int(band.tile_id)] = rejected
    return rejections


def tile_bands(bands: Sequence[SeamBand]) -> list[SeamBand]:
    """The non-empty bands in tile order, one per tile (a tile's bands joined)."""
    by_tile: dict[int, list[SeamBand]] = {}
    for band in bands:
        if len(band.ranks):
            by_tile.setdefault(int(band.tile_id), []).append(band)
    return [parts[0] if len(parts) == 1 else SeamBand(tile_id, np.concatenate([b.ranks for b in parts]),
                                                      np.concatenate([b.xyz for b in parts]))
            for tile_id, parts in sorted(by_tile.items())]


def identical_groups(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(n,) each point's group among the (n, 3) points, and (groups,) each group's first point: a group's points
    share their coordinates (model.rules.identical_runs: a hash collision at most splits a group, which only
    costs a query more)."""
    order, starts = identical_runs(xyz)
    group = np.empty(len(order), dtype=np.int64)
    group[order] = np.cumsum(starts) - 1
    return group, order[starts]

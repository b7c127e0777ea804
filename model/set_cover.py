"""The hole cover's picks: a greedy set cover of the points left farther than the radius from every fill pick,
each pick the one of them that brings the most of them within the radius.

Why: the cover used to be farthest point sampling continued from the fill, which takes the point farthest from
every pick first: the outermost stray of a sparse cluster, then the next one out. Cover picks sit off the
surfaces around them, and each enters the 16-point neighbourhoods of the fill picks nearby when a thinned
cloud's curvature is taken: on bcts_1 as one tile at 0.1 (hole radius 1.5x FPS's p99) the cover's 9 % of the
picks raised the squared curvature error of the 37 % of the scan served by fill picks beside them by half, and
the scan's CE by 13 %. A greedy cover needs fewer picks for the same radius (1-14 % on five scans, each as
one tile at 0.1), each centred on what it serves, so the fill keeps more: in pipeline runs at 0.2, 0.1 and
0.05 CE fell on 22 of 24 scan-ratio pairs (by 0.4-5.3 %) for at most 1.5 % more Chamfer and 3 % more p99,
Hausdorff unchanged (README: quality). Picking among every point near a hole, not only its own, lowered CE
more on the forest (6 %) but cost 2-4 % of p99 and Chamfer, past issue 10's bounds on two scans.
"""
from __future__ import annotations

import heapq

import numpy as np
from pykdtree.kdtree import KDTree

INSIDE = 1.0 - 1e-9  # a pick reaches the points strictly inside this share of the radius: within it by any rounding
REACHED = 32  # far points first asked for per far point (a far point of a real scan has about 10 within the radius)
PAIRS = 1 << 22  # pairs a cover tables at most, or REACHED per far point if more (a core holds at most --max-tile-points):
# 200k far points, each with 105 within the radius, tabled 6.2M pairs and peaked at 520 MB (tracemalloc)


def greedy_set_cover(points: np.ndarray, radius: float) -> np.ndarray:
    """Positions among `points` (n, 3) float64 of a greedy cover of them at `radius`, in pick order: each pick is
    the point that brings the most points not yet within the radius of a pick within it (the first such point on
    ties), until every point is.

    The counts only fall as picks are made, so a point's stale count is an upper bound: a heap of the points
    that bring two or more pops one, recounts it, and picks it only if it still leads (lazy greedy, exact). Once
    none brings two, the greedy takes every point that still brings one, in order: for each point still open, the
    first point that reaches it (worked out at once; most picks of a real scan's cover are these)."""
    if len(points) == 0:
        return np.empty(0, dtype=np.int64)
    site_of, target_of = reach_pairs(points, radius)
    counts = np.bincount(site_of, minlength=len(points))
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    uncovered = bytearray(b"\x01") * len(points)
    picks = leading_picks(target_of.tolist(), starts, counts, uncovered)
    is_open = np.frombuffer(bytes(uncovered), dtype=np.uint8).astype(bool)[target_of]
    _, first = np.unique(target_of[is_open], return_index=True)  # pairs ascend by site: the first site per point
    return np.concatenate([np.asarray(picks, dtype=np.int64), np.unique(site_of[is_open][first])])


def leading_picks(targets_of: list[int], starts: np.ndarray, counts: np.ndarray, uncovered: bytearray) -> list[int]:
    """The lazy greedy's picks while some point brings two or more uncovered ones; point p reaches
    targets_of[starts[p]:starts[p] + counts[p]]; marks what the picks bring in `uncovered`."""
    reach = {int(site): targets_of[starts[site]:starts[site] + counts[site]] for site in np.flatnonzero(counts >= 2)}
    heap = [(-len(reached), site) for site, reached in reach.items()]
    heapq.heapify(heap)
    picks: list[int] = []
    while heap:  # every entry brings two or more: one that falls to one waits for the single picks
        stale, site = heapq.heappop(heap)
        count = sum(uncovered[target] for target in reach[site])
        if count < -stale:
            if count > 1:
                heapq.heappush(heap, (-count, site))
            continue
        picks.append(site)
        for target in reach[site]:
            uncovered[target] = 0
    return picks


def reach_pairs(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(p,) picks and (p,) points of pairs within the radius of each other, ascending by pick: each point's
    REACHED nearest within the radius, from a kd-tree (being near is mutual, so a point's row is what it
    reaches; each point reaches itself), asked again with 4x as many for the points with more while the
    pairs (and the search's own table) stay within PAIRS: the memory is bounded whatever the hole. A point
    whose row stays cut is credited with fewer points than it reaches: in so dense a hole the greedy takes
    more picks than it needs, but every point is still brought within the radius."""
    tree = KDTree(points)
    bound = radius * INSIDE
    sites, reached, kept = [], [], 0
    asked, k = np.arange(len(points)), min(REACHED, len(points))
    while len(asked):
        _, index = tree.query(points[asked], k=k, distance_upper_bound=bound)
        index = index.reshape(len(asked), k)
        found = index < len(points)
        wider = min(4 * k, len(points))
        full = found[:, -1] if k < len(points) else np.zeros(len(asked), dtype=bool)
        if kept + int(found[~full].sum()) + int(full.sum()) * wider > max(PAIRS, REACHED * len(points)):
            full[:] = False  # asking again could outgrow the bound: the full rows stay cut
        sites.append(np.repeat(asked[~full], found[~full].sum(axis=1)))
        reached.append(index[~full][found[~full]])
        kept += len(sites[-1])
        asked, k = asked[full], wider
    site_of, target_of = np.concatenate(sites), np.concatenate(reached).astype(np.int64)
    order = np.argsort(site_of, kind="stable")
    return site_of[order], target_of[order]

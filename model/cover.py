"""How many picks a tile needs so that none of its points is farther than a radius from one: the count a
run's survey measures per tile, so a tile's budget floor is what its hole cover really needs.

Why: floors of one point per voxel of edge r (the radius) came out at 1.7-2.1x what farthest point sampling
needs to bring every point within r (six scans at 0.1), so they took 76-100 % of the target and left the
budgets that follow saliency across tiles idle. Farthest point sampling's own numbers give the real count:
its k-th pick is the point farthest from the first k, so its distance to them (its insertion radius) is
exactly how far the first k leave the farthest point, and the fewest picks that cover at r are the picks
before the first whose insertion radius is at most r.
"""
from __future__ import annotations

import numpy as np

from model.baselines import fps_order
from model.geometry import PointTree
from model.rules import most_twins

EARLIER_NEIGHBOURS = 8  # nearest picks of its own block searched for a pick's nearest earlier one (16 gave the
# same radii on a bcts tile, 12 % slower)


def cover_order(points: np.ndarray, count: int) -> np.ndarray:
    """Indices of the first min(count, n) picks of farthest point sampling on `points` (n, 3) from the point
    fps_order's start 0 gives (fpsample, on float32 coordinates; an index repeats once every point is picked):
    the picks a tile's cover is counted with, and the ones a tile at its floor keeps (model.stratified); the
    same points in the same order give the same picks."""
    return fps_order(np.ascontiguousarray(points, dtype=np.float32), min(count, len(points)), 0)


def insertion_radii(points: np.ndarray, picks: np.ndarray) -> np.ndarray:
    """(m,) for `picks` (m,), the first picks of cover_order(points, ...): each pick's distance to the picks
    before it (inf for the first). Worked out in doubling
    blocks: a pick's nearest among the picks before its block (one tree per block), and among the
    EARLIER_NEIGHBOURS nearest of its own block those before it; where its nearest earlier pick is in its
    block but not among those (rare), the value is an upper bound, which only ever asks for more picks. Picks
    past a tile's distinct points are exact twins: a block's tree holds at most EARLIER_NEIGHBOURS of them at
    a position (model.geometry.PointTree), the earliest, so a later twin finds an earlier one at 0; the trees of
    earlier picks hold one. Picks at distinct positions (the usual case) are checked once, not block by block."""
    xyz = np.ascontiguousarray(points[picks], dtype=np.float64)
    distinct = most_twins(xyz) <= 1
    gaps = np.full(len(picks), np.inf)
    first = 1
    while first < len(picks):
        block = xyz[first:min(2 * first, len(picks))]
        before, _ = PointTree.of(xyz[:first], 1, distinct).query(block, 1, squared=False)
        k = min(EARLIER_NEIGHBOURS, len(block))
        distance, index = PointTree.of(block, k, distinct).query(block, k, squared=False)
        earlier = index.reshape(len(block), k) < np.arange(len(block))[:, None]
        within = np.where(earlier, distance.reshape(len(block), k), np.inf).min(axis=1)
        gaps[first:first + len(block)] = np.minimum(before.reshape(-1), within)
        first += len(block)
    return gaps


def cover_counts(points: np.ndarray, count: int, radii: np.ndarray, finest: float | None = None) -> np.ndarray:
    """(g,) for each of `radii` (g,) the number of cover_order picks that leave no point of
    `points` (n, 3) farther than it (a greedy cover: 1.7-2.1x fewer picks than voxels of that edge), or -1
    where the picks sampled (sampled_cover) are too few."""
    if len(points) == 0:
        return np.zeros(len(radii), dtype=np.int64)
    if count <= 0 and finest is None:
        return np.full(len(radii), -1, dtype=np.int64)
    picks, shrinking = sampled_cover(points, count, finest)
    return counts_within(shrinking, radii, complete=len(picks) == len(points))


def sampled_cover(points: np.ndarray, count: int, finest: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The first cover_order picks of `points` (n, 3, not empty), (m,), and (m,) non-increasing the radius the
    picks before each leave covered (inf for the first): `count` of them (at least one), or with `finest` more
    (as many again as a surface would need, the sampling redone) until they cover at `finest` or every point is
    sampled: a tile sparse for a run's hole radius needs more than its share of the count there."""
    sampled = min(max(count, 1), len(points))
    while True:
        picks = cover_order(points, sampled)
        shrinking = np.minimum.accumulate(insertion_radii(points, picks))  # the true radii only shrink
        if finest is None or sampled == len(points) or shrinking[-1] <= finest or not finest > 0:
            return picks, shrinking
        sampled = grown_sample(sampled, float(shrinking[-1]), finest, len(points))


def counts_within(shrinking: np.ndarray, radii: np.ndarray, complete: bool) -> np.ndarray:
    """(g,) for each of `radii` (g,) how many picks cover at it, given `shrinking` (m,), the radius the picks before
    each leave covered (sampled_cover): -1 where m picks may not; `complete`: the picks are every point, so they
    cover at any radius."""
    # the picks before the first whose gap is at most r cover at r: those whose gap exceeds it
    needed = np.searchsorted(-shrinking, -np.asarray(radii, dtype=np.float64), side="left")
    if complete:
        return needed.astype(np.int64)
    return np.where(needed < len(shrinking), needed, -1).astype(np.int64)


def grown_sample(sampled: int, gap: float, finest: float, points: int) -> int:
    """How many of `points` picks to sample after `sampled` left a gap of `gap` (> finest): on a surface the
    picks needed grow with (gap / finest)^2, and a quarter more is asked so one more round nearly always
    does (4x after a single pick, which leaves no gap yet)."""
    growth = (gap / finest) ** 2 if np.isfinite(gap) else 4.0
    return min(points, max(sampled + 1, int(np.ceil(1.25 * sampled * growth))))

"""Classic simplifiers: seeded random, voxel (nearest-to-centre real point) and 3-D farthest point sampling."""
from __future__ import annotations

from typing import Callable

import fpsample
import numpy as np

from model.geometry import curvature, knn, local_eigenvalues
from model.rules import capped_twins, column_max, column_min, distinct_count, kept_count, most_twins, spread_order
from model.selection import Selection, Tile, topped_up

FPS_OVERSHOOT = 1.06  # extra samples asked of FPS over core+halo so enough of them land in the core (none without a halo)
VOXEL_COUNT_SLACK = 0.02  # the searched cell may give up to 2 % more voxels than the budget; the rest are trimmed


def random_simplify(tile: Tile, budget: int) -> Selection:
    """A seeded uniform random sample of the core points; any prefix is itself uniform."""
    core = np.flatnonzero(tile.core)
    order = np.random.default_rng(tile.seed).permutation(core)
    return Selection.of(tile, order[:budget])


def uniform_vertices(vertices: np.ndarray, ratio: float, seed: int = 0) -> np.ndarray:
    """The paper's uniform mesh baseline: round(ratio * V) of the vertices, a seeded random subset.

    It is random_simplify on one tile holding every vertex, so a mesh and a tile sample alike.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    tile = Tile(vertices, np.ones(len(vertices), dtype=bool), np.zeros(3), seed)
    return random_simplify(tile, kept_count(ratio, len(vertices))).xyz


def fps_simplify(tile: Tile, budget: int) -> Selection:
    """Farthest point sampling over the tile's core points; the halo is not used.

    FPS over core+halo keeping core picks (farthest_core_picks) leaves holes along seams: each tile
    counts its halo picks as covering the seam band, but drops them, and the neighbour's own picks lie
    elsewhere. Measured at 0.1 (tiled Hausdorff / untiled FPS's): street 2.1 -> 1.04, lone-star
    1.7 -> 1.10, bcts_1 1.8 -> 1.19, with the same Chamfer and p99.
    """
    core = np.flatnonzero(tile.core)
    if len(core) == len(tile.xyz):
        return farthest_core_picks(tile, budget)
    own = Tile(tile.xyz[core], np.ones(len(core), dtype=bool), tile.centre, tile.seed)
    return Selection.of(tile, core[farthest_core_picks(own, budget).indices])


def farthest_core_picks(tile: Tile, budget: int) -> Selection:
    """Farthest point sampling over core+halo, keeping core picks until `budget` of them are made.

    fpsample's bucket FPS returns points in FPS order; the halo share of the samples is estimated and
    the run repeated with more samples if too few core points came out. Exact duplicates come last.
    """
    budget = min(budget, tile.core_count)
    if budget == 0:
        return Selection.of(tile, np.empty(0, dtype=np.int64))
    n = len(tile.xyz)
    core = np.flatnonzero(tile.core)
    rng = np.random.default_rng(tile.seed)
    start = int(core[rng.integers(len(core))])
    points = np.ascontiguousarray(tile.xyz, dtype=np.float32)
    wanted = budget * n / len(core) * (FPS_OVERSHOOT if n > len(core) else 1.0)  # FPS's order is the same for any count
    while True:
        samples = min(n, int(np.ceil(wanted)) + 1)
        order = first_occurrences(fps_order(points, samples, start))
        picks = order[tile.core[order]]
        if len(picks) >= budget or samples == n:
            return Selection.of(tile, topped_up(picks, core, budget, rng))
        wanted = samples * 1.5 * budget / max(len(picks), 1)


def first_occurrences(order: np.ndarray) -> np.ndarray:
    """Each index once, where it first comes: fpsample repeats indices once every point left coincides
    with a picked one (exact duplicates, all at distance 0)."""
    _, first = np.unique(order, return_index=True)
    return order[np.sort(first)]


def fps_order(points: np.ndarray, samples: int, start: int) -> np.ndarray:
    """Indices of `samples` points in farthest-point order (all points, in FPS order, if samples == n): each pick
    the point farthest from the picks before it. fpsample 1.0.2's kd-line sampling reads `start` as a position in
    its own tree's order, so the first pick is not points[start] but a point fixed by `start`, the points and
    the bucket height (seeded and repeatable all the same; measured: start 0 on 1,000 random points began at
    index 729, its plain `fps_sampling` at 0)."""
    if samples <= 1:
        return np.array([start], dtype=np.int64)
    if most_twins(points) > len(points) >> bucket_height(len(points)):
        held = capped_twins(points, 1)
        if len(held) < len(points):  # not only a collision of position hashes
            return distinct_fps_order(points, held, samples, start)
    return fpsample.bucket_fps_kdline_sampling(points, samples, h=bucket_height(len(points)),
                                               start_idx=start).astype(np.int64)


def distinct_fps_order(points: np.ndarray, held: np.ndarray, samples: int, start: int) -> np.ndarray:
    """fps_order over the first point at each position (`held`: capped_twins(points, 1)), then repeats of the
    first pick up to `samples`, as fpsample repeats once every point left is a twin of a pick: for points of
    which one position holds more than a bucket of fpsample's tree, whose picks there each cost a pass over
    the twins (80,000 twins and 100 other points, 12,000 picks: 2.9 s; a scanner's no-return spot of 400,000
    in one tile, minutes)."""
    order = held[fps_order(np.ascontiguousarray(points[held]), min(samples, len(held)), start % len(held))]
    return np.concatenate([order, np.full(samples - len(order), order[0])])


def bucket_height(points: int) -> int:
    """fpsample's kd-line height h for `points` points (buckets of 2**h <= n points): log2(n) - 8 as fpsample
    advises up to 2**15 points, then about half of log2(n) less one, as the bucket then grows like sqrt(n).
    Measured at a tenth picked, one thread, ms by h: 70k lone-star points h7 31, h8 (log2(n) - 8) 39; 140k h7
    84, h9 124; 200k h7/h8 143, h9 186; 300k h8 262, h9 314; 500k h8 587, h9 609; 35-62k h6 11-29 against h7
    13-28. The picks are still farthest point sampling, from another first point (see fps_order)."""
    levels = int(np.log2(points))
    return max(1, min(levels, int(np.clip(min(levels - 8, levels // 2 - 1), 3, 9))))


def voxel_simplify(tile: Tile, budget: int, slack: float = VOXEL_COUNT_SLACK) -> Selection:
    """One real point per voxel (the one nearest the voxel centre), with the cell size searched so the
    voxel count just meets the budget (at most `slack` over it); voxels are aligned to the scan origin so
    tiles share one grid.

    Representatives come in a progressive order (model.rules.spread_order, its start seeded), so the
    extra ones trimmed to the budget, and any prefix a run or `--levels` keeps, are spread over the tile;
    if even the finest grid gives too few (duplicate points), the rest of the core tops the count up in
    random order.
    """
    budget = min(budget, tile.core_count)
    core = np.flatnonzero(tile.core)
    if budget == 0:
        return Selection.of(tile, np.empty(0, dtype=np.int64))
    points = tile.xyz[core] + tile.centre
    columns, bounds = axis_columns(points), (column_min(points), column_max(points))
    cell = _cell_for_budget(columns, bounds, budget, slack, None if tile.voxels is None else tile.voxels.edge_for(budget))
    reps = core[_voxel_representatives(columns, bounds, cell)]
    rng = np.random.default_rng(tile.seed)
    order = reps[spread_order(tile.xyz[reps], int(rng.integers(len(reps))))]
    return Selection.of(tile, topped_up(order, core, budget, rng))


def axis_columns(points: np.ndarray) -> list[np.ndarray]:
    """The x, y and z columns of (n, 3) points, each contiguous (n,): elementwise work on them ran 4.5x faster
    than on the (n, 3) rows (voxel keys of 30k points, 0.37 against 1.67 ms), with the same values."""
    return [np.ascontiguousarray(points[:, axis]) for axis in range(3)]


def _voxel_keys(columns: list[np.ndarray], cell: float, mins: np.ndarray, maxs: np.ndarray) -> np.ndarray:
    """One int64 key per point (its (n,) x, y, z `columns`) naming its voxel; mins/maxs bound the points
    (floor is monotone, so the lowest voxel index is floor(mins / cell) without another pass over them)."""
    low = np.floor(mins / cell)
    span = (np.floor(maxs / cell) - low + 1).astype(np.int64)
    i, j, k = ((np.floor(column / cell) - lowest).astype(np.int64) for column, lowest in zip(columns, low))
    return (i * span[1] + j) * span[2] + k


def _cell_for_budget(columns: list[np.ndarray], bounds: tuple[np.ndarray, np.ndarray], budget: int,
                     slack: float, start: float | None = None) -> float:
    """A cell size whose occupied-voxel count, for points given as x, y, z `columns` (axis_columns) within
    (3,) mins and maxs `bounds`, is at least the budget and at most `slack` (a share) above it.

    The count falls roughly as a power of the cell size, so each step interpolates in log-log space
    between a cell known to give enough voxels and one known to give too few. Those two are the finest
    cell and one holding everything, or, from a `start` near the answer (a run's survey of the tile), the
    first cells on either side of it (about 4 counts on bcts tiles where the widest bracket took 12).
    """
    mins, maxs = bounds
    extent = float((maxs - mins).max())
    finest = max(extent / 2**20, 1e-6)  # keeps keys within int64 and below the coordinates' precision

    def count(cell: float) -> int:
        return distinct_count(_voxel_keys(columns, cell, mins, maxs))

    if start is None or extent == 0 or budget * (1 + slack) >= len(columns[0]):  # near every point: the finest
        (low, low_count), (high, high_count) = (finest, count(finest)), (extent * 2, 1)  # cell ends it at once
    else:
        (low, low_count), (high, high_count) = _bracket(count, start, budget, slack, (finest, extent * 2))
    if extent == 0 or low_count <= budget * (1 + slack):
        return low
    if high_count >= budget:
        return high
    while high / low > 1 + 1e-9 and low_count > budget * (1 + slack):
        share = (np.log(low_count) - np.log(budget)) / (np.log(low_count) - np.log(high_count))
        mid = float(np.exp(np.log(low) + np.clip(share, 0.05, 0.95) * np.log(high / low)))
        mid_count = count(mid)
        if mid_count >= budget:
            low, low_count = mid, mid_count
        else:
            high, high_count = mid, mid_count
    return low


MIN_CELL_STEP = 1.01  # the least change of cell the bracket search makes
CRAWL_STEPS = 8  # moves before the bracket search's steps grow: a count this slow to cross the budget is on a plateau


def _bracket(count: Callable[[float], int], start: float, budget: int, slack: float,
             limits: tuple[float, float]) -> tuple[tuple[float, int], tuple[float, int]]:
    """(cell, count) pairs from `start` on: one with at least `budget` voxels and one with fewer, or the
    first within `slack` above the budget as both. Steps follow count ~ cell**-2 (a surface's voxels),
    aimed at the middle of the window, and at least MIN_CELL_STEP. After CRAWL_STEPS moves the step's
    power doubles with each move: where the count hardly follows the cell (a plateau of exact duplicates, a
    budget above what any cell gives) the search ends in a few more counts, not hundreds of 1 % moves
    (a bcts tile at ratio 0.99: 604 counts, 0.3 s, before)."""
    finest, coarsest = limits
    aim = budget * (1 + slack / 2)
    cell, enough, too_few, moves = min(max(start, finest), coarsest), None, None, 0
    while True:
        found = (cell, count(cell))
        if found[1] >= budget:
            enough = found
            if found[1] <= budget * (1 + slack) or cell >= coarsest:
                return found, found
        else:
            too_few = found
            if cell <= finest:  # duplicates: even the finest cell gives too few
                return found, found
        if enough is not None and too_few is not None:
            return enough, too_few
        moves += 1  # every move goes the same way: the first count on the other side of the budget ends the search
        step = ((found[1] / aim) ** 0.5) ** (2 ** max(moves - CRAWL_STEPS, 0))
        cell = (min(max(cell * step, finest), cell / MIN_CELL_STEP) if too_few is not None
                else min(max(cell * step, cell * MIN_CELL_STEP), coarsest))


def _voxel_representatives(columns: list[np.ndarray], bounds: tuple[np.ndarray, np.ndarray],
                           cell: float) -> np.ndarray:
    """Index of the point (of x, y, z `columns` within (3,) mins and maxs `bounds`) nearest its voxel
    centre, one per occupied voxel, in voxel-key order; of equally near ones, the first. One sort by key (numpy's
    unstable one: a stable sort took 12 of a 150k-point tile's 17 ms here), then each voxel's least distance and
    the lowest index holding it, whatever order the sort left ties in (a lexsort by key and distance gave the
    same picks 2.6x slower on bcts tiles)."""
    keys = _voxel_keys(columns, cell, *bounds)
    distance = np.zeros(len(keys))
    for column in columns:
        offset = column - (np.floor(column / cell) + 0.5) * cell
        distance += offset * offset
    if len(keys) == 0:
        return np.empty(0, dtype=np.int64)
    order = np.argsort(keys)
    ordered, near = keys[order], distance[order]
    starts = np.flatnonzero(np.diff(ordered, prepend=ordered[0] - 1))
    least = np.repeat(np.minimum.reduceat(near, starts), np.diff(np.append(starts, len(near))))
    holders = np.flatnonzero(near == least)
    voxel = np.searchsorted(starts, holders, side="right")
    first = np.flatnonzero(np.diff(voxel, prepend=-1))
    return np.minimum.reduceat(order[holders], first)


def tcp_simplify(tile: Tile, budget: int) -> Selection:
    """Top curvature points (the paper's TCP baseline): core points by decreasing curvature kappa.

    kappa is estimated over core+halo, so a core point at the tile border sees its neighbours across
    the seam. A prefix is the coarser result. Exact ties (exactly flat patches have kappa 0) fall in a
    seeded random order, so such points come as a uniform sample, not in storage order.
    """
    budget = min(budget, tile.core_count)
    if budget == 0:
        return Selection.of(tile, np.empty(0, dtype=np.int64))
    eigenvalues = local_eigenvalues(tile.xyz, knn(tile.xyz))
    core = np.random.default_rng(tile.seed).permutation(np.flatnonzero(tile.core))
    order = core[np.argsort(-curvature(eigenvalues)[core], kind="stable")]
    return Selection.of(tile, order[:budget])

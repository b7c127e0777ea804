"""Per-tile point budgets that sum exactly to round(ratio * N), by the largest-remainder method."""
from __future__ import annotations

import numpy as np

from model.rules import (MORTON_STEPS, column_max, column_min, distinct_of_sorted, kept_count, morton_codes,
                         sorted_distinct, voxel_edge_for)


def tile_budgets(counts: np.ndarray, ratio: float, floors: np.ndarray | None = None,
                 weights: np.ndarray | None = None, extra: np.ndarray | None = None) -> np.ndarray:
    """Integer budgets <= counts summing to kept_count(ratio, counts.sum()): proportional to `weights`
    (the counts by default; coverage_weights for methods that space points evenly) plus each tile's
    `extra` (a stratified fill's hole cover: hole_voxels), never above a tile's count and never below its
    floor (the runner's: one point per non-empty tile, so no tile's area is left empty).

    Quotas are min(count, max(floor, c * weight + extra)) with c >= 0 chosen so they sum to the target
    (floors and extras scaled down if they alone exceed it); integers by the largest-remainder method,
    ties to the lower tile id.
    """
    return shared_budgets(counts, kept_count(ratio, int(np.sum(counts))), floors, weights, extra)


def grouped_budgets(counts: np.ndarray, ratio: float, groups: np.ndarray, floors: np.ndarray | None = None,
                    weights: np.ndarray | None = None, extra: np.ndarray | None = None) -> np.ndarray:
    """tile_budgets with the tiles of a group (groups: (tiles,) ids; the tiles a split cell became) budgeted
    as one tile, as the unsplit cell would have been, then its budget shared among them in proportion to
    their weights, at least a point each: splitting a crowded cell for memory leaves its points' shares as
    they were (budgeted one by one, each part's floor would pull them towards even spacing)."""
    counts = np.asarray(counts, dtype=np.int64)
    weights = counts.astype(np.float64) if weights is None else np.asarray(weights, dtype=np.float64)
    floors = np.zeros_like(counts) if floors is None else np.asarray(floors, dtype=np.int64)
    extra = np.zeros(len(counts)) if extra is None else np.asarray(extra, dtype=np.float64)
    ids, members = np.unique(groups, return_inverse=True)
    if len(ids) == len(counts):
        return tile_budgets(counts, ratio, floors, weights, extra)
    summed = [np.bincount(members, values, len(ids)) for values in (counts, floors, weights, extra)]
    totals = tile_budgets(summed[0].astype(np.int64), ratio, summed[1].astype(np.int64), summed[2], summed[3])
    budgets = np.zeros_like(counts)
    for group, total in enumerate(totals):
        tiles = np.flatnonzero(members == group)
        budgets[tiles] = shared_budgets(counts[tiles], int(total), np.minimum(counts[tiles], 1), weights[tiles],
                                        extra[tiles])
    return budgets


def shared_budgets(counts: np.ndarray, target: int, floors: np.ndarray | None = None,
                   weights: np.ndarray | None = None, extra: np.ndarray | None = None) -> np.ndarray:
    """tile_budgets for a given total `target` (at most counts.sum())."""
    counts = np.asarray(counts, dtype=np.int64)
    weights = counts.astype(np.float64) if weights is None else np.asarray(weights, dtype=np.float64)
    floors = np.zeros_like(counts) if floors is None else np.minimum(np.asarray(floors, dtype=np.int64), counts)
    extra = np.zeros(len(counts)) if extra is None else np.asarray(extra, dtype=np.float64)
    least = np.minimum(np.maximum(floors, extra), counts)  # the quotas at c = 0
    if least.sum() >= target:
        caps = np.ceil(least - 1e-9).astype(np.int64)
        return largest_remainder(least * (target / max(float(least.sum()), 1e-300)), caps, target)
    low = np.zeros(len(counts), dtype=bool)  # tiles held at their floor
    high = np.zeros(len(counts), dtype=bool)  # tiles held at their count
    while True:
        free = ~(low | high)
        scale = ((target - floors[low].sum() - counts[high].sum() - extra[free].sum())
                 / max(float(weights[free].sum()), 1e-300))
        quotas = scale * weights + extra
        under, over = free & (quotas < floors), free & (quotas > counts)
        if not (under.any() or over.any()):
            break
        # clipped to floors and counts the free quotas sum to the target plus `raised - cut`: if positive, the
        # final rate is lower than this one, so the tiles under their floors stay there (and those over their
        # counts may not); otherwise the ones over their counts stay there. Pinning both sides at once could
        # pin one wrongly for good and miss the total (counts 2000/500, floors 900/1, ratio 0.5: 1,400 for 1,250)
        raised, cut = float((floors[under] - quotas[under]).sum()), float((quotas[over] - counts[over]).sum())
        if raised > cut or not over.any():
            low |= under
        else:
            high |= over
    quotas = np.where(low, floors, np.where(high, counts, quotas))
    return largest_remainder(quotas, counts, target, minimum=floors)


def largest_remainder(quotas: np.ndarray, caps: np.ndarray, target: int, minimum: np.ndarray | None = None) -> np.ndarray:
    """Integers near `quotas`, within [minimum, caps], summing to `target`: floors first, then one more each
    to the largest remainders (stable: ties to the lower index)."""
    budgets = np.minimum(np.floor(quotas + 1e-9).astype(np.int64), caps)
    if minimum is not None:
        budgets = np.maximum(budgets, np.minimum(minimum, caps))
    short = target - int(budgets.sum())
    order = np.argsort(-(quotas - budgets), kind="stable")
    order = order[budgets[order] < caps[order]]
    budgets[order[:short]] += 1
    return budgets


def occupied_voxels(xyz: np.ndarray, sizes: np.ndarray, origin: np.ndarray | None = None) -> np.ndarray:
    """(len(sizes),) number of occupied cubic voxels of each edge length among the (n, 3) points, on grids
    from `origin` (3,) (the points' minimum by default; at most it, so a subset of a cloud is counted on
    the cloud's grids); `sizes` ascending, each twice the one before (the survey's levels), so each
    level's voxels are the last level's occupied ones halved: floor(x / 2s) = floor(x / s) >> 1 exactly,
    since dividing by a power of two is exact in floating point. Once the voxels fit a Z-order code, one
    sort serves every level left, halving being a shift of the sorted codes (1.7x faster than a sort per
    level on bcts tiles)."""
    sizes = np.asarray(sizes, dtype=np.float64)
    if np.any(sizes[1:] != 2 * sizes[:-1]):
        raise ValueError(f"voxel sizes must double from one level to the next, not {sizes.tolist()}")
    counts = np.zeros(len(sizes), dtype=np.int64)
    if len(xyz) == 0:
        return counts
    origin = column_min(xyz) if origin is None else origin
    cells = np.floor((xyz - origin) / sizes[0]).astype(np.int64)  # (m, 3) occupied voxels so far
    level = 0
    while level < len(sizes) and cells.max() >= MORTON_STEPS:  # too many voxels across for a code
        span = column_max(cells) + 1
        if float(span[0]) * float(span[1]) * float(span[2]) < 2.0**63:  # one int64 key per voxel
            keys = sorted_distinct((cells[:, 0] * span[1] + cells[:, 1]) * span[2] + cells[:, 2])
            rows, layer = np.divmod(keys, span[2])
            cells = np.column_stack([*np.divmod(rows, span[1]), layer])
        else:  # a stray point so far off that even a key overflows: distinct rows (slower, exact)
            cells = np.unique(cells, axis=0)
        counts[level] = len(cells)
        cells >>= 1
        level += 1
    if level == len(sizes):
        return counts
    codes = np.sort(morton_codes(cells))
    for level in range(level, len(sizes)):
        codes = distinct_of_sorted(codes)
        counts[level] = len(codes)
        codes >>= np.uint64(3)
    return counts


def coverage_weights(occupied: np.ndarray, sizes: np.ndarray, target: int) -> np.ndarray:
    """Per-tile share of a uniform-spacing pass over the whole scan: each tile's occupied voxels at the
    voxel size whose scan-wide total is `target` (log-log interpolation between the measured sizes).

    occupied: (tiles, levels) counts at `sizes` (ascending). A global FPS or voxel thinning keeps about one
    point per such voxel, so budgets in proportion to these counts make tiles agree on one spacing.
    """
    return voxels_at(occupied, sizes, even_spacing(occupied, sizes, target))


def even_spacing(occupied: np.ndarray, sizes: np.ndarray, target: int) -> float:
    """The voxel edge at which the whole scan has `target` occupied voxels (log-log interpolated): the
    spacing of an even thinning to `target` points, and the finest any `target` points can cover."""
    return voxel_edge_for(occupied.sum(axis=0), sizes, target)


def voxels_at(occupied: np.ndarray, sizes: np.ndarray, size: float) -> np.ndarray:
    """(tiles,) occupied voxels of each tile at voxel edge `size`, log-log interpolated between the measured
    `sizes` (ascending; held at the ends). np.interp's own arithmetic (the same values, to the bit), for every
    tile at once: a run's Chamfer bound plans budgets at about 30 radii, and one np.interp per tile took 7.9 ms
    a call at 5,000 tiles, this 0.6 ms."""
    log_sizes, at = np.log(sizes), np.log(max(size, 1e-300))
    rows = np.log(np.maximum(occupied, 1e-3))  # (tiles, levels)
    if at <= log_sizes[0] or at >= log_sizes[-1]:
        return np.exp(rows[:, 0 if at <= log_sizes[0] else -1])
    below = int(np.searchsorted(log_sizes, at, side="right")) - 1
    slope = (rows[:, below + 1] - rows[:, below]) / (log_sizes[below + 1] - log_sizes[below])
    return np.exp(slope * (at - log_sizes[below]) + rows[:, below])


RADIUS_STEPS = 16  # cover counts per doubling of the radius: a count read at the grid radius just below the
# wanted one is at most 2**(1/16) = 4.4 % finer, about 9 % more picks on a surface (never fewer)


def radius_grid(sizes: np.ndarray) -> np.ndarray:
    """(RADIUS_STEPS * (levels - 1) + 1,) ascending radii from sizes[0] to sizes[-1], 2**(1/RADIUS_STEPS)
    apart: where a survey counts the cover, given its (levels,) doubling voxel sizes."""
    steps = RADIUS_STEPS * (len(sizes) - 1)
    return float(sizes[0]) * 2.0 ** (np.arange(steps + 1) / RADIUS_STEPS)


def count_at(counts: np.ndarray, radii: np.ndarray, radius: float) -> np.ndarray:
    """(tiles,) each tile's cover count at `radius`, read at the grid radius just below it (so never
    fewer picks than it needs); -1 where unknown (the radius is below the grid, or the tile's sample
    fell short). counts: (tiles, g) cover_counts at `radii` (g,)."""
    at = int(np.searchsorted(radii, radius * (1 + 1e-12), side="right")) - 1
    if at < 0:
        return np.full(len(counts), -1, dtype=np.int64)
    return np.asarray(counts)[:, at].astype(np.int64)


def least_covers(covers: np.ndarray, sampled: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """(tiles, g) each tile's cover count at each radius of its survey's grid (radius_grid) from its (tiles, g)
    surveyed `covers`, one more than the (tiles,) picks its survey `sampled` where they fell short (-1: the least
    it can be; the run counts those tiles' own), at most its (tiles,) points `counts`."""
    return np.minimum(np.where(covers < 0, np.asarray(sampled)[:, None] + 1, covers), np.asarray(counts)[:, None])


def feasible_radius(least: np.ndarray, radii: np.ndarray, target: int) -> float:
    """The finest of `radii` (g,) at which the (tiles, g) `least` covers fit in `target` points: below it the
    hole cover cannot be completed (inf where none fits)."""
    fitting = np.flatnonzero(least.sum(axis=0) <= target)
    return float(radii[fitting[0]]) if len(fitting) else float("inf")


def last_over(least: np.ndarray, target: int) -> int:
    """The last column of the (tiles, g) `least` covers (ascending radii) whose counts add up to more than
    `target`, -1 where none does: one farthest point sampling of the whole scan to `target` picks covers at a
    radius past it (the least covers are at most the true counts), so a tile's count is needed there and beyond."""
    over = np.flatnonzero(least.sum(axis=0) > target)
    return int(over[-1]) if len(over) else -1


def one_radius_counts(least: np.ndarray, target: int) -> np.ndarray:
    """(tiles,) the picks each tile's farthest point sampling needs to cover its core at r*, the one radius at
    which the tiles' counts add up to `target`: log-log interpolated between the two columns of the (tiles, g)
    `least` covers that bracket it (last_over and the next; the first or last column where r* is off the grid),
    which must be exact counts there. Why: one sampling of the whole scan covers everywhere at about one radius,
    where the tiles' samplings at their shares of the count cover dense tiles finer than sparse ones."""
    totals = least.sum(axis=0).astype(np.float64)
    below = last_over(least, target)
    if below < 0 or below == least.shape[1] - 1:
        return least[:, max(below, 0)].astype(np.float64)
    return between_columns(least, below, np.log(totals[below] / max(target, 1))
                           / np.log(totals[below] / max(totals[below + 1], 1.0)))


def count_between(least: np.ndarray, radii: np.ndarray, radius: float) -> np.ndarray:
    """(tiles,) each tile's cover count at `radius` from its (tiles, g) `least` covers at `radii` (g,), log-log
    interpolated between the grid radii either side (the end column off the grid): where a run plans the
    budgets its hole radius would give, as its floors are read exactly from each tile's kept picks
    (pipeline.engine.covers.cover_floors; the grid radius below took up to 9 % more picks)."""
    column = int(np.searchsorted(radii, radius * (1 + 1e-12), side="right")) - 1  # a grid radius, within rounding
    if column < 0 or column >= len(radii) - 1:
        return least[:, min(max(column, 0), len(radii) - 1)].astype(np.float64)
    step = max(np.log(radius / radii[column]) / np.log(radii[column + 1] / radii[column]), 0.0)
    return np.ceil(between_columns(least, column, step) * (1 - 1e-12))


def between_columns(least: np.ndarray, column: int, step: float) -> np.ndarray:
    """(tiles,) counts `step` (0 to 1, in log radius) of the way from `least`'s column to the next, log-log
    (a surface's count falls as a power of the radius); 0 for a tile with no points."""
    fine, coarse = (np.maximum(least[:, at], 1).astype(np.float64) for at in (column, column + 1))
    return np.where(least[:, column] > 0, fine * (coarse / fine) ** step, 0.0)


DISC_EDGE = float(np.sqrt(np.pi))  # a hole's cover point serves the points within the cover radius r of it: on a
# surface a disc of area pi r^2, the area of a square of edge sqrt(pi) r. Counted at edge r, the holes came out 5.8x
# the covers' picks on lone-star at 0.1 (9 tiles), at sqrt(pi) r 1.2x


def hole_voxels(occupied: np.ndarray, filled: np.ndarray, sizes: np.ndarray, radius: float) -> np.ndarray:
    """(tiles,) the hole cover's expected picks in each tile at cover radius `radius`: voxels of edge DISC_EDGE x
    radius that hold core points but none of the tile's trial fill (a fill at the scan's rate), each one
    about what one cover pick serves.

    occupied, filled: (tiles, levels) counts at `sizes` of the core's voxels and of its trial fill's (on the
    same grids, so the picks' voxels are among the core's); log-log interpolated, never below 0."""
    edge = DISC_EDGE * radius
    return np.maximum(voxels_at(occupied, sizes, edge) - voxels_at(filled, sizes, edge), 0.0)


def saliency_weights(counts: np.ndarray, levels: np.ndarray, loss_sums: np.ndarray,
                     strength: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Tile weights for tile_budgets and each tile's detail scale, so that tiled keep weights are those of
    one pass over the whole scan: a point's weight is 1 + strength x loss / (the scan's mean loss), and a
    tile holding it gets the sum of its points' weights.

    counts: (tiles,) core positions (model.selection.Tile.positions: exact twins count once, as a fill weighs
    them); levels: (tiles,) mean absolute loss per core point; loss_sums: (tiles,) sums of the relative loss
    (loss / level) over those positions. Scales are strength x level / scan mean (0 if no loss).
    """
    counts = np.asarray(counts, dtype=np.float64)
    levels = np.asarray(levels, dtype=np.float64)
    scan_level = float((counts * levels).sum() / max(counts.sum(), 1.0))
    scales = strength * levels / scan_level if scan_level > 0 else np.zeros_like(levels)
    return counts + scales * np.asarray(loss_sums, dtype=np.float64), scales


def pooled_quantile(quantiles: list[np.ndarray], sizes: np.ndarray, level: float = 0.5) -> float:
    """The `level` quantile (the median by default) of the union of samples, each given by evenly spaced
    quantiles or by its values (its own length may be 0) and the size it stands for (sizes: (samples,)); 0 when
    every sample is empty."""
    values = [q for q in quantiles if len(q)]
    if not values:
        return 0.0
    weights = np.concatenate([np.full(len(q), size / len(q)) for q, size in zip(quantiles, sizes) if len(q)])
    values_flat = np.concatenate(values)
    order = np.argsort(values_flat, kind="stable")
    cumulative = np.cumsum(weights[order])
    return float(values_flat[order][np.searchsorted(cumulative, level * cumulative[-1])])


def nested_budgets(parent: np.ndarray, total: int) -> np.ndarray:
    """(tiles,) budgets summing to `total` <= parent.sum(), each at most the parent's: a coarser level shares
    its points between tiles as the finer one does, so each tile's level is a prefix of its finer level."""
    parent = np.asarray(parent, dtype=np.int64)
    return largest_remainder(parent * (total / max(int(parent.sum()), 1)), parent, total)

"""The hole radius a run's coverage promise allows: the widest at which the output's Chamfer distance, as the
survey estimates it, is at most the method's `chamfer_bound` (model.stratified.CHAMFER_BOUND, 1.3) times
that of an even thinning (farthest point sampling) to the same count: in a run, one sampling of the whole scan
as the tiles stand for it (pipeline.engine.covers.fps_reference); a tile on its own, its own sampling.

Why: the default's radius (a multiple of the fill's typical spacing, never below the even spacing) sits at
1.5-1.7 times FPS's p99 on every shared scan; on the French extra-bytes file, whose detail weights pack the
fill tightly, the Chamfer distance there came out 1.4-1.8x FPS's: sparse areas thinned far below their share
(at 0.1, a radius of 1.26 times FPS's p99 gives 1.30x, its CE still 0.54x the best baseline's). Chamfer
(the mean squared scan-to-result distance) is what such areas cost, and the survey can estimate it: the
trial fill leaves each core point a distance d from its nearest pick; the hole cover brings every point
farther than r within r of a pick (its squared distance then COVERED_SQUARE r^2, on average). In pipeline
runs the estimate over FPS's came out 0.02-0.11 above the measured ratio on the extra-bytes file and autzen
at 0.1, up to 0.07 below it on autzen at 0.2 (where the reference, then each tile's sampling at its share of
the count, was also 5 % above an untiled FPS's: 1.35x measured; against one covering radius for all tiles, 0.3.12,
1.27x). Where the default's radius already keeps the estimate within the bound (bcts, lone-star, the street),
nothing changes.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from model.cover import cover_order
from model.geometry import DISTANCE_QUANTILES, nearest_distance

SAMPLE_POINTS = 4096  # core points a survey measures distances from (an even stride): 2.5 ms on a 31k-point
# bcts tile, about 2 % of its survey and simplify work
COVERED_SQUARE = 1.0 / 3.0  # a covered point's mean squared distance to the cover's picks, over r^2: 0.27-0.36
# measured (three scans as one tile, four radii): a hole's points lie along scan lines (1/3 on a line about its
# middle) more than across a disc (1/2)
EVEN_POINTS = 1 << 17  # a tile on its own takes its even thinning's Chamfer distance from at most this many points:
# farthest point sampling over a 1M-point tile cost 1.7 s, over 110k 0.05 s; on a surface the squared spacing
# follows the area each pick serves, so fewer picks over a stride of the points give it back, scaled: strided
# to 32k points, four scans at three ratios came out at 0.74-1.21x the full sampling's (bcts's canopy, low,
# is no surface)
BISECTIONS = 30  # halvings of the radius interval: far finer than the cover's 2**(1/16) radius grid


def mean_clipped_square(gaps: np.ndarray, radius: float) -> np.ndarray:
    """(tiles,) each tile's estimated mean squared distance to its picks once every point farther than
    `radius` is covered: d^2 up to the radius, COVERED_SQUARE r^2 beyond. gaps: (tiles, q) evenly spaced
    quantiles of d (from 0 to 1), integrated by the trapezoid rule."""
    square = np.where(gaps <= radius, gaps * gaps, COVERED_SQUARE * radius * radius)
    return 0.5 * (square[:, :-1] + square[:, 1:]).mean(axis=1)


def estimated_chamfer(gaps: np.ndarray, stretch: np.ndarray, counts: np.ndarray, radius: float) -> float:
    """The scan's estimated Chamfer distance at hole radius `radius`: tiles' means weighted by their (tiles,)
    core `counts`, each tile's distances times its (tiles,) `stretch` (sqrt of its share of the count over
    its budget: on a surface, spacing grows as the root of the area each pick serves)."""
    return float((mean_clipped_square(gaps * stretch[:, None], radius) * counts).sum() / counts.sum())


def bounded_radius(estimate: Callable[[float], float], limit: float, widest: float, finest: float) -> float:
    """The widest radius in [finest, widest] whose `estimate` (a scan's Chamfer distance at a radius) is at
    most `limit`, by bisection: `widest` itself where it already is, `finest` where none is. The estimate
    is taken to grow with the radius; where budgets planned at each radius make it dip (their floors and
    hole shares move with it), the radius found keeps the bound without being sure to be the widest that does."""
    if widest <= finest or estimate(widest) <= limit:
        return widest
    low, high = finest, widest
    for _ in range(BISECTIONS):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if estimate(middle) <= limit else (low, middle)
    return low


def core_sample(core_xyz: np.ndarray) -> np.ndarray:
    """A tile's sample, (s, 3): an even stride over its core's (c, 3) points, SAMPLE_POINTS to twice as many
    of them (all, for fewer); the same points for the survey, a cover count and a tile on its own."""
    return core_xyz[::max(1, len(core_xyz) // SAMPLE_POINTS)]


def fill_gaps(sample_xyz: np.ndarray, fill_xyz: np.ndarray) -> np.ndarray:
    """(DISTANCE_QUANTILES,) quantiles of the distance from a tile's sample (s, 3: core_sample) to the
    nearest of a fill's points (m, 3)."""
    return np.quantile(nearest_distance(fill_xyz, sample_xyz), DISTANCE_QUANTILES)


def mean_square_distance(sample_xyz: np.ndarray, picks_xyz: np.ndarray) -> float:
    """The mean squared distance from a tile's sample (s, 3) to the nearest of `picks_xyz` (m, 3)."""
    return float(np.mean(nearest_distance(picks_xyz, sample_xyz) ** 2))


def tile_radius(core_xyz: np.ndarray, fill_xyz: np.ndarray, budget: int, widest: float, bound: float) -> float:
    """The hole radius for a tile simplified on its own (no run, no survey: a mesh's vertices, the API on one
    tile): the widest up to `widest` whose estimated Chamfer distance is at most `bound` x that of `budget`
    farthest point picks of the core (c, 3), from the tile's own trial fill's points (m, 3), down to about the
    radius those picks cover."""
    if budget == 0 or len(fill_xyz) == 0:
        return widest
    even_xyz, area_share = even_thinning(core_xyz, budget)
    sample = core_sample(core_xyz)
    even = nearest_distance(even_xyz, sample)
    covered, gaps, one = float(even.max()), fill_gaps(sample, fill_xyz)[None, :], np.ones(1)
    return bounded_radius(lambda radius: estimated_chamfer(gaps, one, one, radius),
                          bound * float(np.mean(even ** 2)) * area_share, widest,
                          min(covered * np.sqrt(area_share), widest))


def even_thinning(core_xyz: np.ndarray, budget: int) -> tuple[np.ndarray, float]:
    """Farthest point picks standing for `budget` of the core (c, 3): (m, 3) picks and the share of the core's
    area each serves over what one of `budget` picks would (squared distances to them scale by it). A core
    of more than EVEN_POINTS is thinned on an even stride of at most that many, with picks in proportion
    (the same share of the points: as many picks on the stride overstated how close the sample's points lie,
    as more of them are picks)."""
    if len(core_xyz) <= EVEN_POINTS:
        return core_xyz[cover_order(core_xyz, budget)], 1.0
    strided = core_xyz[::int(np.ceil(len(core_xyz) / EVEN_POINTS))]
    picks = max(1, round(budget * len(strided) / len(core_xyz)))
    return strided[cover_order(strided, picks)], picks / budget

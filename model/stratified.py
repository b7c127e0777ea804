"""Density-preserving stratified thinning with a coverage guarantee (`--method stratified`).

Why: measured on airborne, terrestrial and simulated mobile scans (bench/quality.py), the curvature
metrics (CE, RE, SDM) reward an output whose local density follows the scan's, as random sampling's
does, while Chamfer and Hausdorff reward even coverage, as FPS's does. Random's weakness is its clumps
and holes, FPS's is that it flattens the density pattern. This method takes each side's strength:

1. fill: every core point has the same chance to be kept, and the picks are drawn by systematic
   sampling along a Morton curve through the tile, so each run of 1/ratio consecutive points on the
   curve keeps one: the density pattern of random sampling without its clumps;
2. cover: points still farther than `COVER_SPACINGS` typical output spacings from every pick (holes in
   sparse areas: far ranges, isolated objects, stray returns) are covered by a greedy set cover
   (model.set_cover: each pick the one of them that brings the most of them within the radius), and
   the fill gives up as many picks, so the count stays exact and no hole is left open
   while the budget can close it.

Picks come in priority order (fill picks in radical-inverse order along the curve, hole picks in the
cover's order, the fullest holes first, interleaved by rank), so a prefix is itself a spread-out,
coarser result.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from model.baselines import first_occurrences
from model.chamfer_bound import tile_radius
from model.cover import cover_order
from model.geometry import DISTANCE_QUANTILES, PointTree, local_features, nearest_distance, nearest_member
from model.rules import distinct_of_sorted, interleaved, radical_inverse_order
from model.selection import FillLoss, Selection, Tile, topped_up
from model.set_cover import greedy_set_cover

COVER_SPACINGS = 2.0  # a point farther than this many typical output spacings from every pick is a hole
CHAMFER_BOUND = 1.3  # a run narrows that radius until the output's estimated Chamfer distance is at most this many
# times an even thinning's (model.chamfer_bound; issue 10's coverage target)
MAX_COVER_ROUNDS = 6  # fill-and-cover rounds before the budget goes to farthest point sampling alone


LossOf = Callable[[Tile, int], FillLoss]


def no_loss(tile: Tile, budget: int) -> FillLoss:
    """Equal chances for every point: the plain stratified fill."""
    return FillLoss(None, 0.0)


def measured_loss(tile: Tile, budget: int) -> FillLoss:
    """The curvature loss of one even thinning of the tile itself (curvature_loss) over its core mean; 0 in
    the halo."""
    loss = np.zeros(len(tile.xyz))
    loss[tile.core] = curvature_loss(tile, budget)
    level = float(loss[tile.core].mean()) if tile.core.any() else 0.0
    return FillLoss(loss / level if level > 0 else np.zeros_like(loss), level)


def stratified_selection(tile: Tile, budget: int, loss_of: LossOf, cover_spacings: float = COVER_SPACINGS,
                         strength: float = 1.0, chamfer_bound: float = CHAMFER_BOUND) -> Selection:
    """The fill and cover of the module doc. For a tile on its own (no `tile.context`), `loss_of(tile,
    budget)` sets the keep weights 1 + strength x relative loss and the cover radius is `cover_spacings`
    typical spacings of a trial fill at strength 1 (so a stronger weighting, which packs its picks closer
    on detail, does not shrink the radius: the run's survey measures spacings so too), narrowed as a run
    narrows its radius to keep `chamfer_bound` (model.chamfer_bound.tile_radius); a pipeline run's
    context holds the scan-wide weights and radius instead, and the prefix the run keeps (fill and cover
    are planned for it; the picks after it are random)."""
    context = tile.context
    budget = min(budget, tile.core_count)
    if budget == 0:
        return Selection.of(tile, np.empty(0, dtype=np.int64))
    planned = budget if context is None or context.kept is None else min(budget, context.kept)
    core = np.flatnonzero(tile.core)
    curve = tile.curve
    rng = np.random.default_rng(tile.seed)
    phase = rng.random()
    loss = loss_of(tile, planned) if context is None else context.loss
    curve_weights = curve_of(keep_weights(tile, loss, strength if context is None else context.detail_scale), curve)
    trial = weighted_picks(curve, curve_weights, planned, phase)
    radius = context.cover_radius if context is not None else own_radius(
        tile, trial if strength == 1.0 else trial_fill(tile, planned, loss, phase), planned, cover_spacings,
        chamfer_bound)
    if context is not None and at_cover_floor(planned, context.cover_count):  # the trial's holes, the fill's first
        # guess, are not covered for nothing there (on the extra-bytes file at 0.1, 23 of 33 tiles)
        fill, cover = np.empty(0, dtype=np.int64), farthest_cover(tile, planned)
    else:
        holes = len(hole_cover(tile.xyz, trial, tile.fillable, radius, curve))
        fill, cover = filled_and_covered(tile, lambda count: weighted_picks(curve, curve_weights, count, phase),
                                         planned, radius, holes)
    order = interleaved(fill[radical_inverse_order(len(fill))], cover)
    return Selection.of(tile, topped_up(topped_up(order, tile.fillable, budget, rng), core, budget, rng))  # twins last


def at_cover_floor(budget: int | np.ndarray, cover_count: int | np.ndarray) -> bool | np.ndarray:
    """Whether a tile's budget (or (tiles,) budgets) is at or under its floor, the picks that cover it at the hole
    radius: no fill fits beside the cover, so farthest point sampling, which covers the tile at that count,
    picks it alone."""
    return np.asarray(budget) <= np.asarray(cover_count)


def own_radius(tile: Tile, trial: np.ndarray, budget: int, cover_spacings: float, chamfer_bound: float) -> float:
    """The hole radius of a tile on its own: `cover_spacings` typical spacings of its trial fill (indices
    `trial`, of `budget` core points), narrowed to keep `chamfer_bound` (model.chamfer_bound.tile_radius)."""
    fill_xyz = tile.xyz[trial]
    core_xyz = tile.xyz if tile.core.all() else tile.xyz[tile.core]
    return tile_radius(core_xyz, fill_xyz, budget, cover_spacings * typical_spacing(fill_xyz), chamfer_bound)


def filled_and_covered(tile: Tile, fill_of: Callable[[int], np.ndarray], budget: int, radius: float,
                       holes: int) -> tuple[np.ndarray, np.ndarray]:
    """A fill of budget - h core points (`fill_of(count)`) and the cover of the holes it leaves, with h the
    cover's own size: the fill gives up `holes` picks (a first guess, from a fill of the whole budget),
    and gives up more while the cover of what it leaves needs more (a smaller fill leaves more holes).
    Each retry gives up the shortfall twice over (the holes grow about as fast again as the fill shrinks),
    so one retry nearly always settles; picks the cover leaves unused are topped up by the caller. If the
    rounds run out unsettled, or leave no fill (a budget at about the tile's cover count: its floor), the
    budget is spent on farthest point sampling alone, which covers the tile once the budget reaches its
    cover count (model.cover), and whose picks are spread at any count (a cut greedy cover's are not;
    nor is a greedy cover of a whole dense tile cheap). A run sends a budget at or under the tile's cover count
    there at once (stratified_selection), as no fill fits beside the cover."""
    holes = min(holes, budget)
    for _ in range(MAX_COVER_ROUNDS):
        if holes == budget:  # no fill left
            break
        fill = fill_of(budget - holes)
        rest = (tile.core if tile.fill_mask is None else tile.fill_mask).copy()  # a twin is covered with its first
        rest[fill] = False
        cover = hole_cover(tile.xyz, fill, np.flatnonzero(rest), radius, tile.curve)
        if len(cover) <= holes:
            return fill, cover
        holes = min(2 * len(cover) - holes, budget)
    return np.empty(0, dtype=np.int64), farthest_cover(tile, budget)


def farthest_cover(tile: Tile, budget: int) -> np.ndarray:
    """`budget` distinct core points in model.cover's cover_order: the picks a run's survey counts a tile's
    cover with, so they cover the core at the hole radius once the budget reaches that count (a budget at
    the tile's floor)."""
    core = np.flatnonzero(tile.core)
    return core[first_occurrences(cover_order(tile.xyz[core], budget))]


def fill_weights(loss: FillLoss, detail_scale: float) -> np.ndarray | None:
    """(n,) keep weights 1 + detail_scale * relative loss: an even share plus a share following the loss
    (None: equal weights)."""
    return None if loss.relative is None else 1.0 + detail_scale * loss.relative


def keep_weights(tile: Tile, loss: FillLoss, detail_scale: float) -> np.ndarray | None:
    """(n,) the fill's keep weights (fill_weights), 0 at exact twins past the first of a position
    (Tile.fill_mask): a fill takes twins only where its count asks for more points than the core has
    positions (topped up); None: equal weights."""
    weights, mask = fill_weights(loss, detail_scale), tile.fill_mask
    if mask is None:
        return weights
    return mask.astype(np.float64) if weights is None else weights * mask


def curve_of(weights: np.ndarray | None, curve: np.ndarray) -> np.ndarray | None:
    """The weights of the points in curve order (None stays None)."""
    return None if weights is None else weights[curve]


def trial_fill(tile: Tile, budget: int, loss: FillLoss, phase: float = 0.5) -> np.ndarray:
    """Indices of the points a fill of `budget` core points with keep weights 1 + relative loss picks (no hole
    cover): what a run's survey measures a tile's spacing and holes on (at phase 0.5), whatever the
    method's loss strength, so the hole radius is the default's for any."""
    curve = tile.curve
    return weighted_picks(curve, curve_of(keep_weights(tile, loss, 1.0), curve), min(budget, tile.core_count), phase)


def pick_spacings(picks: np.ndarray) -> np.ndarray:
    """(len(DISTANCE_QUANTILES),) quantiles of the nearest-pick distance among `picks` (m, 3) (empty below two
    picks): pooled over tiles' trial fills, the scan's typical output spacing."""
    if len(picks) < 2:
        return np.empty(0)
    distance, _ = PointTree.of(np.ascontiguousarray(picks, dtype=np.float64), 2).query(picks, 2, squared=False)
    return np.quantile(distance[:, 1], DISTANCE_QUANTILES)


def curvature_loss(tile: Tile, budget: int, phase: float = 0.5, here: np.ndarray | None = None) -> np.ndarray:
    """(c,) |K(p) - K'(nearest pick)| per core point p, in tile order: how far an even thinning to `budget`
    core points (the stratified fill with equal weights, at `phase`) moves the mean curvature K that CE
    compares (K' on the thinned cloud). It is what CE adds up, point by point, for that thinning. `here`:
    the core's own K (c,), if already known."""
    core = np.flatnonzero(tile.core)
    fill = systematic_picks(tile.curve, budget, phase)
    here = local_features(tile.xyz, core, order=tile.core_order).mean_curvature[core] if here is None else here
    thinned = local_features(tile.xyz[fill], np.arange(len(fill))).mean_curvature  # point_features' values, no normals
    return np.abs(here - thinned[nearest_member(tile.xyz, fill, core)])


def weighted_picks(curve: np.ndarray, weights: np.ndarray | None, count: int, phase: float) -> np.ndarray:
    """`count` points along a curve, each kept with probability proportional to its weight (capped at 1),
    by systematic sampling: the picks are the points whose cumulative probability crosses phase + j."""
    if weights is None:
        return systematic_picks(curve, count, phase)
    if count <= 0:
        return np.empty(0, dtype=np.int64)
    cumulative = np.cumsum(keep_probabilities(weights, count))
    positions = np.searchsorted(cumulative, phase + np.arange(count), side="right")
    return curve[distinct_of_sorted(np.minimum(positions, len(curve) - 1))]  # positions ascend: no sort needed


def keep_probabilities(weights: np.ndarray, count: int) -> np.ndarray:
    """min(1, c * weights) with c such that they sum to `count` (<= len(weights)), or, where fewer points have
    a positive weight, 1 at each of them."""
    probabilities = np.zeros(len(weights))
    free = np.ones(len(weights), dtype=bool)
    left = float(count)
    while free.any():
        if not weights[free].sum() > 0:  # only zero weights left (twins past the first): never picked
            break
        probabilities[free] = weights[free] * (left / weights[free].sum())
        full = free & (probabilities >= 1)
        if not full.any():
            break
        probabilities[full] = 1.0
        free &= ~full
        left = count - float((~free).sum())  # the capped points each hold 1
    return np.minimum(probabilities, 1.0)


def systematic_picks(curve: np.ndarray, count: int, phase: float) -> np.ndarray:
    """`count` of the points listed along a curve, one in each run of len/count consecutive ones, at a
    fixed phase in [0, 1) of the run (systematic sampling): exact count, no two runs share a pick."""
    if count <= 0:
        return np.empty(0, dtype=np.int64)
    positions = np.floor((np.arange(count) + phase) * (len(curve) / count)).astype(np.int64)
    return curve[np.minimum(positions, len(curve) - 1)]


def typical_spacing(points: np.ndarray) -> float:
    """Median distance from each point to its nearest other point (0 for fewer than two points)."""
    if len(points) < 2:
        return 0.0
    points = np.ascontiguousarray(points, dtype=np.float64)
    distance, _ = PointTree.of(points, 2).query(points, 2, squared=False)
    return float(np.median(distance[:, 1]))


def hole_cover(xyz: np.ndarray, kept: np.ndarray, candidates: np.ndarray, radius: float,
               curve: np.ndarray | None = None) -> np.ndarray:
    """Candidates that bring every candidate within `radius` of a pick, in pick order: a greedy set cover
    (model.set_cover) of the candidates farther than `radius` from the kept points (all of them when none is
    kept), each pick the one of them that brings the most of them within it, so the holes with the most
    points are closed first. `curve`: the tile's curve (Tile.curve), holding every kept point and
    candidate, if the caller has it (fewer distances are then queried)."""
    if len(candidates) == 0 or radius <= 0:
        return np.empty(0, dtype=np.int64)
    if len(kept) == 0:
        distance = np.full(len(candidates), np.inf)
    else:
        distance = np.zeros(len(candidates))
        open_ = np.arange(len(candidates)) if curve is None else np.flatnonzero(~near_along(xyz, kept, candidates,
                                                                                             radius, curve))
        distance[open_] = nearest_distance(xyz[kept], xyz[candidates[open_]])
    far = candidates[distance > radius]
    if len(far) == 0:
        return far.astype(np.int64)
    return far[greedy_set_cover(np.ascontiguousarray(xyz[far], dtype=np.float64), radius)]


def near_along(xyz: np.ndarray, kept: np.ndarray, candidates: np.ndarray, radius: float,
               curve: np.ndarray) -> np.ndarray:
    """(m,) bool: candidates surely within `radius` of a kept point, as the kept point before or after them
    on the tile's Z-order `curve` is (with a margin of 1e-9 of the radius, so the tree would say so too).
    On bcts_1+2's tiles that settled 91 % of the fills' candidates, and the covers' distances took 0.8-0.9 s
    instead of 1.3-1.8 s (one thread), with the same covers. Worked out for every point of the curve, in
    curve order (each one's kept neighbours then lie at rising positions: gathers that walk memory in
    order), then read at the candidates: 0.60 -> 0.46 s on those tiles against gathering at the candidates."""
    position = np.full(len(xyz), -1, dtype=np.int64)
    position[curve] = np.arange(len(curve))
    is_kept = np.zeros(len(curve), dtype=bool)
    is_kept[position[kept]] = True
    kept_at = np.flatnonzero(is_kept)  # curve positions of the kept points, ascending
    before = np.cumsum(is_kept) - is_kept  # kept points strictly before each position: the next one's rank
    near = np.zeros(len(curve), dtype=bool)
    reach = (radius * (1 - 1e-9)) ** 2
    columns = [xyz[curve, axis] for axis in range(3)]
    for beside in (kept_at[np.maximum(before - 1, 0)], kept_at[np.minimum(before, len(kept_at) - 1)]):
        squared = np.zeros(len(curve))
        for column in columns:
            offset = column - column[beside]
            squared += offset * offset
        near |= squared <= reach
    return near[position[candidates]]

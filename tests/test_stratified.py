"""Stratified thinning: the scan's density pattern where it is dense, no hole where it is sparse."""
import numpy as np
import pytest
from scipy.spatial import cKDTree

from model import Tile, get_simplifier
from model.rules import radical_inverse_order
from model import set_cover
from model.selection import FillContext, FillLoss
from model.stratified import hole_cover, near_along, systematic_picks, typical_spacing


def dense_beside_sparse(seed: int = 0) -> tuple[Tile, np.ndarray]:
    """A 20 x 20 m plane sampled 100x denser on its left half than on its right: (tile, sparse mask)."""
    rng = np.random.default_rng(seed)
    dense = rng.uniform([0, 0], [10, 20], size=(40_000, 2))
    sparse = rng.uniform([10, 0], [20, 20], size=(400, 2))
    xy = np.concatenate([dense, sparse])
    xyz = np.column_stack([xy, rng.normal(0, 0.005, len(xy))])
    is_sparse = np.arange(len(xyz)) >= len(dense)
    return Tile(xyz - xyz.mean(0), np.ones(len(xyz), bool), np.zeros(3), seed=4), is_sparse


@pytest.mark.parametrize("method", ["stratified", "learned"])
def test_dense_side_keeps_its_share_and_sparse_side_has_no_hole(method):
    tile, is_sparse = dense_beside_sparse()
    budget = round(0.05 * len(tile.xyz))
    kept = get_simplifier(method)(tile, budget).indices
    spacing = typical_spacing(tile.xyz[kept])
    # every sparse point lies within two output spacings of a pick; random leaves most of them farther
    gap = cKDTree(tile.xyz[kept]).query(tile.xyz[is_sparse])[0]
    random_gap = cKDTree(tile.xyz[get_simplifier("random")(tile, budget).indices]).query(tile.xyz[is_sparse])[0]
    assert gap.max() <= 2 * spacing * (1 + 1e-9) and (random_gap > 2 * spacing).mean() > 0.5
    # the dense side still holds nearly all of its proportional share (random's pattern)
    assert (~is_sparse[kept]).sum() > 0.85 * budget * (~is_sparse).mean()


def test_covering_radius_close_to_fps_and_far_below_random():
    tile, is_sparse = dense_beside_sparse(1)
    budget = 1_000
    gaps = {m: cKDTree(tile.xyz[get_simplifier(m)(tile, budget).indices]).query(tile.xyz)[0].max()
            for m in ("stratified", "fps", "random")}
    assert gaps["stratified"] < 0.5 * gaps["random"]
    assert gaps["stratified"] < 3 * gaps["fps"]


def test_systematic_picks_one_per_run_along_the_curve():
    curve = np.arange(1_000)[::-1]
    picks = systematic_picks(curve, 100, 0.5)
    assert len(np.unique(picks)) == 100
    np.testing.assert_array_equal(np.sort(picks // 10), np.arange(100))  # one in each run of 10


def test_radical_inverse_prefixes_spread_over_the_range():
    order = radical_inverse_order(1_000)
    assert sorted(order) == list(range(1_000))
    for prefix in (4, 16, 100):
        gaps = np.diff(np.sort(order[:prefix]))
        assert gaps.max() <= 2.5 * 1_000 / prefix


def test_hole_cover_brings_every_far_point_within_the_radius():
    rng = np.random.default_rng(2)
    xyz = np.column_stack([rng.uniform(0, 10, size=(5_000, 2)), np.zeros(5_000)])
    kept = np.flatnonzero(xyz[:, 0] < 2)[:50]  # picks only on the left strip
    candidates = np.setdiff1d(np.arange(len(xyz)), kept)
    cover = hole_cover(xyz, kept, candidates, 1.0)
    distance = cKDTree(xyz[np.concatenate([kept, cover])]).query(xyz[candidates])[0]
    assert distance.max() <= 1.0 and 0 < len(cover) < 200


def test_same_picks_wherever_the_tile_sits():
    """Only relative positions matter (up to round-off at Morton cell borders: 99 % of picks equal)."""
    tile, _ = dense_beside_sparse(3)
    moved = Tile(tile.xyz + [1234.5, -77.0, 3.0], tile.core, tile.centre, tile.seed)
    here = get_simplifier("stratified")(tile, 900).indices
    there = get_simplifier("stratified")(moved, 900).indices
    assert len(np.intersect1d(here, there)) >= 0.99 * 900


def test_thin_pole_on_a_dense_plane_keeps_its_whole_height():
    """A 10 m pole of 300 points on a plane of 60,000: at 0.01 random keeps about 3 pole points and leaves
    metres of it bare; stratified covers the pole from foot to top."""
    rng = np.random.default_rng(7)
    plane = np.column_stack([rng.uniform(0, 30, size=(60_000, 2)), rng.normal(0, 0.01, 60_000)])
    height = rng.uniform(0, 10, 300)
    angle = rng.uniform(0, 2 * np.pi, 300)
    pole = np.column_stack([15 + 0.05 * np.cos(angle), 15 + 0.05 * np.sin(angle), height])
    xyz = np.concatenate([plane, pole])
    tile = Tile(xyz - xyz.mean(0), np.ones(len(xyz), bool), np.zeros(3), seed=1)
    budget = round(0.01 * len(xyz))
    on_pole = np.arange(len(xyz)) >= len(plane)
    gaps = {m: cKDTree(tile.xyz[get_simplifier(m)(tile, budget).indices]).query(tile.xyz[on_pole])[0].max()
            for m in ("stratified", "random")}
    spacing = typical_spacing(tile.xyz[get_simplifier("stratified")(tile, budget).indices])
    assert gaps["stratified"] <= 2 * spacing * (1 + 1e-9) < gaps["random"]


def scattered_returns_over_a_plane(seed: int = 5) -> Tile:
    """A dense 40 x 40 m plane and 3,000 stray returns scattered 1-9 m above it: many small holes, so a
    fill that gives points up to the cover leaves more holes than the fill of the whole budget did."""
    rng = np.random.default_rng(seed)
    plane = np.column_stack([rng.uniform(0, 40, size=(80_000, 2)), rng.normal(0, 0.01, 80_000)])
    strays = np.column_stack([rng.uniform(0, 40, size=(3_000, 2)), rng.uniform(1, 9, 3_000)])
    xyz = np.concatenate([plane, strays])
    return Tile(xyz - xyz.mean(0), np.ones(len(xyz), bool), np.zeros(3), seed=2)


@pytest.mark.parametrize("method", ["stratified", "learned"])
def test_kept_prefix_leaves_no_point_beyond_the_radius_when_a_reserve_follows(method):
    """A run keeps `kept` picks of budget + reserve: those alone bring every point within the cover radius,
    however many holes the shrunk fill opens (the old cover was cut to a first guess of their number, and
    the reserve cut its tail: stray returns and wire stretches were left metres from any pick)."""
    tile = scattered_returns_over_a_plane()
    kept, reserve, radius = 4_000, 200, 1.2
    context = FillContext(FillLoss(None, 0.0), 0.0, radius, kept=kept)
    order = get_simplifier(method)(Tile(tile.xyz, tile.core, tile.centre, tile.seed, context), kept + reserve).indices
    assert len(order) == kept + reserve == len(np.unique(order))
    gap = cKDTree(tile.xyz[order[:kept]]).query(tile.xyz)[0]
    assert gap.max() <= radius


def test_hole_cover_needs_fewer_picks_than_farthest_point_sampling_and_takes_the_fullest_holes_first():
    """Stray returns over a plane: the greedy cover closes every hole with fewer picks than farthest point
    sampling continued from the kept points needs at the same radius, and each pick brings no more newly
    covered strays than the one before it."""
    tile = scattered_returns_over_a_plane(6)
    xyz, radius = tile.xyz, 1.0
    kept = np.arange(0, 80_000, 20)  # the plane only
    candidates = np.setdiff1d(np.arange(len(xyz)), kept)
    cover = hole_cover(xyz, kept, candidates, radius)
    assert cKDTree(xyz[np.concatenate([kept, cover])]).query(xyz[candidates])[0].max() <= radius
    far = candidates[cKDTree(xyz[kept]).query(xyz[candidates])[0] > radius]
    gap, fps = cKDTree(xyz[kept]).query(xyz[far])[0], 0
    while gap.max() > radius:  # farthest point sampling continued from the kept points, brute force
        pick = int(np.argmax(gap))
        gap = np.minimum(gap, np.linalg.norm(xyz[far] - xyz[far[pick]], axis=1))
        fps += 1
    assert len(cover) < fps
    newly, open_ = [], np.ones(len(far), dtype=bool)
    for pick in cover:
        reached = open_ & (np.linalg.norm(xyz[far] - xyz[pick], axis=1) < radius)
        newly.append(reached.sum())
        open_ &= ~reached
    assert np.all(np.diff(newly) <= 0) and newly[0] > 1 and not open_.any()


def test_a_budget_too_small_for_the_holes_is_spent_as_farthest_point_sampling():
    """When covering at the radius would take more than the whole budget, no fill is left and every pick
    covers (FPS from scratch): the gaps stay FPS's, not those of the random top-up that filled in before."""
    rng = np.random.default_rng(8)
    xyz = rng.uniform(0, 10, size=(4_000, 3))
    tile = Tile(xyz - xyz.mean(0), np.ones(len(xyz), bool), np.zeros(3), seed=3)
    context = FillContext(FillLoss(None, 0.0), 0.0, 0.05, kept=60)
    picks = get_simplifier("stratified")(Tile(tile.xyz, tile.core, tile.centre, tile.seed, context), 60).indices
    assert len(np.unique(picks)) == 60
    gap = cKDTree(tile.xyz[picks]).query(tile.xyz)[0].max()
    fps_gap = cKDTree(tile.xyz[get_simplifier("fps")(tile, 60).indices]).query(tile.xyz)[0].max()
    random_gap = cKDTree(tile.xyz[get_simplifier("random")(tile, 60).indices]).query(tile.xyz)[0].max()
    assert gap <= 1.2 * fps_gap < random_gap


def brute_force_greedy_cover(xyz: np.ndarray, kept: np.ndarray, candidates: np.ndarray, radius: float) -> list[int]:
    """The greedy set cover by its definition, O(n^2): far = candidates beyond the radius of every kept point;
    repeatedly the first far point (in candidate order) that brings the most open far points within the radius."""
    gap = (np.sqrt(((xyz[candidates, None] - xyz[None, kept]) ** 2).sum(-1)).min(axis=1) if len(kept)
           else np.full(len(candidates), np.inf))
    far = candidates[gap > radius]
    reaches = np.sqrt(((xyz[far, None] - xyz[None, far]) ** 2).sum(-1)) < radius * (1 - 1e-9)
    open_, picks = np.ones(len(far), dtype=bool), []
    while open_.any():
        best = int(np.argmax((reaches & open_).sum(axis=1)))
        picks.append(int(far[best]))
        open_ &= ~reaches[best]
    return picks


def test_hole_cover_is_the_brute_force_greedy_cover_where_a_pick_reaches_many():
    """With tight clusters of 24 far points (each reaching the whole cluster) beside sparse strays, the cover
    must pick exactly what the greedy set cover by its definition picks."""
    rng = np.random.default_rng(7)
    clusters = np.repeat(rng.uniform(0, 30, (12, 3)), 24, axis=0) + rng.normal(0, 0.05, (288, 3))
    xyz = np.concatenate([clusters, rng.uniform(0, 30, (300, 3))])
    kept = np.arange(0, len(xyz), 97)
    candidates = np.setdiff1d(np.arange(len(xyz)), kept)
    expected = brute_force_greedy_cover(xyz, kept, candidates, 0.8)
    assert len(expected) > 12
    np.testing.assert_array_equal(hole_cover(xyz, kept, candidates, 0.8), expected)


def test_hole_cover_of_a_hole_denser_than_its_pairs_can_hold_still_covers_it(monkeypatch):
    """The pairs a cover tables stay within a bound (the memory, whatever the hole), here lowered to 20,000: in a
    hole of 3,000 far points within a few radii (450,000 pairs), some duplicated 40 times over, a pick is
    credited with fewer points than it reaches, and every one of them must still end within the radius."""
    monkeypatch.setattr(set_cover, "PAIRS", 20_000)
    rng = np.random.default_rng(9)
    dense = np.concatenate([rng.normal(0, 0.6, (2_600, 3)), np.repeat(rng.normal(0, 0.6, (10, 3)), 40, axis=0)])
    xyz = np.concatenate([[[20.0, 0.0, 0.0]], dense])
    candidates = np.arange(1, len(xyz))
    assert len(set_cover.reach_pairs(dense, 0.5)[0]) <= 32 * len(dense)
    cover = hole_cover(xyz, np.array([0]), candidates, 0.5)
    assert len(np.unique(cover)) == len(cover) and 0 < len(cover) < 600
    assert cKDTree(xyz[cover]).query(xyz[candidates])[0].max() <= 0.5


def test_hole_cover_with_nothing_kept_covers_every_candidate_as_the_greedy_does():
    """With no kept point every candidate is far: the cover is the greedy set cover of them all."""
    rng = np.random.default_rng(12)
    xyz = np.concatenate([rng.uniform(0, 10, (400, 3)), rng.normal(5, 0.02, (20, 3))])
    candidates = np.arange(3, len(xyz))
    cover = hole_cover(xyz, np.empty(0, dtype=np.int64), candidates, 1.5)
    np.testing.assert_array_equal(cover, brute_force_greedy_cover(xyz, np.empty(0, dtype=np.int64), candidates, 1.5))
    assert cKDTree(xyz[cover]).query(xyz[candidates])[0].max() <= 1.5 and 1 < len(cover) < len(candidates) // 3


def test_candidates_settled_along_the_curve_are_within_reach_and_the_cover_is_unchanged():
    """near_along settles a candidate by the kept points before and after it on the tile's curve, so the
    tree is asked only for the rest: what it settles must be within the radius, it must settle most of the
    candidates within it of an even fill, and the cover must be the one of asking the tree for every candidate."""
    rng = np.random.default_rng(11)
    xyz = np.concatenate([rng.uniform(0, 20, (6_000, 3)) * [1, 1, 0.05], rng.uniform(0, 40, (200, 3))])
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    for count, radius in ((600, 1.0), (600, 0.3), (60, 2.0)):
        kept = systematic_picks(tile.curve, count, 0.5)
        candidates = np.setdiff1d(np.arange(len(xyz)), kept)
        near = near_along(xyz, kept, candidates, radius, tile.curve)
        distance = cKDTree(xyz[kept]).query(xyz[candidates])[0]
        assert (distance[near] <= radius).all() and near.sum() > 0.7 * (distance <= radius).sum() > 0
        np.testing.assert_array_equal(hole_cover(xyz, kept, candidates, radius, tile.curve),
                                      hole_cover(xyz, kept, candidates, radius))


def sheet_with_a_spot(twins: int = 4_000, seed: int = 5) -> Tile:
    """A 20 x 20 m plane of 8,000 points and a scanner's no-return spot: `twins` exact copies of one point above it."""
    rng = np.random.default_rng(seed)
    plane = np.column_stack([rng.uniform(0, 20, size=(8_000, 2)), rng.normal(0, 0.005, 8_000)])
    xyz = np.concatenate([np.repeat([[10.0, 10.0, 1.5]], twins, axis=0), plane])
    return Tile(xyz - 10.0, np.ones(len(xyz), bool), np.zeros(3), seed=6)


@pytest.mark.parametrize("method", ["stratified", "learned"])
def test_a_fill_keeps_one_point_of_a_spot_of_twins_until_the_count_asks_for_more_than_the_positions(method):
    """Exact twins add no shape: the fill weighs them 0, so the spot keeps one point and the plane the rest; a
    budget past the tile's positions keeps every position and tops up with twins."""
    tile = sheet_with_a_spot()
    assert tile.positions == 8_001 and tile.fill_mask.sum() == 8_001 and not tile.fill_mask[1:4_000].any()
    at_spot = np.arange(len(tile.xyz)) < 4_000
    kept = get_simplifier(method)(tile, 1_200).indices
    assert len(np.unique(kept)) == 1_200 and at_spot[kept].sum() == 1
    everything = get_simplifier(method)(tile, 9_000).indices
    assert len(np.unique(everything)) == 9_000 and (~at_spot[everything]).sum() == 8_000
    assert Tile(tile.xyz[4_000:], np.ones(8_000, bool), np.zeros(3), 6).fill_mask is None  # no twins: as before

"""Cover counts: how many farthest-point picks leave no point beyond a radius (a run's tile floors)."""
from __future__ import annotations

import fpsample
import numpy as np
from scipy.spatial import cKDTree

from model import Tile, get_simplifier
from model.baselines import bucket_height, fps_order
from model.cover import cover_counts, insertion_radii
from model.selection import FillContext, FillLoss
from tiling.budgets import count_at, count_between, occupied_voxels, radius_grid, voxels_at


def plane_with_strays(seed: int = 0) -> np.ndarray:
    """(23,000, 3): a 40 m noisy plane and stray returns 1-9 m above it (a 2-D and a 3-D part)."""
    rng = np.random.default_rng(seed)
    plane = np.column_stack([rng.uniform(0, 40, size=(20_000, 2)), rng.normal(0, 0.01, 20_000)])
    strays = np.column_stack([rng.uniform(0, 40, size=(3_000, 2)), rng.uniform(1, 9, 3_000)])
    return np.concatenate([plane, strays])


def largest_gap(xyz: np.ndarray, picks: np.ndarray) -> float:
    return float(cKDTree(xyz[picks]).query(xyz)[0].max())


def test_insertion_radii_are_each_picks_distance_to_the_picks_before_it():
    xyz = plane_with_strays()
    order = fps_order(xyz.astype(np.float32), 1_500, 0)
    gaps = insertion_radii(xyz, order)
    picks = xyz[order]
    brute = [np.inf] + [float(np.sqrt(((picks[:k] - picks[k]) ** 2).sum(axis=1)).min()) for k in range(1, 1_500)]
    np.testing.assert_allclose(gaps, brute)


def test_farthest_point_sampling_stays_exact_with_buckets_that_grow_like_the_square_root_of_the_points():
    """fpsample's buckets of 2**h points: log2(n) - 8 up to 2**15 points, then about sqrt(n)/2 (measured
    faster: model.baselines.bucket_height); each pick is still the point farthest from the picks before it."""
    assert [bucket_height(n) for n in (100, 9_600, 26_000, 40_000, 70_000, 140_000, 300_000, 1_000_000)] == [
        3, 5, 6, 6, 7, 7, 8, 8]
    assert all(2 ** bucket_height(n) <= n for n in range(2, 70_000, 997))
    xyz = np.random.default_rng(3).uniform(0, 50, size=(70_000, 3))  # float distances: no ties
    order = fps_order(xyz.astype(np.float32), 60, 0)
    nearest = np.sqrt(((xyz - xyz[order[0]]) ** 2).sum(axis=1))  # fpsample starts where its tree puts `start`
    for pick in order[1:]:
        assert nearest[pick] == nearest.max()
        nearest = np.minimum(nearest, np.sqrt(((xyz - xyz[pick]) ** 2).sum(axis=1)))


def test_farthest_point_sampling_of_a_spot_of_twins_picks_each_position_once_then_repeats_as_fpsample_does():
    """A position holding more points than a bucket of fpsample's tree (a scanner's no-return spot) costs fpsample
    a pass over the twins for each pick past the distinct points: the sampling runs on one point of each
    position instead, still farthest point sampling, and then repeats its first pick as fpsample repeats once
    every point left is a twin of a pick; insertion radii read those repeats as 0."""
    xyz = np.concatenate([np.zeros((5_000, 3)), plane_with_strays()[:1_000]])
    order = fps_order(xyz.astype(np.float32), 1_500, 7)
    assert len(order) == 1_500 and len(np.unique(order)) == 1_001
    assert set(order[:1_001].tolist()) >= set(range(5_000, 6_000)) and (order[1_001:] == order[0]).all()
    nearest = np.sqrt(((xyz - xyz[order[0]]) ** 2).sum(axis=1))
    for pick in order[1:1_001]:  # each pick the point farthest from the picks before it
        assert nearest[pick] == nearest.max()
        nearest = np.minimum(nearest, np.sqrt(((xyz - xyz[pick]) ** 2).sum(axis=1)))
    gaps = insertion_radii(xyz, order)
    assert (gaps[1_001:] == 0).all() and gaps[1_000] > 0
    few = np.concatenate([np.zeros((3, 3)), xyz[5_000:]])  # fewer twins than a bucket: fpsample's own order
    assert fps_order(few.astype(np.float32), 500, 7).tolist() == fpsample.bucket_fps_kdline_sampling(
        few.astype(np.float32), 500, h=bucket_height(len(few)), start_idx=7).tolist()


def test_a_cover_count_of_picks_leaves_no_point_beyond_the_radius_and_one_fewer_does():
    xyz = plane_with_strays(1)
    radii = np.array([0.8, 1.2, 2.0, 4.0])
    counts = cover_counts(xyz, 2_000, radii, finest=0.8)
    order = fps_order(xyz.astype(np.float32), int(counts.max()), 0)
    assert np.all(np.diff(counts) < 0)
    for radius, count in zip(radii, counts):
        assert largest_gap(xyz, order[:count]) <= radius < largest_gap(xyz, order[:count - 1])


def test_a_cover_needs_about_half_the_voxels_of_its_radius_on_a_surface():
    """The floors this replaces: one point per voxel of edge r, about twice what a cover at r needs."""
    xyz = plane_with_strays(2)[:20_000]  # the plane alone
    sizes = 0.5 * 2.0 ** np.arange(5)
    counts = count_at(cover_counts(xyz, 2_000, radius_grid(sizes), finest=1.0)[None], radius_grid(sizes), 1.0)[0]
    voxels = voxels_at(occupied_voxels(xyz, sizes)[None], sizes, 1.0)[0]
    assert 0.3 * voxels < counts < 0.7 * voxels


def test_counts_are_sampled_on_until_the_finest_radius_and_unknown_below_it():
    """A sparse tile needs more than its share at the scan's radius: its first picks (10 here) are not enough,
    so it samples on until they cover at `finest`; finer radii than the picks reached stay unknown (-1)."""
    xyz = plane_with_strays(3)
    radii = np.array([0.05, 1.0, 3.0])
    counts = cover_counts(xyz, 10, radii, finest=1.0)
    assert counts[0] == -1 and counts[1] > 10 and 0 < counts[2] < counts[1]
    np.testing.assert_array_equal(counts[1:], cover_counts(xyz, 5_000, radii, finest=1.0)[1:])
    assert np.all(cover_counts(xyz[:50], 10, radii, finest=0.01) >= 1)  # all sampled: every radius known
    assert cover_counts(xyz, 10, radii)[1] == -1  # no finest: the first picks alone
    np.testing.assert_array_equal(cover_counts(xyz, 1, radii, finest=1.0)[1:], counts[1:])  # one pick: no gap yet


def test_count_at_reads_the_grid_radius_just_below_and_unknown_below_the_grid():
    radii = radius_grid(np.array([1.0, 2.0]))
    counts = np.arange(len(radii))[::-1][None] + 5
    assert len(radii) == 17 and radii[-1] == 2.0
    assert count_at(counts, radii, radii[3] * 1.01)[0] == counts[0, 3]
    assert count_at(counts, radii, radii[3])[0] == counts[0, 3]
    assert count_at(counts, radii, 0.99)[0] == -1


def test_planned_floors_are_read_between_the_grid_radii_either_side():
    """Halfway (in log radius) between radii counted 400 and 100, a surface's count is 200 (rounded up); on a
    grid radius its own count; off the grid the end column; an empty tile 0."""
    radii = np.array([1.0, 2.0, 4.0])
    least = np.array([[400, 100, 25], [0, 0, 0]])
    assert count_between(least, radii, np.sqrt(2.0)).tolist() == [200.0, 0.0]
    assert count_between(least, radii, 2.0).tolist() == [100.0, 0.0]
    assert count_between(least, radii, 0.5).tolist() == [400.0, 0.0]
    assert count_between(least, radii, 9.0).tolist() == [25.0, 0.0]


def test_a_budget_at_the_cover_count_still_covers_the_tile():
    """A tile at its floor gets just the picks a cover needs: the fill-and-cover rounds cannot settle there
    (each smaller fill leaves more holes), so the budget goes to farthest point sampling alone, which is
    what the count counted; a run tells the tile its count, and it skips the rounds (on the street, five
    tiles ran all six, each a hole cover). Before, the rounds ran out and the cover was cut: points were
    left past the radius."""
    xyz = plane_with_strays(4)
    xyz -= xyz.mean(axis=0)
    core = np.ones(len(xyz), dtype=bool)
    radius = 1.5
    budget = int(cover_counts(xyz, 1_000, np.array([radius]), radius)[0])
    for counted in (0, budget):  # the run's count unknown to the tile (the rounds run out), or known: no rounds
        context = FillContext(FillLoss(None, 0.0), 0.0, radius, kept=budget, cover_count=counted)
        picks = get_simplifier("stratified")(Tile(xyz, core, np.zeros(3), 1, context), budget).indices
        assert len(np.unique(picks)) == budget
        assert largest_gap(xyz, picks) <= radius * (1 + 1e-6)  # farthest point sampling on float32 coordinates


def test_a_tiles_own_count_starts_from_what_its_surveys_gap_asks_for():
    """A tile whose survey's picks (1.5x its share) fell short at the run's radius counts again from as many
    picks as the gap they left asks for (the finest grid radius they covered at), not from them again; with no
    grid radius covered, the gap is unknown and the survey's picks are sampled first."""
    from pipeline.engine.covers import first_sample
    from pipeline.engine.tasks import TileSurvey

    radii = radius_grid(np.array([1.0, 2.0, 4.0]))
    covers = np.where(radii >= 2.0, 50, -1)
    survey = TileSurvey(np.zeros(3), 10_000, 10_000, 0.0, 0.0, np.empty(0), 100, np.zeros(3), covers, np.empty(0))
    assert first_sample(survey, radii, 1.0) == int(np.ceil(1.25 * 150 * 4))  # gap 2: 4x the picks, and a quarter
    unknown = TileSurvey(np.zeros(3), 10_000, 10_000, 0.0, 0.0, np.empty(0), 100, np.zeros(3), np.full(len(radii), -1),
                         np.empty(0))
    assert first_sample(unknown, radii, 1.0) == 150
    xyz = plane_with_strays(5)
    radius = np.array([0.7])
    assert cover_counts(xyz, 1_500, radius, finest=0.7)[0] == cover_counts(xyz, 50, radius, finest=0.7)[0]

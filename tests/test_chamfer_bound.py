"""The Chamfer bound on the hole radius (model.chamfer_bound): its estimate, the survey measures it is
estimated from, and a tile on its own."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from model.baselines import fps_simplify
from model.chamfer_bound import (COVERED_SQUARE, bounded_radius, estimated_chamfer, mean_clipped_square,
                                 mean_square_distance)
from model.cover import counts_within, cover_counts, cover_order, sampled_cover
from model.geometry import DISTANCE_QUANTILES
from model.methods import Learned
from model.rules import kept_count
from model.selection import Tile
from pipeline.engine.tasks import (FloorJob, ReferenceJob, exact_floor, reference_square, survey_fill,
                                   surveyed_picks)
from tiling.budgets import feasible_radius, last_over, least_covers, one_radius_counts, radius_grid


def test_a_covered_point_counts_its_share_of_the_radius_and_a_near_one_its_own_distance():
    gaps = np.linspace(0.0, 2.0, 65)[None, :]  # distances spread evenly over [0, 2]
    assert mean_clipped_square(gaps, 3.0)[0] == pytest.approx(4 / 3, rel=1e-3)  # E[d^2], d uniform on [0, 2]
    # half the points within 1 (E[d^2] = 1/3 there), half beyond it, covered at COVERED_SQUARE
    assert mean_clipped_square(gaps, 1.0)[0] == pytest.approx(0.5 / 3 + 0.5 * COVERED_SQUARE, rel=2e-2)


def test_a_tile_given_a_quarter_of_its_share_counts_twice_its_distances():
    gaps = np.array([np.full(65, 0.1), np.full(65, 0.1)])
    even = estimated_chamfer(gaps, np.ones(2), np.array([1.0, 3.0]), 10.0)
    stretched = estimated_chamfer(gaps, np.array([2.0, 1.0]), np.array([1.0, 3.0]), 10.0)
    assert even == pytest.approx(0.01) and stretched == pytest.approx((0.04 + 3 * 0.01) / 4)


def test_the_radius_is_kept_where_the_bound_holds_and_narrowed_to_where_it_just_holds():
    def estimate(radius: float) -> float:
        return radius ** 2
    assert bounded_radius(estimate, 4.0, widest=1.5, finest=0.1) == 1.5  # the default's radius, untouched
    assert bounded_radius(estimate, 4.0, widest=3.0, finest=0.1) == pytest.approx(2.0, rel=1e-6)
    assert bounded_radius(estimate, 4.0, widest=3.0, finest=2.5) == 2.5  # never below the finest


def test_a_survey_measures_its_fills_gaps_and_keeps_its_sample_and_farthest_point_picks():
    """A 20k-point tile with a sparse half: the quantiles are those of the sample's distances to the trial
    fill, and the survey keeps the sample and as many farthest point picks, in their order, for the run's
    reference."""
    rng = np.random.default_rng(2)
    xyz = np.concatenate([rng.uniform([0, 0, 0], [4, 4, 0.01], size=(18_000, 3)),
                          rng.uniform([4, 0, 0], [8, 4, 0.01], size=(2_000, 3))])
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    budget = kept_count(0.1, len(xyz))
    sizes = 0.05 * 2.0 ** np.arange(5)
    survey = survey_fill(tile, xyz, budget, sizes, Learned())
    sample = xyz[::len(xyz) // 4096]
    even = cover_order(xyz, surveyed_picks(budget, len(xyz)))
    assert len(even) == int(np.ceil(1.5 * budget)) and np.array_equal(survey.even_xyz, xyz[even])
    assert np.array_equal(survey.sample_xyz, sample)
    assert np.all(np.diff(survey.even_radii) <= 0)  # the radius the picks before each leave covered
    assert np.array_equal(counts_within(survey.even_radii, radius_grid(sizes), complete=False), survey.covers)
    assert len(survey.gaps) == len(DISTANCE_QUANTILES) and np.all(np.diff(survey.gaps) >= 0)
    assert survey.gaps[-1] > 2 * survey.gaps[32]  # the sparse half's far points
    assert len(survey.covers) == len(radius_grid(sizes))


def test_a_tile_on_its_own_keeps_the_bound_from_its_own_trial_fill():
    """The floor-and-bump scene as one tile (a mesh's vertices and the API take this path): the default
    narrows its radius from its own trial fill and as many farthest point picks, as a run does from its
    survey: Chamfer over one FPS of the tile 1.51x with a bound of 100 (the radius unbounded), 1.19x with
    the default's 1.3, the bumpy part still keeping nearly twice its share (a quarter)."""
    rng = np.random.default_rng(5)
    xy = rng.uniform([0, 0], [16, 4], size=(64_000, 2))
    bumpy = xy[:, 0] >= 12
    z = np.where(bumpy, 0.4 * np.sin(6 * xy[:, 0]) * np.cos(6 * xy[:, 1]), 0.0) + 0.002 * rng.normal(size=len(xy))
    xyz = np.column_stack([xy, z]) - [8.0, 2.0, 0.0]
    tile = Tile(xyz, np.ones(len(xyz), dtype=bool), np.zeros(3), seed=0)
    even_chamfer = np.mean(cKDTree(xyz[fps_simplify(tile, 6_400).indices]).query(xyz)[0] ** 2)
    chamfers = {}
    for bound in (1.3, 100.0):
        kept = Learned(chamfer_bound=bound)(tile, 6_400).indices
        assert len(kept) == 6_400 and bumpy[kept].mean() > 0.4
        chamfers[bound] = np.mean(cKDTree(xyz[kept]).query(xyz)[0] ** 2) / even_chamfer
    assert chamfers[1.3] <= 1.3 < 1.4 < chamfers[100.0], chamfers


def test_the_least_covers_read_a_short_survey_as_one_more_than_its_picks_and_fit_the_target_from_some_radius():
    """A survey samples some picks, so a count it knows is at most their number: -1 means more."""
    covers = np.array([[-1, -1, 28, 10], [-1, 24, 20, 5]])  # (tiles, radii), shares 30 and 25
    least = least_covers(covers, sampled=np.array([30, 25]), counts=np.array([30, 200]))
    assert least.tolist() == [[30, 30, 28, 10], [26, 24, 20, 5]]  # at most the tile's points
    radii = np.array([0.5, 1.0, 2.0, 4.0])
    assert [feasible_radius(least, radii, target) for target in (60, 54, 48, 10)] == [0.5, 1.0, 2.0, np.inf]


def test_one_radius_counts_are_read_between_the_grid_radii_where_the_total_crosses_the_target():
    """Totals 400, 200, 100 at three radii: a target of 200 is the middle column; 141 lies halfway (in log)
    between it and the last, so each tile's count is the geometric mean of its two; off the grid, the end
    column."""
    least = np.array([[300, 150, 50], [100, 50, 50]])
    assert [last_over(least, target) for target in (500, 300, 150, 99)] == [-1, 0, 1, 2]
    assert one_radius_counts(least, 200).tolist() == [150.0, 50.0]
    assert one_radius_counts(least, 141) == pytest.approx([np.sqrt(150 * 50), 50.0], rel=2e-2)
    assert one_radius_counts(least, 1_000).tolist() == [300.0, 100.0]
    assert one_radius_counts(least, 50).tolist() == [50.0, 50.0]


def test_one_covering_radius_stands_for_one_farthest_point_sampling_where_the_tiles_shares_do_not():
    """A dense plane and, beside it, a tile of scattered points through a volume (stray returns): each tile's
    farthest point sampling at its share of the count gives a mean squared distance 3.8x one sampling of both
    (the strays' 400 picks leave them far apart); each run to the one radius at which their counts add up to
    the count, 1.04x."""
    rng = np.random.default_rng(1)
    plane = np.column_stack([rng.uniform(0, 4, 40_000), rng.uniform(0, 4, 40_000), 0.01 * rng.normal(size=40_000)])
    strays = np.column_stack([rng.uniform(4, 16, 4_000), rng.uniform(0, 4, 4_000), rng.uniform(0, 4, 4_000)])
    tiles, points, target = [plane, strays], np.array([40_000, 4_000]), 4_400
    scan = np.concatenate(tiles)
    untiled = mean_square_distance(scan, scan[cover_order(scan, target)])
    shares, radii = points // 10, 0.01 * 2.0 ** (np.arange(160) / 16)
    covers = np.array([cover_counts(xyz, share, radii, finest=radii[0]) for xyz, share in zip(tiles, shares)])
    picks = np.rint(one_radius_counts(least_covers(covers, shares, points), target)).astype(int)

    def pooled(counts: np.ndarray) -> float:
        return sum(size * mean_square_distance(xyz, xyz[cover_order(xyz, count)])
                   for size, xyz, count in zip(points, tiles, counts)) / points.sum()
    assert picks.sum() == pytest.approx(target, rel=0.02) and picks[1] > 5 * shares[1]
    assert pooled(shares) > 3 * untiled and pooled(picks) == pytest.approx(untiled, rel=0.06)


def test_a_tiles_kept_picks_give_its_exact_floor_and_its_reference_at_any_count(tmp_path):
    """From the file a survey (or a cover count) keeps: the fewest first picks that bring every core point
    within a radius (checked by brute force), and the sample's mean squared distance to any number of first
    picks; more picks than were kept is an error, not a quiet clip."""
    rng = np.random.default_rng(4)
    core = np.column_stack([rng.uniform(0, 10, 8_000), rng.uniform(0, 10, 8_000), 0.01 * rng.normal(size=8_000)])
    picks, shrinking = sampled_cover(core, 800)
    sample = core[::2]
    path = tmp_path / "survey-0.npz"
    np.savez(path, even_xyz=core[picks], even_radii=shrinking, sample_xyz=sample)
    radius = 1.01 * float(shrinking[500])
    floor = exact_floor(FloorJob(str(path), radius, len(core)))
    assert cKDTree(core[picks[:floor]]).query(core)[0].max() <= radius
    assert cKDTree(core[picks[:floor - 1]]).query(core)[0].max() > radius
    squares = cKDTree(core[picks[:300]]).query(sample)[0] ** 2
    assert reference_square(ReferenceJob(str(path), 300)) == pytest.approx(squares.mean())
    with pytest.raises(ValueError, match="900 picks asked of the 800 kept"):
        reference_square(ReferenceJob(str(path), 900))

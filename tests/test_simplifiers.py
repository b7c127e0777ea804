"""What the classic simplifiers promise beyond the contract every method meets (tests/test_conformance.py):
nested prefixes for fps and random, a seed that changes the picks, fps spreading better than random and
keeping every far cluster of a tiny tile, and voxel's one point per voxel."""
import numpy as np
import pytest

from model import Tile, get_simplifier

CLASSIC = ("fps", "voxel", "random", "stratified")  # keep source positions; the learned method has its own tests


def make_tile(n: int = 20_000, seed: int = 5) -> Tile:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 40, size=(n, 3)) * [1, 1, 0.1]
    core = (xyz[:, 0] > 3) & (xyz[:, 0] < 37)
    centre = np.array([500_000.0, 4_000_000.0, 100.0])
    return Tile(xyz - xyz.mean(0), core, centre, seed=11)


@pytest.mark.parametrize("method", CLASSIC)
def test_another_seed_gives_other_picks(method):
    tile = make_tile()
    first = get_simplifier(method)(tile, 1_500)
    other = get_simplifier(method)(Tile(tile.xyz, tile.core, tile.centre, seed=12), 1_500)
    assert not np.array_equal(first.indices, other.indices)


@pytest.mark.parametrize("method", ["fps", "random"])
def test_prefix_is_the_coarser_result(method):
    tile = make_tile()
    fine = get_simplifier(method)(tile, 3_000)
    coarse = get_simplifier(method)(tile, 300)
    np.testing.assert_array_equal(fine.indices[:300], coarse.indices)


def test_fps_spreads_points_better_than_random():
    from scipy.spatial import cKDTree

    tile = make_tile()
    x = tile.xyz[:, 0] - tile.xyz[:, 0].min()
    interior = tile.xyz[(x > 6) & (x < 34)]  # away from the halo, whose share of FPS picks is dropped
    gaps = {}
    for method in ("fps", "random"):
        kept = get_simplifier(method)(tile, 500).xyz
        gaps[method] = cKDTree(kept).query(interior)[0].max()  # covering radius
    assert gaps["fps"] < 0.6 * gaps["random"]


@pytest.mark.parametrize("centre", [np.zeros(3), np.array([500_000.0, 4_000_000.0, 100.0])])
def test_fps_keeps_one_point_of_each_far_cluster_on_a_tiny_tile(centre):
    """Three tight pairs of points 10 m apart: three fps picks are one of each pair, whatever the seed and
    wherever the tile lies (which points, not only how many: no cluster vanishes while another keeps two)."""
    xyz = np.array([[0, 0, 0], [0.01, 0, 0], [10, 0, 0], [10, 0.01, 0], [0, 10, 0], [0, 10, 0.01]])
    for seed in range(5):
        tile = Tile(xyz - xyz.mean(axis=0), np.ones(len(xyz), dtype=bool), centre, seed)
        assert sorted(get_simplifier("fps")(tile, 3).indices // 2) == [0, 1, 2]


def test_voxel_keeps_one_point_per_voxel_nearest_its_centre():
    tile = make_tile()
    selection = get_simplifier("voxel")(tile, 800)
    from model.baselines import VOXEL_COUNT_SLACK, _cell_for_budget, axis_columns

    points = tile.xyz[tile.core] + tile.centre
    cell = _cell_for_budget(axis_columns(points), (points.min(axis=0), points.max(axis=0)), 800, VOXEL_COUNT_SLACK)
    kept = selection.xyz + tile.centre
    kept_voxels = np.floor(kept / cell)
    assert len(np.unique(kept_voxels, axis=0)) == 800
    # each kept point is the one nearest its voxel's centre among the core points of that voxel
    voxels = np.floor(points / cell)
    for point, voxel in zip(kept[:50], kept_voxels[:50]):
        members = points[(voxels == voxel).all(axis=1)]
        centre = (voxel + 0.5) * cell
        assert np.linalg.norm(point - centre) <= np.linalg.norm(members - centre, axis=1).min() + 1e-12


def test_voxel_representative_is_the_nearest_and_of_equally_near_ones_the_first():
    """Per voxel, in key order, the point nearest its centre; a tie goes to the earlier point (what a
    stable lexsort by key and distance gave)."""
    from model.baselines import _voxel_representatives, axis_columns

    points = np.array([[1.7, 0.5, 0.5], [0.75, 0.5, 0.5], [0.25, 0.5, 0.5], [1.45, 0.5, 0.5], [0.5, 0.5, 0.9]])
    bounds = (points.min(axis=0), points.max(axis=0))
    assert _voxel_representatives(axis_columns(points), bounds, 1.0).tolist() == [1, 3]
    assert _voxel_representatives(axis_columns(points[:0]), bounds, 1.0).tolist() == []


def test_voxel_representatives_of_many_tied_points_are_the_lowest_index_nearest_ones():
    """The key sort is numpy's unstable one: over thousands of points, most of them exact duplicates scattered
    through the array (so the sort reorders ties), each voxel still gives the lowest index among its points
    nearest the centre, as a brute-force pass over the voxels finds."""
    from model.baselines import _voxel_representatives, axis_columns

    rng = np.random.default_rng(3)
    distinct = rng.uniform(0, 6, size=(300, 3))
    points = distinct[rng.integers(0, len(distinct), 20_000)]
    bounds = (points.min(axis=0), points.max(axis=0))
    cell = 1.0
    voxels = np.floor(points / cell)
    near = ((points - (voxels + 0.5) * cell) ** 2).sum(axis=1)
    expected = {}
    for index, voxel in enumerate(map(tuple, voxels)):
        best = expected.get(voxel)
        if best is None or near[index] < near[best]:
            expected[voxel] = index
    got = _voxel_representatives(axis_columns(points), bounds, cell)
    assert sorted(got.tolist()) == sorted(expected.values())


def test_voxel_tops_up_when_points_are_duplicates():
    xyz = np.repeat(np.random.default_rng(0).uniform(0, 1, size=(50, 3)), 4, axis=0)
    tile = Tile(xyz, np.ones(len(xyz), bool), np.zeros(3), seed=1)
    selection = get_simplifier("voxel")(tile, 120)
    assert len(np.unique(selection.indices)) == 120


@pytest.mark.parametrize("start_over_survey", [None, 1.0, 0.1, 10.0, 1e-9, 1e9])
def test_voxel_cell_search_meets_the_budget_from_any_start(start_over_survey):
    """From a run survey's estimate (the tile's occupied voxels at doubling edges), from far either side of
    it, or with no start, the cell found gives the budget's voxels, at most the slack more."""
    from model.baselines import VOXEL_COUNT_SLACK, _cell_for_budget, axis_columns
    from model.selection import VoxelCounts
    from tiling.budgets import occupied_voxels

    tile = make_tile()
    points = tile.xyz[tile.core] + tile.centre
    sizes = 0.5 * 2.0 ** np.arange(-4, 5)
    survey = VoxelCounts(sizes, occupied_voxels(points, sizes))
    start = None if start_over_survey is None else survey.edge_for(800) * start_over_survey
    cell = _cell_for_budget(axis_columns(points), (points.min(axis=0), points.max(axis=0)), 800, VOXEL_COUNT_SLACK,
                            start)
    assert 800 <= len(np.unique(np.floor(points / cell), axis=0)) <= 800 * (1 + VOXEL_COUNT_SLACK)


@pytest.mark.parametrize("share", [0.97, 0.99, 1.0])
def test_voxel_cell_search_near_every_point_takes_few_counts(share, monkeypatch):
    """A budget near the tile's point count, where the count hardly moves with the cell (a scan's exact
    duplicates: no cell gives every point its own voxel): the search from the survey's start ends in a few
    counts (it once crawled 1 % a count: 600 counts, 0.3 s a bcts tile)."""
    import model.baselines as baselines
    from model.selection import VoxelCounts
    from tiling.budgets import occupied_voxels

    distinct = make_tile().xyz + [0.0, 0.0, 50.0]
    points = np.concatenate([distinct, distinct[: len(distinct) // 20]])  # 5 % exact duplicates
    budget = round(share * len(points))
    sizes = np.sqrt(40 * 40 / budget) * 2.0 ** np.arange(-4, 5)
    counted = []
    monkeypatch.setattr(baselines, "distinct_count", lambda keys: counted.append(1) or len(np.unique(keys)))
    cell = baselines._cell_for_budget(baselines.axis_columns(points), (points.min(axis=0), points.max(axis=0)), budget,
                                      baselines.VOXEL_COUNT_SLACK,
                                      VoxelCounts(sizes, occupied_voxels(points, sizes)).edge_for(budget))
    assert len(counted) <= 30
    assert len(np.unique(np.floor((points - points.min(axis=0)) / cell), axis=0)) == len(distinct)  # all it can


def test_voxel_with_a_survey_keeps_one_point_per_voxel_and_tops_up_duplicates():
    from dataclasses import replace

    from model.baselines import VOXEL_COUNT_SLACK, _cell_for_budget, axis_columns
    from model.selection import VoxelCounts
    from tiling.budgets import occupied_voxels

    tile = make_tile()
    points = tile.xyz[tile.core] + tile.centre
    sizes = 0.5 * 2.0 ** np.arange(-4, 5)
    survey = VoxelCounts(sizes, occupied_voxels(points, sizes))
    kept = get_simplifier("voxel")(replace(tile, voxels=survey), 800).xyz + tile.centre
    cell = _cell_for_budget(axis_columns(points), (points.min(axis=0), points.max(axis=0)), 800, VOXEL_COUNT_SLACK,
                            survey.edge_for(800))
    assert len(np.unique(np.floor(kept / cell), axis=0)) == 800
    xyz = np.repeat(np.random.default_rng(0).uniform(0, 1, size=(50, 3)), 4, axis=0)
    twins = Tile(xyz, np.ones(len(xyz), bool), np.zeros(3), seed=1,
                 voxels=VoxelCounts(sizes / 50, occupied_voxels(xyz, sizes / 50)))
    assert len(np.unique(get_simplifier("voxel")(twins, 120).indices)) == 120

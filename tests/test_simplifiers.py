"""The simplifier interface: exact budgets of core points, priority order, determinism by seed."""
import numpy as np
import pytest

from model import Tile, get_simplifier
from model.registry import CORE_ONLY

CLASSIC = ("fps", "voxel", "random", "stratified")  # keep source positions; the learned method has its own tests


def make_tile(n: int = 20_000, seed: int = 5) -> Tile:
    rng = np.random.default_rng(seed)
    xyz = rng.uniform(0, 40, size=(n, 3)) * [1, 1, 0.1]
    core = (xyz[:, 0] > 3) & (xyz[:, 0] < 37)
    centre = np.array([500_000.0, 4_000_000.0, 100.0])
    return Tile(xyz - xyz.mean(0), core, centre, seed=11)


@pytest.mark.parametrize("method", CLASSIC)
def test_exact_budget_of_unique_core_points(method):
    tile = make_tile()
    for budget in (1, 37, 2_000, tile.core_count):
        selection = get_simplifier(method)(tile, budget)
        assert len(selection.indices) == budget
        assert len(np.unique(selection.indices)) == budget
        assert tile.core[selection.indices].all()
        np.testing.assert_array_equal(selection.xyz, tile.xyz[selection.indices])


@pytest.mark.parametrize("method", CLASSIC)
def test_deterministic_for_a_seed(method):
    tile = make_tile()
    first = get_simplifier(method)(tile, 1_500)
    again = get_simplifier(method)(tile, 1_500)
    np.testing.assert_array_equal(first.indices, again.indices)
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


def test_voxel_keeps_one_point_per_voxel_nearest_its_centre():
    tile = make_tile()
    selection = get_simplifier("voxel")(tile, 800)
    from model.baselines import _cell_for_budget

    points = tile.xyz[tile.core] + tile.centre
    cell = _cell_for_budget(points, 800)
    kept = selection.xyz + tile.centre
    kept_voxels = np.floor(kept / cell)
    assert len(np.unique(kept_voxels, axis=0)) == 800
    # each kept point is the one nearest its voxel's centre among the core points of that voxel
    voxels = np.floor(points / cell)
    for point, voxel in zip(kept[:50], kept_voxels[:50]):
        members = points[(voxels == voxel).all(axis=1)]
        centre = (voxel + 0.5) * cell
        assert np.linalg.norm(point - centre) <= np.linalg.norm(members - centre, axis=1).min() + 1e-12


def test_voxel_tops_up_when_points_are_duplicates():
    xyz = np.repeat(np.random.default_rng(0).uniform(0, 1, size=(50, 3)), 4, axis=0)
    tile = Tile(xyz, np.ones(len(xyz), bool), np.zeros(3), seed=1)
    selection = get_simplifier("voxel")(tile, 120)
    assert len(np.unique(selection.indices)) == 120


@pytest.mark.parametrize("method", CLASSIC + ("tcp", "stratified-detail", "learned", "paper", "paper-refined"))
@pytest.mark.parametrize("n", [1, 2, 3, 7, 9])
def test_tiny_tiles(method, n):
    xyz = np.random.default_rng(n).uniform(size=(n, 3))
    tile = Tile(xyz, np.ones(n, bool), np.zeros(3), seed=2)
    assert len(get_simplifier(method)(tile, n).indices) == n
    assert len(get_simplifier(method)(tile, 1).indices) == 1


@pytest.mark.parametrize("method", CLASSIC)
def test_exact_duplicates_are_each_kept_once(method):
    """Every point twice, or one point repeated: the budget is met by distinct source points, all core."""
    base = make_tile(2_000)
    doubled = Tile(np.concatenate([base.xyz, base.xyz]), np.concatenate([base.core, base.core]), base.centre, 3)
    same = Tile(np.zeros((500, 3)), np.ones(500, dtype=bool), base.centre, 3)
    for tile in (doubled, same):
        for budget in (tile.core_count // 10, tile.core_count * 3 // 4, tile.core_count):
            indices = get_simplifier(method)(tile, budget).indices
            assert len(np.unique(indices)) == budget and tile.core[indices].all()


@pytest.mark.parametrize("method", CORE_ONLY)
def test_core_only_methods_pick_the_same_points_without_the_halo(method):
    """A run loads only the core of a CORE_ONLY method's tiles: the picks must be those made with the halo."""
    tile = make_tile()
    core = np.flatnonzero(tile.core)
    alone = Tile(tile.xyz[core], np.ones(len(core), dtype=bool), tile.centre, tile.seed)
    np.testing.assert_array_equal(core[get_simplifier(method)(alone, 1_500).indices],
                                  get_simplifier(method)(tile, 1_500).indices)

